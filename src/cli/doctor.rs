//! `cadence doctor`: checks this host for hard timing (`cadence::host_check`) and, with `--unit`,
//! prints the systemd unit that runs the IO stage as a service (sysconfig::systemd).

use std::path::PathBuf;

use cadence::host_check::{run_checks, DoctorOptions, HostFacts, Status};
use clap::Args;
use sysconfig::systemd::{unit, UnitSpec};

#[derive(Debug, Args)]
pub struct DoctorArgs {
    /// SCHED_FIFO priority to try (the [realtime] default for the IO threads is 60).
    #[arg(long, default_value_t = 60)]
    pub fifo_priority: i32,
    /// Wake-up latency samples (1 ms sleeps); 0 skips the measurement.
    #[arg(long, default_value_t = 2000)]
    pub samples: usize,
    /// Print a systemd unit for the IO stage instead of checking the host.
    #[arg(long)]
    pub unit: bool,
    /// printer.cfg the service loads (with --unit; made absolute).
    #[arg(long, requires = "unit")]
    pub config: Option<PathBuf>,
    /// Service instance name prints attach to (with --unit).
    #[arg(long, default_value = "printer", requires = "unit")]
    pub instance: String,
    /// User the service runs as (with --unit; default: $USER).
    #[arg(long, requires = "unit")]
    pub user: Option<String>,
    /// CPUs the service may use, comma-separated (with --unit; default: all).
    #[arg(long, value_delimiter = ',', requires = "unit")]
    pub cpus: Vec<usize>,
}

pub fn run(args: &DoctorArgs) -> Result<(), String> {
    if args.unit {
        print!("{}", unit(&unit_spec(args)?));
        return Ok(());
    }
    let is_root = cadence::host_check::running_as_root();
    let checks = run_checks(
        &HostFacts::read(),
        &DoctorOptions {
            fifo_priority: args.fifo_priority,
            wakeup_samples: args.samples,
            is_root,
        },
    );
    for c in &checks {
        println!("{c}");
    }
    let worst = checks.iter().map(|c| c.status).max().unwrap_or(Status::Ok);
    match worst {
        Status::Fail => Err("some real-time guarantees are off on this host (see FAIL above)".into()),
        Status::Warn => {
            println!("Cadence runs here; the warnings above weaken its timing guarantees.");
            Ok(())
        }
        Status::Ok => {
            println!("This host is fit for hard timing.");
            Ok(())
        }
    }
}

fn unit_spec(args: &DoctorArgs) -> Result<UnitSpec, String> {
    let exe = std::env::current_exe().map_err(|e| format!("cannot find the cadence executable: {e}"))?;
    let config = match &args.config {
        Some(p) => std::fs::canonicalize(p).map_err(|e| format!("{}: {e}", p.display()))?,
        None => return Err("--unit needs --config printer.cfg (the file the service loads)".into()),
    };
    let user = args
        .user
        .clone()
        .or_else(|| std::env::var("USER").ok())
        .unwrap_or_else(|| "root".into());
    Ok(UnitSpec {
        exe,
        config,
        instance: args.instance.clone(),
        user,
        cpus: args.cpus.clone(),
    })
}

//! End to end: TMC drivers on the simulated printer (examples/simulated-sensorless.cfg with
//! 20 mm axes). Two TMC2209s share one UART line (addresses 0 and 1) and home X and Y
//! sensorlessly (`tmc2209_stepper_x:virtual_endstop`, `driver_SGTHRS: 100`), a TMC2130 on
//! software SPI drives Z (homed on its switch), a TMC2208 the extruder.
//!
//! The simulated MCU's drivers (firmware `sim::tmc`) keep the registers the host writes over
//! `tmcuart_send` / `spi_send` + `spi_transfer`, answer reads with CRC-checked replies, and
//! raise DIAG only while the carriage is at its end of travel *and* the registers route a stall
//! to the pin (SGTHRS > 0, TCOOLTHRS > 0, stealthChop): the host's sensorless set-up around
//! homing is what makes the axis stop, and `DUMP_TMC` shows what the driver holds.

use std::path::{Path, PathBuf};
use std::sync::{Mutex, PoisonError};
use std::time::Duration;

use cadence_tests::{
    assert_success, home_traced, net_steps, retry_homing_timeouts, run, scratch, short_homing_config_text,
    Run,
};
use firmware::trace::read_trace;

const TIMEOUT: Duration = Duration::from_secs(180);
/// The multi-MCU stop budget (µs).
const BUDGET_US: f64 = 25_000.0;
/// X and Y steps per mm.
const STEPS_PER_MM: f64 = 80.0;

/// One printer at a time: homing's timeouts are real-time ones.
static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

fn config(dir: &Path, edit: impl Fn(String) -> String) -> PathBuf {
    let path = dir.join("printer.cfg");
    std::fs::write(&path, edit(short_homing_config_text("simulated-sensorless.cfg"))).expect("write config");
    path
}

/// `cadence print` of the G-code `g` on `cfg`, one printer at a time, run again after a homing
/// timeout (a loaded VM).
fn print(g: &Path, cfg: &Path) -> Run {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(PoisonError::into_inner);
    retry_homing_timeouts(
        || {
            let mut cmd = std::process::Command::new(cadence_tests::bin("cadence"));
            cmd.arg("print")
                .arg(g)
                .arg("--config")
                .arg(cfg)
                .arg("--no-progress");
            run(&mut cmd, TIMEOUT)
        },
        |r| r,
    )
}

/// The stop bounds (µs after the trigger) of every pass of the `homing AXIS:` line.
fn stop_bounds(out: &str, axis: char) -> Vec<(f64, f64)> {
    let key = format!("homing {axis}:");
    let line = out.lines().find(|l| l.contains(&key)).unwrap_or_default();
    cadence_tests::stop_bounds(line)
}

fn home(dir: &Path, cfg: &Path, axes: &str) -> (Run, PathBuf) {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(PoisonError::into_inner);
    let trace = dir.join("home.trace");
    let r = retry_homing_timeouts(|| run(&mut home_traced(axes, cfg, &trace), TIMEOUT), |r| r);
    (r, trace)
}

#[test]
fn sensorless_homing_stops_x_and_y_at_their_end_of_travel_within_the_budget() {
    let dir = scratch("tmc-sensorless");
    let cfg = config(&dir, |t| t);
    let (r, trace) = home(&dir, &cfg, "xy");
    assert_success(&r);
    let out = format!("{}{}", r.stdout, r.stderr);
    for axis in ['x', 'y'] {
        let bounds = stop_bounds(&out, axis);
        assert_eq!(bounds.len(), 1, "one pass (homing_retract_dist 0): {out}");
        for (first, last) in bounds {
            assert!(
                last <= BUDGET_US && first <= last,
                "{axis}: stop {first}..{last} µs: {out}"
            );
        }
        println!(
            "{}",
            out.lines()
                .find(|l| l.contains(&format!("homing {axis}:")))
                .unwrap_or_default()
        );
    }
    assert!(out.contains("homed position: x=0.000000 y=0.000000"), "{out}");
    // The step trace: X and Y (oids 0, 1) started 2 mm from their ends (10% of 20 mm) and the
    // host says they stopped at 0: the MCU's net steps agree within the overshoot the host
    // accounted for (a step).
    let trace = read_trace(&trace).expect("trace");
    let net = net_steps(&trace);
    for oid in [0u8, 1] {
        let moved = net.get(&oid).copied().unwrap_or(0) as f64 / STEPS_PER_MM;
        assert!(
            (moved + 2.0).abs() <= 2.0 / STEPS_PER_MM,
            "oid {oid} moved {moved} mm"
        );
    }
    for line in out
        .lines()
        .filter(|l| l.contains("host view") || l.contains("overshoot:"))
    {
        println!("{line}");
    }
}

#[test]
fn without_stall_reporting_the_axis_never_triggers() {
    let dir = scratch("tmc-no-stall");
    let cfg = config(&dir, |t| t.replacen("driver_SGTHRS: 100", "driver_SGTHRS: 0", 1));
    let (r, _) = home(&dir, &cfg, "x");
    assert_eq!(r.code, Some(1), "{}{}", r.stdout, r.stderr);
    assert!(
        r.stderr.contains("No trigger on x after full movement"),
        "{}",
        r.stderr
    );
}

#[test]
fn dump_tmc_reads_back_what_was_written_and_set_tmc_current_changes_the_driver() {
    let dir = scratch("tmc-commands");
    let cfg = config(&dir, |t| t);
    let g = dir.join("tmc.gcode");
    std::fs::write(
        &g,
        "G28\nDUMP_TMC STEPPER=stepper_x\nSET_TMC_CURRENT STEPPER=stepper_x CURRENT=0.6 HOLDCURRENT=0.3\n\
         DUMP_TMC STEPPER=stepper_x REGISTER=IHOLD_IRUN\nDUMP_TMC STEPPER=stepper_x REGISTER=DRV_STATUS\n\
         SET_TMC_FIELD STEPPER=stepper_z FIELD=sgt VALUE=-5\nDUMP_TMC STEPPER=stepper_z REGISTER=CHOPCONF\n\
         DUMP_TMC STEPPER=stepper_z REGISTER=COOLCONF\nINIT_TMC STEPPER=extruder\nDUMP_TMC STEPPER=extruder REGISTER=IFCNT\n\
         G1 X10 Y10 F3000\n",
    )
    .expect("gcode");
    let r = print(&g, &cfg);
    assert_success(&r);
    let out = &r.stdout;
    let has = |s: &str| assert!(out.lines().any(|l| l.trim() == s), "no line '{s}' in:\n{out}");
    // Written at start, read back from the simulated driver: pdn_disable, mstep_reg_select,
    // multistep_filt, stealthChop (en_spreadcycle 0); toff 3, hstrt 5, tbl 2, vsense, 16
    // microsteps, interpolation.
    has("========== Write-only registers ==========");
    has("SGTHRS:     00000064 sgthrs=100");
    has("IHOLD_IRUN: 0008190f ihold=15 irun=25 iholddelay=8");
    has("========== Queried registers ==========");
    has("GCONF:      000001c0 pdn_disable=1 mstep_reg_select=1 multistep_filt=1");
    has("CHOPCONF:   14030053 toff=3 hstrt=5 tbl=2 vsense=1 mres=4(16usteps) intpol=1");
    // 10 registers at start, 3 switched for homing and 3 restored: every write counted (a write
    // the host had to repeat, its confirmation lost on a loaded VM, counts twice).
    let ifcnt = |l: &str| -> Option<u32> {
        l.trim()
            .strip_prefix("IFCNT:")?
            .split("ifcnt=")
            .nth(1)?
            .parse()
            .ok()
    };
    let counts: Vec<u32> = out.lines().filter_map(ifcnt).collect();
    assert!(counts.len() == 2 && counts[0] >= 16, "{counts:?}\n{out}");
    // The sensorless settings were restored after homing.
    has("TCOOLTHRS:  00000000");
    // 0.6 A / 0.3 A through 0.11 Ω: IRUN 19, IHOLD 9; the driver's current scale follows.
    has("Run Current: 0.61A Hold Current: 0.31A");
    has("IHOLD_IRUN: 00081309 ihold=9 irun=19 iholddelay=8");
    has("DRV_STATUS: 00130000 cs_actual=19");
    // The TMC2130 over SPI: its CHOPCONF read back, the field written.
    has("CHOPCONF:   14028384 toff=4 hend=7 tbl=1 vsense=1 mres=4(16usteps) intpol=1");
    has("COOLCONF:   007b0000 sgt=-5");
    // The TMC2208 rewritten by INIT_TMC: its 6 registers twice.
    assert!(counts[1] >= 12, "{counts:?}");
}

/// A Duet's TMC UART analog mux (`select_pins`): X and Y both at address 0 on one line, told
/// apart by the select outputs the host sets before each transfer; each driver keeps its own
/// current (without the mux both would take every write), and both still home sensorlessly.
#[test]
fn drivers_behind_an_analog_mux_are_reached_one_at_a_time() {
    let dir = scratch("tmc-mux");
    let cfg = config(&dir, |t| {
        t.replace(
            "uart_pin: PE6\nuart_address: 0\nrun_current: 0.8\n",
            "uart_pin: PE6\nselect_pins: !PC14, PC15\nrun_current: 0.8\n",
        )
        .replace(
            "uart_pin: PE6\nuart_address: 1\nrun_current: 0.8\n",
            "uart_pin: PE6\nselect_pins: PC14, !PC15\nrun_current: 0.5\n",
        )
    });
    let text = std::fs::read_to_string(&cfg).expect("config");
    assert_eq!(
        text.matches("select_pins").count(),
        2,
        "the example's UART sections changed"
    );
    let g = dir.join("mux.gcode");
    std::fs::write(
        &g,
        "G28 X Y\nDUMP_TMC STEPPER=stepper_x REGISTER=IHOLD_IRUN\nDUMP_TMC STEPPER=stepper_y REGISTER=IHOLD_IRUN\n",
    )
    .expect("gcode");
    let r = print(&g, &cfg);
    assert_success(&r);
    let out = &r.stdout;
    let irun: Vec<&str> = out
        .lines()
        .filter_map(|l| l.trim().strip_prefix("IHOLD_IRUN:"))
        .collect();
    // 0.8 A and 0.5 A through 0.11 Ω: IRUN 25 and 15.
    assert_eq!(irun.len(), 2, "{out}");
    assert!(
        irun[0].contains("irun=25") && irun[1].contains("irun=15"),
        "{irun:?}"
    );
}

/// A TMC SPI daisy chain (`chain_length`, `chain_position`): Z and the extruder as TMC2130s on
/// one chip select, each datagram placed for its driver in the chain's frame; a field written to
/// one driver stays in that driver (a frame placed or read at the wrong place would show it in
/// the other, or fail the write's check).
#[test]
fn drivers_on_an_spi_daisy_chain_keep_their_own_registers() {
    let dir = scratch("tmc-chain");
    let cfg = config(&dir, |t| {
        t.replace(
            "cs_pin: PE9\n",
            "cs_pin: PE9\nchain_length: 2\nchain_position: 1\n",
        )
        .replace(
            "[tmc2208 extruder]\nuart_pin: PE13\nrun_current: 0.5\n",
            "[tmc2130 extruder]\ncs_pin: PE9\nchain_length: 2\nchain_position: 2\n\
             spi_software_sclk_pin: PE10\nspi_software_mosi_pin: PE11\nspi_software_miso_pin: PE12\n\
             run_current: 0.3\n",
        )
    });
    let text = std::fs::read_to_string(&cfg).expect("config");
    assert_eq!(
        text.matches("chain_position").count(),
        2,
        "the example's TMC sections changed"
    );
    let g = dir.join("chain.gcode");
    std::fs::write(
        &g,
        "DUMP_TMC STEPPER=stepper_z REGISTER=CHOPCONF\nDUMP_TMC STEPPER=extruder REGISTER=CHOPCONF\n\
         SET_TMC_FIELD STEPPER=extruder FIELD=toff VALUE=5\n\
         DUMP_TMC STEPPER=stepper_z REGISTER=CHOPCONF\nDUMP_TMC STEPPER=extruder REGISTER=CHOPCONF\n",
    )
    .expect("gcode");
    let mut cmd = std::process::Command::new(cadence_tests::bin("cadence"));
    cmd.arg("print")
        .arg(&g)
        .arg("--config")
        .arg(&cfg)
        .arg("--no-progress");
    let r = run(&mut cmd, TIMEOUT);
    assert_success(&r);
    let out = &r.stdout;
    let chop: Vec<&str> = out
        .lines()
        .filter_map(|l| l.trim().strip_prefix("CHOPCONF:"))
        .collect();
    assert_eq!(chop.len(), 4, "{out}");
    // Read back from each driver: Z's configured toff 4, the extruder's own, then 5 on the
    // extruder only.
    assert!(
        chop[0].contains("toff=4") && chop[1].contains("toff=4"),
        "{chop:?}"
    );
    assert!(
        chop[2].contains("toff=4") && chop[3].contains("toff=5"),
        "{chop:?}"
    );
}

/// X on a TMC2240 (SPI, `rref`, DIAG0 open drain) homed sensorlessly with stallGuard4
/// (`driver_SG4_THRS`, stealthChop): the host turns the stall routing on around the homing; its
/// current bits are the datasheet's for `rref`, and `DUMP_TMC` reads them back.
#[test]
fn a_tmc2240_homes_x_sensorlessly_and_reads_back_its_current() {
    let dir = scratch("tmc2240");
    let cfg = config(&dir, |t| {
        t.replace(
            "tmc2209_stepper_x:virtual_endstop",
            "tmc2240_stepper_x:virtual_endstop",
        )
        .replace(
            "[tmc2209 stepper_x]\nuart_pin: PE6\nuart_address: 0\nrun_current: 0.8\nhold_current: 0.5\n\
             stealthchop_threshold: 999999\ndiag_pin: ^PE7\ndriver_SGTHRS: 100\n",
            "[tmc2240 stepper_x]\ncs_pin: PE14\nspi_software_sclk_pin: PE10\nspi_software_mosi_pin: PE11\n\
             spi_software_miso_pin: PE12\nrref: 12000\nrun_current: 0.8\nhold_current: 0.5\n\
             stealthchop_threshold: 999999\ndiag0_pin: ^!PE7\ndriver_SG4_THRS: 20\n",
        )
    });
    let text = std::fs::read_to_string(&cfg).expect("config");
    assert!(
        text.contains("[tmc2240 stepper_x]"),
        "the example's X driver changed"
    );
    let (r, _) = home(&dir, &cfg, "x");
    assert_success(&r);
    let out = format!("{}{}", r.stdout, r.stderr);
    assert!(out.contains("homed position: x=0.000000"), "{out}");
    let bounds = stop_bounds(&out, 'x');
    assert!(
        bounds
            .iter()
            .all(|&(first, last)| first <= last && last <= BUDGET_US),
        "{out}"
    );
    let g = dir.join("dump.gcode");
    std::fs::write(
        &g,
        "DUMP_TMC STEPPER=stepper_x REGISTER=GLOBALSCALER\nDUMP_TMC STEPPER=stepper_x REGISTER=IHOLD_IRUN\n\
         DUMP_TMC STEPPER=stepper_x REGISTER=DRV_CONF\n",
    )
    .expect("gcode");
    let r = print(&g, &cfg);
    assert_success(&r);
    // rref 12 kΩ, range 0 (0.69 A RMS full scale)… 0.8 A needs range 1: Ifs = 24000 / 12000 /
    // √2 = 1.414 A; G = ⌊0.8 · 256 / 1.414 + ½⌋ = 145; IRUN = 31, IHOLD = ⌊0.5 · 8192 /
    // (145 · 1.414) − ½⌋ = 19.
    let out = &r.stdout;
    assert!(out.contains("globalscaler=145"), "{out}");
    assert!(out.contains("irun=31") && out.contains("ihold=19"), "{out}");
    assert!(out.contains("current_range=1"), "{out}");
}

/// The printer of this file with Z on a TMC2660 (1.0 A through 0.051 Ω, idle at 20 %).
fn tmc2660_config(dir: &Path) -> PathBuf {
    config(dir, |t| {
        t.replace(
            "[tmc2130 stepper_z]\ncs_pin: PE9\n",
            "[tmc2660 stepper_z]\ncs_pin: PE9\nsense_resistor: 0.051\nidle_current_percent: 20\n",
        )
        .replace(
            "run_current: 0.6\ninterpolate: True\n",
            "run_current: 1.0\ninterpolate: True\n",
        )
    })
}

/// Z on a TMC2660 (20-bit datagrams, SPI mode 0, one current in SGCSCONF's CS with `vsense`):
/// its settings are written at start, `DUMP_TMC` shows them as written and reads the status
/// answers (DRVCONF's `rdsel` chosen first), whose coolStep current `se` is the CS written;
/// SET_TMC_CURRENT changes it.
#[test]
fn a_tmc2660_is_configured_and_answers_its_status() {
    let dir = scratch("tmc2660");
    let cfg = tmc2660_config(&dir);
    let text = std::fs::read_to_string(&cfg).expect("config");
    assert!(
        text.contains("[tmc2660 stepper_z]") && text.contains("run_current: 1.0"),
        "{text}"
    );
    let g = dir.join("dump.gcode");
    std::fs::write(
        &g,
        "DUMP_TMC STEPPER=stepper_z\nSET_TMC_CURRENT STEPPER=stepper_z CURRENT=0.5\n\
         DUMP_TMC STEPPER=stepper_z REGISTER=READRSP@RDSEL2\n",
    )
    .expect("gcode");
    let r = print(&g, &cfg);
    assert_success(&r);
    let out = &r.stdout;
    // 1.0 A through 0.051 Ω: CS = ⌊32 · 0.051 · 1.0 · √2 / 0.165 + ½⌋ − 1 = 13 with vsense.
    assert!(out.contains("cs=13"), "{out}");
    assert!(out.contains("vsense=1"), "{out}");
    let se: Vec<&str> = out.lines().filter(|l| l.contains("READRSP@RDSEL2:")).collect();
    assert_eq!(se.len(), 2, "{out}");
    assert!(se[0].contains("se=13"), "{se:?}");
    // 0.5 A: CS 6.
    assert!(se[1].contains("se=6"), "{se:?}");
}

/// `DUMP_TMC STEPPER=stepper_z REGISTER=READRSP@RDSEL2` on a live session: the coolStep current
/// `se` the simulated TMC2660 answers with, which is the CS it holds.
fn tmc2660_se(printer: &cadence::Printer, events: &std::sync::mpsc::Receiver<cadence::Event>) -> i64 {
    while events.try_recv().is_ok() {}
    printer
        .run_command("DUMP_TMC STEPPER=stepper_z REGISTER=READRSP@RDSEL2")
        .expect("DUMP_TMC");
    let deadline = std::time::Instant::now() + Duration::from_secs(30);
    while std::time::Instant::now() < deadline {
        if let Ok(cadence::Event::Response(line)) = events.recv_timeout(Duration::from_millis(200)) {
            let se = line.split_once("READRSP@RDSEL2:").and_then(|(_, r)| {
                r.split_whitespace()
                    .find_map(|w| w.strip_prefix("se=")?.parse().ok())
            });
            if let Some(se) = se {
                return se;
            }
        }
    }
    panic!("no READRSP@RDSEL2 answer");
}

/// Z on a TMC2660 with `idle_current_percent: 20` on a live session: once the printer is
/// quiet and its steppers have been still 0.5 s, the driver holds 20 % of its run current
/// (1.0 A: CS 13; 0.2 A: CS 2), motion gets the run current back before its first step, and
/// the next quiet spell lowers it again. The driver's CS is read back through its status.
#[test]
fn a_tmc2660_runs_at_its_idle_current_while_the_printer_is_idle() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(PoisonError::into_inner);
    let dir = scratch("tmc2660-idle");
    let cfg = tmc2660_config(&dir);
    let opts = cadence::PrinterOptions {
        log_to_stderr: true,
        ..cadence::PrinterOptions::default()
    };
    let mut printer = cadence::Printer::open(cadence::PrinterSource::ConfigFile(cfg), opts).expect("open");
    let events = printer.events().expect("events");
    // Quiet from the start: the idle current comes once nothing moved for 0.5 s (polled; each
    // DUMP_TMC is a command without motion, which does not end the idle spell).
    let wait_idle = |what: &str| {
        let deadline = std::time::Instant::now() + Duration::from_secs(60);
        loop {
            let se = tmc2660_se(&printer, &events);
            if se == 2 {
                return;
            }
            assert!(se == 13, "{what}: CS {se}");
            assert!(
                std::time::Instant::now() < deadline,
                "{what}: never at the idle current"
            );
            std::thread::sleep(Duration::from_millis(300));
        }
    };
    wait_idle("at start");
    // Motion: homing and a move run at the run current; DUMP_TMC comes right after the move
    // (in the same stream, no quiet spell between).
    printer
        .run_gcode_stream(
            "moves.gcode",
            std::io::Cursor::new("G28 Z\nG1 Z5 F600\nDUMP_TMC STEPPER=stepper_z REGISTER=READRSP@RDSEL2\n"),
        )
        .expect("moves");
    let mut after_move = None;
    while let Ok(e) = events.recv_timeout(Duration::from_secs(5)) {
        if let cadence::Event::Response(line) = e {
            if let Some((_, r)) = line.split_once("READRSP@RDSEL2:") {
                after_move = r
                    .split_whitespace()
                    .find_map(|w| w.strip_prefix("se=")?.parse::<i64>().ok());
                break;
            }
        }
    }
    assert_eq!(after_move, Some(13), "run current after the move");
    // Quiet again: back to the idle current.
    wait_idle("after the move");
    printer.close().expect("close");
}

//! `cadence check-config printer.cfg`: loads a config as a print would and lists every error
//! and warning found (file:line, section, option), the sections read, ignored and refused, and
//! checks each MCU's pins and objects against a data dictionary. Exit status 1 with errors.

use std::path::PathBuf;

use cadence::hardware::Machine;
use clap::Args;
use sysconfig::printer::check::{check, CheckedSection, SectionUse};

/// Arguments of `cadence check-config`.
#[derive(Debug, Args)]
pub struct CheckConfigArgs {
    /// The printer.cfg to check (includes are read relative to it).
    pub config: PathBuf,
    /// Data dictionary the MCUs' pins are checked against (default: the Cadence firmware's,
    /// which the simulator serves).
    #[arg(long)]
    pub dictionary: Option<PathBuf>,
}

pub fn run(args: &CheckConfigArgs) -> Result<(), String> {
    let report = check(&args.config);
    let mut errors: Vec<String> = report.errors.iter().map(|e| e.to_string()).collect();
    let mut warnings = report.warnings.clone();
    let mut notes = Vec::new();
    if let Some(cfg) = &report.config {
        match Machine::from_config(cfg) {
            Ok(machine) => {
                let dict = cadence::wire_check::load_dictionary(args.dictionary.as_deref())?;
                let which = args
                    .dictionary
                    .as_ref()
                    .map_or("the Cadence firmware's".to_string(), |p| p.display().to_string());
                for mcu in &cfg.mcus {
                    match cadence::mcus::config_commands(&dict, &machine, &mcu.name) {
                        Ok((cmds, _, _)) => notes.push(format!(
                            "mcu '{}': {} configuration commands encode with {which} dictionary",
                            mcu.name,
                            cmds.len()
                        )),
                        Err(e) => errors.push(format!("mcu '{}' ({which} dictionary): {e}", mcu.name)),
                    }
                }
            }
            Err(e) => errors.push(e.to_string()),
        }
        warnings.retain(|w| !w.is_empty());
    }
    let count = |u: fn(&SectionUse) -> bool| report.sections_of(u).count();
    println!(
        "{}: {} sections: {} read, {} ignored, {} refused, {} unknown",
        report.file.display(),
        report.sections.len(),
        count(|u| *u == SectionUse::Read),
        count(|u| *u == SectionUse::Ignored),
        count(|u| matches!(u, SectionUse::Refused(_))),
        count(|u| *u == SectionUse::Unknown),
    );
    let list = |title: &str, u: fn(&SectionUse) -> bool| {
        let names: Vec<String> = report.sections_of(u).map(section_ref).collect();
        if !names.is_empty() {
            println!("{title}:");
            for n in names {
                println!("  {n}");
            }
        }
    };
    list("read", |u| *u == SectionUse::Read);
    list("ignored (accepted, no effect in Cadence)", |u| {
        *u == SectionUse::Ignored
    });
    list("refused (not supported by Cadence yet)", |u| {
        matches!(u, SectionUse::Refused(_))
    });
    list("unknown (not a Klipper section)", |u| *u == SectionUse::Unknown);
    for n in &notes {
        println!("{n}");
    }
    for w in &warnings {
        println!("warning: {w}");
    }
    for e in &errors {
        println!("error: {e}");
    }
    if report.stopped_early {
        println!("(the check stopped at an error it cannot set aside: fix it and check again)");
    }
    println!("{} errors, {} warnings", errors.len(), warnings.len());
    if errors.is_empty() {
        Ok(())
    } else {
        Err(format!("{}: {} errors", report.file.display(), errors.len()))
    }
}

/// `[name] file:line`, with the missing feature for a refused section.
fn section_ref(s: &CheckedSection) -> String {
    match s.usage {
        SectionUse::Refused(what) => format!("[{}] {} ({what})", s.name, s.at),
        _ => format!("[{}] {}", s.name, s.at),
    }
}

//! Slicer output as slicers write it, printed without edits: start/end G-code in the styles of
//! PrusaSlicer, Cura, OrcaSlicer and SuperSlicer (`tests/slicers/*.gcode`: PRINT_START /
//! START_PRINT with parameters, M190/M109 waits, M73, M486 and EXCLUDE_OBJECT labels, G92 E0,
//! M201/M203/M204/M205/M900, T0, G10/G11, G2/G3 with G17) on a printer.cfg with the macros such
//! G-code calls (`tests/slicers/printer.cfg`). Each file is planned in batch mode with
//! `--strict` (any command the printer does not know fails it) and its wire stream proven
//! against the G-code with `decode --check`.

use std::time::Duration;

use cadence_tests::{cadence, scratch, workspace};

const TIMEOUT: Duration = Duration::from_secs(120);

#[test]
fn slicer_start_and_end_code_prints_without_edits() {
    let dir = scratch("dialect-slicers");
    let slicers = workspace().join("tests/slicers");
    let cfg = slicers.join("printer.cfg");
    let cfg_s = cfg.to_str().unwrap();
    for (file, said) in [
        ("prusaslicer.gcode", "Excluding object 1"),
        ("cura.gcode", "primed, printing at 200.0 / 60.0"),
        ("orcaslicer.gcode", "Excluding object CUBE_B"),
        ("superslicer.gcode", "primed, printing at 210.0 / 55.0"),
    ] {
        let g = slicers.join(file);
        let out = dir.join(file.replace(".gcode", ".bin"));
        let (g_s, out_s) = (g.to_str().unwrap(), out.to_str().unwrap());
        let run = cadence(
            &["print", g_s, "--config", cfg_s, "--batch", out_s, "--strict"],
            TIMEOUT,
        );
        assert_eq!(run.code, Some(0), "{file}: {}\n{}", run.stdout, run.stderr);
        let all = format!("{}{}", run.stdout, run.stderr);
        assert!(all.contains(said), "{file}: no {said:?} in {all}");
        assert!(!all.contains("Unknown command"), "{file}: {all}");
        let check = cadence(&["decode", out_s, "--check", g_s, "--config", cfg_s], TIMEOUT);
        assert_eq!(check.code, Some(0), "{file}: {}\n{}", check.stdout, check.stderr);
        assert_eq!(
            check.stdout.matches(": ok").count(),
            4,
            "{file}: {}",
            check.stdout
        );
    }
}

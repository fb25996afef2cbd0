//! `[gcode_macro]` end to end, in batch mode: a print that calls macros (parameters with
//! defaults, a nested macro reading the toolhead position, `SET_GCODE_VARIABLE`, a G28 override
//! through `rename_existing`) writes exactly the wire bytes of the same print with the macros
//! expanded by hand; a macro's error names the file, the calling line and the macro.

use std::path::Path;
use std::time::Duration;

use cadence_tests::{scratch, workspace};

const TIMEOUT: Duration = Duration::from_secs(120);

const MACROS: &str = "
[gcode_macro G28]
rename_existing: G28.1
gcode:
  G28.1 {rawparams}
  G1 Z5 F600

[gcode_macro START_PRINT]
variable_layers: 0
gcode:
  {% set speed = params.SPEED|default(3000)|int %}
  G28
  G1 X{params.X|default(10)} Y10 F{speed}
  SIDE DX=20
  SET_GCODE_VARIABLE MACRO=START_PRINT VARIABLE=layers VALUE=2

[gcode_macro NEXT]
gcode:
  SIDE DX={printer['gcode_macro START_PRINT'].layers * 5}

[gcode_macro SIDE]
gcode:
  G1 X{printer.toolhead.position.x + params.DX|float} E1
";

fn print_batch(dir: &Path, name: &str, gcode: &str, cfg: &Path) -> Result<Vec<u8>, String> {
    let g = dir.join(format!("{name}.gcode"));
    std::fs::write(&g, gcode).expect("write gcode");
    let out = dir.join(format!("{name}.bin"));
    let run = cadence_tests::print_batch(&g, cfg, &out, TIMEOUT);
    if run.code != Some(0) {
        return Err(run.stderr);
    }
    Ok(std::fs::read(&out).expect("read stream"))
}

#[test]
fn macros_write_the_bytes_of_their_expansion() {
    let dir = scratch("macros");
    let base = std::fs::read_to_string(workspace().join("examples/simulated-cartesian.cfg")).unwrap();
    let cfg = dir.join("printer.cfg");
    std::fs::write(&cfg, format!("{base}\n{MACROS}")).unwrap();
    let with_macros = print_batch(
        &dir,
        "macros",
        "M83\nSTART_PRINT X=15\nNEXT\nG1 X50 Y50 F6000\n",
        &cfg,
    )
    .unwrap();
    // By hand: G28 then Z5 (the override), X15 (the parameter), SIDE +20 from X15; then NEXT,
    // rendered after START_PRINT ran, sees the variable it set: SIDE +2*5 from X35. (A
    // template is rendered whole when called, as Klipper does: START_PRINT itself could not
    // see its own SET_GCODE_VARIABLE.)
    let by_hand = print_batch(
        &dir,
        "by_hand",
        "M83\nG28\nG1 Z5 F600\nG1 X15 Y10 F3000\nG1 X35 E1\nG1 X45 E1\nG1 X50 Y50 F6000\n",
        &cfg,
    )
    .unwrap();
    assert!(with_macros.len() > 100);
    assert!(
        with_macros == by_hand,
        "the macro print's stream differs from its hand expansion"
    );
}

#[test]
fn macro_errors_name_the_line_and_the_macro() {
    let dir = scratch("macro-errors");
    let base = std::fs::read_to_string(workspace().join("examples/simulated-cartesian.cfg")).unwrap();
    let cfg = dir.join("printer.cfg");
    let bad = "[gcode_macro CHECK]\ngcode:\n  {% if params.T|int < 100 %}{action_raise_error('too cold: ' ~ params.T)}{% endif %}\n  G4 P1\n[gcode_macro OUTER]\ngcode:\n  G28\n  CHECK T=50\n";
    std::fs::write(&cfg, format!("{base}\n{bad}")).unwrap();
    let err = print_batch(&dir, "raise", "G28\nCHECK T=150\nOUTER\n", &cfg).unwrap_err();
    assert!(
        err.contains("raise.gcode:3: in macro OUTER: too cold: 50"),
        "{err}"
    );
    let err = print_batch(
        &dir,
        "set",
        "SET_GCODE_VARIABLE MACRO=CHECK VARIABLE=x VALUE=1\n",
        &cfg,
    )
    .unwrap_err();
    assert!(
        err.contains("set.gcode:1: Unknown gcode_macro variable 'x'"),
        "{err}"
    );
}

//! `[gcode_macro NAME]` sections → the planner's [`MacroDef`]s: `gcode` (required, the Jinja
//! template, continuation lines kept), `description`, `rename_existing`, and any number of
//! `variable_NAME` literals. The name is upper-cased as Klipper does; the templates are
//! compiled at load ([`planner::gcode::macros::Macros`]), so a syntax error names its section
//! before anything moves; the G-code feed runs them.

use planner::gcode::macros::MacroDef;

use super::error::ConfigError;
use super::reader::Reader;

/// Every `[gcode_macro NAME]`, in file order.
pub(crate) fn read_gcode_macros(reader: &Reader<'_>) -> Result<Vec<MacroDef>, ConfigError> {
    let mut out = Vec::new();
    for s in reader.sections_with_arg("gcode_macro") {
        let name = s.arg().unwrap_or_default().to_uppercase();
        let gcode = s.string("gcode")?;
        let description = s.value("description").map(|v| v.text.clone());
        let rename_existing = s.value("rename_existing").map(|v| v.text.trim().to_uppercase());
        let variables = s
            .options_with_prefix("variable_")
            .into_iter()
            .map(|(var, v)| (var.to_lowercase(), v.text.clone()))
            .collect();
        out.push(MacroDef {
            name,
            gcode,
            description,
            rename_existing,
            variables,
            at: s.at().to_string(),
        });
    }
    Ok(out)
}

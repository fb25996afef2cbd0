//! The host-side G-code objects of Klipper that hold no motion: `[delayed_gcode]` timers
//! (`UPDATE_DELAYED_GCODE`), `[save_variables]` (`SAVE_VARIABLE`, the file's text),
//! `[idle_timeout]` (`SET_IDLE_TIMEOUT`, its state) and `[display_status]` (`M73`,
//! `SET_DISPLAY_TEXT`, `M117`), with the `printer` status objects templates see.
//!
//! Time is an argument: every timer counts in print time (seconds on the printer's timeline,
//! as the caller's feed advances it), so a print replays the same way every time. Klipper's
//! timers run on the host's clock while G-code is read up to a couple of seconds ahead of
//! motion; here a timer fires between two G-code lines once the print timeline passed its due
//! time.
//!
//! `[delayed_gcode]` (Klipper's `delayed_gcode.py` semantics): a timer starts at
//! `initial_duration` after the start (0: not armed); `UPDATE_DELAYED_GCODE ID= DURATION=`
//! re-arms it `DURATION` seconds from now (0 cancels); called from inside its own script it
//! makes the timer repeat after `DURATION` from when it fired.
//!
//! `[save_variables]`: the file is Python's `configparser` format Klipper writes: a
//! `[Variables]` section, one `name = repr(value)` line per variable in name order; values
//! are Python literals ([`parse_literal`], [`python_repr`]).

use std::collections::BTreeMap;
use std::path::PathBuf;

use minijinja::value::{Value, ValueKind};
use minijinja::Environment;

use super::macros::call_params;

/// The name a `[delayed_gcode ID]`'s script runs under as a macro: lower case, so no G-code
/// command (upper-cased by the parser) can call it.
pub fn delayed_macro_name(id: &str) -> String {
    format!("delayed_gcode {id}")
}

/// The name `[idle_timeout]`'s script runs under as a macro (lower case: see above).
pub const IDLE_TIMEOUT_MACRO: &str = "idle_timeout";

/// Klipper's `[idle_timeout] gcode` default.
pub const DEFAULT_IDLE_GCODE: &str = "TURN_OFF_HEATERS\nM84";

/// Klipper's `[idle_timeout] timeout` default (s).
pub const DEFAULT_IDLE_TIMEOUT: f64 = 600.0;

/// The commands [`HostObjects`] answers (with their sections; `SET_IDLE_TIMEOUT` always).
pub const HOST_COMMANDS: [&str; 5] = [
    "UPDATE_DELAYED_GCODE",
    "SAVE_VARIABLE",
    "SET_IDLE_TIMEOUT",
    "M73",
    "SET_DISPLAY_TEXT",
];

/// What the printer.cfg sections configure.
#[derive(Debug, Clone, PartialEq)]
pub struct HostConfig {
    /// `[delayed_gcode ID]`: the id and its `initial_duration` (s); its script is the macro
    /// [`delayed_macro_name`].
    pub delayed: Vec<(String, f64)>,
    /// `[idle_timeout] timeout` (s); its script is the macro [`IDLE_TIMEOUT_MACRO`].
    pub idle_timeout: f64,
    /// `[save_variables] filename` (`~` expanded).
    pub save_variables: Option<PathBuf>,
    /// Whether there is a `[display_status]`.
    pub display_status: bool,
    /// `[force_move] enable_force_move`: `SET_KINEMATIC_POSITION` is a command.
    pub enable_force_move: bool,
    /// `[bed_screws]`: `BED_SCREWS_ADJUST` and its answers.
    pub bed_screws: Option<super::bed_screws::BedScrewsConfig>,
}

impl Default for HostConfig {
    fn default() -> Self {
        HostConfig {
            delayed: Vec::new(),
            idle_timeout: DEFAULT_IDLE_TIMEOUT,
            save_variables: None,
            display_status: false,
            enable_force_move: false,
            bed_screws: None,
        }
    }
}

/// Why a host command was refused (Klipper's wording).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{0}")]
pub struct HostError(pub String);

/// What a host command asks of the caller besides its state change.
#[derive(Debug, Clone, PartialEq)]
pub enum HostAction {
    /// Nothing more.
    Done,
    /// A line to answer with (`idle_timeout: Timeout set to 30.00 s`).
    Respond(String),
    /// Write `text` to the `[save_variables]` file at `path` (the planner does no IO).
    Save { path: PathBuf, text: String },
}

#[derive(Debug, Clone)]
struct Timer {
    id: String,
    duration: f64,
    due: Option<f64>,
    repeat: bool,
}

/// `[idle_timeout]`'s state as Klipper names it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IdleState {
    /// Nothing has run since the start or since the timeout's script.
    Idle,
    /// G-code is running.
    Printing,
    /// The G-code source went quiet: the timeout counts.
    Ready,
}

impl IdleState {
    fn name(self) -> &'static str {
        match self {
            IdleState::Idle => "Idle",
            IdleState::Printing => "Printing",
            IdleState::Ready => "Ready",
        }
    }
}

/// The state of the host objects.
#[derive(Debug, Clone)]
pub struct HostObjects {
    timers: Vec<Timer>,
    /// The timer whose script is running.
    inside: Option<usize>,
    /// The print time the feed has reached.
    now: f64,
    idle_timeout: f64,
    idle_state: IdleState,
    /// When the G-code went quiet (print time), in [`IdleState::Ready`].
    ready_since: f64,
    printing_since: f64,
    saved: Option<(PathBuf, BTreeMap<String, Value>)>,
    display: Option<(Option<f64>, Option<String>)>,
    force_move: bool,
    bed_screws: Option<super::bed_screws::BedScrewsTool>,
}

impl Default for HostObjects {
    fn default() -> Self {
        HostObjects::new(&HostConfig::default(), 0.0)
    }
}

impl HostObjects {
    /// The objects of `cfg`, the print starting at print time `start` (when timers with an
    /// `initial_duration` are armed from).
    pub fn new(cfg: &HostConfig, start: f64) -> HostObjects {
        let timers = cfg
            .delayed
            .iter()
            .map(|(id, initial)| Timer {
                id: id.clone(),
                duration: *initial,
                due: (*initial > 0.0).then_some(start + initial),
                repeat: false,
            })
            .collect();
        HostObjects {
            timers,
            inside: None,
            now: start,
            idle_timeout: cfg.idle_timeout,
            idle_state: IdleState::Idle,
            ready_since: start,
            printing_since: start,
            saved: cfg.save_variables.clone().map(|p| (p, BTreeMap::new())),
            display: cfg.display_status.then_some((None, None)),
            force_move: cfg.enable_force_move,
            bed_screws: cfg.bed_screws.clone().map(super::bed_screws::BedScrewsTool::new),
        }
    }

    /// Loads the `[save_variables]` file's text (Klipper's "Unable to parse existing variable
    /// file" when a value is not a literal).
    pub fn load_variables(&mut self, text: &str) -> Result<(), HostError> {
        let Some((_, vars)) = self.saved.as_mut() else {
            return Ok(());
        };
        *vars = parse_variables_file(text)?;
        Ok(())
    }

    /// `SET_KINEMATIC_POSITION` is a command (`[force_move] enable_force_move: True`).
    pub fn force_move(&self) -> bool {
        self.force_move
    }

    /// `[bed_screws]`'s tool, when the printer has one (the feed runs its commands: see
    /// [`super::bed_screws`]).
    pub fn bed_screws_mut(&mut self) -> Option<&mut super::bed_screws::BedScrewsTool> {
        self.bed_screws.as_mut()
    }

    /// The `[save_variables]` file, when the printer has one.
    pub fn variables_file(&self) -> Option<&PathBuf> {
        self.saved.as_ref().map(|(p, _)| p)
    }

    /// True when `name` is a command these objects answer on this printer.
    pub fn handles(&self, name: &str) -> bool {
        match name {
            "UPDATE_DELAYED_GCODE" => !self.timers.is_empty(),
            "SAVE_VARIABLE" => self.saved.is_some(),
            "SET_IDLE_TIMEOUT" => true,
            "M73" | "SET_DISPLAY_TEXT" => self.display.is_some(),
            _ => false,
        }
    }

    /// The print time the feed has reached (timers count from it). Never goes back.
    pub fn set_now(&mut self, now: f64) {
        if now > self.now {
            self.now = now;
        }
    }

    /// The print time the feed has reached.
    pub fn now(&self) -> f64 {
        self.now
    }

    /// Notes a command the feed runs: G-code is printing (the idle timeout starts over), and
    /// `M117`'s text is the display's message.
    pub fn observe(&mut self, name: &str, raw: &str) {
        if self.idle_state != IdleState::Printing {
            self.idle_state = IdleState::Printing;
            self.printing_since = self.now;
        }
        if name == "M117" {
            if let Some((_, message)) = self.display.as_mut() {
                let text = raw.trim().get(4..).unwrap_or("").trim();
                *message = (!text.is_empty()).then(|| text.to_string());
            }
        }
    }

    /// The G-code source went quiet at print time `now` (a session between commands).
    pub fn quiet(&mut self, now: f64) {
        self.set_now(now);
        if self.idle_state == IdleState::Printing {
            self.idle_state = IdleState::Ready;
            self.ready_since = self.now;
        }
    }

    /// True (once) when the idle timeout elapsed: the caller runs [`IDLE_TIMEOUT_MACRO`],
    /// after which the state is `Idle`.
    pub fn idle_timeout_due(&mut self) -> bool {
        if self.idle_state == IdleState::Ready && self.now - self.ready_since >= self.idle_timeout {
            self.idle_state = IdleState::Idle;
            return true;
        }
        false
    }

    /// The earliest due timer at or before now: the caller runs its script
    /// ([`delayed_macro_name`]) between [`Self::timer_started`] and [`Self::timer_done`].
    pub fn due_timer(&self) -> Option<usize> {
        self.due_before(self.now)
    }

    /// The earliest timer due at or before `t`.
    pub fn due_before(&self, t: f64) -> Option<usize> {
        self.timers
            .iter()
            .enumerate()
            .filter_map(|(i, tm)| tm.due.filter(|&d| d <= t).map(|d| (i, d)))
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .map(|(i, _)| i)
    }

    /// The id of timer `i`.
    pub fn timer_id(&self, i: usize) -> &str {
        self.timers.get(i).map_or("", |t| t.id.as_str())
    }

    /// Timers still armed (id, due print time), for a print that ends before they fire.
    pub fn pending_timers(&self) -> Vec<(String, f64)> {
        self.timers
            .iter()
            .filter_map(|t| t.due.map(|d| (t.id.clone(), d)))
            .collect()
    }

    /// Timer `i` fires: its script runs now. The print time it fired at is returned.
    pub fn timer_started(&mut self, i: usize) -> f64 {
        self.inside = Some(i);
        let fired = self.timers.get(i).and_then(|t| t.due).unwrap_or(self.now);
        if let Some(t) = self.timers.get_mut(i) {
            t.due = None;
            t.repeat = false;
        }
        fired
    }

    /// Timer `i`'s script ended; `fired` is what [`Self::timer_started`] returned. A repeat
    /// asked from inside the script arms it `duration` after `fired`.
    pub fn timer_done(&mut self, i: usize, fired: f64) {
        self.inside = None;
        if let Some(t) = self.timers.get_mut(i) {
            if t.repeat {
                t.due = Some(fired + t.duration);
            }
            t.repeat = false;
        }
    }

    /// Runs one of [`HOST_COMMANDS`] (see [`Self::handles`]) with its parameters.
    pub fn command(&mut self, name: &str, rawparams: &str) -> Result<HostAction, HostError> {
        let params = call_params(name, rawparams);
        let float = |key: &str| -> Result<Option<f64>, HostError> {
            match params.get(key) {
                None => Ok(None),
                Some(v) => match v.trim().parse::<f64>() {
                    Ok(x) if x.is_finite() => Ok(Some(x)),
                    _ => Err(HostError(format!(
                        "Error on '{name} {rawparams}': unable to parse '{v}' as a float"
                    ))),
                },
            }
        };
        match name {
            "UPDATE_DELAYED_GCODE" => {
                let id = params
                    .get("ID")
                    .ok_or_else(|| HostError(format!("Error on '{name} {rawparams}': missing ID")))?;
                let Some(i) = self.timers.iter().position(|t| &t.id == id) else {
                    return Err(HostError(format!("The value '{id}' is not valid for ID")));
                };
                let duration = float("DURATION")?
                    .ok_or_else(|| HostError(format!("Error on '{name} {rawparams}': missing DURATION")))?;
                if duration < 0.0 {
                    return Err(HostError(format!(
                        "Error on '{name} {rawparams}': parameter 'DURATION' must be at least 0"
                    )));
                }
                let now = self.now;
                let inside = self.inside == Some(i);
                if let Some(t) = self.timers.get_mut(i) {
                    t.duration = duration;
                    if inside {
                        t.repeat = duration != 0.0;
                    } else {
                        t.due = (duration > 0.0).then_some(now + duration);
                    }
                }
                Ok(HostAction::Done)
            }
            "SET_IDLE_TIMEOUT" => {
                let timeout = float("TIMEOUT")?.unwrap_or(self.idle_timeout);
                if timeout <= 0.0 {
                    return Err(HostError(format!(
                        "Error on '{name} {rawparams}': parameter 'TIMEOUT' must be above 0"
                    )));
                }
                self.idle_timeout = timeout;
                if self.idle_state == IdleState::Ready {
                    self.ready_since = self.now;
                }
                Ok(HostAction::Respond(format!(
                    "idle_timeout: Timeout set to {timeout:.2} s"
                )))
            }
            "M73" => {
                if let (Some(p), Some((progress, _))) = (float("P")?, self.display.as_mut()) {
                    *progress = Some((p / 100.0).clamp(0.0, 1.0));
                }
                Ok(HostAction::Done)
            }
            "SET_DISPLAY_TEXT" => {
                if let Some((_, message)) = self.display.as_mut() {
                    *message = params.get("MSG").cloned();
                }
                Ok(HostAction::Done)
            }
            "SAVE_VARIABLE" => self.save_variable(name, rawparams, &params),
            _ => Err(HostError(format!("Unknown command:\"{name}\""))),
        }
    }

    fn save_variable(
        &mut self,
        name: &str,
        rawparams: &str,
        params: &BTreeMap<String, String>,
    ) -> Result<HostAction, HostError> {
        let Some((path, vars)) = self.saved.as_mut() else {
            return Err(HostError(format!("Unknown command:\"{name}\"")));
        };
        let missing = |k: &str| HostError(format!("Error on '{name} {rawparams}': missing {k}"));
        let var = params.get("VARIABLE").ok_or_else(|| missing("VARIABLE"))?;
        if var.to_lowercase() != *var {
            return Err(HostError("VARIABLE must not contain upper case".to_string()));
        }
        let text = params.get("VALUE").ok_or_else(|| missing("VALUE"))?;
        let value =
            parse_literal(text).map_err(|_| HostError(format!("Unable to parse '{text}' as a literal")))?;
        vars.insert(var.clone(), value);
        Ok(HostAction::Save {
            path: path.clone(),
            text: variables_file_text(vars),
        })
    }

    /// The `printer` status objects: `idle_timeout`, and with their sections
    /// `save_variables`, `bed_screws` and `display_status` (`progress` falls back to
    /// `file_progress`).
    pub fn status(&self, file_progress: Option<f64>) -> BTreeMap<String, Value> {
        let mut out = BTreeMap::new();
        let printing_time = match self.idle_state {
            IdleState::Printing => self.now - self.printing_since,
            _ => 0.0,
        };
        out.insert(
            "idle_timeout".to_string(),
            Value::from_iter([
                ("state", Value::from(self.idle_state.name())),
                ("printing_time", Value::from(printing_time)),
                ("idle_timeout", Value::from(self.idle_timeout)),
            ]),
        );
        if let Some((_, vars)) = &self.saved {
            out.insert(
                "save_variables".to_string(),
                Value::from_iter([("variables", Value::from(vars.clone()))]),
            );
        }
        if let Some(tool) = &self.bed_screws {
            let (active, stage, current, accepted) = tool.status();
            out.insert(
                "bed_screws".to_string(),
                Value::from_iter([
                    ("is_active", Value::from(active)),
                    ("state", stage.map_or(Value::from(()), Value::from)),
                    ("current_screw", Value::from(current)),
                    ("accepted_screws", Value::from(accepted)),
                ]),
            );
        }
        if let Some((progress, message)) = &self.display {
            let progress = progress.or(file_progress).unwrap_or(0.0);
            out.insert(
                "display_status".to_string(),
                Value::from_iter([
                    ("progress", Value::from(progress)),
                    ("message", message.clone().map_or(Value::from(()), Value::from)),
                ]),
            );
        }
        out
    }
}

/// A Python literal (`10`, `1.5`, `'text'`, `"text"`, `[1, 2]`, `{'a': 1}`, `True`, `None`),
/// as Klipper's `ast.literal_eval` takes `SAVE_VARIABLE VALUE=` and the variables file.
pub fn parse_literal(text: &str) -> Result<Value, String> {
    let mut env = Environment::new();
    // A name is no literal (`not x` would otherwise read as `not undefined`, i.e. true).
    env.set_undefined_behavior(minijinja::UndefinedBehavior::Strict);
    let expr = env.compile_expression(text.trim()).map_err(|e| e.to_string())?;
    let value = expr.eval(()).map_err(|e| e.to_string())?;
    if value.is_undefined() {
        return Err("names are not literals".to_string());
    }
    Ok(value)
}

/// `value` as Python's `repr` writes it (what Klipper stores in the variables file).
pub fn python_repr(value: &Value) -> String {
    match value.kind() {
        ValueKind::Undefined | ValueKind::None => "None".to_string(),
        ValueKind::Bool => if value.is_true() { "True" } else { "False" }.to_string(),
        ValueKind::Number => match (i64::try_from(value.clone()), f64::try_from(value.clone())) {
            (Ok(i), _) if value.is_integer() => i.to_string(),
            (_, Ok(f)) if f.is_finite() => {
                let s = format!("{f:?}");
                // Python writes 1e+20 where Rust writes 1e20.
                match s.split_once('e') {
                    Some((m, e)) if !e.starts_with('-') => format!("{m}e+{e}"),
                    _ => s,
                }
            }
            (_, Ok(f)) if f.is_nan() => "nan".to_string(),
            (_, Ok(f)) if f > 0.0 => "inf".to_string(),
            (_, Ok(_)) => "-inf".to_string(),
            _ => value.to_string(),
        },
        ValueKind::String => python_str(value.as_str().unwrap_or("")),
        ValueKind::Seq => {
            let items: Vec<String> = value
                .try_iter()
                .map(|it| it.map(|v| python_repr(&v)).collect())
                .unwrap_or_default();
            format!("[{}]", items.join(", "))
        }
        ValueKind::Map => {
            let items: Vec<String> = value
                .try_iter()
                .map(|it| {
                    it.map(|k| {
                        let v = value.get_item(&k).unwrap_or_default();
                        format!("{}: {}", python_repr(&k), python_repr(&v))
                    })
                    .collect()
                })
                .unwrap_or_default();
            format!("{{{}}}", items.join(", "))
        }
        _ => python_str(&value.to_string()),
    }
}

/// A string as Python's `repr` quotes it: single quotes unless the text has a single quote
/// and no double quote.
fn python_str(s: &str) -> String {
    let quote = if s.contains('\'') && !s.contains('"') {
        '"'
    } else {
        '\''
    };
    let mut out = String::with_capacity(s.len() + 2);
    out.push(quote);
    for c in s.chars() {
        match c {
            '\\' => out.push_str("\\\\"),
            '\n' => out.push_str("\\n"),
            '\r' => out.push_str("\\r"),
            '\t' => out.push_str("\\t"),
            c if c == quote => {
                out.push('\\');
                out.push(c);
            }
            c if (c as u32) < 0x20 || c as u32 == 0x7f => out.push_str(&format!("\\x{:02x}", c as u32)),
            c => out.push(c),
        }
    }
    out.push(quote);
    out
}

/// The variables file's text: `[Variables]`, then `name = repr` in name order, then a blank
/// line (as `configparser` writes it).
pub fn variables_file_text(vars: &BTreeMap<String, Value>) -> String {
    let mut out = String::from("[Variables]\n");
    for (k, v) in vars {
        out.push_str(&format!("{k} = {}\n", python_repr(v)));
    }
    out.push('\n');
    out
}

/// Reads a variables file: the `[Variables]` section's `name = literal` (or `name: literal`)
/// lines; other sections, blank lines and `#`/`;` comments are skipped, and a value may go on
/// over indented continuation lines, as `configparser` reads them.
pub fn parse_variables_file(text: &str) -> Result<BTreeMap<String, Value>, HostError> {
    let bad = |line: usize, why: String| {
        HostError(format!(
            "Unable to parse existing variable file (line {line}: {why})"
        ))
    };
    let mut vars = BTreeMap::new();
    let mut in_variables = false;
    let mut current: Option<(usize, String, String)> = None;
    let finish =
        |cur: Option<(usize, String, String)>, vars: &mut BTreeMap<String, Value>| -> Result<(), HostError> {
            if let Some((line, k, v)) = cur {
                let value = parse_literal(&v).map_err(|e| bad(line, format!("{k} = {v}: {e}")))?;
                vars.insert(k, value);
            }
            Ok(())
        };
    for (n, raw) in text.lines().enumerate() {
        let line_no = n + 1;
        let trimmed = raw.trim();
        if raw.starts_with([' ', '\t']) && !trimmed.is_empty() {
            if let Some((_, _, v)) = current.as_mut() {
                v.push('\n');
                v.push_str(trimmed);
                continue;
            }
        }
        finish(current.take(), &mut vars)?;
        if trimmed.is_empty() || trimmed.starts_with(['#', ';']) {
            continue;
        }
        if let Some(section) = trimmed.strip_prefix('[').and_then(|s| s.strip_suffix(']')) {
            in_variables = section == "Variables";
            continue;
        }
        let Some(sep) = trimmed.find(['=', ':']) else {
            return Err(bad(line_no, format!("'{trimmed}' is not 'name = value'")));
        };
        if in_variables {
            let key = trimmed[..sep].trim().to_lowercase();
            let value = trimmed[sep + 1..].trim().to_string();
            current = Some((line_no, key, value));
        }
    }
    finish(current.take(), &mut vars)?;
    Ok(vars)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn cfg() -> HostConfig {
        HostConfig {
            delayed: vec![("blink".into(), 2.0), ("later".into(), 0.0)],
            idle_timeout: 30.0,
            save_variables: Some(PathBuf::from("/tmp/vars.cfg")),
            display_status: true,
            enable_force_move: false,
            bed_screws: None,
        }
    }

    #[test]
    fn delayed_gcode_arms_fires_repeats_and_cancels() {
        let mut h = HostObjects::new(&cfg(), 10.0);
        assert_eq!(h.due_timer(), None);
        h.set_now(12.0);
        let i = h.due_timer().unwrap();
        assert_eq!(h.timer_id(i), "blink");
        let fired = h.timer_started(i);
        assert_eq!(fired, 12.0);
        // Inside its own script: a repeat after DURATION from when it fired.
        h.command("UPDATE_DELAYED_GCODE", "ID=blink DURATION=1.5")
            .unwrap();
        h.timer_done(i, fired);
        assert_eq!(h.pending_timers(), [("blink".to_string(), 13.5)]);
        // From outside: DURATION from now; 0 cancels.
        h.command("UPDATE_DELAYED_GCODE", "ID=later DURATION=5").unwrap();
        assert_eq!(
            h.due_before(17.0).map(|i| h.timer_id(i).to_string()),
            Some("blink".into())
        );
        h.command("UPDATE_DELAYED_GCODE", "ID=blink DURATION=0").unwrap();
        assert_eq!(h.pending_timers(), [("later".to_string(), 17.0)]);
        // Fired without a repeat: disarmed.
        h.set_now(20.0);
        let i = h.due_timer().unwrap();
        let f = h.timer_started(i);
        h.timer_done(i, f);
        assert!(h.pending_timers().is_empty());
        let e = h
            .command("UPDATE_DELAYED_GCODE", "ID=nope DURATION=1")
            .unwrap_err();
        assert_eq!(e.0, "The value 'nope' is not valid for ID");
        assert!(h.command("UPDATE_DELAYED_GCODE", "ID=blink").is_err());
        assert!(h.command("UPDATE_DELAYED_GCODE", "ID=blink DURATION=-1").is_err());
    }

    #[test]
    fn idle_timeout_counts_from_quiet_and_reports() {
        let mut h = HostObjects::new(&cfg(), 0.0);
        h.observe("G1", "G1 X1");
        assert_eq!(
            h.status(None)["idle_timeout"].get_attr("state").unwrap().as_str(),
            Some("Printing")
        );
        h.quiet(5.0);
        h.set_now(34.0);
        assert!(!h.idle_timeout_due());
        h.set_now(35.0);
        assert!(h.idle_timeout_due());
        assert!(!h.idle_timeout_due());
        assert_eq!(
            h.status(None)["idle_timeout"].get_attr("state").unwrap().as_str(),
            Some("Idle")
        );
        assert_eq!(
            h.command("SET_IDLE_TIMEOUT", "TIMEOUT=12").unwrap(),
            HostAction::Respond("idle_timeout: Timeout set to 12.00 s".into())
        );
        assert!(h.command("SET_IDLE_TIMEOUT", "TIMEOUT=0").is_err());
    }

    #[test]
    fn display_status_m73_and_messages() {
        let mut h = HostObjects::new(&cfg(), 0.0);
        let ds = |h: &HostObjects| h.status(Some(0.25))["display_status"].clone();
        assert_eq!(f64::try_from(ds(&h).get_attr("progress").unwrap()).unwrap(), 0.25);
        h.command("M73", "P42 R10").unwrap();
        h.observe("M117", "M117 Layer 3");
        assert_eq!(f64::try_from(ds(&h).get_attr("progress").unwrap()).unwrap(), 0.42);
        assert_eq!(ds(&h).get_attr("message").unwrap().as_str(), Some("Layer 3"));
        h.command("SET_DISPLAY_TEXT", "MSG=\"hello there\"").unwrap();
        assert_eq!(ds(&h).get_attr("message").unwrap().as_str(), Some("hello there"));
        h.command("SET_DISPLAY_TEXT", "").unwrap();
        assert!(ds(&h).get_attr("message").unwrap().is_none());
        let plain = HostObjects::new(&HostConfig::default(), 0.0);
        assert!(
            !plain.handles("M73") && !plain.handles("SAVE_VARIABLE") && plain.handles("SET_IDLE_TIMEOUT")
        );
        assert!(!plain.status(None).contains_key("display_status"));
    }

    #[test]
    fn save_variable_writes_klipper_file_and_reads_it_back() {
        let mut h = HostObjects::new(&cfg(), 0.0);
        h.load_variables("[Variables]\nz_offset = 0.125\nname = 'pla'\n\n")
            .unwrap();
        let HostAction::Save { path, text } = h.command("SAVE_VARIABLE", "VARIABLE=count VALUE=3").unwrap()
        else {
            panic!("no save");
        };
        assert_eq!(path, PathBuf::from("/tmp/vars.cfg"));
        assert_eq!(text, "[Variables]\ncount = 3\nname = 'pla'\nz_offset = 0.125\n\n");
        let HostAction::Save { text, .. } = h
            .command(
                "SAVE_VARIABLE",
                "VARIABLE=pts VALUE=\"[1, 2.5, 'a', True, None, {'k': 'v'}]\"",
            )
            .unwrap()
        else {
            panic!("no save");
        };
        assert!(
            text.contains("pts = [1, 2.5, 'a', True, None, {'k': 'v'}]\n"),
            "{text}"
        );
        assert_eq!(parse_variables_file(&text).unwrap().len(), 4);
        let vars = h.status(None)["save_variables"].get_attr("variables").unwrap();
        assert_eq!(i64::try_from(vars.get_attr("count").unwrap()).unwrap(), 3);
        assert_eq!(
            h.command("SAVE_VARIABLE", "VARIABLE=Count VALUE=1")
                .unwrap_err()
                .0,
            "VARIABLE must not contain upper case"
        );
        assert_eq!(
            h.command("SAVE_VARIABLE", "VARIABLE=c VALUE=bare").unwrap_err().0,
            "Unable to parse 'bare' as a literal"
        );
        assert!(h.load_variables("[Variables]\nx = not literal\n").is_err());
    }

    #[test]
    fn repr_of_numbers_and_strings() {
        let r = |t: &str| python_repr(&parse_literal(t).unwrap());
        assert_eq!(r("1.0"), "1.0");
        assert_eq!(r("-7"), "-7");
        assert_eq!(r("1e20"), "1e+20");
        assert_eq!(r("\"a\\\\b\""), "'a\\\\b'");
        assert_eq!(r("False"), "False");
        assert_eq!(r("\"it's\""), "\"it's\"");
    }

    proptest! {
        #[test]
        fn variables_file_parser_and_commands_never_panic(text in "(?s).{0,120}", raw in ".{0,60}") {
            let _ = parse_variables_file(&text);
            let mut h = HostObjects::new(&cfg(), 0.0);
            for name in HOST_COMMANDS {
                let _ = h.command(name, &raw);
            }
        }

        #[test]
        fn saved_values_read_back_equal(v in proptest::collection::vec(-1e6f64..1e6, 0..4), s in "[a-z '\"]{0,10}") {
            let mut vars = BTreeMap::new();
            vars.insert("nums".to_string(), Value::from(v.clone()));
            vars.insert("text".to_string(), Value::from(s.clone()));
            let back = parse_variables_file(&variables_file_text(&vars)).unwrap();
            prop_assert_eq!(back["text"].as_str(), Some(s.as_str()));
            let nums: Vec<f64> = back["nums"].try_iter().unwrap().map(|x| f64::try_from(x).unwrap()).collect();
            prop_assert_eq!(nums, v);
        }
    }
}

//! G-code macros with Klipper's semantics: `[gcode_macro NAME]` templates rendered with
//! MiniJinja in Klipper's Jinja2 dialect, and the call stack that runs their lines.
//!
//! Klipper's template syntax: `{% … %}` statements, `{ … }` expressions (one brace, not two),
//! `{# … #}` comments; Python string/dict/list methods (`.lower()`, `.split()`, `.items()`)
//! through minijinja-contrib's pycompat. A macro sees:
//! - `params`: the call's parameters with upper-cased names and string values (`G28 X` →
//!   `{"X": ""}`; `START_PRINT BED=60` → `{"BED": "60"}`, quotes around a value removed);
//! - `rawparams`: the text after the command name;
//! - its own `variable_*` values as plain names (`{ my_var }`), and every macro's as
//!   `printer["gcode_macro NAME"].var`;
//! - `printer`: the status objects the caller provides (`toolhead`, `gcode_move`, …);
//! - `action_respond_info(msg)`, `action_raise_error(msg)` and `action_emergency_stop(msg)`.
//!
//! `rename_existing: NEW` makes a macro replace a command of the same name; the command stays
//! reachable as `NEW` ([`Macros::original_of`]). `SET_GCODE_VARIABLE MACRO= VARIABLE= VALUE=`
//! sets a variable to a literal (`10`, `'text'`, `[1, 2]`, `True`), as Klipper's Python literal.
//!
//! The call stack ([`Script`]) renders a macro when its call line is reached (so a macro sees
//! the state left by the lines before it), refuses a macro that calls itself, and bounds the
//! nesting depth. Rendering allocates: macros run where G-code is read, not in a real-time loop.

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::sync::{Arc, Mutex};

use minijinja::syntax::SyntaxConfig;
use minijinja::value::Value;
use minijinja::{Environment, Error as JinjaError, ErrorKind, UndefinedBehavior};

use super::host::{HostConfig, HostObjects};

/// Deepest macro nesting accepted (Klipper has no fixed bound; a runaway chain of distinct
/// macros is stopped here).
pub const MAX_MACRO_DEPTH: usize = 64;

/// One `[gcode_macro NAME]` section.
#[derive(Debug, Clone, PartialEq)]
pub struct MacroDef {
    /// The command name, upper-cased (`START_PRINT`).
    pub name: String,
    /// The `gcode:` template.
    pub gcode: String,
    /// `description:`.
    pub description: Option<String>,
    /// `rename_existing:`, upper-cased.
    pub rename_existing: Option<String>,
    /// `variable_NAME: literal` pairs, the name lower-cased as Klipper.
    pub variables: Vec<(String, String)>,
    /// Where the section is (`printer.cfg:12`), for errors.
    pub at: String,
}

/// Why a macro could not be defined, rendered or run.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MacroError {
    /// The template does not compile.
    #[error("{at}: [gcode_macro {name}] gcode: {message}")]
    Template {
        name: String,
        at: String,
        message: String,
    },
    /// A `variable_*` value is not a literal.
    #[error("{at}: [gcode_macro {name}] variable_{variable}: '{value}' is not a literal ({message})")]
    Variable {
        name: String,
        at: String,
        variable: String,
        value: String,
        message: String,
    },
    /// Two macros with one name, or `rename_existing` naming a macro.
    #[error("{at}: [gcode_macro {name}] {message}")]
    Definition {
        name: String,
        at: String,
        message: String,
    },
    /// Rendering failed (an undefined name, a bad filter argument…).
    #[error("Error evaluating 'gcode_macro {name}:gcode': {message}")]
    Render { name: String, message: String },
    /// The macro called `action_raise_error(message)`.
    #[error("{message}")]
    Raised { name: String, message: String },
    /// The macro called `action_emergency_stop(message)`.
    #[error("Shutdown due to {message}")]
    EmergencyStop { name: String, message: String },
    /// A macro called itself, directly or through others.
    #[error("Macro {name} called recursively")]
    Recursive { name: String },
    /// Macros nested deeper than [`MAX_MACRO_DEPTH`].
    #[error("Macro {name} nested more than {MAX_MACRO_DEPTH} deep")]
    TooDeep { name: String },
    /// SET_GCODE_VARIABLE with a missing or wrong parameter.
    #[error("{0}")]
    SetVariable(String),
}

/// What rendering a macro produced besides its lines.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Rendered {
    /// The script's non-empty lines, trimmed, in order.
    pub lines: Vec<String>,
    /// `action_respond_info` messages, in order.
    pub messages: Vec<String>,
}

#[derive(Debug)]
struct MacroState {
    def: MacroDef,
    variables: BTreeMap<String, Value>,
}

/// The printer's macros: compiled templates and their variables.
#[derive(Debug)]
pub struct Macros {
    env: Environment<'static>,
    macros: HashMap<String, MacroState>,
    /// `rename_existing` name → the command it keeps reachable.
    renamed: HashMap<String, String>,
    /// Collects the `action_*` calls of the render in progress.
    actions: Arc<Mutex<Actions>>,
    /// `[respond]`'s default prefix when the printer has the section (then `RESPOND` and
    /// `M118` are commands, see [`super::respond`]).
    respond_prefix: Option<String>,
    /// `[delayed_gcode]`, `[save_variables]`, `[idle_timeout]`, `[display_status]`.
    host: HostObjects,
}

#[derive(Debug, Default)]
struct Actions {
    messages: Vec<String>,
    emergency: Option<String>,
}

/// Klipper's delimiters: `{%`/`%}` statements, `{`/`}` expressions, `{#`/`#}` comments.
fn klipper_syntax() -> Result<SyntaxConfig, JinjaError> {
    SyntaxConfig::builder()
        .block_delimiters("{%", "%}")
        .variable_delimiters("{", "}")
        .comment_delimiters("{#", "#}")
        .build()
}

impl Macros {
    /// Compiles `defs`; errors name the section and what is wrong.
    pub fn new(defs: Vec<MacroDef>) -> Result<Macros, MacroError> {
        let mut env = Environment::new();
        let definition = |d: &MacroDef, message: String| MacroError::Definition {
            name: d.name.clone(),
            at: d.at.clone(),
            message,
        };
        if let Some(d) = defs.first() {
            env.set_syntax(klipper_syntax().map_err(|e| definition(d, e.to_string()))?);
        }
        env.set_undefined_behavior(UndefinedBehavior::Lenient);
        env.set_unknown_method_callback(minijinja_contrib::pycompat::unknown_method_callback);
        env.set_keep_trailing_newline(true);
        let actions = Arc::new(Mutex::new(Actions::default()));
        let a = Arc::clone(&actions);
        env.add_function("action_respond_info", move |msg: String| {
            if let Ok(mut a) = a.lock() {
                a.messages.push(msg);
            }
            String::new()
        });
        env.add_function(
            "action_raise_error",
            |msg: String| -> Result<String, JinjaError> {
                Err(JinjaError::new(ErrorKind::InvalidOperation, RAISED).with_source(Raised(msg)))
            },
        );
        let a = Arc::clone(&actions);
        env.add_function("action_emergency_stop", move |msg: Option<String>| {
            if let Ok(mut a) = a.lock() {
                a.emergency = Some(msg.unwrap_or_else(|| "action_emergency_stop".to_string()));
            }
            String::new()
        });
        env.add_function("action_call_remote_method", |_name: String| String::new());

        let mut macros = HashMap::new();
        let mut renamed = HashMap::new();
        for d in defs {
            if macros.contains_key(&d.name) {
                return Err(definition(&d, "is defined twice".to_string()));
            }
            env.add_template_owned(d.name.clone(), d.gcode.clone())
                .map_err(|e| MacroError::Template {
                    name: d.name.clone(),
                    at: d.at.clone(),
                    message: jinja_message(&e),
                })?;
            let mut variables = BTreeMap::new();
            for (var, text) in &d.variables {
                let value = literal(&env, text).map_err(|message| MacroError::Variable {
                    name: d.name.clone(),
                    at: d.at.clone(),
                    variable: var.clone(),
                    value: text.clone(),
                    message,
                })?;
                variables.insert(var.clone(), value);
            }
            if let Some(new) = &d.rename_existing {
                renamed.insert(new.clone(), d.name.clone());
            }
            macros.insert(d.name.clone(), MacroState { def: d, variables });
        }
        for (new, old) in &renamed {
            if let Some(m) = macros.get(new) {
                return Err(definition(
                    &m.def,
                    format!("is the rename_existing name of [gcode_macro {old}]"),
                ));
            }
        }
        Ok(Macros {
            env,
            macros,
            renamed,
            actions,
            respond_prefix: None,
            host: HostObjects::default(),
        })
    }

    /// With the host objects of `cfg` (timers armed from print time `start`).
    pub fn with_host(mut self, cfg: &HostConfig, start: f64) -> Macros {
        self.host = HostObjects::new(cfg, start);
        self
    }

    /// The host objects (`[delayed_gcode]` timers, saved variables, idle timeout, display).
    pub fn host(&self) -> &HostObjects {
        &self.host
    }

    /// The host objects, to change.
    pub fn host_mut(&mut self) -> &mut HostObjects {
        &mut self.host
    }

    /// With `[respond]` (its default prefix), `RESPOND` and `M118` answer; without, they are
    /// unknown commands as on Klipper.
    pub fn with_respond(mut self, prefix: Option<String>) -> Macros {
        self.respond_prefix = prefix;
        self
    }

    /// `[respond]`'s default prefix, when the printer has the section.
    pub fn respond_prefix(&self) -> Option<&str> {
        self.respond_prefix.as_deref()
    }

    /// True when the G-code feed runs `name` here rather than planning it: a macro,
    /// `SET_GCODE_VARIABLE`, or with `[respond]` `RESPOND`/`M118`.
    pub fn is_feed_command(&self, name: &str) -> bool {
        name == "SET_GCODE_VARIABLE"
            || self.is_macro(name)
            || self.host.handles(name)
            || (self.respond_prefix.is_some() && super::respond::is_respond_command(name))
    }

    /// True when `name` (upper-cased) is a macro.
    pub fn is_macro(&self, name: &str) -> bool {
        self.macros.contains_key(name)
    }

    /// The command a `rename_existing` name stands for (`G28.1` → `G28`).
    pub fn original_of(&self, name: &str) -> Option<&str> {
        self.renamed.get(name).map(String::as_str)
    }

    /// The macros' names and descriptions, sorted by name (for `HELP`; the lower-case
    /// scripts of other sections left out).
    pub fn descriptions(&self) -> Vec<(&str, &str)> {
        let mut v: Vec<(&str, &str)> = self
            .macros
            .values()
            .filter(|m| !is_section_script(&m.def.name))
            .map(|m| {
                (
                    m.def.name.as_str(),
                    m.def.description.as_deref().unwrap_or("G-Code macro"),
                )
            })
            .collect();
        v.sort_unstable();
        v
    }

    /// Every macro's variables as `printer["gcode_macro NAME"]` objects.
    pub fn status(&self) -> BTreeMap<String, Value> {
        self.macros
            .iter()
            .filter(|(name, _)| !is_section_script(name))
            .map(|(name, m)| (format!("gcode_macro {name}"), Value::from(m.variables.clone())))
            .collect()
    }

    /// Renders macro `name` called with `rawparams`, `printer` being the caller's status
    /// objects (macro variables are added to them).
    pub fn render(
        &self,
        name: &str,
        rawparams: &str,
        printer: &serde_json::Value,
    ) -> Result<Rendered, MacroError> {
        let Some(m) = self.macros.get(name) else {
            return Err(MacroError::Render {
                name: name.to_string(),
                message: "no such macro".to_string(),
            });
        };
        let render_error = |message: String| MacroError::Render {
            name: name.to_string(),
            message,
        };
        let mut printer_obj: BTreeMap<String, Value> = match printer {
            serde_json::Value::Object(o) => o
                .iter()
                .map(|(k, v)| (k.clone(), Value::from_serialize(v)))
                .collect(),
            _ => BTreeMap::new(),
        };
        printer_obj.extend(self.status());
        for (k, v) in self.host.status(None) {
            printer_obj.entry(k).or_insert(v);
        }
        let mut ctx: BTreeMap<String, Value> = m.variables.clone();
        ctx.insert("params".into(), Value::from(call_params(name, rawparams)));
        ctx.insert("rawparams".into(), Value::from(rawparams));
        ctx.insert("printer".into(), Value::from(printer_obj));
        if let Ok(mut a) = self.actions.lock() {
            *a = Actions::default();
        }
        let template = self
            .env
            .get_template(name)
            .map_err(|e| render_error(jinja_message(&e)))?;
        let text = template.render(ctx).map_err(|e| match raised(&e) {
            Some(message) => MacroError::Raised {
                name: name.to_string(),
                message,
            },
            None => render_error(jinja_message(&e)),
        })?;
        let (messages, emergency) = match self.actions.lock() {
            Ok(mut a) => (std::mem::take(&mut a.messages), a.emergency.take()),
            Err(_) => (Vec::new(), None),
        };
        if let Some(message) = emergency {
            return Err(MacroError::EmergencyStop {
                name: name.to_string(),
                message,
            });
        }
        let lines = text
            .lines()
            .map(str::trim)
            .filter(|l| !l.is_empty())
            .map(str::to_string)
            .collect();
        Ok(Rendered { lines, messages })
    }

    /// `SET_GCODE_VARIABLE MACRO=name VARIABLE=var VALUE=literal`, given its `rawparams`.
    pub fn set_variable(&mut self, rawparams: &str) -> Result<(), MacroError> {
        let params = call_params("SET_GCODE_VARIABLE", rawparams);
        let get = |key: &str| {
            params.get(key).cloned().ok_or_else(|| {
                MacroError::SetVariable(format!("Error on 'SET_GCODE_VARIABLE': missing {key}"))
            })
        };
        let (macro_name, variable, text) = (
            get("MACRO")?.to_uppercase(),
            get("VARIABLE")?.to_lowercase(),
            get("VALUE")?,
        );
        let value = literal(&self.env, &text)
            .map_err(|e| MacroError::SetVariable(format!("Unable to parse '{text}' as a literal: {e}")))?;
        let m = self
            .macros
            .get_mut(&macro_name)
            .ok_or_else(|| MacroError::SetVariable(format!("Unknown gcode_macro '{macro_name}'")))?;
        match m.variables.get_mut(&variable) {
            Some(slot) => {
                *slot = value;
                Ok(())
            }
            None => Err(MacroError::SetVariable(format!(
                "Unknown gcode_macro variable '{variable}'"
            ))),
        }
    }
}

/// True for the script of another section run as a macro (`homing_override`,
/// `delayed_gcode ID`, `idle_timeout`): their names are lower case, which no G-code command is.
fn is_section_script(name: &str) -> bool {
    name.starts_with(|c: char| c.is_ascii_lowercase())
}

/// Marker text of the error `action_raise_error` returns (its message rides in the source).
const RAISED: &str = "action_raise_error";

#[derive(Debug)]
struct Raised(String);

impl std::fmt::Display for Raised {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for Raised {}

/// The message of an `action_raise_error`, found in the error's source chain.
fn raised(e: &JinjaError) -> Option<String> {
    let mut source: Option<&(dyn std::error::Error + 'static)> = std::error::Error::source(e);
    while let Some(s) = source {
        if let Some(r) = s.downcast_ref::<Raised>() {
            return Some(r.0.clone());
        }
        source = s.source();
    }
    None
}

/// A MiniJinja error as one line: its kind and detail, and the template line.
fn jinja_message(e: &JinjaError) -> String {
    let detail = e.detail().map(|d| format!(": {d}")).unwrap_or_default();
    match e.line() {
        Some(line) => format!("{}{detail} (template line {line})", e.kind()),
        None => format!("{}{detail}", e.kind()),
    }
}

/// Evaluates `text` as a literal (Klipper takes `variable_*` and `VALUE=` as Python literals;
/// Jinja's literals are the same numbers, quoted strings, lists, dicts, True/False/None).
fn literal(env: &Environment<'static>, text: &str) -> Result<Value, String> {
    let expr = env
        .compile_expression(text.trim())
        .map_err(|e| jinja_message(&e))?;
    let value = expr.eval(()).map_err(|e| jinja_message(&e))?;
    if value.is_undefined() {
        return Err("names are not literals (quote a string: 'text')".to_string());
    }
    Ok(value)
}

/// The parameters of a call: traditional commands (`G28 X Y`, `M104 S200`) give one entry per
/// letter word; extended commands (`START_PRINT BED=60 EXTRUDER="215"`) one per `KEY=VALUE`,
/// with surrounding quotes removed. Names are upper-cased.
pub fn call_params(name: &str, rawparams: &str) -> BTreeMap<String, String> {
    let traditional = name.len() >= 2
        && name.as_bytes()[0].is_ascii_alphabetic()
        && name[1..].bytes().all(|c| c.is_ascii_digit() || c == b'.');
    let mut out = BTreeMap::new();
    if traditional {
        for word in rawparams.split_whitespace() {
            let mut chars = word.chars();
            if let Some(letter) = chars.next() {
                out.insert(
                    letter.to_ascii_uppercase().to_string(),
                    chars.as_str().to_string(),
                );
            }
        }
        return out;
    }
    let mut rest = rawparams.trim_start();
    while !rest.is_empty() {
        let Some(eq) = rest.find('=') else { break };
        let key = rest[..eq].trim();
        let after = &rest[eq + 1..];
        let (value, next) = match after.strip_prefix('"') {
            Some(q) => match q.find('"') {
                Some(end) => (&q[..end], &q[end + 1..]),
                None => (q, ""),
            },
            None => match after.find(char::is_whitespace) {
                Some(end) => (&after[..end], &after[end..]),
                None => (after, ""),
            },
        };
        let key = key.rsplit(char::is_whitespace).next().unwrap_or(key);
        if !key.is_empty() {
            out.insert(key.to_uppercase(), value.to_string());
        }
        rest = next.trim_start();
    }
    out
}

/// The command name of a G-code line, upper-cased, and the text after it; `None` for a
/// blank or comment-only line. Comments (`;`) are removed; an `N` line number is skipped.
pub fn split_command(line: &str) -> Option<(String, &str)> {
    let code = line.split(';').next().unwrap_or("").trim();
    let code = match code.strip_prefix(['N', 'n']) {
        Some(rest) if rest.starts_with(|c: char| c.is_ascii_digit()) => {
            rest.trim_start_matches(|c: char| c.is_ascii_digit()).trim_start()
        }
        _ => code,
    };
    if code.is_empty() {
        return None;
    }
    let bytes = code.as_bytes();
    // Traditional commands may be packed (`G1X10`): the name is the letter and its number.
    let end = if bytes[0].is_ascii_alphabetic() && bytes.get(1).is_some_and(|c| c.is_ascii_digit()) {
        1 + code[1..]
            .find(|c: char| !(c.is_ascii_digit() || c == '.'))
            .unwrap_or(code.len() - 1)
    } else {
        code.find(char::is_whitespace).unwrap_or(code.len())
    };
    Some((code[..end].to_uppercase(), code[end..].trim_start()))
}

/// A line a running macro produced, with the macros it came through (outermost first).
#[derive(Debug, Clone, PartialEq)]
pub struct ScriptLine {
    pub text: String,
    pub macros: Vec<String>,
}

#[derive(Debug)]
struct Frame {
    name: String,
    lines: VecDeque<String>,
}

/// The macro call stack: the lines of the macros being run, innermost first.
#[derive(Debug, Default)]
pub struct Script {
    frames: Vec<Frame>,
}

impl Script {
    /// An empty stack.
    pub fn new() -> Script {
        Script::default()
    }

    /// True when no macro is running (the caller reads its own source next).
    pub fn is_idle(&self) -> bool {
        self.frames.is_empty()
    }

    /// The next line of the innermost running macro (finished macros are popped).
    pub fn next_line(&mut self) -> Option<ScriptLine> {
        while let Some(top) = self.frames.last_mut() {
            if let Some(text) = top.lines.pop_front() {
                let macros = self.frames.iter().map(|f| f.name.clone()).collect();
                return Some(ScriptLine { text, macros });
            }
            self.frames.pop();
        }
        None
    }

    /// Calls macro `name`: renders it now (with `printer` as it is now) and runs its lines
    /// next. Returns its `action_respond_info` messages.
    pub fn call(
        &mut self,
        macros: &Macros,
        name: &str,
        rawparams: &str,
        printer: &serde_json::Value,
    ) -> Result<Vec<String>, MacroError> {
        // A frame whose lines are all taken is still running its last line (this call, maybe):
        // frames are popped only by `next_line`, so a macro calling itself last is caught.
        if self.frames.iter().any(|f| f.name == name) {
            return Err(MacroError::Recursive {
                name: name.to_string(),
            });
        }
        if self.frames.len() >= MAX_MACRO_DEPTH {
            return Err(MacroError::TooDeep {
                name: name.to_string(),
            });
        }
        let rendered = macros.render(name, rawparams, printer)?;
        self.frames.push(Frame {
            name: name.to_string(),
            lines: rendered.lines.into(),
        });
        Ok(rendered.messages)
    }

    /// Drops every running macro (after an error: Klipper abandons the whole script).
    pub fn abort(&mut self) {
        self.frames.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use serde_json::json;

    fn def(name: &str, gcode: &str) -> MacroDef {
        MacroDef {
            name: name.into(),
            gcode: gcode.into(),
            description: None,
            rename_existing: None,
            variables: Vec::new(),
            at: "printer.cfg:1".into(),
        }
    }

    fn lines(r: Result<Rendered, MacroError>) -> Vec<String> {
        r.unwrap_or_else(|e| panic!("{e}")).lines
    }

    #[test]
    fn klipper_dialect_params_and_printer() {
        let m = Macros::new(vec![def(
            "START_PRINT",
            "{% set bed = params.BED|default(60)|float %}\n\
             M190 S{bed}\n\
             {% if printer.toolhead.homed_axes != 'xyz' %}G28{% endif %}\n\
             M104 S{params.EXTRUDER|int} ; raw: {rawparams}\n\
             {# a comment #}\n\
             G1 X{printer.toolhead.position.x + 10}\n",
        )])
        .unwrap();
        let printer = json!({"toolhead": {"homed_axes": "", "position": {"x": 5.0}}});
        assert_eq!(
            lines(m.render("START_PRINT", "EXTRUDER=215 BED=\"70\"", &printer)),
            [
                "M190 S70.0",
                "G28",
                "M104 S215 ; raw: EXTRUDER=215 BED=\"70\"",
                "G1 X15.0"
            ]
        );
    }

    #[test]
    fn variables_status_and_set_gcode_variable() {
        let mut d = def(
            "COUNT",
            "M117 {count} {printer['gcode_macro COUNT'].label.upper()}",
        );
        d.variables = vec![("count".into(), "3".into()), ("label".into(), "'abc'".into())];
        let mut m = Macros::new(vec![d]).unwrap();
        assert_eq!(lines(m.render("COUNT", "", &json!({}))), ["M117 3 ABC"]);
        m.set_variable("MACRO=count VARIABLE=COUNT VALUE=4").unwrap();
        m.set_variable("MACRO=COUNT VARIABLE=label VALUE=\"'x y'\"")
            .unwrap();
        assert_eq!(lines(m.render("COUNT", "", &json!({}))), ["M117 4 X Y"]);
        assert_eq!(
            m.set_variable("MACRO=COUNT VARIABLE=nope VALUE=1"),
            Err(MacroError::SetVariable(
                "Unknown gcode_macro variable 'nope'".into()
            ))
        );
        assert!(m.set_variable("MACRO=COUNT VARIABLE=count VALUE=bare").is_err());
        assert!(m.set_variable("MACRO=NONE VARIABLE=count VALUE=1").is_err());
    }

    #[test]
    fn actions_and_errors() {
        let m = Macros::new(vec![
            def("SAY", "{action_respond_info('hello ' ~ params.N)}\nG4 P1"),
            def("FAIL", "{action_raise_error('Bed too cold')}"),
            def("STOP", "{action_emergency_stop('bad thing')}"),
            def("BAD", "{ no_such_function(1) }"),
        ])
        .unwrap();
        let r = m.render("SAY", "N=2", &json!({})).unwrap();
        assert_eq!(
            (r.lines, r.messages),
            (vec!["G4 P1".to_string()], vec!["hello 2".to_string()])
        );
        let e = m.render("FAIL", "", &json!({})).unwrap_err();
        assert_eq!(e.to_string(), "Bed too cold");
        assert!(matches!(
            m.render("STOP", "", &json!({})),
            Err(MacroError::EmergencyStop { .. })
        ));
        let e = m.render("BAD", "", &json!({})).unwrap_err().to_string();
        assert!(e.starts_with("Error evaluating 'gcode_macro BAD:gcode'"), "{e}");
    }

    #[test]
    fn definition_errors_name_the_section() {
        let e = Macros::new(vec![def("X", "{% if %}")]).unwrap_err().to_string();
        assert!(e.starts_with("printer.cfg:1: [gcode_macro X] gcode: "), "{e}");
        let mut d = def("X", "G28");
        d.variables = vec![("v".into(), "not a literal".into())];
        let e = Macros::new(vec![d]).unwrap_err().to_string();
        assert!(
            e.starts_with("printer.cfg:1: [gcode_macro X] variable_v: 'not a literal'"),
            "{e}"
        );
        assert!(Macros::new(vec![def("X", "G28"), def("X", "G1")]).is_err());
        let mut d = def("G28", "G28.1 {rawparams}");
        d.rename_existing = Some("G28.1".into());
        let m = Macros::new(vec![d]).unwrap();
        assert_eq!(m.original_of("G28.1"), Some("G28"));
        assert_eq!(lines(m.render("G28", "X Y", &json!({}))), ["G28.1 X Y"]);
    }

    #[test]
    fn script_runs_nested_macros_and_refuses_recursion() {
        let m = Macros::new(vec![
            def("OUTER", "G1 X1\nINNER V=2\nG1 X3"),
            def("INNER", "G1 X{params.V}"),
            def("LOOP", "LOOP"),
        ])
        .unwrap();
        let mut s = Script::new();
        s.call(&m, "OUTER", "", &json!({})).unwrap();
        let mut run = Vec::new();
        while let Some(l) = s.next_line() {
            if let Some((name, rest)) = split_command(&l.text) {
                if m.is_macro(&name) {
                    s.call(&m, &name, rest, &json!({})).unwrap();
                    continue;
                }
            }
            run.push((l.text, l.macros.join(">")));
        }
        assert_eq!(
            run,
            [
                ("G1 X1".to_string(), "OUTER".to_string()),
                ("G1 X2".to_string(), "OUTER>INNER".to_string()),
                ("G1 X3".to_string(), "OUTER".to_string())
            ]
        );
        assert!(s.is_idle());
        s.call(&m, "LOOP", "", &json!({})).unwrap();
        let l = s.next_line().unwrap();
        assert_eq!(
            s.call(&m, "LOOP", "", &json!({})),
            Err(MacroError::Recursive { name: "LOOP".into() }),
            "{l:?}"
        );
    }

    #[test]
    fn params_and_command_split() {
        assert_eq!(split_command("  g28 x y ; home"), Some(("G28".into(), "x y")));
        assert_eq!(split_command("N12 G1X10Y2"), Some(("G1".into(), "X10Y2")));
        assert_eq!(
            split_command("start_print BED=60"),
            Some(("START_PRINT".into(), "BED=60"))
        );
        assert_eq!(split_command("G28.1 X"), Some(("G28.1".into(), "X")));
        assert_eq!(split_command("; only"), None);
        let p = call_params("M104", "S200 T0");
        assert_eq!((p["S"].as_str(), p["T"].as_str()), ("200", "0"));
        let p = call_params("START", "A=1 b=\"two words\" C=");
        assert_eq!(
            (p["A"].as_str(), p["B"].as_str(), p["C"].as_str()),
            ("1", "two words", "")
        );
    }

    proptest! {
        #[test]
        fn parsers_and_renders_never_panic(text in "(?s).{0,80}", raw in ".{0,40}") {
            let _ = split_command(&text);
            let _ = call_params("X", &raw);
            let _ = call_params("G1", &raw);
            if let Ok(m) = Macros::new(vec![def("T", &text)]) {
                let _ = m.render("T", &raw, &json!({"toolhead": {}}));
            }
        }
    }
}

//! `[exclude_object]`'s bookkeeping as Klipper has it: `EXCLUDE_OBJECT_DEFINE NAME= [CENTER=]
//! [POLYGON=]` (no NAME: list the objects; `RESET=1`: forget them), `EXCLUDE_OBJECT_START
//! NAME=` / `EXCLUDE_OBJECT_END [NAME=]` around an object's moves, and `EXCLUDE_OBJECT NAME=`
//! (or `CURRENT=1`; `RESET=1 [NAME=]` takes exclusions back; no parameter: list them). Names are
//! upper-cased. While the current object is excluded the G-code state drops its moves
//! ([`ExcludeObjects::skipping`]; see `machine`).

use super::macros::call_params;

/// The four commands.
pub const EXCLUDE_COMMANDS: [&str; 4] = [
    "EXCLUDE_OBJECT",
    "EXCLUDE_OBJECT_DEFINE",
    "EXCLUDE_OBJECT_END",
    "EXCLUDE_OBJECT_START",
];

/// Defined and excluded objects, and the one being printed.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ExcludeObjects {
    /// Defined object names, sorted.
    objects: Vec<String>,
    /// Excluded object names, sorted.
    excluded: Vec<String>,
    current: Option<String>,
}

impl ExcludeObjects {
    /// True while the moves being read belong to an excluded object.
    pub fn skipping(&self) -> bool {
        self.current.as_ref().is_some_and(|c| self.excluded.contains(c))
    }

    /// The excluded objects' names, sorted.
    pub fn excluded(&self) -> &[String] {
        &self.excluded
    }

    /// Runs one of [`EXCLUDE_COMMANDS`] (`name`) with `rawparams` (the text after the name).
    /// Returns Klipper's answer when there is one; an error for `CURRENT=1` without a current
    /// object or a START without NAME.
    pub fn command(&mut self, name: &str, rawparams: &str) -> Result<Option<String>, String> {
        let p = call_params(name, rawparams);
        let get = |k: &str| p.get(k).map(|v| v.to_uppercase()).filter(|v| !v.is_empty());
        let flag = |k: &str| p.get(k).is_some_and(|v| !v.is_empty() && v != "0");
        match name {
            "EXCLUDE_OBJECT_DEFINE" => {
                if flag("RESET") {
                    *self = ExcludeObjects::default();
                } else if let Some(n) = get("NAME") {
                    self.define(n);
                } else {
                    return Ok(Some(format!("Known objects: {}", self.objects.join(" "))));
                }
            }
            "EXCLUDE_OBJECT_START" => {
                let n = get("NAME").ok_or_else(|| format!("{name}: needs NAME"))?;
                self.define(n.clone());
                self.current = Some(n);
            }
            "EXCLUDE_OBJECT_END" => {
                let Some(current) = self.current.take() else {
                    // Klipper says so only once something is excluded.
                    let said = "EXCLUDE_OBJECT_END called, but no object is currently active";
                    return Ok((!self.excluded.is_empty()).then(|| said.to_string()));
                };
                if let Some(n) = get("NAME").filter(|n| *n != current) {
                    return Ok(Some(format!(
                        "EXCLUDE_OBJECT_END NAME={n} does not match the current object NAME={current}"
                    )));
                }
            }
            _ => {
                let named = get("NAME");
                if flag("RESET") {
                    match named {
                        Some(n) => {
                            self.excluded.retain(|e| *e != n);
                            return Ok(Some(format!("Unexcluding object {n}")));
                        }
                        None => self.excluded.clear(),
                    }
                } else if let Some(n) =
                    named.or_else(|| flag("CURRENT").then(|| self.current.clone()).flatten())
                {
                    if !self.excluded.contains(&n) {
                        self.excluded.push(n.clone());
                        self.excluded.sort();
                    }
                    return Ok(Some(format!("Excluding object {n}")));
                } else if flag("CURRENT") {
                    return Err("There is no current object to cancel".into());
                } else {
                    return Ok(Some(format!("Excluded objects: {}", self.excluded.join(" "))));
                }
            }
        }
        Ok(None)
    }

    /// `printer.exclude_object` as Klipper's status object has it: `objects` (each with its
    /// `name`; center and polygon are not kept), `excluded_objects`, `current_object`.
    pub fn status(&self) -> serde_json::Value {
        let objects: Vec<serde_json::Value> = self
            .objects
            .iter()
            .map(|n| serde_json::json!({ "name": n }))
            .collect();
        serde_json::json!({
            "objects": objects,
            "excluded_objects": self.excluded,
            "current_object": self.current,
        })
    }

    fn define(&mut self, name: String) {
        if let Err(i) = self.objects.binary_search(&name) {
            self.objects.insert(i, name);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn objects_are_defined_excluded_and_skipped_as_klipper() {
        let mut x = ExcludeObjects::default();
        let mut run = |name: &str, raw: &str| x.command(name, raw);
        assert_eq!(
            run(
                "EXCLUDE_OBJECT_DEFINE",
                "NAME=cube_1 CENTER=30,30 POLYGON=[[20,20],[40,20]]"
            ),
            Ok(None)
        );
        assert_eq!(run("EXCLUDE_OBJECT_DEFINE", "NAME=a"), Ok(None));
        assert_eq!(
            run("EXCLUDE_OBJECT_DEFINE", ""),
            Ok(Some("Known objects: A CUBE_1".into()))
        );
        assert_eq!(
            run("EXCLUDE_OBJECT", "NAME=cube_1"),
            Ok(Some("Excluding object CUBE_1".into()))
        );
        assert_eq!(
            run("EXCLUDE_OBJECT", ""),
            Ok(Some("Excluded objects: CUBE_1".into()))
        );
        assert_eq!(
            run("EXCLUDE_OBJECT", "CURRENT=1"),
            Err("There is no current object to cancel".into())
        );
        assert_eq!(run("EXCLUDE_OBJECT_START", "NAME=a"), Ok(None));
        assert_eq!(
            run("EXCLUDE_OBJECT_END", "NAME=b"),
            Ok(Some(
                "EXCLUDE_OBJECT_END NAME=B does not match the current object NAME=A".into()
            ))
        );
        assert!(run("EXCLUDE_OBJECT_START", "").is_err());
        let mut x = ExcludeObjects::default();
        x.command("EXCLUDE_OBJECT", "NAME=cube_1").unwrap();
        x.command("EXCLUDE_OBJECT_START", "NAME=a").unwrap();
        assert!(!x.skipping());
        x.command("EXCLUDE_OBJECT_END", "").unwrap();
        x.command("EXCLUDE_OBJECT_START", "NAME=Cube_1").unwrap();
        assert!(x.skipping());
        x.command("EXCLUDE_OBJECT_END", "NAME=cube_1").unwrap();
        assert!(!x.skipping());
        x.command("EXCLUDE_OBJECT_START", "NAME=cube_1").unwrap();
        assert_eq!(
            x.command("EXCLUDE_OBJECT", "RESET=1 NAME=cube_1"),
            Ok(Some("Unexcluding object CUBE_1".into()))
        );
        assert!(!x.skipping());
        x.command("EXCLUDE_OBJECT", "CURRENT=1").unwrap();
        assert!(x.skipping());
        x.command("EXCLUDE_OBJECT_DEFINE", "RESET=1").unwrap();
        assert!(!x.skipping() && x.excluded().is_empty());
    }

    proptest! {
        #[test]
        fn any_parameters_answer_or_error(cmd in 0usize..4, raw in ".{0,60}") {
            let mut x = ExcludeObjects::default();
            let _ = x.command(EXCLUDE_COMMANDS[cmd], &raw);
        }
    }
}

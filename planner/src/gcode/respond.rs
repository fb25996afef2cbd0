//! `[respond]`'s commands as Klipper has them: `RESPOND [TYPE=echo|echo_no_space|command|error]
//! [PREFIX=…] [MSG=…]` and `M118 text`, answered with the message after a prefix (`echo:`,
//! `//`, `!!`; by default the section's `default_prefix`, else its `default_type`'s, else
//! `echo:`). Parameters are read as macro parameters are ([`super::macros::call_params`]:
//! `MSG="two words"`).

use super::macros::call_params;

/// `TYPE=` (and `default_type:`) values and their prefixes; `echo_no_space` is `echo:` without
/// the space before the message.
pub const RESPOND_TYPES: [(&str, &str); 3] = [("echo", "echo:"), ("command", "//"), ("error", "!!")];

/// The prefix of `default_type` (`None`: Klipper's default, `echo`).
pub fn type_prefix(default_type: Option<&str>) -> Option<&'static str> {
    let t = default_type.unwrap_or("echo");
    RESPOND_TYPES.iter().find(|(n, _)| *n == t).map(|(_, p)| *p)
}

/// True for the commands of [`respond`].
pub fn is_respond_command(name: &str) -> bool {
    name == "RESPOND" || name == "M118"
}

/// Why `RESPOND` was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RespondError {
    /// A `TYPE=` that is none of [`RESPOND_TYPES`] nor `echo_no_space` (Klipper's words).
    #[error("RESPOND TYPE '{0}' is invalid. Must be one of 'echo', 'command', or 'error'")]
    BadType(String),
}

/// The answer to `RESPOND`/`M118` (`name`) with `rawparams` (the text after the name), the
/// section's prefix being `default_prefix`. A bad `TYPE` is Klipper's error.
pub fn respond(default_prefix: &str, name: &str, rawparams: &str) -> Result<String, RespondError> {
    if name == "M118" {
        return Ok(format!("{default_prefix} {}", rawparams.trim()));
    }
    let params = call_params(name, rawparams);
    let mut prefix = default_prefix.to_string();
    let mut space = true;
    if let Some(t) = params.get("TYPE") {
        let t = t.to_lowercase();
        match RESPOND_TYPES.iter().find(|(n, _)| *n == t) {
            Some((_, p)) => prefix = (*p).to_string(),
            None if t == "echo_no_space" => {
                prefix = "echo:".to_string();
                space = false;
            }
            None => return Err(RespondError::BadType(t)),
        }
    }
    if let Some(p) = params.get("PREFIX") {
        prefix = p.clone();
    }
    let msg = params.get("MSG").map_or("", String::as_str);
    Ok(match space {
        true => format!("{prefix} {msg}"),
        false => format!("{prefix}{msg}"),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn answers_as_klipper() {
        let r = |raw: &str| respond("echo:", "RESPOND", raw);
        assert_eq!(r("MSG=hello").unwrap(), "echo: hello");
        assert_eq!(r("MSG=\"two words\"").unwrap(), "echo: two words");
        assert_eq!(r("TYPE=command MSG=x").unwrap(), "// x");
        assert_eq!(r("TYPE=Error MSG=x").unwrap(), "!! x");
        assert_eq!(r("TYPE=echo_no_space MSG=x").unwrap(), "echo:x");
        assert_eq!(r("PREFIX=note: MSG=x").unwrap(), "note: x");
        assert_eq!(r("").unwrap(), "echo: ");
        let e = r("TYPE=loud MSG=x").unwrap_err().to_string();
        assert!(
            e.contains("'loud'") && e.contains("'echo', 'command', or 'error'"),
            "{e}"
        );
        assert_eq!(respond("//", "M118", " Layer 3 done").unwrap(), "// Layer 3 done");
        assert_eq!(type_prefix(None), Some("echo:"));
        assert_eq!(type_prefix(Some("error")), Some("!!"));
        assert_eq!(type_prefix(Some("loud")), None);
    }

    proptest! {
        #[test]
        fn any_text_answers_or_errors(raw in ".{0,80}") {
            let _ = respond("echo:", "RESPOND", &raw);
            let _ = respond("echo:", "M118", &raw);
        }
    }
}

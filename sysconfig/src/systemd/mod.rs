//! systemd units for Cadence on a printer's board, written in one place with one quoting rule:
//! - [`io_stage`]: the IO stage alone (`cadence serve --role io`), which prints attach to
//!   (`cadence doctor --unit`);
//! - [`service`]: the printer service front ends talk to (`cadence serve -a SOCKET`,
//!   `cadence service print|install`).

pub mod io_stage;
pub mod service;

pub use io_stage::{unit, UnitSpec};
pub use service::{unit_text, ServiceUnit};

/// Quotes one argument for an `ExecStart=` line by systemd's rules: bare when it is made only of
/// characters systemd reads literally, otherwise in double quotes with `"` and `\` escaped and
/// the specifiers `%` and `$` doubled.
pub(crate) fn quote(arg: &str) -> String {
    if !arg.is_empty()
        && arg
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "/._-:=+,@".contains(c))
    {
        return arg.to_owned();
    }
    let mut q = String::with_capacity(arg.len() + 2);
    q.push('"');
    for c in arg.chars() {
        match c {
            '"' | '\\' => {
                q.push('\\');
                q.push(c);
            }
            '%' => q.push_str("%%"),
            '$' => q.push_str("$$"),
            _ => q.push(c),
        }
    }
    q.push('"');
    q
}

#[cfg(test)]
mod tests {
    use super::quote;

    #[test]
    fn quoting_follows_systemd_rules() {
        assert_eq!(quote("/a/b.cfg"), "/a/b.cfg");
        assert_eq!(quote("a b"), "\"a b\"");
        assert_eq!(quote("100%"), "\"100%%\"");
        assert_eq!(quote("$HOME"), "\"$$HOME\"");
        assert_eq!(quote("q\"\\"), "\"q\\\"\\\\\"");
        assert_eq!(quote(""), "\"\"");
    }
}

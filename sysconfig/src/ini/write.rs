//! Writes a [`ConfigFile`] back as config text: one flattened file (includes already resolved,
//! comments gone), each section once, multi-line values as indented continuation lines.
//!
//! Parsing the output gives the same sections and options (locations aside), except for values
//! the format cannot carry: a `#` or `;` after whitespace would be read back as a comment.

use std::fmt;

use super::ConfigFile;

/// Indentation of continuation lines.
const INDENT: &str = "    ";

impl fmt::Display for ConfigFile {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, section) in self.sections.iter().enumerate() {
            if i > 0 {
                writeln!(f)?;
            }
            writeln!(f, "[{}]", section.name)?;
            for (key, value) in &section.options {
                let mut lines = value.text.split('\n');
                match lines.next() {
                    Some(first) if !first.is_empty() => writeln!(f, "{key}: {first}")?,
                    _ => writeln!(f, "{key}:")?,
                }
                for line in lines {
                    if line.is_empty() {
                        writeln!(f)?;
                    } else {
                        writeln!(f, "{INDENT}{line}")?;
                    }
                }
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    #[test]
    fn writes_sections_options_and_continuations() {
        let text = "[b]\nx = 1\n[a arg]\ngcode:\n  G28\n\n  G1 X1\n[b]\ny: 2\n";
        let cfg = super::super::parse_str(text, Path::new("mem.cfg")).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            cfg.to_string(),
            "[b]\nx: 1\ny: 2\n\n[a arg]\ngcode:\n    G28\n\n    G1 X1\n"
        );
    }
}

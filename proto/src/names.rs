//! The grammar of every name that comes from outside and becomes part of a key expression, a
//! file name, a database key or a log line: machine ids, temperature-sensor names, probe types,
//! effect ids and the chunks of a key-expression prefix.
//!
//! A name is 1 to [`MAX_NAME_LEN`] bytes of ASCII letters, digits, `_`, `-` and `.`, and does
//! not start with `.` or `-`. So a name can never be a zenoh wildcard (`*`, `**`, `$*`), never
//! span two key chunks (`/`), never carry a query (`?`), a fragment (`#`), the admin space
//! (`@`), a path (`..`), a shell option (`-x`) or a control character into a log line.
//! Every entry point checks names with [`check`] before using them: raw samples (the key's
//! machine and the sample's), calibration puts and gets, the service configuration, the CLI.

use std::fmt;

/// The longest name, bytes.
pub const MAX_NAME_LEN: usize = 64;

/// The longest key-expression prefix (chunks joined by `/`), bytes.
pub const MAX_PREFIX_LEN: usize = 128;

/// A name that does not follow the grammar.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NameError {
    /// What the name is (`machine id`, `sensor name`, `prefix`, ...).
    pub what: &'static str,
    /// The name, shortened and escaped so that it is safe to print.
    pub shown: String,
    /// What is wrong.
    pub reason: String,
}

impl fmt::Display for NameError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} {}: {} (names are 1–{MAX_NAME_LEN} characters of A–Z a–z 0–9 _ - ., not starting with . or -)",
            self.what, self.shown, self.reason
        )
    }
}

impl std::error::Error for NameError {}

/// A name from outside, quoted, escaped and cut to at most 40 characters: safe to print in a
/// message or a log line whatever it holds.
pub fn shown(name: &str) -> String {
    let mut s: String = name.chars().take(40).collect();
    if s.len() < name.len() {
        s.push('…');
    }
    format!("{s:?}")
}

/// Checks `name` against the grammar; `what` names it in the error (`"machine id"`).
pub fn check(what: &'static str, name: &str) -> Result<(), NameError> {
    let err = |reason: String| NameError {
        what,
        shown: shown(name),
        reason,
    };
    if name.is_empty() {
        return Err(err("is empty".into()));
    }
    if name.len() > MAX_NAME_LEN {
        return Err(err(format!(
            "is {} bytes long, more than {MAX_NAME_LEN}",
            name.len()
        )));
    }
    if let Some(c) = name
        .chars()
        .find(|c| !(c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.')))
    {
        return Err(err(format!("holds {c:?}, which is not allowed")));
    }
    if name.starts_with('.') || name.starts_with('-') {
        return Err(err("starts with `.` or `-`".into()));
    }
    Ok(())
}

/// Whether `name` follows the grammar.
pub fn is_valid(name: &str) -> bool {
    check("name", name).is_ok()
}

/// Checks a machine id.
pub fn check_machine(id: &str) -> Result<(), NameError> {
    check("machine id", id)
}

/// Checks a key-expression prefix: one or more names joined by `/`, at most
/// [`MAX_PREFIX_LEN`] bytes.
pub fn check_prefix(prefix: &str) -> Result<(), NameError> {
    if prefix.len() > MAX_PREFIX_LEN {
        return Err(NameError {
            what: "prefix",
            shown: shown(prefix),
            reason: format!("is longer than {MAX_PREFIX_LEN} bytes"),
        });
    }
    for chunk in prefix.split('/') {
        check("prefix chunk", chunk).map_err(|mut e| {
            e.shown = format!("{} in prefix {}", e.shown, shown(prefix));
            e
        })?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_grammar_refuses_every_key_expression_metacharacter() {
        for ok in ["m1", "CMM_7", "bay-3.left", "a", &"x".repeat(MAX_NAME_LEN)] {
            assert!(check_machine(ok).is_ok(), "{ok}");
        }
        for bad in [
            "",
            "*",
            "**",
            "$*",
            "m$*",
            "a/b",
            "m?x=1",
            "m#1",
            "@admin",
            "..",
            ".hidden",
            "-rf",
            "m 1",
            "m\n1",
            "m\u{7}",
            "m\u{0}",
            "Süd",
            &"x".repeat(MAX_NAME_LEN + 1),
        ] {
            let e = check_machine(bad).unwrap_err();
            let msg = e.to_string();
            assert!(msg.starts_with("machine id "), "{msg}");
            assert!(!msg.contains('\n') && !msg.contains('\u{0}'), "{msg:?}");
        }
        assert!(check_prefix("cmm").is_ok());
        assert!(check_prefix("plant1/cmm").is_ok());
        for bad in ["", "cmm/", "/cmm", "cmm/*", "**", "cmm//x"] {
            assert!(check_prefix(bad).is_err(), "{bad}");
        }
        // A long hostile name is shown cut and escaped.
        let long = format!("{}\u{1b}[31m", "y".repeat(5000));
        let e = check_machine(&long).unwrap_err().to_string();
        assert!(
            e.len() < 400 && e.contains('…') && !e.contains('\u{1b}'),
            "{e}"
        );
    }
}

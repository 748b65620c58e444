//! The bad-input marker (exit 2: the user can fix it). Which errors are bad input is decided at the crate's top
//! ([`crate::is_bad_input`]), where every room's error type is known; this bottom room knows none of them.

/// Bad input that has no richer error type of its own (a command-line value, say). The message names what and where.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct BadInput(pub String);

/// A value a key does not allow: which key (as the file spells it, e.g. `motor.displacement_cm3`), and what is wrong.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{key} {message}")]
pub struct KeyError {
    pub key: String,
    pub message: String,
}

impl KeyError {
    pub fn new(key: String, message: String) -> KeyError {
        KeyError { key, message }
    }
}

/// Whether a file the user named cannot be read for a reason theirs to fix: it is missing, not readable, a
/// directory, or not UTF-8 text (exit 2, not 1).
pub fn unreadable_is_bad_input(e: &std::io::Error) -> bool {
    use std::io::ErrorKind::{InvalidData, IsADirectory, NotADirectory, NotFound, PermissionDenied};
    matches!(e.kind(), NotFound | PermissionDenied | IsADirectory | NotADirectory | InvalidData)
}

//! The bad-input marker (exit 2: the user can fix it). Which errors are bad input is decided at the crate's top
//! ([`crate::is_bad_input`]), where every room's error type is known; this bottom room knows none of them.

/// Bad input that has no richer error type of its own (a command-line value, say). The message names what and where.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct BadInput(pub String);

//! Telling bad input (exit 2: the user can fix it) from everything else (exit 1).

use crate::plant::ModelError;
use crate::recording::RecordingError;
use crate::service::ConfigError;

/// Bad input that has no richer error type of its own (a command-line value, say). The message names what and where.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct BadInput(pub String);

/// True when some error in the chain is bad input: a model file, config, recording or argument the user can fix.
pub fn is_bad_input(err: &(dyn std::error::Error + 'static)) -> bool {
    let mut cur: Option<&(dyn std::error::Error + 'static)> = Some(err);
    while let Some(e) = cur {
        if e.is::<BadInput>() {
            return true;
        }
        if let Some(m) = e.downcast_ref::<ModelError>() {
            return m.is_bad_input();
        }
        if let Some(r) = e.downcast_ref::<RecordingError>() {
            return r.is_bad_input();
        }
        if let Some(c) = e.downcast_ref::<ConfigError>() {
            return c.is_bad_input();
        }
        cur = e.source();
    }
    false
}

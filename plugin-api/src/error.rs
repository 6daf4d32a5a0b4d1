use serde::{Deserialize, Serialize};

/// An error a plugin returns: a stable machine-readable `code` and a message a person can act on.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, thiserror::Error)]
#[error("{code}: {message}")]
pub struct PluginError {
    pub code: String,
    pub message: String,
}

impl PluginError {
    pub fn new(code: impl Into<String>, message: impl Into<String>) -> Self {
        PluginError {
            code: code.into(),
            message: message.into(),
        }
    }

    /// Encodes an answer as JSON; a value that cannot be encoded becomes an `internal` error
    /// instead of a panic.
    pub fn encode<T: serde::Serialize>(answer: &T) -> Result<serde_json::Value, PluginError> {
        serde_json::to_value(answer)
            .map_err(|e| PluginError::new("internal", format!("cannot encode answer: {e}")))
    }

    /// The request or config had a field the plugin could not accept.
    pub fn invalid(message: impl Into<String>) -> Self {
        PluginError::new("invalid_request", message)
    }

    /// The backend does not implement this contract operation (`op` names it, e.g. `mdi`).
    pub fn unsupported(op: &str) -> Self {
        PluginError::new(
            "unsupported",
            format!("this machine backend does not support `{op}`"),
        )
    }
}

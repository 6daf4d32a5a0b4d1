//! Reading a plugin's JSON config field by field, with errors that name the key and the value
//! that was given (code `invalid_config`). Shared by the Rust backends so every plugin words
//! the same mistake the same way.

use crate::PluginError;
use serde_json::{Map, Value};
use std::time::Duration;

/// An `invalid_config` error.
pub fn invalid(message: impl Into<String>) -> PluginError {
    PluginError::new("invalid_config", message)
}

/// A finite number.
pub fn number(key: &str, v: &Value) -> Result<f64, PluginError> {
    match v.as_f64() {
        Some(n) if n.is_finite() => Ok(n),
        _ => Err(invalid(format!("`{key}` must be a number, got {v}"))),
    }
}

/// A finite number greater than 0.
pub fn positive(key: &str, v: &Value) -> Result<f64, PluginError> {
    let n = number(key, v)?;
    if n > 0.0 {
        Ok(n)
    } else {
        Err(invalid(format!("`{key}` must be greater than 0, got {n}")))
    }
}

/// A finite number, 0 or more.
pub fn non_negative(key: &str, v: &Value) -> Result<f64, PluginError> {
    let n = number(key, v)?;
    if n >= 0.0 {
        Ok(n)
    } else {
        Err(invalid(format!("`{key}` must be 0 or more, got {n}")))
    }
}

/// A whole number of milliseconds greater than 0.
pub fn millis(key: &str, v: &Value) -> Result<Duration, PluginError> {
    match v.as_u64() {
        Some(ms) if ms > 0 => Ok(Duration::from_millis(ms)),
        _ => Err(invalid(format!(
            "`{key}` must be a whole number of milliseconds greater than 0, got {v}"
        ))),
    }
}

/// `true` or `false`.
pub fn boolean(key: &str, v: &Value) -> Result<bool, PluginError> {
    v.as_bool()
        .ok_or_else(|| invalid(format!("`{key}` must be true or false, got {v}")))
}

/// A JSON object.
pub fn object<'a>(key: &str, v: &'a Value) -> Result<&'a Map<String, Value>, PluginError> {
    v.as_object()
        .ok_or_else(|| invalid(format!("`{key}` must be an object, got {v}")))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use serde_json::json;

    #[test]
    fn errors_name_the_key_and_the_value() {
        let e = positive("rapid_mm_min", &json!(-3)).unwrap_err();
        assert_eq!(e.code, "invalid_config");
        assert!(
            e.message.contains("`rapid_mm_min`") && e.message.contains("-3"),
            "{e}"
        );
        assert!(number("x", &json!("fast"))
            .unwrap_err()
            .message
            .contains("\"fast\""));
        assert!(non_negative("x", &json!(-0.5)).is_err());
        assert_eq!(non_negative("x", &json!(0)).unwrap(), 0.0);
        assert!(millis("t", &json!(0)).is_err());
        assert_eq!(
            millis("t", &json!(250)).unwrap(),
            Duration::from_millis(250)
        );
        assert!(boolean("b", &json!(1)).is_err());
        assert!(object("o", &json!([])).is_err());
    }
}

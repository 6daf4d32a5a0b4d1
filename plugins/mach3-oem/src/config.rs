//! The plugin's JSON configuration; every error names the key.

use crate::codes::Codes;
use fresa_plugin_api::PluginError;
use serde_json::Value;
use std::time::Duration;

#[derive(Debug, Clone)]
pub struct Config {
    /// `host:port` of the agent.
    pub agent: String,
    pub secret: String,
    /// Status polls per second (one batched request each).
    pub poll_interval: Duration,
    /// Longest wait for one agent request (connect, handshake, batch).
    pub timeout: Duration,
    pub jog_feed_mm_min: f64,
    /// What DRO 816 shows on a program's first line (Mach3: 0).
    pub line_dro_base: u32,
    pub codes: Codes,
}

const KNOWN: &str =
    "agent, secret, secret_file, poll_hz, timeout_ms, jog_feed_mm_min, line_dro_base, codes";

fn invalid(message: impl Into<String>) -> PluginError {
    PluginError::new("invalid_config", message)
}

fn number(key: &str, v: &Value, min: f64, max: f64) -> Result<f64, PluginError> {
    match v.as_f64() {
        Some(n) if n.is_finite() && (min..=max).contains(&n) => Ok(n),
        _ => Err(invalid(format!(
            "`{key}` must be a number from {min} to {max}, got {v}"
        ))),
    }
}

fn string(key: &str, v: &Value) -> Result<String, PluginError> {
    match v.as_str() {
        Some(s) if !s.trim().is_empty() => Ok(s.trim().to_string()),
        _ => Err(invalid(format!(
            "`{key}` must be a non-empty string, got {v}"
        ))),
    }
}

impl Config {
    pub fn from_json(value: &Value) -> Result<Config, PluginError> {
        let obj = value.as_object().ok_or_else(|| {
            invalid(format!(
                "config must be an object like {{\"agent\":\"host:port\",\"secret\":\"...\"}}, got {value}"
            ))
        })?;
        let mut agent = None;
        let mut secret = None;
        let mut cfg = Config {
            agent: String::new(),
            secret: String::new(),
            poll_interval: Duration::from_millis(100),
            timeout: Duration::from_millis(3000),
            jog_feed_mm_min: 1000.0,
            line_dro_base: 0,
            codes: Codes::default(),
        };
        for (key, v) in obj {
            match key.as_str() {
                "agent" => agent = Some(string(key, v)?),
                "secret" => secret = Some(string(key, v)?),
                "secret_file" => {
                    let path = string(key, v)?;
                    let text = std::fs::read_to_string(&path)
                        .map_err(|e| invalid(format!("`secret_file`: cannot read {path}: {e}")))?;
                    secret = Some(
                        string(key, &Value::String(text))
                            .map_err(|_| invalid(format!("`secret_file`: {path} is empty")))?,
                    );
                }
                "poll_hz" => {
                    cfg.poll_interval = Duration::from_secs_f64(1.0 / number(key, v, 0.5, 50.0)?)
                }
                "timeout_ms" => {
                    cfg.timeout = Duration::from_millis(number(key, v, 100.0, 60_000.0)? as u64)
                }
                "jog_feed_mm_min" => cfg.jog_feed_mm_min = number(key, v, 1.0, 100_000.0)?,
                "line_dro_base" => match v.as_u64() {
                    Some(b @ (0 | 1)) => cfg.line_dro_base = b as u32,
                    _ => return Err(invalid(format!("`line_dro_base` must be 0 or 1, got {v}"))),
                },
                "codes" => cfg.codes = Codes::with_overrides(v).map_err(invalid)?,
                other => {
                    return Err(invalid(format!(
                        "unknown config key `{other}` (known: {KNOWN})"
                    )))
                }
            }
        }
        cfg.agent = agent.ok_or_else(|| {
            invalid("`agent` is required: the Mach3 agent's address, e.g. \"192.168.1.20:5873\"")
        })?;
        if !cfg.agent.contains(':') {
            return Err(invalid(format!(
                "`agent` must be host:port, got {:?}",
                cfg.agent
            )));
        }
        cfg.secret = secret.ok_or_else(|| {
            invalid("`secret` or `secret_file` is required: the agent's shared secret")
        })?;
        Ok(cfg)
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use serde_json::json;

    #[test]
    fn defaults_and_errors() {
        let c = Config::from_json(&json!({"agent": "127.0.0.1:1", "secret": "x"})).unwrap();
        assert_eq!(c.poll_interval, Duration::from_millis(100));
        for (cfg, key) in [
            (json!({"secret": "x"}), "agent"),
            (json!({"agent": "h:1"}), "secret"),
            (json!({"agent": "h", "secret": "x"}), "agent"),
            (
                json!({"agent": "h:1", "secret": "x", "poll_hz": 0}),
                "poll_hz",
            ),
            (
                json!({"agent": "h:1", "secret": "x", "codes": {"nope": 1}}),
                "codes.nope",
            ),
            (
                json!({"agent": "h:1", "secret": "x", "secret_file": "/nonexistent/x"}),
                "secret_file",
            ),
            (
                json!({"agent": "h:1", "secret": "x", "colour": 1}),
                "colour",
            ),
        ] {
            let e = Config::from_json(&cfg).unwrap_err();
            assert_eq!(e.code, "invalid_config");
            assert!(e.message.contains(key), "{key}: {}", e.message);
        }
    }
}

//! The plugin's JSON configuration. Parsed by hand so every error names the offending key.

use fresa_plugin_api::config_fields::{invalid, number, positive};
use fresa_plugin_api::contract::Axis;
use fresa_plugin_api::kit;
use fresa_plugin_api::PluginError;
use serde_json::Value;
use std::path::PathBuf;
use std::time::Duration;

/// Settings of one simulated machine. See the crate README for the JSON shape.
#[derive(Debug, Clone, PartialEq)]
pub struct Config {
    /// Multiplies every motion and dwell time: 1.0 = real time, 0.0 = instant.
    pub time_scale: f64,
    /// Speed of rapid (G0) and go-to-zero moves, mm/min.
    pub rapid_mm_min: f64,
    /// Jog feed when a jog request gives none, mm/min.
    pub jog_feed_mm_min: f64,
    /// Where each executed program line is appended as `{"run":R,"line":L}`.
    pub execution_log: Option<PathBuf>,
    /// Minimum time between two `status` events while the machine moves.
    pub status_interval: Duration,
    /// Soft limits per axis (machine coordinates), `None` = unlimited.
    pub travel: [Option<(f64, f64)>; 4],
    /// `connect` enters alarm with this message instead of idle (as a controller that needs an
    /// unlock after power-up does); `reset` clears it. For tests of alarm handling.
    pub alarm_at_connect: Option<String>,
}

impl Default for Config {
    fn default() -> Self {
        Config {
            time_scale: 1.0,
            rapid_mm_min: 5000.0,
            jog_feed_mm_min: 1000.0,
            execution_log: None,
            status_interval: Duration::from_millis(100),
            travel: [None; 4],
            alarm_at_connect: None,
        }
    }
}

impl Config {
    /// Parses the plugin config. `null` or `{}` gives the defaults.
    pub fn from_json(value: &Value) -> Result<Config, PluginError> {
        let mut cfg = Config::default();
        let obj = match value {
            Value::Null => return Ok(cfg),
            Value::Object(o) => o,
            other => {
                return Err(invalid(format!(
                    "config must be a JSON object, got {other}"
                )))
            }
        };
        for (key, v) in obj {
            match key.as_str() {
                "time_scale" => {
                    let n = number(key, v)?;
                    if n < 0.0 {
                        return Err(invalid(format!("`time_scale` must be 0 or more, got {n}")));
                    }
                    cfg.time_scale = n;
                }
                "rapid_mm_min" => cfg.rapid_mm_min = positive(key, v)?,
                "jog_feed_mm_min" => cfg.jog_feed_mm_min = positive(key, v)?,
                "execution_log" => match v {
                    Value::String(s) if !s.is_empty() => cfg.execution_log = Some(PathBuf::from(s)),
                    Value::Null => cfg.execution_log = None,
                    _ => {
                        return Err(invalid(format!(
                            "`execution_log` must be a non-empty file path string, got {v}"
                        )))
                    }
                },
                "status_interval_ms" => {
                    let ms = v.as_u64().ok_or_else(|| {
                        invalid(format!(
                            "`status_interval_ms` must be a whole number of milliseconds (0 or more), got {v}"
                        ))
                    })?;
                    cfg.status_interval = Duration::from_millis(ms);
                }
                "travel" => cfg.travel = kit::travel_from_json(v, &Axis::ALL)?,
                "alarm_at_connect" => match v {
                    Value::String(s) if !s.trim().is_empty() => {
                        cfg.alarm_at_connect = Some(s.clone())
                    }
                    Value::Null => cfg.alarm_at_connect = None,
                    _ => {
                        return Err(invalid(format!(
                            "`alarm_at_connect` must be a non-empty message string, got {v}"
                        )))
                    }
                },
                other => {
                    return Err(invalid(format!(
                        "unknown config key `{other}` (known: time_scale, rapid_mm_min, \
                         jog_feed_mm_min, execution_log, status_interval_ms, travel, \
                         alarm_at_connect)"
                    )))
                }
            }
        }
        Ok(cfg)
    }

    /// The first axis of `pos` (machine coordinates) outside the soft limits, as a message
    /// (the kit's check, shared by every backend).
    pub fn check_travel(&self, pos: [f64; 4]) -> Result<(), String> {
        kit::check_travel(&self.travel, pos)
    }

    /// Seconds a move of `distance_mm` at `feed_mm_min` takes, scaled.
    pub fn move_seconds(&self, distance_mm: f64, feed_mm_min: f64) -> f64 {
        if self.time_scale == 0.0 || distance_mm <= 0.0 || feed_mm_min <= 0.0 {
            0.0
        } else {
            distance_mm / feed_mm_min * 60.0 * self.time_scale
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;
    use serde_json::json;

    #[test]
    fn defaults_and_full_config() {
        assert_eq!(Config::from_json(&json!({})).unwrap(), Config::default());
        let c = Config::from_json(&json!({
            "time_scale": 0, "rapid_mm_min": 3000, "jog_feed_mm_min": 500.5,
            "execution_log": "/tmp/x.log", "status_interval_ms": 20,
            "travel": {"x": [-10, 300], "Z": [-100, 0]}
        }))
        .unwrap();
        assert_eq!(c.time_scale, 0.0);
        assert_eq!(c.rapid_mm_min, 3000.0);
        assert_eq!(c.travel[0], Some((-10.0, 300.0)));
        assert_eq!(c.travel[2], Some((-100.0, 0.0)));
        assert_eq!(c.travel[1], None);
        assert_eq!(c.status_interval, Duration::from_millis(20));
    }

    #[test]
    fn errors_name_the_key() {
        for (cfg, key) in [
            (json!({"time_scal": 1}), "time_scal"),
            (json!({"time_scale": "fast"}), "time_scale"),
            (json!({"time_scale": -1}), "time_scale"),
            (json!({"rapid_mm_min": 0}), "rapid_mm_min"),
            (json!({"jog_feed_mm_min": null}), "jog_feed_mm_min"),
            (json!({"execution_log": 3}), "execution_log"),
            (json!({"status_interval_ms": 1.5}), "status_interval_ms"),
            (json!({"travel": {"b": [0, 1]}}), "travel.b"),
            (json!({"travel": {"x": [1]}}), "travel.x"),
            (json!({"travel": {"x": [2, 1]}}), "travel.x"),
            (json!({"alarm_at_connect": true}), "alarm_at_connect"),
        ] {
            let e = Config::from_json(&cfg).unwrap_err();
            assert_eq!(e.code, "invalid_config");
            assert!(e.message.contains(key), "{key}: {}", e.message);
        }
    }
}

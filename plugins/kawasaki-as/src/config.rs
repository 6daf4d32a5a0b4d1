//! The plugin's JSON configuration. Parsed by hand so every error names the offending key.

use crate::convert::{Envelope, Mapping};
use fresa_gcode::Unsupported;
use fresa_plugin_api::config_fields::{invalid, millis, number, positive};
use fresa_plugin_api::PluginError;
use serde_json::Value;
use std::path::PathBuf;
use std::time::Duration;

/// The robot's default TCP port (the seed's robot program listens there).
pub const DEFAULT_PORT: u16 = 55000;

/// Which robot program runs on the controller.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Protocol {
    /// The seed's `FRESADORA` program, exactly as printed: stop-and-wait, no SPEED.
    Legacy,
    /// The program this plugin generates: sequence numbers, SPEED, a window, CP ON.
    FresaV1,
}

impl Protocol {
    pub fn name(self) -> &'static str {
        match self {
            Protocol::Legacy => "legacy",
            Protocol::FresaV1 => "fresa-v1",
        }
    }
}

/// Speeds the robot is given, mm/s.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Speeds {
    /// G0 moves (the seed's robot program fixes 10 mm/s).
    pub rapid_mm_s: f64,
    /// Cutting feed is clamped to `cut_min_mm_s..=cut_max_mm_s`.
    pub cut_min_mm_s: f64,
    pub cut_max_mm_s: f64,
}

impl Default for Speeds {
    fn default() -> Self {
        Speeds {
            rapid_mm_s: 10.0,
            cut_min_mm_s: 5.0,
            cut_max_mm_s: 15.0,
        }
    }
}

impl Speeds {
    /// Cutting speed for a G-code feed in mm/min: mm/s, clamped.
    pub fn cutting(&self, feed_mm_min: f64) -> f64 {
        (feed_mm_min / 60.0).clamp(self.cut_min_mm_s, self.cut_max_mm_s)
    }

    /// The cutting speed sent for a programmed (clamped) speed `mm_s` under a feed override of
    /// `percent`: scaled, never above `cut_max_mm_s` (the robot's cutting limit), and never
    /// below what the wire can carry. The override may take it below `cut_min_mm_s`: that
    /// clamp is for programs' feeds, the operator slowing a cut down decides for himself.
    pub fn overridden(&self, mm_s: f64, percent: f64) -> f64 {
        (mm_s * percent / 100.0)
            .min(self.cut_max_mm_s)
            .max(crate::codec::MIN_SPEED_MM_S)
    }
}

/// Settings of one robot. See the crate README for the JSON shape.
#[derive(Debug, Clone, PartialEq)]
pub struct Config {
    /// `host:port` of the robot's TCP server.
    pub address: String,
    pub protocol: Protocol,
    pub mapping: Mapping,
    pub speeds: Speeds,
    pub envelope: Envelope,
    /// Arc chord tolerance, mm.
    pub arc_tolerance_mm: f64,
    /// fresa-v1: commands sent ahead of their acknowledgement.
    pub window: usize,
    /// Policy for G-code words the interpreter does not implement.
    pub unsupported: Unsupported,
    pub connect_timeout: Duration,
    /// Longest wait for the robot's greeting and part zero.
    pub handshake_timeout: Duration,
    /// Longest wait for one `done` (a motion may take long at 5 mm/s).
    pub reply_timeout: Duration,
    /// legacy: file where every acknowledged motion is recorded, so a resume after a server
    /// crash starts at the exact next motion.
    pub journal: Option<PathBuf>,
}

impl Default for Config {
    fn default() -> Self {
        Config {
            address: String::new(),
            protocol: Protocol::Legacy,
            mapping: Mapping::default(),
            speeds: Speeds::default(),
            envelope: Envelope::default(),
            arc_tolerance_mm: 0.01,
            window: 4,
            unsupported: Unsupported::Error,
            connect_timeout: Duration::from_secs(3),
            handshake_timeout: Duration::from_secs(5),
            reply_timeout: Duration::from_secs(60),
            journal: None,
        }
    }
}

/// Slowest speed a config may set, mm/s: far above what the fresa-v1 wire can carry (6
/// decimals), so a SPEED command never goes out as 0.000000 (a fuzz finding), and slow enough
/// for any real cut.
const MIN_CONFIG_SPEED_MM_S: f64 = 0.01;

fn speed(key: &str, v: &Value) -> Result<f64, PluginError> {
    let n = positive(key, v)?;
    if n < MIN_CONFIG_SPEED_MM_S {
        return Err(invalid(format!(
            "`{key}` must be at least {MIN_CONFIG_SPEED_MM_S} mm/s, got {n}"
        )));
    }
    Ok(n)
}

const KNOWN: &str = "address, protocol, mapping, rapid_mm_s, cut_min_mm_s, cut_max_mm_s, \
                     envelope, machine_zero, arc_tolerance_mm, window, unsupported, \
                     connect_timeout_ms, handshake_timeout_ms, reply_timeout_ms, journal";

fn triple(key: &str, v: &Value) -> Result<[f64; 3], PluginError> {
    let a = v
        .as_array()
        .filter(|a| a.len() == 3)
        .ok_or_else(|| invalid(format!("`{key}` must be [x, y, z] in mm, got {v}")))?;
    Ok([
        number(key, &a[0])?,
        number(key, &a[1])?,
        number(key, &a[2])?,
    ])
}

/// `host:port`, `host` (default port) or `[v6]:port`.
fn address(v: &Value) -> Result<String, PluginError> {
    let s = v
        .as_str()
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .ok_or_else(|| {
            invalid(format!(
                "`address` must be the robot's \"host:port\" (port {DEFAULT_PORT} when left out), got {v}"
            ))
        })?;
    let has_port = match s.rsplit_once(':') {
        Some((host, port)) => {
            if host.contains(':') && !host.ends_with(']') {
                false // a bare IPv6 address
            } else {
                port.parse::<u16>().map_err(|_| {
                    invalid(format!(
                        "`address`: port {port:?} of {s:?} is not a number 0..65535"
                    ))
                })?;
                true
            }
        }
        None => false,
    };
    Ok(if has_port {
        s.to_string()
    } else if s.contains(':') && !s.starts_with('[') {
        format!("[{s}]:{DEFAULT_PORT}")
    } else {
        format!("{s}:{DEFAULT_PORT}")
    })
}

impl Config {
    /// Parses the plugin config; everything but `address` has a default.
    pub fn from_json(value: &Value) -> Result<Config, PluginError> {
        let mut cfg = Config::default();
        let obj = value.as_object().ok_or_else(|| {
            invalid(format!(
                "config must be a JSON object with at least `address`, got {value}"
            ))
        })?;
        let mut machine_zero = None;
        let mut envelope = None;
        for (key, v) in obj {
            match key.as_str() {
                "address" => cfg.address = address(v)?,
                "protocol" => {
                    cfg.protocol = match v.as_str() {
                        Some("legacy") => Protocol::Legacy,
                        Some("fresa-v1") => Protocol::FresaV1,
                        _ => {
                            return Err(invalid(format!(
                                "`protocol` must be \"legacy\" or \"fresa-v1\", got {v}"
                            )))
                        }
                    }
                }
                "mapping" => cfg.mapping = Mapping::from_json(v)?,
                "rapid_mm_s" => cfg.speeds.rapid_mm_s = speed(key, v)?,
                "cut_min_mm_s" => cfg.speeds.cut_min_mm_s = speed(key, v)?,
                "cut_max_mm_s" => cfg.speeds.cut_max_mm_s = speed(key, v)?,
                "envelope" => envelope = Some(v),
                "machine_zero" => machine_zero = Some(triple(key, v)?),
                "arc_tolerance_mm" => {
                    let t = positive(key, v)?;
                    if !(0.0001..=1.0).contains(&t) {
                        return Err(invalid(format!(
                            "`arc_tolerance_mm` must be between 0.0001 and 1 mm, got {t}"
                        )));
                    }
                    cfg.arc_tolerance_mm = t;
                }
                "window" => {
                    cfg.window = match v.as_u64() {
                        Some(n @ 1..=64) => n as usize,
                        _ => {
                            return Err(invalid(format!(
                                "`window` must be a whole number 1..64, got {v}"
                            )))
                        }
                    }
                }
                "unsupported" => {
                    cfg.unsupported = match v.as_str() {
                        Some("error") => Unsupported::Error,
                        Some("skip_with_warning") => Unsupported::SkipWithWarning,
                        _ => {
                            return Err(invalid(format!(
                                "`unsupported` must be \"error\" or \"skip_with_warning\", got {v}"
                            )))
                        }
                    }
                }
                "connect_timeout_ms" => cfg.connect_timeout = millis(key, v)?,
                "handshake_timeout_ms" => cfg.handshake_timeout = millis(key, v)?,
                "reply_timeout_ms" => cfg.reply_timeout = millis(key, v)?,
                "journal" => match v {
                    Value::String(s) if !s.is_empty() => cfg.journal = Some(PathBuf::from(s)),
                    Value::Null => cfg.journal = None,
                    _ => {
                        return Err(invalid(format!(
                            "`journal` must be a non-empty file path string, got {v}"
                        )))
                    }
                },
                other => {
                    return Err(invalid(format!(
                        "unknown config key `{other}` (known: {KNOWN})"
                    )))
                }
            }
        }
        if cfg.address.is_empty() {
            return Err(invalid(format!(
                "`address` is required: the robot's \"host:port\" (port {DEFAULT_PORT} when left out)"
            )));
        }
        if cfg.speeds.cut_min_mm_s > cfg.speeds.cut_max_mm_s {
            return Err(invalid(format!(
                "`cut_min_mm_s` {} is greater than `cut_max_mm_s` {}",
                cfg.speeds.cut_min_mm_s, cfg.speeds.cut_max_mm_s
            )));
        }
        if let Some(v) = envelope {
            cfg.envelope = Envelope::from_json(v, cfg.envelope.machine_zero)?;
        }
        if let Some(z) = machine_zero {
            cfg.envelope.machine_zero = z;
        }
        Ok(cfg)
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;
    use serde_json::json;

    #[test]
    fn defaults_match_the_seed() {
        let c = Config::from_json(&json!({"address": "127.0.0.1:55000", "protocol": "legacy"}))
            .unwrap();
        assert_eq!(c.protocol, Protocol::Legacy);
        assert_eq!(c.speeds, Speeds::default());
        assert_eq!(c.envelope, Envelope::default());
        assert_eq!(c.mapping, Mapping::default());
        assert_eq!(c.window, 4);
        let c = Config::from_json(&json!({"address": "robot.local"})).unwrap();
        assert_eq!(c.address, "robot.local:55000");
        let c = Config::from_json(&json!({"address": "::1"})).unwrap();
        assert_eq!(c.address, "[::1]:55000");
        let c = Config::from_json(&json!({"address": "[::1]:9"})).unwrap();
        assert_eq!(c.address, "[::1]:9");
    }

    #[test]
    fn full_config() {
        let c = Config::from_json(&json!({
            "address": "10.0.0.5:6000", "protocol": "fresa-v1",
            "mapping": {"x": "Y", "y": "X", "z": "-Z"},
            "rapid_mm_s": 20, "cut_min_mm_s": 1, "cut_max_mm_s": 30,
            "envelope": {"x": [-10, 10], "y": [-20, 20], "z": [-5, 5]},
            "machine_zero": [-300, 10, 0],
            "arc_tolerance_mm": 0.05, "window": 8, "unsupported": "skip_with_warning",
            "connect_timeout_ms": 100, "handshake_timeout_ms": 200, "reply_timeout_ms": 300,
            "journal": "/tmp/j"
        }))
        .unwrap();
        assert_eq!(c.protocol, Protocol::FresaV1);
        assert_eq!(c.window, 8);
        assert_eq!(c.envelope.machine_zero, [-300.0, 10.0, 0.0]);
        assert_eq!(c.envelope.min, [-10.0, -20.0, -5.0]);
        assert_eq!(c.mapping.map([1.0, 2.0, 3.0]), [2.0, 1.0, -3.0]);
        assert_eq!(c.unsupported, Unsupported::SkipWithWarning);
        assert_eq!(c.journal, Some(PathBuf::from("/tmp/j")));
    }

    #[test]
    fn errors_name_the_key() {
        for (cfg, key) in [
            (json!({}), "address"),
            (json!({"address": ""}), "address"),
            (json!({"address": "h:99999"}), "address"),
            (json!({"address": "h", "protocol": "v2"}), "protocol"),
            (json!({"address": "h", "speed": 3}), "speed"),
            (json!({"address": "h", "rapid_mm_s": 0}), "rapid_mm_s"),
            (json!({"address": "h", "cut_min_mm_s": 20}), "cut_min_mm_s"),
            (json!({"address": "h", "window": 0}), "window"),
            (
                json!({"address": "h", "arc_tolerance_mm": 5}),
                "arc_tolerance_mm",
            ),
            (
                json!({"address": "h", "mapping": {"x": "X", "y": "X", "z": "Z"}}),
                "mapping",
            ),
            (json!({"address": "h", "mapping": {"x": "Q"}}), "mapping.x"),
            (
                json!({"address": "h", "envelope": {"x": [1, -1]}}),
                "envelope.x",
            ),
            (
                json!({"address": "h", "machine_zero": [1, 2]}),
                "machine_zero",
            ),
            (
                json!({"address": "h", "unsupported": "skip"}),
                "unsupported",
            ),
            (
                json!({"address": "h", "reply_timeout_ms": -1}),
                "reply_timeout_ms",
            ),
            (json!({"address": "h", "journal": 4}), "journal"),
        ] {
            let e = Config::from_json(&cfg).unwrap_err();
            assert_eq!(e.code, "invalid_config");
            assert!(e.message.contains(key), "{key}: {}", e.message);
        }
    }

    #[test]
    fn speed_clamp() {
        let s = Speeds::default();
        assert_eq!(s.cutting(60.0), 5.0); // 1 mm/s -> 5
        assert_eq!(s.cutting(600.0), 10.0);
        assert_eq!(s.cutting(6000.0), 15.0);
    }
}

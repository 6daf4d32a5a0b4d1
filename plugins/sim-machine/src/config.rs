//! The plugin's JSON configuration. Parsed by hand so every error names the offending key.

use fresa_plugin_api::config_fields::{invalid, number, positive};
use fresa_plugin_api::contract::{io, Axis};
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
    /// Simulated input switches, each active while its axis is at or beyond a position, so a
    /// test (or a demo user) presses one by moving onto it.
    pub switches: Vec<Switch>,
    /// The physical tools (issue 26): how far each tool's tip reaches below the spindle's
    /// controlled point, mm, by tool number. The `probe` switch is touched by the tip, so a
    /// longer tool trips it higher up; a tool not listed (and tool 0, none) is 0 mm long.
    pub tool_lengths: std::collections::BTreeMap<u32, f64>,
    /// The tool in the spindle at start-up (0: none). A tool-change hold puts the new one in.
    pub tool: u32,
}

/// An input switch at a machine position: active while `axis` is at or above its level
/// (`above`) or at or below it. The level is `at`, or, for a Z switch with a surface (uneven
/// stock under a probe), `at + slope_x*x + slope_y*y + slope_xy*x*y` at the machine's X, Y.
#[derive(Debug, Clone, PartialEq)]
pub struct Switch {
    /// Its input name (`limit_x_max`, `probe`, ...).
    pub name: String,
    pub axis: Axis,
    pub at: f64,
    pub above: bool,
    /// `slope_x`, `slope_y`, `slope_xy` (Z switches only; zero: a flat level).
    pub surface: [f64; 3],
    /// A round wall in the XY plane instead of a level (the probe only): a bore or a boss,
    /// met by the tool's centre (the simulated tool has no radius). `axis`, `at`, `above` and
    /// `surface` do not apply then.
    pub circle: Option<Circle>,
}

/// A round wall for centre finding (`switches.probe.bore` / `.boss`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Circle {
    pub x: f64,
    pub y: f64,
    pub radius: f64,
    /// A bore: active at or beyond the radius (the wall around the tool). A boss: active
    /// within it, at or below `top` (the stud under and beside the tool).
    pub bore: bool,
    pub top: f64,
}

impl Circle {
    fn active_at(&self, pos: &[f64; 4]) -> bool {
        let d = (pos[0] - self.x).hypot(pos[1] - self.y);
        if self.bore {
            d >= self.radius
        } else {
            d <= self.radius && pos[2] <= self.top
        }
    }
}

impl Switch {
    /// Where the switch's edge lies on its axis with the machine at `pos` (X, Y matter for a
    /// surface).
    pub fn level_at(&self, pos: &[f64; 4]) -> f64 {
        let [sx, sy, sxy] = self.surface;
        self.at + sx * pos[0] + sy * pos[1] + sxy * pos[0] * pos[1]
    }

    pub fn active_at(&self, pos: &[f64; 4]) -> bool {
        if let Some(c) = &self.circle {
            return c.active_at(pos);
        }
        let p = pos[self.axis.index()];
        let level = self.level_at(pos);
        if self.above {
            p >= level
        } else {
            p <= level
        }
    }

    /// Limits and the e-stop stop the machine when they become active; a probe or door only
    /// shows.
    pub fn trips(&self) -> bool {
        self.name == io::ESTOP || self.name.starts_with(io::LIMIT)
    }
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
            switches: Vec::new(),
            tool_lengths: std::collections::BTreeMap::new(),
            tool: 0,
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
                "switches" => cfg.switches = switches(v)?,
                "tool_lengths" => cfg.tool_lengths = tool_lengths(v)?,
                "tool" => {
                    cfg.tool = v
                        .as_u64()
                        .and_then(|t| u32::try_from(t).ok())
                        .ok_or_else(|| {
                            invalid(format!(
                                "`tool` must be a tool number (0 for none), got {v}"
                            ))
                        })?
                }
                other => {
                    return Err(invalid(format!(
                        "unknown config key `{other}` (known: time_scale, rapid_mm_min, \
                         jog_feed_mm_min, execution_log, status_interval_ms, travel, \
                         alarm_at_connect, switches, tool_lengths, tool)"
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

    /// How far the tip of physical tool `tool` reaches below the spindle, mm.
    pub fn tool_length(&self, tool: u32) -> f64 {
        self.tool_lengths.get(&tool).copied().unwrap_or(0.0)
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

/// The longest physical tool, mm.
const MAX_TOOL_LENGTH_MM: f64 = 1000.0;

/// `{"1": 50, "2": 62.5}`: tool number -> length, mm.
fn tool_lengths(v: &Value) -> Result<std::collections::BTreeMap<u32, f64>, PluginError> {
    let Value::Object(map) = v else {
        return Err(invalid(format!(
            "`tool_lengths` must be an object like {{\"1\": 50, \"2\": 62.5}}, got {v}"
        )));
    };
    let mut out = std::collections::BTreeMap::new();
    for (k, v) in map {
        let key = format!("tool_lengths.{k}");
        let tool: u32 = k
            .parse()
            .map_err(|_| invalid(format!("`{key}`: {k:?} is not a tool number")))?;
        let len = number(&key, v)?;
        if !(0.0..=MAX_TOOL_LENGTH_MM).contains(&len) {
            return Err(invalid(format!(
                "`{key}` must be 0 to {MAX_TOOL_LENGTH_MM} mm, got {len}"
            )));
        }
        out.insert(tool, len);
    }
    Ok(out)
}

/// `{"limit_x_max": {"axis": "x", "at_or_above": 95}, "probe": {"axis": "z", "at_or_below": -20}}`
fn switches(v: &Value) -> Result<Vec<Switch>, PluginError> {
    let Value::Object(map) = v else {
        return Err(invalid(format!(
            "`switches` must be an object like {{\"limit_x_max\": {{\"axis\": \"x\", \"at_or_above\": 95}}}}, got {v}"
        )));
    };
    let mut out = Vec::new();
    for (name, spec) in map {
        let key = format!("switches.{name}");
        if !io::is_input_name(name) {
            return Err(invalid(format!(
                "`{key}`: not an input name (estop, probe, door, limit, limit_x, limit_x_min, limit_x_max, ... for x, y, z, a)"
            )));
        }
        let Value::Object(spec) = spec else {
            return Err(invalid(format!(
                "`{key}` must be an object with `axis` and `at_or_above` or `at_or_below`, got {spec}"
            )));
        };
        if let Some(c) = circle(name, &key, spec)? {
            out.push(c);
            continue;
        }
        let mut axis = None;
        let mut at = None;
        let mut surface = [0.0; 3];
        for (k, v) in spec {
            let field = format!("{key}.{k}");
            match k.as_str() {
                "axis" => {
                    axis = Some(match v.as_str().map(str::to_ascii_lowercase).as_deref() {
                        Some("x") => Axis::X,
                        Some("y") => Axis::Y,
                        Some("z") => Axis::Z,
                        Some("a") => Axis::A,
                        _ => {
                            return Err(invalid(format!(
                                "`{field}` must be \"x\", \"y\", \"z\" or \"a\", got {v}"
                            )))
                        }
                    })
                }
                "at_or_above" | "at_or_below" if at.is_none() => {
                    at = Some((number(&field, v)?, k == "at_or_above"))
                }
                "at_or_above" | "at_or_below" => {
                    return Err(invalid(format!(
                        "`{key}`: give one of `at_or_above` and `at_or_below`"
                    )))
                }
                "slope_x" => surface[0] = number(&field, v)?,
                "slope_y" => surface[1] = number(&field, v)?,
                "slope_xy" => surface[2] = number(&field, v)?,
                other => {
                    return Err(invalid(format!(
                        "`{key}`: unknown key `{other}` (known: axis, at_or_above, at_or_below, \
                         slope_x, slope_y, slope_xy)"
                    )))
                }
            }
        }
        let axis = axis.ok_or_else(|| invalid(format!("`{key}.axis` is required")))?;
        let (at, above) =
            at.ok_or_else(|| invalid(format!("`{key}` needs `at_or_above` or `at_or_below`")))?;
        if axis != Axis::Z && surface != [0.0; 3] {
            return Err(invalid(format!(
                "`{key}`: a surface (`slope_x`, `slope_y`, `slope_xy`) is for a Z switch only"
            )));
        }
        // A surface steeper than 1:1 is no stock a probe could follow down.
        if surface.iter().any(|s| s.abs() > 1.0) {
            return Err(invalid(format!(
                "`{key}`: slopes must be between -1 and 1, got {surface:?}"
            )));
        }
        out.push(Switch {
            name: name.clone(),
            axis,
            at,
            above,
            surface,
            circle: None,
        });
    }
    Ok(out)
}

/// `{"bore": {"x", "y", "diameter"}}` or `{"boss": {"x", "y", "diameter", "top_z"}}` (the
/// probe only), or `None` for a level switch.
fn circle(
    name: &str,
    key: &str,
    spec: &serde_json::Map<String, Value>,
) -> Result<Option<Switch>, PluginError> {
    let (kind, v) = match (spec.get("bore"), spec.get("boss")) {
        (None, None) => return Ok(None),
        (Some(v), None) => ("bore", v),
        (None, Some(v)) => ("boss", v),
        (Some(_), Some(_)) => {
            return Err(invalid(format!("`{key}`: give one of `bore` and `boss`")))
        }
    };
    if name != io::PROBE {
        return Err(invalid(format!(
            "`{key}.{kind}`: only the probe can be a round wall"
        )));
    }
    if spec.len() != 1 {
        return Err(invalid(format!(
            "`{key}`: `{kind}` stands alone (no `axis`, `at_or_above`, ... beside it)"
        )));
    }
    let Value::Object(c) = v else {
        return Err(invalid(format!(
            "`{key}.{kind}` must be an object with `x`, `y` and `diameter`, got {v}"
        )));
    };
    let (mut x, mut y, mut d, mut top) = (None, None, None, None);
    for (k, v) in c {
        let field = format!("{key}.{kind}.{k}");
        let n = number(&field, v)?;
        match k.as_str() {
            "x" => x = Some(n),
            "y" => y = Some(n),
            "diameter" if n > 0.0 => d = Some(n),
            "diameter" => return Err(invalid(format!("`{field}` must be more than 0, got {n}"))),
            "top_z" if kind == "boss" => top = Some(n),
            other => {
                return Err(invalid(format!(
                    "`{key}.{kind}`: unknown key `{other}` (known: x, y, diameter{})",
                    if kind == "boss" { ", top_z" } else { "" }
                )))
            }
        }
    }
    let need = |v: Option<f64>, f: &str| {
        v.ok_or_else(|| invalid(format!("`{key}.{kind}.{f}` is required")))
    };
    Ok(Some(Switch {
        name: name.to_string(),
        axis: Axis::X,
        at: 0.0,
        above: true,
        surface: [0.0; 3],
        circle: Some(Circle {
            x: need(x, "x")?,
            y: need(y, "y")?,
            radius: need(d, "diameter")? / 2.0,
            bore: kind == "bore",
            top: if kind == "boss" {
                need(top, "top_z")?
            } else {
                f64::INFINITY
            },
        }),
    }))
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
        let c = Config::from_json(&json!({
            "switches": {"limit_x_max": {"axis": "X", "at_or_above": 95}, "probe": {"axis": "z", "at_or_below": -20}}
        }))
        .unwrap();
        let max = c.switches.iter().find(|s| s.name == "limit_x_max").unwrap();
        assert!(max.active_at(&[95.0, 0.0, 0.0, 0.0]) && !max.active_at(&[94.9, 0.0, 0.0, 0.0]));
        assert!(max.trips());
        let probe = c.switches.iter().find(|s| s.name == "probe").unwrap();
        assert!(probe.active_at(&[0.0, 0.0, -20.0, 0.0]) && !probe.trips());
        // A tilted, twisted surface under the probe.
        let c = Config::from_json(&json!({"switches": {"probe": {
            "axis": "z", "at_or_below": -1, "slope_x": 0.01, "slope_y": -0.02, "slope_xy": 0.001
        }}}))
        .unwrap();
        let probe = &c.switches[0];
        let level = -1.0 + 0.01 * 10.0 - 0.02 * 20.0 + 0.001 * 200.0;
        assert!((probe.level_at(&[10.0, 20.0, 0.0, 0.0]) - level).abs() < 1e-12);
        assert!(probe.active_at(&[10.0, 20.0, level, 0.0]));
        assert!(!probe.active_at(&[10.0, 20.0, level + 1e-9, 0.0]));
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
            (json!({"tool_lengths": {"x": 1}}), "tool_lengths.x"),
            (json!({"tool_lengths": {"2": -1}}), "tool_lengths.2"),
            (json!({"tool": -1}), "tool"),
            (
                json!({"switches": {"limit_q": {"axis": "x", "at_or_above": 1}}}),
                "switches.limit_q",
            ),
            (
                json!({"switches": {"probe": {"axis": "b", "at_or_above": 1}}}),
                "switches.probe.axis",
            ),
            (
                json!({"switches": {"probe": {"axis": "z"}}}),
                "switches.probe",
            ),
            (
                json!({"switches": {"probe": {"axis": "z", "at_or_above": "x"}}}),
                "switches.probe.at_or_above",
            ),
            (
                json!({"switches": {"probe": {"axis": "z", "at_or_below": 0, "slope_x": "1"}}}),
                "switches.probe.slope_x",
            ),
            (
                json!({"switches": {"limit_x": {"axis": "x", "at_or_above": 9, "slope_y": 0.1}}}),
                "switches.limit_x",
            ),
            (
                json!({"switches": {"probe": {"axis": "z", "at_or_below": 0, "slope_y": 2}}}),
                "switches.probe",
            ),
        ] {
            let e = Config::from_json(&cfg).unwrap_err();
            assert_eq!(e.code, "invalid_config");
            assert!(e.message.contains(key), "{key}: {}", e.message);
        }
    }

    /// A round probe wall: a bore is active from its radius out, a boss within it and at or
    /// below its top; refused for other switches, beside level keys, or without its fields.
    #[test]
    fn round_probe_walls_parse_and_refuse_what_does_not_fit() {
        let c = Config::from_json(
            &json!({"switches": {"probe": {"bore": {"x": 1, "y": 2, "diameter": 10}}}}),
        )
        .unwrap();
        let bore = &c.switches[0];
        assert!(!bore.active_at(&[1.0, 2.0, 0.0, 0.0]) && bore.active_at(&[6.0, 2.0, 0.0, 0.0]));
        let c = Config::from_json(&json!({"switches": {"probe": {"boss": {"x": 0, "y": 0, "diameter": 10, "top_z": -1}}}}))
            .unwrap();
        let boss = &c.switches[0];
        assert!(boss.active_at(&[4.0, 0.0, -2.0, 0.0]));
        assert!(!boss.active_at(&[4.0, 0.0, 0.0, 0.0]) && !boss.active_at(&[6.0, 0.0, -2.0, 0.0]));
        for (spec, key) in [
            (
                json!({"door": {"bore": {"x": 0, "y": 0, "diameter": 1}}}),
                "switches.door.bore",
            ),
            (
                json!({"probe": {"bore": {"x": 0, "y": 0, "diameter": 1}, "axis": "z"}}),
                "switches.probe",
            ),
            (
                json!({"probe": {"boss": {"x": 0, "y": 0, "diameter": 1}}}),
                "switches.probe.boss.top_z",
            ),
            (
                json!({"probe": {"bore": {"x": 0, "y": 0, "diameter": -1}}}),
                "switches.probe.bore.diameter",
            ),
        ] {
            let e = Config::from_json(&json!({"switches": spec})).unwrap_err();
            assert!(e.message.contains(key), "{key}: {}", e.message);
        }
    }
}

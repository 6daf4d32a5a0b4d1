//! The plugin's JSON configuration. Parsed by hand so every error names the offending key.

use crate::coils::{CoilMap, Excitation};
use crate::pins;
use crate::planner::{AxisLimits, Machine};
use crate::port::ScriptedInput;
use fresa_plugin_api::config_fields::{boolean, invalid, non_negative, number, object, positive};
use fresa_plugin_api::contract::{io, Axis};
use fresa_plugin_api::PluginError;
use serde_json::{Map, Value};
use std::path::PathBuf;
use std::time::Duration;

/// Where the outputs go.
#[derive(Debug, Clone, PartialEq)]
pub enum PortSpec {
    Sim,
    Ppdev(PathBuf),
}

/// What an input pin means when active.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum InputFunction {
    EStop,
    /// A limit switch: of one axis (`Some('X')`) or a chain shared by all, at one end
    /// (`Some(false)` min, `Some(true)` max) or covering both.
    Limit(Option<char>, Option<bool>),
    /// Shown only; never trips (a touch probe, a door switch).
    Probe,
    Door,
}

impl InputFunction {
    /// Parses a `function` value: `estop`, `probe`, `door`, `limit`, `limit_x`, `limit_x_min`,
    /// `limit_x_max`, ... for x, y, z.
    pub fn parse(s: &str) -> Option<InputFunction> {
        Some(match s {
            "estop" => InputFunction::EStop,
            "probe" => InputFunction::Probe,
            "door" => InputFunction::Door,
            "limit" => InputFunction::Limit(None, None),
            _ => {
                let rest = s.strip_prefix("limit_")?;
                let (axis, end) = rest.split_at(rest.len().min(1));
                let axis = match axis {
                    "x" => 'X',
                    "y" => 'Y',
                    "z" => 'Z',
                    _ => return None,
                };
                let end = match end {
                    "" => None,
                    "_min" => Some(false),
                    "_max" => Some(true),
                    _ => return None,
                };
                InputFunction::Limit(Some(axis), end)
            }
        })
    }

    /// The input's name in the machine status (the contract's `io` naming scheme).
    pub fn io_name(self) -> String {
        match self {
            InputFunction::EStop => io::ESTOP.into(),
            InputFunction::Probe => io::PROBE.into(),
            InputFunction::Door => io::DOOR.into(),
            InputFunction::Limit(None, _) => io::LIMIT.into(),
            InputFunction::Limit(Some(a), end) => {
                let axis = match a {
                    'X' => Axis::X,
                    'Y' => Axis::Y,
                    _ => Axis::Z,
                };
                io::limit(axis, end)
            }
        }
    }

    /// Whether the machine stops when this input becomes active.
    pub fn trips(self) -> bool {
        matches!(self, InputFunction::EStop | InputFunction::Limit(..))
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Input {
    pub pin: u8,
    pub function: InputFunction,
    /// Active when the pin is low (normally-closed switch to ground, pull-up).
    pub active_low: bool,
}

impl Input {
    pub fn describe(&self) -> String {
        match self.function {
            InputFunction::EStop => format!("e-stop (pin {})", self.pin),
            InputFunction::Limit(..) => {
                format!(
                    "limit switch {} (pin {})",
                    self.function.io_name(),
                    self.pin
                )
            }
            InputFunction::Probe | InputFunction::Door => {
                format!("{} (pin {})", self.function.io_name(), self.pin)
            }
        }
    }
}

#[derive(Debug, Clone, PartialEq)]
pub struct Config {
    pub port: PortSpec,
    pub machine: Machine,
    pub coils: [CoilMap; 2],
    /// Control pin of the tool lift, and whether "lifted" is the low level.
    pub lift_pin: u8,
    pub lift_invert: bool,
    pub idle_off: Duration,
    /// Below this much time to the next tick the loop spins instead of sleeping.
    pub spin: Duration,
    pub realtime_priority: bool,
    /// CPU the output thread is pinned to (`cpu`), if any.
    pub cpu: Option<usize>,
    pub inputs: Vec<Input>,
    /// How long an input's new level must hold before the status shows it (switch bounce).
    /// Trips do not wait for it: a limit or e-stop stops the motors in the tick that reads it.
    pub input_debounce: Duration,
    pub jog_feed_mm_min: f64,
    pub execution_log: Option<PathBuf>,
    pub status_interval: Duration,
    pub sim_inputs: Vec<ScriptedInput>,
}

fn pin_number(key: &str, v: &Value) -> Result<u8, PluginError> {
    v.as_u64()
        .and_then(|n| u8::try_from(n).ok())
        .ok_or_else(|| invalid(format!("`{key}` must be a pin number, got {v}")))
}

struct AxisConfig {
    limits: AxisLimits,
    coils: CoilMap,
}

fn axis(name: &str, v: Option<&Value>, default_bits: [u8; 4]) -> Result<AxisConfig, PluginError> {
    let mut turns_per_cm = 7.0;
    let mut steps_per_turn = 200.0;
    let mut steps_per_mm = None;
    let mut limits = AxisLimits {
        steps_per_mm: 0.0,
        max_rate: 500.0,
        start_rate: 100.0,
        accel: 2000.0,
    };
    let mut coils = CoilMap {
        excitation: Excitation::FullStep,
        bits: default_bits,
    };
    if let Some(v) = v {
        for (k, v) in object(&format!("axes.{name}"), v)? {
            let key = format!("axes.{name}.{k}");
            match k.as_str() {
                "steps_per_mm" => steps_per_mm = Some(positive(&key, v)?),
                "turns_per_cm" => turns_per_cm = positive(&key, v)?,
                "steps_per_turn" => steps_per_turn = positive(&key, v)?,
                "max_rate" => limits.max_rate = positive(&key, v)?,
                "start_rate" => limits.start_rate = positive(&key, v)?,
                "accel" => limits.accel = positive(&key, v)?,
                "excitation" => {
                    coils.excitation = v.as_str().and_then(Excitation::parse).ok_or_else(|| {
                        invalid(format!(
                            "`{key}` must be \"full_step\", \"wave\" or \"half_step\", got {v}"
                        ))
                    })?
                }
                "coil_bits" => {
                    let arr = v.as_array().filter(|a| a.len() == 4).ok_or_else(|| {
                        invalid(format!(
                            "`{key}` must be 4 data bits [A+, A-, B+, B-], e.g. [0,1,2,3], got {v}"
                        ))
                    })?;
                    for (i, b) in arr.iter().enumerate() {
                        coils.bits[i] = b
                            .as_u64()
                            .filter(|b| *b <= 7)
                            .map(|b| b as u8)
                            .ok_or_else(|| {
                                invalid(format!("`{key}[{i}]` must be a data bit 0..7, got {b}"))
                            })?;
                    }
                }
                _ => return Err(invalid(format!("unknown config key `{key}`"))),
            }
        }
    }
    limits.steps_per_mm = steps_per_mm.unwrap_or(turns_per_cm * steps_per_turn / 10.0);
    if limits.start_rate > limits.max_rate {
        return Err(invalid(format!(
            "`axes.{name}.start_rate` ({}) must not exceed `axes.{name}.max_rate` ({})",
            limits.start_rate, limits.max_rate
        )));
    }
    Ok(AxisConfig { limits, coils })
}

fn travel(v: &Value) -> Result<[Option<(f64, f64)>; 2], PluginError> {
    let t = fresa_plugin_api::kit::travel_from_json(v, &[Axis::X, Axis::Y])?;
    Ok([t[0], t[1]])
}

fn inputs(v: &Value) -> Result<Vec<Input>, PluginError> {
    let arr = v.as_array().ok_or_else(|| {
        invalid(format!(
            "`inputs` must be a list like [{{\"pin\":10,\"function\":\"limit_x\",\"active_low\":false}}], got {v}"
        ))
    })?;
    let mut out: Vec<Input> = Vec::new();
    for (i, item) in arr.iter().enumerate() {
        let obj = object(&format!("inputs[{i}]"), item)?;
        let mut pin = None;
        let mut function = None;
        let mut active_low = false;
        for (k, v) in obj {
            let key = format!("inputs[{i}].{k}");
            match k.as_str() {
                "pin" => {
                    let p = pin_number(&key, v)?;
                    if pins::input_bit(p).is_none() {
                        return Err(invalid(format!(
                            "`{key}`: {p} is not an input pin (10, 11, 12, 13 or 15)"
                        )));
                    }
                    pin = Some(p);
                }
                "function" => {
                    function = Some(v.as_str().and_then(InputFunction::parse).ok_or_else(|| {
                        invalid(format!(
                            "`{key}` must be \"estop\", \"probe\", \"door\", \"limit\", or \"limit_x\", \"limit_x_min\", \"limit_x_max\" (also for y and z), got {v}"
                        ))
                    })?)
                }
                "active_low" => active_low = boolean(&key, v)?,
                _ => return Err(invalid(format!("unknown config key `{key}`"))),
            }
        }
        let pin = pin.ok_or_else(|| invalid(format!("`inputs[{i}].pin` is required")))?;
        let function =
            function.ok_or_else(|| invalid(format!("`inputs[{i}].function` is required")))?;
        if out.iter().any(|o| o.pin == pin) {
            return Err(invalid(format!(
                "`inputs[{i}].pin`: pin {pin} is mapped twice"
            )));
        }
        out.push(Input {
            pin,
            function,
            active_low,
        });
    }
    Ok(out)
}

fn sim_inputs(v: &Value) -> Result<Vec<ScriptedInput>, PluginError> {
    let arr = v.as_array().ok_or_else(|| {
        invalid(format!(
            "`sim_inputs` must be a list like [{{\"after_writes\":200,\"pin\":10,\"level\":\"high\"}}], got {v}"
        ))
    })?;
    let mut out = Vec::new();
    for (i, item) in arr.iter().enumerate() {
        let obj = object(&format!("sim_inputs[{i}]"), item)?;
        let mut s = ScriptedInput {
            after_writes: 0,
            pin: 0,
            level: true,
        };
        for (k, v) in obj {
            let key = format!("sim_inputs[{i}].{k}");
            match k.as_str() {
                "after_writes" => {
                    s.after_writes = v
                        .as_u64()
                        .ok_or_else(|| invalid(format!("`{key}` must be a count, got {v}")))?
                }
                "pin" => {
                    s.pin = pin_number(&key, v)?;
                    if pins::input_bit(s.pin).is_none() {
                        return Err(invalid(format!("`{key}`: {} is not an input pin", s.pin)));
                    }
                }
                "level" => {
                    s.level = match v.as_str() {
                        Some("high") => true,
                        Some("low") => false,
                        _ => {
                            return Err(invalid(format!(
                                "`{key}` must be \"high\" or \"low\", got {v}"
                            )))
                        }
                    }
                }
                _ => return Err(invalid(format!("unknown config key `{key}`"))),
            }
        }
        if s.pin == 0 {
            return Err(invalid(format!("`sim_inputs[{i}].pin` is required")));
        }
        out.push(s);
    }
    Ok(out)
}

impl Config {
    pub fn from_json(value: &Value) -> Result<Config, PluginError> {
        let empty = Map::new();
        let obj = match value {
            Value::Null => &empty,
            Value::Object(o) => o,
            other => {
                return Err(invalid(format!(
                    "config must be a JSON object, got {other}"
                )))
            }
        };
        let mut port = None;
        let mut tick_hz = 20_000.0;
        let mut idle_off_ms = 15.0;
        // Spinning the whole period at SCHED_FIFO trips the kernel's real-time throttling (95 % of
        // each second by default) and stalls the loop for 50 ms (such a loop takes nice -20
        // instead, see `output::scheduling`, and then shares its CPU); 40 us still sleeps part of
        // every 50 us tick, and covers a stock kernel's wake-up latency (15-25 us measured on
        // a VM), so the tick starts on time (see the README's jitter measurements).
        let mut spin_us = 40.0;
        let mut realtime_priority = true;
        let mut cpu = None;
        let mut rapid_mm_min = 6000.0;
        let mut jog_feed_mm_min = 300.0;
        let mut execution_log = None;
        let mut status_interval_ms = 100.0;
        let mut travel_xy = [None; 2];
        let mut ins = Vec::new();
        let mut input_debounce_ms = 5.0;
        let mut sim = Vec::new();
        let mut lift_pin = 1u8;
        let mut lift_invert = false;
        let mut lift_above_mm = 0.0;
        let mut lift_settle_ms = 50.0;
        let mut axes_v: Option<&Map<String, Value>> = None;
        for (key, v) in obj {
            match key.as_str() {
                "port" => {
                    port = Some(match v.as_str() {
                        Some("sim") => PortSpec::Sim,
                        Some(p) if p.starts_with("/dev/") && cfg!(target_os = "linux") => {
                            PortSpec::Ppdev(PathBuf::from(p))
                        }
                        // Checked here so the machine is refused before anything is stored.
                        Some(p) if !cfg!(target_os = "linux") => {
                            return Err(invalid(format!(
                                "`port` {p:?}: a real parallel port is driven through Linux \
                                 ppdev, which this platform ({}) does not have; use \"sim\" or \
                                 run the server on Linux",
                                std::env::consts::OS
                            )))
                        }
                        _ => {
                            return Err(invalid(format!(
                        "`port` must be \"sim\" or a ppdev device like \"/dev/parport0\", got {v}"
                    )))
                        }
                    })
                }
                "tick_hz" => tick_hz = positive(key, v)?,
                "idle_off_ms" => idle_off_ms = positive(key, v)?,
                "spin_us" => spin_us = non_negative(key, v)?,
                "realtime_priority" => realtime_priority = boolean(key, v)?,
                "cpu" => {
                    cpu = match v {
                        Value::Null => None,
                        v => match v.as_u64() {
                            Some(n) if n < 1024 => Some(n as usize),
                            _ => {
                                return Err(invalid(format!(
                                    "`cpu` must be a CPU number from 0 to 1023 (or null), got {v}"
                                )))
                            }
                        },
                    }
                }
                "rapid_mm_min" => rapid_mm_min = positive(key, v)?,
                "jog_feed_mm_min" => jog_feed_mm_min = positive(key, v)?,
                "status_interval_ms" => status_interval_ms = non_negative(key, v)?,
                "execution_log" => match v {
                    Value::String(s) if !s.is_empty() => execution_log = Some(PathBuf::from(s)),
                    Value::Null => execution_log = None,
                    _ => {
                        return Err(invalid(format!(
                            "`execution_log` must be a file path, got {v}"
                        )))
                    }
                },
                "travel" => travel_xy = travel(v)?,
                "axes" => {
                    let o = object(key, v)?;
                    if let Some(k) = o.keys().find(|k| *k != "x" && *k != "y") {
                        return Err(invalid(format!(
                            "unknown key `axes.{k}` (the steppers are x and y; z is `z_lift`)"
                        )));
                    }
                    axes_v = Some(o);
                }
                "z_lift" => {
                    for (k, v) in object(key, v)? {
                        let key = format!("z_lift.{k}");
                        match k.as_str() {
                            "pin" => {
                                lift_pin = pin_number(&key, v)?;
                                if pins::output_bit(lift_pin).is_none() {
                                    return Err(invalid(format!(
                                        "`{key}`: {lift_pin} is not a control output pin (1, 14, 16 or 17)"
                                    )));
                                }
                            }
                            "invert" => lift_invert = boolean(&key, v)?,
                            "above_mm" => lift_above_mm = number(&key, v)?,
                            "settle_ms" => lift_settle_ms = non_negative(&key, v)?,
                            _ => return Err(invalid(format!("unknown config key `{key}`"))),
                        }
                    }
                }
                "inputs" => ins = inputs(v)?,
                "input_debounce_ms" => input_debounce_ms = non_negative(key, v)?,
                "sim_inputs" => sim = sim_inputs(v)?,
                _ => return Err(invalid(format!("unknown config key `{key}`"))),
            }
        }
        let port = port.ok_or_else(|| {
            invalid("`port` is required: \"sim\" or a ppdev device like \"/dev/parport0\"")
        })?;
        if !sim.is_empty() && port != PortSpec::Sim {
            return Err(invalid("`sim_inputs` only applies to `port: \"sim\"`"));
        }
        let x = axis("x", axes_v.and_then(|o| o.get("x")), [0, 1, 2, 3])?;
        let y = axis("y", axes_v.and_then(|o| o.get("y")), [4, 5, 6, 7])?;
        for (name, a) in [("x", &x), ("y", &y)] {
            if a.limits.max_rate > tick_hz / 2.0 {
                return Err(invalid(format!(
                    "`axes.{name}.max_rate` ({}) must be at most half of `tick_hz` ({tick_hz})",
                    a.limits.max_rate
                )));
            }
        }
        let mut seen = 0u8;
        for (name, a) in [("x", &x), ("y", &y)] {
            for b in a.coils.bits {
                if seen & (1 << b) != 0 {
                    return Err(invalid(format!(
                        "`axes.{name}.coil_bits`: data bit {b} is used twice"
                    )));
                }
                seen |= 1 << b;
            }
        }
        Ok(Config {
            port,
            machine: Machine {
                axes: [x.limits, y.limits],
                tick_hz,
                rapid_mm_min,
                lift_above_mm,
                lift_settle_ticks: (lift_settle_ms / 1000.0 * tick_hz).round() as u64,
                travel: travel_xy,
            },
            coils: [x.coils, y.coils],
            lift_pin,
            lift_invert,
            idle_off: Duration::from_secs_f64(idle_off_ms / 1000.0),
            spin: Duration::from_secs_f64(spin_us / 1e6),
            realtime_priority,
            cpu,
            inputs: ins,
            input_debounce: Duration::from_secs_f64(input_debounce_ms / 1000.0),
            jog_feed_mm_min,
            execution_log,
            status_interval: Duration::from_secs_f64(status_interval_ms / 1000.0),
            sim_inputs: sim,
        })
    }

    /// Input levels at which no input is active (the simulated port starts there).
    pub fn quiet_levels(&self) -> Vec<(u8, bool)> {
        self.inputs.iter().map(|i| (i.pin, i.active_low)).collect()
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use serde_json::json;

    #[test]
    fn defaults_follow_the_seed() {
        let c = Config::from_json(&json!({"port":"sim"})).unwrap();
        assert_eq!(c.machine.axes[0].steps_per_mm, 140.0);
        assert_eq!(c.coils[1].bits, [4, 5, 6, 7]);
        assert_eq!(c.idle_off, Duration::from_millis(15));
        assert_eq!(c.lift_pin, 1);
    }

    #[test]
    fn errors_name_the_key() {
        for (cfg, needle) in [
            (json!({}), "`port` is required"),
            (json!({"port":"lpt1"}), "`port`"),
            (
                json!({"port":"sim","axes":{"x":{"excitation":"micro"}}}),
                "axes.x.excitation",
            ),
            (
                json!({"port":"sim","axes":{"y":{"coil_bits":[0,1,2,3]}}}),
                "data bit 0 is used twice",
            ),
            (
                json!({"port":"sim","inputs":[{"pin":9,"function":"estop"}]}),
                "inputs[0].pin",
            ),
            (
                json!({"port":"sim","axes":{"x":{"max_rate":20000}}}),
                "axes.x.max_rate",
            ),
            (
                json!({"port":"sim","speed":1}),
                "unknown config key `speed`",
            ),
            (
                json!({"port":"/dev/parport0","sim_inputs":[{"pin":10}]}),
                "sim_inputs",
            ),
        ] {
            let e = Config::from_json(&cfg).unwrap_err();
            assert!(e.message.contains(needle), "{cfg}: {}", e.message);
        }
    }
}

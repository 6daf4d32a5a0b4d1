//! Limits the server enforces before anything reaches a backend: configured limits that are
//! sane, jogs inside them, MDI lines that parse and stay within any machine's reach. Travel
//! (per-axis soft limits) is the backend's to check, with one function for jogs, MDI and
//! programs (`fresa_plugin_api`'s backend kit); these bounds hold even where none is configured.

use crate::error::{Error, Result};
use crate::store::MachineRow;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Largest `max_jog_mm` a machine may be configured with: one jog request is a hand move.
pub const MAX_JOG_MM: f64 = 1000.0;
/// Largest `max_feed_mm_min`: well above any spindle machine's rapid rate.
pub const MAX_FEED_MM_MIN: f64 = 100_000.0;
/// Largest `max_probe_feed_mm_min`: a probe that trips stops from this feed, and faster
/// than this no probe or plate survives the overshoot.
pub const MAX_PROBE_FEED_MM_MIN: f64 = 2000.0;
/// `max_probe_feed_mm_min` when a machine is created without one.
pub const DEFAULT_PROBE_FEED_MM_MIN: f64 = 300.0;
/// No machine's work envelope reaches further from its origin than this (mm); a coordinate
/// beyond it is a typo or an attack (`G0 X1e30`), refused before any backend sees it. The
/// G-code interpreter's own bound, so MDI lines, uploads and `fresa gcode check` share one rule.
pub const MAX_COORDINATE_MM: f64 = fresa_gcode::MAX_COORDINATE_MM;
/// Longest MDI line accepted, bytes.
pub const MAX_MDI_LINE: usize = 256;
/// Most segments (moves, and arcs as 0.002 mm chords) one MDI line may make: a backend checks
/// all of an MDI line's moves before the first, so it holds them (a circle of 1 m radius is
/// about 1,600 chords).
pub const MAX_MDI_SEGMENTS: u64 = 1_000_000;

/// Widest feed and spindle override a machine may be configured to allow, percent.
pub const MAX_FEED_OVERRIDE: f64 = 300.0;
pub const MAX_SPINDLE_OVERRIDE: f64 = 200.0;

/// The overrides an operator may set on one machine, percent (`override_limits` of the
/// machine; a rapid override goes up to 100, the machine's rapid rate). Fields left out when
/// the machine is created take these defaults.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(default, deny_unknown_fields)]
pub struct OverrideLimits {
    pub feed_min: f64,
    pub feed_max: f64,
    pub spindle_min: f64,
    pub spindle_max: f64,
    pub rapid_min: f64,
}

impl Default for OverrideLimits {
    fn default() -> Self {
        OverrideLimits {
            feed_min: 10.0,
            feed_max: 200.0,
            spindle_min: 50.0,
            spindle_max: 150.0,
            rapid_min: 25.0,
        }
    }
}

impl OverrideLimits {
    pub fn of(row: &MachineRow) -> OverrideLimits {
        OverrideLimits {
            feed_min: row.feed_override_min,
            feed_max: row.feed_override_max,
            spindle_min: row.spindle_override_min,
            spindle_max: row.spindle_override_max,
            rapid_min: row.rapid_override_min,
        }
    }

    /// Each range holds 100 % and lies inside what any machine may allow.
    pub fn check_configured(&self) -> Result<()> {
        let ranges = [
            ("feed", self.feed_min, self.feed_max, MAX_FEED_OVERRIDE),
            (
                "spindle",
                self.spindle_min,
                self.spindle_max,
                MAX_SPINDLE_OVERRIDE,
            ),
            ("rapid", self.rapid_min, 100.0, 100.0),
        ];
        for (name, min, max, ceiling) in ranges {
            if !(min.is_finite() && min > 0.0 && min <= 100.0) {
                return Err(Error::invalid(
                    "invalid_field",
                    format!(
                        "field `override_limits.{name}_min` must be above 0 and at most 100 (%), got {min}"
                    ),
                ));
            }
            if !(max.is_finite() && (100.0..=ceiling).contains(&max)) {
                return Err(Error::invalid(
                    "invalid_field",
                    format!(
                        "field `override_limits.{name}_max` must be from 100 to {ceiling} (%), got {max}"
                    ),
                ));
            }
        }
        Ok(())
    }

    /// The overrides a `set_overrides` asks for, each inside this machine's range.
    pub fn check(&self, feed: Option<f64>, spindle: Option<f64>, rapid: Option<f64>) -> Result<()> {
        if feed.is_none() && spindle.is_none() && rapid.is_none() {
            return Err(Error::invalid(
                "invalid_field",
                "give at least one of `feed`, `spindle` and `rapid` (percent)",
            ));
        }
        let asked = [
            ("feed", feed, self.feed_min, self.feed_max),
            ("spindle", spindle, self.spindle_min, self.spindle_max),
            ("rapid", rapid, self.rapid_min, 100.0),
        ];
        for (name, v, min, max) in asked {
            let Some(v) = v else { continue };
            if !(v.is_finite() && (min..=max).contains(&v)) {
                return Err(Error::invalid(
                    "override_out_of_range",
                    format!(
                        "field `{name}`: {v} % is outside this machine's {name} override range, \
                         {min} to {max} %"
                    ),
                ));
            }
        }
        Ok(())
    }
}

/// A configured limit: finite, positive and at most `max`, or an error naming the field.
pub fn check_configured(field: &str, value: f64, max: f64) -> Result<f64> {
    if !(value.is_finite() && value > 0.0 && value <= max) {
        return Err(Error::invalid(
            "invalid_field",
            format!("field `{field}` must be a positive number of at most {max}, got {value}"),
        ));
    }
    Ok(value)
}

/// Config keys whose value is a file a backend writes (its execution log or journal).
pub const BACKEND_FILE_KEYS: [&str; 2] = ["execution_log", "journal"];

/// Files a backend writes stay inside the data directory: whoever may add a machine must not
/// make the server append to any file it can reach. A relative name is placed in the data
/// directory; the config is rewritten with the full path the backend gets.
pub fn confine_backend_files(config: &mut serde_json::Value, data_dir: &Path) -> Result<()> {
    use std::path::Component;
    let Some(obj) = config.as_object_mut() else {
        return Ok(());
    };
    for key in BACKEND_FILE_KEYS {
        let Some(v) = obj.get(key) else { continue };
        let Some(given) = v.as_str() else {
            // Not a path: the backend names its own type error.
            continue;
        };
        let path = Path::new(given);
        let outside = || {
            Error::invalid(
                "invalid_field",
                format!(
                    "field `config.{key}`: {given:?} is outside the data directory {}; backend files live there (give a file name, e.g. \"mill.log\")",
                    data_dir.display()
                ),
            )
        };
        if path.components().any(|c| matches!(c, Component::ParentDir)) {
            return Err(outside());
        }
        let full = if path.is_absolute() {
            path.to_path_buf()
        } else {
            data_dir.join(path)
        };
        if !full.starts_with(data_dir) {
            return Err(outside());
        }
        obj.insert(key.into(), serde_json::json!(full));
    }
    Ok(())
}

/// One jog against the machine's configured limits.
pub fn check_jog(row: &MachineRow, distance: f64, feed: Option<f64>) -> Result<()> {
    if !distance.is_finite() || distance == 0.0 {
        return Err(Error::invalid(
            "invalid_field",
            format!("field `distance` must be a non-zero number, got {distance}"),
        ));
    }
    if distance.abs() > row.max_jog_mm {
        return Err(Error::invalid(
            "jog_too_far",
            format!(
                "field `distance`: {distance} mm exceeds this machine's jog limit of {} mm per request",
                row.max_jog_mm
            ),
        ));
    }
    if let Some(f) = feed {
        if !(f.is_finite() && f > 0.0 && f <= row.max_feed_mm_min) {
            return Err(Error::invalid(
                "feed_out_of_range",
                format!(
                    "field `feed`: {f} mm/min is outside 0..{} mm/min",
                    row.max_feed_mm_min
                ),
            ));
        }
    }
    Ok(())
}

/// One non-empty G-code line the interpreter accepts (what the backend will check again). The
/// interpreter refuses every target, centre and offset beyond [`MAX_COORDINATE_MM`], and
/// dwells, feeds and speeds beyond its limits, naming the word.
pub fn check_mdi_line(line: &str) -> std::result::Result<(), String> {
    if line.trim().is_empty() {
        return Err("an MDI line must not be empty".into());
    }
    if line.contains(['\n', '\r']) {
        return Err("an MDI line must be one line (no line breaks)".into());
    }
    if line.len() > MAX_MDI_LINE {
        return Err(format!(
            "an MDI line is at most {MAX_MDI_LINE} bytes, got {}",
            line.len()
        ));
    }
    let interp = fresa_gcode::Interpreter::new(line.as_bytes(), fresa_gcode::Config::default());
    let budget = fresa_gcode::WorkBudget::new(MAX_MDI_SEGMENTS, 0.002);
    // The reader refuses coordinates beyond MAX_COORDINATE_MM (and A beyond as many degrees).
    for motion in fresa_gcode::budgeted(interp, budget) {
        motion.map_err(|e| format!("{line:?}: column {}: {}", e.column, e.message))?;
    }
    Ok(())
}

/// A command request body (`{"command": "zero", "axis": "X"}`) as the HTTP API and the MQTT
/// command topics take it: a field the command does not have is an error, not ignored (a
/// misspelt `axis` must not zero every axis).
pub fn parse_command(raw: &serde_json::Value) -> Result<fresa_plugin_api::contract::Command> {
    use fresa_plugin_api::contract::Command;
    let cmd: Command = serde_json::from_value(raw.clone()).map_err(|e| {
        Error::invalid(
            "invalid_command",
            format!("{e} (commands: cycle_start, feed_hold, resume, stop, reset, home, zero, go_to_zero, select_offset, set_output, toggle_output)"),
        )
    })?;
    let known = serde_json::to_value(cmd).unwrap_or_default();
    if let (Some(given), Some(known)) = (raw.as_object(), known.as_object()) {
        if let Some(extra) = given.keys().find(|k| !known.contains_key(*k)) {
            return Err(Error::invalid(
                "invalid_command",
                format!(
                    "unknown field `{extra}` for command {:?} (its fields: {})",
                    known["command"].as_str().unwrap_or_default(),
                    known.keys().cloned().collect::<Vec<_>>().join(", ")
                ),
            ));
        }
    }
    Ok(cmd)
}

/// A probing move's distance (at most `max_jog_mm`) and feed (more than 0, at most
/// `max_probe_feed_mm_min`), for every operation that probes.
pub fn check_probe(row: &MachineRow, distance: f64, feed: f64) -> Result<()> {
    if distance > row.max_jog_mm {
        return Err(Error::invalid(
            "probe_too_far",
            format!(
                "field `distance`: {distance} mm exceeds this machine's limit of {} mm per \
                 move (`max_jog_mm`)",
                row.max_jog_mm
            ),
        ));
    }
    if !(feed.is_finite() && feed > 0.0 && feed <= row.max_probe_feed_mm_min) {
        return Err(Error::invalid(
            "feed_out_of_range",
            format!(
                "field `feed`: {feed} mm/min is outside 0..{} mm/min (the machine's \
                 `max_probe_feed_mm_min`)",
                row.max_probe_feed_mm_min
            ),
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn huge_and_non_finite_limits_are_refused() {
        for v in [1e308, f64::NAN, f64::INFINITY, 0.0, -1.0, 1000.5] {
            assert!(
                check_configured("max_jog_mm", v, MAX_JOG_MM).is_err(),
                "{v}"
            );
        }
        assert_eq!(
            check_configured("max_jog_mm", 1000.0, MAX_JOG_MM).ok(),
            Some(1000.0)
        );
    }

    #[test]
    fn backend_files_stay_in_the_data_directory() {
        let dir = Path::new("/var/lib/fresa");
        let mut c = serde_json::json!({"execution_log": "mill.log", "time_scale": 1.0});
        assert!(confine_backend_files(&mut c, dir).is_ok());
        assert_eq!(c["execution_log"], "/var/lib/fresa/mill.log");
        let mut c = serde_json::json!({"execution_log": "/var/lib/fresa/logs/a.log"});
        assert!(confine_backend_files(&mut c, dir).is_ok());
        for bad in [
            "/etc/passwd",
            "../x.log",
            "/var/lib/fresa/../../etc/x",
            "/var/lib/fresa2/x",
        ] {
            let mut c = serde_json::json!({"journal": bad});
            let e = confine_backend_files(&mut c, dir)
                .err()
                .map(|e| e.message)
                .unwrap_or_default();
            assert!(e.contains("config.journal"), "{bad}: {e}");
        }
    }

    #[test]
    fn mdi_coordinates_beyond_reach_are_refused_naming_the_axis() {
        // G-code has no exponents: `1e30` is X1 and an E word, refused as such.
        let e = check_mdi_line("G0 X1e30").err().unwrap_or_default();
        assert!(e.contains("column 6"), "{e}");
        let e = check_mdi_line("G0 X2000000").err().unwrap_or_default();
        assert!(e.contains("X=2000000"), "{e}");
        let e = check_mdi_line("G91 G1 Y-2000000 F100")
            .err()
            .unwrap_or_default();
        assert!(e.contains("Y="), "{e}");
        assert!(check_mdi_line("G0 X100 Y-50 Z5").is_ok());
        let e = check_mdi_line("G0 A2000000").err().unwrap_or_default();
        assert!(e.contains("A=2000000"), "{e}");
        assert!(check_mdi_line("G0 A90").is_ok());
        // Half a billion chords from one short line: refused before any are made.
        let e = check_mdi_line("G2 X0 Y0 I400000 J0 P10000 F100")
            .err()
            .unwrap_or_default();
        assert!(e.contains("work budget exceeded"), "{e}");
        // Expression results: overflow, huge values, dwells and nesting.
        let e = check_mdi_line("G0 X[10**300*10**300]")
            .err()
            .unwrap_or_default();
        assert!(
            e.contains("column 13") && e.contains("not a finite number"),
            "{e}"
        );
        let e = check_mdi_line("G0 X[10**300]").err().unwrap_or_default();
        assert!(e.contains("X=1e300") && e.contains("1000000"), "{e}");
        let e = check_mdi_line("G4 P[10**300]").err().unwrap_or_default();
        assert!(e.contains("column 4") && e.contains("86400 s"), "{e}");
        let deep = format!("G0 X{}1{}", "[".repeat(100), "]".repeat(100));
        let e = check_mdi_line(&deep).err().unwrap_or_default();
        assert!(e.contains("column 69") && e.contains("64 levels"), "{e}");
    }
}

//! The Mach3 OEM codes the adapter uses, compiled in (transcribed from the project's
//! `mach3-oem-codes.csv` and `mach3-oem.md`). A machine's config may override any of them by
//! name (`"codes": {"resume": 1000}`), for screen sets or Mach3 versions that differ.

use serde_json::Value;

/// What a code addresses in Mach3.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    Button,
    Dro,
    Led,
}

/// Every code the adapter uses, by role. The discriminant indexes [`TABLE`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Code {
    CycleStart,
    FeedHold,
    Rewind,
    Stop,
    Resume,
    ZeroAll,
    /// Zero X; Y..C follow (`ZeroX + axis`).
    ZeroX,
    GoToZero,
    Reset,
    HomeAll,
    /// Ref X; Y..C follow.
    RefX,
    /// X position (work coordinates); Y..C follow.
    PosX,
    Elapsed,
    Estimate,
    Line,
    Feed,
    MotionMode,
    FeedOverride,
    Tool,
    /// Fixture (work) offset X of the active fixture; Y..C follow.
    FixtureX,
    FixtureNumber,
    EstopLed,
    RunningLed,
    PausedLed,
    MovingLed,
    IncrementalLed,
    FloodOn,
    FloodOff,
    // --- machine I/O (issue 18) ---
    MistOn,
    MistOff,
    SpindleCwLed,
    SpindleCcwLed,
    FloodLed,
    MistLed,
    LimitXMaxLed,
    LimitXMinLed,
    LimitYMaxLed,
    LimitYMinLed,
    LimitZMaxLed,
    LimitZMinLed,
    // --- overrides (issue 26) and probing (issue 25) ---
    SpindleOverride,
    RapidOverride,
    RapidOverrideToggle,
    RapidOverrideLed,
    ProbeLed,
}

/// `(role, config name, kind, default code, meaning)`.
pub const TABLE: &[(Code, &str, Kind, i16, &str)] = &[
    (
        Code::CycleStart,
        "cycle_start",
        Kind::Button,
        1000,
        "Cycle start",
    ),
    (
        Code::FeedHold,
        "feed_hold",
        Kind::Button,
        1001,
        "Pause (feed hold)",
    ),
    (Code::Rewind, "rewind", Kind::Button, 1002, "Rewind"),
    (Code::Stop, "stop", Kind::Button, 1003, "Stop"),
    (Code::Resume, "resume", Kind::Button, 1005, "Resume"),
    (Code::ZeroAll, "zero_all", Kind::Button, 1007, "Zero all"),
    (
        Code::ZeroX,
        "zero_x",
        Kind::Button,
        1008,
        "Zero X (Y..C = +1..+5)",
    ),
    (Code::GoToZero, "go_to_zero", Kind::Button, 1017, "GotoZs"),
    (Code::Reset, "reset", Kind::Button, 1021, "Reset: a toggle"),
    (Code::HomeAll, "home_all", Kind::Button, 105, "Ref all home"),
    (
        Code::RefX,
        "ref_x",
        Kind::Button,
        1022,
        "Ref X (Y..C = +1..+5)",
    ),
    (Code::PosX, "dro_x", Kind::Dro, 800, "X DRO (Y..C = +1..+5)"),
    (Code::Elapsed, "dro_elapsed", Kind::Dro, 814, "Elapsed"),
    (Code::Estimate, "dro_estimate", Kind::Dro, 815, "Estimate"),
    (
        Code::Line,
        "dro_line",
        Kind::Dro,
        816,
        "Current line number",
    ),
    (Code::Feed, "dro_feed", Kind::Dro, 818, "Feed rate"),
    (
        Code::MotionMode,
        "dro_motion_mode",
        Kind::Dro,
        819,
        "Motion mode (G0, G1, ...)",
    ),
    (
        Code::FeedOverride,
        "dro_feed_override",
        Kind::Dro,
        821,
        "Feed override %",
    ),
    (Code::Tool, "dro_tool", Kind::Dro, 824, "Tool number"),
    (
        Code::FixtureX,
        "dro_fixture_x",
        Kind::Dro,
        830,
        "X fixture offset (Y..C = +1..+5)",
    ),
    (
        Code::FixtureNumber,
        "dro_fixture_number",
        Kind::Dro,
        46,
        "Current fixture number (1 = G54)",
    ),
    (
        Code::EstopLed,
        "led_estop",
        Kind::Led,
        800,
        "Reset / e-stop latched",
    ),
    (
        Code::RunningLed,
        "led_running",
        Kind::Led,
        804,
        "Program running",
    ),
    (
        Code::PausedLed,
        "led_paused",
        Kind::Led,
        805,
        "Paused (feed hold)",
    ),
    (
        Code::MovingLed,
        "led_moving",
        Kind::Led,
        999,
        "System moving",
    ),
    // Not in the project's code table (its LED rows were unreadable). The Mach3 plugin SDK's
    // `Mach3Led.h` names OEM LED 48 "Abs Coordinate Mode" and 49 "Incremental Coordinate
    // Mode", and Mach3 macros restore G91 when LED 48 is out: 49 is the G91 lamp.
    (
        Code::IncrementalLed,
        "led_incremental",
        Kind::Led,
        49,
        "G91 (incremental) active",
    ),
    (Code::FloodOn, "flood_on", Kind::Button, 224, "Flood ON"),
    (Code::FloodOff, "flood_off", Kind::Button, 225, "Flood OFF"),
    (Code::MistOn, "mist_on", Kind::Button, 226, "Mist ON"),
    (Code::MistOff, "mist_off", Kind::Button, 227, "Mist OFF"),
    // The LEDs below carry the machine's I/O lamps. The project's code table has no LED rows
    // for them, so these defaults follow the OEM LED numbers of Mach3's standard screen sets as
    // far as we know them, NOT a verified source: check each on the installation (Mach3's
    // Diagnostics page shows the same lamps) and override any that differ by name.
    (
        Code::SpindleCwLed,
        "led_spindle_cw",
        Kind::Led,
        11,
        "Spindle on, clockwise",
    ),
    (
        Code::SpindleCcwLed,
        "led_spindle_ccw",
        Kind::Led,
        12,
        "Spindle on, counter-clockwise",
    ),
    (
        Code::FloodLed,
        "led_flood",
        Kind::Led,
        13,
        "Flood coolant on",
    ),
    (Code::MistLed, "led_mist", Kind::Led, 14, "Mist coolant on"),
    (
        Code::LimitXMaxLed,
        "led_limit_x_max",
        Kind::Led,
        36,
        "X++ limit switch active",
    ),
    (
        Code::LimitXMinLed,
        "led_limit_x_min",
        Kind::Led,
        37,
        "X-- limit switch active",
    ),
    (
        Code::LimitYMaxLed,
        "led_limit_y_max",
        Kind::Led,
        38,
        "Y++ limit switch active",
    ),
    (
        Code::LimitYMinLed,
        "led_limit_y_min",
        Kind::Led,
        39,
        "Y-- limit switch active",
    ),
    (
        Code::LimitZMaxLed,
        "led_limit_z_max",
        Kind::Led,
        40,
        "Z++ limit switch active",
    ),
    (
        Code::LimitZMinLed,
        "led_limit_z_min",
        Kind::Led,
        41,
        "Z-- limit switch active",
    ),
    (
        Code::SpindleOverride,
        "dro_spindle_override",
        Kind::Dro,
        74,
        "Spindle Speed Override %",
    ),
    (
        Code::RapidOverride,
        "dro_rapid_override",
        Kind::Dro,
        223,
        "Rapid Override % (in force only while rapid override is toggled on)",
    ),
    (
        Code::RapidOverrideToggle,
        "rapid_override_toggle",
        Kind::Button,
        287,
        "Toggle override of rapid feeds",
    ),
    // Not in the project's code table (no LED rows): the Mach3 plugin SDK's `Mach3Led.h` names
    // OEM LED 109 "Rapids being overridden" and 825 "Digitise In" (the probe input; Mach3
    // probing macros check it before G31).
    (
        Code::RapidOverrideLed,
        "led_rapid_override",
        Kind::Led,
        109,
        "Rapids being overridden (button 287 on)",
    ),
    (
        Code::ProbeLed,
        "led_probe",
        Kind::Led,
        825,
        "Probe (digitise) input active",
    ),
];

/// The LEDs that are the machine's inputs and outputs in its status: (role, status name, is
/// an output). `spindle` itself is CW or CCW lit; `spindle_ccw` is the CCW LED.
pub const IO_LEDS: &[(Code, &str, bool)] = &[
    (Code::SpindleCwLed, "spindle_cw", true),
    (Code::SpindleCcwLed, "spindle_ccw", true),
    (Code::FloodLed, "coolant_flood", true),
    (Code::MistLed, "coolant_mist", true),
    (Code::LimitXMaxLed, "limit_x_max", false),
    (Code::LimitXMinLed, "limit_x_min", false),
    (Code::LimitYMaxLed, "limit_y_max", false),
    (Code::LimitYMinLed, "limit_y_min", false),
    (Code::LimitZMaxLed, "limit_z_max", false),
    (Code::LimitZMinLed, "limit_z_min", false),
    (Code::ProbeLed, "probe", false),
];

/// The codes of one machine: the defaults with its config overrides applied.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Codes {
    values: Vec<i16>,
}

impl Default for Codes {
    fn default() -> Self {
        Codes {
            values: TABLE.iter().map(|row| row.3).collect(),
        }
    }
}

impl Codes {
    pub fn get(&self, code: Code) -> i16 {
        self.values[code as usize]
    }

    /// `base` plus an axis index, for the X..C families (zero, ref, DROs).
    pub fn axis(&self, base: Code, axis: usize) -> i16 {
        self.get(base).saturating_add(axis as i16)
    }

    /// Applies `{"name": code, ...}`; an unknown name or a non-`short` value is an error that
    /// names it.
    pub fn with_overrides(overrides: &Value) -> Result<Codes, String> {
        let mut codes = Codes::default();
        let obj = overrides
            .as_object()
            .ok_or_else(|| format!("`codes` must be an object of name: code, got {overrides}"))?;
        for (name, v) in obj {
            let Some(row) = TABLE.iter().position(|row| row.1 == name) else {
                let known: Vec<&str> = TABLE.iter().map(|row| row.1).collect();
                return Err(format!(
                    "unknown key `codes.{name}` (known: {})",
                    known.join(", ")
                ));
            };
            let code = v
                .as_i64()
                .and_then(|n| i16::try_from(n).ok())
                .filter(|n| *n >= 0)
                .ok_or_else(|| format!("`codes.{name}` must be a Mach3 code 0..32767, got {v}"))?;
            codes.values[row] = code;
        }
        Ok(codes)
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use serde_json::json;

    #[test]
    fn table_is_indexed_by_role() {
        for (i, row) in TABLE.iter().enumerate() {
            assert_eq!(row.0 as usize, i, "{}", row.1);
        }
        let c = Codes::default();
        assert_eq!(c.get(Code::Reset), 1021);
        assert_eq!(c.axis(Code::ZeroX, 2), 1010);
        assert_eq!(c.axis(Code::FixtureX, 3), 833);
    }

    #[test]
    fn overrides_apply_and_errors_name_the_key() {
        let c = Codes::with_overrides(&json!({"resume": 1000})).unwrap();
        assert_eq!(c.get(Code::Resume), 1000);
        assert_eq!(c.get(Code::CycleStart), 1000);
        let e = Codes::with_overrides(&json!({"resum": 1000})).unwrap_err();
        assert!(e.contains("codes.resum"), "{e}");
        let e = Codes::with_overrides(&json!({"resume": 70000})).unwrap_err();
        assert!(e.contains("codes.resume"), "{e}");
    }
}

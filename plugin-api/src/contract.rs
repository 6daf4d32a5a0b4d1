//! The machine-backend contract: the JSON requests the host sends with `call`, the responses it
//! expects, and the events a backend emits through the host table. Typed here so Rust plugins and
//! the server share one definition; C plugins read the same shapes from the README.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Axes every machine exposes (absent axes simply never move).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Axis {
    X,
    Y,
    Z,
    A,
}

impl Axis {
    pub const ALL: [Axis; 4] = [Axis::X, Axis::Y, Axis::Z, Axis::A];

    pub fn index(self) -> usize {
        match self {
            Axis::X => 0,
            Axis::Y => 1,
            Axis::Z => 2,
            Axis::A => 3,
        }
    }

    pub fn letter(self) -> char {
        ['X', 'Y', 'Z', 'A'][self.index()]
    }
}

/// One value per axis, serialised as `{"x":..,"y":..,"z":..,"a":..}`.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct AxisValues {
    #[serde(default)]
    pub x: f64,
    #[serde(default)]
    pub y: f64,
    #[serde(default)]
    pub z: f64,
    #[serde(default)]
    pub a: f64,
}

impl AxisValues {
    pub fn from_array(v: [f64; 4]) -> Self {
        AxisValues {
            x: v[0],
            y: v[1],
            z: v[2],
            a: v[3],
        }
    }
    pub fn to_array(self) -> [f64; 4] {
        [self.x, self.y, self.z, self.a]
    }
    pub fn get(&self, axis: Axis) -> f64 {
        self.to_array()[axis.index()]
    }
    pub fn set(&mut self, axis: Axis, value: f64) {
        let mut v = self.to_array();
        v[axis.index()] = value;
        *self = AxisValues::from_array(v);
    }
}

/// The six work coordinate systems.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
pub enum WorkOffset {
    #[default]
    G54,
    G55,
    G56,
    G57,
    G58,
    G59,
}

impl WorkOffset {
    pub const ALL: [WorkOffset; 6] = [
        WorkOffset::G54,
        WorkOffset::G55,
        WorkOffset::G56,
        WorkOffset::G57,
        WorkOffset::G58,
        WorkOffset::G59,
    ];
    pub fn index(self) -> usize {
        self as usize
    }
    pub fn name(self) -> &'static str {
        ["G54", "G55", "G56", "G57", "G58", "G59"][self.index()]
    }
    pub fn parse(s: &str) -> Option<Self> {
        WorkOffset::ALL
            .into_iter()
            .find(|o| o.name().eq_ignore_ascii_case(s))
    }
}

/// What a machine is doing, as far as the backend can tell.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum MachineState {
    /// No link to the controller; `MachineStatus::reason` says why.
    #[default]
    Offline,
    Idle,
    Jogging,
    Homing,
    Running,
    Paused,
    /// Latched fault (e-stop, limit, reset needed); `MachineStatus::alarm` says which.
    Alarm,
    /// The backend stopped answering calls. Set only by the host, never by a backend: what
    /// the machine does is unknown, so it is not reported as busy or idle.
    Unresponsive,
}

impl MachineState {
    pub const ALL: [MachineState; 8] = [
        MachineState::Offline,
        MachineState::Idle,
        MachineState::Jogging,
        MachineState::Homing,
        MachineState::Running,
        MachineState::Paused,
        MachineState::Alarm,
        MachineState::Unresponsive,
    ];

    /// The state's wire name (`"idle"`, `"running"`, ...), for messages and logs.
    pub fn as_str(self) -> &'static str {
        match self {
            MachineState::Offline => "offline",
            MachineState::Idle => "idle",
            MachineState::Jogging => "jogging",
            MachineState::Homing => "homing",
            MachineState::Running => "running",
            MachineState::Paused => "paused",
            MachineState::Alarm => "alarm",
            MachineState::Unresponsive => "unresponsive",
        }
    }

    /// States in which the machine is moving or may move without a new command.
    pub fn is_busy(self) -> bool {
        matches!(
            self,
            MachineState::Jogging
                | MachineState::Homing
                | MachineState::Running
                | MachineState::Paused
        )
    }
}

/// A snapshot of the machine, reported by `status` and by `status` events.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MachineStatus {
    pub state: MachineState,
    pub machine_position: AxisValues,
    pub work_position: AxisValues,
    /// Current programmed feed, mm/min.
    pub feed: f64,
    /// Feed override in percent (100 = programmed feed).
    #[serde(default = "hundred")]
    pub feed_override: f64,
    /// Spindle speed override in percent (100 = programmed speed).
    #[serde(default = "hundred")]
    pub spindle_override: f64,
    /// Rapid (G0) override in percent (100 = the machine's rapid rate).
    #[serde(default = "hundred")]
    pub rapid_override: f64,
    pub active_offset: WorkOffset,
    /// Run being executed, as given in `load_program`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub run: Option<i64>,
    /// Source line being executed (1-based).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub line: Option<u32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub alarm: Option<String>,
    /// Why the machine is offline, when it is.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    // --- machine I/O additions (issue 18) ---
    /// The inputs the backend supports, by [`io`] name: `true` active (switch pressed),
    /// `null` supported but not known right now. A name that is absent is not supported, so
    /// "unknown" is never shown as "off". Empty from backends that report no inputs (and from
    /// plugins built before this field existed).
    #[serde(default)]
    pub inputs: BTreeMap<String, Option<bool>>,
    /// The outputs the backend supports, by [`io`] name, with the same rules: booleans for
    /// switches (`spindle`, `coolant_flood`, ...), numbers where the backend has them
    /// (`spindle_rpm`).
    #[serde(default)]
    #[cfg_attr(feature = "openapi", schema(value_type = Object))]
    pub outputs: BTreeMap<String, Option<IoValue>>,
    // --- pause reason additions (issue 26) ---
    /// Why the machine holds, while its state is `paused` (and while it jogs during a
    /// tool-change hold). Absent otherwise, and from backends that do not say.
    /// (Boxed: most statuses have none, and events carrying a status stay small.)
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hold: Option<Box<Hold>>,
}

/// The value of an output: a switch or a number (e.g. spindle rpm).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum IoValue {
    On(bool),
    Number(f64),
}

/// The stable names of machine inputs and outputs in [`MachineStatus`]. Limits are
/// `limit_<axis>_min` / `limit_<axis>_max` for a switch at one end, `limit_<axis>` for one
/// switch (or a series chain) covering both ends of an axis, and `limit` for a chain shared by
/// every axis.
pub mod io {
    use super::Axis;

    pub const ESTOP: &str = "estop";
    pub const PROBE: &str = "probe";
    pub const DOOR: &str = "door";
    pub const LIMIT: &str = "limit";

    pub const SPINDLE: &str = "spindle";
    /// `true` while the spindle turns counter-clockwise (M4); `false` clockwise.
    pub const SPINDLE_CCW: &str = "spindle_ccw";
    pub const SPINDLE_RPM: &str = "spindle_rpm";
    pub const COOLANT_FLOOD: &str = "coolant_flood";
    pub const COOLANT_MIST: &str = "coolant_mist";
    pub const Z_LIFT: &str = "z_lift";

    /// `limit_x`, `limit_x_min` (`end` = `Some(false)`), `limit_x_max` (`Some(true)`).
    pub fn limit(axis: Axis, end: Option<bool>) -> String {
        let a = axis.letter().to_ascii_lowercase();
        match end {
            None => format!("limit_{a}"),
            Some(false) => format!("limit_{a}_min"),
            Some(true) => format!("limit_{a}_max"),
        }
    }

    /// Whether `name` follows the naming scheme (inputs): `estop`, `probe`, `door`, `limit`,
    /// `limit_<x|y|z|a>` with an optional `_min` / `_max`.
    pub fn is_input_name(name: &str) -> bool {
        if matches!(name, ESTOP | PROBE | DOOR | LIMIT) {
            return true;
        }
        let Some(rest) = name.strip_prefix("limit_") else {
            return false;
        };
        let (axis, end) = rest.split_at(rest.len().min(1));
        matches!(axis, "x" | "y" | "z" | "a") && matches!(end, "" | "_min" | "_max")
    }
}

fn hundred() -> f64 {
    100.0
}

impl Default for MachineStatus {
    fn default() -> Self {
        MachineStatus {
            state: MachineState::default(),
            machine_position: AxisValues::default(),
            work_position: AxisValues::default(),
            feed: 0.0,
            feed_override: hundred(),
            spindle_override: hundred(),
            rapid_override: hundred(),
            active_offset: WorkOffset::default(),
            run: None,
            line: None,
            alarm: None,
            reason: None,
            inputs: BTreeMap::new(),
            outputs: BTreeMap::new(),
            hold: None,
        }
    }
}

// ---- pause reasons and tool changes (issue 26) ----------------------------------------------

/// Why a machine holds (see [`MachineStatus::hold`]).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Hold {
    pub kind: HoldKind,
    /// What happened, in words for the operator, e.g. `M0 at line 12: change clamp`.
    pub message: String,
    /// The program line that held the run (M0, M1, M6).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub line: Option<u32>,
    /// The program's own `(MSG, ...)` text on that line.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub program_message: Option<String>,
    /// What the operator does to go on: `cycle_start` after a program stop or a tool change
    /// (the program asked for the operator), `resume` after a feed hold or a pause.
    pub continue_with: ContinueWith,
    /// Kind `tool_change`: which tools, and how the new one's length applies.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tool_change: Option<ToolChangeHold>,
    /// Set by the host, never by a backend: why going on is refused right now (e.g. the
    /// database is unavailable, and a run only goes on once it can be recorded).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub blocked: Option<String>,
}

/// What held the machine.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum HoldKind {
    /// M0 in the program.
    ProgramPause,
    /// M1 in the program, with the machine's optional stop on.
    OptionalStop,
    /// M6: a manual tool change (see [`ToolChangeHold`]).
    ToolChange,
    /// A feed hold (the command, a pendant's Pause key without a run).
    FeedHold,
    /// The run was paused (`POST /jobs/{id}/pause`, a pendant's Pause key).
    Pause,
    /// Set by the host: the pendant that started the run was lost (`stop_program_on_lost`).
    PendantLost,
}

impl HoldKind {
    /// The kind's wire name.
    pub fn as_str(self) -> &'static str {
        match self {
            HoldKind::ProgramPause => "program_pause",
            HoldKind::OptionalStop => "optional_stop",
            HoldKind::ToolChange => "tool_change",
            HoldKind::FeedHold => "feed_hold",
            HoldKind::Pause => "pause",
            HoldKind::PendantLost => "pendant_lost",
        }
    }
}

/// The button that applies to a hold (see [`Hold::continue_with`]).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ContinueWith {
    CycleStart,
    Resume,
}

/// A manual tool change the run holds for.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ToolChangeHold {
    /// The tool in the spindle before the change, when the backend knows it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub from: Option<u32>,
    /// The tool the program asks for (its last `T` word).
    pub to: u32,
    /// G43 (tool length compensation) is in force: at cycle start the new tool's length from
    /// the tool table takes the old one's place. Otherwise the program runs on the work offset
    /// alone, and a new tool's length difference is taken up by the work offset's Z (the host's
    /// tool setter does that).
    #[serde(default)]
    pub length_compensation: bool,
    /// Set by the host: the tool table's descriptions of `from` and `to`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub from_description: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub to_description: Option<String>,
}

/// How a run holds at M6 (see [`Request::LoadProgram`]'s `tool_change`).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct ToolChangeSetup {
    /// Machine position to go to for the change: Z first (up to its Z, at the current X Y),
    /// then X and Y. A does not move. Absent: the machine stays where M6 found it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub position: Option<AxisValues>,
}

/// Immediate machine commands. Serialised with a `command` tag, e.g. `{"command":"zero","axis":"X"}`.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "command", rename_all = "snake_case", deny_unknown_fields)]
pub enum Command {
    CycleStart,
    FeedHold,
    Resume,
    Stop,
    Reset,
    /// Home (reference) one axis, or all when `axis` is absent.
    Home {
        #[serde(default)]
        axis: Option<Axis>,
    },
    /// Set the active work offset so the work position of one axis (or all) becomes zero.
    Zero {
        #[serde(default)]
        axis: Option<Axis>,
    },
    /// Move to work zero (Z first to a safe height, then XY/A, then Z down).
    GoToZero,
    /// Make this work offset the active one.
    SelectOffset {
        offset: WorkOffset,
    },
    // --- parport-stepper additions (issue 7) ---
    /// Switch a named digital output on or off, e.g.
    /// `{"command":"set_output","name":"z_lift","on":true}`. Refused while the machine moves.
    SetOutput {
        name: OutputName,
        on: bool,
    },
    // --- pendant macro additions (issue 4) ---
    /// Flip a named digital output, e.g. `{"command":"toggle_output","name":"spindle"}`.
    /// Answer: `{"output": name, "on": bool}` (the new state) where the backend knows it.
    ToggleOutput {
        name: OutputName,
    },
    // --- run control additions (issue 26) ---
    /// Set the feed, spindle and/or rapid override, in percent of the programmed value; an
    /// absent one is left as it is, e.g. `{"command":"set_overrides","feed":50}`. Applies to
    /// program and MDI moves from the next planning interval on, also during a run (jogs and
    /// probing moves keep their own feeds). The host has already checked each against the
    /// machine's range. Answer: `{}`; the status reports the values in force.
    SetOverrides {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        feed: Option<f64>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        spindle: Option<f64>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        rapid: Option<f64>,
    },
}

/// The three overrides in force, in percent.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Overrides {
    pub feed: f64,
    pub spindle: f64,
    pub rapid: f64,
}

impl Default for Overrides {
    fn default() -> Self {
        Overrides {
            feed: 100.0,
            spindle: 100.0,
            rapid: 100.0,
        }
    }
}

impl Overrides {
    /// These overrides with the ones a `set_overrides` command gives replaced.
    pub fn with(self, feed: Option<f64>, spindle: Option<f64>, rapid: Option<f64>) -> Overrides {
        Overrides {
            feed: feed.unwrap_or(self.feed),
            spindle: spindle.unwrap_or(self.spindle),
            rapid: rapid.unwrap_or(self.rapid),
        }
    }
}

/// Digital outputs a backend may expose to `Command::SetOutput`.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OutputName {
    /// The tool lift (Z up/down) of a machine whose Z is not interpolated.
    ZLift,
    // --- pendant macro additions (issue 4) ---
    /// Spindle on (clockwise) / off.
    Spindle,
    /// Flood coolant on / off.
    Coolant,
}

impl OutputName {
    /// The output's wire name (`"z_lift"`, `"spindle"`, `"coolant"`), for messages.
    pub fn as_str(self) -> &'static str {
        match self {
            OutputName::ZLift => "z_lift",
            OutputName::Spindle => "spindle",
            OutputName::Coolant => "coolant",
        }
    }
}

/// Program run control.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RunAction {
    Start,
    Pause,
    Resume,
    Cancel,
}

/// A request the host sends a machine backend. Serialised with an `op` tag.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "op", rename_all = "snake_case")]
// `load_program` carries the most (tools, preamble, height map): one request is made per call
// and never kept in bulk, so boxing its fields would only add allocations.
#[allow(clippy::large_enum_variant)]
pub enum Request {
    /// Open the link to the controller (idempotent). Answer: `MachineStatus`.
    Connect,
    /// Answer: `MachineStatus`.
    Status,
    /// Incremental jog. The host has already bounded distance and feed. Answer: `{}`.
    Jog {
        axis: Axis,
        distance: f64,
        /// mm/min; the backend's default jog feed when absent.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        feed: Option<f64>,
    },
    /// Answer: `{}` (or `{"offsets": OffsetTable}` after zeroing).
    Command(Command),
    /// Answer: `OffsetTable`.
    GetOffsets,
    /// Answer: `{}`.
    SetOffset {
        offset: WorkOffset,
        values: AxisValues,
    },
    /// Load a program file (UTF-8 G-code) to run from `start_line` (1-based) under run id `run`.
    /// Answer: `{"lines": total, "start_line": actual}`; a backend that knows it already executed
    /// lines of this run (idempotent resume) may start later than asked and says so.
    LoadProgram {
        run: i64,
        path: String,
        start_line: u32,
        /// The part zero the run started with, when resuming it: a backend whose controller
        /// reports its own part zero refuses to start (code `part_zero_changed`) if the
        /// reported one differs. Absent on a first start or an operator-confirmed resume.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        expected_part_zero: Option<AxisValues>,
        /// The machine's tool table (Fresa's database): what G41/G42 `D<n>` offset by. A
        /// backend that interprets the program itself uses it, so it runs the path the upload
        /// check validated. Absent: no tools.
        #[serde(default, skip_serializing_if = "Vec::is_empty")]
        tools: Vec<ProgramTool>,
        /// The work budget: most segments (moves, and arcs as chords) the program may linearise
        /// to; a backend that interprets it refuses more (`work_budget_exceeded`, naming the
        /// line) before any motion. Absent: the backend's default (`DEFAULT_MAX_SEGMENTS`).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        max_segments: Option<u64>,
        // --- tool change and pause additions (issue 26) ---
        /// The machine's optional stop switch: on, M1 holds the run like M0; absent (off), M1
        /// is passed over.
        #[serde(default, skip_serializing_if = "std::ops::Not::not")]
        optional_stop: bool,
        /// M6 holds the run for a manual tool change (spindle off, to the change position,
        /// jogging and probing allowed; cycle start goes back to where it held and on; see
        /// the README). Absent: M6 passes and the backend changes nothing.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        tool_change: Option<ToolChangeSetup>,
        /// A run that goes on from `start_line` inside the program (a start at a line, a
        /// resume): what the backend does before that line's first motion (see [`Preamble`]).
        /// A backend that does it says so in its answer (`"preamble": true`); one that cannot
        /// do it safely refuses with `unsupported` and the reason.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        preamble: Option<Preamble>,
        // --- height map additions (issue 25) ---
        /// A height map to apply: every move's Z gets the map's correction under it, moves
        /// split where they cross grid lines (see [`crate::heightmap`]); in the program's work
        /// coordinates. A backend that applies it says so in its answer
        /// ([`ProgramLoaded::height_map`]); one that cannot refuses with `unsupported`, naming
        /// why. Absent: no correction.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        height_map: Option<crate::heightmap::HeightMap>,
    },
    /// Answer: `{}`.
    Run { action: RunAction },
    /// The host is about to destroy the instance: stop motion, close links. Answer: `{}`.
    Shutdown,
    // --- kawasaki-as additions (issue 6) ---
    /// A named file the backend generates for the operator, e.g. `as-program` (the controller
    /// program of a robot backend). Answer: `{"content_type": "...", "file_name"?: "...",
    /// "body": "..."}`. Errors: `unknown_artifact` (this backend has none of that name),
    /// `not_available` (not in the current configuration).
    GetArtifact { name: String },
    // --- pendant macro additions (issue 4) ---
    /// Execute one MDI line (no newline), e.g. `{"op":"mdi","line":"G91 G0 Z5"}`. The backend
    /// validates it before any motion and leaves the controller's modal state (distance mode,
    /// motion mode, feed, work offset) as it found it. Answer: `{}`. Errors: `invalid_gcode`,
    /// `unsupported` (the backend cannot run MDI, or not this kind of line).
    Mdi { line: String },
    // --- estimate additions (issue 26) ---
    /// How this machine moves, for run-time estimates. Answer: [`MotionProfile`]. Errors:
    /// `unsupported` (the host then assumes rapids at 5000 mm/min and no acceleration).
    MotionProfile,
    // --- probing additions (issue 25) ---
    /// A probing move (G38.2-G38.5): see [`Probe`]. Answer: `{}` once it is queued (checked
    /// against the travel for its whole distance, refused with `probe_already_in_state` when
    /// the probe already reads what it looks for); the outcome comes later as a
    /// [`Event::ProbeEnded`] with the same `id`. Errors: `unsupported` (no probe, or not on
    /// that axis, with the reason), `out_of_travel`, `busy`, `alarm`.
    Probe(Probe),
    // --- tool change additions (issue 26) ---
    /// The machine's tool table changed (e.g. a tool measured during a tool-change hold): use
    /// it from now on, in the run in progress too (G43 H, and the length a tool change under
    /// G43 takes). Answer: `{}`. Errors: `unsupported`.
    SetTools { tools: Vec<ProgramTool> },
}

impl Request {
    /// Decodes a request from the host; a malformed or unknown one is an `invalid_request` error
    /// that says what serde found wrong.
    ///
    /// An operation this build of the contract does not know (a newer host's `op` or
    /// `command`) is `unsupported`, as an operation the backend does not implement is: a plugin
    /// built against an older contract then answers a new operation the way the host expects.
    pub fn from_json(request: serde_json::Value) -> Result<Request, crate::PluginError> {
        serde_json::from_value(request.clone()).map_err(|e| refused(&request, &e))
    }

    /// [`Request::from_json`] straight from the bytes of a call, with no `Value` in between
    /// (one is parsed only to explain a refusal).
    pub fn from_slice(request: &[u8]) -> Result<Request, crate::PluginError> {
        serde_json::from_slice(request).map_err(|e| {
            let parsed = serde_json::from_slice(request).unwrap_or(serde_json::Value::Null);
            refused(&parsed, &e)
        })
    }
}

/// Why a request was not decoded: `unsupported` when serde's complaint is exactly that the
/// request's `op` (or its command's `command`) is a variant this contract does not have,
/// otherwise `invalid_request` with serde's own words.
fn refused(request: &serde_json::Value, e: &serde_json::Error) -> crate::PluginError {
    let op = request.get("op").and_then(serde_json::Value::as_str);
    let name = match op {
        Some("command") => request.get("command").and_then(serde_json::Value::as_str),
        other => other,
    };
    match name {
        Some(name)
            if e.to_string()
                .starts_with(&format!("unknown variant `{name}`")) =>
        {
            crate::PluginError::new(
                "unsupported",
                format!(
                    "this machine backend does not know `{name}` (it was built against an \
                     older plugin contract)"
                ),
            )
        }
        _ => crate::PluginError::invalid(format!("invalid request: {e}")),
    }
}

/// How a machine moves, as far as a run-time estimate needs it (answer to `motion_profile`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MotionProfile {
    /// G0 speed, mm/min.
    pub rapid_mm_min: f64,
    /// Lowest feed the machine runs, mm/min (lower programmed feeds are raised); 0: none.
    #[serde(default)]
    pub min_feed_mm_min: f64,
    /// Highest feed the machine runs, mm/min (higher programmed feeds are capped); 0: none.
    #[serde(default)]
    pub max_feed_mm_min: f64,
    /// Path acceleration, mm/s²; 0: speed changes at once.
    #[serde(default)]
    pub accel_mm_s2: f64,
    /// The largest step in an axis's speed a corner may make without slowing, mm/s; 0: the
    /// machine stops at every corner (with acceleration).
    #[serde(default)]
    pub corner_jump_mm_s: f64,
    /// The limits above are each axis's, not the path's: a diagonal straight move runs at the
    /// limits divided by the largest share any one axis makes of it (a step generator whose
    /// axes run at their own rates). False: path limits.
    #[serde(default)]
    pub per_axis: bool,
}

/// A probing move: `axis` moves by `distance` (signed: its sign is the direction) at `feed`
/// mm/min until the probe input reads `until`; then motion stops at once and the position where
/// the input changed is reported. The distance ending first is `not_tripped`, not a fault (the
/// host decides what that means: G38.2 fails, G38.3 goes on).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Probe {
    /// The host's number for this probe, repeated in its [`Event::ProbeEnded`].
    pub id: u64,
    pub axis: Axis,
    pub distance: f64,
    pub feed: f64,
    #[serde(default)]
    pub until: ProbeUntil,
}

/// What a probing move waits for (G38.2/.3 contact, G38.4/.5 release).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ProbeUntil {
    /// The probe input becomes active (the tool touches the plate).
    #[default]
    Contact,
    /// The probe input becomes inactive (the tool leaves it).
    Release,
}

impl ProbeUntil {
    /// The input level that ends the move.
    pub fn wants_active(self) -> bool {
        self == ProbeUntil::Contact
    }
}

/// How a probing move ended (see [`Event::ProbeEnded`]).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ProbeOutcome {
    /// The input changed: `trip` is where.
    Tripped,
    /// The whole distance ran with no change.
    NotTripped,
    /// Stop, feed hold or shutdown ended it first.
    Stopped,
    /// A fault ended it (an alarm, a limit); `message` says which.
    Failed,
}

/// Answer to `run` and `command cycle_start`: `{}`, or `{"part_zero": ...}` from a backend
/// whose controller reports its part zero when a run starts (the host stores it with the run).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct RunAnswer {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub part_zero: Option<AxisValues>,
}

/// Answer to `get_artifact`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Artifact {
    pub content_type: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub file_name: Option<String>,
    pub body: String,
}

/// Work offsets G54..G59, in the order of `WorkOffset::ALL`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
pub struct OffsetTable {
    pub active: WorkOffset,
    pub offsets: Vec<(WorkOffset, AxisValues)>,
}

/// One tool of [`Request::LoadProgram`]'s table, millimetres (the same shape as
/// `fresa_gcode::Tool`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ProgramTool {
    pub tool: u32,
    pub diameter_mm: f64,
    #[serde(default)]
    pub length_mm: f64,
}

/// Answer to `load_program`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ProgramLoaded {
    pub lines: u32,
    pub start_line: u32,
    /// The backend will carry out the request's preamble before `start_line` (absent: it
    /// got none, or does not know preambles and ignored it).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub preamble: bool,
    /// The height map sent with the program is applied (issue 25). A backend built before
    /// height maps ignores the field it does not know and leaves this out, so the host, seeing
    /// no confirmation, refuses to start rather than cut uncorrected.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub height_map: bool,
}

impl ProgramLoaded {
    /// A program of `lines` lines loaded to start at `start_line`, with no preamble and no
    /// height map.
    pub fn new(lines: u32, start_line: u32) -> ProgramLoaded {
        ProgramLoaded {
            lines,
            start_line,
            preamble: false,
            height_map: false,
        }
    }
}

/// Events a machine backend emits. Serialised with an `event` tag.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "event", rename_all = "snake_case")]
pub enum Event {
    /// The status changed. Backends may emit freely; the host rate-limits what it forwards.
    Status(MachineStatus),
    /// Every motion of `line` of run `run` has been executed.
    LineAcknowledged { run: i64, line: u32 },
    StateChanged {
        from: MachineState,
        to: MachineState,
    },
    Alarm {
        message: String,
        /// The input that tripped it (an [`io`] name), when an input did.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        input: Option<String>,
    },
    /// Run `run` finished: `completed`, `failed` (with `message`) or `cancelled`.
    RunEnded {
        run: i64,
        outcome: RunOutcome,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        message: Option<String>,
    },
    // --- parport-stepper additions (issue 7) ---
    /// Process monitor, once per executed program line that moved: the largest distance (mm)
    /// between the stepped path and the programmed path of `line`, and the run's progress by
    /// planned time. Transient: the host forwards it, it does not store it.
    LineReport {
        run: i64,
        line: u32,
        max_deviation_mm: f64,
        /// Planned motion time done, 0..100.
        percent: f64,
        /// Planned motion time left, seconds (pauses not counted).
        remaining_s: f64,
    },
    // --- probing additions (issue 25) ---
    /// Probing move `id` ended. `trip` is the machine position latched when the input changed
    /// (only with `tripped`); `position` is where motion came to rest (past the trip by the
    /// stopping distance, the overshoot). Emitted after the machine's state has left
    /// `jogging`, so the host may act on the machine at once.
    ProbeEnded {
        id: u64,
        outcome: ProbeOutcome,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        trip: Option<AxisValues>,
        position: AxisValues,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        message: Option<String>,
    },
    // --- kawasaki-as additions (issue 6) ---
    /// The controller reported its part zero (machine/robot base coordinates), e.g. at the
    /// start of a run. The host stores it in the part-zero history with source `robot`.
    PartZeroReported {
        values: AxisValues,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        run: Option<i64>,
    },
}

// --- start at a line additions (issue 26) ---

/// What a backend does before the first motion of a run that goes on from inside a program
/// (`load_program`'s `start_line` > 1): the host has interpreted the lines before it without
/// motion and planned how to bring the machine to that line's state and start point. The
/// backend's own interpreter rebuilds the rest of the modal state from the lines before (units,
/// distance modes, feed, G92...); these steps are what it must do to the machine, in order.
/// Moves are straight, in machine coordinates, and checked against the travel with the rest of
/// the program before anything moves.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Preamble {
    /// The line it leads to. A backend that starts at another line (its execution log shows
    /// more of the run done) answers that line and refuses to start this preamble
    /// (`start_line_moved`): the host plans one for the new line and loads again.
    pub line: u32,
    /// The machine position it was planned from: a backend standing elsewhere refuses it
    /// (`machine_moved`).
    pub from: AxisValues,
    pub steps: Vec<PreambleStep>,
}

/// Most steps a [`Preamble`] may have (a host plans at most 6).
pub const MAX_PREAMBLE_STEPS: usize = 16;

/// One step of a [`Preamble`], tagged `step`, e.g. `{"step":"move","z":10}`.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "step", rename_all = "snake_case", deny_unknown_fields)]
pub enum PreambleStep {
    /// Make this work offset the active one (the program's at the line).
    Offset { offset: WorkOffset },
    /// Spindle as at the line (`off`, or turning at `rpm`).
    Spindle { direction: SpindleTurn, rpm: f64 },
    /// Coolant as at the line.
    Coolant { mist: bool, flood: bool },
    /// A straight move to these machine coordinates (an absent axis stays where it is), at
    /// `feed` mm/min, or at the rapid rate when absent.
    Move {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        x: Option<f64>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        y: Option<f64>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        z: Option<f64>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        a: Option<f64>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        feed: Option<f64>,
    },
}

impl PreambleStep {
    /// Where a move ends when it starts at machine position `from` (`None`: not a move).
    pub fn target(&self, from: [f64; 4]) -> Option<[f64; 4]> {
        match *self {
            PreambleStep::Move { x, y, z, a, .. } => {
                let to = [x, y, z, a];
                Some(std::array::from_fn(|i| to[i].unwrap_or(from[i])))
            }
            _ => None,
        }
    }
}

/// Which way the spindle turns (M3, M4) or that it stands (M5).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SpindleTurn {
    Cw,
    Ccw,
    Off,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RunOutcome {
    Completed,
    Failed,
    Cancelled,
}

// ---- Pendant transport (kind `pendant_transport`) -------------------------------------------
// A pendant transport instance speaks to one handwheel pendant. It never touches the store or the
// HTTP API: it reports what the operator did (events below) and the core decides what moves.

/// A key (or key combination) pressed on a pendant.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PendantKey {
    /// Zero every axis.
    Zero,
    ZeroX,
    ZeroY,
    ZeroZ,
    ZeroA,
    Reset,
    Stop,
    Rewind,
    Start,
    Pause,
    /// Go to work zero.
    Home,
    /// User macros (Fn + key); what they do is configured per pendant in the core.
    M1,
    M2,
    M3,
    M4,
}

/// Events a pendant transport emits. Serialised with an `event` tag.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "event", rename_all = "snake_case")]
pub enum PendantEvent {
    /// The link to the pendant is up (hello sent).
    Connected {
        address: String,
    },
    /// The link is down (closed, reset, or silent too long); the transport keeps reconnecting.
    Lost {
        reason: String,
    },
    /// The wheel turned: move `axis` by `count` (signed) x `step` in the machine's units.
    Jog {
        axis: Axis,
        count: i32,
        step: f64,
    },
    Key {
        key: PendantKey,
    },
    /// A program upload finished. The counts are what the pendant declared; the core checks them
    /// against `lines` and answers `confirm_upload` only once the job is stored.
    Upload {
        upload: u64,
        lines: Vec<String>,
        declared_lines: u64,
        declared_chars: u64,
    },
    /// An upload could not even be received (not text, too long, connection lost, no end).
    UploadFailed {
        reason: String,
    },
}

/// The longest status line a pendant's LCD shows (one line of its 20x4 display).
pub const PENDANT_STATUS_LINE: usize = 20;

/// Job progress for the pendant's display.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct PendantJob {
    pub elapsed_s: u64,
    pub estimated_s: u64,
    pub total_lines: u64,
    pub line: u64,
}

/// Requests the host sends a pendant transport. Serialised with an `op` tag.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "op", rename_all = "snake_case")]
pub enum PendantRequest {
    /// The status cache the pendant's position/progress polls are answered from. Answer: `{}`.
    PendantStatus {
        position: AxisValues,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        job: Option<PendantJob>,
        // --- pause reason additions (issue 26) ---
        /// One line for the pendant's LCD (ASCII, at most [`PENDANT_STATUS_LINE`]
        /// characters), e.g. `M0 change clamp` while a run holds; absent when there is
        /// nothing to say.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        status_line: Option<String>,
    },
    /// The upload was stored as a job: tell the pendant (N53). Answer: `{"sent": bool}`.
    ConfirmUpload { upload: u64 },
    /// Answer: `{"connected": bool, "address": "host:port"}`.
    LinkState,
    /// Only for an instance created with `{"discover": true}`: pendants seen on the LAN.
    /// Answer: `{"pendants": [{"name", "host", "addresses", "port", "address"}]}`.
    Discovered,
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use serde_json::json;

    #[test]
    fn a_malformed_request_is_an_invalid_request_naming_the_problem() {
        let e = Request::from_json(json!({"op": "fly"})).unwrap_err();
        assert_eq!(e.code, "unsupported");
        assert!(e.message.contains("fly"), "{e}");
        let e = Request::from_json(json!({"op": "command", "command": "fly"})).unwrap_err();
        assert_eq!(e.code, "unsupported");
        // A known operation with a field that is unknown or wrong is malformed.
        let e = Request::from_json(json!({"op": "command", "command": "home", "axis": "fly"}))
            .unwrap_err();
        assert_eq!(e.code, "invalid_request", "{e}");
        let e = Request::from_json(json!({"op": "jog", "axis": "Q", "distance": 1})).unwrap_err();
        assert!(e.message.contains('Q'), "{e}");
        assert_eq!(
            Request::from_json(json!({"op": "status"})).unwrap(),
            Request::Status
        );
    }

    #[test]
    fn state_names_are_the_wire_names() {
        for s in MachineState::ALL {
            assert_eq!(serde_json::to_value(s).unwrap(), json!(s.as_str()));
        }
        // The names the server and clients already know must never change.
        let names = MachineState::ALL.map(MachineState::as_str);
        assert_eq!(
            names,
            [
                "offline",
                "idle",
                "jogging",
                "homing",
                "running",
                "paused",
                "alarm",
                "unresponsive"
            ]
        );
        assert!(!MachineState::Unresponsive.is_busy());
    }

    #[test]
    fn requests_decode_from_bytes_like_from_values() {
        let bytes = br#"{"op":"jog","axis":"X","distance":1.5}"#;
        let v: serde_json::Value = serde_json::from_slice(bytes).unwrap();
        assert_eq!(
            Request::from_slice(bytes).unwrap(),
            Request::from_json(v).unwrap()
        );
        assert_eq!(
            Request::from_slice(b"{").unwrap_err().code,
            "invalid_request"
        );
    }

    #[test]
    fn command_wire_shape_matches_the_http_api() {
        let c: Command = serde_json::from_value(json!({"command":"zero","axis":"X"})).unwrap();
        assert_eq!(
            c,
            Command::Zero {
                axis: Some(Axis::X)
            }
        );
        let r = serde_json::to_value(Request::Command(Command::FeedHold)).unwrap();
        assert_eq!(r, json!({"op":"command","command":"feed_hold"}));
        let back: Request = serde_json::from_value(r).unwrap();
        assert_eq!(back, Request::Command(Command::FeedHold));
    }

    #[test]
    fn unknown_command_fields_are_rejected() {
        let e = serde_json::from_value::<Command>(json!({"command":"zero","axes":"X"}));
        assert!(e.is_err());
    }

    #[test]
    fn set_output_and_line_report_wire_shapes() {
        let c: Command =
            serde_json::from_value(json!({"command":"set_output","name":"z_lift","on":true}))
                .unwrap();
        assert_eq!(
            c,
            Command::SetOutput {
                name: OutputName::ZLift,
                on: true
            }
        );
        assert!(serde_json::from_value::<Command>(
            json!({"command":"set_output","name":"vacuum","on":true})
        )
        .is_err());
        let t: Command =
            serde_json::from_value(json!({"command":"toggle_output","name":"spindle"})).unwrap();
        assert_eq!(
            t,
            Command::ToggleOutput {
                name: OutputName::Spindle
            }
        );
        assert_eq!(
            serde_json::to_value(OutputName::Coolant).unwrap(),
            json!(OutputName::Coolant.as_str())
        );
        let mdi = serde_json::to_value(Request::Mdi {
            line: "G0 Z5".into(),
        })
        .unwrap();
        assert_eq!(mdi, json!({"op":"mdi","line":"G0 Z5"}));
        let e = Event::LineReport {
            run: 2,
            line: 5,
            max_deviation_mm: 0.25,
            percent: 50.0,
            remaining_s: 1.5,
        };
        let v = serde_json::to_value(&e).unwrap();
        assert_eq!(
            v,
            json!({"event":"line_report","run":2,"line":5,"max_deviation_mm":0.25,
                   "percent":50.0,"remaining_s":1.5})
        );
        assert_eq!(serde_json::from_value::<Event>(v).unwrap(), e);
    }

    #[test]
    fn events_round_trip() {
        let e = Event::LineAcknowledged { run: 3, line: 17 };
        let v = serde_json::to_value(&e).unwrap();
        assert_eq!(v, json!({"event":"line_acknowledged","run":3,"line":17}));
        assert_eq!(serde_json::from_value::<Event>(v).unwrap(), e);
    }
}

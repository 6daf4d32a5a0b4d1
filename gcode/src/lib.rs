//! # fresa-gcode
//!
//! G-code reader, modal interpreter, arc linearisation and program analysis for
//! 3-axis milling. No I/O of its own (it reads any [`std::io::BufRead`]), no async.
//!
//! * [`Interpreter`] streams canonical [`Motion`]s (millimetres, program
//!   coordinates, 1-based source line) from any reader, in constant memory.
//! * [`linearise`] turns arcs into chords within a tolerance with exact endpoints.
//! * [`analyse`] computes bounds, lengths and a feed-based run-time estimate.
//!
//! The dialect is the common ground of grbl and LinuxCNC plus LinuxCNC's
//! parameters, expressions, O-word control flow, canned cycles and G92/G52,
//! checked against LinuxCNC's `rs274` (tests/conformance.rs); see the crate
//! README for the full list of words and the rules that are applied.
//!
//! ```
//! use fresa_gcode::{analyse, linearise, AnalysisOptions, Config, Interpreter, Motion};
//!
//! let program = "G21 G90\nG0 X10 Y0\nG1 Z-1 F300\nG2 X-10 I-10 (half circle)\nM30\n";
//!
//! // Canonical motions: arcs stay arcs.
//! let motions: Vec<Motion> = Interpreter::new(program.as_bytes(), Config::default())
//!     .collect::<Result<_, _>>()?;
//! assert!(matches!(motions[2], Motion::Arc { line: 4, clockwise: true, .. }));
//!
//! // Arcs as chords within 0.002 mm; the last chord ends exactly at X-10.
//! let chords = linearise(Interpreter::new(program.as_bytes(), Config::default()), 0.002)
//!     .filter_map(Result::ok)
//!     .filter(|m| m.line() == 4)
//!     .count();
//! assert_eq!(chords as u64, fresa_gcode::segments_for(10.0, std::f64::consts::PI, 0.002));
//!
//! // Bounds, lengths and a feed-based time estimate in one streaming pass.
//! let a = analyse(program.as_bytes(), &AnalysisOptions::default())?;
//! let cut = a.cutting_bounds.unwrap();
//! assert_eq!((cut.min[1], cut.max[1]), (-10.0, 0.0)); // G2 goes through -Y
//!
//! // Errors name line and column.
//! let err = Interpreter::new("G0 X1\nG1 X2 Q3 F1\n".as_bytes(), Config::default())
//!     .find_map(Result::err)
//!     .unwrap();
//! assert_eq!((err.line, err.column), (2, 7));
//! # Ok::<(), fresa_gcode::GcodeError>(())
//! ```

#![forbid(unsafe_code)]

mod analysis;
mod arc;
mod comp;
mod estimate;
mod expr;
mod flow;
mod interp;
mod lex;

pub use analysis::{
    analyse, probe_spread, Analysis, AnalysisOptions, Bounds, OffsetChangeNote, ProbeSpread,
    RotaryBounds,
};
pub use arc::{
    budgeted, linearise, segments_for, segments_of, ArcGeometry, Budgeted, Linearise, WorkBudget,
    DEFAULT_MAX_SEGMENTS, MIN_TOLERANCE_MM,
};
pub use estimate::{Estimator, MotionProfile, TimeMark, TimeTable};
pub use interp::{
    FeedMode, Interpreter, ModalState, StartError, StartRefusal, StartRefusalReason, WorkOffsetSet,
};

// Input bounds: whatever a program says, it cannot make the reader recurse without end or put
// a number no machine can run into a motion. Each is an error naming line, column and limit.

/// Deepest nesting of one value: every `[`, `#` (parameter indirection) and unary sign that
/// holds a further value is one level (`#[#[1]]` is four, `ABS[ABS[1]]` two). LinuxCNC allows
/// a few dozen; real programs use a handful. Bounds the reader's stack use on any thread.
pub const MAX_EXPRESSION_DEPTH: usize = 64;
/// Most O-word blocks (`if`, `while`, `do`, `repeat`) open at once within one call level.
pub const MAX_BLOCK_NESTING: usize = 64;
/// No machine reaches further from its origin than this (mm; degrees for A): a coordinate,
/// arc centre or offset beyond it is a typo or an attack (`X[10**300]`), refused where the
/// program says it. The server's MDI and upload checks use the same bound.
pub const MAX_COORDINATE_MM: f64 = 1_000_000.0;
/// Longest dwell (G4 P, G82/G89 P), seconds: 24 h.
pub const MAX_DWELL_SECONDS: f64 = 86_400.0;
/// Largest F word in its own units after G20/G21 (mm/min; 1/min in G93, mm/rev in G95).
/// Far above any machine: a machine runs a faster feed at its own maximum, and programs do ask
/// for that (LinuxCNC's sample `3D_Chips.ngc` programs 2,250,000 mm/min).
pub const MAX_FEED: f64 = 100_000_000.0;
/// Largest S word (rpm).
pub const MAX_SPINDLE_RPM: f64 = 1_000_000.0;
/// Most events (messages, spindle, coolant, dwells, ...) that may wait behind the moves cutter
/// compensation holds until the next move: a loop of messages with no move would otherwise pile
/// them up without end (memory), and every line under compensation copies them (time).
pub const MAX_HELD_EVENTS: usize = 1000;

use serde::{Deserialize, Serialize};

/// X, Y, Z in millimetres.
pub type Point = [f64; 3];

/// Travel of the rotary A axis (degrees, program coordinates) during one
/// move. Moves carry it only when A changes, so a consumer without an A axis
/// refuses exactly the moves that need one. A moves linearly with the XYZ
/// path, start to end, as in LinuxCNC.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct RotaryMove {
    pub from: f64,
    pub to: f64,
}

impl RotaryMove {
    /// `Some` if A moves from `from` to `to`.
    #[inline]
    pub fn between(from: f64, to: f64) -> Option<Self> {
        (from != to).then_some(RotaryMove { from, to })
    }
}

/// What to do with words the interpreter does not implement (cutter
/// compensation, G10, B/C/U/V/W axes, probing, ...).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub enum Unsupported {
    /// Stop with a [`GcodeError`] naming line and column (default: never guess).
    #[default]
    Error,
    /// Skip the whole line, record a [`Warning`], and carry on. Motion that
    /// depends on the skipped line (e.g. the following lines of a canned
    /// cycle) is still rejected or skipped, never executed as something else.
    SkipWithWarning,
}

/// Interpreter settings. `Config::default()` is what grbl/LinuxCNC would do
/// with a 0.002 mm chord tolerance. (De)serialisable for settings files;
/// missing fields take their defaults.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct Config {
    /// Chord tolerance for [`linearise`] / [`Interpreter::linearised`] (mm).
    /// The interpreter and [`analyse`] keep arcs exact.
    pub arc_tolerance_mm: f64,
    /// Policy for unsupported words.
    pub unsupported: Unsupported,
    /// Stored position for G28, program coordinates in mm.
    pub g28_position: Point,
    /// Stored position for G30, program coordinates in mm.
    pub g30_position: Point,
    /// Position assumed before the first move (program coordinates, mm).
    pub initial_position: Point,
    /// A axis position assumed before the first move (degrees).
    pub initial_a_deg: f64,
    /// Machine-coordinate origin of G54..G59, G59.1..G59.3 (index 0..9), mm.
    /// Only used to convert G53 moves and work-system switches into program
    /// coordinates; all zeros (the default) means "same origin".
    pub work_offsets: [Point; 9],
    /// Skip lines starting with `/` (the block-delete switch is on). Default true.
    pub block_delete: bool,
    /// End the stream after M2/M30 (and after a closing `%`), as a controller
    /// does. Default true.
    pub stop_at_program_end: bool,
    /// IJK arcs: start/end radius difference above which the arc is always an
    /// error (grbl/LinuxCNC: 0.5 mm).
    pub arc_radius_max_error_mm: f64,
    /// IJK arcs: a difference above this AND above `arc_radius_rel_error` of the
    /// radius is an error (0.005 mm). R arcs: how much too small R may be to
    /// still be taken as a half circle.
    pub arc_radius_abs_tolerance_mm: f64,
    /// Relative radius tolerance (0.001 = 0.1 %).
    pub arc_radius_rel_error: f64,
    /// Largest arc radius accepted (mm); default 1e6 (1 km). Bounds the chords
    /// one arc can produce.
    pub max_arc_radius_mm: f64,
    /// Longest accepted line in bytes; keeps memory bounded on garbage input.
    pub max_line_bytes: usize,
    /// At most this many warnings are kept (the rest are counted).
    pub max_warnings: usize,
    /// Most nesting levels, the main program included (O-word `call`,
    /// `M98`); deeper is an error naming the line. Default 10, LinuxCNC's.
    pub max_call_depth: usize,
    /// Most loop passes (`while`, `do`, `repeat`, M98 `L`) and subroutine calls in one program;
    /// more is an error naming the line, so a runaway loop cannot hang an
    /// upload check. Default 10,000,000.
    pub max_loop_iterations: u64,
    /// Loops and calls need the program text again: from the first O-word
    /// or M98 on, the lines read are kept in memory, at most this many bytes
    /// (more is an error naming the line). Default 256 MiB.
    pub max_kept_program_bytes: usize,
    /// The machine's tool table: the radius for cutter compensation
    /// (`G41`/`G42` with `D`, or without `D` the tool in the spindle).
    /// Empty by default: a G41/G42 that needs a tool is then an error naming
    /// the line and the tool.
    pub tools: ToolTable,
    /// Where a probing move is taken to end when no machine gives its result
    /// back ([`Interpreter::probe_result`]): LinuxCNC's stand-alone
    /// assumption by default.
    pub probe_assumption: ProbeAssumption,
}

/// What the interpreter assumes a probing move found when no machine said
/// (an upload check). [`analysis::probe_spread`] runs both to see which moves
/// depend on a probe's result.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ProbeAssumption {
    /// No contact: the move ran its whole way and the tool rests 0.254 mm
    /// (0.01 in) back toward the start (LinuxCNC's rs274 stand-alone).
    #[default]
    NoContact,
    /// Contact at once: the trip and the rest are the start point (the other
    /// end of what a probe along the move can return).
    ContactAtStart,
}

/// One tool of a [`ToolTable`], millimetres.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Tool {
    /// Cutter diameter; cutter compensation offsets the path by half of it
    /// (a negative diameter offsets to the other side, as in LinuxCNC).
    pub diameter_mm: f64,
    /// Tool length offset (G43). Carried for the controller; program
    /// coordinates do not depend on it.
    #[serde(default)]
    pub length_mm: f64,
}

/// Tools by number (the `T` / `D` word).
pub type ToolTable = std::collections::BTreeMap<u32, Tool>;

/// A tool table from `(tool, diameter_mm, length_mm)` rows, as the store, the plugin contract
/// and tool files hold them.
pub fn tool_table(rows: impl IntoIterator<Item = (u32, f64, f64)>) -> ToolTable {
    rows.into_iter()
        .map(|(tool, diameter_mm, length_mm)| {
            (
                tool,
                Tool {
                    diameter_mm,
                    length_mm,
                },
            )
        })
        .collect()
}

impl Default for Config {
    fn default() -> Self {
        Config {
            arc_tolerance_mm: 0.002,
            unsupported: Unsupported::Error,
            g28_position: [0.0; 3],
            g30_position: [0.0; 3],
            initial_position: [0.0; 3],
            initial_a_deg: 0.0,
            work_offsets: [[0.0; 3]; 9],
            block_delete: true,
            stop_at_program_end: true,
            arc_radius_max_error_mm: 0.5,
            arc_radius_abs_tolerance_mm: 0.005,
            arc_radius_rel_error: 0.001,
            max_arc_radius_mm: 1e6,
            max_line_bytes: 64 * 1024,
            max_warnings: 1000,
            max_call_depth: 10,
            max_loop_iterations: 10_000_000,
            max_kept_program_bytes: 256 * 1024 * 1024,
            tools: ToolTable::new(),
            probe_assumption: ProbeAssumption::NoContact,
        }
    }
}

/// Arc plane (G17/G18/G19).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize)]
pub enum Plane {
    /// G17: X then Y, normal +Z.
    XY,
    /// G18: Z then X, normal +Y (grbl/LinuxCNC axis order).
    ZX,
    /// G19: Y then Z, normal +X.
    YZ,
}

impl Plane {
    /// Indices (first axis, second axis, normal/linear axis) into a [`Point`].
    /// Counter-clockwise is the positive rotation from first to second axis,
    /// seen from the positive normal; G2 is the other way.
    #[inline]
    pub fn axes(self) -> (usize, usize, usize) {
        match self {
            Plane::XY => (0, 1, 2),
            Plane::ZX => (2, 0, 1),
            Plane::YZ => (1, 2, 0),
        }
    }
}

/// Spindle state after an M3/M4/M5 or S word.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum SpindleDirection {
    /// M3
    Clockwise,
    /// M4
    CounterClockwise,
    /// M5
    Off,
}

/// One canonical event. Coordinates are millimetres in program coordinates
/// (the active work system), feeds are mm/min, `line` is the 1-based source line.
/// Serialises as `{"type": "Rapid", "line": 3, ...}`.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "type")]
pub enum Motion {
    /// G0 (also G28/G30 legs and G53 G0). `a`: the A axis's travel, when it moves.
    Rapid {
        line: u32,
        from: Point,
        to: Point,
        #[serde(skip_serializing_if = "Option::is_none")]
        a: Option<RotaryMove>,
    },
    /// G1, one chord of a linearised arc, or of a G5/G5.1 spline. `a`: the
    /// A axis's travel, when it moves; the feed is along XYZ, or in
    /// degrees/min when only A moves (LinuxCNC's rule).
    Linear {
        line: u32,
        from: Point,
        to: Point,
        feed_mm_min: f64,
        #[serde(skip_serializing_if = "Option::is_none")]
        a: Option<RotaryMove>,
    },
    /// G2/G3. `centre` has the start's coordinate on the plane normal; the
    /// normal axis moves linearly with angle (helix). `sweep_rad` is the total
    /// positive angle travelled in the direction given by `clockwise`,
    /// including `turns - 1` extra full turns (P word). A start radius that
    /// differs slightly from the end radius (within tolerance) is a spiral.
    Arc {
        line: u32,
        from: Point,
        to: Point,
        centre: Point,
        plane: Plane,
        clockwise: bool,
        feed_mm_min: f64,
        turns: u32,
        sweep_rad: f64,
    },
    /// G38.2-G38.5: a straight probing move toward `to` at `feed_mm_min`
    /// until the probe input closes (`contact`: G38.2/G38.3) or opens
    /// (G38.4/G38.5); `must_trip` (G38.2/G38.4) makes a move that ends with
    /// no change an error of the run. Where it tripped feeds the rest of the
    /// program: a backend that executes it gives the result back with
    /// [`Interpreter::probe_result`] before it asks for the next motion;
    /// without one (an upload check) the probe is taken to end at `to`
    /// without tripping and the tool to rest 0.254 mm (0.01 in) back toward
    /// `from`, as LinuxCNC's stand-alone interpreter assumes.
    Probe {
        line: u32,
        from: Point,
        to: Point,
        feed_mm_min: f64,
        contact: bool,
        must_trip: bool,
    },
    /// G4 P seconds.
    Dwell { line: u32, seconds: f64 },
    /// M3/M4/M5, or a new S while running.
    Spindle {
        line: u32,
        direction: SpindleDirection,
        rpm: f64,
    },
    /// M7/M8/M9.
    Coolant { line: u32, mist: bool, flood: bool },
    /// M6 with the tool selected by the last T word.
    ToolChange { line: u32, tool: u32 },
    /// G43 H (Some) or G49 (None): the controlled point changes; program
    /// coordinates do not.
    ToolLengthOffset { line: u32, tool: Option<u32> },
    /// G54..G59 (1..6), G59.1..G59.3 (7..9).
    WorkOffset { line: u32, system: u8 },
    /// `(msg, text)` comment not on an M0/M1 line.
    Message { line: u32, text: String },
    /// M0 (optional = false) / M1 (optional = true), with a `(msg,...)` on the same line.
    Pause {
        line: u32,
        optional: bool,
        message: Option<String>,
    },
    /// M2/M30 (or the closing `%`).
    ProgramEnd { line: u32 },
    /// G92, G92.1, G92.2, G92.3 or G52 (`code` = G number * 10: 920, 921,
    /// 922, 923, 520): the program moved its origin by `offset` (mm, the
    /// offset now in effect, zero when cancelled). The coordinates of every
    /// motion already include it (they stay in the active work system's
    /// frame), so a backend needs to do nothing; it is reported for the
    /// analysis and the operator.
    /// `offset_a`: the same for the A axis (degrees), left out of JSON when 0.
    OffsetChange {
        line: u32,
        code: u16,
        offset: Point,
        #[serde(skip_serializing_if = "is_zero")]
        offset_a: f64,
    },
    /// G10 L2 / L20 (`l` = 2 or 20): the program set work system `system`
    /// (1..9 = G54..G59.3) to `origin` (machine coordinates, mm, as the
    /// program sees them: `Config::work_offsets` plus what the program
    /// changed). Like G92, the change is folded into the coordinates of every
    /// later motion (they stay in the frame of the machine's own offsets), so
    /// a backend needs to do nothing and the machine's stored offsets are not
    /// changed; it is reported for the analysis and the operator.
    WorkOffsetChange {
        line: u32,
        l: u8,
        system: u8,
        origin: Point,
    },
}

/// What a probing move ([`Motion::Probe`]) found, in the frame motions are
/// given in (program coordinates plus the program's own offsets, mm).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProbeResult {
    /// The input changed (the move did not run its whole way).
    pub tripped: bool,
    /// Where it changed (`to` when it did not).
    pub trip: Point,
    /// Where the tool came to rest.
    pub rest: Point,
}

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

impl Motion {
    /// 1-based source line.
    #[inline]
    pub fn line(&self) -> u32 {
        match self {
            Motion::Rapid { line, .. }
            | Motion::Linear { line, .. }
            | Motion::Arc { line, .. }
            | Motion::Probe { line, .. }
            | Motion::Dwell { line, .. }
            | Motion::Spindle { line, .. }
            | Motion::Coolant { line, .. }
            | Motion::ToolChange { line, .. }
            | Motion::ToolLengthOffset { line, .. }
            | Motion::WorkOffset { line, .. }
            | Motion::Message { line, .. }
            | Motion::Pause { line, .. }
            | Motion::OffsetChange { line, .. }
            | Motion::WorkOffsetChange { line, .. }
            | Motion::ProgramEnd { line } => *line,
        }
    }

    /// The A axis's travel of a rapid or linear move, if A moves.
    #[inline]
    pub fn rotary(&self) -> Option<RotaryMove> {
        match self {
            Motion::Rapid { a, .. } | Motion::Linear { a, .. } => *a,
            _ => None,
        }
    }

    /// End point of a move (rapid, linear, arc), `None` for other events.
    #[inline]
    pub fn end_point(&self) -> Option<Point> {
        match self {
            Motion::Rapid { to, .. }
            | Motion::Linear { to, .. }
            | Motion::Arc { to, .. }
            | Motion::Probe { to, .. } => Some(*to),
            _ => None,
        }
    }
}

/// What went wrong, for programs that want to branch on it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum ErrorKind {
    /// Malformed text: bad number, unclosed comment, unknown character.
    Syntax,
    /// Well-formed but not implemented here (see [`Unsupported`]).
    Unsupported,
    /// Semantically invalid: two words of one modal group, missing feed, ...
    Invalid,
    /// Arc cannot be built: radius mismatch, R too small, zero radius.
    Arc,
    /// Input is not UTF-8.
    Utf8,
    /// The reader failed, or a line is too long.
    Io,
    /// The program would cause more work than its [`WorkBudget`] allows.
    Budget,
}

/// An error with the source position (1-based line and character column).
#[derive(Debug, Clone, PartialEq, Serialize, thiserror::Error)]
#[error("line {line}, column {column}: {message}")]
pub struct GcodeError {
    pub line: u32,
    pub column: u32,
    pub kind: ErrorKind,
    pub message: String,
}

/// Something skipped or worth knowing, with its position.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Warning {
    pub line: u32,
    pub column: u32,
    pub message: String,
}

//! Start at a line (issue 26): the modal state the lines before a line leave (interpreted
//! without motion by `fresa_gcode::Interpreter::state_at`) and the preamble that brings the
//! machine to it: up to a safe Z, the work offset, spindle and coolant as at the line, across
//! in X/Y (and A) at rapid to the start point, down to its Z at feed. A start at a line and a
//! resume after an interruption both go through [`plan`]; the preview shows the same plan.
//!
//! Safe Z (machine coordinates) is the highest of: where the machine's Z is, the highest Z any
//! move before the line reached (converted with the machine's work offsets), and the machine's
//! configured `safe_z_mm`. The way down is at the program's feed at the line (mm/min, G95
//! times the spindle speed), at most the machine's `max_feed_mm_min`; with none (no F yet, or
//! G93) at its `max_probe_feed_mm_min`, the slow feed it approaches surfaces at.

use crate::error::{Error, Result};
use crate::store::{MachineRow, Store};
use fresa_gcode::{ModalState, SpindleDirection, StartError, StartRefusalReason};
use fresa_plugin_api::contract::{
    AxisValues, MachineStatus, Preamble, PreambleStep, SpindleTurn, WorkOffset,
};
use serde::Serialize;
use std::fmt::Write as _;
use std::path::PathBuf;
use utoipa::ToSchema;

/// Below this (mm, degrees) two positions are the same: no move is planned between them.
const SAME: f64 = 1e-6;

/// What a plan needs to know of the machine, gathered by [`setup`].
#[derive(Debug, Clone)]
pub struct Setup {
    pub tools: fresa_gcode::ToolTable,
    pub unsupported: fresa_gcode::Unsupported,
    /// Machine origins of G54..G59 (the store's, which the backend has).
    pub offsets: [[f64; 4]; 6],
    /// The work offset active now.
    pub active: WorkOffset,
    /// Where the machine is now, machine coordinates.
    pub position: [f64; 4],
    pub safe_z_mm: Option<f64>,
    pub max_feed_mm_min: f64,
    /// The feed of the way down when the program gives none at the line.
    pub fallback_feed_mm_min: f64,
}

/// The machine's side of a plan: its tool table, unsupported-word policy and offsets from the
/// store, its position and active offset from `status`.
pub async fn setup(store: &Store, row: &MachineRow, status: &MachineStatus) -> Result<Setup> {
    let tools = crate::store::ToolRow::to_gcode(&store.tools(row.id).await?);
    let mut offsets = [[0.0; 4]; 6];
    for (o, v) in store.offsets(row.id).await? {
        offsets[o.index()] = v.to_array();
    }
    let unsupported = if row.config_json()["unsupported"] == "skip_with_warning" {
        fresa_gcode::Unsupported::SkipWithWarning
    } else {
        fresa_gcode::Unsupported::Error
    };
    Ok(Setup {
        tools,
        unsupported,
        offsets,
        active: status.active_offset,
        position: status.machine_position.to_array(),
        safe_z_mm: row.safe_z_mm,
        max_feed_mm_min: row.max_feed_mm_min,
        fallback_feed_mm_min: row.max_probe_feed_mm_min,
    })
}

/// A start at a line, planned: what `GET /jobs/{id}/start-preview` shows and what a start or
/// resume sends the backend (`preamble`).
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct StartPlan {
    pub from_line: u32,
    /// The modal state the lines before `from_line` leave (`fresa_gcode::ModalState`:
    /// position and highest Z in the program's frame, mm; feed converted to mm).
    #[schema(value_type = Object)]
    pub state: ModalState,
    /// The state as G-code words (`G21 G17 G90 ... G1 F1000`).
    pub state_gcode: String,
    /// Where the program is when the line begins, machine coordinates: where the approach
    /// ends.
    pub start: AxisValues,
    /// The Z the approach goes up to before it moves across, machine coordinates.
    pub safe_z: f64,
    /// The feed of the way down to the start point, mm/min.
    pub approach_feed_mm_min: f64,
    pub preamble: Preamble,
    /// The state and the preamble as G-code-like text (moves as `G53`, machine coordinates).
    pub gcode: String,
}

/// Plans a start of the program at `path` at `line` (on a blocking thread: it interprets the
/// lines before it). Refusals have their own codes (see [`refused`]).
pub async fn plan(path: PathBuf, line: u32, setup: Setup) -> Result<StartPlan> {
    tokio::task::spawn_blocking(move || {
        let file = std::fs::File::open(&path).map_err(|e| {
            Error::internal(format!("program file {} is missing: {e}", path.display()))
        })?;
        let reader = std::io::BufReader::with_capacity(1 << 16, file);
        plan_from(reader, line, &setup)
    })
    .await
    .map_err(|e| Error::internal(format!("start planning failed: {e}")))?
}

/// [`plan`] from a reader.
pub fn plan_from(reader: impl std::io::BufRead, line: u32, setup: &Setup) -> Result<StartPlan> {
    let here = setup.position;
    let active = setup.offsets[setup.active.index()];
    let mut config = fresa_gcode::Config {
        unsupported: setup.unsupported,
        tools: setup.tools.clone(),
        // The program's position before its first move is where the machine is, as the
        // backends interpret it.
        initial_position: [
            here[0] - active[0],
            here[1] - active[1],
            here[2] - active[2],
        ],
        initial_a_deg: here[3] - active[3],
        ..fresa_gcode::Config::default()
    };
    for (i, o) in setup.offsets.iter().enumerate() {
        config.work_offsets[i] = [o[0], o[1], o[2]];
    }
    let mut interp = fresa_gcode::Interpreter::new(reader, config);
    let state = interp.state_at(line).map_err(|e| match e {
        StartError::Gcode(e) => Error::invalid("invalid_gcode", format!("G-code error at {e}")),
        StartError::Refused(r) => refused(r.reason, r.to_string()),
    })?;
    let Some(offset) = usize::from(state.work_offset)
        .checked_sub(1)
        .and_then(|i| WorkOffset::ALL.get(i).copied())
    else {
        return Err(Error::invalid(
            "start_unsupported_offset",
            format!(
                "line {line}: the program is in G59.{} there, a work system this machine does \
                 not have (it has G54..G59)",
                state.work_offset.saturating_sub(6)
            ),
        ));
    };
    let origin = setup.offsets[offset.index()];
    let start: [f64; 4] = [
        state.position[0] + origin[0],
        state.position[1] + origin[1],
        state.position[2] + origin[2],
        state.a + origin[3],
    ];
    let highest = state.highest_z.map(|z| z + origin[2]);
    let safe_z = [Some(here[2]), highest, setup.safe_z_mm]
        .into_iter()
        .flatten()
        .fold(f64::NEG_INFINITY, f64::max)
        .max(start[2]);
    let approach_feed_mm_min = state
        .feed_mm_min()
        .filter(|f| *f > 0.0)
        .unwrap_or(setup.fallback_feed_mm_min)
        .min(setup.max_feed_mm_min);
    let mut steps = Vec::new();
    if safe_z > here[2] + SAME {
        steps.push(PreambleStep::Move {
            x: None,
            y: None,
            z: Some(safe_z),
            a: None,
            feed: None,
        });
    }
    steps.push(PreambleStep::Offset { offset });
    steps.push(PreambleStep::Spindle {
        direction: match state.spindle {
            SpindleDirection::Clockwise => SpindleTurn::Cw,
            SpindleDirection::CounterClockwise => SpindleTurn::Ccw,
            SpindleDirection::Off => SpindleTurn::Off,
        },
        rpm: state.rpm,
    });
    steps.push(PreambleStep::Coolant {
        mist: state.mist,
        flood: state.flood,
    });
    let across = (0..2).any(|i| (start[i] - here[i]).abs() > SAME);
    let turn = (start[3] - here[3]).abs() > SAME;
    if across || turn {
        steps.push(PreambleStep::Move {
            x: across.then_some(start[0]),
            y: across.then_some(start[1]),
            z: None,
            a: turn.then_some(start[3]),
            feed: None,
        });
    }
    if safe_z - start[2] > SAME {
        steps.push(PreambleStep::Move {
            x: None,
            y: None,
            z: Some(start[2]),
            a: None,
            feed: Some(approach_feed_mm_min),
        });
    }
    let preamble = Preamble {
        line,
        from: AxisValues::from_array(here),
        steps,
    };
    let state_gcode = state.words();
    let gcode = text(&state, &state_gcode, &preamble);
    Ok(StartPlan {
        from_line: line,
        state,
        state_gcode,
        start: AxisValues::from_array(start),
        safe_z,
        approach_feed_mm_min,
        preamble,
        gcode,
    })
}

/// The API's error for a start the interpreter refuses: one code per reason.
pub fn refused(reason: StartRefusalReason, message: String) -> Error {
    let code = match reason {
        StartRefusalReason::PastEnd => "start_past_end",
        StartRefusalReason::NotRun => "start_line_not_run",
        StartRefusalReason::Loop => "start_in_loop",
        StartRefusalReason::Subroutine => "start_in_subroutine",
        StartRefusalReason::CutterCompensation => "start_under_cutter_compensation",
        StartRefusalReason::CannedCycleRepeat => "start_in_canned_cycle_repeat",
    };
    Error::invalid(code, message)
}

/// The state and the preamble as G-code-like text.
fn text(state: &ModalState, words: &str, p: &Preamble) -> String {
    let mut t = String::new();
    let _ = writeln!(
        t,
        "(state at line {}, from the lines before it)\n{words}",
        p.line
    );
    if state.g92_offset != [0.0; 3] || state.g92_offset_a != 0.0 {
        let o = state.g92_offset;
        let _ = writeln!(
            t,
            "(G92/G52 offset in effect: X{} Y{} Z{} A{})",
            mm(o[0]),
            mm(o[1]),
            mm(o[2]),
            mm(state.g92_offset_a)
        );
    }
    for s in &state.work_offsets_set {
        let o = s.origin;
        let _ = writeln!(
            t,
            "(work system {} set by the program: X{} Y{} Z{})",
            s.system,
            mm(o[0]),
            mm(o[1]),
            mm(o[2])
        );
    }
    let _ = writeln!(t, "(preamble, machine coordinates)");
    for step in &p.steps {
        let line = match *step {
            PreambleStep::Offset { offset } => offset.name().to_string(),
            PreambleStep::Spindle { direction, rpm } => match direction {
                SpindleTurn::Cw => format!("S{} M3", mm(rpm)),
                SpindleTurn::Ccw => format!("S{} M4", mm(rpm)),
                SpindleTurn::Off => "M5".into(),
            },
            PreambleStep::Coolant { mist, flood } => match (mist, flood) {
                (false, false) => "M9".into(),
                (true, false) => "M7".into(),
                (false, true) => "M8".into(),
                (true, true) => "M7 M8".into(),
            },
            PreambleStep::Move { x, y, z, a, feed } => {
                let mut m = String::from(if feed.is_some() { "G53 G1" } else { "G53 G0" });
                for (letter, v) in [('X', x), ('Y', y), ('Z', z), ('A', a)] {
                    if let Some(v) = v {
                        let _ = write!(m, " {letter}{}", mm(v));
                    }
                }
                if let Some(f) = feed {
                    let _ = write!(m, " F{}", mm(f));
                }
                m
            }
        };
        let _ = writeln!(t, "{line}");
    }
    let _ = write!(t, "(line {} follows)", p.line);
    t
}

fn mm(v: f64) -> String {
    let s = format!("{v:.4}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    if s == "-0" {
        "0".into()
    } else {
        s.to_string()
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn setup(position: [f64; 4]) -> Setup {
        let mut offsets = [[0.0; 4]; 6];
        offsets[1] = [100.0, 50.0, -20.0, 0.0];
        Setup {
            tools: Default::default(),
            unsupported: Default::default(),
            offsets,
            active: WorkOffset::G54,
            position,
            safe_z_mm: None,
            max_feed_mm_min: 5000.0,
            fallback_feed_mm_min: 300.0,
        }
    }

    const PROGRAM: &str = "G21 G90\nG55\nG0 Z10\nG0 X5 Y5\nS8000 M3 M8\nG1 Z-2 F400\n\
                           G1 X15\nG0 Z5\nG0 X30\nG1 Z-3\nG1 Y20\n";

    #[test]
    fn up_to_the_highest_z_then_the_state_then_across_then_down_at_feed() {
        // At line 10 the program is at X30 Y5 Z5 in G55 (Z10 was its highest, = -10 machine).
        let p = plan_from(PROGRAM.as_bytes(), 10, &setup([0.0, 0.0, -40.0, 0.0])).unwrap();
        assert_eq!(p.start.to_array(), [130.0, 55.0, -15.0, 0.0]);
        assert_eq!(p.safe_z, -10.0);
        assert_eq!(p.approach_feed_mm_min, 400.0);
        assert_eq!(
            p.preamble.steps,
            vec![
                PreambleStep::Move {
                    x: None,
                    y: None,
                    z: Some(-10.0),
                    a: None,
                    feed: None
                },
                PreambleStep::Offset {
                    offset: WorkOffset::G55
                },
                PreambleStep::Spindle {
                    direction: SpindleTurn::Cw,
                    rpm: 8000.0
                },
                PreambleStep::Coolant {
                    mist: false,
                    flood: true
                },
                PreambleStep::Move {
                    x: Some(130.0),
                    y: Some(55.0),
                    z: None,
                    a: None,
                    feed: None
                },
                PreambleStep::Move {
                    x: None,
                    y: None,
                    z: Some(-15.0),
                    a: None,
                    feed: Some(400.0)
                },
            ]
        );
        assert_eq!(p.preamble.from.to_array(), [0.0, 0.0, -40.0, 0.0]);
        assert!(
            p.gcode
                .contains("G53 G0 Z-10\nG55\nS8000 M3\nM8\nG53 G0 X130 Y55\nG53 G1 Z-15 F400\n"),
            "{}",
            p.gcode
        );
        assert!(
            p.state_gcode.starts_with("G21 G17 G90 G91.1 G94 G55"),
            "{}",
            p.state_gcode
        );
    }

    #[test]
    fn a_higher_machine_z_or_safe_height_wins_and_nothing_moves_where_it_need_not() {
        // The machine stands higher than anything the program did: it does not go up.
        let p = plan_from(PROGRAM.as_bytes(), 10, &setup([0.0, 0.0, 0.0, 0.0])).unwrap();
        assert_eq!(p.safe_z, 0.0);
        assert!(matches!(p.preamble.steps[0], PreambleStep::Offset { .. }));
        // A configured safe height above both.
        let mut s = setup([0.0, 0.0, -40.0, 0.0]);
        s.safe_z_mm = Some(-1.0);
        let p = plan_from(PROGRAM.as_bytes(), 10, &s).unwrap();
        assert_eq!(p.safe_z, -1.0);
        // Already at the start point: no move across, no way down.
        let p = plan_from(PROGRAM.as_bytes(), 10, &setup([130.0, 55.0, -15.0, 0.0])).unwrap();
        assert_eq!(p.safe_z, -10.0);
        assert_eq!(p.preamble.steps.len(), 5, "up, the state, then back down");
        let at_top = plan_from(PROGRAM.as_bytes(), 10, &setup([130.0, 55.0, -10.0, 0.0]));
        let steps = at_top.unwrap().preamble.steps;
        assert_eq!(steps.len(), 4, "{steps:?}");
    }

    #[test]
    fn refusals_have_their_own_codes() {
        let e = plan_from(PROGRAM.as_bytes(), 40, &setup([0.0; 4])).unwrap_err();
        assert_eq!(e.code, "start_past_end");
        assert!(e.message.starts_with("line 40: "), "{e}");
        let looped = "#1=0\no1 while [#1 LT 2]\nG0 X[#1]\n#1=[#1+1]\no1 endwhile\n";
        let e = plan_from(looped.as_bytes(), 3, &setup([0.0; 4])).unwrap_err();
        assert_eq!(e.code, "start_in_loop");
        let e = plan_from("G0 X1\nG59.1\nG0 X2\n".as_bytes(), 3, &setup([0.0; 4])).unwrap_err();
        assert_eq!(e.code, "start_unsupported_offset");
    }
}

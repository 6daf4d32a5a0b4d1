//! A loaded program, interpreted once up front into the steps the machine executes.

use fresa_gcode::{linearise, GcodeError, Interpreter, Motion};
use fresa_plugin_api::contract::WorkOffset;

/// Chord tolerance for arcs, mm.
pub const ARC_TOLERANCE_MM: f64 = 0.002;

/// One thing the machine does for a source line.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Step {
    /// Straight move to `to` (program coordinates, mm) at `feed` mm/min, or rapid when `None`.
    /// `a`: where the A axis ends (program degrees) when the move turns it; A and XYZ move
    /// together, and the feed is along XYZ (degrees/min when only A moves), as in LinuxCNC.
    Move {
        to: [f64; 3],
        a: Option<f64>,
        feed: Option<f64>,
    },
    /// G4: wait this many (unscaled) seconds.
    Dwell(f64),
    /// M0: pause the run until resumed.
    Pause,
    /// G54..G59 in the program: later moves use this offset.
    UseOffset(WorkOffset),
}

/// A whole program, ready to run.
#[derive(Debug, Clone, PartialEq)]
pub struct Plan {
    /// Number of source lines (every one is acknowledged).
    pub lines: u32,
    /// Steps in execution order, each with its 1-based source line (<= `lines`).
    pub steps: Vec<(u32, Step)>,
}

/// Interprets the whole program. `initial_position` is where the tool is, in program
/// coordinates (X, Y, Z, A); `work_offsets` the machine origin of G54..G59 (XYZ); `tools` the
/// machine's tool table (G41/G42 `D`).
pub fn plan(
    text: &str,
    initial_position: [f64; 4],
    work_offsets: [[f64; 3]; 6],
    tools: fresa_gcode::ToolTable,
) -> Result<Plan, GcodeError> {
    let lines = u32::try_from(text.lines().count()).unwrap_or(u32::MAX);
    let [x, y, z, a] = initial_position;
    let mut config = fresa_gcode::Config {
        initial_position: [x, y, z],
        initial_a_deg: a,
        tools,
        ..Default::default()
    };
    config.work_offsets[..6].copy_from_slice(&work_offsets);
    let interp = Interpreter::new(text.as_bytes(), config);
    let mut steps = Vec::new();
    for motion in linearise(interp, ARC_TOLERANCE_MM) {
        let motion = motion?;
        let line = motion.line().clamp(1, lines.max(1));
        let step = match motion {
            Motion::Rapid { to, a, .. } => Step::Move {
                to,
                a: a.map(|a| a.to),
                feed: None,
            },
            Motion::Linear {
                to, feed_mm_min, a, ..
            } => Step::Move {
                to,
                a: a.map(|a| a.to),
                feed: Some(feed_mm_min),
            },
            // `linearise` turns every arc into chords; an arc here would be a bug there.
            Motion::Arc {
                to, feed_mm_min, ..
            } => Step::Move {
                to,
                a: None,
                feed: Some(feed_mm_min),
            },
            Motion::Dwell { seconds, .. } => Step::Dwell(seconds),
            Motion::Pause {
                optional: false, ..
            } => Step::Pause,
            Motion::WorkOffset { system, .. } => match system {
                1..=6 => Step::UseOffset(WorkOffset::ALL[usize::from(system) - 1]),
                _ => continue,
            },
            // Spindle, coolant, tool changes, messages, M1 (optional stop off) and the end of
            // the program do not move the simulated machine.
            _ => continue,
        };
        steps.push((line, step));
    }
    Ok(Plan { lines, steps })
}

impl Plan {
    /// Checks every move against `check` (given machine coordinates), using `offsets` (the
    /// machine origins of G54..G59) starting in `active`. Returns `line L: message`.
    pub fn check_moves(
        &self,
        offsets: &[[f64; 4]; 6],
        active: WorkOffset,
        start_a: f64,
        check: impl Fn([f64; 4]) -> Result<(), String>,
    ) -> Result<(), String> {
        let mut offset = offsets[active.index()];
        let mut machine_a = start_a;
        for (line, step) in &self.steps {
            match step {
                Step::Move { to, a, .. } => {
                    let target = machine_target(*to, *a, &offset, machine_a);
                    machine_a = target[3];
                    check(target).map_err(|m| format!("line {line}: {m}"))?;
                }
                Step::UseOffset(o) => offset = offsets[o.index()],
                _ => {}
            }
        }
        Ok(())
    }
}

/// Machine coordinates of program point `to` (and program A `a`, when the move turns A)
/// under `offset`; otherwise A stays at the machine's `current_a`.
pub fn machine_target(to: [f64; 3], a: Option<f64>, offset: &[f64; 4], current_a: f64) -> [f64; 4] {
    [
        to[0] + offset[0],
        to[1] + offset[1],
        to[2] + offset[2],
        a.map_or(current_a, |a| a + offset[3]),
    ]
}

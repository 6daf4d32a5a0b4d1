//! G-code -> robot commands: interpretation with `fresa-gcode` (arcs linearised by tolerance),
//! axis mapping, feed (mm/min) -> clamped SPEED (mm/s), and the envelope check of every point.

use crate::config::Speeds;
use fresa_gcode::{linearise, GcodeError, Interpreter, Motion, Unsupported};
use fresa_plugin_api::config_fields::invalid;
use fresa_plugin_api::heightmap::HeightMap;
use fresa_plugin_api::PluginError;
use serde_json::Value;

const AXES: [char; 3] = ['X', 'Y', 'Z'];

/// Robot axis `i` = `sign[i]` * CNC axis `source[i]`. Default X=X, Y=-Y, Z=-Z (the seed's
/// `TRANS(x, -y, -z)`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Mapping {
    source: [usize; 3],
    sign: [f64; 3],
}

impl Default for Mapping {
    fn default() -> Self {
        Mapping {
            source: [0, 1, 2],
            sign: [1.0, -1.0, -1.0],
        }
    }
}

impl Mapping {
    /// `{"x": "X", "y": "-Y", "z": "-Z"}`: for each robot axis, a signed CNC axis. Axes left
    /// out keep their default; the result must use each CNC axis once.
    pub fn from_json(v: &Value) -> Result<Mapping, PluginError> {
        let obj = v.as_object().ok_or_else(|| {
            invalid(format!(
                "`mapping` must be an object like {{\"x\": \"X\", \"y\": \"-Y\", \"z\": \"-Z\"}}, got {v}"
            ))
        })?;
        let mut m = Mapping::default();
        for (key, spec) in obj {
            let robot = ["x", "y", "z"]
                .iter()
                .position(|a| a.eq_ignore_ascii_case(key))
                .ok_or_else(|| {
                    invalid(format!("unknown key `mapping.{key}` (expected x, y or z)"))
                })?;
            let text = spec.as_str().unwrap_or("").trim();
            let (sign, axis) = match text.strip_prefix('-') {
                Some(rest) => (-1.0, rest),
                None => (1.0, text.strip_prefix('+').unwrap_or(text)),
            };
            let source = AXES
                .iter()
                .position(|a| axis.len() == 1 && axis.eq_ignore_ascii_case(&a.to_string()))
                .ok_or_else(|| {
                    invalid(format!(
                        "`mapping.{key}` must be a G-code axis with an optional sign (\"X\", \"-Y\", ...), got {spec}"
                    ))
                })?;
            m.source[robot] = source;
            m.sign[robot] = sign;
        }
        let mut used = [false; 3];
        for s in m.source {
            used[s] = true;
        }
        if used.contains(&false) {
            return Err(invalid(format!(
                "`mapping` must use each of X, Y, Z once, got {}",
                m.describe()
            )));
        }
        Ok(m)
    }

    /// G-code point (program coordinates, mm) -> robot point relative to part zero.
    #[inline]
    pub fn map(&self, p: [f64; 3]) -> [f64; 3] {
        std::array::from_fn(|i| self.sign[i] * p[self.source[i]])
    }

    /// Robot point -> G-code point.
    pub fn unmap(&self, r: [f64; 3]) -> [f64; 3] {
        let mut p = [0.0; 3];
        for i in 0..3 {
            p[self.source[i]] = self.sign[i] * r[i];
        }
        p
    }

    pub fn describe(&self) -> String {
        (0..3)
            .map(|i| {
                format!(
                    "{}={}{}",
                    AXES[i],
                    if self.sign[i] < 0.0 { "-" } else { "" },
                    AXES[self.source[i]]
                )
            })
            .collect::<Vec<_>>()
            .join(", ")
    }
}

/// The work box, relative to the CNC "machine zero" given in robot base coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Envelope {
    pub min: [f64; 3],
    pub max: [f64; 3],
    /// Robot base coordinates of the box's reference point (the seed: its centre).
    pub machine_zero: [f64; 3],
}

impl Default for Envelope {
    fn default() -> Self {
        Envelope {
            min: [-150.0, -250.0, -70.0],
            max: [150.0, 250.0, 70.0],
            machine_zero: [-400.0, 0.0, -30.0],
        }
    }
}

/// Slack for points exactly on a face (arc chords, decimal round trips).
const ENVELOPE_EPS: f64 = 1e-9;

impl Envelope {
    /// `{"x": [min, max], ...}`; axes left out keep their default.
    pub fn from_json(v: &Value, machine_zero: [f64; 3]) -> Result<Envelope, PluginError> {
        let obj = v.as_object().ok_or_else(|| {
            invalid(format!(
                "`envelope` must be an object like {{\"x\": [-150, 150], ...}}, got {v}"
            ))
        })?;
        let mut e = Envelope {
            machine_zero,
            ..Envelope::default()
        };
        for (key, range) in obj {
            let i = ["x", "y", "z"]
                .iter()
                .position(|a| a.eq_ignore_ascii_case(key))
                .ok_or_else(|| {
                    invalid(format!("unknown key `envelope.{key}` (expected x, y or z)"))
                })?;
            let pair = range
                .as_array()
                .filter(|a| a.len() == 2)
                .and_then(|a| Some((a[0].as_f64()?, a[1].as_f64()?)))
                .filter(|(a, b)| a.is_finite() && b.is_finite())
                .ok_or_else(|| {
                    invalid(format!(
                        "`envelope.{key}` must be [min, max] in mm, got {range}"
                    ))
                })?;
            if pair.0 > pair.1 {
                return Err(invalid(format!(
                    "`envelope.{key}`: min {} is greater than max {}",
                    pair.0, pair.1
                )));
            }
            e.min[i] = pair.0;
            e.max[i] = pair.1;
        }
        Ok(e)
    }

    /// Checks robot point `p` (relative to `part_zero`, robot base coordinates). The error
    /// names the axis, the value and the limits.
    pub fn check(&self, part_zero: [f64; 3], p: [f64; 3]) -> Result<(), String> {
        for i in 0..3 {
            let rel = part_zero[i] + p[i] - self.machine_zero[i];
            if rel < self.min[i] - ENVELOPE_EPS || rel > self.max[i] + ENVELOPE_EPS {
                return Err(format!(
                    "robot {}={:.3} relative to the part zero is {:.3} from the machine zero, outside the envelope {}..{}",
                    AXES[i], p[i], rel, self.min[i], self.max[i]
                ));
            }
        }
        Ok(())
    }
}

/// Most robot motions one program may convert to (moves, and arc chords at
/// `arc_tolerance_mm`): the converted program is held in memory (about 40 bytes a command, so
/// at most about 400 MB), and at the robot's tens of moves a second it would run for days.
pub const MAX_COMMANDS: u64 = 10_000_000;

/// One thing the streamer does.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Cmd {
    /// Cutting speed, mm/s (fresa-v1 only; the legacy robot program fixes its own).
    Speed(f64),
    /// Move to a robot point relative to part zero: rapid (`JMOVE`) or cutting (`LMOVE`).
    Move { rapid: bool, to: [f64; 3] },
    /// G4: wait until every motion sent is done, then this many seconds.
    Dwell(f64),
    /// M0: stop sending; the run pauses until resumed.
    Pause,
}

/// A converted program.
#[derive(Debug, Clone, PartialEq)]
pub struct Plan {
    /// Source lines (every one is acknowledged).
    pub lines: u32,
    /// Commands in order, each with its 1-based source line.
    pub cmds: Vec<(u32, Cmd)>,
    /// What the interpreter skipped or noted, `line L, column C: ...`.
    pub warnings: Vec<String>,
}

/// Options of the conversion.
#[derive(Debug, Clone, Copy)]
pub struct Convert {
    pub mapping: Mapping,
    pub speeds: Speeds,
    pub arc_tolerance_mm: f64,
    pub unsupported: Unsupported,
}

impl Convert {
    /// Interprets the whole program. Errors name line and column.
    pub fn plan(&self, text: &str) -> Result<Plan, GcodeError> {
        self.plan_with_tools(text, fresa_gcode::ToolTable::new())
    }

    /// [`Convert::plan`] with the machine's tool table (G41/G42 `D`).
    pub fn plan_with_tools(
        &self,
        text: &str,
        tools: fresa_gcode::ToolTable,
    ) -> Result<Plan, GcodeError> {
        self.plan_bounded(text, tools, fresa_gcode::DEFAULT_MAX_SEGMENTS)
    }

    /// [`Convert::plan_with_tools`] within a work budget of `max_segments` robot motions (moves,
    /// and arcs as chords at `arc_tolerance_mm`), counted before any is made: a program over
    /// it is an [`fresa_gcode::ErrorKind::Budget`] error naming its line, so the commands kept
    /// are bounded by the budget whatever one arc asks for.
    pub fn plan_bounded(
        &self,
        text: &str,
        tools: fresa_gcode::ToolTable,
        max_segments: u64,
    ) -> Result<Plan, GcodeError> {
        self.plan_mapped(text, tools, max_segments, None)
    }

    /// [`Convert::plan_bounded`] with a height map (issue 25): every move's Z gets the map's
    /// correction, each move split where it crosses a grid line (`fresa_plugin_api::heightmap`),
    /// in program coordinates before the axis mapping. The pieces count against
    /// `max_segments`.
    pub fn plan_mapped(
        &self,
        text: &str,
        tools: fresa_gcode::ToolTable,
        max_segments: u64,
        height_map: Option<&HeightMap>,
    ) -> Result<Plan, GcodeError> {
        let lines = u32::try_from(text.lines().count()).unwrap_or(u32::MAX);
        let config = fresa_gcode::Config {
            arc_tolerance_mm: self.arc_tolerance_mm,
            unsupported: self.unsupported,
            tools,
            ..Default::default()
        };
        let mut interp = Interpreter::new(text.as_bytes(), config);
        let mut cmds = Vec::new();
        let mut speed = None;
        let mut warnings = Vec::new();
        let budget = fresa_gcode::WorkBudget::new(max_segments, self.arc_tolerance_mm);
        let motions = fresa_gcode::budgeted(&mut interp, budget);
        // The program point the robot is at (uncorrected): the part zero at the start.
        let mut from = height_map.map_or([0.0; 3], |m| m.uncorrected([0.0; 3]));
        let mut moves: u64 = 0;
        for motion in linearise(motions, self.arc_tolerance_mm) {
            let motion = motion?;
            let line = motion.line().clamp(1, lines.max(1));
            // The points a move goes through: its end, or with a height map each piece's end,
            // corrected.
            let mut path = |to: [f64; 3]| -> Result<Vec<[f64; 3]>, GcodeError> {
                let points = match height_map {
                    None => vec![to],
                    Some(m) => m
                        .corrected_path(from, to)
                        .into_iter()
                        .map(|(_, p)| p)
                        .collect(),
                };
                from = to;
                moves += points.len() as u64;
                if height_map.is_some() && moves > max_segments {
                    return Err(GcodeError {
                        line,
                        column: 1,
                        kind: fresa_gcode::ErrorKind::Budget,
                        message: format!(
                            "work budget exceeded: the height map splits the program's moves \
                             into more than {max_segments} robot motions"
                        ),
                    });
                }
                Ok(points)
            };
            // The robot's six joints place the tool in X/Y/Z only; a program that turns a
            // rotary table is refused whole, before anything moves.
            if let Some(a) = motion.rotary() {
                return Err(GcodeError {
                    line,
                    column: 1,
                    kind: fresa_gcode::ErrorKind::Unsupported,
                    message: format!(
                        "A axis motion (to A{}): the Kawasaki robot has no A axis",
                        a.to
                    ),
                });
            }
            if matches!(motion, Motion::Probe { .. }) {
                return Err(GcodeError {
                    line,
                    column: 1,
                    kind: fresa_gcode::ErrorKind::Unsupported,
                    message: "G38 probing: the Kawasaki robot's AS link has no probe input"
                        .to_string(),
                });
            }
            match motion {
                Motion::Rapid { to, .. } => {
                    for p in path(to)? {
                        cmds.push((
                            line,
                            Cmd::Move {
                                rapid: true,
                                to: self.mapping.map(p),
                            },
                        ));
                    }
                }
                // `linearise` leaves no arcs; an arc here would be a bug there, and its end
                // point is still a correct (if coarse) target.
                Motion::Linear {
                    to, feed_mm_min, ..
                }
                | Motion::Arc {
                    to, feed_mm_min, ..
                } => {
                    let v = self.speeds.cutting(feed_mm_min);
                    if speed != Some(v) {
                        speed = Some(v);
                        cmds.push((line, Cmd::Speed(v)));
                    }
                    for p in path(to)? {
                        cmds.push((
                            line,
                            Cmd::Move {
                                rapid: false,
                                to: self.mapping.map(p),
                            },
                        ));
                    }
                }
                Motion::Dwell { seconds, .. } => cmds.push((line, Cmd::Dwell(seconds.max(0.0)))),
                Motion::Pause {
                    optional: false, ..
                } => cmds.push((line, Cmd::Pause)),
                Motion::ToolChange { tool, .. } => warnings.push(format!(
                    "line {line}: tool change to T{tool} ignored (the robot has no tool changer)"
                )),
                // Spindle (set by hand on its supply), coolant, messages, M1, program end.
                _ => {}
            }
        }
        warnings.extend(
            interp
                .warnings()
                .iter()
                .map(|w| format!("line {}, column {}: {}", w.line, w.column, w.message)),
        );
        Ok(Plan {
            lines,
            cmds,
            warnings,
        })
    }
}

impl Plan {
    /// Checks every motion against the envelope before anything moves. The error names the
    /// G-code line and the point in G-code and robot coordinates.
    pub fn check_envelope(
        &self,
        envelope: &Envelope,
        mapping: &Mapping,
        part_zero: [f64; 3],
    ) -> Result<(), String> {
        for (line, cmd) in &self.cmds {
            if let Cmd::Move { to, .. } = cmd {
                if let Err(why) = envelope.check(part_zero, *to) {
                    let g = mapping.unmap(*to);
                    return Err(format!(
                        "line {line}: G-code point X{:.3} Y{:.3} Z{:.3}: {why} (part zero {:.3} {:.3} {:.3}, machine zero {:.3} {:.3} {:.3}); nothing was moved",
                        g[0], g[1], g[2], part_zero[0], part_zero[1], part_zero[2],
                        envelope.machine_zero[0], envelope.machine_zero[1], envelope.machine_zero[2]
                    ));
                }
            }
        }
        Ok(())
    }

    /// Index of the first command of `line` or later.
    pub fn first_cmd_at(&self, line: u32) -> usize {
        self.cmds.partition_point(|(l, _)| *l < line)
    }

    /// The last line all of whose commands are among the first `done` commands.
    pub fn acked_through(&self, done: usize) -> u32 {
        match self.cmds.get(done) {
            Some((line, _)) => line.saturating_sub(1),
            None => self.lines,
        }
    }

    /// Cutting speed in effect before command `index` (the last `Speed` before it).
    pub fn speed_before(&self, index: usize) -> Option<f64> {
        self.cmds[..index.min(self.cmds.len())]
            .iter()
            .rev()
            .find_map(|(_, c)| match c {
                Cmd::Speed(v) => Some(*v),
                _ => None,
            })
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;
    use proptest::prelude::*;
    use serde_json::json;

    fn conv() -> Convert {
        Convert {
            mapping: Mapping::default(),
            speeds: Speeds::default(),
            arc_tolerance_mm: 0.01,
            unsupported: Unsupported::Error,
        }
    }

    #[test]
    fn default_mapping_is_the_seeds() {
        let m = Mapping::default();
        assert_eq!(m.map([1.0, 2.0, 3.0]), [1.0, -2.0, -3.0]);
        assert_eq!(m.describe(), "X=X, Y=-Y, Z=-Z");
        let m = Mapping::from_json(&json!({"x": "-Y", "y": "+X"})).unwrap();
        assert_eq!(m.map([1.0, 2.0, 3.0]), [-2.0, 1.0, -3.0]);
    }

    /// A height map corrects every motion's Z in program coordinates, before the axis
    /// mapping, and splits a move where it crosses grid lines; the pieces count against the
    /// budget.
    #[test]
    fn a_height_map_corrects_and_splits_the_robot_motions() {
        // Correction 0 at X 0, 1 at X 10, 0.5 at X 20 (the same along Y).
        let map = HeightMap {
            x0: 0.0,
            y0: 0.0,
            dx: 10.0,
            dy: 10.0,
            nx: 3,
            ny: 2,
            z: vec![0.0, 1.0, 0.5, 0.0, 1.0, 0.5],
        };
        let text = "G0 X0 Y5 Z2\nG1 X20 Y5 Z-1 F600\n";
        let plan = conv()
            .plan_mapped(text, Default::default(), 1000, Some(&map))
            .unwrap();
        let moves: Vec<[f64; 3]> = plan
            .cmds
            .iter()
            .filter_map(|(_, c)| match c {
                Cmd::Move { to, .. } => Some(Mapping::default().unmap(*to)),
                _ => None,
            })
            .collect();
        // Line 1 (from the part zero, on X 0: no crossing), line 2 split at X 10.
        let want = [
            [0.0, 5.0, 2.0],
            [10.0, 5.0, 0.5 + 1.0],
            [20.0, 5.0, -1.0 + 0.5],
        ];
        assert_eq!(moves.len(), want.len(), "{moves:?}");
        for (got, want) in moves.iter().zip(want) {
            for k in 0..3 {
                assert!((got[k] - want[k]).abs() < 1e-9, "{moves:?}");
            }
        }
        // Without a map: the same program, uncorrected, one motion a move.
        let plain = conv().plan_bounded(text, Default::default(), 1000).unwrap();
        assert_eq!(
            plain
                .cmds
                .iter()
                .filter(|(_, c)| matches!(c, Cmd::Move { .. }))
                .count(),
            2
        );
        // The split pieces count against the budget.
        let e = conv()
            .plan_mapped(text, Default::default(), 2, Some(&map))
            .unwrap_err();
        assert_eq!((e.line, e.kind), (2, fresa_gcode::ErrorKind::Budget), "{e}");
    }

    #[test]
    fn a_program_over_the_work_budget_is_refused_before_its_commands_are_made() {
        // ~2 x 10^8 chords at 0.01 mm: refused at its line, no command kept.
        let huge = "G0 X0 Y0\nG2 X0 Y0 I400000 J0 P10000 F100\n";
        let e = conv()
            .plan_bounded(huge, Default::default(), 1_000_000)
            .unwrap_err();
        assert_eq!((e.line, e.kind), (2, fresa_gcode::ErrorKind::Budget), "{e}");
        // Within it: every chord is a command.
        let p = conv()
            .plan_bounded("G0 X5\nG2 I-5 F100\n", Default::default(), 1_000)
            .unwrap();
        let moves = p
            .cmds
            .iter()
            .filter(|(_, c)| matches!(c, Cmd::Move { .. }))
            .count() as u64;
        assert_eq!(
            moves,
            1 + fresa_gcode::segments_for(5.0, std::f64::consts::TAU, 0.01)
        );
    }

    #[test]
    fn program_to_commands() {
        let p = conv()
            .plan("G21 G90\nG0 X10 Y5 Z2\nG1 Z-1 F120\nG1 X20 F3000\n(c)\nG1 X30\n")
            .unwrap();
        assert_eq!(p.lines, 6);
        assert_eq!(
            p.cmds,
            vec![
                (
                    2,
                    Cmd::Move {
                        rapid: true,
                        to: [10.0, -5.0, -2.0]
                    }
                ),
                (3, Cmd::Speed(5.0)),
                (
                    3,
                    Cmd::Move {
                        rapid: false,
                        to: [10.0, -5.0, 1.0]
                    }
                ),
                (4, Cmd::Speed(15.0)),
                (
                    4,
                    Cmd::Move {
                        rapid: false,
                        to: [20.0, -5.0, 1.0]
                    }
                ),
                (
                    6,
                    Cmd::Move {
                        rapid: false,
                        to: [30.0, -5.0, 1.0]
                    }
                ),
            ]
        );
        assert_eq!(p.acked_through(0), 1);
        assert_eq!(p.acked_through(3), 3);
        assert_eq!(p.acked_through(5), 5);
        assert_eq!(p.acked_through(6), 6);
        assert_eq!(p.first_cmd_at(4), 3);
        assert_eq!(p.speed_before(5), Some(15.0));
    }

    #[test]
    fn arcs_by_tolerance_not_one_degree() {
        // A 90 degree arc of radius 10: 1-degree steps would give 90 points; 0.01 mm
        // tolerance needs far fewer, and a coarser tolerance fewer still.
        let prog = "G21 G90 G0 X10 Y0\nG3 X0 Y10 I-10 J0 F600\n";
        let fine = conv().plan(prog).unwrap();
        let coarse = Convert {
            arc_tolerance_mm: 0.5,
            ..conv()
        }
        .plan(prog)
        .unwrap();
        let moves = |p: &Plan| {
            p.cmds
                .iter()
                .filter(|(l, c)| *l == 2 && matches!(c, Cmd::Move { .. }))
                .count()
        };
        assert!(
            moves(&fine) > moves(&coarse),
            "{} vs {}",
            moves(&fine),
            moves(&coarse)
        );
        assert_ne!(moves(&fine), 90);
        // Every chord point lies on the circle and the last one is the exact end.
        for (_, c) in fine.cmds.iter().filter(|(l, _)| *l == 2) {
            if let Cmd::Move { to, .. } = c {
                let r = (to[0] * to[0] + to[1] * to[1]).sqrt();
                assert!((r - 10.0).abs() < 1e-9, "{to:?}");
            }
        }
        assert_eq!(
            fine.cmds.last().unwrap().1,
            Cmd::Move {
                rapid: false,
                to: [0.0, -10.0, 0.0]
            }
        );
    }

    #[test]
    fn unsupported_words_follow_the_policy() {
        let prog = "G21 G91\nG42 D08\nG1 X1 F100\n";
        let e = conv().plan(prog).unwrap_err();
        assert_eq!(e.line, 2);
        let p = Convert {
            unsupported: Unsupported::SkipWithWarning,
            ..conv()
        }
        .plan(prog)
        .unwrap();
        assert!(
            p.warnings.iter().any(|w| w.starts_with("line 2")),
            "{:?}",
            p.warnings
        );
        assert_eq!(p.cmds.len(), 2);
    }

    #[test]
    fn envelope_error_names_line_and_point() {
        let p = conv().plan("G21 G90\nG0 X0 Y0 Z5\nG1 X151 F600\n").unwrap();
        let e = Envelope::default();
        let m = Mapping::default();
        let err = p.check_envelope(&e, &m, e.machine_zero).unwrap_err();
        assert!(
            err.starts_with("line 3: G-code point X151.000 Y0.000 Z5.000"),
            "{err}"
        );
        assert!(err.contains("robot X=151.000"), "{err}");
        // The same program fits when the part zero is 10 mm towards -X.
        let zero = [e.machine_zero[0] - 10.0, 0.0, -30.0];
        p.check_envelope(&e, &m, zero).unwrap();
    }

    proptest! {
        #[test]
        fn mapping_round_trips(perm in 0usize..6, signs in 0u8..8, p in proptest::array::uniform3(-1e4f64..1e4)) {
            let perms = [[0,1,2],[0,2,1],[1,0,2],[1,2,0],[2,0,1],[2,1,0]];
            let src = perms[perm];
            let spec = |i: usize| format!("{}{}", if signs & (1 << i) != 0 { "-" } else { "" }, AXES[src[i]]);
            let m = Mapping::from_json(&json!({"x": spec(0), "y": spec(1), "z": spec(2)})).unwrap();
            let r = m.map(p);
            for i in 0..3 {
                prop_assert_eq!(r[i].abs(), p[src[i]].abs());
            }
            prop_assert_eq!(m.unmap(r), p);
        }

        #[test]
        fn speed_is_always_within_the_clamp(feed in 0.0f64..1e6, lo in 0.1f64..20.0, span in 0.0f64..50.0) {
            let s = Speeds { rapid_mm_s: 10.0, cut_min_mm_s: lo, cut_max_mm_s: lo + span };
            let v = s.cutting(feed);
            prop_assert!(v >= lo && v <= lo + span);
            if feed / 60.0 >= lo && feed / 60.0 <= lo + span {
                prop_assert!((v - feed / 60.0).abs() < 1e-12);
            }
        }

        #[test]
        fn envelope_accepts_exactly_the_box(p in proptest::array::uniform3(-400f64..400.0)) {
            let e = Envelope::default();
            let inside = (0..3).all(|i| p[i] >= e.min[i] && p[i] <= e.max[i]);
            prop_assert_eq!(e.check(e.machine_zero, p).is_ok(), inside);
        }
    }
}

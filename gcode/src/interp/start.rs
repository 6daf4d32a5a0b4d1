//! Starting a program at a line ("run from line"): the modal state the lines before it leave
//! ([`Interpreter::state_at`]), and the reasons a start there cannot be made safely.

use super::{FeedMode, Interpreter, MotionMode};
use crate::flow::BlockKind;
use crate::{GcodeError, Motion, Plane, Point, SpindleDirection};
use serde::Serialize;
use std::io::BufRead;

/// The modal state in force when a line begins, as the lines before it left it: what a
/// controller must be set to before it can go on from that line (see
/// [`Interpreter::state_at`]). Coordinates are millimetres in the frame motions are given in
/// (program coordinates with the program's own G92/G52/G10 offsets folded in, in the active
/// work system), A in degrees.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ModalState {
    /// The line this is the state before.
    pub line: u32,
    /// G20 (true) or G21.
    pub inch: bool,
    pub plane: Plane,
    /// G90 (true) or G91.
    pub absolute: bool,
    /// G90.1 (true) or G91.1: arc centres absolute.
    pub arc_absolute: bool,
    pub feed_mode: FeedMode,
    /// The F word in force, converted to millimetres: mm/min in G94, mm/rev in G95, 1/min
    /// (no length) in G93; `None` when no F is in force (none yet, or the feed mode changed).
    pub feed: Option<f64>,
    /// The motion mode as its G number times ten (0 G0, 10 G1, 20 G2, 30 G3, 50 G5, 51 G5.1,
    /// 382..385 G38.2..G38.5, 730 G73, 810..890 G81..G89); `None` for G80 or none yet.
    pub motion: Option<u16>,
    /// The active work system: 1..6 = G54..G59, 7..9 = G59.1..G59.3.
    pub work_offset: u8,
    /// The G92/G52 offset in effect (mm; zero when none).
    pub g92_offset: Point,
    /// The same for A (degrees).
    pub g92_offset_a: f64,
    /// Work systems the program itself set with G10 L2/L20, and their origins as the program
    /// sees them (machine mm). Folded into the coordinates of every motion, like G92.
    pub work_offsets_set: Vec<WorkOffsetSet>,
    /// The tool selected by the last T word.
    pub tool: u32,
    /// The tool in the spindle (the last M6, or M61 Q).
    pub tool_in_spindle: u32,
    /// G43 H: the tool whose length offset is applied; `None` after G49 or before any G43.
    pub tool_length_offset: Option<u32>,
    pub spindle: SpindleDirection,
    /// The S word in force.
    pub rpm: f64,
    /// M7 / M8.
    pub mist: bool,
    pub flood: bool,
    /// Canned cycles retract to R (G99, true) or to the initial level (G98).
    pub retract_to_r: bool,
    /// Where the tool is when the line begins: the end of the last move before it (the
    /// compensated point after a G40), or the configured initial position when none moved.
    pub position: Point,
    /// The A axis, likewise (degrees).
    pub a: f64,
    /// The highest Z any move before the line reached (its end, or the top of an arc), in the
    /// frame of this state's work system (a move made in another one is converted with
    /// [`crate::Config::work_offsets`]); `None` when no move came before the line.
    pub highest_z: Option<f64>,
}

/// A work system the program set itself (G10 L2/L20).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct WorkOffsetSet {
    /// 1..9 = G54..G59.3.
    pub system: u8,
    /// Its origin, machine mm, as the program set it.
    pub origin: Point,
}

impl ModalState {
    /// The feed in force in mm/min: the F word in G94, F times the spindle speed in G95;
    /// `None` in G93 (inverse time gives no speed of its own) or when there is none.
    pub fn feed_mm_min(&self) -> Option<f64> {
        let f = self.feed?;
        match self.feed_mode {
            FeedMode::PerMinute => Some(f),
            FeedMode::PerRevolution if self.rpm > 0.0 => Some(f * self.rpm),
            _ => None,
        }
    }

    /// The state as G-code words, in the order LinuxCNC applies them: units, plane, distance
    /// modes, feed mode, work system, retract mode, tool, tool length offset, spindle, coolant,
    /// motion mode and feed, e.g. `G21 G17 G90 G91.1 G94 G54 G99 T1 M61 Q1 G43 H1 S5000 M3 M9
    /// G1 F1000`. Numbers in the program's units, as G-code would give them.
    pub fn words(&self) -> String {
        let unit = if self.inch { 25.4 } else { 1.0 };
        let mut w: Vec<String> = vec![
            if self.inch { "G20" } else { "G21" }.into(),
            match self.plane {
                Plane::XY => "G17",
                Plane::ZX => "G18",
                Plane::YZ => "G19",
            }
            .into(),
            if self.absolute { "G90" } else { "G91" }.into(),
            if self.arc_absolute { "G90.1" } else { "G91.1" }.into(),
            match self.feed_mode {
                FeedMode::PerMinute => "G94",
                FeedMode::InverseTime => "G93",
                FeedMode::PerRevolution => "G95",
            }
            .into(),
            match self.work_offset {
                s @ 1..=6 => format!("G{}", 53 + u16::from(s)),
                s => format!("G59.{}", s.saturating_sub(6)),
            },
            if self.retract_to_r { "G99" } else { "G98" }.into(),
        ];
        w.push(format!("T{}", self.tool));
        w.push(format!("M61 Q{}", self.tool_in_spindle));
        match self.tool_length_offset {
            Some(h) => w.push(format!("G43 H{h}")),
            None => w.push("G49".into()),
        }
        w.push(format!("S{}", number(self.rpm)));
        w.push(
            match self.spindle {
                SpindleDirection::Clockwise => "M3",
                SpindleDirection::CounterClockwise => "M4",
                SpindleDirection::Off => "M5",
            }
            .into(),
        );
        match (self.mist, self.flood) {
            (false, false) => w.push("M9".into()),
            (mist, flood) => {
                if mist {
                    w.push("M7".into());
                }
                if flood {
                    w.push("M8".into());
                }
            }
        }
        w.push(match self.motion {
            None => "G80".into(),
            Some(code) if code % 10 == 0 => format!("G{}", code / 10),
            Some(code) => format!("G{}.{}", code / 10, code % 10),
        });
        if let Some(f) = self.feed {
            let f = if self.feed_mode == FeedMode::InverseTime {
                f
            } else {
                f / unit
            };
            w.push(format!("F{}", number(f)));
        }
        w.join(" ")
    }
}

/// A number as G-code gives it: at most 4 decimals, no trailing zeros.
fn number(v: f64) -> String {
    let s = format!("{v:.4}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    if s == "-0" {
        "0".into()
    } else {
        s.to_string()
    }
}

/// Why a program cannot start at a line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum StartRefusalReason {
    /// The line is past the program's last line, or after its end (M2/M30).
    PastEnd,
    /// The line never runs where it stands (a subroutine's definition, a branch not taken):
    /// no motion leads to it.
    NotRun,
    /// The line is inside an O-word loop (`while`, `do`, `repeat`).
    Loop,
    /// The line runs inside a subroutine (O-word `call` or M98).
    Subroutine,
    /// Cutter radius compensation (G41/G42) is on when the line begins.
    CutterCompensation,
    /// The line repeats a canned cycle (L above 1).
    CannedCycleRepeat,
}

impl StartRefusalReason {
    /// A stable name for the reason (`past_end`, `not_run`, `loop`, `subroutine`,
    /// `cutter_compensation`, `canned_cycle_repeat`).
    pub fn name(self) -> &'static str {
        match self {
            StartRefusalReason::PastEnd => "past_end",
            StartRefusalReason::NotRun => "not_run",
            StartRefusalReason::Loop => "loop",
            StartRefusalReason::Subroutine => "subroutine",
            StartRefusalReason::CutterCompensation => "cutter_compensation",
            StartRefusalReason::CannedCycleRepeat => "canned_cycle_repeat",
        }
    }
}

/// A start at `line` that cannot be made safely, and why (`message` names the construct and
/// its line).
#[derive(Debug, Clone, PartialEq, Serialize, thiserror::Error)]
#[error("line {line}: {message}")]
pub struct StartRefusal {
    pub line: u32,
    pub reason: StartRefusalReason,
    pub message: String,
}

/// What [`Interpreter::state_at`] may answer instead of a state.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StartError {
    /// The program has an error before the line, or on it.
    #[error(transparent)]
    Gcode(#[from] GcodeError),
    #[error(transparent)]
    Refused(StartRefusal),
}

/// [`Interpreter::state_at`] under way.
#[derive(Debug, Clone)]
pub(crate) struct StartAt {
    line: u32,
    /// The interpreter stopped before running the line (it runs again next).
    reached: bool,
    /// A later line ran in the main program (no call, no loop) before it: it never runs.
    overtaken_by: Option<u32>,
    /// The line was passed over while skipping (the O-word construct, its keyword and line).
    passed_in: Option<(String, &'static str, u32)>,
}

impl<R: BufRead> Interpreter<R> {
    /// Called by `step` once a line is about to run while [`Interpreter::state_at`] looks for
    /// its line: whether to stop (the line is kept to run next).
    pub(super) fn stops_here(&mut self) -> bool {
        let Some(s) = self.start_at.as_mut() else {
            return false;
        };
        if s.reached || s.overtaken_by.is_some() {
            return false;
        }
        if let Some(skip) = &self.flow.skip {
            if self.line_no == s.line {
                let what = match skip.until.first() {
                    Some(crate::flow::Keyword::EndSub) => "sub",
                    Some(crate::flow::Keyword::ElseIf | crate::flow::Keyword::EndIf) => "if",
                    Some(crate::flow::Keyword::EndWhile) => "while",
                    Some(crate::flow::Keyword::EndRepeat) => "repeat",
                    _ => "search",
                };
                s.passed_in = Some((skip.name.clone(), what, skip.from_line));
            }
            return false;
        }
        if self.line_no == s.line {
            s.reached = true;
        } else if self.line_no > s.line
            && self.flow.frames.is_empty()
            && !self.flow.blocks.iter().any(|b| is_loop(b.kind))
        {
            s.overtaken_by = Some(self.line_no);
        } else {
            return false;
        }
        self.replay = true;
        true
    }

    /// Interprets the program up to `line` (1-based) without yielding the events of the lines
    /// before it (nothing before it is executed: only its modal effects count), and answers
    /// the modal state in force when `line` begins. Call it on a new interpreter, before
    /// taking any motion; afterwards the interpreter yields the events of `line` and of the
    /// program after it, in order, as it would have.
    ///
    /// `line` is the line where the program first runs in its main flow: a start inside a
    /// subroutine or an O-word loop is refused (the lines before it in the loop, or the
    /// caller, would never run again), as is one under cutter compensation (its path depends
    /// on the moves before), one on a canned cycle with L above 1 (which repeats were made is
    /// unknown), one past the program's end, and one on a line that never runs where it stands
    /// (a subroutine's definition, a branch not taken). The line itself is interpreted before
    /// this answers (so its errors and the L check come first); its events wait to be taken.
    /// After an error the interpreter is done (it yields nothing more).
    pub fn state_at(&mut self, line: u32) -> Result<ModalState, StartError> {
        let r = self.find_state(line);
        self.start_at = None;
        if r.is_err() {
            self.done = true;
            self.replay = false;
            self.queue.clear();
        }
        r
    }

    fn find_state(&mut self, line: u32) -> Result<ModalState, StartError> {
        let refuse = |reason, message: String| {
            Err(StartError::Refused(StartRefusal {
                line,
                reason,
                message,
            }))
        };
        if line == 0 {
            return refuse(
                StartRefusalReason::PastEnd,
                "lines are numbered from 1".into(),
            );
        }
        self.start_at = Some(StartAt {
            line,
            reached: false,
            overtaken_by: None,
            passed_in: None,
        });
        let offsets = self.cfg.work_offsets;
        // Highest machine Z of the moves before the line, and the work system they are in.
        let mut coord = self.st.coord;
        let mut highest: Option<f64> = None;
        let mut ended = None;
        loop {
            while let Some(m) = self.queue.pop_front() {
                let top = match &m {
                    Motion::WorkOffset { system, .. } => {
                        coord = system.saturating_sub(1).min(8);
                        None
                    }
                    Motion::ProgramEnd { line } => {
                        ended = Some(*line);
                        None
                    }
                    Motion::Arc { to, .. } => Some(
                        crate::ArcGeometry::from_motion(&m)
                            .map_or(to[2], |g| g.bounds().1[2].max(to[2])),
                    ),
                    other => other.end_point().map(|p| p[2]),
                };
                if let Some(z) = top {
                    let z = z + offsets[coord as usize][2];
                    highest = Some(highest.map_or(z, |h: f64| h.max(z)));
                }
            }
            let (reached, overtaken, passed) = match &self.start_at {
                Some(s) => (s.reached, s.overtaken_by, s.passed_in.clone()),
                None => (false, None, None),
            };
            if reached {
                break;
            }
            if overtaken.is_some() || self.done {
                let total = self.reader_line_no;
                return match (passed, ended) {
                    (Some((name, what, from)), _) => refuse(
                        StartRefusalReason::NotRun,
                        match what {
                            "sub" => format!(
                                "it is inside the definition of subroutine o<{name}> (line \
                                 {from}), which runs only when called: start at the line of a \
                                 call instead"
                            ),
                            "if" => format!(
                                "it is in a branch of o<{name}> if (line {from}) that is not \
                                 taken, so no motion leads to it"
                            ),
                            _ => format!(
                                "the program passes over it (o<{name}> from line {from}) \
                                 without running it, so no motion leads to it"
                            ),
                        },
                    ),
                    (None, Some(end)) if end < line => refuse(
                        StartRefusalReason::PastEnd,
                        format!("the program ends at line {end} (M2/M30), before this line"),
                    ),
                    (None, _) if total < line => refuse(
                        StartRefusalReason::PastEnd,
                        format!("past the end of the program ({total} lines)"),
                    ),
                    (None, _) => refuse(
                        StartRefusalReason::NotRun,
                        "the program never runs this line where it stands (it has no motion \
                         leading to it)"
                            .into(),
                    ),
                };
            }
            self.step()?;
        }
        let state = self.snapshot(line, highest.map(|h| h - offsets[coord as usize][2]));
        if let Some(f) = self.flow.frames.last() {
            let message = if f.m98_left.is_some() {
                format!(
                    "it runs inside subprogram O{} (M98 on line {}): a start there would \
                     return to a caller that never ran; start at line {} (the M98) instead",
                    f.name, f.call_line, f.call_line
                )
            } else {
                format!(
                    "it runs inside subroutine o<{}> (called on line {}): a start there would \
                     return to a caller that never ran; start at line {} (the call) instead",
                    f.name, f.call_line, f.call_line
                )
            };
            return refuse(StartRefusalReason::Subroutine, message);
        }
        if let Some(b) = self.flow.blocks.iter().rev().find(|b| is_loop(b.kind)) {
            let at = self.flow.prog.lines.get(b.start).map_or(0, |l| l.0);
            return refuse(
                StartRefusalReason::Loop,
                format!(
                    "it is inside the O-word loop o<{}> {} (line {at}): the passes before it \
                     would never run and the ones after would skip the lines before it; start \
                     at line {at} (the loop) or after its end",
                    b.name,
                    b.kind.keyword()
                ),
            );
        }
        if self.comp.side.is_some() {
            let on = self
                .comp_since
                .map_or(String::new(), |l| format!(" at line {l}"));
            return refuse(
                StartRefusalReason::CutterCompensation,
                format!(
                    "cutter radius compensation (G41/G42, turned on{on}) is on here: the \
                     offset path depends on the moves before; start before it is turned on or \
                     after the G40 that ends it"
                ),
            );
        }
        // The line itself runs now (its events wait to be taken), so that its errors and what
        // it repeats are known before anything moves.
        self.start_at = None;
        self.cycle_repeats = None;
        if self.replay {
            self.step()?;
        }
        if let Some((_, l)) = self.cycle_repeats.filter(|c| c.0 == line) {
            return refuse(
                StartRefusalReason::CannedCycleRepeat,
                format!(
                    "it repeats a canned cycle {} times (L{}): a run interrupted in it cannot \
                     tell which repeats were made, and a start there makes all of them again; \
                     start at the line after it",
                    number(l),
                    number(l)
                ),
            );
        }
        Ok(state)
    }

    /// The state before `line` runs (the interpreter stopped before it).
    fn snapshot(&self, line: u32, highest_z: Option<f64>) -> ModalState {
        let st = &self.st;
        let frame = self.frame();
        let mut pos = st.pos;
        // After G40 the tool is where compensation left it; the next move starts there.
        if let Some(d) = self.comp.detached {
            pos[0] = d[0];
            pos[1] = d[1];
        }
        let position = std::array::from_fn(|i| pos[i] + frame[i]);
        let work_offsets_set = (0..9)
            .filter(|&i| self.params.work_offsets[i] != self.cfg.work_offsets[i])
            .map(|i| WorkOffsetSet {
                system: i as u8 + 1,
                origin: self.params.work_offsets[i],
            })
            .collect();
        ModalState {
            line,
            inch: st.inch,
            plane: st.plane,
            absolute: st.absolute,
            arc_absolute: st.arc_absolute,
            feed_mode: st.feed_mode,
            feed: st.feed,
            motion: match st.motion {
                MotionMode::None => None,
                MotionMode::Rapid => Some(0),
                MotionMode::Linear => Some(10),
                MotionMode::Cw => Some(20),
                MotionMode::Ccw => Some(30),
                MotionMode::Unsupported(c)
                | MotionMode::Cycle(c)
                | MotionMode::Probe(c)
                | MotionMode::Spline(c) => Some(c),
            },
            work_offset: st.coord + 1,
            g92_offset: self.g92,
            g92_offset_a: self.g92_a,
            work_offsets_set,
            tool: st.tool,
            tool_in_spindle: st.spindle_tool,
            tool_length_offset: st.tlo,
            spindle: st.spindle,
            rpm: st.rpm,
            mist: st.mist,
            flood: st.flood,
            retract_to_r: self.cycle.retract_to_r,
            position,
            a: st.a + self.g92_a,
            highest_z,
        }
    }
}

fn is_loop(kind: BlockKind) -> bool {
    !matches!(kind, BlockKind::If { .. })
}

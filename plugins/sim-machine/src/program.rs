//! A loaded program: checked whole at load, then interpreted again as it runs, step by step, so
//! memory does not grow with the program (or with one huge arc).

use fresa_gcode::{
    budgeted, linearise, Budgeted, GcodeError, Interpreter, Linearise, ModalState, Motion,
    SpindleDirection, StartError,
};
use fresa_plugin_api::contract::WorkOffset;
use fresa_plugin_api::heightmap::HeightMap;
use std::io::{BufRead, Seek};

/// Chord tolerance for arcs, mm.
pub const ARC_TOLERANCE_MM: f64 = 0.002;

/// One thing the machine does for a source line.
#[derive(Debug, Clone, PartialEq)]
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
    /// M0 (M1 when `optional`): pause the run until resumed, with the line's `(MSG, ...)`.
    Pause {
        optional: bool,
        message: Option<String>,
    },
    /// M6: the tool the last T word selected goes into the spindle.
    ToolChange(u32),
    /// G43 H (the tool whose length applies) or G49 (`None`).
    ToolLength(Option<u32>),
    /// G54..G59 in the program: later moves use this offset.
    UseOffset(WorkOffset),
    /// M3/M4 (true) or M5: the spindle output.
    Spindle(bool),
    /// M7/M8/M9: the flood coolant output (the simulated machine has no mist output).
    Coolant { flood: bool },
    /// G38.2-G38.5: probe toward `to` (program coordinates) at `feed` until the probe closes
    /// (`contact`) or opens; `must_trip`: ending without that is an error of the run. The
    /// result goes back with [`Steps::probe_result`] before the next step is taken.
    Probe {
        to: [f64; 3],
        feed: f64,
        contact: bool,
        must_trip: bool,
    },
}

/// Where a plan's text comes from: the program file, kept open from load to run (so the run
/// reads what was checked), or a string (MDI lines, tests).
#[derive(Debug)]
enum Source {
    File(std::fs::File),
    Text(String),
}

/// A program, ready to run: what it needs to be interpreted again, step by step.
#[derive(Debug)]
pub struct Plan {
    /// Number of source lines (every one is acknowledged).
    pub lines: u32,
    source: Source,
    config: fresa_gcode::Config,
    max_segments: u64,
    /// M1 holds (the machine's optional stop is on).
    pub optional_stop: bool,
    /// M6 holds for a manual tool change, as this says; `None`: M6 passes.
    pub tool_change: Option<fresa_plugin_api::contract::ToolChangeSetup>,
    /// Added to every move's Z, in the work coordinates the program starts in (issue 25).
    pub height_map: Option<HeightMap>,
}

/// Why a program cannot run here.
#[derive(Debug, Clone, PartialEq)]
pub enum Refusal {
    /// A G-code error (the work budget's included), with line and column.
    Gcode(GcodeError),
    /// The program probes (at this line) and the machine has no probe input.
    NoProbe(u32),
    /// A move outside the travel: `line L: message`.
    Travel(String),
    /// The program cannot start at the line asked for (see `Interpreter::state_at`).
    Start(fresa_gcode::StartRefusal),
    /// Something a height-mapped program cannot do here: `line L: message`.
    HeightMap(String),
}

/// The steps of a [`Plan`] in execution order, each with its 1-based source line (<= `lines`).
pub struct Steps<'a> {
    motions: Linearise<Budgeted<Interpreter<Box<dyn BufRead + 'a>>>>,
    lines: u32,
}

impl Steps<'_> {
    /// What the probing step just taken found (program coordinates): the rest of the program
    /// is interpreted with it (#5061.., #5070, the tool's position).
    pub fn probe_result(&mut self, result: fresa_gcode::ProbeResult) {
        self.motions.inner_mut().inner_mut().probe_result(result);
    }
}

impl Iterator for Steps<'_> {
    type Item = Result<(u32, Step), GcodeError>;

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            let motion = match self.motions.next()? {
                Ok(m) => m,
                Err(e) => return Some(Err(e)),
            };
            let line = motion.line().clamp(1, self.lines.max(1));
            let Some(step) = step_of(motion) else {
                continue;
            };
            return Some(Ok((line, step)));
        }
    }
}

/// What a linearised motion does to the simulated machine; `None` for what does not move it.
fn step_of(motion: Motion) -> Option<Step> {
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
        Motion::Probe {
            to,
            feed_mm_min,
            contact,
            must_trip,
            ..
        } => Step::Probe {
            to,
            feed: feed_mm_min,
            contact,
            must_trip,
        },
        Motion::Dwell { seconds, .. } => Step::Dwell(seconds),
        Motion::Pause {
            optional, message, ..
        } => Step::Pause { optional, message },
        Motion::ToolChange { tool, .. } => Step::ToolChange(tool),
        Motion::ToolLengthOffset { tool, .. } => Step::ToolLength(tool),
        Motion::WorkOffset {
            system: system @ 1..=6,
            ..
        } => Step::UseOffset(WorkOffset::ALL[usize::from(system) - 1]),
        Motion::Spindle { direction, .. } => Step::Spindle(direction != SpindleDirection::Off),
        Motion::Coolant { flood, .. } => Step::Coolant { flood },
        // Messages, other work offset systems and the end of the program do not move the
        // simulated machine.
        _ => return None,
    };
    Some(step)
}

/// The interpreter settings of a plan. `initial_position` is where the tool is, in program
/// coordinates (X, Y, Z, A); `work_offsets` the machine origin of G54..G59 (XYZ); `tools` the
/// machine's tool table (G41/G42 `D`).
fn config(
    initial_position: [f64; 4],
    work_offsets: [[f64; 3]; 6],
    tools: fresa_gcode::ToolTable,
) -> fresa_gcode::Config {
    let [x, y, z, a] = initial_position;
    let mut config = fresa_gcode::Config {
        initial_position: [x, y, z],
        initial_a_deg: a,
        tools,
        ..Default::default()
    };
    config.work_offsets[..6].copy_from_slice(&work_offsets);
    config
}

/// A plan of `text` (an MDI line, a test program), within the default work budget.
pub fn plan(
    text: &str,
    initial_position: [f64; 4],
    work_offsets: [[f64; 3]; 6],
    tools: fresa_gcode::ToolTable,
) -> Plan {
    Plan {
        lines: u32::try_from(text.lines().count()).unwrap_or(u32::MAX),
        source: Source::Text(text.to_string()),
        config: config(initial_position, work_offsets, tools),
        max_segments: fresa_gcode::DEFAULT_MAX_SEGMENTS,
        optional_stop: false,
        tool_change: None,
        height_map: None,
    }
}

/// A plan of the program `file` of `lines` lines (see `kit::open_program`), within a work
/// budget of `max_segments`.
pub fn plan_file(
    file: std::fs::File,
    lines: u32,
    initial_position: [f64; 4],
    work_offsets: [[f64; 3]; 6],
    tools: fresa_gcode::ToolTable,
    max_segments: u64,
) -> Plan {
    Plan {
        lines,
        source: Source::File(file),
        config: config(initial_position, work_offsets, tools),
        max_segments,
        optional_stop: false,
        tool_change: None,
        height_map: None,
    }
}

impl Plan {
    /// The same plan within another work budget.
    pub fn with_max_segments(self, max_segments: u64) -> Plan {
        Plan {
            max_segments,
            ..self
        }
    }

    /// The same plan with the machine's run options: M1 holds when `optional_stop`, M6 holds
    /// for a tool change as `tool_change` says.
    pub fn with_run_options(
        self,
        optional_stop: bool,
        tool_change: Option<fresa_plugin_api::contract::ToolChangeSetup>,
    ) -> Plan {
        Plan {
            optional_stop,
            tool_change,
            ..self
        }
    }

    /// The length (mm) the tool table gives tool `tool` for G43 (0 when it has none).
    pub fn table_length(&self, tool: u32) -> f64 {
        self.config.tools.get(&tool).map_or(0.0, |t| t.length_mm)
    }

    /// The steps from the start of the program, interpreted as they are taken.
    pub fn steps(&self) -> Result<Steps<'_>, GcodeError> {
        Ok(self.steps_with(self.interpreter()?))
    }

    /// The steps from where the program first runs `line`, the lines before it interpreted for
    /// their modal state only (see `Interpreter::state_at`), and that state.
    pub fn steps_from(&self, line: u32) -> Result<(ModalState, Steps<'_>), StartError> {
        let mut interp = self.interpreter()?;
        let state = interp.state_at(line)?;
        Ok((state, self.steps_with(interp)))
    }

    /// A new interpreter of the program, from its first line.
    fn interpreter(&self) -> Result<Interpreter<Box<dyn BufRead + '_>>, GcodeError> {
        let reader: Box<dyn BufRead + '_> = match &self.source {
            Source::File(f) => {
                let mut f = f;
                f.rewind().map_err(|e| GcodeError {
                    line: 1,
                    column: 1,
                    kind: fresa_gcode::ErrorKind::Io,
                    message: format!("cannot read the program again: {e}"),
                })?;
                Box::new(std::io::BufReader::with_capacity(1 << 16, f))
            }
            Source::Text(t) => Box::new(t.as_bytes()),
        };
        Ok(Interpreter::new(reader, self.config.clone()))
    }

    /// The steps of `interp` from here, within the work budget.
    fn steps_with<'a>(&self, interp: Interpreter<Box<dyn BufRead + 'a>>) -> Steps<'a> {
        let budget = fresa_gcode::WorkBudget::new(self.max_segments, ARC_TOLERANCE_MM);
        Steps {
            motions: linearise(budgeted(interp, budget), ARC_TOLERANCE_MM),
            lines: self.lines,
        }
    }

    /// The same plan with `map` added to every move's Z.
    pub fn with_height_map(self, map: Option<HeightMap>) -> Plan {
        Plan {
            height_map: map,
            ..self
        }
    }

    /// Interprets the whole program once and checks every move from where it first runs
    /// `from_line` on against `check` (given machine coordinates), using `offsets` (the
    /// machine origins of G54..G59) starting in `active` (the lines before `from_line` only
    /// change the modal state, see `Interpreter::state_at`; a start there it refuses is
    /// refused). With a height map, each piece of each move as it will run (see
    /// [`Plan::map_move`]) is checked, and the pieces count against the work budget; a program
    /// that probes or selects another work offset is refused (the map's frame is the
    /// offset's, and a probe's result cannot be corrected). A G-code error anywhere wins over a
    /// move outside the travel (as when the program was interpreted whole before its moves
    /// were checked).
    /// A probing move is checked for its whole distance (it may trip anywhere along it, or not
    /// at all); the moves after it as if it ran its whole way (they may depend on its result);
    /// without a probe input (`has_probe`) the first one refuses the program.
    pub fn check(
        &self,
        (offsets, active): (&[[f64; 4]; 6], WorkOffset),
        start_a: f64,
        has_probe: bool,
        from_line: u32,
        check: impl Fn([f64; 4]) -> Result<(), String>,
    ) -> Result<(), Refusal> {
        if from_line > self.lines {
            return Ok(());
        }
        let (state, steps) = self.steps_from(from_line).map_err(|e| match e {
            StartError::Gcode(e) => Refusal::Gcode(e),
            StartError::Refused(r) => Refusal::Start(r),
        })?;
        let active = offset_of(state.work_offset).unwrap_or(active);
        let mut current = active;
        let mut machine_a = start_a;
        let mut outside = None;
        // G43: the tool length in force (from the lines before the start too), and the tool
        // it is of (a tool change under G43 puts the new tool's in force at cycle start).
        let mut tlo: Option<u32> = state.tool_length_offset;
        // Where the tool is when the program's own moves begin: where it stands, or (a start
        // at a line) where the preamble brings it, the program's position before that line;
        // with a map, as the program point a corrected path continues from.
        let start = if from_line > 1 {
            state.position
        } else {
            self.config.initial_position
        };
        let mut from = match &self.height_map {
            Some(map) => map.uncorrected(start),
            None => start,
        };
        let mut pieces: u64 = 0;
        for step in steps {
            let (line, step) = step.map_err(Refusal::Gcode)?;
            if outside.is_some() {
                continue;
            }
            let offset = with_tool_length(
                &offsets[current.index()],
                tlo.map_or(0.0, |t| self.table_length(t)),
            );
            if let Some(refusal) = self.height_map.as_ref().and_then(|_| match step {
                Step::Probe { .. } => Some(format!(
                    "line {line}: a height-mapped program cannot probe (G38.x): the map \
                     corrects programmed Z, not a probe's result"
                )),
                Step::UseOffset(o) if o != active => Some(format!(
                    "line {line}: {} while a height map applies: the map is in the work \
                     coordinates of {}, where the job started",
                    o.name(),
                    active.name()
                )),
                _ => None,
            }) {
                return Err(Refusal::HeightMap(refusal));
            }
            match step {
                Step::ToolLength(t) => tlo = t,
                Step::UseOffset(o) => current = o,
                Step::ToolChange(t) => {
                    let Some(setup) = &self.tool_change else {
                        continue;
                    };
                    if tlo.is_some() {
                        tlo = Some(t);
                    }
                    if let Some(p) = setup.position {
                        if let Err(m) = check([p.x, p.y, p.z, machine_a]) {
                            outside = Some(format!("line {line}: the tool-change position: {m}"));
                        }
                    }
                }
                Step::Move { to, a, .. } => {
                    let path = self.map_move(from, to, a, &offset, machine_a);
                    from = to;
                    pieces += path.len() as u64;
                    if pieces > self.max_segments {
                        return Err(Refusal::Gcode(GcodeError {
                            line,
                            column: 1,
                            kind: fresa_gcode::ErrorKind::Budget,
                            message: format!(
                                "work budget exceeded: the height map splits the program's \
                                 moves into more than {} pieces",
                                self.max_segments
                            ),
                        }));
                    }
                    for target in path {
                        machine_a = target[3];
                        if let Err(m) = check(target) {
                            outside = Some(format!("line {line}: {m}"));
                            break;
                        }
                    }
                }
                Step::Probe { .. } if !has_probe => return Err(Refusal::NoProbe(line)),
                Step::Probe { to, .. } => {
                    from = to;
                    if let Err(m) = check(machine_target(to, None, &offset, machine_a)) {
                        outside = Some(format!("line {line}: probing move: {m}"));
                    }
                }
                _ => {}
            }
        }
        outside.map_or(Ok(()), |m| Err(Refusal::Travel(m)))
    }
}

/// A work offset with a tool length offset (G43, mm) added to its Z: machine Z = program Z +
/// offset Z + tool length (a longer tool's spindle stays higher for the same tip position).
pub fn with_tool_length(offset: &[f64; 4], tool_length: f64) -> [f64; 4] {
    let mut o = *offset;
    o[2] += tool_length;
    o
}

/// The machine's work offset of work system `system` (1..6 = G54..G59); `None` for
/// G59.1..G59.3, which it does not have.
pub fn offset_of(system: u8) -> Option<WorkOffset> {
    usize::from(system)
        .checked_sub(1)
        .and_then(|i| WorkOffset::ALL.get(i))
        .copied()
}

impl Plan {
    /// The machine targets of one move from program point `from` to `to` (program A `a` when
    /// it turns A, from machine A `machine_a`) under `offset`: just the end without a height
    /// map; with one, the end of each piece the map splits it into, Z corrected, A turning
    /// along in proportion.
    pub fn map_move(
        &self,
        from: [f64; 3],
        to: [f64; 3],
        a: Option<f64>,
        offset: &[f64; 4],
        machine_a: f64,
    ) -> Vec<[f64; 4]> {
        let end = machine_target(to, a, offset, machine_a);
        let Some(map) = &self.height_map else {
            return vec![end];
        };
        map.corrected_path(from, to)
            .into_iter()
            .map(|(t, p)| {
                let a = machine_a + (end[3] - machine_a) * t;
                [p[0] + offset[0], p[1] + offset[1], p[2] + offset[2], a]
            })
            .collect()
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

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    /// The planner as it was before it streamed: every step of the program in one vector.
    fn whole(text: &str, start: [f64; 4], offsets: [[f64; 3]; 6]) -> Vec<(u32, Step)> {
        let lines = u32::try_from(text.lines().count()).unwrap_or(u32::MAX);
        let interp = Interpreter::new(text.as_bytes(), config(start, offsets, Default::default()));
        let mut steps = Vec::new();
        for motion in linearise(interp, ARC_TOLERANCE_MM) {
            let motion = motion.unwrap();
            let line = motion.line().clamp(1, lines.max(1));
            let Some(step) = step_of(motion) else {
                continue;
            };
            steps.push((line, step));
        }
        steps
    }

    /// The programs of the sim-machine's tests (tests/sim.rs and the black-box tests) and the
    /// shared corpus.
    fn programs() -> Vec<String> {
        let mut v: Vec<String> = [
            "G21 G90\nG0 X10 Y5 Z2\nG1 Z-1 F300\nG2 X20 Y5 I5 J0\nG3 X10 Y5 R5\nG4 P0.5\nM0\nG1 X0\nM30\n",
            "G90 G0 X1\nG55\nG0 X2\nG54 G1 X3 F100\nG59.1 G0 X4\nG56\nG0 A90 X1\nG1 A0 F3600\n",
            "G0 X5\nG2 I-5 P3 Z-3 F600\nG18 G3 X0 Z2 I-5 K0\nG19 G91 G2 Y10 J5 K0\nG90\n",
            "G91 G0 X1\nG0 X1\nG90 G81 X5 Y5 Z-1 R1 F100\nX6\nG80\n",
        ]
        .map(String::from)
        .to_vec();
        let mut back = String::from("G21 G90\n");
        for i in 0..200 {
            back.push_str(&format!("G1 X{} F600\n", i % 2));
        }
        v.push(back);
        let corpus =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/corpus/gcode");
        for e in std::fs::read_dir(&corpus).unwrap() {
            let text = std::fs::read_to_string(e.unwrap().path()).unwrap();
            // Only what interprets to the end (errors are compared below, by line).
            let ok = Interpreter::new(text.as_bytes(), Default::default()).all(|m| m.is_ok());
            if ok {
                v.push(text);
            }
        }
        v
    }

    #[test]
    fn streamed_steps_are_the_whole_plan_of_before() {
        let start = [1.0, -2.0, 3.0, 0.0];
        let offsets = [
            [0.0; 3],
            [10.0, 0.0, 0.0],
            [0.0; 3],
            [0.0; 3],
            [0.0; 3],
            [0.0; 3],
        ];
        for text in programs() {
            let plan = plan(&text, start, offsets, Default::default());
            let streamed: Vec<_> = plan.steps().unwrap().map(Result::unwrap).collect();
            assert_eq!(streamed, whole(&text, start, offsets), "{text:.80}");
            // A second pass (the run after the load's check) yields the same again.
            let again: Vec<_> = plan.steps().unwrap().map(Result::unwrap).collect();
            assert_eq!(again, streamed);
        }
        // From a file too.
        let dir = std::env::temp_dir().join(format!("fresa-sim-plan-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("p.nc");
        let text = &programs()[0];
        std::fs::write(&path, text).unwrap();
        let (file, lines) = fresa_plugin_api::kit::open_program(path.to_str().unwrap()).unwrap();
        let plan = plan_file(file, lines, start, offsets, Default::default(), 1000);
        for _ in 0..2 {
            let streamed: Vec<_> = plan.steps().unwrap().map(Result::unwrap).collect();
            assert_eq!(streamed, whole(text, start, offsets));
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn the_check_refuses_the_budget_gcode_errors_and_travel_naming_the_line() {
        let offsets = [[0.0; 4]; 6];
        let travel = |p: [f64; 4]| {
            if p[0] > 100.0 {
                Err(format!("X={} is outside the travel", p[0]))
            } else {
                Ok(())
            }
        };
        let check = |text: &str| {
            plan(text, [0.0; 4], [[0.0; 3]; 6], Default::default()).check(
                (&offsets, WorkOffset::G54),
                0.0,
                true,
                1,
                travel,
            )
        };
        assert_eq!(check("G0 X10\nG1 X20 F100\n"), Ok(()));
        assert_eq!(
            check("G0 X10\nG0 X200\n"),
            Err(Refusal::Travel(
                "line 2: X=200 is outside the travel".into()
            ))
        );
        // A G-code error later in the program wins, as before.
        match check("G0 X200\nG1 X1 Q3 F1\n") {
            Err(Refusal::Gcode(e)) => assert_eq!(e.line, 2),
            other => panic!("{other:?}"),
        }
        // ~3e8 chords: refused at its line before the first chord, in constant memory.
        match check("G0 X0 Y0\nG2 X0 Y0 I400000 J0 P10000 F100\n") {
            Err(Refusal::Gcode(e)) => {
                assert_eq!((e.line, e.kind), (2, fresa_gcode::ErrorKind::Budget), "{e}")
            }
            other => panic!("{other:?}"),
        }
    }
}

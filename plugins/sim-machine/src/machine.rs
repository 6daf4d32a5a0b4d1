//! The simulated machine: the shared state handling of `fresa_plugin_api::kit` plus the one
//! motion thread the machine owns. Requests only change state and queue work; the motion
//! thread moves the axes in small time slices, so stop and feed hold take effect within one
//! slice.

use crate::config::{Config, Switch};
use crate::program::{self, Plan, Refusal, Step};
use fresa_plugin_api::backend::{LoadProgram, MachineBackend};
use fresa_plugin_api::contract::{
    io, Axis, HoldKind, IoValue, MachineState, MachineStatus, OutputName, Overrides, Preamble,
    PreambleStep, Probe, ProgramLoaded, ProgramTool, SpindleTurn, ToolChangeHold, ToolChangeSetup,
};
use fresa_plugin_api::exec_log::ExecLog;
use fresa_plugin_api::kit::{
    self, Events, Interrupted, Job, KitConfig, Loaded, MdiMove, MotionThread,
};
use fresa_plugin_api::{Host, PluginError};
use serde_json::{json, Value};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

pub use fresa_plugin_api::kit::EventSink;

/// Most segments one MDI line may make: its moves are all checked, then queued together.
const MDI_MAX_SEGMENTS: u64 = 1_000_000;

/// How far past a probe switch's edge an instant (time-scale 0) machine stops, mm.
const EDGE_MM: f64 = 1e-6;

/// Which override a timed stretch follows.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Pace {
    /// Program and MDI feed moves (G1/G2/G3).
    Feed,
    /// G0 and go-to-zero.
    Rapid,
    /// Jogs, probing moves and dwells: no override.
    Fixed,
}

impl Pace {
    /// The speed factor (1 = programmed).
    fn rate(self, o: &Overrides) -> f64 {
        match self {
            Pace::Feed => o.feed / 100.0,
            Pace::Rapid => o.rapid / 100.0,
            Pace::Fixed => 1.0,
        }
    }
}

/// Longest time the motion thread goes without looking at stop / feed hold.
const SLICE: Duration = Duration::from_millis(5);
/// Longest gap between two program moves still taken up by the next (see `Core::flow`): a
/// few slices and the thread's scheduling, not a hold.
const FLOW_GAP: Duration = Duration::from_millis(50);

// The simulated machine keeps, beyond the kit's state (its outputs, spindle and flood coolant,
// and switch inputs are the kit's I/O maps), only its tools.
type Kit = kit::Kit<Plan, Tools>;
type State = kit::State<Plan, Tools>;

/// The tools: the physical one in the spindle, and the lengths the host's tool table gives
/// (what G43 applies).
#[derive(Debug, Default)]
struct Tools {
    /// Tool number in the spindle (0: none).
    spindle: u32,
    /// Tool table lengths, mm, from `load_program` and `set_tools`.
    table: std::collections::BTreeMap<u32, f64>,
    /// The tool whose length G43 put in force in the run under way (`None`: G49).
    g43: Option<u32>,
}

impl Tools {
    fn table_length(&self, tool: u32) -> f64 {
        self.table.get(&tool).copied().unwrap_or(0.0)
    }
}

/// The output's name in the status, or why the simulated machine has none of that name.
fn output_key(name: OutputName) -> Result<&'static str, PluginError> {
    match name {
        OutputName::Spindle => Ok(io::SPINDLE),
        OutputName::Coolant => Ok(io::COOLANT_FLOOD),
        OutputName::ZLift => Err(PluginError::new(
            "unsupported",
            format!("sim-machine has no output {:?}", name.as_str()),
        )),
    }
}

fn off_outputs() -> [(String, Option<IoValue>); 2] {
    [io::SPINDLE, io::COOLANT_FLOOD].map(|k| (k.to_string(), Some(IoValue::On(false))))
}

/// What a probing move watches: the probe switch (where the tool in the spindle meets it),
/// and the level that ends the move.
struct ProbeWatch {
    switch: Switch,
    active: bool,
}

/// A simulated 4-axis machine. Thread-safe; dropping it stops motion and joins its thread.
pub struct SimMachine {
    core: Arc<Core>,
    worker: MotionThread,
}

struct Core {
    cfg: Config,
    kit: Kit,
    /// When the last program move ended on the program's own timeline: the next one starts
    /// there, not when the motion thread got to it, so a program takes its nominal time
    /// (slice rounding and the time between two moves are not added to every move, which
    /// made jobs of many short moves run noticeably longer than their length at their feed).
    flow: Mutex<Option<Instant>>,
}

/// Length a feed applies to (LinuxCNC's rule): the XYZ path, or the A turn in degrees when
/// only A moves.
fn distance(a: &[f64; 4], b: &[f64; 4]) -> f64 {
    let xyz = a[..3]
        .iter()
        .zip(&b[..3])
        .map(|(x, y)| (x - y) * (x - y))
        .sum::<f64>()
        .sqrt();
    if xyz > 0.0 {
        xyz
    } else {
        (a[3] - b[3]).abs()
    }
}

impl Core {
    /// The switch as the machine meets it with tool `spindle` in: the `probe` switch is
    /// touched by the tool's tip, which a longer tool brings down further for the same
    /// machine Z, so on Z it trips that much higher up. Limits and the rest are the carriage's.
    fn as_met(&self, sw: &Switch, spindle: u32) -> Switch {
        let mut sw = sw.clone();
        if sw.name == io::PROBE && sw.axis == Axis::Z {
            sw.at += self.cfg.tool_length(spindle);
        }
        sw
    }

    /// The probe switch as the tool in the spindle meets it, if the machine has one.
    fn probe_switch(&self, spindle: u32) -> Option<Switch> {
        self.cfg
            .switches
            .iter()
            .find(|s| s.name == io::PROBE)
            .map(|s| self.as_met(s, spindle))
    }

    /// Reads the switches at the current position into the status. Answers the limit or
    /// e-stop that has just become active, if any (a switch that stays pressed trips once,
    /// so the axis can be jogged off it after a reset).
    fn sense(&self, sh: &mut State, ev: &mut Events) -> Option<String> {
        let mut trip = None;
        let spindle = sh.extra.spindle;
        let levels: Vec<(String, Option<bool>)> = self
            .cfg
            .switches
            .iter()
            .map(|sw| {
                let on = self.as_met(sw, spindle).active_at(&sh.pos);
                let was_on = sh.inputs.get(&sw.name) == Some(&Some(true));
                if on && !was_on && sw.trips() && trip.is_none() {
                    trip = Some(sw.name.clone());
                }
                (sw.name.clone(), Some(on))
            })
            .collect();
        sh.set_io(levels, [], ev);
        trip
    }

    // ----- motion thread -----

    fn worker(self: Arc<Self>) {
        while let Some(job) = self.kit.wait_for_job() {
            if let Job::Probe(p) = job {
                let result = catch_unwind(AssertUnwindSafe(|| self.run_probe(&p)))
                    .unwrap_or_else(|_| Err(Interrupted::Failed("internal error (panic)".into())));
                self.kit.finish_probe(p.id, result, |_| {});
                continue;
            }
            let run = job.run();
            let result = catch_unwind(AssertUnwindSafe(|| self.run_job(job)))
                .unwrap_or_else(|_| Err(Interrupted::Failed("internal error (panic)".into())));
            self.kit.finish_job(run, result, |sh| {
                // A program's end (M2/M30, the end of the file) or its abort stops the spindle
                // and the coolant, as a controller does; G43 ends with it.
                if run.is_some() {
                    sh.outputs.extend(off_outputs());
                    sh.extra.g43 = None;
                }
            });
        }
    }

    /// A move target the motion thread is about to start: outside the travel is an alarm
    /// (requests check before queueing, so this only guards against a bug).
    fn check(&self, target: [f64; 4]) -> Result<(), Interrupted> {
        self.cfg
            .check_travel(target)
            .map_err(|m| Interrupted::Alarm(format!("soft limit: {m}")))
    }

    fn run_job(&self, job: Job<Plan>) -> Result<(), Interrupted> {
        match job {
            Job::Jog(jog) => {
                let target = jog.target(self.kit.lock().pos);
                self.check(target)?;
                self.move_to(target, jog.feed, Pace::Fixed, false)
            }
            Job::GoToZero => {
                let path = self.kit.lock().go_to_zero_path();
                path.into_iter()
                    .try_for_each(|p| self.move_to(p, self.cfg.rapid_mm_min, Pace::Rapid, false))
            }
            Job::Mdi(moves) => {
                // An MDI line's feed is not left behind as the programmed feed.
                let feed = self.kit.lock().feed;
                let result = moves.iter().try_for_each(|m| {
                    self.check(m.to)?;
                    let pace = if m.rapid { Pace::Rapid } else { Pace::Feed };
                    self.move_to(m.to, m.feed, pace, false)
                });
                self.kit.lock().feed = feed;
                result
            }
            Job::Program(l) => self.run_program(l),
            // Taken apart by `worker` (a probe ends with its own report).
            Job::Probe(p) => self.run_probe(&p).map(drop),
        }
    }

    /// A probing move: toward the target at the probe's feed, watching the `probe` switch
    /// every slice. The trip is latched where the switch's edge lies between the last two
    /// slices (as a controller's probe input latches the position in hardware); motion stops in
    /// the slice that saw it, so it rests up to one slice's travel past the trip (at once in
    /// a time-scale 0 simulation).
    fn run_probe(&self, p: &Probe) -> Result<Option<[f64; 4]>, Interrupted> {
        let jog = kit::Jog {
            axis: p.axis,
            distance: p.distance,
            feed: p.feed,
        };
        self.probe_move(|start| jog.target(start), p.feed, p.until.wants_active())
    }

    /// One probing move from where the machine is to `target(start)` (machine coordinates),
    /// checked against the travel, until the `probe` switch reads `active`: the trip, if it
    /// did (a request's probe and a program's G38 share it).
    fn probe_move(
        &self,
        target: impl FnOnce([f64; 4]) -> [f64; 4],
        feed: f64,
        active: bool,
    ) -> Result<Option<[f64; 4]>, Interrupted> {
        let sh = self.kit.lock();
        let watch = self
            .probe_switch(sh.extra.spindle)
            .map(|switch| ProbeWatch { switch, active });
        let start = sh.pos;
        let target = target(start);
        self.check(target)?;
        let seconds = self.cfg.move_seconds(distance(&start, &target), feed);
        // A probe stops where it trips: off the program's timeline.
        let from = self.flow_start(false);
        self.timed_locked(
            sh,
            Some((start, target)),
            seconds,
            Some(feed),
            Pace::Fixed,
            watch.as_ref(),
            from,
        )
        .map(|(trip, _)| trip)
    }

    fn run_program(&self, l: Loaded<Plan>) -> Result<(), Interrupted> {
        // A run's timeline starts with its first move.
        self.flow_start(false);
        if l.start_line > l.plan.lines {
            // Every line was done before (a resume after the last one): nothing to run.
            return Ok(());
        }
        // Interpreted again as it runs (it was checked whole at load): memory stays flat. No
        // step is interpreted ahead of the one running (a probe's result feeds the next).
        let failed = |e: fresa_gcode::GcodeError| Interrupted::Failed(e.to_string());
        // The lines before the start line are interpreted but not executed: only their modal
        // effects carry over (a probe among them keeps the interpreter's assumption).
        let (state, mut steps) = l.plan.steps_from(l.start_line).map_err(|e| match e {
            fresa_gcode::StartError::Gcode(e) => failed(e),
            fresa_gcode::StartError::Refused(r) => Interrupted::Failed(r.to_string()),
        })?;
        self.kit.with(|sh, _| {
            if let Some(o) = program::offset_of(state.work_offset) {
                sh.active = o;
            }
            if let Some(f) = state.feed_mm_min() {
                sh.feed = f;
            }
            // G43 as the lines before the start left it.
            sh.extra.g43 = state.tool_length_offset;
            sh.tool_length_offset = state
                .tool_length_offset
                .map_or(0.0, |t| sh.extra.table_length(t));
        });
        if let Some(p) = &l.preamble {
            self.run_preamble(l.run, p, l.plan.height_map.as_ref())?;
        }
        let mut ahead: Option<(u32, Step)> = None;
        for line in l.start_line..=l.plan.lines {
            // No new line starts while held or after a stop, even one without motion.
            self.kit.line_gate()?;
            self.kit.with(|sh, _| sh.line = Some(line));
            loop {
                let (step_line, step) = match ahead.take() {
                    Some(s) => s,
                    None => match steps.next() {
                        Some(next) => next.map_err(failed)?,
                        None => break,
                    },
                };
                if step_line > line {
                    ahead = Some((step_line, step));
                    break;
                }
                match step {
                    Step::Probe {
                        to,
                        feed,
                        contact,
                        must_trip,
                    } => {
                        let result = self.program_probe(step_line, to, feed, contact, must_trip)?;
                        steps.probe_result(result);
                    }
                    Step::Pause { optional, message } => {
                        if !optional || l.plan.optional_stop {
                            self.program_stop(step_line, optional, message)?;
                        }
                    }
                    Step::ToolChange(tool) => {
                        if let Some(setup) = &l.plan.tool_change {
                            self.tool_change(step_line, tool, setup)?;
                        }
                    }
                    step => self.run_step(&l.plan, &step)?,
                }
            }
            self.kit.lines_done(l.run, line..=line, Vec::new())?;
        }
        Ok(())
    }

    /// The preamble of a run that goes on from inside the program: each step in order (a
    /// pause holds between steps and within a move, a stop ends it), each recorded in the
    /// execution log as `{"run":R,"preamble_step":I,"step":{...},"from":[x,y,z,a],"to":[...]}`
    /// (machine positions before and after it), so the approach can be checked afterwards.
    /// With a height map, each move's Z gets the map's correction under its end (its work
    /// X/Y), so the approach ends where the corrected program goes on.
    fn run_preamble(
        &self,
        run: i64,
        p: &Preamble,
        map: Option<&fresa_plugin_api::heightmap::HeightMap>,
    ) -> Result<(), Interrupted> {
        for (i, step) in p.steps.iter().enumerate() {
            self.kit.line_gate()?;
            let from = self.kit.lock().pos;
            match *step {
                PreambleStep::Offset { offset } => self.kit.with(|sh, ev| {
                    if sh.active != offset {
                        sh.active = offset;
                        sh.push_status(ev);
                    }
                }),
                PreambleStep::Spindle { direction, .. } => {
                    self.set_output(io::SPINDLE, direction != SpindleTurn::Off)
                }
                PreambleStep::Coolant { flood, .. } => self.set_output(io::COOLANT_FLOOD, flood),
                PreambleStep::Move { feed, .. } => {
                    let Some(mut to) = step.target(from) else {
                        continue;
                    };
                    if let Some(map) = map {
                        let offset = {
                            let sh = self.kit.lock();
                            program::with_tool_length(
                                &sh.offsets[sh.active.index()],
                                sh.tool_length_offset,
                            )
                        };
                        to[2] += map.correction(to[0] - offset[0], to[1] - offset[1]);
                    }
                    self.check(to)?;
                    match feed {
                        Some(f) => self.move_to(to, f, Pace::Feed, false)?,
                        None => self.move_to(to, self.cfg.rapid_mm_min, Pace::Rapid, false)?,
                    }
                }
            }
            let to = self.kit.lock().pos;
            self.kit.log_record(&json!({
                "run": run, "preamble_step": i + 1, "step": step, "from": from, "to": to,
            }))?;
        }
        Ok(())
    }

    /// Switches one of the simulated outputs (spindle, flood coolant); the change shows at once.
    fn set_output(&self, key: &str, on: bool) {
        self.kit
            .with(|sh, ev| sh.set_io([], [(key.to_string(), Some(IoValue::On(on)))], ev));
    }

    /// A probing move of a program (G38.2-G38.5), in program coordinates: what it found, for
    /// the rest of the program. G38.2/G38.4 fail the run when the probe already reads what
    /// they look for or never does; G38.3/G38.5 then go on (tripped at once, or untripped at
    /// the end).
    fn program_probe(
        &self,
        line: u32,
        to: [f64; 3],
        feed: f64,
        contact: bool,
        must_trip: bool,
    ) -> Result<fresa_gcode::ProbeResult, Interrupted> {
        let name = match (contact, must_trip) {
            (true, true) => "G38.2",
            (true, false) => "G38.3",
            (false, true) => "G38.4",
            (false, false) => "G38.5",
        };
        let (offset, start, switch) = {
            let sh = self.kit.lock();
            let offset =
                program::with_tool_length(&sh.offsets[sh.active.index()], sh.tool_length_offset);
            (offset, sh.pos, self.probe_switch(sh.extra.spindle))
        };
        let program = |m: [f64; 4]| [m[0] - offset[0], m[1] - offset[1], m[2] - offset[2]];
        let Some(switch) = switch else {
            return Err(Interrupted::Failed(format!(
                "line {line}: {name} but this machine has no probe input"
            )));
        };
        if switch.active_at(&start) == contact {
            if must_trip {
                return Err(Interrupted::Failed(format!(
                    "line {line}: {name}: the probe is already {} at the start",
                    if contact { "in contact" } else { "open" }
                )));
            }
            let here = program(start);
            return Ok(fresa_gcode::ProbeResult {
                tripped: true,
                trip: here,
                rest: here,
            });
        }
        let trip = self.probe_move(
            |from| program::machine_target(to, None, &offset, from[3]),
            feed,
            contact,
        )?;
        if trip.is_none() && must_trip {
            return Err(Interrupted::Failed(format!(
                "line {line}: {name} ended without the probe {} (moved its whole way to \
                 X{:.3} Y{:.3} Z{:.3})",
                if contact { "touching" } else { "opening" },
                to[0],
                to[1],
                to[2]
            )));
        }
        let rest = program(self.kit.lock().pos);
        Ok(fresa_gcode::ProbeResult {
            tripped: trip.is_some(),
            trip: trip.map_or(to, program),
            rest,
        })
    }

    fn run_step(&self, plan: &Plan, step: &Step) -> Result<(), Interrupted> {
        match *step {
            Step::Move { to, a, feed } => {
                // With a height map the move runs as the pieces the map splits it into, each
                // with its Z corrected, from where the machine stands (its program point
                // found by taking the correction off again: exact, the correction depending on
                // X and Y only).
                let targets = {
                    let sh = self.kit.lock();
                    let offset = program::with_tool_length(
                        &sh.offsets[sh.active.index()],
                        sh.tool_length_offset,
                    );
                    let here: [f64; 3] = std::array::from_fn(|i| sh.pos[i] - offset[i]);
                    let from = plan
                        .height_map
                        .as_ref()
                        .map_or(here, |m| m.uncorrected(here));
                    plan.map_move(from, to, a, &offset, sh.pos[3])
                };
                for target in targets {
                    self.check(target)?;
                    match feed {
                        Some(f) => self.move_to(target, f, Pace::Feed, true)?,
                        None => self.move_to(target, self.cfg.rapid_mm_min, Pace::Rapid, true)?,
                    }
                }
                Ok(())
            }
            Step::Dwell(seconds) => self.timed(
                None,
                seconds.max(0.0) * self.cfg.time_scale,
                0.0,
                Pace::Fixed,
                true,
            ),
            Step::ToolLength(t) => {
                self.kit.with(|sh, ev| {
                    sh.extra.g43 = t;
                    sh.tool_length_offset = t.map_or(0.0, |t| sh.extra.table_length(t));
                    sh.push_status(ev);
                });
                Ok(())
            }
            Step::Spindle(on) => {
                self.set_output(io::SPINDLE, on);
                Ok(())
            }
            Step::UseOffset(o) => {
                self.kit.with(|sh, ev| {
                    if sh.active != o {
                        sh.active = o;
                        sh.push_status(ev);
                    }
                });
                Ok(())
            }
            Step::Coolant { flood } => {
                self.set_output(io::COOLANT_FLOOD, flood);
                Ok(())
            }
            // Taken apart by `run_program` (a probe's result feeds the interpreter; pauses
            // and tool changes follow the run's options).
            Step::Probe { .. } | Step::Pause { .. } | Step::ToolChange(_) => Err(
                Interrupted::Failed("internal error: a program step outside a program".into()),
            ),
        }
    }

    /// M0, or M1 with the optional stop on: the run holds, saying why, until cycle start.
    fn program_stop(
        &self,
        line: u32,
        optional: bool,
        message: Option<String>,
    ) -> Result<(), Interrupted> {
        let (code, kind, what) = if optional {
            ("M1", HoldKind::OptionalStop, "optional stop")
        } else {
            ("M0", HoldKind::ProgramPause, "program pause")
        };
        let text = format!(
            "{code} at line {line}: {}",
            message.as_deref().unwrap_or(what)
        );
        let hold = kit::program_hold(kind, text, Some(line), message);
        self.kit.with(|sh, ev| self.kit.program_hold(sh, ev, hold));
        self.timed(None, 0.0, 0.0, Pace::Fixed, false)
    }

    /// M6 with tool-change holds on: the spindle stops, the machine goes to the change
    /// position (Z first), the operator puts tool `tool` in (the simulation's spindle holds
    /// it from here on) and the run holds; jogs and probing moves are carried out meanwhile.
    /// Cycle start puts the new tool's length in force if G43 is, and goes back to where the
    /// tool tip was at M6 (up to a safe Z, across, down), then on.
    fn tool_change(
        &self,
        line: u32,
        tool: u32,
        setup: &ToolChangeSetup,
    ) -> Result<(), Interrupted> {
        // Where the tip was, in program coordinates, and whether G43 is in force.
        let (held, from, g43) = self.kit.with(|sh, ev| {
            sh.set_io(
                [],
                [(io::SPINDLE.to_string(), Some(IoValue::On(false)))],
                ev,
            );
            let off =
                program::with_tool_length(&sh.offsets[sh.active.index()], sh.tool_length_offset);
            let held: [f64; 4] = std::array::from_fn(|i| sh.pos[i] - off[i]);
            let g43 = sh.extra.g43.is_some();
            (held, sh.extra.spindle, g43)
        });
        let start = self.kit.lock().pos;
        let change_z = setup.position.map(|p| p.z);
        if let Some(p) = setup.position {
            let safe = start[2].max(p.z);
            let path = [
                [start[0], start[1], safe, start[3]],
                [p.x, p.y, safe, start[3]],
                [p.x, p.y, p.z, start[3]],
            ];
            path.iter().try_for_each(|w| self.check(*w))?;
            path.into_iter()
                .try_for_each(|w| self.move_to(w, self.cfg.rapid_mm_min, Pace::Rapid, false))?;
        }
        let message = match from {
            0 => format!("M6 at line {line}: put tool T{tool} in"),
            f if f == tool => format!("M6 at line {line}: tool T{tool} again"),
            f => format!("M6 at line {line}: change tool T{f} for T{tool}"),
        };
        let mut hold = kit::program_hold(HoldKind::ToolChange, message, Some(line), None);
        hold.tool_change = Some(ToolChangeHold {
            from: (from != 0).then_some(from),
            to: tool,
            length_compensation: g43,
            from_description: None,
            to_description: None,
        });
        self.kit.with(|sh, ev| {
            sh.extra.spindle = tool;
            // The new tool meets the probe switch at its own height.
            self.sense(sh, ev);
            self.kit.program_hold(sh, ev, hold);
        });
        self.kit.serve_tool_change(|job| match job {
            Job::Jog(jog) => {
                let target = jog.target(self.kit.lock().pos);
                self.check(target)?;
                self.move_to(target, jog.feed, Pace::Fixed, false)
                    .map(|()| None)
            }
            Job::Probe(p) => self.run_probe(p),
            // The kit queues nothing else during a tool-change hold.
            _ => Ok(None),
        })?;
        // Cycle start: the new tool's length under G43, then back to where the tip was.
        let (target, here) = self.kit.with(|sh, ev| {
            if g43 {
                sh.extra.g43 = Some(tool);
                sh.tool_length_offset = sh.extra.table_length(tool);
                sh.push_status(ev);
            }
            let off =
                program::with_tool_length(&sh.offsets[sh.active.index()], sh.tool_length_offset);
            let target: [f64; 4] = std::array::from_fn(|i| held[i] + off[i]);
            (target, sh.pos)
        });
        let safe = here[2].max(target[2]).max(change_z.unwrap_or(f64::MIN));
        let path = [
            [here[0], here[1], safe, here[3]],
            [target[0], target[1], safe, target[3]],
            target,
        ];
        path.iter().try_for_each(|w| self.check(*w))?;
        path.into_iter()
            .try_for_each(|w| self.move_to(w, self.cfg.rapid_mm_min, Pace::Rapid, false))
    }

    /// A straight move at `feed` (mm/min, before the override `pace` names).
    /// A straight move at `feed`; `flow`: a program's move, on the program's timeline (see
    /// `Core::flow`).
    fn move_to(
        &self,
        target: [f64; 4],
        feed: f64,
        pace: Pace,
        flow: bool,
    ) -> Result<(), Interrupted> {
        let start = self.kit.lock().pos;
        let seconds = self.cfg.move_seconds(distance(&start, &target), feed);
        self.timed(Some((start, target)), seconds, feed, pace, flow)
    }

    /// Where the probe switch's edge lies on the slice from `a` to `b`, if the switch reads
    /// what the probe waits for at `b`. The edge is where the axis meets the switch's level
    /// (a surface's height under the tool): exact for a move along the switch's axis, and
    /// for any straight move across a tilted plane.
    fn probe_trip(watch: &ProbeWatch, a: [f64; 4], b: [f64; 4]) -> Option<[f64; 4]> {
        let sw = &watch.switch;
        if sw.active_at(&b) != watch.active {
            return None;
        }
        if sw.circle.is_some() {
            // A round wall: where along the slice its state changes, by halving (to well
            // below a micrometre), the point on the side that reads what the probe waits for.
            let at = |t: f64| -> [f64; 4] { std::array::from_fn(|k| a[k] + (b[k] - a[k]) * t) };
            let (mut lo, mut hi) = (0.0, 1.0);
            for _ in 0..60 {
                let mid = (lo + hi) / 2.0;
                if sw.active_at(&at(mid)) == watch.active {
                    hi = mid;
                } else {
                    lo = mid;
                }
            }
            return Some(at(hi));
        }
        let i = sw.axis.index();
        let (fa, fb) = (a[i] - sw.level_at(&a), b[i] - sw.level_at(&b));
        let t = if fa == fb {
            0.0
        } else {
            (fa / (fa - fb)).clamp(0.0, 1.0)
        };
        Some(std::array::from_fn(|k| a[k] + (b[k] - a[k]) * t))
    }

    /// Spends `seconds` (already scaled) of un-held time, moving linearly from `start` to
    /// `target` when given. Holds while the machine is paused; returns early on abort.
    fn timed(
        &self,
        path: Option<([f64; 4], [f64; 4])>,
        seconds: f64,
        feed: f64,
        pace: Pace,
        flow: bool,
    ) -> Result<(), Interrupted> {
        let sh = self.kit.lock();
        let feed = path.map(|_| feed);
        let from = self.flow_start(flow);
        let ended = self.timed_locked(sh, path, seconds, feed, pace, None, from);
        if let (true, Ok((_, end))) = (flow, &ended) {
            *self.flow.lock().unwrap_or_else(|e| e.into_inner()) = *end;
        }
        ended.map(drop)
    }

    /// Where a move starts on the timeline: where the last program move ended, for a program's
    /// move that follows it closely; now for anything else (and the timeline is broken off).
    /// A longer gap is a real stop (a hold between lines), not the motion thread's own delay.
    fn flow_start(&self, flow: bool) -> Instant {
        let last = self.flow.lock().unwrap_or_else(|e| e.into_inner()).take();
        let now = Instant::now();
        match last {
            Some(t) if flow && t <= now && now.duration_since(t) <= FLOW_GAP => t,
            _ => now,
        }
    }

    /// [`Core::timed`] under the lock, its time counted from `from`; `probe` ends the move
    /// early where the probe switch changes, answering the trip position. Also answers when
    /// the move ended on its own timeline (`None` when it did not run its whole way in time).
    #[allow(clippy::too_many_arguments)]
    fn timed_locked<'a>(
        &'a self,
        mut sh: MutexGuard<'a, State>,
        path: Option<([f64; 4], [f64; 4])>,
        seconds: f64,
        feed: Option<f64>,
        pace: Pace,
        probe: Option<&ProbeWatch>,
        from: Instant,
    ) -> Result<(Option<[f64; 4]>, Option<Instant>), Interrupted> {
        if let Some(f) = feed {
            sh.feed = f;
        }
        let mut done = 0.0;
        let mut last = from;
        loop {
            if self.kit.aborted() || sh.shutdown {
                return Err(Interrupted::Aborted);
            }
            if sh.state == MachineState::Paused {
                // Feed hold: the position stays where the last slice left it.
                self.kit.note_held(&mut sh);
                sh = self.kit.wait(sh);
                last = Instant::now();
                continue;
            }
            // `done` is the move's own (nominal) time: an override read every slice makes it
            // run slower or faster from this slice on. No acceleration is simulated, so the
            // new speed applies at once.
            let rate = pace.rate(&sh.overrides);
            let now = Instant::now();
            done += now.duration_since(last).as_secs_f64() * rate;
            last = now;
            let frac = if seconds <= 0.0 {
                1.0
            } else {
                (done / seconds).min(1.0)
            };
            if let Some((a, b)) = path {
                let before = sh.pos;
                sh.pos = if frac >= 1.0 {
                    b
                } else {
                    std::array::from_fn(|i| a[i] + (b[i] - a[i]) * frac)
                };
                let trip = probe.and_then(|w| Self::probe_trip(w, before, sh.pos));
                if let Some(at) = trip {
                    if seconds <= 0.0 {
                        sh.pos = at;
                        // An instant machine stops at the first point past the edge: on the
                        // edge itself an inclusive switch still reads closed after a release.
                        if let Some(w) = probe.filter(|w| w.switch.active_at(&at) != w.active) {
                            let i = w.switch.axis.index();
                            sh.pos[i] += EDGE_MM.copysign(b[i] - a[i]);
                        }
                    }
                    let mut ev = Vec::new();
                    self.sense(&mut sh, &mut ev);
                    sh.push_status(&mut ev);
                    self.kit.release(sh, ev);
                    return Ok((Some(at), None));
                }
                if !self.cfg.switches.is_empty() {
                    let mut ev = Vec::new();
                    let trip = self.sense(&mut sh, &mut ev);
                    if !ev.is_empty() {
                        self.kit.release(sh, ev);
                        sh = self.kit.lock();
                    }
                    if let Some(input) = trip {
                        // Motion ends in the slice that reached the switch.
                        let at = sh.pos;
                        return Err(Interrupted::Tripped {
                            message: format!(
                                "input {input} tripped at X{:.3} Y{:.3} Z{:.3} A{:.3}",
                                at[0], at[1], at[2], at[3]
                            ),
                            input,
                        });
                    }
                }
                let due = sh
                    .last_status
                    .is_none_or(|t| now.duration_since(t) >= self.cfg.status_interval);
                if due {
                    let mut ev = Vec::new();
                    sh.push_status(&mut ev);
                    self.kit.release(sh, ev);
                    sh = self.kit.lock();
                }
            }
            if frac >= 1.0 {
                // The move's nominal end, before `now` by the time run past it.
                let over = Duration::try_from_secs_f64((done - seconds).max(0.0) / rate)
                    .unwrap_or_default();
                return Ok((None, now.checked_sub(over)));
            }
            // Finite: travel checks bound every distance, and feeds are positive.
            let wait = Duration::try_from_secs_f64((seconds - done) / rate)
                .unwrap_or(SLICE)
                .min(SLICE);
            sh = self.kit.wait_timeout(sh, wait);
        }
    }
}

impl SimMachine {
    /// Creates a machine from its JSON config; its events go to `sink`.
    pub fn new(config: &Value, sink: EventSink) -> Result<SimMachine, PluginError> {
        let cfg = Config::from_json(config)?;
        let log = match &cfg.execution_log {
            Some(path) => Some(ExecLog::open(path)?),
            None => None,
        };
        let kit_cfg = KitConfig {
            jog_feed_mm_min: cfg.jog_feed_mm_min,
            travel: cfg.travel,
        };
        let tools = Tools {
            spindle: cfg.tool,
            ..Tools::default()
        };
        let core = Arc::new(Core {
            cfg,
            kit: Kit::new(kit_cfg, sink, log, tools),
            flow: Mutex::new(None),
        });
        core.kit.with(|sh, ev| {
            sh.set_io([], off_outputs(), ev);
            core.sense(sh, ev);
        });
        let worker_core = Arc::clone(&core);
        let worker = MotionThread::spawn("sim-machine motion", move || worker_core.worker())?;
        Ok(SimMachine { core, worker })
    }

    fn kit(&self) -> &Kit {
        &self.core.kit
    }

    /// Switches spindle or coolant (`None` = toggle). Switching on is refused in alarm;
    /// switching off never is. Answers the new state.
    fn output(&self, name: OutputName, on: Option<bool>) -> Result<Value, PluginError> {
        let key = output_key(name)?;
        self.kit().with(|sh, ev| {
            sh.require_online()?;
            let current = sh.outputs.get(key) == Some(&Some(IoValue::On(true)));
            let new = on.unwrap_or(!current);
            if new && !current {
                sh.require_no_alarm(&format!("switch the {} on", name.as_str()))?;
            }
            sh.set_io([], [(key.to_string(), Some(IoValue::On(new)))], ev);
            Ok(json!({"output": name, "on": new}))
        })
    }
}

impl MachineBackend for SimMachine {
    fresa_plugin_api::kit_backend_methods!();

    fn create(host: Host, config: Value) -> Result<Self, PluginError> {
        SimMachine::new(&config, Arc::new(move |event| host.emit(event)))
    }

    fn connect(&self) -> Result<MachineStatus, PluginError> {
        Ok(self
            .kit()
            .connect(self.core.cfg.alarm_at_connect.as_deref()))
    }

    /// The simulated machine changes speed at once (no acceleration is simulated) and runs
    /// G0 at its `rapid_mm_min`; its time is that, times `time_scale`.
    fn motion_profile(&self) -> Result<fresa_plugin_api::contract::MotionProfile, PluginError> {
        Ok(fresa_plugin_api::contract::MotionProfile {
            rapid_mm_min: self.core.cfg.rapid_mm_min,
            min_feed_mm_min: 0.0,
            max_feed_mm_min: 0.0,
            accel_mm_s2: 0.0,
            corner_jump_mm_s: 0.0,
            per_axis: false,
        })
    }

    // The simulated machine has no part zero of its own to compare.
    fn load_program(&self, p: LoadProgram) -> Result<ProgramLoaded, PluginError> {
        let kit = self.kit();
        let start = kit.logged_start(p.run, p.start_line)?;
        let (work, offsets, active, pos) = {
            let sh = kit.lock();
            sh.require_still("load a program")?;
            let st = sh.status();
            (st.work_position.to_array(), sh.offsets, sh.active, sh.pos)
        };
        // The preamble's moves are checked with the program's: the A axis the program starts
        // from is where the approach leaves it.
        let approach = match &p.preamble {
            Some(pre) => kit.check_preamble(pos, pre)?,
            None => Vec::new(),
        };
        let a = approach.last().map_or(pos[3], |m| m.0[3]);
        let (file, lines) = kit::open_program(&p.path)?;
        let xyz = offsets.map(|o| [o[0], o[1], o[2]]);
        let tools =
            fresa_gcode::tool_table(p.tools.iter().map(|t| (t.tool, t.diameter_mm, t.length_mm)));
        let budget = p.max_segments.unwrap_or(fresa_gcode::DEFAULT_MAX_SEGMENTS);
        if let Some(map) = &p.height_map {
            map.validate().map_err(PluginError::invalid)?;
        }
        let table: std::collections::BTreeMap<u32, f64> =
            tools.iter().map(|(n, t)| (*n, t.length_mm)).collect();
        let plan = program::plan_file(file, lines, work, xyz, tools, budget)
            .with_run_options(p.optional_stop, p.tool_change)
            .with_height_map(p.height_map);
        let has_probe = self.core.cfg.switches.iter().any(|s| s.name == io::PROBE);
        plan.check((&offsets, active), a, has_probe, start, |p| {
            self.core.cfg.check_travel(p)
        })
        .map_err(|r| match r {
            Refusal::NoProbe(line) => PluginError::new(
                "unsupported",
                format!(
                    "line {line} probes (G38.x) but this machine has no probe input \
                         (configure a `probe` switch)"
                ),
            ),
            Refusal::Gcode(e) if e.kind == fresa_gcode::ErrorKind::Budget => PluginError::new(
                "work_budget_exceeded",
                format!("{e}; the budget is the server's `max_program_segments`"),
            ),
            Refusal::Gcode(e) => PluginError::new("invalid_program", e.to_string()),
            Refusal::Travel(m) => PluginError::new("out_of_travel", m),
            Refusal::Start(r) => PluginError::new("start_refused", r.to_string()),
            Refusal::HeightMap(m) => PluginError::new("unsupported", m),
        })?;
        let mapped = plan.height_map.is_some();
        let mut loaded =
            kit.install_plan_with(p.run, plan, (lines, p.start_line, start), p.preamble)?;
        loaded.height_map = mapped;
        kit.with(|sh, _| sh.extra.table = table);
        Ok(loaded)
    }

    /// The tool table's lengths G43 applies, from now on (in a run too: a tool measured
    /// during a tool-change hold).
    fn set_tools(&self, tools: Vec<ProgramTool>) -> Result<(), PluginError> {
        if let Some(t) = tools.iter().find(|t| !t.length_mm.is_finite()) {
            return Err(PluginError::invalid(format!(
                "tool {}: length_mm must be a finite number",
                t.tool
            )));
        }
        self.kit().with(|sh, _| {
            sh.extra.table = tools.iter().map(|t| (t.tool, t.length_mm)).collect();
        });
        Ok(())
    }

    fn reset(&self) -> Result<(), PluginError> {
        self.kit().reset(|sh| {
            // As a controller's reset does: spindle and coolant off. (The status event goes
            // out with the reset's state change.)
            sh.outputs.extend(off_outputs());
            Ok(())
        })
    }

    fn jog(&self, axis: Axis, distance: f64, feed: Option<f64>) -> Result<(), PluginError> {
        self.kit().jog(axis, distance, feed)
    }

    /// Probes against the configured `probe` switch (see `Core::run_probe`).
    /// All three apply from the motion thread's next slice (5 ms); the simulated spindle has
    /// no speed to scale, so its override is only reported.
    fn set_overrides(
        &self,
        feed: Option<f64>,
        spindle: Option<f64>,
        rapid: Option<f64>,
    ) -> Result<(), PluginError> {
        self.kit().set_overrides(feed, spindle, rapid)
    }

    fn probe(&self, probe: Probe) -> Result<(), PluginError> {
        self.kit().probe(probe)
    }

    fn home(&self, axis: Option<Axis>) -> Result<(), PluginError> {
        self.kit().home(axis, |sh, axis| match axis {
            Some(a) => sh.pos[a.index()] = 0.0,
            None => sh.pos = [0.0; 4],
        })?;
        // Homing declares a new position: the switches read there (no trip, nothing moved).
        self.kit().with(|sh, ev| self.core.sense(sh, ev));
        Ok(())
    }

    fn set_output(&self, name: OutputName, on: bool) -> Result<Value, PluginError> {
        self.output(name, Some(on))
    }

    fn toggle_output(&self, name: OutputName) -> Result<Value, PluginError> {
        self.output(name, None)
    }

    /// One MDI line: interpreted alone from the current work position (so G91/G90, F and
    /// motion mode in it last for this line only), every move checked against `travel`
    /// before any starts, then run like a jog (state `jogging`, stop/feed hold end it).
    fn mdi(&self, line: &str) -> Result<(), PluginError> {
        if line.contains(['\n', '\r']) {
            return Err(PluginError::new(
                "invalid_gcode",
                "MDI takes exactly one line (no line breaks)",
            ));
        }
        let (work, offsets, active, mut a) = {
            let sh = self.kit().lock();
            sh.require_online()?;
            sh.require_no_alarm("run MDI")?;
            sh.require_still("run MDI")?;
            (
                sh.status().work_position.to_array(),
                sh.offsets,
                sh.active,
                sh.pos[3],
            )
        };
        let plan = program::plan(
            line,
            work,
            offsets.map(|o| [o[0], o[1], o[2]]),
            fresa_gcode::ToolTable::new(),
        )
        .with_max_segments(MDI_MAX_SEGMENTS);
        let invalid = |e: fresa_gcode::GcodeError| {
            PluginError::new("invalid_gcode", format!("MDI {line:?}: {e}"))
        };
        let mut moves = Vec::new();
        for step in plan.steps().map_err(invalid)? {
            let (_, step) = step.map_err(invalid)?;
            match step {
                // Passed over in MDI, as before tool changes and G43 were simulated; an MDI
                // line does not switch the simulated outputs (set_output does).
                Step::ToolChange(_)
                | Step::ToolLength(_)
                | Step::Spindle(_)
                | Step::Coolant { .. }
                | Step::Pause { optional: true, .. } => {}
                Step::Move { to, a: to_a, feed } => {
                    let target = program::machine_target(to, to_a, &offsets[active.index()], a);
                    a = target[3];
                    self.core.cfg.check_travel(target).map_err(|m| {
                        PluginError::new("out_of_travel", format!("MDI {line:?} refused: {m}"))
                    })?;
                    moves.push(MdiMove {
                        to: target,
                        feed: feed.unwrap_or(self.core.cfg.rapid_mm_min),
                        rapid: feed.is_none(),
                    });
                }
                other => {
                    return Err(PluginError::new(
                        "unsupported",
                        format!(
                            "sim-machine MDI runs moves only; {line:?} has {}",
                            match other {
                                Step::Dwell(_) => "a dwell",
                                Step::Pause { .. } => "a program pause",
                                Step::Probe { .. } => "a probing move (use the probe API)",
                                _ => "a work offset change",
                            }
                        ),
                    ))
                }
            }
        }
        self.kit().queue_mdi(moves, offsets, active)
    }
}

impl Drop for SimMachine {
    fn drop(&mut self) {
        self.core.kit.end_motion_thread();
        self.worker.join();
    }
}

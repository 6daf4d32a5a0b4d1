//! The machine: the shared state handling of `fresa_plugin_api::kit` plus the one output
//! thread. Requests change state and queue work; the output thread runs the tick loop,
//! executes plans, reads the inputs every tick and reports what happened.

use crate::config::{Config, Input, InputFunction, PortSpec};
use crate::output::{
    avoid_cpu, pin_to_cpu, rt_throttle_limit, scheduling, tight_timer_slack, Output, Pacer,
    Scheduling, HIGHEST_NICE,
};
use crate::planner::{
    self, Action, Builder, Item, Machine, Pace, PlanEnd, PlanStream, ProgramStream, Retimable,
    Scale, Start,
};
use crate::port::{Port, SharedSimPort, SimPort};
use fresa_plugin_api::backend::{LoadProgram, MachineBackend};
use fresa_plugin_api::contract::{
    io, Axis, Event, IoValue, MachineState, MachineStatus, OutputName, Probe, ProbeUntil,
    ProgramLoaded,
};
use fresa_plugin_api::exec_log::ExecLog;
use fresa_plugin_api::kit::{self, Interrupted, Job, KitConfig, MotionThread};
use fresa_plugin_api::{Host, PluginError};
use serde_json::{json, Value};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

pub use fresa_plugin_api::kit::EventSink;
/// Receives the plugin's log lines.
pub type LogSink = Arc<dyn Fn(LogLevel, &str) + Send + Sync>;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LogLevel {
    Info,
    Warn,
}

/// Input polling period while nothing moves and every coil is off.
const IDLE_POLL: Duration = Duration::from_millis(1);
/// Writes the simulated port remembers.
const SIM_KEEP_WRITES: usize = 1 << 16;

/// What the stepper machine adds to the kit's state. The kit's `pos` follows `steps` and `z`
/// (see [`sync_pos`]).
#[derive(Debug, Default)]
struct Drive {
    steps: [i64; 2],
    /// Commanded Z, machine mm (Z is a lift, not a stepper).
    z: f64,
    lift: bool,
    /// A manual lift change for the output thread to apply.
    lift_request: Option<bool>,
    /// An e-stop input is active now.
    estop: Option<String>,
}

type Kit = kit::Kit<Program, Drive>;
type State = kit::State<Program, Drive>;

/// A program checked whole at load (every line interpreted and planned, nothing kept), planned
/// again as it runs: from the file kept open since, from where the machine was at load.
#[derive(Debug)]
pub struct Program {
    file: std::fs::File,
    lines: u32,
    start: Start,
    start_line: u32,
    /// What to do before `start_line` (checked at load).
    preamble: Option<fresa_plugin_api::contract::Preamble>,
    tools: fresa_gcode::ToolTable,
    max_segments: u64,
    /// Length and end state of the plan, from the check.
    end: PlanEnd,
}

/// Items planned ahead of the output thread at most: the planner runs on a thread of its own,
/// so a slow line never holds up a step.
const PLAN_QUEUE: usize = 1024;
/// Motion the planner keeps queued ahead of the output thread (at least one item): an
/// override re-plans everything behind it, so this bounds how long one takes to apply. It must
/// also cover the planner thread's worst wait for a CPU.
const PLAN_AHEAD: Duration = Duration::from_millis(50);
/// Longest piece of a move given to the output thread at once: the rest of a long move can
/// still be re-planned for an override.
const PIECE: Duration = Duration::from_millis(10);

/// What `execute` needs to know of a plan besides its items.
struct Summary {
    lines: u32,
    total_ticks: u64,
    end_z: f64,
    end_lift: bool,
}

impl Summary {
    fn of(plan: &planner::Plan) -> Summary {
        Summary {
            lines: plan.lines,
            total_ticks: plan.total_ticks,
            end_z: plan.end_z,
            end_lift: plan.end_lift,
        }
    }
}

pub struct Stepper {
    core: Arc<Core>,
    worker: MotionThread,
    /// The simulated port, when `port` is `sim` (tests read what was written).
    pub sim_port: Option<SharedSimPort>,
}

struct Core {
    cfg: Config,
    /// The CPU the output thread pins itself to (`cpu`, in real time only).
    loop_cpu: Option<usize>,
    kit: Kit,
    /// The feed and rapid override the planner plans for (set with the kit's overrides).
    scale: Arc<Mutex<Scale>>,
}

/// Reads a shared scale (a poisoned lock still holds a valid value).
fn scale_of(cell: &Mutex<Scale>) -> Scale {
    *cell.lock().unwrap_or_else(|e| e.into_inner())
}

/// The rapids of a go-to-zero along `path` (machine mm) from `start`, at the rapid override
/// of `scale`; checked against the travel.
fn go_to_zero_plan<'m>(
    m: &'m Machine,
    start: &Start,
    path: &[[f64; 4]],
    scale: Scale,
) -> Result<Builder<'m>, String> {
    let mut b = Builder::new(m, start).scaled(scale);
    for p in path {
        b.move_to(0, [p[0], p[1]], p[2], Some(m.rapid_mm_min), Pace::Rapid)?;
    }
    Ok(b)
}

/// Ticks of `d` at the machine's tick rate (at least one).
fn ticks_of(cfg: &Config, d: Duration) -> u64 {
    ((d.as_secs_f64() * cfg.machine.tick_hz).round() as u64).max(1)
}

/// Machine mm of motor step counts `steps` with the lift at `z`.
fn machine_mm(cfg: &Config, steps: [i64; 2], z: f64) -> [f64; 4] {
    [
        steps[0] as f64 / cfg.machine.axes[0].steps_per_mm,
        steps[1] as f64 / cfg.machine.axes[1].steps_per_mm,
        z,
        0.0,
    ]
}

/// Machine mm from the step counts and the lift's Z; the lift output as the status shows it.
fn sync_pos(sh: &mut State, cfg: &Config) {
    sh.pos = machine_mm(cfg, sh.extra.steps, sh.extra.z);
    sh.outputs
        .insert(io::Z_LIFT.to_string(), Some(IoValue::On(sh.extra.lift)));
}

/// The output loop's lateness against its deadlines over the last 10 s of ticks it timed
/// (microseconds; p50 and p99 to the 0.5 us bucket above): numbers in the status's `outputs`,
/// so a shop sees its PC's real jitter in the status and in `/metrics`
/// (`fresa_machine_output{io="loop_lateness_p99_us"}`). Absent until the loop has timed 10 s
/// of ticks; they stay at the last figures while it idles.
const LATENESS_P50: &str = "loop_lateness_p50_us";
const LATENESS_P99: &str = "loop_lateness_p99_us";
const LATENESS_MAX: &str = "loop_lateness_max_us";

/// Why a job stops at an input: the alarm names it.
fn tripped(input: &Input) -> Interrupted {
    Interrupted::Tripped {
        input: input.function.io_name(),
        message: input.describe(),
    }
}

fn start(sh: &State) -> Start {
    Start {
        steps: sh.extra.steps,
        z: sh.extra.z,
        lift: sh.extra.lift,
        offsets: sh.offsets,
        active: sh.active,
    }
}

fn port_error(e: std::io::Error) -> Interrupted {
    Interrupted::Alarm(format!("parallel port I/O failed: {e}"))
}

/// Why the tick loop of a plan ends before the plan does.
enum Halt {
    /// The probe input reads what the probing move waits for, in the tick just begun (nothing
    /// has moved in it).
    Probed,
    Interrupted(Interrupted),
}

impl From<Interrupted> for Halt {
    fn from(e: Interrupted) -> Halt {
        Halt::Interrupted(e)
    }
}

impl Core {
    /// Latches an alarm unless one is latched already (the first cause is the one shown).
    fn alarm_once(&self, sh: &mut State, message: String, ev: &mut Vec<Event>) {
        if sh.state != MachineState::Alarm {
            sh.raise_alarm(message, ev);
        }
    }

    /// Shows input levels that changed (debounced) in the status at once.
    /// Also shows the loop's lateness over the last 10 s of ticks (see [`LATENESS_P50`]).
    fn show_inputs(&self, out: &mut Output) {
        let levels = out.take_shown_inputs();
        let late = out.pacer.take_lateness();
        if levels.is_none() && late.is_none() {
            return;
        }
        let outputs = late.map(|r| {
            let us = |v: f64| Some(IoValue::Number((v * 10.0).round() / 10.0));
            [
                (LATENESS_P50.to_string(), us(r.p50_us)),
                (LATENESS_P99.to_string(), us(r.p99_us)),
                (LATENESS_MAX.to_string(), us(r.max_us)),
            ]
        });
        self.kit.with(|sh, ev| {
            sh.set_io(
                levels.unwrap_or_default(),
                outputs.into_iter().flatten(),
                ev,
            )
        });
    }

    // ----- output thread -----

    fn worker(self: Arc<Self>, mut out: Output) {
        loop {
            let job = {
                let mut sh = self.kit.lock();
                if sh.shutdown {
                    drop(sh);
                    out.coils_off();
                    let _ = out.end(false);
                    return;
                }
                if let Some(on) = sh.extra.lift_request.take() {
                    out.set_lift(on);
                }
                match self.kit.take_job(&mut sh) {
                    Some(job) => Some(job),
                    None => {
                        if !out.coils_on() {
                            // Nothing to time: poll the inputs slowly, wake up for work.
                            drop(self.kit.wait_timeout(sh, IDLE_POLL));
                            out.pacer.restart();
                        }
                        None
                    }
                }
            };
            match job {
                None => self.idle_tick(&mut out),
                Some(job) => self.finish_job(&mut out, job),
            }
        }
    }

    /// One tick with no job: inputs are still watched, coils still time out.
    fn idle_tick(&self, out: &mut Output) {
        let trip = match out.begin() {
            Ok(t) => t,
            Err(e) => {
                self.port_failed(out, e);
                return;
            }
        };
        self.show_inputs(out);
        if trip.is_some() {
            out.coils_off();
        }
        let estop = out.estop_active().map(|i| i.describe());
        self.kit.with(|sh, ev| {
            sh.extra.estop = estop;
            if let Some(input) = trip {
                if sh.state != MachineState::Offline && sh.state != MachineState::Alarm {
                    sh.raise_input_alarm(input.function.io_name(), input.describe(), ev);
                }
            }
        });
        let wait = out.coils_on();
        if let Err(e) = out.end(wait) {
            self.port_failed(out, e);
        }
    }

    fn port_failed(&self, out: &mut Output, e: std::io::Error) {
        out.coils_off();
        self.kit
            .with(|sh, ev| self.alarm_once(sh, format!("parallel port I/O failed: {e}"), ev));
        // Do not spin on a dead port.
        std::thread::sleep(Duration::from_millis(100));
    }

    fn finish_job(&self, out: &mut Output, job: Job<Program>) {
        out.pacer.restart();
        match job {
            // A probe ends with its own report (where it tripped, if it did).
            Job::Probe(p) => {
                let result = self.guarded(out, |out| self.run_probe(out, &p));
                let update = self.settle(out);
                self.kit.finish_probe(p.id, result, update);
            }
            job => {
                let run = job.run();
                let result = self.guarded(out, |out| self.run_job(out, job));
                let update = self.settle(out);
                self.kit.finish_job(run, result, update);
            }
        }
    }

    /// Runs a job's motion: a panic fails the job, an alarm switches the coils off.
    fn guarded<T>(
        &self,
        out: &mut Output,
        motion: impl FnOnce(&mut Output) -> Result<T, Interrupted>,
    ) -> Result<T, Interrupted> {
        let result = catch_unwind(AssertUnwindSafe(|| motion(&mut *out)))
            .unwrap_or_else(|_| Err(Interrupted::Failed("internal error (panic)".into())));
        if matches!(result, Err(Interrupted::Alarm(_))) {
            out.coils_off();
        }
        result
    }

    /// Writes what a job left (coils off after an alarm, still on after a probe's trip: they
    /// hold the position and time out as after any move) before anyone looks; answers the
    /// kit's update of the state to it.
    fn settle(&self, out: &mut Output) -> impl FnOnce(&mut State) + '_ {
        let _ = out.end(false);
        let pos = out.pos;
        let estop = out.estop_active().map(|i| i.describe());
        move |sh: &mut State| {
            // Before anyone can send reset after an alarm.
            sh.extra.estop = estop;
            sh.extra.steps = pos;
            sync_pos(sh, &self.cfg);
        }
    }

    fn run_job(&self, out: &mut Output, job: Job<Program>) -> Result<(), Interrupted> {
        let m = &self.cfg.machine;
        match job {
            Job::Jog(jog) => {
                let (start, here) = {
                    let sh = self.kit.lock();
                    (start(&sh), sh.pos)
                };
                let to = jog.target(here);
                let mut b = Builder::new(m, &start);
                b.move_to(0, [to[0], to[1]], to[2], Some(jog.feed), Pace::Fixed)
                    .map_err(|e| Interrupted::Alarm(format!("soft limit: {e}")))?;
                let plan = b.finish(0);
                let summary = Summary::of(&plan);
                self.execute(out, plan.items.into_iter().map(Ok), summary, None, None)
                    .map(drop)
            }
            Job::GoToZero => {
                let (start, path) = {
                    let sh = self.kit.lock();
                    (start(&sh), sh.go_to_zero_path())
                };
                // Rapids, planned (and checked against the travel) here, then given out by the
                // planner thread, which re-plans them when the rapid override changes.
                let b = go_to_zero_plan(m, &start, &path, scale_of(&self.scale))
                    .map_err(|e| Interrupted::Alarm(format!("soft limit: {e}")))?;
                let summary = Summary::of(&b.finish(0));
                let piece = ticks_of(&self.cfg, PIECE);
                let items = self.planned(move |lane, machine, scale| {
                    // Checked just above: cannot fail now.
                    if let Ok(b) = go_to_zero_plan(machine, &start, &path, scale_of(scale)) {
                        lane.feed(PlanStream::new(b, piece), scale);
                    }
                })?;
                self.execute(out, items, summary, None, None).map(drop)
            }
            // Not queued by this backend (no MDI); refused rather than ignored.
            Job::Mdi(_) => Err(Interrupted::Failed("parport-stepper runs no MDI".into())),
            Job::Program(l) => {
                let run = (l.run, l.start_line);
                let p = &l.plan;
                let summary = Summary {
                    lines: p.lines,
                    total_ticks: p.end.total_ticks,
                    end_z: p.end.z,
                    end_lift: p.end.lift,
                };
                let items = self.program_items(p)?;
                self.execute(out, items, summary, Some(run), None).map(drop)
            }
            // Taken apart by `finish_job` (a probe ends with its own report).
            Job::Probe(p) => self.run_probe(out, &p).map(drop),
        }
    }

    /// A probing move along X or Y: a jog that ends in the first tick whose read of the probe
    /// input (its raw level, not the debounced one) is what `p.until` waits for. Answers the
    /// trip, machine mm: the motor position of that tick, in which nothing stepped.
    fn run_probe(&self, out: &mut Output, p: &Probe) -> Result<Option<[f64; 4]>, Interrupted> {
        let m = &self.cfg.machine;
        let ax = match p.axis {
            Axis::X => &m.axes[0],
            Axis::Y => &m.axes[1],
            // Refused by `Stepper::probe`; a failure rather than a guess if one gets here.
            other => {
                return Err(Interrupted::Failed(format!(
                    "cannot probe {other:?}: not a stepper axis"
                )))
            }
        };
        let (start, here) = {
            let sh = self.kit.lock();
            (start(&sh), sh.pos)
        };
        // A stepper stops dead without losing steps only from at most its start rate (the rate
        // it starts at without a ramp). Probing no faster than that, the stop in the tick that
        // reads the probe is safe and overshoots by zero steps; a faster feed is clamped.
        let feed = p.feed.min(ax.start_rate / ax.steps_per_mm * 60.0);
        let to = kit::Jog {
            axis: p.axis,
            distance: p.distance,
            feed,
        }
        .target(here);
        let mut b = Builder::new(m, &start);
        b.move_to(0, [to[0], to[1]], to[2], Some(feed), Pace::Fixed)
            .map_err(|e| Interrupted::Alarm(format!("soft limit: {e}")))?;
        let plan = b.finish(0);
        let summary = Summary::of(&plan);
        let items = plan.items.into_iter().map(Ok);
        let trip = self.execute(out, items, summary, None, Some(p.until))?;
        Ok(trip.map(|steps| machine_mm(&self.cfg, steps, start.z)))
    }

    /// Starts a tick of a plan: reads the inputs and shows what changed. Ends the plan before
    /// anything moves in this tick when a limit or e-stop trips (the coils go off in this
    /// tick's write) or when `probe` is watched and the probe input reads what it waits for
    /// (the coils stay on, holding).
    fn begin_tick(&self, out: &mut Output, probe: Option<ProbeUntil>) -> Result<(), Halt> {
        let trip = out.begin().map_err(port_error)?;
        self.show_inputs(out);
        if let Some(input) = trip {
            out.coils_off();
            return Err(tripped(&input).into());
        }
        if probe.is_some_and(|u| out.input_active(InputFunction::Probe) == u.wants_active()) {
            return Err(Halt::Probed);
        }
        Ok(())
    }

    /// Moves the timeline one tick on: ends the current tick, then starts real ticks until the
    /// timeline has advanced by one. Every started tick reads the inputs and the stop / hold
    /// flags. A feed hold slows the timeline down to a stop along a ramp (and resume speeds it
    /// up again), so the motors decelerate instead of stopping dead; once stopped, the hold is
    /// confirmed to the waiting request.
    fn advance(
        &self,
        out: &mut Output,
        tl: &mut Timeline,
        probe: Option<ProbeUntil>,
    ) -> Result<(), Halt> {
        loop {
            out.end(true).map_err(port_error)?;
            self.begin_tick(out, probe)?;
            if self.kit.aborted() {
                return Err(Interrupted::Aborted.into());
            }
            let hold = self.kit.hold_requested();
            if tl.tick(hold) {
                return Ok(());
            }
            if hold && tl.rate == 0.0 {
                self.kit.confirm_held();
            }
        }
    }

    /// Starts a planner thread running `plan` (which gives out its plan through the lane it
    /// gets, with the machine and the shared override); answers the items as the output
    /// thread takes them. Waiting for one (the planner fell behind) still sees a stop; the
    /// planner ends when the job does.
    fn planned<'a>(
        &'a self,
        plan: impl FnOnce(&Lane, &Machine, &Mutex<Scale>) + Send + 'static,
    ) -> Result<LaneItems<'a>, Interrupted> {
        let lane = Arc::new(Lane::new(ticks_of(&self.cfg, PLAN_AHEAD)));
        let machine = self.cfg.machine.clone();
        let scale = Arc::clone(&self.scale);
        let feeder = Arc::clone(&lane);
        let loop_cpu = self.loop_cpu;
        std::thread::Builder::new()
            .name("parport planner".into())
            .spawn(move || {
                if let Some(cpu) = loop_cpu {
                    // Started by the output thread, it would share that thread's CPU. The
                    // only failure is a process given that one CPU, where the loop's log line
                    // already says other work shares it.
                    let _ = avoid_cpu(cpu);
                }
                let _done = PlannerDone(&feeder);
                plan(&feeder, &machine, &scale);
            })
            .map_err(|e| Interrupted::Failed(format!("cannot start the planner thread: {e}")))?;
        Ok(LaneItems {
            lane,
            kit: &self.kit,
        })
    }

    /// The items of a loaded program, planned again from its file as the output thread takes
    /// them, for the overrides in force.
    fn program_items<'a>(&'a self, p: &Program) -> Result<LaneItems<'a>, Interrupted> {
        let failed =
            |e: std::io::Error| Interrupted::Failed(format!("cannot read the program again: {e}"));
        let mut file = p.file.try_clone().map_err(failed)?;
        std::io::Seek::rewind(&mut file).map_err(failed)?;
        let (lines, start, start_line) = (p.lines, p.start, p.start_line);
        let (tools, max_segments) = (p.tools.clone(), p.max_segments);
        let piece = ticks_of(&self.cfg, PIECE);
        let preamble = p.preamble.clone();
        self.planned(move |lane, machine, scale| {
            let reader = std::io::BufReader::with_capacity(1 << 16, file);
            let stream = ProgramStream::new(
                machine,
                reader,
                (lines, start_line),
                &start,
                preamble.as_ref(),
                tools,
                max_segments,
            )
            .scaled(scale_of(scale))
            .in_pieces(piece);
            lane.feed(stream, scale);
        })
    }

    /// Executes a plan's items on the tick grid. `run` = (run id, first line to acknowledge).
    /// With `probe`, watches the probe input every tick and ends at the first tick that reads
    /// what it waits for: answers the motor position of that tick (`None`: the plan ran out).
    fn execute(
        &self,
        out: &mut Output,
        items: impl Iterator<Item = Result<Item, Interrupted>>,
        plan: Summary,
        run: Option<(i64, u32)>,
        probe: Option<ProbeUntil>,
    ) -> Result<Option<[i64; 2]>, Interrupted> {
        match self.step_plan(out, items, plan, run, probe) {
            Ok(()) => Ok(None),
            Err(Halt::Probed) => Ok(Some(out.pos)),
            Err(Halt::Interrupted(e)) => Err(e),
        }
    }

    /// The tick loop of [`Core::execute`].
    fn step_plan(
        &self,
        out: &mut Output,
        items: impl Iterator<Item = Result<Item, Interrupted>>,
        plan: Summary,
        run: Option<(i64, u32)>,
        probe: Option<ProbeUntil>,
    ) -> Result<(), Halt> {
        let mut tl = Timeline::new(&self.cfg);
        let mut stepped_at: Option<u64> = None;
        let mut next_ack = run.map_or(1, |r| r.1);
        let mut line_dev: Option<(u32, f64)> = None;
        let mut last_publish = Instant::now();
        // Tick 0 of the timeline.
        self.begin_tick(out, probe)?;
        for item in items {
            let item = item?;
            if let Some((run, _)) = run {
                // The first item of a later line: every line before it is done.
                if item.line > next_ack {
                    self.line_done(
                        run,
                        item.line - 1,
                        &mut next_ack,
                        &mut line_dev,
                        tl.t,
                        &plan,
                    )?;
                    self.kit.with(|sh, _| sh.line = Some(item.line));
                }
            }
            match &item.action {
                Action::Move(mv) => {
                    self.kit.with(|sh, _| sh.feed = mv.peak_feed_mm_min());
                    for s in mv.steps() {
                        let at = item.start_tick + s.tick;
                        // At most one step per tick, whatever the schedule says: two in one
                        // write would skip a phase.
                        while tl.t < at || stepped_at == Some(tl.t) {
                            self.advance(out, &mut tl, probe)?;
                        }
                        stepped_at = Some(tl.t);
                        out.step(s.pos);
                        match &mut line_dev {
                            Some((l, d)) if *l == item.line => *d = d.max(s.deviation_mm),
                            _ => line_dev = Some((item.line, s.deviation_mm)),
                        }
                        // Steps come at most every other tick (max_rate <= tick_hz / 2), so
                        // reading the clock per step is cheap.
                        if last_publish.elapsed() >= self.cfg.status_interval {
                            last_publish = Instant::now();
                            let pos = out.pos;
                            self.kit.with(|sh, ev| {
                                sh.extra.steps = pos;
                                sync_pos(sh, &self.cfg);
                                sh.push_status(ev);
                            });
                        }
                    }
                }
                Action::Lift { on, settle, z } => {
                    out.set_lift(*on);
                    let (on, z) = (*on, *z);
                    self.kit.with(|sh, ev| {
                        sh.extra.lift = on;
                        sh.extra.z = z;
                        sync_pos(sh, &self.cfg);
                        sh.push_status(ev);
                    });
                    let until = item.start_tick + settle;
                    while tl.t < until {
                        self.advance(out, &mut tl, probe)?;
                    }
                }
                Action::Dwell(ticks) => {
                    let until = item.start_tick + ticks;
                    while tl.t < until {
                        self.advance(out, &mut tl, probe)?;
                    }
                }
                Action::Pause => {
                    // M0 comes between moves, with the motors at rest: hold at once.
                    tl.rate = 0.0;
                    self.kit.with(|sh, ev| self.kit.program_pause(sh, ev));
                }
                Action::UseOffset(o) => {
                    let o = *o;
                    self.kit.with(|sh, ev| {
                        if sh.active != o {
                            sh.active = o;
                            sh.push_status(ev);
                        }
                    });
                }
            }
        }
        let pos = out.pos;
        self.kit.with(|sh, _| {
            sh.extra.steps = pos;
            sh.extra.z = plan.end_z;
            sh.extra.lift = plan.end_lift;
            sync_pos(sh, &self.cfg);
        });
        if let Some((run, _)) = run {
            self.line_done(run, plan.lines, &mut next_ack, &mut line_dev, tl.t, &plan)?;
        }
        Ok(())
    }

    /// Everything up to `line` is done: report the deviation of the line that moved, log and
    /// acknowledge every line from `next_ack` to `line`.
    fn line_done(
        &self,
        run: i64,
        line: u32,
        next_ack: &mut u32,
        line_dev: &mut Option<(u32, f64)>,
        t: u64,
        plan: &Summary,
    ) -> Result<(), Interrupted> {
        let total = plan.total_ticks.max(1) as f64;
        let percent = ((t as f64 / total) * 100.0).min(100.0);
        let remaining_s = plan.total_ticks.saturating_sub(t) as f64 / self.cfg.machine.tick_hz;
        let mut report = Vec::new();
        if let Some((l, d)) = line_dev.take() {
            report.push(Event::LineReport {
                run,
                line: l,
                max_deviation_mm: (d * 1e6).round() / 1e6,
                percent: (percent * 10.0).round() / 10.0,
                remaining_s: (remaining_s * 1000.0).round() / 1000.0,
            });
        }
        self.kit.lines_done(run, *next_ack..=line, report)?;
        *next_ack = (*next_ack).max(line.saturating_add(1));
        Ok(())
    }
}

impl MachineBackend for Stepper {
    fresa_plugin_api::kit_backend_methods!();

    fn create(host: Host, config: Value) -> Result<Self, PluginError> {
        Stepper::new(
            &config,
            Arc::new(move |event| host.emit(event)),
            Arc::new(move |level, message| match level {
                LogLevel::Info => host.info(message),
                LogLevel::Warn => host.warn(message),
            }),
            Timing::Real,
        )
    }

    fn connect(&self) -> Result<MachineStatus, PluginError> {
        Ok(self.kit().connect(None))
    }

    /// From the axes' limits (see [`planner::motion_profile`]).
    fn motion_profile(&self) -> Result<fresa_plugin_api::contract::MotionProfile, PluginError> {
        Ok(planner::motion_profile(&self.core.cfg.machine))
    }

    fn load_program(&self, p: LoadProgram) -> Result<ProgramLoaded, PluginError> {
        if p.height_map.is_some() {
            return Err(PluginError::new(
                "unsupported",
                "parport-stepper cannot apply a height map: its Z is an on/off tool lift \
                 (the `z_lift` output), with no Z positions to correct",
            ));
        }
        let kit = self.kit();
        let actual = kit.logged_start(p.run, p.start_line)?;
        let (start, pos) = {
            let sh = kit.lock();
            sh.require_still("load a program")?;
            (start(&sh), sh.pos)
        };
        if let Some(pre) = &p.preamble {
            kit.check_preamble(pos, pre)?;
        }
        let (file, lines) = kit::open_program(&p.path)?;
        let tools = gcode_tools(&p.tools);
        let max_segments = p.max_segments.unwrap_or(fresa_gcode::DEFAULT_MAX_SEGMENTS);
        // The whole program planned once, to check it before anything moves; nothing of the
        // plan is kept but its length and end (it is planned again as it runs).
        let unreadable = |e: std::io::Error| {
            PluginError::new("program_unreadable", format!("cannot read {}: {e}", p.path))
        };
        let reader =
            std::io::BufReader::with_capacity(1 << 16, file.try_clone().map_err(unreadable)?);
        let machine = &self.core.cfg.machine;
        let mut stream = ProgramStream::new(
            machine,
            reader,
            (lines, actual),
            &start,
            p.preamble.as_ref(),
            tools.clone(),
            max_segments,
        )
        .scaled(scale_of(&self.core.scale));
        if let Some(Err(m)) = stream.by_ref().find(Result::is_err) {
            let code = if m.contains("work budget exceeded") {
                "work_budget_exceeded"
            } else if m.contains("outside the travel") {
                "out_of_travel"
            } else if stream.start_refused() {
                "start_refused"
            } else {
                "invalid_program"
            };
            let m = if code == "work_budget_exceeded" {
                format!("{m}; the budget is the server's `max_program_segments`")
            } else {
                m
            };
            return Err(PluginError::new(code, m));
        }
        let program = Program {
            file,
            lines,
            start,
            start_line: actual,
            preamble: p.preamble.clone(),
            tools,
            max_segments,
            end: stream.end(),
        };
        kit.install_plan_with(p.run, program, (lines, p.start_line, actual), p.preamble)
    }

    fn reset(&self) -> Result<(), PluginError> {
        self.kit().reset(|sh| {
            if sh.state == MachineState::Alarm {
                if let Some(e) = &sh.extra.estop {
                    return Err(PluginError::new(
                        "alarm",
                        format!("cannot reset: {e} is still active"),
                    ));
                }
            }
            Ok(())
        })
    }

    fn jog(&self, axis: Axis, distance: f64, feed: Option<f64>) -> Result<(), PluginError> {
        if axis == Axis::A && distance.is_finite() {
            return Err(PluginError::new(
                "unsupported",
                "this machine has no A axis (X and Y are steppers, Z is the tool lift)",
            ));
        }
        self.kit().jog(axis, distance, feed)
    }

    /// Probes along X or Y (see `Core::run_probe`); the kit checks the probe input, its level
    /// and the travel.
    fn probe(&self, p: Probe) -> Result<(), PluginError> {
        let why = match p.axis {
            Axis::X | Axis::Y => return self.kit().probe(p),
            Axis::Z => "Z is a tool lift (on/off), not a stepper axis",
            Axis::A => "this machine has no A axis",
        };
        Err(PluginError::new(
            "unsupported",
            format!("parport-stepper cannot probe {:?}: {why}", p.axis),
        ))
    }

    /// No home switches: homing declares the current position machine zero.
    fn home(&self, axis: Option<Axis>) -> Result<(), PluginError> {
        let cfg = &self.core.cfg;
        self.kit().home(axis, |sh, axis| {
            match axis {
                Some(Axis::X) => sh.extra.steps[0] = 0,
                Some(Axis::Y) => sh.extra.steps[1] = 0,
                Some(Axis::Z) => sh.extra.z = 0.0,
                Some(Axis::A) => {}
                None => {
                    sh.extra.steps = [0, 0];
                    sh.extra.z = 0.0;
                }
            }
            sync_pos(sh, cfg);
        })
    }

    fn set_output(&self, name: OutputName, on: bool) -> Result<Value, PluginError> {
        self.lift(name, Some(on))
            .map(|on| json!({ "z_lift": on, "output": OutputName::ZLift, "on": on }))
    }

    fn toggle_output(&self, name: OutputName) -> Result<Value, PluginError> {
        self.lift(name, None)
            .map(|on| json!({ "z_lift": on, "output": OutputName::ZLift, "on": on }))
    }

    /// Feed and rapid overrides re-plan the motion not yet given to the output thread (see
    /// `Lane`); the spindle is not this machine's to set.
    fn set_overrides(
        &self,
        feed: Option<f64>,
        spindle: Option<f64>,
        rapid: Option<f64>,
    ) -> Result<(), PluginError> {
        if let Some(s) = spindle.filter(|s| *s != 100.0) {
            return Err(PluginError::new(
                "unsupported",
                format!(
                    "parport-stepper cannot override the spindle speed (asked {s} %): the \
                     parallel port drives only the X/Y steppers and the Z lift, the spindle is \
                     not connected to it; feed and rapid overrides work"
                ),
            ));
        }
        let kit = self.kit();
        kit.set_overrides(feed, spindle, rapid)?;
        // Under the kit's lock, so concurrent calls leave the scale of the last one.
        kit.with(|sh, _| {
            *self.core.scale.lock().unwrap_or_else(|e| e.into_inner()) = Scale {
                feed: sh.overrides.feed / 100.0,
                rapid: sh.overrides.rapid / 100.0,
            };
        });
        Ok(())
    }

    fn mdi(&self, _line: &str) -> Result<(), PluginError> {
        Err(PluginError::new(
            "unsupported",
            "parport-stepper runs whole programs only: no MDI",
        ))
    }
}

/// The plan queue between a planner thread and the output thread: at most [`PLAN_QUEUE`] items
/// and about [`PLAN_AHEAD`] of motion, so an override re-plans all but that much.
struct Lane {
    q: Mutex<LaneQueue>,
    cv: std::sync::Condvar,
    /// Ticks of motion to keep queued.
    ahead: u64,
}

#[derive(Default)]
struct LaneQueue {
    items: std::collections::VecDeque<Result<Item, String>>,
    /// Ticks of the queued items.
    ticks: u64,
    /// The planner has given out everything (or failed).
    done: bool,
    /// The output thread takes nothing more (the job ended or stopped).
    closed: bool,
}

fn item_ticks(item: &Result<Item, String>) -> u64 {
    item.as_ref().map_or(0, |i| i.action.ticks())
}

impl Lane {
    fn new(ahead: u64) -> Lane {
        Lane {
            q: Mutex::new(LaneQueue::default()),
            cv: std::sync::Condvar::new(),
            ahead,
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, LaneQueue> {
        self.q.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Planner side: gives out `stream`'s items as the output thread takes them, re-planning
    /// what is not given out yet whenever the override in `scale` changes (noticed within a
    /// millisecond). Returns when the stream ends or the output thread takes no more.
    fn feed(&self, mut stream: impl Retimable, scale: &Mutex<Scale>) {
        let mut planned_for = scale_of(scale);
        loop {
            let now = {
                let mut q = self.lock();
                loop {
                    if q.closed {
                        return;
                    }
                    let now = scale_of(scale);
                    let room =
                        q.items.len() < PLAN_QUEUE && (q.items.is_empty() || q.ticks < self.ahead);
                    if now != planned_for || room {
                        break now;
                    }
                    q = self
                        .cv
                        .wait_timeout(q, Duration::from_millis(1))
                        .map_or_else(|e| e.into_inner().0, |(g, _)| g);
                }
            };
            if now != planned_for {
                stream.retime(now);
                planned_for = now;
                continue;
            }
            let Some(item) = stream.next() else { return };
            let mut q = self.lock();
            q.ticks += item_ticks(&item);
            q.items.push_back(item);
            drop(q);
            self.cv.notify_all();
        }
    }
}

/// Marks the lane done when its planner thread ends, also by a panic (then with an error, so
/// the job fails instead of ending early as if complete).
struct PlannerDone<'a>(&'a Lane);

impl Drop for PlannerDone<'_> {
    fn drop(&mut self) {
        let mut q = self.0.lock();
        if std::thread::panicking() {
            q.items.push_back(Err(
                "internal error: the motion planner stopped (panic)".into()
            ));
        }
        q.done = true;
        drop(q);
        self.0.cv.notify_all();
    }
}

/// Output side of a [`Lane`]: its items as they come; a stop while waiting for one ends the
/// wait. Dropping it tells the planner to stop.
struct LaneItems<'a> {
    lane: Arc<Lane>,
    kit: &'a Kit,
}

impl Iterator for LaneItems<'_> {
    type Item = Result<Item, Interrupted>;

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            {
                let mut q = self.lane.lock();
                if let Some(item) = q.items.pop_front() {
                    q.ticks = q.ticks.saturating_sub(item_ticks(&item));
                    drop(q);
                    self.lane.cv.notify_all();
                    return Some(item.map_err(Interrupted::Failed));
                }
                if q.done {
                    return None;
                }
                drop(self.lane.cv.wait_timeout(q, Duration::from_millis(1)));
            }
            if self.kit.aborted() {
                return Some(Err(Interrupted::Aborted));
            }
        }
    }
}

impl Drop for LaneItems<'_> {
    fn drop(&mut self) {
        self.lane.lock().closed = true;
        self.lane.cv.notify_all();
    }
}

/// A plan's clock: advances by `rate` (0..=1) timeline ticks per real tick. Feed hold ramps
/// the rate to 0, resume back to 1, each over the time the slowest-accelerating axis needs to
/// stop from its max rate, so the step rate never changes faster than about twice `accel`.
struct Timeline {
    t: u64,
    rate: f64,
    phase: f64,
    ramp_step: f64,
}

impl Timeline {
    fn new(cfg: &Config) -> Timeline {
        let ramp_s = cfg
            .machine
            .axes
            .iter()
            .map(|a| a.max_rate / a.accel)
            .fold(0.0, f64::max);
        let ramp_ticks = (ramp_s * cfg.machine.tick_hz).max(1.0);
        Timeline {
            t: 0,
            rate: 1.0,
            phase: 0.0,
            ramp_step: 1.0 / ramp_ticks,
        }
    }

    /// One real tick; true when the timeline moved on by one tick.
    fn tick(&mut self, hold: bool) -> bool {
        self.rate = if hold {
            (self.rate - self.ramp_step).max(0.0)
        } else {
            (self.rate + self.ramp_step).min(1.0)
        };
        self.phase += self.rate;
        if self.phase >= 1.0 - 1e-9 {
            self.phase = (self.phase - 1.0).max(0.0);
            self.t += 1;
            true
        } else {
            false
        }
    }
}

/// How the output loop keeps time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Timing {
    /// Real ticks at `tick_hz` on absolute deadlines.
    Real,
    /// No waiting at all (tests of the loop's logic; ticks are still counted).
    Virtual,
}

impl Stepper {
    /// Creates a machine from its JSON config; events go to `sink`, log lines to `log`.
    /// `Timing::Virtual` runs the loop without waiting (tests of its logic).
    pub fn new(
        config: &Value,
        sink: EventSink,
        log: LogSink,
        timing: Timing,
    ) -> Result<Stepper, PluginError> {
        let cfg = Config::from_json(config)?;
        let mut sim_port = None;
        let port: Box<dyn Port> = match &cfg.port {
            PortSpec::Sim => {
                let p = SharedSimPort(Arc::new(Mutex::new(SimPort::new(
                    cfg.quiet_levels(),
                    cfg.sim_inputs.clone(),
                    SIM_KEEP_WRITES,
                ))));
                sim_port = Some(p.clone());
                Box::new(p)
            }
            PortSpec::Ppdev(path) => open_ppdev(path)?,
        };
        let exec_log = match &cfg.execution_log {
            Some(path) => Some(ExecLog::open(path)?),
            None => None,
        };
        let period = match timing {
            Timing::Real => Some(Duration::from_secs_f64(1.0 / cfg.machine.tick_hz)),
            Timing::Virtual => None,
        };
        let out = Output::new(&cfg, port, Pacer::new(period, cfg.spin), false);
        let kit_cfg = KitConfig {
            jog_feed_mm_min: cfg.jog_feed_mm_min,
            travel: [cfg.machine.travel[0], cfg.machine.travel[1], None, None],
        };
        let loop_cpu = cfg.cpu.filter(|_| timing == Timing::Real);
        let core = Arc::new(Core {
            cfg,
            loop_cpu,
            kit: Kit::new(kit_cfg, sink, exec_log, Drive::default()),
            scale: Arc::new(Mutex::new(Scale::default())),
        });
        // Every configured input is supported, and unknown until the output thread's first read.
        let unknown: Vec<_> = core
            .cfg
            .inputs
            .iter()
            .map(|i| (i.function.io_name(), None))
            .collect();
        core.kit.with(|sh, ev| {
            sync_pos(sh, &core.cfg);
            sh.set_io(unknown, [], ev);
        });
        let worker_core = Arc::clone(&core);
        let want_rt = core.cfg.realtime_priority && timing == Timing::Real;
        let cpu = core.loop_cpu;
        let period = 1.0 / core.cfg.machine.tick_hz;
        let always_spins = core.cfg.spin.as_secs_f64() >= period;
        let worker = MotionThread::spawn("parport output", move || {
            if timing == Timing::Real {
                if let Err(e) = tight_timer_slack() {
                    log(
                        LogLevel::Warn,
                        &format!("output loop could not set its timer slack to 1 ns ({e}); its sleeps may end up to 50 us late"),
                    );
                }
            }
            let pinned = match cpu.map(|cpu| (cpu, pin_to_cpu(cpu))) {
                None => false,
                Some((cpu, Ok(()))) => {
                    log(LogLevel::Info, &format!("output loop pinned to CPU {cpu}"));
                    true
                }
                Some((cpu, Err(e))) => {
                    log(
                        LogLevel::Warn,
                        &format!("output loop could NOT be pinned to CPU {cpu} ({e}); it runs on any CPU"),
                    );
                    false
                }
            };
            let sched = scheduling(want_rt, always_spins, rt_throttle_limit());
            match (&sched, sched.apply()) {
                (Scheduling::AsStarted, _) => {}
                (Scheduling::RealTime, Ok(())) => log(LogLevel::Info, "output loop runs with real-time priority (SCHED_FIFO)"),
                (Scheduling::RealTime, Err(e)) => log(
                    LogLevel::Warn,
                    &format!(
                        "output loop could NOT get real-time priority ({e}); step timing may jitter under load. Grant CAP_SYS_NICE (e.g. `setcap cap_sys_nice+ep fresa`) or raise RLIMIT_RTPRIO"
                    ),
                ),
                (Scheduling::HighestNormal { rt_limit }, applied) => {
                    let why = format!(
                        "output loop spins every whole tick (spin_us >= the {:.1} us period) and the kernel throttles real-time threads (kernel.sched_rt_runtime_us = {rt_limit}), which would stop it about 50 ms each second",
                        period * 1e6
                    );
                    match applied {
                        Ok(()) => log(
                            if pinned { LogLevel::Info } else { LogLevel::Warn },
                            &format!(
                                "{why}: it runs at the highest normal priority (nice {HIGHEST_NICE}) instead of SCHED_FIFO. Other work on its CPU can still delay it by milliseconds{}; `sysctl kernel.sched_rt_runtime_us=-1` lets it take SCHED_FIFO",
                                if pinned { "" } else { ": give it a CPU of its own (`cpu`, best with isolcpus=)" }
                            ),
                        ),
                        Err(e) => log(
                            LogLevel::Warn,
                            &format!(
                                "{why}; it could NOT take the highest normal priority (nice {HIGHEST_NICE}) instead ({e}), so other work may delay it. Grant CAP_SYS_NICE (e.g. `setcap cap_sys_nice+ep fresa`) or raise RLIMIT_NICE"
                            ),
                        ),
                    }
                }
            }
            worker_core.worker(out)
        })?;
        Ok(Stepper {
            core,
            worker,
            sim_port,
        })
    }

    fn kit(&self) -> &Kit {
        &self.core.kit
    }

    /// Switches the Z lift (`None` = toggle), only while nothing moves; answers the new state.
    fn lift(&self, name: OutputName, on: Option<bool>) -> Result<bool, PluginError> {
        if name != OutputName::ZLift {
            return Err(PluginError::new(
                "unsupported",
                format!(
                    "parport-stepper has no output {:?} (only \"z_lift\")",
                    name.as_str()
                ),
            ));
        }
        self.kit().with(|sh, ev| {
            sh.require_no_alarm("switch the Z lift")?;
            sh.require_still("switch the Z lift")?;
            let on = on.unwrap_or(!sh.extra.lift);
            sh.extra.lift = on;
            sh.extra.lift_request = Some(on);
            sh.set_io([], [(io::Z_LIFT.to_string(), Some(IoValue::On(on)))], ev);
            Ok(on)
        })
    }
}

#[cfg(target_os = "linux")]
fn open_ppdev(path: &std::path::Path) -> Result<Box<dyn Port>, PluginError> {
    crate::port::Ppdev::open(path)
        .map(|p| Box::new(p) as Box<dyn Port>)
        .map_err(|e| {
            PluginError::new(
                "port_unavailable",
                format!(
                    "cannot open {} through ppdev: {e} (is the `ppdev` module loaded and the user in group `lp`?)",
                    path.display()
                ),
            )
        })
}

#[cfg(not(target_os = "linux"))]
fn open_ppdev(path: &std::path::Path) -> Result<Box<dyn Port>, PluginError> {
    Err(PluginError::new(
        "port_unavailable",
        format!("{}: ppdev is only available on Linux", path.display()),
    ))
}

impl Drop for Stepper {
    fn drop(&mut self) {
        self.core.kit.end_motion_thread();
        self.worker.join();
    }
}

/// The host's tool table as the interpreter takes it.
fn gcode_tools(tools: &[fresa_plugin_api::contract::ProgramTool]) -> fresa_gcode::ToolTable {
    fresa_gcode::tool_table(tools.iter().map(|t| (t.tool, t.diameter_mm, t.length_mm)))
}

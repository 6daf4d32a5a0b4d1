//! The machine: state shared between request threads and the one output thread. Requests
//! change state and queue work; the output thread runs the tick loop, executes plans, reads the
//! inputs every tick and reports what happened.

use crate::config::{Config, PortSpec};
use crate::output::{realtime_priority, Output, Pacer};
use crate::planner::{self, Action, Builder, Plan, Start};
use crate::port::{Port, SharedSimPort, SimPort};
use fresa_plugin_api::contract::{
    Axis, AxisValues, Command, Event, MachineState, MachineStatus, OffsetTable, OutputName,
    ProgramLoaded, Request, RunAction, RunOutcome, WorkOffset,
};
use fresa_plugin_api::exec_log::ExecLog;
use fresa_plugin_api::PluginError;
use serde_json::{json, Value};
use std::collections::VecDeque;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// Receives every event the machine emits, from any thread, in order.
pub type EventSink = Arc<dyn Fn(&Event) + Send + Sync>;
/// Receives the plugin's log lines.
pub type LogSink = Arc<dyn Fn(LogLevel, &str) + Send + Sync>;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LogLevel {
    Info,
    Warn,
}

const MAX_QUEUED_JOGS: usize = 64;
const STOP_CONFIRM: Duration = Duration::from_secs(5);
/// Input polling period while nothing moves and every coil is off.
const IDLE_POLL: Duration = Duration::from_millis(1);
/// Writes the simulated port remembers.
const SIM_KEEP_WRITES: usize = 1 << 16;

pub struct Stepper {
    core: Arc<Core>,
    worker: Mutex<Option<JoinHandle<()>>>,
    /// The simulated port, when `port` is `sim` (tests read what was written).
    pub sim_port: Option<SharedSimPort>,
}

struct Core {
    cfg: Config,
    sink: EventSink,
    shared: Mutex<Shared>,
    cv: Condvar,
    emit_order: Mutex<()>,
    log: Option<Mutex<ExecLog>>,
    /// Abort the job in progress (stop); read every tick.
    abort: AtomicBool,
    /// Feed hold / M0: the timeline is frozen; read every tick.
    hold: AtomicBool,
}

#[derive(Debug)]
struct Loaded {
    run: i64,
    plan: Plan,
    start_line: u32,
}

#[derive(Debug)]
enum Job {
    Jog {
        axis: Axis,
        distance: f64,
        feed: f64,
    },
    GoToZero,
    Program(Loaded),
}

#[derive(Debug)]
struct Shared {
    state: MachineState,
    reason: Option<String>,
    alarm: Option<String>,
    steps: [i64; 2],
    /// Commanded Z, machine mm (Z is a lift, not a stepper).
    z: f64,
    lift: bool,
    /// A manual lift change for the output thread to apply.
    lift_request: Option<bool>,
    /// Machine mm where all queued motion ends (for bounding jogs).
    end_mm: [f64; 3],
    offsets: [[f64; 4]; 6],
    active: WorkOffset,
    feed: f64,
    run: Option<i64>,
    line: Option<u32>,
    program: Option<Loaded>,
    queue: VecDeque<Job>,
    busy: bool,
    shutdown: bool,
    /// An e-stop input is active now.
    estop: Option<String>,
}

enum Interrupted {
    Aborted,
    Alarm(String),
    Failed(String),
}

type Events = Vec<Event>;

impl Shared {
    fn machine_mm(&self, cfg: &Config) -> [f64; 4] {
        [
            self.steps[0] as f64 / cfg.machine.axes[0].steps_per_mm,
            self.steps[1] as f64 / cfg.machine.axes[1].steps_per_mm,
            self.z,
            0.0,
        ]
    }

    fn status(&self, cfg: &Config) -> MachineStatus {
        let pos = self.machine_mm(cfg);
        let off = self.offsets[self.active.index()];
        MachineStatus {
            state: self.state,
            machine_position: AxisValues::from_array(pos),
            work_position: AxisValues::from_array(std::array::from_fn(|i| pos[i] - off[i])),
            feed: self.feed,
            feed_override: 100.0,
            active_offset: self.active,
            run: self.run,
            line: self.line,
            alarm: self.alarm.clone(),
            reason: self.reason.clone(),
        }
    }

    fn offset_table(&self) -> OffsetTable {
        OffsetTable {
            active: self.active,
            offsets: WorkOffset::ALL
                .into_iter()
                .map(|o| (o, AxisValues::from_array(self.offsets[o.index()])))
                .collect(),
        }
    }

    fn start(&self) -> Start {
        Start {
            steps: self.steps,
            z: self.z,
            lift: self.lift,
            offsets: self.offsets,
            active: self.active,
        }
    }

    fn require_online(&self) -> Result<(), PluginError> {
        if self.state == MachineState::Offline {
            return Err(PluginError::new(
                "offline",
                "the machine is not connected: send `connect` first",
            ));
        }
        Ok(())
    }

    fn require_still(&self, what: &str) -> Result<(), PluginError> {
        self.require_online()?;
        if self.state.is_busy() || self.busy {
            return Err(PluginError::new(
                "busy",
                format!("cannot {what} while the machine is {}", self.state.as_str()),
            ));
        }
        Ok(())
    }

    fn require_no_alarm(&self, what: &str) -> Result<(), PluginError> {
        if self.state == MachineState::Alarm {
            return Err(PluginError::new(
                "alarm",
                format!(
                    "cannot {what}: the machine is in alarm ({}); send reset first",
                    self.alarm.as_deref().unwrap_or("no reason given")
                ),
            ));
        }
        Ok(())
    }

    fn cancel_pending(&mut self, ev: &mut Events) {
        let loaded = self.program.take();
        let queued = self.queue.drain(..).filter_map(|j| match j {
            Job::Program(l) => Some(l),
            _ => None,
        });
        for l in loaded.into_iter().chain(queued).collect::<Vec<_>>() {
            if self.run == Some(l.run) && !self.busy {
                self.run = None;
                self.line = None;
            }
            ev.push(Event::RunEnded {
                run: l.run,
                outcome: RunOutcome::Cancelled,
                message: Some("stopped before it started".into()),
            });
        }
    }
}

impl Core {
    fn lock(&self) -> MutexGuard<'_, Shared> {
        self.shared.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn release(&self, guard: MutexGuard<'_, Shared>, events: Events) {
        self.cv.notify_all();
        if events.is_empty() {
            drop(guard);
            return;
        }
        let order = self.emit_order.lock().unwrap_or_else(|e| e.into_inner());
        drop(guard);
        for e in &events {
            (self.sink)(e);
        }
        drop(order);
    }

    fn with<R>(&self, f: impl FnOnce(&mut Shared, &mut Events) -> R) -> R {
        let mut guard = self.lock();
        let mut ev = Vec::new();
        let r = f(&mut guard, &mut ev);
        self.release(guard, ev);
        r
    }

    fn push_status(&self, sh: &Shared, ev: &mut Events) {
        ev.push(Event::Status(sh.status(&self.cfg)));
    }

    fn set_state(&self, sh: &mut Shared, to: MachineState, ev: &mut Events) {
        if sh.state != to {
            ev.push(Event::StateChanged { from: sh.state, to });
            sh.state = to;
            self.push_status(sh, ev);
        }
    }

    fn raise_alarm(&self, sh: &mut Shared, message: String, ev: &mut Events) {
        sh.queue.clear();
        sh.alarm = Some(message.clone());
        ev.push(Event::Alarm { message });
        self.set_state(sh, MachineState::Alarm, ev);
    }

    // ----- output thread -----

    fn worker(self: Arc<Self>, mut out: Output) {
        loop {
            let job = {
                let mut sh = self.lock();
                if sh.shutdown {
                    drop(sh);
                    out.coils_off();
                    let _ = out.end(false);
                    return;
                }
                if let Some(on) = sh.lift_request.take() {
                    out.set_lift(on);
                }
                match sh.queue.pop_front() {
                    Some(job) => {
                        sh.busy = true;
                        Some(job)
                    }
                    None => {
                        if !out.coils_on() {
                            // Nothing to time: poll the inputs slowly, wake up for work.
                            let (g, _) = self
                                .cv
                                .wait_timeout(sh, IDLE_POLL)
                                .unwrap_or_else(|e| e.into_inner());
                            drop(g);
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
        if trip.is_some() {
            out.coils_off();
        }
        let estop = out.estop_active().map(|i| i.describe());
        self.with(|sh, ev| {
            sh.estop = estop;
            if let Some(input) = trip {
                if sh.state != MachineState::Alarm && sh.state != MachineState::Offline {
                    self.raise_alarm(sh, input.describe(), ev);
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
        self.with(|sh, ev| {
            if sh.state != MachineState::Alarm {
                self.raise_alarm(sh, format!("parallel port I/O failed: {e}"), ev);
            }
        });
        // Do not spin on a dead port.
        std::thread::sleep(Duration::from_millis(100));
    }

    fn finish_job(&self, out: &mut Output, job: Job) {
        let run = match &job {
            Job::Program(l) => Some(l.run),
            _ => None,
        };
        out.pacer.restart();
        let result = catch_unwind(AssertUnwindSafe(|| self.run_job(out, job)))
            .unwrap_or_else(|_| Err(Interrupted::Failed("internal error (panic)".into())));
        if matches!(result, Err(Interrupted::Alarm(_))) {
            out.coils_off();
        }
        // Write what the job left (coils off after an alarm) before anyone looks.
        let _ = out.end(false);
        let pos = out.pos;
        let estop = out.estop_active().map(|i| i.describe());
        let mut sh = self.lock();
        let mut ev = Vec::new();
        sh.busy = false;
        // Before anyone can send reset after the alarm below.
        sh.estop = estop;
        self.hold.store(false, Ordering::SeqCst);
        self.abort.store(false, Ordering::SeqCst);
        sh.steps = pos;
        let here = sh.machine_mm(&self.cfg);
        sh.end_mm = [here[0], here[1], here[2]];
        if let Some(run) = run {
            let (outcome, message) = match &result {
                Ok(()) => (RunOutcome::Completed, None),
                Err(Interrupted::Aborted) => (RunOutcome::Cancelled, None),
                Err(Interrupted::Alarm(m) | Interrupted::Failed(m)) => {
                    (RunOutcome::Failed, Some(m.clone()))
                }
            };
            sh.run = None;
            sh.line = None;
            ev.push(Event::RunEnded {
                run,
                outcome,
                message,
            });
        }
        match result {
            Err(Interrupted::Alarm(m)) => self.raise_alarm(&mut sh, m, &mut ev),
            _ if sh.queue.is_empty() && sh.state != MachineState::Offline => {
                self.set_state(&mut sh, MachineState::Idle, &mut ev);
                self.push_status(&sh, &mut ev);
            }
            _ => self.push_status(&sh, &mut ev),
        }
        self.release(sh, ev);
    }

    fn run_job(&self, out: &mut Output, job: Job) -> Result<(), Interrupted> {
        let m = &self.cfg.machine;
        match job {
            Job::Jog {
                axis,
                distance,
                feed,
            } => {
                let start = self.lock().start();
                let here = [
                    start.steps[0] as f64 / m.axes[0].steps_per_mm,
                    start.steps[1] as f64 / m.axes[1].steps_per_mm,
                    start.z,
                ];
                let mut to = here;
                to[axis.index()] += distance;
                let mut b = Builder::new(m, &start);
                b.move_to(0, [to[0], to[1]], to[2], Some(feed))
                    .map_err(|e| Interrupted::Alarm(format!("soft limit: {e}")))?;
                self.execute(out, &b.finish(0), None)
            }
            Job::GoToZero => {
                let start = self.lock().start();
                let zero = start.offsets[start.active.index()];
                let here = [
                    start.steps[0] as f64 / m.axes[0].steps_per_mm,
                    start.steps[1] as f64 / m.axes[1].steps_per_mm,
                ];
                let safe_z = start.z.max(zero[2]);
                let mut b = Builder::new(m, &start);
                let rapid = Some(m.rapid_mm_min);
                b.move_to(0, here, safe_z, rapid)
                    .and_then(|()| b.move_to(0, [zero[0], zero[1]], safe_z, rapid))
                    .and_then(|()| b.move_to(0, [zero[0], zero[1]], zero[2], rapid))
                    .map_err(|e| Interrupted::Alarm(format!("soft limit: {e}")))?;
                self.execute(out, &b.finish(0), None)
            }
            Job::Program(l) => {
                let run = (l.run, l.start_line);
                self.execute(out, &l.plan, Some(run))
            }
        }
    }

    /// Moves the timeline one tick on: ends the current tick, then starts real ticks until the
    /// timeline has advanced by one. Every started tick reads the inputs and the stop / hold
    /// flags. A feed hold slows the timeline down to a stop along a ramp (and resume speeds it
    /// up again), so the motors decelerate instead of stopping dead.
    fn advance(&self, out: &mut Output, tl: &mut Timeline) -> Result<(), Interrupted> {
        loop {
            out.end(true)
                .map_err(|e| Interrupted::Alarm(format!("parallel port I/O failed: {e}")))?;
            let trip = out
                .begin()
                .map_err(|e| Interrupted::Alarm(format!("parallel port I/O failed: {e}")))?;
            if let Some(input) = trip {
                // No step in this tick: the coils go off in the same write.
                out.coils_off();
                return Err(Interrupted::Alarm(input.describe()));
            }
            if self.abort.load(Ordering::SeqCst) {
                return Err(Interrupted::Aborted);
            }
            if tl.tick(self.hold.load(Ordering::SeqCst)) {
                return Ok(());
            }
        }
    }

    /// Executes a plan on the tick grid. `run` = (run id, first line to acknowledge).
    fn execute(
        &self,
        out: &mut Output,
        plan: &Plan,
        run: Option<(i64, u32)>,
    ) -> Result<(), Interrupted> {
        let mut tl = Timeline::new(&self.cfg);
        let mut stepped_at: Option<u64> = None;
        let mut next_ack = run.map_or(1, |r| r.1);
        let mut line_dev: Option<(u32, f64)> = None;
        let mut last_publish = Instant::now();
        // Tick 0 of the timeline.
        if let Some(input) = out
            .begin()
            .map_err(|e| Interrupted::Alarm(format!("parallel port I/O failed: {e}")))?
        {
            out.coils_off();
            return Err(Interrupted::Alarm(input.describe()));
        }
        for item in &plan.items {
            if let Some((run, _)) = run {
                // The first item of a later line: every line before it is done.
                if item.line > next_ack {
                    self.line_done(run, item.line - 1, &mut next_ack, &mut line_dev, tl.t, plan)?;
                    self.with(|sh, _| sh.line = Some(item.line));
                }
            }
            match &item.action {
                Action::Move(mv) => {
                    self.with(|sh, _| sh.feed = mv.peak_feed_mm_min());
                    for s in mv.steps() {
                        let at = item.start_tick + s.tick;
                        // At most one step per tick, whatever the schedule says: two in one
                        // write would skip a phase.
                        while tl.t < at || stepped_at == Some(tl.t) {
                            self.advance(out, &mut tl)?;
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
                            self.with(|sh, ev| {
                                sh.steps = pos;
                                self.push_status(sh, ev);
                            });
                        }
                    }
                }
                Action::Lift { on, settle, z } => {
                    out.set_lift(*on);
                    let (on, z) = (*on, *z);
                    self.with(|sh, ev| {
                        sh.lift = on;
                        sh.z = z;
                        self.push_status(sh, ev);
                    });
                    let until = item.start_tick + settle;
                    while tl.t < until {
                        self.advance(out, &mut tl)?;
                    }
                }
                Action::Dwell(ticks) => {
                    let until = item.start_tick + ticks;
                    while tl.t < until {
                        self.advance(out, &mut tl)?;
                    }
                }
                Action::Pause => {
                    // M0 comes between moves, with the motors at rest: hold at once.
                    self.hold.store(true, Ordering::SeqCst);
                    tl.rate = 0.0;
                    self.with(|sh, ev| {
                        if sh.state == MachineState::Running {
                            self.set_state(sh, MachineState::Paused, ev);
                        }
                    });
                }
                Action::UseOffset(o) => {
                    let o = *o;
                    self.with(|sh, ev| {
                        if sh.active != o {
                            sh.active = o;
                            self.push_status(sh, ev);
                        }
                    });
                }
            }
        }
        let pos = out.pos;
        self.with(|sh, _| {
            sh.steps = pos;
            sh.z = plan.end_z;
            sh.lift = plan.end_lift;
        });
        if let Some((run, _)) = run {
            self.line_done(run, plan.lines, &mut next_ack, &mut line_dev, tl.t, plan)?;
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
        plan: &Plan,
    ) -> Result<(), Interrupted> {
        let total = plan.total_ticks.max(1) as f64;
        let percent = ((t as f64 / total) * 100.0).min(100.0);
        let remaining_s = plan.total_ticks.saturating_sub(t) as f64 / self.cfg.machine.tick_hz;
        let mut ev = Vec::new();
        if let Some((l, d)) = line_dev.take() {
            ev.push(Event::LineReport {
                run,
                line: l,
                max_deviation_mm: (d * 1e6).round() / 1e6,
                percent: (percent * 10.0).round() / 10.0,
                remaining_s: (remaining_s * 1000.0).round() / 1000.0,
            });
        }
        while *next_ack <= line {
            if let Some(log) = &self.log {
                log.lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .append(run, *next_ack)
                    .map_err(Interrupted::Failed)?;
            }
            ev.push(Event::LineAcknowledged {
                run,
                line: *next_ack,
            });
            *next_ack += 1;
        }
        let sh = self.lock();
        self.release(sh, ev);
        Ok(())
    }

    // ----- requests -----

    fn connect(&self) -> Result<Value, PluginError> {
        let st = self.with(|sh, ev| {
            if sh.state == MachineState::Offline {
                sh.reason = None;
                self.set_state(sh, MachineState::Idle, ev);
            }
            sh.status(&self.cfg)
        });
        PluginError::encode(&st)
    }

    fn jog(&self, axis: Axis, distance: f64, feed: Option<f64>) -> Result<Value, PluginError> {
        if !distance.is_finite() {
            return Err(PluginError::invalid(format!(
                "jog distance must be a finite number, got {distance}"
            )));
        }
        if axis == Axis::A {
            return Err(PluginError::new(
                "unsupported",
                "this machine has no A axis (X and Y are steppers, Z is the tool lift)",
            ));
        }
        let feed = feed.unwrap_or(self.cfg.jog_feed_mm_min);
        if !(feed.is_finite() && feed > 0.0) {
            return Err(PluginError::invalid(format!(
                "jog feed must be greater than 0 mm/min, got {feed}"
            )));
        }
        self.with(|sh, ev| {
            sh.require_online()?;
            sh.require_no_alarm("jog")?;
            if !matches!(sh.state, MachineState::Idle | MachineState::Jogging) {
                return Err(PluginError::new(
                    "busy",
                    format!("cannot jog while the machine is {}", sh.state.as_str()),
                ));
            }
            if sh.queue.len() >= MAX_QUEUED_JOGS {
                return Err(PluginError::new(
                    "busy",
                    format!("{MAX_QUEUED_JOGS} jogs are already queued"),
                ));
            }
            let mut target = sh.end_mm;
            target[axis.index()] += distance;
            for i in 0..2 {
                if let Some((min, max)) = self.cfg.machine.travel[i] {
                    if target[i] < min || target[i] > max {
                        return Err(PluginError::new(
                            "out_of_travel",
                            format!(
                                "jog refused: {} would end at {:.3} mm, outside the travel [{min}, {max}]",
                                ['X', 'Y'][i],
                                target[i]
                            ),
                        ));
                    }
                }
            }
            sh.end_mm = target;
            sh.queue.push_back(Job::Jog {
                axis,
                distance,
                feed,
            });
            self.set_state(sh, MachineState::Jogging, ev);
            Ok(json!({}))
        })
    }

    /// Aborts all motion and the program; returns once the output thread confirmed.
    fn stop(&self) {
        let mut sh = self.lock();
        let mut ev = Vec::new();
        sh.cancel_pending(&mut ev);
        if sh.busy {
            self.abort.store(true, Ordering::SeqCst);
            self.release(sh, ev);
            let deadline = Instant::now() + STOP_CONFIRM;
            let mut sh = self.lock();
            while sh.busy {
                let now = Instant::now();
                if now >= deadline {
                    break;
                }
                sh = self
                    .cv
                    .wait_timeout(sh, deadline - now)
                    .map(|(g, _)| g)
                    .unwrap_or_else(|e| e.into_inner().0);
            }
        } else {
            if matches!(
                sh.state,
                MachineState::Jogging | MachineState::Running | MachineState::Paused
            ) {
                self.set_state(&mut sh, MachineState::Idle, &mut ev);
            }
            self.release(sh, ev);
        }
    }

    fn pause(&self, strict: bool) -> Result<Value, PluginError> {
        let jogging = self.with(|sh, ev| match sh.state {
            MachineState::Running => {
                self.hold.store(true, Ordering::SeqCst);
                self.set_state(sh, MachineState::Paused, ev);
                Ok(false)
            }
            MachineState::Jogging if !strict => Ok(true),
            _ if strict && sh.run.is_none() => Err(PluginError::new(
                "not_running",
                "no program is running: nothing to pause",
            )),
            _ => Ok(false),
        })?;
        if jogging {
            self.stop();
        }
        Ok(json!({}))
    }

    fn resume(&self, strict: bool) -> Result<Value, PluginError> {
        self.with(|sh, ev| match sh.state {
            MachineState::Paused => {
                self.hold.store(false, Ordering::SeqCst);
                self.set_state(sh, MachineState::Running, ev);
                Ok(json!({}))
            }
            _ if strict && sh.run.is_none() => Err(PluginError::new(
                "not_running",
                "no program is running: nothing to resume",
            )),
            _ => Ok(json!({})),
        })
    }

    fn cycle_start(&self) -> Result<Value, PluginError> {
        self.with(|sh, ev| {
            sh.require_online()?;
            sh.require_no_alarm("start")?;
            match sh.state {
                MachineState::Paused => {
                    self.hold.store(false, Ordering::SeqCst);
                    self.set_state(sh, MachineState::Running, ev);
                    return Ok(json!({}));
                }
                MachineState::Running => return Ok(json!({})),
                _ => {}
            }
            sh.require_still("start a program")?;
            let loaded = sh.program.take().ok_or_else(|| {
                PluginError::new(
                    "no_program",
                    "no program is loaded: send load_program first",
                )
            })?;
            sh.run = Some(loaded.run);
            sh.line = Some(loaded.start_line);
            sh.queue.push_back(Job::Program(loaded));
            self.set_state(sh, MachineState::Running, ev);
            Ok(json!({}))
        })
    }

    fn command(&self, c: Command) -> Result<Value, PluginError> {
        match c {
            Command::CycleStart => self.cycle_start(),
            Command::FeedHold => self.pause(false),
            Command::Resume => self.resume(false),
            Command::Stop => {
                self.stop();
                Ok(json!({}))
            }
            Command::Reset => {
                self.stop();
                self.with(|sh, ev| {
                    if sh.state == MachineState::Alarm {
                        if let Some(e) = &sh.estop {
                            return Err(PluginError::new(
                                "alarm",
                                format!("cannot reset: {e} is still active"),
                            ));
                        }
                        sh.alarm = None;
                        self.set_state(sh, MachineState::Idle, ev);
                    }
                    Ok(json!({}))
                })
            }
            Command::Home { axis } => self.with(|sh, ev| {
                // No home switches: homing declares the current position machine zero.
                sh.require_still("home")?;
                match axis {
                    Some(Axis::X) => sh.steps[0] = 0,
                    Some(Axis::Y) => sh.steps[1] = 0,
                    Some(Axis::Z) => sh.z = 0.0,
                    Some(Axis::A) => {}
                    None => {
                        sh.steps = [0, 0];
                        sh.z = 0.0;
                    }
                }
                let here = sh.machine_mm(&self.cfg);
                sh.end_mm = [here[0], here[1], here[2]];
                self.push_status(sh, ev);
                Ok(json!({}))
            }),
            Command::Zero { axis } => self.with(|sh, ev| {
                sh.require_still("zero")?;
                let (pos, i) = (sh.machine_mm(&self.cfg), sh.active.index());
                match axis {
                    Some(a) => sh.offsets[i][a.index()] = pos[a.index()],
                    None => sh.offsets[i] = pos,
                }
                self.push_status(sh, ev);
                Ok(json!({ "offsets": PluginError::encode(&sh.offset_table())? }))
            }),
            Command::GoToZero => self.with(|sh, ev| {
                sh.require_no_alarm("go to zero")?;
                sh.require_still("go to zero")?;
                let zero = sh.offsets[sh.active.index()];
                sh.end_mm = [zero[0], zero[1], zero[2]];
                sh.queue.push_back(Job::GoToZero);
                self.set_state(sh, MachineState::Jogging, ev);
                Ok(json!({}))
            }),
            Command::SelectOffset { offset } => self.with(|sh, ev| {
                sh.require_still("select an offset")?;
                sh.active = offset;
                self.push_status(sh, ev);
                Ok(json!({}))
            }),
            Command::SetOutput {
                name: OutputName::ZLift,
                on,
            } => self.with(|sh, _| {
                sh.require_no_alarm("switch the Z lift")?;
                sh.require_still("switch the Z lift")?;
                sh.lift = on;
                sh.lift_request = Some(on);
                Ok(json!({ "z_lift": on }))
            }),
            Command::ToggleOutput {
                name: OutputName::ZLift,
            } => self.with(|sh, _| {
                sh.require_no_alarm("switch the Z lift")?;
                sh.require_still("switch the Z lift")?;
                let on = !sh.lift;
                sh.lift = on;
                sh.lift_request = Some(on);
                Ok(json!({ "z_lift": on, "output": OutputName::ZLift, "on": on }))
            }),
            Command::SetOutput { name, .. } | Command::ToggleOutput { name } => {
                Err(PluginError::new(
                    "unsupported",
                    format!(
                        "parport-stepper has no output {:?} (only \"z_lift\")",
                        name.as_str()
                    ),
                ))
            }
        }
    }

    fn set_offset(&self, offset: WorkOffset, values: AxisValues) -> Result<Value, PluginError> {
        if values.to_array().iter().any(|v| !v.is_finite()) {
            return Err(PluginError::invalid("offset values must be finite numbers"));
        }
        self.with(|sh, ev| {
            sh.require_still("change offsets")?;
            sh.offsets[offset.index()] = values.to_array();
            if offset == sh.active {
                self.push_status(sh, ev);
            }
            Ok(json!({}))
        })
    }

    fn load_program(&self, run: i64, path: &str, start_line: u32) -> Result<Value, PluginError> {
        if start_line == 0 {
            return Err(PluginError::invalid(
                "start_line is 1-based: 0 is not a line",
            ));
        }
        let start = {
            let sh = self.lock();
            sh.require_still("load a program")?;
            sh.start()
        };
        let bytes = std::fs::read(path).map_err(|e| {
            PluginError::new("program_unreadable", format!("cannot read {path}: {e}"))
        })?;
        let text = String::from_utf8(bytes).map_err(|e| {
            let valid = &e.as_bytes()[..e.utf8_error().valid_up_to()];
            let line = valid.iter().filter(|b| **b == b'\n').count() + 1;
            PluginError::new(
                "invalid_program",
                format!("line {line}: {path} is not UTF-8 text"),
            )
        })?;
        let mut actual = start_line;
        if let Some(log) = &self.log {
            let last = log
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .last_line(run)?;
            if let Some(last) = last {
                actual = actual.max(last.saturating_add(1));
            }
        }
        let plan =
            planner::plan_program(&self.cfg.machine, &text, &start, actual).map_err(|m| {
                let code = if m.contains("outside the travel") {
                    "out_of_travel"
                } else {
                    "invalid_program"
                };
                PluginError::new(code, m)
            })?;
        let end = plan.lines.saturating_add(1);
        if start_line > end {
            return Err(PluginError::invalid(format!(
                "start_line {start_line} is past the end of the program ({} lines)",
                plan.lines
            )));
        }
        let actual = actual.min(end);
        let lines = plan.lines;
        self.with(|sh, ev| {
            sh.require_still("load a program")?;
            if let Some(old) = sh.program.take() {
                if old.run != run {
                    ev.push(Event::RunEnded {
                        run: old.run,
                        outcome: RunOutcome::Cancelled,
                        message: Some(format!("replaced by run {run} before it started")),
                    });
                }
            }
            sh.program = Some(Loaded {
                run,
                plan,
                start_line: actual,
            });
            Ok(())
        })?;
        PluginError::encode(&ProgramLoaded {
            lines,
            start_line: actual,
        })
    }

    fn shutdown(&self) {
        self.stop();
        self.with(|sh, ev| {
            sh.reason = Some("shut down".into());
            sh.alarm = None;
            self.set_state(sh, MachineState::Offline, ev);
        });
    }

    fn handle(&self, request: Request) -> Result<Value, PluginError> {
        match request {
            Request::GetArtifact { name } => Err(PluginError::new(
                "unknown_artifact",
                format!("parport-stepper has no artifact {name:?}"),
            )),
            Request::Connect => self.connect(),
            Request::Status => PluginError::encode(&self.lock().status(&self.cfg)),
            Request::Jog {
                axis,
                distance,
                feed,
            } => self.jog(axis, distance, feed),
            Request::Command(c) => self.command(c),
            Request::GetOffsets => PluginError::encode(&self.lock().offset_table()),
            Request::SetOffset { offset, values } => self.set_offset(offset, values),
            Request::LoadProgram {
                run,
                path,
                start_line,
                ..
            } => self.load_program(run, &path, start_line),
            Request::Run { action } => match action {
                RunAction::Start => self.cycle_start(),
                RunAction::Pause => self.pause(true),
                RunAction::Resume => self.resume(true),
                RunAction::Cancel => {
                    self.stop();
                    Ok(json!({}))
                }
            },
            Request::Shutdown => {
                self.shutdown();
                Ok(json!({}))
            }
            Request::Mdi { .. } => Err(PluginError::new(
                "unsupported",
                "parport-stepper runs whole programs only: no MDI",
            )),
        }
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
            Some(path) => Some(Mutex::new(ExecLog::open(path)?)),
            None => None,
        };
        let period = match timing {
            Timing::Real => Some(Duration::from_secs_f64(1.0 / cfg.machine.tick_hz)),
            Timing::Virtual => None,
        };
        let out = Output::new(&cfg, port, Pacer::new(period, cfg.spin), false);
        let core = Arc::new(Core {
            cfg,
            sink,
            shared: Mutex::new(Shared {
                state: MachineState::Offline,
                reason: Some("not connected yet".into()),
                alarm: None,
                steps: [0, 0],
                z: 0.0,
                lift: false,
                lift_request: None,
                end_mm: [0.0; 3],
                offsets: [[0.0; 4]; 6],
                active: WorkOffset::G54,
                feed: 0.0,
                run: None,
                line: None,
                program: None,
                queue: VecDeque::new(),
                busy: false,
                shutdown: false,
                estop: None,
            }),
            cv: Condvar::new(),
            emit_order: Mutex::new(()),
            log: exec_log,
            abort: AtomicBool::new(false),
            hold: AtomicBool::new(false),
        });
        let worker_core = Arc::clone(&core);
        let want_rt = core.cfg.realtime_priority && timing == Timing::Real;
        let worker = std::thread::Builder::new()
            .name("parport output".into())
            .spawn(move || {
                if want_rt {
                    match realtime_priority() {
                        Ok(()) => log(LogLevel::Info, "output loop runs with real-time priority (SCHED_FIFO)"),
                        Err(e) => log(
                            LogLevel::Warn,
                            &format!(
                                "output loop could NOT get real-time priority ({e}); step timing may jitter under load. Grant CAP_SYS_NICE (e.g. `setcap cap_sys_nice+ep fresa`) or raise RLIMIT_RTPRIO"
                            ),
                        ),
                    }
                }
                worker_core.worker(out)
            })
            .map_err(|e| {
                PluginError::new("internal", format!("cannot start the output thread: {e}"))
            })?;
        Ok(Stepper {
            core,
            worker: Mutex::new(Some(worker)),
            sim_port,
        })
    }

    pub fn request(&self, request: Value) -> Result<Value, PluginError> {
        let request = Request::from_json(request)?;
        self.core.handle(request)
    }

    pub fn handle(&self, request: Request) -> Result<Value, PluginError> {
        self.core.handle(request)
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
        self.core.with(|sh, _| sh.shutdown = true);
        self.core.abort.store(true, Ordering::SeqCst);
        let handle = self.worker.lock().unwrap_or_else(|e| e.into_inner()).take();
        if let Some(h) = handle {
            let _ = h.join();
        }
    }
}

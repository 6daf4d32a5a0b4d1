//! The simulated machine: state shared between request threads and the one motion thread the
//! machine owns. Requests only change state and queue work; the motion thread moves the axes in
//! small time slices, so stop and feed hold take effect within one slice.

use crate::config::Config;
use crate::program::{self, Plan, Step};
use fresa_plugin_api::contract::{
    Axis, AxisValues, Command, Event, MachineState, MachineStatus, OffsetTable, OutputName,
    ProgramLoaded, Request, RunAction, RunOutcome, WorkOffset,
};
use fresa_plugin_api::exec_log::ExecLog;
use fresa_plugin_api::PluginError;
use serde_json::{json, Value};
use std::collections::VecDeque;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// Receives every event the machine emits, from any thread, in order.
pub type EventSink = Arc<dyn Fn(&Event) + Send + Sync>;

/// Longest time the motion thread goes without looking at stop / feed hold.
const SLICE: Duration = Duration::from_millis(5);
/// Jog requests queued behind the running one at most.
const MAX_QUEUED_JOGS: usize = 64;
/// How long `stop` waits for the motion thread to confirm that motion ended.
const STOP_CONFIRM: Duration = Duration::from_secs(5);

/// A simulated 4-axis machine. Thread-safe; dropping it stops motion and joins its thread.
pub struct SimMachine {
    core: Arc<Core>,
    worker: Mutex<Option<JoinHandle<()>>>,
}

struct Core {
    cfg: Config,
    sink: EventSink,
    shared: Mutex<Shared>,
    /// Signalled on every change the motion thread or a waiting `stop` may care about.
    cv: Condvar,
    /// Held while emitting, taken before `shared` is released, so events leave in the order
    /// the state changed.
    emit_order: Mutex<()>,
    log: Option<Mutex<ExecLog>>,
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
    /// One MDI line: straight moves to these machine targets, each at its feed.
    Mdi(Vec<([f64; 4], f64)>),
    Program(Loaded),
}

#[derive(Debug)]
struct Shared {
    state: MachineState,
    reason: Option<String>,
    alarm: Option<String>,
    /// Machine position, mm (A in degrees).
    pos: [f64; 4],
    /// End of the move in progress, if any.
    move_end: Option<[f64; 4]>,
    /// Machine origin of G54..G59.
    offsets: [[f64; 4]; 6],
    active: WorkOffset,
    feed: f64,
    run: Option<i64>,
    line: Option<u32>,
    /// Loaded with `load_program`, not started yet.
    program: Option<Loaded>,
    queue: VecDeque<Job>,
    /// The motion thread is executing a job.
    busy: bool,
    /// Abort the job in progress (set by stop, cleared by the motion thread).
    abort: bool,
    shutdown: bool,
    last_status: Option<Instant>,
    spindle: bool,
    coolant: bool,
}

/// Why a job ended early.
enum Interrupted {
    Aborted,
    Alarm(String),
    Failed(String),
}

type Events = Vec<Event>;

impl Shared {
    fn status(&self) -> MachineStatus {
        let off = self.offsets[self.active.index()];
        let work: [f64; 4] = std::array::from_fn(|i| self.pos[i] - off[i]);
        MachineStatus {
            state: self.state,
            machine_position: AxisValues::from_array(self.pos),
            work_position: AxisValues::from_array(work),
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

    fn push_status(&mut self, ev: &mut Events) {
        ev.push(Event::Status(self.status()));
        self.last_status = Some(Instant::now());
    }

    fn set_state(&mut self, to: MachineState, ev: &mut Events) {
        if self.state != to {
            ev.push(Event::StateChanged {
                from: self.state,
                to,
            });
            self.state = to;
            self.push_status(ev);
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

    /// Refuses while anything moves or a run is in progress (offsets, homing, loading).
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

    /// Refuses new motion while in alarm.
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

    /// Drops queued jobs and the loaded program; runs among them end as cancelled.
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

fn distance(a: &[f64; 4], b: &[f64; 4]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y) * (x - y))
        .sum::<f64>()
        .sqrt()
}

impl Core {
    fn lock(&self) -> MutexGuard<'_, Shared> {
        self.shared.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Releases the state lock, then emits `events` (in order with every other emitter).
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

    /// Runs `f` under the state lock and emits what it produced.
    fn with<R>(&self, f: impl FnOnce(&mut Shared, &mut Events) -> R) -> R {
        let mut guard = self.lock();
        let mut ev = Vec::new();
        let r = f(&mut guard, &mut ev);
        self.release(guard, ev);
        r
    }

    // ----- motion thread -----

    fn worker(self: Arc<Self>) {
        loop {
            let mut sh = self.lock();
            while sh.queue.is_empty() && !sh.shutdown {
                sh = self.cv.wait(sh).unwrap_or_else(|e| e.into_inner());
            }
            if sh.shutdown {
                return;
            }
            let Some(job) = sh.queue.pop_front() else {
                continue;
            };
            sh.busy = true;
            let run = match &job {
                Job::Program(l) => Some(l.run),
                _ => None,
            };
            drop(sh);

            let result = catch_unwind(AssertUnwindSafe(|| self.run_job(job)))
                .unwrap_or_else(|_| Err(Interrupted::Failed("internal error (panic)".into())));

            let mut sh = self.lock();
            let mut ev = Vec::new();
            sh.busy = false;
            sh.abort = false;
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
            if let Err(Interrupted::Alarm(m)) = result {
                sh.queue.clear();
                sh.alarm = Some(m.clone());
                ev.push(Event::Alarm { message: m });
                sh.set_state(MachineState::Alarm, &mut ev);
            } else if sh.queue.is_empty() && sh.state != MachineState::Offline {
                sh.set_state(MachineState::Idle, &mut ev);
            }
            self.release(sh, ev);
        }
    }

    fn run_job(&self, job: Job) -> Result<(), Interrupted> {
        match job {
            Job::Jog {
                axis,
                distance,
                feed,
            } => {
                let mut target = self.lock().pos;
                target[axis.index()] += distance;
                self.cfg
                    .check_travel(target)
                    .map_err(|m| Interrupted::Alarm(format!("soft limit: {m}")))?;
                self.move_to(target, feed)
            }
            Job::GoToZero => {
                let (pos, zero) = {
                    let sh = self.lock();
                    (sh.pos, sh.offsets[sh.active.index()])
                };
                let rapid = self.cfg.rapid_mm_min;
                let safe_z = pos[2].max(zero[2]);
                self.move_to([pos[0], pos[1], safe_z, pos[3]], rapid)?;
                self.move_to([zero[0], zero[1], safe_z, zero[3]], rapid)?;
                self.move_to(zero, rapid)
            }
            Job::Mdi(moves) => {
                // An MDI line's feed is not left behind as the programmed feed.
                let feed = self.lock().feed;
                let result = moves.iter().try_for_each(|&(to, f)| self.move_to(to, f));
                self.lock().feed = feed;
                result
            }
            Job::Program(l) => self.run_program(l),
        }
    }

    fn run_program(&self, l: Loaded) -> Result<(), Interrupted> {
        let steps = &l.plan.steps;
        // Lines before the start line are interpreted (done at load) but not executed: only
        // their modal effects carry over.
        let skip = steps.partition_point(|(line, _)| *line < l.start_line);
        self.with(|sh, _| {
            for (_, step) in &steps[..skip] {
                match step {
                    Step::Move { feed: Some(f), .. } => sh.feed = *f,
                    Step::UseOffset(o) => sh.active = *o,
                    _ => {}
                }
            }
        });
        let mut cursor = skip;
        for line in l.start_line..=l.plan.lines {
            self.with(|sh, _| sh.line = Some(line));
            while let Some((_, step)) = steps.get(cursor).filter(|(sl, _)| *sl <= line) {
                self.run_step(step)?;
                cursor += 1;
            }
            if let Some(log) = &self.log {
                log.lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .append(l.run, line)
                    .map_err(Interrupted::Failed)?;
            }
            self.with(|_, ev| ev.push(Event::LineAcknowledged { run: l.run, line }));
        }
        Ok(())
    }

    fn run_step(&self, step: &Step) -> Result<(), Interrupted> {
        match *step {
            Step::Move { to, feed } => {
                let target = {
                    let sh = self.lock();
                    program::machine_target(to, &sh.offsets[sh.active.index()], sh.pos[3])
                };
                self.cfg
                    .check_travel(target)
                    .map_err(|m| Interrupted::Alarm(format!("soft limit: {m}")))?;
                self.move_to(target, feed.unwrap_or(self.cfg.rapid_mm_min))
            }
            Step::Dwell(seconds) => self.timed(None, seconds.max(0.0) * self.cfg.time_scale, 0.0),
            Step::Pause => {
                self.with(|sh, ev| {
                    if sh.state == MachineState::Running {
                        sh.set_state(MachineState::Paused, ev);
                    }
                });
                self.timed(None, 0.0, 0.0)
            }
            Step::UseOffset(o) => {
                self.with(|sh, ev| {
                    if sh.active != o {
                        sh.active = o;
                        sh.push_status(ev);
                    }
                });
                Ok(())
            }
        }
    }

    fn move_to(&self, target: [f64; 4], feed: f64) -> Result<(), Interrupted> {
        let start = self.lock().pos;
        let seconds = self.cfg.move_seconds(distance(&start, &target), feed);
        self.timed(Some((start, target)), seconds, feed)
    }

    /// Spends `seconds` (already scaled) of un-held time, moving linearly from `start` to
    /// `target` when given. Holds while the machine is paused; returns early on abort.
    fn timed(
        &self,
        path: Option<([f64; 4], [f64; 4])>,
        seconds: f64,
        feed: f64,
    ) -> Result<(), Interrupted> {
        let mut sh = self.lock();
        if let Some((_, end)) = path {
            sh.feed = feed;
            sh.move_end = Some(end);
        }
        let result = self.timed_locked(sh, path, seconds);
        self.lock().move_end = None;
        result
    }

    fn timed_locked<'a>(
        &'a self,
        mut sh: MutexGuard<'a, Shared>,
        path: Option<([f64; 4], [f64; 4])>,
        seconds: f64,
    ) -> Result<(), Interrupted> {
        let mut done = 0.0;
        let mut last = Instant::now();
        loop {
            if sh.abort || sh.shutdown {
                return Err(Interrupted::Aborted);
            }
            if sh.state == MachineState::Paused {
                // Feed hold: the position stays where the last slice left it.
                sh = self.cv.wait(sh).unwrap_or_else(|e| e.into_inner());
                last = Instant::now();
                continue;
            }
            let now = Instant::now();
            done += now.duration_since(last).as_secs_f64();
            last = now;
            let frac = if seconds <= 0.0 {
                1.0
            } else {
                (done / seconds).min(1.0)
            };
            if let Some((a, b)) = path {
                sh.pos = if frac >= 1.0 {
                    b
                } else {
                    std::array::from_fn(|i| a[i] + (b[i] - a[i]) * frac)
                };
                let due = sh
                    .last_status
                    .is_none_or(|t| now.duration_since(t) >= self.cfg.status_interval);
                if due {
                    let mut ev = Vec::new();
                    sh.push_status(&mut ev);
                    self.release(sh, ev);
                    sh = self.lock();
                }
            }
            if frac >= 1.0 {
                return Ok(());
            }
            let wait = Duration::from_secs_f64(seconds - done).min(SLICE);
            sh = self
                .cv
                .wait_timeout(sh, wait)
                .map(|(g, _)| g)
                .unwrap_or_else(|e| e.into_inner().0);
        }
    }

    // ----- requests -----

    fn status(&self) -> Result<Value, PluginError> {
        let st = self.lock().status();
        PluginError::encode(&st)
    }

    fn connect(&self) -> Result<Value, PluginError> {
        let st = self.with(|sh, ev| {
            if sh.state == MachineState::Offline {
                sh.reason = None;
                match &self.cfg.alarm_at_connect {
                    Some(m) => {
                        sh.alarm = Some(m.clone());
                        ev.push(Event::Alarm { message: m.clone() });
                        sh.set_state(MachineState::Alarm, ev);
                    }
                    None => sh.set_state(MachineState::Idle, ev),
                }
            }
            sh.status()
        });
        PluginError::encode(&st)
    }

    fn jog(&self, axis: Axis, distance: f64, feed: Option<f64>) -> Result<Value, PluginError> {
        if !distance.is_finite() {
            return Err(PluginError::invalid(format!(
                "jog distance must be a finite number, got {distance}"
            )));
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
            // Where this jog will end, counting the move in progress and the jogs queued.
            let mut target = sh.move_end.unwrap_or(sh.pos);
            for job in &sh.queue {
                if let Job::Jog { axis, distance, .. } = job {
                    target[axis.index()] += distance;
                }
            }
            target[axis.index()] += distance;
            self.cfg
                .check_travel(target)
                .map_err(|m| PluginError::new("out_of_travel", format!("jog refused: {m}")))?;
            sh.queue.push_back(Job::Jog {
                axis,
                distance,
                feed,
            });
            sh.set_state(MachineState::Jogging, ev);
            Ok(json!({}))
        })
    }

    /// Aborts all motion and the program; returns once the motion thread confirmed.
    fn stop(&self) {
        let mut sh = self.lock();
        let mut ev = Vec::new();
        sh.cancel_pending(&mut ev);
        if sh.busy {
            sh.abort = true;
            self.release(sh, ev);
            let deadline = Instant::now() + STOP_CONFIRM;
            let mut sh = self.lock();
            while sh.busy && sh.abort {
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
                sh.set_state(MachineState::Idle, &mut ev);
            }
            self.release(sh, ev);
        }
    }

    fn pause(&self, strict: bool) -> Result<Value, PluginError> {
        let jogging = self.with(|sh, ev| match sh.state {
            MachineState::Running => {
                sh.set_state(MachineState::Paused, ev);
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
            // A jog is not resumable: feed hold ends it where it is.
            self.stop();
        }
        Ok(json!({}))
    }

    fn resume(&self, strict: bool) -> Result<Value, PluginError> {
        self.with(|sh, ev| match sh.state {
            MachineState::Paused => {
                sh.set_state(MachineState::Running, ev);
                Ok(json!({}))
            }
            _ if strict && sh.run.is_none() => Err(PluginError::new(
                "not_running",
                "no program is running: nothing to resume",
            )),
            _ => Ok(json!({})),
        })
    }

    /// Starts the loaded program, or resumes a paused one.
    fn cycle_start(&self) -> Result<Value, PluginError> {
        self.with(|sh, ev| {
            sh.require_online()?;
            sh.require_no_alarm("start")?;
            match sh.state {
                MachineState::Paused => {
                    sh.set_state(MachineState::Running, ev);
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
            sh.set_state(MachineState::Running, ev);
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
                    // As a controller's reset does: spindle and coolant off.
                    sh.spindle = false;
                    sh.coolant = false;
                    if sh.state == MachineState::Alarm {
                        sh.alarm = None;
                        sh.set_state(MachineState::Idle, ev);
                    }
                });
                Ok(json!({}))
            }
            Command::Home { axis } => self.with(|sh, ev| {
                sh.require_still("home")?;
                match axis {
                    Some(a) => sh.pos[a.index()] = 0.0,
                    None => sh.pos = [0.0; 4],
                }
                sh.push_status(ev);
                Ok(json!({}))
            }),
            Command::Zero { axis } => self.with(|sh, ev| {
                sh.require_still("zero")?;
                let (pos, i) = (sh.pos, sh.active.index());
                match axis {
                    Some(a) => sh.offsets[i][a.index()] = pos[a.index()],
                    None => sh.offsets[i] = pos,
                }
                sh.push_status(ev);
                Ok(json!({ "offsets": PluginError::encode(&sh.offset_table())? }))
            }),
            Command::GoToZero => self.with(|sh, ev| {
                sh.require_no_alarm("go to zero")?;
                sh.require_still("go to zero")?;
                let zero = sh.offsets[sh.active.index()];
                let mut waypoint = sh.pos;
                waypoint[2] = waypoint[2].max(zero[2]);
                for p in [waypoint, [zero[0], zero[1], waypoint[2], zero[3]], zero] {
                    self.cfg.check_travel(p).map_err(|m| {
                        PluginError::new("out_of_travel", format!("go to zero refused: {m}"))
                    })?;
                }
                sh.queue.push_back(Job::GoToZero);
                sh.set_state(MachineState::Jogging, ev);
                Ok(json!({}))
            }),
            Command::SetOutput { name, on } => self.set_output(name, Some(on)),
            Command::ToggleOutput { name } => self.set_output(name, None),
            Command::SelectOffset { offset } => self.with(|sh, ev| {
                sh.require_still("select an offset")?;
                sh.active = offset;
                sh.push_status(ev);
                Ok(json!({}))
            }),
        }
    }

    /// Switches spindle or coolant (`None` = toggle). Switching on is refused in alarm;
    /// switching off never is. Answers the new state.
    fn set_output(&self, name: OutputName, on: Option<bool>) -> Result<Value, PluginError> {
        self.with(|sh, _| {
            sh.require_online()?;
            let current = match name {
                OutputName::Spindle => sh.spindle,
                OutputName::Coolant => sh.coolant,
                OutputName::ZLift => {
                    return Err(PluginError::new(
                        "unsupported",
                        format!("sim-machine has no output {:?}", name.as_str()),
                    ))
                }
            };
            let new = on.unwrap_or(!current);
            if new && !current {
                sh.require_no_alarm(&format!("switch the {} on", name.as_str()))?;
            }
            if name == OutputName::Spindle {
                sh.spindle = new;
            } else {
                sh.coolant = new;
            }
            Ok(json!({"output": name, "on": new}))
        })
    }

    /// One MDI line: interpreted alone from the current work position (so G91/G90, F and
    /// motion mode in it last for this line only), every move checked against `travel`
    /// before any starts, then run like a jog (state `jogging`, stop/feed hold end it).
    fn mdi(&self, line: &str) -> Result<Value, PluginError> {
        if line.contains(['\n', '\r']) {
            return Err(PluginError::new(
                "invalid_gcode",
                "MDI takes exactly one line (no line breaks)",
            ));
        }
        let (work, offsets, active) = {
            let sh = self.lock();
            sh.require_online()?;
            sh.require_no_alarm("run MDI")?;
            sh.require_still("run MDI")?;
            (sh.status().work_position.to_array(), sh.offsets, sh.active)
        };
        let plan = program::plan(
            line,
            [work[0], work[1], work[2]],
            offsets.map(|o| [o[0], o[1], o[2]]),
        )
        .map_err(|e| PluginError::new("invalid_gcode", format!("MDI {line:?}: {e}")))?;
        let a = self.lock().pos[3];
        let mut moves = Vec::new();
        for (_, step) in &plan.steps {
            match step {
                Step::Move { to, feed } => {
                    let target = program::machine_target(*to, &offsets[active.index()], a);
                    self.cfg.check_travel(target).map_err(|m| {
                        PluginError::new("out_of_travel", format!("MDI {line:?} refused: {m}"))
                    })?;
                    moves.push((target, feed.unwrap_or(self.cfg.rapid_mm_min)));
                }
                other => {
                    return Err(PluginError::new(
                        "unsupported",
                        format!(
                            "sim-machine MDI runs moves only; {line:?} has {}",
                            match other {
                                Step::Dwell(_) => "a dwell",
                                Step::Pause => "a program pause",
                                _ => "a work offset change",
                            }
                        ),
                    ))
                }
            }
        }
        self.with(|sh, ev| {
            sh.require_no_alarm("run MDI")?;
            sh.require_still("run MDI")?;
            if sh.offsets != offsets || sh.active != active {
                return Err(PluginError::new(
                    "busy",
                    "the work offsets changed while the MDI line was checked; send it again",
                ));
            }
            if !moves.is_empty() {
                sh.queue.push_back(Job::Mdi(moves));
                sh.set_state(MachineState::Jogging, ev);
            }
            Ok(json!({}))
        })
    }

    fn set_offset(&self, offset: WorkOffset, values: AxisValues) -> Result<Value, PluginError> {
        if values.to_array().iter().any(|v| !v.is_finite()) {
            return Err(PluginError::invalid("offset values must be finite numbers"));
        }
        self.with(|sh, ev| {
            sh.require_still("change offsets")?;
            sh.offsets[offset.index()] = values.to_array();
            if offset == sh.active {
                sh.push_status(ev);
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
        let (work, offsets, active, a) = {
            let sh = self.lock();
            sh.require_still("load a program")?;
            let st = sh.status();
            (
                st.work_position.to_array(),
                sh.offsets,
                sh.active,
                sh.pos[3],
            )
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
        let xyz = offsets.map(|o| [o[0], o[1], o[2]]);
        let plan = program::plan(&text, [work[0], work[1], work[2]], xyz)
            .map_err(|e| PluginError::new("invalid_program", e.to_string()))?;
        plan.check_moves(&offsets, active, a, |p| self.cfg.check_travel(p))
            .map_err(|m| PluginError::new("out_of_travel", m))?;
        let end = plan.lines.saturating_add(1);
        if start_line > end {
            return Err(PluginError::invalid(format!(
                "start_line {start_line} is past the end of the program ({} lines)",
                plan.lines
            )));
        }
        let mut actual = start_line;
        if let Some(log) = &self.log {
            let last = log
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .last_line(run)?;
            if let Some(last) = last {
                actual = actual.max(last.saturating_add(1)).min(end);
            }
        }
        let lines = plan.lines;
        self.with(|sh, ev| {
            sh.require_still("load a program")?;
            // A program loaded earlier and never started is replaced.
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
            sh.set_state(MachineState::Offline, ev);
        });
    }

    fn handle(&self, request: Request) -> Result<Value, PluginError> {
        match request {
            Request::Connect => self.connect(),
            Request::Status => self.status(),
            Request::Jog {
                axis,
                distance,
                feed,
            } => self.jog(axis, distance, feed),
            Request::Command(c) => self.command(c),
            Request::GetOffsets => PluginError::encode(&self.lock().offset_table()),
            Request::SetOffset { offset, values } => self.set_offset(offset, values),
            // The simulated machine has no part zero of its own to compare.
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
            Request::GetArtifact { name } => Err(PluginError::new(
                "unknown_artifact",
                format!("sim-machine has no artifact {name:?}"),
            )),
            Request::Mdi { line } => self.mdi(&line),
        }
    }
}

impl SimMachine {
    /// Creates a machine from its JSON config; its events go to `sink`.
    pub fn new(config: &Value, sink: EventSink) -> Result<SimMachine, PluginError> {
        let cfg = Config::from_json(config)?;
        let log = match &cfg.execution_log {
            Some(path) => Some(Mutex::new(ExecLog::open(path)?)),
            None => None,
        };
        let core = Arc::new(Core {
            cfg,
            sink,
            shared: Mutex::new(Shared {
                state: MachineState::Offline,
                reason: Some("not connected yet".into()),
                alarm: None,
                pos: [0.0; 4],
                move_end: None,
                offsets: [[0.0; 4]; 6],
                active: WorkOffset::G54,
                feed: 0.0,
                run: None,
                line: None,
                program: None,
                queue: VecDeque::new(),
                busy: false,
                abort: false,
                shutdown: false,
                last_status: None,
                spindle: false,
                coolant: false,
            }),
            cv: Condvar::new(),
            emit_order: Mutex::new(()),
            log,
        });
        let worker_core = Arc::clone(&core);
        let worker = std::thread::Builder::new()
            .name("sim-machine motion".into())
            .spawn(move || worker_core.worker())
            .map_err(|e| {
                PluginError::new("internal", format!("cannot start the motion thread: {e}"))
            })?;
        Ok(SimMachine {
            core,
            worker: Mutex::new(Some(worker)),
        })
    }

    /// Handles one JSON request (see `fresa_plugin_api::contract::Request`).
    pub fn request(&self, request: Value) -> Result<Value, PluginError> {
        let request = Request::from_json(request)?;
        self.core.handle(request)
    }

    /// The typed form of [`SimMachine::request`].
    pub fn handle(&self, request: Request) -> Result<Value, PluginError> {
        self.core.handle(request)
    }
}

impl Drop for SimMachine {
    fn drop(&mut self) {
        self.core.with(|sh, _| {
            sh.shutdown = true;
            sh.abort = true;
        });
        let handle = self.worker.lock().unwrap_or_else(|e| e.into_inner()).take();
        if let Some(h) = handle {
            let _ = h.join();
        }
    }
}

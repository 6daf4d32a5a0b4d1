//! The state handling shared by machine backends that plan and time motion themselves
//! (sim-machine, parport-stepper): one state machine (offline, idle, jogging, running, paused,
//! alarm), the job queue a motion thread works off, run bookkeeping, work offsets, execution
//! log use, line acknowledgements, event emission in order, and the soft-limit check every
//! motion passes. A backend keeps only what moves: its motion thread and its planner.
//! Holds say why (`State::hold`, the status's `hold`); a program's tool-change hold
//! ([`Kit::program_hold`], [`Kit::serve_tool_change`]) lets jogs, probing moves and offset
//! changes through while the run waits for cycle start.
//!
//! Threads: request threads call the [`Kit`] request methods; one motion thread per machine
//! takes [`Job`]s ([`Kit::take_job`]), executes them, and reports with [`Kit::finish_job`].
//! Stop, cancel and hold answer only once the motion thread confirmed (see the README).

use crate::config_fields::{invalid, number, object};
use crate::contract::{
    io, Axis, AxisValues, ContinueWith, Event, Hold, HoldKind, IoValue, MachineState,
    MachineStatus, OffsetTable, Overrides, Preamble, PreambleStep, Probe, ProbeOutcome, RunOutcome,
    WorkOffset, MAX_PREAMBLE_STEPS,
};
use crate::exec_log::ExecLog;
use crate::PluginError;
use std::collections::{BTreeMap, VecDeque};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

/// Receives every event the machine emits, from any thread, in order.
pub type EventSink = Arc<dyn Fn(&Event) + Send + Sync>;
/// Events collected under the state lock, emitted once it is released.
pub type Events = Vec<Event>;
/// Soft limits per axis (X Y Z A), machine coordinates, `None` = unlimited.
pub type Travel = [Option<(f64, f64)>; 4];

/// A preamble's move as [`Kit::check_preamble`] resolves it: its machine target and feed
/// (mm/min; `None`: rapid).
pub type ApproachMove = ([f64; 4], Option<f64>);

/// Jog requests queued behind the running one at most.
pub const MAX_QUEUED_JOGS: usize = 64;
/// How long stop and hold wait for the motion thread to confirm.
pub const STOP_CONFIRM: Duration = Duration::from_secs(5);
/// No machine coordinate is ever larger than this (mm), configured travel or not: bigger or
/// non-finite targets are input errors, and would overflow motion timing.
pub const MAX_COORDINATE_MM: f64 = 1e6;

/// The soft-limit check of every jog, MDI, go-to-zero and program move: each coordinate must
/// be finite, within ±[`MAX_COORDINATE_MM`], and within the configured travel.
pub fn check_travel(travel: &Travel, pos: [f64; 4]) -> Result<(), String> {
    for axis in Axis::ALL {
        let v = pos[axis.index()];
        if !v.is_finite() || v.abs() > MAX_COORDINATE_MM {
            return Err(format!(
                "{}={v} is outside the travel any machine has (at most {MAX_COORDINATE_MM} mm from 0)",
                axis.letter()
            ));
        }
        if let Some((min, max)) = travel[axis.index()] {
            // A hair of tolerance so arc chords ending exactly on a limit are accepted.
            if v < min - 1e-9 || v > max + 1e-9 {
                return Err(format!(
                    "{}={v:.4} is outside the travel [{min}, {max}] (machine coordinates)",
                    axis.letter()
                ));
            }
        }
    }
    Ok(())
}

/// Parses a `travel` config object like `{"x":[min,max],"z":[min,max]}`; only `axes` may be
/// limited.
pub fn travel_from_json(v: &serde_json::Value, axes: &[Axis]) -> Result<Travel, PluginError> {
    let mut out = [None; 4];
    for (key, range) in object("travel", v)? {
        let axis = axes
            .iter()
            .find(|a| a.letter().to_string().eq_ignore_ascii_case(key))
            .ok_or_else(|| {
                let names: Vec<String> = axes
                    .iter()
                    .map(|a| a.letter().to_ascii_lowercase().to_string())
                    .collect();
                let expected = match names.split_last() {
                    Some((last, [])) => last.clone(),
                    Some((last, rest)) => format!("{} or {last}", rest.join(", ")),
                    None => "none".into(),
                };
                invalid(format!("unknown key `travel.{key}` (expected {expected})"))
            })?;
        let pair = range.as_array().filter(|a| a.len() == 2).ok_or_else(|| {
            invalid(format!(
                "`travel.{key}` must be [min, max] in mm, got {range}"
            ))
        })?;
        let name = format!("travel.{key}");
        let (min, max) = (number(&name, &pair[0])?, number(&name, &pair[1])?);
        if min > max {
            return Err(invalid(format!(
                "`travel.{key}`: min {min} is greater than max {max}"
            )));
        }
        out[axis.index()] = Some((min, max));
    }
    Ok(out)
}

/// The program file as UTF-8 text; errors say which line is not.
pub fn read_program(path: &str) -> Result<String, PluginError> {
    let bytes = std::fs::read(path)
        .map_err(|e| PluginError::new("program_unreadable", format!("cannot read {path}: {e}")))?;
    String::from_utf8(bytes).map_err(|e| {
        let valid = &e.as_bytes()[..e.utf8_error().valid_up_to()];
        let line = valid.iter().filter(|b| **b == b'\n').count() + 1;
        PluginError::new(
            "invalid_program",
            format!("line {line}: {path} is not UTF-8 text"),
        )
    })
}

/// Opens a program file to be read as it runs: checks that all of it is UTF-8 text (the error
/// names the first line that is not) and counts its lines as `str::lines` does, reading it in
/// blocks, so memory does not grow with the program. The file comes back rewound; keeping it
/// open from load to run means the run reads the program that was checked.
pub fn open_program(path: &str) -> Result<(std::fs::File, u32), PluginError> {
    use std::io::{Read, Seek};
    let unreadable = |e: std::io::Error| {
        PluginError::new("program_unreadable", format!("cannot read {path}: {e}"))
    };
    let mut file = std::fs::File::open(path).map_err(unreadable)?;
    let mut buf = vec![0u8; 1 << 16];
    // Bytes of a UTF-8 sequence split by the block boundary, moved to the front of `buf`
    // (never a newline: those are single bytes).
    let mut carry = 0;
    let mut newlines: u64 = 0;
    let mut last = None;
    loop {
        let n = match file.read(&mut buf[carry..]) {
            Ok(n) => n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(unreadable(e)),
        };
        let not_utf8 = |line: u64| {
            PluginError::new(
                "invalid_program",
                format!("line {line}: {path} is not UTF-8 text"),
            )
        };
        if n == 0 {
            if carry > 0 {
                return Err(not_utf8(newlines + 1));
            }
            break;
        }
        let before = newlines;
        newlines += buf[carry..carry + n]
            .iter()
            .filter(|b| **b == b'\n')
            .count() as u64;
        last = Some(buf[carry + n - 1]);
        let block = &buf[..carry + n];
        carry = match std::str::from_utf8(block) {
            Ok(_) => 0,
            Err(e) if e.error_len().is_none() => {
                // An unfinished sequence at the end: completed by the next block (or not).
                let valid = e.valid_up_to();
                let len = block.len();
                buf.copy_within(valid..len, 0);
                len - valid
            }
            Err(e) => {
                let valid = &block[..e.valid_up_to()];
                let line = before + valid.iter().filter(|b| **b == b'\n').count() as u64 + 1;
                return Err(not_utf8(line));
            }
        };
    }
    let lines = newlines + u64::from(last.is_some_and(|b| b != b'\n'));
    file.rewind().map_err(unreadable)?;
    Ok((file, u32::try_from(lines).unwrap_or(u32::MAX)))
}

/// Refuses a start line past the program's end (one past the last line is a finished run).
pub fn check_start_line(start_line: u32, lines: u32) -> Result<(), PluginError> {
    if start_line > lines.saturating_add(1) {
        return Err(PluginError::invalid(format!(
            "start_line {start_line} is past the end of the program ({lines} lines)"
        )));
    }
    Ok(())
}

/// The motion thread of a machine; [`MotionThread::join`] waits for it (after
/// [`Kit::end_motion_thread`]).
#[derive(Debug)]
pub struct MotionThread(Mutex<Option<std::thread::JoinHandle<()>>>);

impl MotionThread {
    /// Starts `body` on a thread named `name`.
    pub fn spawn(
        name: &str,
        body: impl FnOnce() + Send + 'static,
    ) -> Result<MotionThread, PluginError> {
        let handle = std::thread::Builder::new()
            .name(name.into())
            .spawn(body)
            .map_err(|e| {
                PluginError::new("internal", format!("cannot start the {name} thread: {e}"))
            })?;
        Ok(MotionThread(Mutex::new(Some(handle))))
    }

    pub fn join(&self) {
        let handle = self.0.lock().unwrap_or_else(|e| e.into_inner()).take();
        if let Some(h) = handle {
            let _ = h.join();
        }
    }
}

/// What the kit needs to know of a backend's configuration.
#[derive(Debug, Clone)]
pub struct KitConfig {
    /// Default jog feed, mm/min.
    pub jog_feed_mm_min: f64,
    pub travel: Travel,
}

/// A program loaded with `load_program`, planned by the backend (`P`).
#[derive(Debug)]
pub struct Loaded<P> {
    pub run: i64,
    pub plan: P,
    pub start_line: u32,
    /// What to do before `start_line` (checked at load, see [`Kit::check_preamble`]); the
    /// backend's motion thread carries it out before the program's first line.
    pub preamble: Option<Preamble>,
}

/// One incremental jog.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Jog {
    pub axis: Axis,
    pub distance: f64,
    /// mm/min
    pub feed: f64,
}

impl Jog {
    /// Where the jog ends when it starts at machine position `from`.
    pub fn target(&self, from: [f64; 4]) -> [f64; 4] {
        let mut to = from;
        to[self.axis.index()] += self.distance;
        to
    }
}

/// Work for the motion thread.
#[derive(Debug)]
pub enum Job<P> {
    Jog(Jog),
    /// Z up to a safe height, then XY/A, then Z down, to the active work zero.
    GoToZero,
    /// One MDI line: straight moves to these machine targets, each at its feed.
    Mdi(Vec<MdiMove>),
    /// A probing move: ends with [`Kit::finish_probe`], not [`Kit::finish_job`].
    Probe(Probe),
    Program(Loaded<P>),
}

/// One straight move of an MDI line, in machine coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MdiMove {
    pub to: [f64; 4],
    /// mm/min (the rapid rate for a G0).
    pub feed: f64,
    /// A G0: the rapid override applies to it, not the feed override.
    pub rapid: bool,
}

impl<P> Job<P> {
    /// The run a program job executes.
    pub fn run(&self) -> Option<i64> {
        match self {
            Job::Program(l) => Some(l.run),
            _ => None,
        }
    }
}

/// Why a job ended early.
#[derive(Debug)]
pub enum Interrupted {
    /// Stop, cancel or shutdown.
    Aborted,
    /// A latched fault: the machine goes to alarm.
    Alarm(String),
    /// An input (an [`io`](crate::contract::io) name) tripped: the machine goes to alarm
    /// and the alarm names the input.
    Tripped { input: String, message: String },
    /// The run failed (e.g. the execution log could not be written); no alarm.
    Failed(String),
}

/// The machine state, behind the kit's lock. `X` is the backend's own part.
#[derive(Debug)]
pub struct State<P, X> {
    pub state: MachineState,
    pub reason: Option<String>,
    pub alarm: Option<String>,
    /// Machine position, mm (A in degrees). Backends whose truth is elsewhere (step counts)
    /// keep it in step.
    pub pos: [f64; 4],
    /// Machine position where all queued motion ends (bounds jogs queued behind jogs).
    pub end: [f64; 4],
    /// Machine origin of G54..G59.
    pub offsets: [[f64; 4]; 6],
    pub active: WorkOffset,
    pub feed: f64,
    /// Feed, spindle and rapid overrides in force; the motion thread reads them every slice
    /// (or planning interval), so a change applies to the move under way.
    pub overrides: Overrides,
    pub run: Option<i64>,
    pub line: Option<u32>,
    /// Loaded with `load_program`, not started yet.
    pub program: Option<Loaded<P>>,
    pub queue: VecDeque<Job<P>>,
    /// The motion thread is executing a job.
    pub busy: bool,
    pub shutdown: bool,
    /// When the last status event was queued (for rate limiting by the motion thread).
    pub last_status: Option<Instant>,
    /// The probing move queued or under way, by its id: nothing else moves until it ends.
    pub probing: Option<u64>,
    /// Inputs and outputs as reported in the status (see `MachineStatus::inputs`); change
    /// them with [`State::set_io`] so every change is reported.
    pub inputs: BTreeMap<String, Option<bool>>,
    pub outputs: BTreeMap<String, Option<IoValue>>,
    /// Why the machine holds (the status's `hold`): set with the hold, cleared when the run
    /// goes on or ends.
    pub hold: Option<Hold>,
    /// The tool length offset a program's G43 put in force, mm (0 after G49 and when no run
    /// is under way): the work position's Z is the tool tip's, machine Z - offset Z - this.
    pub tool_length_offset: f64,
    pub extra: X,
}

impl<P, X> State<P, X> {
    pub fn status(&self) -> MachineStatus {
        let mut off = self.offsets[self.active.index()];
        off[Axis::Z.index()] += self.tool_length_offset;
        MachineStatus {
            state: self.state,
            machine_position: AxisValues::from_array(self.pos),
            work_position: AxisValues::from_array(std::array::from_fn(|i| self.pos[i] - off[i])),
            feed: self.feed,
            feed_override: self.overrides.feed,
            spindle_override: self.overrides.spindle,
            rapid_override: self.overrides.rapid,
            active_offset: self.active,
            run: self.run,
            line: self.line,
            alarm: self.alarm.clone(),
            reason: self.reason.clone(),
            inputs: self.inputs.clone(),
            outputs: self.outputs.clone(),
            hold: self.hold.clone().map(Box::new),
        }
    }

    /// Held for a manual tool change (M6): jogs, probing moves and offset changes are allowed
    /// (the state is `jogging` while one runs, `paused` otherwise).
    pub fn in_tool_change(&self) -> bool {
        self.run.is_some()
            && matches!(self.state, MachineState::Paused | MachineState::Jogging)
            && self
                .hold
                .as_ref()
                .is_some_and(|h| h.kind == HoldKind::ToolChange)
    }

    /// Held for a tool change with nothing moving.
    pub fn still_in_tool_change(&self) -> bool {
        self.in_tool_change() && self.state == MachineState::Paused
    }

    /// [`State::require_still`], except in a tool-change hold with nothing moving (where
    /// the operator probes, touches off and measures the new tool).
    pub fn require_still_or_tool_change(&self, what: &str) -> Result<(), PluginError> {
        if self.still_in_tool_change() {
            return Ok(());
        }
        self.require_still(what)
    }

    /// Sets inputs and outputs; a status event goes out at once when anything changed (an
    /// operator watches lamps, so I/O changes are not rate limited like positions).
    pub fn set_io(
        &mut self,
        inputs: impl IntoIterator<Item = (String, Option<bool>)>,
        outputs: impl IntoIterator<Item = (String, Option<IoValue>)>,
        ev: &mut Events,
    ) {
        let mut changed = false;
        for (name, v) in inputs {
            changed |= self.inputs.insert(name, v) != Some(v);
        }
        for (name, v) in outputs {
            changed |= self.outputs.insert(name, v) != Some(v);
        }
        if changed {
            self.push_status(ev);
        }
    }

    pub fn offset_table(&self) -> OffsetTable {
        OffsetTable {
            active: self.active,
            offsets: WorkOffset::ALL
                .into_iter()
                .map(|o| (o, AxisValues::from_array(self.offsets[o.index()])))
                .collect(),
        }
    }

    pub fn push_status(&mut self, ev: &mut Events) {
        ev.push(Event::Status(self.status()));
        self.last_status = Some(Instant::now());
    }

    /// The status (with the new state and the position that goes with it) goes out before
    /// the state change: a host that shows the change alone first would show, e.g., `idle` at
    /// a position the machine has already left, if the two reach it apart.
    pub fn set_state(&mut self, to: MachineState, ev: &mut Events) {
        if self.state != to {
            let from = self.state;
            self.state = to;
            self.push_status(ev);
            ev.push(Event::StateChanged { from, to });
        }
    }

    /// The waypoints of go-to-zero from here: Z up to a safe height (the higher of here and
    /// work zero), then X/Y/A over, then Z down to work zero.
    pub fn go_to_zero_path(&self) -> [[f64; 4]; 3] {
        let zero = self.offsets[self.active.index()];
        let pos = self.pos;
        let safe_z = pos[2].max(zero[2]);
        [
            [pos[0], pos[1], safe_z, pos[3]],
            [zero[0], zero[1], safe_z, zero[3]],
            zero,
        ]
    }

    /// Latches an alarm: queued work is dropped.
    pub fn raise_alarm(&mut self, message: String, ev: &mut Events) {
        self.latch_alarm(message, None, ev);
    }

    /// Latches an alarm tripped by `input` (an [`io`](crate::contract::io) name).
    pub fn raise_input_alarm(&mut self, input: String, message: String, ev: &mut Events) {
        self.latch_alarm(message, Some(input), ev);
    }

    fn latch_alarm(&mut self, message: String, input: Option<String>, ev: &mut Events) {
        let dropped = self.drop_queued_probes();
        self.queue.clear();
        for id in dropped {
            self.probe_ended(id, ProbeOutcome::Failed, None, Some(message.clone()), ev);
        }
        self.alarm = Some(message.clone());
        ev.push(Event::Alarm { message, input });
        self.set_state(MachineState::Alarm, ev);
    }

    pub fn require_online(&self) -> Result<(), PluginError> {
        if self.state == MachineState::Offline {
            return Err(PluginError::new(
                "offline",
                "the machine is not connected: send `connect` first",
            ));
        }
        Ok(())
    }

    /// Refuses while anything moves or a run is in progress (offsets, homing, loading).
    pub fn require_still(&self, what: &str) -> Result<(), PluginError> {
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
    pub fn require_no_alarm(&self, what: &str) -> Result<(), PluginError> {
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

    /// Takes the probing moves out of the queue (their ends are reported by the caller).
    fn drop_queued_probes(&mut self) -> Vec<u64> {
        let mut ids = Vec::new();
        self.queue.retain(|j| match j {
            Job::Probe(p) => {
                ids.push(p.id);
                false
            }
            _ => true,
        });
        if !self.busy {
            self.probing = None;
        }
        ids
    }

    /// Reports probing move `id` ended (see [`Event::ProbeEnded`]), at the current position.
    fn probe_ended(
        &mut self,
        id: u64,
        outcome: ProbeOutcome,
        trip: Option<[f64; 4]>,
        message: Option<String>,
        ev: &mut Events,
    ) {
        ev.push(Event::ProbeEnded {
            id,
            outcome,
            trip: trip.map(AxisValues::from_array),
            position: AxisValues::from_array(self.pos),
            message,
        });
    }

    /// Drops queued jobs and the loaded program; runs among them end as cancelled, probing
    /// moves as stopped.
    fn cancel_pending(&mut self, ev: &mut Events) {
        for id in self.drop_queued_probes() {
            let m = "stopped before the probing move started".to_string();
            self.probe_ended(id, ProbeOutcome::Stopped, None, Some(m), ev);
        }
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

/// The shared part of a locally planned machine. `P` is the backend's program plan, `X` its
/// own state (kept under the same lock).
pub struct Kit<P, X> {
    pub cfg: KitConfig,
    sink: EventSink,
    shared: Mutex<State<P, X>>,
    /// Signalled on every change the motion thread or a waiting request may care about.
    pub cv: Condvar,
    /// Held while emitting, taken before the state lock is released, so events leave in the
    /// order the state changed (and a waiter can wait for emission to finish).
    emit_order: Mutex<()>,
    log: Option<Mutex<ExecLog>>,
    /// Abort the job in progress (stop); motion threads read it every slice or tick.
    abort: AtomicBool,
    /// Feed hold / pause requested; motion threads read it every slice or tick.
    hold: AtomicBool,
    /// The motion thread confirmed it holds (no new motion until resumed).
    held: AtomicBool,
    /// End the jog or probe run during a tool-change hold (feed hold, jog cancel), not the run.
    hold_job_abort: AtomicBool,
}

impl<P, X> Kit<P, X> {
    /// A machine that starts offline ("not connected yet").
    pub fn new(cfg: KitConfig, sink: EventSink, log: Option<ExecLog>, extra: X) -> Kit<P, X> {
        Kit {
            cfg,
            sink,
            shared: Mutex::new(State {
                state: MachineState::Offline,
                reason: Some("not connected yet".into()),
                alarm: None,
                pos: [0.0; 4],
                end: [0.0; 4],
                offsets: [[0.0; 4]; 6],
                active: WorkOffset::G54,
                feed: 0.0,
                overrides: Overrides::default(),
                run: None,
                line: None,
                program: None,
                queue: VecDeque::new(),
                busy: false,
                shutdown: false,
                last_status: None,
                probing: None,
                inputs: BTreeMap::new(),
                outputs: BTreeMap::new(),
                hold: None,
                tool_length_offset: 0.0,
                extra,
            }),
            cv: Condvar::new(),
            emit_order: Mutex::new(()),
            log: log.map(Mutex::new),
            abort: AtomicBool::new(false),
            hold: AtomicBool::new(false),
            held: AtomicBool::new(false),
            hold_job_abort: AtomicBool::new(false),
        }
    }

    pub fn lock(&self) -> MutexGuard<'_, State<P, X>> {
        self.shared.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Releases the state lock, then emits `events` (in order with every other emitter).
    pub fn release(&self, guard: MutexGuard<'_, State<P, X>>, events: Events) {
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
    pub fn with<R>(&self, f: impl FnOnce(&mut State<P, X>, &mut Events) -> R) -> R {
        let mut guard = self.lock();
        let mut ev = Vec::new();
        let r = f(&mut guard, &mut ev);
        self.release(guard, ev);
        r
    }

    /// Waits on the condition variable for at most `timeout`.
    pub fn wait_timeout<'a>(
        &'a self,
        guard: MutexGuard<'a, State<P, X>>,
        timeout: Duration,
    ) -> MutexGuard<'a, State<P, X>> {
        self.cv
            .wait_timeout(guard, timeout)
            .map(|(g, _)| g)
            .unwrap_or_else(|e| e.into_inner().0)
    }

    pub fn wait<'a>(&'a self, guard: MutexGuard<'a, State<P, X>>) -> MutexGuard<'a, State<P, X>> {
        self.cv.wait(guard).unwrap_or_else(|e| e.into_inner())
    }

    // ----- motion thread -----

    /// Stop or shutdown asked the job in progress to end (or, during a tool-change hold, a
    /// feed hold the jog or probe under way).
    pub fn aborted(&self) -> bool {
        self.abort.load(Ordering::SeqCst) || self.hold_job_abort.load(Ordering::SeqCst)
    }

    /// Feed hold or pause is asked for.
    pub fn hold_requested(&self) -> bool {
        self.hold.load(Ordering::SeqCst)
    }

    /// A program pause (M0) reached by the motion thread: hold now, confirmed at once.
    pub fn program_pause(&self, sh: &mut State<P, X>, ev: &mut Events) {
        let line = sh.line;
        let message = match line {
            Some(l) => format!("M0 at line {l}: program pause"),
            None => "M0: program pause".to_string(),
        };
        self.program_hold(
            sh,
            ev,
            program_hold(HoldKind::ProgramPause, message, line, None),
        );
    }

    /// The program holds for `hold` (M0, M1 with the optional stop on, M6), reached by the
    /// motion thread: hold now, confirmed at once. Cycle start (or resume) goes on.
    pub fn program_hold(&self, sh: &mut State<P, X>, ev: &mut Events, hold: Hold) {
        self.hold.store(true, Ordering::SeqCst);
        sh.end = sh.pos;
        sh.hold = Some(hold);
        if sh.state == MachineState::Running {
            sh.set_state(MachineState::Paused, ev);
        } else {
            sh.push_status(ev);
        }
        self.note_held(sh);
    }

    /// Holds the run for a manual tool change (after [`Kit::program_hold`] with a
    /// `tool_change` hold) until cycle start or resume (`Ok`) or a stop (`Aborted`). Jogs and
    /// probing moves queued meanwhile (the kit allows them in this hold) are carried out with
    /// `run`, the backend's own execution of them, answering a probe's trip; a feed hold or a
    /// jog cancel ends the one under way (and drops those queued), not the run. A fault
    /// during one (a limit) ends the run with it.
    pub fn serve_tool_change(
        &self,
        mut run: impl FnMut(&Job<P>) -> Result<Option<[f64; 4]>, Interrupted>,
    ) -> Result<(), Interrupted> {
        let mut sh = self.lock();
        loop {
            if self.abort.load(Ordering::SeqCst) || sh.shutdown {
                return Err(Interrupted::Aborted);
            }
            match sh.state {
                MachineState::Running => return Ok(()),
                MachineState::Paused | MachineState::Jogging => {}
                // Not left by anything but a stop (which the abort flag says).
                _ => return Err(Interrupted::Aborted),
            }
            let job = if sh.state == MachineState::Jogging {
                sh.queue.pop_front()
            } else {
                None
            };
            let Some(job) = job else {
                if sh.state == MachineState::Jogging {
                    // Nothing left to run (a feed hold dropped it): held again.
                    self.hold_job_abort.store(false, Ordering::SeqCst);
                    let mut ev = Vec::new();
                    sh.set_state(MachineState::Paused, &mut ev);
                    self.release(sh, ev);
                    sh = self.lock();
                    continue;
                }
                self.note_held(&mut sh);
                sh = self.wait(sh);
                continue;
            };
            drop(sh);
            let result = run(&job);
            sh = self.lock();
            let mut ev = Vec::new();
            self.hold_job_abort.store(false, Ordering::SeqCst);
            sh.end = sh.pos;
            if sh.queue.is_empty() && sh.state == MachineState::Jogging {
                sh.set_state(MachineState::Paused, &mut ev);
            } else {
                sh.push_status(&mut ev);
            }
            if let Job::Probe(p) = &job {
                sh.probing = None;
                let (outcome, trip, message) = probe_outcome(&result);
                sh.probe_ended(p.id, outcome, trip, message, &mut ev);
            }
            self.release(sh, ev);
            match result {
                Err(e @ (Interrupted::Alarm(_) | Interrupted::Tripped { .. })) => return Err(e),
                _ if self.abort.load(Ordering::SeqCst) => return Err(Interrupted::Aborted),
                _ => {}
            }
            sh = self.lock();
        }
    }

    /// The motion thread holds (starts nothing new until resumed). Called under the lock
    /// (`sh` proves it), so a waiting `pause` cannot miss the wake-up.
    pub fn note_held(&self, _sh: &mut State<P, X>) {
        if !self.held.swap(true, Ordering::SeqCst) {
            self.cv.notify_all();
        }
    }

    /// [`Kit::note_held`] for a motion thread that does not hold the lock; cheap when the
    /// hold was confirmed already (call it every tick while held).
    pub fn confirm_held(&self) {
        if !self.held.load(Ordering::SeqCst) {
            let mut sh = self.lock();
            self.note_held(&mut sh);
        }
    }

    /// Blocks the motion thread before a new program line while the machine is paused;
    /// `Aborted` on stop. For motion threads that may block (not a tick loop).
    pub fn line_gate(&self) -> Result<(), Interrupted> {
        let mut sh = self.lock();
        loop {
            if self.aborted() || sh.shutdown {
                return Err(Interrupted::Aborted);
            }
            if sh.state != MachineState::Paused {
                return Ok(());
            }
            self.note_held(&mut sh);
            sh = self.wait(sh);
        }
    }

    /// Takes the next job, if any, and marks the motion thread busy.
    pub fn take_job(&self, sh: &mut State<P, X>) -> Option<Job<P>> {
        let job = sh.queue.pop_front()?;
        sh.busy = true;
        Some(job)
    }

    /// Blocks until there is a job (and takes it) or the machine shuts down (`None`).
    pub fn wait_for_job(&self) -> Option<Job<P>> {
        let mut sh = self.lock();
        loop {
            if sh.shutdown {
                return None;
            }
            if let Some(job) = self.take_job(&mut sh) {
                return Some(job);
            }
            sh = self.wait(sh);
        }
    }

    /// The job of run `run` (if a program) ended with `result`: `update` applies what the
    /// motion thread knows (final position...), then the run ends (event) and the machine goes
    /// to alarm or idle. A waiting stop returns only after these events were emitted.
    pub fn finish_job(
        &self,
        run: Option<i64>,
        result: Result<(), Interrupted>,
        update: impl FnOnce(&mut State<P, X>),
    ) {
        self.finish(run, result, update, |_, _| {});
    }

    /// The probing move `id` ended: `Ok(Some(trip))` when the input changed at machine
    /// position `trip`, `Ok(None)` when the whole distance ran without it. As
    /// [`Kit::finish_job`], then a `probe_ended` event (after the state left jogging).
    pub fn finish_probe(
        &self,
        id: u64,
        result: Result<Option<[f64; 4]>, Interrupted>,
        update: impl FnOnce(&mut State<P, X>),
    ) {
        let (outcome, trip, message) = probe_outcome(&result);
        let result = result.map(drop);
        self.finish(None, result, update, |sh, ev| {
            sh.probing = None;
            sh.probe_ended(id, outcome, trip, message, ev);
        });
    }

    fn finish(
        &self,
        run: Option<i64>,
        result: Result<(), Interrupted>,
        update: impl FnOnce(&mut State<P, X>),
        last: impl FnOnce(&mut State<P, X>, &mut Events),
    ) {
        let mut sh = self.lock();
        let mut ev = Vec::new();
        sh.busy = false;
        update(&mut sh);
        self.hold.store(false, Ordering::SeqCst);
        self.held.store(false, Ordering::SeqCst);
        self.abort.store(false, Ordering::SeqCst);
        self.hold_job_abort.store(false, Ordering::SeqCst);
        sh.hold = None;
        if run.is_some() {
            // G43 lasts for the run that set it.
            sh.tool_length_offset = 0.0;
        }
        sh.end = sh.pos;
        if let Some(run) = run {
            let (outcome, message) = match &result {
                Ok(()) => (RunOutcome::Completed, None),
                Err(Interrupted::Aborted) => (RunOutcome::Cancelled, None),
                Err(
                    Interrupted::Alarm(m)
                    | Interrupted::Failed(m)
                    | Interrupted::Tripped { message: m, .. },
                ) => (RunOutcome::Failed, Some(m.clone())),
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
            Err(Interrupted::Alarm(m)) => sh.raise_alarm(m, &mut ev),
            Err(Interrupted::Tripped { input, message }) => {
                sh.raise_input_alarm(input, message, &mut ev)
            }
            _ if sh.queue.is_empty() && sh.state != MachineState::Offline => {
                if sh.state == MachineState::Idle {
                    sh.push_status(&mut ev);
                } else {
                    sh.set_state(MachineState::Idle, &mut ev);
                }
            }
            _ => sh.push_status(&mut ev),
        }
        last(&mut sh, &mut ev);
        self.release(sh, ev);
    }

    /// Program lines `lines` of `run` are executed: each is logged, then acknowledged, after
    /// `before` (e.g. a line report). Nothing is emitted if the log cannot be written.
    pub fn lines_done(
        &self,
        run: i64,
        lines: std::ops::RangeInclusive<u32>,
        before: Events,
    ) -> Result<(), Interrupted> {
        let mut ev = before;
        // Where the line's motion ended: the motion thread has nothing under way between lines.
        let pos = self.log.as_ref().map(|_| self.lock().pos);
        for line in lines {
            if let Some(log) = &self.log {
                log.lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .append_at(run, line, pos)
                    .map_err(Interrupted::Failed)?;
            }
            ev.push(Event::LineAcknowledged { run, line });
        }
        let sh = self.lock();
        self.release(sh, ev);
        Ok(())
    }

    // ----- requests -----

    pub fn status(&self) -> MachineStatus {
        self.lock().status()
    }

    /// Goes online (idle, or alarm `alarm_at_connect`); idempotent.
    pub fn connect(&self, alarm_at_connect: Option<&str>) -> MachineStatus {
        self.with(|sh, ev| {
            if sh.state == MachineState::Offline {
                sh.reason = None;
                match alarm_at_connect {
                    Some(m) => sh.raise_alarm(m.to_string(), ev),
                    None => sh.set_state(MachineState::Idle, ev),
                }
            }
            sh.status()
        })
    }

    /// Queues a jog after checking its end (behind the motion already queued) against the
    /// travel.
    pub fn jog(&self, axis: Axis, distance: f64, feed: Option<f64>) -> Result<(), PluginError> {
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
            if sh.probing.is_some() {
                return Err(PluginError::new(
                    "busy",
                    "cannot jog while the machine probes",
                ));
            }
            let free =
                sh.run.is_none() && matches!(sh.state, MachineState::Idle | MachineState::Jogging);
            if !(free || sh.in_tool_change()) {
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
            let jog = Jog {
                axis,
                distance,
                feed,
            };
            let target = jog.target(sh.end);
            check_travel(&self.cfg.travel, target)
                .map_err(|m| PluginError::new("out_of_travel", format!("jog refused: {m}")))?;
            sh.end = target;
            sh.queue.push_back(Job::Jog(jog));
            sh.set_state(MachineState::Jogging, ev);
            Ok(())
        })
    }

    /// Queues a probing move after checking it: a finite, non-zero distance and a positive
    /// feed, a probe input whose level is known and not already the one looked for, and the
    /// whole distance inside the travel (the trip may come anywhere along it). The motion
    /// thread runs it and ends it with [`Kit::finish_probe`].
    pub fn probe(&self, p: Probe) -> Result<(), PluginError> {
        if !(p.distance.is_finite() && p.distance != 0.0) {
            return Err(PluginError::invalid(format!(
                "probe distance must be a finite number other than 0, got {}",
                p.distance
            )));
        }
        if !(p.feed.is_finite() && p.feed > 0.0) {
            return Err(PluginError::invalid(format!(
                "probe feed must be greater than 0 mm/min, got {}",
                p.feed
            )));
        }
        self.with(|sh, ev| {
            sh.require_no_alarm("probe")?;
            sh.require_still_or_tool_change("probe")?;
            match sh.inputs.get(io::PROBE) {
                None => {
                    return Err(PluginError::new(
                        "unsupported",
                        "this machine has no probe input (configure one to probe)",
                    ))
                }
                Some(None) => {
                    return Err(PluginError::new(
                        "probe_unknown",
                        "the probe input's level is not known yet; try again",
                    ))
                }
                Some(Some(active)) if *active == p.until.wants_active() => {
                    return Err(PluginError::new(
                        "probe_already_in_state",
                        format!(
                            "the probe is already {}: nothing to probe for (check the clip \
                             and the plate)",
                            if *active { "in contact" } else { "open" }
                        ),
                    ))
                }
                Some(Some(_)) => {}
            }
            let target = Jog {
                axis: p.axis,
                distance: p.distance,
                feed: p.feed,
            }
            .target(sh.pos);
            check_travel(&self.cfg.travel, target).map_err(|m| {
                PluginError::new(
                    "out_of_travel",
                    format!("probe refused (its whole distance must be inside the travel): {m}"),
                )
            })?;
            sh.end = target;
            sh.probing = Some(p.id);
            sh.queue.push_back(Job::Probe(p));
            sh.set_state(MachineState::Jogging, ev);
            Ok(())
        })
    }

    /// Aborts all motion and the program. Answers once the motion thread confirmed and the
    /// run's end was emitted; `stop_unconfirmed` if it did not confirm in time.
    pub fn stop(&self) -> Result<(), PluginError> {
        let mut sh = self.lock();
        let mut ev = Vec::new();
        sh.cancel_pending(&mut ev);
        if !sh.busy {
            sh.hold = None;
            if matches!(
                sh.state,
                MachineState::Jogging | MachineState::Running | MachineState::Paused
            ) {
                sh.set_state(MachineState::Idle, &mut ev);
            }
            self.hold.store(false, Ordering::SeqCst);
            self.release(sh, ev);
            return Ok(());
        }
        // Set under the lock: a motion thread waiting on the condition variable sees it.
        self.abort.store(true, Ordering::SeqCst);
        self.release(sh, ev);
        self.confirmed("stop", |sh| !sh.busy)?;
        // finish_job took `emit_order` before releasing the lock: once we get it, its
        // events (the run's end) have been emitted.
        drop(self.emit_order.lock().unwrap_or_else(|e| e.into_inner()));
        Ok(())
    }

    /// Pauses a running program (`run pause`, strict) or holds whatever moves (feed hold):
    /// answers once the motion thread confirmed it holds. A jog is not resumable: feed hold
    /// ends it where it is.
    pub fn pause(&self, strict: bool) -> Result<(), PluginError> {
        let jogging = self.with(|sh, ev| match sh.state {
            MachineState::Running => {
                self.hold.store(true, Ordering::SeqCst);
                sh.hold = Some(if strict {
                    operator_hold(HoldKind::Pause, "paused by the operator")
                } else {
                    operator_hold(HoldKind::FeedHold, "feed hold")
                });
                sh.set_state(MachineState::Paused, ev);
                Ok(false)
            }
            // A jog or probe during a tool-change hold ends where it is; the run stays held.
            MachineState::Jogging if sh.in_tool_change() => {
                self.hold_job_abort.store(true, Ordering::SeqCst);
                for id in sh.drop_queued_probes() {
                    let m = "stopped before the probing move started".to_string();
                    sh.probe_ended(id, ProbeOutcome::Stopped, None, Some(m), ev);
                }
                sh.queue.clear();
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
            return self.stop();
        }
        self.confirmed("hold", |sh| {
            if sh.in_tool_change() {
                return sh.state == MachineState::Paused;
            }
            !sh.busy || sh.state != MachineState::Paused || self.held.load(Ordering::SeqCst)
        })
    }

    /// Waits (at most [`STOP_CONFIRM`]) until `done` holds; `stop_unconfirmed` naming `what`
    /// otherwise.
    fn confirmed(
        &self,
        what: &str,
        done: impl Fn(&State<P, X>) -> bool,
    ) -> Result<(), PluginError> {
        let deadline = Instant::now() + STOP_CONFIRM;
        let mut sh = self.lock();
        while !done(&sh) {
            let now = Instant::now();
            if now >= deadline {
                return Err(PluginError::new(
                    "stop_unconfirmed",
                    format!(
                        "the motion thread did not confirm the {what} within {} s",
                        STOP_CONFIRM.as_secs()
                    ),
                ));
            }
            sh = self.wait_timeout(sh, deadline - now);
        }
        Ok(())
    }

    /// Resumes a paused program; `strict` (run control) refuses when no run is in progress.
    pub fn resume(&self, strict: bool) -> Result<(), PluginError> {
        self.with(|sh, ev| match sh.state {
            MachineState::Paused => {
                self.resume_locked(sh, ev);
                Ok(())
            }
            MachineState::Jogging if sh.in_tool_change() => Err(jogging_in_tool_change()),
            _ if strict && sh.run.is_none() => Err(PluginError::new(
                "not_running",
                "no program is running: nothing to resume",
            )),
            _ => Ok(()),
        })
    }

    fn resume_locked(&self, sh: &mut State<P, X>, ev: &mut Events) {
        self.held.store(false, Ordering::SeqCst);
        self.hold.store(false, Ordering::SeqCst);
        sh.hold = None;
        sh.set_state(MachineState::Running, ev);
    }

    /// Starts the loaded program, or resumes a paused one.
    pub fn cycle_start(&self) -> Result<(), PluginError> {
        self.with(|sh, ev| {
            sh.require_online()?;
            sh.require_no_alarm("start")?;
            match sh.state {
                MachineState::Paused => {
                    self.resume_locked(sh, ev);
                    return Ok(());
                }
                MachineState::Running => return Ok(()),
                MachineState::Jogging if sh.in_tool_change() => {
                    return Err(jogging_in_tool_change())
                }
                _ => {}
            }
            sh.require_still("start a program")?;
            if let Some(e) = sh.program.as_ref().and_then(stale_preamble) {
                return Err(e);
            }
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
            Ok(())
        })
    }

    /// Stops, then `reset` (the backend's part: outputs off, refusals) and clears the alarm.
    pub fn reset(
        &self,
        reset: impl FnOnce(&mut State<P, X>) -> Result<(), PluginError>,
    ) -> Result<(), PluginError> {
        self.stop()?;
        self.with(|sh, ev| {
            reset(sh)?;
            if sh.state == MachineState::Alarm {
                sh.alarm = None;
                sh.set_state(MachineState::Idle, ev);
            } else {
                // What the backend's part switched off shows at once.
                sh.push_status(ev);
            }
            Ok(())
        })
    }

    /// Homing without switches: `set` declares the current position of `axis` (all when
    /// `None`) machine zero, in the backend's terms.
    pub fn home(
        &self,
        axis: Option<Axis>,
        set: impl FnOnce(&mut State<P, X>, Option<Axis>),
    ) -> Result<(), PluginError> {
        self.with(|sh, ev| {
            sh.require_still("home")?;
            set(sh, axis);
            sh.end = sh.pos;
            sh.push_status(ev);
            Ok(())
        })
    }

    /// Sets the active work offset so the work position of `axis` (or all) becomes zero.
    pub fn zero(&self, axis: Option<Axis>) -> Result<OffsetTable, PluginError> {
        self.with(|sh, ev| {
            sh.require_still_or_tool_change("zero")?;
            let (mut pos, i) = (sh.pos, sh.active.index());
            // Zero is where the tool tip is (G43 in force during a tool-change hold).
            pos[Axis::Z.index()] -= sh.tool_length_offset;
            match axis {
                Some(a) => sh.offsets[i][a.index()] = pos[a.index()],
                None => sh.offsets[i] = pos,
            }
            sh.push_status(ev);
            Ok(sh.offset_table())
        })
    }

    /// Queues the move to work zero after checking each of its waypoints against the travel.
    pub fn go_to_zero(&self) -> Result<(), PluginError> {
        self.with(|sh, ev| {
            sh.require_no_alarm("go to zero")?;
            sh.require_still("go to zero")?;
            let path = sh.go_to_zero_path();
            for p in path {
                check_travel(&self.cfg.travel, p).map_err(|m| {
                    PluginError::new("out_of_travel", format!("go to zero refused: {m}"))
                })?;
            }
            sh.end = path[2];
            sh.queue.push_back(Job::GoToZero);
            sh.set_state(MachineState::Jogging, ev);
            Ok(())
        })
    }

    pub fn select_offset(&self, offset: WorkOffset) -> Result<(), PluginError> {
        self.with(|sh, ev| {
            sh.require_still("select an offset")?;
            sh.active = offset;
            sh.push_status(ev);
            Ok(())
        })
    }

    pub fn get_offsets(&self) -> OffsetTable {
        self.lock().offset_table()
    }

    /// Sets the overrides given, in percent (the host has checked them against the machine's
    /// range; here only that each is a positive finite number and a rapid one is at most 100),
    /// also during a run: the motion thread applies them from its next slice.
    pub fn set_overrides(
        &self,
        feed: Option<f64>,
        spindle: Option<f64>,
        rapid: Option<f64>,
    ) -> Result<(), PluginError> {
        for (field, v) in [("feed", feed), ("spindle", spindle), ("rapid", rapid)] {
            if let Some(v) = v.filter(|v| !(v.is_finite() && *v > 0.0)) {
                return Err(PluginError::invalid(format!(
                    "`{field}` override must be a positive percentage, got {v}"
                )));
            }
        }
        if let Some(r) = rapid.filter(|r| *r > 100.0) {
            return Err(PluginError::invalid(format!(
                "`rapid` override is at most 100 % (the machine's rapid rate), got {r}"
            )));
        }
        self.with(|sh, ev| {
            sh.require_online()?;
            let next = sh.overrides.with(feed, spindle, rapid);
            if next != sh.overrides {
                sh.overrides = next;
                sh.push_status(ev);
            }
            Ok(())
        })
    }

    pub fn set_offset(&self, offset: WorkOffset, values: AxisValues) -> Result<(), PluginError> {
        if values.to_array().iter().any(|v| !v.is_finite()) {
            return Err(PluginError::invalid("offset values must be finite numbers"));
        }
        self.with(|sh, ev| {
            sh.require_still_or_tool_change("change offsets")?;
            sh.offsets[offset.index()] = values.to_array();
            if offset == sh.active {
                sh.push_status(ev);
            }
            Ok(())
        })
    }

    /// Queues one MDI line's moves (already checked against the travel), unless the offsets
    /// changed since the caller planned it from `offsets`/`active`.
    pub fn queue_mdi(
        &self,
        moves: Vec<MdiMove>,
        offsets: [[f64; 4]; 6],
        active: WorkOffset,
    ) -> Result<(), PluginError> {
        self.with(|sh, ev| {
            sh.require_no_alarm("run MDI")?;
            sh.require_still("run MDI")?;
            if sh.offsets != offsets || sh.active != active {
                return Err(PluginError::new(
                    "busy",
                    "the work offsets changed while the MDI line was checked; send it again",
                ));
            }
            if let Some(last) = moves.last() {
                sh.end = last.to;
                sh.queue.push_back(Job::Mdi(moves));
                sh.set_state(MachineState::Jogging, ev);
            }
            Ok(())
        })
    }

    /// Stops and goes offline ("shut down").
    pub fn shutdown(&self) -> Result<(), PluginError> {
        let stopped = self.stop();
        self.with(|sh, ev| {
            sh.reason = Some("shut down".into());
            sh.alarm = None;
            sh.set_state(MachineState::Offline, ev);
        });
        stopped
    }

    /// For `Drop`: the motion thread ends its job and returns.
    pub fn end_motion_thread(&self) {
        self.with(|sh, _| {
            sh.shutdown = true;
            self.abort.store(true, Ordering::SeqCst);
        });
    }

    /// The line a run starts from: `start_line`, or later when the execution log shows lines
    /// of this run already executed (idempotent resume).
    pub fn logged_start(&self, run: i64, start_line: u32) -> Result<u32, PluginError> {
        if start_line == 0 {
            return Err(PluginError::invalid(
                "start_line is 1-based: 0 is not a line",
            ));
        }
        let last = match &self.log {
            Some(log) => log
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .last_line(run)?,
            None => None,
        };
        Ok(last.map_or(start_line, |l| start_line.max(l.saturating_add(1))))
    }

    /// Installs a planned program of `lines` lines, to start at `start` (from
    /// [`Kit::logged_start`]); `asked` is the start line the host asked for.
    pub fn install_plan(
        &self,
        run: i64,
        plan: P,
        lines: u32,
        asked: u32,
        start: u32,
    ) -> Result<crate::contract::ProgramLoaded, PluginError> {
        self.install_plan_with(run, plan, (lines, asked, start), None)
    }

    /// [`Kit::install_plan`] with the preamble the host sent (checked by the backend with
    /// [`Kit::check_preamble`]). One planned for another line than `start` is kept but
    /// refused at cycle start (`start_line_moved`): the answer names the line, and the host
    /// loads again with a preamble for it.
    pub fn install_plan_with(
        &self,
        run: i64,
        plan: P,
        (lines, asked, start): (u32, u32, u32),
        preamble: Option<Preamble>,
    ) -> Result<crate::contract::ProgramLoaded, PluginError> {
        check_start_line(asked, lines)?;
        let start_line = start.min(lines.saturating_add(1));
        // Every line was done already: nothing runs, so nothing needs approaching.
        let preamble = preamble.filter(|_| start_line <= lines);
        let leads_here = preamble.as_ref().is_some_and(|p| p.line == start_line);
        self.install(Loaded {
            run,
            plan,
            start_line,
            preamble,
        })?;
        Ok(crate::contract::ProgramLoaded {
            lines,
            start_line,
            preamble: leads_here,
            height_map: false,
        })
    }

    /// Checks a preamble before it is accepted: at most [`MAX_PREAMBLE_STEPS`] steps, finite
    /// numbers, positive feeds, planned from `pos` (the machine position now; else
    /// `machine_moved`), and every move's end inside the travel (`out_of_travel`, naming the
    /// step). Answers the moves, each as its machine target and feed (`None`: rapid).
    pub fn check_preamble(
        &self,
        pos: [f64; 4],
        p: &Preamble,
    ) -> Result<Vec<ApproachMove>, PluginError> {
        if p.steps.len() > MAX_PREAMBLE_STEPS {
            return Err(PluginError::invalid(format!(
                "a preamble has at most {MAX_PREAMBLE_STEPS} steps, got {}",
                p.steps.len()
            )));
        }
        let from = p.from.to_array();
        if from
            .iter()
            .zip(&pos)
            .any(|(a, b)| !a.is_finite() || (a - b).abs() > 1e-6)
        {
            return Err(PluginError::new(
                "machine_moved",
                format!(
                    "the preamble was planned from X{:.4} Y{:.4} Z{:.4} A{:.4} but the machine \
                     is at X{:.4} Y{:.4} Z{:.4} A{:.4}: plan it again",
                    from[0], from[1], from[2], from[3], pos[0], pos[1], pos[2], pos[3]
                ),
            ));
        }
        let mut at = pos;
        let mut moves = Vec::new();
        for (i, step) in p.steps.iter().enumerate() {
            let bad =
                |what: String| PluginError::invalid(format!("preamble step {}: {what}", i + 1));
            match *step {
                PreambleStep::Spindle { rpm, .. } if !(rpm.is_finite() && rpm >= 0.0) => {
                    return Err(bad(format!("spindle rpm must be 0 or more, got {rpm}")))
                }
                PreambleStep::Move { feed: Some(f), .. } if !(f.is_finite() && f > 0.0) => {
                    return Err(bad(format!("feed must be greater than 0 mm/min, got {f}")))
                }
                _ => {}
            }
            if let Some(to) = step.target(at) {
                check_travel(&self.cfg.travel, to).map_err(|m| {
                    PluginError::new(
                        "out_of_travel",
                        format!(
                            "preamble step {} (the approach to line {}): {m}",
                            i + 1,
                            p.line
                        ),
                    )
                })?;
                let feed = match *step {
                    PreambleStep::Move { feed, .. } => feed,
                    _ => None,
                };
                moves.push((to, feed));
                at = to;
            }
        }
        Ok(moves)
    }

    /// Appends one record of the backend's own shape to the execution log (if there is
    /// one), e.g. what a preamble did; a record that is not a line is skipped by
    /// [`ExecLog::last_line`].
    pub fn log_record<T: serde::Serialize>(&self, record: &T) -> Result<(), Interrupted> {
        match &self.log {
            Some(log) => log
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .append_entry(record)
                .map_err(Interrupted::Failed),
            None => Ok(()),
        }
    }

    /// `run` requests: start, pause, resume (strict) and cancel (a stop).
    pub fn run(
        &self,
        action: crate::contract::RunAction,
    ) -> Result<crate::contract::RunAnswer, PluginError> {
        use crate::contract::RunAction;
        match action {
            RunAction::Start => self.cycle_start()?,
            RunAction::Pause => self.pause(true)?,
            RunAction::Resume => self.resume(true)?,
            RunAction::Cancel => self.stop()?,
        }
        Ok(Default::default())
    }

    /// Makes `loaded` the program the next cycle start runs; one loaded earlier and never
    /// started is replaced (its run ends as cancelled).
    pub fn install(&self, loaded: Loaded<P>) -> Result<(), PluginError> {
        self.with(|sh, ev| {
            sh.require_still("load a program")?;
            if let Some(old) = sh.program.take() {
                if old.run != loaded.run {
                    ev.push(Event::RunEnded {
                        run: old.run,
                        outcome: RunOutcome::Cancelled,
                        message: Some(format!("replaced by run {} before it started", loaded.run)),
                    });
                }
            }
            sh.program = Some(loaded);
            Ok(())
        })
    }
}

/// A hold the program asked for (M0, M1, M6): the operator goes on with cycle start.
pub fn program_hold(
    kind: HoldKind,
    message: String,
    line: Option<u32>,
    program_message: Option<String>,
) -> Hold {
    Hold {
        kind,
        message,
        line,
        program_message,
        continue_with: ContinueWith::CycleStart,
        tool_change: None,
        blocked: None,
    }
}

/// A hold the operator asked for (feed hold, pause): resume goes on.
fn operator_hold(kind: HoldKind, message: &str) -> Hold {
    Hold {
        kind,
        message: message.to_string(),
        line: None,
        program_message: None,
        continue_with: ContinueWith::Resume,
        tool_change: None,
        blocked: None,
    }
}

fn jogging_in_tool_change() -> PluginError {
    PluginError::new(
        "busy",
        "a jog or probing move of the tool change is under way: wait for it to end (or feed \
         hold it) before cycle start",
    )
}

/// What a probing move's result reports (see [`Event::ProbeEnded`]).
fn probe_outcome(
    result: &Result<Option<[f64; 4]>, Interrupted>,
) -> (ProbeOutcome, Option<[f64; 4]>, Option<String>) {
    match result {
        Ok(Some(t)) => (ProbeOutcome::Tripped, Some(*t), None),
        Ok(None) => (ProbeOutcome::NotTripped, None, None),
        Err(Interrupted::Aborted) => (
            ProbeOutcome::Stopped,
            None,
            Some("stopped before the probe changed".to_string()),
        ),
        Err(
            Interrupted::Alarm(m)
            | Interrupted::Failed(m)
            | Interrupted::Tripped { message: m, .. },
        ) => (ProbeOutcome::Failed, None, Some(m.clone())),
    }
}

/// A loaded program whose preamble leads to another line than the one it starts from.
fn stale_preamble<P>(l: &Loaded<P>) -> Option<PluginError> {
    let p = l.preamble.as_ref().filter(|p| p.line != l.start_line)?;
    Some(PluginError::new(
        "start_line_moved",
        format!(
            "run {} starts at line {} (the execution log shows the lines before it done), but \
             its preamble leads to line {}: load it again with a preamble for line {}",
            l.run, l.start_line, p.line, l.start_line
        ),
    ))
}

/// The [`crate::MachineBackend`] methods a kit-based backend answers straight from its kit,
/// for use inside `impl MachineBackend for T` where `T` has `fn kit(&self) -> &Kit<P, X>`:
/// status, run, cycle start, feed hold, resume, stop, shutdown, jog, zero, go to zero,
/// offsets. The backend writes the rest (create, connect, load_program, reset, home...).
#[macro_export]
macro_rules! kit_backend_methods {
    () => {
        fn status(&self) -> Result<$crate::contract::MachineStatus, $crate::PluginError> {
            Ok(self.kit().status())
        }
        fn run(
            &self,
            action: $crate::contract::RunAction,
        ) -> Result<$crate::contract::RunAnswer, $crate::PluginError> {
            self.kit().run(action)
        }
        fn cycle_start(&self) -> Result<$crate::contract::RunAnswer, $crate::PluginError> {
            self.kit().cycle_start().map(|()| Default::default())
        }
        fn feed_hold(&self) -> Result<(), $crate::PluginError> {
            self.kit().pause(false)
        }
        fn resume(&self) -> Result<(), $crate::PluginError> {
            self.kit().resume(false)
        }
        fn stop(&self) -> Result<(), $crate::PluginError> {
            self.kit().stop()
        }
        fn shutdown(&self) -> Result<(), $crate::PluginError> {
            self.kit().shutdown()
        }
        fn zero(
            &self,
            axis: Option<$crate::contract::Axis>,
        ) -> Result<Option<$crate::contract::OffsetTable>, $crate::PluginError> {
            self.kit().zero(axis).map(Some)
        }
        fn go_to_zero(&self) -> Result<(), $crate::PluginError> {
            self.kit().go_to_zero()
        }
        fn select_offset(
            &self,
            offset: $crate::contract::WorkOffset,
        ) -> Result<(), $crate::PluginError> {
            self.kit().select_offset(offset)
        }
        fn get_offsets(&self) -> Result<$crate::contract::OffsetTable, $crate::PluginError> {
            Ok(self.kit().get_offsets())
        }
        fn set_offset(
            &self,
            offset: $crate::contract::WorkOffset,
            values: $crate::contract::AxisValues,
        ) -> Result<(), $crate::PluginError> {
            self.kit().set_offset(offset, values)
        }
    };
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use serde_json::json;

    #[test]
    fn open_program_counts_lines_like_str_lines_and_names_the_line_that_is_not_utf8() {
        let dir = std::env::temp_dir().join(format!("fresa-kit-open-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("p.nc");
        let p = path.to_str().unwrap();
        // A multi-byte character straddling the 64 KiB block boundary, CRLF, no final newline.
        let mut long = "G0 X1\r\n".repeat(65536 / 7);
        while long.len() < 65535 {
            long.push(' ');
        }
        long.push_str("é\nG1 X2 F1\n\nG0 X3");
        for text in ["", "\n", "a", "a\n", "a\nb", "a\r\nb\r\n", long.as_str()] {
            std::fs::write(&path, text).unwrap();
            let (mut f, lines) = open_program(p).unwrap();
            assert_eq!(lines as usize, text.lines().count(), "{text:?}");
            let mut back = String::new();
            std::io::Read::read_to_string(&mut f, &mut back).unwrap();
            assert_eq!(back, text, "rewound");
            assert_eq!(read_program(p).unwrap(), text);
        }
        let mut bad = long.clone().into_bytes();
        bad.extend_from_slice(b"\nG0 \xff\n");
        std::fs::write(&path, &bad).unwrap();
        let e = open_program(p).unwrap_err();
        let expected = read_program(p).unwrap_err();
        assert_eq!(
            (e.code.as_str(), e.message.as_str()),
            (expected.code.as_str(), expected.message.as_str())
        );
        // A sequence cut short by the end of the file.
        std::fs::write(&path, b"G0 X1\n\xc3").unwrap();
        let e = open_program(p).unwrap_err();
        assert!(e.message.starts_with("line 2: "), "{e:?}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn travel_refuses_huge_and_non_finite_targets_without_limits() {
        let none = [None; 4];
        assert!(check_travel(&none, [1e5, 0.0, 0.0, 0.0]).is_ok());
        for bad in [1e308, f64::INFINITY, f64::NAN, -2e6] {
            let e = check_travel(&none, [0.0, bad, 0.0, 0.0]).unwrap_err();
            assert!(
                e.contains("outside the travel") && e.starts_with("Y="),
                "{e}"
            );
        }
        let x = [Some((0.0, 10.0)), None, None, None];
        assert!(check_travel(&x, [10.0, 0.0, 0.0, 0.0]).is_ok());
        assert!(check_travel(&x, [10.1, 0.0, 0.0, 0.0]).is_err());
    }

    #[test]
    fn travel_config_names_the_axes_it_takes() {
        let t = travel_from_json(&json!({"x": [-1, 2], "Z": [-3, 0]}), &Axis::ALL).unwrap();
        assert_eq!(t, [Some((-1.0, 2.0)), None, Some((-3.0, 0.0)), None]);
        let e = travel_from_json(&json!({"z": [0, 1]}), &[Axis::X, Axis::Y]).unwrap_err();
        assert!(e.message.contains("expected x or y"), "{e}");
        let e = travel_from_json(&json!({"x": [2, 1]}), &Axis::ALL).unwrap_err();
        assert!(e.message.contains("travel.x"), "{e}");
    }
}

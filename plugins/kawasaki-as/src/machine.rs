//! The machine backend: requests from the host, one streaming thread per run.
//!
//! `load_program` converts the whole program; `run start` connects, reads the robot's part
//! zero, checks it (resume) and every point against the envelope, and only then starts the
//! robot program and the streaming thread. Progress is acknowledged per source line once every
//! motion of the line is done.

use crate::codec::{V1Cmd, V1Msg};
use crate::config::{Config, Protocol};
use crate::convert::{Cmd, Convert, Plan};
use crate::link::{self, LegacyLink, LinkError, V1Link};
use fresa_plugin_api::backend::{LoadProgram, MachineBackend};
use fresa_plugin_api::contract::{
    Artifact, Axis, AxisValues, Event, MachineState, MachineStatus, OffsetTable, Overrides,
    ProgramLoaded, RunAction, RunAnswer, RunOutcome, WorkOffset,
};
use fresa_plugin_api::exec_log::ExecLog;
use fresa_plugin_api::{Host, PluginError};
use serde::{Deserialize, Serialize};
use serde_json::Value;
use std::collections::{HashMap, VecDeque};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// Why kawasaki-as does not start a program at a line. The link to the robot opens only when a
/// run starts (connecting ends the robot program's one session), so where the robot stands,
/// where a safe approach must begin, is unknown when the program is checked against the
/// envelope; and the spindle is switched by hand, so the robot cannot rebuild it.
pub const NO_PREAMBLE: &str = "kawasaki-as cannot start a program at a line safely: the link to \
    the robot opens only when the run starts, so where the robot stands (where an approach to \
    the line must begin) cannot be checked against the envelope beforehand, and the spindle is \
    switched by hand";

/// Receives every event the machine emits, from any thread.
pub type EventSink = Arc<dyn Fn(&Event) + Send + Sync>;
/// Receives warnings for the host's log.
pub type LogSink = Arc<dyn Fn(&str) + Send + Sync>;

/// Least time between two `status` events while streaming.
const STATUS_INTERVAL: Duration = Duration::from_millis(100);

/// A resumed run's robot part zero may differ by this much (mm) from the one it started with.
pub const PART_ZERO_TOLERANCE_MM: f64 = 0.001;

/// A Kawasaki robot streamed over TCP. Thread-safe; dropping it ends the run thread.
pub struct KawasakiMachine {
    core: Arc<Core>,
    worker: Mutex<Option<JoinHandle<()>>>,
}

/// How long a cancel or stop waits for the robot to finish the moves already sent.
const END_WAIT: Duration = Duration::from_secs(5);

struct Core {
    cfg: Config,
    convert: Convert,
    sink: EventSink,
    log: LogSink,
    sh: Mutex<Shared>,
    cv: Condvar,
    /// Malformed or unexpected robot messages can come with every reply: rate-limited.
    quiet: fresa_plugin_api::quiet::Quiet,
}

struct Loaded {
    run: i64,
    plan: Arc<Plan>,
    /// Source line the host asked to start from.
    start_line: u32,
    /// First command to execute (later than `start_line`'s first when already done).
    start_cmd: usize,
    tag: String,
    expected_zero: Option<[f64; 3]>,
    /// legacy only: where acknowledged commands are recorded.
    journal: Option<Journal>,
}

#[derive(Default)]
struct Shared {
    state: MachineState,
    reason: Option<String>,
    alarm: Option<String>,
    run: Option<i64>,
    line: Option<u32>,
    loaded: Option<Loaded>,
    pause: bool,
    cancel: bool,
    busy: bool,
    part_zero: Option<[f64; 3]>,
    /// Last robot point reached (relative to part zero).
    at: [f64; 3],
    feed_mm_s: f64,
    /// Commands done per run, as far as this process saw (resume after a link drop).
    progress: HashMap<i64, usize>,
    /// The run's connection, so a shutdown can cut it without waiting for a long motion.
    socket: Option<std::net::TcpStream>,
    /// When the last `status` event left during a run.
    last_status: Option<Instant>,
    /// Runs ended so far, counted after their `run_ended` event left: a cancel or stop waits
    /// for this to move so it answers only once the run is over.
    runs_ended: u64,
    /// Overrides in force (fresa-v1 applies the feed one; see `set_overrides`).
    overrides: Overrides,
}

impl Shared {
    fn status(&self, cfg: &Config) -> MachineStatus {
        let zero = self.part_zero.unwrap_or([0.0; 3]);
        let g = cfg.mapping.unmap(self.at);
        MachineStatus {
            state: self.state,
            machine_position: AxisValues {
                x: zero[0] + self.at[0],
                y: zero[1] + self.at[1],
                z: zero[2] + self.at[2],
                a: 0.0,
            },
            work_position: AxisValues {
                x: g[0],
                y: g[1],
                z: g[2],
                a: 0.0,
            },
            feed: self.feed_mm_s * 60.0,
            feed_override: self.overrides.feed,
            spindle_override: self.overrides.spindle,
            rapid_override: self.overrides.rapid,
            run: self.run,
            line: self.line,
            alarm: self.alarm.clone(),
            reason: self.reason.clone(),
            ..MachineStatus::default()
        }
    }
}

/// legacy: `{"tag":"<run>-<program hash>","done":N}` per acknowledged command, so a resume
/// after a crash of the server starts at the exact next motion. Keyed by run id and program
/// content, so a journal shared by mistake cannot match another program. Kept in the shared
/// execution log file machinery, with its own record shape.
struct Journal {
    log: ExecLog,
    tag: String,
}

#[derive(Serialize, Deserialize)]
struct JournalEntry {
    tag: String,
    done: u64,
}

impl Journal {
    fn open(path: &Path, tag: &str) -> Result<Journal, PluginError> {
        Ok(Journal {
            log: ExecLog::open_as(path, "journal")?,
            tag: tag.to_string(),
        })
    }

    fn record(&mut self, done: usize) -> Result<(), String> {
        self.log.append_entry(&JournalEntry {
            tag: self.tag.clone(),
            done: done as u64,
        })
    }

    /// Commands done for this tag; an unreadable journal counts as none done.
    fn done(&self) -> usize {
        self.log
            .entries::<JournalEntry>()
            .map(|es| {
                es.into_iter()
                    .filter(|e| e.tag == self.tag)
                    .map(|e| e.done)
                    .max()
                    .unwrap_or(0)
            })
            .unwrap_or(0) as usize
    }
}

/// FNV-1a: a hash that stays the same across builds (the tag must survive a server upgrade).
fn fnv1a(text: &str) -> u64 {
    text.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    })
}

fn link_error(e: LinkError) -> PluginError {
    let code = match e {
        LinkError::Connect { .. } => "robot_unreachable",
        LinkError::Timeout(..) => "robot_timeout",
        _ => "robot_link",
    };
    PluginError::new(code, e.to_string())
}

enum Session {
    Legacy(LegacyLink),
    V1(V1Link),
}

enum Ended {
    Completed,
    Cancelled,
    Failed(String),
}

impl KawasakiMachine {
    pub fn new(
        config: &Value,
        sink: EventSink,
        log: LogSink,
    ) -> Result<KawasakiMachine, PluginError> {
        let cfg = Config::from_json(config)?;
        let convert = Convert {
            mapping: cfg.mapping,
            speeds: cfg.speeds,
            arc_tolerance_mm: cfg.arc_tolerance_mm,
            unsupported: cfg.unsupported,
        };
        Ok(KawasakiMachine {
            core: Arc::new(Core {
                cfg,
                convert,
                sink,
                log,
                sh: Mutex::new(Shared::default()),
                cv: Condvar::new(),
                quiet: fresa_plugin_api::quiet::Quiet::per_minute(),
            }),
            worker: Mutex::new(None),
        })
    }

    pub fn config(&self) -> &Config {
        &self.core.cfg
    }

    fn status_now(&self) -> MachineStatus {
        self.core.lock().status(&self.core.cfg)
    }

    /// Stop and reset are the same here: cancel the run, clear the alarm.
    fn stop_and_clear(&self) -> Result<(), PluginError> {
        let ended = self.cancel_and_wait();
        self.core.with(|sh, ev| {
            sh.alarm = None;
            if sh.state == MachineState::Alarm {
                sh.set_state(MachineState::Idle, ev);
            }
        });
        ended
    }

    fn artifact(&self, name: &str) -> Result<Artifact, PluginError> {
        match name {
            "as-program" => match self.core.cfg.protocol {
                Protocol::FresaV1 => Ok(Artifact {
                    content_type: "text/plain; charset=utf-8".into(),
                    file_name: Some("FRESA_V1.pg".into()),
                    body: crate::as_program::generate(&self.core.cfg),
                }),
                Protocol::Legacy => Err(PluginError::new(
                    "not_available",
                    "this machine uses protocol `legacy`: load the seed's FRESADORA program on the controller \
                     (set \"protocol\": \"fresa-v1\" to get a generated program)",
                )),
            },
            other => Err(PluginError::new(
                "unknown_artifact",
                format!("kawasaki-as has no artifact {other:?} (known: as-program)"),
            )),
        }
    }

    /// `p`'s program converted within `max_segments` with `tools`, kept for the run.
    fn load(
        &self,
        p: &LoadProgram,
        tools: fresa_gcode::ToolTable,
        max_segments: u64,
    ) -> Result<ProgramLoaded, PluginError> {
        let (run, path, start_line) = (p.run, p.path.as_str(), p.start_line);
        let (expected_zero, height_map) = (p.expected_part_zero, p.height_map.as_ref());
        if self.core.lock().busy {
            return Err(PluginError::new("busy", "a run is in progress"));
        }
        let text = std::fs::read_to_string(path).map_err(|e| {
            PluginError::new("program_unreadable", format!("cannot read {path}: {e}"))
        })?;
        let plan = self
            .core
            .convert
            .plan_mapped(&text, tools, max_segments, height_map)
            .map_err(|e| match e.kind {
                fresa_gcode::ErrorKind::Budget if max_segments == crate::convert::MAX_COMMANDS => {
                    PluginError::new(
                        "work_budget_exceeded",
                        format!(
                            "{e}; kawasaki-as converts at most {} robot motions a program \
                             (split the program)",
                            crate::convert::MAX_COMMANDS
                        ),
                    )
                }
                fresa_gcode::ErrorKind::Budget => PluginError::new(
                    "work_budget_exceeded",
                    format!("{e}; the budget is the server's `max_program_segments`"),
                ),
                _ => PluginError::new("invalid_program", e.to_string()),
            })?;
        if start_line == 0 || start_line > plan.lines.max(1) {
            return Err(PluginError::invalid(format!(
                "start_line {start_line} is outside the program's lines 1..{}",
                plan.lines
            )));
        }
        for w in &plan.warnings {
            self.core.log_warn(&format!("run {run}: {w}"));
        }
        // Identifies this run of this program to the robot (fresa-v1) and in the journal.
        // A height map changes every motion: it is part of what the robot ran.
        let identity = match height_map {
            Some(m) => format!("{text}\n{}", serde_json::to_string(m).unwrap_or_default()),
            None => text.clone(),
        };
        let tag = format!("{run}-{:08x}", fnv1a(&identity) as u32);
        let mut start_cmd = plan.first_cmd_at(start_line);
        // What this process or the journal knows was done already.
        let seen = self.core.lock().progress.get(&run).copied().unwrap_or(0);
        // legacy: the robot cannot say what it executed, so every acknowledged command is
        // journalled; by default next to the program file the server stored (one data
        // directory, one journal: runs of another database can never be mistaken for ours).
        let journal = match self.core.cfg.protocol {
            Protocol::Legacy => {
                let p = self
                    .core
                    .cfg
                    .journal
                    .clone()
                    .unwrap_or_else(|| PathBuf::from(format!("{path}.kawasaki-journal")));
                Some(Journal::open(&p, &tag)?)
            }
            Protocol::FresaV1 => None,
        };
        let journaled = journal.as_ref().map_or(0, Journal::done);
        start_cmd = start_cmd.max(seen).max(journaled).min(plan.cmds.len());
        // Later than asked only when commands from the asked line on are known to be done.
        let actual_line = if start_cmd > plan.first_cmd_at(start_line) {
            start_line
                .max(plan.acked_through(start_cmd) + 1)
                .min(plan.lines + 1)
        } else {
            start_line
        };
        let lines = plan.lines;
        self.core.with(|sh, _| {
            sh.loaded = Some(Loaded {
                run,
                plan: Arc::new(plan),
                start_line,
                start_cmd,
                tag,
                expected_zero: expected_zero.map(|z| [z.x, z.y, z.z]),
                journal,
            });
        });
        Ok(ProgramLoaded {
            height_map: height_map.is_some(),
            ..ProgramLoaded::new(lines, actual_line.min(lines.max(1)))
        })
    }

    /// Connects, checks part zero and envelope, starts the robot program and the stream.
    fn start(&self) -> Result<RunAnswer, PluginError> {
        let core = self.core.clone();
        let loaded = {
            let mut sh = core.lock();
            if sh.busy {
                return Ok(RunAnswer::default());
            }
            sh.loaded.take().ok_or_else(|| {
                PluginError::new(
                    "no_program",
                    "no program is loaded: send load_program first",
                )
            })?
        };
        self.join();
        let cfg = &core.cfg;
        let stream = link::connect(&cfg.address, cfg.connect_timeout).map_err(link_error)?;
        let cut = stream.try_clone().ok();
        let (mut session, zero) = match cfg.protocol {
            Protocol::Legacy => {
                let mut l = LegacyLink::new(stream);
                let z = l.greeting(cfg.handshake_timeout).map_err(link_error)?;
                (Session::Legacy(l), z)
            }
            Protocol::FresaV1 => {
                let mut l = V1Link::new(stream);
                let z = l.hello(cfg.handshake_timeout).map_err(link_error)?;
                (Session::V1(l), z)
            }
        };
        core.emit(&Event::PartZeroReported {
            values: AxisValues {
                x: zero[0],
                y: zero[1],
                z: zero[2],
                a: 0.0,
            },
            run: Some(loaded.run),
        });
        let refuse = |session: Session, e: PluginError| {
            // Nothing was sent to the robot: its program ends when the socket closes.
            match session {
                Session::Legacy(l) => l.close(),
                Session::V1(l) => l.close(),
            }
            Err(e)
        };
        if let Some(expected) = loaded.expected_zero {
            if (0..3).any(|i| (expected[i] - zero[i]).abs() > PART_ZERO_TOLERANCE_MM) {
                return refuse(
                    session,
                    PluginError::new(
                        "part_zero_changed",
                        format!(
                            "the robot reports part zero ({:.3}, {:.3}, {:.3}) but run {} started with ({:.3}, {:.3}, {:.3}); \
                             bring the tool back to the original part zero and restart the robot program, \
                             or confirm the new part zero explicitly",
                            zero[0], zero[1], zero[2], loaded.run, expected[0], expected[1], expected[2]
                        ),
                    ),
                );
            }
        }
        if let Err(why) = loaded
            .plan
            .check_envelope(&cfg.envelope, &cfg.mapping, zero)
        {
            return refuse(session, PluginError::new("out_of_envelope", why));
        }
        let mut start_cmd = loaded.start_cmd;
        let started = match &mut session {
            Session::Legacy(l) => l.start(cfg.handshake_timeout),
            Session::V1(l) => l.run(&loaded.tag, cfg.handshake_timeout).map(|last| {
                // The robot's own count is exact: sequence number = command index + 1.
                start_cmd = start_cmd
                    .max(usize::try_from(last).unwrap_or(usize::MAX))
                    .min(loaded.plan.cmds.len());
            }),
        };
        if let Err(e) = started {
            return refuse(session, link_error(e));
        }
        let run = loaded.run;
        core.with(|sh, ev| {
            sh.part_zero = Some(zero);
            sh.at = [0.0; 3];
            sh.busy = true;
            sh.pause = false;
            sh.cancel = false;
            sh.run = Some(run);
            sh.socket = cut;
            sh.line = Some(loaded.start_line);
            sh.alarm = None;
            sh.reason = None;
            sh.set_state(MachineState::Running, ev);
        });
        let worker_core = core.clone();
        let handle = std::thread::Builder::new()
            .name(format!("kawasaki-run-{run}"))
            .spawn(move || worker_core.stream(session, loaded, start_cmd))
            .map_err(|e| {
                PluginError::new("internal", format!("cannot start the run thread: {e}"))
            })?;
        *self.worker.lock().unwrap_or_else(|e| e.into_inner()) = Some(handle);
        Ok(RunAnswer {
            part_zero: Some(AxisValues {
                x: zero[0],
                y: zero[1],
                z: zero[2],
                a: 0.0,
            }),
        })
    }

    fn pause(&self, strict: bool) -> Result<(), PluginError> {
        self.hold(true, strict)
    }

    /// Overrides, as far as the protocol can carry them: fresa-v1 changes the cutting speed
    /// between streamed commands (a `SPEED` with sequence number 0 before the next one it
    /// sends); the seed's program (legacy) fixes its speeds. Whatever cannot be applied refuses
    /// the whole request, saying why, and nothing changes. 100 % is always accepted.
    fn apply_overrides(
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
        let asked = |v: Option<f64>| v.filter(|v| *v != 100.0);
        let unsupported = |why: String| Err(PluginError::new("unsupported", why));
        if let Some(s) = asked(spindle) {
            return unsupported(format!(
                "kawasaki-as cannot override the spindle speed (asked {s} %): the spindle's speed \
                 is set by hand with the potentiometer on its supply, not by the robot (spec: \
                 \"speed set by a 0-10 V potentiometer on its supply (not by the robot)\")"
            ));
        }
        let legacy = self.core.cfg.protocol == Protocol::Legacy;
        if let Some(f) = asked(feed).filter(|_| legacy) {
            return unsupported(format!(
                "kawasaki-as with protocol `legacy` cannot override the feed (asked {f} %): the \
                 seed's robot program runs every LMOVE at its own `SPEED 15 MM/S ALWAYS` and \
                 ignores any other command without an answer (spec: \"`LMOVE,x,y,z` ... Robot runs \
                 it at 15 mm/s.\"; \"Unknown commands are ignored by the robot without an \
                 answer\"), so no speed can be sent during a run; protocol `fresa-v1` can"
            ));
        }
        if let Some(r) = asked(rapid) {
            let why = if legacy {
                "the seed's robot program runs every JMOVE at its own `SPEED 10 MM/S ALWAYS` \
                 (spec: \"`JMOVE,x,y,z` - for G0. The robot runs it as a *linear* move at a \
                 fixed 10 mm/s.\")"
            } else {
                "fresa-v1's robot program runs every JMOVE at its constant `rapid` (the \
                 machine's `rapid_mm_s`) and has no command to change it"
            };
            return unsupported(format!(
                "kawasaki-as cannot override the rapid speed (asked {r} %): {why}"
            ));
        }
        let status = {
            let mut sh = self.core.lock();
            let next = sh.overrides.with(feed, spindle, rapid);
            (next != sh.overrides).then(|| {
                sh.overrides = next;
                sh.status(&self.core.cfg)
            })
        };
        if let Some(st) = status {
            self.core.emit(&Event::Status(st));
        }
        Ok(())
    }

    fn resume(&self, strict: bool) -> Result<(), PluginError> {
        self.hold(false, strict)
    }

    /// Pause (`hold`) or resume the run: stop or restart sending. `strict` (run control, not the
    /// feed-hold button) refuses when no program is loaded; otherwise a no-op is fine.
    fn hold(&self, hold: bool, strict: bool) -> Result<(), PluginError> {
        let (from, to, what) = if hold {
            (MachineState::Running, MachineState::Paused, "pause")
        } else {
            (MachineState::Paused, MachineState::Running, "resume")
        };
        let r = self.core.with(|sh, ev| {
            if sh.state == from {
                sh.pause = hold;
                sh.set_state(to, ev);
                Ok(())
            } else if strict && sh.run.is_none() {
                Err(PluginError::new(
                    "not_running",
                    format!("no program is running: nothing to {what}"),
                ))
            } else {
                Ok(())
            }
        });
        // Wakes the sender after a resume (harmless after a pause).
        self.core.cv.notify_all();
        r
    }

    /// Cancels and waits until the run has ended: no further command is sent, the robot has
    /// finished the ones it already had (a window of at most `window` short moves), and
    /// `run_ended` has been emitted. A robot still moving after [`END_WAIT`] gets
    /// `stop_unconfirmed`: the run then ends, cancelled, when those moves are done.
    fn cancel_and_wait(&self) -> Result<(), PluginError> {
        let before = {
            let sh = self.core.lock();
            sh.busy.then_some(sh.runs_ended)
        };
        self.cancel();
        let Some(before) = before else { return Ok(()) };
        let deadline = Instant::now() + END_WAIT;
        let mut sh = self.core.lock();
        while sh.runs_ended == before {
            let now = Instant::now();
            if now >= deadline {
                return Err(PluginError::new(
                    "stop_unconfirmed",
                    format!(
                        "the robot is still finishing the moves already sent after {END_WAIT:?}; the run ends, cancelled, when they are done"
                    ),
                ));
            }
            sh = match self.core.cv.wait_timeout(sh, deadline - now) {
                Ok((g, _)) => g,
                Err(e) => e.into_inner().0,
            };
        }
        Ok(())
    }

    /// Stops sending; the run thread sends EXIT once the robot waits for a command.
    fn cancel(&self) {
        self.core.with(|sh, _| {
            sh.cancel = true;
            if let Some(l) = sh.loaded.take() {
                sh.progress.remove(&l.run);
            }
        });
        self.core.cv.notify_all();
    }

    fn join(&self) {
        let handle = self.worker.lock().unwrap_or_else(|e| e.into_inner()).take();
        if let Some(h) = handle {
            let _ = h.join();
        }
    }
}

impl KawasakiMachine {
    /// Cancels and closes the link at once: the robot program's receive fails after the motion
    /// in progress and it ends. What was executed is known at the next start (journal or the
    /// robot's sequence number).
    fn cut(&self) {
        self.cancel();
        let socket = self.core.lock().socket.take();
        if let Some(s) = socket {
            let _ = s.shutdown(std::net::Shutdown::Both);
        }
    }
}

impl Drop for KawasakiMachine {
    fn drop(&mut self) {
        self.cut();
        self.join();
    }
}

impl Shared {
    fn set_state(&mut self, to: MachineState, ev: &mut Vec<Event>) {
        if self.state != to {
            ev.push(Event::StateChanged {
                from: self.state,
                to,
            });
            self.state = to;
        }
    }
}

impl Core {
    fn lock(&self) -> MutexGuard<'_, Shared> {
        self.sh.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Runs `f` under the lock, then emits what it produced followed by a status.
    fn with<R>(&self, f: impl FnOnce(&mut Shared, &mut Vec<Event>) -> R) -> R {
        let mut ev = Vec::new();
        let (r, status) = {
            let mut sh = self.lock();
            let r = f(&mut sh, &mut ev);
            (r, (!ev.is_empty()).then(|| sh.status(&self.cfg)))
        };
        for e in &ev {
            (self.sink)(e);
        }
        if let Some(s) = status {
            (self.sink)(&Event::Status(s));
        }
        r
    }

    fn emit(&self, e: &Event) {
        (self.sink)(e);
    }

    fn log_warn(&self, message: &str) {
        (self.log)(message);
    }

    /// Emits acknowledgements for lines `*acked + 1 ..= through`.
    fn ack(&self, run: i64, acked: &mut u32, through: u32) {
        while *acked < through {
            *acked += 1;
            self.emit(&Event::LineAcknowledged { run, line: *acked });
        }
    }

    /// Marks commands `..done` as executed.
    fn mark(
        &self,
        run: i64,
        plan: &Plan,
        journal: &mut Option<Journal>,
        done: usize,
        acked: &mut u32,
    ) -> Result<(), String> {
        if let Some(j) = journal {
            j.record(done)?;
        }
        let status = {
            let mut sh = self.lock();
            sh.progress.insert(run, done);
            if let Some((line, Cmd::Move { to, .. })) =
                done.checked_sub(1).and_then(|i| plan.cmds.get(i))
            {
                sh.at = *to;
                sh.line = Some(*line);
            }
            // The position moves with every motion; report it a few times a second.
            let now = Instant::now();
            let due = sh
                .last_status
                .is_none_or(|t| now.duration_since(t) >= STATUS_INTERVAL);
            if due {
                sh.last_status = Some(now);
            }
            due.then(|| sh.status(&self.cfg))
        };
        if let Some(st) = status {
            self.emit(&Event::Status(st));
        }
        self.ack(run, acked, plan.acked_through(done));
        Ok(())
    }

    /// Waits while paused; true when the run is cancelled.
    fn hold(&self) -> bool {
        let mut sh = self.lock();
        while sh.pause && !sh.cancel {
            sh = self.cv.wait(sh).unwrap_or_else(|e| e.into_inner());
        }
        sh.cancel
    }

    /// Sleeps `secs`, waking early on cancel. True when cancelled.
    fn dwell(&self, secs: f64) -> bool {
        let end = Instant::now() + Duration::from_secs_f64(secs.min(3600.0));
        let mut sh = self.lock();
        while !sh.cancel {
            let now = Instant::now();
            if now >= end {
                break;
            }
            sh = self
                .cv
                .wait_timeout(sh, end - now)
                .map(|(g, _)| g)
                .unwrap_or_else(|e| e.into_inner().0);
        }
        sh.cancel
    }

    fn pause_at_m0(&self) {
        self.with(|sh, ev| {
            if sh.state == MachineState::Running {
                sh.pause = true;
                sh.set_state(MachineState::Paused, ev);
            }
        });
    }

    /// The run thread.
    fn stream(self: Arc<Self>, session: Session, mut loaded: Loaded, start_cmd: usize) {
        let run = loaded.run;
        let journal = &mut loaded.journal;
        let plan = loaded.plan.clone();
        let mut acked = loaded.start_line.saturating_sub(1);
        // Lines already done before this start (known from the journal or the robot).
        self.ack(
            run,
            &mut acked,
            plan.acked_through(start_cmd).min(plan.lines),
        );
        let ended = match session {
            Session::Legacy(link) => {
                self.stream_legacy(link, &plan, journal, run, start_cmd, &mut acked)
            }
            Session::V1(link) => self.stream_v1(link, &plan, journal, run, start_cmd, &mut acked),
        };
        let (outcome, message) = match ended {
            Ended::Completed => {
                self.ack(run, &mut acked, plan.lines);
                (RunOutcome::Completed, None)
            }
            Ended::Cancelled => (RunOutcome::Cancelled, None),
            Ended::Failed(m) => (RunOutcome::Failed, Some(m)),
        };
        self.with(|sh, ev| {
            sh.busy = false;
            sh.socket = None;
            sh.run = None;
            sh.line = None;
            sh.pause = false;
            if outcome != RunOutcome::Failed {
                sh.progress.remove(&run);
            }
            if let Some(m) = &message {
                sh.reason = Some(m.clone());
            }
            // Idle first: whoever sees the run end may start or resume at once and must not
            // find the machine still running.
            sh.set_state(MachineState::Idle, ev);
            ev.push(Event::RunEnded {
                run,
                outcome,
                message,
            });
        });
        // After `with` has emitted the events: whoever waits for the end sees them sent.
        self.lock().runs_ended += 1;
        self.cv.notify_all();
    }

    fn stream_legacy(
        &self,
        mut link: LegacyLink,
        plan: &Plan,
        journal: &mut Option<Journal>,
        run: i64,
        start_cmd: usize,
        acked: &mut u32,
    ) -> Ended {
        let cfg = &self.cfg;
        for i in start_cmd..plan.cmds.len() {
            if self.hold() {
                link.exit();
                return Ended::Cancelled;
            }
            let (line, cmd) = plan.cmds[i];
            match cmd {
                // The seed's program fixes its own speeds and ignores SPEED without answering.
                Cmd::Speed(_) => {}
                Cmd::Dwell(s) => {
                    if self.dwell(s) {
                        link.exit();
                        return Ended::Cancelled;
                    }
                }
                Cmd::Pause => self.pause_at_m0(),
                Cmd::Move { rapid, to } => {
                    {
                        let mut sh = self.lock();
                        sh.line = Some(line);
                        sh.feed_mm_s = if rapid { 10.0 } else { 15.0 };
                    }
                    let sent = link.send_move(rapid, to).and_then(|()| {
                        link.expect_done(cfg.reply_timeout, "`done` after a motion")
                    });
                    for g in link.garbage.drain(..) {
                        self.warn_quiet("malformed", || {
                            format!("skipped a malformed robot message: {g:?}")
                        });
                    }
                    if let Err(e) = sent {
                        link.close();
                        return Ended::Failed(format!(
                            "line {line}: {e}; resume continues with this motion (it may already have been executed: \
                             the legacy protocol cannot tell, and repeating an absolute move is harmless)"
                        ));
                    }
                }
            }
            if let Err(e) = self.mark(run, plan, journal, i + 1, acked) {
                link.exit();
                return Ended::Failed(e);
            }
        }
        link.exit();
        Ended::Completed
    }

    fn stream_v1(
        &self,
        mut link: V1Link,
        plan: &Plan,
        journal: &mut Option<Journal>,
        run: i64,
        start_cmd: usize,
        acked: &mut u32,
    ) -> Ended {
        let cfg = &self.cfg;
        let window = cfg.window;
        // Sent and not yet done: command indices (usize::MAX: a SPEED of our own, seq 0), with
        // the speed a SPEED among them set.
        let mut inflight: VecDeque<(usize, Option<f64>)> = VecDeque::new();
        let mut next = start_cmd;
        // The feed override the speed last sent follows (the robot program's own starting speed
        // follows none).
        let mut sent_for = 100.0;
        // A resumed run: the robot's speed is whatever it was; set the one in effect.
        if start_cmd > 0 {
            if let Some(v) = plan.speed_before(start_cmd) {
                let feed = self.lock().overrides.feed;
                let mm_s = cfg.speeds.overridden(v, feed);
                let _ = link.send(&V1Cmd::Speed { seq: 0, mm_s });
                inflight.push_back((usize::MAX, Some(mm_s)));
                sent_for = feed;
            }
        }
        loop {
            let (pause, cancel, feed) = {
                let sh = self.lock();
                (sh.pause, sh.cancel, sh.overrides.feed)
            };
            // A feed override changed: the programmed speed in force, scaled, goes out before
            // the next command (the motions already sent keep theirs; the robot program takes
            // a SPEED once the motion before it is complete).
            if feed != sent_for
                && !pause
                && !cancel
                && inflight.len() < window
                && next < plan.cmds.len()
            {
                let programmed = plan.speed_before(next).unwrap_or(cfg.speeds.cut_min_mm_s);
                let mm_s = cfg.speeds.overridden(programmed, feed);
                let _ = link.send(&V1Cmd::Speed { seq: 0, mm_s });
                inflight.push_back((usize::MAX, Some(mm_s)));
                sent_for = feed;
            }
            if cancel && inflight.is_empty() {
                link.exit(cfg.handshake_timeout);
                return Ended::Cancelled;
            }
            // Fill the window.
            while !pause && !cancel && inflight.len() < window && next < plan.cmds.len() {
                let (line, cmd) = plan.cmds[next];
                let seq = next as u64 + 1;
                let mut speed = None;
                match cmd {
                    Cmd::Speed(v) => {
                        let mm_s = cfg.speeds.overridden(v, feed);
                        let _ = link.send(&V1Cmd::Speed { seq, mm_s });
                        speed = Some(mm_s);
                        sent_for = feed;
                    }
                    Cmd::Move { rapid, to } => {
                        let _ = link.send(&V1Cmd::Move { seq, rapid, to });
                        self.lock().line = Some(line);
                    }
                    // Local commands wait until everything before them is done.
                    Cmd::Dwell(_) | Cmd::Pause if !inflight.is_empty() => break,
                    Cmd::Dwell(s) => {
                        if self.dwell(s) {
                            break;
                        }
                        next += 1;
                        if let Err(e) = self.mark(run, plan, journal, next, acked) {
                            link.close();
                            return Ended::Failed(e);
                        }
                        continue;
                    }
                    Cmd::Pause => {
                        self.pause_at_m0();
                        next += 1;
                        if let Err(e) = self.mark(run, plan, journal, next, acked) {
                            link.close();
                            return Ended::Failed(e);
                        }
                        break;
                    }
                }
                inflight.push_back((next, speed));
                next += 1;
            }
            if let Err(e) = link.flush() {
                link.close();
                return Ended::Failed(format!(
                    "{e}; resume continues at the robot's last executed command"
                ));
            }
            if inflight.is_empty() {
                if next >= plan.cmds.len() {
                    link.exit(cfg.handshake_timeout);
                    return Ended::Completed;
                }
                if self.hold() {
                    link.exit(cfg.handshake_timeout);
                    return Ended::Cancelled;
                }
                continue;
            }
            let msg = link.recv(cfg.reply_timeout, "`done` of a command");
            for g in link.garbage.drain(..) {
                self.warn_quiet("malformed", || {
                    format!("skipped a malformed robot message: {g}")
                });
            }
            match msg {
                Ok(V1Msg::Done(seq)) => {
                    let Some(&(front, speed)) = inflight.front() else {
                        continue;
                    };
                    let expected = if front == usize::MAX {
                        0
                    } else {
                        front as u64 + 1
                    };
                    if seq != expected {
                        link.close();
                        return Ended::Failed(format!(
                            "the robot acknowledged command {seq} but {expected} was the oldest one outstanding"
                        ));
                    }
                    inflight.pop_front();
                    if let Some(v) = speed {
                        self.lock().feed_mm_s = v;
                    }
                    if front != usize::MAX {
                        if let Err(e) = self.mark(run, plan, journal, front + 1, acked) {
                            link.close();
                            return Ended::Failed(e);
                        }
                    }
                }
                Ok(V1Msg::Err { seq, message }) => {
                    link.close();
                    return Ended::Failed(format!("the robot refused command {seq}: {message}"));
                }
                Ok(other) => self.warn_quiet("unexpected", || {
                    format!("unexpected robot message {other:?}; skipped")
                }),
                Err(e) => {
                    link.close();
                    let line = inflight
                        .front()
                        .and_then(|(i, _)| plan.cmds.get(*i))
                        .map(|(l, _)| format!("line {l}: "))
                        .unwrap_or_default();
                    return Ended::Failed(format!(
                        "{line}{e}; resume continues at the robot's last executed command"
                    ));
                }
            }
        }
    }

    fn warn(&self, message: &str) {
        (self.log)(message);
    }

    fn warn_quiet(&self, kind: &str, message: impl FnOnce() -> String) {
        if let Some(line) = self.quiet.admit(kind, message) {
            self.warn(&line);
        }
    }
}

/// Why home, zero, go-to-zero and work offsets are refused, for the operator.
fn taught_on_pendant() -> PluginError {
    PluginError::new(
        "unsupported",
        "the robot's part zero is taught on its pendant and reported when a job starts; \
         home, zero, go-to-zero and work offsets are not available",
    )
}

impl MachineBackend for KawasakiMachine {
    /// The AS protocol this backend speaks streams motions and reads positions; it has no
    /// probe input or a motion that ends on one (a robot would need a signal input wired and
    /// an AS program watching it), so a probe is refused with the reason.
    fn probe(&self, _probe: fresa_plugin_api::contract::Probe) -> Result<(), PluginError> {
        Err(PluginError::new(
            "unsupported",
            "kawasaki-as cannot probe: the robot's AS link has no probe input or a move that \
             stops on one; set the part zero by teaching it (part-zero) instead",
        ))
    }

    /// The robot is given its speeds by this backend: G0 at `rapid_mm_s`, feeds clamped to
    /// `cut_min_mm_s..=cut_max_mm_s`. Its own acceleration and blending (CP ON) are the
    /// controller's and not known here: none is assumed.
    fn motion_profile(&self) -> Result<fresa_plugin_api::contract::MotionProfile, PluginError> {
        let s = self.core.cfg.speeds;
        Ok(fresa_plugin_api::contract::MotionProfile {
            rapid_mm_min: s.rapid_mm_s * 60.0,
            min_feed_mm_min: s.cut_min_mm_s * 60.0,
            max_feed_mm_min: s.cut_max_mm_s * 60.0,
            accel_mm_s2: 0.0,
            corner_jump_mm_s: 0.0,
            per_axis: false,
        })
    }

    fn create(host: Host, config: Value) -> Result<Self, PluginError> {
        KawasakiMachine::new(
            &config,
            Arc::new(move |event| host.emit(event)),
            Arc::new(move |message| host.warn(message)),
        )
    }

    fn connect(&self) -> Result<MachineStatus, PluginError> {
        self.core.with(|sh, ev| {
            if sh.state == MachineState::Offline {
                sh.set_state(MachineState::Idle, ev);
            }
        });
        Ok(self.status_now())
    }

    fn status(&self) -> Result<MachineStatus, PluginError> {
        Ok(self.status_now())
    }

    /// A start at a line (a preamble) is refused: see [`NO_PREAMBLE`].
    fn load_program(&self, p: LoadProgram) -> Result<ProgramLoaded, PluginError> {
        if p.preamble.is_some() {
            return Err(PluginError::new("unsupported", NO_PREAMBLE));
        }
        let tools =
            fresa_gcode::tool_table(p.tools.iter().map(|t| (t.tool, t.diameter_mm, t.length_mm)));
        // The converted program is kept whole (the run and resumes index its commands), about
        // 40 bytes a command: at most MAX_COMMANDS of them, whatever the host's budget.
        let budget = p
            .max_segments
            .unwrap_or(fresa_gcode::DEFAULT_MAX_SEGMENTS)
            .min(crate::convert::MAX_COMMANDS);
        if let Some(map) = &p.height_map {
            map.validate().map_err(PluginError::invalid)?;
        }
        self.load(&p, tools, budget)
    }

    fn run(&self, action: RunAction) -> Result<RunAnswer, PluginError> {
        match action {
            RunAction::Start => return self.start(),
            RunAction::Pause => self.pause(true)?,
            RunAction::Resume => self.resume(true)?,
            RunAction::Cancel => self.cancel_and_wait()?,
        }
        Ok(RunAnswer::default())
    }

    fn cycle_start(&self) -> Result<RunAnswer, PluginError> {
        if self.core.lock().state == MachineState::Paused {
            self.resume(false).map(|()| RunAnswer::default())
        } else {
            self.start()
        }
    }

    fn feed_hold(&self) -> Result<(), PluginError> {
        self.pause(false)
    }

    fn resume(&self) -> Result<(), PluginError> {
        KawasakiMachine::resume(self, false)
    }

    fn stop(&self) -> Result<(), PluginError> {
        self.stop_and_clear()
    }

    fn reset(&self) -> Result<(), PluginError> {
        self.stop_and_clear()
    }

    fn shutdown(&self) -> Result<(), PluginError> {
        self.cut();
        self.join();
        self.core
            .with(|sh, ev| sh.set_state(MachineState::Offline, ev));
        Ok(())
    }

    fn jog(&self, _axis: Axis, _distance: f64, _feed: Option<f64>) -> Result<(), PluginError> {
        Err(PluginError::new(
            "unsupported",
            "the robot is jogged with its teach pendant, not through this server",
        ))
    }

    fn home(&self, _axis: Option<Axis>) -> Result<(), PluginError> {
        Err(taught_on_pendant())
    }

    fn zero(&self, _axis: Option<Axis>) -> Result<Option<OffsetTable>, PluginError> {
        Err(taught_on_pendant())
    }

    fn go_to_zero(&self) -> Result<(), PluginError> {
        Err(taught_on_pendant())
    }

    fn select_offset(&self, _offset: WorkOffset) -> Result<(), PluginError> {
        Err(taught_on_pendant())
    }

    // The robot works relative to the part zero taught on its pendant; G54..G59 are kept by
    // the server but do not move it. Outputs and MDI keep the trait's `unsupported` answers.
    fn get_offsets(&self) -> Result<OffsetTable, PluginError> {
        Ok(OffsetTable::default())
    }

    fn set_offset(&self, _offset: WorkOffset, _values: AxisValues) -> Result<(), PluginError> {
        Ok(())
    }

    fn get_artifact(&self, name: &str) -> Result<Artifact, PluginError> {
        self.artifact(name)
    }

    fn set_overrides(
        &self,
        feed: Option<f64>,
        spindle: Option<f64>,
        rapid: Option<f64>,
    ) -> Result<(), PluginError> {
        self.apply_overrides(feed, spindle, rapid)
    }
}

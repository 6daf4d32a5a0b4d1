//! Live machines. Each machine is one task (see [`actor`]) that owns its run lifecycle: the
//! current run and its state, the acknowledged line, the machine row, and the order in which
//! calls reach the backend. Everyone else holds a [`Machine`] handle: it reads what the task
//! publishes (status, row, run) and sends it messages that are answered only once the change
//! they ask for is true. Stop, feed hold and reset skip the task's queue (see [`lanes`]).

mod actor;
pub mod centre;
pub mod counters;
pub mod deadman;
pub mod heightmap;
pub mod holds;
mod lanes;
pub mod limits;
mod moves;
mod preamble;
pub mod probing;
pub mod unstored;

pub use lanes::BackendError;

use crate::error::{Error, Result};
use crate::events::EventBus;
use crate::events::EventKind;
use crate::store::{JobRow, MachineRow, PartZeroRow, RunRow, RunState, Store};
use crate::views::{JobProgress, StatusView};
use fresa_plugin_api::contract::{
    Axis, AxisValues, Command, Event, MachineState, MachineStatus, Request, WorkOffset,
};
use fresa_plugin_api::host::{HostSink, Instance, PluginLibrary};
use fresa_plugin_api::quiet::Quiet;
use serde_json::{json, Value};
use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicI64, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::{mpsc, oneshot, watch};

pub struct MachineOptions {
    pub timeout: Duration,
    pub status_interval: Duration,
    pub programs_dir: PathBuf,
    /// Where each machine records acknowledged lines the store could not take
    /// (`DATA_DIR/unstored`).
    pub unstored_dir: PathBuf,
    /// The work budget sent with every `load_program` (`max_program_segments`).
    pub max_program_segments: u64,
}

/// The current run as everyone but the machine's task sees it.
#[derive(Debug, Clone, PartialEq)]
pub struct RunView {
    pub run_id: i64,
    pub job_id: i64,
    pub total_lines: i64,
    pub state: RunState,
    /// Last acknowledged line.
    pub line: i64,
    /// The program's time by line (from its analysis), for the time left.
    pub times: Option<Arc<fresa_gcode::TimeTable>>,
    /// Its `job.state running` event is on the bus. Until then the status loop sends no
    /// `job.progress` for it, so no stream sees a run's progress before the run's start.
    pub announced: bool,
}

impl RunView {
    /// Its progress as `job.progress` and a status's `job` show it, the time left under the
    /// feed and rapid overrides in force (percent).
    pub fn progress(&self, feed_pct: f64, rapid_pct: f64) -> JobProgress {
        let remaining = self.times.as_ref().map(|t| {
            let line = u32::try_from(self.line.max(0)).unwrap_or(u32::MAX);
            t.remaining_after(line, feed_pct, rapid_pct)
        });
        JobProgress::new(
            self.job_id,
            self.run_id,
            self.line,
            self.total_lines,
            remaining,
        )
    }
}

/// Lets stop and feed hold overtake requests already queued for the task: each motion request
/// carries the epoch it was sent in, and the task refuses to start motion for a request that a
/// stop has overtaken. Shutdown closes the gate for good.
#[derive(Default)]
pub(crate) struct Gate {
    epoch: AtomicU64,
    closed: AtomicBool,
}

impl Gate {
    pub(crate) fn ticket(&self) -> u64 {
        self.epoch.load(Ordering::SeqCst)
    }
    pub(crate) fn overtake(&self) {
        self.epoch.fetch_add(1, Ordering::SeqCst);
    }
    fn close(&self) {
        self.closed.store(true, Ordering::SeqCst);
        self.overtake();
    }
    /// Ok while nothing stopped the machine since `ticket` was taken.
    pub(crate) fn check(&self, ticket: u64) -> Result<()> {
        if self.closed.load(Ordering::SeqCst) {
            return Err(Error::new(
                crate::error::ErrorKind::Unavailable,
                "shutting_down",
                "the server is shutting down; no new motion is started",
            ));
        }
        if self.epoch.load(Ordering::SeqCst) != ticket {
            return Err(Error::conflict(
                "stopped",
                "a stop or feed hold arrived while this request waited; it was not carried out",
            ));
        }
        Ok(())
    }
}

/// A backend instance created but not yet attached to a machine.
pub struct Prepared {
    instance: Instance,
    events: mpsc::UnboundedReceiver<Event>,
    machine_id: Arc<AtomicI64>,
}

struct Sink {
    tx: mpsc::UnboundedSender<Event>,
    /// Set once the machine row exists; 0 while the config is being checked.
    machine_id: Arc<AtomicI64>,
    /// An unknown event repeats per event: warned about once a minute, with a count.
    quiet: Quiet,
}

impl Sink {
    /// Queues a decoded event, or warns about one that is JSON but not a contract event.
    fn accept(
        &self,
        decoded: std::result::Result<Event, serde_json::Error>,
        raw: &dyn Fn() -> String,
    ) {
        match decoded {
            // Unbounded on purpose: a plugin thread must never block on the host, and every
            // line acknowledgement matters. The task drains in batches.
            Ok(e) => {
                let _ = self.tx.send(e);
            }
            Err(e) => {
                if let Some(line) = self.quiet.admit("unknown-event", || {
                    format!("unknown backend event {}; ignored: {e}", raw())
                }) {
                    let id = Some(self.machine_id.load(Ordering::Relaxed)).filter(|&id| id != 0);
                    tracing::warn!(machine = id, "{line}");
                }
            }
        }
    }
}

impl HostSink for Sink {
    fn event(&self, event: Value) {
        use serde::Deserialize;
        self.accept(Event::deserialize(&event), &|| event.to_string());
    }
    /// On the plugin's thread: straight from the plugin's bytes to the contract's event.
    fn event_json(&self, bytes: &[u8]) -> std::result::Result<(), serde_json::Error> {
        let decoded = fresa_plugin_api::host::decode_event::<Event>(bytes)?;
        self.accept(decoded, &|| String::from_utf8_lossy(bytes).into_owned());
        Ok(())
    }
    fn log(&self, level: u32, message: &str) {
        use fresa_plugin_api::abi::*;
        // No machine id yet while the backend is created to check a new machine's config: the
        // field is left out then rather than logged as a misleading `machine=0`.
        let id = Some(self.machine_id.load(Ordering::Relaxed)).filter(|&id| id != 0);
        match level {
            LOG_ERROR => tracing::error!(machine = id, "{message}"),
            LOG_WARN => tracing::warn!(machine = id, "{message}"),
            LOG_INFO => tracing::info!(machine = id, "{message}"),
            LOG_DEBUG => tracing::debug!(machine = id, "{message}"),
            _ => tracing::trace!(machine = id, "{message}"),
        }
    }
}

type Reply<T> = oneshot::Sender<Result<T>>;

/// What the task is asked to do. Motion requests carry the gate ticket taken when they were
/// sent.
pub(crate) enum Msg {
    Restore {
        reply: oneshot::Sender<()>,
    },
    /// One operation of the contract (a jog, an MDI line, a command), handled by the one path
    /// its declared properties drive (`fresa_plugin_api::operation`).
    Call {
        request: Request,
        actor: String,
        ticket: u64,
        reply: Reply<Value>,
    },
    /// Records a part zero (at `position`, or where the machine stands), refused while it moves.
    /// Not a backend operation (the host reads the position and keeps the record), so it is not
    /// in the operation table.
    PartZero {
        position: Option<AxisValues>,
        source: String,
        note: Option<String>,
        actor: String,
        reply: Reply<PartZeroRow>,
    },
    Start {
        job: JobRow,
        actor: String,
        /// A start at a line (`None`: from the first; see `crate::start_at`).
        from_line: Option<u32>,
        ticket: u64,
        /// The height map to apply (issue 25), checked against the job already.
        height_map: Option<heightmap::Applied>,
        reply: Reply<RunRow>,
    },
    /// Pause and cancel travel on the task's urgent channel: served before anything queued on
    /// the ordinary one, and while the task waits for an ordinary backend call.
    Pause {
        job_id: i64,
        actor: String,
        /// The host pauses the run itself for this reason (a pendant lost), shown as its hold.
        reason: Option<(fresa_plugin_api::contract::HoldKind, String)>,
        reply: Reply<RunRow>,
    },
    Resume {
        job: JobRow,
        actor: String,
        confirm_part_zero: bool,
        confirm_line: Option<i64>,
        ticket: u64,
        reply: Reply<RunRow>,
    },
    Cancel {
        job_id: i64,
        actor: String,
        reply: Reply<RunRow>,
    },
    /// Answered once everything sent before it, and every backend event queued, is handled.
    Sync {
        reply: oneshot::Sender<()>,
    },
}

/// A handle on a live machine. Cheap to share; the state behind it belongs to the task.
pub struct Machine {
    pub id: i64,
    tx: mpsc::UnboundedSender<Msg>,
    /// Pause and cancel of the running job: never queued behind an ordinary message.
    urgent_tx: mpsc::UnboundedSender<Msg>,
    lanes: Option<Arc<lanes::Lanes>>,
    /// Why the backend is missing (plugin not found, config rejected).
    unavailable: Option<String>,
    status: watch::Receiver<MachineStatus>,
    row: watch::Receiver<MachineRow>,
    run: watch::Receiver<Option<RunView>>,
    /// The job of the current run.
    job: watch::Receiver<Option<JobRow>>,
    /// The current run's row as launched: with `run`, the current run without the database.
    launched: watch::Receiver<Option<RunRow>>,
    gate: Arc<Gate>,
    bus: EventBus,
    timeout: Duration,
    /// The continuous jog and its keep-alives.
    deadman: deadman::Deadman,
    /// The last probing move's end, as the backend reported it (see [`probing`]).
    probe_ended: watch::Receiver<Option<probing::ProbeEnd>>,
    /// Numbers probing moves, so an end is matched to its own move.
    probe_ids: AtomicU64,
    /// How the machine moves, once the backend said (see [`Machine::motion_profile`]).
    profile: std::sync::OnceLock<Option<fresa_gcode::MotionProfile>>,
    /// The host's part of why the machine holds (see [`holds`]).
    holds: Arc<holds::HostHolds>,
    /// The height map grid being probed, if any (see [`heightmap`]).
    grid: heightmap::Slot,
    /// State changes and maintenance counters (see [`counters`]).
    records: Arc<counters::Records>,
    /// `status_view` serialised, for status polls (see [`Machine::status_json`]).
    status_json: std::sync::Mutex<StatusJson>,
}

/// The last status serialised, and the receivers that say whether it is still current: a watch
/// receiver's `has_changed` is one atomic load, so a poll costs no clone and no serialisation
/// until the task publishes a new status or run.
struct StatusJson {
    status: watch::Receiver<MachineStatus>,
    run: watch::Receiver<Option<RunView>>,
    json: Option<bytes::Bytes>,
}

impl Machine {
    /// Creates a backend instance from `config`, off the async runtime. Its events queue until
    /// [`Machine::start`] takes it, so the instance a config was checked with is the one kept
    /// (a real controller is not connected twice).
    pub async fn prepare(library: &PluginLibrary, config: Value) -> Result<Prepared, String> {
        let (tx, rx) = mpsc::unbounded_channel();
        let machine_id = Arc::new(AtomicI64::new(0));
        let sink = Arc::new(Sink {
            tx,
            machine_id: machine_id.clone(),
            quiet: Quiet::per_minute(),
        });
        let lib = library.clone();
        match tokio::task::spawn_blocking(move || lib.create(&config, sink)).await {
            Ok(Ok(instance)) => Ok(Prepared {
                instance,
                events: rx,
                machine_id,
            }),
            Ok(Err(e)) => Err(e.to_string()),
            Err(e) => Err(format!("backend create failed: {e}")),
        }
    }

    /// Starts the machine's task for `row` and brings the backend to the state the store
    /// remembers (connect, offsets, active offset). Never fails: a machine whose backend could
    /// not be created is kept, offline with the reason, so the operator sees it and can fix it.
    pub async fn start(
        row: MachineRow,
        backend: Result<Prepared, String>,
        store: Store,
        bus: EventBus,
        opts: &MachineOptions,
    ) -> Arc<Machine> {
        let (lanes, events, unavailable) = match backend {
            Ok(p) => {
                p.machine_id.store(row.id, Ordering::Relaxed);
                match lanes::Lanes::new(p.instance, row.id, opts.timeout) {
                    Ok(l) => (Some(Arc::new(l)), Some(p.events), None),
                    Err(e) => (
                        None,
                        None,
                        Some(format!("cannot start the call thread: {e}")),
                    ),
                }
            }
            Err(reason) => (None, None, Some(reason)),
        };
        let status = MachineStatus {
            state: MachineState::Offline,
            reason: unavailable.clone(),
            ..Default::default()
        };
        let (status_tx, status_rx) = watch::channel(status);
        let (row_tx, row_rx) = watch::channel(row.clone());
        let (run_tx, run_rx) = watch::channel(None);
        let (job_tx, job_rx) = watch::channel(None);
        let (launched_tx, launched_rx) = watch::channel(None);
        let (probe_tx, probe_rx) = watch::channel(None);
        let (tx, rx) = mpsc::unbounded_channel();
        let (urgent_tx, urgent_rx) = mpsc::unbounded_channel();
        let gate = Arc::new(Gate::default());
        let holds = Arc::new(holds::HostHolds::new(store.health().clone()));
        let m = Arc::new(Machine {
            id: row.id,
            tx,
            urgent_tx,
            lanes: lanes.clone(),
            unavailable: unavailable.clone(),
            status: status_rx.clone(),
            row: row_rx,
            run: run_rx.clone(),
            job: job_rx,
            launched: launched_rx,
            gate: gate.clone(),
            bus: bus.clone(),
            timeout: opts.timeout,
            deadman: deadman::Deadman::default(),
            probe_ended: probe_rx,
            probe_ids: AtomicU64::new(1),
            profile: std::sync::OnceLock::new(),
            holds: holds.clone(),
            grid: Default::default(),
            records: Default::default(),
            status_json: std::sync::Mutex::new(StatusJson {
                status: status_rx.clone(),
                run: run_rx.clone(),
                json: None,
            }),
        });
        let task_store = store.clone();
        let task = actor::Task {
            id: row.id,
            lanes,
            unavailable,
            store,
            bus: bus.clone(),
            programs_dir: opts.programs_dir.clone(),
            max_program_segments: opts.max_program_segments,
            status: status_tx,
            row: row_tx,
            run: run_tx,
            gate,
            job: job_tx,
            launched: launched_tx,
            probe_ended: probe_tx,
            pending: Default::default(),
            unstored: unstored::Marker::start(&opts.unstored_dir, row.id),
            urgent: Arc::new(tokio::sync::Mutex::new(urgent_rx)),
            loading: None,
            held_before_start: None,
            holds,
        };
        tokio::spawn(task.run(rx, events));
        tokio::spawn(status_loop(m.clone(), bus.clone(), opts.status_interval));
        tokio::spawn(counters::track(m.clone(), task_store, bus));
        let (reply, done) = oneshot::channel();
        if m.tx.send(Msg::Restore { reply }).is_ok() {
            let _ = done.await;
        }
        m
    }

    pub fn row(&self) -> MachineRow {
        self.row.borrow().clone()
    }

    /// The last status the backend reported; `unresponsive` (with the reason) while a call into
    /// it is overdue.
    pub fn status(&self) -> MachineStatus {
        let mut s = self.status.borrow().clone();
        if let Some(why) = self.unresponsive() {
            s.state = MachineState::Unresponsive;
            s.reason = Some(why);
        }
        self.holds.explain(&mut s);
        s
    }

    pub fn unresponsive(&self) -> Option<String> {
        self.lanes.as_ref().and_then(|l| l.unresponsive())
    }

    pub fn unavailable_reason(&self) -> Option<&str> {
        self.unavailable.as_deref()
    }

    /// The current run, if any.
    /// The status as the API, the `status` event and the MQTT bridge show it: the backend's
    /// status, the machine id and the active run's progress.
    pub fn status_view(&self) -> StatusView {
        let status = self.status();
        let job = self
            .run
            .borrow()
            .as_ref()
            .map(|r| r.progress(status.feed_override, status.rapid_override));
        StatusView {
            status,
            machine: self.id,
            job,
        }
    }

    /// [`Machine::status_view`] as JSON, serialised once per change of the status or the run
    /// and shared by every poll until the next one. Not cached while the backend is unresponsive
    /// or the machine holds: those views also depend on the call lanes' clock and on the host's
    /// holds (`holds::HostHolds::explain`, which reads the database's health), which publish no
    /// change of their own.
    pub fn status_json(&self) -> Result<bytes::Bytes> {
        if self.unresponsive().is_none() {
            let mut c = self
                .status_json
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner);
            // An error: the task ended (shutdown); the last values are still read.
            let changed =
                c.status.has_changed().unwrap_or(true) || c.run.has_changed().unwrap_or(true);
            if !changed {
                if let Some(json) = &c.json {
                    return Ok(json.clone());
                }
            }
            let status = c.status.borrow_and_update().clone();
            let job = c
                .run
                .borrow_and_update()
                .as_ref()
                .map(|r| r.progress(status.feed_override, status.rapid_override));
            if status.hold.is_none() {
                let view = StatusView {
                    status,
                    machine: self.id,
                    job,
                };
                let json = bytes::Bytes::from(serde_json::to_vec(&view).map_err(unserialisable)?);
                c.json = Some(json.clone());
                return Ok(json);
            }
            c.json = None;
        }
        Ok(bytes::Bytes::from(
            serde_json::to_vec(&self.status_view()).map_err(unserialisable)?,
        ))
    }

    pub fn run(&self) -> Option<RunView> {
        self.run.borrow().clone()
    }

    /// The job of the current run, if any (known without the database).
    pub fn current_job(&self) -> Option<JobRow> {
        self.job.borrow().clone()
    }

    /// The current run's row as it was launched, with the state and line the task has published
    /// since (known without the database, like [`Machine::current_job`]).
    pub fn current_run(&self) -> Option<RunRow> {
        current_row(self.run.borrow().as_ref(), &self.launched.borrow())
    }

    pub fn subscribe_status(&self) -> watch::Receiver<MachineStatus> {
        self.status.clone()
    }

    pub fn subscribe_run(&self) -> watch::Receiver<Option<RunView>> {
        self.run.clone()
    }

    async fn ask<T>(&self, make: impl FnOnce(Reply<T>) -> Msg) -> Result<T> {
        self.ask_on(&self.tx, make).await
    }

    async fn ask_on<T>(
        &self,
        channel: &mpsc::UnboundedSender<Msg>,
        make: impl FnOnce(Reply<T>) -> Msg,
    ) -> Result<T> {
        let (reply, answer) = oneshot::channel();
        channel
            .send(make(reply))
            .map_err(|_| Error::internal(format!("machine {} has stopped", self.id)))?;
        answer
            .await
            .map_err(|_| Error::internal(format!("machine {} dropped the request", self.id)))?
    }

    /// The gate stops and feed holds move: queued inputs (a pendant's) keep its ticket.
    pub(crate) fn gate(&self) -> &Arc<Gate> {
        &self.gate
    }

    /// Bounds-checks one jog against the machine's limits, sends it and records it.
    pub async fn jog(
        &self,
        axis: Axis,
        distance: f64,
        feed: Option<f64>,
        actor: &str,
    ) -> Result<()> {
        self.jog_ticketed(axis, distance, feed, actor, self.gate.ticket())
            .await
    }

    /// A jog asked for when the gate gave `ticket` (it waited in a queue since): refused with
    /// `stopped` if a stop or feed hold came after that.
    pub(crate) async fn jog_ticketed(
        &self,
        axis: Axis,
        distance: f64,
        feed: Option<f64>,
        actor: &str,
        ticket: u64,
    ) -> Result<()> {
        limits::check_jog(&self.row(), distance, feed)?;
        self.ask(|reply| Msg::Call {
            request: Request::Jog {
                axis,
                distance,
                feed,
            },
            actor: actor.into(),
            ticket,
            reply,
        })
        .await
        .map(drop)
    }

    /// One MDI line: checked like a program line, refused while a job runs.
    pub async fn mdi(&self, line: &str, actor: &str) -> Result<()> {
        self.mdi_ticketed(line, actor, self.gate.ticket()).await
    }

    /// An MDI line that waited in a queue since the gate gave `ticket` (see `jog_ticketed`).
    pub(crate) async fn mdi_ticketed(&self, line: &str, actor: &str, ticket: u64) -> Result<()> {
        limits::check_mdi_line(line)
            .map_err(|e| Error::invalid("invalid_gcode", format!("field `line`: {e}")))?;
        self.ask(|reply| Msg::Call {
            request: Request::Mdi { line: line.into() },
            actor: actor.into(),
            ticket,
            reply,
        })
        .await
        .map(drop)
    }

    /// One immediate command. Stop, feed hold and reset go straight to the backend's urgent
    /// lane (they overtake everything queued, and whatever motion request was waiting is not
    /// carried out); the rest are ordered by the task.
    pub async fn command(&self, command: Command, actor: &str) -> Result<Value> {
        if !command.is_urgent() {
            return self
                .command_ticketed(command, actor, self.gate.ticket())
                .await;
        }
        if matches!(command, Command::Stop | Command::FeedHold) {
            self.gate.overtake();
            self.deadman.release(None);
        }
        let answer = self.urgent(&Request::Command(command)).await?;
        self.bus
            .record_or_log(
                EventKind::MachineCommand,
                Some(self.id),
                Some(actor),
                json!(command),
            )
            .await;
        // The backend reports the run it stopped before it answers; let the task record that
        // (and refresh the status) before the caller hears "stopped". Bounded: a task stuck
        // in a hung call must not hold up the answer to a stop that already happened.
        self.settle().await;
        Ok(answer)
    }

    /// A command that is not urgent and waited in a queue since the gate gave `ticket` (see
    /// `jog_ticketed`).
    pub(crate) async fn command_ticketed(
        &self,
        command: Command,
        actor: &str,
        ticket: u64,
    ) -> Result<Value> {
        debug_assert!(!command.is_urgent());
        // Every caller (HTTP, MQTT, a pendant macro, the CLI) meets the machine's own range.
        if let Command::SetOverrides {
            feed,
            spindle,
            rapid,
        } = command
        {
            limits::OverrideLimits::of(&self.row()).check(feed, spindle, rapid)?;
        }
        self.ask(|reply| Msg::Call {
            request: Request::Command(command),
            actor: actor.into(),
            ticket,
            reply,
        })
        .await
    }

    /// A continuous jog: toward `positive` or negative `axis` at `feed`, at most the machine's
    /// `max_jog_mm`, for as long as [`Machine::jog_keepalive`] comes at least every
    /// [`deadman::DEADMAN`]; then cancelled as [`Machine::cancel_jogs`] does (recorded with the
    /// actor `deadman:<actor>`). One at a time per machine.
    pub async fn jog_continuous(
        self: &Arc<Self>,
        axis: Axis,
        positive: bool,
        feed: Option<f64>,
        actor: &str,
    ) -> Result<()> {
        let id = self.deadman.arm().ok_or_else(|| {
            Error::conflict(
                "machine_busy",
                format!(
                    "machine {} already jogs continuously: keep it alive or cancel it",
                    self.id
                ),
            )
        })?;
        let reach = self.row().max_jog_mm;
        let distance = if positive { reach } else { -reach };
        // Started and watched by a task of its own, not by the caller: a caller that goes away
        // mid-request (an HTTP client whose connection drops) must not leave a jog that nobody
        // watches. Its keep-alives then stop, and the watcher cancels the jog.
        let (m, actor) = (self.clone(), actor.to_string());
        let (started, answer) = oneshot::channel();
        tokio::spawn(async move {
            if let Err(e) = m.jog(axis, distance, feed, &actor).await {
                m.deadman.release(Some(id));
                let _ = started.send(Err(e));
                return;
            }
            // The task has seen the jog start: a state other than jogging from now on means it
            // ended. The deadline counts from here, not from before a slow backend took it.
            m.sync().await;
            m.deadman.feed();
            let _ = started.send(Ok(()));
            m.hold_continuous(id, &format!("deadman:{actor}")).await;
        });
        answer
            .await
            .unwrap_or_else(|_| Err(Error::internal("the continuous jog's task ended early")))
    }

    /// Watches continuous jog `id` until it ends by itself or misses its keep-alive.
    async fn hold_continuous(&self, id: u64, actor: &str) {
        while let Some(deadline) = self.deadman.deadline(id) {
            if self.status().state != MachineState::Jogging {
                break; // it went its whole way, or something else stopped it
            }
            if std::time::Instant::now() >= deadline {
                self.deadman.release(Some(id));
                if let Err(e) = self.cancel_jogs(actor).await {
                    tracing::error!(machine = self.id, error = %e, "the deadman could not stop a continuous jog");
                }
                return;
            }
            tokio::time::sleep_until(deadline.into()).await;
        }
        self.deadman.release(Some(id));
    }

    /// The keep-alive of a continuous jog; 409 `no_continuous_jog` once it has ended.
    pub fn jog_keepalive(&self) -> Result<()> {
        if self.deadman.feed() {
            return Ok(());
        }
        Err(Error::conflict(
            "no_continuous_jog",
            format!(
                "machine {} has no continuous jog under way (it ended, or missed a keep-alive)",
                self.id
            ),
        ))
    }

    /// Ends the jog under way and every jog still queued for it, from anyone (HTTP, MQTT, the
    /// CLI, pendants' wheel moves and macros): the gate moves first, so nothing queued before
    /// this starts afterwards, then a stop on the urgent lane, answered once the backend
    /// confirmed motion stopped. A running job is not a jog: refused with `machine_busy`
    /// (pause or cancel the job).
    pub async fn cancel_jogs(&self, actor: &str) -> Result<Value> {
        // During a tool-change hold the jog belongs to the held run: a feed hold ends it (and
        // the jogs queued behind it) and leaves the run held.
        let held = holds::in_tool_change(&self.status());
        if let (Some(_), true) = (self.run(), held) {
            self.gate.overtake();
            self.deadman.release(None);
            let was = self.status().state;
            self.urgent(&Request::Command(Command::FeedHold)).await?;
            self.bus
                .record_or_log(
                    EventKind::MachineJogCancel,
                    Some(self.id),
                    Some(actor),
                    json!({"state_before": was, "tool_change_hold": true}),
                )
                .await;
            self.settle().await;
            return Ok(json!({"stopped": was == MachineState::Jogging}));
        }
        if let Some(r) = self.run() {
            return Err(Error::conflict(
                "machine_busy",
                format!(
                    "machine {} is running job {} (run {}); a job is paused or cancelled, not \
                     jog-cancelled",
                    self.id, r.job_id, r.run_id
                ),
            ));
        }
        self.gate.overtake();
        self.deadman.release(None);
        let was = self.status().state;
        self.urgent(&Request::Command(Command::Stop)).await?;
        self.bus
            .record_or_log(
                EventKind::MachineJogCancel,
                Some(self.id),
                Some(actor),
                json!({"state_before": was}),
            )
            .await;
        // The status the caller sees next is the stopped one.
        self.settle().await;
        Ok(json!({"stopped": was.is_busy()}))
    }

    /// Records a part zero at `position` (machine coordinates) or, without one, where the
    /// machine stands now. Refused with `machine_moving` while it moves, like zeroing and
    /// offset changes.
    pub async fn record_part_zero(
        &self,
        position: Option<AxisValues>,
        source: &str,
        note: Option<&str>,
        actor: &str,
    ) -> Result<PartZeroRow> {
        self.ask(|reply| Msg::PartZero {
            position,
            source: source.into(),
            note: note.map(str::to_string),
            actor: actor.into(),
            reply,
        })
        .await
    }

    /// A call on the urgent lane, outside the task.
    async fn urgent(&self, request: &Request) -> Result<Value> {
        let lanes = self.lanes.as_ref().ok_or_else(|| {
            Error::from(BackendError::Unavailable(
                self.unavailable.clone().unwrap_or_default(),
            ))
        })?;
        Ok(lanes.call(request).await?)
    }

    pub async fn set_offset(
        &self,
        offset: WorkOffset,
        values: AxisValues,
        actor: &str,
    ) -> Result<()> {
        self.call(Request::SetOffset { offset, values }, actor)
            .await
            .map(drop)
    }

    /// Gives the backend the machine's tool table (see `Request::SetTools`): a tool measured
    /// during a tool-change hold applies to the run in progress.
    pub async fn set_tools(
        &self,
        tools: Vec<fresa_plugin_api::contract::ProgramTool>,
        actor: &str,
    ) -> Result<()> {
        self.call(Request::SetTools { tools }, actor)
            .await
            .map(drop)
    }

    /// After an urgent call: the backend reports the run it stopped before it answers; let the
    /// task record that (and refresh the status) before the caller hears "stopped". Bounded: a
    /// task stuck in a hung call must not hold up the answer to a stop that already happened.
    async fn settle(&self) {
        let (reply, done) = oneshot::channel();
        let refresh = Msg::Call {
            request: Request::Status,
            actor: String::new(),
            ticket: self.gate.ticket(),
            reply,
        };
        if self.tx.send(refresh).is_ok() {
            let bound = self.timeout.min(Duration::from_secs(2));
            let _ = tokio::time::timeout(bound, done).await;
        }
    }

    /// How this machine moves (its backend's `motion_profile`: rapid rate, acceleration,
    /// cornering), for the time estimate of programs uploaded for it. Asked once and kept (it
    /// is the backend's configuration); `None` when the backend has none (then kept too) or
    /// cannot answer now (asked again next time).
    pub async fn motion_profile(&self) -> Option<fresa_gcode::MotionProfile> {
        if let Some(p) = self.profile.get() {
            return *p;
        }
        let known = match self.call(Request::MotionProfile, "").await {
            Ok(v) => serde_json::from_value::<fresa_plugin_api::contract::MotionProfile>(v)
                .ok()
                .map(|p| fresa_gcode::MotionProfile {
                    rapid_mm_min: p.rapid_mm_min,
                    min_feed_mm_min: p.min_feed_mm_min,
                    max_feed_mm_min: p.max_feed_mm_min,
                    accel_mm_s2: p.accel_mm_s2,
                    corner_jump_mm_s: p.corner_jump_mm_s,
                    per_axis: p.per_axis,
                }),
            Err(e) if e.message.contains("unsupported") => None,
            Err(_) => return None,
        };
        *self.profile.get_or_init(|| known)
    }

    pub async fn artifact(&self, name: &str) -> Result<Value> {
        self.call(Request::GetArtifact { name: name.into() }, "")
            .await
    }

    /// An operation that does not start motion (no ticket to keep), through the task's one call
    /// path.
    async fn call(&self, request: Request, actor: &str) -> Result<Value> {
        let ticket = self.gate.ticket();
        self.ask(|reply| Msg::Call {
            request,
            actor: actor.into(),
            ticket,
            reply,
        })
        .await
    }

    pub async fn start_job(&self, job: JobRow, actor: &str) -> Result<RunRow> {
        self.start_job_with(job, None, None, actor).await
    }

    /// Starts the job from `from_line` (`None`: its first line): the machine is brought to the
    /// state and start point of that line first (see `crate::start_at`).
    pub async fn start_job_from(
        &self,
        job: JobRow,
        from_line: Option<u32>,
        actor: &str,
    ) -> Result<RunRow> {
        self.start_job_with(job, from_line, None, actor).await
    }

    /// [`Machine::start_job`] with height map `height_map` applied (issue 25).
    pub async fn start_job_mapped(
        &self,
        job: JobRow,
        height_map: Option<(i64, &Store)>,
        actor: &str,
    ) -> Result<RunRow> {
        self.start_job_with(job, None, height_map, actor).await
    }

    /// Starts the job from `from_line` (`None`: its first line) with height map `height_map`
    /// applied: refused before anything moves when the map does not fit the job (see
    /// [`heightmap::applied_for_job`]), and while a grid is being probed.
    pub async fn start_job_with(
        &self,
        job: JobRow,
        from_line: Option<u32>,
        height_map: Option<(i64, &Store)>,
        actor: &str,
    ) -> Result<RunRow> {
        if let Some(map) = self.grid.current() {
            return Err(Error::conflict(
                "machine_busy",
                format!("machine {} is probing height map {map}", self.id),
            ));
        }
        let ticket = self.gate.ticket();
        let height_map = match height_map {
            Some((id, store)) => {
                Some(heightmap::applied_for_job(store, &job, id, &self.status()).await?)
            }
            None => None,
        };
        self.ask(|reply| Msg::Start {
            job,
            actor: actor.into(),
            from_line,
            ticket,
            height_map,
            reply,
        })
        .await
    }

    /// Pauses the running job; served by the task ahead of ordinary messages (see `Msg::Pause`).
    pub async fn pause_job(&self, job_id: i64, actor: &str) -> Result<RunRow> {
        self.pause_job_because(job_id, actor, None).await
    }

    /// [`Machine::pause_job`] by the host itself, for `reason` (kind and message), which the
    /// hold then shows (e.g. `pendant_lost`).
    pub async fn pause_job_because(
        &self,
        job_id: i64,
        actor: &str,
        reason: Option<(fresa_plugin_api::contract::HoldKind, String)>,
    ) -> Result<RunRow> {
        self.ask_on(&self.urgent_tx, |reply| Msg::Pause {
            job_id,
            actor: actor.into(),
            reason,
            reply,
        })
        .await
    }

    /// `confirm_part_zero`: the operator accepts whatever part zero the controller reports
    /// now, instead of requiring the one the run started with. `confirm_line`: the last line
    /// that was executed, as the operator found it, for a run whose stored line may be behind.
    pub async fn resume_job(
        &self,
        job: JobRow,
        actor: &str,
        confirm_part_zero: bool,
        confirm_line: Option<i64>,
    ) -> Result<RunRow> {
        let ticket = self.gate.ticket();
        self.ask(|reply| Msg::Resume {
            job,
            actor: actor.into(),
            confirm_part_zero,
            confirm_line,
            ticket,
            reply,
        })
        .await
    }

    /// Cancels the job's run; served like [`Machine::pause_job`].
    pub async fn cancel_job(&self, job_id: i64, actor: &str) -> Result<RunRow> {
        self.ask_on(&self.urgent_tx, |reply| Msg::Cancel {
            job_id,
            actor: actor.into(),
            reply,
        })
        .await
    }

    /// Waits until everything sent to the task so far is handled.
    pub async fn sync(&self) {
        let (reply, done) = oneshot::channel();
        if self.tx.send(Msg::Sync { reply }).is_ok() {
            let _ = done.await;
        }
    }

    /// Shutdown, step one: no new motion from now on, whatever is queued.
    pub fn close_gate(&self) {
        self.gate.close();
    }

    /// Shutdown, step two: tell the backend to stop motion and close its links, on the urgent
    /// lane (it does not wait for the task or for a hung ordinary call).
    pub async fn shutdown_backend(&self) -> Result<()> {
        self.urgent(&Request::Shutdown).await.map(|_| ())
    }
}

/// The current run's row: its row at launch with the state and line published since (the task
/// and readers without the database derive it the same way).
fn current_row(view: Option<&RunView>, launched: &Option<RunRow>) -> Option<RunRow> {
    let view = view?;
    let mut row = launched.clone().filter(|r| r.id == view.run_id)?;
    row.state = view.state;
    row.last_line = row.last_line.max(view.line);
    Some(row)
}

/// Publishes status and job progress at most once per interval, and only when they changed.
/// Read-only: it changes nothing the task owns.
async fn status_loop(machine: Arc<Machine>, bus: EventBus, interval: Duration) {
    let mut last_sent: Option<StatusView> = None;
    let mut last_progress: Option<(i64, i64)> = None;
    let mut tick = tokio::time::interval(interval);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tick.tick().await;
        if machine.tx.is_closed() {
            return;
        }
        // The view as `GET /machines/{id}/status` shows it (job progress included), so the
        // last `status` event, the retained MQTT status and the API agree once it settles.
        let current = machine.status_view();
        // Read after the view: `announced` only ever turns true for a run, so a view taken
        // before it is still one whose `running` is on the bus by now.
        let announced = machine.run.borrow().as_ref().is_none_or(|r| r.announced);
        let progress = current
            .job
            .as_ref()
            .filter(|_| announced)
            .map(|j| (j.run, j.line));
        if last_sent.as_ref() != Some(&current) {
            bus.transient(EventKind::Status, Some(machine.id), json!(current));
        }
        if progress != last_progress {
            if let Some(p) = current.job.as_ref().filter(|_| announced) {
                bus.transient(EventKind::JobProgress, Some(machine.id), json!(p));
            }
            last_progress = progress;
        }
        last_sent = Some(current);
    }
}

fn unserialisable(e: serde_json::Error) -> Error {
    Error::internal(format!("cannot serialise the machine status: {e}"))
}

/// All live machines, by id. A plain lock, never held across an await: every status poll and
/// forwarding decision reads it, and a read is a few nanoseconds.
#[derive(Default)]
pub struct Machines {
    map: std::sync::RwLock<MachineMap>,
}

/// Hashed with foldhash rather than SipHash: a status poll looks a machine up twice, and SipHash
/// was about 300 of its instructions. SipHash defends a map against keys chosen to collide, but
/// only an admin adds machines here (a client's id only looks one up).
type MachineMap = HashMap<i64, Arc<Machine>, foldhash::fast::RandomState>;

impl Machines {
    fn read(&self) -> std::sync::RwLockReadGuard<'_, MachineMap> {
        self.map
            .read()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }
    fn write(&self) -> std::sync::RwLockWriteGuard<'_, MachineMap> {
        self.map
            .write()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }
    pub fn insert(&self, m: Arc<Machine>) {
        self.write().insert(m.id, m);
    }
    /// Machine `id` if this node drives it (the status shortcut in front of the HTTP router asks
    /// this on every poll).
    pub fn get(&self, id: i64) -> Option<Arc<Machine>> {
        self.read().get(&id).cloned()
    }
    /// Whether this node drives machine `id` (the forwarding layer asks this
    /// on every machine request).
    pub fn is_local(&self, id: i64) -> bool {
        self.read().contains_key(&id)
    }
    /// Forgets a machine (moved to another node); the caller stops its backend.
    pub fn remove(&self, id: i64) -> Option<Arc<Machine>> {
        self.write().remove(&id)
    }
    pub fn all(&self) -> Vec<Arc<Machine>> {
        let mut v: Vec<_> = self.read().values().cloned().collect();
        v.sort_by_key(|m| m.id);
        v
    }
}

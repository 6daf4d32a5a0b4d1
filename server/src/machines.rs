//! Live machines: one backend plugin instance each, the calls into it, and the task that turns
//! its events into persisted job progress, audit events and rate-limited status updates.

use crate::events::EventBus;
use crate::store::{MachineRow, Store};
use fresa_plugin_api::contract::{
    Command, Event, MachineState, MachineStatus, Request, RunOutcome,
};
use fresa_plugin_api::host::{CallError, HostSink, Instance, PluginLibrary};
use serde_json::{json, Value};
use std::collections::HashMap;
use std::sync::atomic::{AtomicI64, Ordering};
use std::sync::{Arc, Mutex as StdMutex};
use std::time::Duration;
use tokio::sync::{mpsc, watch, RwLock, Semaphore};

/// Why a call into a backend failed, in terms the API can report.
#[derive(Debug, thiserror::Error)]
pub enum BackendError {
    #[error("machine backend is not available: {0}")]
    Unavailable(String),
    #[error("machine backend did not answer within {0:?}")]
    Timeout(Duration),
    #[error("{0}")]
    Call(#[from] CallError),
}

/// The job run a machine is executing, so its events can be attributed.
#[derive(Debug, Clone, Copy)]
pub struct CurrentRun {
    pub run_id: i64,
    pub job_id: i64,
    pub total_lines: i64,
}

pub struct Machine {
    pub id: i64,
    row: StdMutex<MachineRow>,
    instance: Option<Arc<Instance>>,
    /// Why `instance` is missing (plugin not found, config rejected).
    unavailable: Option<String>,
    calls: Arc<Semaphore>,
    timeout: Duration,
    status: watch::Sender<MachineStatus>,
    pub current_run: StdMutex<Option<CurrentRun>>,
    /// Acknowledged line of the current run as last seen (for status and progress).
    pub acked_line: StdMutex<Option<(i64, i64)>>,
}

/// A backend instance created but not yet attached to a machine.
pub struct Prepared {
    instance: Instance,
    events: mpsc::UnboundedReceiver<Value>,
    machine_id: Arc<AtomicI64>,
}

struct Sink {
    tx: mpsc::UnboundedSender<Value>,
    /// Set once the machine row exists; 0 while the config is being checked.
    machine_id: Arc<AtomicI64>,
}

impl HostSink for Sink {
    fn event(&self, event: Value) {
        // Unbounded on purpose: a plugin thread must never block on the host, and every
        // line acknowledgement matters. The consumer drains in batches.
        let _ = self.tx.send(event);
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

pub struct MachineOptions {
    pub timeout: Duration,
    pub max_concurrent_calls: usize,
    pub status_interval: Duration,
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

    /// Starts the machine for `row`. Never fails: a machine whose backend could not be created
    /// is kept, offline with the reason, so the operator sees it and can fix the config.
    pub fn start(
        row: MachineRow,
        backend: Result<Prepared, String>,
        store: Store,
        bus: EventBus,
        opts: &MachineOptions,
    ) -> Arc<Machine> {
        let (instance, events, unavailable) = match backend {
            Ok(p) => {
                p.machine_id.store(row.id, Ordering::Relaxed);
                (Some(Arc::new(p.instance)), p.events, None)
            }
            Err(reason) => (None, mpsc::unbounded_channel().1, Some(reason)),
        };
        let status = MachineStatus {
            state: MachineState::Offline,
            reason: unavailable.clone(),
            ..Default::default()
        };
        let (status_tx, _) = watch::channel(status);
        let m = Arc::new(Machine {
            id: row.id,
            row: StdMutex::new(row),
            instance,
            unavailable,
            calls: Arc::new(Semaphore::new(opts.max_concurrent_calls)),
            timeout: opts.timeout,
            status: status_tx,
            current_run: StdMutex::new(None),
            acked_line: StdMutex::new(None),
        });
        tokio::spawn(event_loop(m.clone(), events, store, bus.clone()));
        tokio::spawn(status_loop(m.clone(), bus, opts.status_interval));
        m
    }

    pub fn row(&self) -> MachineRow {
        self.row
            .lock()
            .map(|r| r.clone())
            .unwrap_or_else(|p| p.into_inner().clone())
    }

    pub fn set_row(&self, row: MachineRow) {
        if let Ok(mut r) = self.row.lock() {
            *r = row;
        }
    }

    pub fn status(&self) -> MachineStatus {
        self.status.borrow().clone()
    }

    pub fn subscribe_status(&self) -> watch::Receiver<MachineStatus> {
        self.status.subscribe()
    }

    pub fn unavailable_reason(&self) -> Option<&str> {
        self.unavailable.as_deref()
    }

    /// Calls the backend off the async runtime, bounded by the per-machine semaphore and a
    /// timeout. Urgent commands (stop, feed hold, reset) skip the queue: they must overtake it.
    pub async fn call(&self, request: &Request) -> Result<Value, BackendError> {
        let instance = self.instance.clone().ok_or_else(|| {
            BackendError::Unavailable(self.unavailable.clone().unwrap_or_default())
        })?;
        let urgent = matches!(request, Request::Command(c) if c.is_urgent())
            || matches!(request, Request::Shutdown);
        let _permit = if urgent {
            None
        } else {
            match tokio::time::timeout(self.timeout, self.calls.clone().acquire_owned()).await {
                Ok(Ok(p)) => Some(p),
                Ok(Err(_)) => {
                    return Err(BackendError::Unavailable("machine is shutting down".into()))
                }
                Err(_) => return Err(BackendError::Timeout(self.timeout)),
            }
        };
        let req = serde_json::to_value(request).map_err(|e| CallError::Protocol(e.to_string()))?;
        let task = tokio::task::spawn_blocking(move || instance.call(&req));
        match tokio::time::timeout(self.timeout, task).await {
            Ok(Ok(result)) => Ok(result?),
            Ok(Err(join)) => Err(BackendError::Call(CallError::Panic(join.to_string()))),
            Err(_) => Err(BackendError::Timeout(self.timeout)),
        }
    }

    /// Asks the backend for a fresh status and publishes it.
    pub async fn refresh_status(&self, req: Request) -> Result<MachineStatus, BackendError> {
        let v = self.call(&req).await?;
        let s: MachineStatus = serde_json::from_value(v)
            .map_err(|e| CallError::Protocol(format!("status has an unexpected shape: {e}")))?;
        self.status.send_replace(s.clone());
        Ok(s)
    }

    pub fn set_current_run(&self, run: Option<CurrentRun>) {
        if let Ok(mut r) = self.current_run.lock() {
            *r = run;
        }
    }

    pub fn current_run(&self) -> Option<CurrentRun> {
        self.current_run.lock().ok().and_then(|r| *r)
    }

    /// The last acknowledged line of run `run_id` (0 when none or another run's).
    pub fn acked_line_of(&self, run_id: i64) -> i64 {
        self.acked_line
            .lock()
            .ok()
            .and_then(|a| *a)
            .filter(|(run, _)| *run == run_id)
            .map(|(_, l)| l)
            .unwrap_or(0)
    }
}

/// Persists what the backend reports. Line acknowledgements are coalesced: everything queued is
/// drained first and only the highest line per run is written, in one transaction.
async fn event_loop(
    machine: Arc<Machine>,
    mut rx: mpsc::UnboundedReceiver<Value>,
    store: Store,
    bus: EventBus,
) {
    let id = machine.id;
    let mut batch = Vec::new();
    while rx.recv_many(&mut batch, 1024).await > 0 {
        let mut acks: HashMap<i64, u32> = HashMap::new();
        for raw in batch.drain(..) {
            let event: Event = match serde_json::from_value(raw.clone()) {
                Ok(e) => e,
                Err(e) => {
                    tracing::warn!(machine = id, error = %e, event = %raw, "unknown backend event; ignored");
                    continue;
                }
            };
            match event {
                Event::Status(s) => {
                    machine.status.send_replace(s);
                }
                Event::LineAcknowledged { run, line } => {
                    let e = acks.entry(run).or_insert(line);
                    *e = (*e).max(line);
                }
                Event::StateChanged { from, to } => {
                    machine.status.send_modify(|s| s.state = to);
                    bus.transient("machine.state", Some(id), json!({"from": from, "to": to}));
                }
                Event::Alarm { message } => {
                    bus.record_or_log(
                        "machine.alarm",
                        Some(id),
                        None,
                        json!({ "message": message }),
                    )
                    .await;
                }
                Event::RunEnded {
                    run,
                    outcome,
                    message,
                } => {
                    flush_acks(&machine, &store, &mut acks).await;
                    let to = match outcome {
                        RunOutcome::Completed => "completed",
                        RunOutcome::Failed => "failed",
                        RunOutcome::Cancelled => "cancelled",
                    };
                    crate::jobs::finish_run(&machine, &store, &bus, run, to, message.as_deref())
                        .await;
                }
                Event::LineReport {
                    run,
                    line,
                    max_deviation_mm,
                    percent,
                    remaining_s,
                } => {
                    // Transient like job.progress: one per line is too many for the audit log,
                    // and the next report supersedes it for the monitor.
                    let job = machine
                        .current_run()
                        .filter(|c| c.run_id == run)
                        .map(|c| c.job_id);
                    bus.transient(
                        "job.line_report",
                        Some(id),
                        json!({"job": job, "run": run, "line": line,
                               "max_deviation_mm": max_deviation_mm,
                               "percent": percent, "remaining_s": remaining_s}),
                    );
                }
                Event::PartZeroReported { values, run } => {
                    record_reported_part_zero(&machine, &store, &bus, values, run).await;
                }
            }
        }
        flush_acks(&machine, &store, &mut acks).await;
    }
}

/// A controller's own part zero joins the history (source `robot`) when it differs from the
/// latest record, so repeated reports of the same zero do not flood it.
async fn record_reported_part_zero(
    machine: &Machine,
    store: &Store,
    bus: &EventBus,
    values: fresa_plugin_api::contract::AxisValues,
    run: Option<i64>,
) {
    const SAME_MM: f64 = 1e-6;
    match store.latest_part_zero(machine.id).await {
        Ok(Some(last))
            if last.source == "robot"
                && [
                    last.x - values.x,
                    last.y - values.y,
                    last.z - values.z,
                    last.a - values.a,
                ]
                .iter()
                .all(|d| d.abs() <= SAME_MM) =>
        {
            return;
        }
        Ok(_) => {}
        Err(e) => {
            tracing::error!(machine = machine.id, error = %e, "could not read the part-zero history");
            return;
        }
    }
    let note = run.map(|r| format!("reported by the controller at the start of run {r}"));
    match store
        .insert_part_zero(machine.id, values, "robot", "robot", note.as_deref())
        .await
    {
        Ok(row) => {
            bus.record_or_log(
                "machine.part_zero",
                Some(machine.id),
                Some("robot"),
                json!(row),
            )
            .await
        }
        Err(e) => {
            tracing::error!(machine = machine.id, error = %e, "could not store the reported part zero")
        }
    }
}

async fn flush_acks(machine: &Machine, store: &Store, acks: &mut HashMap<i64, u32>) {
    for (run, line) in acks.drain() {
        if let Err(e) = store.ack_line(run, line as i64).await {
            tracing::error!(machine = machine.id, run, line, error = %e, "could not persist acknowledged line");
            continue;
        }
        if let Ok(mut a) = machine.acked_line.lock() {
            *a = Some((run, line as i64));
        }
    }
}

/// Publishes status and job progress at most once per interval, and only when they changed.
async fn status_loop(machine: Arc<Machine>, bus: EventBus, interval: Duration) {
    let mut rx = machine.subscribe_status();
    let mut last_sent: Option<MachineStatus> = None;
    let mut last_progress: Option<(i64, i64)> = None;
    let mut tick = tokio::time::interval(interval);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tick.tick().await;
        let current = rx.borrow_and_update().clone();
        if last_sent.as_ref() != Some(&current) {
            bus.transient("status", Some(machine.id), json!(current));
            last_sent = Some(current);
        }
        let acked = machine.acked_line.lock().ok().and_then(|a| *a);
        if acked != last_progress {
            if let (Some((run, line)), Some(cur)) = (acked, machine.current_run()) {
                if cur.run_id == run {
                    bus.transient("job.progress", Some(machine.id), progress_json(&cur, line));
                }
            }
            last_progress = acked;
        }
    }
}

pub fn progress_json(run: &CurrentRun, line: i64) -> Value {
    let percent = if run.total_lines > 0 {
        (line as f64 / run.total_lines as f64 * 100.0).min(100.0)
    } else {
        0.0
    };
    json!({"job": run.job_id, "run": run.run_id, "line": line, "total_lines": run.total_lines,
           "percent": (percent * 10.0).round() / 10.0})
}

/// All live machines, by id.
#[derive(Default)]
pub struct Machines {
    map: RwLock<HashMap<i64, Arc<Machine>>>,
}

impl Machines {
    pub async fn insert(&self, m: Arc<Machine>) {
        self.map.write().await.insert(m.id, m);
    }
    pub async fn get(&self, id: i64) -> Option<Arc<Machine>> {
        self.map.read().await.get(&id).cloned()
    }
    pub async fn all(&self) -> Vec<Arc<Machine>> {
        let mut v: Vec<_> = self.map.read().await.values().cloned().collect();
        v.sort_by_key(|m| m.id);
        v
    }
}

/// Brings a freshly started machine to the state the store remembers: offsets, active offset.
pub async fn restore_state(m: &Machine, store: &Store) {
    if m.instance.is_none() {
        return;
    }
    match m.refresh_status(Request::Connect).await {
        Ok(_) => {}
        Err(e) => {
            tracing::warn!(machine = m.id, error = %e, "connect failed");
            m.status.send_modify(|s| {
                s.state = MachineState::Offline;
                s.reason = Some(e.to_string());
            });
            return;
        }
    }
    if let Ok(offsets) = store.offsets(m.id).await {
        for (offset, values) in offsets {
            if let Err(e) = m.call(&Request::SetOffset { offset, values }).await {
                tracing::warn!(machine = m.id, offset = offset.name(), error = %e, "could not restore work offset");
            }
        }
    }
    let row = m.row();
    if let Some(o) = fresa_plugin_api::contract::WorkOffset::parse(&row.active_offset) {
        let _ = m
            .call(&Request::Command(Command::SelectOffset { offset: o }))
            .await;
    }
    let _ = m.refresh_status(Request::Status).await;
}

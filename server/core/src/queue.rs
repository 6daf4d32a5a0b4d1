//! Job queues per machine (issue 28): N parts of a job run one after another, with an
//! operator's confirmation ("next part loaded") before each part when `confirm_between`.
//!
//! A machine's queue is in one of four states, stored (migration 0014) so a restart or a move
//! to another node finds it as it was:
//! * `idle`: nothing to run;
//! * `waiting_confirm`: the next part waits for `confirm` (the pendant's START does the same).
//!   The first part of a queue always waits for a confirm, whatever `confirm_between` says: a
//!   machine never starts because a part was added to a list;
//! * `running`: a part runs (`run`); when it completes the next part waits for a confirm, or,
//!   with `confirm_between` false, starts at once;
//! * `held` (`reason`): a part was stopped, failed, was cancelled or interrupted (a restart), or
//!   an automatic start was refused. Nothing starts until an operator releases it; the part
//!   that did not complete is not counted, so after `release` it waits for a confirm again.
//!
//! Each entry is `count` parts of one job with a `done` counter; it leaves the queue when its
//! last part completed. Starting a part is `jobs::start`, the path of `POST /jobs/{id}/start`.
//! The machine's node watches its runs (`spawn_runner`): `job.state` events wake it, and it
//! also looks once a second, so a missed event only delays the next step.

use crate::app::{App, SharedApp};
use crate::error::{Error, Result};
use crate::events::EventKind;
pub use crate::queue_state::{Queues, Summary};
use crate::store::{QueueEntryRow, QueueStateRow, RunState};
use fresa_plugin_api::contract::MachineState;
use serde::Serialize;
use serde_json::json;
use std::sync::Arc;
use std::time::Duration;

/// Most entries one machine's queue holds.
pub const MAX_ENTRIES: usize = 100;
/// Most parts one entry may ask for.
pub const MAX_COUNT: i64 = 10_000;
/// Most machines one dispatch may name.
pub const MAX_DISPATCH_MACHINES: usize = 64;

/// One entry as the API shows it.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct EntryView {
    pub id: i64,
    pub job: i64,
    pub position: i64,
    pub count: i64,
    pub done: i64,
    pub confirm_between: bool,
    /// `running`, `waiting_confirm` or `held` for the entry whose part is next or under way,
    /// `queued` for the others.
    pub state: String,
    pub created_by: String,
    /// Milliseconds since the Unix epoch.
    pub created_at: i64,
}

/// A machine's queue as the API shows it.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct QueueView {
    pub machine: i64,
    /// `idle`, `waiting_confirm`, `running` or `held`.
    pub state: String,
    /// Why it holds.
    pub reason: Option<String>,
    /// The entry whose part runs, waits or held the queue.
    pub entry: Option<i64>,
    /// The run of the part under way (or that held the queue).
    pub run: Option<i64>,
    /// In queue order.
    pub entries: Vec<EntryView>,
}

/// A part started (by a confirm, or a dispatch).
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct Started {
    pub machine: i64,
    pub job: i64,
    pub run: i64,
    pub entry: Option<i64>,
}

struct Current {
    state: String,
    reason: Option<String>,
    entry: Option<i64>,
    run: Option<i64>,
}

fn current(row: Option<QueueStateRow>) -> Current {
    match row {
        Some(r) => Current {
            state: r.state,
            reason: r.reason,
            entry: r.entry_id,
            run: r.run_id,
        },
        None => Current {
            state: "idle".into(),
            reason: None,
            entry: None,
            run: None,
        },
    }
}

/// The machine, known to the store (any node's), or `unknown_machine`.
async fn check_machine(app: &App, machine: i64) -> Result<()> {
    match app.store.health().read(app.store.machine(machine)).await? {
        Some(_) => Ok(()),
        None => Err(Error::not_found(
            "unknown_machine",
            format!("no machine with id {machine}"),
        )),
    }
}

async fn load(app: &App, machine: i64) -> Result<(Current, Vec<QueueEntryRow>)> {
    let health = app.store.health();
    let state = current(health.read(app.store.queue_state(machine)).await?);
    let entries = health.read(app.store.queue_entries(machine)).await?;
    Ok((state, entries))
}

fn view(machine: i64, cur: &Current, entries: &[QueueEntryRow]) -> QueueView {
    let focus = match cur.state.as_str() {
        "running" | "held" => cur.entry,
        "waiting_confirm" => entries.first().map(|e| e.id),
        _ => None,
    };
    QueueView {
        machine,
        state: cur.state.clone(),
        reason: cur.reason.clone(),
        entry: focus,
        run: cur.run,
        entries: entries
            .iter()
            .map(|e| EntryView {
                id: e.id,
                job: e.job_id,
                position: e.position,
                count: e.count,
                done: e.done,
                confirm_between: e.confirm_between != 0,
                state: if Some(e.id) == focus {
                    cur.state.clone()
                } else {
                    "queued".into()
                },
                created_by: e.created_by.clone(),
                created_at: e.created_at,
            })
            .collect(),
    }
}

fn summary_of(cur: &Current, entries: &[QueueEntryRow]) -> Summary {
    let part = match cur.state.as_str() {
        "waiting_confirm" => entries.first().map(|e| (e.done + 1, e.count)),
        _ => None,
    };
    Summary {
        state: cur.state.clone(),
        part,
    }
}

/// Stores the new state and remembers it for the LCD.
async fn set(
    app: &App,
    machine: i64,
    state: &str,
    reason: Option<&str>,
    entry: Option<i64>,
    run: Option<i64>,
) -> Result<()> {
    app.store
        .health()
        .guard(
            app.store
                .set_queue_state(machine, state, reason, entry, run),
        )
        .await?;
    let entries = app.store.queue_entries(machine).await.unwrap_or_default();
    let cur = Current {
        state: state.into(),
        reason: reason.map(str::to_string),
        entry,
        run,
    };
    app.queues.note(machine, summary_of(&cur, &entries));
    Ok(())
}

/// `GET /machines/{id}/queue`.
pub async fn get(app: &App, machine: i64) -> Result<QueueView> {
    check_machine(app, machine).await?;
    let (cur, entries) = load(app, machine).await?;
    Ok(view(machine, &cur, &entries))
}

/// Adds `count` parts of `job` (a job of this machine) at the end of the queue. An idle queue
/// then waits for a confirm for its first part.
pub async fn add(
    app: &App,
    machine: i64,
    job_id: i64,
    count: i64,
    confirm_between: bool,
    actor: &str,
) -> Result<QueueView> {
    check_machine(app, machine).await?;
    if !(1..=MAX_COUNT).contains(&count) {
        return Err(Error::invalid(
            "invalid_field",
            format!("field `count` must be 1 to {MAX_COUNT}, got {count}"),
        ));
    }
    let job = crate::jobs::job(app, job_id).await?;
    if job.machine_id != machine {
        return Err(Error::invalid(
            "invalid_field",
            format!(
                "field `job`: job {job_id} belongs to machine {}, not {machine} (upload it for \
                 this machine, or use POST /queue to give it to a free machine)",
                job.machine_id
            ),
        ));
    }
    let _guard = app.queues.lock(machine).await;
    let (cur, entries) = load(app, machine).await?;
    if entries.len() >= MAX_ENTRIES {
        return Err(Error::conflict(
            "queue_full",
            format!("machine {machine}'s queue already holds {MAX_ENTRIES} entries"),
        ));
    }
    let health = app.store.health();
    let entry = health
        .guard(
            app.store
                .insert_queue_entry(machine, job_id, count, confirm_between, actor),
        )
        .await?;
    app.bus
        .record_or_log(
            EventKind::QueueAdd,
            Some(machine),
            Some(actor),
            json!({"machine": machine, "entry": entry, "job": job_id, "count": count, "confirm_between": confirm_between}),
        )
        .await;
    if cur.state == "idle" {
        set(app, machine, "waiting_confirm", None, None, None).await?;
        waiting_event(app, machine, None).await;
    }
    let (cur, entries) = load(app, machine).await?;
    Ok(view(machine, &cur, &entries))
}

async fn waiting_event(app: &App, machine: i64, actor: Option<&str>) {
    let next = app
        .store
        .queue_entries(machine)
        .await
        .ok()
        .and_then(|e| e.into_iter().next());
    let data = match next {
        Some(e) => {
            json!({"machine": machine, "entry": e.id, "job": e.job_id, "part": e.done + 1, "count": e.count})
        }
        None => json!({"machine": machine}),
    };
    app.bus
        .record_or_log(EventKind::QueueWaiting, Some(machine), actor, data)
        .await;
}

fn unknown_entry(machine: i64, entry: i64) -> Error {
    Error::not_found(
        "unknown_queue_entry",
        format!("machine {machine}'s queue has no entry {entry}"),
    )
}

/// Removes an entry; not the one whose part is running (stop or cancel that run first).
pub async fn remove(app: &App, machine: i64, entry: i64, actor: &str) -> Result<QueueView> {
    check_machine(app, machine).await?;
    let _guard = app.queues.lock(machine).await;
    let (cur, _) = load(app, machine).await?;
    if cur.state == "running" && cur.entry == Some(entry) {
        return Err(Error::conflict(
            "queue_entry_running",
            format!(
                "entry {entry} has a part running (run {}); stop or cancel it first",
                cur.run.unwrap_or_default()
            ),
        ));
    }
    let health = app.store.health();
    if !health
        .guard(app.store.delete_queue_entry(machine, entry))
        .await?
    {
        return Err(unknown_entry(machine, entry));
    }
    app.bus
        .record_or_log(
            EventKind::QueueRemove,
            Some(machine),
            Some(actor),
            json!({"machine": machine, "entry": entry}),
        )
        .await;
    let (cur, entries) = load(app, machine).await?;
    if entries.is_empty() && cur.state == "waiting_confirm" {
        set(app, machine, "idle", None, None, None).await?;
        done_event(app, machine).await;
    } else {
        set(
            app,
            machine,
            &cur.state,
            cur.reason.as_deref(),
            cur.entry,
            cur.run,
        )
        .await?;
    }
    let (cur, entries) = load(app, machine).await?;
    Ok(view(machine, &cur, &entries))
}

/// Puts an entry at `position` (1-based; past the end: last).
pub async fn move_entry(
    app: &App,
    machine: i64,
    entry: i64,
    position: i64,
    actor: &str,
) -> Result<QueueView> {
    check_machine(app, machine).await?;
    if position < 1 {
        return Err(Error::invalid(
            "invalid_field",
            format!("field `position` is 1-based, got {position}"),
        ));
    }
    let _guard = app.queues.lock(machine).await;
    let health = app.store.health();
    if !health
        .guard(app.store.move_queue_entry(machine, entry, position))
        .await?
    {
        return Err(unknown_entry(machine, entry));
    }
    app.bus
        .record_or_log(
            EventKind::QueueMove,
            Some(machine),
            Some(actor),
            json!({"machine": machine, "entry": entry, "position": position}),
        )
        .await;
    let (cur, entries) = load(app, machine).await?;
    app.queues.note(machine, summary_of(&cur, &entries));
    Ok(view(machine, &cur, &entries))
}

/// "Next part loaded": starts the next part, through the same path as `POST /jobs/{id}/start`.
/// A refused start leaves the queue waiting and answers the refusal.
pub async fn confirm(app: &App, machine: i64, actor: &str) -> Result<Started> {
    check_machine(app, machine).await?;
    let _guard = app.queues.lock(machine).await;
    let (cur, entries) = load(app, machine).await?;
    if cur.state != "waiting_confirm" {
        return Err(not_waiting(machine, &cur));
    }
    let Some(next) = entries.first() else {
        return Err(not_waiting(machine, &cur));
    };
    let run = crate::jobs::start(app, next.job_id, actor).await?;
    set(app, machine, "running", None, Some(next.id), Some(run.id)).await?;
    app.bus
        .record_or_log(
            EventKind::QueueConfirm,
            Some(machine),
            Some(actor),
            json!({"machine": machine, "entry": next.id, "job": next.job_id, "run": run.id, "part": next.done + 1, "count": next.count}),
        )
        .await;
    Ok(Started {
        machine,
        job: next.job_id,
        run: run.id,
        entry: Some(next.id),
    })
}

fn not_waiting(machine: i64, cur: &Current) -> Error {
    let why = match cur.state.as_str() {
        "held" => format!(
            "it is held ({}); release it first",
            cur.reason.as_deref().unwrap_or("no reason recorded")
        ),
        "running" => format!("a part is running (run {})", cur.run.unwrap_or_default()),
        _ => "it has no parts".to_string(),
    };
    Error::conflict(
        "queue_not_waiting",
        format!("machine {machine}'s queue does not wait for a confirm: {why}"),
    )
}

/// Whether the machine's queue waits for a confirm (the pendant's START confirms then).
pub async fn waits_for_confirm(app: &App, machine: i64) -> bool {
    matches!(
        app.store.queue_state(machine).await,
        Ok(Some(r)) if r.state == "waiting_confirm"
    )
}

/// Ends a hold: a part still running goes on; otherwise the next part waits for a confirm.
pub async fn release(app: &App, machine: i64, actor: &str) -> Result<QueueView> {
    check_machine(app, machine).await?;
    let _guard = app.queues.lock(machine).await;
    let (cur, entries) = load(app, machine).await?;
    if cur.state != "held" {
        return Err(Error::conflict(
            "queue_not_held",
            format!("machine {machine}'s queue is {}, not held", cur.state),
        ));
    }
    let health = app.store.health();
    let active = match cur.run {
        Some(id) => health
            .read(app.store.run(id))
            .await?
            .is_some_and(|r| r.state.is_active()),
        None => false,
    };
    let to = if active {
        set(app, machine, "running", None, cur.entry, cur.run).await?;
        "running"
    } else if entries.is_empty() {
        set(app, machine, "idle", None, None, None).await?;
        "idle"
    } else {
        set(app, machine, "waiting_confirm", None, None, None).await?;
        "waiting_confirm"
    };
    app.bus
        .record_or_log(
            EventKind::QueueRelease,
            Some(machine),
            Some(actor),
            json!({"machine": machine, "reason": cur.reason, "state": to}),
        )
        .await;
    if to == "waiting_confirm" {
        waiting_event(app, machine, Some(actor)).await;
    }
    let (cur, entries) = load(app, machine).await?;
    Ok(view(machine, &cur, &entries))
}

async fn done_event(app: &App, machine: i64) {
    app.bus
        .record_or_log(
            EventKind::QueueDone,
            Some(machine),
            None,
            json!({"machine": machine}),
        )
        .await;
}

async fn hold(app: &App, machine: i64, reason: &str, entry: Option<i64>, run: Option<i64>) {
    if let Err(e) = set(app, machine, "held", Some(reason), entry, run).await {
        tracing::error!(machine, error = %e, "could not store the queue's hold");
    }
    app.bus
        .record_or_log(
            EventKind::QueueHold,
            Some(machine),
            None,
            json!({"machine": machine, "reason": reason, "entry": entry, "run": run}),
        )
        .await;
}

/// Watches the runs of the queues of this node's machines, and moves each queue on when its
/// part ended. The first pass (start-up) never starts a part: a part that completed while the
/// server was down leaves the next one waiting for a confirm.
pub fn spawn_runner(app: &SharedApp) {
    let weak = Arc::downgrade(app);
    let mut events = app.bus.subscribe();
    let stop = app.shutdown.clone();
    tokio::spawn(async move {
        let mut first = true;
        loop {
            let Some(app) = weak.upgrade() else { return };
            step(&app, first).await;
            drop(app);
            first = false;
            let tick = tokio::time::sleep(Duration::from_secs(1));
            tokio::pin!(tick);
            loop {
                tokio::select! {
                    _ = stop.cancelled() => return,
                    _ = &mut tick => break,
                    e = events.recv() => match e {
                        Ok(e) if e.is(EventKind::JobState) => break,
                        Ok(_) => {}
                        Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => break,
                        Err(tokio::sync::broadcast::error::RecvError::Closed) => return,
                    },
                }
            }
        }
    });
}

async fn step(app: &App, first: bool) {
    if !app.store.health().is_up() {
        return;
    }
    let states = match app.store.queue_states().await {
        Ok(s) => s,
        Err(e) => {
            tracing::debug!(error = %e, "queue runner: cannot read the queues");
            return;
        }
    };
    for row in states {
        let machine = row.machine_id;
        if !app.machines.is_local(machine) {
            continue;
        }
        // Only a running queue moves by itself; the others change through the API, which
        // notes their summary. The first pass notes every queue's, for the LCD.
        if row.state != "running" && !first {
            continue;
        }
        let _guard = app.queues.lock(machine).await;
        // Read again under the lock: an operator may have changed it meanwhile.
        let cur = match app.store.queue_state(machine).await {
            Ok(r) => current(r),
            Err(_) => continue,
        };
        if cur.state == "running" {
            if let Err(e) = advance(app, machine, &cur, first).await {
                tracing::warn!(machine, error = %e, "queue runner: cannot move the queue on");
            }
        }
        let entries = app.store.queue_entries(machine).await.unwrap_or_default();
        let cur = match app.store.queue_state(machine).await {
            Ok(r) => current(r),
            Err(_) => continue,
        };
        app.queues.note(machine, summary_of(&cur, &entries));
    }
}

/// A running queue whose part has ended: counted and on to the next part, or held.
async fn advance(app: &App, machine: i64, cur: &Current, first: bool) -> Result<()> {
    let run = match cur.run {
        Some(id) => app.store.run(id).await?,
        None => None,
    };
    let Some(run) = run else {
        hold(
            app,
            machine,
            "the part's run is not known",
            cur.entry,
            cur.run,
        )
        .await;
        return Ok(());
    };
    if run.state.is_active() {
        return Ok(());
    }
    if run.state != RunState::Completed {
        let message = run
            .message
            .as_deref()
            .map(|m| format!(": {m}"))
            .unwrap_or_default();
        let reason = format!(
            "run {} of job {} ended {}{message}",
            run.id,
            run.job_id,
            run.state.as_str()
        );
        hold(app, machine, &reason, cur.entry, cur.run).await;
        return Ok(());
    }
    if let Some(entry) = cur.entry {
        app.store.queue_part_done(entry).await?;
    }
    let entries = app.store.queue_entries(machine).await?;
    let Some(next) = entries.first() else {
        set(app, machine, "idle", None, None, None).await?;
        done_event(app, machine).await;
        return Ok(());
    };
    if next.confirm_between != 0 || first {
        set(app, machine, "waiting_confirm", None, None, None).await?;
        waiting_event(app, machine, None).await;
        return Ok(());
    }
    match crate::jobs::start(app, next.job_id, "queue").await {
        Ok(run) => {
            set(app, machine, "running", None, Some(next.id), Some(run.id)).await?;
            app.bus
                .record_or_log(
                    EventKind::QueueStarted,
                    Some(machine),
                    Some("queue"),
                    json!({"machine": machine, "entry": next.id, "job": next.job_id, "run": run.id, "part": next.done + 1, "count": next.count}),
                )
                .await;
        }
        Err(e) => {
            let reason = format!("the next part could not start: {} ({})", e.message, e.code);
            hold(app, machine, &reason, Some(next.id), None).await;
        }
    }
    Ok(())
}

/// Why a machine did not take a dispatched part.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct Refusal {
    pub machine: i64,
    pub code: String,
    pub message: String,
}

/// Starts a part of `job_id` on `machine` (of this node) if it is free: idle, no run, and its
/// queue idle. The job is the machine's own, or a copy of it made for this machine (same
/// program). The start is `jobs::start`'s, so the backend's whole-program check applies.
pub async fn take(app: &App, machine: i64, job_id: i64, actor: &str) -> Result<Started> {
    let m = app.machines.get(machine).ok_or_else(|| {
        Error::conflict(
            "machine_unavailable",
            format!("machine {machine} is not driven by this node"),
        )
    })?;
    let job = crate::jobs::job(app, job_id).await?;
    let _guard = app.queues.lock(machine).await;
    let (cur, entries) = load(app, machine).await?;
    if cur.state != "idle" || !entries.is_empty() {
        return Err(Error::conflict(
            "machine_busy",
            format!(
                "machine {machine}'s queue is {} with {} entries",
                cur.state,
                entries.len()
            ),
        ));
    }
    if let Some(r) = m.run() {
        return Err(Error::conflict(
            "machine_busy",
            format!(
                "machine {machine} is running job {} (run {})",
                r.job_id, r.run_id
            ),
        ));
    }
    let state = m.status().state;
    if state != MachineState::Idle {
        return Err(Error::conflict(
            "machine_busy",
            format!("machine {machine} is {}, not idle", state.as_str()),
        ));
    }
    let job_here = if job.machine_id == machine {
        job.id
    } else {
        copy_job(app, &job, machine, actor).await?
    };
    let run = crate::jobs::start(app, job_here, actor).await?;
    Ok(Started {
        machine,
        job: job_here,
        run: run.id,
        entry: None,
    })
}

/// The same program as a job of `machine`: the newest of its last 100 jobs with the same
/// program, or else a new job of that program (the file is shared by its hash) analysed for
/// this machine (its tool table, unsupported-word policy and motion profile: a program this
/// machine would refuse at upload is refused here too), so repeated dispatches do not pile up
/// copies.
async fn copy_job(app: &App, job: &crate::store::JobRow, machine: i64, actor: &str) -> Result<i64> {
    let health = app.store.health();
    let theirs = health.read(app.store.list_jobs(Some(machine), 100)).await?;
    if let Some(same) = theirs.iter().find(|j| j.sha256 == job.sha256) {
        return Ok(same.id);
    }
    let analysis = crate::jobs::analysis_for(app, &job.sha256, machine).await?;
    let id = app
        .store
        .health()
        .guard(app.store.insert_job(crate::store::NewJob {
            name: &job.name,
            machine_id: machine,
            sha256: &job.sha256,
            size_bytes: job.size_bytes,
            line_count: job.line_count,
            analysis: analysis.map(|a| a.to_string()),
            source: "dispatch",
        }))
        .await?;
    app.bus
        .record_or_log(
            EventKind::JobCreated,
            Some(machine),
            Some(actor),
            json!({"job": id, "name": job.name, "sha256": job.sha256, "lines": job.line_count, "bytes": job.size_bytes, "source": "dispatch", "copy_of": job.id}),
        )
        .await;
    Ok(id)
}

/// The dispatch's audit event.
pub async fn record_dispatch(
    app: &App,
    job: i64,
    started: Option<&Started>,
    refused: &[Refusal],
    actor: &str,
) {
    app.bus
        .record_or_log(
            EventKind::QueueDispatch,
            started.map(|s| s.machine),
            Some(actor),
            json!({"job": job, "machine": started.map(|s| s.machine), "run": started.map(|s| s.run), "started_job": started.map(|s| s.job), "refused": refused}),
        )
        .await;
}

//! Pendants: one `pendant_transport` plugin instance per configured pendant. The plugin reports
//! what the operator did; this module routes it to the bound machine through the same calls the
//! HTTP API uses (bounded jogs, commands, job control, the one upload path), records every
//! action in the event log as `pendant:<id>`, and pushes the status cache the plugin answers the
//! pendant's polls from.

use crate::app::App;
use crate::error::{Error, ErrorKind};
use crate::machine::Machine;
use crate::store::{MacroAction, PendantRow, RunState};
use fresa_plugin_api::contract::{
    Axis, Command, MachineState, PendantEvent, PendantJob, PendantKey, PendantRequest,
};
use fresa_plugin_api::host::Instance;
use serde_json::{json, Value};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex as StdMutex};
use std::time::{Duration, Instant};
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;

/// The plugin that speaks the MPG pendants' protocol.
pub const TRANSPORT_PLUGIN: &str = "mpg-pendant";
/// How often the status cache is refreshed (only changes are pushed).
const STATUS_PUSH: Duration = Duration::from_millis(50);

/// Settings the core reads from a pendant's `config` (the rest goes to the transport plugin).
const CORE_KEYS: [&str; 1] = ["stop_program_on_lost"];

pub mod registry;
use registry::{lock, Sink};
pub use registry::{Pendant, Pendants};

/// Pendants announced on the LAN by mDNS, each marked with the configured pendant (if any)
/// that uses its address. The browser starts on the first call, so a fresh list fills in
/// over the next second or two.
pub async fn discovered(app: &App) -> Result<Value, Error> {
    let inst = {
        let mut d = app.pendants.discovery.lock().await;
        match d.as_ref() {
            Some(i) => i.clone(),
            None => {
                let lib = app.plugins.get(TRANSPORT_PLUGIN).ok_or_else(|| {
                    Error::conflict(
                        "plugin_missing",
                        format!("no plugin named {TRANSPORT_PLUGIN:?} is loaded"),
                    )
                })?;
                let (tx, _) = mpsc::unbounded_channel();
                let sink = Arc::new(Sink { tx, id: 0 });
                let lib = lib.clone();
                let i = tokio::task::spawn_blocking(move || {
                    lib.create(&json!({"discover": true}), sink)
                })
                .await
                .map_err(|e| Error::internal(e.to_string()))?
                .map_err(|e| {
                    Error::new(ErrorKind::Unavailable, "mdns_unavailable", e.to_string())
                })?;
                let i = Arc::new(i);
                *d = Some(i.clone());
                i
            }
        }
    };
    let req = json!(PendantRequest::Discovered);
    let mut v = tokio::task::spawn_blocking(move || inst.call(&req))
        .await
        .map_err(|e| Error::internal(e.to_string()))?
        .map_err(|e| Error::internal(e.to_string()))?;
    let configured: Vec<(String, i64)> = app
        .pendants
        .all()
        .await
        .iter()
        .map(|p| {
            let r = p.row();
            (r.address.to_ascii_lowercase(), r.id)
        })
        .collect();
    if let Some(list) = v["pendants"].as_array_mut() {
        for f in list {
            let addr = f["address"]
                .as_str()
                .unwrap_or_default()
                .to_ascii_lowercase();
            let id = configured
                .iter()
                .find(|(a, _)| *a == addr)
                .map(|(_, id)| *id);
            f["pendant"] = json!(id);
        }
    }
    Ok(v)
}

/// The transport config: the pendant's `config` minus the core's keys, plus address and dialect.
pub fn transport_config(row: &PendantRow) -> Value {
    let mut cfg = row.config_json();
    if let Some(o) = cfg.as_object_mut() {
        for k in CORE_KEYS {
            o.remove(k);
        }
        o.insert("address".into(), json!(row.address));
        o.insert("dialect".into(), json!(row.dialect));
        o.insert("pendant".into(), json!(row.id));
    }
    cfg
}

type Created = (Instance, mpsc::UnboundedReceiver<Value>);

/// Creates the transport instance for `row`; it starts connecting at once. An error is the
/// plugin's verdict on the config (or the plugin is missing).
pub async fn create_instance(app: &App, row: &PendantRow) -> Result<Created, String> {
    let lib = app
        .plugins
        .get(TRANSPORT_PLUGIN)
        .ok_or_else(|| format!("no plugin named {TRANSPORT_PLUGIN:?} is loaded"))?
        .clone();
    let (tx, rx) = mpsc::unbounded_channel();
    let sink = Arc::new(Sink { tx, id: row.id });
    let config = transport_config(row);
    let instance = tokio::task::spawn_blocking(move || lib.create(&config, sink))
        .await
        .map_err(|e| format!("transport create failed: {e}"))?
        .map_err(|e| e.to_string())?;
    Ok((instance, rx))
}

/// Makes `row` live with its transport (or without one, keeping the reason so the operator
/// sees it), and starts the tasks that route its events and push its status cache.
pub async fn attach(
    app: &Arc<App>,
    row: PendantRow,
    created: Result<Created, String>,
) -> Arc<Pendant> {
    let macros = app.store.pendant_macros(row.id).await.unwrap_or_default();
    let (instance, rx, unavailable) = match created {
        Ok((i, rx)) => (Some(Arc::new(i)), rx, None),
        Err(e) => {
            tracing::error!(pendant = row.id, error = %e, "pendant transport not available");
            (None, mpsc::unbounded_channel().1, Some(e))
        }
    };
    let p = Arc::new(Pendant {
        id: row.id,
        row: StdMutex::new(row),
        instance: StdMutex::new(instance),
        unavailable,
        connected: AtomicBool::new(false),
        macros: StdMutex::new(macros),
        started_run: StdMutex::new(None),
        stop: CancellationToken::new(),
    });
    app.pendants.map.write().await.insert(p.id, p.clone());
    tokio::spawn(event_loop(app.clone(), p.clone(), rx));
    tokio::spawn(status_loop(app.clone(), p.clone()));
    p
}

/// Starts every stored pendant. A pendant whose transport cannot start is logged and skipped.
pub async fn start_all(app: &Arc<App>) {
    let rows = match app.store.list_pendants().await {
        Ok(r) => r,
        Err(e) => {
            tracing::error!(error = %e, "cannot list pendants");
            return;
        }
    };
    // Each node talks to its own pendants (the ones on its network).
    let me = app.settings.node.name.as_str();
    for row in rows.into_iter().filter(|r| r.node.as_deref() == Some(me)) {
        let created = create_instance(app, &row).await;
        attach(app, row, created).await;
    }
}

async fn event_loop(app: Arc<App>, p: Arc<Pendant>, mut rx: mpsc::UnboundedReceiver<Value>) {
    let mut batch = Vec::new();
    loop {
        let n = tokio::select! {
            _ = p.stop.cancelled() => return,
            _ = app.shutdown.cancelled() => return,
            n = rx.recv_many(&mut batch, 256) => n,
        };
        if n == 0 {
            return;
        }
        let events: Vec<PendantEvent> = batch
            .drain(..)
            .filter_map(|raw| match serde_json::from_value(raw.clone()) {
                Ok(e) => Some(e),
                Err(e) => {
                    tracing::warn!(pendant = p.id, error = %e, event = %raw, "unknown pendant event; ignored");
                    None
                }
            })
            .collect();
        // Motion asked for just before the link died is not started: nobody can stop it from
        // that pendant any more. Stop, pause and reset still go through.
        let lost_at = events
            .iter()
            .rposition(|e| matches!(e, PendantEvent::Lost { .. }));
        for (i, ev) in events.into_iter().enumerate() {
            if lost_at.is_some_and(|l| i < l) && starts_motion(&ev) {
                tracing::warn!(pendant = p.id, event = ?ev, "input dropped: the pendant was lost right after sending it");
                continue;
            }
            if matches!(ev, PendantEvent::Upload { .. }) {
                // Storing a long program takes a while; it must not delay a lost-pendant stop.
                let (app, p) = (app.clone(), p.clone());
                tokio::spawn(async move { handle(&app, &p, ev).await });
                continue;
            }
            handle(&app, &p, ev).await;
        }
    }
}

fn starts_motion(ev: &PendantEvent) -> bool {
    match ev {
        PendantEvent::Jog { .. } => true,
        PendantEvent::Key { key } => !matches!(
            key,
            PendantKey::Stop | PendantKey::Pause | PendantKey::Reset
        ),
        _ => false,
    }
}

async fn bound_machine(app: &App, p: &Pendant) -> Option<Arc<Machine>> {
    let id = p.row().machine_id?;
    app.machines.get(id).await
}

/// Records that pendant input did nothing, and why.
async fn refuse(
    app: &App,
    p: &Pendant,
    machine: Option<i64>,
    input: Value,
    code: &str,
    reason: &str,
) {
    tracing::warn!(pendant = p.id, %input, code, reason, "pendant input refused");
    app.bus
        .record_or_log(
            "pendant.refused",
            machine,
            Some(&p.actor()),
            json!({"pendant": p.id, "input": input, "code": code, "reason": reason}),
        )
        .await;
}

async fn handle(app: &Arc<App>, p: &Arc<Pendant>, ev: PendantEvent) {
    match ev {
        PendantEvent::Connected { address } => {
            p.connected.store(true, Ordering::Relaxed);
            let m = p.row().machine_id;
            app.bus
                .record_or_log(
                    "pendant.connected",
                    m,
                    Some(&p.actor()),
                    json!({"pendant": p.id, "address": address}),
                )
                .await;
        }
        PendantEvent::Lost { reason } => {
            p.connected.store(false, Ordering::Relaxed);
            let stopped = stop_motion_of_lost(app, p).await;
            let m = p.row().machine_id;
            app.bus
                .record_or_log(
                    "pendant.lost",
                    m,
                    Some(&p.actor()),
                    json!({"pendant": p.id, "reason": reason, "stopped": stopped}),
                )
                .await;
        }
        PendantEvent::Jog { axis, count, step } => {
            let input = json!({"jog": {"axis": axis, "count": count, "step": step}});
            let Some(m) = ready_machine(app, p, &input).await else {
                return;
            };
            let distance = count as f64 * step;
            app.pendants.last_mover_set(m.id, p.id);
            if let Err(e) = m.jog(axis, distance, None, &p.actor()).await {
                refuse(app, p, Some(m.id), input, e.code, &e.message).await;
            }
        }
        PendantEvent::Key { key } => key_pressed(app, p, key).await,
        PendantEvent::Upload {
            upload,
            lines,
            declared_lines,
            declared_chars,
        } => receive_upload(app, p, upload, lines, declared_lines, declared_chars).await,
        PendantEvent::UploadFailed { reason } => {
            let m = p.row().machine_id;
            app.bus
                .record_or_log(
                    "pendant.upload_rejected",
                    m,
                    Some(&p.actor()),
                    json!({"pendant": p.id, "reason": reason}),
                )
                .await;
        }
    }
}

/// The bound machine if it may move; otherwise records why not and returns None.
async fn ready_machine(app: &App, p: &Pendant, input: &Value) -> Option<Arc<Machine>> {
    let Some(m) = bound_machine(app, p).await else {
        refuse(
            app,
            p,
            None,
            input.clone(),
            "not_bound",
            "the pendant is not bound to a machine",
        )
        .await;
        return None;
    };
    let st = m.status();
    if st.state == MachineState::Alarm {
        let why = format!(
            "machine {} is in alarm: {}",
            m.id,
            st.alarm.unwrap_or_default()
        );
        refuse(app, p, Some(m.id), input.clone(), "machine_alarm", &why).await;
        return None;
    }
    Some(m)
}

/// Lost pendant: stop motion it started that may still be running (urgent stop, which
/// overtakes queued calls). A program it started keeps running unless `stop_program_on_lost`.
async fn stop_motion_of_lost(app: &Arc<App>, p: &Pendant) -> bool {
    let Some(m) = bound_machine(app, p).await else {
        return false;
    };
    let mut stopped = false;
    if app.pendants.last_mover_take_if(m.id, p.id) && m.run().is_none() {
        // Only motion from a jog or go-to-zero; a Stop while idle is harmless.
        match m.command(Command::Stop, &p.actor()).await {
            Ok(_) => stopped = true,
            Err(e) => {
                tracing::error!(pendant = p.id, machine = m.id, error = %e, "could not stop motion of a lost pendant")
            }
        }
    }
    let started = *lock(&p.started_run);
    if p.stop_program_on_lost() {
        if let (Some(cur), Some(run)) = (m.run(), started) {
            if cur.run_id == run {
                match crate::jobs::pause(app, cur.job_id, &p.actor()).await {
                    Ok(_) => stopped = true,
                    Err(e) => {
                        tracing::error!(pendant = p.id, error = %e.message, "could not hold the program of a lost pendant")
                    }
                }
            }
        }
    }
    stopped
}

async fn key_pressed(app: &Arc<App>, p: &Arc<Pendant>, key: PendantKey) {
    let input = json!({"key": key});
    let actor = p.actor();
    // Stop, pause and reset never wait for anything and are allowed in alarm.
    let safe = matches!(
        key,
        PendantKey::Stop | PendantKey::Pause | PendantKey::Reset
    );
    let m = if safe {
        match bound_machine(app, p).await {
            Some(m) => m,
            None => {
                refuse(
                    app,
                    p,
                    None,
                    input,
                    "not_bound",
                    "the pendant is not bound to a machine",
                )
                .await;
                return;
            }
        }
    } else {
        match ready_machine(app, p, &input).await {
            Some(m) => m,
            None => return,
        }
    };
    let zero = |axis| Some(Command::Zero { axis });
    let command = match key {
        PendantKey::Zero => zero(None),
        PendantKey::ZeroX => zero(Some(Axis::X)),
        PendantKey::ZeroY => zero(Some(Axis::Y)),
        PendantKey::ZeroZ => zero(Some(Axis::Z)),
        PendantKey::ZeroA => zero(Some(Axis::A)),
        PendantKey::Reset => Some(Command::Reset),
        PendantKey::Stop => Some(Command::Stop),
        PendantKey::Home => {
            app.pendants.last_mover_set(m.id, p.id);
            Some(Command::GoToZero)
        }
        _ => None,
    };
    let result: Result<(), Error> = match (command, key) {
        (Some(c), _) => m.command(c, &actor).await.map(|_| ()),
        (None, PendantKey::Pause) => match m.run() {
            Some(r) => crate::jobs::pause(app, r.job_id, &actor).await.map(|_| ()),
            None => m.command(Command::FeedHold, &actor).await.map(|_| ()),
        },
        (None, PendantKey::Start) => start_key(app, p, &m, &actor).await,
        (None, PendantKey::Rewind) => {
            // Every Start of a finished or new job runs from line 1; nothing to move.
            app.bus
                .record_or_log(
                    "pendant.rewind",
                    Some(m.id),
                    Some(&actor),
                    json!({"pendant": p.id}),
                )
                .await;
            Ok(())
        }
        (None, k) => run_macro(app, p, &m, k, &actor).await,
    };
    if let Err(e) = result {
        refuse(app, p, Some(m.id), input, e.code, &e.message).await;
    }
}

/// Start: resume a paused run, otherwise start the machine's newest job.
async fn start_key(app: &Arc<App>, p: &Pendant, m: &Machine, actor: &str) -> Result<(), Error> {
    if let Some(r) = m.run() {
        if r.state == RunState::Paused {
            // Never confirms a changed part zero: that decision belongs to the operator at the API.
            return crate::jobs::resume(app, r.job_id, actor, false, None)
                .await
                .map(|_| ());
        }
        return Err(Error::conflict(
            "machine_busy",
            format!("machine {} is already running job {}", m.id, r.job_id),
        ));
    }
    let job = app
        .store
        .list_jobs(Some(m.id), 1)
        .await?
        .into_iter()
        .next()
        .ok_or_else(|| {
            Error::conflict("no_job", format!("machine {} has no job to start", m.id))
        })?;
    let run = crate::jobs::start(app, job.id, actor).await?;
    *lock(&p.started_run) = Some(run.id);
    Ok(())
}

async fn run_macro(
    app: &Arc<App>,
    p: &Pendant,
    m: &Machine,
    key: PendantKey,
    actor: &str,
) -> Result<(), Error> {
    let slot = match key {
        PendantKey::M1 => 1,
        PendantKey::M2 => 2,
        PendantKey::M3 => 3,
        _ => 4,
    };
    let action = p.macros()[slot - 1].clone().ok_or_else(|| {
        Error::conflict(
            "macro_unassigned",
            format!("M{slot} has no action configured for pendant {}", p.id),
        )
    })?;
    match action {
        MacroAction::Command { command } => {
            if matches!(command, Command::GoToZero | Command::Home { .. }) {
                app.pendants.last_mover_set(m.id, p.id);
            }
            m.command(command, actor).await.map(|_| ())
        }
        MacroAction::Jog { axis, distance } => {
            app.pendants.last_mover_set(m.id, p.id);
            m.jog(axis, distance, None, actor).await
        }
        MacroAction::Toggle { output } => m
            .command(Command::ToggleOutput { name: output }, actor)
            .await
            .map(|_| ()),
        MacroAction::Mdi { line } => {
            app.pendants.last_mover_set(m.id, p.id);
            m.mdi(&line, actor).await
        }
    }
}

/// A finished upload becomes a job through the same path as HTTP uploads, only if the character
/// count matches exactly and no more lines arrived than were declared; the pendant gets N53 only
/// after the job row is committed.
///
/// Fewer lines than declared are the published firmware's blank lines: it counts every line for
/// N03START but sends an empty one as a zero-length send, which puts nothing on the wire. Blank
/// lines add nothing to the N03FIN character count, so an exact character count still proves
/// that every non-empty line arrived; the number of blank lines assumed dropped is recorded.
async fn receive_upload(
    app: &Arc<App>,
    p: &Pendant,
    upload: u64,
    lines: Vec<String>,
    declared_lines: u64,
    declared_chars: u64,
) {
    let row = p.row();
    let actor = p.actor();
    let chars: u64 = lines.iter().map(|l| l.len() as u64).sum();
    let problem = if row.machine_id.is_none() {
        Some((
            "not_bound",
            "the pendant is not bound to a machine; the upload is dropped".to_string(),
        ))
    } else if lines.len() as u64 > declared_lines {
        Some((
            "line_count_mismatch",
            format!(
                "received {} lines but N03START declared only {declared_lines}",
                lines.len()
            ),
        ))
    } else if chars != declared_chars {
        Some((
            "char_count_mismatch",
            format!("received {chars} characters but N03FIN declared {declared_chars}"),
        ))
    } else {
        None
    };
    if let Some((code, reason)) = problem {
        tracing::warn!(pendant = p.id, code, reason, "pendant upload rejected");
        app.bus
            .record_or_log(
                "pendant.upload_rejected",
                row.machine_id,
                Some(&actor),
                json!({"pendant": p.id, "code": code, "reason": reason, "lines": lines.len(), "chars": chars}),
            )
            .await;
        return;
    }
    let blank_lines_dropped = declared_lines - lines.len() as u64;
    if blank_lines_dropped > 0 {
        tracing::info!(
            pendant = p.id,
            blank_lines_dropped,
            "pendant upload: fewer lines than declared with an exact character count; taken as \
             blank lines the firmware does not send"
        );
    }
    let machine_id = row.machine_id.unwrap_or_default();
    let stored = async {
        let mut pending = crate::programs::PendingProgram::create(
            &app.settings.programs_dir(),
            app.settings.max_upload_bytes,
        )
        .await?;
        // Newline-normalised: every line ends with \n.
        let mut chunk = Vec::with_capacity(1 << 16);
        for l in &lines {
            chunk.extend_from_slice(l.as_bytes());
            chunk.push(b'\n');
            if chunk.len() >= 1 << 16 {
                pending.write(&chunk).await?;
                chunk.clear();
            }
        }
        pending.write(&chunk).await?;
        let program = pending.finish(None).await?;
        let name = format!("{} upload", row.name);
        crate::jobs::store_program(app, program, machine_id, Some(name), &actor, &actor).await
    }
    .await;
    match stored {
        Ok(job) => {
            let sent = match p.instance() {
                Some(i) => {
                    let req = json!(PendantRequest::ConfirmUpload { upload });
                    tokio::task::spawn_blocking(move || i.call(&req))
                        .await
                        .ok()
                        .and_then(|r| r.ok())
                        .and_then(|v| v["sent"].as_bool())
                        .unwrap_or(false)
                }
                None => false,
            };
            app.bus
                .record_or_log(
                    "pendant.upload",
                    Some(machine_id),
                    Some(&actor),
                    json!({"pendant": p.id, "job": job.id, "lines": job.lines, "bytes": job.bytes, "sha256": job.sha256, "confirmed": sent, "declared_lines": declared_lines, "blank_lines_dropped": blank_lines_dropped}),
                )
                .await;
        }
        Err(e) => {
            app.bus
                .record_or_log(
                    "pendant.upload_rejected",
                    Some(machine_id),
                    Some(&actor),
                    json!({"pendant": p.id, "code": e.code, "reason": e.message}),
                )
                .await;
        }
    }
}

/// Keeps the plugin's status cache current: work position and job progress of the bound
/// machine, pushed only when they change.
async fn status_loop(app: Arc<App>, p: Arc<Pendant>) {
    let mut tick = tokio::time::interval(STATUS_PUSH);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut last: Option<Value> = None;
    // (run id, when first seen, estimated seconds)
    let mut run_seen: Option<(i64, Instant, u64)> = None;
    loop {
        tokio::select! {
            _ = p.stop.cancelled() => return,
            _ = app.shutdown.cancelled() => return,
            _ = tick.tick() => {}
        }
        let m = bound_machine(&app, &p).await;
        let (position, job) = match &m {
            Some(m) => {
                let st = m.status();
                let job = match m.run() {
                    Some(r) => {
                        if run_seen.map(|s| s.0) != Some(r.run_id) {
                            let eta = app
                                .store
                                .job(r.job_id)
                                .await
                                .ok()
                                .flatten()
                                .and_then(|j| j.analysis)
                                .and_then(|a| serde_json::from_str::<Value>(&a).ok())
                                .and_then(|a| a["estimated_seconds"].as_f64())
                                .unwrap_or(0.0);
                            run_seen = Some((r.run_id, Instant::now(), eta.max(0.0) as u64));
                        }
                        let line = r.line;
                        let (_, since, eta) = run_seen.unwrap_or((0, Instant::now(), 0));
                        Some(PendantJob {
                            elapsed_s: since.elapsed().as_secs(),
                            estimated_s: eta,
                            total_lines: r.total_lines.max(0) as u64,
                            line: line.max(0) as u64,
                        })
                    }
                    None => None,
                };
                (st.work_position, job)
            }
            None => Default::default(),
        };
        let req = json!(PendantRequest::PendantStatus { position, job });
        if last.as_ref() == Some(&req) {
            continue;
        }
        if let Some(i) = p.instance() {
            // The plugin only swaps its cache under a lock: cheap enough to call inline.
            match i.call(&req) {
                Ok(_) => last = Some(req),
                Err(e) => tracing::warn!(pendant = p.id, error = %e, "status push failed"),
            }
        }
    }
}

/// `GET /api/v1/pendants` shape.
pub fn pendant_json(p: &Pendant) -> Value {
    let row = p.row();
    let macros: serde_json::Map<String, Value> = p
        .macros()
        .iter()
        .enumerate()
        .map(|(i, a)| (format!("M{}", i + 1), json!(a)))
        .collect();
    json!({"id": row.id, "name": row.name, "address": row.address, "dialect": row.dialect,
           "machine": row.machine_id, "connected": p.connected(), "config": row.config_json(),
           "macros": macros, "available": p.unavailable.is_none(), "reason": p.unavailable,
           "created_at": row.created_at})
}

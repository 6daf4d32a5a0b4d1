//! Pendants: one `pendant_transport` plugin instance per configured pendant. The plugin reports
//! what the operator did; this module routes it to the bound machine through the same calls the
//! HTTP API uses (bounded jogs, commands, job control, the one upload path), records every
//! action in the event log as `pendant:<id>`, and pushes the status cache the plugin answers the
//! pendant's polls from.

use crate::app::App;
use crate::error::{Error, ErrorKind};
use crate::events::EventKind;
use crate::machine::Machine;
use crate::store::{MacroAction, PendantRow};
use fresa_plugin_api::contract::{
    Axis, AxisValues, Command, MachineState, PendantEvent, PendantJob, PendantKey, PendantRequest,
    WorkOffset,
};
use fresa_plugin_api::host::Instance;
use fresa_plugin_api::quiet::Quiet;
use serde_json::{json, Value};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex as StdMutex};
use std::time::{Duration, Instant};
use tokio_util::sync::CancellationToken;

/// The plugin that speaks the MPG pendants' protocol.
pub const TRANSPORT_PLUGIN: &str = "mpg-pendant";
/// How often the status cache is refreshed (only changes are pushed).
const STATUS_PUSH: Duration = Duration::from_millis(50);

/// Settings the core reads from a pendant's `config` (the rest goes to the transport plugin).
const CORE_KEYS: [&str; 2] = ["stop_program_on_lost", "touch_plate_mm"];

pub mod inbox;
pub mod registry;
use inbox::{Binding, Inbox, Input, Urgent};
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
                let sink = Arc::new(Sink {
                    inbox: Arc::new(Inbox::new(0)),
                    id: 0,
                    quiet: Quiet::per_minute(),
                });
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

type Created = (Instance, Arc<Inbox>);

/// Creates the transport instance for `row`; it starts connecting at once. An error is the
/// plugin's verdict on the config (or the plugin is missing).
pub async fn create_instance(app: &App, row: &PendantRow) -> Result<Created, String> {
    let lib = app
        .plugins
        .get(TRANSPORT_PLUGIN)
        .ok_or_else(|| format!("no plugin named {TRANSPORT_PLUGIN:?} is loaded"))?
        .clone();
    let inbox = Arc::new(Inbox::new(row.id));
    let sink = Arc::new(Sink {
        inbox: inbox.clone(),
        id: row.id,
        quiet: Quiet::per_minute(),
    });
    let config = transport_config(row);
    let instance = tokio::task::spawn_blocking(move || lib.create(&config, sink))
        .await
        .map_err(|e| format!("transport create failed: {e}"))?
        .map_err(|e| e.to_string())?;
    Ok((instance, inbox))
}

/// Makes `row` live with its transport (or without one, keeping the reason so the operator
/// sees it), and starts its tasks: one for STOP, feed hold, reset and link changes, one for
/// everything else (so the first never waits behind a jog), and the status cache push.
pub async fn attach(
    app: &Arc<App>,
    row: PendantRow,
    created: Result<Created, String>,
) -> Arc<Pendant> {
    let macros = app.store.pendant_macros(row.id).await.unwrap_or_default();
    let (instance, inbox, unavailable) = match created {
        Ok((i, inbox)) => (Some(Arc::new(i)), inbox, None),
        Err(e) => {
            tracing::error!(pendant = row.id, error = %e, "pendant transport not available");
            (None, Arc::new(Inbox::new(row.id)), Some(e))
        }
    };
    let p = Arc::new(Pendant {
        id: row.id,
        row: StdMutex::new(row),
        instance: StdMutex::new(instance),
        unavailable,
        inbox,
        macros: StdMutex::new(macros),
        started_run: StdMutex::new(None),
        in_set_cero: AtomicBool::new(false),
        stop: CancellationToken::new(),
        quiet: Quiet::per_minute(),
    });
    bind(&p, bound_machine(app, &p).await.as_deref());
    app.pendants.map.write().await.insert(p.id, p.clone());
    tokio::spawn(urgent_loop(app.clone(), p.clone()));
    tokio::spawn(input_loop(app.clone(), p.clone()));
    tokio::spawn(status_loop(app.clone(), p.clone()));
    p
}

/// Tells the inbox which machine (and whose gate) new inputs are for.
pub(super) fn bind(p: &Pendant, m: Option<&Machine>) {
    p.inbox.bind(m.map(|m| Binding {
        machine: m.id,
        gate: m.gate().clone(),
        max_jog_mm: m.row().max_jog_mm,
    }));
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

/// STOP, feed hold, reset and link changes, in order, never behind an ordinary input.
async fn urgent_loop(app: Arc<App>, p: Arc<Pendant>) {
    loop {
        while let Some(u) = p.inbox.pop_urgent() {
            match u {
                Urgent::Connected { address } => {
                    let m = p.row().machine_id;
                    app.bus
                        .record_or_log(
                            EventKind::PendantConnected,
                            m,
                            Some(&p.actor()),
                            json!({"pendant": p.id, "address": address}),
                        )
                        .await;
                }
                Urgent::Lost { reason } => {
                    let stopped = stop_motion_of_lost(&app, &p).await;
                    let m = p.row().machine_id;
                    app.bus
                        .record_or_log(
                            EventKind::PendantLost,
                            m,
                            Some(&p.actor()),
                            json!({"pendant": p.id, "reason": reason, "stopped": stopped}),
                        )
                        .await;
                }
                Urgent::Key(key) => key_pressed(&app, &p, key, None).await,
            }
        }
        tokio::select! {
            _ = p.stop.cancelled() => return,
            _ = app.shutdown.cancelled() => return,
            _ = p.inbox.urgent_ready.notified() => {}
        }
    }
}

/// Everything else, in order. A wheel move waits while the machine still jogs (the previous
/// one, or anyone's), and wheel counts arriving meanwhile join it: one jog of one tap never
/// waits behind a backlog, and a backlog is one pending move a stop drops.
async fn input_loop(app: Arc<App>, p: Arc<Pendant>) {
    loop {
        let work = async {
            match p.inbox.next_is_wheel() {
                Some(true) => wheel(&app, &p).await,
                Some(false) => {
                    if let Some(input) = p.inbox.pop_other() {
                        other_input(&app, &p, input).await
                    }
                }
                None => p.inbox.ordinary_ready.notified().await,
            }
        };
        tokio::select! {
            _ = p.stop.cancelled() => return,
            _ = app.shutdown.cancelled() => return,
            _ = work => {}
        }
    }
}

/// One wheel move: at most `max_jog_mm` of the queued counts, once the machine no longer jogs.
async fn wheel(app: &Arc<App>, p: &Arc<Pendant>) {
    let m = bound_machine(app, p).await;
    if let Some(m) = &m {
        let mut status = m.subscribe_status();
        if status
            .wait_for(|s| s.state != MachineState::Jogging)
            .await
            .is_err()
        {
            // The machine's task has ended: its queued wheel move can never run, and left at
            // the front it would be offered again at once, forever.
            let _ = p.inbox.take_wheel(f64::INFINITY);
            return;
        }
    }
    let max = m.as_ref().map_or(f64::INFINITY, |m| m.row().max_jog_mm);
    let Some(j) = p.inbox.take_wheel(max) else {
        return;
    };
    p.in_set_cero
        .store(is_set_cero_step(j.axis, j.count, j.step), Ordering::Relaxed);
    let input = json!({"jog": {"axis": j.axis, "count": j.count, "step": j.step}});
    let Some(m) = ready_machine(app, p, &input).await else {
        return;
    };
    let ticket = match j.ticket {
        Some(t) if t.machine == m.id => t.epoch,
        // Meant for the machine the pendant was bound to before.
        Some(_) => return,
        None => m.gate().ticket(),
    };
    if !claim_motion(app, p, &m) {
        return;
    }
    let distance = j.count as f64 * j.step;
    match m
        .jog_ticketed(j.axis, distance, None, &p.actor(), ticket)
        .await
    {
        // The task has seen the backend start the jog before the next move waits for its end.
        Ok(()) => m.sync().await,
        Err(e) if e.code == "stopped" => {
            tracing::debug!(
                pendant = p.id,
                "a queued wheel move was overtaken by a stop"
            )
        }
        Err(e) => refuse(app, p, Some(m.id), input, e.code, &e.message).await,
    }
}

/// A wheel move the firmware's "Set cero" routine sends: Z down in 0.0001 steps (the spec's
/// `N01S0.0001Z-0100`; the inbox may have merged several into one).
fn is_set_cero_step(axis: Axis, count: i64, step: f64) -> bool {
    axis == Axis::Z && count < 0 && (step - SET_CERO_STEP).abs() < 1e-9
}

const SET_CERO_STEP: f64 = 0.0001;

/// The end of "Set cero" on a plate `plate_mm` thick: Z zeroed where the plate closed, then the
/// active work offset moved so Z reads the plate's thickness there (the tool tip is on the
/// plate's top, `plate_mm` above the part). Two backend calls rather than one computed offset,
/// so whatever else the backend folds into Z (tool length, G92) stays as it was. Waits for the
/// routine's last step to end first, as the firmware does before it sends `ZeroZ`. Recorded as
/// `machine.touch_off` with the offset before and after; if the second call fails, Z reads 0
/// (as without a plate) and the refusal says so.
async fn set_cero_on_plate(
    app: &App,
    p: &Pendant,
    m: &Machine,
    plate_mm: f64,
    actor: &str,
    ticket: u64,
) -> Result<(), Error> {
    let mut status = m.subscribe_status();
    let still = status.wait_for(|s| s.state != MachineState::Jogging);
    if tokio::time::timeout(SET_CERO_SETTLE, still).await.is_err() {
        return Err(Error::conflict(
            "machine_moving",
            format!(
                "machine {} still jogs {SET_CERO_SETTLE:?} after the last Set cero step",
                m.id
            ),
        ));
    }
    let active = m.status().active_offset;
    let active_values = |offsets: Vec<(WorkOffset, AxisValues)>| {
        offsets
            .into_iter()
            .find(|(o, _)| *o == active)
            .map(|(_, v)| v)
            .unwrap_or_default()
    };
    let before = active_values(app.store.offsets(m.id).await?);
    m.command_ticketed(
        Command::Zero {
            axis: Some(Axis::Z),
        },
        actor,
        ticket,
    )
    .await?;
    let mut after = active_values(app.store.offsets(m.id).await?);
    let zeroed_z = after.z;
    after.z -= plate_mm;
    m.set_offset(active, after, actor).await.map_err(|e| {
        Error::new(
            e.kind,
            e.code,
            format!(
                "Z was zeroed on the plate but not raised by its {plate_mm} mm: {}",
                e.message
            ),
        )
    })?;
    app.bus
        .record_or_log(
            EventKind::MachineTouchOff,
            Some(m.id),
            Some(actor),
            json!({
                "pendant": p.id, "axis": "Z", "plate_mm": plate_mm, "offset": active,
                "before": before, "after": after, "zeroed_z": zeroed_z,
                "machine_z": m.status().machine_position.z,
            }),
        )
        .await;
    Ok(())
}

/// How long the last Set cero step may take to end before `ZeroZ` is refused.
const SET_CERO_SETTLE: Duration = Duration::from_secs(10);

/// Marks the pendant as the one moving `m` and checks the link is still up: a loss handled
/// after this sees the mark and stops the machine; one before it is seen here.
fn claim_motion(app: &App, p: &Pendant, m: &Machine) -> bool {
    app.pendants.last_mover_set(m.id, p.id);
    if p.inbox.connected() {
        return true;
    }
    app.pendants.last_mover_take_if(m.id, p.id);
    tracing::info!(
        pendant = p.id,
        "input dropped: the pendant was lost right after sending it"
    );
    false
}

async fn other_input(app: &Arc<App>, p: &Arc<Pendant>, input: Input) {
    match input {
        Input::Key { key, ticket } => key_pressed(app, p, key, ticket).await,
        Input::Other(PendantEvent::Upload {
            upload,
            lines,
            declared_lines,
            declared_chars,
        }) => {
            // Storing a long program takes a while; later keys need not wait for it.
            let (app, p) = (app.clone(), p.clone());
            tokio::spawn(async move {
                receive_upload(&app, &p, upload, lines, declared_lines, declared_chars).await
            });
        }
        Input::Other(PendantEvent::UploadFailed { reason }) => {
            let m = p.row().machine_id;
            app.bus
                .record_or_log(
                    EventKind::PendantUploadRejected,
                    m,
                    Some(&p.actor()),
                    json!({"pendant": p.id, "reason": reason}),
                )
                .await;
        }
        // Link events and wheel moves never reach here (the inbox routes them).
        Input::Other(other) => {
            tracing::debug!(pendant = p.id, event = ?other, "pendant event ignored")
        }
        Input::Jog { .. } => {}
    }
}

async fn bound_machine(app: &App, p: &Pendant) -> Option<Arc<Machine>> {
    let id = p.row().machine_id?;
    app.machines.get(id)
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
    if let Some(line) = p
        .quiet
        .admit(code, || format!("pendant input refused: {input}: {reason}"))
    {
        tracing::warn!(pendant = p.id, code, "{line}");
    }
    app.bus
        .record_or_log(
            EventKind::PendantRefused,
            machine,
            Some(&p.actor()),
            json!({"pendant": p.id, "input": input, "code": code, "reason": reason}),
        )
        .await;
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
                let why = format!("pendant {} (which started the run) was lost", p.id);
                let reason = Some((fresa_plugin_api::contract::HoldKind::PendantLost, why));
                match crate::jobs::pause_because(app, cur.job_id, &p.actor(), reason).await {
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

/// `ticket`: for a motion key, the gate ticket from when it arrived (a stop since then drops it).
async fn key_pressed(
    app: &Arc<App>,
    p: &Arc<Pendant>,
    key: PendantKey,
    ticket: Option<inbox::Ticket>,
) {
    let input = json!({"key": key});
    let actor = p.actor();
    // Any key ends a Set cero routine; only ZeroZ finishes it on the plate.
    let ends_set_cero = p.in_set_cero.swap(false, Ordering::Relaxed) && key == PendantKey::ZeroZ;
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
    let ticket = match ticket {
        Some(t) if t.machine != m.id => return,
        Some(t) => t.epoch,
        None => m.gate().ticket(),
    };
    if inbox::moves(key) {
        if m.gate().check(ticket).is_err() {
            tracing::debug!(pendant = p.id, ?key, "a queued key was overtaken by a stop");
            return;
        }
        if !claim_motion(app, p, &m) {
            return;
        }
    }
    let zero = |axis| Some(Command::Zero { axis });
    let command = match key {
        PendantKey::Zero => zero(None),
        PendantKey::ZeroX => zero(Some(Axis::X)),
        PendantKey::ZeroY => zero(Some(Axis::Y)),
        PendantKey::ZeroZ => zero(Some(Axis::Z)),
        PendantKey::ZeroA => zero(Some(Axis::A)),
        PendantKey::Reset => Some(Command::Reset),
        PendantKey::Stop => Some(Command::Stop),
        PendantKey::Home => Some(Command::GoToZero),
        _ => None,
    };
    let plate = p.touch_plate_mm().filter(|_| ends_set_cero);
    let result: Result<(), Error> = match (command, plate) {
        (Some(_), Some(plate_mm)) => set_cero_on_plate(app, p, &m, plate_mm, &actor, ticket).await,
        (command, _) => match (command, key) {
            (Some(c), _) if c.is_urgent() => m.command(c, &actor).await.map(|_| ()),
            (Some(c), _) => m.command_ticketed(c, &actor, ticket).await.map(|_| ()),
            (None, PendantKey::Pause) => match m.run() {
                Some(r) => crate::jobs::pause(app, r.job_id, &actor).await.map(|_| ()),
                None => m.command(Command::FeedHold, &actor).await.map(|_| ()),
            },
            (None, PendantKey::Start) => start_key(app, p, &m, &actor).await,
            (None, PendantKey::Rewind) => {
                // Every Start of a finished or new job runs from line 1; nothing to move.
                app.bus
                    .record_or_log(
                        EventKind::PendantRewind,
                        Some(m.id),
                        Some(&actor),
                        json!({"pendant": p.id}),
                    )
                    .await;
                Ok(())
            }
            (None, k) => run_macro(p, &m, k, &actor, ticket).await,
        },
    };
    if let Err(e) = result {
        refuse(app, p, Some(m.id), input, e.code, &e.message).await;
    }
}

/// Start: resume a paused run; while the machine's queue waits for a confirm, confirm it (the
/// next part is loaded: issue 28); otherwise start the machine's newest job.
async fn start_key(app: &Arc<App>, p: &Pendant, m: &Machine, actor: &str) -> Result<(), Error> {
    if let Some(r) = m.run() {
        // Resume whatever the published run says: it can lag a pause the machine's task has
        // just stored (the key then came right after the pause), and the task, which orders
        // both, knows. A job that really runs is not resumable: the machine is busy. Never
        // confirms a changed part zero: that decision belongs to the operator at the API.
        return match crate::jobs::resume(app, r.job_id, actor, false, None).await {
            Ok(_) => Ok(()),
            Err(e) if e.code == "not_resumable" => Err(Error::conflict(
                "machine_busy",
                format!("machine {} is already running job {}", m.id, r.job_id),
            )),
            Err(e) => Err(e),
        };
    }
    if crate::queue::waits_for_confirm(app, m.id).await {
        let started = crate::queue::confirm(app, m.id, actor).await?;
        *lock(&p.started_run) = Some(started.run);
        return Ok(());
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
    p: &Pendant,
    m: &Machine,
    key: PendantKey,
    actor: &str,
    ticket: u64,
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
        MacroAction::Command { command } if command.is_urgent() => {
            m.command(command, actor).await.map(|_| ())
        }
        MacroAction::Command { command } => {
            m.command_ticketed(command, actor, ticket).await.map(|_| ())
        }
        MacroAction::Jog { axis, distance } => {
            m.jog_ticketed(axis, distance, None, actor, ticket).await
        }
        MacroAction::Toggle { output } => m
            .command_ticketed(Command::ToggleOutput { name: output }, actor, ticket)
            .await
            .map(|_| ()),
        MacroAction::Mdi { line } => m.mdi_ticketed(&line, actor, ticket).await,
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
                EventKind::PendantUploadRejected,
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
                    EventKind::PendantUpload,
                    Some(machine_id),
                    Some(&actor),
                    json!({"pendant": p.id, "job": job.id, "lines": job.lines, "bytes": job.bytes, "sha256": job.sha256, "confirmed": sent, "declared_lines": declared_lines, "blank_lines_dropped": blank_lines_dropped}),
                )
                .await;
        }
        Err(e) => {
            app.bus
                .record_or_log(
                    EventKind::PendantUploadRejected,
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
        bind(&p, m.as_deref());
        let (position, job, status_line) = match &m {
            Some(m) => {
                let st = m.status();
                // Why the machine holds, on the LCD (issue 26).
                let status_line = st
                    .hold
                    .as_ref()
                    .filter(|_| st.state == MachineState::Paused || m.run().is_some())
                    .map(|h| crate::machine::holds::lcd_line(h))
                    // Otherwise, a queue waiting for the next part or held (issue 28).
                    .or_else(|| app.queues.lcd_line(m.id));
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
                (st.work_position, job, status_line)
            }
            None => Default::default(),
        };
        let req = json!(PendantRequest::PendantStatus {
            position,
            job,
            status_line
        });
        if last.as_ref() == Some(&req) {
            continue;
        }
        if let Some(i) = p.instance() {
            // The plugin only swaps its cache under a lock: cheap enough to call inline.
            match i.call(&req) {
                Ok(_) => last = Some(req),
                Err(e) => {
                    if let Some(line) = p
                        .quiet
                        .admit("status-push", || format!("status push failed: {e}"))
                    {
                        tracing::warn!(pendant = p.id, "{line}");
                    }
                }
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

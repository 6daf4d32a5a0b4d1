//! The event bus: persisted events (job state, commands, offsets, alarms: the audit log) get an
//! id from the `events` table and can be replayed with `Last-Event-ID`; transient events
//! (status, job progress) are only fanned out, since the next one supersedes them.

use crate::config::EventRetention;
use crate::store::{now_ms, EventRow, Store};
use serde::Serialize;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, OnceLock};
use tokio::sync::{broadcast, Mutex};

/// What the bus does with an event of a type.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Keeping {
    /// Fanned out only, no id: the next one supersedes it ([`EventBus::transient`]).
    Transient,
    /// Persisted with an id ([`EventBus::record_or_log`]); high-volume traffic (jogs, commands,
    /// MDI lines, pendant connects, refusals, rewinds), also pruned beyond
    /// `event_retention_count`.
    Routine,
    /// Persisted and kept `audit_retention_days`: what was made, run, set or lost.
    Audit,
}

/// Declares [`EventKind`] from one table: a variant, its wire name and its keeping per line.
/// The generated `name` and `keeping` are exhaustive matches (no catch-all) and [`EventKind::ALL`]
/// lists every variant, so a new type is decided in one place, all at once.
macro_rules! event_kinds {
    ($($(#[$doc:meta])* $variant:ident = $name:literal, $keeping:ident;)*) => {
        /// Every event type the server emits. The bus takes this instead of a string, so an
        /// event cannot go out with a typo in its type, nor live-only when it is persisted (or
        /// the other way round).
        #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
        pub enum EventKind {
            $($(#[$doc])* $variant,)*
        }

        impl EventKind {
            /// Every type, in table order.
            pub const ALL: &'static [EventKind] = &[$(EventKind::$variant,)*];

            /// The type as on the wire: SSE `event:`, the `type` field, the `events` table,
            /// MQTT and webhook topics. Never renamed: clients and stored rows use these.
            pub const fn name(self) -> &'static str {
                match self {
                    $(EventKind::$variant => $name,)*
                }
            }

            pub const fn keeping(self) -> Keeping {
                match self {
                    $(EventKind::$variant => Keeping::$keeping,)*
                }
            }
        }
    };
}

event_kinds! {
    /// The machine's status, as `GET /machines/{id}/status` answers it ([`crate::views::StatusView`]).
    Status = "status", Transient;
    JobProgress = "job.progress", Transient;
    JobLineReport = "job.line_report", Transient;
    MachineIo = "machine.io", Transient;
    MachineState = "machine.state", Transient;
    MachineCommand = "machine.command", Routine;
    MachineJog = "machine.jog", Routine;
    MachineMdi = "machine.mdi", Routine;
    MachineJogCancel = "machine.jog_cancel", Routine;
    /// A probing move was started (what was asked); its result is in the answer, and in
    /// `machine.touch_off` when it set an offset.
    MachineProbe = "machine.probe", Routine;
    PendantConnected = "pendant.connected", Routine;
    PendantLost = "pendant.lost", Routine;
    PendantRefused = "pendant.refused", Routine;
    PendantRewind = "pendant.rewind", Routine;
    PendantUploadRejected = "pendant.upload_rejected", Routine;
    JobCreated = "job.created", Audit;
    JobState = "job.state", Audit;
    MachineCreated = "machine.created", Audit;
    MachineOffsets = "machine.offsets", Audit;
    MachinePartZero = "machine.part_zero", Audit;
    /// Z set from a touch plate of known thickness (the pendant's Set cero, or a probing
    /// touch-off): the offset before and after.
    MachineTouchOff = "machine.touch_off", Audit;
    MachineAlarm = "machine.alarm", Audit;
    MachineNode = "machine.node", Audit;
    MachineTools = "machine.tools", Audit;
    /// A machine's run settings changed (optional stop, tool-change policy and position, tool
    /// setter): the new settings.
    MachineRunSettings = "machine.run_settings", Audit;
    /// A tool's length was measured on the tool setter: the trip, the length stored, and the
    /// work offset's Z moved for it during a tool change (before and after).
    MachineToolMeasured = "machine.tool_measured", Audit;
    PendantCreated = "pendant.created", Audit;
    PendantBound = "pendant.bound", Audit;
    PendantMacro = "pendant.macro", Audit;
    PendantDeleted = "pendant.deleted", Audit;
    PendantNode = "pendant.node", Audit;
    PendantUpload = "pendant.upload", Audit;
    WebhookCreated = "webhook.created", Audit;
    WebhookDeleted = "webhook.deleted", Audit;
    /// A height map's grid probed one more point (issue 25).
    HeightMapProgress = "height_map.progress", Transient;
    /// A height map's grid ended: `complete`, `stopped` or `failed`, with what it probed.
    HeightMapEnded = "height_map.ended", Audit;
    HeightMapDeleted = "height_map.deleted", Audit;
    /// Job queues (issue 28): an entry of N parts added to a machine's queue.
    QueueAdd = "queue.add", Audit;
    QueueRemove = "queue.remove", Audit;
    QueueMove = "queue.move", Audit;
    /// The next part waits for an operator's confirm ("next part loaded").
    QueueWaiting = "queue.waiting_confirm", Audit;
    /// An operator confirmed and the part started: `machine`, `entry`, `job`, `run`, `part`.
    QueueConfirm = "queue.confirm", Audit;
    /// A part started without a confirm (`confirm_between` false): as `queue.confirm`.
    QueueStarted = "queue.started", Audit;
    /// The queue holds (a part stopped, failed, was cancelled or interrupted): `reason`.
    QueueHold = "queue.hold", Audit;
    QueueRelease = "queue.release", Audit;
    /// The machine's queue has no parts left.
    QueueDone = "queue.done", Audit;
    /// `POST /queue` gave a part to a free machine: `machine`, `job`, `run`, `refused`.
    QueueDispatch = "queue.dispatch", Audit;
    /// A maintenance interval of a machine came due (once per crossing): `name`, `counter`,
    /// `every`, `value` (the counter now), `since_done` (the counter since it was last done).
    MachineMaintenanceDue = "machine.maintenance_due", Audit;
    /// A maintenance interval was marked done (its interval starts again): `name`, `counter`,
    /// `value`.
    MachineMaintenanceDone = "machine.maintenance_done", Audit;
}

impl EventKind {
    /// Persisted in the event log (routine or audit), with an id.
    pub const fn is_persisted(self) -> bool {
        !matches!(self.keeping(), Keeping::Transient)
    }

    /// The type a wire name stands for, if the server emits it.
    pub fn from_name(name: &str) -> Option<EventKind> {
        EventKind::ALL.iter().copied().find(|k| k.name() == name)
    }
}

/// An operation's audit event (the plugin-api operation table decides which one).
impl From<fresa_plugin_api::operation::AuditEvent> for EventKind {
    fn from(e: fresa_plugin_api::operation::AuditEvent) -> Self {
        use fresa_plugin_api::operation::AuditEvent;
        match e {
            AuditEvent::Jog => EventKind::MachineJog,
            AuditEvent::Mdi => EventKind::MachineMdi,
            AuditEvent::Offsets => EventKind::MachineOffsets,
            AuditEvent::Command => EventKind::MachineCommand,
            AuditEvent::Probe => EventKind::MachineProbe,
        }
    }
}

impl std::fmt::Display for EventKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

#[derive(Debug, Clone, Serialize, serde::Deserialize)]
pub struct BusEvent {
    /// Present on persisted events only.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub id: Option<i64>,
    /// The wire name: an [`EventKind`]'s for what this server emits; a row read back from the
    /// log may hold a type an older version wrote.
    #[serde(rename = "type")]
    pub kind: String,
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub machine: Option<i64>,
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub actor: Option<String>,
    pub time: i64,
    pub data: serde_json::Value,
    /// The node it happened on, when the store is shared by nodes.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub node: Option<String>,
    /// This event as JSON text, made the first time it is asked for: an event fans out to
    /// every subscriber as one `Arc`, so it is serialised once, not once per SSE client.
    #[serde(skip)]
    json: OnceLock<String>,
    /// `data` as JSON text, likewise (what MQTT publishes as a status).
    #[serde(skip)]
    data_json: OnceLock<String>,
    /// The whole SSE frame (`event:`, `data:`, `id:`), likewise: every stream sends the same
    /// shared bytes, so a client costs no copy of the event.
    #[serde(skip)]
    sse: OnceLock<bytes::Bytes>,
}

impl BusEvent {
    fn new(
        id: Option<i64>,
        kind: String,
        machine: Option<i64>,
        actor: Option<String>,
        time: i64,
        data: serde_json::Value,
        node: Option<String>,
    ) -> Self {
        BusEvent {
            id,
            kind,
            machine,
            actor,
            time,
            data,
            node,
            json: OnceLock::new(),
            data_json: OnceLock::new(),
            sse: OnceLock::new(),
        }
    }

    /// Whether this is an event of type `kind`.
    pub fn is(&self, kind: EventKind) -> bool {
        self.kind == kind.name()
    }

    /// The whole event as JSON (what SSE sends as `data:` and MQTT as an event message),
    /// serialised once.
    pub fn json(&self) -> &str {
        self.json
            .get_or_init(|| serde_json::to_string(self).unwrap_or_default())
    }

    /// Its `data` as JSON, serialised once.
    pub fn data_json(&self) -> &str {
        self.data_json.get_or_init(|| self.data.to_string())
    }

    /// This event as one Server-Sent Events frame, made once and shared by every stream.
    pub fn sse(&self) -> bytes::Bytes {
        self.sse
            .get_or_init(|| sse_frame(&self.kind, self.json(), self.id))
            .clone()
    }
}

/// One SSE frame: `event: KIND`, `data: JSON`, `id: ID` (if any), then an empty line. `json`
/// is compact JSON, which holds no line break (one inside a string is escaped); a stray one
/// would end the frame early, so each line becomes a `data:` line of its own, as SSE defines.
pub fn sse_frame(kind: &str, json: &str, id: Option<i64>) -> bytes::Bytes {
    let mut f = String::with_capacity(json.len() + kind.len() + 32);
    f.push_str("event: ");
    f.extend(kind.chars().filter(|c| !matches!(c, '\n' | '\r')));
    f.push('\n');
    for line in json.split(['\n', '\r']) {
        f.push_str("data: ");
        f.push_str(line);
        f.push('\n');
    }
    if let Some(id) = id {
        use std::fmt::Write;
        let _ = writeln!(f, "id: {id}");
    }
    f.push('\n');
    bytes::Bytes::from(f)
}

impl From<EventRow> for BusEvent {
    fn from(r: EventRow) -> Self {
        BusEvent::new(
            Some(r.id),
            r.kind,
            r.machine_id,
            r.actor,
            r.created_at,
            serde_json::from_str(&r.data).unwrap_or(serde_json::Value::Null),
            r.node,
        )
    }
}

/// Transient events (status, progress) a node shares with the other nodes: bounded, so a slow
/// database drops some (the next status supersedes them) instead of growing memory.
const SHARED_TRANSIENT_QUEUE: usize = 1024;
/// PostgreSQL limits a notification's payload to 8000 bytes.
const MAX_NOTIFY_PAYLOAD: usize = 7900;
/// The notification channel of transient events.
const TRANSIENT_CHANNEL: &str = "fresa_transient";

#[derive(Clone)]
pub struct EventBus {
    store: Store,
    tx: broadcast::Sender<Arc<BusEvent>>,
    /// Persist-then-send under one lock so live subscribers see ids in increasing order. The
    /// lock also guards the events recorded while the database was unreachable, oldest first:
    /// they are written (and only then sent, with their ids) before any newer event.
    order: Arc<Mutex<VecDeque<Delayed>>>,
    /// Set when the store is shared by nodes (PostgreSQL): persisted events reach subscribers
    /// only through the tail ([`spawn_tail`]), in id order, whichever node appended them.
    shared: Option<Shared>,
    /// Delayed events dropped because the buffer was full (the oldest go first).
    dropped: Arc<AtomicU64>,
    /// How many events wait for the database now (for `/metrics`, without taking the lock).
    waiting: Arc<AtomicUsize>,
}

/// At most this many events wait for the database; an outage longer than that loses the oldest
/// ones (counted in `/metrics`), never blocks the caller.
pub const MAX_DELAYED_EVENTS: usize = 10_000;

/// An audit event recorded while the database was unreachable.
struct Delayed {
    kind: EventKind,
    machine: Option<i64>,
    actor: Option<String>,
    data: serde_json::Value,
    /// When it happened (Unix ms); written into the data as `recorded_at` since the row's own
    /// time is when it reached the database.
    at: i64,
}

#[derive(Clone)]
struct Shared {
    /// Wakes the tail at once after a local append (not waiting for the notification).
    wake: Arc<tokio::sync::Notify>,
    /// Transient events for the other nodes.
    outbox: tokio::sync::mpsc::Sender<Arc<BusEvent>>,
    outbox_rx: Arc<Mutex<Option<tokio::sync::mpsc::Receiver<Arc<BusEvent>>>>>,
}

impl EventBus {
    pub fn new(store: Store, capacity: usize) -> Self {
        let (tx, _) = broadcast::channel(capacity);
        let shared = (store.dialect() == crate::store::Dialect::Postgres).then(|| {
            let (outbox, rx) = tokio::sync::mpsc::channel(SHARED_TRANSIENT_QUEUE);
            Shared {
                wake: Arc::new(tokio::sync::Notify::new()),
                outbox,
                outbox_rx: Arc::new(Mutex::new(Some(rx))),
            }
        });
        EventBus {
            store,
            tx,
            order: Arc::new(Mutex::new(VecDeque::new())),
            shared,
            dropped: Arc::new(AtomicU64::new(0)),
            waiting: Arc::new(AtomicUsize::new(0)),
        }
    }

    /// Events waiting for the database, and those dropped because too many waited.
    pub fn delayed_counts(&self) -> (usize, u64) {
        (
            self.waiting.load(Ordering::Relaxed),
            self.dropped.load(Ordering::Relaxed),
        )
    }

    /// Writes the delayed events, oldest first, while the database takes them. Returns whether
    /// none are left. Called with the order lock held.
    async fn write_delayed(&self, delayed: &mut VecDeque<Delayed>) -> bool {
        let health = self.store.health();
        while let Some(d) = delayed.front() {
            let mut data = d.data.clone();
            if let Some(obj) = data.as_object_mut() {
                obj.insert("recorded_at".into(), serde_json::json!(d.at));
            }
            let written = health
                .guard(self.store.append_event(
                    d.kind.name(),
                    d.machine,
                    d.actor.as_deref(),
                    &data.to_string(),
                ))
                .await;
            match written {
                Ok(row) => {
                    self.publish_row(row, data);
                    delayed.pop_front();
                }
                Err(e) if e.code == "database_unavailable" => break,
                Err(e) => {
                    tracing::error!(kind = %d.kind, error = %e, "could not persist a delayed event; dropped");
                    delayed.pop_front();
                }
            }
        }
        self.waiting.store(delayed.len(), Ordering::Relaxed);
        delayed.is_empty()
    }

    /// Writes the events delayed by an outage as soon as the database is back, so they do not
    /// wait for the next event to be recorded.
    pub fn spawn_delayed_writer(&self, stop: tokio_util::sync::CancellationToken) {
        let bus = self.clone();
        let mut health = self.store.health().subscribe();
        tokio::spawn(async move {
            loop {
                tokio::select! {
                    _ = stop.cancelled() => return,
                    r = health.wait_for(|s| *s == crate::store::DbState::Up) => if r.is_err() { return },
                }
                {
                    let mut delayed = bus.order.lock().await;
                    bus.write_delayed(&mut delayed).await;
                }
                tokio::select! {
                    _ = stop.cancelled() => return,
                    r = health.changed() => if r.is_err() { return },
                }
            }
        });
    }

    /// A row just appended, to the subscribers: directly on a store of its own; through the tail
    /// when the store is shared (it delivers every node's events in id order).
    fn publish_row(&self, row: crate::store::EventRow, data: serde_json::Value) {
        match &self.shared {
            Some(shared) => shared.wake.notify_one(),
            None => {
                let _ = self.tx.send(Arc::new(BusEvent::new(
                    Some(row.id),
                    row.kind,
                    row.machine_id,
                    row.actor,
                    row.created_at,
                    data,
                    row.node,
                )));
            }
        }
    }

    /// Appends to the event log and fans out. Returns the event id. For persisted types only:
    /// a live-only one is a bug, refused (and fanned out as it should have been).
    pub async fn record(
        &self,
        kind: EventKind,
        machine: Option<i64>,
        actor: Option<&str>,
        data: serde_json::Value,
    ) -> Result<i64, sqlx::Error> {
        if !kind.is_persisted() {
            wrong_path(kind);
            self.transient(kind, machine, data);
            return Err(sqlx::Error::Protocol(format!(
                "event type {kind} is live-only; it has no id"
            )));
        }
        let mut delayed = self.order.lock().await;
        if !delayed.is_empty() {
            self.write_delayed(&mut delayed).await;
        }
        let row = self
            .store
            .append_event(kind.name(), machine, actor, &data.to_string())
            .await?;
        let id = row.id;
        self.publish_row(row, data);
        Ok(id)
    }

    /// Like [`record`](Self::record) but never fails the action that caused the event: while the
    /// database is unreachable the event waits in memory (at most [`MAX_DELAYED_EVENTS`]) and is
    /// written, then sent with its id, when the database returns; other failures are logged.
    ///
    /// For persisted types only: a live-only one is a bug, fanned out as it should have been.
    pub async fn record_or_log(
        &self,
        kind: EventKind,
        machine: Option<i64>,
        actor: Option<&str>,
        data: serde_json::Value,
    ) {
        if !kind.is_persisted() {
            wrong_path(kind);
            return self.transient(kind, machine, data);
        }
        let mut delayed = self.order.lock().await;
        let health = self.store.health();
        // Behind older delayed events, or while the database is down: wait in memory.
        let caught_up = health.is_up() && self.write_delayed(&mut delayed).await;
        let data = if caught_up {
            let written = health
                .guard(
                    self.store
                        .append_event(kind.name(), machine, actor, &data.to_string()),
                )
                .await;
            match written {
                Ok(row) => {
                    self.publish_row(row, data);
                    return;
                }
                Err(e) if e.code == "database_unavailable" => data,
                Err(e) => {
                    tracing::error!(kind = kind.name(), error = %e, "could not persist event");
                    return;
                }
            }
        } else {
            data
        };
        if delayed.len() >= MAX_DELAYED_EVENTS {
            delayed.pop_front();
            self.dropped.fetch_add(1, Ordering::Relaxed);
        }
        delayed.push_back(Delayed {
            kind,
            machine,
            actor: actor.map(str::to_string),
            data,
            at: now_ms(),
        });
        self.waiting.store(delayed.len(), Ordering::Relaxed);
    }

    /// Fans out a live-only event. For live-only types only: a persisted one is a bug, recorded
    /// (in the background) as it should have been rather than lost from the log.
    pub fn transient(&self, kind: EventKind, machine: Option<i64>, data: serde_json::Value) {
        if kind.is_persisted() {
            wrong_path(kind);
            if let Ok(rt) = tokio::runtime::Handle::try_current() {
                let bus = self.clone();
                rt.spawn(async move { bus.record_or_log(kind, machine, None, data).await });
            }
            return;
        }
        let event = Arc::new(BusEvent::new(
            None,
            kind.name().to_string(),
            machine,
            None,
            now_ms(),
            data,
            self.store.node().map(str::to_string),
        ));
        if let Some(shared) = &self.shared {
            // Full: the database is slow or away; this status is superseded by the next one.
            let _ = shared.outbox.try_send(event.clone());
        }
        let _ = self.tx.send(event);
    }

    pub fn subscribe(&self) -> broadcast::Receiver<Arc<BusEvent>> {
        self.tx.subscribe()
    }

    /// Live event-stream subscribers (SSE clients and internal listeners).
    pub fn subscribers(&self) -> usize {
        self.tx.receiver_count()
    }

    /// Whether `e` happened on this node (an event from before nodes existed counts as ours):
    /// integrations that act on events (webhooks, MQTT) act on their own node's only, so a
    /// shared store does not deliver each event once per node.
    pub fn is_local(&self, e: &BusEvent) -> bool {
        match (&e.node, self.store.node()) {
            (Some(theirs), Some(ours)) => theirs == ours,
            _ => true,
        }
    }
}

/// An event sent on the path its type does not take (a bug): loud in debug builds and tests,
/// logged in release.
fn wrong_path(kind: EventKind) {
    debug_assert!(
        false,
        "event type {kind} sent on the wrong path ({:?})",
        kind.keeping()
    );
    tracing::error!(kind = kind.name(), keeping = ?kind.keeping(), "event sent on the wrong path; rerouted");
}

/// On a store shared by nodes (PostgreSQL), follows the event table and fans every node's
/// events out to this node's subscribers, in id order: the notification on `fresa_events` (or
/// a local append) wakes it, the table is the source of truth, and a slow poll covers a lost
/// notification or a reconnect. Also relays transient events between nodes. Does nothing on
/// SQLite, where the bus fans out directly.
pub fn spawn_tail(bus: EventBus, database_url: String, stop: tokio_util::sync::CancellationToken) {
    let Some(shared) = bus.shared.clone() else {
        return;
    };
    tokio::spawn(relay_transient(
        bus.clone(),
        database_url.clone(),
        stop.clone(),
    ));
    tokio::spawn(async move {
        const POLL: std::time::Duration = std::time::Duration::from_secs(1);
        const PAGE: i64 = 500;
        let mut cursor = match bus.store.last_event_id().await {
            Ok(id) => id,
            Err(e) => {
                tracing::error!(error = %e, "event tail: cannot read the last event id; starting from 0");
                0
            }
        };
        let mut listener = listen(&database_url, &[crate::store::EVENTS_CHANNEL]).await;
        loop {
            tokio::select! {
                _ = stop.cancelled() => return,
                _ = shared.wake.notified() => {}
                _ = tokio::time::sleep(POLL) => {}
                n = next_notification(&mut listener) => {
                    if n.is_none() {
                        // The listening connection broke: listen again on the next round.
                        listener = listen(&database_url, &[crate::store::EVENTS_CHANNEL]).await;
                    }
                }
            }
            loop {
                match bus.store.events_after(cursor, PAGE).await {
                    Ok(rows) => {
                        let full = rows.len() as i64 == PAGE;
                        for row in rows {
                            cursor = row.id;
                            let _ = bus.tx.send(Arc::new(BusEvent::from(row)));
                        }
                        if !full {
                            break;
                        }
                    }
                    Err(e) => {
                        tracing::warn!(error = %e, "event tail: cannot read new events; retrying");
                        break;
                    }
                }
            }
        }
    });
}

/// Sends this node's transient events to the others and fans theirs out here.
async fn relay_transient(
    bus: EventBus,
    database_url: String,
    stop: tokio_util::sync::CancellationToken,
) {
    let Some(shared) = bus.shared.clone() else {
        return;
    };
    let Some(mut outbox) = shared.outbox_rx.lock().await.take() else {
        return;
    };
    let mut listener = listen(&database_url, &[TRANSIENT_CHANNEL]).await;
    let quiet = fresa_plugin_api::quiet::Quiet::per_minute();
    loop {
        tokio::select! {
            _ = stop.cancelled() => return,
            e = outbox.recv() => {
                let Some(e) = e else { return };
                let payload = e.json();
                if payload.len() > MAX_NOTIFY_PAYLOAD {
                    tracing::debug!(kind = %e.kind, bytes = payload.len(), "transient event too large to share with other nodes");
                    continue;
                }
                if let Err(err) = bus.store.notify(TRANSIENT_CHANNEL, payload).await {
                    tracing::debug!(error = %err, "could not share a transient event with other nodes");
                }
            }
            n = next_notification(&mut listener) => match n {
                Some(payload) => match serde_json::from_str::<BusEvent>(&payload) {
                    Ok(e) if !bus.is_local(&e) => { let _ = bus.tx.send(Arc::new(e)); }
                    Ok(_) => {}
                    Err(err) => {
                        if let Some(line) = quiet.admit("unreadable", || {
                            format!("unreadable transient event from another node; ignored: {err}")
                        }) {
                            tracing::warn!("{line}");
                        }
                    }
                },
                None => listener = listen(&database_url, &[TRANSIENT_CHANNEL]).await,
            },
        }
    }
}

/// A PostgreSQL connection listening on `channels`, or `None` (logged) if it cannot be made now.
async fn listen(url: &str, channels: &[&str]) -> Option<sqlx::postgres::PgListener> {
    let attempt = async {
        let mut l = sqlx::postgres::PgListener::connect(url).await?;
        l.listen_all(channels.iter().copied()).await?;
        Ok::<_, sqlx::Error>(l)
    };
    match attempt.await {
        Ok(l) => Some(l),
        Err(e) => {
            tracing::debug!(error = %e, ?channels, "cannot listen for other nodes' events now; polling");
            None
        }
    }
}

/// The next notification's payload; `None` when the connection broke (after a pause, so a
/// database that is away is not hammered). Pending forever without a listener.
async fn next_notification(listener: &mut Option<sqlx::postgres::PgListener>) -> Option<String> {
    let Some(l) = listener.as_mut() else {
        tokio::time::sleep(std::time::Duration::from_secs(1)).await;
        return None;
    };
    match l.try_recv().await {
        Ok(Some(n)) => Some(n.payload().to_string()),
        Ok(None) | Err(_) => {
            *listener = None;
            tokio::time::sleep(std::time::Duration::from_millis(200)).await;
            None
        }
    }
}

// ---- retention ----

/// The audit trail, kept `audit_retention_days`: what was made, run, set or lost. Every other
/// persisted type (jogs, commands, MDI lines, pendant connects, refusals, rewinds:
/// high-volume traffic) is routine and also goes beyond `event_retention_count`; see
/// [`Keeping`]. Types an older version wrote and this one no longer emits are routine.
pub fn audit_event_types() -> Vec<&'static str> {
    EventKind::ALL
        .iter()
        .filter(|k| k.keeping() == Keeping::Audit)
        .map(|k| k.name())
        .collect()
}

/// Rows per delete: one short write transaction each, so machine tasks and uploads waiting
/// for the write lock get it between batches.
const PRUNE_BATCH: u32 = 1000;
const DAY_MS: i64 = 86_400_000;

/// Deletes what `policy` no longer keeps. Returns how many events went. With a `budget`, stops
/// after the batch that overruns it (the next pass goes on).
pub async fn prune(
    store: &Store,
    policy: &EventRetention,
    budget: Option<std::time::Duration>,
) -> Result<u64, sqlx::Error> {
    let started = std::time::Instant::now();
    let now = now_ms();
    let routine_before = now - i64::from(policy.routine_days) * DAY_MS;
    let audit_before = now - i64::from(policy.audit_days) * DAY_MS;
    // Fixed for the pass: newer events only move the real cut up, never down.
    let audit = audit_event_types();
    let cut = store
        .routine_event_count_cut(&audit, policy.routine_count)
        .await?;
    let mut total = 0;
    loop {
        let n = store
            .prune_events_batch(&audit, routine_before, cut, audit_before, PRUNE_BATCH)
            .await?;
        total += n;
        if n < u64::from(PRUNE_BATCH) || budget.is_some_and(|b| started.elapsed() >= b) {
            return Ok(total);
        }
        // Let queued writers take the lock before the next batch.
        tokio::time::sleep(std::time::Duration::from_millis(5)).await;
    }
}

/// [`prune`], logging the result instead of returning it.
pub async fn prune_and_log(
    store: &Store,
    policy: &EventRetention,
    budget: Option<std::time::Duration>,
) {
    match prune(store, policy, budget).await {
        Ok(0) => {}
        Ok(n) => {
            let left = store.event_count().await.unwrap_or(-1);
            tracing::info!(pruned = n, left, "event log pruned by retention");
        }
        Err(e) => tracing::error!(error = %e, "event log retention pass failed"),
    }
}

/// Runs [`prune`] every `policy.prune_interval` until `stop` is cancelled.
pub fn spawn_pruner(
    store: Store,
    policy: EventRetention,
    stop: tokio_util::sync::CancellationToken,
) -> tokio::task::JoinHandle<()> {
    tokio::spawn(async move {
        loop {
            tokio::select! {
                _ = stop.cancelled() => return,
                _ = tokio::time::sleep(policy.prune_interval) => {}
            }
            prune_and_log(&store, &policy, None).await;
        }
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    /// The wire names are the API: pinned here, so a rename shows up as a failing test.
    #[test]
    fn event_types_keep_their_wire_names_and_keeping() {
        let names: Vec<&str> = EventKind::ALL.iter().map(|k| k.name()).collect();
        let mut unique = names.clone();
        unique.sort_unstable();
        unique.dedup();
        assert_eq!(unique.len(), names.len(), "duplicate wire names: {names:?}");
        for k in EventKind::ALL {
            assert_eq!(EventKind::from_name(k.name()), Some(*k));
        }
        assert_eq!(EventKind::from_name("bench.event"), None);
        let live: Vec<&str> = EventKind::ALL
            .iter()
            .filter(|k| !k.is_persisted())
            .map(|k| k.name())
            .collect();
        assert_eq!(
            live,
            [
                "status",
                "job.progress",
                "job.line_report",
                "machine.io",
                "machine.state",
                "height_map.progress"
            ]
        );
        assert_eq!(
            audit_event_types(),
            [
                "job.created",
                "job.state",
                "machine.created",
                "machine.offsets",
                "machine.part_zero",
                "machine.touch_off",
                "machine.alarm",
                "machine.node",
                "machine.tools",
                "machine.run_settings",
                "machine.tool_measured",
                "pendant.created",
                "pendant.bound",
                "pendant.macro",
                "pendant.deleted",
                "pendant.node",
                "pendant.upload",
                "webhook.created",
                "webhook.deleted",
                "height_map.ended",
                "height_map.deleted",
                "queue.add",
                "queue.remove",
                "queue.move",
                "queue.waiting_confirm",
                "queue.confirm",
                "queue.started",
                "queue.hold",
                "queue.release",
                "queue.done",
                "queue.dispatch",
                "machine.maintenance_due",
                "machine.maintenance_done",
            ]
        );
    }

    /// Every persisted event goes out as JSON once, whoever reads it.
    #[test]
    fn an_event_is_serialised_once_and_as_before() {
        let e = BusEvent::new(
            Some(3),
            EventKind::JobState.name().into(),
            Some(1),
            Some("op".into()),
            5,
            serde_json::json!({"job": 2}),
            None,
        );
        let first = e.json() as *const str;
        assert_eq!(e.json() as *const str, first);
        let v: serde_json::Value = serde_json::from_str(e.json()).unwrap();
        assert_eq!(
            v,
            serde_json::json!({"id": 3, "type": "job.state", "machine": 1, "actor": "op", "time": 5, "data": {"job": 2}})
        );
        assert_eq!(e.data_json(), r#"{"job":2}"#);
    }

    #[tokio::test]
    async fn retention_cuts_routine_events_by_count_and_keeps_the_audit() {
        let dir = std::env::temp_dir().join(format!(
            "fresa-retention-{}-{}",
            std::process::id(),
            rand::random::<u64>()
        ));
        std::fs::create_dir_all(&dir).unwrap();
        let store = Store::open(&dir.join("t.db")).await.unwrap();
        let bus = EventBus::new(store.clone(), 16);
        let created = bus
            .record(
                EventKind::MachineCreated,
                Some(1),
                None,
                serde_json::json!({}),
            )
            .await
            .unwrap();
        let mut jogs = Vec::new();
        for _ in 0..10 {
            jogs.push(
                bus.record(EventKind::MachineJog, Some(1), None, serde_json::json!({}))
                    .await
                    .unwrap(),
            );
        }
        let state = bus
            .record(EventKind::JobState, Some(1), None, serde_json::json!({}))
            .await
            .unwrap();
        let policy = EventRetention {
            routine_count: 3,
            ..EventRetention::default()
        };
        assert_eq!(store.events_pruned_through().await.unwrap(), 0);
        assert_eq!(prune(&store, &policy, None).await.unwrap(), 7);
        let left: Vec<i64> = store
            .events_after(0, 100)
            .await
            .unwrap()
            .iter()
            .map(|e| e.id)
            .collect();
        let mut want = vec![created];
        want.extend(&jogs[7..]);
        want.push(state);
        assert_eq!(left, want);
        assert_eq!(store.events_pruned_through().await.unwrap(), jogs[6]);
        // A second pass has nothing left to do and keeps the mark.
        assert_eq!(prune(&store, &policy, None).await.unwrap(), 0);
        assert_eq!(store.events_pruned_through().await.unwrap(), jogs[6]);
        std::fs::remove_dir_all(dir).ok();
    }
}

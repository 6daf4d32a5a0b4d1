//! The event bus: persisted events (job state, commands, offsets, alarms: the audit log) get an
//! id from the `events` table and can be replayed with `Last-Event-ID`; transient events
//! (status, job progress) are only fanned out, since the next one supersedes them.

use crate::store::{now_ms, EventRow, Store};
use serde::Serialize;
use std::sync::Arc;
use tokio::sync::{broadcast, Mutex};

#[derive(Debug, Clone, Serialize)]
pub struct BusEvent {
    /// Present on persisted events only.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub id: Option<i64>,
    #[serde(rename = "type")]
    pub kind: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub machine: Option<i64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub actor: Option<String>,
    pub time: i64,
    pub data: serde_json::Value,
}

impl From<EventRow> for BusEvent {
    fn from(r: EventRow) -> Self {
        BusEvent {
            id: Some(r.id),
            kind: r.kind,
            machine: r.machine_id,
            actor: r.actor,
            time: r.created_at,
            data: serde_json::from_str(&r.data).unwrap_or(serde_json::Value::Null),
        }
    }
}

#[derive(Clone)]
pub struct EventBus {
    store: Store,
    tx: broadcast::Sender<Arc<BusEvent>>,
    /// Persist-then-send under one lock so live subscribers see ids in increasing order.
    order: Arc<Mutex<()>>,
}

impl EventBus {
    pub fn new(store: Store, capacity: usize) -> Self {
        let (tx, _) = broadcast::channel(capacity);
        EventBus {
            store,
            tx,
            order: Arc::new(Mutex::new(())),
        }
    }

    /// Appends to the event log and fans out. Returns the event id.
    pub async fn record(
        &self,
        kind: &str,
        machine: Option<i64>,
        actor: Option<&str>,
        data: serde_json::Value,
    ) -> Result<i64, sqlx::Error> {
        let _guard = self.order.lock().await;
        let row = self
            .store
            .append_event(kind, machine, actor, &data.to_string())
            .await?;
        let id = row.id;
        let _ = self.tx.send(Arc::new(BusEvent {
            id: Some(id),
            kind: kind.to_string(),
            machine,
            actor: actor.map(str::to_string),
            time: row.created_at,
            data,
        }));
        Ok(id)
    }

    /// Like [`record`](Self::record) but logs instead of failing: for events whose loss must not
    /// fail the action that caused them.
    pub async fn record_or_log(
        &self,
        kind: &str,
        machine: Option<i64>,
        actor: Option<&str>,
        data: serde_json::Value,
    ) {
        if let Err(e) = self.record(kind, machine, actor, data).await {
            tracing::error!(kind, error = %e, "could not persist event");
        }
    }

    pub fn transient(&self, kind: &str, machine: Option<i64>, data: serde_json::Value) {
        let _ = self.tx.send(Arc::new(BusEvent {
            id: None,
            kind: kind.to_string(),
            machine,
            actor: None,
            time: now_ms(),
            data,
        }));
    }

    pub fn subscribe(&self) -> broadcast::Receiver<Arc<BusEvent>> {
        self.tx.subscribe()
    }

    /// Live event-stream subscribers (SSE clients and internal listeners).
    pub fn subscribers(&self) -> usize {
        self.tx.receiver_count()
    }
}

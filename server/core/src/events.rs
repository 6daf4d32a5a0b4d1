//! The event bus: persisted events (job state, commands, offsets, alarms: the audit log) get an
//! id from the `events` table and can be replayed with `Last-Event-ID`; transient events
//! (status, job progress) are only fanned out, since the next one supersedes them.

use crate::config::EventRetention;
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

// ---- retention ----

/// The audit trail, kept `audit_retention_days`: what was made, run, set or lost. Every other
/// type (jogs, commands, MDI lines, pendant connects, refusals, rewinds: high-volume traffic)
/// is routine and also goes beyond `event_retention_count`. A new event type is routine
/// unless it is added here.
pub const AUDIT_EVENT_TYPES: &[&str] = &[
    "job.created",
    "job.state",
    "machine.created",
    "machine.offsets",
    "machine.part_zero",
    "machine.alarm",
    "machine.tools",
    "pendant.created",
    "pendant.bound",
    "pendant.macro",
    "pendant.deleted",
    "pendant.upload",
    "webhook.created",
    "webhook.deleted",
];

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
    let cut = store
        .routine_event_count_cut(AUDIT_EVENT_TYPES, policy.routine_count)
        .await?;
    let mut total = 0;
    loop {
        let n = store
            .prune_events_batch(
                AUDIT_EVENT_TYPES,
                routine_before,
                cut,
                audit_before,
                PRUNE_BATCH,
            )
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
            .record("machine.created", Some(1), None, serde_json::json!({}))
            .await
            .unwrap();
        let mut jogs = Vec::new();
        for _ in 0..10 {
            jogs.push(
                bus.record("machine.jog", Some(1), None, serde_json::json!({}))
                    .await
                    .unwrap(),
            );
        }
        let state = bus
            .record("job.state", Some(1), None, serde_json::json!({}))
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

//! The event (audit) log: appended by the bus, pruned by retention in bounded batches.

use super::{now_ms, Result, Store};
use sqlx::FromRow;

#[derive(Debug, Clone, FromRow)]
pub struct EventRow {
    pub id: i64,
    #[sqlx(rename = "type")]
    pub kind: String,
    pub machine_id: Option<i64>,
    pub actor: Option<String>,
    pub data: String,
    pub created_at: i64,
    /// The node it happened on (`None`: before nodes, or a tool).
    pub node: Option<String>,
}

/// The PostgreSQL advisory lock key that orders event appends across nodes ("fresa" in ASCII).
const EVENT_APPEND_LOCK: i64 = 0x0066_7265_7361;
/// The PostgreSQL notification channel that says "new events were committed".
pub const EVENTS_CHANNEL: &str = "fresa_events";

impl Store {
    // ---- events ----

    /// Appends an event. On PostgreSQL, appends from every node are serialised by a
    /// transaction-level advisory lock, so ids are committed in increasing order: a node that
    /// reads "everything after id N" never misses a lower id committed later. The `NOTIFY` in
    /// the same transaction wakes every node's tail when it commits.
    pub async fn append_event(
        &self,
        kind: &str,
        machine_id: Option<i64>,
        actor: Option<&str>,
        data: &str,
    ) -> Result<EventRow> {
        let mut tx = self.begin().await?;
        if self.dialect == super::Dialect::Postgres {
            sqlx::query("SELECT pg_advisory_xact_lock($1)")
                .bind(EVENT_APPEND_LOCK)
                .execute(&mut *tx)
                .await?;
        }
        let row: EventRow = sqlx::query_as(
            "INSERT INTO events (type, machine_id, actor, data, created_at, node) VALUES ($1, $2, $3, $4, $5, $6) RETURNING *",
        )
        .bind(kind)
        .bind(machine_id)
        .bind(actor)
        .bind(data)
        .bind(now_ms())
        .bind(self.node())
        .fetch_one(&mut *tx)
        .await?;
        if self.dialect == super::Dialect::Postgres {
            sqlx::query(&format!("NOTIFY {EVENTS_CHANNEL}"))
                .execute(&mut *tx)
                .await?;
        }
        tx.commit().await?;
        Ok(row)
    }

    /// A PostgreSQL notification (`pg_notify`) to every listening node.
    pub async fn notify(&self, channel: &str, payload: &str) -> Result<()> {
        sqlx::query("SELECT pg_notify($1, $2)")
            .bind(channel)
            .bind(payload)
            .execute(&self.pool)
            .await
            .map(|_| ())
    }

    pub async fn events_after(&self, after_id: i64, limit: i64) -> Result<Vec<EventRow>> {
        sqlx::query_as("SELECT * FROM events WHERE id > $1 ORDER BY id LIMIT $2")
            .bind(after_id)
            .bind(limit)
            .fetch_all(&self.pool)
            .await
    }

    /// The highest event id retention has deleted (0: none). A replay from an earlier id has
    /// a gap.
    pub async fn events_pruned_through(&self) -> Result<i64> {
        sqlx::query_scalar("SELECT pruned_through FROM event_retention WHERE id = 1")
            .fetch_optional(&self.pool)
            .await
            .map(Option::unwrap_or_default)
    }

    /// The id of the newest routine event (type not in `audit_types`) that is beyond the
    /// newest `keep` of them: routine events up to it are past the count limit.
    pub async fn routine_event_count_cut(
        &self,
        audit_types: &[&str],
        keep: u64,
    ) -> Result<Option<i64>> {
        let n = audit_types.len();
        let sql = format!(
            "SELECT id FROM events WHERE type NOT IN ({}) ORDER BY id DESC LIMIT 1 OFFSET ${}",
            placeholders(1, n),
            n + 1
        );
        let mut q = sqlx::query_scalar(&sql);
        for t in audit_types {
            q = q.bind(*t);
        }
        q.bind(i64::try_from(keep).unwrap_or(i64::MAX))
            .fetch_optional(&self.pool)
            .await
    }

    /// Deletes at most `batch` of the oldest events that retention allows to go: routine
    /// events created before `routine_before` (ms) or with id <= `routine_cut`, audit events
    /// created before `audit_before`. Returns how many went.
    pub async fn prune_events_batch(
        &self,
        audit_types: &[&str],
        routine_before: i64,
        routine_cut: Option<i64>,
        audit_before: i64,
        batch: u32,
    ) -> Result<u64> {
        // Parameters: $1 the id bound, then the condition's (the type list twice).
        let n = audit_types.len();
        let first = placeholders(2, n);
        let second = placeholders(n + 4, n);
        let (before, cut, audit) = (n + 2, n + 3, 2 * n + 4);
        let cond = format!(
            "((type NOT IN ({first}) AND (created_at < ${before} OR id <= ${cut}))
               OR (type IN ({second}) AND created_at < ${audit}))"
        );
        macro_rules! bind_cond {
            ($q:expr) => {{
                let mut q = $q;
                for t in audit_types {
                    q = q.bind(*t);
                }
                q = q.bind(routine_before).bind(routine_cut.unwrap_or(0));
                for t in audit_types {
                    q = q.bind(*t);
                }
                q.bind(audit_before)
            }};
        }
        // Find the batch with a plain read (WAL readers take no lock), so the write below
        // only scans up to its last id, however much of the log is kept. NOT INDEXED: walk in
        // id order and stop at `batch` matches; the planner would otherwise collect every
        // match of the OR through the created_at index and sort them, each batch.
        // (PostgreSQL has no NOT INDEXED; its planner picks the id order for a LIMIT.)
        let not_indexed = self.pick("NOT INDEXED", "");
        let find = format!(
            "SELECT MAX(id) FROM (SELECT id FROM events {not_indexed} WHERE {cond} ORDER BY id LIMIT $1) AS batch"
        );
        let upto: Option<i64> = bind_cond!(sqlx::query_scalar(&find).bind(i64::from(batch)))
            .fetch_one(&self.pool)
            .await?;
        let Some(upto) = upto else {
            return Ok(0);
        };
        // The condition is fixed for the pass and newer events have higher ids: this deletes
        // exactly the batch found above.
        let delete = format!("DELETE FROM events {not_indexed} WHERE id <= $1 AND {cond}");
        let mut tx = self.begin().await?;
        let n = bind_cond!(sqlx::query(&delete).bind(upto))
            .execute(&mut *tx)
            .await?
            .rows_affected();
        sqlx::query(self.pick(
            "UPDATE event_retention SET pruned_through = MAX(pruned_through, $1) WHERE id = 1",
            "UPDATE event_retention SET pruned_through = GREATEST(pruned_through, $1) WHERE id = 1",
        ))
        .bind(upto)
        .execute(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(n)
    }

    /// The highest id ever given to an event (deleted or not): AUTOINCREMENT never reuses one,
    /// so a client holding a higher id saw another log (the store was restored from a backup).
    pub async fn last_event_id(&self) -> Result<i64> {
        sqlx::query_scalar(self.pick(
            "SELECT COALESCE((SELECT seq FROM sqlite_sequence WHERE name = 'events'), 0)",
            // The sequence's last value counts only once it has been used.
            "SELECT CASE WHEN is_called THEN last_value ELSE 0 END FROM events_id_seq",
        ))
        .fetch_one(&self.pool)
        .await
    }

    /// How many events the log holds (for the log line after a prune).
    pub async fn event_count(&self) -> Result<i64> {
        sqlx::query_scalar("SELECT COUNT(*) FROM events")
            .fetch_one(&self.pool)
            .await
    }
}

/// `$first,...` (`n` of them) for an `IN (...)` list; an empty list matches no type.
fn placeholders(first: usize, n: usize) -> String {
    if n == 0 {
        return "''".into();
    }
    (first..first + n)
        .map(|i| format!("${i}"))
        .collect::<Vec<_>>()
        .join(",")
}

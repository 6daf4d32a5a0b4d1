//! Job queues per machine (issue 28, migration 0014): the entries waiting on a machine and
//! where its queue is. The rules (what may follow what) are `crate::queue`'s; these only read
//! and write.

use super::{now_ms, Result, Store};
use sqlx::FromRow;

/// One entry: `count` parts of job `job_id`, `done` of them completed.
#[derive(Debug, Clone, PartialEq, FromRow)]
pub struct QueueEntryRow {
    pub id: i64,
    pub machine_id: i64,
    pub job_id: i64,
    pub position: i64,
    pub count: i64,
    pub done: i64,
    /// 1: each part after the first waits for a confirm too; 0: it starts once the one before
    /// completed.
    pub confirm_between: i64,
    pub created_by: String,
    pub created_at: i64,
}

/// Where a machine's queue is (`idle`, `waiting_confirm`, `running`, `held`).
#[derive(Debug, Clone, PartialEq, FromRow)]
pub struct QueueStateRow {
    pub machine_id: i64,
    pub state: String,
    pub reason: Option<String>,
    pub entry_id: Option<i64>,
    pub run_id: Option<i64>,
    pub updated_at: i64,
}

impl Store {
    // ---- job queues ----

    /// The machine's entries in queue order.
    pub async fn queue_entries(&self, machine_id: i64) -> Result<Vec<QueueEntryRow>> {
        sqlx::query_as("SELECT * FROM queue_entries WHERE machine_id = $1 ORDER BY position, id")
            .bind(machine_id)
            .fetch_all(&self.pool)
            .await
    }

    pub async fn queue_state(&self, machine_id: i64) -> Result<Option<QueueStateRow>> {
        sqlx::query_as("SELECT * FROM machine_queues WHERE machine_id = $1")
            .bind(machine_id)
            .fetch_optional(&self.pool)
            .await
    }

    /// Every stored queue state (for the queues of the machines a node drives).
    pub async fn queue_states(&self) -> Result<Vec<QueueStateRow>> {
        sqlx::query_as("SELECT * FROM machine_queues ORDER BY machine_id")
            .fetch_all(&self.pool)
            .await
    }

    pub async fn set_queue_state(
        &self,
        machine_id: i64,
        state: &str,
        reason: Option<&str>,
        entry_id: Option<i64>,
        run_id: Option<i64>,
    ) -> Result<()> {
        let mut tx = self.begin().await?;
        sqlx::query(
            "INSERT INTO machine_queues (machine_id, state, reason, entry_id, run_id, updated_at)
             VALUES ($1, $2, $3, $4, $5, $6)
             ON CONFLICT (machine_id) DO UPDATE SET state = excluded.state,
               reason = excluded.reason, entry_id = excluded.entry_id,
               run_id = excluded.run_id, updated_at = excluded.updated_at",
        )
        .bind(machine_id)
        .bind(state)
        .bind(reason)
        .bind(entry_id)
        .bind(run_id)
        .bind(now_ms())
        .execute(&mut *tx)
        .await?;
        tx.commit().await
    }

    /// Adds an entry at the end of the machine's queue; its id.
    pub async fn insert_queue_entry(
        &self,
        machine_id: i64,
        job_id: i64,
        count: i64,
        confirm_between: bool,
        created_by: &str,
    ) -> Result<i64> {
        let mut tx = self.begin().await?;
        let last: Option<i64> =
            sqlx::query_scalar("SELECT MAX(position) FROM queue_entries WHERE machine_id = $1")
                .bind(machine_id)
                .fetch_one(&mut *tx)
                .await?;
        let id = sqlx::query_scalar(
            "INSERT INTO queue_entries (machine_id, job_id, position, count, done,
               confirm_between, created_by, created_at)
             VALUES ($1, $2, $3, $4, 0, $5, $6, $7) RETURNING id",
        )
        .bind(machine_id)
        .bind(job_id)
        .bind(last.unwrap_or(0) + 1)
        .bind(count)
        .bind(i64::from(confirm_between))
        .bind(created_by)
        .bind(now_ms())
        .fetch_one(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(id)
    }

    /// Removes an entry of the machine's queue; whether there was one.
    pub async fn delete_queue_entry(&self, machine_id: i64, id: i64) -> Result<bool> {
        let mut tx = self.begin().await?;
        let done = sqlx::query("DELETE FROM queue_entries WHERE id = $1 AND machine_id = $2")
            .bind(id)
            .bind(machine_id)
            .execute(&mut *tx)
            .await?;
        tx.commit().await?;
        Ok(done.rows_affected() > 0)
    }

    /// Puts entry `id` at `position` (1-based, clamped to the queue) and renumbers the rest in
    /// their order; false if the machine has no such entry.
    pub async fn move_queue_entry(&self, machine_id: i64, id: i64, position: i64) -> Result<bool> {
        let mut tx = self.begin().await?;
        let mut ids: Vec<i64> = sqlx::query_scalar(
            "SELECT id FROM queue_entries WHERE machine_id = $1 ORDER BY position, id",
        )
        .bind(machine_id)
        .fetch_all(&mut *tx)
        .await?;
        let Some(at) = ids.iter().position(|&e| e == id) else {
            return Ok(false);
        };
        ids.remove(at);
        let to = usize::try_from(position.saturating_sub(1))
            .unwrap_or(0)
            .min(ids.len());
        ids.insert(to, id);
        for (i, e) in ids.iter().enumerate() {
            sqlx::query("UPDATE queue_entries SET position = $1 WHERE id = $2")
                .bind(i as i64 + 1)
                .bind(*e)
                .execute(&mut *tx)
                .await?;
        }
        tx.commit().await?;
        Ok(true)
    }

    /// Counts a completed part of entry `id`; the entry leaves the queue with its last part.
    /// Whether the entry is still there.
    pub async fn queue_part_done(&self, id: i64) -> Result<bool> {
        let mut tx = self.begin().await?;
        sqlx::query("UPDATE queue_entries SET done = done + 1 WHERE id = $1")
            .bind(id)
            .execute(&mut *tx)
            .await?;
        let gone = sqlx::query("DELETE FROM queue_entries WHERE id = $1 AND done >= count")
            .bind(id)
            .execute(&mut *tx)
            .await?;
        tx.commit().await?;
        Ok(gone.rows_affected() == 0)
    }
}

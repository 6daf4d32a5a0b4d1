//! The append-only event (audit) log.

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
}

impl Store {
    // ---- events ----

    pub async fn append_event(
        &self,
        kind: &str,
        machine_id: Option<i64>,
        actor: Option<&str>,
        data: &str,
    ) -> Result<EventRow> {
        let mut tx = self.begin().await?;
        let row: EventRow = sqlx::query_as(
            "INSERT INTO events (type, machine_id, actor, data, created_at) VALUES (?, ?, ?, ?, ?) RETURNING *",
        )
        .bind(kind)
        .bind(machine_id)
        .bind(actor)
        .bind(data)
        .bind(now_ms())
        .fetch_one(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(row)
    }

    pub async fn events_after(&self, after_id: i64, limit: i64) -> Result<Vec<EventRow>> {
        sqlx::query_as("SELECT * FROM events WHERE id > ? ORDER BY id LIMIT ?")
            .bind(after_id)
            .bind(limit)
            .fetch_all(&self.pool)
            .await
    }
}

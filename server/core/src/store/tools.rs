//! Each machine's tool table: the diameters cutter compensation (G41/G42 D) offsets by.

use super::{now_ms, Result, Store};
use serde::{Deserialize, Serialize};
use sqlx::FromRow;

/// One tool of a machine's table, millimetres.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, FromRow)]
pub struct ToolRow {
    /// Tool number: the `T` and `D` words.
    pub tool: i64,
    /// Cutter diameter; G41/G42 offset the path by half of it (negative: the other side).
    pub diameter_mm: f64,
    /// Tool length offset (G43).
    pub length_mm: f64,
    pub description: String,
}

impl ToolRow {
    /// The interpreter's view of a table.
    pub fn to_gcode(rows: &[ToolRow]) -> fresa_gcode::ToolTable {
        fresa_gcode::tool_table(
            rows.iter()
                .filter_map(|r| Some((u32::try_from(r.tool).ok()?, r.diameter_mm, r.length_mm))),
        )
    }
}

impl Store {
    // ---- tool tables ----

    pub async fn tools(&self, machine_id: i64) -> Result<Vec<ToolRow>> {
        sqlx::query_as(
            "SELECT tool, diameter_mm, length_mm, description FROM machine_tools
             WHERE machine_id = $1 ORDER BY tool",
        )
        .bind(machine_id)
        .fetch_all(&self.pool)
        .await
    }

    /// Replaces the whole table in one transaction.
    pub async fn replace_tools(&self, machine_id: i64, tools: &[ToolRow]) -> Result<()> {
        let mut tx = self.begin().await?;
        sqlx::query("DELETE FROM machine_tools WHERE machine_id = $1")
            .bind(machine_id)
            .execute(&mut *tx)
            .await?;
        let now = now_ms();
        for t in tools {
            insert_tool(&mut tx, machine_id, t, now).await?;
        }
        tx.commit().await
    }

    /// Adds or replaces one tool.
    pub async fn upsert_tool(&self, machine_id: i64, tool: &ToolRow) -> Result<()> {
        let mut tx = self.begin().await?;
        insert_tool(&mut tx, machine_id, tool, now_ms()).await?;
        tx.commit().await
    }

    /// Removes one tool; false if the table did not have it.
    pub async fn delete_tool(&self, machine_id: i64, tool: i64) -> Result<bool> {
        let mut tx = self.begin().await?;
        let done = sqlx::query("DELETE FROM machine_tools WHERE machine_id = $1 AND tool = $2")
            .bind(machine_id)
            .bind(tool)
            .execute(&mut *tx)
            .await?;
        tx.commit().await?;
        Ok(done.rows_affected() > 0)
    }
}

async fn insert_tool(
    tx: &mut sqlx::Transaction<'static, sqlx::Any>,
    machine_id: i64,
    t: &ToolRow,
    now: i64,
) -> Result<()> {
    sqlx::query(
        "INSERT INTO machine_tools (machine_id, tool, diameter_mm, length_mm, description, updated_at)
         VALUES ($1, $2, $3, $4, $5, $6)
         ON CONFLICT (machine_id, tool) DO UPDATE SET diameter_mm = excluded.diameter_mm,
         length_mm = excluded.length_mm, description = excluded.description,
         updated_at = excluded.updated_at",
    )
    .bind(machine_id)
    .bind(t.tool)
    .bind(t.diameter_mm)
    .bind(t.length_mm)
    .bind(&t.description)
    .bind(now)
    .execute(&mut **tx)
    .await?;
    Ok(())
}

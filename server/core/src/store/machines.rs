//! Machines, their work offsets and part-zero history.

use super::{now_ms, Result, Store};
use fresa_plugin_api::contract::{AxisValues, WorkOffset};
use serde::Serialize;
use sqlx::FromRow;

#[derive(Debug, Clone, Serialize, FromRow)]
pub struct MachineRow {
    pub id: i64,
    pub name: String,
    pub backend: String,
    #[serde(skip)]
    pub config: String,
    pub max_jog_mm: f64,
    pub max_feed_mm_min: f64,
    /// Fastest probing feed accepted, mm/min.
    pub max_probe_feed_mm_min: f64,
    /// Override ranges, percent (see `limits::OverrideLimits`).
    pub feed_override_min: f64,
    pub feed_override_max: f64,
    pub spindle_override_min: f64,
    pub spindle_override_max: f64,
    pub rapid_override_min: f64,
    pub active_offset: String,
    pub created_at: i64,
    /// The node that drives it (`None`: not claimed yet; see `Store::claim_unowned`).
    pub node: Option<String>,
    /// The machine Z (mm) a start at a line goes up to at least before moving across (see
    /// `crate::start_at`); `None`: not configured.
    pub safe_z_mm: Option<f64>,
}

impl MachineRow {
    pub fn config_json(&self) -> serde_json::Value {
        serde_json::from_str(&self.config).unwrap_or(serde_json::Value::Object(Default::default()))
    }
}

#[derive(Debug, Clone, Serialize, FromRow)]
pub struct PartZeroRow {
    pub id: i64,
    pub machine_id: i64,
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub a: f64,
    pub source: String,
    pub actor: String,
    pub note: Option<String>,
    pub created_at: i64,
}

impl Store {
    // ---- machines ----

    /// A machine with the default override ranges.
    pub async fn insert_machine(
        &self,
        name: &str,
        backend: &str,
        config: &serde_json::Value,
        max_jog_mm: f64,
        max_feed_mm_min: f64,
        max_probe_feed_mm_min: f64,
    ) -> Result<i64> {
        let limits = crate::machine::limits::OverrideLimits::default();
        self.insert_machine_with(
            name,
            backend,
            config,
            [max_jog_mm, max_feed_mm_min, max_probe_feed_mm_min],
            &limits,
        )
        .await
    }

    /// `maxima`: `max_jog_mm`, `max_feed_mm_min`, `max_probe_feed_mm_min`.
    pub async fn insert_machine_with(
        &self,
        name: &str,
        backend: &str,
        config: &serde_json::Value,
        maxima: [f64; 3],
        overrides: &crate::machine::limits::OverrideLimits,
    ) -> Result<i64> {
        let [max_jog_mm, max_feed_mm_min, max_probe_feed_mm_min] = maxima;
        let mut tx = self.begin().await?;
        let now = now_ms();
        let id: i64 = sqlx::query_scalar(
            "INSERT INTO machines (name, backend, config, max_jog_mm, max_feed_mm_min,
                                   max_probe_feed_mm_min, feed_override_min, feed_override_max,
                                   spindle_override_min, spindle_override_max,
                                   rapid_override_min, created_at, node)
             VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12, $13) RETURNING id",
        )
        .bind(name)
        .bind(backend)
        .bind(config.to_string())
        .bind(max_jog_mm)
        .bind(max_feed_mm_min)
        .bind(max_probe_feed_mm_min)
        .bind(overrides.feed_min)
        .bind(overrides.feed_max)
        .bind(overrides.spindle_min)
        .bind(overrides.spindle_max)
        .bind(overrides.rapid_min)
        .bind(now)
        .bind(self.node())
        .fetch_one(&mut *tx)
        .await?;
        for o in WorkOffset::ALL {
            sqlx::query(
                "INSERT INTO work_offsets (machine_id, name, updated_at) VALUES ($1, $2, $3)",
            )
            .bind(id)
            .bind(o.name())
            .bind(now)
            .execute(&mut *tx)
            .await?;
        }
        tx.commit().await?;
        Ok(id)
    }

    /// Sets the machine's `safe_z_mm` (start at a line).
    pub async fn set_machine_safe_z(&self, id: i64, safe_z_mm: Option<f64>) -> Result<()> {
        sqlx::query("UPDATE machines SET safe_z_mm = $1 WHERE id = $2")
            .bind(safe_z_mm)
            .bind(id)
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    pub async fn list_machines(&self) -> Result<Vec<MachineRow>> {
        sqlx::query_as("SELECT * FROM machines ORDER BY id")
            .fetch_all(&self.pool)
            .await
    }

    pub async fn machine(&self, id: i64) -> Result<Option<MachineRow>> {
        sqlx::query_as("SELECT * FROM machines WHERE id = $1")
            .bind(id)
            .fetch_optional(&self.pool)
            .await
    }

    pub async fn machine_by_name(&self, name: &str) -> Result<Option<MachineRow>> {
        sqlx::query_as("SELECT * FROM machines WHERE name = $1")
            .bind(name)
            .fetch_optional(&self.pool)
            .await
    }

    pub async fn set_active_offset(&self, machine_id: i64, offset: WorkOffset) -> Result<()> {
        let mut tx = self.begin().await?;
        sqlx::query("UPDATE machines SET active_offset = $1 WHERE id = $2")
            .bind(offset.name())
            .bind(machine_id)
            .execute(&mut *tx)
            .await?;
        tx.commit().await
    }

    // ---- work offsets ----

    pub async fn offsets(&self, machine_id: i64) -> Result<Vec<(WorkOffset, AxisValues)>> {
        let rows: Vec<(String, f64, f64, f64, f64)> = sqlx::query_as(
            "SELECT name, x, y, z, a FROM work_offsets WHERE machine_id = $1 ORDER BY name",
        )
        .bind(machine_id)
        .fetch_all(&self.pool)
        .await?;
        Ok(rows
            .into_iter()
            .filter_map(|(n, x, y, z, a)| {
                WorkOffset::parse(&n).map(|o| (o, AxisValues { x, y, z, a }))
            })
            .collect())
    }

    /// Saves several offsets atomically (a zero-all changes one table row per axis at once).
    pub async fn set_offsets(
        &self,
        machine_id: i64,
        values: &[(WorkOffset, AxisValues)],
    ) -> Result<()> {
        let mut tx = self.begin().await?;
        let now = now_ms();
        for (o, v) in values {
            sqlx::query(
                "INSERT INTO work_offsets (machine_id, name, x, y, z, a, updated_at) VALUES ($1, $2, $3, $4, $5, $6, $7)
                 ON CONFLICT (machine_id, name) DO UPDATE SET x = excluded.x, y = excluded.y,
                 z = excluded.z, a = excluded.a, updated_at = excluded.updated_at",
            )
            .bind(machine_id)
            .bind(o.name())
            .bind(v.x)
            .bind(v.y)
            .bind(v.z)
            .bind(v.a)
            .bind(now)
            .execute(&mut *tx)
            .await?;
        }
        tx.commit().await
    }

    // ---- part zeros ----

    pub async fn insert_part_zero(
        &self,
        machine_id: i64,
        at: AxisValues,
        source: &str,
        actor: &str,
        note: Option<&str>,
    ) -> Result<PartZeroRow> {
        let mut tx = self.begin().await?;
        let row: PartZeroRow = sqlx::query_as(
            "INSERT INTO part_zeros (machine_id, x, y, z, a, source, actor, note, created_at)
             VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9) RETURNING *",
        )
        .bind(machine_id)
        .bind(at.x)
        .bind(at.y)
        .bind(at.z)
        .bind(at.a)
        .bind(source)
        .bind(actor)
        .bind(note)
        .bind(now_ms())
        .fetch_one(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(row)
    }

    /// The latest part zero recorded for a machine, if any.
    pub async fn latest_part_zero(&self, machine_id: i64) -> Result<Option<PartZeroRow>> {
        sqlx::query_as("SELECT * FROM part_zeros WHERE machine_id = $1 ORDER BY id DESC LIMIT 1")
            .bind(machine_id)
            .fetch_optional(&self.pool)
            .await
    }

    /// The part zero the controller reported when `run` started (see migration 0003).
    pub async fn run_part_zero(&self, run_id: i64) -> Result<Option<AxisValues>> {
        let text: Option<Option<String>> =
            sqlx::query_scalar("SELECT part_zero FROM job_runs WHERE id = $1")
                .bind(run_id)
                .fetch_optional(&self.pool)
                .await?;
        Ok(text.flatten().and_then(|t| serde_json::from_str(&t).ok()))
    }

    pub async fn set_run_part_zero(&self, run_id: i64, at: AxisValues) -> Result<()> {
        let mut tx = self.begin().await?;
        sqlx::query("UPDATE job_runs SET part_zero = $1 WHERE id = $2")
            .bind(serde_json::json!(at).to_string())
            .bind(run_id)
            .execute(&mut *tx)
            .await?;
        tx.commit().await
    }

    pub async fn part_zeros(&self, machine_id: i64) -> Result<Vec<PartZeroRow>> {
        sqlx::query_as("SELECT * FROM part_zeros WHERE machine_id = $1 ORDER BY id DESC")
            .bind(machine_id)
            .fetch_all(&self.pool)
            .await
    }
}

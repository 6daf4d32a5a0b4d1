//! Persistence: one SQLite file in WAL mode. Every write runs in a `BEGIN IMMEDIATE`
//! transaction so concurrent writers queue on SQLite's lock instead of failing mid-transaction.

use fresa_plugin_api::contract::{AxisValues, WorkOffset};
use serde::Serialize;
use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqlitePoolOptions, SqliteSynchronous};
use sqlx::{FromRow, SqlitePool};
use std::path::Path;
use std::str::FromStr;
use std::time::Duration;

pub type Result<T> = std::result::Result<T, sqlx::Error>;

pub fn now_ms() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_millis() as i64)
        .unwrap_or(0)
}

#[derive(Clone)]
pub struct Store {
    pool: SqlitePool,
}

#[derive(Debug, Clone, Serialize, FromRow)]
pub struct MachineRow {
    pub id: i64,
    pub name: String,
    pub backend: String,
    #[serde(skip)]
    pub config: String,
    pub max_jog_mm: f64,
    pub max_feed_mm_min: f64,
    pub active_offset: String,
    pub created_at: i64,
}

impl MachineRow {
    pub fn config_json(&self) -> serde_json::Value {
        serde_json::from_str(&self.config).unwrap_or(serde_json::Value::Object(Default::default()))
    }
}

#[derive(Debug, Clone, Serialize, FromRow)]
pub struct JobRow {
    pub id: i64,
    pub name: String,
    pub machine_id: i64,
    pub sha256: String,
    pub size_bytes: i64,
    pub line_count: i64,
    #[serde(skip)]
    pub analysis: Option<String>,
    pub source: String,
    pub created_at: i64,
}

#[derive(Debug, Clone, Serialize, FromRow)]
pub struct RunRow {
    pub id: i64,
    pub job_id: i64,
    pub machine_id: i64,
    pub state: String,
    pub last_line: i64,
    pub message: Option<String>,
    pub created_at: i64,
    pub started_at: Option<i64>,
    pub ended_at: Option<i64>,
    pub updated_at: i64,
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

#[derive(Debug, Clone, FromRow)]
pub struct TokenRow {
    pub name: String,
    pub role: String,
}

/// Run states that still own the machine.
pub const ACTIVE_RUN_STATES: &str = "('queued','running','paused')";

pub struct NewJob<'a> {
    pub name: &'a str,
    pub machine_id: i64,
    pub sha256: &'a str,
    pub size_bytes: i64,
    pub line_count: i64,
    pub analysis: Option<String>,
    pub source: &'a str,
}

impl Store {
    /// Opens (creating if needed) the database and applies the migrations in `migrations/`.
    pub async fn open(path: &Path) -> Result<Store> {
        let opts = SqliteConnectOptions::from_str(&format!("sqlite://{}", path.display()))?
            .create_if_missing(true)
            .journal_mode(SqliteJournalMode::Wal)
            // NORMAL in WAL mode survives a process crash (kill -9); only an OS crash can lose
            // the last commits, which is an acceptable price for fast acknowledgements.
            .synchronous(SqliteSynchronous::Normal)
            .foreign_keys(true)
            .busy_timeout(Duration::from_secs(10));
        let pool = SqlitePoolOptions::new()
            .max_connections(8)
            .connect_with(opts)
            .await?;
        sqlx::migrate!("../migrations").run(&pool).await?;
        Ok(Store { pool })
    }

    pub async fn ping(&self) -> Result<()> {
        sqlx::query("SELECT 1")
            .execute(&self.pool)
            .await
            .map(|_| ())
    }

    pub(crate) async fn begin(&self) -> Result<sqlx::Transaction<'static, sqlx::Sqlite>> {
        self.pool.begin_with("BEGIN IMMEDIATE").await
    }

    /// For feature modules that keep their queries next to their code (e.g. `pendants`).
    pub(crate) fn pool(&self) -> &SqlitePool {
        &self.pool
    }

    // ---- machines ----

    pub async fn insert_machine(
        &self,
        name: &str,
        backend: &str,
        config: &serde_json::Value,
        max_jog_mm: f64,
        max_feed_mm_min: f64,
    ) -> Result<i64> {
        let mut tx = self.begin().await?;
        let now = now_ms();
        let id: i64 = sqlx::query_scalar(
            "INSERT INTO machines (name, backend, config, max_jog_mm, max_feed_mm_min, created_at)
             VALUES (?, ?, ?, ?, ?, ?) RETURNING id",
        )
        .bind(name)
        .bind(backend)
        .bind(config.to_string())
        .bind(max_jog_mm)
        .bind(max_feed_mm_min)
        .bind(now)
        .fetch_one(&mut *tx)
        .await?;
        for o in WorkOffset::ALL {
            sqlx::query("INSERT INTO work_offsets (machine_id, name, updated_at) VALUES (?, ?, ?)")
                .bind(id)
                .bind(o.name())
                .bind(now)
                .execute(&mut *tx)
                .await?;
        }
        tx.commit().await?;
        Ok(id)
    }

    pub async fn list_machines(&self) -> Result<Vec<MachineRow>> {
        sqlx::query_as("SELECT * FROM machines ORDER BY id")
            .fetch_all(&self.pool)
            .await
    }

    pub async fn machine(&self, id: i64) -> Result<Option<MachineRow>> {
        sqlx::query_as("SELECT * FROM machines WHERE id = ?")
            .bind(id)
            .fetch_optional(&self.pool)
            .await
    }

    pub async fn machine_by_name(&self, name: &str) -> Result<Option<MachineRow>> {
        sqlx::query_as("SELECT * FROM machines WHERE name = ?")
            .bind(name)
            .fetch_optional(&self.pool)
            .await
    }

    pub async fn set_active_offset(&self, machine_id: i64, offset: WorkOffset) -> Result<()> {
        let mut tx = self.begin().await?;
        sqlx::query("UPDATE machines SET active_offset = ? WHERE id = ?")
            .bind(offset.name())
            .bind(machine_id)
            .execute(&mut *tx)
            .await?;
        tx.commit().await
    }

    // ---- work offsets ----

    pub async fn offsets(&self, machine_id: i64) -> Result<Vec<(WorkOffset, AxisValues)>> {
        let rows: Vec<(String, f64, f64, f64, f64)> = sqlx::query_as(
            "SELECT name, x, y, z, a FROM work_offsets WHERE machine_id = ? ORDER BY name",
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
                "INSERT INTO work_offsets (machine_id, name, x, y, z, a, updated_at) VALUES (?, ?, ?, ?, ?, ?, ?)
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
             VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?) RETURNING *",
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
        sqlx::query_as("SELECT * FROM part_zeros WHERE machine_id = ? ORDER BY id DESC LIMIT 1")
            .bind(machine_id)
            .fetch_optional(&self.pool)
            .await
    }

    /// The part zero the controller reported when `run` started (see migration 0003).
    pub async fn run_part_zero(&self, run_id: i64) -> Result<Option<AxisValues>> {
        let text: Option<Option<String>> =
            sqlx::query_scalar("SELECT part_zero FROM job_runs WHERE id = ?")
                .bind(run_id)
                .fetch_optional(&self.pool)
                .await?;
        Ok(text.flatten().and_then(|t| serde_json::from_str(&t).ok()))
    }

    pub async fn set_run_part_zero(&self, run_id: i64, at: AxisValues) -> Result<()> {
        let mut tx = self.begin().await?;
        sqlx::query("UPDATE job_runs SET part_zero = ? WHERE id = ?")
            .bind(serde_json::json!(at).to_string())
            .bind(run_id)
            .execute(&mut *tx)
            .await?;
        tx.commit().await
    }

    pub async fn part_zeros(&self, machine_id: i64) -> Result<Vec<PartZeroRow>> {
        sqlx::query_as("SELECT * FROM part_zeros WHERE machine_id = ? ORDER BY id DESC")
            .bind(machine_id)
            .fetch_all(&self.pool)
            .await
    }

    // ---- jobs and runs ----

    pub async fn insert_job(&self, job: NewJob<'_>) -> Result<i64> {
        let mut tx = self.begin().await?;
        let id = sqlx::query_scalar(
            "INSERT INTO jobs (name, machine_id, sha256, size_bytes, line_count, analysis, source, created_at)
             VALUES (?, ?, ?, ?, ?, ?, ?, ?) RETURNING id",
        )
        .bind(job.name)
        .bind(job.machine_id)
        .bind(job.sha256)
        .bind(job.size_bytes)
        .bind(job.line_count)
        .bind(job.analysis)
        .bind(job.source)
        .bind(now_ms())
        .fetch_one(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(id)
    }

    pub async fn job(&self, id: i64) -> Result<Option<JobRow>> {
        sqlx::query_as("SELECT * FROM jobs WHERE id = ?")
            .bind(id)
            .fetch_optional(&self.pool)
            .await
    }

    pub async fn list_jobs(&self, machine_id: Option<i64>, limit: i64) -> Result<Vec<JobRow>> {
        sqlx::query_as(
            "SELECT * FROM jobs WHERE (?1 IS NULL OR machine_id = ?1) ORDER BY id DESC LIMIT ?2",
        )
        .bind(machine_id)
        .bind(limit)
        .fetch_all(&self.pool)
        .await
    }

    /// Creates a run in state `running`, unless the machine already has an active run
    /// (checked inside the same transaction, so two concurrent starts cannot both win).
    pub async fn start_run(
        &self,
        job_id: i64,
        machine_id: i64,
    ) -> Result<std::result::Result<RunRow, RunRow>> {
        let mut tx = self.begin().await?;
        if let Some(b) = active_run_except(&mut tx, machine_id, None).await? {
            return Ok(Err(b));
        }
        let now = now_ms();
        let row: RunRow = sqlx::query_as(
            "INSERT INTO job_runs (job_id, machine_id, state, created_at, started_at, updated_at)
             VALUES (?, ?, 'running', ?, ?, ?) RETURNING *",
        )
        .bind(job_id)
        .bind(machine_id)
        .bind(now)
        .bind(now)
        .bind(now)
        .fetch_one(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(Ok(row))
    }

    /// Moves a run to `to` only if it is currently in one of `from` (a compare-and-set, so a
    /// late event cannot resurrect a finished run). Returns the updated row if it moved.
    pub async fn transition_run(
        &self,
        run_id: i64,
        from: &[&str],
        to: &str,
        message: Option<&str>,
    ) -> Result<Option<RunRow>> {
        let mut tx = self.begin().await?;
        let current: Option<RunRow> = sqlx::query_as("SELECT * FROM job_runs WHERE id = ?")
            .bind(run_id)
            .fetch_optional(&mut *tx)
            .await?;
        let Some(current) = current else {
            return Ok(None);
        };
        if !from.contains(&current.state.as_str()) {
            return Ok(None);
        }
        let now = now_ms();
        let terminal = matches!(to, "completed" | "failed" | "cancelled" | "interrupted");
        let row: RunRow = sqlx::query_as(
            "UPDATE job_runs SET state = ?, message = ?, updated_at = ?,
               ended_at = CASE WHEN ? THEN ? ELSE NULL END
             WHERE id = ? RETURNING *",
        )
        .bind(to)
        .bind(message)
        .bind(now)
        .bind(terminal)
        .bind(now)
        .bind(run_id)
        .fetch_one(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(Some(row))
    }

    /// Records the last acknowledged line; never moves backwards.
    pub async fn ack_line(&self, run_id: i64, line: i64) -> Result<()> {
        let mut tx = self.begin().await?;
        sqlx::query(
            "UPDATE job_runs SET last_line = MAX(last_line, ?), updated_at = ? WHERE id = ?",
        )
        .bind(line)
        .bind(now_ms())
        .bind(run_id)
        .execute(&mut *tx)
        .await?;
        tx.commit().await
    }

    pub async fn run(&self, id: i64) -> Result<Option<RunRow>> {
        sqlx::query_as("SELECT * FROM job_runs WHERE id = ?")
            .bind(id)
            .fetch_optional(&self.pool)
            .await
    }

    pub async fn latest_run(&self, job_id: i64) -> Result<Option<RunRow>> {
        sqlx::query_as("SELECT * FROM job_runs WHERE job_id = ? ORDER BY id DESC LIMIT 1")
            .bind(job_id)
            .fetch_optional(&self.pool)
            .await
    }

    /// The latest run of each of `job_ids`, in one query (for job lists).
    pub async fn latest_runs(&self, job_ids: &[i64]) -> Result<Vec<RunRow>> {
        if job_ids.is_empty() {
            return Ok(Vec::new());
        }
        let ids = serde_json::to_string(job_ids).unwrap_or_else(|_| "[]".into());
        sqlx::query_as(
            "SELECT * FROM job_runs WHERE id IN (SELECT MAX(id) FROM job_runs
               WHERE job_id IN (SELECT value FROM json_each(?)) GROUP BY job_id)",
        )
        .bind(ids)
        .fetch_all(&self.pool)
        .await
    }

    /// At start-up nothing can be running: every run that was active when the previous process
    /// died becomes `interrupted`, keeping its last acknowledged line for a resume.
    pub async fn interrupt_active_runs(&self) -> Result<Vec<RunRow>> {
        let mut tx = self.begin().await?;
        let rows: Vec<RunRow> = sqlx::query_as(&format!(
            "UPDATE job_runs SET state = 'interrupted', updated_at = ?1, ended_at = ?1,
               message = 'server stopped while the run was ' || state
             WHERE state IN {ACTIVE_RUN_STATES} RETURNING *"
        ))
        .bind(now_ms())
        .fetch_all(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(rows)
    }

    /// Puts an interrupted or paused-by-restart run back to `running` for a resume.
    pub async fn reopen_run(
        &self,
        run_id: i64,
        machine_id: i64,
    ) -> Result<std::result::Result<RunRow, RunRow>> {
        let mut tx = self.begin().await?;
        if let Some(b) = active_run_except(&mut tx, machine_id, Some(run_id)).await? {
            return Ok(Err(b));
        }
        let row: RunRow = sqlx::query_as(
            "UPDATE job_runs SET state = 'running', message = NULL, ended_at = NULL, updated_at = ?
             WHERE id = ? RETURNING *",
        )
        .bind(now_ms())
        .bind(run_id)
        .fetch_one(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(Ok(row))
    }

    /// Number of job runs per state, for `/metrics`.
    pub async fn run_state_counts(&self) -> Result<Vec<(String, i64)>> {
        sqlx::query_as("SELECT state, COUNT(*) FROM job_runs GROUP BY state ORDER BY state")
            .fetch_all(&self.pool)
            .await
    }

    // ---- tokens ----

    pub async fn insert_token(&self, name: &str, role: &str, hash: &str) -> Result<i64> {
        let mut tx = self.begin().await?;
        let id = sqlx::query_scalar(
            "INSERT INTO tokens (name, role, hash, created_at) VALUES (?, ?, ?, ?) RETURNING id",
        )
        .bind(name)
        .bind(role)
        .bind(hash)
        .bind(now_ms())
        .fetch_one(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(id)
    }

    pub async fn token_by_hash(&self, hash: &str) -> Result<Option<TokenRow>> {
        sqlx::query_as("SELECT name, role FROM tokens WHERE hash = ?")
            .bind(hash)
            .fetch_optional(&self.pool)
            .await
    }

    pub async fn token_count(&self) -> Result<i64> {
        sqlx::query_scalar("SELECT COUNT(*) FROM tokens")
            .fetch_one(&self.pool)
            .await
    }

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

/// The run that owns `machine_id` (queued, running or paused), other than `except`. Called
/// inside the write transaction that is about to make a run active, so two starts cannot race.
async fn active_run_except(
    tx: &mut sqlx::Transaction<'static, sqlx::Sqlite>,
    machine_id: i64,
    except: Option<i64>,
) -> Result<Option<RunRow>> {
    sqlx::query_as(&format!(
        "SELECT * FROM job_runs WHERE machine_id = ?1 AND (?2 IS NULL OR id != ?2)
           AND state IN {ACTIVE_RUN_STATES} LIMIT 1"
    ))
    .bind(machine_id)
    .bind(except)
    .fetch_optional(&mut **tx)
    .await
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;

    async fn store() -> (Store, std::path::PathBuf) {
        let dir = std::env::temp_dir().join(format!(
            "fresa-store-{}-{}",
            std::process::id(),
            rand::random::<u64>()
        ));
        std::fs::create_dir_all(&dir).unwrap();
        (Store::open(&dir.join("t.db")).await.unwrap(), dir)
    }

    async fn machine_with_job(s: &Store, lines: i64) -> (i64, i64) {
        let m = s
            .insert_machine("m", "sim-machine", &serde_json::json!({}), 50.0, 1000.0)
            .await
            .unwrap();
        let j = s
            .insert_job(NewJob {
                name: "a",
                machine_id: m,
                sha256: "x",
                size_bytes: 1,
                line_count: lines,
                analysis: None,
                source: "http",
            })
            .await
            .unwrap();
        (m, j)
    }

    #[tokio::test]
    async fn second_start_on_a_busy_machine_is_refused() {
        let (s, dir) = store().await;
        let (m, j) = machine_with_job(&s, 1).await;
        let first = s.start_run(j, m).await.unwrap();
        assert!(first.is_ok());
        let second = s.start_run(j, m).await.unwrap();
        assert_eq!(second.err().map(|r| r.id), first.ok().map(|r| r.id));
        std::fs::remove_dir_all(dir).ok();
    }

    #[tokio::test]
    async fn restart_marks_active_runs_interrupted_and_keeps_last_line() {
        let (s, dir) = store().await;
        let (m, j) = machine_with_job(&s, 9).await;
        let run = s.start_run(j, m).await.unwrap().unwrap();
        s.ack_line(run.id, 5).await.unwrap();
        s.ack_line(run.id, 3).await.unwrap(); // never backwards
        let rows = s.interrupt_active_runs().await.unwrap();
        assert_eq!(rows.len(), 1);
        assert_eq!(rows[0].state, "interrupted");
        assert_eq!(rows[0].last_line, 5);
        // A finished run cannot be moved by a late event.
        assert!(s
            .transition_run(run.id, &["running"], "completed", None)
            .await
            .unwrap()
            .is_none());
        std::fs::remove_dir_all(dir).ok();
    }

    #[tokio::test]
    async fn latest_runs_gives_each_jobs_newest_run() {
        let (s, dir) = store().await;
        let (m, j1) = machine_with_job(&s, 3).await;
        let j2 = s
            .insert_job(NewJob {
                name: "b",
                machine_id: m,
                sha256: "y",
                size_bytes: 1,
                line_count: 1,
                analysis: None,
                source: "http",
            })
            .await
            .unwrap();
        let first = s.start_run(j1, m).await.unwrap().unwrap();
        s.transition_run(first.id, &["running"], "cancelled", None)
            .await
            .unwrap();
        let second = s.start_run(j1, m).await.unwrap().unwrap();
        let mut runs = s.latest_runs(&[j1, j2]).await.unwrap();
        runs.sort_by_key(|r| r.job_id);
        assert_eq!(runs.len(), 1, "job {j2} has no run");
        assert_eq!((runs[0].job_id, runs[0].id), (j1, second.id));
        assert!(s.latest_runs(&[]).await.unwrap().is_empty());
        std::fs::remove_dir_all(dir).ok();
    }

    #[tokio::test]
    async fn a_run_keeps_the_part_zero_it_started_with() {
        let (s, dir) = store().await;
        let (m, j) = machine_with_job(&s, 3).await;
        let run = s.start_run(j, m).await.unwrap().unwrap();
        assert_eq!(s.run_part_zero(run.id).await.unwrap(), None);
        let zero = AxisValues {
            x: -400.0,
            y: 0.5,
            z: -30.0,
            a: 0.0,
        };
        s.set_run_part_zero(run.id, zero).await.unwrap();
        assert_eq!(s.run_part_zero(run.id).await.unwrap(), Some(zero));
        // The run row itself still reads (the new column is not in RunRow).
        assert_eq!(s.run(run.id).await.unwrap().unwrap().id, run.id);
        assert!(s.latest_part_zero(m).await.unwrap().is_none());
        s.insert_part_zero(m, zero, "robot", "robot", None)
            .await
            .unwrap();
        let last = s.latest_part_zero(m).await.unwrap().unwrap();
        assert_eq!((last.source.as_str(), last.y), ("robot", 0.5));
        std::fs::remove_dir_all(dir).ok();
    }
}

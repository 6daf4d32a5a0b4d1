//! Jobs and their runs.

use super::{now_ms, Result, Store};
use serde::Serialize;
use sqlx::FromRow;

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
    pub state: RunState,
    pub last_line: i64,
    pub message: Option<String>,
    pub created_at: i64,
    pub started_at: Option<i64>,
    pub ended_at: Option<i64>,
    pub updated_at: i64,
    /// Set when the server stopped while lines of this run were acknowledged only in memory
    /// (the database could not be written): the highest such line it recorded. `last_line` may
    /// then be behind what ran, and a resume needs `confirm_line` (issue 23).
    pub unstored_line: Option<i64>,
    /// The line the run was started from (a start at a line, issue 26); `None` from line 1.
    /// The lines before it never ran and are never acknowledged.
    pub from_line: Option<i64>,
    /// The height map the run was started with (issue 25), if any; a resume applies it again.
    pub height_map_id: Option<i64>,
}

impl RunRow {
    /// The line a resume of this run goes on from: the one after the last acknowledged, and
    /// never one before the line it was started from.
    pub fn next_line(&self) -> i64 {
        (self.last_line + 1).max(self.from_line.unwrap_or(1))
    }
}

/// A run's state. The database keeps it as the lowercase name; only the machine's task moves a
/// live run between states (see `machine::actor`), and `can_move_to` is the state machine: every
/// write of a run's state checks it inside its transaction (`start_run` creates a run in
/// `running`, its entry state; `transition_run` and `reopen_run` are compare-and-sets;
/// `interrupt_active_runs_of` moves active runs to `interrupted`, which every active state may).
/// There is no `queued` state until there is a queue (the databases' CHECK still allows the
/// name, so adding it back needs no migration).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RunState {
    Running,
    Paused,
    Completed,
    Failed,
    Cancelled,
    Interrupted,
}

impl RunState {
    pub fn as_str(self) -> &'static str {
        match self {
            RunState::Running => "running",
            RunState::Paused => "paused",
            RunState::Completed => "completed",
            RunState::Failed => "failed",
            RunState::Cancelled => "cancelled",
            RunState::Interrupted => "interrupted",
        }
    }

    /// The run still owns its machine.
    pub fn is_active(self) -> bool {
        matches!(self, RunState::Running | RunState::Paused)
    }

    /// Nothing follows these (a new run is a new row).
    pub fn is_final(self) -> bool {
        matches!(self, RunState::Completed | RunState::Cancelled)
    }

    /// The run state machine: running <-> paused -> completed | failed | cancelled |
    /// interrupted; failed | interrupted -> running (resume) | cancelled | completed (a resume
    /// with every line already acknowledged).
    pub fn can_move_to(self, to: RunState) -> bool {
        use RunState::*;
        match (self, to) {
            (Running, Paused) | (Paused, Running) => true,
            (Running | Paused, Completed | Failed | Cancelled | Interrupted) => true,
            (Failed | Interrupted, Running | Cancelled) => true,
            // A resume that finds every line already acknowledged: nothing left to run.
            (Interrupted | Failed, Completed) => true,
            _ => false,
        }
    }
}

// Stored as its name (TEXT on both databases).
impl sqlx::Type<sqlx::Any> for RunState {
    fn type_info() -> sqlx::any::AnyTypeInfo {
        <&str as sqlx::Type<sqlx::Any>>::type_info()
    }
}

impl<'q> sqlx::Encode<'q, sqlx::Any> for RunState {
    fn encode_by_ref(
        &self,
        buf: &mut <sqlx::Any as sqlx::Database>::ArgumentBuffer<'q>,
    ) -> std::result::Result<sqlx::encode::IsNull, sqlx::error::BoxDynError> {
        <&str as sqlx::Encode<'q, sqlx::Any>>::encode_by_ref(&self.as_str(), buf)
    }
}

impl<'r> sqlx::Decode<'r, sqlx::Any> for RunState {
    fn decode(
        value: sqlx::any::AnyValueRef<'r>,
    ) -> std::result::Result<Self, sqlx::error::BoxDynError> {
        let name = <&str as sqlx::Decode<'r, sqlx::Any>>::decode(value)?;
        ALL_RUN_STATES
            .into_iter()
            .find(|s| s.as_str() == name)
            .ok_or_else(|| format!("unknown run state {name:?} in the database").into())
    }
}

pub(super) const ALL_RUN_STATES: [RunState; 6] = [
    RunState::Running,
    RunState::Paused,
    RunState::Completed,
    RunState::Failed,
    RunState::Cancelled,
    RunState::Interrupted,
];

impl std::fmt::Display for RunState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// Run states that still own the machine (`RunState::is_active`), as SQL; a test keeps the two
/// equal.
pub(super) const ACTIVE_RUN_STATES: &str = "('running','paused')";

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
    // ---- jobs and runs ----

    pub async fn insert_job(&self, job: NewJob<'_>) -> Result<i64> {
        let mut tx = self.begin().await?;
        let id = sqlx::query_scalar(
            "INSERT INTO jobs (name, machine_id, sha256, size_bytes, line_count, analysis, source, created_at)
             VALUES ($1, $2, $3, $4, $5, $6, $7, $8) RETURNING id",
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
        sqlx::query_as("SELECT * FROM jobs WHERE id = $1")
            .bind(id)
            .fetch_optional(&self.pool)
            .await
    }

    pub async fn list_jobs(&self, machine_id: Option<i64>, limit: i64) -> Result<Vec<JobRow>> {
        sqlx::query_as(
            "SELECT * FROM jobs WHERE ($1 IS NULL OR machine_id = $1) ORDER BY id DESC LIMIT $2",
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
        self.start_run_from(job_id, machine_id, None).await
    }

    /// [`Store::start_run`] of a run started from `from_line` (`None`: the first line).
    pub async fn start_run_from(
        &self,
        job_id: i64,
        machine_id: i64,
        from_line: Option<i64>,
    ) -> Result<std::result::Result<RunRow, RunRow>> {
        let mut tx = self.begin().await?;
        if let Some(b) = self.active_run_except(&mut tx, machine_id, None).await? {
            return Ok(Err(b));
        }
        let now = now_ms();
        let row: RunRow = sqlx::query_as(
            "INSERT INTO job_runs (job_id, machine_id, state, created_at, started_at, updated_at,
                                   from_line)
             VALUES ($1, $2, 'running', $3, $4, $5, $6) RETURNING *",
        )
        .bind(job_id)
        .bind(machine_id)
        .bind(now)
        .bind(now)
        .bind(now)
        .bind(from_line)
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
        from: &[RunState],
        to: RunState,
        message: Option<&str>,
    ) -> Result<Option<RunRow>> {
        let mut tx = self.begin().await?;
        // PostgreSQL: the row stays locked until commit, so a concurrent transition (another
        // node's) waits and then sees the new state. SQLite's BEGIN IMMEDIATE already excludes it.
        let current: Option<RunRow> = sqlx::query_as(self.pick(
            "SELECT * FROM job_runs WHERE id = $1",
            "SELECT * FROM job_runs WHERE id = $1 FOR UPDATE",
        ))
        .bind(run_id)
        .fetch_optional(&mut *tx)
        .await?;
        let Some(current) = current else {
            return Ok(None);
        };
        if !from.contains(&current.state) || !current.state.can_move_to(to) {
            return Ok(None);
        }
        let now = now_ms();
        let terminal = !to.is_active();
        let row: RunRow = sqlx::query_as(
            "UPDATE job_runs SET state = $1, message = $2, updated_at = $3,
               ended_at = CASE WHEN $4 THEN $5 ELSE NULL END
             WHERE id = $6 RETURNING *",
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
            self.pick(
                "UPDATE job_runs SET last_line = MAX(last_line, $1), updated_at = $2 WHERE id = $3",
                "UPDATE job_runs SET last_line = GREATEST(last_line, $1), updated_at = $2 WHERE id = $3",
            ),
        )
        .bind(line)
        .bind(now_ms())
        .bind(run_id)
        .execute(&mut *tx)
        .await?;
        tx.commit().await
    }

    pub async fn run(&self, id: i64) -> Result<Option<RunRow>> {
        sqlx::query_as("SELECT * FROM job_runs WHERE id = $1")
            .bind(id)
            .fetch_optional(&self.pool)
            .await
    }

    pub async fn latest_run(&self, job_id: i64) -> Result<Option<RunRow>> {
        sqlx::query_as("SELECT * FROM job_runs WHERE job_id = $1 ORDER BY id DESC LIMIT 1")
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
        sqlx::query_as(self.pick(
            "SELECT * FROM job_runs WHERE id IN (SELECT MAX(id) FROM job_runs
               WHERE job_id IN (SELECT value FROM json_each($1)) GROUP BY job_id)",
            "SELECT * FROM job_runs WHERE id IN (SELECT MAX(id) FROM job_runs
               WHERE job_id IN (SELECT value::BIGINT FROM json_array_elements_text($1::JSON))
               GROUP BY job_id)",
        ))
        .bind(ids)
        .fetch_all(&self.pool)
        .await
    }

    /// Puts a run back to `running` for a resume, only if it is in one of `from` (a
    /// compare-and-set like [`Store::transition_run`], so two resumes or a resume racing a
    /// cancel cannot both win) and the machine has no other active run (checked in the same
    /// transaction). `Err(row)`: the other active run, or this run as it is now if it was no
    /// longer in `from`.
    pub async fn reopen_run(
        &self,
        run_id: i64,
        machine_id: i64,
        from: &[RunState],
    ) -> Result<std::result::Result<RunRow, RunRow>> {
        let mut tx = self.begin().await?;
        if let Some(b) = self
            .active_run_except(&mut tx, machine_id, Some(run_id))
            .await?
        {
            return Ok(Err(b));
        }
        let current: RunRow = sqlx::query_as(self.pick(
            "SELECT * FROM job_runs WHERE id = $1",
            "SELECT * FROM job_runs WHERE id = $1 FOR UPDATE",
        ))
        .bind(run_id)
        .fetch_one(&mut *tx)
        .await?;
        if !from.contains(&current.state) || !current.state.can_move_to(RunState::Running) {
            return Ok(Err(current));
        }
        let row: RunRow = sqlx::query_as(
            "UPDATE job_runs SET state = 'running', message = NULL, ended_at = NULL, updated_at = $1
             WHERE id = $2 RETURNING *",
        )
        .bind(now_ms())
        .bind(run_id)
        .fetch_one(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(Ok(row))
    }

    /// Records that lines of a run up to `line` were acknowledged but not stored before the
    /// server stopped (start-up, from the machines' records; see `machine::unstored`). A run
    /// that has ended for good (completed, cancelled) needs no resume and is left alone.
    /// Returns whether a run was marked.
    pub async fn mark_unstored_line(&self, run_id: i64, line: i64) -> Result<bool> {
        let mut tx = self.begin().await?;
        let marked = sqlx::query(self.pick(
            "UPDATE job_runs SET unstored_line = MAX(COALESCE(unstored_line, 0), $1), updated_at = $2
             WHERE id = $3 AND state NOT IN ('completed', 'cancelled')",
            "UPDATE job_runs SET unstored_line = GREATEST(COALESCE(unstored_line, 0), $1), updated_at = $2
             WHERE id = $3 AND state NOT IN ('completed', 'cancelled')",
        ))
        .bind(line)
        .bind(now_ms())
        .bind(run_id)
        .execute(&mut *tx)
        .await?
        .rows_affected()
            > 0;
        tx.commit().await?;
        Ok(marked)
    }

    /// Marks every active run of `machine_id` as in [`Store::mark_unstored_line`], at its stored
    /// line: for a machine whose record of unstored lines could not be read.
    pub async fn mark_unstored_active_runs(&self, machine_id: i64) -> Result<u64> {
        let mut tx = self.begin().await?;
        let n = sqlx::query(&format!(
            "UPDATE job_runs SET unstored_line = last_line, updated_at = $1
             WHERE machine_id = $2 AND state IN {ACTIVE_RUN_STATES}"
        ))
        .bind(now_ms())
        .bind(machine_id)
        .execute(&mut *tx)
        .await?
        .rows_affected();
        tx.commit().await?;
        Ok(n)
    }

    /// The operator's word on where a run whose stored line may be behind stopped: `line` is
    /// its last executed line. Raises `last_line` to it (never lowers it) and clears
    /// `unstored_line`, so the resume goes on from the next line. Returns the run.
    pub async fn confirm_run_line(&self, run_id: i64, line: i64) -> Result<Option<RunRow>> {
        let mut tx = self.begin().await?;
        let row = sqlx::query_as(self.pick(
            "UPDATE job_runs SET last_line = MAX(last_line, $1), unstored_line = NULL, updated_at = $2
             WHERE id = $3 RETURNING *",
            "UPDATE job_runs SET last_line = GREATEST(last_line, $1), unstored_line = NULL, updated_at = $2
             WHERE id = $3 RETURNING *",
        ))
        .bind(line)
        .bind(now_ms())
        .bind(run_id)
        .fetch_optional(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(row)
    }

    /// Number of job runs per state, for `/metrics`.
    pub async fn run_state_counts(&self) -> Result<Vec<(String, i64)>> {
        sqlx::query_as("SELECT state, COUNT(*) FROM job_runs GROUP BY state ORDER BY state")
            .fetch_all(&self.pool)
            .await
    }
}

impl Store {
    /// The run that owns `machine_id` (queued, running or paused), other than `except`. Called
    /// inside the write transaction that is about to make a run active, so two starts cannot
    /// race: on SQLite that transaction holds the write lock; on PostgreSQL the machine's row is
    /// locked first, so a start through another node waits for this one.
    async fn active_run_except(
        &self,
        tx: &mut sqlx::Transaction<'static, sqlx::Any>,
        machine_id: i64,
        except: Option<i64>,
    ) -> Result<Option<RunRow>> {
        if self.dialect() == super::Dialect::Postgres {
            sqlx::query("SELECT id FROM machines WHERE id = $1 FOR UPDATE")
                .bind(machine_id)
                .execute(&mut **tx)
                .await?;
        }
        sqlx::query_as(&format!(
            "SELECT * FROM job_runs WHERE machine_id = $1 AND ($2 IS NULL OR id != $2)
               AND state IN {ACTIVE_RUN_STATES} LIMIT 1"
        ))
        .bind(machine_id)
        .bind(except)
        .fetch_optional(&mut **tx)
        .await
    }
}

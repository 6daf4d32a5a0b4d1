//! The shop's records (issue 28, part 2; migration 0015): part records, machine state changes,
//! maintenance counters and where each maintenance interval stands.

use super::{now_ms, Result, Store};
use serde::Serialize;
use sqlx::FromRow;

/// A part: one run that ended, as `GET /parts` lists it (JSON columns as text; the HTTP layer
/// shows them parsed).
#[derive(Debug, Clone, PartialEq, Serialize, FromRow)]
pub struct PartRow {
    pub id: i64,
    pub run_id: i64,
    pub job_id: i64,
    pub machine_id: i64,
    pub machine_name: String,
    pub node: Option<String>,
    pub program_name: String,
    pub program_sha256: String,
    pub work_offset: String,
    pub work_zero: Option<String>,
    pub part_zero: Option<String>,
    pub tool_table: String,
    pub tool_table_sha256: String,
    pub operators: String,
    pub confirmations: String,
    pub outcome: String,
    pub message: Option<String>,
    pub line_count: i64,
    pub from_line: Option<i64>,
    pub last_line: i64,
    pub lines_run: i64,
    pub estimate_s: Option<f64>,
    pub actual_s: Option<f64>,
    pub started_at: Option<i64>,
    pub ended_at: i64,
}

/// The filters and page of `GET /parts`: newest first, ordered by (`ended_at`, `id`); `before`
/// is the last row of the previous page.
#[derive(Debug, Clone, Default)]
pub struct PartFilter {
    pub job: Option<i64>,
    pub machine: Option<i64>,
    /// `ended_at` at or after (ms).
    pub from: Option<i64>,
    /// `ended_at` before (ms).
    pub to: Option<i64>,
    pub before: Option<(i64, i64)>,
    pub limit: i64,
}

/// Maintenance counters as stored (only ever raised, see [`Store::raise_counters`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, FromRow)]
pub struct CountersRow {
    pub spindle_ms: i64,
    pub motion_ms: i64,
    pub distance_x: f64,
    pub distance_y: f64,
    pub distance_z: f64,
    pub distance_a: f64,
    pub jobs: i64,
}

/// Where one maintenance interval of a machine stands.
#[derive(Debug, Clone, PartialEq, FromRow)]
pub struct MarkRow {
    pub name: String,
    /// The counter's value (hours or jobs) when it was last done.
    pub done_value: f64,
    /// `machine.maintenance_due` was raised for this interval (1) or not (0).
    pub due_raised: i64,
    pub done_at: Option<i64>,
    pub done_by: Option<String>,
}

impl Store {
    // ---- part records ----

    /// Writes the record of a run that ended; a run that ends again (a failed run resumed)
    /// replaces its record, keeping its id.
    pub async fn upsert_part(&self, p: &PartRow) -> Result<()> {
        // Lines only rise: two writes of one end (the end, then a late acknowledged line) may
        // land in either order.
        let max = self.pick("MAX", "GREATEST");
        let sql = format!(
            "INSERT INTO part_records (run_id, job_id, machine_id, machine_name, node,
               program_name, program_sha256, work_offset, work_zero, part_zero, tool_table,
               tool_table_sha256, operators, confirmations, outcome, message, line_count,
               from_line, last_line, lines_run, estimate_s, actual_s, started_at, ended_at)
             VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12, $13, $14, $15, $16, $17,
               $18, $19, $20, $21, $22, $23, $24)
             ON CONFLICT (run_id) DO UPDATE SET node = excluded.node,
               work_offset = excluded.work_offset, work_zero = excluded.work_zero,
               part_zero = excluded.part_zero, tool_table = excluded.tool_table,
               tool_table_sha256 = excluded.tool_table_sha256, operators = excluded.operators,
               confirmations = excluded.confirmations, outcome = excluded.outcome,
               message = excluded.message, from_line = excluded.from_line,
               last_line = {max}(part_records.last_line, excluded.last_line),
               lines_run = {max}(part_records.lines_run, excluded.lines_run),
               estimate_s = excluded.estimate_s, actual_s = excluded.actual_s,
               started_at = excluded.started_at, ended_at = excluded.ended_at"
        );
        let mut tx = self.begin().await?;
        sqlx::query(&sql)
            .bind(p.run_id)
            .bind(p.job_id)
            .bind(p.machine_id)
            .bind(&p.machine_name)
            .bind(&p.node)
            .bind(&p.program_name)
            .bind(&p.program_sha256)
            .bind(&p.work_offset)
            .bind(&p.work_zero)
            .bind(&p.part_zero)
            .bind(&p.tool_table)
            .bind(&p.tool_table_sha256)
            .bind(&p.operators)
            .bind(&p.confirmations)
            .bind(&p.outcome)
            .bind(&p.message)
            .bind(p.line_count)
            .bind(p.from_line)
            .bind(p.last_line)
            .bind(p.lines_run)
            .bind(p.estimate_s)
            .bind(p.actual_s)
            .bind(p.started_at)
            .bind(p.ended_at)
            .execute(&mut *tx)
            .await?;
        tx.commit().await
    }

    /// One page of part records, newest first. Only the filters given are in the statement, so
    /// each filtered query can use its index (`part_records_machine`, `_job`, `_ended`).
    pub async fn parts(&self, f: &PartFilter) -> Result<Vec<PartRow>> {
        let mut sql = String::from("SELECT * FROM part_records WHERE 1 = 1");
        let mut n = 0;
        let mut next = |sql: &mut String, clause: &str| {
            n += 1;
            sql.push_str(&clause.replace('?', &format!("${n}")));
        };
        if f.job.is_some() {
            next(&mut sql, " AND job_id = ?");
        }
        if f.machine.is_some() {
            next(&mut sql, " AND machine_id = ?");
        }
        if f.from.is_some() {
            next(&mut sql, " AND ended_at >= ?");
        }
        if f.to.is_some() {
            next(&mut sql, " AND ended_at < ?");
        }
        if f.before.is_some() {
            // A row value: both databases walk the index from there (an OR of the two
            // comparisons made PostgreSQL scan).
            next(&mut sql, " AND (ended_at, id) < (?");
            next(&mut sql, ", ?)");
        }
        next(&mut sql, " ORDER BY ended_at DESC, id DESC LIMIT ?");
        let mut q = sqlx::query_as::<_, PartRow>(&sql);
        for v in [f.job, f.machine, f.from, f.to].into_iter().flatten() {
            q = q.bind(v);
        }
        if let Some((at, id)) = f.before {
            q = q.bind(at).bind(id);
        }
        q.bind(f.limit).fetch_all(&self.pool).await
    }

    /// The events that name who ran `run` on `machine_id` since `since` (ms): its `job.state`
    /// changes and the queue's `queue.confirm`s, oldest first, at most `limit`.
    pub async fn run_audit(
        &self,
        machine_id: i64,
        since: i64,
        limit: i64,
    ) -> Result<Vec<super::EventRow>> {
        sqlx::query_as(
            "SELECT * FROM events WHERE machine_id = $1 AND created_at >= $2
               AND type IN ('job.state', 'queue.confirm') ORDER BY id LIMIT $3",
        )
        .bind(machine_id)
        .bind(since)
        .bind(limit)
        .fetch_all(&self.pool)
        .await
    }

    // ---- machine states ----

    /// Records that `machine_id` entered `state` at `since` (ms).
    pub async fn insert_machine_state(
        &self,
        machine_id: i64,
        state: &str,
        since: i64,
    ) -> Result<()> {
        let mut tx = self.begin().await?;
        sqlx::query("INSERT INTO machine_states (machine_id, state, since) VALUES ($1, $2, $3)")
            .bind(machine_id)
            .bind(state)
            .bind(since)
            .execute(&mut *tx)
            .await?;
        tx.commit().await
    }

    /// `(state, since)`: the state `machine_id` was in at `from` (its last change at or before
    /// it) and every change in `[from, to)`, in order. Both parts are range reads of
    /// `machine_states_since`.
    pub async fn machine_states(
        &self,
        machine_id: i64,
        from: i64,
        to: i64,
    ) -> Result<Vec<(String, i64)>> {
        sqlx::query_as(
            "SELECT state, since FROM machine_states
             WHERE machine_id = $1 AND since < $3 AND since >= COALESCE(
               (SELECT MAX(since) FROM machine_states WHERE machine_id = $1 AND since <= $2), $2)
             ORDER BY since, id",
        )
        .bind(machine_id)
        .bind(from)
        .bind(to)
        .fetch_all(&self.pool)
        .await
    }

    // ---- counters ----

    pub async fn counters(&self, machine_id: i64) -> Result<Option<CountersRow>> {
        sqlx::query_as(
            "SELECT spindle_ms, motion_ms, distance_x, distance_y, distance_z, distance_a, jobs
             FROM machine_counters WHERE machine_id = $1",
        )
        .bind(machine_id)
        .fetch_optional(&self.pool)
        .await
    }

    /// Stores a machine's counters, each only if higher than what is stored: a writer behind
    /// (a second node, a late retry) can never move them backwards.
    pub async fn raise_counters(&self, machine_id: i64, c: &CountersRow) -> Result<()> {
        let max = self.pick("MAX", "GREATEST");
        let sql = format!(
            "INSERT INTO machine_counters (machine_id, spindle_ms, motion_ms, distance_x,
               distance_y, distance_z, distance_a, jobs, updated_at)
             VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9)
             ON CONFLICT (machine_id) DO UPDATE SET
               spindle_ms = {max}(machine_counters.spindle_ms, excluded.spindle_ms),
               motion_ms = {max}(machine_counters.motion_ms, excluded.motion_ms),
               distance_x = {max}(machine_counters.distance_x, excluded.distance_x),
               distance_y = {max}(machine_counters.distance_y, excluded.distance_y),
               distance_z = {max}(machine_counters.distance_z, excluded.distance_z),
               distance_a = {max}(machine_counters.distance_a, excluded.distance_a),
               jobs = {max}(machine_counters.jobs, excluded.jobs),
               updated_at = excluded.updated_at"
        );
        let mut tx = self.begin().await?;
        sqlx::query(&sql)
            .bind(machine_id)
            .bind(c.spindle_ms)
            .bind(c.motion_ms)
            .bind(c.distance_x)
            .bind(c.distance_y)
            .bind(c.distance_z)
            .bind(c.distance_a)
            .bind(c.jobs)
            .bind(now_ms())
            .execute(&mut *tx)
            .await?;
        tx.commit().await
    }

    // ---- maintenance ----

    pub async fn set_machine_maintenance(&self, id: i64, json: &str) -> Result<()> {
        let mut tx = self.begin().await?;
        sqlx::query("UPDATE machines SET maintenance = $1 WHERE id = $2")
            .bind(json)
            .bind(id)
            .execute(&mut *tx)
            .await?;
        tx.commit().await
    }

    pub async fn machine_maintenance(&self, id: i64) -> Result<Option<String>> {
        sqlx::query_scalar("SELECT maintenance FROM machines WHERE id = $1")
            .bind(id)
            .fetch_optional(&self.pool)
            .await
    }

    pub async fn maintenance_marks(&self, machine_id: i64) -> Result<Vec<MarkRow>> {
        sqlx::query_as(
            "SELECT name, done_value, due_raised, done_at, done_by FROM maintenance_marks
             WHERE machine_id = $1 ORDER BY name",
        )
        .bind(machine_id)
        .fetch_all(&self.pool)
        .await
    }

    /// Marks the interval `name` due (raised); true if this call raised it (it was not yet), so
    /// two writers cannot both announce one crossing.
    pub async fn raise_maintenance_due(&self, machine_id: i64, name: &str) -> Result<bool> {
        let mut tx = self.begin().await?;
        sqlx::query(
            "INSERT INTO maintenance_marks (machine_id, name, done_value, due_raised)
             VALUES ($1, $2, 0, 0) ON CONFLICT (machine_id, name) DO NOTHING",
        )
        .bind(machine_id)
        .bind(name)
        .execute(&mut *tx)
        .await?;
        let changed = sqlx::query(
            "UPDATE maintenance_marks SET due_raised = 1
             WHERE machine_id = $1 AND name = $2 AND due_raised = 0",
        )
        .bind(machine_id)
        .bind(name)
        .execute(&mut *tx)
        .await?
        .rows_affected();
        tx.commit().await?;
        Ok(changed == 1)
    }

    /// The interval `name` was done at counter value `value`: it starts again from there.
    pub async fn maintenance_done(
        &self,
        machine_id: i64,
        name: &str,
        value: f64,
        actor: &str,
    ) -> Result<()> {
        let mut tx = self.begin().await?;
        sqlx::query(
            "INSERT INTO maintenance_marks (machine_id, name, done_value, due_raised, done_at,
               done_by) VALUES ($1, $2, $3, 0, $4, $5)
             ON CONFLICT (machine_id, name) DO UPDATE SET done_value = excluded.done_value,
               due_raised = 0, done_at = excluded.done_at, done_by = excluded.done_by",
        )
        .bind(machine_id)
        .bind(name)
        .bind(value)
        .bind(now_ms())
        .bind(actor)
        .execute(&mut *tx)
        .await?;
        tx.commit().await
    }
}

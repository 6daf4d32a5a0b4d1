//! Height maps (issue 25): grids of probed surface heights, kept per machine (migration 0013),
//! and the map a run was started with (`job_runs.height_map_id`).

use super::{now_ms, Result, Store};
use sqlx::FromRow;

/// A height map as stored. `points` is a JSON array of `nx * ny` work Z values (row by row,
/// Y from `y0` up), `null` where the grid did not get to.
#[derive(Debug, Clone, PartialEq, FromRow)]
pub struct HeightMapRow {
    pub id: i64,
    pub machine_id: i64,
    /// `probing`, `complete`, `stopped`, `failed`.
    pub state: String,
    pub x0: f64,
    pub x1: f64,
    pub y0: f64,
    pub y1: f64,
    pub nx: i64,
    pub ny: i64,
    pub clearance: f64,
    pub distance: f64,
    pub feed: f64,
    /// The work zero in machine coordinates when it was probed (machine - work position).
    pub offset_x: f64,
    pub offset_y: f64,
    pub offset_z: f64,
    pub points: String,
    pub message: Option<String>,
    pub created_by: String,
    pub created_at: i64,
    pub finished_at: Option<i64>,
}

/// What a new map is (its row starts `probing`, every point unknown).
pub struct NewHeightMap<'a> {
    pub machine_id: i64,
    pub area: [f64; 4],
    pub nx: i64,
    pub ny: i64,
    pub clearance: f64,
    pub distance: f64,
    pub feed: f64,
    pub offset: [f64; 3],
    pub points: &'a str,
    pub created_by: &'a str,
}

impl Store {
    // ---- height maps ----

    pub async fn insert_height_map(&self, m: NewHeightMap<'_>) -> Result<i64> {
        let mut tx = self.begin().await?;
        let [x0, x1, y0, y1] = m.area;
        let id = sqlx::query_scalar(
            "INSERT INTO height_maps (machine_id, state, x0, x1, y0, y1, nx, ny, clearance,
               distance, feed, offset_x, offset_y, offset_z, points, created_by, created_at)
             VALUES ($1, 'probing', $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12, $13, $14, $15,
               $16) RETURNING id",
        )
        .bind(m.machine_id)
        .bind(x0)
        .bind(x1)
        .bind(y0)
        .bind(y1)
        .bind(m.nx)
        .bind(m.ny)
        .bind(m.clearance)
        .bind(m.distance)
        .bind(m.feed)
        .bind(m.offset[0])
        .bind(m.offset[1])
        .bind(m.offset[2])
        .bind(m.points)
        .bind(m.created_by)
        .bind(now_ms())
        .fetch_one(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(id)
    }

    /// The points probed so far of a map still `probing`.
    pub async fn update_height_map_points(&self, id: i64, points: &str) -> Result<()> {
        let mut tx = self.begin().await?;
        sqlx::query("UPDATE height_maps SET points = $1 WHERE id = $2 AND state = 'probing'")
            .bind(points)
            .bind(id)
            .execute(&mut *tx)
            .await?;
        tx.commit().await
    }

    /// Ends a map that is `probing`: its final state, points and why (false if it had ended).
    pub async fn finish_height_map(
        &self,
        id: i64,
        state: &str,
        points: &str,
        message: Option<&str>,
    ) -> Result<bool> {
        let mut tx = self.begin().await?;
        let done = sqlx::query(
            "UPDATE height_maps SET state = $1, points = $2, message = $3, finished_at = $4
             WHERE id = $5 AND state = 'probing'",
        )
        .bind(state)
        .bind(points)
        .bind(message)
        .bind(now_ms())
        .bind(id)
        .execute(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(done.rows_affected() > 0)
    }

    pub async fn height_map(&self, id: i64) -> Result<Option<HeightMapRow>> {
        sqlx::query_as("SELECT * FROM height_maps WHERE id = $1")
            .bind(id)
            .fetch_optional(&self.pool)
            .await
    }

    /// A machine's maps, newest first.
    pub async fn list_height_maps(&self, machine_id: i64) -> Result<Vec<HeightMapRow>> {
        sqlx::query_as("SELECT * FROM height_maps WHERE machine_id = $1 ORDER BY id DESC")
            .bind(machine_id)
            .fetch_all(&self.pool)
            .await
    }

    pub async fn count_height_maps(&self, machine_id: i64) -> Result<i64> {
        sqlx::query_scalar("SELECT COUNT(*) FROM height_maps WHERE machine_id = $1")
            .bind(machine_id)
            .fetch_one(&self.pool)
            .await
    }

    /// Removes a map that is not being probed; the removed row, if there was one.
    pub async fn delete_height_map(&self, id: i64) -> Result<Option<HeightMapRow>> {
        let mut tx = self.begin().await?;
        let row: Option<HeightMapRow> = sqlx::query_as(
            "DELETE FROM height_maps WHERE id = $1 AND state <> 'probing' RETURNING *",
        )
        .bind(id)
        .fetch_optional(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(row)
    }

    /// Start-up: maps of `node`'s machines left `probing` by a process that stopped become
    /// `failed` (what they probed is kept); their ids and machines.
    pub async fn fail_probing_height_maps_of(&self, node: &str) -> Result<Vec<(i64, i64)>> {
        let mut tx = self.begin().await?;
        let ids: Vec<(i64, i64)> = sqlx::query_as(
            "UPDATE height_maps SET state = 'failed', finished_at = $1,
               message = 'the server stopped while the grid was being probed'
             WHERE state = 'probing' AND machine_id IN (SELECT id FROM machines WHERE node = $2)
             RETURNING id, machine_id",
        )
        .bind(now_ms())
        .bind(node)
        .fetch_all(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(ids)
    }

    /// Records the height map run `run_id` was started with.
    pub async fn set_run_height_map(&self, run_id: i64, height_map: i64) -> Result<()> {
        let mut tx = self.begin().await?;
        sqlx::query("UPDATE job_runs SET height_map_id = $1 WHERE id = $2")
            .bind(height_map)
            .bind(run_id)
            .execute(&mut *tx)
            .await?;
        tx.commit().await
    }
}

//! Nodes sharing the store: who they are and when they last spoke, which node drives which
//! machine and pendant, the secret they vouch for forwarded requests with, and programs by
//! content so any node can read any job's program.

use super::{now_ms, Result, Store};
use serde::Serialize;
use sqlx::FromRow;

#[derive(Debug, Clone, Serialize, FromRow)]
pub struct NodeRow {
    pub name: String,
    pub url: String,
    pub version: String,
    pub started_at: i64,
    pub heartbeat_at: i64,
    /// JSON: machine id -> status, as of the heartbeat.
    #[serde(skip)]
    pub machines: String,
}

/// Programs are stored in chunks of this size: well under any row or packet limit, few rows.
const CHUNK_BYTES: usize = 256 * 1024;

impl Store {
    /// Records that node `name` (re)started and is reachable at `url`.
    pub async fn register_node(&self, name: &str, url: &str, version: &str) -> Result<()> {
        let now = now_ms();
        let mut tx = self.begin().await?;
        sqlx::query(
            "INSERT INTO nodes (name, url, version, started_at, heartbeat_at, machines)
             VALUES ($1, $2, $3, $4, $4, '{}')
             ON CONFLICT (name) DO UPDATE SET url = $2, version = $3, started_at = $4,
               heartbeat_at = $4",
        )
        .bind(name)
        .bind(url)
        .bind(version)
        .bind(now)
        .execute(&mut *tx)
        .await?;
        tx.commit().await
    }

    /// The node's heartbeat, with its machines' status (JSON object by machine id).
    pub async fn node_heartbeat(&self, name: &str, machines: &str) -> Result<()> {
        let mut tx = self.begin().await?;
        sqlx::query("UPDATE nodes SET heartbeat_at = $1, machines = $2 WHERE name = $3")
            .bind(now_ms())
            .bind(machines)
            .bind(name)
            .execute(&mut *tx)
            .await?;
        tx.commit().await
    }

    pub async fn list_nodes(&self) -> Result<Vec<NodeRow>> {
        sqlx::query_as("SELECT * FROM nodes ORDER BY name")
            .fetch_all(&self.pool)
            .await
    }

    pub async fn node_row(&self, name: &str) -> Result<Option<NodeRow>> {
        sqlx::query_as("SELECT * FROM nodes WHERE name = $1")
            .bind(name)
            .fetch_optional(&self.pool)
            .await
    }

    /// Machines and pendants made before nodes existed become `node`'s (a single box upgraded
    /// keeps driving what it drove). Returns how many machines it took.
    pub async fn claim_unowned(&self, node: &str) -> Result<u64> {
        let mut tx = self.begin().await?;
        let n = sqlx::query("UPDATE machines SET node = $1 WHERE node IS NULL")
            .bind(node)
            .execute(&mut *tx)
            .await?
            .rows_affected();
        sqlx::query("UPDATE pendants SET node = $1 WHERE node IS NULL")
            .bind(node)
            .execute(&mut *tx)
            .await?;
        tx.commit().await?;
        Ok(n)
    }

    /// Moves a machine to another node (the hardware moved). Refused (returns `false`) while it
    /// has an active run: the run belongs to the process driving it.
    pub async fn set_machine_node(&self, machine_id: i64, node: &str) -> Result<bool> {
        let mut tx = self.begin().await?;
        let n = sqlx::query(&format!(
            "UPDATE machines SET node = $1 WHERE id = $2 AND NOT EXISTS
               (SELECT 1 FROM job_runs WHERE machine_id = $2 AND state IN {})",
            super::jobs::ACTIVE_RUN_STATES
        ))
        .bind(node)
        .bind(machine_id)
        .execute(&mut *tx)
        .await?
        .rows_affected();
        tx.commit().await?;
        Ok(n == 1)
    }

    /// The secret nodes sign forwarded requests with; made by the first node that asks.
    pub async fn node_secret(&self) -> Result<String> {
        let fresh = hex::encode(rand::random::<[u8; 32]>());
        let mut tx = self.begin().await?;
        sqlx::query(
            "INSERT INTO cluster (id, node_secret) VALUES (1, $1) ON CONFLICT (id) DO NOTHING",
        )
        .bind(&fresh)
        .execute(&mut *tx)
        .await?;
        let secret: String = sqlx::query_scalar("SELECT node_secret FROM cluster WHERE id = 1")
            .fetch_one(&mut *tx)
            .await?;
        tx.commit().await?;
        Ok(secret)
    }

    // ---- programs by content ----

    /// Stores a program (read from `program`) under its sha256 unless it is there already
    /// (the same program uploaded twice, or by two nodes at once, is stored once). Streams in
    /// chunks: a large program is never held in memory whole.
    pub async fn save_program(
        &self,
        sha256: &str,
        mut program: impl tokio::io::AsyncRead + Unpin,
    ) -> std::result::Result<(), sqlx::Error> {
        use tokio::io::AsyncReadExt;
        if self.has_program(sha256).await? {
            return Ok(());
        }
        let mut tx = self.begin().await?;
        let mut seq = 0i64;
        loop {
            let mut chunk = Vec::with_capacity(CHUNK_BYTES);
            while chunk.len() < CHUNK_BYTES {
                let n = (&mut program)
                    .take((CHUNK_BYTES - chunk.len()) as u64)
                    .read_to_end(&mut chunk)
                    .await
                    .map_err(sqlx::Error::Io)?;
                if n == 0 {
                    break;
                }
            }
            let last = chunk.len() < CHUNK_BYTES;
            // An empty program is one empty chunk, so "stored" means "chunk 0 exists".
            if !chunk.is_empty() || seq == 0 {
                sqlx::query(
                    "INSERT INTO program_chunks (sha256, seq, data) VALUES ($1, $2, $3)
                     ON CONFLICT (sha256, seq) DO NOTHING",
                )
                .bind(sha256)
                .bind(seq)
                .bind(chunk)
                .execute(&mut *tx)
                .await?;
            }
            if last {
                break;
            }
            seq += 1;
        }
        tx.commit().await
    }

    pub async fn has_program(&self, sha256: &str) -> Result<bool> {
        let n: i64 =
            sqlx::query_scalar("SELECT COUNT(*) FROM program_chunks WHERE sha256 = $1 AND seq = 0")
                .bind(sha256)
                .fetch_one(&self.pool)
                .await?;
        Ok(n > 0)
    }

    /// Chunk `seq` (from 0) of a stored program; `None` past the end or when the store does
    /// not have it. Not verified: the reader checks the hash of the whole.
    pub async fn program_chunk(&self, sha256: &str, seq: i64) -> Result<Option<Vec<u8>>> {
        sqlx::query_scalar("SELECT data FROM program_chunks WHERE sha256 = $1 AND seq = $2")
            .bind(sha256)
            .bind(seq)
            .fetch_optional(&self.pool)
            .await
    }

    /// Runs left active on `node`'s machines by a process that is gone become `interrupted`.
    /// Only that node's: the other nodes' runs are theirs, and running.
    pub async fn interrupt_active_runs_of(&self, node: &str) -> Result<Vec<super::RunRow>> {
        let mut tx = self.begin().await?;
        let rows: Vec<super::RunRow> = sqlx::query_as(&format!(
            "UPDATE job_runs SET state = 'interrupted', updated_at = $1, ended_at = $1,
               message = 'server stopped while the run was ' || state
             WHERE state IN {} AND machine_id IN (SELECT id FROM machines WHERE node = $2)
             RETURNING *",
            super::jobs::ACTIVE_RUN_STATES
        ))
        .bind(now_ms())
        .bind(node)
        .fetch_all(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(rows)
    }
}

//! Persistence: one SQLite file in WAL mode. Every write runs in a `BEGIN IMMEDIATE`
//! transaction so concurrent writers queue on SQLite's lock instead of failing mid-transaction.

use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqlitePoolOptions, SqliteSynchronous};
use sqlx::SqlitePool;
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

mod backup;
mod events;
mod jobs;
mod machines;
mod pendants;
#[cfg(test)]
mod tests;
mod tokens;
mod webhooks;

pub use backup::{backup_database, BackupError};
pub use events::EventRow;
pub use jobs::{JobRow, NewJob, RunRow, RunState};
pub use machines::{MachineRow, PartZeroRow};
pub use pendants::{MacroAction, PendantRow};
pub use tokens::{is_unique_violation, TokenInfo, TokenRow};
pub use webhooks::{DeliveryOutcome, WebhookRow, WebhookTarget};

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
        sqlx::migrate!("../../migrations").run(&pool).await?;
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
}

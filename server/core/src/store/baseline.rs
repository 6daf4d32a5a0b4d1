//! A new SQLite store is made from a baseline, the schema (and the rows) migrations 1 to
//! [`VERSION`] leave, in one transaction, and those migrations are recorded in sqlx's table as
//! applied; the migrations after it then run as on any store. Replaying every migration on an
//! empty file was most of a first start (15-25 ms: each `ALTER TABLE` makes SQLite re-read the
//! whole schema), where a store an older version made is upgraded by the migrations as before.
//! This is the usual split (Rails' `schema.rb`, Django's squashed migrations): history for old
//! stores, the current shape for new ones.
//!
//! The baseline (`migrations/baseline/sqlite.sql`) is what SQLite itself holds after the
//! migrations, dumped by the test `a_new_store_from_the_baseline_equals_one_from_every_migration`
//! (which also checks the two agree; `FRESA_WRITE_BASELINE=1` rewrites it). A baseline that falls
//! behind new migrations costs only their time at a first start, never a wrong schema.
//!
//! The store is made in a file beside its place and renamed there once complete, so a first
//! start interrupted half-way leaves no half-made store behind.

use super::Result;
use sqlx::migrate::{Migrate, Migrator};
use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqliteSynchronous};
use sqlx::{ConnectOptions, Connection, Executor};
use std::path::{Path, PathBuf};

/// The last migration the baseline includes.
pub(crate) const VERSION: i64 = 15;

/// The SQLite schema and rows after migrations 1..=[`VERSION`].
pub(crate) const SCHEMA: &str = include_str!("../../../../migrations/baseline/sqlite.sql");

/// Every SQLite migration (the same list `Store::connect` applies).
pub(crate) static MIGRATOR: Migrator = sqlx::migrate!("../../migrations");

/// Makes a new store at `path` (which must not exist) from the baseline.
pub(crate) async fn create(path: &Path) -> Result<()> {
    let new = beside(path);
    remove_leftovers(&new);
    let made = async {
        let mut conn = SqliteConnectOptions::new()
            .filename(&new)
            .create_if_missing(true)
            .journal_mode(SqliteJournalMode::Wal)
            .synchronous(SqliteSynchronous::Normal)
            .connect()
            .await?;
        conn.ensure_migrations_table().await?;
        let mut tx = conn.begin().await?;
        // Several statements in one string: SQLite's executor runs them in turn.
        tx.execute(SCHEMA).await?;
        for m in MIGRATOR.iter().filter(|m| m.version <= VERSION) {
            // The row sqlx writes when it applies a migration (its execution time unknown).
            sqlx::query(
                "INSERT INTO _sqlx_migrations (version, description, success, checksum, execution_time) \
                 VALUES ($1, $2, TRUE, $3, 0)",
            )
            .bind(m.version)
            .bind(&*m.description)
            .bind(&*m.checksum)
            .execute(&mut *tx)
            .await?;
        }
        tx.commit().await?;
        // Closing the only connection checkpoints the WAL into the file (and syncs it).
        conn.close().await
    };
    if let Err(e) = made.await {
        remove_leftovers(&new);
        return Err(e);
    }
    std::fs::rename(&new, path).map_err(sqlx::Error::Io)
}

/// `store.db.new` beside `store.db`.
fn beside(path: &Path) -> PathBuf {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(".new");
    path.with_file_name(name)
}

/// A store a stopped first start was making, with its WAL and shared-memory files.
fn remove_leftovers(new: &Path) {
    for suffix in ["", "-wal", "-shm"] {
        let mut name = new.as_os_str().to_os_string();
        name.push(suffix);
        let file = PathBuf::from(name);
        match std::fs::remove_file(&file) {
            Ok(()) => {
                tracing::info!(file = %file.display(), "removed what a stopped first start left of a new store")
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => {
                tracing::warn!(file = %file.display(), error = %e, "cannot remove a half-made store")
            }
        }
    }
}

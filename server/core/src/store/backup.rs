//! Online backup: `VACUUM INTO` reads one consistent snapshot through SQLite's own locking, so
//! it is safe while a server is writing (WAL readers never block the writer).

use sqlx::sqlite::{SqliteConnectOptions, SqliteConnection};
use sqlx::Connection;
use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::time::Duration;

#[derive(Debug, thiserror::Error)]
pub enum BackupError {
    #[error("{0} exists; refusing to overwrite it (choose another file name)")]
    Exists(PathBuf),
    #[error("no database at {0}: is the data directory right (--data-dir, FRESA_DATA_DIR)?")]
    NoDatabase(PathBuf),
    #[error("database {0} is empty (0 bytes): nothing to back up")]
    EmptyDatabase(PathBuf),
    #[error("backup of {db} into {dest} failed: {source}")]
    Sqlite {
        db: PathBuf,
        dest: PathBuf,
        source: sqlx::Error,
    },
    #[error("the backup {dest} failed its integrity check: {message}")]
    Check { dest: PathBuf, message: String },
    #[error("cannot move the finished backup to {dest}: {source}")]
    Io {
        dest: PathBuf,
        source: std::io::Error,
    },
}

/// Writes a compacted copy of the database at `db` to `dest`, which must not exist; returns
/// its size in bytes. The copy is written beside `dest` first and only appears under `dest`
/// once complete and checked, so an interrupted backup never looks like a good one.
pub async fn backup_database(db: &Path, dest: &Path) -> Result<u64, BackupError> {
    match std::fs::metadata(db) {
        Err(_) => return Err(BackupError::NoDatabase(db.to_path_buf())),
        Ok(m) if m.len() == 0 => return Err(BackupError::EmptyDatabase(db.to_path_buf())),
        Ok(_) => {}
    }
    if dest.exists() {
        return Err(BackupError::Exists(dest.to_path_buf()));
    }
    let name = dest
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "backup".into());
    let partial = dest.with_file_name(format!(".{name}.partial-{}", std::process::id()));
    let sqlite = |source| BackupError::Sqlite {
        db: db.to_path_buf(),
        dest: dest.to_path_buf(),
        source,
    };
    let result = async {
        let opts = SqliteConnectOptions::from_str(&format!("sqlite://{}", db.display()))
            .map_err(sqlite)?
            .create_if_missing(false)
            .busy_timeout(Duration::from_secs(10));
        let mut conn = SqliteConnection::connect_with(&opts)
            .await
            .map_err(sqlite)?;
        sqlx::query("VACUUM INTO $1")
            .bind(partial.to_string_lossy().into_owned())
            .execute(&mut conn)
            .await
            .map_err(sqlite)?;
        conn.close().await.map_err(sqlite)?;
        check(&partial, dest).await?;
        publish(&partial, dest)
    }
    .await;
    if result.is_err() {
        let _ = std::fs::remove_file(&partial);
    }
    result
}

async fn check(partial: &Path, dest: &Path) -> Result<(), BackupError> {
    let fail = |message: String| BackupError::Check {
        dest: dest.to_path_buf(),
        message,
    };
    let opts = SqliteConnectOptions::from_str(&format!("sqlite://{}", partial.display()))
        .map_err(|e| fail(e.to_string()))?
        .read_only(true);
    let mut conn = SqliteConnection::connect_with(&opts)
        .await
        .map_err(|e| fail(e.to_string()))?;
    let verdict: String = sqlx::query_scalar("PRAGMA quick_check")
        .fetch_one(&mut conn)
        .await
        .map_err(|e| fail(e.to_string()))?;
    let _ = conn.close().await;
    if verdict != "ok" {
        return Err(fail(verdict));
    }
    Ok(())
}

/// A hard link fails if `dest` appeared meanwhile, so an existing file is never replaced.
fn publish(partial: &Path, dest: &Path) -> Result<u64, BackupError> {
    let io = |source| BackupError::Io {
        dest: dest.to_path_buf(),
        source,
    };
    match std::fs::hard_link(partial, dest) {
        Ok(()) => {
            let _ = std::fs::remove_file(partial);
        }
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
            return Err(BackupError::Exists(dest.to_path_buf()))
        }
        // Filesystems without hard links: the existence check above has to do.
        Err(_) => std::fs::rename(partial, dest).map_err(io)?,
    }
    std::fs::metadata(dest).map(|m| m.len()).map_err(io)
}

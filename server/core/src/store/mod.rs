//! Persistence on SQLite (the embedded default: one file in WAL mode) or PostgreSQL (shared by
//! several nodes), chosen by the database URL. One set of store functions runs on both through
//! sqlx's `Any` driver: queries use `$N` parameters (both understand them), and the few
//! statements the two dialects write differently are chosen with [`Store::dialect`]. Every
//! write runs in a transaction; on SQLite it is `BEGIN IMMEDIATE`, so concurrent writers queue
//! on SQLite's lock instead of failing mid-transaction.

use sqlx::any::{AnyConnectOptions, AnyPoolOptions};
use sqlx::{AnyPool, Executor};
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

/// `2026-11-30T21:14:03Z` (with `.123` before the `Z` when `millis`) for a Unix time in ms:
/// the one way times are written in messages, logs and the CLI.
pub fn utc_text(ms: i64, millis: bool) -> String {
    let secs = ms.div_euclid(1000);
    let (days, rem) = (secs.div_euclid(86_400), secs.rem_euclid(86_400));
    // Civil date from days since 1970-01-01 (Howard Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    let fraction = if millis {
        format!(".{:03}", ms.rem_euclid(1000))
    } else {
        String::new()
    };
    format!(
        "{year:04}-{month:02}-{day:02}T{:02}:{:02}:{:02}{fraction}Z",
        rem / 3600,
        rem % 3600 / 60,
        rem % 60
    )
}

#[cfg(test)]
#[test]
fn utc_times_match_known_dates() {
    assert_eq!(utc_text(0, false), "1970-01-01T00:00:00Z");
    // `date -u -d @1796073243` = Mon Nov 30 21:14:03 UTC 2026
    assert_eq!(utc_text(1_796_073_243_000, false), "2026-11-30T21:14:03Z");
    assert_eq!(
        utc_text(1_796_073_243_456, true),
        "2026-11-30T21:14:03.456Z"
    );
    assert_eq!(utc_text(951_782_400_000, false), "2000-02-29T00:00:00Z");
}

/// Which database a store runs on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Dialect {
    Sqlite,
    Postgres,
}

#[derive(Clone)]
pub struct Store {
    pool: AnyPool,
    dialect: Dialect,
    health: DbHealth,
    /// Tokens the database accepted, for authentication while it is unreachable.
    known_tokens: tokens::KnownTokens,
    /// The node this process is (see [`Store::for_node`]): machines and pendants it creates
    /// belong to it. `None` in tools and tests that are no node.
    node: Option<std::sync::Arc<str>>,
}

mod backup;
pub(crate) mod baseline;
mod events;
pub mod health;
mod heightmaps;
mod jobs;
mod machines;
mod nodes;
mod pendants;
mod queue;
mod records;
mod run_settings;
#[cfg(any(test, feature = "test-support"))]
pub mod test_postgres;
#[cfg(test)]
mod tests;
mod tokens;
mod tools;
mod webhooks;

pub use backup::{backup_database, BackupError};
pub use events::{EventRow, EVENTS_CHANNEL};
pub use health::{DbHealth, DbState};
pub use heightmaps::{HeightMapRow, NewHeightMap};
pub use jobs::{JobRow, NewJob, RunRow, RunState};
pub use machines::{MachineRow, PartZeroRow};
pub use nodes::NodeRow;
pub use pendants::{MacroAction, PendantRow};
pub use queue::{QueueEntryRow, QueueStateRow};
pub use records::{CountersRow, MarkRow, PartFilter, PartRow};
pub use run_settings::{MachineXyz, RunSettings, ToolChangePolicy, ToolSetter};
pub use tokens::{is_unique_violation, TokenHash, TokenInfo, TokenRow};
pub use tools::ToolRow;
pub use webhooks::{DeliveryOutcome, WebhookRow, WebhookTarget};

impl Store {
    /// Opens (creating if needed) the SQLite database at `path` and applies the migrations.
    /// A new one is made from the baseline schema (see [`baseline`]).
    pub async fn open(path: &Path) -> Result<Store> {
        if matches!(std::fs::metadata(path), Err(e) if e.kind() == std::io::ErrorKind::NotFound) {
            baseline::create(path).await?;
        }
        Store::connect(&sqlite_url(path)).await
    }

    /// Opens `sqlite://PATH` or `postgres://...` and applies that dialect's migrations
    /// (`migrations/` for SQLite, `migrations/postgres/` for PostgreSQL).
    pub async fn connect(url: &str) -> Result<Store> {
        sqlx::any::install_default_drivers();
        let dialect = if url.starts_with("postgres:") || url.starts_with("postgresql:") {
            Dialect::Postgres
        } else if url.starts_with("sqlite:") {
            Dialect::Sqlite
        } else {
            return Err(sqlx::Error::Configuration(
                format!("unsupported database URL {:?}: use sqlite://PATH or postgres://USER@HOST:PORT/DB", redact_url(url)).into(),
            ));
        };
        let opts = AnyConnectOptions::from_str(url)?;
        let pool = match dialect {
            Dialect::Sqlite => {
                AnyPoolOptions::new()
                    .max_connections(8)
                    .before_acquire(|conn, _| {
                        Box::pin(async move { Ok(outside_transaction(conn)) })
                    })
                    .after_connect(|conn, _| {
                        Box::pin(async move {
                            // WAL: readers never wait for the writer. NORMAL in WAL mode
                            // survives a process crash (kill -9); only an OS crash can lose the
                            // last commits, an acceptable price for fast acknowledgements.
                            conn.execute(
                                "PRAGMA journal_mode = WAL; PRAGMA synchronous = NORMAL; \
                                 PRAGMA foreign_keys = ON; PRAGMA busy_timeout = 10000;",
                            )
                            .await
                            .map(|_| ())
                        })
                    })
                    .connect_with(opts)
                    .await?
            }
            Dialect::Postgres => {
                AnyPoolOptions::new()
                    .max_connections(8)
                    .before_acquire(|conn, _| {
                        Box::pin(async move { Ok(outside_transaction(conn)) })
                    })
                    .acquire_timeout(Duration::from_secs(10))
                    .connect_with(opts)
                    .await?
            }
        };
        match dialect {
            Dialect::Sqlite => baseline::MIGRATOR.run(&pool).await?,
            Dialect::Postgres => {
                sqlx::migrate!("../../migrations/postgres")
                    .run(&pool)
                    .await?
            }
        }
        Ok(Store {
            pool,
            dialect,
            health: DbHealth::new(redact_url(url)),
            known_tokens: Default::default(),
            node: None,
        })
    }

    /// The same store, for the node `name`: what it creates belongs to that node.
    pub fn for_node(mut self, name: &str) -> Store {
        self.node = Some(name.into());
        self
    }

    /// The node this store handle belongs to, if any.
    pub fn node(&self) -> Option<&str> {
        self.node.as_deref()
    }

    /// Whether the database answers (shared by every clone of this store).
    pub fn health(&self) -> &DbHealth {
        &self.health
    }

    pub fn dialect(&self) -> Dialect {
        self.dialect
    }

    /// `sqlite` or `postgres`, the same word as the URL scheme.
    pub fn dialect_name(&self) -> &'static str {
        match self.dialect {
            Dialect::Sqlite => "sqlite",
            Dialect::Postgres => "postgres",
        }
    }

    /// The statement for this store's dialect, where the two write it differently.
    pub(crate) fn pick<'a>(&self, sqlite: &'a str, postgres: &'a str) -> &'a str {
        match self.dialect {
            Dialect::Sqlite => sqlite,
            Dialect::Postgres => postgres,
        }
    }

    pub async fn ping(&self) -> Result<()> {
        sqlx::query("SELECT 1")
            .execute(&self.pool)
            .await
            .map(|_| ())
    }

    /// A write the health monitor commits while the database is down: only a write tells
    /// whether a full or read-only disk takes writes again.
    pub async fn probe_write(&self) -> Result<()> {
        let mut tx = self.begin().await?;
        sqlx::query("UPDATE store_probe SET at_ms = $1 WHERE id = 1")
            .bind(now_ms())
            .execute(&mut *tx)
            .await?;
        tx.commit().await
    }

    pub(crate) async fn begin(&self) -> Result<sqlx::Transaction<'static, sqlx::Any>> {
        match self.dialect {
            Dialect::Sqlite => self.pool.begin_with("BEGIN IMMEDIATE").await,
            Dialect::Postgres => self.pool.begin().await,
        }
    }

    /// For feature modules that keep their queries next to their code (e.g. `pendants`).
    pub(crate) fn pool(&self) -> &AnyPool {
        &self.pool
    }
}

/// Whether a pooled connection may be handed out: not if sqlx still counts it inside a
/// transaction. A dropped `Transaction` queues a ROLLBACK, and sqlx-sqlite lowers its count only
/// when that ROLLBACK succeeds; when SQLite has already ended the transaction itself (it rolls
/// back the whole transaction when a COMMIT meets a full disk or an I/O error), the ROLLBACK
/// fails with "no transaction is active", the count stays at 1, and every later `BEGIN
/// IMMEDIATE` on that connection was refused ("attempted to call begin_with at non-zero
/// transaction depth"): one connection in eight failed every write until a restart (issue 23).
/// Such a connection is closed instead (which also rolls back anything SQLite might still hold
/// open) and the pool opens a fresh one.
fn outside_transaction(conn: &mut sqlx::AnyConnection) -> bool {
    let inside = sqlx::Connection::is_in_transaction(conn);
    if inside {
        tracing::warn!("a pooled database connection was left inside a failed transaction; closed");
    }
    !inside
}

/// The URL of the SQLite file at `path`, created when missing. The `Any` driver parses it as a
/// URL before SQLite's own parser sees it, so the path is percent-encoded (SQLite's side
/// decodes it): spaces, `?`, `#` and Windows paths (`C:\ProgramData\...`, where `C:` would
/// otherwise read as a host and port) all arrive intact. `sqlite:` without `//` keeps a drive
/// letter from being taken for a host.
pub fn sqlite_url(path: &Path) -> String {
    let mut url = String::from("sqlite:");
    for b in path.to_string_lossy().bytes() {
        if b.is_ascii_alphanumeric() || b"-._~/:".contains(&b) {
            url.push(b as char);
        } else {
            url.push_str(&format!("%{b:02X}"));
        }
    }
    url.push_str("?mode=rwc");
    url
}

/// A database URL for messages: the password replaced by `***`.
pub fn redact_url(url: &str) -> String {
    match (url.find("://"), url.rfind('@')) {
        (Some(scheme), Some(at)) if at > scheme => {
            let userinfo = &url[scheme + 3..at];
            match userinfo.find(':') {
                Some(colon) => format!(
                    "{}{}:***{}",
                    &url[..scheme + 3],
                    &userinfo[..colon],
                    &url[at..]
                ),
                None => url.to_string(),
            }
        }
        _ => url.to_string(),
    }
}

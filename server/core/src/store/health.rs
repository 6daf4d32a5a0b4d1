//! Whether the database answers, as one `watch` every part of the node reads: the machine tasks
//! start no new motion and keep their writes pending while it is down, the event bus buffers
//! audit events, `/healthz` and `/metrics` report it. A monitor task pings the database with a
//! short timeout; a write that fails for a connection or disk reason (full, I/O error, read-only)
//! marks it down at once. Down is left only when a probe *write* commits: a read answers on a
//! full or read-only disk too, and would end an outage that every write still meets (issue 23).

pub use crate::error::{is_unreachable, outage_reason};
use crate::error::{Error, ErrorKind};
use crate::store::{now_ms, Store};
use std::future::Future;
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::watch;
use tokio_util::sync::CancellationToken;

/// How often the monitor pings, and how long a ping may take before the database counts as down.
pub const PING_INTERVAL: Duration = Duration::from_millis(500);
pub const PING_TIMEOUT: Duration = Duration::from_millis(1000);

#[derive(Debug, Clone, PartialEq, Eq)]
pub enum DbState {
    Up,
    /// Unreachable since `since_ms` (Unix ms), for `reason` (the first error seen).
    Down {
        since_ms: i64,
        reason: String,
    },
}

/// Shared by every clone of a [`Store`].
#[derive(Clone)]
pub struct DbHealth {
    state: Arc<watch::Sender<DbState>>,
    /// The database as people may read it: the URL with its password redacted.
    database: Arc<str>,
}

impl DbHealth {
    pub fn new(database: String) -> DbHealth {
        DbHealth {
            state: Arc::new(watch::channel(DbState::Up).0),
            database: database.into(),
        }
    }

    pub fn database(&self) -> &str {
        &self.database
    }

    pub fn state(&self) -> DbState {
        self.state.borrow().clone()
    }

    pub fn is_up(&self) -> bool {
        matches!(*self.state.borrow(), DbState::Up)
    }

    pub fn subscribe(&self) -> watch::Receiver<DbState> {
        self.state.subscribe()
    }

    /// Marks the database down; an outage already known keeps its start and first reason.
    pub fn mark_down(&self, reason: &str) {
        let changed = self.state.send_if_modified(|s| match s {
            DbState::Up => {
                *s = DbState::Down {
                    since_ms: now_ms(),
                    reason: reason.to_string(),
                };
                true
            }
            DbState::Down { .. } => false,
        });
        if changed {
            tracing::error!(database = %self.database, reason, "database unreachable: no new motion is started, writes are kept until it returns");
        }
    }

    pub fn mark_up(&self) {
        let changed = self.state.send_if_modified(|s| match s {
            DbState::Down { .. } => {
                *s = DbState::Up;
                true
            }
            DbState::Up => false,
        });
        if changed {
            tracing::info!(database = %self.database, "database reachable again");
        }
    }

    /// A failed store call: marks the database down when the error says it cannot take writes
    /// (the reason names the cause: "disk full: ..."). Returns whether it did.
    pub fn observe(&self, e: &sqlx::Error) -> bool {
        match outage_reason(e) {
            Some(reason) => {
                self.mark_down(&reason);
                true
            }
            None => false,
        }
    }

    /// The error for a request refused because the database is down.
    pub fn unavailable_error(&self) -> Error {
        let (since, reason) = match &*self.state.borrow() {
            DbState::Down { since_ms, reason } => (*since_ms, reason.clone()),
            DbState::Up => (now_ms(), "a write failed".to_string()),
        };
        Error::new(
            ErrorKind::Unavailable,
            "database_unavailable",
            format!(
                "the database {} is unavailable since {} ({reason}); no new motion is started until it returns (stop, feed hold, pause and cancel still work)",
                self.database,
                super::utc_text(since, false)
            ),
        )
    }

    /// Ok while the database is up; the `database_unavailable` error otherwise.
    pub fn check(&self) -> Result<(), Error> {
        if self.is_up() {
            Ok(())
        } else {
            Err(self.unavailable_error())
        }
    }

    /// Runs a store call unless the database is known to be down, and gives up on it as soon as
    /// the database is seen down meanwhile (the pool would otherwise keep retrying for its whole
    /// acquire timeout). A call given up on may or may not have committed: callers retry only
    /// writes that are safe to repeat (the store's never-backwards and compare-and-set rules).
    pub async fn guard<T>(&self, call: impl Future<Output = sqlx::Result<T>>) -> Result<T, Error> {
        self.check()?;
        let mut state = self.subscribe();
        tokio::select! {
            r = call => r.map_err(|e| {
                if self.observe(&e) {
                    self.unavailable_error()
                } else {
                    e.into()
                }
            }),
            _ = state.wait_for(|s| *s != DbState::Up) => Err(self.unavailable_error()),
        }
    }

    /// Runs a store *read*. While up it is [`DbHealth::guard`]; while down it is tried anyway,
    /// within [`PING_TIMEOUT`]: a full or read-only disk still answers reads, and an unreachable
    /// database costs at most that. A failure for an outage reason (or no answer) is the
    /// `database_unavailable` error; the read never ends an outage (only a probe write does).
    pub async fn read<T>(&self, call: impl Future<Output = sqlx::Result<T>>) -> Result<T, Error> {
        if self.is_up() {
            return self.guard(call).await;
        }
        match tokio::time::timeout(PING_TIMEOUT, call).await {
            Ok(Ok(v)) => Ok(v),
            Ok(Err(e)) if outage_reason(&e).is_some() => Err(self.unavailable_error()),
            Ok(Err(e)) => Err(e.into()),
            Err(_) => Err(self.unavailable_error()),
        }
    }

    /// One check of the monitor: while up, a ping (a read) that fails or takes longer than
    /// [`PING_TIMEOUT`] marks the database down; while down, only a probe write that commits
    /// within it marks it up again.
    pub async fn probe(&self, store: &Store) {
        let was_up = self.is_up();
        let answer = if was_up {
            tokio::time::timeout(PING_TIMEOUT, store.ping()).await
        } else {
            tokio::time::timeout(PING_TIMEOUT, store.probe_write()).await
        };
        match answer {
            Ok(Ok(())) => self.mark_up(),
            Ok(Err(e)) => self.mark_down(&outage_reason(&e).unwrap_or_else(|| e.to_string())),
            Err(_) => self.mark_down(&format!(
                "no answer to a {} within {} ms",
                if was_up { "ping" } else { "probe write" },
                PING_TIMEOUT.as_millis()
            )),
        }
    }

    /// Runs [`DbHealth::probe`] every [`PING_INTERVAL`] until `shutdown`.
    pub fn spawn_monitor(&self, store: Store, shutdown: CancellationToken) {
        let health = self.clone();
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(PING_INTERVAL);
            tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            loop {
                tokio::select! {
                    _ = shutdown.cancelled() => return,
                    _ = tick.tick() => {}
                }
                health.probe(&store).await;
            }
        });
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn an_outage_keeps_its_start_and_ends_only_when_marked_up() {
        let h = DbHealth::new("postgres://fresa@db/x".into());
        assert!(h.check().is_ok());
        h.mark_down("connection refused");
        let DbState::Down { since_ms, .. } = h.state() else {
            panic!("not down")
        };
        h.mark_down("another error");
        assert_eq!(
            h.state(),
            DbState::Down {
                since_ms,
                reason: "connection refused".into()
            }
        );
        let e = h.check().unwrap_err();
        assert_eq!(e.code, "database_unavailable");
        assert!(e.message.contains("postgres://fresa@db/x"), "{}", e.message);
        assert!(e.message.contains("connection refused"), "{}", e.message);
        h.mark_up();
        assert!(h.is_up());
    }

    #[test]
    fn connection_failures_count_as_unreachable_and_refusals_do_not() {
        assert!(is_unreachable(&sqlx::Error::PoolTimedOut));
        assert!(is_unreachable(&sqlx::Error::Io(std::io::Error::from(
            std::io::ErrorKind::ConnectionRefused
        ))));
        assert!(!is_unreachable(&sqlx::Error::RowNotFound));
    }
}

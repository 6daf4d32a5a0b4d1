//! API tokens (hashed). A token is valid while its row exists and it has not expired:
//! revoking deletes the row, so nothing that checks tokens can forget to check revocation.

use super::{now_ms, Result, Store};
use sqlx::FromRow;

/// Last use is written at most this often per token, so checking a token stays a read.
const LAST_USED_GRANULARITY_MS: i64 = 60_000;

/// While the database is unreachable, a token it accepted this recently still authenticates, so
/// an operator's stop, pause or cancel over the network is not refused for want of the token
/// table (a revocation made meanwhile by another process is seen once the database returns).
const KNOWN_TOKEN_TTL_MS: i64 = 10 * 60_000;

/// Tokens the database accepted: hash -> (row, expires_at, when it was accepted). Keyed by the
/// digest, which a client cannot choose (that would take a SHA-256 preimage), so a fast hasher
/// without SipHash's defence against chosen keys is safe here; every read with a token looks
/// one up.
pub(crate) type KnownTokens = std::sync::Arc<
    std::sync::Mutex<
        std::collections::HashMap<
            String,
            (TokenRow, Option<i64>, i64),
            foldhash::fast::RandomState,
        >,
    >,
>;

/// A token's SHA-256 as the 64 lowercase hex digits the `tokens` table keeps: the one place
/// that says how a secret is stored, for everything that checks or creates tokens (HTTP, MQTT,
/// `fresa token`). Made on the stack, since a read with a token hashes it on every request.
pub struct TokenHash([u8; 64]);

impl TokenHash {
    pub fn of(secret: &str) -> TokenHash {
        use sha2::{Digest, Sha256};
        let mut hex = [0; 64];
        // Cannot fail: 32 bytes are always 64 digits.
        let _ = hex::encode_to_slice(Sha256::digest(secret.as_bytes()), &mut hex);
        TokenHash(hex)
    }

    pub fn as_str(&self) -> &str {
        std::str::from_utf8(&self.0).unwrap_or_default()
    }
}

/// A valid token's name and role. Shared text: the tokens the store remembers are handed out
/// on every read that carries one (`token_accepted_within`), and a clone is a count, not a copy.
#[derive(Debug, Clone)]
pub struct TokenRow {
    pub name: std::sync::Arc<str>,
    pub role: std::sync::Arc<str>,
}

/// What `fresa token list` shows: everything but the hash. Times are UTC, `YYYY-MM-DD HH:MM`.
#[derive(Debug, Clone)]
pub struct TokenInfo {
    pub name: String,
    pub role: String,
    pub created: String,
    pub expires: Option<String>,
    pub expired: bool,
    pub last_used: Option<String>,
}

/// A `list_tokens` row as the database gives it: `expired` as 0/1, because the Any driver
/// decodes booleans only from real ones (SQLite has none).
#[derive(FromRow)]
struct TokenListRow {
    name: String,
    role: String,
    created: String,
    expires: Option<String>,
    expired: i64,
    last_used: Option<String>,
}

impl Store {
    // ---- tokens ----

    /// Fails with a unique-constraint error (see [`is_unique_violation`]) if `name` exists.
    pub async fn insert_token(
        &self,
        name: &str,
        role: &str,
        hash: &str,
        expires_at: Option<i64>,
    ) -> Result<i64> {
        let mut tx = self.begin().await?;
        let id = sqlx::query_scalar(
            "INSERT INTO tokens (name, role, hash, created_at, expires_at) VALUES ($1, $2, $3, $4, $5) RETURNING id",
        )
        .bind(name)
        .bind(role)
        .bind(hash)
        .bind(now_ms())
        .bind(expires_at)
        .fetch_one(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(id)
    }

    /// The token with this hash, if it exists and has not expired. Records its last use (at
    /// most once a minute).
    pub async fn token_by_hash(&self, hash: &str) -> Result<Option<TokenRow>> {
        let now = now_ms();
        if !self.health.is_up() {
            return self.known_token(hash, now);
        }
        let row: Option<(String, String, Option<i64>, Option<i64>)> = match sqlx::query_as(
            "SELECT name, role, last_used_at, expires_at FROM tokens
              WHERE hash = $1 AND (expires_at IS NULL OR expires_at > $2)",
        )
        .bind(hash)
        .bind(now)
        .fetch_optional(&self.pool)
        .await
        {
            Ok(row) => row,
            Err(e) if self.health.observe(&e) => return self.known_token(hash, now),
            Err(e) => return Err(e),
        };
        let Some((name, role, last_used, expires_at)) = row else {
            self.forget_token(|h, _| h == hash);
            return Ok(None);
        };
        let row = TokenRow {
            name: name.into(),
            role: role.into(),
        };
        if let Ok(mut known) = self.known_tokens.lock() {
            known.insert(hash.to_string(), (row.clone(), expires_at, now));
        }
        if last_used.is_none_or(|t| now - t >= LAST_USED_GRANULARITY_MS) {
            // Best effort: a busy database must not turn a valid token into an error.
            if let Err(e) = sqlx::query("UPDATE tokens SET last_used_at = $1 WHERE hash = $2")
                .bind(now)
                .bind(hash)
                .execute(&self.pool)
                .await
            {
                tracing::debug!(error = %e, "could not record a token's last use");
            }
        }
        Ok(Some(row))
    }

    /// A token the database accepted within [`KNOWN_TOKEN_TTL_MS`], while it is unreachable.
    fn known_token(&self, hash: &str, now: i64) -> Result<Option<TokenRow>> {
        match self.accepted_since(hash, now - KNOWN_TOKEN_TTL_MS, now) {
            Some(row) => Ok(Some(row)),
            None => Err(sqlx::Error::Io(std::io::Error::new(
                std::io::ErrorKind::NotConnected,
                "the database is unreachable and this token was not checked recently",
            ))),
        }
    }

    /// The token with this hash if [`Store::token_by_hash`] accepted it less than `within_ms`
    /// ago and it has not expired since; `None` means "ask the database". Answered from memory,
    /// without waiting: a caller that may act on a slightly old answer (a read) uses it to skip
    /// the database round trip, at the price of seeing a revocation up to `within_ms` late.
    pub fn token_accepted_within(&self, hash: &str, within_ms: i64) -> Option<TokenRow> {
        let now = now_ms();
        self.accepted_since(hash, now - within_ms, now)
    }

    /// The token if the database accepted it after `since` (and not after `now`) and it is
    /// unexpired at `now`. Times are the wall clock's: an acceptance that looks later than now
    /// means the clock was set back, and is not trusted (else a clock set back an hour would let
    /// reads trust a revoked token for that hour).
    pub(super) fn accepted_since(&self, hash: &str, since: i64, now: i64) -> Option<TokenRow> {
        let known = self.known_tokens.lock().ok()?;
        match known.get(hash) {
            Some((row, expires, accepted))
                if (since + 1..=now).contains(accepted) && expires.is_none_or(|t| t > now) =>
            {
                Some(row.clone())
            }
            _ => None,
        }
    }

    fn forget_token(&self, mut which: impl FnMut(&str, &TokenRow) -> bool) {
        if let Ok(mut known) = self.known_tokens.lock() {
            known.retain(|h, (row, _, _)| !which(h, row));
        }
    }

    /// Tokens that can still be used (not expired).
    pub async fn token_count(&self) -> Result<i64> {
        sqlx::query_scalar(
            "SELECT COUNT(*) FROM tokens WHERE expires_at IS NULL OR expires_at > $1",
        )
        .bind(now_ms())
        .fetch_one(&self.pool)
        .await
    }

    pub async fn list_tokens(&self) -> Result<Vec<TokenInfo>> {
        let sql = self.pick(
            "SELECT name, role,
                    strftime('%Y-%m-%d %H:%M', created_at / 1000, 'unixepoch') AS created,
                    strftime('%Y-%m-%d %H:%M', expires_at / 1000, 'unixepoch') AS expires,
                    CASE WHEN expires_at <= $1 THEN 1 ELSE 0 END AS expired,
                    strftime('%Y-%m-%d %H:%M', last_used_at / 1000, 'unixepoch') AS last_used
               FROM tokens ORDER BY name",
            "SELECT name, role,
                    to_char(to_timestamp(created_at / 1000.0) AT TIME ZONE 'UTC', 'YYYY-MM-DD HH24:MI') AS created,
                    to_char(to_timestamp(expires_at / 1000.0) AT TIME ZONE 'UTC', 'YYYY-MM-DD HH24:MI') AS expires,
                    CASE WHEN expires_at <= $1 THEN 1 ELSE 0 END::BIGINT AS expired,
                    to_char(to_timestamp(last_used_at / 1000.0) AT TIME ZONE 'UTC', 'YYYY-MM-DD HH24:MI') AS last_used
               FROM tokens ORDER BY name",
        );
        let rows: Vec<TokenListRow> = sqlx::query_as(sql)
            .bind(now_ms())
            .fetch_all(&self.pool)
            .await?;
        Ok(rows
            .into_iter()
            .map(|r| TokenInfo {
                name: r.name,
                role: r.role,
                created: r.created,
                expires: r.expires,
                expired: r.expired != 0,
                last_used: r.last_used,
            })
            .collect())
    }

    /// Deletes the token named `name`; false if there is none.
    pub async fn revoke_token(&self, name: &str) -> Result<bool> {
        let mut tx = self.begin().await?;
        let n = sqlx::query("DELETE FROM tokens WHERE name = $1")
            .bind(name)
            .execute(&mut *tx)
            .await?
            .rows_affected();
        tx.commit().await?;
        self.forget_token(|_, row| &*row.name == name);
        Ok(n > 0)
    }
}

/// Whether a store error is a UNIQUE constraint violation (e.g. a token name that exists).
pub fn is_unique_violation(e: &sqlx::Error) -> bool {
    matches!(e, sqlx::Error::Database(d) if d.is_unique_violation())
}

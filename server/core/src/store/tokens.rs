//! API tokens (hashed).

use super::{now_ms, Result, Store};
use sqlx::FromRow;

#[derive(Debug, Clone, FromRow)]
pub struct TokenRow {
    pub name: String,
    pub role: String,
}

impl Store {
    // ---- tokens ----

    pub async fn insert_token(&self, name: &str, role: &str, hash: &str) -> Result<i64> {
        let mut tx = self.begin().await?;
        let id = sqlx::query_scalar(
            "INSERT INTO tokens (name, role, hash, created_at) VALUES (?, ?, ?, ?) RETURNING id",
        )
        .bind(name)
        .bind(role)
        .bind(hash)
        .bind(now_ms())
        .fetch_one(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(id)
    }

    pub async fn token_by_hash(&self, hash: &str) -> Result<Option<TokenRow>> {
        sqlx::query_as("SELECT name, role FROM tokens WHERE hash = ?")
            .bind(hash)
            .fetch_optional(&self.pool)
            .await
    }

    pub async fn token_count(&self) -> Result<i64> {
        sqlx::query_scalar("SELECT COUNT(*) FROM tokens")
            .fetch_one(&self.pool)
            .await
    }
}

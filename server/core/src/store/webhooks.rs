//! Webhook registrations and the outcome of their deliveries (the deliveries themselves are
//! made by `fresa-integrations`).

use super::{now_ms, Result, Store};
use serde::Serialize;
use sqlx::FromRow;

/// A webhook as the API shows it: everything but the secret.
#[derive(Debug, Clone, Serialize, FromRow)]
pub struct WebhookRow {
    pub id: i64,
    pub url: String,
    /// JSON array text in the database; see [`WebhookRow::event_filter`].
    #[serde(skip)]
    pub events: String,
    pub created_by: String,
    pub created_at: i64,
    pub last_status: Option<i64>,
    pub last_error: Option<String>,
    pub last_attempts: i64,
    pub last_delivery_at: Option<i64>,
    pub delivered: i64,
    pub failed: i64,
}

impl WebhookRow {
    /// The event types it wants (`job` matches `job.*`); empty: every persisted event.
    pub fn event_filter(&self) -> Vec<String> {
        serde_json::from_str(&self.events).unwrap_or_default()
    }
}

/// What the deliverer needs: where, what, and the signing key.
#[derive(Debug, Clone, FromRow)]
pub struct WebhookTarget {
    pub id: i64,
    pub url: String,
    pub events: String,
    pub secret: String,
}

impl WebhookTarget {
    pub fn event_filter(&self) -> Vec<String> {
        serde_json::from_str(&self.events).unwrap_or_default()
    }
}

/// How one delivery ended, after its retries.
#[derive(Debug, Clone)]
pub struct DeliveryOutcome {
    pub ok: bool,
    pub status: Option<u16>,
    pub error: Option<String>,
    pub attempts: u32,
}

const COLUMNS: &str = "id, url, events, created_by, created_at, last_status, last_error, \
                       last_attempts, last_delivery_at, delivered, failed";

impl Store {
    // ---- webhooks ----

    pub async fn insert_webhook(
        &self,
        url: &str,
        events: &[String],
        secret: &str,
        created_by: &str,
    ) -> Result<WebhookRow> {
        let mut tx = self.begin().await?;
        let events = serde_json::to_string(events).unwrap_or_else(|_| "[]".into());
        let row = sqlx::query_as(&format!(
            "INSERT INTO webhooks (url, events, secret, created_by, created_at)
             VALUES ($1, $2, $3, $4, $5) RETURNING {COLUMNS}"
        ))
        .bind(url)
        .bind(events)
        .bind(secret)
        .bind(created_by)
        .bind(now_ms())
        .fetch_one(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(row)
    }

    pub async fn webhooks(&self) -> Result<Vec<WebhookRow>> {
        sqlx::query_as(&format!("SELECT {COLUMNS} FROM webhooks ORDER BY id"))
            .fetch_all(&self.pool)
            .await
    }

    pub async fn webhook(&self, id: i64) -> Result<Option<WebhookRow>> {
        sqlx::query_as(&format!("SELECT {COLUMNS} FROM webhooks WHERE id = $1"))
            .bind(id)
            .fetch_optional(&self.pool)
            .await
    }

    /// Every webhook's id, filter and secret, for the deliverer.
    pub async fn webhook_targets(&self) -> Result<Vec<WebhookTarget>> {
        sqlx::query_as("SELECT id, url, events, secret FROM webhooks ORDER BY id")
            .fetch_all(&self.pool)
            .await
    }

    /// True if it existed.
    pub async fn delete_webhook(&self, id: i64) -> Result<bool> {
        let mut tx = self.begin().await?;
        let n = sqlx::query("DELETE FROM webhooks WHERE id = $1")
            .bind(id)
            .execute(&mut *tx)
            .await?
            .rows_affected();
        tx.commit().await?;
        Ok(n > 0)
    }

    pub async fn record_webhook_delivery(&self, id: i64, outcome: &DeliveryOutcome) -> Result<()> {
        let mut tx = self.begin().await?;
        sqlx::query(
            "UPDATE webhooks SET last_status = $1, last_error = $2, last_attempts = $3,
                    last_delivery_at = $4, delivered = delivered + $5, failed = failed + $6
              WHERE id = $7",
        )
        .bind(outcome.status.map(i64::from))
        .bind(outcome.error.as_deref())
        .bind(i64::from(outcome.attempts))
        .bind(now_ms())
        .bind(i64::from(outcome.ok))
        .bind(i64::from(!outcome.ok))
        .bind(id)
        .execute(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(())
    }
}

//! `/webhooks`: admins register URLs that receive signed deliveries of persisted events.
//! Registration is in `fresa_core::webhooks`; deliveries in `fresa-integrations`.

use super::auth::Caller;
use super::error::{ApiError, Json, Path};
use crate::openapi::ErrorBody;
use axum::extract::State;
use axum::http::StatusCode;
use axum::Extension;
use fresa_core::store::WebhookRow;
use fresa_core::SharedApp;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct NewWebhook {
    /// `http://` or `https://`; receives `POST`s.
    url: String,
    /// Event types to deliver; `job` matches `job.*`. Absent or empty: every persisted event.
    #[serde(default)]
    events: Vec<String>,
}

/// A webhook and how its deliveries went. The secret is never shown again after creation.
#[derive(Serialize, ToSchema)]
#[schema(as = Webhook)]
pub struct WebhookView {
    id: i64,
    url: String,
    events: Vec<String>,
    created_by: String,
    created_at: i64,
    /// HTTP status of the last delivery's last attempt; null when it got no answer (or none yet).
    last_status: Option<i64>,
    last_error: Option<String>,
    /// Attempts the last delivery took.
    last_attempts: i64,
    last_delivery_at: Option<i64>,
    /// Deliveries answered 2xx, and deliveries that failed every attempt.
    delivered: i64,
    failed: i64,
}

impl From<WebhookRow> for WebhookView {
    fn from(r: WebhookRow) -> Self {
        WebhookView {
            events: r.event_filter(),
            id: r.id,
            url: r.url,
            created_by: r.created_by,
            created_at: r.created_at,
            last_status: r.last_status,
            last_error: r.last_error,
            last_attempts: r.last_attempts,
            last_delivery_at: r.last_delivery_at,
            delivered: r.delivered,
            failed: r.failed,
        }
    }
}

/// The new webhook with its signing secret: shown this once.
#[derive(Serialize, ToSchema)]
pub struct CreatedWebhook {
    #[serde(flatten)]
    webhook: WebhookView,
    /// The HMAC-SHA256 key for `Fresa-Signature`; store it now, it is not shown again.
    secret: String,
}

#[utoipa::path(get, path = "/api/v1/webhooks", tag = "webhooks",
    responses((status = 200, description = "Every webhook (without secrets)", body = [WebhookView])))]
pub async fn list(State(app): State<SharedApp>) -> Result<Json<Vec<WebhookView>>, ApiError> {
    Ok(Json(
        app.store
            .webhooks()
            .await?
            .into_iter()
            .map(WebhookView::from)
            .collect(),
    ))
}

#[utoipa::path(get, path = "/api/v1/webhooks/{id}", tag = "webhooks",
    params(("id" = i64, Path, description = "webhook id", example = 1)),
    responses(
        (status = 200, description = "The webhook (without its secret)", body = WebhookView),
        (status = 404, description = "`unknown_webhook`", body = ErrorBody),
    ))]
pub async fn get_one(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
) -> Result<Json<WebhookView>, ApiError> {
    let row = app.store.webhook(id).await?.ok_or_else(|| {
        ApiError::not_found("unknown_webhook", format!("no webhook with id {id}"))
    })?;
    Ok(Json(row.into()))
}

/// Deliveries: `POST` to `url`, body = the event as on the event stream (`Event`), headers
/// `Fresa-Event` (type), `Fresa-Delivery` (`<webhook>-<event id>`, the same on every retry) and
/// `Fresa-Signature: t=<unix seconds>,v1=<hex HMAC-SHA256(secret, "<t>.<body>")>`. A 2xx answer
/// is a success; anything else is retried with doubling delays.
#[utoipa::path(post, path = "/api/v1/webhooks", tag = "webhooks",
    request_body(content = NewWebhook, example = json!({"url": "http://erp.lan:9000/fresa", "events": ["job.state"]})),
    responses(
        (status = 201, description = "Registered; the answer carries the signing `secret`, shown this once", body = CreatedWebhook),
        (status = 422, description = "`invalid_field` (naming the field); `webhook_target_refused`: the URL's host is this server, a loopback, link-local, unspecified, multicast or broadcast address or a cloud metadata service (see `webhooks.allowed_hosts`)", body = ErrorBody),
    ))]
pub async fn create(
    State(app): State<SharedApp>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<NewWebhook>,
) -> Result<(StatusCode, Json<CreatedWebhook>), ApiError> {
    let created = fresa_core::webhooks::create(&app, &req.url, req.events, &caller.name).await?;
    Ok((
        StatusCode::CREATED,
        Json(CreatedWebhook {
            webhook: created.row.into(),
            secret: created.secret,
        }),
    ))
}

#[utoipa::path(delete, path = "/api/v1/webhooks/{id}", tag = "webhooks",
    params(("id" = i64, Path, description = "webhook id", example = 1)),
    responses(
        (status = 204, description = "Removed; deliveries waiting for it are dropped"),
        (status = 404, description = "`unknown_webhook`", body = ErrorBody),
    ))]
pub async fn delete(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
) -> Result<StatusCode, ApiError> {
    fresa_core::webhooks::delete(&app, id, &caller.name).await?;
    Ok(StatusCode::NO_CONTENT)
}

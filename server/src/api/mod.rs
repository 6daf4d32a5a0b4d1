//! HTTP API v1. See the README's endpoint table.

pub mod auth;
pub mod error;
mod events;
mod jobs;
mod machines;

use crate::app::SharedApp;
use axum::extract::{DefaultBodyLimit, State};
use axum::http::StatusCode;
use axum::response::IntoResponse;
use axum::routing::{get, post, put};
use axum::Router;
use error::Json;

pub fn router(app: SharedApp) -> Router {
    let api = Router::new()
        .route("/machines", get(machines::list).post(machines::create))
        .route("/machines/{id}", get(machines::get_one))
        .route("/machines/{id}/status", get(machines::status))
        .route("/machines/{id}/jog", post(machines::jog))
        .route("/machines/{id}/commands", post(machines::command))
        .route("/machines/{id}/offsets", get(machines::offsets))
        .route("/machines/{id}/offsets/{name}", put(machines::set_offset))
        .route(
            "/machines/{id}/part-zero",
            get(machines::part_zeros).post(machines::record_part_zero),
        )
        .route(
            "/jobs",
            get(jobs::list)
                .post(jobs::upload)
                // Uploads are streamed to disk under our own limit (`max_upload_bytes`).
                .layer(DefaultBodyLimit::disable()),
        )
        .route("/jobs/{id}", get(jobs::get_one))
        .route("/jobs/{id}/gcode", get(jobs::gcode))
        .route("/jobs/{id}/{action}", post(jobs::control))
        .route("/plugins", get(plugins))
        .route("/events", get(events::stream))
        .layer(axum::middleware::from_fn_with_state(
            app.clone(),
            auth::middleware,
        ));
    Router::new()
        .nest("/api/v1", api)
        .route("/healthz", get(healthz))
        .fallback(not_found)
        .layer(tower_http::trace::TraceLayer::new_for_http())
        .with_state(app)
}

async fn healthz(State(app): State<SharedApp>) -> impl IntoResponse {
    match app.store.ping().await {
        Ok(()) => (
            StatusCode::OK,
            axum::Json(serde_json::json!({"status": "ok"})),
        ),
        Err(e) => (
            StatusCode::SERVICE_UNAVAILABLE,
            axum::Json(serde_json::json!({"status": "unavailable", "message": e.to_string()})),
        ),
    }
}

async fn plugins(State(app): State<SharedApp>) -> Json<serde_json::Value> {
    Json(serde_json::json!({
        "plugins": app.plugins.infos(),
        "failures": app.plugins.failures,
        "abi": format!("{}.{}", fresa_plugin_api::abi::ABI_MAJOR, fresa_plugin_api::abi::ABI_MINOR),
    }))
}

async fn not_found(uri: axum::http::Uri) -> error::ApiError {
    error::ApiError::not_found("not_found", format!("no such endpoint: {}", uri.path()))
}

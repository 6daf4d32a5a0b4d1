//! HTTP API v1. See the README's endpoint table.

pub mod auth;
pub mod error;
mod events;
mod jobs;
pub(crate) mod machines;
mod pendants;

use axum::extract::{DefaultBodyLimit, State};
use axum::http::StatusCode;
use axum::response::IntoResponse;
use axum::routing::{get, post, put};
use axum::Router;
use error::Json;
use fresa_core::SharedApp;

pub fn router(app: SharedApp) -> Router {
    let api = Router::new()
        .route("/machines", get(machines::list).post(machines::create))
        .route("/machines/{id}", get(machines::get_one))
        .route("/machines/{id}/status", get(machines::status))
        .route("/machines/{id}/jog", post(machines::jog))
        .route("/machines/{id}/commands", post(machines::command))
        .route("/machines/{id}/mdi", post(machines::mdi))
        .route("/machines/{id}/offsets", get(machines::offsets))
        .route("/machines/{id}/offsets/{name}", put(machines::set_offset))
        .route(
            "/machines/{id}/part-zero",
            get(machines::part_zeros).post(machines::record_part_zero),
        )
        .route("/machines/{id}/as-program", get(machines::as_program))
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
        .route("/pendants", get(pendants::list).post(pendants::create))
        .route("/pendants/discovered", get(pendants::discovered))
        .route(
            "/pendants/{id}",
            get(pendants::get_one)
                .patch(pendants::patch)
                .delete(pendants::delete),
        )
        .route("/plugins", get(plugins))
        .route("/events", get(events::stream))
        .layer(axum::middleware::from_fn_with_state(
            app.clone(),
            auth::middleware,
        ));
    Router::new()
        .nest("/api/v1", api)
        .route("/healthz", get(healthz))
        .route(
            "/metrics",
            get(metrics).layer(axum::middleware::from_fn_with_state(
                app.clone(),
                auth::middleware,
            )),
        )
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

/// Prometheus text format. Read-only and cheap: gauges from memory plus one grouped query.
async fn metrics(State(app): State<SharedApp>) -> Result<impl IntoResponse, error::ApiError> {
    use std::fmt::Write;
    let mut out = String::new();
    let _ = writeln!(
        out,
        "# HELP fresa_machine_state 1 for the state each machine is in."
    );
    let _ = writeln!(out, "# TYPE fresa_machine_state gauge");
    for m in app.machines.all().await {
        let state = serde_json::to_value(m.status().state)
            .ok()
            .and_then(|v| v.as_str().map(str::to_string))
            .unwrap_or_default();
        let name = m.row().name.replace(['\\', '"', '\n'], "_");
        let _ = writeln!(
            out,
            "fresa_machine_state{{machine=\"{}\",name=\"{name}\",state=\"{state}\"}} 1",
            m.id
        );
    }
    let _ = writeln!(out, "# HELP fresa_job_runs Job runs by state.");
    let _ = writeln!(out, "# TYPE fresa_job_runs gauge");
    for (state, n) in app.store.run_state_counts().await? {
        let _ = writeln!(out, "fresa_job_runs{{state=\"{state}\"}} {n}");
    }
    let _ = writeln!(
        out,
        "# TYPE fresa_plugins_loaded gauge\nfresa_plugins_loaded {}",
        app.plugins.names().len()
    );
    let _ = writeln!(
        out,
        "# TYPE fresa_plugin_load_failures gauge\nfresa_plugin_load_failures {}",
        app.plugins.failures.len()
    );
    let _ = writeln!(
        out,
        "# TYPE fresa_event_subscribers gauge\nfresa_event_subscribers {}",
        app.bus.subscribers()
    );
    Ok((
        [(
            axum::http::header::CONTENT_TYPE,
            "text/plain; version=0.0.4",
        )],
        out,
    ))
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

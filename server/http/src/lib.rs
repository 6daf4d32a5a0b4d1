//! HTTP API v1. See the README's endpoint table.

pub mod auth;
mod console;
pub mod error;
mod events;
mod guard;
mod jobs;
pub(crate) mod machines;
mod pendants;

use axum::extract::{DefaultBodyLimit, State};
use axum::http::StatusCode;
use axum::response::IntoResponse;
use axum::routing::{delete, get, patch, post, put};
use axum::Router;
use error::Json;
use fresa_core::SharedApp;

/// Every route with the role it needs: reading is for viewers, moving machines and jobs for
/// operators, configuring machines, pendants and plugins for admins.
pub fn router(app: SharedApp) -> Router {
    use auth::needs;
    use auth::Role::{Admin, Operator, Viewer};
    let api = Router::new()
        .route(
            "/machines",
            needs(Viewer, get(machines::list)).merge(needs(Admin, post(machines::create))),
        )
        .route("/machines/{id}", needs(Viewer, get(machines::get_one)))
        .route(
            "/machines/{id}/status",
            needs(Viewer, get(machines::status)),
        )
        .route("/machines/{id}/jog", needs(Operator, post(machines::jog)))
        .route(
            "/machines/{id}/commands",
            needs(Operator, post(machines::command)),
        )
        .route("/machines/{id}/mdi", needs(Operator, post(machines::mdi)))
        .route(
            "/machines/{id}/offsets",
            needs(Viewer, get(machines::offsets)),
        )
        .route(
            "/machines/{id}/offsets/{name}",
            needs(Operator, put(machines::set_offset)),
        )
        .route(
            "/machines/{id}/part-zero",
            needs(Viewer, get(machines::part_zeros))
                .merge(needs(Operator, post(machines::record_part_zero))),
        )
        .route(
            "/machines/{id}/as-program",
            needs(Viewer, get(machines::as_program)),
        )
        .route(
            "/jobs",
            needs(Viewer, get(jobs::list)).merge(needs(
                Operator,
                // Uploads are streamed to disk under our own limit (`max_upload_bytes`).
                post(jobs::upload).layer(DefaultBodyLimit::disable()),
            )),
        )
        .route("/jobs/{id}", needs(Viewer, get(jobs::get_one)))
        .route("/jobs/{id}/gcode", needs(Viewer, get(jobs::gcode)))
        .route(
            "/jobs/{id}/toolpath",
            needs(Viewer, get(jobs::toolpath)).layer(compression()),
        )
        .route("/jobs/{id}/{action}", needs(Operator, post(jobs::control)))
        .route(
            "/pendants",
            needs(Viewer, get(pendants::list)).merge(needs(Admin, post(pendants::create))),
        )
        .route(
            "/pendants/discovered",
            needs(Viewer, get(pendants::discovered)),
        )
        .route(
            "/pendants/{id}",
            needs(Viewer, get(pendants::get_one))
                // Binding a pendant to a machine is an operator's job; creating or deleting
                // one is an admin's.
                .merge(needs(Operator, patch(pendants::patch)))
                .merge(needs(Admin, delete(pendants::delete))),
        )
        .route("/plugins", needs(Viewer, get(plugins)))
        .route("/whoami", needs(Viewer, get(whoami)))
        .route("/events", needs(Viewer, get(events::stream)))
        .layer(axum::middleware::from_fn_with_state(
            app.clone(),
            auth::middleware,
        ));
    // The console's files need no token (the API calls they make do); still behind the guard.
    let console = Router::new()
        .route("/", get(console::index))
        .route("/assets/{name}", get(console::asset))
        .layer(compression());
    let router = Router::new()
        .nest("/api/v1", api)
        .merge(console)
        .route("/healthz", get(healthz))
        .route(
            "/metrics",
            needs(Viewer, get(metrics)).layer(axum::middleware::from_fn_with_state(
                app.clone(),
                auth::middleware,
            )),
        )
        .fallback(not_found)
        .method_not_allowed_fallback(method_not_allowed);
    // CORS only when some origin is allowed: deny-by-default needs no layer at all.
    let router = if app.settings.cors_origins.is_empty() {
        router
    } else {
        router.layer(cors(&app.settings.cors_origins))
    };
    router
        .layer(
            tower_http::trace::TraceLayer::new_for_http().make_span_with(
                |req: &axum::http::Request<_>| {
                    // The URI without secrets: an `access_token` in the query is not logged.
                    tracing::debug_span!(
                        "request",
                        method = %req.method(),
                        uri = %auth::redacted_uri(req.uri()),
                        version = ?req.version(),
                    )
                },
            ),
        )
        .with_state(app)
}

/// The whole HTTP service: the router behind the cross-site and rebinding guard. The guard wraps
/// the router once (not each route), so a request pays for it once.
pub fn service(app: SharedApp) -> Service {
    use tower::Layer;
    let settings = std::sync::Arc::new(app.settings.clone());
    guard::Guard(settings).layer(router(app))
}

/// What `service` returns: serve it with hyper (requests with an axum `Body`).
pub type Service = guard::Guarded<Router>;

/// gzip for the console's files and toolpaths (not for the event stream, whose events must not
/// wait in a compressor's buffer).
fn compression() -> tower_http::compression::CompressionLayer {
    tower_http::compression::CompressionLayer::new()
}

/// Who the caller is and whether this server needs a token: the console disables what the role
/// may not do and asks for a token when one is needed.
async fn whoami(
    State(app): State<SharedApp>,
    axum::Extension(caller): axum::Extension<auth::Caller>,
) -> Json<serde_json::Value> {
    Json(serde_json::json!({
        "name": caller.name,
        "role": caller.role.name(),
        "auth_required": app.auth_required,
    }))
}

/// Deny-by-default CORS: only the configured origins get CORS headers (and preflights).
fn cors(origins: &[String]) -> tower_http::cors::CorsLayer {
    use axum::http::{header, HeaderValue, Method};
    use tower_http::cors::{AllowOrigin, CorsLayer};
    let list: Vec<HeaderValue> = origins.iter().filter_map(|o| o.parse().ok()).collect();
    CorsLayer::new()
        .allow_origin(AllowOrigin::list(list))
        .allow_methods([
            Method::GET,
            Method::POST,
            Method::PUT,
            Method::PATCH,
            Method::DELETE,
        ])
        .allow_headers([
            header::AUTHORIZATION,
            header::CONTENT_TYPE,
            header::HeaderName::from_static("last-event-id"),
        ])
}

async fn method_not_allowed(method: axum::http::Method, uri: axum::http::Uri) -> error::ApiError {
    error::ApiError::new(
        StatusCode::METHOD_NOT_ALLOWED,
        "method_not_allowed",
        format!("{method} is not allowed on {}", uri.path()),
    )
}

/// `ok`; `degraded` (still 200: the other machines work) naming machines whose backend stopped
/// answering; 503 when the database does not answer.
async fn healthz(State(app): State<SharedApp>) -> impl IntoResponse {
    if let Err(e) = app.store.ping().await {
        return (
            StatusCode::SERVICE_UNAVAILABLE,
            axum::Json(serde_json::json!({"status": "unavailable", "message": e.to_string()})),
        );
    }
    let unresponsive: Vec<i64> = app
        .machines
        .all()
        .await
        .iter()
        .filter(|m| m.unresponsive().is_some())
        .map(|m| m.id)
        .collect();
    let status = if unresponsive.is_empty() {
        "ok"
    } else {
        "degraded"
    };
    (
        StatusCode::OK,
        axum::Json(serde_json::json!({"status": status, "unresponsive_machines": unresponsive})),
    )
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
        "skipped": app.plugins.skipped,
        "abi": format!("{}.{}", fresa_plugin_api::abi::ABI_MAJOR, fresa_plugin_api::abi::ABI_MINOR),
    }))
}

async fn not_found(uri: axum::http::Uri) -> error::ApiError {
    error::ApiError::not_found("not_found", format!("no such endpoint: {}", uri.path()))
}

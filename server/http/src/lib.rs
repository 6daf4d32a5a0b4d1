//! HTTP API v1. See the README's endpoint table.

pub mod admission;
pub mod auth;
mod console;
pub mod error;
mod events;
pub mod forward;
mod guard;
mod heightmaps;
mod jobs;
pub(crate) mod machines;
mod middleware;
pub mod openapi;
mod pendants;
mod queue;
mod records;
mod request_log;
mod status_polls;
mod toolchange;
mod tools;
mod webhooks;

use axum::extract::{DefaultBodyLimit, State};
use axum::http::StatusCode;
use axum::response::IntoResponse;
use axum::Router;
use error::Json;
use fresa_core::SharedApp;
use openapi::{needs, public, ErrorBody};
use utoipa::OpenApi;
use utoipa_axum::router::{OpenApiRouter, UtoipaMethodRouterExt};
use utoipa_axum::routes;

/// Every route with the role it needs: reading is for viewers, moving machines and jobs for
/// operators, configuring machines, pendants and plugins for admins.
///
/// A route is added only as `.routes(needs(ROLE, routes!(handler)))`: the handler's
/// `#[utoipa::path(METHOD, path = ...)]` gives its method and path, so the router and the
/// OpenAPI description (`GET /api/v1/openapi.json`) are built from the same lines.
///
/// `admission` (shared with the accept loop) is what the event stream and `/metrics` read; only
/// those routes carry it. `after_describing` is called on the thread that described the API
/// for its first `GET /api/v1/openapi.json`, once the description is serialised: the daemon
/// gives back what only describing used (see [`openapi::Document`]). Authentication,
/// forwarding and CORS are around the router, in [`service`].
pub fn routes(
    admission: Option<std::sync::Arc<admission::Admission>>,
    after_describing: fn(),
) -> Routes {
    let (router, _) = described_router(admission, openapi::Document::new(after_describing));
    Routes(
        router
            .fallback(not_found)
            .method_not_allowed_fallback(method_not_allowed),
    )
}

/// The routing table of [`routes`], before it is given the app. Building it is about a quarter
/// of a first start's instructions (each route's OpenAPI operation is made with it, then
/// dropped), and it needs nothing from the store, so `fresa serve` builds it on a thread of its
/// own while the store opens.
pub struct Routes(Router<SharedApp>);

/// The OpenAPI description of [`routes`], as served (for tools and tests without a server).
pub fn openapi_document() -> String {
    doc_json(&described_router(None, openapi::Document::new(|| ())).1)
}

fn doc_json(doc: &utoipa::openapi::OpenApi) -> String {
    doc.to_pretty_json().unwrap_or_else(|e| {
        tracing::error!(error = %e, "could not serialise the OpenAPI description");
        "{}".into()
    })
}

fn described_router(
    admission: Option<std::sync::Arc<admission::Admission>>,
    document: openapi::Document,
) -> (Router<SharedApp>, utoipa::openapi::OpenApi) {
    use auth::Role::{Admin, Operator, Viewer};
    let with_admission = axum::Extension(admission);
    let api = OpenApiRouter::new()
        .routes(needs(Viewer, routes!(machines::list)))
        .routes(needs(Admin, routes!(machines::create)))
        .routes(needs(Viewer, routes!(machines::get_one)))
        .routes(needs(Viewer, routes!(machines::status)))
        .routes(needs(Operator, routes!(machines::jog)))
        .routes(needs(Operator, routes!(machines::jog_cancel)))
        .routes(needs(Operator, routes!(machines::probe)))
        .routes(needs(Operator, routes!(machines::touch_off)))
        .routes(needs(Operator, routes!(machines::find_centre)))
        .routes(needs(Operator, routes!(machines::overrides)))
        .routes(needs(Operator, routes!(machines::jog_keepalive)))
        .routes(needs(Operator, routes!(machines::command)))
        .routes(needs(Operator, routes!(machines::mdi)))
        .routes(needs(Viewer, routes!(machines::offsets)))
        .routes(needs(Operator, routes!(machines::set_offset)))
        .routes(needs(Viewer, routes!(machines::part_zeros)))
        .routes(needs(Operator, routes!(machines::record_part_zero)))
        .routes(needs(Viewer, routes!(machines::as_program)))
        .routes(needs(Operator, routes!(heightmaps::create)))
        .routes(needs(Viewer, routes!(heightmaps::list)))
        .routes(needs(Viewer, routes!(heightmaps::get_one)))
        .routes(needs(Operator, routes!(heightmaps::delete)))
        .routes(needs(Viewer, routes!(heightmaps::fit)))
        .routes(needs(Viewer, routes!(tools::list_tools)))
        .routes(needs(Admin, routes!(tools::replace_tools)))
        .routes(needs(Admin, routes!(tools::set_tool)))
        .routes(needs(Admin, routes!(tools::delete_tool)))
        .routes(needs(Viewer, routes!(toolchange::get_run_settings)))
        .routes(needs(Operator, routes!(toolchange::patch_run_settings)))
        .routes(needs(Operator, routes!(toolchange::measure_tool)))
        .routes(needs(Viewer, routes!(records::parts)))
        .routes(needs(Viewer, routes!(records::utilisation)))
        .routes(needs(Viewer, routes!(records::counters)))
        .routes(needs(Admin, routes!(records::maintenance_done)))
        .routes(needs(Viewer, routes!(jobs::list)))
        .routes(needs(
            Operator,
            // Uploads are streamed to disk under our own limit (`max_upload_bytes`).
            routes!(jobs::upload).map(|r| r.layer(DefaultBodyLimit::disable())),
        ))
        .routes(needs(Viewer, routes!(jobs::get_one)))
        .routes(needs(Viewer, routes!(jobs::gcode)))
        .routes(needs(
            Viewer,
            routes!(jobs::toolpath).map(|r| r.layer(compression())),
        ))
        .routes(needs(Operator, routes!(jobs::control)))
        .routes(needs(Viewer, routes!(jobs::start_preview)))
        .routes(needs(Viewer, routes!(queue::get)))
        .routes(needs(Operator, routes!(queue::add)))
        .routes(needs(Operator, routes!(queue::remove)))
        .routes(needs(Operator, routes!(queue::move_entry)))
        .routes(needs(Operator, routes!(queue::confirm)))
        .routes(needs(Operator, routes!(queue::release)))
        .routes(needs(Operator, routes!(queue::take)))
        .routes(needs(Operator, routes!(queue::dispatch)))
        .routes(needs(Viewer, routes!(pendants::list)))
        .routes(needs(Admin, routes!(pendants::create)))
        .routes(needs(Viewer, routes!(pendants::discovered)))
        .routes(needs(Viewer, routes!(pendants::get_one)))
        // Binding a pendant to a machine is an operator's job; creating or deleting one is an
        // admin's.
        .routes(needs(Operator, routes!(pendants::patch)))
        .routes(needs(Admin, routes!(pendants::delete)))
        .routes(needs(Admin, routes!(pendants::set_node)))
        .routes(needs(Admin, routes!(webhooks::list)))
        .routes(needs(Admin, routes!(webhooks::create)))
        .routes(needs(Admin, routes!(webhooks::get_one)))
        .routes(needs(Admin, routes!(webhooks::delete)))
        .routes(needs(Viewer, routes!(plugins)))
        .routes(needs(Viewer, routes!(whoami)))
        .routes(needs(
            Viewer,
            routes!(events::stream).map(|r| r.layer(with_admission.clone())),
        ))
        .routes(needs(Viewer, routes!(nodes)))
        .routes(needs(Admin, routes!(machines::set_node)))
        // Public, like the console's files (see `Gate`): the description (`openapi::openapi_json`).
        .routes(public(
            routes!(openapi::openapi_json).map(|r| r.layer(axum::Extension(document))),
        ));
    let metrics = OpenApiRouter::new()
        .routes(needs(Viewer, routes!(metrics)).map(|r| r.layer(with_admission.clone())));
    // The console's files need no token (the API calls they make do); still behind the guard.
    OpenApiRouter::with_openapi(openapi::ApiDoc::openapi())
        // Merged, not nested: each API handler's annotation carries its full `/api/v1/...` path,
        // so no request pays for `nest`'s per-request URI rewrite (a new `Uri` for every call).
        .merge(api)
        .routes(public(
            routes!(console::index).map(|r| r.layer(compression())),
        ))
        .routes(public(
            routes!(console::asset).map(|r| r.layer(compression())),
        ))
        .routes(public(routes!(healthz)))
        .merge(metrics)
        .split_for_parts()
}

/// The whole HTTP service, from the outside in: the cross-site and rebinding guard, the request
/// log, CORS (only when some origin is allowed: deny-by-default needs no layer at all), the
/// [`Gate`] (authentication, then forwarding), the status polls' shortcut (`status_polls`), the
/// router. Each wraps the router once, not each route (axum's `Router::layer` wraps every route,
/// and each such layer costs a request a clone of the boxed route and a boxed future), so a
/// request pays for each once. `admission` is shared with the accept loop (per-client
/// connections) and read by auth, the event stream and `/metrics`.
pub fn service(
    app: SharedApp,
    admission: std::sync::Arc<admission::Admission>,
    routes: Routes,
) -> Service {
    use tower::Layer;
    let settings = std::sync::Arc::new(app.settings.clone());
    let gate = Gate {
        pair: (
            auth::Authenticate::new(app.clone(), Some(admission.clone())),
            forward::ForwardState::new(app.clone()),
        ),
    };
    let origins = app.settings.cors_origins.clone();
    let routed = status_polls::StatusPolls::new(app.clone(), routes.0.with_state(app));
    let gated = middleware::Layer(gate).layer(routed);
    let with_cors = if origins.is_empty() {
        tower::util::Either::Right(gated)
    } else {
        tower::util::Either::Left(cors(&origins).layer(gated))
    };
    guard::Guard(settings).layer(request_log::RequestLog.layer(with_cors))
}

/// What `service` returns: serve it with hyper (requests with an axum `Body`).
pub type Service =
    guard::Guarded<request_log::Logged<tower::util::Either<tower_http::cors::Cors<Gated>, Gated>>>;

/// The router behind the [`Gate`], with status polls answered in front of it.
pub type Gated = middleware::Service<Gate, status_polls::StatusPolls<Router>>;

/// Which requests authentication and forwarding see, decided from the path before routing:
/// everything under `/api/v1/` but its OpenAPI description passes authentication and then the
/// forwarding check (it needs to know the caller); `/metrics` passes authentication only; the
/// console's files, `/healthz`, the description and paths outside the API need no token. An
/// unknown path under `/api/v1/` is authenticated before it is answered 404. The route table
/// declares each route's role; a test checks that this split agrees with it for every route.
#[derive(Clone)]
pub struct Gate {
    /// Authentication, then forwarding (it needs to know the caller).
    pair: (auth::Authenticate, forward::ForwardState),
}

enum Scope {
    Public,
    Authenticated,
    AuthenticatedAndForwarded,
}

fn scope(path: &str) -> Scope {
    match path.strip_prefix("/api/v1/") {
        Some("openapi.json") => Scope::Public,
        Some(_) => Scope::AuthenticatedAndForwarded,
        None if path == "/metrics" => Scope::Authenticated,
        None => Scope::Public,
    }
}

impl middleware::Middleware for Gate {
    fn fast(&self, req: axum::extract::Request) -> middleware::Fast {
        match scope(req.uri().path()) {
            Scope::Public => middleware::Fast::Pass(req),
            Scope::Authenticated => self.pair.0.fast(req),
            Scope::AuthenticatedAndForwarded => self.pair.fast(req),
        }
    }

    fn slow(
        self,
        req: axum::extract::Request,
        next: impl middleware::Next,
    ) -> futures_util::future::BoxFuture<'static, axum::response::Response> {
        match scope(req.uri().path()) {
            Scope::Public => next.run(req),
            Scope::Authenticated => self.pair.0.slow(req, next),
            Scope::AuthenticatedAndForwarded => self.pair.slow(req, next),
        }
    }
}

/// gzip for the console's files and toolpaths (not for the event stream, whose events must not
/// wait in a compressor's buffer).
fn compression() -> tower_http::compression::CompressionLayer {
    tower_http::compression::CompressionLayer::new()
}

/// The nodes sharing this server's store: each one's address, version, last heartbeat,
/// whether it is reachable, and the machines it drives. A server on its own is one node.
#[utoipa::path(get, path = "/api/v1/nodes", tag = "server",
    responses(
        (status = 200, description = "Every node, by name: `name`, `url`, `version`, `started_at`, `last_heartbeat` (ms since the epoch), `reachable`, `this_node`, `machines` (ids)", body = [Object]),
    ))]
async fn nodes(State(app): State<SharedApp>) -> Result<Json<serde_json::Value>, error::ApiError> {
    Ok(Json(serde_json::json!(app.nodes().await?)))
}

/// Who the caller is and whether this server needs a token: the console disables what the role
/// may not do and asks for a token when one is needed.
#[utoipa::path(get, path = "/api/v1/whoami", tag = "server",
    responses(
        (status = 200, description = "`{\"name\", \"role\", \"auth_required\"}`: the caller's token name (or `local`), its role, and whether this server needs a token", body = Object),
    ))]
async fn whoami(
    State(app): State<SharedApp>,
    axum::Extension(caller): axum::Extension<auth::Caller>,
) -> Json<serde_json::Value> {
    Json(serde_json::json!({
        "name": &*caller.name,
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

/// `{"status": "ok"|"degraded", "unresponsive_machines": [id]}`, and while the database is
/// unreachable `"database": {"status": "unavailable", "since": ms, "message": ...}`.
#[derive(serde::Serialize, utoipa::ToSchema)]
#[allow(dead_code)] // describes the JSON `healthz` builds
struct Health {
    status: String,
    unresponsive_machines: Vec<i64>,
    #[schema(value_type = Option<Object>)]
    database: Option<serde_json::Value>,
}

/// `ok`; `degraded` (still 200: running jobs go on, stop and pause work) naming machines whose
/// backend stopped answering, or the database while it is unreachable (no new motion then).
/// Read from memory: the database's health monitor keeps it current, so this answers at once
/// even while the database does not.
#[utoipa::path(get, path = "/healthz", tag = "system",
    responses(
        (status = 200, description = "`ok`, or `degraded` naming machines whose backend stopped answering and, under `database`, an unreachable database (since when, why)", body = Health),
    ))]
async fn healthz(State(app): State<SharedApp>) -> impl IntoResponse {
    let unresponsive: Vec<i64> = app
        .machines
        .all()
        .iter()
        .filter(|m| m.unresponsive().is_some())
        .map(|m| m.id)
        .collect();
    let health = app.store.health();
    let database = match health.state() {
        fresa_core::store::DbState::Up => None,
        fresa_core::store::DbState::Down { since_ms, .. } => Some(serde_json::json!({
            "status": "unavailable",
            "since": since_ms,
            "message": health.unavailable_error().message,
        })),
    };
    let status = if unresponsive.is_empty() && database.is_none() {
        "ok"
    } else {
        "degraded"
    };
    let mut body = serde_json::json!({"status": status, "unresponsive_machines": unresponsive});
    if let Some(db) = database {
        body["database"] = db;
    }
    (StatusCode::OK, axum::Json(body))
}

/// Prometheus text format. Read-only and cheap: gauges from memory plus one grouped query.
#[utoipa::path(get, path = "/metrics", tag = "system",
    responses(
        (status = 200, description = "Prometheus text: machine states, job runs by state, plugins, event subscribers, integration queues and drops", content_type = "text/plain", body = String),
        (status = 500, description = "`internal` (the database failed)", body = ErrorBody),
    ))]
async fn metrics(
    State(app): State<SharedApp>,
    axum::Extension(admission): axum::Extension<Option<std::sync::Arc<admission::Admission>>>,
) -> Result<impl IntoResponse, error::ApiError> {
    use std::fmt::Write;
    let mut out = String::new();
    let _ = writeln!(
        out,
        "# HELP fresa_machine_state 1 for the state each machine is in."
    );
    let _ = writeln!(out, "# TYPE fresa_machine_state gauge");
    let mut input_lines = String::new();
    let mut output_lines = String::new();
    for m in app.machines.all() {
        let status = m.status();
        let state = status.state.as_str();
        let name = m.row().name.replace(['\\', '"', '\n'], "_");
        let _ = writeln!(
            out,
            "fresa_machine_state{{machine=\"{}\",name=\"{name}\",state=\"{state}\"}} 1",
            m.id
        );
        // Known values only: a supported input that is unknown right now has no sample.
        for (io, value) in &status.inputs {
            if let Some(on) = value {
                let _ = writeln!(
                    input_lines,
                    "fresa_machine_input{{machine=\"{}\",io=\"{io}\"}} {}",
                    m.id,
                    u8::from(*on)
                );
            }
        }
        for (io, value) in &status.outputs {
            let v = match value {
                Some(fresa_plugin_api::contract::IoValue::On(on)) => f64::from(u8::from(*on)),
                Some(fresa_plugin_api::contract::IoValue::Number(n)) => *n,
                None => continue,
            };
            let _ = writeln!(
                output_lines,
                "fresa_machine_output{{machine=\"{}\",io=\"{io}\"}} {v}",
                m.id
            );
        }
    }
    let _ = writeln!(
        out,
        "# HELP fresa_machine_input 1 while a machine input (limit, e-stop, probe, door) is active.\n# TYPE fresa_machine_input gauge\n{input_lines}# HELP fresa_machine_output A machine output: 1/0 for switches, the value for numbers (spindle_rpm).\n# TYPE fresa_machine_output gauge"
    );
    out.push_str(&output_lines);
    let health = app.store.health();
    let (delayed, dropped) = app.bus.delayed_counts();
    let _ = writeln!(
        out,
        "# HELP fresa_database_up 1 while the database answers its health pings.\n# TYPE fresa_database_up gauge\nfresa_database_up {}\n# HELP fresa_events_delayed Audit events waiting in memory for the database.\n# TYPE fresa_events_delayed gauge\nfresa_events_delayed {delayed}\n# TYPE fresa_events_delayed_dropped_total counter\nfresa_events_delayed_dropped_total {dropped}",
        u8::from(health.is_up())
    );
    // Job runs live in the database: left out while it is unreachable (the gauges above are
    // what matters then).
    if health.is_up() {
        let _ = writeln!(out, "# HELP fresa_job_runs Job runs by state.");
        let _ = writeln!(out, "# TYPE fresa_job_runs gauge");
        for (state, n) in app.store.run_state_counts().await? {
            let _ = writeln!(out, "fresa_job_runs{{state=\"{state}\"}} {n}");
        }
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
    out.push_str(&records_metrics(&app).await);
    out.push_str(&app.integrations.prometheus());
    if let Some(a) = admission {
        out.push_str(&a.prometheus());
    }
    out.push_str(&app.previews.prometheus());
    Ok((
        [(
            axum::http::header::CONTENT_TYPE,
            "text/plain; version=0.0.4",
        )],
        out,
    ))
}

/// The shop's records in `/metrics`: seconds per utilisation state since start, and each
/// machine's maintenance counters (as stored plus counted since; they never go backwards).
async fn records_metrics(app: &fresa_core::App) -> String {
    use std::fmt::Write;
    let mut out = String::from(
        "# HELP fresa_machine_state_seconds_total Seconds each machine spent in each utilisation state since the server started.\n# TYPE fresa_machine_state_seconds_total counter\n",
    );
    let mut counters = String::from(
        "# HELP fresa_machine_spindle_seconds_total Spindle-on time of each machine.\n# TYPE fresa_machine_spindle_seconds_total counter\n# HELP fresa_machine_motion_seconds_total Motion time (running, jogging, homing) of each machine.\n# TYPE fresa_machine_motion_seconds_total counter\n# HELP fresa_machine_distance_mm_total Distance travelled per axis.\n# TYPE fresa_machine_distance_mm_total counter\n# HELP fresa_machine_jobs_total Runs ended on each machine.\n# TYPE fresa_machine_jobs_total counter\n# HELP fresa_maintenance_due 1 while a maintenance interval is due.\n# TYPE fresa_maintenance_due gauge\n",
    );
    for m in app.machines.all() {
        for (state, secs) in m.state_seconds() {
            let _ = writeln!(
                out,
                "fresa_machine_state_seconds_total{{machine=\"{}\",state=\"{state}\"}} {secs:.3}",
                m.id
            );
        }
        let c = m.counters();
        let id = m.id;
        let _ = writeln!(
            counters,
            "fresa_machine_spindle_seconds_total{{machine=\"{id}\"}} {:.3}\nfresa_machine_motion_seconds_total{{machine=\"{id}\"}} {:.3}\nfresa_machine_jobs_total{{machine=\"{id}\"}} {}",
            c.spindle_hours * 3600.0,
            c.motion_hours * 3600.0,
            c.jobs
        );
        if let Some(d) = c.distance_mm.as_object() {
            for (axis, v) in d {
                let _ = writeln!(
                    counters,
                    "fresa_machine_distance_mm_total{{machine=\"{id}\",axis=\"{axis}\"}} {:.3}",
                    v.as_f64().unwrap_or(0.0)
                );
            }
        }
        for item in &c.maintenance {
            let name = item.name.as_str();
            let _ = writeln!(
                counters,
                "fresa_maintenance_due{{machine=\"{id}\",name=\"{name}\"}} {}",
                u8::from(item.due)
            );
        }
    }
    out.push_str(&counters);
    out
}

#[utoipa::path(get, path = "/api/v1/plugins", tag = "system",
    responses((status = 200, description = "Loaded `plugins`, load `failures`, `skipped` libraries with their reason, and the host's `abi`", body = Object)))]
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

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;

    /// The `Gate` decides from the path which requests are authenticated; the route table
    /// declares each route's role (`x-fresa-role` in the description). They must agree for every
    /// route, or a new route could be reachable without a token.
    #[test]
    fn the_gate_authenticates_exactly_the_routes_declared_with_a_role() {
        let (_, mut doc) = described_router(None, openapi::Document::new(|| ()));
        let mut operations = 0;
        for (path, item) in doc.paths.paths.iter_mut() {
            for op in openapi::operations(item) {
                let role = op
                    .extensions
                    .as_ref()
                    .and_then(|e| e.get("x-fresa-role"))
                    .and_then(|v| v.as_str())
                    .expect(path)
                    .to_string();
                let authenticated = !matches!(scope(path), Scope::Public);
                assert_eq!(
                    authenticated,
                    role != "none",
                    "{path} is declared with role {role}"
                );
                operations += 1;
            }
        }
        assert!(operations > 60, "only {operations} operations described");
    }
}

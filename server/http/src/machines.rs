use super::auth::Caller;
use super::error::{ApiError, Json, Path, Query};
use crate::openapi::ErrorBody;
use axum::extract::State;
use axum::http::StatusCode;
use axum::Extension;
use fresa_core::admin;
use fresa_core::machine::centre::{CentreAsk, CentreKind, CentreReport};
use fresa_core::machine::probing::{ProbeAsk, ProbeReport, TouchOffAsk, TouchOffReport};
use fresa_core::machine::{limits, Machine};
use fresa_core::store::MachineRow;
use fresa_core::views::{MachineView, StatusView};
use fresa_core::SharedApp;
use fresa_plugin_api::contract::{
    Axis, AxisValues, Command, MachineState, MachineStatus, ProbeUntil, WorkOffset,
};
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use std::sync::Arc;
use utoipa::ToSchema;

async fn machine(app: &SharedApp, id: i64) -> Result<Arc<Machine>, ApiError> {
    app.machines
        .get(id)
        .ok_or_else(|| ApiError::not_found("unknown_machine", format!("no machine with id {id}")))
}

fn machine_json(m: &Machine) -> MachineView {
    MachineView::new(m.row(), m.status())
}

fn view(row: MachineRow, status: MachineStatus) -> MachineView {
    MachineView::new(row, status)
}

/// A machine this node does not drive, from the store and its node's last heartbeat.
async fn remote_view(app: &SharedApp, id: i64) -> Result<MachineView, ApiError> {
    let row = app.store.machine(id).await?.ok_or_else(|| {
        ApiError::not_found("unknown_machine", format!("no machine with id {id}"))
    })?;
    let status = app.remote_status(&row).await;
    Ok(view(row, status))
}

/// `{"id": N}`: what a create answers with (201).
#[derive(Serialize, ToSchema)]
pub struct Created {
    pub id: i64,
}

/// `{"ok": true}`: the request was carried out.
#[derive(Serialize, ToSchema)]
pub struct Done {
    pub ok: bool,
}

#[utoipa::path(get, path = "/api/v1/machines", tag = "machines",
    responses((status = 200, description = "Every machine", body = [MachineView])))]
pub async fn list(State(app): State<SharedApp>) -> Result<Json<Vec<MachineView>>, ApiError> {
    // Every machine in the store: this node's live, the others' as of their node's heartbeat.
    let nodes: std::collections::HashMap<String, fresa_core::store::NodeRow> = app
        .store
        .list_nodes()
        .await?
        .into_iter()
        .map(|n| (n.name.clone(), n))
        .collect();
    let mut out = Vec::new();
    for row in app.store.list_machines().await? {
        match app.machines.get(row.id) {
            Some(m) => out.push(machine_json(&m)),
            None => {
                let node = row.node.as_deref().and_then(|n| nodes.get(n));
                let status = app.remote_status_from(&row, node);
                out.push(view(row, status));
            }
        }
    }
    Ok(Json(out))
}

#[utoipa::path(get, path = "/api/v1/machines/{id}", tag = "machines",
    params(("id" = i64, Path, description = "machine id", example = 1)),
    responses(
        (status = 200, description = "The machine", body = MachineView),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
    ))]
pub async fn get_one(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
) -> Result<Json<MachineView>, ApiError> {
    match app.machines.get(id) {
        Some(m) => Ok(Json(machine_json(&m))),
        None => remote_view(&app, id).await.map(Json),
    }
}

#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct NewMachine {
    /// Unique, at most 100 characters.
    name: String,
    /// A loaded backend plugin (`GET /plugins`).
    backend: String,
    /// The backend's settings; it checks them before anything is stored.
    #[serde(default)]
    #[schema(value_type = Option<Object>)]
    config: Option<Value>,
    /// Longest jog accepted, mm (default 50, at most 1000).
    #[serde(default)]
    max_jog_mm: Option<f64>,
    /// Fastest jog feed accepted, mm/min (default 5000, at most 100000).
    #[serde(default)]
    max_feed_mm_min: Option<f64>,
    /// Fastest probing feed, mm/min (default 300, at most 2000).
    max_probe_feed_mm_min: Option<f64>,
    /// The overrides an operator may set, percent (default feed 10-200, spindle 50-150,
    /// rapid 25-100; a range must hold 100).
    #[serde(default)]
    override_limits: Option<admin::OverrideLimits>,
    /// The machine Z (machine coordinates, mm) a start at a line or a resume goes up to at
    /// least before moving across to the start point (default: none; the machine's own Z and
    /// the program's highest Z before the line decide).
    #[serde(default)]
    safe_z_mm: Option<f64>,
    /// Maintenance intervals, each a `name` and one of `every_spindle_hours`,
    /// `every_motion_hours`, `every_jobs` (default none; at most 32). Each raises
    /// `machine.maintenance_due` once when it comes due (see `GET /machines/{id}/counters`).
    #[serde(default)]
    maintenance: Option<Vec<fresa_core::records::MaintenanceItem>>,
}

#[utoipa::path(post, path = "/api/v1/machines", tag = "machines",
    request_body(content = NewMachine, example = json!({"name": "router-2", "backend": "sim-machine", "config": {"time_scale": 0.01}})),
    responses(
        (status = 201, description = "Created", body = Created),
        (status = 409, description = "`name_taken`", body = ErrorBody),
        (status = 422, description = "`invalid_field`, `invalid_name`, `unknown_backend`, `invalid_config`", body = ErrorBody),
    ))]
pub async fn create(
    State(app): State<SharedApp>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<NewMachine>,
) -> Result<(StatusCode, Json<Created>), ApiError> {
    let req = admin::NewMachine {
        name: req.name,
        backend: req.backend,
        config: req.config,
        max_jog_mm: req.max_jog_mm,
        max_feed_mm_min: req.max_feed_mm_min,
        max_probe_feed_mm_min: req.max_probe_feed_mm_min,
        override_limits: req.override_limits,
        safe_z_mm: req.safe_z_mm,
        maintenance: req.maintenance,
    };
    let id = admin::create_machine(&app, req, &caller.name).await?;
    Ok((StatusCode::CREATED, Json(Created { id })))
}

/// `?until=STATE`: the status once the machine is in that state, e.g. `idle` after a jog (the
/// jog's answer comes when the move is under way, not done).
#[derive(Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct StatusWait {
    /// Answer once the machine is in this state (`idle`, `running`, `paused`, ...).
    #[param(example = "idle")]
    until: Option<MachineState>,
    /// Longest wait for `until`, in seconds: default 30, at most 60; then 409 `wait_timeout`.
    timeout_s: Option<f64>,
}

/// The longest a status request may wait for `until`: a waiting request holds a connection.
const MAX_STATUS_WAIT_S: f64 = 60.0;

#[utoipa::path(get, path = "/api/v1/machines/{id}/status", tag = "machines",
    params(("id" = i64, Path, description = "machine id", example = 1), StatusWait),
    responses(
        (status = 200, description = "The machine's status (with `until`: once it is in that state)", body = StatusView),
        (status = 400, description = "`invalid_query`: an unknown state or a timeout that is not 0..60 s", body = ErrorBody),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
        (status = 409, description = "`wait_timeout`: not in the `until` state within `timeout_s`", body = ErrorBody),
    ))]
pub async fn status(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Query(wait): Query<StatusWait>,
) -> Result<axum::response::Response, ApiError> {
    match app.machines.get(id) {
        Some(m) => {
            if let Some(target) = wait.until {
                wait_for_state(&m, target, wait.timeout_s).await?;
            }
            use axum::response::IntoResponse;
            // Serialised once per change and shared by every poll (see `status_json`).
            Ok((
                [(
                    axum::http::header::CONTENT_TYPE,
                    axum::http::HeaderValue::from_static("application/json"),
                )],
                m.status_json()?,
            )
                .into_response())
        }
        // Reached for another node's machine only while that node is unreachable (otherwise
        // the request was forwarded): offline, and why.
        None => {
            let row = app.store.machine(id).await?.ok_or_else(|| {
                ApiError::not_found("unknown_machine", format!("no machine with id {id}"))
            })?;
            Ok(axum::response::IntoResponse::into_response(Json(
                StatusView::remote(id, app.remote_status(&row).await),
            )))
        }
    }
}

/// Waits until `m` is in `target`, at most `timeout_s` (default 30 s, at most 60 s).
async fn wait_for_state(
    m: &Machine,
    target: MachineState,
    timeout_s: Option<f64>,
) -> Result<(), ApiError> {
    let seconds = timeout_s.unwrap_or(30.0);
    if !(seconds.is_finite() && (0.0..=MAX_STATUS_WAIT_S).contains(&seconds)) {
        return Err(ApiError::bad_request(
            "invalid_query",
            format!("query `timeout_s`: {seconds} is not 0 to {MAX_STATUS_WAIT_S} seconds"),
        ));
    }
    let mut rx = m.subscribe_status();
    let limit = std::time::Duration::from_secs_f64(seconds);
    // Reached, or the machine's task ended (shutdown): answer with what it last was.
    if tokio::time::timeout(limit, rx.wait_for(|s| s.state == target))
        .await
        .is_ok()
    {
        return Ok(());
    }
    Err(ApiError::conflict(
        "wait_timeout",
        format!(
            "machine {} is still {} after {seconds} s, not {}",
            m.id,
            m.status().state.as_str(),
            target.as_str()
        ),
    ))
}

#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct NodeReq {
    /// The node that drives the machine from now on (its `node_name`).
    node: String,
}

/// Moves a machine to another node (the hardware moved): that node starts driving it within a
/// heartbeat, and this one lets go. Refused while a run is active.
#[utoipa::path(put, path = "/api/v1/machines/{id}/node", tag = "machines",
    params(("id" = i64, Path, description = "machine id", example = 1)),
    request_body(content = NodeReq, example = json!({"node": "hall-2"})),
    responses(
        (status = 200, description = "Moved", body = MachineView),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
        (status = 409, description = "`machine_busy`: a run is active", body = ErrorBody),
        (status = 422, description = "`invalid_field`", body = ErrorBody),
    ))]
pub async fn set_node(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<NodeReq>,
) -> Result<Json<MachineView>, ApiError> {
    admin::set_machine_node(&app, id, &req.node, &caller.name).await?;
    remote_view(&app, id).await.map(Json)
}

#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct JogReq {
    axis: Axis,
    /// mm (degrees for A), signed; at most the machine's `max_jog_mm`. Not with `continuous`.
    #[serde(default)]
    distance: Option<f64>,
    /// mm/min; at most the machine's `max_feed_mm_min`.
    #[serde(default)]
    feed: Option<f64>,
    /// Move toward `direction` until `jog/cancel` or a missing keep-alive
    /// (`POST /machines/{id}/jog/keepalive` at least every 250 ms), at most `max_jog_mm`.
    #[serde(default)]
    continuous: bool,
    /// `+` or `-`: a continuous jog's direction.
    #[serde(default)]
    direction: Option<String>,
}

#[utoipa::path(post, path = "/api/v1/machines/{id}/jog", tag = "machines",
    params(("id" = i64, Path, description = "machine id", example = 1)),
    request_body(content = JogReq, example = json!({"axis": "X", "distance": 5.0})),
    responses(
        (status = 200, description = "The jog was carried out (a continuous one: started)", body = Done),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
        (status = 409, description = "`machine_busy` (also: a continuous jog is under way), `stopped`, `backend_rejected`", body = ErrorBody),
        (status = 422, description = "`jog_too_far`, `feed_out_of_range`, `invalid_field`, `backend_rejected`", body = ErrorBody),
        (status = 502, description = "`backend_error`", body = ErrorBody),
        (status = 503, description = "`machine_offline`, `machine_unresponsive`, `shutting_down`", body = ErrorBody),
        (status = 504, description = "`backend_timeout`", body = ErrorBody),
    ))]
pub async fn jog(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<JogReq>,
) -> Result<Json<Done>, ApiError> {
    let m = machine(&app, id).await?;
    let invalid = |m: &str| ApiError::unprocessable("invalid_field", m.to_string());
    match (req.continuous, req.distance, req.direction.as_deref()) {
        (false, Some(distance), None) => m.jog(req.axis, distance, req.feed, &caller.name).await?,
        (true, None, Some(d @ ("+" | "-"))) => {
            m.jog_continuous(req.axis, d == "+", req.feed, &caller.name)
                .await?
        }
        (false, None, _) => return Err(invalid("field `distance` is required (or `continuous`)")),
        (false, Some(_), Some(_)) => {
            return Err(invalid(
                "field `direction` is for a continuous jog; `distance` has its sign",
            ))
        }
        (true, Some(_), _) => {
            return Err(invalid(
                "field `distance` is not for a continuous jog (it moves until released)",
            ))
        }
        (true, None, _) => {
            return Err(invalid(
                "field `direction` must be \"+\" or \"-\" for a continuous jog",
            ))
        }
    }
    Ok(Json(Done { ok: true }))
}

/// Keeps a continuous jog going for another 250 ms.
#[utoipa::path(post, path = "/api/v1/machines/{id}/jog/keepalive", tag = "machines",
    params(("id" = i64, Path, description = "machine id", example = 1)),
    responses(
        (status = 200, description = "Still held", body = Done),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
        (status = 409, description = "`no_continuous_jog`: it ended (its whole way, a cancel or stop, or a missed keep-alive)", body = ErrorBody),
    ))]
pub async fn jog_keepalive(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
) -> Result<Json<Done>, ApiError> {
    machine(&app, id).await?.jog_keepalive()?;
    Ok(Json(Done { ok: true }))
}

/// `{"ok": true, "stopped": bool}`: whether a motion was under way when the cancel came.
#[derive(Serialize, ToSchema)]
pub struct JogCancelled {
    ok: bool,
    stopped: bool,
}

/// Ends the jog under way and drops every jog still queued for the machine (HTTP, MQTT, CLI,
/// pendant wheel moves and macros); answered once the backend confirmed motion stopped.
#[utoipa::path(post, path = "/api/v1/machines/{id}/jog/cancel", tag = "machines",
    params(("id" = i64, Path, description = "machine id", example = 1)),
    responses(
        (status = 200, description = "Stopped; nothing queued before it will move the machine", body = JogCancelled),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
        (status = 409, description = "`machine_busy`: a job runs (pause or cancel the job instead), `backend_rejected` (`stop_unconfirmed`)", body = ErrorBody),
        (status = 502, description = "`backend_error`", body = ErrorBody),
        (status = 503, description = "`machine_offline`, `machine_unresponsive`", body = ErrorBody),
        (status = 504, description = "`backend_timeout`", body = ErrorBody),
    ))]
pub async fn jog_cancel(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
) -> Result<Json<JogCancelled>, ApiError> {
    let m = machine(&app, id).await?;
    let answer = m.cancel_jogs(&caller.name).await?;
    Ok(Json(JogCancelled {
        ok: true,
        stopped: answer["stopped"].as_bool().unwrap_or(false),
    }))
}

/// `+` or `-` (a probing direction), or an error naming the field.
fn toward(field: &str, v: &str) -> Result<bool, ApiError> {
    match v {
        "+" => Ok(true),
        "-" => Ok(false),
        other => Err(ApiError::unprocessable(
            "invalid_field",
            format!("field `{field}` must be \"+\" or \"-\", got {other:?}"),
        )),
    }
}

#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ProbeReq {
    axis: Axis,
    /// `+` or `-`: the direction to probe in.
    toward: String,
    /// mm to move at most (positive); at most the machine's `max_jog_mm`.
    distance: f64,
    /// mm/min; at most the machine's `max_probe_feed_mm_min`.
    feed: f64,
    /// `contact` (default, G38.2) or `release` (G38.4): what ends the move.
    #[serde(default)]
    until: ProbeUntil,
}

/// A probing move for scripts: moves until the probe input changes (or the distance ends) and
/// answers where it tripped. Refused if the probe already reads what it looks for; a stop
/// during it answers `stopped` once motion ended; a dropped connection stops it.
#[utoipa::path(post, path = "/api/v1/machines/{id}/probe", tag = "machines",
    params(("id" = i64, Path, description = "machine id", example = 1)),
    request_body(content = ProbeReq, example = json!({"axis": "Z", "toward": "-", "distance": 40, "feed": 300})),
    responses(
        (status = 200, description = "The move ended: `tripped` with the trip position, or `not_tripped`", body = ProbeReport),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
        (status = 409, description = "`probe_already_in_state`, `stopped` (a stop or feed hold ended it), `probe_failed` (an alarm), `machine_busy`", body = ErrorBody),
        (status = 422, description = "`probe_unsupported` (no probe input, or not this axis), `out_of_travel` (the whole distance must be inside the travel), `probe_too_far`, `feed_out_of_range`, `invalid_field`", body = ErrorBody),
        (status = 503, description = "`machine_offline`, `machine_unresponsive`, `shutting_down`, `database_unavailable`", body = ErrorBody),
        (status = 504, description = "`backend_timeout`, `probe_unconfirmed`", body = ErrorBody),
    ))]
pub async fn probe(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<ProbeReq>,
) -> Result<Json<ProbeReport>, ApiError> {
    let m = machine(&app, id).await?;
    let ask = ProbeAsk {
        axis: req.axis,
        positive: toward("toward", &req.toward)?,
        distance: req.distance,
        feed: req.feed,
        until: req.until,
    };
    Ok(Json(m.probe(ask, &caller.name).await?))
}

/// Overrides to set, percent of the programmed value; a field left out stays as it is.
#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct OverridesReq {
    /// Feed override for program and MDI feed moves (default range 10-200).
    #[serde(default)]
    feed: Option<f64>,
    /// Spindle speed override (default range 50-150).
    #[serde(default)]
    spindle: Option<f64>,
    /// Rapid (G0) override (default range 25-100).
    #[serde(default)]
    rapid: Option<f64>,
}

/// The overrides in force, percent, as the machine reports them.
#[derive(Serialize, ToSchema)]
pub struct OverridesView {
    feed: f64,
    spindle: f64,
    rapid: f64,
}

/// Sets the feed, spindle and/or rapid override, also while a job runs (that is when an
/// operator needs it: chatter, a tool about to break). Applied from the backend's next planning
/// interval; jogs and probing moves keep their own feeds. Recorded as `machine.command`
/// (`set_overrides`). Overrides start at 100 % whenever the server starts.
#[utoipa::path(post, path = "/api/v1/machines/{id}/overrides", tag = "machines",
    params(("id" = i64, Path, description = "machine id", example = 1)),
    request_body(content = OverridesReq, example = json!({"feed": 50, "rapid": 25})),
    responses(
        (status = 200, description = "The overrides in force", body = OverridesView),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
        (status = 422, description = "`override_out_of_range` (outside the machine's `override_limits`), `invalid_field`, `backend_rejected` (message `unsupported: ...`: the backend cannot apply one, saying why; nothing changed)", body = ErrorBody),
        (status = 503, description = "`machine_offline`, `machine_unresponsive`, `shutting_down`", body = ErrorBody),
        (status = 504, description = "`backend_timeout`", body = ErrorBody),
    ))]
pub async fn overrides(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<OverridesReq>,
) -> Result<Json<OverridesView>, ApiError> {
    let m = machine(&app, id).await?;
    let command = Command::SetOverrides {
        feed: req.feed,
        spindle: req.spindle,
        rapid: req.rapid,
    };
    m.command(command, &caller.name).await?;
    let st = m.status();
    Ok(Json(OverridesView {
        feed: st.feed_override,
        spindle: st.spindle_override,
        rapid: st.rapid_override,
    }))
}

fn default_retract() -> f64 {
    5.0
}

#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct TouchOffReq {
    /// `Z`, or `X`/`Y` (edge finding, with `toward` and `tool_diameter_mm`).
    axis: Axis,
    /// The plate's thickness, mm (0: the tool touches the part itself). Z reads this where
    /// the tool touches; on X/Y the part's edge behind the plate becomes 0.
    plate_mm: f64,
    /// X/Y: the tool's (or probe tip's) diameter, mm.
    #[serde(default)]
    tool_diameter_mm: Option<f64>,
    /// mm to probe at most; at most the machine's `max_jog_mm`.
    distance: f64,
    /// mm/min; at most the machine's `max_probe_feed_mm_min`.
    feed: f64,
    /// mm to move back off the plate afterwards (default 5).
    #[serde(default = "default_retract")]
    retract_mm: f64,
    /// `-` or `+`; on Z `-` (down onto the plate) when left out, required on X/Y.
    #[serde(default)]
    toward: Option<String>,
}

/// Touch-off on a plate: probes toward it, sets the active work offset so Z reads the plate's
/// thickness where the tool touched (on X/Y: so the part's edge behind the plate reads 0,
/// the tool's radius taken into account), retracts, and answers once the retract ended. A
/// probe that does not touch changes nothing.
#[utoipa::path(post, path = "/api/v1/machines/{id}/touch-off", tag = "machines",
    params(("id" = i64, Path, description = "machine id", example = 1)),
    request_body(content = TouchOffReq, example = json!({"axis": "Z", "plate_mm": 15, "distance": 40, "feed": 300, "retract_mm": 5})),
    responses(
        (status = 200, description = "The offset was set and the tool retracted", body = TouchOffReport),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
        (status = 409, description = "`probe_already_in_state`, `stopped`, `probe_failed`, `machine_busy`, `machine_moving`", body = ErrorBody),
        (status = 422, description = "`probe_not_tripped` (nothing changed), `probe_unsupported`, `out_of_travel`, `probe_too_far`, `feed_out_of_range`, `invalid_field`", body = ErrorBody),
        (status = 503, description = "`machine_offline`, `machine_unresponsive`, `shutting_down`, `database_unavailable`", body = ErrorBody),
        (status = 504, description = "`backend_timeout`, `probe_unconfirmed`", body = ErrorBody),
    ))]
pub async fn touch_off(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<TouchOffReq>,
) -> Result<Json<TouchOffReport>, ApiError> {
    let m = machine(&app, id).await?;
    let positive = match (req.axis, req.toward.as_deref()) {
        (_, Some(t)) => toward("toward", t)?,
        (Axis::Z, None) => false,
        (a, None) => {
            return Err(ApiError::unprocessable(
                "invalid_field",
                format!(
                    "field `toward` (\"+\" or \"-\") is needed for an {} touch-off",
                    a.letter()
                ),
            ))
        }
    };
    let ask = TouchOffAsk {
        axis: req.axis,
        positive,
        plate_mm: req.plate_mm,
        tool_diameter_mm: req.tool_diameter_mm,
        distance: req.distance,
        feed: req.feed,
        retract_mm: req.retract_mm,
    };
    Ok(Json(m.touch_off(ask, &caller.name).await?))
}

fn default_clearance() -> f64 {
    5.0
}

#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct FindCentreReq {
    /// `bore` (the tool inside a hole, at the probing depth) or `boss` (above a round stud).
    kind: CentreKind,
    /// The tool's (or probe tip's) diameter, mm.
    tool_diameter_mm: f64,
    /// Bore: how far to probe out each way; boss: how far to probe in from outside it
    /// (default twice `clearance_mm`). mm, at most `max_jog_mm`.
    #[serde(default)]
    distance: Option<f64>,
    /// Probing feed, mm/min, at most the machine's `max_probe_feed_mm_min`.
    feed: f64,
    /// Put the active work offset's X/Y zero on the centre (default true).
    #[serde(default = "yes")]
    set_zero: bool,
    /// Boss: its diameter, roughly, mm.
    #[serde(default)]
    boss_diameter_mm: Option<f64>,
    /// Boss: how far outside it the tool goes down, mm (default 5).
    #[serde(default = "default_clearance")]
    clearance_mm: f64,
    /// Boss: how far below the start Z to probe, mm.
    #[serde(default)]
    depth_mm: Option<f64>,
}

fn yes() -> bool {
    true
}

/// Finds a bore's or a boss's centre by probing X both ways, Y both ways through the X
/// chord's midpoint, and X again through the centre; ends on the centre and, with `set_zero`,
/// moves the active work offset so X and Y read 0 there. A probe that finds no wall changes
/// nothing. Recorded as `machine.touch_off` (`source` `bore_centre` / `boss_centre`).
#[utoipa::path(post, path = "/api/v1/machines/{id}/find-centre", tag = "machines",
    params(("id" = i64, Path, description = "machine id", example = 1)),
    request_body(content = FindCentreReq, example = json!({"kind": "bore", "tool_diameter_mm": 6, "distance": 20, "feed": 100})),
    responses(
        (status = 200, description = "The centre and both diameters (and the offset, when set)", body = CentreReport),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
        (status = 409, description = "`probe_already_in_state`, `stopped`, `probe_failed`, `machine_busy`, `machine_moving`, `machine_moved`", body = ErrorBody),
        (status = 422, description = "`probe_not_tripped` (no wall within the distance; nothing changed), `probe_unsupported`, `out_of_travel`, `probe_too_far`, `feed_out_of_range`, `invalid_field`", body = ErrorBody),
        (status = 503, description = "`machine_offline`, `machine_unresponsive`, `shutting_down`, `database_unavailable`", body = ErrorBody),
        (status = 504, description = "`backend_timeout`, `probe_unconfirmed`", body = ErrorBody),
    ))]
pub async fn find_centre(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<FindCentreReq>,
) -> Result<Json<CentreReport>, ApiError> {
    let m = machine(&app, id).await?;
    let ask = CentreAsk {
        kind: req.kind,
        tool_diameter_mm: req.tool_diameter_mm,
        distance: match (req.kind, req.distance) {
            (_, Some(d)) => d,
            (CentreKind::Boss, None) => 2.0 * req.clearance_mm,
            (CentreKind::Bore, None) => {
                return Err(ApiError::unprocessable(
                    "invalid_field",
                    "field `distance` is needed for a bore: how far to probe out each way",
                ))
            }
        },
        feed: req.feed,
        set_zero: req.set_zero,
        boss_diameter_mm: req.boss_diameter_mm,
        clearance_mm: req.clearance_mm,
        depth_mm: req.depth_mm,
    };
    Ok(Json(m.find_centre(ask, &caller.name).await?))
}

#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct MdiReq {
    /// One G-code line, checked before it is sent.
    line: String,
}

#[utoipa::path(post, path = "/api/v1/machines/{id}/mdi", tag = "machines",
    params(("id" = i64, Path, description = "machine id", example = 1)),
    request_body(content = MdiReq, example = json!({"line": "G91 G0 Z5"})),
    responses(
        (status = 200, description = "The line was carried out", body = Done),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
        (status = 409, description = "`machine_busy`, `stopped`, `backend_rejected`", body = ErrorBody),
        (status = 422, description = "`invalid_gcode` (with the column), `backend_rejected`", body = ErrorBody),
        (status = 502, description = "`backend_error`", body = ErrorBody),
        (status = 503, description = "`machine_offline`, `machine_unresponsive`, `shutting_down`", body = ErrorBody),
        (status = 504, description = "`backend_timeout`", body = ErrorBody),
    ))]
pub async fn mdi(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<MdiReq>,
) -> Result<Json<Done>, ApiError> {
    let m = machine(&app, id).await?;
    m.mdi(&req.line, &caller.name).await?;
    Ok(Json(Done { ok: true }))
}

/// `{"ok": true, "result": ...}`: the backend's answer, e.g. `{"output", "on"}` for a toggle.
#[derive(Serialize, ToSchema)]
pub struct CommandDone {
    ok: bool,
    #[schema(value_type = Object)]
    result: Value,
}

#[utoipa::path(post, path = "/api/v1/machines/{id}/commands", tag = "machines",
    params(("id" = i64, Path, description = "machine id", example = 1)),
    request_body(content = Command, example = json!({"command": "zero", "axis": "X"})),
    responses(
        (status = 200, description = "The command was carried out", body = CommandDone),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
        (status = 409, description = "`machine_busy`, `machine_moving` (zero, select_offset while the machine moves), `stopped`, `backend_rejected`", body = ErrorBody),
        (status = 422, description = "`invalid_command`, `backend_rejected`", body = ErrorBody),
        (status = 502, description = "`backend_error`", body = ErrorBody),
        (status = 503, description = "`machine_offline`, `machine_unresponsive`, `shutting_down`", body = ErrorBody),
        (status = 504, description = "`backend_timeout`", body = ErrorBody),
    ))]
pub async fn command(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
    Json(raw): Json<Value>,
) -> Result<Json<CommandDone>, ApiError> {
    let m = machine(&app, id).await?;
    let cmd = limits::parse_command(&raw)?;
    let answer = m.command(cmd, &caller.name).await?;
    Ok(Json(CommandDone {
        ok: true,
        result: answer,
    }))
}

/// The work offsets and which is active.
#[derive(ToSchema)]
#[allow(dead_code)] // describes the JSON `offsets` builds
pub struct OffsetsView {
    active: WorkOffset,
    /// `G54`..`G59` to their values.
    offsets: std::collections::BTreeMap<String, AxisValues>,
}

#[utoipa::path(get, path = "/api/v1/machines/{id}/offsets", tag = "machines",
    params(("id" = i64, Path, description = "machine id", example = 1)),
    responses(
        (status = 200, description = "The work offsets", body = OffsetsView),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
    ))]
pub async fn offsets(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
) -> Result<Json<Value>, ApiError> {
    let m = machine(&app, id).await?;
    let offsets = app.store.offsets(id).await?;
    let map: serde_json::Map<String, Value> = offsets
        .iter()
        .map(|(o, v)| (o.name().to_string(), json!(v)))
        .collect();
    Ok(Json(
        json!({"active": m.row().active_offset, "offsets": map}),
    ))
}

/// Any of the axes; the others keep their values.
#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct OffsetReq {
    x: Option<f64>,
    y: Option<f64>,
    z: Option<f64>,
    a: Option<f64>,
}

/// `{"offset", "values"}`: the offset as now stored.
#[derive(ToSchema)]
#[allow(dead_code)] // describes the JSON `set_offset` builds
pub struct OffsetSet {
    offset: WorkOffset,
    values: AxisValues,
}

#[utoipa::path(put, path = "/api/v1/machines/{id}/offsets/{name}", tag = "machines",
    params(("id" = i64, Path, description = "machine id", example = 1),
           ("name" = WorkOffset, Path, description = "G54..G59", example = "G55")),
    request_body(content = OffsetReq, example = json!({"x": 10.0, "y": 20.0})),
    responses(
        (status = 200, description = "Set in the backend and stored", body = OffsetSet),
        (status = 404, description = "`unknown_machine`, `unknown_offset`", body = ErrorBody),
        (status = 409, description = "`machine_moving`, `backend_rejected`", body = ErrorBody),
        (status = 422, description = "`invalid_field`", body = ErrorBody),
        (status = 503, description = "`machine_offline`, `machine_unresponsive`", body = ErrorBody),
    ))]
pub async fn set_offset(
    State(app): State<SharedApp>,
    Path((id, name)): Path<(i64, String)>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<OffsetReq>,
) -> Result<Json<Value>, ApiError> {
    let m = machine(&app, id).await?;
    let offset = WorkOffset::parse(&name).ok_or_else(|| {
        ApiError::not_found(
            "unknown_offset",
            format!("{name:?} is not a work offset (G54..G59)"),
        )
    })?;
    let current = app
        .store
        .offsets(id)
        .await?
        .into_iter()
        .find(|(o, _)| *o == offset)
        .map(|(_, v)| v)
        .unwrap_or_default();
    let mut values = current;
    for (axis, v) in [
        (Axis::X, req.x),
        (Axis::Y, req.y),
        (Axis::Z, req.z),
        (Axis::A, req.a),
    ] {
        if let Some(v) = v {
            if !v.is_finite() {
                return Err(ApiError::unprocessable(
                    "invalid_field",
                    format!(
                        "field `{}` must be a finite number",
                        axis.letter().to_ascii_lowercase()
                    ),
                ));
            }
            values.set(axis, v);
        }
    }
    m.set_offset(offset, values, &caller.name).await?;
    Ok(Json(json!({"offset": offset, "values": values})))
}

#[derive(Deserialize, Default, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct PartZeroReq {
    /// Machine coordinates of the part zero; the current machine position when absent.
    #[serde(default)]
    position: Option<AxisValues>,
    #[serde(default)]
    source: Option<String>,
    #[serde(default)]
    note: Option<String>,
}

#[utoipa::path(post, path = "/api/v1/machines/{id}/part-zero", tag = "machines",
    params(("id" = i64, Path, description = "machine id", example = 1)),
    request_body(content = Option<PartZeroReq>, description = "Optional: an empty body records the current machine position", example = json!({"note": "vise jaw, left"})),
    responses(
        (status = 201, description = "Recorded: `id`, `machine_id`, `x`, `y`, `z`, `a`, `source`, `actor`, `note`, `created_at`", body = Object),
        (status = 400, description = "`invalid_json`", body = ErrorBody),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
        (status = 409, description = "`machine_moving`: nothing is recorded while the machine moves (or holds a paused job)", body = ErrorBody),
        (status = 503, description = "`machine_offline`, `machine_unresponsive`, `database_unavailable`", body = ErrorBody),
    ))]
pub async fn record_part_zero(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
    body: axum::body::Bytes,
) -> Result<(StatusCode, Json<Value>), ApiError> {
    let m = machine(&app, id).await?;
    // The body is optional: an empty POST records the current position.
    let req: PartZeroReq = if body.iter().all(u8::is_ascii_whitespace) {
        PartZeroReq::default()
    } else {
        serde_json::from_slice(&body)
            .map_err(|e| ApiError::bad_request("invalid_json", format!("part zero: {e}")))?
    };
    let req = admin::PartZero {
        position: req.position,
        source: req.source,
        note: req.note,
    };
    let row = admin::record_part_zero(&m, req, &caller.name).await?;
    Ok((StatusCode::CREATED, Json(json!(row))))
}

#[utoipa::path(get, path = "/api/v1/machines/{id}/part-zero", tag = "machines",
    params(("id" = i64, Path, description = "machine id", example = 1)),
    responses(
        (status = 200, description = "Part-zero history, newest first: `id`, `machine_id`, `x`, `y`, `z`, `a`, `source`, `actor`, `note`, `created_at`", body = [Object]),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
    ))]
pub async fn part_zeros(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
) -> Result<Json<Value>, ApiError> {
    machine(&app, id).await?;
    Ok(Json(json!(app.store.part_zeros(id).await?)))
}

/// `GET /machines/{id}/as-program`: the controller program the backend generates (robot
/// backends), as a download.
#[utoipa::path(get, path = "/api/v1/machines/{id}/as-program", tag = "machines",
    params(("id" = i64, Path, description = "machine id", example = 1)),
    responses(
        (status = 200, description = "The generated program (kawasaki-as `fresa-v1`), as an attachment", content_type = "text/plain", body = String),
        (status = 404, description = "`unknown_machine`; `no_artifact` for backends without one", body = ErrorBody),
        (status = 409, description = "`not_available` (a legacy-protocol robot)", body = ErrorBody),
    ))]
pub async fn as_program(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
) -> Result<axum::response::Response, ApiError> {
    artifact(&app, id, "as-program").await
}

async fn artifact(
    app: &SharedApp,
    id: i64,
    name: &str,
) -> Result<axum::response::Response, ApiError> {
    use axum::response::IntoResponse;
    let m = machine(app, id).await?;
    let backend = m.row().backend;
    let answer = m.artifact(name).await?;
    let body = answer["body"]
        .as_str()
        .ok_or_else(|| {
            ApiError::internal(format!("backend {backend} answered {name} without a body"))
        })?
        .to_string();
    let content_type = answer["content_type"]
        .as_str()
        .unwrap_or("application/octet-stream")
        .to_string();
    let file_name = answer["file_name"]
        .as_str()
        .unwrap_or(name)
        .replace('"', "");
    Ok((
        [
            (axum::http::header::CONTENT_TYPE, content_type),
            (
                axum::http::header::CONTENT_DISPOSITION,
                format!("attachment; filename=\"{file_name}\""),
            ),
        ],
        body,
    )
        .into_response())
}

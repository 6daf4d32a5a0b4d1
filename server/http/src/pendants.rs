use super::auth::Caller;
use super::error::{ApiError, Json, Path};
use crate::machines::Created;
use crate::openapi::ErrorBody;
use axum::extract::State;
use axum::http::StatusCode;
use axum::Extension;
use fresa_core::admin;
use fresa_core::pendants as core;
use fresa_core::SharedApp;
use serde::Deserialize;
use serde_json::Value;
use std::collections::BTreeMap;
use utoipa::ToSchema;

#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct NewPendant {
    name: String,
    /// `host:port` (default port 8001), an IP or DNS name.
    address: String,
    /// The machine to bind it to.
    #[serde(default)]
    machine: Option<i64>,
    /// `firmware` (default) or `document`.
    #[serde(default)]
    dialect: Option<String>,
    #[serde(default)]
    #[schema(value_type = Option<Object>)]
    config: Option<Value>,
    /// `M1`..`M4` to an action (`{"type": "command"|"jog"|"toggle"|"mdi", ...}`) or null.
    #[serde(default)]
    #[schema(value_type = Option<Object>)]
    macros: Option<BTreeMap<String, Option<Value>>>,
}

/// A pendant and its link.
#[derive(ToSchema)]
#[allow(dead_code)] // describes `fresa_core::pendants::pendant_json`
pub struct Pendant {
    id: i64,
    name: String,
    address: String,
    dialect: String,
    machine: Option<i64>,
    connected: bool,
    #[schema(value_type = Object)]
    config: Value,
    /// `M1`..`M4` to their action (or null).
    #[schema(value_type = Object)]
    macros: Value,
    /// False when the transport plugin is not loaded; `reason` says why.
    available: bool,
    reason: Option<String>,
    created_at: i64,
}

#[utoipa::path(post, path = "/api/v1/pendants", tag = "pendants",
    request_body(content = NewPendant, example = json!({"name": "bench-1", "address": "127.0.0.1:8001", "dialect": "firmware"})),
    responses(
        (status = 201, description = "Created; the server connects to it", body = Created),
        (status = 409, description = "`name_taken`", body = ErrorBody),
        (status = 422, description = "`invalid_field`, `invalid_name`, `unknown_machine`, `machine_on_other_node`", body = ErrorBody),
    ))]
pub async fn create(
    State(app): State<SharedApp>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<NewPendant>,
) -> Result<(StatusCode, Json<Created>), ApiError> {
    let req = admin::NewPendant {
        name: req.name,
        address: req.address,
        machine: req.machine,
        dialect: req.dialect,
        config: req.config,
        macros: req.macros,
    };
    let id = admin::create_pendant(&app, req, &caller.name).await?;
    Ok((StatusCode::CREATED, Json(Created { id })))
}

#[utoipa::path(get, path = "/api/v1/pendants", tag = "pendants",
    responses((status = 200, description = "Every pendant", body = [Pendant])))]
pub async fn list(State(app): State<SharedApp>) -> Json<Vec<Value>> {
    Json(
        app.pendants
            .all()
            .await
            .iter()
            .map(|p| core::pendant_json(p))
            .collect(),
    )
}

async fn pendant(app: &SharedApp, id: i64) -> Result<std::sync::Arc<core::Pendant>, ApiError> {
    app.pendants
        .get(id)
        .await
        .ok_or_else(|| ApiError::not_found("unknown_pendant", format!("no pendant with id {id}")))
}

#[utoipa::path(get, path = "/api/v1/pendants/{id}", tag = "pendants",
    params(("id" = i64, Path, description = "pendant id", example = 1)),
    responses(
        (status = 200, description = "The pendant", body = Pendant),
        (status = 404, description = "`unknown_pendant`", body = ErrorBody),
    ))]
pub async fn get_one(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
) -> Result<Json<Value>, ApiError> {
    let p = pendant(&app, id).await?;
    Ok(Json(core::pendant_json(&p)))
}

/// `null` and absent differ for `machine`: absent keeps the binding, `null` unbinds.
fn double_option<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Option<Option<i64>>, D::Error> {
    Option::<i64>::deserialize(d).map(Some)
}

#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct PatchPendant {
    /// Bind to this machine; `null` unbinds; absent keeps the binding.
    #[serde(default, deserialize_with = "double_option")]
    #[schema(value_type = Option<i64>)]
    machine: Option<Option<i64>>,
    /// `M1`..`M4` to an action or null (see `NewPendant.macros`).
    #[serde(default)]
    #[schema(value_type = Option<Object>)]
    macros: Option<BTreeMap<String, Option<Value>>>,
}

#[utoipa::path(patch, path = "/api/v1/pendants/{id}", tag = "pendants",
    params(("id" = i64, Path, description = "pendant id", example = 1)),
    request_body(content = PatchPendant, example = json!({"machine": null})),
    responses(
        (status = 200, description = "The pendant as now bound", body = Pendant),
        (status = 404, description = "`unknown_pendant`", body = ErrorBody),
        (status = 422, description = "`invalid_field`, `unknown_machine`, `machine_on_other_node`", body = ErrorBody),
    ))]
pub async fn patch(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<PatchPendant>,
) -> Result<Json<Value>, ApiError> {
    let p = pendant(&app, id).await?;
    admin::change_pendant(&app, &p, req.machine, req.macros.as_ref(), &caller.name).await?;
    Ok(Json(core::pendant_json(&p)))
}

#[utoipa::path(delete, path = "/api/v1/pendants/{id}", tag = "pendants",
    params(("id" = i64, Path, description = "pendant id", example = 1)),
    responses(
        (status = 204, description = "Removed; its link is closed"),
        (status = 404, description = "`unknown_pendant`", body = ErrorBody),
    ))]
pub async fn delete(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
) -> Result<StatusCode, ApiError> {
    pendant(&app, id).await?;
    admin::delete_pendant(&app, id, &caller.name).await?;
    Ok(StatusCode::NO_CONTENT)
}

#[utoipa::path(get, path = "/api/v1/pendants/discovered", tag = "pendants",
    responses((status = 200, description = "Pendants announced on the LAN by mDNS (`MPGnnnnnn`, `_http._tcp`)", body = Object)))]
pub async fn discovered(State(app): State<SharedApp>) -> Result<Json<Value>, ApiError> {
    Ok(Json(core::discovered(&app).await?))
}

#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct PendantNodeReq {
    /// The node whose network the pendant is on now (its `node_name`).
    node: String,
}

/// Moves a pendant to another node (it was carried to another hall): that node opens its link
/// within a heartbeat and this one closes it. The machine binding is kept only if that machine
/// is driven by the new node.
#[utoipa::path(put, path = "/api/v1/pendants/{id}/node", tag = "pendants",
    params(("id" = i64, Path, description = "pendant id", example = 1)),
    request_body(content = PendantNodeReq, example = json!({"node": "hall-2"})),
    responses(
        (status = 200, description = "Moved: `{\"pendant\", \"node\", \"machine\"}`", body = Object),
        (status = 404, description = "`unknown_pendant`", body = ErrorBody),
        (status = 422, description = "`invalid_field`", body = ErrorBody),
    ))]
pub async fn set_node(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<PendantNodeReq>,
) -> Result<Json<Value>, ApiError> {
    let body = admin::set_pendant_node(&app, id, &req.node, &caller.name).await?;
    Ok(Json(body))
}

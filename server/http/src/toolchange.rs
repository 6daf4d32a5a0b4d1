//! Run settings (optional stop, what M6 does, the tool-change position, the tool setter) and
//! measuring a tool on the setter (issues 25 and 26): `/machines/{id}/run-settings`,
//! `/machines/{id}/tools/{tool}/measure`.

use super::auth::Caller;
use super::error::{ApiError, Json, Path};
use crate::openapi::ErrorBody;
use axum::extract::State;
use axum::Extension;
use fresa_core::run_settings::RunSettingsView;
use fresa_core::tool_setter::MeasureReport;
use fresa_core::SharedApp;
use serde_json::Value;

#[utoipa::path(get, path = "/api/v1/machines/{id}/run-settings", tag = "machines",
    params(("id" = i64, Path, description = "machine id", example = 1)),
    responses(
        (status = 200, description = "The machine's run settings (the defaults until changed)", body = RunSettingsView),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
    ))]
pub async fn get_run_settings(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
) -> Result<Json<RunSettingsView>, ApiError> {
    Ok(Json(fresa_core::run_settings::get(&app, id).await?))
}

/// Changes the settings given and keeps the others: `optional_stop` (M1 holds when on),
/// `tool_change` (`hold`, `ignore`, `refuse`), `tool_change_position` (machine X Y Z, or null),
/// `tool_setter` (`{x, y, z, distance_mm, feed_mm_min, reference_tool}`, or null). They apply
/// from the next job start.
#[utoipa::path(patch, path = "/api/v1/machines/{id}/run-settings", tag = "machines",
    params(("id" = i64, Path, description = "machine id", example = 1)),
    request_body(content = Object, example = json!({"optional_stop": true, "tool_change": "hold",
        "tool_change_position": {"x": 0, "y": 0, "z": 0},
        "tool_setter": {"x": 0, "y": 0, "z": 0, "distance_mm": 20, "feed_mm_min": 200, "reference_tool": 1}})),
    responses(
        (status = 200, description = "The settings now", body = RunSettingsView),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
        (status = 422, description = "`invalid_field`", body = ErrorBody),
        (status = 503, description = "`database_unavailable`", body = ErrorBody),
    ))]
pub async fn patch_run_settings(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
    Json(changes): Json<Value>,
) -> Result<Json<RunSettingsView>, ApiError> {
    Ok(Json(
        fresa_core::run_settings::patch(&app, id, &changes, &caller.name).await?,
    ))
}

/// Measures the tool in the spindle (taken to be `tool`) on the machine's tool setter: up to
/// the setter's Z, across, probe down, back up. Its length (trip Z minus the reference tool's)
/// goes into the tool table; during a tool-change hold for it, without G43, the work offset's
/// Z is moved by the new length minus the old tool's. Allowed while the machine is idle or
/// held for a tool change.
#[utoipa::path(post, path = "/api/v1/machines/{id}/tools/{tool}/measure", tag = "machines",
    params(("id" = i64, Path, description = "machine id", example = 1),
           ("tool" = i64, Path, description = "tool number", example = 1)),
    responses(
        (status = 200, description = "Measured and stored", body = MeasureReport),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
        (status = 409, description = "`no_tool_setter`, `reference_not_measured`, `machine_busy`, `machine_moving`, `probe_already_in_state`, `stopped`, `probe_failed`", body = ErrorBody),
        (status = 422, description = "`probe_not_tripped` (nothing stored), `invalid_field`, `out_of_travel`, `jog_too_far`", body = ErrorBody),
        (status = 503, description = "`machine_offline`, `machine_unresponsive`, `shutting_down`, `database_unavailable`", body = ErrorBody),
        (status = 504, description = "`backend_timeout`, `probe_unconfirmed`", body = ErrorBody),
    ))]
pub async fn measure_tool(
    State(app): State<SharedApp>,
    Path((id, tool)): Path<(i64, i64)>,
    Extension(caller): Extension<Caller>,
) -> Result<Json<MeasureReport>, ApiError> {
    Ok(Json(
        fresa_core::tool_setter::measure(&app, id, tool, &caller.name).await?,
    ))
}

//! Height maps (issue 25): probe a grid over an area, list, show and delete maps, and how a
//! map fits a job. The core does the work (`fresa_core::machine::heightmap`); these only parse
//! and shape the answers.

use super::auth::Caller;
use super::error::{ApiError, Json, Path, Query};
use crate::openapi::ErrorBody;
use axum::extract::State;
use axum::http::StatusCode;
use axum::Extension;
use fresa_core::machine::heightmap::{self, GridAsk, HeightMapFit, HeightMapView};
use fresa_core::machine::Machine;
use fresa_core::SharedApp;
use serde::Deserialize;
use std::sync::Arc;
use utoipa::{IntoParams, ToSchema};

async fn machine(app: &SharedApp, id: i64) -> Result<Arc<Machine>, ApiError> {
    app.machines
        .get(id)
        .ok_or_else(|| ApiError::not_found("unknown_machine", format!("no machine with id {id}")))
}

fn default_clearance() -> f64 {
    2.0
}

fn default_distance() -> f64 {
    5.0
}

fn default_feed() -> f64 {
    100.0
}

/// A grid to probe, in the work coordinates in force.
#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct GridReq {
    /// The area, work X/Y, mm (`x0 < x1`, `y0 < y1`).
    x0: f64,
    x1: f64,
    y0: f64,
    y1: f64,
    /// Points along X and along Y, 2 to 50 each.
    nx: u32,
    ny: u32,
    /// Work Z to travel at between points and to probe down from (default 2).
    #[serde(default = "default_clearance")]
    clearance: f64,
    /// How far below the clearance a probe may go, mm (default 5; at most `max_jog_mm`).
    #[serde(default = "default_distance")]
    distance: f64,
    /// Probing feed, mm/min (default 100; at most `max_probe_feed_mm_min`).
    #[serde(default = "default_feed")]
    feed: f64,
    /// Feed of the moves between points, mm/min (the backend's jog feed when left out).
    #[serde(default)]
    travel_feed: Option<f64>,
}

/// Starts probing a grid: Z up to the clearance, then at each point (rows in a serpentine) X/Y
/// there, a probe down, the work Z where it touched recorded, back up. Answered at once with
/// the map (`probing`); `height_map.progress` follows each point and `height_map.ended`
/// (audit) its end. STOP or feed hold ends it (`stopped`); an alarm, a probe that does not
/// touch (naming the point) or a refused move fails it; either way what was probed is kept
/// and the map is never applied.
#[utoipa::path(post, path = "/api/v1/machines/{id}/height-maps", tag = "height maps",
    params(("id" = i64, Path, description = "machine id", example = 1)),
    request_body(content = GridReq, example = json!({"x0": 0, "x1": 10, "y0": 0, "y1": 10, "nx": 2, "ny": 2, "clearance": 2, "distance": 15, "feed": 300})),
    responses(
        (status = 202, description = "Probing started: the map, `probing`", body = HeightMapView),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
        (status = 409, description = "`machine_busy` (a job runs, the machine moves, or another grid is probed), `machine_not_ready` (alarm, offline), `height_map_limit`", body = ErrorBody),
        (status = 422, description = "`invalid_field` (naming it), `probe_too_far`, `feed_out_of_range`, `out_of_travel` (the grid's moves leave the configured travel; nothing moved)", body = ErrorBody),
        (status = 503, description = "`database_unavailable`", body = ErrorBody),
    ))]
pub async fn create(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<GridReq>,
) -> Result<(StatusCode, Json<HeightMapView>), ApiError> {
    let m = machine(&app, id).await?;
    let ask = GridAsk {
        area: [req.x0, req.x1, req.y0, req.y1],
        nx: req.nx,
        ny: req.ny,
        clearance: req.clearance,
        distance: req.distance,
        feed: req.feed,
        travel_feed: req.travel_feed,
    };
    let view = m.start_height_map(&app.store, ask, &caller.name).await?;
    Ok((StatusCode::ACCEPTED, Json(view)))
}

/// The machine's height maps, newest first.
#[utoipa::path(get, path = "/api/v1/machines/{id}/height-maps", tag = "height maps",
    params(("id" = i64, Path, description = "machine id", example = 1)),
    responses(
        (status = 200, description = "Its maps (with their points)", body = [HeightMapView]),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
    ))]
pub async fn list(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
) -> Result<Json<Vec<HeightMapView>>, ApiError> {
    if app.store.machine(id).await?.is_none() {
        return Err(ApiError::not_found(
            "unknown_machine",
            format!("no machine with id {id}"),
        ));
    }
    let rows = app.store.list_height_maps(id).await?;
    Ok(Json(rows.iter().map(HeightMapView::from_row).collect()))
}

async fn one(
    app: &SharedApp,
    id: i64,
    hid: i64,
) -> Result<fresa_core::store::HeightMapRow, ApiError> {
    app.store
        .height_map(hid)
        .await?
        .filter(|r| r.machine_id == id)
        .ok_or_else(|| {
            ApiError::not_found(
                "unknown_height_map",
                format!("machine {id} has no height map {hid}"),
            )
        })
}

#[utoipa::path(get, path = "/api/v1/machines/{id}/height-maps/{hid}", tag = "height maps",
    params(("id" = i64, Path, description = "machine id", example = 1),
           ("hid" = i64, Path, description = "height map id", example = 1)),
    responses(
        (status = 200, description = "The map: state, points, range, who and when", body = HeightMapView),
        (status = 404, description = "`unknown_height_map`", body = ErrorBody),
    ))]
pub async fn get_one(
    State(app): State<SharedApp>,
    Path((id, hid)): Path<(i64, i64)>,
) -> Result<Json<HeightMapView>, ApiError> {
    Ok(Json(HeightMapView::from_row(&one(&app, id, hid).await?)))
}

/// Deletes a map (not one being probed: stop the machine to end that first). Recorded as
/// `height_map.deleted`. Runs that used it keep its number; resuming one is then refused.
#[utoipa::path(delete, path = "/api/v1/machines/{id}/height-maps/{hid}", tag = "height maps",
    params(("id" = i64, Path, description = "machine id", example = 1),
           ("hid" = i64, Path, description = "height map id", example = 1)),
    responses(
        (status = 204, description = "Deleted"),
        (status = 404, description = "`unknown_height_map`", body = ErrorBody),
        (status = 409, description = "`height_map_probing`", body = ErrorBody),
    ))]
pub async fn delete(
    State(app): State<SharedApp>,
    Path((id, hid)): Path<(i64, i64)>,
    Extension(caller): Extension<Caller>,
) -> Result<StatusCode, ApiError> {
    heightmap::delete(&app.store, &app.bus, id, hid, &caller.name).await?;
    Ok(StatusCode::NO_CONTENT)
}

#[derive(Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct FitParams {
    /// The job whose program the map would correct.
    #[param(example = 1)]
    job: i64,
}

/// How a map fits a job's program, as a start with it would check: the program's cutting XY
/// extent against the map's area (both in the work coordinates in force now), the overhang
/// if it leaves it, and the Z correction range over the program's area.
#[utoipa::path(get, path = "/api/v1/machines/{id}/height-maps/{hid}/fit", tag = "height maps",
    params(("id" = i64, Path, description = "machine id", example = 1),
           ("hid" = i64, Path, description = "height map id", example = 1), FitParams),
    responses(
        (status = 200, description = "The fit (`fits` false names the overhang)", body = HeightMapFit),
        (status = 404, description = "`unknown_machine`, `unknown_height_map`, `unknown_job`", body = ErrorBody),
        (status = 409, description = "`height_map_incomplete`", body = ErrorBody),
        (status = 422, description = "`height_map_other_machine`", body = ErrorBody),
    ))]
pub async fn fit(
    State(app): State<SharedApp>,
    Path((id, hid)): Path<(i64, i64)>,
    Query(q): Query<FitParams>,
) -> Result<Json<HeightMapFit>, ApiError> {
    let m = machine(&app, id).await?;
    let row = one(&app, id, hid).await?;
    let job = fresa_core::jobs::job(&app, q.job).await?;
    let (fit, _) = heightmap::fit(&row, &job, &m.status())?;
    Ok(Json(fit))
}

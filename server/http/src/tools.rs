//! A machine's tool table: what G41/G42 `D<n>` offset by (`/machines/{id}/tools`).

use super::auth::Caller;
use super::error::{ApiError, Json, Path};
use crate::openapi::ErrorBody;
use axum::extract::State;
use axum::http::StatusCode;
use axum::Extension;
use fresa_core::store::ToolRow;
use fresa_core::SharedApp;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

/// One tool, millimetres.
#[derive(Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
#[schema(as = Tool)]
pub struct ToolView {
    /// Tool number (the `T` and `D` words), 1..=99999.
    #[schema(example = 1)]
    tool: i64,
    /// Cutter diameter: G41/G42 offset the path by half of it (negative: to the other side).
    #[schema(example = 6.0)]
    diameter_mm: f64,
    /// Tool length offset (G43); 0 when absent.
    #[serde(default)]
    length_mm: f64,
    #[serde(default)]
    description: String,
}

impl From<ToolRow> for ToolView {
    fn from(r: ToolRow) -> Self {
        ToolView {
            tool: r.tool,
            diameter_mm: r.diameter_mm,
            length_mm: r.length_mm,
            description: r.description,
        }
    }
}

impl From<ToolView> for ToolRow {
    fn from(v: ToolView) -> Self {
        ToolRow {
            tool: v.tool,
            diameter_mm: v.diameter_mm,
            length_mm: v.length_mm,
            description: v.description,
        }
    }
}

/// One tool's values (its number is in the path).
#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ToolReq {
    diameter_mm: f64,
    #[serde(default)]
    length_mm: f64,
    #[serde(default)]
    description: String,
}

#[utoipa::path(get, path = "/api/v1/machines/{id}/tools", tag = "machines",
    params(("id" = i64, Path, description = "machine id", example = 1)),
    responses(
        (status = 200, description = "The tool table, by tool number", body = Vec<ToolView>),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
    ))]
pub async fn list_tools(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
) -> Result<Json<Vec<ToolView>>, ApiError> {
    let rows = fresa_core::tools::list(&app, id).await?;
    Ok(Json(rows.into_iter().map(ToolView::from).collect()))
}

#[utoipa::path(put, path = "/api/v1/machines/{id}/tools", tag = "machines",
    params(("id" = i64, Path, description = "machine id", example = 1)),
    request_body(content = Vec<ToolView>, example = json!([
        {"tool": 1, "diameter_mm": 6.0, "description": "6 mm flat end mill"},
        {"tool": 8, "diameter_mm": 3.175, "length_mm": 42.5}])),
    responses(
        (status = 200, description = "Replaced; the table as now stored", body = Vec<ToolView>),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
        (status = 422, description = "`invalid_field` (names the field, e.g. `tools[1].diameter_mm`)", body = ErrorBody),
    ))]
pub async fn replace_tools(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<Vec<ToolView>>,
) -> Result<Json<Vec<ToolView>>, ApiError> {
    let rows = req.into_iter().map(ToolRow::from).collect();
    let stored = fresa_core::tools::replace(&app, id, rows, &caller.name).await?;
    Ok(Json(stored.into_iter().map(ToolView::from).collect()))
}

#[utoipa::path(put, path = "/api/v1/machines/{id}/tools/{tool}", tag = "machines",
    params(("id" = i64, Path, description = "machine id", example = 1),
           ("tool" = i64, Path, description = "tool number", example = 4)),
    request_body(content = ToolReq, example = json!({"diameter_mm": 6.0, "description": "6 mm flat end mill"})),
    responses(
        (status = 200, description = "Added or replaced", body = ToolView),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
        (status = 422, description = "`invalid_field`", body = ErrorBody),
    ))]
pub async fn set_tool(
    State(app): State<SharedApp>,
    Path((id, tool)): Path<(i64, i64)>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<ToolReq>,
) -> Result<Json<ToolView>, ApiError> {
    let row = ToolRow {
        tool,
        diameter_mm: req.diameter_mm,
        length_mm: req.length_mm,
        description: req.description,
    };
    let stored = fresa_core::tools::set(&app, id, row, &caller.name).await?;
    Ok(Json(stored.into()))
}

#[utoipa::path(delete, path = "/api/v1/machines/{id}/tools/{tool}", tag = "machines",
    params(("id" = i64, Path, description = "machine id", example = 1),
           ("tool" = i64, Path, description = "tool number", example = 1)),
    responses(
        (status = 204, description = "Removed"),
        (status = 404, description = "`unknown_machine`, `unknown_tool`", body = ErrorBody),
    ))]
pub async fn delete_tool(
    State(app): State<SharedApp>,
    Path((id, tool)): Path<(i64, i64)>,
    Extension(caller): Extension<Caller>,
) -> Result<StatusCode, ApiError> {
    fresa_core::tools::delete(&app, id, tool, &caller.name).await?;
    Ok(StatusCode::NO_CONTENT)
}

//! The shop's records (issue 28, part 2): part records, utilisation, a machine's maintenance
//! counters and marking maintenance done. The core does the work (`fresa_core::reports`);
//! these parse the query, pick JSON or CSV (`Accept: text/csv`) and shape the answer.

use super::auth::Caller;
use super::error::{ApiError, Json, Path, Query};
use crate::openapi::ErrorBody;
use axum::extract::State;
use axum::http::{header, HeaderMap};
use axum::response::{IntoResponse, Response};
use axum::Extension;
use fresa_core::machine::counters::{CountersView, MaintenanceView};
use fresa_core::records::{parse_time, part_csv_row, PART_CSV_HEADER};
use fresa_core::reports::{self, PartsPage, PartsQuery, UtilisationReport};
use fresa_core::SharedApp;
use serde::Deserialize;
use utoipa::IntoParams;

/// Whether the client asked for CSV (`Accept: text/csv`).
fn wants_csv(headers: &HeaderMap) -> bool {
    headers
        .get(header::ACCEPT)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.split(',').any(|t| t.trim().starts_with("text/csv")))
}

fn csv(body: String, next: Option<&str>) -> Response {
    let mut r = ([(header::CONTENT_TYPE, "text/csv; charset=utf-8")], body).into_response();
    // The page cursor, where JSON has `next`.
    if let Some(v) = next.and_then(|n| header::HeaderValue::from_str(n).ok()) {
        r.headers_mut().insert("x-next-cursor", v);
    }
    r
}

fn time(field: &str, v: Option<String>) -> Result<Option<i64>, ApiError> {
    v.map(|t| parse_time(field, &t))
        .transpose()
        .map_err(Into::into)
}

#[derive(Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct PartsParams {
    /// Only this job's parts.
    job: Option<i64>,
    /// Only this machine's parts.
    #[param(example = 1)]
    machine: Option<i64>,
    /// Ended at or after: Unix ms, `YYYY-MM-DD` or `YYYY-MM-DDTHH:MM:SSZ` (UTC).
    #[param(example = "2026-01-01")]
    from: Option<String>,
    /// Ended before (same forms).
    to: Option<String>,
    /// Per page, newest first (1..1000, default 100).
    #[param(example = 50)]
    limit: Option<i64>,
    /// The `next` of the previous page (CSV: its `X-Next-Cursor` header).
    cursor: Option<String>,
}

#[utoipa::path(get, path = "/api/v1/parts", tag = "records",
    params(PartsParams),
    responses(
        (status = 200, description = "A page of part records (one per run that ended), newest first; with `Accept: text/csv` the same as CSV (header row; operators joined with `;`, confirmations counted; the next page's cursor in `X-Next-Cursor`)", body = PartsPage),
        (status = 400, description = "`invalid_query`: a time, limit or cursor that does not parse", body = ErrorBody),
        (status = 503, description = "`database_unavailable`", body = ErrorBody),
    ))]
pub async fn parts(
    State(app): State<SharedApp>,
    headers: HeaderMap,
    Query(p): Query<PartsParams>,
) -> Result<Response, ApiError> {
    let q = PartsQuery {
        job: p.job,
        machine: p.machine,
        from: time("from", p.from)?,
        to: time("to", p.to)?,
        limit: p.limit,
        cursor: p.cursor,
    };
    let page = reports::parts(&app, q).await?;
    if wants_csv(&headers) {
        let mut body = String::from(PART_CSV_HEADER);
        body.push('\n');
        for part in &page.parts {
            body.push_str(&part_csv_row(part));
            body.push('\n');
        }
        return Ok(csv(body, page.next.as_deref()));
    }
    Ok(Json(page).into_response())
}

#[derive(Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct UtilisationParams {
    /// From (default: 7 days before `to`): Unix ms, `YYYY-MM-DD` or `YYYY-MM-DDTHH:MM:SSZ`.
    #[param(example = "2026-01-01")]
    from: Option<String>,
    /// To (default and at most: now); at most 366 days after `from`.
    to: Option<String>,
}

#[utoipa::path(get, path = "/api/v1/reports/utilisation", tag = "records",
    params(UtilisationParams),
    responses(
        (status = 200, description = "Seconds per machine, UTC day and state (`cutting`, `idle`, `held`, `alarm`, `unresponsive`, `offline`) from the recorded state changes; with `Accept: text/csv` one row per machine and day", body = UtilisationReport),
        (status = 400, description = "`invalid_query`: a time that does not parse, `from` not before `to`, more than 366 days", body = ErrorBody),
        (status = 503, description = "`database_unavailable`", body = ErrorBody),
    ))]
pub async fn utilisation(
    State(app): State<SharedApp>,
    headers: HeaderMap,
    Query(p): Query<UtilisationParams>,
) -> Result<Response, ApiError> {
    let report = reports::utilisation(&app, time("from", p.from)?, time("to", p.to)?).await?;
    if wants_csv(&headers) {
        return Ok(csv(reports::utilisation_csv(&report), None));
    }
    Ok(Json(report).into_response())
}

#[utoipa::path(get, path = "/api/v1/machines/{id}/counters", tag = "records",
    params(("id" = i64, Path, example = 1)),
    responses(
        (status = 200, description = "Spindle-on and motion hours, distance per axis, jobs run, the state now and each maintenance interval (`since_done`, `due`)", body = CountersView),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
    ))]
pub async fn counters(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
) -> Result<Json<CountersView>, ApiError> {
    Ok(Json(reports::counters(&app, id).await?))
}

#[utoipa::path(post, path = "/api/v1/machines/{id}/maintenance/{name}/done", tag = "records",
    params(("id" = i64, Path, example = 1), ("name" = String, Path, example = "lubricate")),
    responses(
        (status = 200, description = "The interval, started again from the counter's value now; event `machine.maintenance_done`", body = MaintenanceView),
        (status = 404, description = "`unknown_machine`, `unknown_maintenance`", body = ErrorBody),
        (status = 503, description = "`database_unavailable`", body = ErrorBody),
    ))]
pub async fn maintenance_done(
    State(app): State<SharedApp>,
    Extension(caller): Extension<Caller>,
    Path((id, name)): Path<(i64, String)>,
) -> Result<Json<MaintenanceView>, ApiError> {
    Ok(Json(
        reports::maintenance_done(&app, id, &name, &caller.name).await?,
    ))
}

//! Job queues per machine and dispatch to a free machine (issue 28). The core does the work
//! (`fresa_core::queue`); these parse and shape the answers. A machine's queue routes are
//! forwarded to its node like every `/machines/{id}/...` route; a dispatch tries each machine
//! named, asking the node that drives it.

use super::auth::Caller;
use super::error::{ApiError, Json, Path};
use crate::openapi::ErrorBody;
use axum::extract::State;
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::Extension;
use fresa_core::nodes::Owner;
use fresa_core::queue::{self, QueueView, Refusal, Started};
use fresa_core::SharedApp;
use serde::Deserialize;
use utoipa::ToSchema;

fn default_count() -> i64 {
    1
}

fn yes() -> bool {
    true
}

/// Parts of a job to add to the machine's queue.
#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct AddReq {
    /// A job of this machine.
    job: i64,
    /// How many parts (1 to 10000; default 1): one entry with a `done` counter.
    #[serde(default = "default_count")]
    count: i64,
    /// Wait for a confirm before each part (default true). The first part of an idle queue
    /// always waits for one.
    #[serde(default = "yes")]
    confirm_between: bool,
}

/// The machine's queue: its state (`idle`, `waiting_confirm`, `running`, `held` with the
/// `reason`) and its entries in order, each with `count`, `done` and its state.
#[utoipa::path(get, path = "/api/v1/machines/{id}/queue", tag = "queue",
    params(("id" = i64, Path, description = "machine id", example = 1)),
    responses(
        (status = 200, description = "The queue", body = QueueView),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
    ))]
pub async fn get(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
) -> Result<Json<QueueView>, ApiError> {
    Ok(Json(queue::get(&app, id).await?))
}

/// Adds `count` parts of a job at the end of the queue (`queue.add`). An idle queue then waits
/// for a confirm (`queue.waiting_confirm`): nothing starts until an operator confirms.
#[utoipa::path(post, path = "/api/v1/machines/{id}/queue", tag = "queue",
    params(("id" = i64, Path, description = "machine id", example = 1)),
    request_body(content = AddReq, example = json!({"job": 1, "count": 3, "confirm_between": true})),
    responses(
        (status = 200, description = "The queue with the new entry", body = QueueView),
        (status = 404, description = "`unknown_machine`, `unknown_job`", body = ErrorBody),
        (status = 409, description = "`queue_full` (100 entries)", body = ErrorBody),
        (status = 422, description = "`invalid_field` (`count` out of range, a job of another machine)", body = ErrorBody),
    ))]
pub async fn add(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<AddReq>,
) -> Result<Json<QueueView>, ApiError> {
    Ok(Json(
        queue::add(
            &app,
            id,
            req.job,
            req.count,
            req.confirm_between,
            &caller.name,
        )
        .await?,
    ))
}

/// Removes an entry (`queue.remove`); not the one whose part is running.
#[utoipa::path(delete, path = "/api/v1/machines/{id}/queue/{entry}", tag = "queue",
    params(("id" = i64, Path, description = "machine id", example = 1),
           ("entry" = i64, Path, description = "queue entry id", example = 1)),
    responses(
        (status = 200, description = "The queue without it", body = QueueView),
        (status = 404, description = "`unknown_machine`, `unknown_queue_entry`", body = ErrorBody),
        (status = 409, description = "`queue_entry_running`", body = ErrorBody),
    ))]
pub async fn remove(
    State(app): State<SharedApp>,
    Path((id, entry)): Path<(i64, i64)>,
    Extension(caller): Extension<Caller>,
) -> Result<Json<QueueView>, ApiError> {
    Ok(Json(queue::remove(&app, id, entry, &caller.name).await?))
}

/// Where to put an entry.
#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct MoveReq {
    /// 1-based; past the end: last.
    position: i64,
}

/// Moves an entry to `position` (`queue.move`).
#[utoipa::path(post, path = "/api/v1/machines/{id}/queue/{entry}/move", tag = "queue",
    params(("id" = i64, Path, description = "machine id", example = 1),
           ("entry" = i64, Path, description = "queue entry id", example = 1)),
    request_body(content = MoveReq, example = json!({"position": 1})),
    responses(
        (status = 200, description = "The queue in its new order", body = QueueView),
        (status = 404, description = "`unknown_machine`, `unknown_queue_entry`", body = ErrorBody),
        (status = 422, description = "`invalid_field`", body = ErrorBody),
    ))]
pub async fn move_entry(
    State(app): State<SharedApp>,
    Path((id, entry)): Path<(i64, i64)>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<MoveReq>,
) -> Result<Json<QueueView>, ApiError> {
    Ok(Json(
        queue::move_entry(&app, id, entry, req.position, &caller.name).await?,
    ))
}

/// "Next part loaded": starts the next part as `POST /jobs/{id}/start` does (same checks);
/// `queue.confirm` names the `run`, `machine` and `entry`. A refused start leaves the queue
/// waiting and answers the start's refusal. The pendant's START does the same while the queue
/// waits.
#[utoipa::path(post, path = "/api/v1/machines/{id}/queue/confirm", tag = "queue",
    params(("id" = i64, Path, description = "machine id", example = 1)),
    responses(
        (status = 200, description = "The part started: `machine`, `job`, `run`, `entry`", body = Started),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
        (status = 409, description = "`queue_not_waiting`, or the start's refusal (`machine_busy`, ...)", body = ErrorBody),
        (status = 422, description = "the start's refusal (`out_of_travel`, ...)", body = ErrorBody),
    ))]
pub async fn confirm(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
) -> Result<Json<Started>, ApiError> {
    Ok(Json(queue::confirm(&app, id, &caller.name).await?))
}

/// Ends a hold (`queue.release`): a part still running goes on; otherwise the next part waits
/// for a confirm.
#[utoipa::path(post, path = "/api/v1/machines/{id}/queue/release", tag = "queue",
    params(("id" = i64, Path, description = "machine id", example = 1)),
    responses(
        (status = 200, description = "The queue", body = QueueView),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
        (status = 409, description = "`queue_not_held`", body = ErrorBody),
    ))]
pub async fn release(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
) -> Result<Json<QueueView>, ApiError> {
    Ok(Json(queue::release(&app, id, &caller.name).await?))
}

/// A job to run on one machine if it is free.
#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct TakeReq {
    job: i64,
}

/// Starts one part of a job on this machine if it is free (idle, no run, an idle empty
/// queue): what `POST /queue` asks of each machine it tries. For a job of another machine it
/// runs its own newest job with the same program, or a copy made for it.
#[utoipa::path(post, path = "/api/v1/machines/{id}/queue/take", tag = "queue",
    params(("id" = i64, Path, description = "machine id", example = 1)),
    request_body(content = TakeReq, example = json!({"job": 1})),
    responses(
        (status = 200, description = "Started: `machine`, `job` (this machine's), `run`", body = Started),
        (status = 404, description = "`unknown_job`", body = ErrorBody),
        (status = 409, description = "`machine_busy`, `machine_unavailable`, or the start's refusal", body = ErrorBody),
        (status = 422, description = "the start's refusal (`out_of_travel`, ...)", body = ErrorBody),
    ))]
pub async fn take(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<TakeReq>,
) -> Result<Json<Started>, ApiError> {
    Ok(Json(queue::take(&app, id, req.job, &caller.name).await?))
}

/// A part for the first free machine of a list.
#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct DispatchReq {
    job: i64,
    /// Tried in this order (1 to 64 machines).
    machines: Vec<i64>,
}

/// Where a dispatched part went.
#[derive(serde::Serialize, ToSchema)]
pub struct Dispatched {
    pub machine: i64,
    /// The job that runs: the one asked for, or its copy for the chosen machine.
    pub job: i64,
    pub run: i64,
    /// The machines tried before it and why they did not take it.
    pub refused: Vec<Refusal>,
}

/// Gives one part of a job to the first machine of the list that is free and accepts the
/// program (the same start as `POST /jobs/{id}/start`, with its whole-program check), on any
/// node. Recorded as `queue.dispatch`. When none takes it: 409 `no_machine_free` with
/// `refused`, each machine's `code` and `message`.
#[utoipa::path(post, path = "/api/v1/queue", tag = "queue",
    request_body(content = DispatchReq, example = json!({"job": 1, "machines": [1]})),
    responses(
        (status = 200, description = "The machine chosen and the run", body = Dispatched),
        (status = 404, description = "`unknown_job`", body = ErrorBody),
        (status = 409, description = "`no_machine_free`: `refused` names why each machine did not take it", body = ErrorBody),
        (status = 422, description = "`invalid_field`", body = ErrorBody),
    ))]
pub async fn dispatch(
    State(app): State<SharedApp>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<DispatchReq>,
) -> Result<Response, ApiError> {
    if req.machines.is_empty() || req.machines.len() > queue::MAX_DISPATCH_MACHINES {
        return Err(ApiError::unprocessable(
            "invalid_field",
            format!(
                "field `machines` must name 1 to {} machines, got {}",
                queue::MAX_DISPATCH_MACHINES,
                req.machines.len()
            ),
        ));
    }
    // Unknown job: answered before any machine is tried.
    fresa_core::jobs::job(&app, req.job).await?;
    let mut refused = Vec::new();
    let mut seen = std::collections::HashSet::new();
    for &m in &req.machines {
        if !seen.insert(m) {
            continue;
        }
        let tried = match app.machine_owner(m).await? {
            Owner::Local => queue::take(&app, m, req.job, &caller.name)
                .await
                .map_err(|e| (e.code.to_string(), e.message)),
            Owner::Remote(node) => {
                crate::forward::take_remote(&app, m, &node, req.job, &caller).await
            }
            Owner::Unknown => Err((
                "unknown_machine".to_string(),
                format!("no machine with id {m}"),
            )),
        };
        match tried {
            Ok(started) => {
                queue::record_dispatch(&app, req.job, Some(&started), &refused, &caller.name).await;
                return Ok(Json(Dispatched {
                    machine: started.machine,
                    job: started.job,
                    run: started.run,
                    refused,
                })
                .into_response());
            }
            Err((code, message)) => refused.push(Refusal {
                machine: m,
                code,
                message,
            }),
        }
    }
    queue::record_dispatch(&app, req.job, None, &refused, &caller.name).await;
    let message = refused
        .iter()
        .map(|r| format!("machine {}: {} ({})", r.machine, r.message, r.code))
        .collect::<Vec<_>>()
        .join("; ");
    let body = serde_json::json!({
        "code": "no_machine_free",
        "message": format!("no machine took job {}: {message}", req.job),
        "refused": refused,
    });
    Ok((StatusCode::CONFLICT, axum::Json(body)).into_response())
}

use super::auth::Caller;
use super::error::{ApiError, Json, Path, Query};
use axum::body::Body;
use axum::extract::{FromRequest, Multipart, Request, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Extension;
use fresa_core::jobs as core;
use fresa_core::programs::{self, PendingProgram};
use fresa_core::SharedApp;
use futures_util::StreamExt;
use serde::Deserialize;
use serde_json::{json, Value};

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct UploadParams {
    machine: Option<i64>,
    name: Option<String>,
    sha256: Option<String>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ListParams {
    machine: Option<i64>,
    limit: Option<i64>,
}

pub async fn list(
    State(app): State<SharedApp>,
    Query(p): Query<ListParams>,
) -> Result<Json<Vec<Value>>, ApiError> {
    let jobs = app
        .store
        .list_jobs(p.machine, p.limit.unwrap_or(100).clamp(1, 1000))
        .await?;
    let ids: Vec<i64> = jobs.iter().map(|j| j.id).collect();
    let runs: std::collections::HashMap<i64, fresa_core::store::RunRow> = app
        .store
        .latest_runs(&ids)
        .await?
        .into_iter()
        .map(|r| (r.job_id, r))
        .collect();
    let out = jobs
        .iter()
        .map(|j| core::job_json(j, runs.get(&j.id)))
        .collect();
    Ok(Json(out))
}

pub async fn get_one(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
) -> Result<Json<Value>, ApiError> {
    let job = app
        .store
        .job(id)
        .await?
        .ok_or_else(|| ApiError::not_found("unknown_job", format!("no job with id {id}")))?;
    let run = app.store.latest_run(id).await?;
    Ok(Json(core::job_json(&job, run.as_ref())))
}

pub async fn gcode(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
) -> Result<Response, ApiError> {
    let job = app
        .store
        .job(id)
        .await?
        .ok_or_else(|| ApiError::not_found("unknown_job", format!("no job with id {id}")))?;
    let path = programs::program_path(&app.settings.programs_dir(), &job.sha256);
    let file = tokio::fs::File::open(&path).await.map_err(|e| {
        ApiError::internal(format!("program file {} is missing: {e}", path.display()))
    })?;
    let body = Body::from_stream(tokio_util::io::ReaderStream::new(file));
    Ok(([(header::CONTENT_TYPE, "text/plain; charset=utf-8")], body).into_response())
}

/// Upload: the raw body is the program (`?machine=ID&name=NAME[&sha256=HEX]`), or a multipart
/// form with a `file` part (and optional `machine`, `name`, `sha256` parts). Streamed to disk,
/// checked, hashed, analysed; the job exists only once all of that succeeded.
pub async fn upload(
    State(app): State<SharedApp>,
    Extension(caller): Extension<Caller>,
    Query(mut params): Query<UploadParams>,
    req: Request,
) -> Result<(StatusCode, Json<Value>), ApiError> {
    let is_multipart = req
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("multipart/form-data"));
    // Check the machine before reading a possibly huge body.
    if !is_multipart {
        check_machine(&app, params.machine).await?;
    }
    let limit = app.settings.max_upload_bytes;
    let idle = app.settings.upload_idle_timeout;
    let dir = app.settings.programs_dir();
    let mut pending = PendingProgram::create(&dir, limit).await?;
    let mut file_name = None;
    if is_multipart {
        let mut mp = Multipart::from_request(req, &())
            .await
            .map_err(|e| ApiError::bad_request("invalid_multipart", e.body_text()))?;
        let mut got_file = false;
        while let Some(mut field) = within(idle, mp.next_field())
            .await?
            .map_err(|e| ApiError::bad_request("invalid_multipart", e.body_text()))?
        {
            match field.name().unwrap_or("") {
                "file" => {
                    // Two programs in one form would be stored joined as one.
                    if got_file {
                        return Err(ApiError::bad_request(
                            "invalid_multipart",
                            "the form has more than one `file` part; upload one program per request",
                        ));
                    }
                    file_name = field.file_name().map(str::to_string);
                    while let Some(chunk) = within(idle, field.chunk())
                        .await?
                        .map_err(|e| ApiError::bad_request("invalid_multipart", e.body_text()))?
                    {
                        pending.write(&chunk).await?;
                    }
                    got_file = true;
                }
                other @ ("machine" | "name" | "sha256") => {
                    let other = other.to_string();
                    let text = within(idle, field.text())
                        .await?
                        .map_err(|e| ApiError::bad_request("invalid_multipart", e.body_text()))?;
                    match other.as_str() {
                        "machine" => {
                            params.machine = Some(text.trim().parse().map_err(|_| {
                                ApiError::bad_request(
                                    "invalid_field",
                                    format!("part `machine` must be an integer id, got {text:?}"),
                                )
                            })?)
                        }
                        "name" => params.name = Some(text),
                        _ => params.sha256 = Some(text.trim().to_string()),
                    }
                }
                other => {
                    return Err(ApiError::bad_request(
                        "invalid_multipart",
                        format!("unexpected part {other:?} (expected file, machine, name, sha256)"),
                    ))
                }
            }
        }
        if !got_file {
            return Err(ApiError::bad_request(
                "invalid_multipart",
                "the form has no `file` part",
            ));
        }
        check_machine(&app, params.machine).await?;
    } else {
        let mut stream = req.into_body().into_data_stream();
        while let Some(chunk) = within(idle, stream.next()).await? {
            let chunk = chunk.map_err(|e| {
                ApiError::bad_request("upload_aborted", format!("upload did not complete: {e}"))
            })?;
            pending.write(&chunk).await?;
        }
    }
    let machine_id = params.machine.ok_or_else(|| {
        ApiError::bad_request("missing_field", "query parameter `machine` is required")
    })?;
    let program = pending.finish(params.sha256.as_deref()).await?;
    let job = core::store_program(
        &app,
        program,
        machine_id,
        params.name.or(file_name),
        "http",
        &caller.name,
    )
    .await?;
    let (id, sha, lines, analysis) = (job.id, job.sha256, job.lines, job.analysis);
    Ok((
        StatusCode::CREATED,
        Json(json!({"id": id, "sha256": sha, "line_count": lines, "analysis": analysis})),
    ))
}

/// One read of an upload's body, bounded by `upload_idle_timeout_secs`: a client that stops
/// sending gets a JSON error and its temporary file is removed (when `PendingProgram` drops),
/// instead of holding a connection and a file open for ever.
async fn within<T>(
    idle: std::time::Duration,
    read: impl std::future::Future<Output = T>,
) -> Result<T, ApiError> {
    tokio::time::timeout(idle, read).await.map_err(|_| {
        ApiError::new(
            StatusCode::REQUEST_TIMEOUT,
            "upload_timeout",
            format!(
                "the upload sent nothing for {} s (upload_idle_timeout_secs); it was dropped",
                idle.as_secs()
            ),
        )
    })
}

async fn check_machine(app: &SharedApp, machine: Option<i64>) -> Result<(), ApiError> {
    let id = machine.ok_or_else(|| {
        ApiError::bad_request("missing_field", "query parameter `machine` is required")
    })?;
    if app.store.machine(id).await?.is_none() {
        return Err(ApiError::not_found(
            "unknown_machine",
            format!("no machine with id {id}"),
        ));
    }
    Ok(())
}

/// Optional body of `POST /jobs/{id}/resume`.
#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct ResumeBody {
    /// Accept the part zero the controller reports now, even if it differs from the run's.
    #[serde(default)]
    confirm_part_zero: bool,
}

pub async fn control(
    State(app): State<SharedApp>,
    Path((id, action)): Path<(i64, String)>,
    Extension(caller): Extension<Caller>,
    body: axum::body::Bytes,
) -> Result<Json<Value>, ApiError> {
    let run = match action.as_str() {
        "start" => core::start(&app, id, &caller.name).await?,
        "pause" => core::pause(&app, id, &caller.name).await?,
        "resume" => {
            // The body is optional: an empty POST resumes without confirming anything.
            let body: ResumeBody = if body.iter().all(u8::is_ascii_whitespace) {
                ResumeBody::default()
            } else {
                serde_json::from_slice(&body)
                    .map_err(|e| ApiError::bad_request("invalid_json", format!("resume: {e}")))?
            };
            core::resume(&app, id, &caller.name, body.confirm_part_zero).await?
        }
        "cancel" => core::cancel(&app, id, &caller.name).await?,
        other => {
            return Err(ApiError::not_found(
                "unknown_action",
                format!("no job action {other:?} (start, pause, resume, cancel)"),
            ))
        }
    };
    let job = app
        .store
        .job(id)
        .await?
        .ok_or_else(|| ApiError::internal("job vanished"))?;
    Ok(Json(core::job_json(&job, Some(&run))))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ToolpathParams {
    max_vertices: Option<usize>,
}

/// The job's path for previews in the binary format of `fresa_core::toolpath` (README: Toolpath
/// format), decimated to `max_vertices` (default 250000).
pub async fn toolpath(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Query(p): Query<ToolpathParams>,
) -> Result<Response, ApiError> {
    use fresa_core::toolpath::{DEFAULT_MAX_VERTICES, MAX_MAX_VERTICES, MIN_MAX_VERTICES};
    let max = p.max_vertices.unwrap_or(DEFAULT_MAX_VERTICES);
    if !(MIN_MAX_VERTICES..=MAX_MAX_VERTICES).contains(&max) {
        return Err(ApiError::bad_request(
            "invalid_query",
            format!("`max_vertices` must be {MIN_MAX_VERTICES}..={MAX_MAX_VERTICES}, got {max}"),
        ));
    }
    let bytes = core::toolpath(&app, id, max).await?;
    Ok((
        [
            (header::CONTENT_TYPE, "application/octet-stream"),
            // Programs never change (content-addressed), so neither does their path.
            (header::CACHE_CONTROL, "private, max-age=3600"),
        ],
        bytes,
    )
        .into_response())
}

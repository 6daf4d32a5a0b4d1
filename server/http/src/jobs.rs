use super::auth::Caller;
use super::error::{ApiError, Json, Path, Query};
use crate::openapi::ErrorBody;
use axum::body::Body;
use axum::extract::{FromRequest, Multipart, Request, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Extension;
use fresa_core::jobs as core;
use fresa_core::programs::PendingProgram;
use fresa_core::views::JobView;
use fresa_core::SharedApp;
use futures_util::StreamExt;
use serde::Deserialize;
use serde_json::{json, Value};
use utoipa::{IntoParams, ToSchema};

#[derive(Deserialize, Default, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct UploadParams {
    /// The machine the job is for (required; a multipart `machine` part may give it instead).
    #[param(example = 1)]
    machine: Option<i64>,
    /// Job name (default: the multipart file name).
    #[param(example = "spiral")]
    name: Option<String>,
    /// Expected SHA-256 of the program, hex: a mismatch refuses the upload.
    sha256: Option<String>,
}

#[derive(Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct ListParams {
    /// Only this machine's jobs.
    machine: Option<i64>,
    /// At most this many, newest first (1..1000, default 100).
    limit: Option<i64>,
}

/// The multipart form of an upload.
#[derive(ToSchema)]
#[allow(dead_code)] // describes the form `upload` reads
pub struct UploadForm {
    /// The program.
    #[schema(format = Binary, value_type = String)]
    file: Vec<u8>,
    machine: Option<i64>,
    name: Option<String>,
    sha256: Option<String>,
}

/// What an upload answers with.
#[derive(ToSchema)]
#[allow(dead_code)] // describes the JSON `upload` builds
pub struct Uploaded {
    id: i64,
    sha256: String,
    line_count: i64,
    /// Bounds, lengths, time estimate.
    #[schema(value_type = Object)]
    analysis: Value,
}

/// Run control: what `POST /jobs/{id}/{action}` does.
#[derive(ToSchema)]
#[schema(rename_all = "snake_case")]
#[allow(dead_code)] // the path segment `control` matches on
pub enum JobAction {
    Start,
    Pause,
    Resume,
    Cancel,
}

#[utoipa::path(get, path = "/api/v1/jobs", tag = "jobs", params(ListParams),
    responses(
        (status = 200, description = "Jobs, newest first", body = [JobView]),
        (status = 400, description = "`invalid_query`", body = ErrorBody),
        (status = 503, description = "`database_unavailable`: the store cannot be read (during an outage, jobs a machine runs are shown as it knows them)", body = ErrorBody),
    ))]
pub async fn list(
    State(app): State<SharedApp>,
    Query(p): Query<ListParams>,
) -> Result<Json<Vec<JobView>>, ApiError> {
    let jobs = core::list(&app, p.machine, p.limit.unwrap_or(100).clamp(1, 1000)).await?;
    let mut out = Vec::with_capacity(jobs.len());
    for (job, run) in &jobs {
        let hold = core::live_hold(&app, job.id).await;
        out.push(JobView::new(job, run.as_ref()).with_hold(hold));
    }
    Ok(Json(out))
}

#[utoipa::path(get, path = "/api/v1/jobs/{id}", tag = "jobs",
    params(("id" = i64, Path, description = "job id", example = 1)),
    responses(
        (status = 200, description = "The job", body = JobView),
        (status = 404, description = "`unknown_job`", body = ErrorBody),
        (status = 503, description = "`database_unavailable`: the store cannot be read and no machine of this node runs the job", body = ErrorBody),
    ))]
pub async fn get_one(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
) -> Result<Json<JobView>, ApiError> {
    let (job, run) = core::job_with_run(&app, id).await?;
    let hold = core::live_hold(&app, id).await;
    Ok(Json(JobView::new(&job, run.as_ref()).with_hold(hold)))
}

#[derive(Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct GcodeParams {
    /// Only the lines from this one (1-based): a window of the program, e.g. for a listing
    /// around the line running (default: the whole program).
    #[param(example = 1)]
    from_line: Option<u32>,
    /// How many lines from `from_line` (1..=500, default 100); each is cut at 512 bytes.
    #[param(example = 20)]
    lines: Option<u32>,
}

#[utoipa::path(get, path = "/api/v1/jobs/{id}/gcode", tag = "jobs",
    params(("id" = i64, Path, description = "job id", example = 1), GcodeParams),
    responses(
        (status = 200, description = "The stored program, or with `from_line`/`lines` that window of its lines (each ending with a newline; empty past the end)", content_type = "text/plain", body = String),
        (status = 400, description = "`invalid_query`: `from_line` 0 or `lines` out of range", body = ErrorBody),
        (status = 404, description = "`unknown_job`", body = ErrorBody),
        (status = 503, description = "`database_unavailable`: the store cannot be read and no machine of this node runs the job", body = ErrorBody),
    ))]
pub async fn gcode(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Query(p): Query<GcodeParams>,
) -> Result<Response, ApiError> {
    if p.from_line.is_some() || p.lines.is_some() {
        let text =
            fresa_core::listing::window(&app, id, p.from_line.unwrap_or(1), p.lines.unwrap_or(100))
                .await?;
        return Ok(([(header::CONTENT_TYPE, "text/plain; charset=utf-8")], text).into_response());
    }
    let (_, path) = core::program(&app, id).await?;
    let file = tokio::fs::File::open(&path).await.map_err(|e| {
        ApiError::internal(format!("program file {} is missing: {e}", path.display()))
    })?;
    let body = Body::from_stream(tokio_util::io::ReaderStream::new(file));
    Ok(([(header::CONTENT_TYPE, "text/plain; charset=utf-8")], body).into_response())
}

/// Upload: the raw body is the program (`?machine=ID&name=NAME[&sha256=HEX]`), or a multipart
/// form with a `file` part (and optional `machine`, `name`, `sha256` parts). Streamed to disk,
/// checked, hashed, analysed; the job exists only once all of that succeeded.
#[utoipa::path(post, path = "/api/v1/jobs", tag = "jobs", params(UploadParams),
    request_body(content(
        (String = "text/plain", example = "G21 G90\nG0 X1 Y1\nG1 X5 F300\nM2\n"),
        (UploadForm = "multipart/form-data"),
    ), description = "The program (UTF-8 G-code), streamed; at most `max_upload_bytes`"),
    responses(
        (status = 201, description = "Stored and analysed", body = Uploaded),
        (status = 400, description = "`missing_field`, `invalid_multipart`, `upload_aborted`, `invalid_query`", body = ErrorBody),
        (status = 404, description = "`unknown_machine`", body = ErrorBody),
        (status = 408, description = "`upload_timeout`", body = ErrorBody),
        (status = 413, description = "`too_large`", body = ErrorBody),
        (status = 422, description = "`invalid_gcode` (line and column), `work_budget_exceeded` (the line where the program passed `max_program_segments`), `not_utf8`, `sha256_mismatch`", body = ErrorBody),
        (status = 503, description = "`database_unavailable` (the store cannot be written: nothing is kept), `disk_full` (no room for the program)", body = ErrorBody),
    ))]
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
    // A store that cannot be written could not keep the job: refused before any byte is read
    // or written.
    app.store.health().check()?;
    // Check the machine before reading a possibly huge body.
    if !is_multipart {
        check_machine(&app, params.machine).await?;
    }
    let limit = app.settings.max_upload_bytes;
    let idle = app.settings.upload_idle_timeout;
    let dir = app.settings.programs_dir();
    let mut pending = PendingProgram::create(&dir, limit).await?;
    // The machine is known before the body: the program is analysed as it arrives.
    if let (false, Some(m)) = (is_multipart, params.machine) {
        pending.analyse_alongside(core::analysis_options(&app, m).await?);
    }
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

/// The optional body of run control: `from_line` for `start`, `confirm_part_zero` and
/// `confirm_line` for `resume` (each refuses the other's fields).
#[derive(ToSchema)]
#[allow(dead_code)] // describes the JSON `control` reads per action
pub struct ControlBody {
    /// `start` only: start at this line (1-based). The lines before it are interpreted without
    /// motion, then the machine is brought to their modal state (work offset, spindle,
    /// coolant) and start point: up to a safe Z, across at rapid, down at feed (see
    /// `GET /jobs/{id}/start-preview`). Refused, naming the reason and the line, inside an
    /// O-word loop or subroutine, under cutter compensation, on a canned cycle with L > 1, past
    /// the end, or on a line that never runs.
    from_line: Option<u32>,
    /// `start` only: a complete height map of the job's machine to apply (issue 25; see
    /// `StartBody`).
    height_map: Option<i64>,
    /// `resume` only: accept the part zero the controller reports now, even if it differs
    /// from the run's.
    confirm_part_zero: Option<bool>,
    /// `resume` only: for a run whose stored line may be behind (`unstored_line`), the last
    /// line that was executed, as the operator found it.
    confirm_line: Option<i64>,
}

/// Optional body of `POST /jobs/{id}/resume`.
#[derive(Deserialize, Default, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ResumeBody {
    /// Accept the part zero the controller reports now, even if it differs from the run's.
    #[serde(default)]
    confirm_part_zero: bool,
    /// For a run whose stored line may be behind (its `unstored_line` is set: the server
    /// stopped while acknowledged lines could not be stored): the last line that was executed,
    /// as the operator found it on the machine. The resume goes on from the next line.
    #[serde(default)]
    confirm_line: Option<i64>,
}

/// Optional body of `POST /jobs/{id}/start`: every field optional, each a start option of
/// its own.
#[derive(Deserialize, Default, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct StartBody {
    /// Start at this line (1-based): see `ControlBody::from_line`.
    #[serde(default)]
    from_line: Option<u32>,
    /// A complete height map of the job's machine to apply (issue 25): every move's Z gets the
    /// probed surface's height under it. Refused before anything moves when the program's
    /// cutting moves leave the map's area (`outside_height_map`) or the backend cannot apply
    /// one (`height_map_unsupported`).
    #[serde(default)]
    height_map: Option<i64>,
}

/// The optional JSON body of a run control action: an empty body is its defaults.
fn body_or_default<T: Default + serde::de::DeserializeOwned>(
    action: &str,
    body: &[u8],
) -> Result<T, ApiError> {
    if body.iter().all(u8::is_ascii_whitespace) {
        return Ok(T::default());
    }
    serde_json::from_slice(body)
        .map_err(|e| ApiError::bad_request("invalid_json", format!("{action}: {e}")))
}

#[utoipa::path(post, path = "/api/v1/jobs/{id}/{action}", tag = "jobs",
    params(("id" = i64, Path, description = "job id", example = 1),
           ("action" = inline(JobAction), Path, description = "`resume` also continues an `interrupted` or `failed` run from the next unacknowledged line, through the same preamble as a start at that line", example = "start")),
    request_body(content = Option<ControlBody>, description = "Optional: `from_line` and `height_map` for `start`, `confirm_part_zero` / `confirm_line` for `resume`", example = json!({"from_line": 2})),
    responses(
        (status = 200, description = "Done: the job with its run (answered only once true: a `cancel` after motion stopped)", body = JobView),
        (status = 400, description = "`invalid_json`", body = ErrorBody),
        (status = 404, description = "`unknown_job`, `unknown_action`, `unknown_height_map`", body = ErrorBody),
        (status = 409, description = "`height_map_incomplete`, `machine_busy`, `not_started`, `not_running`, `not_resumable`, `not_cancellable`, `part_zero_changed`, `line_unconfirmed` (the stored line may be behind: resume with `confirm_line`), `stopped`, `backend_rejected`", body = ErrorBody),
        (status = 422, description = "`backend_rejected` (e.g. the program leaves the travel), `outside_height_map`, `height_map_unsupported`, `invalid_field` (`confirm_line` out of range, `from_line` 0), `unsupported` (the backend cannot start at a line safely; the message says why), `start_in_loop`, `start_in_subroutine`, `start_under_cutter_compensation`, `start_in_canned_cycle_repeat`, `start_past_end`, `start_line_not_run`, `start_unsupported_offset` (the message names the line and the construct; nothing is started)", body = ErrorBody),
        (status = 503, description = "`machine_offline`, `machine_unresponsive`, `machine_unavailable`, `shutting_down`, `database_unavailable` (start and resume; pause and cancel of the running job still work)", body = ErrorBody),
    ))]
pub async fn control(
    State(app): State<SharedApp>,
    Path((id, action)): Path<(i64, String)>,
    Extension(caller): Extension<Caller>,
    body: axum::body::Bytes,
) -> Result<Json<JobView>, ApiError> {
    // Read first: while the database is unreachable the job is known from its machine only as
    // long as its run is current, and a cancel ends that.
    let job = core::job(&app, id).await?;
    let run = match action.as_str() {
        "start" => {
            let body: StartBody = body_or_default("start", &body)?;
            core::start_with(&app, id, body.from_line, body.height_map, &caller.name).await?
        }
        "pause" => core::pause(&app, id, &caller.name).await?,
        "resume" => {
            // The body is optional: an empty POST resumes without confirming anything.
            let body: ResumeBody = if body.iter().all(u8::is_ascii_whitespace) {
                ResumeBody::default()
            } else {
                serde_json::from_slice(&body)
                    .map_err(|e| ApiError::bad_request("invalid_json", format!("resume: {e}")))?
            };
            core::resume(
                &app,
                id,
                &caller.name,
                body.confirm_part_zero,
                body.confirm_line,
            )
            .await?
        }
        "cancel" => core::cancel(&app, id, &caller.name).await?,
        other => {
            return Err(ApiError::not_found(
                "unknown_action",
                format!("no job action {other:?} (start, pause, resume, cancel)"),
            ))
        }
    };
    let hold = core::live_hold(&app, id).await;
    Ok(Json(JobView::new(&job, Some(&run)).with_hold(hold)))
}

#[derive(Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct PreviewParams {
    /// The line to start at (1-based).
    #[param(example = 2)]
    from_line: u32,
}

/// What `POST /jobs/{id}/start {"from_line": N}` would do from where the machine stands now:
/// the modal state the lines before N leave, and the preamble (as steps and as G-code-like
/// text, moves in machine coordinates) that brings the machine there. Moves nothing. A start
/// that cannot be made is refused here with the same code and message.
#[utoipa::path(get, path = "/api/v1/jobs/{id}/start-preview", tag = "jobs",
    params(("id" = i64, Path, description = "job id", example = 1), PreviewParams),
    responses(
        (status = 200, description = "The state at the line and the preamble", body = fresa_core::start_at::StartPlan),
        (status = 400, description = "`invalid_query`", body = ErrorBody),
        (status = 404, description = "`unknown_job`", body = ErrorBody),
        (status = 409, description = "`machine_unavailable`", body = ErrorBody),
        (status = 422, description = "`invalid_field`, `start_in_loop`, `start_in_subroutine`, `start_under_cutter_compensation`, `start_in_canned_cycle_repeat`, `start_past_end`, `start_line_not_run`, `start_unsupported_offset`, `invalid_gcode`", body = ErrorBody),
    ))]
pub async fn start_preview(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Query(p): Query<PreviewParams>,
) -> Result<Json<fresa_core::start_at::StartPlan>, ApiError> {
    Ok(Json(core::start_preview(&app, id, p.from_line).await?))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ToolpathParams {
    max_vertices: Option<usize>,
}

/// The job's path for previews in the binary format of `fresa_core::toolpath` (README: Toolpath
/// format), decimated to `max_vertices` (default 250000).
#[utoipa::path(get, path = "/api/v1/jobs/{id}/toolpath", tag = "jobs",
    params(
        ("id" = i64, Path, description = "job id", example = 1),
        ("max_vertices" = Option<usize>, Query, description = "vertex budget, 1000..2000000 (default 250000)"),
    ),
    responses(
        (status = 200, description = "The path: a 48-byte `FTP1` header, then per vertex float32 x, y, z, u32 source line, u8 kind (README: Toolpath format)", content_type = "application/octet-stream"),
        (status = 400, description = "`invalid_query`: max_vertices out of range", body = ErrorBody),
        (status = 404, description = "`unknown_job`", body = ErrorBody),
        (status = 422, description = "`invalid_gcode`, or `work_budget_exceeded`: the program (stored before the budget was checked at upload) linearises to more than `max_program_segments`", body = ErrorBody),
    ))]
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
    // The cache keeps its copy; the body gets its own (a few MB at most, once per request).
    let bytes = bytes.as_ref().clone();
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

//! Jobs: from a checked program (see `programs`) to a stored, analysed job, and run control,
//! which belongs to the job's machine: these functions find it and ask its task. The run state
//! machine is `store::RunState`.

use crate::app::App;
use crate::error::{Error, Result};
use crate::events::EventKind;
use crate::machine::Machine;
use crate::programs::StoredProgram;
use crate::store::{JobRow, NewJob, RunRow};
use serde_json::json;
use std::sync::Arc;

/// A job created from a checked program.
pub struct CreatedJob {
    pub id: i64,
    pub sha256: String,
    pub lines: u64,
    pub bytes: u64,
    pub analysis: Option<serde_json::Value>,
}

/// Analyses a finished program, moves it to its content-addressed name and inserts the job row:
/// the one path from an uploaded program to a job (HTTP and pendant uploads). The job exists only
/// once all of that succeeded; a failed insert removes a file this upload created.
pub async fn store_program(
    app: &App,
    program: StoredProgram,
    machine_id: i64,
    name: Option<String>,
    source: &str,
    actor: &str,
) -> Result<CreatedJob> {
    let name = match name
        .as_deref()
        .map(|n| Error::valid_name("name", n))
        .transpose()?
    {
        Some(n) if !n.is_empty() => n.to_string(),
        _ => format!("program-{}", &program.sha256[..12]),
    };
    let opts = analysis_options(app, machine_id).await?;
    let mut program = program;
    let analysis = analyse(&mut program, opts).await?;
    let sha = program.sha256.clone();
    let (lines, bytes) = (program.lines, program.bytes);
    let dir = app.settings.programs_dir();
    let (path, created) = program.place(&dir)?;
    // Nodes sharing the store read each other's programs from it: the program is there before
    // any node can see the job.
    if app.store.dialect() == crate::store::Dialect::Postgres {
        let saved = async {
            let file = tokio::fs::File::open(&path).await.map_err(|e| {
                Error::internal(format!("cannot read the program {}: {e}", path.display()))
            })?;
            app.store
                .health()
                .guard(app.store.save_program(&sha, file))
                .await
        };
        if let Err(e) = saved.await {
            if created {
                let _ = std::fs::remove_file(&path);
            }
            return Err(e);
        }
    }
    // Through the health guard: a full disk found here is the store's outage like any other.
    let inserted = app
        .store
        .health()
        .guard(app.store.insert_job(NewJob {
            name: &name,
            machine_id,
            sha256: &sha,
            size_bytes: bytes as i64,
            line_count: lines as i64,
            analysis: analysis.as_ref().map(|a| a.to_string()),
            source,
        }))
        .await;
    let id = match inserted {
        Ok(id) => id,
        Err(e) => {
            if created {
                let _ = std::fs::remove_file(&path);
            }
            return Err(e);
        }
    };
    app.bus
        .record_or_log(
            EventKind::JobCreated,
            Some(machine_id),
            Some(actor),
            json!({"job": id, "name": name, "sha256": sha, "lines": lines, "bytes": bytes, "source": source}),
        )
        .await;
    Ok(CreatedJob {
        id,
        sha256: sha,
        lines,
        bytes,
        analysis: analysis.map(crate::views::public_analysis),
    })
}

/// How a program for `machine_id` is analysed: its unsupported-word policy and tool table, the
/// work budget, and the time estimate with the machine's own rapid rate, acceleration and
/// cornering (when this node drives it and its backend says). An upload asks for these before
/// its first byte, to analyse the program as it arrives.
pub async fn analysis_options(app: &App, machine_id: i64) -> Result<fresa_gcode::AnalysisOptions> {
    let config = fresa_gcode::Config {
        unsupported: unsupported_policy(app, machine_id).await?,
        tools: crate::tools::gcode_table(app, machine_id).await?,
        ..fresa_gcode::Config::default()
    };
    let profile = match app.machines.get(machine_id) {
        Some(m) => m.motion_profile().await,
        None => None,
    };
    Ok(fresa_gcode::AnalysisOptions {
        config,
        max_segments: app.settings.max_program_segments,
        profile,
        ..fresa_gcode::AnalysisOptions::default()
    })
}

/// A machine whose config says `"unsupported": "skip_with_warning"` gets its programs analysed
/// with that policy (its backend converts them the same way); every other machine: errors.
async fn unsupported_policy(app: &App, machine_id: i64) -> Result<fresa_gcode::Unsupported> {
    let row = app.store.machine(machine_id).await?;
    let skip = row.is_some_and(|r| r.config_json()["unsupported"] == "skip_with_warning");
    Ok(if skip {
        fresa_gcode::Unsupported::SkipWithWarning
    } else {
        fresa_gcode::Unsupported::Error
    })
}

/// Interprets the whole program before the job is stored (with the machine's unsupported-word
/// policy and tool table): a program with an error never becomes a job, and the stored analysis
/// (bounds, length, ETA) serves previews and progress.
async fn analyse(
    program: &mut StoredProgram,
    opts: fresa_gcode::AnalysisOptions,
) -> Result<Option<serde_json::Value>> {
    let path = program
        .temp_path()
        .ok_or_else(|| Error::internal("program file already moved"))?
        .to_path_buf();
    // The analysis that ran as the upload arrived, if it ran with these very options.
    let done = program
        .alongside
        .take()
        .filter(|a| a.opts == opts)
        .map(|a| a.result);
    analyse_file(path, done, opts).await
}

/// The analysis a job of stored program `sha256` for `machine_id` stores (that machine's
/// unsupported-word policy, tool table and motion profile), or the error that refuses it: a
/// program given to another machine (dispatch) is checked as its own upload would be.
pub async fn analysis_for(
    app: &App,
    sha256: &str,
    machine_id: i64,
) -> Result<Option<serde_json::Value>> {
    let path =
        crate::programs::local_copy(&app.store, &app.settings.programs_dir(), sha256).await?;
    let opts = analysis_options(app, machine_id).await?;
    analyse_file(path, None, opts).await
}

/// Analyses the program at `path` with `opts` (or finishes `done`, an analysis already run on
/// the same bytes with them).
async fn analyse_file(
    path: std::path::PathBuf,
    done: Option<std::result::Result<fresa_gcode::Analysis, fresa_gcode::GcodeError>>,
    opts: fresa_gcode::AnalysisOptions,
) -> Result<Option<serde_json::Value>> {
    let max_segments = opts.max_segments;
    let result = tokio::task::spawn_blocking(move || {
        let open =
            || std::fs::File::open(&path).map(|f| std::io::BufReader::with_capacity(1 << 16, f));
        let mut analysis = match done {
            Some(a) => a,
            None => fresa_gcode::analyse(open()?, &opts),
        };
        // A program that probes: which moves depend on the result, and the bounds of both
        // ends of what the probes can return (a second interpretation, side by side).
        if let Ok(a) = analysis.as_mut() {
            if a.probe_moves > 0 {
                a.merge_probe_spread(&fresa_gcode::probe_spread(open()?, open()?, &opts));
            }
        }
        Ok::<_, std::io::Error>(analysis)
    })
    .await
    .map_err(|e| Error::internal(format!("analysis failed: {e}")))?
    .map_err(|e| Error::internal(format!("cannot read the stored program: {e}")))?;
    match result {
        Ok(a) => Ok(Some(json!(a))),
        Err(e) => Err(gcode_error(&e, max_segments)),
    }
}

/// A job's toolpath in the preview format of [`crate::toolpath`], at most `max_vertices`
/// vertices, interpreted with the same unsupported-word policy and tool table as its upload and
/// within the work budget. Computed once and cached (see [`crate::previews`]); abandoned when
/// the caller stops waiting for it.
pub async fn toolpath(app: &App, job_id: i64, max_vertices: usize) -> Result<Arc<Vec<u8>>> {
    let job = app
        .store
        .job(job_id)
        .await?
        .ok_or_else(|| Error::not_found("unknown_job", format!("no job with id {job_id}")))?;
    let unsupported = unsupported_policy(app, job.machine_id).await?;
    let tools = crate::tools::gcode_table(app, job.machine_id).await?;
    let max_segments = app.settings.max_program_segments;
    let key = {
        use std::fmt::Write;
        let mut k = format!(
            "{}|{max_vertices}|{unsupported:?}|{max_segments}|",
            job.sha256
        );
        for (n, t) in &tools {
            let _ = write!(k, "{n}:{:?}:{:?};", t.diameter_mm, t.length_mm);
        }
        k
    };
    let path =
        crate::programs::local_copy(&app.store, &app.settings.programs_dir(), &job.sha256).await?;
    app.previews
        .get(key, move |cancel| {
            let file = std::fs::File::open(&path).map_err(|e| {
                Error::internal(format!("program file {} is missing: {e}", path.display()))
            })?;
            let reader = std::io::BufReader::with_capacity(1 << 16, file);
            let config = fresa_gcode::Config {
                unsupported,
                tools,
                ..fresa_gcode::Config::default()
            };
            crate::toolpath::Toolpath::build_bounded(
                reader,
                config,
                max_vertices,
                max_segments,
                cancel,
            )
            .map(|t| t.map(|t| t.encode()))
            .map_err(|e| gcode_error(&e, max_segments))
        })
        .await
}

/// A G-code error as the API answers it: a program over the work budget gets its own code and
/// says how to raise the budget.
pub fn gcode_error(e: &fresa_gcode::GcodeError, max_segments: u64) -> Error {
    match e.kind {
        fresa_gcode::ErrorKind::Budget => Error::invalid(
            "work_budget_exceeded",
            format!(
                "G-code error at {e}; the budget is the server's `max_program_segments` \
                 ({max_segments}): raise it in the config file to accept such programs"
            ),
        ),
        _ => Error::invalid("invalid_gcode", format!("G-code error at {e}")),
    }
}

/// The job `job_id` as a machine of this node knows it: its current job, with the run as the
/// task last reported it (`None` while the run is not known in memory).
async fn known(app: &App, job_id: i64) -> Option<(JobRow, Option<RunRow>)> {
    for m in app.machines.all() {
        if let Some(job) = m.current_job().filter(|j| j.id == job_id) {
            let run = m.current_run().filter(|r| r.job_id == job_id);
            return Some((job, run));
        }
    }
    None
}

/// The lookups below: while the database is down, a job a machine runs is answered from that
/// machine (its state and line are newer than the store's, whose writes wait in memory); any
/// other job from the store, which may still answer reads (a full disk does). A store that
/// cannot answer gives `database_unavailable`, the same refusal run control gives.
fn unavailable(e: &Error) -> bool {
    e.code == "database_unavailable"
}

/// A job by id: from the store, or, while the database is down, from the machine that is
/// running it (so its run can still be paused or cancelled).
pub async fn job(app: &App, job_id: i64) -> Result<JobRow> {
    let health = app.store.health();
    if !health.is_up() {
        if let Some((job, _)) = known(app, job_id).await {
            return Ok(job);
        }
    }
    match health.read(app.store.job(job_id)).await {
        Ok(job) => job.ok_or_else(|| unknown_job(job_id)),
        Err(e) if unavailable(&e) => known(app, job_id).await.map(|(job, _)| job).ok_or(e),
        Err(e) => Err(e),
    }
}

fn unknown_job(job_id: i64) -> Error {
    Error::not_found("unknown_job", format!("no job with id {job_id}"))
}

/// A job and its latest run, as `GET /jobs/{id}` shows them (see [`job_json`]); outage-aware
/// like [`job`], answering a running job from its machine while the database is down.
pub async fn job_with_run(app: &App, job_id: i64) -> Result<(JobRow, Option<RunRow>)> {
    let health = app.store.health();
    let from_machine = || async {
        match known(app, job_id).await {
            Some((job, Some(run))) => Some((job, Some(run))),
            _ => None,
        }
    };
    if !health.is_up() {
        if let Some(found) = from_machine().await {
            return Ok(found);
        }
    }
    let stored = async {
        let job = health
            .read(app.store.job(job_id))
            .await?
            .ok_or_else(|| unknown_job(job_id))?;
        let run = health.read(app.store.latest_run(job_id)).await?;
        Ok((job, run))
    };
    match stored.await {
        Err(e) if unavailable(&e) => from_machine().await.ok_or(e),
        other => other,
    }
}

/// Jobs, newest first, each with its latest run (`GET /jobs`): from the store, which may still
/// answer reads during an outage; there the runs this node's machines are running are shown as
/// the machines know them. A list cannot be answered from memory alone (it would be
/// incomplete), so a store that cannot answer gives `database_unavailable`.
pub async fn list(
    app: &App,
    machine: Option<i64>,
    limit: i64,
) -> Result<Vec<(JobRow, Option<RunRow>)>> {
    let health = app.store.health();
    let jobs = health.read(app.store.list_jobs(machine, limit)).await?;
    let ids: Vec<i64> = jobs.iter().map(|j| j.id).collect();
    let mut runs: std::collections::HashMap<i64, RunRow> = health
        .read(app.store.latest_runs(&ids))
        .await?
        .into_iter()
        .map(|r| (r.job_id, r))
        .collect();
    if !health.is_up() {
        for m in app.machines.all() {
            if let Some(run) = m.current_run().filter(|r| ids.contains(&r.job_id)) {
                runs.insert(run.job_id, run);
            }
        }
    }
    Ok(jobs
        .into_iter()
        .map(|j| {
            let run = runs.remove(&j.id);
            (j, run)
        })
        .collect())
}

/// The job's program file on this node (`GET /jobs/{id}/gcode`): the job is found as by
/// [`job`], so a running job's program is served from disk during an outage too.
pub async fn program(app: &App, job_id: i64) -> Result<(JobRow, std::path::PathBuf)> {
    let job = job(app, job_id).await?;
    let path =
        crate::programs::local_copy(&app.store, &app.settings.programs_dir(), &job.sha256).await?;
    Ok((job, path))
}

async fn load_job(app: &App, job_id: i64) -> Result<(JobRow, Arc<Machine>)> {
    let job = job(app, job_id).await?;
    let machine = app.machines.get(job.machine_id).ok_or_else(|| {
        Error::conflict(
            "machine_unavailable",
            format!("machine {} of job {job_id} is not loaded", job.machine_id),
        )
    })?;
    Ok((job, machine))
}

// Run control is the machine's: these find the job's machine and ask its task.

pub async fn start(app: &App, job_id: i64, actor: &str) -> Result<RunRow> {
    start_with(app, job_id, None, None, actor).await
}

/// Starts the job from `from_line` (`None`: its first line): the lines before it are
/// interpreted without motion and the machine is brought to their modal state and the start
/// point first (see [`crate::start_at`]); a start that cannot be made safely is refused naming
/// the reason and the line, and creates no run. With `height_map`, that map of the job's
/// machine is applied to the program's Z (issue 25; see `machine::heightmap`).
pub async fn start_with(
    app: &App,
    job_id: i64,
    from_line: Option<u32>,
    height_map: Option<i64>,
    actor: &str,
) -> Result<RunRow> {
    let (job, machine) = load_job(app, job_id).await?;
    if let Some(n) = from_line {
        check_start_line(&job, n)?;
    }
    crate::run_settings::check_start(app, &job).await?;
    let map = height_map.map(|id| (id, &app.store));
    machine.start_job_with(job, from_line, map, actor).await
}

/// What a start at `from_line` would do, from where the machine stands now (`GET
/// /jobs/{id}/start-preview`): the modal state the lines before it leave and the preamble.
/// Moves nothing and records nothing.
pub async fn start_preview(
    app: &App,
    job_id: i64,
    from_line: u32,
) -> Result<crate::start_at::StartPlan> {
    let (job, machine) = load_job(app, job_id).await?;
    check_start_line(&job, from_line)?;
    let path =
        crate::programs::local_copy(&app.store, &app.settings.programs_dir(), &job.sha256).await?;
    let setup = crate::start_at::setup(&app.store, &machine.row(), &machine.status()).await?;
    crate::start_at::plan(path, from_line, setup).await
}

/// A start line the job has: 1..=its line count.
fn check_start_line(job: &JobRow, line: u32) -> Result<()> {
    if line == 0 {
        return Err(Error::invalid(
            "invalid_field",
            "field `from_line` is 1-based: 0 is not a line",
        ));
    }
    if i64::from(line) > job.line_count {
        return Err(crate::start_at::refused(
            fresa_gcode::StartRefusalReason::PastEnd,
            format!(
                "line {line}: past the end of the program ({} lines)",
                job.line_count
            ),
        ));
    }
    Ok(())
}

pub async fn pause(app: &App, job_id: i64, actor: &str) -> Result<RunRow> {
    pause_because(app, job_id, actor, None).await
}

/// A pause the host asks for itself, for `reason` (kind and message), which the machine's hold
/// then shows (a pendant lost).
pub async fn pause_because(
    app: &App,
    job_id: i64,
    actor: &str,
    reason: Option<(fresa_plugin_api::contract::HoldKind, String)>,
) -> Result<RunRow> {
    let (_, machine) = load_job(app, job_id).await?;
    machine.pause_job_because(job_id, actor, reason).await
}

/// Why the job's run holds, while its machine (on this node) holds it: the machine's status's
/// `hold`, as the job view shows it.
pub async fn live_hold(app: &App, job_id: i64) -> Option<fresa_plugin_api::contract::Hold> {
    for m in app.machines.all() {
        if m.current_job().is_some_and(|j| j.id == job_id) {
            let held = m
                .run()
                .is_some_and(|r| r.state == crate::store::RunState::Paused);
            return m.status().hold.filter(|_| held).map(|h| *h);
        }
    }
    None
}

/// `confirm_part_zero`: the operator accepts whatever part zero the controller reports now,
/// instead of requiring the one the run started with. `confirm_line`: for a run whose stored
/// line may be behind (`unstored_line`), the last line executed, as the operator found it.
pub async fn resume(
    app: &App,
    job_id: i64,
    actor: &str,
    confirm_part_zero: bool,
    confirm_line: Option<i64>,
) -> Result<RunRow> {
    let (job, machine) = load_job(app, job_id).await?;
    machine
        .resume_job(job, actor, confirm_part_zero, confirm_line)
        .await
}

pub async fn cancel(app: &App, job_id: i64, actor: &str) -> Result<RunRow> {
    let (_, machine) = load_job(app, job_id).await?;
    machine.cancel_job(job_id, actor).await
}

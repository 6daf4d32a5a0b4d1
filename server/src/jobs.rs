//! Jobs: storing uploaded programs (streamed to disk, hashed, checked) and driving job runs
//! through their state machine: running <-> paused -> completed | failed | cancelled, and
//! interrupted (by a restart) -> running again on resume, from the next unacknowledged line.

use crate::api::error::ApiError;
use crate::app::App;
use crate::events::EventBus;
use crate::machines::{CurrentRun, Machine};
use crate::store::{JobRow, NewJob, RunRow, Store};
use fresa_plugin_api::contract::{AxisValues, ProgramLoaded, Request, RunAction};
use serde_json::json;
use sha2::{Digest, Sha256};
use std::path::{Path, PathBuf};
use tokio::io::AsyncWriteExt;

/// Checks a program stream as it arrives: UTF-8, no binary bytes, counts lines. Tracks the
/// position so an error can name line and column.
pub struct ProgramChecker {
    line: u64,
    column: u64,
    /// Bytes of a UTF-8 sequence split across chunks.
    pending: Vec<u8>,
    pub bytes: u64,
    last_byte: Option<u8>,
}

impl Default for ProgramChecker {
    fn default() -> Self {
        ProgramChecker {
            line: 1,
            column: 1,
            pending: Vec::new(),
            bytes: 0,
            last_byte: None,
        }
    }
}

impl ProgramChecker {
    pub fn feed(&mut self, chunk: &[u8]) -> Result<(), ApiError> {
        self.bytes += chunk.len() as u64;
        let mut data = std::mem::take(&mut self.pending);
        data.extend_from_slice(chunk);
        let (valid, rest) = match std::str::from_utf8(&data) {
            Ok(s) => (s, &[][..]),
            Err(e) => {
                let (ok, bad) = data.split_at(e.valid_up_to());
                if e.error_len().is_some() {
                    // Count what was valid so the position points at the bad byte.
                    self.advance(std::str::from_utf8(ok).unwrap_or(""))?;
                    return Err(ApiError::unprocessable(
                        "not_utf8",
                        format!(
                            "program is not UTF-8 text: invalid byte 0x{:02x} at line {}, column {}",
                            bad[0], self.line, self.column
                        ),
                    ));
                }
                (std::str::from_utf8(ok).unwrap_or(""), bad)
            }
        };
        self.advance(valid)?;
        self.pending = rest.to_vec();
        if let Some(&b) = chunk.last() {
            self.last_byte = Some(b);
        }
        Ok(())
    }

    fn advance(&mut self, text: &str) -> Result<(), ApiError> {
        for c in text.chars() {
            match c {
                '\n' => {
                    self.line += 1;
                    self.column = 1;
                }
                '\r' | '\t' => self.column += 1,
                c if c.is_control() => {
                    return Err(ApiError::unprocessable(
                        "binary_program",
                        format!(
                        "program looks binary: control character U+{:04X} at line {}, column {}",
                        c as u32, self.line, self.column
                    ),
                    ))
                }
                _ => self.column += 1,
            }
        }
        Ok(())
    }

    /// Final checks; returns the number of lines.
    pub fn finish(&self) -> Result<u64, ApiError> {
        if !self.pending.is_empty() {
            return Err(ApiError::unprocessable(
                "not_utf8",
                format!(
                    "program ends in the middle of a UTF-8 character at line {}",
                    self.line
                ),
            ));
        }
        if self.bytes == 0 {
            return Err(ApiError::bad_request(
                "empty_program",
                "the program is empty (0 bytes)",
            ));
        }
        // A final line without a newline still counts.
        Ok(if self.last_byte == Some(b'\n') {
            self.line - 1
        } else {
            self.line
        })
    }
}

/// A program being written to a temporary file. Dropping it without `commit` deletes the file,
/// so a rejected or interrupted upload leaves nothing on disk.
pub struct PendingProgram {
    tmp: Option<PathBuf>,
    file: tokio::fs::File,
    hasher: Sha256,
    pub checker: ProgramChecker,
    limit: u64,
}

impl PendingProgram {
    pub async fn create(programs_dir: &Path, limit: u64) -> Result<Self, ApiError> {
        let tmp = programs_dir.join(format!(".upload-{}.tmp", rand::random::<u64>()));
        let file = tokio::fs::File::create(&tmp)
            .await
            .map_err(|e| ApiError::internal(format!("cannot create {}: {e}", tmp.display())))?;
        Ok(PendingProgram {
            tmp: Some(tmp),
            file,
            hasher: Sha256::new(),
            checker: ProgramChecker::default(),
            limit,
        })
    }

    pub async fn write(&mut self, chunk: &[u8]) -> Result<(), ApiError> {
        if self.checker.bytes + chunk.len() as u64 > self.limit {
            return Err(ApiError::new(
                axum::http::StatusCode::PAYLOAD_TOO_LARGE,
                "too_large",
                format!(
                    "program is larger than the upload limit of {} bytes",
                    self.limit
                ),
            ));
        }
        self.checker.feed(chunk)?;
        self.hasher.update(chunk);
        self.file
            .write_all(chunk)
            .await
            .map_err(|e| ApiError::internal(format!("cannot write program: {e}")))
    }

    /// Finishes the file: flushes it to disk and returns (temp path, sha256, lines, bytes).
    pub async fn finish(
        mut self,
        expected_sha256: Option<&str>,
    ) -> Result<StoredProgram, ApiError> {
        let lines = self.checker.finish()?;
        let sha = hex::encode(self.hasher.clone().finalize());
        if let Some(expected) = expected_sha256 {
            if !expected.eq_ignore_ascii_case(&sha) {
                return Err(ApiError::unprocessable(
                    "sha256_mismatch",
                    format!(
                        "sha256 of the received program is {sha}, but the client said {expected}"
                    ),
                ));
            }
        }
        self.file
            .sync_all()
            .await
            .map_err(|e| ApiError::internal(format!("cannot flush program: {e}")))?;
        let tmp = self
            .tmp
            .take()
            .ok_or_else(|| ApiError::internal("upload finished twice"))?;
        Ok(StoredProgram {
            tmp: Some(tmp),
            sha256: sha,
            lines,
            bytes: self.checker.bytes,
        })
    }
}

impl Drop for PendingProgram {
    fn drop(&mut self) {
        if let Some(t) = self.tmp.take() {
            let _ = std::fs::remove_file(t);
        }
    }
}

/// A complete, checked program still in its temporary file.
pub struct StoredProgram {
    tmp: Option<PathBuf>,
    pub sha256: String,
    pub lines: u64,
    pub bytes: u64,
}

impl StoredProgram {
    pub fn temp_path(&self) -> Option<&Path> {
        self.tmp.as_deref()
    }

    /// Moves the file to its content-addressed name. Returns whether this upload created it
    /// (so a failed DB insert can remove it again without touching a file other jobs use).
    pub fn place(mut self, programs_dir: &Path) -> Result<(PathBuf, bool), ApiError> {
        let dest = program_path(programs_dir, &self.sha256);
        let tmp = self
            .tmp
            .take()
            .ok_or_else(|| ApiError::internal("program placed twice"))?;
        if dest.exists() {
            let _ = std::fs::remove_file(&tmp);
            return Ok((dest, false));
        }
        std::fs::rename(&tmp, &dest).map_err(|e| {
            let _ = std::fs::remove_file(&tmp);
            ApiError::internal(format!("cannot store program as {}: {e}", dest.display()))
        })?;
        Ok((dest, true))
    }
}

impl Drop for StoredProgram {
    fn drop(&mut self) {
        if let Some(t) = self.tmp.take() {
            let _ = std::fs::remove_file(t);
        }
    }
}

pub fn program_path(programs_dir: &Path, sha256: &str) -> PathBuf {
    programs_dir.join(format!("{sha256}.nc"))
}

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
) -> Result<CreatedJob, ApiError> {
    let analysis = analyse(&program, unsupported_policy(app, machine_id).await?).await?;
    let name = name
        .filter(|n| !n.trim().is_empty())
        .unwrap_or_else(|| format!("program-{}", &program.sha256[..12]));
    let sha = program.sha256.clone();
    let (lines, bytes) = (program.lines, program.bytes);
    let dir = app.settings.programs_dir();
    let (path, created) = program.place(&dir)?;
    let inserted = app
        .store
        .insert_job(NewJob {
            name: &name,
            machine_id,
            sha256: &sha,
            size_bytes: bytes as i64,
            line_count: lines as i64,
            analysis: analysis.as_ref().map(|a| a.to_string()),
            source,
        })
        .await;
    let id = match inserted {
        Ok(id) => id,
        Err(e) => {
            if created {
                let _ = std::fs::remove_file(&path);
            }
            return Err(e.into());
        }
    };
    app.bus
        .record_or_log(
            "job.created",
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
        analysis,
    })
}

/// A machine whose config says `"unsupported": "skip_with_warning"` gets its programs analysed
/// with that policy (its backend converts them the same way); every other machine: errors.
async fn unsupported_policy(
    app: &App,
    machine_id: i64,
) -> Result<fresa_gcode::Unsupported, ApiError> {
    let row = app.store.machine(machine_id).await?;
    let skip = row.is_some_and(|r| r.config_json()["unsupported"] == "skip_with_warning");
    Ok(if skip {
        fresa_gcode::Unsupported::SkipWithWarning
    } else {
        fresa_gcode::Unsupported::Error
    })
}

/// Interprets the whole program before the job is stored: a program with an error never becomes
/// a job, and the stored analysis (bounds, length, ETA) serves previews and progress.
async fn analyse(
    program: &StoredProgram,
    unsupported: fresa_gcode::Unsupported,
) -> Result<Option<serde_json::Value>, ApiError> {
    let path = program
        .temp_path()
        .ok_or_else(|| ApiError::internal("program file already moved"))?
        .to_path_buf();
    let result = tokio::task::spawn_blocking(move || {
        let file = std::fs::File::open(&path)?;
        let reader = std::io::BufReader::with_capacity(1 << 16, file);
        let mut opts = fresa_gcode::AnalysisOptions::default();
        opts.config.unsupported = unsupported;
        Ok::<_, std::io::Error>(fresa_gcode::analyse(reader, &opts))
    })
    .await
    .map_err(|e| ApiError::internal(format!("analysis failed: {e}")))?
    .map_err(|e| ApiError::internal(format!("cannot read the stored program: {e}")))?;
    match result {
        Ok(a) => Ok(Some(json!(a))),
        Err(e) => Err(ApiError::unprocessable(
            "invalid_gcode",
            format!("G-code error at {e}"),
        )),
    }
}

/// Job as the API shows it: the job row, its analysis and its latest run.
pub fn job_json(job: &JobRow, run: Option<&RunRow>) -> serde_json::Value {
    let analysis: serde_json::Value = job
        .analysis
        .as_deref()
        .and_then(|a| serde_json::from_str(a).ok())
        .unwrap_or(serde_json::Value::Null);
    let (state, line) = match run {
        Some(r) => (r.state.as_str(), r.last_line),
        None => ("ready", 0),
    };
    let percent = if job.line_count > 0 {
        ((line as f64 / job.line_count as f64) * 1000.0).round() / 10.0
    } else {
        0.0
    };
    json!({
        "id": job.id, "name": job.name, "machine": job.machine_id, "sha256": job.sha256,
        "size_bytes": job.size_bytes, "line_count": job.line_count, "source": job.source,
        "created_at": job.created_at, "analysis": analysis,
        "state": state, "line": line, "percent": percent,
        "run": run,
    })
}

fn run_event(run: &RunRow) -> serde_json::Value {
    json!({"job": run.job_id, "run": run.id, "state": run.state, "line": run.last_line, "message": run.message})
}

/// Moves a run to a terminal state from a backend report. Late or duplicate reports are ignored.
pub async fn finish_run(
    machine: &Machine,
    store: &Store,
    bus: &EventBus,
    run_id: i64,
    to: &str,
    message: Option<&str>,
) {
    match store
        .transition_run(run_id, &["running", "paused", "queued"], to, message)
        .await
    {
        Ok(Some(row)) => {
            if machine.current_run().map(|c| c.run_id) == Some(run_id) {
                machine.set_current_run(None);
            }
            bus.record_or_log("job.state", Some(row.machine_id), None, run_event(&row))
                .await;
        }
        Ok(None) => {}
        Err(e) => tracing::error!(run = run_id, error = %e, "could not record end of run"),
    }
}

async fn load_job(app: &App, job_id: i64) -> Result<(JobRow, std::sync::Arc<Machine>), ApiError> {
    let job =
        app.store.job(job_id).await?.ok_or_else(|| {
            ApiError::not_found("unknown_job", format!("no job with id {job_id}"))
        })?;
    let machine = app.machines.get(job.machine_id).await.ok_or_else(|| {
        ApiError::conflict(
            "machine_unavailable",
            format!("machine {} of job {job_id} is not loaded", job.machine_id),
        )
    })?;
    Ok((job, machine))
}

/// Loads the program into the backend from `start_line` and starts it. On failure the run is
/// marked failed with the backend's reason.
async fn launch(
    app: &App,
    machine: &Machine,
    job: &JobRow,
    run: RunRow,
    start_line: u32,
    actor: &str,
    expected_part_zero: Option<AxisValues>,
) -> Result<RunRow, ApiError> {
    let path = program_path(&app.settings.programs_dir(), &job.sha256);
    machine.set_current_run(Some(CurrentRun {
        run_id: run.id,
        job_id: job.id,
        total_lines: job.line_count,
    }));
    let load = machine
        .call(&Request::LoadProgram {
            run: run.id,
            path: path.to_string_lossy().into_owned(),
            start_line,
            expected_part_zero,
        })
        .await;
    let started = match load {
        Ok(v) => {
            let loaded: Option<ProgramLoaded> = serde_json::from_value(v).ok();
            if let Some(l) = &loaded {
                if l.start_line != start_line {
                    tracing::info!(
                        run = run.id,
                        asked = start_line,
                        actual = l.start_line,
                        "backend resumed later: it had already executed earlier lines"
                    );
                }
            }
            // Announce `running` before the backend can finish the run, so the audit log never
            // shows `completed` without the `running` before it.
            app.bus
                .record_or_log(
                    "job.state",
                    Some(run.machine_id),
                    Some(actor),
                    run_event(&run),
                )
                .await;
            machine
                .call(&Request::Run {
                    action: RunAction::Start,
                })
                .await
        }
        Err(e) => Err(e),
    };
    let answer = match started {
        Ok(a) => a,
        Err(e) => {
            machine.set_current_run(None);
            let msg = e.to_string();
            finish_run(machine, &app.store, &app.bus, run.id, "failed", Some(&msg)).await;
            return Err(ApiError::from_backend(e));
        }
    };
    // A controller that reports its own part zero: the run keeps the one it (re)started with,
    // for the check on the next resume.
    if let Some(zero) = answer
        .get("part_zero")
        .and_then(|z| serde_json::from_value::<AxisValues>(z.clone()).ok())
    {
        app.store.set_run_part_zero(run.id, zero).await?;
    }
    Ok(app.store.run(run.id).await?.unwrap_or(run))
}

/// The machine's state if it is busy. The cached status can lag the backend's events (a run
/// ended, the `idle` status is still on its way), so a busy cache is checked with a fresh
/// status before a client that reacted at once to `run_ended` is refused.
async fn busy_state(machine: &Machine) -> Option<fresa_plugin_api::contract::MachineState> {
    let cached = machine.status().state;
    if !cached.is_busy() {
        return None;
    }
    let state = match machine.refresh_status(Request::Status).await {
        Ok(fresh) => fresh.state,
        Err(_) => cached,
    };
    state.is_busy().then_some(state)
}

pub async fn start(app: &App, job_id: i64, actor: &str) -> Result<RunRow, ApiError> {
    let (job, machine) = load_job(app, job_id).await?;
    if let Some(state) = busy_state(&machine).await {
        return Err(ApiError::conflict(
            "machine_busy",
            format!(
                "machine {} is {}; wait for it to be idle",
                machine.id,
                state.as_str()
            ),
        ));
    }
    if let Some(reason) = machine.unavailable_reason() {
        return Err(ApiError::conflict("machine_offline", reason.to_string()));
    }
    let run = match app.store.start_run(job.id, machine.id).await? {
        Ok(r) => r,
        Err(busy) => {
            return Err(ApiError::conflict(
                "machine_busy",
                format!(
                    "machine {} is running job {} (run {}, {})",
                    machine.id, busy.job_id, busy.id, busy.state
                ),
            ))
        }
    };
    launch(app, &machine, &job, run, 1, actor, None).await
}

pub async fn pause(app: &App, job_id: i64, actor: &str) -> Result<RunRow, ApiError> {
    let (_, machine) = load_job(app, job_id).await?;
    let run = latest(app, job_id).await?;
    if run.state != "running" {
        return Err(ApiError::conflict(
            "not_running",
            format!("job {job_id} is {}, not running", run.state),
        ));
    }
    machine
        .call(&Request::Run {
            action: RunAction::Pause,
        })
        .await
        .map_err(ApiError::from_backend)?;
    transition(app, &run, &["running"], "paused", actor).await
}

/// `confirm_part_zero`: the operator accepts whatever part zero the controller reports now,
/// instead of requiring the one the run started with.
pub async fn resume(
    app: &App,
    job_id: i64,
    actor: &str,
    confirm_part_zero: bool,
) -> Result<RunRow, ApiError> {
    let (job, machine) = load_job(app, job_id).await?;
    let run = latest(app, job_id).await?;
    match run.state.as_str() {
        "paused" => {
            machine.call(&Request::Run { action: RunAction::Resume }).await.map_err(ApiError::from_backend)?;
            transition(app, &run, &["paused"], "running", actor).await
        }
        "interrupted" | "failed" => {
            if let Some(state) = busy_state(&machine).await {
                return Err(ApiError::conflict(
                    "machine_busy",
                    format!("machine {} is {}", machine.id, state.as_str()),
                ));
            }
            let reopened = match app.store.reopen_run(run.id, machine.id).await? {
                Ok(r) => r,
                Err(busy) => {
                    return Err(ApiError::conflict(
                        "machine_busy",
                        format!("machine {} is running job {} (run {})", machine.id, busy.job_id, busy.id),
                    ))
                }
            };
            let next = u32::try_from(reopened.last_line + 1).unwrap_or(u32::MAX);
            if reopened.last_line >= job.line_count {
                // Everything was acknowledged before the interruption: nothing left to run.
                finish_run(&machine, &app.store, &app.bus, run.id, "completed", None).await;
                return Ok(app.store.run(run.id).await?.unwrap_or(reopened));
            }
            let expected = if confirm_part_zero {
                None
            } else {
                app.store.run_part_zero(run.id).await?
            };
            launch(app, &machine, &job, reopened, next, actor, expected).await
        }
        other => Err(ApiError::conflict(
            "not_resumable",
            format!("job {job_id} is {other}; only paused, interrupted or failed jobs can be resumed (start it again for a new run)"),
        )),
    }
}

pub async fn cancel(app: &App, job_id: i64, actor: &str) -> Result<RunRow, ApiError> {
    let (_, machine) = load_job(app, job_id).await?;
    let run = latest(app, job_id).await?;
    match run.state.as_str() {
        "running" | "paused" | "queued" => {
            machine
                .call(&Request::Run {
                    action: RunAction::Cancel,
                })
                .await
                .map_err(ApiError::from_backend)?;
            machine.set_current_run(None);
            transition(
                app,
                &run,
                &["running", "paused", "queued"],
                "cancelled",
                actor,
            )
            .await
        }
        "interrupted" | "failed" => {
            transition(app, &run, &["interrupted", "failed"], "cancelled", actor).await
        }
        other => Err(ApiError::conflict(
            "not_cancellable",
            format!("job {job_id} is already {other}"),
        )),
    }
}

async fn latest(app: &App, job_id: i64) -> Result<RunRow, ApiError> {
    app.store.latest_run(job_id).await?.ok_or_else(|| {
        ApiError::conflict(
            "not_started",
            format!("job {job_id} has never been started"),
        )
    })
}

async fn transition(
    app: &App,
    run: &RunRow,
    from: &[&str],
    to: &str,
    actor: &str,
) -> Result<RunRow, ApiError> {
    match app.store.transition_run(run.id, from, to, None).await? {
        Some(row) => {
            app.bus
                .record_or_log(
                    "job.state",
                    Some(row.machine_id),
                    Some(actor),
                    run_event(&row),
                )
                .await;
            Ok(row)
        }
        // The backend finished the run meanwhile; report what it is now.
        None => Ok(app.store.run(run.id).await?.unwrap_or_else(|| run.clone())),
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn counts_lines_with_and_without_final_newline() {
        let mut c = ProgramChecker::default();
        c.feed(b"G0 X1\nG1 Y2\n").unwrap();
        assert_eq!(c.finish().unwrap(), 2);
        let mut c = ProgramChecker::default();
        c.feed(b"G0 X1\nG1 Y2").unwrap();
        assert_eq!(c.finish().unwrap(), 2);
    }

    #[test]
    fn utf8_split_across_chunks_is_fine_but_bad_bytes_are_located() {
        let text = "(café)\nG0 X1\n".as_bytes();
        let mut c = ProgramChecker::default();
        c.feed(&text[..4]).unwrap();
        c.feed(&text[4..]).unwrap();
        assert_eq!(c.finish().unwrap(), 2);

        let mut c = ProgramChecker::default();
        let e = c.feed(b"G0 X1\nG1 \xff").unwrap_err();
        assert!(e.message.contains("line 2, column 4"), "{}", e.message);
    }

    #[test]
    fn binary_and_empty_are_rejected() {
        let mut c = ProgramChecker::default();
        let e = c.feed(b"G0\0X1").unwrap_err();
        assert_eq!(e.code, "binary_program");
        assert!(e.message.contains("line 1, column 3"), "{}", e.message);
        let c = ProgramChecker::default();
        assert_eq!(c.finish().unwrap_err().code, "empty_program");
    }
}

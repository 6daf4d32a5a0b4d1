//! Jobs: storing uploaded programs (streamed to disk, hashed, checked) and driving job runs
//! through their state machine: running <-> paused -> completed | failed | cancelled, and
//! interrupted (by a restart) -> running again on resume, from the next unacknowledged line.

use crate::app::App;
use crate::error::{Error, ErrorKind, Result};
use crate::machine::Machine;
use crate::store::{JobRow, NewJob, RunRow};
use serde_json::json;
use sha2::{Digest, Sha256};
use std::path::{Path, PathBuf};
use std::sync::Arc;
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
    pub fn feed(&mut self, chunk: &[u8]) -> Result<()> {
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
                    return Err(Error::invalid(
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

    fn advance(&mut self, text: &str) -> Result<()> {
        for c in text.chars() {
            match c {
                '\n' => {
                    self.line += 1;
                    self.column = 1;
                }
                '\r' | '\t' => self.column += 1,
                c if c.is_control() => {
                    return Err(Error::invalid(
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
    pub fn finish(&self) -> Result<u64> {
        if !self.pending.is_empty() {
            return Err(Error::invalid(
                "not_utf8",
                format!(
                    "program ends in the middle of a UTF-8 character at line {}",
                    self.line
                ),
            ));
        }
        if self.bytes == 0 {
            return Err(Error::bad_request(
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
    pub async fn create(programs_dir: &Path, limit: u64) -> Result<Self> {
        let tmp = programs_dir.join(format!(".upload-{}.tmp", rand::random::<u64>()));
        let file = tokio::fs::File::create(&tmp)
            .await
            .map_err(|e| Error::internal(format!("cannot create {}: {e}", tmp.display())))?;
        Ok(PendingProgram {
            tmp: Some(tmp),
            file,
            hasher: Sha256::new(),
            checker: ProgramChecker::default(),
            limit,
        })
    }

    pub async fn write(&mut self, chunk: &[u8]) -> Result<()> {
        if self.checker.bytes + chunk.len() as u64 > self.limit {
            return Err(Error::new(
                ErrorKind::TooLarge,
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
            .map_err(|e| Error::internal(format!("cannot write program: {e}")))
    }

    /// Finishes the file: flushes it to disk and returns (temp path, sha256, lines, bytes).
    pub async fn finish(mut self, expected_sha256: Option<&str>) -> Result<StoredProgram> {
        let lines = self.checker.finish()?;
        let sha = hex::encode(self.hasher.clone().finalize());
        if let Some(expected) = expected_sha256 {
            if !expected.eq_ignore_ascii_case(&sha) {
                return Err(Error::invalid(
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
            .map_err(|e| Error::internal(format!("cannot flush program: {e}")))?;
        let tmp = self
            .tmp
            .take()
            .ok_or_else(|| Error::internal("upload finished twice"))?;
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
    pub fn place(mut self, programs_dir: &Path) -> Result<(PathBuf, bool)> {
        let dest = program_path(programs_dir, &self.sha256);
        let tmp = self
            .tmp
            .take()
            .ok_or_else(|| Error::internal("program placed twice"))?;
        if dest.exists() {
            let _ = std::fs::remove_file(&tmp);
            return Ok((dest, false));
        }
        std::fs::rename(&tmp, &dest).map_err(|e| {
            let _ = std::fs::remove_file(&tmp);
            Error::internal(format!("cannot store program as {}: {e}", dest.display()))
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
) -> Result<CreatedJob> {
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
async fn unsupported_policy(app: &App, machine_id: i64) -> Result<fresa_gcode::Unsupported> {
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
) -> Result<Option<serde_json::Value>> {
    let path = program
        .temp_path()
        .ok_or_else(|| Error::internal("program file already moved"))?
        .to_path_buf();
    let result = tokio::task::spawn_blocking(move || {
        let file = std::fs::File::open(&path)?;
        let reader = std::io::BufReader::with_capacity(1 << 16, file);
        let mut opts = fresa_gcode::AnalysisOptions::default();
        opts.config.unsupported = unsupported;
        Ok::<_, std::io::Error>(fresa_gcode::analyse(reader, &opts))
    })
    .await
    .map_err(|e| Error::internal(format!("analysis failed: {e}")))?
    .map_err(|e| Error::internal(format!("cannot read the stored program: {e}")))?;
    match result {
        Ok(a) => Ok(Some(json!(a))),
        Err(e) => Err(Error::invalid(
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

async fn load_job(app: &App, job_id: i64) -> Result<(JobRow, Arc<Machine>)> {
    let job = app
        .store
        .job(job_id)
        .await?
        .ok_or_else(|| Error::not_found("unknown_job", format!("no job with id {job_id}")))?;
    let machine = app.machines.get(job.machine_id).await.ok_or_else(|| {
        Error::conflict(
            "machine_unavailable",
            format!("machine {} of job {job_id} is not loaded", job.machine_id),
        )
    })?;
    Ok((job, machine))
}

// Run control is the machine's: these find the job's machine and ask its task.

pub async fn start(app: &App, job_id: i64, actor: &str) -> Result<RunRow> {
    let (job, machine) = load_job(app, job_id).await?;
    machine.start_job(job, actor).await
}

pub async fn pause(app: &App, job_id: i64, actor: &str) -> Result<RunRow> {
    let (_, machine) = load_job(app, job_id).await?;
    machine.pause_job(job_id, actor).await
}

/// `confirm_part_zero`: the operator accepts whatever part zero the controller reports now,
/// instead of requiring the one the run started with.
pub async fn resume(
    app: &App,
    job_id: i64,
    actor: &str,
    confirm_part_zero: bool,
) -> Result<RunRow> {
    let (job, machine) = load_job(app, job_id).await?;
    machine.resume_job(job, actor, confirm_part_zero).await
}

pub async fn cancel(app: &App, job_id: i64, actor: &str) -> Result<RunRow> {
    let (_, machine) = load_job(app, job_id).await?;
    machine.cancel_job(job_id, actor).await
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

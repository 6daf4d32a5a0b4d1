//! The execution log of a machine backend: one JSON line `{"run":R,"line":L}` per executed
//! program line, so that `load_program` after a restart can start past what already ran
//! (idempotent resume, see the README). Shared by the Rust backends.

use crate::PluginError;
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use std::fs::{File, OpenOptions};
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Entry {
    pub run: i64,
    pub line: u32,
    /// When the line finished, ms since the Unix epoch (an independent record of how long
    /// each line took, e.g. under an override). Absent in logs written before it existed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub at_ms: Option<u64>,
    /// Where the machine was when the line finished: machine coordinates X, Y, Z, A (mm,
    /// degrees), an independent record of the path executed (e.g. with a height map). Absent
    /// in logs written before it existed, and from backends that do not know it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pos: Option<[f64; 4]>,
}

/// An open, append-only execution log.
#[derive(Debug)]
pub struct ExecLog {
    path: PathBuf,
    file: File,
}

impl ExecLog {
    pub fn open(path: &Path) -> Result<ExecLog, PluginError> {
        ExecLog::open_as(path, "execution_log")
    }

    /// Opens a log whose path came from config key `key` (named in the error).
    pub fn open_as(path: &Path, key: &str) -> Result<ExecLog, PluginError> {
        let file = OpenOptions::new()
            .create(true)
            .append(true)
            .open(path)
            .map_err(|e| {
                PluginError::new(
                    "invalid_config",
                    format!("`{key}`: cannot open {} for appending: {e}", path.display()),
                )
            })?;
        Ok(ExecLog {
            path: path.to_path_buf(),
            file,
        })
    }

    /// Appends one entry and flushes it to the operating system (one `write` call, so a torn
    /// entry can only be the last line, which [`ExecLog::last_line`] skips).
    pub fn append(&mut self, run: i64, line: u32) -> Result<(), String> {
        self.append_at(run, line, None)
    }

    /// [`ExecLog::append`] with the machine position where the line finished.
    pub fn append_at(&mut self, run: i64, line: u32, pos: Option<[f64; 4]>) -> Result<(), String> {
        let at_ms = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .ok()
            .map(|d| d.as_millis() as u64);
        self.append_entry(&Entry {
            run,
            line,
            at_ms,
            pos,
        })
    }

    /// Appends any one-line JSON record (backends with their own record shape).
    pub fn append_entry<T: Serialize>(&mut self, entry: &T) -> Result<(), String> {
        let mut text = serde_json::to_vec(entry)
            .map_err(|e| format!("cannot encode an execution log entry: {e}"))?;
        text.push(b'\n');
        self.file
            .write_all(&text)
            .and_then(|()| self.file.flush())
            .map_err(|e| format!("cannot write execution log {}: {e}", self.path.display()))
    }

    /// Every line that decodes as a `T`, in order; other lines (torn, foreign) are skipped.
    pub fn entries<T: DeserializeOwned>(&self) -> Result<Vec<T>, PluginError> {
        let io = |e: std::io::Error| {
            PluginError::new(
                "io",
                format!("cannot read execution log {}: {e}", self.path.display()),
            )
        };
        let file = File::open(&self.path).map_err(io)?;
        let mut out = Vec::new();
        for text in BufReader::new(file).lines() {
            if let Ok(entry) = serde_json::from_str::<T>(&text.map_err(io)?) {
                out.push(entry);
            }
        }
        Ok(out)
    }

    /// The highest line logged for `run`, if any. Lines that are not entries are skipped.
    pub fn last_line(&self, run: i64) -> Result<Option<u32>, PluginError> {
        Ok(self
            .entries::<Entry>()?
            .into_iter()
            .filter(|e| e.run == run)
            .map(|e| e.line)
            .max())
    }
}

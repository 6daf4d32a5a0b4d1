//! The execution log of a machine backend: one JSON line `{"run":R,"line":L}` per executed
//! program line, so that `load_program` after a restart can start past what already ran
//! (idempotent resume, see the README). Shared by the Rust backends.

use crate::PluginError;
use serde::{Deserialize, Serialize};
use std::fs::{File, OpenOptions};
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Entry {
    pub run: i64,
    pub line: u32,
}

/// An open, append-only execution log.
#[derive(Debug)]
pub struct ExecLog {
    path: PathBuf,
    file: File,
}

impl ExecLog {
    pub fn open(path: &Path) -> Result<ExecLog, PluginError> {
        let file = OpenOptions::new()
            .create(true)
            .append(true)
            .open(path)
            .map_err(|e| {
                PluginError::new(
                    "invalid_config",
                    format!(
                        "`execution_log`: cannot open {} for appending: {e}",
                        path.display()
                    ),
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
        let text = format!("{{\"run\":{run},\"line\":{line}}}\n");
        self.file
            .write_all(text.as_bytes())
            .and_then(|()| self.file.flush())
            .map_err(|e| format!("cannot write execution log {}: {e}", self.path.display()))
    }

    /// The highest line logged for `run`, if any. Lines that are not entries are skipped.
    pub fn last_line(&self, run: i64) -> Result<Option<u32>, PluginError> {
        let file = File::open(&self.path).map_err(|e| {
            PluginError::new(
                "io",
                format!("cannot read execution log {}: {e}", self.path.display()),
            )
        })?;
        let mut last = None;
        for text in BufReader::new(file).lines() {
            let text = text.map_err(|e| {
                PluginError::new(
                    "io",
                    format!("cannot read execution log {}: {e}", self.path.display()),
                )
            })?;
            if let Ok(entry) = serde_json::from_str::<Entry>(&text) {
                if entry.run == run {
                    last = last.max(Some(entry.line));
                }
            }
        }
        Ok(last)
    }
}

//! Uploaded programs on disk: checked as they stream in (UTF-8, no binary, line and column of
//! any error), hashed, written to a temporary file that vanishes unless committed, then moved to
//! their content-addressed name `programs/<sha256>.nc`.

use crate::error::{Error, ErrorKind, Result};
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

/// A failed write of a program: a full disk is 503 `disk_full` (the upload can be sent again
/// once there is room; nothing of it is kept), anything else an internal error.
fn write_failed(what: &str, e: std::io::Error) -> Error {
    // ENOSPC on Unix; ERROR_HANDLE_DISK_FULL and ERROR_DISK_FULL on Windows.
    let full = if cfg!(windows) {
        matches!(e.raw_os_error(), Some(39 | 112))
    } else {
        e.raw_os_error() == Some(28)
    };
    if full {
        Error::new(
            ErrorKind::Unavailable,
            "disk_full",
            format!("{what}: the disk is full ({e}); free some space and upload again"),
        )
    } else {
        Error::internal(format!("{what}: {e}"))
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
            .map_err(|e| write_failed(&format!("cannot create {}", tmp.display()), e))?;
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
            .map_err(|e| write_failed("cannot write program", e))
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
            .map_err(|e| write_failed("cannot flush program", e))?;
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

/// The local file of program `sha256`. A job uploaded on another node has its program only in
/// the shared store: it is copied here (streamed, chunk by chunk), checked against its hash and
/// kept, so every later read is local.
pub async fn local_copy(
    store: &crate::store::Store,
    programs_dir: &Path,
    sha256: &str,
) -> Result<PathBuf> {
    let dest = program_path(programs_dir, sha256);
    if tokio::fs::try_exists(&dest).await.unwrap_or(false) {
        return Ok(dest);
    }
    if !store.has_program(sha256).await? {
        return Err(Error::internal(format!(
            "program {sha256} is neither in {} nor in the store",
            programs_dir.display()
        )));
    }
    // The temporary name is the uploads' one, so a crash mid-copy leaves nothing at start-up.
    let mut pending = PendingProgram::create(programs_dir, u64::MAX).await?;
    let mut seq = 0;
    while let Some(chunk) = store.program_chunk(sha256, seq).await? {
        pending.hasher.update(&chunk);
        pending
            .file
            .write_all(&chunk)
            .await
            .map_err(|e| Error::internal(format!("cannot write program copy: {e}")))?;
        seq += 1;
    }
    let got = hex::encode(pending.hasher.clone().finalize());
    if got != sha256 {
        return Err(Error::internal(format!(
            "the store's copy of program {sha256} is damaged (its sha256 is {got})"
        )));
    }
    pending
        .file
        .sync_all()
        .await
        .map_err(|e| Error::internal(format!("cannot flush program copy: {e}")))?;
    let tmp = pending
        .tmp
        .take()
        .ok_or_else(|| Error::internal("program copy finished twice"))?;
    std::fs::rename(&tmp, &dest).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        Error::internal(format!("cannot store program as {}: {e}", dest.display()))
    })?;
    tracing::info!(sha256, "program copied from the shared store");
    Ok(dest)
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

    /// A full disk under an upload is 503 `disk_full` (issue 23), not 500: `/dev/full` answers
    /// every write with ENOSPC, as a full filesystem does.
    #[cfg(target_os = "linux")]
    #[test]
    fn a_write_on_a_full_disk_is_disk_full() {
        use std::io::Write;
        let e = std::fs::OpenOptions::new()
            .write(true)
            .open("/dev/full")
            .unwrap()
            .write_all(b"G0 X1\n")
            .unwrap_err();
        let e = write_failed("cannot write program", e);
        assert_eq!((e.kind, e.code), (ErrorKind::Unavailable, "disk_full"));
        assert!(e.message.contains("the disk is full"), "{}", e.message);
        let other = write_failed("cannot write program", std::io::Error::other("boom"));
        assert_eq!(other.code, "internal");
    }
}

//! Uploaded programs on disk: checked as they stream in (UTF-8, no binary, line and column of
//! any error), hashed, written to a temporary file that vanishes unless committed, then moved to
//! their content-addressed name `programs/<sha256>.nc`.

use crate::error::{Error, ErrorKind, Result};
use sha2::{Digest, Sha256};
use std::path::{Path, PathBuf};
use tokio::io::AsyncWriteExt;

/// Checks a program stream as it arrives: UTF-8, no binary bytes, counts lines. Tracks the
/// position so an error can name line and column.
///
/// One pass over the bytes as they are (no copy): the standard library's UTF-8 check, then a
/// scan that looks at eight bytes at a time and stops only at a newline or at a byte that can
/// start a control character; columns are counted only at the end of a chunk and for an error.
pub struct ProgramChecker {
    line: u64,
    /// Column (in characters) of the next byte after the last chunk.
    column: u64,
    /// Bytes of a UTF-8 sequence split across chunks (at most 3).
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

/// Whether any byte of `w` is below 0x20, 0x7F, or 0xC2 (the lead byte of U+0080..U+00BF,
/// where the C1 controls are): the bytes [`ProgramChecker::scan`] must look at.
#[inline(always)]
fn needs_look(w: u64) -> bool {
    const ONES: u64 = 0x0101_0101_0101_0101;
    const HIGH: u64 = 0x8080_8080_8080_8080;
    let has_zero = |x: u64| x.wrapping_sub(ONES) & !x & HIGH;
    // Any byte < 0x20 (exact for a bound up to 0x80).
    let below = w.wrapping_sub(ONES * 0x20) & !w & HIGH;
    below | has_zero(w ^ (ONES * 0x7F)) | has_zero(w ^ (ONES * 0xC2)) != 0
}

/// Characters in valid UTF-8 `b` (bytes that are not continuation bytes).
fn chars(b: &[u8]) -> u64 {
    if b.is_ascii() {
        b.len() as u64
    } else {
        b.iter().filter(|&&c| (c & 0xC0) != 0x80).count() as u64
    }
}

impl ProgramChecker {
    pub fn feed(&mut self, chunk: &[u8]) -> Result<()> {
        self.bytes += chunk.len() as u64;
        let mut rest = chunk;
        if !self.pending.is_empty() {
            // Complete the character split at the end of the last chunk.
            let want = match self.pending[0] {
                0xF0.. => 4,
                0xE0.. => 3,
                _ => 2,
            };
            let take = (want - self.pending.len().min(want)).min(rest.len());
            let mut joined = std::mem::take(&mut self.pending);
            joined.extend_from_slice(&rest[..take]);
            rest = &rest[take..];
            match std::str::from_utf8(&joined) {
                Ok(s) => self.scan(s.as_bytes())?,
                Err(e) if e.error_len().is_none() => {
                    // Still incomplete: the chunk was shorter than the character.
                    self.pending = joined;
                    if let Some(&b) = chunk.last() {
                        self.last_byte = Some(b);
                    }
                    return Ok(());
                }
                Err(e) => return Err(self.not_utf8(joined[e.valid_up_to()])),
            }
        }
        let valid = match std::str::from_utf8(rest) {
            Ok(_) => rest,
            Err(e) => {
                let (ok, bad) = rest.split_at(e.valid_up_to());
                // Whatever comes first in the text is reported: a control character in the
                // valid part, else the bad byte (its position counted over the valid part).
                self.scan(ok)?;
                if e.error_len().is_some() {
                    return Err(self.not_utf8(bad[0]));
                }
                self.pending = bad.to_vec();
                if let Some(&b) = chunk.last() {
                    self.last_byte = Some(b);
                }
                return Ok(());
            }
        };
        self.scan(valid)?;
        if let Some(&b) = chunk.last() {
            self.last_byte = Some(b);
        }
        Ok(())
    }

    fn not_utf8(&self, byte: u8) -> Error {
        Error::invalid(
            "not_utf8",
            format!(
                "program is not UTF-8 text: invalid byte 0x{byte:02x} at line {}, column {}",
                self.line, self.column
            ),
        )
    }

    /// Counts lines and finds control characters (other than newline, CR and tab) in valid
    /// UTF-8 `b`; afterwards `column` is the column after `b`.
    fn scan(&mut self, b: &[u8]) -> Result<()> {
        let n = b.len();
        let mut line_start = 0;
        let mut i = 0;
        while i < n {
            while i + 8 <= n {
                let mut w = [0u8; 8];
                w.copy_from_slice(&b[i..i + 8]);
                if needs_look(u64::from_le_bytes(w)) {
                    break;
                }
                i += 8;
            }
            let Some(&c) = b.get(i) else { break };
            let control = match c {
                b'\n' => {
                    self.line += 1;
                    self.column = 1;
                    line_start = i + 1;
                    None
                }
                b'\r' | b'\t' => None,
                0..=0x1F | 0x7F => Some(u32::from(c)),
                // U+0080..U+009F: 0xC2 then 0x80..0x9F (valid UTF-8, so the byte is there).
                0xC2 if b.get(i + 1).is_some_and(|&d| d <= 0x9F) => {
                    b.get(i + 1).map(|&d| u32::from(d))
                }
                _ => None,
            };
            if let Some(code) = control {
                self.column += chars(&b[line_start..i]);
                return Err(Error::invalid(
                    "binary_program",
                    format!(
                        "program looks binary: control character U+{code:04X} at line {}, column {}",
                        self.line, self.column
                    ),
                ));
            }
            i += 1;
        }
        self.column += chars(&b[line_start..]);
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

/// Bytes of program collected before one write to the file.
const WRITE_BLOCK: usize = 1 << 20;

/// A program being written to a temporary file. Dropping it without `commit` deletes the file,
/// so a rejected or interrupted upload leaves nothing on disk.
pub struct PendingProgram {
    tmp: Option<PathBuf>,
    /// Written in blocks of [`WRITE_BLOCK`]: an upload arrives in chunks of a few KiB, and each
    /// write of a `tokio::fs::File` is a trip to the blocking pool.
    file: tokio::io::BufWriter<tokio::fs::File>,
    hasher: Sha256,
    pub checker: ProgramChecker,
    limit: u64,
    /// The analysis running alongside the upload (see [`PendingProgram::analyse_alongside`]).
    alongside: Option<Alongside>,
}

/// Bytes handed to the analysis thread at a time.
const TAP_BLOCK: usize = 256 * 1024;
/// Blocks in flight to the analysis thread: the upload waits when it is this far ahead.
const TAP_BLOCKS: usize = 8;

/// The program's analysis, run on a blocking thread while the upload still arrives, from the
/// same bytes as they are written: on a machine with two cores the analysis (the slow part)
/// no longer waits for the last byte, and nothing is read back from the disk.
struct Alongside {
    opts: fresa_gcode::AnalysisOptions,
    tx: Option<tokio::sync::mpsc::Sender<Vec<u8>>>,
    buf: Vec<u8>,
    task: tokio::task::JoinHandle<
        std::result::Result<fresa_gcode::Analysis, fresa_gcode::GcodeError>,
    >,
}

/// The analysis thread's side of the tap: blocks of the upload as a `BufRead`; the end of
/// input when the upload is finished (or dropped).
struct TapReader {
    rx: tokio::sync::mpsc::Receiver<Vec<u8>>,
    cur: Vec<u8>,
    pos: usize,
}

impl std::io::Read for TapReader {
    fn read(&mut self, out: &mut [u8]) -> std::io::Result<usize> {
        use std::io::BufRead;
        let avail = self.fill_buf()?;
        let n = avail.len().min(out.len());
        out[..n].copy_from_slice(&avail[..n]);
        self.consume(n);
        Ok(n)
    }
}

impl std::io::BufRead for TapReader {
    fn fill_buf(&mut self) -> std::io::Result<&[u8]> {
        while self.pos >= self.cur.len() {
            match self.rx.blocking_recv() {
                Some(block) => {
                    self.cur = block;
                    self.pos = 0;
                }
                None => return Ok(&[]),
            }
        }
        Ok(&self.cur[self.pos..])
    }
    fn consume(&mut self, n: usize) {
        self.pos = (self.pos + n).min(self.cur.len());
    }
}

/// An analysis that ran alongside the upload, with the options it ran with.
pub struct AlongsideAnalysis {
    pub opts: fresa_gcode::AnalysisOptions,
    pub result: std::result::Result<fresa_gcode::Analysis, fresa_gcode::GcodeError>,
}

impl PendingProgram {
    pub async fn create(programs_dir: &Path, limit: u64) -> Result<Self> {
        let tmp = programs_dir.join(format!(".upload-{}.tmp", rand::random::<u64>()));
        let file = tokio::fs::File::create(&tmp)
            .await
            .map_err(|e| write_failed(&format!("cannot create {}", tmp.display()), e))?;
        Ok(PendingProgram {
            tmp: Some(tmp),
            file: tokio::io::BufWriter::with_capacity(WRITE_BLOCK, file),
            hasher: Sha256::new(),
            checker: ProgramChecker::default(),
            limit,
            alongside: None,
        })
    }

    /// Analyses the program with `opts` as it arrives (before the first `write`). The result
    /// comes with the finished program; the job is stored with it when the options the job
    /// needs are still these (otherwise the file is analysed again, as without this).
    pub fn analyse_alongside(&mut self, opts: fresa_gcode::AnalysisOptions) {
        if self.checker.bytes > 0 || self.alongside.is_some() {
            return;
        }
        let (tx, rx) = tokio::sync::mpsc::channel(TAP_BLOCKS);
        let reader = TapReader {
            rx,
            cur: Vec::new(),
            pos: 0,
        };
        let run_opts = opts.clone();
        let task = tokio::task::spawn_blocking(move || fresa_gcode::analyse(reader, &run_opts));
        self.alongside = Some(Alongside {
            opts,
            tx: Some(tx),
            buf: Vec::with_capacity(TAP_BLOCK),
            task,
        });
    }

    /// Hands what has gathered to the analysis thread (waits while it is [`TAP_BLOCKS`]
    /// behind). An analysis that already ended (an error in the program) takes no more.
    async fn tap_send(&mut self, last: bool) {
        let Some(a) = self.alongside.as_mut() else {
            return;
        };
        if let Some(tx) = &a.tx {
            if !a.buf.is_empty() {
                let block = std::mem::replace(&mut a.buf, Vec::with_capacity(TAP_BLOCK));
                if tx.send(block).await.is_err() {
                    a.tx = None;
                }
            }
        }
        if last {
            a.tx = None;
        }
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
        if let Some(a) = self.alongside.as_mut() {
            if a.tx.is_some() {
                a.buf.extend_from_slice(chunk);
                if a.buf.len() >= TAP_BLOCK {
                    self.tap_send(false).await;
                }
            }
        }
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
            .flush()
            .await
            .map_err(|e| write_failed("cannot write program", e))?;
        self.file
            .get_ref()
            .sync_all()
            .await
            .map_err(|e| write_failed("cannot flush program", e))?;
        self.tap_send(true).await;
        let alongside = match self.alongside.take() {
            Some(a) => match a.task.await {
                Ok(result) => Some(AlongsideAnalysis {
                    opts: a.opts,
                    result,
                }),
                // The thread panicked: analysed again from the file (and failing there too).
                Err(_) => None,
            },
            None => None,
        };
        let tmp = self
            .tmp
            .take()
            .ok_or_else(|| Error::internal("upload finished twice"))?;
        Ok(StoredProgram {
            tmp: Some(tmp),
            sha256: sha,
            lines,
            bytes: self.checker.bytes,
            alongside,
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
    /// The analysis that ran while the program arrived, if one was asked for.
    pub alongside: Option<AlongsideAnalysis>,
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
        .flush()
        .await
        .map_err(|e| Error::internal(format!("cannot write program copy: {e}")))?;
    pending
        .file
        .get_ref()
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

    /// The checker as it was (one char at a time over a copy), the reference for the fast one.
    fn reference(data: &[u8]) -> std::result::Result<u64, String> {
        let (valid, bad) = match std::str::from_utf8(data) {
            Ok(s) => (s, None),
            Err(e) => (
                std::str::from_utf8(&data[..e.valid_up_to()]).unwrap(),
                Some(e),
            ),
        };
        let (mut line, mut column) = (1u64, 1u64);
        for c in valid.chars() {
            match c {
                '\n' => (line, column) = (line + 1, 1),
                '\r' | '\t' => column += 1,
                c if c.is_control() => {
                    return Err(format!(
                        "control character U+{:04X} at line {line}, column {column}",
                        c as u32
                    ))
                }
                _ => column += 1,
            }
        }
        match bad {
            Some(e) if e.error_len().is_some() => Err(format!(
                "invalid byte 0x{:02x} at line {line}, column {column}",
                data[e.valid_up_to()]
            )),
            Some(_) => Err(format!("middle of a UTF-8 character at line {line}")),
            None if data.is_empty() => Err("empty".into()),
            None => Ok(if data.last() == Some(&b'\n') {
                line - 1
            } else {
                line
            }),
        }
    }

    fn checked(chunks: &[&[u8]]) -> std::result::Result<u64, String> {
        let mut c = ProgramChecker::default();
        for ch in chunks {
            c.feed(ch).map_err(|e| e.message)?;
        }
        c.finish().map_err(|e| e.message)
    }

    /// Same answers (lines, or the error's kind and position) as the reference, for texts
    /// with multi-byte characters, C0/C1 controls, DEL and bad bytes, split at every point.
    #[test]
    fn the_fast_checker_agrees_with_the_reference_at_every_split() {
        let texts: &[&[u8]] = &[
            b"G0 X1\nG1 Y2.5 F300\n(a comment long enough for words)\nM2\n",
            "(caf\u{e9} \u{2014} \u{1F600})\nG0 X1\r\n\tG1 Y2\n".as_bytes(),
            b"G0 X1 Y2 Z3 (eight+ bytes)\nG1 X2\x7f\n",
            "G0 X1 Y2 Z3 (eight+ bytes)\nG1 \u{85}X2\n".as_bytes(),
            "G0 X1 Y2 Z3 (\u{a0}\u{bf}\u{c0} ok)\nG1 X2\n".as_bytes(),
            b"G0 X1 Y2 Z3 (eight+ bytes)\nG1 X2 \x01\n",
            b"G0 X1 Y2 Z3 (eight+ bytes)\nG1 \xc3X2\n",
            b"G0 X1 Y2 Z3 (eight+ bytes)\nG1 \xff\x01\n",
            b"G0 \x02 X1 \xff",
            b"G0 X1 (\xe2\x82",
            b"no newline at the end, \xc3\xa9 here",
        ];
        for t in texts {
            let want = reference(t);
            for cut in 0..=t.len() {
                let got = checked(&[&t[..cut], &t[cut..]]);
                match (&want, &got) {
                    (Ok(a), Ok(b)) => assert_eq!(a, b, "{t:?} cut at {cut}"),
                    (Err(a), Err(b)) => {
                        let tail = a.split(" at ").last().unwrap();
                        assert!(b.ends_with(tail), "{t:?} cut at {cut}: {b} vs {a}");
                        assert!(b.contains(a.split(" at ").next().unwrap()), "{b} vs {a}");
                    }
                    _ => panic!("{t:?} cut at {cut}: {got:?} vs {want:?}"),
                }
            }
            // And one byte at a time.
            let bytes: Vec<&[u8]> = t.chunks(1).collect();
            assert_eq!(checked(&bytes).is_ok(), want.is_ok(), "{t:?} bytewise");
        }
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

    /// The analysis that runs while the program arrives (in odd-sized chunks, more than the
    /// tap's blocks in flight) is the one a separate pass over the stored file gives; a
    /// program with an error gets the same error; a rejected upload leaves no file.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn the_analysis_alongside_equals_the_analysis_of_the_file() {
        let dir = std::env::temp_dir().join(format!("fresa-tap-{}", rand::random::<u64>()));
        std::fs::create_dir_all(&dir).unwrap();
        let mut text = String::from("G21 G90\n(a comment)\n");
        for i in 0..60_000 {
            text.push_str(&format!(
                "G1 X{}.5 Y-{}.25 F{}\n",
                i % 97,
                i % 13,
                300 + i % 7
            ));
            if i % 50 == 0 {
                text.push_str("G2 X0 Y0 I1 J0\n");
            }
        }
        text.push_str("M2\n");
        let opts = fresa_gcode::AnalysisOptions::default();
        let bad = "G0 X1\nG1 Y2 Q\n".repeat(3);
        for program in [text.as_str(), bad.as_str()] {
            let mut p = PendingProgram::create(&dir, u64::MAX).await.unwrap();
            p.analyse_alongside(opts.clone());
            for chunk in program.as_bytes().chunks(7_919) {
                p.write(chunk).await.unwrap();
            }
            let stored = p.finish(None).await.unwrap();
            let file = std::fs::read(stored.temp_path().unwrap()).unwrap();
            assert_eq!(file, program.as_bytes());
            let alongside = stored.alongside.as_ref().unwrap();
            assert_eq!(alongside.opts, opts);
            let again = fresa_gcode::analyse(&file[..], &opts);
            match (&alongside.result, &again) {
                (Ok(a), Ok(b)) => {
                    assert_eq!(a, b);
                    assert!(a.motion_lines > 60_000, "{}", a.motion_lines);
                }
                (Err(a), Err(b)) => assert_eq!(a, b),
                (a, b) => panic!("alongside {a:?} but from the file {b:?}"),
            }
        }
        // Not UTF-8: refused, its temporary file gone, the analysis thread left to end.
        let mut p = PendingProgram::create(&dir, u64::MAX).await.unwrap();
        p.analyse_alongside(opts.clone());
        p.write(b"G0 X1\n").await.unwrap();
        assert_eq!(p.write(b"G1 \xff\n").await.unwrap_err().code, "not_utf8");
        drop(p);
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 0);
        std::fs::remove_dir_all(&dir).unwrap();
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

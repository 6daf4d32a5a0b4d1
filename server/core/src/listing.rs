//! A window of a stored program's lines, for the console's run screen (the listing scrolled to
//! the line running): `GET /jobs/{id}/gcode?from_line=N&lines=M`. A program may be hundreds of
//! megabytes, so a window is found through a sparse index of line starts (one byte offset every
//! [`INDEX_STRIDE`] lines), built by one pass over the file the first time a window of that
//! program is asked for, and kept by content (sha256: the same bytes have the same index) in a
//! small cache of [`INDEX_CACHE_ENTRIES`]. A window then costs one seek and at most
//! [`INDEX_STRIDE`] + `lines` lines read, whatever the program's size; its answer is bounded by
//! [`MAX_WINDOW_LINES`] lines of at most [`MAX_LINE_BYTES`] bytes each.

use crate::app::App;
use crate::error::{Error, Result};
use std::io::{BufRead, BufReader, Read, Seek, SeekFrom};
use std::path::Path;
use std::sync::{Arc, Mutex};

/// Most lines one window may hold.
pub const MAX_WINDOW_LINES: u32 = 500;
/// A listed line longer than this is cut (at a character boundary) and ends with `…`; the
/// listing is for reading, and G-code lines are short.
pub const MAX_LINE_BYTES: usize = 512;
/// Lines between two indexed offsets: an index costs 8 bytes per this many lines.
pub const INDEX_STRIDE: u64 = 1024;
/// Programs whose index is kept (least recently used out first).
pub const INDEX_CACHE_ENTRIES: usize = 16;

/// Byte offsets of lines 1, 1 + stride, 1 + 2 stride, ...
#[derive(Debug)]
struct LineIndex {
    starts: Vec<u64>,
}

/// Indexes by program sha256, most recently used last.
static INDEXES: Mutex<Vec<(String, Arc<LineIndex>)>> = Mutex::new(Vec::new());

/// Lines `from_line ..` (1-based, at most `lines` of them) of job `job_id`'s program, each
/// ending with `\n` (a line's own `\r\n` or `\n` removed first); empty past the program's end.
pub async fn window(app: &App, job_id: i64, from_line: u32, lines: u32) -> Result<String> {
    if from_line == 0 {
        return Err(Error::bad_request(
            "invalid_query",
            "`from_line` counts from 1",
        ));
    }
    if !(1..=MAX_WINDOW_LINES).contains(&lines) {
        return Err(Error::bad_request(
            "invalid_query",
            format!("`lines` must be 1..={MAX_WINDOW_LINES}, got {lines}"),
        ));
    }
    let (job, path) = crate::jobs::program(app, job_id).await?;
    tokio::task::spawn_blocking(move || {
        let index = index_of(&job.sha256, &path)?;
        read_window(&path, &index, from_line, lines)
    })
    .await
    .map_err(|e| Error::internal(format!("reading the program's lines failed: {e}")))?
}

fn missing(path: &Path, e: std::io::Error) -> Error {
    Error::internal(format!(
        "program file {} cannot be read: {e}",
        path.display()
    ))
}

fn index_of(sha256: &str, path: &Path) -> Result<Arc<LineIndex>> {
    {
        let mut cache = INDEXES.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(i) = cache.iter().position(|(k, _)| k == sha256) {
            let entry = cache.remove(i);
            let index = entry.1.clone();
            cache.push(entry);
            return Ok(index);
        }
    }
    // Built outside the lock: another request for the same program may build it too, which
    // costs a pass but is correct (the last one in stays).
    let file = std::fs::File::open(path).map_err(|e| missing(path, e))?;
    let index = Arc::new(
        build_index(BufReader::with_capacity(1 << 20, file)).map_err(|e| missing(path, e))?,
    );
    let mut cache = INDEXES.lock().unwrap_or_else(|p| p.into_inner());
    cache.retain(|(k, _)| k != sha256);
    if cache.len() >= INDEX_CACHE_ENTRIES {
        cache.remove(0);
    }
    cache.push((sha256.to_string(), index.clone()));
    Ok(index)
}

fn build_index(mut reader: impl BufRead) -> std::io::Result<LineIndex> {
    let mut starts = vec![0u64];
    let mut offset = 0u64;
    // Lines begun so far (line 1 begins at offset 0).
    let mut line = 1u64;
    loop {
        let chunk = reader.fill_buf()?;
        if chunk.is_empty() {
            break;
        }
        for (i, &b) in chunk.iter().enumerate() {
            if b == b'\n' {
                line += 1;
                if (line - 1).is_multiple_of(INDEX_STRIDE) {
                    starts.push(offset + i as u64 + 1);
                }
            }
        }
        let n = chunk.len();
        offset += n as u64;
        reader.consume(n);
    }
    Ok(LineIndex { starts })
}

fn read_window(path: &Path, index: &LineIndex, from_line: u32, lines: u32) -> Result<String> {
    let first = u64::from(from_line) - 1;
    let slot = (first / INDEX_STRIDE) as usize;
    let Some(&start) = index.starts.get(slot) else {
        return Ok(String::new());
    };
    let mut file = std::fs::File::open(path).map_err(|e| missing(path, e))?;
    file.seek(SeekFrom::Start(start))
        .map_err(|e| missing(path, e))?;
    let mut reader = BufReader::with_capacity(1 << 16, file);
    let mut skip = first - slot as u64 * INDEX_STRIDE;
    let mut buf = Vec::new();
    let mut out = String::new();
    let mut taken = 0;
    while taken < lines {
        buf.clear();
        // A stored program's lines are bounded by the reader's line limit; this bound holds
        // even for a file that changed behind the server's back.
        let n = (&mut reader)
            .take(1 << 20)
            .read_until(b'\n', &mut buf)
            .map_err(|e| missing(path, e))?;
        if n == 0 {
            break;
        }
        if skip > 0 {
            skip -= 1;
            continue;
        }
        while matches!(buf.last(), Some(b'\n' | b'\r')) {
            buf.pop();
        }
        let text = String::from_utf8_lossy(&buf);
        if text.len() > MAX_LINE_BYTES {
            let mut cut = MAX_LINE_BYTES;
            while !text.is_char_boundary(cut) {
                cut -= 1;
            }
            out.push_str(&text[..cut]);
            out.push('…');
        } else {
            out.push_str(&text);
        }
        out.push('\n');
        taken += 1;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn window_of(text: &str, from: u32, lines: u32) -> String {
        let dir = tempfile_dir();
        let path = dir.join("p.nc");
        std::fs::write(&path, text).unwrap();
        let index = build_index(BufReader::new(std::fs::File::open(&path).unwrap())).unwrap();
        let got = read_window(&path, &index, from, lines).unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
        got
    }

    fn tempfile_dir() -> std::path::PathBuf {
        use std::sync::atomic::{AtomicU32, Ordering};
        static N: AtomicU32 = AtomicU32::new(0);
        let d = std::env::temp_dir().join(format!(
            "fresa-listing-{}-{}",
            std::process::id(),
            N.fetch_add(1, Ordering::Relaxed)
        ));
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[test]
    fn windows_anywhere_in_a_long_program_are_its_lines() {
        let lines: Vec<String> = (1..=5000).map(|i| format!("G1 X{i} (line {i})")).collect();
        let text = lines.join("\r\n") + "\r\n";
        for (from, n) in [
            (1, 3),
            (1023, 4),
            (1024, 2),
            (1025, 2),
            (2049, 5),
            (4998, 10),
        ] {
            let got = window_of(&text, from, n);
            let want: String = lines[(from - 1) as usize..]
                .iter()
                .take(n as usize)
                .map(|l| format!("{l}\n"))
                .collect();
            assert_eq!(got, want, "from {from}");
        }
        assert_eq!(window_of(&text, 5001, 5), "");
        assert_eq!(window_of(&text, 90_000, 5), "");
        // No final newline: the last line still counts.
        assert_eq!(window_of("G0 X1\nG0 X2", 2, 5), "G0 X2\n");
    }

    #[test]
    fn a_long_line_is_cut_at_a_character_boundary() {
        let long = format!("({})", "é".repeat(600));
        let got = window_of(&format!("G0\n{long}\nM30\n"), 2, 2);
        let first = got.lines().next().unwrap();
        assert!(first.len() <= MAX_LINE_BYTES + '…'.len_utf8());
        assert!(first.ends_with('…'));
        assert_eq!(got.lines().nth(1), Some("M30"));
    }
}

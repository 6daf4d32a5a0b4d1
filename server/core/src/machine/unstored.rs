//! Acknowledged lines the store could not take, recorded beside it (issue 23). While the
//! database cannot be written a machine's task keeps acknowledged lines in memory
//! (`actor::PendingWrites`); if the process then stops, the run's stored line is behind what ran,
//! by as much as the outage lasted, and a blind resume would run those lines twice on a backend
//! without an execution log of its own. So the task also records which runs have unstored lines
//! in `DATA_DIR/unstored/machine-<id>.json`, and start-up marks those runs (`unstored_line`):
//! their resume needs the operator to confirm the line.
//!
//! The disk that refuses the database's writes may refuse this file's too, so the file is
//! reserved while there is room (a fixed [`SIZE`] bytes, written and synced when the machine
//! starts) and later only overwritten in place: that needs no new blocks on ext4, XFS, NTFS or
//! tmpfs. (A copy-on-write filesystem, btrfs or ZFS, may still refuse it when full, as may a disk
//! gone read-only; the task then logs that a restart would not know.) The record is JSON padded
//! with spaces to the file's size; all spaces means nothing is unstored. Writes run on a blocking
//! thread behind a `watch`, so a slow or failing disk never holds up the machine's task; the
//! latest state is written, at most every [`MIN_INTERVAL`] after the first.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::io::{Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::time::Duration;
use tokio::sync::watch;

/// The directory under the data directory.
pub const DIR: &str = "unstored";
/// Size of each machine's file: room for a few dozen runs, more than a machine ever has pending.
pub const SIZE: usize = 4096;
/// Least time between two writes of one file (the first of an outage is written at once).
const MIN_INTERVAL: Duration = Duration::from_millis(200);

/// A run with lines acknowledged but not stored.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct UnstoredRun {
    pub run: i64,
    /// The highest acknowledged line the store has not been told.
    pub line: i64,
}

/// What one machine's file says.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Record {
    pub machine: i64,
    /// Since when (Unix ms) lines have been waiting.
    pub since_ms: i64,
    pub runs: Vec<UnstoredRun>,
}

/// The path of machine `id`'s file in `dir` (`DATA_DIR/unstored`).
pub fn path(dir: &Path, id: i64) -> PathBuf {
    dir.join(format!("machine-{id}.json"))
}

/// A machine task's handle on its file.
pub struct Marker {
    machine: i64,
    state: watch::Sender<Option<Record>>,
}

impl Marker {
    /// Reserves machine `machine`'s file in `dir` and starts its writer (which ends with the
    /// marker).
    pub fn start(dir: &Path, machine: i64) -> Marker {
        let (state, rx) = watch::channel(None);
        tokio::spawn(writer(path(dir, machine), rx));
        Marker { machine, state }
    }

    /// The acknowledged lines not yet in the store (empty once they landed).
    pub fn show(&self, acks: &BTreeMap<i64, u32>) {
        self.state.send_if_modified(|current| {
            let next = (!acks.is_empty()).then(|| Record {
                machine: self.machine,
                since_ms: current
                    .as_ref()
                    .map_or_else(crate::store::now_ms, |r| r.since_ms),
                runs: acks
                    .iter()
                    .map(|(&run, &line)| UnstoredRun {
                        run,
                        line: i64::from(line),
                    })
                    .collect(),
            });
            let changed = *current != next;
            *current = next;
            changed
        });
    }
}

async fn writer(path: PathBuf, mut rx: watch::Receiver<Option<Record>>) {
    let reserve = path.clone();
    let mut failing = tokio::task::spawn_blocking(move || reserve_file(&reserve))
        .await
        .map_err(|e| e.to_string())
        .and_then(|r| r.map_err(|e| e.to_string()))
        .err();
    if let Some(e) = &failing {
        tracing::warn!(file = %path.display(), error = %e, "cannot reserve the file for unstored lines: a restart during a database outage may not know a run's stored line is behind");
    }
    while rx.changed().await.is_ok() {
        let record = rx.borrow_and_update().clone();
        let (p, r) = (path.clone(), record.clone());
        let written = tokio::task::spawn_blocking(move || write_record(&p, r.as_ref()))
            .await
            .map_err(|e| e.to_string())
            .and_then(|r| r.map_err(|e| e.to_string()));
        match (written, &failing) {
            (Ok(()), Some(_)) => {
                tracing::info!(file = %path.display(), "the file for unstored lines is written again");
                failing = None;
            }
            (Err(e), None) => {
                tracing::error!(file = %path.display(), error = %e, runs = ?record.map(|r| r.runs), "cannot record unstored lines: a restart now would not know these runs' stored line is behind");
                failing = Some(e);
            }
            _ => {}
        }
        tokio::time::sleep(MIN_INTERVAL).await;
    }
}

/// Makes the file [`SIZE`] bytes long and on disk, unless it already is (then it may hold a
/// record start-up has not taken yet: it is left as it is).
fn reserve_file(path: &Path) -> std::io::Result<()> {
    if std::fs::metadata(path).is_ok_and(|m| m.len() == SIZE as u64) {
        return Ok(());
    }
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir)?;
    }
    write_record(path, None)?;
    // The new name must survive a crash too.
    #[cfg(unix)]
    if let Some(dir) = path.parent() {
        std::fs::File::open(dir)?.sync_all()?;
    }
    Ok(())
}

/// Overwrites the file in place with `record` (none: all spaces), padded to [`SIZE`], and
/// syncs it. Records too long for the file keep their newest runs.
fn write_record(path: &Path, record: Option<&Record>) -> std::io::Result<()> {
    let mut text = match record {
        Some(r) => {
            let mut r = r.clone();
            loop {
                let t = serde_json::to_string(&r)?;
                if t.len() < SIZE || r.runs.len() <= 1 {
                    break t;
                }
                r.runs.remove(0);
            }
        }
        None => String::new(),
    }
    .into_bytes();
    text.truncate(SIZE - 1);
    text.resize(SIZE - 1, b' ');
    text.push(b'\n');
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(false)
        .open(path)?;
    f.seek(SeekFrom::Start(0))?;
    f.write_all(&text)?;
    f.sync_data()
}

/// A file the previous process left in `DATA_DIR/unstored`.
#[derive(Debug, PartialEq, Eq)]
pub enum LeftBehind {
    Record(PathBuf, Record),
    /// Torn or unreadable: which of the machine's runs it named is unknown.
    Unreadable {
        path: PathBuf,
        machine: i64,
        error: String,
    },
}

/// The records the previous process left in `dir` (`DATA_DIR/unstored`); files saying nothing
/// is unstored are left out.
pub fn left_behind(dir: &Path) -> Result<Vec<LeftBehind>, String> {
    let entries = match std::fs::read_dir(dir) {
        Ok(d) => d,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(format!("cannot list {}: {e}", dir.display())),
    };
    let mut out = Vec::new();
    for entry in entries.flatten() {
        let path = entry.path();
        let name = entry.file_name();
        let Some(machine) = name
            .to_str()
            .and_then(|n| n.strip_prefix("machine-"))
            .and_then(|n| n.strip_suffix(".json"))
            .and_then(|n| n.parse::<i64>().ok())
        else {
            continue;
        };
        let read = std::fs::read_to_string(&path)
            .map_err(|e| e.to_string())
            .and_then(|text| {
                let text = text.trim();
                if text.is_empty() {
                    Ok(None)
                } else {
                    serde_json::from_str::<Record>(text)
                        .map(Some)
                        .map_err(|e| e.to_string())
                }
            });
        match read {
            Ok(None) => {}
            Ok(Some(record)) => out.push(LeftBehind::Record(path, record)),
            Err(error) => out.push(LeftBehind::Unreadable {
                path,
                machine,
                error,
            }),
        }
    }
    Ok(out)
}

/// Says nothing is unstored in the file at `path` (once start-up has marked its runs).
pub fn clear(path: &Path) -> std::io::Result<()> {
    write_record(path, None)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn a_record_is_written_in_place_read_back_and_cleared() {
        let dir = std::env::temp_dir().join(format!(
            "fresa-unstored-{}-{}",
            std::process::id(),
            rand::random::<u64>()
        ));
        let p = path(&dir, 3);
        reserve_file(&p).unwrap();
        assert_eq!(std::fs::metadata(&p).unwrap().len(), SIZE as u64);
        assert!(left_behind(&dir).unwrap().is_empty());
        let record = Record {
            machine: 3,
            since_ms: 5,
            runs: vec![UnstoredRun { run: 7, line: 40 }],
        };
        write_record(&p, Some(&record)).unwrap();
        assert_eq!(std::fs::metadata(&p).unwrap().len(), SIZE as u64);
        assert_eq!(
            left_behind(&dir).unwrap(),
            vec![LeftBehind::Record(p.clone(), record)]
        );
        // A reservation at the next start leaves a record start-up has not taken.
        reserve_file(&p).unwrap();
        assert_eq!(left_behind(&dir).unwrap().len(), 1);
        clear(&p).unwrap();
        assert!(left_behind(&dir).unwrap().is_empty());
        // A torn record still names its machine.
        std::fs::write(&p, "{\"machine\":3,\"sin").unwrap();
        assert!(matches!(
            left_behind(&dir).unwrap().as_slice(),
            [LeftBehind::Unreadable { machine: 3, .. }]
        ));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_record_too_long_for_the_file_keeps_its_newest_runs() {
        let dir = std::env::temp_dir().join(format!(
            "fresa-unstored-{}-{}",
            std::process::id(),
            rand::random::<u64>()
        ));
        std::fs::create_dir_all(&dir).unwrap();
        let p = path(&dir, 1);
        let runs: Vec<UnstoredRun> = (1..=500).map(|run| UnstoredRun { run, line: 9 }).collect();
        let record = Record {
            machine: 1,
            since_ms: 0,
            runs,
        };
        write_record(&p, Some(&record)).unwrap();
        let Some(LeftBehind::Record(_, back)) = left_behind(&dir).unwrap().pop() else {
            panic!("no record")
        };
        assert!(back.runs.len() < 500);
        assert_eq!(back.runs.last().unwrap().run, 500);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}

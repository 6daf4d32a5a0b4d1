//! What a crash or a lost disk leaves behind: unfinished uploads are removed at start-up, a
//! zero-length database beside stored programs is refused (not silently started empty), and
//! `fresa backup` makes a copy, taken while the server runs, that a new server starts from.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::serde_json::Value;
use fresa_tests::{fresa_cmd, output_text, Opts, Server};
use std::path::Path;
use std::process::Output;
use std::time::Duration;

const T: Duration = Duration::from_secs(60);

fn backup(s: &Server, file: &Path) -> Output {
    fresa_cmd()
        .arg("backup")
        .arg(file)
        .arg("--data-dir")
        .arg(s.data_dir())
        .arg("--config")
        .arg(s.config_file())
        .output()
        .expect("run fresa backup")
}

#[test]
fn unfinished_uploads_are_removed_at_start_up() {
    let mut s = Server::unstarted(Opts::default());
    std::fs::create_dir_all(s.programs_dir()).unwrap();
    // What a kill -9 during two uploads leaves, next to files that must stay.
    std::fs::write(s.programs_dir().join(".upload-1.tmp"), vec![b'G'; 3000]).unwrap();
    std::fs::write(s.programs_dir().join(".upload-2.tmp"), vec![b'G'; 1000]).unwrap();
    std::fs::write(s.programs_dir().join("notes.tmp"), "keep").unwrap();
    s.spawn().unwrap();
    assert!(s.upload_temp_files().is_empty(), "{:?}", s.program_files());
    assert!(s.program_files().contains(&"notes.tmp".to_string()));
    let line = s.wait_log(T, "unfinished upload");
    assert!(
        line.contains("removed 2 unfinished upload(s) (4000 bytes)"),
        "{line}"
    );
    // Uploads still work afterwards and leave no temp file.
    let m = s.sim("m", 0.0);
    s.upload(m.id, "j", "G0 X1\n");
    assert!(s.upload_temp_files().is_empty(), "{:?}", s.program_files());
}

#[test]
fn a_zero_length_database_beside_programs_is_refused() {
    let mut s = Server::unstarted(Opts::default());
    std::fs::create_dir_all(s.programs_dir()).unwrap();
    std::fs::write(s.data_dir().join("fresa.db"), "").unwrap();
    // With no programs it is a fresh data dir: it starts (and the file becomes a store).
    s.spawn().unwrap();
    s.get("/api/v1/machines").expect(200);
    let m = s.sim("m", 0.0);
    s.upload(m.id, "j", "G0 X1\n");
    assert!(s.terminate().success());

    // The store is lost (truncated) but the programs are still there: refuse, say how to
    // restore, and leave the file as it was.
    let db = s.data_dir().join("fresa.db");
    for f in ["fresa.db-wal", "fresa.db-shm"] {
        let _ = std::fs::remove_file(s.data_dir().join(f));
    }
    std::fs::write(&db, "").unwrap();
    let err = s
        .spawn()
        .expect_err("an empty store beside programs must be refused");
    assert!(
        err.contains(&db.display().to_string())
            && err.contains("is empty")
            && err.contains("fresa backup")
            && err.contains("-wal"),
        "{err}"
    );
    assert_eq!(std::fs::metadata(&db).unwrap().len(), 0);
}

#[test]
fn a_backup_taken_while_running_restores_the_jobs() {
    let s = Server::start();
    let m = s.sim("m", 0.0);
    let (done, _) = s.upload_and_start(m.id, "done", "G0 X1\nG0 X0\n");
    s.wait_job_state(done, "completed", T);
    let waiting = s.upload(m.id, "waiting", "G0 Y2\n")["id"].as_i64().unwrap();
    let jobs: Value = s.get("/api/v1/jobs").expect(200);

    let file = s.root().join("fresa-backup.db");
    let out = backup(&s, &file);
    assert!(out.status.success(), "{}", output_text(&out));
    assert!(file.is_file());
    // The server is still fine, and a second backup to the same file is refused.
    s.get("/api/v1/jobs").expect(200);
    let again = backup(&s, &file);
    assert!(!again.status.success(), "{}", output_text(&again));
    assert!(
        String::from_utf8_lossy(&again.stderr).contains("refusing to overwrite"),
        "{}",
        output_text(&again)
    );

    // The old server goes on after the backup; a client has seen its newest event.
    s.jog(m.id, "X", 1.0).expect(200);
    let seen = s
        .events("", Some(0))
        .until(T, "machine.jog", |e| e.event == "machine.jog");
    let client_last = seen.last().and_then(|e| e.id).unwrap();

    // Restore on another data dir: the backup as fresa.db, the programs copied.
    let mut r = Server::unstarted(Opts::default());
    std::fs::create_dir_all(r.programs_dir()).unwrap();
    std::fs::copy(&file, r.data_dir().join("fresa.db")).unwrap();
    for name in s.program_files() {
        std::fs::copy(s.programs_dir().join(&name), r.programs_dir().join(&name)).unwrap();
    }
    r.spawn().unwrap();
    let restored: Value = r.get("/api/v1/jobs").expect(200);
    let key = |v: &Value| -> Vec<(Value, Value, Value)> {
        v.as_array()
            .unwrap()
            .iter()
            .map(|j| (j["id"].clone(), j["name"].clone(), j["sha256"].clone()))
            .collect()
    };
    assert_eq!(key(&restored), key(&jobs), "{restored}");
    assert_eq!(r.job(done)["state"], "completed");
    // That client's id is beyond the restored log: it is told to resync and then gets the
    // new events, although they reuse ids it has seen.
    let stream = r.events("", Some(client_last));
    let first = stream.next(T).expect("resync");
    assert_eq!(first.event, "resync", "{first:?}");
    let restored_last = first.data["last_event_id"].as_i64().unwrap();
    assert!(restored_last < client_last, "{first:?}");
    r.post_empty(&format!("/api/v1/machines/{}/part-zero", m.id))
        .expect(201);
    let got = stream.until(T, "machine.part_zero", |e| e.event == "machine.part_zero");
    assert_eq!(got.last().unwrap().id, Some(restored_last + 1), "{got:?}");

    // The restored job can still run: its program is there.
    r.job_action(waiting, "start").expect(200);
    r.wait_job_state(waiting, "completed", T);
}

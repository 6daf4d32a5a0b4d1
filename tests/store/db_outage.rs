//! The database restarted under a running job (issue 16, Faults). A server on a PostgreSQL of
//! this test's own (stopped like a crash, `pg_ctl stop -m immediate`, and started again):
//! while it is down no new motion starts (jog, MDI, job start and resume answer 503
//! `database_unavailable` naming the database), `/healthz` says `degraded` with the database's
//! outage, a running job goes on to its end, and pause and cancel still stop motion. When the
//! database returns, what was kept in memory lands: the run's stored line is the last line of the
//! sim's execution log, its end state is stored, no line ran twice, and the audit log holds the
//! job's state transitions.
//!
//! The same for a full disk (issue 23): the data directory on a small tmpfs of the test's own,
//! filled to the last page while a job runs; then freed, or the server killed while it is full.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_core::store::test_postgres::DedicatedPostgres;
use fresa_tests::{assert_every_line_once, back_and_forth, wait_for, Opts, Server, Sim};
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

const T: Duration = Duration::from_secs(60);
/// 1 mm lines at 600 mm/min: 10 ms a line at time scale 0.1; 800 lines take about 8 s, long
/// enough to stop the database mid-job and check the refusals before the job ends.
const LINES: i64 = 800;
const TIME_SCALE: f64 = 0.1;

/// A server on a fresh database of `pg`.
fn server_on(pg: &DedicatedPostgres) -> Server {
    let rt = tokio::runtime::Runtime::new().unwrap();
    let url = rt.block_on(pg.fresh_database());
    let mut s = Server::unstarted(Opts::default());
    s.write_config(&format!("database_url = \"{url}\"\n"));
    s.spawn()
        .unwrap_or_else(|e| panic!("server did not start: {e}"));
    s
}

fn start_slow_job(s: &Server, m: &Sim) -> (i64, i64) {
    let job = s.upload(m.id, "slow", back_and_forth(LINES as usize, 1.0, 600.0))["id"]
        .as_i64()
        .unwrap();
    let run = s.job_action(job, "start").expect(200)["run"]["id"]
        .as_i64()
        .unwrap();
    (job, run)
}

/// Stops the database and waits until the server has noticed (`/healthz` names the outage).
fn stop_database(s: &Server, pg: &DedicatedPostgres) -> Value {
    pg.stop();
    let health = wait_for(T, "/healthz to report the database outage", || {
        let h = s.get("/healthz").expect(200);
        h.get("database").is_some().then_some(h)
    });
    assert_eq!(health["status"], "degraded", "{health}");
    assert_eq!(health["database"]["status"], "unavailable", "{health}");
    let message = health["database"]["message"].as_str().unwrap();
    assert!(
        message.contains(&format!("127.0.0.1:{}", pg.port)) && message.contains("since"),
        "the outage names the database and since when: {message}"
    );
    health
}

/// A refusal for want of the database: 503, and a message naming it.
#[track_caller]
fn refused(r: fresa_tests::Resp, pg: &DedicatedPostgres) {
    let message = r.expect_error(503, "database_unavailable");
    assert!(
        message.contains(&format!("127.0.0.1:{}", pg.port)),
        "the refusal names the database: {message}"
    );
}

fn last_logged(m: &Sim, run: i64) -> i64 {
    m.lines_of(run).into_iter().max().unwrap_or(0)
}

/// The job's `job.state` events from the audit log, replayed from the start.
fn job_states(s: &Server, job: i64, until_state: &str) -> Vec<String> {
    let events = s.events("types=job.state", Some(0));
    let got = events.until(
        T,
        &format!("job {job} {until_state} in the audit log"),
        |e| e.job() == Some(job) && e.state() == Some(until_state),
    );
    got.iter()
        .filter(|e| e.job() == Some(job))
        .map(|e| e.state().unwrap_or_default().to_string())
        .collect()
}

#[test]
fn a_running_job_finishes_through_a_database_outage_and_every_line_is_stored_once() {
    let pg = DedicatedPostgres::start();
    let s = server_on(&pg);
    let m = s.sim("mill", TIME_SCALE);
    let spare = s.upload(m.id, "spare", "G1 X1 F600\n")["id"]
        .as_i64()
        .unwrap();
    let (job, run) = start_slow_job(&s, &m);
    wait_for(T, "the job to execute its first lines", || {
        (m.count_of(run) >= 20).then_some(())
    });

    stop_database(&s, &pg);
    let at_outage = m.count_of(run);
    // No new motion of any kind while the database is down.
    refused(s.jog(m.id, "X", 1.0), &pg);
    refused(s.mdi(m.id, "G0 X1"), &pg);
    refused(s.job_action(spare, "start"), &pg);

    // The running job goes on to its end with the database still down: the program is on the
    // node, and stopping mid-cut would spoil the part.
    wait_for(
        T,
        "the job to run to its last line during the outage",
        || (last_logged(&m, run) == LINES).then_some(()),
    );
    assert!(m.count_of(run) > at_outage, "lines ran during the outage");
    let st = s.wait_machine_state(m.id, "idle", T);
    assert!(st["job"].is_null(), "the run ended in memory: {st}");
    assert!(
        s.get("/healthz").expect(200).get("database").is_some(),
        "the database was down all along"
    );

    pg.restart();
    let j = s.wait_job_state(job, "completed", T);
    assert_eq!(j["run"]["id"], run, "{j}");
    assert_eq!(
        j["line"].as_i64(),
        Some(last_logged(&m, run)),
        "the stored line is the last executed one: {j}"
    );
    assert_every_line_once(&m.executed(), run, LINES);
    let states = job_states(&s, job, "completed");
    assert_eq!(states, ["running", "completed"], "audit log of job {job}");
    let h = wait_for(T, "/healthz ok again", || {
        let h = s.get("/healthz").expect(200);
        (h["status"] == "ok").then_some(h)
    });
    assert!(h.get("database").is_none(), "{h}");
    // New motion is allowed again.
    s.job_action(spare, "start").expect(200);
    s.wait_job_state(spare, "completed", T);
}

#[test]
fn pause_and_cancel_stop_a_job_during_an_outage_and_are_stored_when_it_ends() {
    let pg = DedicatedPostgres::start();
    let s = server_on(&pg);
    let m = s.sim("mill", TIME_SCALE);
    let (job, run) = start_slow_job(&s, &m);
    wait_for(T, "the job to execute its first lines", || {
        (m.count_of(run) >= 20).then_some(())
    });
    stop_database(&s, &pg);

    let paused = s.job_action(job, "pause").expect(200);
    assert_eq!(paused["state"], "paused", "{paused}");
    let st = s.status(m.id);
    assert_eq!(st["job"]["run"], run, "{st}");
    // Issue 26: the hold says why it is paused, and that going on waits for the database.
    let st = s.wait_status(m.id, T, "the hold naming the outage", |st| {
        st["state"] == "paused" && st["hold"]["blocked"].is_string()
    });
    assert_eq!(st["hold"]["kind"], "pause", "{st}");
    let blocked = st["hold"]["blocked"].as_str().unwrap();
    assert!(
        blocked.contains(&format!("127.0.0.1:{}", pg.port)),
        "{blocked}"
    );
    refused(s.job_action(job, "resume"), &pg);
    let r = s.job_action(job, "cancel");
    if r.status != 200 {
        panic!("cancel: {r:?}\n{}", s.log());
    }
    let cancelled = r.body;
    assert_eq!(cancelled["state"], "cancelled", "{cancelled}");
    // Answered once motion stopped: the machine is idle and the run is over in memory.
    let st = s.wait_machine_state(m.id, "idle", T);
    assert!(st["job"].is_null(), "{st}");
    let executed = last_logged(&m, run);
    assert!(executed < LINES, "cancelled mid-job");

    pg.restart();
    let j = s.wait_job_state(job, "cancelled", T);
    assert_eq!(
        j["line"].as_i64(),
        Some(executed),
        "the stored line is the last executed one: {j}"
    );
    assert_eq!(
        last_logged(&m, run),
        executed,
        "nothing ran after the cancel"
    );
    let lines = m.lines_of(run);
    assert!(
        lines.iter().copied().eq(1..=executed),
        "every line up to {executed} once, in order"
    );
    let states = job_states(&s, job, "cancelled");
    assert_eq!(
        states,
        ["running", "paused", "cancelled"],
        "audit log of job {job}"
    );
}

/// Reading jobs during an outage (issue 24): the running job is answered as its machine knows
/// it (state, run, the line it has reached) and its program from disk, exactly as long as cancel
/// can find it; any other job, and the list, get the same 503 as run control would.
#[test]
fn the_running_job_is_read_during_an_outage_as_long_as_it_can_be_cancelled() {
    // Long enough (30 s) for the refused reads, each bounded by the store's ping timeout.
    const LONG: usize = 3000;
    let pg = DedicatedPostgres::start();
    let s = server_on(&pg);
    let m = s.sim("mill", TIME_SCALE);
    let spare = s.upload(m.id, "spare", "G1 X1 F600\n")["id"]
        .as_i64()
        .unwrap();
    let program = back_and_forth(LONG, 1.0, 600.0);
    let job = s.upload(m.id, "long", program.clone())["id"]
        .as_i64()
        .unwrap();
    let run = s.job_action(job, "start").expect(200)["run"]["id"]
        .as_i64()
        .unwrap();
    wait_for(T, "the job to execute its first lines", || {
        (m.count_of(run) >= 20).then_some(())
    });
    stop_database(&s, &pg);

    let j = s.job(job);
    assert_eq!(
        (j["id"].as_i64(), j["run"]["id"].as_i64()),
        (Some(job), Some(run)),
        "{j}"
    );
    assert_eq!(j["state"], "running", "{j}");
    assert_eq!(j["name"], "long", "{j}");
    assert_eq!(j["line_count"], LONG, "{j}");
    // The line is the machine's: it moves on while the store cannot take it.
    let line = j["line"].as_i64().unwrap();
    wait_for(T, "GET /jobs/{id} to show the line advancing", || {
        (s.job(job)["line"].as_i64().unwrap() > line).then_some(())
    });
    let g = s.get(&format!("/api/v1/jobs/{job}/gcode"));
    assert_eq!(g.status, 200, "{}", g.text);
    assert!(g.text == program, "the program as uploaded");

    // Nothing else is known without the database.
    refused(s.get(&format!("/api/v1/jobs/{spare}")), &pg);
    refused(s.get(&format!("/api/v1/jobs/{spare}/gcode")), &pg);
    refused(s.get("/api/v1/jobs"), &pg);

    let cancelled = s.job_action(job, "cancel").expect(200);
    assert_eq!(cancelled["state"], "cancelled", "{cancelled}");
    // The run is over in memory: neither a read nor a second cancel can find the job now.
    refused(s.get(&format!("/api/v1/jobs/{job}")), &pg);
    refused(s.job_action(job, "cancel"), &pg);

    pg.restart();
    let j = s.wait_job_state(job, "cancelled", T);
    assert_eq!(j["run"]["id"], run, "{j}");
    assert_eq!(
        j["line"].as_i64(),
        Some(last_logged(&m, run)),
        "the stored line is the last executed one: {j}"
    );
    let listed = s.get(&format!("/api/v1/jobs?machine={}", m.id)).expect(200);
    assert_eq!(listed.as_array().map(Vec::len), Some(2), "{listed}");
}

// ---- a full disk (issue 23) ----

/// A small tmpfs mounted over a server's data directory, as a full disk is what users hit: the
/// database, its WAL and the programs are on it. The sim's execution log, the test's independent
/// record, is on a second tmpfs mounted inside it (backend files must be in the data directory),
/// as a controller's own log would be on its own storage. Mounting needs root (CI runs as root);
/// without it the test fails naming what is missing, it is never skipped.
struct SmallDisk {
    data: PathBuf,
    record: PathBuf,
}

impl SmallDisk {
    fn mount(data: &Path) -> SmallDisk {
        let uid = Command::new("id").arg("-u").output().expect("run id -u");
        let uid = String::from_utf8_lossy(&uid.stdout).trim().to_string();
        assert_eq!(
            uid, "0",
            "the full-disk tests mount a tmpfs, which needs root (CAP_SYS_ADMIN); run them as root (CI does)"
        );
        std::fs::create_dir_all(data).unwrap();
        mount_tmpfs(data, "32m");
        let record = data.join("record");
        std::fs::create_dir_all(&record).unwrap();
        mount_tmpfs(&record, "16m");
        SmallDisk {
            data: data.to_path_buf(),
            record,
        }
    }

    fn ballast(&self) -> PathBuf {
        self.data.join("ballast")
    }

    /// Fills the disk to its last page. Returns the bytes written.
    fn fill(&self) -> u64 {
        use std::io::Write;
        let mut f = std::fs::File::create(self.ballast()).unwrap();
        let mut written = 0u64;
        for chunk in [1 << 20, 4096, 1] {
            let buf = vec![0u8; chunk];
            loop {
                match f.write(&buf) {
                    Ok(0) => break,
                    Ok(n) => written += n as u64,
                    Err(e) if e.raw_os_error() == Some(28) => break,
                    Err(e) => panic!("filling the disk: {e}"),
                }
            }
        }
        written
    }

    fn free(&self) {
        std::fs::remove_file(self.ballast()).unwrap();
    }
}

fn mount_tmpfs(at: &Path, size: &str) {
    let out = Command::new("mount")
        .args([
            "-t",
            "tmpfs",
            "-o",
            &format!("size={size},mode=0755"),
            "tmpfs",
        ])
        .arg(at)
        .output()
        .unwrap_or_else(|e| panic!("run mount (util-linux) to mount a tmpfs: {e}"));
    assert!(
        out.status.success(),
        "mount -t tmpfs on {} failed (needs root with CAP_SYS_ADMIN): {}",
        at.display(),
        String::from_utf8_lossy(&out.stderr)
    );
}

impl Drop for SmallDisk {
    fn drop(&mut self) {
        // Lazily: a server still holding files there must not keep the mount.
        for at in [&self.record, &self.data] {
            let _ = Command::new("umount").arg("-l").arg(at).status();
        }
    }
}

/// A server whose data directory is a fresh [`SmallDisk`], and a sim logging to its record.
fn server_on_small_disk() -> (Server, SmallDisk, Sim) {
    let mut s = Server::unstarted(Opts::default());
    let disk = SmallDisk::mount(&s.data_dir());
    s.spawn()
        .unwrap_or_else(|e| panic!("server did not start: {e}"));
    let log = disk.record.join("exec-mill.log");
    let id = s.create_machine(&json!({
        "name": "mill",
        "backend": "sim-machine",
        "config": {"time_scale": TIME_SCALE, "execution_log": log},
    }));
    (s, disk, Sim { id, log })
}

/// Resident memory of process `pid`, KiB.
fn rss_kib(pid: u32) -> u64 {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .unwrap_or_default()
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next()?.parse().ok())
        .unwrap_or(0)
}

/// Fills the disk under a running job and waits until the server reports it: `/healthz`
/// degraded naming the full disk, `fresa_database_up 0`.
fn fill_and_wait_for_the_outage(s: &Server, disk: &SmallDisk) {
    let bytes = disk.fill();
    eprintln!("filled the disk with {bytes} bytes");
    let health = wait_for(T, "/healthz to report the full disk", || {
        let h = s.get("/healthz").expect(200);
        h.get("database").is_some().then_some(h)
    });
    assert_eq!(health["status"], "degraded", "{health}");
    let message = health["database"]["message"].as_str().unwrap();
    assert!(
        message.contains("disk full: ") && message.contains("fresa.db"),
        "the outage names the database and the full disk: {message}"
    );
    let metrics = s.get("/metrics").text;
    assert!(
        metrics.lines().any(|l| l == "fresa_database_up 0"),
        "{metrics}"
    );
}

#[test]
fn a_full_disk_is_an_outage_a_running_job_finishes_and_freeing_it_recovers_without_restart() {
    let (s, disk, m) = server_on_small_disk();
    let pid = s.pid().unwrap();
    let programs_before = s.program_files();
    let (job, run) = start_slow_job(&s, &m);
    wait_for(T, "the job to execute its first lines", || {
        (m.count_of(run) >= 20).then_some(())
    });
    let rss_before = rss_kib(pid);
    fill_and_wait_for_the_outage(&s, &disk);
    let at_outage = m.count_of(run);
    // A full disk still answers reads: the list comes from the store, the running job's run
    // from its machine.
    let listed = s.get(&format!("/api/v1/jobs?machine={}", m.id)).expect(200);
    assert_eq!(listed[0]["id"], job, "{listed}");
    assert_eq!(listed[0]["state"], "running", "{listed}");

    // Nothing new is taken: an upload is refused before a byte is written, new motion too.
    let msg = s
        .post_bytes(
            &format!("/api/v1/jobs?machine={}&name=late", m.id),
            "G1 X1 F600\n",
        )
        .expect_error(503, "database_unavailable");
    assert!(msg.contains("disk full"), "{msg}");
    assert!(s.upload_temp_files().is_empty(), "{:?}", s.program_files());
    let msg = s
        .jog(m.id, "X", 1.0)
        .expect_error(503, "database_unavailable");
    assert!(msg.contains("disk full"), "{msg}");

    // The running job goes on to its end with the disk still full.
    let mut rss_peak = rss_before;
    wait_for(
        T,
        "the job to run to its last line on the full disk",
        || {
            rss_peak = rss_peak.max(rss_kib(pid));
            (last_logged(&m, run) == LINES).then_some(())
        },
    );
    assert!(m.count_of(run) > at_outage, "lines ran during the outage");
    let st = s.wait_machine_state(m.id, "idle", T);
    assert!(st["job"].is_null(), "the run ended in memory: {st}");
    assert_eq!(
        s.get("/healthz").expect(200)["status"],
        "degraded",
        "the disk is still full"
    );
    let stored = s.job(job);
    assert_eq!(
        stored["state"], "running",
        "the end waits in memory: {stored}"
    );
    assert!(stored["line"].as_i64().unwrap() < LINES, "{stored}");

    // Room again: the store recovers by itself and the kept writes land in order.
    disk.free();
    let freed = Instant::now();
    let h = wait_for(T, "/healthz ok again", || {
        let h = s.get("/healthz").expect(200);
        (h["status"] == "ok").then_some(h)
    });
    let recovered = freed.elapsed();
    assert!(h.get("database").is_none(), "{h}");
    let j = s.wait_job_state(job, "completed", T);
    eprintln!(
        "disk freed -> store up in {} ms, run completed in {} ms; RSS {rss_before} KiB before, {rss_peak} KiB at most while full",
        recovered.as_millis(),
        freed.elapsed().as_millis()
    );
    assert_eq!(j["run"]["id"], run, "{j}");
    assert_eq!(
        j["line"], LINES,
        "the stored line is the last executed one: {j}"
    );
    assert!(j["run"]["unstored_line"].is_null(), "{j}");
    assert_every_line_once(&m.executed(), run, LINES);
    assert_eq!(
        job_states(&s, job, "completed"),
        ["running", "completed"],
        "audit log of job {job}"
    );
    assert!(
        s.get("/metrics")
            .text
            .lines()
            .any(|l| l == "fresa_database_up 1"),
        "up again"
    );
    // The refused upload left nothing; uploads and motion work again.
    assert_eq!(
        s.program_files().len(),
        programs_before.len() + 1,
        "only the job's program: {:?}",
        s.program_files()
    );
    let spare = s.upload(m.id, "spare", "G1 X1 F600\n")["id"]
        .as_i64()
        .unwrap();
    s.job_action(spare, "start").expect(200);
    s.wait_job_state(spare, "completed", T);
    drop(s);
    drop(disk);
}

#[test]
fn a_restart_while_the_disk_is_full_needs_the_operator_to_confirm_the_line() {
    let (mut s, disk, m) = server_on_small_disk();
    let (job, run) = start_slow_job(&s, &m);
    wait_for(T, "the job to execute its first lines", || {
        (m.count_of(run) >= 20).then_some(())
    });
    fill_and_wait_for_the_outage(&s, &disk);
    let at_outage = last_logged(&m, run);
    // The machine records which run has lines the store could not take, beside the store.
    let record = disk.data.join(format!("unstored/machine-{}.json", m.id));
    wait_for(T, "the record of unstored lines", || {
        let text = std::fs::read_to_string(&record).unwrap_or_default();
        text.contains(&format!("\"run\":{run}")).then_some(())
    });
    wait_for(T, "lines run only in memory", || {
        (last_logged(&m, run) >= at_outage + 50).then_some(())
    });
    s.kill();
    let executed = last_logged(&m, run);
    assert!(executed < LINES, "killed mid-job");
    disk.free();
    s.spawn()
        .unwrap_or_else(|e| panic!("server did not restart: {e}"));

    let j = s.job(job);
    assert_eq!(j["state"], "interrupted", "{j}");
    let stored = j["line"].as_i64().unwrap();
    let unstored = j["run"]["unstored_line"]
        .as_i64()
        .unwrap_or_else(|| panic!("{j}"));
    assert!(
        stored < unstored && unstored <= executed,
        "stored {stored}, acknowledged in memory {unstored}, executed {executed}"
    );
    let events = s.events("types=job.state", Some(0));
    let got = events.until(T, "the interruption", |e| {
        e.job() == Some(job) && e.state() == Some("interrupted")
    });
    assert_eq!(
        got.last().unwrap().data["data"]["unstored_line"],
        unstored,
        "{:?}",
        got.last()
    );

    // No blind resume: the stored line is behind what ran.
    let msg = s
        .job_action(job, "resume")
        .expect_error(409, "line_unconfirmed");
    assert!(
        msg.contains(&format!("stored line {stored}"))
            && msg.contains(&format!("at least {unstored}"))
            && msg.contains("confirm_line"),
        "{msg}"
    );
    let resume_from = |line: i64| {
        s.send(
            s.req(reqwest::Method::POST, &format!("/api/v1/jobs/{job}/resume"))
                .json(&json!({ "confirm_line": line })),
        )
    };
    let msg = resume_from(unstored - 1).expect_error(422, "invalid_field");
    assert!(msg.contains("confirm_line"), "{msg}");
    assert_eq!(last_logged(&m, run), executed, "nothing moved");
    assert_eq!(s.job(job)["state"], "interrupted");

    // The operator checked the machine: its last executed line is the log's.
    let r = resume_from(executed).expect(200);
    assert!(
        matches!(r["state"].as_str(), Some("running" | "completed")),
        "{r}"
    );
    let j = s.wait_job_state(job, "completed", T);
    assert_eq!(j["line"], LINES, "{j}");
    assert!(j["run"]["unstored_line"].is_null(), "{j}");
    assert_every_line_once(&m.executed(), run, LINES);
    drop(s);
    drop(disk);
}

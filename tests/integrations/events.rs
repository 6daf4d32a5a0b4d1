//! Server-Sent Events: live job state and progress, replay after `Last-Event-ID` (also across a
//! restart), and the type and machine filters.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::{back_and_forth, Server, SseEvent};
use std::time::Duration;

const T: Duration = Duration::from_secs(60);

/// `(id, type)` of the persisted events in `events`.
fn persisted(events: &[SseEvent]) -> Vec<(i64, String)> {
    events
        .iter()
        .filter_map(|e| e.id.map(|id| (id, e.event.clone())))
        .collect()
}

#[test]
fn live_stream_shows_the_job_running_progressing_and_completed_and_replay_matches_it() {
    let mut s = Server::start();
    let all = s.events("", None);
    let jobs_only = s.events("types=job", None);

    // 40 lines of 1 mm at 600 mm/min at time scale 0.05: about 0.2 s, so progress shows.
    let m = s.sim("m", 0.05);
    let id = s.upload(m.id, "p", back_and_forth(40, 1.0, 600.0))["id"]
        .as_i64()
        .unwrap();
    s.job_action(id, "start").expect(200);

    let seen = all.until(T, "job.state completed", |e| {
        e.event == "job.state" && e.job() == Some(id) && e.state() == Some("completed")
    });
    // Every SSE event carries its type twice (event: and data.type) and persisted ones their id.
    for e in &seen {
        assert_eq!(e.data["type"], e.event.as_str(), "{e:?}");
        assert_eq!(e.data["id"].as_i64(), e.id, "{e:?}");
        assert!(e.data["time"].as_i64().is_some(), "{e:?}");
    }
    let kinds: Vec<&str> = seen
        .iter()
        .filter(|e| e.id.is_some())
        .map(|e| e.event.as_str())
        .collect();
    assert_eq!(
        kinds,
        ["machine.created", "job.created", "job.state", "job.state"],
        "persisted events, in order"
    );
    let states: Vec<&str> = seen
        .iter()
        .filter(|e| e.event == "job.state")
        .map(|e| e.state().unwrap())
        .collect();
    assert_eq!(states, ["running", "completed"]);
    let created = seen.iter().find(|e| e.event == "job.created").unwrap();
    assert_eq!(created.job(), Some(id));
    assert_eq!(created.data["data"]["lines"], 40);
    assert_eq!(created.data["actor"], "local");
    assert_eq!(created.data["machine"], m.id);
    let completed = seen.last().unwrap();
    assert_eq!(completed.data["data"]["line"], 40, "{completed:?}");
    // Status events are transient: no id.
    assert!(
        seen.iter()
            .filter(|e| e.event == "status")
            .all(|e| e.id.is_none()),
        "status events must not have ids"
    );

    // The `job` filter: only job.* events, with progress between running and completed, its
    // line never going backwards.
    let jseen = jobs_only.until(T, "job.state completed", |e| {
        e.event == "job.state" && e.state() == Some("completed")
    });
    assert!(
        jseen.iter().all(|e| e.event.starts_with("job.")),
        "{:?}",
        jseen.iter().map(|e| &e.event).collect::<Vec<_>>()
    );
    let running_at = jseen
        .iter()
        .position(|e| e.state() == Some("running"))
        .expect("running seen");
    let progress: Vec<i64> = jseen
        .iter()
        .filter(|e| e.event == "job.progress")
        .map(|e| e.data["data"]["line"].as_i64().unwrap())
        .collect();
    assert!(
        progress.windows(2).all(|w| w[0] <= w[1]),
        "progress went backwards: {progress:?}"
    );
    // Line 0 = running, nothing acknowledged yet (a status tick can fall before the first ack).
    assert!(
        progress.iter().all(|l| (0..=40).contains(l)),
        "{progress:?}"
    );
    assert!(
        jseen
            .iter()
            .take(running_at)
            .all(|e| e.event != "job.progress"),
        "progress before running"
    );

    // Replay after the first persisted event: exactly the persisted events seen live after it.
    let live = persisted(&seen);
    let (first_id, _) = live[0];
    let last_id = live.last().unwrap().0;
    let replay = s.events("", Some(first_id));
    let got = replay.until(T, "the last live id", |e| e.id == Some(last_id));
    assert_eq!(persisted(&got), live[1..].to_vec());
    // The same with ?after= (for clients that cannot set headers).
    let replay = s.events(&format!("after={first_id}"), None);
    let got = replay.until(T, "the last live id", |e| e.id == Some(last_id));
    assert_eq!(persisted(&got), live[1..].to_vec());

    // Replay with a type filter: only job.state, from the start of the log.
    let states = s.events("types=job.state", Some(0));
    let got = states.until(T, "the completed state", |e| e.id == Some(last_id));
    assert!(got.iter().all(|e| e.event == "job.state"), "{got:?}");
    assert_eq!(
        persisted(&got),
        live.iter()
            .filter(|(_, k)| k == "job.state")
            .cloned()
            .collect::<Vec<_>>()
    );

    // A malformed Last-Event-ID is refused.
    s.send(
        s.req(reqwest::Method::GET, "/api/v1/events")
            .header("Last-Event-ID", "yesterday"),
    )
    .expect_error(400, "invalid_header");

    // The event log is persistent: after a restart the same ids replay.
    s.restart_after_kill();
    let replay = s.events("", Some(first_id));
    let got = replay.until(T, "the last id before the restart", |e| {
        e.id == Some(last_id)
    });
    assert_eq!(persisted(&got), live[1..].to_vec());
}

#[test]
fn machine_filter_only_shows_that_machines_events() {
    let s = Server::start();
    let a = s.sim("a", 0.0);
    let b = s.sim("b", 0.0);
    let ja = s.upload(a.id, "ja", "G0 X1\nG0 X0\n")["id"]
        .as_i64()
        .unwrap();
    let jb = s.upload(b.id, "jb", "G0 Y1\nG0 Y0\n")["id"]
        .as_i64()
        .unwrap();
    s.job_action(jb, "start").expect(200);
    s.wait_job_state(jb, "completed", T);
    s.job_action(ja, "start").expect(200);
    s.wait_job_state(ja, "completed", T);

    let only_a = s.events(&format!("machine={}", a.id), Some(0));
    let got = only_a.until(T, "job a completed", |e| {
        e.job() == Some(ja) && e.state() == Some("completed")
    });
    assert!(
        got.iter().all(|e| e.data["machine"] == a.id),
        "events of another machine: {got:?}"
    );
    let kinds: Vec<String> = persisted(&got).into_iter().map(|(_, k)| k).collect();
    assert!(kinds.contains(&"machine.created".to_string()), "{kinds:?}");
    assert!(kinds.contains(&"job.created".to_string()), "{kinds:?}");
}

/// With instant motion a job can end before the request that started it has recorded
/// `running`. The persisted job.state events of a run must still end with its final state, or an
/// SSE client is left believing the job still runs.
/// A filter that can never match is refused, naming what is wrong, instead of a stream that
/// stays silent forever; groups and exact types are accepted.
#[test]
fn unknown_types_and_machines_are_refused_not_followed_in_silence() {
    let s = Server::start();
    let msg = s
        .get("/api/v1/events?types=job,bogus")
        .expect_error(400, "invalid_query");
    assert!(msg.contains("\"bogus\"") && msg.contains("types"), "{msg}");
    let msg = s
        .get("/api/v1/events?machine=99")
        .expect_error(404, "unknown_machine");
    assert!(msg.contains("99"), "{msg}");
    let m = s.sim("m", 0.0);
    let stream = s.events(
        &format!("types=job,machine.jog,status&machine={}", m.id),
        None,
    );
    s.jog(m.id, "X", 1.0).expect(200);
    stream.until(T, "the jog event", |e| e.event == "machine.jog");
}

#[test]
fn job_state_events_of_instant_jobs_end_with_the_final_state() {
    let s = Server::start();
    let m = s.sim("m", 0.0);
    let mut last_id = 0;
    let mut ids = Vec::new();
    for i in 0..10 {
        let id = s.upload(m.id, &format!("j{i}"), "G0 X1\n")["id"]
            .as_i64()
            .unwrap();
        s.job_action(id, "start").expect(200);
        s.wait_job_state(id, "completed", T);
        s.wait_machine_state(m.id, "idle", T);
        ids.push(id);
    }
    // Wait until the last job's persisted events are all in (two job.state each).
    let states = s.events("types=job.state", Some(0));
    let got = states.until(T, "20 job.state events", |e| {
        if e.id.is_some() {
            last_id += 1;
        }
        last_id == 20
    });
    for id in ids {
        let seq: Vec<&str> = got
            .iter()
            .filter(|e| e.job() == Some(id))
            .map(|e| e.state().unwrap())
            .collect();
        // `running` is recorded before the backend is told to start, so even an instant run
        // shows exactly this sequence.
        assert_eq!(seq, ["running", "completed"], "job {id}");
    }
}

/// A quiet stream gets a keep-alive comment (`:` and a blank line) every `sse_keepalive_secs`,
/// and frames that come meanwhile go out whole: proxies and clients see it alive.
#[test]
fn a_quiet_stream_gets_keep_alive_comments_between_its_events() {
    use std::io::{Read, Write};
    let s = Server::start_with_config("sse_keepalive_secs = 1\n");
    let port: u16 = s.base.rsplit(':').next().unwrap().parse().unwrap();
    let mut c = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    // Only machine.created events: nothing else in this test makes one after the first.
    c.write_all(b"GET /api/v1/events?types=machine.created HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        .unwrap();
    c.set_read_timeout(Some(T)).unwrap();
    let mut got = Vec::new();
    let mut buf = [0u8; 4096];
    let mut read_until = |got: &mut Vec<u8>, what: &str, done: &dyn Fn(&str) -> bool| {
        while !done(&String::from_utf8_lossy(got)) {
            let n = c
                .read(&mut buf)
                .unwrap_or_else(|e| panic!("waiting for {what}: {e}"));
            assert!(n > 0, "the stream closed waiting for {what}");
            got.extend_from_slice(&buf[..n]);
        }
    };
    read_until(&mut got, "two keep-alives", &|t| {
        t.matches(":\n\n").count() >= 2
    });
    let text = String::from_utf8_lossy(&got).into_owned();
    assert!(text.starts_with("HTTP/1.1 200"), "{text}");
    assert!(text.contains("text/event-stream"), "{text}");
    // An event between keep-alives comes out as its own whole frame, then the comments go on
    // (the body is chunked: a comment after the frame is its own chunk).
    let m = s.sim("m", 0.0);
    read_until(
        &mut got,
        "the machine.created frame and a keep-alive after it",
        &|t| {
            t.find("event: machine.created")
                .is_some_and(|i| t[i..].contains(":\n\n"))
        },
    );
    let text = String::from_utf8_lossy(&got).into_owned();
    let frame = &text[text.find("event: machine.created").unwrap()..];
    assert!(frame.contains("\"name\":\"m\""), "{frame}");
    assert!(frame.contains(&format!("\"machine\":{}", m.id)), "{frame}");
}

//! Event log retention: routine events (jogs) are cut to `event_retention_count` while the audit
//! (machine created, part zero) stays; a replay that starts before the cut is told `resync`
//! first and then gets what remains; pruning runs in the background and at start-up.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::{wait_for, Opts, Server, SseEvent};
use std::time::Duration;

const T: Duration = Duration::from_secs(60);

/// Replays the whole log (`Last-Event-ID: 0`) up to the `machine.part_zero` the test records
/// last.
fn replay_all(s: &Server) -> Vec<SseEvent> {
    s.events("", Some(0))
        .until(T, "machine.part_zero", |e| e.event == "machine.part_zero")
}

fn jog_ids(events: &[SseEvent]) -> Vec<i64> {
    events
        .iter()
        .filter(|e| e.event == "machine.jog")
        .map(|e| e.id.expect("persisted events carry an id"))
        .collect()
}

#[test]
fn a_replay_across_the_retention_cut_gets_resync_then_what_remains() {
    let mut s = Server::unstarted(Opts::default());
    s.write_config("event_retention_count = 3\nevent_prune_interval_secs = 1\n");
    s.spawn().unwrap();
    let live = s.events("", None);
    let m = s.sim("m", 0.0);
    for _ in 0..10 {
        s.jog(m.id, "X", 1.0).expect(200);
    }
    s.post_empty(&format!("/api/v1/machines/{}/part-zero", m.id))
        .expect(201);
    let recorded = live.until(T, "machine.part_zero", |e| e.event == "machine.part_zero");
    let jogs = jog_ids(&recorded);
    assert_eq!(jogs.len(), 10, "{recorded:?}");
    let created = recorded
        .iter()
        .find(|e| e.event == "machine.created")
        .and_then(|e| e.id)
        .expect("machine.created recorded");

    // The background pass (every second here) cuts the jogs to the newest 3. Each pass that
    // deleted something logs a line; check the log again after each one.
    let mut passes_seen = 0;
    let replay = wait_for(T, "the jogs pruned to the newest 3", || {
        let passes = s.log().matches("event log pruned by retention").count();
        if passes == passes_seen {
            return None;
        }
        passes_seen = passes;
        let r = replay_all(&s);
        (jog_ids(&r) == jogs[7..]).then_some(r)
    });

    // The gap is announced before anything is replayed, saying where it ends...
    let first = &replay[0];
    assert_eq!(first.event, "resync", "{replay:?}");
    assert_eq!(first.data["after"], 0, "{first:?}");
    let pruned_through = first.data["pruned_through"].as_i64().unwrap();
    assert_eq!(pruned_through, jogs[6], "{first:?}");
    // ...then what remains: the audit event from before the cut, the newest jogs, the part zero.
    let kinds: Vec<&str> = replay[1..].iter().map(|e| e.event.as_str()).collect();
    assert_eq!(
        kinds,
        [
            "machine.created",
            "machine.jog",
            "machine.jog",
            "machine.jog",
            "machine.part_zero"
        ],
        "{replay:?}"
    );
    assert_eq!(replay[1].id, Some(created));

    // A client that already has everything up to the cut has no gap: no resync.
    let after_cut = s.events("", Some(pruned_through));
    let e = after_cut.next(T).expect("replay after the cut");
    assert_eq!((e.event.as_str(), e.id), ("machine.jog", Some(jogs[7])));
    // The same through `?after=` (clients that cannot set headers).
    let by_query = s.events("after=1", None);
    let e = by_query.next(T).expect("replay after id 1");
    assert_eq!(e.event, "resync", "{e:?}");
    assert_eq!(e.data["after"], 1, "{e:?}");

    // Start-up prunes before serving: with the count down to 1 and no background pass
    // within the test, the first replay already has a single jog.
    assert!(s.terminate().success(), "{}", s.log());
    s.write_config("event_retention_count = 1\nevent_prune_interval_secs = 86400\n");
    s.spawn().unwrap();
    let replay = replay_all(&s);
    assert_eq!(replay[0].event, "resync", "{replay:?}");
    assert_eq!(replay[0].data["pruned_through"], jogs[8], "{replay:?}");
    assert_eq!(jog_ids(&replay), [jogs[9]], "{replay:?}");
    assert!(replay.iter().any(|e| e.event == "machine.created"));
    assert!(
        s.log().contains("pruned=2"),
        "start-up pass not logged:\n{}",
        s.log()
    );
}

#[test]
fn retention_settings_are_checked_at_start() {
    let mut s = Server::unstarted(Opts::default());
    s.write_config("event_retention_days = 90\naudit_retention_days = 7\n");
    let err = s
        .spawn()
        .expect_err("audit shorter than routine must be refused");
    assert!(
        err.contains("audit_retention_days") && err.contains("event_retention_days"),
        "{err}"
    );
    s.write_config("event_retention_count = 0\n");
    let err = s.spawn().expect_err("a zero count must be refused");
    assert!(err.contains("event_retention_count"), "{err}");
    // The defaults start.
    s.write_config("");
    s.spawn().unwrap();
    s.get("/api/v1/machines").expect(200);
}

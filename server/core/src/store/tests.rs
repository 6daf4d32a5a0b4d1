#![allow(clippy::unwrap_used, clippy::expect_used)]
use super::*;
use fresa_plugin_api::contract::AxisValues;

/// A store for one test, on SQLite (a file in a temporary directory, removed on drop) or on a
/// fresh database of the test PostgreSQL server.
struct Scratch {
    store: Store,
    dir: Option<std::path::PathBuf>,
}

impl Drop for Scratch {
    fn drop(&mut self) {
        if let Some(dir) = &self.dir {
            std::fs::remove_dir_all(dir).ok();
        }
    }
}

async fn sqlite_store() -> Scratch {
    let dir = std::env::temp_dir().join(format!(
        "fresa-store-{}-{}",
        std::process::id(),
        rand::random::<u64>()
    ));
    std::fs::create_dir_all(&dir).unwrap();
    Scratch {
        store: Store::open(&dir.join("t.db")).await.unwrap(),
        dir: Some(dir),
    }
}

async fn postgres_store() -> Scratch {
    let url = super::test_postgres::fresh_database().await;
    Scratch {
        store: Store::connect(&url).await.unwrap(),
        dir: None,
    }
}

/// Runs each listed `async fn NAME(s: &Store)` as two tests, `NAME::sqlite` and
/// `NAME::postgres`: the store behaves the same on both.
macro_rules! on_both {
    ($($name:ident),* $(,)?) => {$(
        mod $name {
            #[tokio::test]
            async fn sqlite() {
                let s = super::sqlite_store().await;
                assert_eq!(s.store.dialect(), super::Dialect::Sqlite);
                super::$name(&s.store).await
            }
            #[tokio::test]
            async fn postgres() {
                let s = super::postgres_store().await;
                assert_eq!(s.store.dialect(), super::Dialect::Postgres);
                super::$name(&s.store).await
            }
        }
    )*};
}

on_both!(
    second_start_on_a_busy_machine_is_refused,
    concurrent_starts_on_one_machine_let_exactly_one_win,
    restart_marks_active_runs_interrupted_and_keeps_last_line,
    nodes_share_machines_secret_and_programs,
    latest_runs_gives_each_jobs_newest_run,
    a_run_keeps_the_part_zero_it_started_with,
    expired_and_revoked_tokens_are_not_found,
    event_ids_rise_and_replay_in_order,
    pruning_keeps_audit_events_and_records_the_cut,
    tool_tables_are_per_machine_and_replaced_whole,
    a_transaction_the_database_ended_itself_leaves_the_pool_usable,
    unstored_lines_mark_a_run_until_the_operator_confirms_its_line,
    counters_and_part_lines_only_rise_and_maintenance_is_raised_once,
);

/// Issue 23: start-up marks a run the previous process could not store all acknowledged lines
/// of; the operator's confirmed line raises `last_line` and clears the mark; finished runs are
/// never marked.
async fn unstored_lines_mark_a_run_until_the_operator_confirms_its_line(s: &Store) {
    let (m, j) = machine_with_job(s, 62).await;
    let run = s.start_run(j, m).await.unwrap().unwrap();
    assert_eq!(run.unstored_line, None);
    s.ack_line(run.id, 7).await.unwrap();
    assert!(s.mark_unstored_line(run.id, 40).await.unwrap());
    assert!(s.mark_unstored_line(run.id, 30).await.unwrap()); // never lowered
    let r = s.run(run.id).await.unwrap().unwrap();
    assert_eq!((r.last_line, r.unstored_line), (7, Some(40)));
    let confirmed = s.confirm_run_line(run.id, 45).await.unwrap().unwrap();
    assert_eq!((confirmed.last_line, confirmed.unstored_line), (45, None));
    // An unreadable record marks the machine's active runs at their stored line.
    assert_eq!(s.mark_unstored_active_runs(m).await.unwrap(), 1);
    assert_eq!(
        s.run(run.id).await.unwrap().unwrap().unstored_line,
        Some(45)
    );
    s.transition_run(run.id, &[RunState::Running], RunState::Completed, None)
        .await
        .unwrap()
        .unwrap();
    s.confirm_run_line(run.id, 62).await.unwrap();
    assert!(!s.mark_unstored_line(run.id, 62).await.unwrap());
    assert_eq!(s.run(run.id).await.unwrap().unwrap().unstored_line, None);
}

/// Runs `sql` on every connection the pool may hand out (it holds at most 8): for per-connection
/// settings such as SQLite's `max_page_count`.
async fn on_every_connection(s: &Store, sql: &str) {
    let mut held = Vec::new();
    for _ in 0..8 {
        let mut c = s.pool().acquire().await.unwrap();
        sqlx::Executor::execute(&mut *c, sql).await.unwrap();
        held.push(c);
    }
}

/// A few ordinary writes, each in its own transaction: all must succeed.
async fn writes_succeed(s: &Store, m: i64, what: &str) {
    for i in 0..20 {
        s.insert_part_zero(
            m,
            AxisValues::default(),
            "test",
            "t",
            Some(&format!("{what} {i}")),
        )
        .await
        .unwrap_or_else(|e| panic!("write {i} {what}: {e}"));
    }
}

/// Issue 23: a write that fails so that the database itself ends the transaction (SQLite rolls
/// back the whole transaction on a full disk) must not leave the pooled connection believing it
/// is still inside one; that connection refused every later `BEGIN IMMEDIATE` ("attempted to
/// call begin_with at non-zero transaction depth"). On PostgreSQL a failed statement aborts the
/// transaction instead; the pool must be as usable afterwards.
async fn a_transaction_the_database_ended_itself_leaves_the_pool_usable(s: &Store) {
    let (m, _) = machine_with_job(s, 1).await;
    for _ in 0..3 {
        let mut tx = s.begin().await.unwrap();
        // A second machine named "m": SQLite's OR ROLLBACK ends the transaction in the engine,
        // as a full disk does; PostgreSQL aborts it.
        let e = sqlx::query(s.pick(
            "INSERT OR ROLLBACK INTO machines (name, backend, config, created_at) VALUES ('m', 'x', '{}', 0)",
            "INSERT INTO machines (name, backend, config, created_at) VALUES ('m', 'x', '{}', 0)",
        ))
        .execute(&mut *tx)
        .await
        .unwrap_err();
        assert!(is_unique_violation(&e), "{e}");
        drop(tx);
    }
    writes_succeed(s, m, "after a transaction ended by the database").await;
}

/// Issue 23, with a genuine SQLITE_FULL from the engine (`max_page_count` caps the file as a
/// full disk would; it fails the statement, where a full disk fails the commit and ends the
/// transaction, the case above): the error marks the store down as "disk full", a probe write
/// ends the outage once there is room again, and writes succeed without a restart.
#[tokio::test]
async fn a_full_sqlite_database_is_an_outage_and_recovers_when_there_is_room() {
    let scratch = sqlite_store().await;
    let s = &scratch.store;
    let (m, _) = machine_with_job(s, 1).await;
    let pages: i64 = sqlx::query_scalar("PRAGMA page_count")
        .fetch_one(s.pool())
        .await
        .unwrap();
    on_every_connection(s, &format!("PRAGMA max_page_count = {pages}")).await;
    let big = "x".repeat(64 * 1024);
    let mut failed = None;
    for _ in 0..10 {
        let r = s
            .health()
            .guard(s.insert_part_zero(m, AxisValues::default(), "test", "t", Some(&big)))
            .await;
        if let Err(e) = r {
            failed = Some(e);
            break;
        }
    }
    let e = failed.expect("a write into a full database failed");
    assert_eq!(e.code, "database_unavailable", "{e}");
    match s.health().state() {
        DbState::Down { reason, .. } => assert!(reason.starts_with("disk full: "), "{reason}"),
        DbState::Up => panic!("a full database is an outage"),
    }
    on_every_connection(s, "PRAGMA max_page_count = 1073741823").await;
    s.health().probe(s).await;
    assert!(s.health().is_up(), "{:?}", s.health().state());
    writes_succeed(s, m, "after room was made").await;
}

async fn tool_tables_are_per_machine_and_replaced_whole(s: &Store) {
    use super::ToolRow;
    let tool = |n: i64, d: f64| ToolRow {
        tool: n,
        diameter_mm: d,
        length_mm: 1.5,
        description: format!("T{n}"),
    };
    let (a, _) = machine_with_job(s, 1).await;
    let b = s
        .insert_machine(
            "b",
            "sim-machine",
            &serde_json::json!({}),
            50.0,
            1000.0,
            300.0,
        )
        .await
        .unwrap();
    s.replace_tools(a, &[tool(1, 6.0), tool(2, 3.0)])
        .await
        .unwrap();
    s.upsert_tool(b, &tool(1, 10.0)).await.unwrap();
    s.upsert_tool(a, &tool(2, 4.0)).await.unwrap();
    assert_eq!(s.tools(a).await.unwrap(), vec![tool(1, 6.0), tool(2, 4.0)]);
    assert_eq!(s.tools(b).await.unwrap(), vec![tool(1, 10.0)]);
    s.replace_tools(a, &[tool(7, 2.0)]).await.unwrap();
    assert_eq!(s.tools(a).await.unwrap(), vec![tool(7, 2.0)]);
    assert!(s.delete_tool(a, 7).await.unwrap());
    assert!(!s.delete_tool(a, 7).await.unwrap());
    assert!(s.tools(a).await.unwrap().is_empty());
    assert_eq!(s.tools(b).await.unwrap().len(), 1);
}

async fn machine_with_job(s: &Store, lines: i64) -> (i64, i64) {
    let m = s
        .insert_machine(
            "m",
            "sim-machine",
            &serde_json::json!({}),
            50.0,
            1000.0,
            300.0,
        )
        .await
        .unwrap();
    let j = s
        .insert_job(NewJob {
            name: "a",
            machine_id: m,
            sha256: "x",
            size_bytes: 1,
            line_count: lines,
            analysis: None,
            source: "http",
        })
        .await
        .unwrap();
    (m, j)
}

async fn second_start_on_a_busy_machine_is_refused(s: &Store) {
    let (m, j) = machine_with_job(s, 1).await;
    let first = s.start_run(j, m).await.unwrap();
    assert!(first.is_ok());
    let second = s.start_run(j, m).await.unwrap();
    assert_eq!(second.err().map(|r| r.id), first.ok().map(|r| r.id));
}

/// Eight starts at once (eight connections, as eight nodes or clients would send them): the
/// transaction that checks "no active run" and inserts one is atomic on both databases.
async fn concurrent_starts_on_one_machine_let_exactly_one_win(s: &Store) {
    let (m, j) = machine_with_job(s, 1).await;
    let starts = (0..8).map(|_| {
        let s = s.clone();
        tokio::spawn(async move { s.start_run(j, m).await.unwrap() })
    });
    let mut won = Vec::new();
    let mut refused = Vec::new();
    for t in starts {
        match t.await.unwrap() {
            Ok(run) => won.push(run.id),
            Err(busy) => refused.push(busy.id),
        }
    }
    assert_eq!(won.len(), 1, "exactly one start wins: {won:?}");
    assert!(
        refused.iter().all(|id| *id == won[0]),
        "{refused:?} vs {won:?}"
    );
    // A late event moving the winner twice: the compare-and-set lets one through.
    let (a, b) = tokio::join!(
        s.transition_run(won[0], &[RunState::Running], RunState::Completed, None),
        s.transition_run(won[0], &[RunState::Running], RunState::Failed, Some("x")),
    );
    let moved = [a.unwrap(), b.unwrap()];
    assert_eq!(moved.iter().filter(|r| r.is_some()).count(), 1, "{moved:?}");
}

async fn event_ids_rise_and_replay_in_order(s: &Store) {
    assert_eq!(s.last_event_id().await.unwrap(), 0);
    let mut ids = Vec::new();
    for i in 0..5 {
        let row = s
            .append_event(
                "job.state",
                Some(1),
                Some("local"),
                &format!("{{\"i\":{i}}}"),
            )
            .await
            .unwrap();
        ids.push(row.id);
    }
    assert!(ids.windows(2).all(|w| w[0] < w[1]), "{ids:?}");
    assert_eq!(s.last_event_id().await.unwrap(), ids[4]);
    let after: Vec<i64> = s
        .events_after(ids[1], 10)
        .await
        .unwrap()
        .into_iter()
        .map(|e| e.id)
        .collect();
    assert_eq!(after, ids[2..]);
    assert_eq!(s.event_count().await.unwrap(), 5);
}

async fn pruning_keeps_audit_events_and_records_the_cut(s: &Store) {
    for kind in ["machine.jog", "job.state", "machine.jog", "machine.jog"] {
        s.append_event(kind, None, None, "{}").await.unwrap();
    }
    let audit = ["job.state"];
    // Routine events up to the count cut (keep the newest one) go; the audit one stays.
    let cut = s.routine_event_count_cut(&audit, 1).await.unwrap();
    assert_eq!(cut, Some(3));
    let gone = s.prune_events_batch(&audit, 0, cut, 0, 1000).await.unwrap();
    assert_eq!(gone, 2);
    let left: Vec<String> = s
        .events_after(0, 10)
        .await
        .unwrap()
        .into_iter()
        .map(|e| e.kind)
        .collect();
    assert_eq!(left, ["job.state", "machine.jog"]);
    assert_eq!(s.events_pruned_through().await.unwrap(), 3);
    // Ids are never reused after a prune.
    assert_eq!(s.last_event_id().await.unwrap(), 4);
}

/// Both dialects have the same migrations (version and name): adding one to only one side
/// fails here.
#[test]
fn migrations_are_kept_in_step_on_both_databases() {
    let versions = |m: &sqlx::migrate::Migrator| -> Vec<(i64, String)> {
        m.iter()
            .map(|m| (m.version, m.description.to_string()))
            .collect()
    };
    let sqlite = sqlx::migrate!("../../migrations");
    let postgres = sqlx::migrate!("../../migrations/postgres");
    assert_eq!(versions(&sqlite), versions(&postgres));
    assert!(versions(&sqlite).len() >= 4);
}

async fn restart_marks_active_runs_interrupted_and_keeps_last_line(s: &Store) {
    // Two nodes share the store; node "a" restarts.
    let (m, j) = machine_with_job(&s.clone().for_node("a"), 9).await;
    let other = s
        .clone()
        .for_node("b")
        .insert_machine(
            "on-b",
            "sim-machine",
            &serde_json::json!({}),
            50.0,
            1000.0,
            300.0,
        )
        .await
        .unwrap();
    assert_eq!(
        s.machine(other).await.unwrap().unwrap().node.as_deref(),
        Some("b")
    );
    let j_other = s
        .insert_job(NewJob {
            name: "b",
            machine_id: other,
            sha256: "00",
            size_bytes: 1,
            line_count: 1,
            analysis: None,
            source: "http",
        })
        .await
        .unwrap();
    let run_other = s.start_run(j_other, other).await.unwrap().unwrap();
    let run = s.start_run(j, m).await.unwrap().unwrap();
    s.ack_line(run.id, 5).await.unwrap();
    s.ack_line(run.id, 3).await.unwrap(); // never backwards
    let rows = s.interrupt_active_runs_of("a").await.unwrap();
    assert_eq!(rows.len(), 1);
    assert_eq!(rows[0].id, run.id);
    assert_eq!(rows[0].state, RunState::Interrupted);
    assert_eq!(rows[0].last_line, 5);
    // Node b's run is still running: it is b's to end.
    assert_eq!(
        s.run(run_other.id).await.unwrap().unwrap().state,
        RunState::Running
    );
    // A finished run cannot be moved by a late event.
    assert!(s
        .transition_run(run.id, &[RunState::Running], RunState::Completed, None)
        .await
        .unwrap()
        .is_none());
}

/// What nodes share: registration and heartbeats, claiming machines made before nodes, moving
/// a machine (not while it runs), one secret, programs by content.
async fn nodes_share_machines_secret_and_programs(s: &Store) {
    s.register_node("a", "http://127.0.0.1:1", "0.1.0")
        .await
        .unwrap();
    s.register_node("b", "http://127.0.0.1:2", "0.1.0")
        .await
        .unwrap();
    s.node_heartbeat("a", r#"{"1":{"state":"idle"}}"#)
        .await
        .unwrap();
    let nodes = s.list_nodes().await.unwrap();
    assert_eq!(
        nodes.iter().map(|n| n.name.as_str()).collect::<Vec<_>>(),
        ["a", "b"]
    );
    assert_eq!(nodes[0].machines, r#"{"1":{"state":"idle"}}"#);
    // Ages come from the database's clock: just written, so about zero.
    assert!((-1000..60_000).contains(&nodes[0].age_ms), "{nodes:?}");
    // Re-registering (a restart) keeps one row and takes the new URL.
    s.register_node("a", "http://127.0.0.1:3", "0.1.0")
        .await
        .unwrap();
    assert_eq!(
        s.node_row("a").await.unwrap().unwrap().url,
        "http://127.0.0.1:3"
    );

    let old = s
        .insert_machine(
            "old",
            "sim-machine",
            &serde_json::json!({}),
            50.0,
            1000.0,
            300.0,
        )
        .await
        .unwrap();
    assert_eq!(s.machine(old).await.unwrap().unwrap().node, None);
    assert_eq!(s.claim_unowned("a").await.unwrap(), 1);
    assert_eq!(s.claim_unowned("b").await.unwrap(), 0);
    assert_eq!(
        s.machine(old).await.unwrap().unwrap().node.as_deref(),
        Some("a")
    );

    let (m, j) = machine_with_job(&s.clone().for_node("a"), 3).await;
    let run = s.start_run(j, m).await.unwrap().unwrap();
    assert!(
        !s.set_machine_node(m, "b").await.unwrap(),
        "moved while running"
    );
    s.transition_run(run.id, &[RunState::Running], RunState::Completed, None)
        .await
        .unwrap()
        .unwrap();
    assert!(s.set_machine_node(m, "b").await.unwrap());
    assert_eq!(
        s.machine(m).await.unwrap().unwrap().node.as_deref(),
        Some("b")
    );

    let secret = s.node_secret().await.unwrap();
    assert_eq!(secret.len(), 64);
    assert_eq!(
        s.node_secret().await.unwrap(),
        secret,
        "one secret for all nodes"
    );

    let program: Vec<u8> = (0..600_000u32)
        .map(|i| b"G1 X1\n"[(i % 6) as usize])
        .collect();
    let read_back = |sha: &'static str| async move {
        let mut all = Vec::new();
        let mut seq = 0;
        while let Some(chunk) = s.program_chunk(sha, seq).await.unwrap() {
            all.extend(chunk);
            seq += 1;
        }
        (seq, all)
    };
    assert!(!s.has_program("abc").await.unwrap());
    s.save_program("abc", &program[..]).await.unwrap();
    s.save_program("abc", &program[..]).await.unwrap(); // stored once
    assert_eq!(read_back("abc").await, (3, program));
    s.save_program("empty", &b""[..]).await.unwrap();
    assert!(s.has_program("empty").await.unwrap());
    assert_eq!(read_back("empty").await, (1, Vec::new()));
}

async fn latest_runs_gives_each_jobs_newest_run(s: &Store) {
    let (m, j1) = machine_with_job(s, 3).await;
    let j2 = s
        .insert_job(NewJob {
            name: "b",
            machine_id: m,
            sha256: "y",
            size_bytes: 1,
            line_count: 1,
            analysis: None,
            source: "http",
        })
        .await
        .unwrap();
    let first = s.start_run(j1, m).await.unwrap().unwrap();
    s.transition_run(first.id, &[RunState::Running], RunState::Cancelled, None)
        .await
        .unwrap();
    let second = s.start_run(j1, m).await.unwrap().unwrap();
    let mut runs = s.latest_runs(&[j1, j2]).await.unwrap();
    runs.sort_by_key(|r| r.job_id);
    assert_eq!(runs.len(), 1, "job {j2} has no run");
    assert_eq!((runs[0].job_id, runs[0].id), (j1, second.id));
    assert!(s.latest_runs(&[]).await.unwrap().is_empty());
}

async fn a_run_keeps_the_part_zero_it_started_with(s: &Store) {
    let (m, j) = machine_with_job(s, 3).await;
    let run = s.start_run(j, m).await.unwrap().unwrap();
    assert_eq!(s.run_part_zero(run.id).await.unwrap(), None);
    let zero = AxisValues {
        x: -400.0,
        y: 0.5,
        z: -30.0,
        a: 0.0,
    };
    s.set_run_part_zero(run.id, zero).await.unwrap();
    assert_eq!(s.run_part_zero(run.id).await.unwrap(), Some(zero));
    // The run row itself still reads (the new column is not in RunRow).
    assert_eq!(s.run(run.id).await.unwrap().unwrap().id, run.id);
    assert!(s.latest_part_zero(m).await.unwrap().is_none());
    s.insert_part_zero(m, zero, "robot", "robot", None)
        .await
        .unwrap();
    let last = s.latest_part_zero(m).await.unwrap().unwrap();
    assert_eq!((last.source.as_str(), last.y), ("robot", 0.5));
}

#[test]
fn run_state_machine_never_leaves_a_final_state() {
    use RunState::*;
    for to in super::jobs::ALL_RUN_STATES {
        assert!(!Cancelled.can_move_to(to), "cancelled -> {to}");
        assert!(!Completed.can_move_to(to), "completed -> {to}");
    }
    assert!(Paused.can_move_to(Running));
    assert!(Interrupted.can_move_to(Running));
    assert!(!Running.can_move_to(Running));
    // The bulk writes follow the same rule: the SQL list of active states is `is_active`, and
    // every active state may become interrupted (start-up and shutdown interrupt them so).
    let active: Vec<String> = super::jobs::ALL_RUN_STATES
        .into_iter()
        .filter(|s| s.is_active())
        .map(|s| format!("'{s}'"))
        .collect();
    assert_eq!(
        super::jobs::ACTIVE_RUN_STATES,
        format!("({})", active.join(","))
    );
    for s in super::jobs::ALL_RUN_STATES
        .into_iter()
        .filter(|s| s.is_active())
    {
        assert!(s.can_move_to(Interrupted), "{s}");
    }
}

/// Migration 0004 makes token names unique; an older database with repeated names must
/// still migrate (the later repeats are renamed `NAME#ID`).
#[tokio::test]
async fn duplicate_token_names_survive_the_unique_name_migration() {
    use sqlx::migrate::Migrator;
    let dir = std::env::temp_dir().join(format!(
        "fresa-store-mig-{}-{}",
        std::process::id(),
        rand::random::<u64>()
    ));
    std::fs::create_dir_all(&dir).unwrap();
    let db = dir.join("old.db");
    let full = sqlx::migrate!("../../migrations");
    let old = Migrator {
        migrations: std::borrow::Cow::Owned(
            full.migrations
                .iter()
                .filter(|m| m.version < 4)
                .cloned()
                .collect(),
        ),
        ..Migrator::DEFAULT
    };
    {
        let pool = sqlx::SqlitePool::connect_with(
            sqlx::sqlite::SqliteConnectOptions::new()
                .filename(&db)
                .create_if_missing(true),
        )
        .await
        .unwrap();
        old.run(&pool).await.unwrap();
        for (name, hash) in [("ana", "h1"), ("ana", "h2"), ("bo", "h3")] {
            sqlx::query(
                "INSERT INTO tokens (name, role, hash, created_at) VALUES ($1, 'viewer', $2, 0)",
            )
            .bind(name)
            .bind(hash)
            .execute(&pool)
            .await
            .unwrap();
        }
        pool.close().await;
    }
    let s = Store::open(&db).await.unwrap();
    let names: Vec<String> = s
        .list_tokens()
        .await
        .unwrap()
        .into_iter()
        .map(|t| t.name)
        .collect();
    assert_eq!(names, ["ana", "ana#2", "bo"]);
    // The second "ana" still works under its new name.
    assert_eq!(
        &*s.token_by_hash("h2").await.unwrap().unwrap().name,
        "ana#2"
    );
    let e = s
        .insert_token("bo", "viewer", "h4", None)
        .await
        .unwrap_err();
    assert!(is_unique_violation(&e), "{e}");
    std::fs::remove_dir_all(dir).ok();
}

async fn expired_and_revoked_tokens_are_not_found(s: &Store) {
    s.insert_token("old", "admin", "h-old", Some(now_ms() - 1))
        .await
        .unwrap();
    s.insert_token("new", "admin", "h-new", Some(now_ms() + 60_000))
        .await
        .unwrap();
    assert!(s.token_by_hash("h-old").await.unwrap().is_none());
    assert!(s.token_by_hash("h-new").await.unwrap().is_some());
    // What the database just accepted is known without asking it again (reads use this for a
    // second); what it refused, or accepted longer ago than asked, is not.
    assert_eq!(
        &*s.token_accepted_within("h-new", 60_000).unwrap().name,
        "new"
    );
    assert!(s.token_accepted_within("h-new", 0).is_none());
    assert!(s.token_accepted_within("h-old", 60_000).is_none());
    assert!(s.token_accepted_within("h-none", 60_000).is_none());
    // The wall clock set back an hour: an acceptance "in the future" is not trusted.
    let hour_ago = now_ms() - 3_600_000;
    assert!(s
        .accepted_since("h-new", hour_ago - 60_000, hour_ago)
        .is_none());
    assert!(s
        .accepted_since("h-new", now_ms() - 60_000, now_ms())
        .is_some());
    assert_eq!(s.token_count().await.unwrap(), 1);
    let listed = s.list_tokens().await.unwrap();
    assert!(listed.iter().any(|t| t.name == "old" && t.expired));
    assert!(listed
        .iter()
        .any(|t| t.name == "new" && !t.expired && t.last_used.is_some()));
    assert!(s.revoke_token("new").await.unwrap());
    assert!(s.token_accepted_within("h-new", 60_000).is_none());
    assert!(!s.revoke_token("new").await.unwrap());
    assert!(s.token_by_hash("h-new").await.unwrap().is_none());
}

/// Paths that a URL would mangle reach SQLite intact: a space, `#`, `?`, `%` in a directory name.
#[tokio::test]
async fn a_database_path_with_url_characters_opens_and_is_that_file() {
    let dir = std::env::temp_dir().join(format!(
        "fresa store #1 ?x %20 {}-{}",
        std::process::id(),
        rand::random::<u64>()
    ));
    std::fs::create_dir_all(&dir).unwrap();
    let db = dir.join("fresa.db");
    let s = Store::open(&db).await.unwrap();
    s.insert_machine(
        "m",
        "sim-machine",
        &serde_json::json!({}),
        50.0,
        1000.0,
        300.0,
    )
    .await
    .unwrap();
    assert!(
        db.is_file(),
        "the store is the file asked for: {}",
        db.display()
    );
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn sqlite_urls_keep_windows_paths_whole() {
    assert_eq!(
        sqlite_url(std::path::Path::new(r"C:\ProgramData\Fresa\fresa.db")),
        "sqlite:C:%5CProgramData%5CFresa%5Cfresa.db?mode=rwc"
    );
    assert_eq!(
        sqlite_url(std::path::Path::new("/var/lib/fresa/fresa.db")),
        "sqlite:/var/lib/fresa/fresa.db?mode=rwc"
    );
}

/// Issue 24: during an outage a read is still tried, since a full or read-only disk answers
/// reads; one the store cannot answer is the outage's refusal, and no read ends the outage.
#[tokio::test]
async fn reads_are_tried_during_an_outage_and_refused_like_writes_when_they_fail() {
    let s = sqlite_store().await;
    let id = s
        .store
        .insert_machine(
            "m",
            "sim-machine",
            &serde_json::json!({}),
            50.0,
            1000.0,
            300.0,
        )
        .await
        .unwrap();
    let h = s.store.health();
    h.mark_down("disk full: test");
    let refused = h.guard(s.store.machine(id)).await.unwrap_err();
    assert_eq!(refused.code, "database_unavailable");
    let row = h.read(s.store.machine(id)).await.unwrap();
    assert_eq!(row.map(|r| r.name).as_deref(), Some("m"));
    // No answer within the ping timeout, or an outage's error: the refusal, naming the outage.
    let silent = h
        .read(std::future::pending::<sqlx::Result<()>>())
        .await
        .unwrap_err();
    assert_eq!(silent.code, "database_unavailable");
    assert!(silent.message.contains("disk full: test"), "{silent}");
    let lost = h
        .read(async { Err::<(), _>(sqlx::Error::PoolTimedOut) })
        .await
        .unwrap_err();
    assert_eq!(lost.code, "database_unavailable");
    // A statement's own failure stays its own.
    let own = h
        .read(async { Err::<(), _>(sqlx::Error::RowNotFound) })
        .await
        .unwrap_err();
    assert_eq!(own.code, "internal");
    assert!(!h.is_up(), "a read never ends an outage");
}

async fn counters_and_part_lines_only_rise_and_maintenance_is_raised_once(s: &Store) {
    use super::{CountersRow, PartFilter, PartRow};
    let (m, j) = machine_with_job(s, 10).await;
    let high = CountersRow {
        spindle_ms: 5000,
        motion_ms: 7000,
        distance_x: 12.5,
        jobs: 3,
        ..Default::default()
    };
    s.raise_counters(m, &high).await.unwrap();
    // A writer behind (a late retry, another node) cannot lower them.
    let low = CountersRow {
        spindle_ms: 1000,
        motion_ms: 9000,
        jobs: 1,
        ..Default::default()
    };
    s.raise_counters(m, &low).await.unwrap();
    let c = s.counters(m).await.unwrap().unwrap();
    assert_eq!(
        (c.spindle_ms, c.motion_ms, c.distance_x, c.jobs),
        (5000, 9000, 12.5, 3)
    );

    // Raised once per crossing until done.
    assert!(s.raise_maintenance_due(m, "lube").await.unwrap());
    assert!(!s.raise_maintenance_due(m, "lube").await.unwrap());
    s.maintenance_done(m, "lube", 1.5, "alice").await.unwrap();
    let marks = s.maintenance_marks(m).await.unwrap();
    assert_eq!((marks[0].done_value, marks[0].due_raised), (1.5, 0));
    assert_eq!(marks[0].done_by.as_deref(), Some("alice"));
    assert!(s.raise_maintenance_due(m, "lube").await.unwrap());

    // One record per run; its lines only rise; pages by (ended_at, id).
    let part = |run_id: i64, last_line: i64, ended_at: i64| PartRow {
        id: 0,
        run_id,
        job_id: j,
        machine_id: m,
        machine_name: "m".into(),
        node: None,
        program_name: "p.nc".into(),
        program_sha256: "x".into(),
        work_offset: "G54".into(),
        work_zero: None,
        part_zero: None,
        tool_table: "[]".into(),
        tool_table_sha256: "y".into(),
        operators: "[]".into(),
        confirmations: "[]".into(),
        outcome: "cancelled".into(),
        message: None,
        line_count: 10,
        from_line: None,
        last_line,
        lines_run: last_line,
        estimate_s: Some(1.0),
        actual_s: None,
        started_at: None,
        ended_at,
    };
    s.upsert_part(&part(1, 7, 100)).await.unwrap();
    s.upsert_part(&part(1, 6, 100)).await.unwrap();
    s.upsert_part(&part(2, 3, 100)).await.unwrap();
    s.upsert_part(&part(3, 3, 200)).await.unwrap();
    let all = s
        .parts(&PartFilter {
            limit: 10,
            ..Default::default()
        })
        .await
        .unwrap();
    let runs: Vec<i64> = all.iter().map(|p| p.run_id).collect();
    assert_eq!(runs, [3, 2, 1]);
    assert_eq!((all[2].last_line, all[2].lines_run), (7, 7));
    let after = s
        .parts(&PartFilter {
            machine: Some(m),
            before: Some((all[1].ended_at, all[1].id)),
            limit: 10,
            ..Default::default()
        })
        .await
        .unwrap();
    assert_eq!(after.iter().map(|p| p.run_id).collect::<Vec<_>>(), [1]);
    let window = s
        .parts(&PartFilter {
            job: Some(j),
            from: Some(150),
            to: Some(250),
            limit: 10,
            ..Default::default()
        })
        .await
        .unwrap();
    assert_eq!(window.iter().map(|p| p.run_id).collect::<Vec<_>>(), [3]);

    // The state in force at `from` and the changes after it.
    for (state, since) in [("idle", 10), ("cutting", 50), ("held", 90), ("idle", 120)] {
        s.insert_machine_state(m, state, since).await.unwrap();
    }
    let states = s.machine_states(m, 60, 120).await.unwrap();
    assert_eq!(
        states,
        [("cutting".to_string(), 50), ("held".to_string(), 90)]
    );
}

/// The SQLite schema and rows of the store at `path`, as the baseline file writes them:
/// every statement SQLite keeps (in the order it made them) and every row as an `INSERT`.
async fn sqlite_dump(path: &std::path::Path) -> String {
    let mut conn = {
        use sqlx::ConnectOptions;
        sqlx::sqlite::SqliteConnectOptions::new()
            .filename(path)
            .connect()
            .await
            .unwrap()
    };
    let mut out: Vec<String> = sqlx::query_scalar(
        "SELECT sql || ';' FROM sqlite_master WHERE sql IS NOT NULL AND name NOT LIKE 'sqlite_%' \
         AND name != '_sqlx_migrations' ORDER BY rowid",
    )
    .fetch_all(&mut conn)
    .await
    .unwrap();
    let tables: Vec<String> = sqlx::query_scalar(
        "SELECT name FROM sqlite_master WHERE type = 'table' AND name NOT LIKE 'sqlite_%' \
         AND name != '_sqlx_migrations' ORDER BY rowid",
    )
    .fetch_all(&mut conn)
    .await
    .unwrap();
    for t in tables {
        let columns: Vec<String> =
            sqlx::query_scalar(&format!("SELECT name FROM pragma_table_info('{t}')"))
                .fetch_all(&mut conn)
                .await
                .unwrap();
        let values = columns
            .iter()
            .map(|c| format!("quote({c})"))
            .collect::<Vec<_>>()
            .join(" || ',' || ");
        let rows: Vec<String> = sqlx::query_scalar(&format!(
            "SELECT 'INSERT INTO {t} VALUES(' || {values} || ');' FROM {t} ORDER BY rowid"
        ))
        .fetch_all(&mut conn)
        .await
        .unwrap();
        out.extend(rows);
    }
    format!(
        "-- Generated: see server/core/src/store/baseline.rs. Do not edit.\n\n{}\n",
        out.join("\n\n")
    )
}

/// A new store is made from the baseline (`migrations/baseline/sqlite.sql`, see `baseline`):
/// it must hold exactly what one made by running every migration holds, and record the same
/// migrations (with sqlx's checksums, so opening it again migrates nothing and fails nothing).
/// `FRESA_WRITE_BASELINE=1` rewrites the baseline from the migrations (then set
/// `baseline::VERSION` to the last one).
#[tokio::test]
async fn a_new_store_from_the_baseline_equals_one_from_every_migration() {
    let dir = std::env::temp_dir().join(format!(
        "fresa-baseline-{}-{}",
        std::process::id(),
        rand::random::<u64>()
    ));
    std::fs::create_dir_all(&dir).unwrap();
    let (chain, fresh) = (dir.join("chain.db"), dir.join("fresh.db"));
    Store::connect(&sqlite_url(&chain)).await.unwrap();
    if std::env::var_os("FRESA_WRITE_BASELINE").is_some() {
        let file = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../migrations/baseline/sqlite.sql"
        );
        std::fs::write(file, sqlite_dump(&chain).await).unwrap();
        let last = super::baseline::MIGRATOR.iter().map(|m| m.version).max();
        panic!("baseline rewritten: set baseline::VERSION to {last:?} and run again");
    }
    let s = Store::open(&fresh).await.unwrap();
    assert!(
        !dir.join("fresh.db.new").exists(),
        "the half-made file was left"
    );
    let (a, b) = (sqlite_dump(&chain).await, sqlite_dump(&fresh).await);
    assert_eq!(
        a, b,
        "a store from the baseline differs from one from the migrations: rewrite the baseline \
         (FRESA_WRITE_BASELINE=1, see this test)"
    );
    let applied = |s: Store| async move {
        sqlx::query_as::<_, (i64, Vec<u8>)>(
            "SELECT version, checksum FROM _sqlx_migrations ORDER BY version",
        )
        .fetch_all(&s.pool)
        .await
        .unwrap()
    };
    let expected: Vec<(i64, Vec<u8>)> = super::baseline::MIGRATOR
        .iter()
        .map(|m| (m.version, m.checksum.to_vec()))
        .collect();
    assert_eq!(applied(s.clone()).await, expected);
    assert_eq!(
        applied(Store::connect(&sqlite_url(&chain)).await.unwrap()).await,
        expected
    );
    // Opened again: nothing to migrate, nothing refused, and it works.
    drop(s);
    let again = Store::open(&fresh).await.unwrap();
    assert_eq!(applied(again.clone()).await, expected);
    assert!(again.list_machines().await.unwrap().is_empty());
    std::fs::remove_dir_all(&dir).ok();
}

/// A first start stopped while it made the store leaves `NAME.new` (and its WAL): the next
/// start removes it and makes the store anew.
#[tokio::test]
async fn a_half_made_store_is_replaced_at_the_next_start() {
    let dir = std::env::temp_dir().join(format!(
        "fresa-halfmade-{}-{}",
        std::process::id(),
        rand::random::<u64>()
    ));
    std::fs::create_dir_all(&dir).unwrap();
    let db = dir.join("fresa.db");
    std::fs::write(dir.join("fresa.db.new"), b"half a store").unwrap();
    std::fs::write(dir.join("fresa.db.new-wal"), b"half a log").unwrap();
    let s = Store::open(&db).await.unwrap();
    assert!(s.list_machines().await.unwrap().is_empty());
    assert!(!dir.join("fresa.db.new").exists());
    assert!(!dir.join("fresa.db.new-wal").exists());
    std::fs::remove_dir_all(&dir).ok();
}

/// The stored form of a secret is its SHA-256 in lowercase hex: databases made by earlier
/// versions hold tokens in this form, so it must never change.
#[test]
fn a_token_is_stored_as_its_sha256_in_lowercase_hex() {
    assert_eq!(
        TokenHash::of("abc").as_str(),
        "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
    );
}

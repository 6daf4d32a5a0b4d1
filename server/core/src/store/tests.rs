#![allow(clippy::unwrap_used, clippy::expect_used)]
use super::*;
use fresa_plugin_api::contract::AxisValues;

async fn store() -> (Store, std::path::PathBuf) {
    let dir = std::env::temp_dir().join(format!(
        "fresa-store-{}-{}",
        std::process::id(),
        rand::random::<u64>()
    ));
    std::fs::create_dir_all(&dir).unwrap();
    (Store::open(&dir.join("t.db")).await.unwrap(), dir)
}

async fn machine_with_job(s: &Store, lines: i64) -> (i64, i64) {
    let m = s
        .insert_machine("m", "sim-machine", &serde_json::json!({}), 50.0, 1000.0)
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

#[tokio::test]
async fn second_start_on_a_busy_machine_is_refused() {
    let (s, dir) = store().await;
    let (m, j) = machine_with_job(&s, 1).await;
    let first = s.start_run(j, m).await.unwrap();
    assert!(first.is_ok());
    let second = s.start_run(j, m).await.unwrap();
    assert_eq!(second.err().map(|r| r.id), first.ok().map(|r| r.id));
    std::fs::remove_dir_all(dir).ok();
}

#[tokio::test]
async fn restart_marks_active_runs_interrupted_and_keeps_last_line() {
    let (s, dir) = store().await;
    let (m, j) = machine_with_job(&s, 9).await;
    let run = s.start_run(j, m).await.unwrap().unwrap();
    s.ack_line(run.id, 5).await.unwrap();
    s.ack_line(run.id, 3).await.unwrap(); // never backwards
    let rows = s.interrupt_active_runs().await.unwrap();
    assert_eq!(rows.len(), 1);
    assert_eq!(rows[0].state, RunState::Interrupted);
    assert_eq!(rows[0].last_line, 5);
    // A finished run cannot be moved by a late event.
    assert!(s
        .transition_run(run.id, &[RunState::Running], RunState::Completed, None)
        .await
        .unwrap()
        .is_none());
    std::fs::remove_dir_all(dir).ok();
}

#[tokio::test]
async fn latest_runs_gives_each_jobs_newest_run() {
    let (s, dir) = store().await;
    let (m, j1) = machine_with_job(&s, 3).await;
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
    std::fs::remove_dir_all(dir).ok();
}

#[tokio::test]
async fn a_run_keeps_the_part_zero_it_started_with() {
    let (s, dir) = store().await;
    let (m, j) = machine_with_job(&s, 3).await;
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
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn run_state_machine_never_leaves_a_final_state() {
    use RunState::*;
    let all = [
        Queued,
        Running,
        Paused,
        Completed,
        Failed,
        Cancelled,
        Interrupted,
    ];
    for to in all {
        assert!(!Cancelled.can_move_to(to), "cancelled -> {to}");
        assert!(!Completed.can_move_to(to), "completed -> {to}");
    }
    assert!(Paused.can_move_to(Running));
    assert!(Interrupted.can_move_to(Running));
    assert!(!Running.can_move_to(Queued));
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
                "INSERT INTO tokens (name, role, hash, created_at) VALUES (?, 'viewer', ?, 0)",
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
    assert_eq!(s.token_by_hash("h2").await.unwrap().unwrap().name, "ana#2");
    let e = s
        .insert_token("bo", "viewer", "h4", None)
        .await
        .unwrap_err();
    assert!(is_unique_violation(&e), "{e}");
    std::fs::remove_dir_all(dir).ok();
}

#[tokio::test]
async fn expired_and_revoked_tokens_are_not_found() {
    let (s, dir) = store().await;
    s.insert_token("old", "admin", "h-old", Some(now_ms() - 1))
        .await
        .unwrap();
    s.insert_token("new", "admin", "h-new", Some(now_ms() + 60_000))
        .await
        .unwrap();
    assert!(s.token_by_hash("h-old").await.unwrap().is_none());
    assert!(s.token_by_hash("h-new").await.unwrap().is_some());
    assert_eq!(s.token_count().await.unwrap(), 1);
    let listed = s.list_tokens().await.unwrap();
    assert!(listed.iter().any(|t| t.name == "old" && t.expired));
    assert!(listed
        .iter()
        .any(|t| t.name == "new" && !t.expired && t.last_used.is_some()));
    assert!(s.revoke_token("new").await.unwrap());
    assert!(!s.revoke_token("new").await.unwrap());
    assert!(s.token_by_hash("h-new").await.unwrap().is_none());
    std::fs::remove_dir_all(dir).ok();
}

//! Start-up and shutdown of the whole [`App`]: the composition root, which is why it may use
//! every other module (and none uses it).

use crate::app::{App, SharedApp};
use crate::config::Settings;
use crate::datadir::{DataDirLock, LockError};
use crate::events::EventBus;
use crate::events::EventKind;
use crate::machine::{Machine, Machines};
use crate::plugins::Registry;
use crate::store::RunRow;
use std::sync::Arc;
use tokio_util::sync::CancellationToken;

#[derive(Debug, thiserror::Error)]
pub enum StartError {
    #[error("cannot create data directory {path}: {source}")]
    DataDir {
        path: std::path::PathBuf,
        source: std::io::Error,
    },
    #[error("cannot open database {database}: {source}")]
    Store {
        database: String,
        source: sqlx::Error,
    },
    #[error(
        "refusing to listen on {0}: it is not a loopback address and no API token exists. \
         Create one first with `fresa token create --role admin --name NAME`"
    )]
    NoTokens(std::net::SocketAddr),
    #[error("{0}")]
    Locked(#[from] LockError),
    #[error(
        "database {db} is empty (0 bytes) but {programs} holds {count} program(s): the store \
         was lost, and starting would forget every job, offset and token. Restore it: copy \
         your latest `fresa backup` file over {db}, remove {db}-wal and {db}-shm if present, \
         and start again (README: Backup and restore). To start with an empty store on \
         purpose, delete {db} first"
    )]
    EmptyDatabase {
        db: std::path::PathBuf,
        programs: std::path::PathBuf,
        count: usize,
    },
    #[error("cannot read the records of unstored acknowledged lines: {0}")]
    Unstored(String),
    /// The plugin loader's thread panicked or was cancelled (a plugin's own failure to load is
    /// logged and skipped by the loader, not this).
    #[error("loading the plugins failed: {0}")]
    PluginLoad(tokio::task::JoinError),
}

impl App {
    /// Opens the store, loads plugins, marks runs the last process left active as interrupted and
    /// starts a backend instance for every machine.
    pub async fn start(settings: Settings) -> Result<SharedApp, StartError> {
        std::fs::create_dir_all(settings.programs_dir()).map_err(|source| StartError::DataDir {
            path: settings.programs_dir(),
            source,
        })?;
        // Before the store is touched: a second server must not mark the first one's runs.
        let lock = DataDirLock::acquire(&settings.data_dir)?;
        remove_upload_leftovers(&settings.programs_dir());
        // A process of its own: it starts while the store opens.
        let pendant_sim = if settings.demo {
            crate::demo::start_pendant_sim()
        } else {
            None
        };
        // Loaded on a blocking thread while the store opens (migrations on a first start): the
        // two do not depend on each other, and each takes milliseconds.
        let plugin_dirs = settings.plugin_dirs.clone();
        let plugins = tokio::task::spawn_blocking(move || Registry::load(&plugin_dirs));
        let db = settings.database_label();
        if settings.database_url.is_none() {
            refuse_lost_database(&settings.db_path(), &settings.programs_dir())?;
        }
        let store = settings
            .open_store()
            .await
            .map_err(|source| StartError::Store {
                database: db.clone(),
                source,
            })?
            .for_node(&settings.node.name);
        let store_error = |source| StartError::Store {
            database: db.clone(),
            source,
        };
        let claimed = store
            .claim_unowned(&settings.node.name)
            .await
            .map_err(store_error)?;
        if claimed > 0 {
            tracing::info!(node = %settings.node.name, machines = claimed, "machines made before nodes now belong to this node");
        }
        let node_secret = store.node_secret().await.map_err(store_error)?;
        tracing::info!(database = %db, dialect = store.dialect_name(), "store ready");
        // Once before serving, so a log that grew while the retention was looser is cut back
        // before anyone replays it; bounded, so a huge backlog cannot hold up the start (the
        // background passes finish it).
        crate::events::prune_and_log(
            &store,
            &settings.event_retention,
            Some(std::time::Duration::from_secs(10)),
        )
        .await;
        let auth_required = !settings.loopback_only();
        if auth_required {
            let n = store
                .token_count()
                .await
                .map_err(|source| StartError::Store {
                    database: db.clone(),
                    source,
                })?;
            if n == 0 {
                return Err(StartError::NoTokens(settings.listen));
            }
        }
        let plugins = plugins.await.map_err(StartError::PluginLoad)?;
        if plugins.names().is_empty() {
            tracing::warn!(
                dirs = ?settings.plugin_dirs,
                "no plugins found; build them with `cargo build --workspace` or pass --plugin-dir"
            );
        } else {
            tracing::info!(plugins = ?plugins.names(), "plugins loaded");
        }
        let bus = EventBus::new(store.clone(), 4096);
        let shutdown = CancellationToken::new();
        // Before the machines start: their tasks read it to refuse new motion during an outage.
        store
            .health()
            .spawn_monitor(store.clone(), shutdown.clone());
        bus.spawn_delayed_writer(shutdown.clone());
        if let Some(url) = &settings.database_url {
            crate::events::spawn_tail(bus.clone(), url.clone(), shutdown.clone());
        }
        crate::events::spawn_pruner(
            store.clone(),
            settings.event_retention.clone(),
            shutdown.clone(),
        );
        let previews = crate::previews::Previews::new(settings.toolpath);
        let app = Arc::new(App {
            settings,
            store: store.clone(),
            bus: bus.clone(),
            plugins,
            machines: Machines::default(),
            pendants: Default::default(),
            shutdown,
            integrations: Default::default(),
            previews,
            queues: Default::default(),
            auth_required,
            node_secret,
            _lock: lock,
        });
        // Before they are interrupted, so the interruption says so.
        mark_unstored_runs(
            &store,
            &app.settings.data_dir.join(crate::machine::unstored::DIR),
        )
        .await
        .map_err(|e| match e {
            Ok(source) => StartError::Store {
                database: db.clone(),
                source,
            },
            Err(message) => StartError::Unstored(message),
        })?;
        for run in store
            .interrupt_active_runs_of(&app.settings.node.name)
            .await
            .map_err(|source| StartError::Store {
                database: db.clone(),
                source,
            })?
        {
            match run.unstored_line {
                Some(unstored) => tracing::warn!(
                    run = run.id,
                    job = run.job_id,
                    last_line = run.last_line,
                    unstored_line = unstored,
                    "run was interrupted by a restart while lines up to at least {unstored} were acknowledged but not stored: its stored line {} may be behind; check the machine and resume with POST /api/v1/jobs/{}/resume {{\"confirm_line\": N}}",
                    run.last_line,
                    run.job_id
                ),
                None => tracing::warn!(
                    run = run.id,
                    job = run.job_id,
                    last_line = run.last_line,
                    "run was interrupted by a restart; resume it with POST /api/v1/jobs/{}/resume",
                    run.job_id
                ),
            }
            record_interrupted(&bus, &run).await;
        }
        crate::machine::heightmap::fail_leftovers(&store, &bus, &app.settings.node.name)
            .await
            .map_err(|source| StartError::Store {
                database: db.clone(),
                source,
            })?;
        if app.settings.demo {
            crate::demo::ensure_demo_machine(&app).await;
        }
        let rows = store
            .list_machines()
            .await
            .map_err(|source| StartError::Store {
                database: db,
                source,
            })?;
        for row in rows {
            if row.node.as_deref() == Some(app.settings.node.name.as_str()) {
                load_machine(&app, row).await;
            }
        }
        if let Some(sim) = pendant_sim {
            crate::demo::ensure_demo_pendant(&app, sim).await;
        }
        // After the machines: it moves on only the queues of machines this node drives.
        crate::queue::spawn_runner(&app);
        crate::pendants::start_all(&app).await;
        Ok(app)
    }

    /// Stops all motion and marks active runs interrupted (resumable), before anything else
    /// of shutdown: no new motion is started from the moment this begins, whatever requests are
    /// still open or queued. Bounded: a backend that does not answer its urgent shutdown call
    /// within `limit` is left behind (it is logged), so the process can still exit.
    pub async fn stop_motion(&self, limit: std::time::Duration) {
        let machines = self.machines.all();
        for m in &machines {
            m.close_gate();
        }
        // Runs first: a backend reports a run it stops on shutdown as cancelled, and that
        // report must find the run already interrupted (so it is ignored).
        match self
            .store
            .interrupt_active_runs_of(&self.settings.node.name)
            .await
        {
            Ok(rows) => {
                for r in rows {
                    tracing::info!(
                        run = r.id,
                        last_line = r.last_line,
                        "run interrupted by shutdown"
                    );
                    record_interrupted(&self.bus, &r).await;
                }
            }
            Err(e) => tracing::error!(error = %e, "could not mark runs interrupted"),
        }
        let stops = machines.iter().map(|m| async move {
            match tokio::time::timeout(limit, m.shutdown_backend()).await {
                Ok(Ok(())) => {}
                Ok(Err(e)) => tracing::error!(
                    machine = m.id,
                    error = %e,
                    "shutdown call failed: the controller may still be moving; check the machine before leaving it"
                ),
                Err(_) => tracing::error!(
                    machine = m.id,
                    "backend did not confirm its stop within {limit:?}: the controller may still be moving; check the machine before leaving it"
                ),
            }
        });
        futures_util::future::join_all(stops).await;
    }

    /// The rest of shutdown, once motion is stopped: pendants and SSE streams.
    pub async fn stop_rest(&self, limit: std::time::Duration) {
        self.shutdown.cancel();
        // Maintenance counters and the `offline` state change, so a restart goes on from here.
        let machines = self.machines.all();
        let flushes = machines.iter().map(|m| m.flush_records(&self.store));
        if tokio::time::timeout(limit, futures_util::future::join_all(flushes))
            .await
            .is_err()
        {
            tracing::warn!("maintenance counters were not stored within {limit:?}");
        }
        if tokio::time::timeout(limit, self.pendants.stop_all())
            .await
            .is_err()
        {
            tracing::warn!("pendant transports did not stop within {limit:?}");
        }
    }
}

/// Starts the task and backend of a machine this node drives. A backend that cannot start
/// leaves the machine listed, offline with the reason.
pub(crate) async fn load_machine(app: &App, row: crate::store::MachineRow) {
    let backend = match app.plugins.get(&row.backend) {
        Some(lib) => Machine::prepare(lib, row.config_json())
            .await
            .map_err(|e| format!("backend rejected its config: {e}")),
        None => Err(format!("no plugin named {:?} is loaded", row.backend)),
    };
    let m = Machine::start(
        row,
        backend,
        app.store.clone(),
        app.bus.clone(),
        &app.machine_options(),
    )
    .await;
    if let Some(reason) = m.unavailable_reason() {
        tracing::error!(machine = m.id, reason, "machine offline");
    }
    app.machines.insert(m);
}

/// Removes `.upload-*.tmp` files a killed process left in `programs/` (a clean shutdown
/// deletes its own). Only safe under the data-dir lock: no other server is writing there.
fn remove_upload_leftovers(programs: &std::path::Path) {
    let entries = match std::fs::read_dir(programs) {
        Ok(d) => d,
        Err(e) => {
            tracing::warn!(dir = %programs.display(), error = %e, "cannot list programs for leftover uploads");
            return;
        }
    };
    let (mut files, mut bytes) = (0u64, 0u64);
    for entry in entries.flatten() {
        let name = entry.file_name();
        let name = name.to_string_lossy();
        if !(name.starts_with(".upload-") && name.ends_with(".tmp")) {
            continue;
        }
        let size = entry.metadata().map(|m| m.len()).unwrap_or(0);
        match std::fs::remove_file(entry.path()) {
            Ok(()) => {
                files += 1;
                bytes += size;
            }
            Err(e) => {
                tracing::warn!(file = %entry.path().display(), error = %e, "cannot remove leftover upload")
            }
        }
    }
    if files > 0 {
        tracing::info!(
            files,
            bytes,
            dir = %programs.display(),
            "removed {files} unfinished upload(s) ({bytes} bytes) left by an earlier process"
        );
    }
}

/// A zero-length `fresa.db` beside stored programs means the database was lost (truncated,
/// or a failed copy); opening it would silently start an empty store. A fresh data dir (no
/// programs) starts normally.
fn refuse_lost_database(
    db: &std::path::Path,
    programs: &std::path::Path,
) -> Result<(), StartError> {
    let empty = std::fs::metadata(db).map(|m| m.len() == 0).unwrap_or(false);
    if !empty {
        return Ok(());
    }
    let count = std::fs::read_dir(programs)
        .map(|d| {
            d.flatten()
                .filter(|e| e.path().extension().is_some_and(|x| x == "nc"))
                .count()
        })
        .unwrap_or(0);
    if count == 0 {
        return Ok(());
    }
    Err(StartError::EmptyDatabase {
        db: db.to_path_buf(),
        programs: programs.to_path_buf(),
        count,
    })
}

async fn record_interrupted(bus: &EventBus, run: &RunRow) {
    let mut data = serde_json::json!({"job": run.job_id, "run": run.id, "state": "interrupted", "line": run.last_line, "message": run.message});
    if let Some(unstored) = run.unstored_line {
        data["unstored_line"] = unstored.into();
    }
    bus.record_or_log(EventKind::JobState, Some(run.machine_id), None, data)
        .await;
}

/// Marks the runs the previous process left acknowledged lines of only in memory (its
/// machines' records in `dir`, see `machine::unstored`), then clears those records. The error:
/// the store's (`Ok`) or the records' (`Err`). A record that cannot be read marks every active
/// run of its machine: which ones it named is unknown.
async fn mark_unstored_runs(
    store: &crate::store::Store,
    dir: &std::path::Path,
) -> Result<(), Result<sqlx::Error, String>> {
    use crate::machine::unstored::{clear, LeftBehind};
    for left in crate::machine::unstored::left_behind(dir).map_err(Err)? {
        let path = match left {
            LeftBehind::Record(path, record) => {
                for r in &record.runs {
                    if store.mark_unstored_line(r.run, r.line).await.map_err(Ok)? {
                        tracing::warn!(
                            machine = record.machine,
                            run = r.run,
                            unstored_line = r.line,
                            "the previous process stopped with acknowledged lines of this run not stored (the database could not be written): its stored line may be behind"
                        );
                    }
                }
                path
            }
            LeftBehind::Unreadable {
                path,
                machine,
                error,
            } => {
                let n = store.mark_unstored_active_runs(machine).await.map_err(Ok)?;
                tracing::error!(file = %path.display(), error, machine, runs = n, "the record of unstored acknowledged lines is unreadable: the machine's active runs need their line confirmed before a resume");
                path
            }
        };
        if let Err(e) = clear(&path) {
            tracing::error!(file = %path.display(), error = %e, "cannot clear the record of unstored lines; the next start marks its runs again");
        }
    }
    Ok(())
}

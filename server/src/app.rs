//! The server's shared state and its start-up sequence.

use crate::config::Settings;
use crate::events::EventBus;
use crate::machines::{Machine, MachineOptions, Machines};
use crate::plugins::Registry;
use crate::store::Store;
use std::sync::Arc;
use tokio_util::sync::CancellationToken;

pub struct App {
    pub settings: Settings,
    pub store: Store,
    pub bus: EventBus,
    pub plugins: Registry,
    pub machines: Machines,
    pub pendants: crate::pendants::Pendants,
    /// Cancelled on shutdown: ends SSE streams and background loops.
    pub shutdown: CancellationToken,
    /// Whether requests must carry a token (any non-loopback bind).
    pub auth_required: bool,
}

pub type SharedApp = Arc<App>;

#[derive(Debug, thiserror::Error)]
pub enum StartError {
    #[error("cannot create data directory {path}: {source}")]
    DataDir {
        path: std::path::PathBuf,
        source: std::io::Error,
    },
    #[error("cannot open database {path}: {source}")]
    Store {
        path: std::path::PathBuf,
        source: sqlx::Error,
    },
    #[error(
        "refusing to listen on {0}: it is not a loopback address and no API token exists. \
         Create one first with `fresa token create --role admin --name NAME`"
    )]
    NoTokens(std::net::SocketAddr),
}

impl App {
    pub fn machine_options(&self) -> MachineOptions {
        MachineOptions {
            timeout: self.settings.plugin_call_timeout,
            max_concurrent_calls: self.settings.plugin_max_concurrent_calls,
            status_interval: self.settings.status_interval,
        }
    }

    /// Opens the store, loads plugins, marks runs the last process left active as interrupted and
    /// starts a backend instance for every machine.
    pub async fn start(settings: Settings) -> Result<SharedApp, StartError> {
        std::fs::create_dir_all(settings.programs_dir()).map_err(|source| StartError::DataDir {
            path: settings.programs_dir(),
            source,
        })?;
        let db = settings.db_path();
        let store = Store::open(&db).await.map_err(|source| StartError::Store {
            path: db.clone(),
            source,
        })?;
        tracing::info!(database = %db.display(), "store ready");
        let auth_required = !settings.loopback_only();
        if auth_required {
            let n = store
                .token_count()
                .await
                .map_err(|source| StartError::Store {
                    path: db.clone(),
                    source,
                })?;
            if n == 0 {
                return Err(StartError::NoTokens(settings.listen));
            }
        }
        let plugins = Registry::load(&settings.plugin_dirs);
        if plugins.names().is_empty() {
            tracing::warn!(
                dirs = ?settings.plugin_dirs,
                "no plugins found; build them with `cargo build --workspace` or pass --plugin-dir"
            );
        } else {
            tracing::info!(plugins = ?plugins.names(), "plugins loaded");
        }
        let bus = EventBus::new(store.clone(), 4096);
        let app = Arc::new(App {
            settings,
            store: store.clone(),
            bus: bus.clone(),
            plugins,
            machines: Machines::default(),
            pendants: Default::default(),
            shutdown: CancellationToken::new(),
            auth_required,
        });
        for run in store
            .interrupt_active_runs()
            .await
            .map_err(|source| StartError::Store {
                path: db.clone(),
                source,
            })?
        {
            tracing::warn!(
                run = run.id,
                job = run.job_id,
                last_line = run.last_line,
                "run was interrupted by a restart; resume it with POST /api/v1/jobs/{}/resume",
                run.job_id
            );
            bus.record_or_log(
                "job.state",
                Some(run.machine_id),
                None,
                serde_json::json!({"job": run.job_id, "run": run.id, "state": "interrupted", "line": run.last_line, "message": run.message}),
            )
            .await;
        }
        if app.settings.demo {
            crate::demo::ensure_demo_machine(&app).await;
        }
        let rows = store
            .list_machines()
            .await
            .map_err(|source| StartError::Store { path: db, source })?;
        for row in rows {
            let backend = match app.plugins.get(&row.backend) {
                Some(lib) => Machine::prepare(lib, row.config_json())
                    .await
                    .map_err(|e| format!("backend rejected its config: {e}")),
                None => Err(format!("no plugin named {:?} is loaded", row.backend)),
            };
            let m = Machine::start(
                row,
                backend,
                store.clone(),
                bus.clone(),
                &app.machine_options(),
            );
            crate::machines::restore_state(&m, &store).await;
            if let Some(reason) = m.unavailable_reason() {
                tracing::error!(machine = m.id, reason, "machine offline");
            }
            app.machines.insert(m).await;
        }
        if app.settings.demo {
            crate::demo::ensure_demo_pendant(&app).await;
        }
        crate::pendants::start_all(&app).await;
        Ok(app)
    }

    /// Marks active runs interrupted so they can be resumed, then stops motion on every machine.
    /// In that order: a backend reports a run it stops on shutdown as cancelled, and that report
    /// must find the run already interrupted (so it is ignored), not turn it into a cancelled one.
    pub async fn stop(&self) {
        self.shutdown.cancel();
        self.pendants.stop_all().await;
        match self.store.interrupt_active_runs().await {
            Ok(rows) => {
                for r in rows {
                    tracing::info!(
                        run = r.id,
                        last_line = r.last_line,
                        "run interrupted by shutdown"
                    );
                    self.bus
                        .record_or_log(
                            "job.state",
                            Some(r.machine_id),
                            None,
                            serde_json::json!({"job": r.job_id, "run": r.id, "state": "interrupted", "line": r.last_line, "message": r.message}),
                        )
                        .await;
                }
            }
            Err(e) => tracing::error!(error = %e, "could not mark runs interrupted"),
        }
        for m in self.machines.all().await {
            if let Err(e) = m.call(&fresa_plugin_api::contract::Request::Shutdown).await {
                tracing::warn!(machine = m.id, error = %e, "shutdown call failed");
            }
        }
    }
}

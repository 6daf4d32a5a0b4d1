//! `fresa serve`: bind, start, notify systemd, serve until SIGTERM/Ctrl-C, shut down cleanly.

use crate::app::App;
use crate::config::Settings;
use std::time::Duration;

pub async fn run(settings: Settings) -> Result<(), Box<dyn std::error::Error>> {
    if let Some(f) = &settings.config_file {
        tracing::info!(file = %f.display(), "config file read");
    }
    tracing::info!(data_dir = %settings.data_dir.display(), "data directory");
    let listener = tokio::net::TcpListener::bind(settings.listen)
        .await
        .map_err(|e| format!("cannot listen on {}: {e}", settings.listen))?;
    let bound = listener.local_addr()?;
    let app = App::start(settings).await?;
    let router = crate::api::router(app.clone());
    // This exact phrase is what scripts and tests wait for.
    tracing::info!("listening on http://{bound}");
    if !app.settings.loopback_only() {
        tracing::info!("not loopback-only: every request needs an API token");
    }
    let _ = sd_notify::notify(false, &[sd_notify::NotifyState::Ready]);
    spawn_watchdog(app.clone());
    let shutdown = app.shutdown.clone();
    let server = axum::serve(listener, router).with_graceful_shutdown(async move {
        wait_for_signal().await;
        tracing::info!("shutting down");
        shutdown.cancel();
    });
    server.await?;
    let _ = sd_notify::notify(false, &[sd_notify::NotifyState::Stopping]);
    app.stop().await;
    tracing::info!("stopped");
    Ok(())
}

/// Pings systemd's watchdog only while the database answers, so a wedged store gets us restarted.
fn spawn_watchdog(app: crate::app::SharedApp) {
    let mut usec = 0u64;
    if !sd_notify::watchdog_enabled(false, &mut usec) || usec == 0 {
        return;
    }
    let period = Duration::from_micros(usec / 2);
    tokio::spawn(async move {
        let mut tick = tokio::time::interval(period);
        loop {
            tick.tick().await;
            match tokio::time::timeout(period, app.store.ping()).await {
                Ok(Ok(())) => {
                    let _ = sd_notify::notify(false, &[sd_notify::NotifyState::Watchdog]);
                }
                _ => tracing::error!("database did not answer; withholding the watchdog ping"),
            }
        }
    });
}

async fn wait_for_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {}
        _ = term => {}
    }
}

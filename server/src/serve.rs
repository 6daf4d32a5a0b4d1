//! `fresa serve`: bind, start, notify systemd, serve until SIGTERM/Ctrl-C, shut down cleanly.
//!
//! Shutdown order: motion first. On the signal every machine's gate closes (no new motion),
//! active runs become `interrupted` (resumable) and each backend is told to stop, on its urgent
//! lane, bounded. Only then do open connections get a bounded grace period to finish; whatever
//! is still open after it is dropped. So a slow client cannot keep a machine cutting, and the
//! process always exits well inside systemd's `TimeoutStopSec` (20 s in the shipped unit).

use fresa_core::config::Settings;
use fresa_core::App;
use std::future::IntoFuture;
use std::time::Duration;

/// At most this long for the backends to confirm they stopped.
const STOP_MOTION_LIMIT: Duration = Duration::from_secs(5);

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
    let router = fresa_http::router(app.clone());
    // This exact phrase is what scripts and tests wait for.
    tracing::info!("listening on http://{bound}");
    if !app.settings.loopback_only() {
        tracing::info!("not loopback-only: every request needs an API token");
    }
    let _ = sd_notify::notify(false, &[sd_notify::NotifyState::Ready]);
    spawn_watchdog(app.clone());
    let drain = tokio_util::sync::CancellationToken::new();
    let drain_signal = drain.clone();
    let mut server = tokio::spawn(
        axum::serve(listener, router)
            .with_graceful_shutdown(async move { drain_signal.cancelled().await })
            .into_future(),
    );
    tokio::select! {
        _ = wait_for_signal() => {}
        r = &mut server => {
            // The server ended on its own (an accept loop error): still stop motion.
            tracing::error!(result = ?r, "HTTP server ended");
        }
    }
    let _ = sd_notify::notify(false, &[sd_notify::NotifyState::Stopping]);
    let limit = STOP_MOTION_LIMIT.min(app.settings.plugin_call_timeout);
    tracing::info!("shutting down: stopping all motion");
    app.stop_motion(limit).await;
    let grace = app.settings.shutdown_grace;
    tracing::info!("motion stopped");
    tracing::info!("draining connections for at most {grace:?}");
    drain.cancel();
    app.stop_rest(limit).await;
    if !server.is_finished() && tokio::time::timeout(grace, &mut server).await.is_err() {
        tracing::warn!("connections still open after {grace:?}; closing them");
        server.abort();
    }
    tracing::info!("stopped");
    Ok(())
}

/// Pings systemd's watchdog only while the database answers, so a wedged store gets us restarted.
fn spawn_watchdog(app: fresa_core::SharedApp) {
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

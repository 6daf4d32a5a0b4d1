//! Where the log goes: stderr for console use (systemd's journal on Linux reads it there); as a
//! Windows service, a daily-rotated file in `<data dir>\logs` plus errors to the Event Log.

use tracing_subscriber::layer::SubscriberExt;
use tracing_subscriber::util::SubscriberInitExt;
use tracing_subscriber::Layer;

/// Default filter when neither `FRESA_LOG` nor the config's `log` says otherwise.
pub const DEFAULT_FILTER: &str = "info,tower_http=warn,sqlx=warn";

/// Log files kept (one a day): two weeks.
pub const LOG_FILES_KEPT: usize = 14;

fn filter(default: &str) -> tracing_subscriber::EnvFilter {
    tracing_subscriber::EnvFilter::try_from_env("FRESA_LOG")
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default))
}

pub fn init_console(default: &str) {
    tracing_subscriber::fmt()
        .with_env_filter(filter(default))
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
}

/// A writer for `logs_dir/fresa.log.YYYY-MM-DD`, rotated daily, [`LOG_FILES_KEPT`] kept.
pub fn rolling_file(
    logs_dir: &std::path::Path,
) -> Result<tracing_appender::rolling::RollingFileAppender, String> {
    std::fs::create_dir_all(logs_dir).map_err(|e| {
        format!(
            "cannot create the log directory {}: {e}",
            logs_dir.display()
        )
    })?;
    tracing_appender::rolling::Builder::new()
        .rotation(tracing_appender::rolling::Rotation::DAILY)
        .filename_prefix("fresa.log")
        .max_log_files(LOG_FILES_KEPT)
        .build(logs_dir)
        .map_err(|e| format!("cannot open a log file in {}: {e}", logs_dir.display()))
}

/// The service's logging: the file, and `errors` (the Event Log) for ERROR events. The guard
/// flushes the file when dropped: keep it until the service has stopped.
pub fn init_service(
    default: &str,
    logs_dir: &std::path::Path,
    errors: Option<Box<dyn ErrorSink>>,
) -> Result<tracing_appender::non_blocking::WorkerGuard, String> {
    let (file, guard) = tracing_appender::non_blocking(rolling_file(logs_dir)?);
    let file_layer = tracing_subscriber::fmt::layer()
        .with_writer(file)
        .with_ansi(false)
        .with_filter(filter(default));
    let errors = errors.map(|sink| ErrorForwarder { sink });
    tracing_subscriber::registry()
        .with(file_layer)
        .with(errors)
        .try_init()
        .map_err(|e| format!("cannot set up logging: {e}"))?;
    Ok(guard)
}

/// Where ERROR events also go (the Windows Event Log).
pub trait ErrorSink: Send + Sync + 'static {
    fn error(&self, message: &str);
}

/// A tracing layer handing each ERROR event, as one line (`target: message key=value ...`), to
/// an [`ErrorSink`].
pub struct ErrorForwarder {
    pub sink: Box<dyn ErrorSink>,
}

impl<S: tracing::Subscriber> Layer<S> for ErrorForwarder {
    fn on_event(
        &self,
        event: &tracing::Event<'_>,
        _ctx: tracing_subscriber::layer::Context<'_, S>,
    ) {
        if *event.metadata().level() != tracing::Level::ERROR {
            return;
        }
        let mut line = Line::default();
        event.record(&mut line);
        let text = format!(
            "{}: {}{}",
            event.metadata().target(),
            line.message,
            line.fields
        );
        self.sink.error(&text);
    }
}

#[derive(Default)]
struct Line {
    message: String,
    fields: String,
}

impl tracing::field::Visit for Line {
    fn record_debug(&mut self, field: &tracing::field::Field, value: &dyn std::fmt::Debug) {
        use std::fmt::Write;
        if field.name() == "message" {
            let _ = write!(self.message, "{value:?}");
        } else {
            let _ = write!(self.fields, " {}={value:?}", field.name());
        }
    }
    fn record_str(&mut self, field: &tracing::field::Field, value: &str) {
        use std::fmt::Write;
        if field.name() == "message" {
            self.message.push_str(value);
        } else {
            let _ = write!(self.fields, " {}={value}", field.name());
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use std::sync::{Arc, Mutex};

    #[derive(Clone, Default)]
    struct Collect(Arc<Mutex<Vec<String>>>);

    impl ErrorSink for Collect {
        fn error(&self, message: &str) {
            self.0.lock().unwrap().push(message.to_string());
        }
    }

    #[test]
    fn only_errors_reach_the_sink_with_their_fields() {
        let sink = Collect::default();
        let subscriber = tracing_subscriber::registry().with(ErrorForwarder {
            sink: Box::new(sink.clone()),
        });
        tracing::subscriber::with_default(subscriber, || {
            tracing::info!("ready");
            tracing::warn!("slow");
            tracing::error!(path = "C:\\x.dll", code = 5, "plugin not loaded");
        });
        let got = sink.0.lock().unwrap().clone();
        assert_eq!(got.len(), 1, "{got:?}");
        assert!(
            got[0].ends_with("plugin not loaded path=C:\\x.dll code=5"),
            "{got:?}"
        );
    }

    #[test]
    fn the_rolling_file_is_created_in_the_logs_dir() {
        use std::io::Write;
        let dir = tempfile::tempdir().unwrap();
        let logs = dir.path().join("logs");
        let mut w = rolling_file(&logs).unwrap();
        w.write_all(b"hello\n").unwrap();
        w.flush().unwrap();
        let names: Vec<String> = std::fs::read_dir(&logs)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names.len(), 1, "{names:?}");
        assert!(names[0].starts_with("fresa.log."), "{names:?}");
    }
}

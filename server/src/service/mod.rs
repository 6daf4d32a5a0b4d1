//! `fresa service install | uninstall | start | stop | status`, and the service itself.
//!
//! What each command does, in which order, how long it waits, and what the running service
//! reports to the service manager while it starts and stops, is written here against two small
//! traits ([`ServiceManager`] for the control calls, [`StatusReporter`] for the running
//! service's status), so it is unit-tested on every platform. `windows.rs` implements them with
//! the `windows-service` crate; on other platforms the commands say they are Windows-only
//! (systemd runs the server there: `contrib/systemd/`).

#[cfg(windows)]
pub mod windows;

use std::future::Future;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio_util::sync::CancellationToken;

/// The name the service is registered under (`sc query Fresa`, `net stop Fresa`).
pub const SERVICE_NAME: &str = "Fresa";
pub const DISPLAY_NAME: &str = "Fresa motion-control server";
pub const DESCRIPTION: &str =
    "Owns the workshop's CNC machines, robots and pendants; HTTP API on the configured address.";

/// How long `start` waits for the service to report running: migrations and plugin loading.
pub const START_WAIT: Duration = Duration::from_secs(60);
/// How long `stop` and `uninstall` wait: motion stops within 5 s, connections then get at most
/// `shutdown_grace_secs` (60 s at most).
pub const STOP_WAIT: Duration = Duration::from_secs(75);
/// Restart after a failure this long after it (three times; the count resets after a day).
pub const RESTART_DELAY: Duration = Duration::from_secs(5);

/// A service's state, as the service manager reports it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum State {
    Stopped,
    StartPending,
    Running,
    StopPending,
    /// Paused, or pausing/continuing: Fresa never asks for these.
    Other,
}

impl std::fmt::Display for State {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            State::Stopped => "stopped",
            State::StartPending => "starting",
            State::Running => "running",
            State::StopPending => "stopping",
            State::Other => "paused",
        })
    }
}

pub type Error = Box<dyn std::error::Error + Send + Sync>;

/// What `install` registers.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ServiceSpec {
    /// The `fresa.exe` the service runs.
    pub exe: PathBuf,
    /// Its arguments: `service run`, and `--data-dir` when not the default.
    pub args: Vec<String>,
    /// Restart this long after the process fails (crash, or a non-zero exit code).
    pub restart_delay: Duration,
}

/// The service manager's control calls, for the service named [`SERVICE_NAME`].
pub trait ServiceManager {
    /// `None`: not installed.
    fn state(&self) -> Result<Option<State>, Error>;
    /// The installed service's command line (`"C:\...\fresa.exe" service run ...`).
    fn command_line(&self) -> Result<Option<String>, Error>;
    /// Registers the service (automatic start, LocalSystem).
    fn create(&self, spec: &ServiceSpec) -> Result<(), Error>;
    /// Restart the service `delay` after its process fails.
    fn restart_on_failure(&self, delay: Duration) -> Result<(), Error>;
    /// Count a stop with a non-zero exit code as a failure too (not only a crash).
    fn restart_on_error_exit(&self) -> Result<(), Error>;
    fn delete(&self) -> Result<(), Error>;
    fn start(&self) -> Result<(), Error>;
    /// Sends the stop control; returns at once.
    fn stop(&self) -> Result<(), Error>;
    /// Lets the Event Log show the service's messages (source [`SERVICE_NAME`]).
    fn register_event_source(&self) -> Result<(), Error>;
    fn deregister_event_source(&self) -> Result<(), Error>;
}

/// The data directory the installed service uses: its `--data-dir` argument, else `default`.
/// So `uninstall` and `start` name the right folder without being told it again.
pub fn installed_data_dir(
    mgr: &dyn ServiceManager,
    default: Option<PathBuf>,
) -> Result<Option<PathBuf>, Error> {
    let from_service = mgr
        .command_line()?
        .and_then(|line| data_dir_argument(&line));
    Ok(from_service.or(default))
}

/// The value after `--data-dir` in a Windows command line (quoted as `CommandLineToArgvW`
/// reads it: `"C:\My Data\\"` is `C:\My Data\`).
pub fn data_dir_argument(command_line: &str) -> Option<PathBuf> {
    let args = split_command_line(command_line);
    let i = args.iter().position(|a| a == "--data-dir")?;
    args.get(i + 1).map(PathBuf::from)
}

/// Splits a command line into arguments by the rules of `CommandLineToArgvW`: spaces separate
/// unless quoted; `2n` backslashes before a quote are `n` and the quote delimits, `2n + 1` are
/// `n` and a literal quote; other backslashes are literal.
fn split_command_line(line: &str) -> Vec<String> {
    let mut args = Vec::new();
    let mut arg = String::new();
    let mut in_arg = false;
    let mut quoted = false;
    let mut chars = line.chars().peekable();
    while let Some(c) = chars.next() {
        match c {
            '\\' => {
                let mut n = 1;
                while chars.peek() == Some(&'\\') {
                    chars.next();
                    n += 1;
                }
                in_arg = true;
                if chars.peek() == Some(&'"') {
                    arg.extend(std::iter::repeat_n('\\', n / 2));
                    if n % 2 == 1 {
                        chars.next();
                        arg.push('"');
                    }
                } else {
                    arg.extend(std::iter::repeat_n('\\', n));
                }
            }
            '"' => {
                in_arg = true;
                quoted = !quoted;
            }
            ' ' | '\t' if !quoted => {
                if in_arg {
                    args.push(std::mem::take(&mut arg));
                    in_arg = false;
                }
            }
            c => {
                in_arg = true;
                arg.push(c);
            }
        }
    }
    if in_arg {
        args.push(arg);
    }
    args
}

/// How often the commands look at the service's state while they wait for it.
#[derive(Debug, Clone, Copy)]
pub struct Waits {
    pub start: Duration,
    pub stop: Duration,
    pub poll: Duration,
}

impl Default for Waits {
    fn default() -> Self {
        Waits {
            start: START_WAIT,
            stop: STOP_WAIT,
            poll: Duration::from_millis(200),
        }
    }
}

fn not_installed() -> Error {
    format!("service {SERVICE_NAME} is not installed (fresa service install)").into()
}

/// Polls the state until it is `want`; `Err` when it becomes `Stopped` instead (and `want` is
/// not `Stopped`), or is still something else at the deadline.
fn wait_for_state(
    mgr: &dyn ServiceManager,
    want: State,
    within: Duration,
    poll: Duration,
    failed: &dyn Fn() -> String,
) -> Result<(), Error> {
    let deadline = Instant::now() + within;
    loop {
        let now = mgr.state()?.ok_or_else(not_installed)?;
        if now == want {
            return Ok(());
        }
        if now == State::Stopped {
            return Err(failed().into());
        }
        if Instant::now() >= deadline {
            return Err(format!(
                "service {SERVICE_NAME} is still {now} after {within:?} (waiting for {want}); {}",
                failed()
            )
            .into());
        }
        std::thread::sleep(poll);
    }
}

/// The config written by `install` when the data directory has none: every key commented out,
/// so the defaults (README, Configuration) apply until the operator changes one.
pub const DEFAULT_CONFIG: &str = "\
# Fresa configuration (see the README's Configuration table for every key).\r
# Restart the service after a change: fresa service stop, then fresa service start.\r
#\r
# listen = \"127.0.0.1:7878\"   # \"0.0.0.0:7878\" for other PCs: then every request needs a token\r
# log = \"info\"\r
# shutdown_grace_secs = 5\r
";

/// `fresa service install`: data and log directories, a commented config if there is none,
/// the service (restarting on failure), and the Event Log source.
pub fn install(
    mgr: &dyn ServiceManager,
    spec: &ServiceSpec,
    data_dir: &Path,
    out: &mut dyn std::io::Write,
) -> Result<(), Error> {
    if let Some(state) = mgr.state()? {
        return Err(format!(
            "service {SERVICE_NAME} is already installed ({state}). To update fresa: \
             fresa service stop, replace the files, fresa service start. To install it again: \
             fresa service uninstall first"
        )
        .into());
    }
    let logs = data_dir.join("logs");
    std::fs::create_dir_all(&logs).map_err(|e| format!("cannot create {}: {e}", logs.display()))?;
    let config = data_dir.join("fresa.toml");
    if !config.exists() {
        std::fs::write(&config, DEFAULT_CONFIG)
            .map_err(|e| format!("cannot write {}: {e}", config.display()))?;
    }
    mgr.create(spec)?;
    // A service that is not restarted is not what was asked for: take it away again.
    if let Err(e) = mgr.restart_on_failure(spec.restart_delay) {
        let removed = match mgr.delete() {
            Ok(()) => "the service was removed again".to_string(),
            Err(d) => format!("removing the service failed too ({d}): fresa service uninstall"),
        };
        return Err(
            format!("cannot set restart-on-failure for {SERVICE_NAME}: {e}; {removed}").into(),
        );
    }
    if let Err(e) = mgr.restart_on_error_exit() {
        writeln!(
            out,
            "warning: {SERVICE_NAME} is restarted after a crash but not after it stops with an \
             error ({e})"
        )?;
    }
    // Errors still reach the log file; the Event Log is the second place they go.
    if let Err(e) = mgr.register_event_source() {
        writeln!(
            out,
            "warning: the Event Log source {SERVICE_NAME} was not registered ({e}); \
             errors are still written to {}",
            logs.display()
        )?;
    }
    writeln!(
        out,
        "installed service {SERVICE_NAME}: {} {}\n\
         data (database, programs): {}\nconfig: {}\nlogs: {}\n\
         it starts at boot; start it now with: fresa service start",
        spec.exe.display(),
        spec.args.join(" "),
        data_dir.display(),
        config.display(),
        logs.display()
    )?;
    Ok(())
}

/// `fresa service start`: returns once the service reports running (it is then serving).
pub fn start(
    mgr: &dyn ServiceManager,
    waits: Waits,
    logs: &Path,
    out: &mut dyn std::io::Write,
) -> Result<(), Error> {
    match mgr.state()?.ok_or_else(not_installed)? {
        State::Running => {
            writeln!(out, "service {SERVICE_NAME} is already running")?;
            return Ok(());
        }
        State::Stopped => mgr.start()?,
        // Already on its way up: wait for it like for our own start.
        State::StartPending => {}
        other => {
            return Err(format!(
                "service {SERVICE_NAME} is {other}; wait until it has stopped, then start it"
            )
            .into())
        }
    }
    let failed = || {
        format!(
            "service {SERVICE_NAME} stopped while starting: see the log in {} and the Event Log \
             (source {SERVICE_NAME})",
            logs.display()
        )
    };
    wait_for_state(mgr, State::Running, waits.start, waits.poll, &failed)?;
    writeln!(out, "service {SERVICE_NAME} is running")?;
    Ok(())
}

/// `fresa service stop`: returns once the service has stopped (motion stopped, running jobs
/// `interrupted`, connections drained).
pub fn stop(
    mgr: &dyn ServiceManager,
    waits: Waits,
    out: &mut dyn std::io::Write,
) -> Result<(), Error> {
    match mgr.state()?.ok_or_else(not_installed)? {
        State::Stopped => {
            writeln!(out, "service {SERVICE_NAME} is not running")?;
            return Ok(());
        }
        State::StopPending => {}
        _ => mgr.stop()?,
    }
    let never = || String::new();
    wait_for_state(mgr, State::Stopped, waits.stop, waits.poll, &never)?;
    writeln!(out, "service {SERVICE_NAME} stopped")?;
    Ok(())
}

/// `fresa service uninstall`: stops it if it runs, removes the service and the Event Log
/// source. The data directory (database, programs, config, logs) is kept.
pub fn uninstall(
    mgr: &dyn ServiceManager,
    waits: Waits,
    data_dir: &Path,
    out: &mut dyn std::io::Write,
) -> Result<(), Error> {
    let state = mgr.state()?.ok_or_else(not_installed)?;
    if state != State::Stopped {
        stop(mgr, waits, out)?;
    }
    mgr.delete()?;
    if let Err(e) = mgr.deregister_event_source() {
        writeln!(out, "warning: the Event Log source was not removed: {e}")?;
    }
    writeln!(
        out,
        "service {SERVICE_NAME} removed; the data directory {} was kept (delete it to remove \
         the database, programs, config and logs)",
        data_dir.display()
    )?;
    Ok(())
}

/// `fresa service status`.
pub fn status(mgr: &dyn ServiceManager, out: &mut dyn std::io::Write) -> Result<(), Error> {
    match mgr.state()? {
        Some(s) => writeln!(out, "service {SERVICE_NAME}: {s}")?,
        None => writeln!(out, "service {SERVICE_NAME}: not installed")?,
    }
    Ok(())
}

/// What the running service tells the service manager.
pub trait StatusReporter: Send + Sync {
    /// `wait_hint`: how long the manager should wait for the next report while pending.
    /// `exit_code`: for `Stopped`, 0 for a clean stop; anything else counts as a failure, and
    /// the failure actions restart the service.
    fn report(&self, state: State, wait_hint: Duration, exit_code: u32);
}

/// The service manager's requests to the running service.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Control {
    Stop,
    /// The machine is shutting down: the same as stop.
    Shutdown,
    Interrogate,
    Other,
}

/// Answers a control request; `false`: not implemented. Stop and shutdown trigger the same
/// graceful path as SIGTERM on Linux.
pub fn handle_control(control: Control, stop: &CancellationToken) -> bool {
    match control {
        Control::Stop | Control::Shutdown => {
            stop.cancel();
            true
        }
        Control::Interrogate => true,
        Control::Other => false,
    }
}

/// Exit code reported when the server failed (start-up error, or it ended with an error).
pub const EXIT_FAILED: u32 = 1;

/// Runs the server as a service: start pending until it serves, running, stop pending once
/// `stop` is cancelled, then stopped (0 when the server ended cleanly, [`EXIT_FAILED`] when not,
/// so the restart-on-failure actions apply).
///
/// `serve` gets the shutdown future and the ready callback, as `serve::run` takes them.
pub async fn run_service<F, Fut>(
    reporter: Arc<dyn StatusReporter>,
    stop: CancellationToken,
    stop_wait: Duration,
    serve: F,
) -> Result<(), String>
where
    F: FnOnce(
        std::pin::Pin<Box<dyn Future<Output = ()> + Send>>,
        Box<dyn FnOnce(std::net::SocketAddr) + Send>,
    ) -> Fut,
    Fut: Future<Output = Result<(), String>>,
{
    reporter.report(State::StartPending, START_WAIT, 0);
    let on_stop = reporter.clone();
    let shutdown = Box::pin(async move {
        stop.cancelled().await;
        on_stop.report(State::StopPending, stop_wait, 0);
    });
    let on_ready = reporter.clone();
    let ready = Box::new(move |addr: std::net::SocketAddr| {
        tracing::info!("service {SERVICE_NAME} running on http://{addr}");
        on_ready.report(State::Running, Duration::ZERO, 0);
    });
    let result = serve(shutdown, ready).await;
    match &result {
        Ok(()) => reporter.report(State::Stopped, Duration::ZERO, 0),
        Err(e) => {
            tracing::error!("service {SERVICE_NAME} failed: {e}");
            reporter.report(State::Stopped, Duration::ZERO, EXIT_FAILED);
        }
    }
    result
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;
    use std::collections::VecDeque;
    use std::sync::Mutex;

    /// A service manager that records every call and plays back scripted states.
    #[derive(Default)]
    struct FakeScm {
        calls: Mutex<Vec<String>>,
        /// States returned by `state()`, in order; the last one repeats.
        states: Mutex<VecDeque<Option<State>>>,
        event_source_fails: bool,
        restart_fails: bool,
        error_exit_flag_fails: bool,
        command_line: Option<String>,
    }

    impl FakeScm {
        fn with_states(states: &[Option<State>]) -> FakeScm {
            FakeScm {
                states: Mutex::new(states.iter().copied().collect()),
                ..FakeScm::default()
            }
        }
        fn calls(&self) -> Vec<String> {
            self.calls.lock().unwrap().clone()
        }
        fn call(&self, name: &str) {
            self.calls.lock().unwrap().push(name.to_string());
        }
    }

    impl ServiceManager for FakeScm {
        fn state(&self) -> Result<Option<State>, Error> {
            let mut s = self.states.lock().unwrap();
            Ok(if s.len() > 1 {
                s.pop_front().unwrap()
            } else {
                *s.front().unwrap()
            })
        }
        fn command_line(&self) -> Result<Option<String>, Error> {
            Ok(self.command_line.clone())
        }
        fn create(&self, spec: &ServiceSpec) -> Result<(), Error> {
            self.call(&format!(
                "create {} {}",
                spec.exe.display(),
                spec.args.join(" ")
            ));
            Ok(())
        }
        fn restart_on_failure(&self, delay: Duration) -> Result<(), Error> {
            self.call(&format!("restart_on_failure {delay:?}"));
            if self.restart_fails {
                return Err("invalid level".into());
            }
            Ok(())
        }
        fn restart_on_error_exit(&self) -> Result<(), Error> {
            self.call("restart_on_error_exit");
            if self.error_exit_flag_fails {
                return Err("invalid level".into());
            }
            Ok(())
        }
        fn delete(&self) -> Result<(), Error> {
            self.call("delete");
            Ok(())
        }
        fn start(&self) -> Result<(), Error> {
            self.call("start");
            Ok(())
        }
        fn stop(&self) -> Result<(), Error> {
            self.call("stop");
            Ok(())
        }
        fn register_event_source(&self) -> Result<(), Error> {
            self.call("register_event_source");
            if self.event_source_fails {
                return Err("access denied".into());
            }
            Ok(())
        }
        fn deregister_event_source(&self) -> Result<(), Error> {
            self.call("deregister_event_source");
            Ok(())
        }
    }

    fn quick() -> Waits {
        Waits {
            start: Duration::from_secs(5),
            stop: Duration::from_secs(5),
            poll: Duration::ZERO,
        }
    }

    fn spec() -> ServiceSpec {
        ServiceSpec {
            exe: PathBuf::from("C:/Fresa/fresa.exe"),
            args: vec!["service".into(), "run".into()],
            restart_delay: RESTART_DELAY,
        }
    }

    #[test]
    fn install_creates_dirs_config_service_and_event_source_once() {
        let dir = tempfile::tempdir().unwrap();
        let data = dir.path().join("Fresa");
        let scm = FakeScm::with_states(&[None]);
        let mut out = Vec::new();
        install(&scm, &spec(), &data, &mut out).unwrap();
        assert_eq!(
            scm.calls(),
            [
                "create C:/Fresa/fresa.exe service run",
                "restart_on_failure 5s",
                "restart_on_error_exit",
                "register_event_source"
            ]
        );
        assert!(data.join("logs").is_dir());
        assert_eq!(
            std::fs::read_to_string(data.join("fresa.toml")).unwrap(),
            DEFAULT_CONFIG
        );
        let text = String::from_utf8(out).unwrap();
        assert!(text.contains(&data.display().to_string()), "{text}");

        // An existing config is the operator's: never overwritten.
        let scm = FakeScm::with_states(&[None]);
        std::fs::write(data.join("fresa.toml"), "listen = \"0.0.0.0:7878\"\n").unwrap();
        install(&scm, &spec(), &data, &mut Vec::new()).unwrap();
        assert_eq!(
            std::fs::read_to_string(data.join("fresa.toml")).unwrap(),
            "listen = \"0.0.0.0:7878\"\n"
        );
    }

    #[test]
    fn install_over_an_installed_service_is_refused_saying_how_to_update() {
        let dir = tempfile::tempdir().unwrap();
        let scm = FakeScm::with_states(&[Some(State::Running)]);
        let e = install(&scm, &spec(), dir.path(), &mut Vec::new())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("already installed") && e.contains("fresa service stop"),
            "{e}"
        );
        assert!(
            scm.calls().is_empty(),
            "nothing was changed: {:?}",
            scm.calls()
        );
    }

    #[test]
    fn an_event_source_that_cannot_be_registered_is_a_warning_not_a_failure() {
        let dir = tempfile::tempdir().unwrap();
        let scm = FakeScm {
            event_source_fails: true,
            ..FakeScm::with_states(&[None])
        };
        let mut out = Vec::new();
        install(&scm, &spec(), dir.path(), &mut out).unwrap();
        let text = String::from_utf8(out).unwrap();
        assert!(
            text.contains("warning") && text.contains("access denied"),
            "{text}"
        );
    }

    #[test]
    fn a_service_that_cannot_be_made_to_restart_is_removed_again() {
        let dir = tempfile::tempdir().unwrap();
        let scm = FakeScm {
            restart_fails: true,
            ..FakeScm::with_states(&[None])
        };
        let e = install(&scm, &spec(), dir.path(), &mut Vec::new())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("restart-on-failure") && e.contains("removed again"),
            "{e}"
        );
        assert_eq!(
            scm.calls(),
            [
                "create C:/Fresa/fresa.exe service run",
                "restart_on_failure 5s",
                "delete"
            ]
        );
        // Only the error-exit flag missing (Wine has no such setting): installed, with a word.
        let scm = FakeScm {
            error_exit_flag_fails: true,
            ..FakeScm::with_states(&[None])
        };
        let mut out = Vec::new();
        install(&scm, &spec(), dir.path(), &mut out).unwrap();
        let text = String::from_utf8(out).unwrap();
        assert!(
            text.contains("warning") && text.contains("after a crash"),
            "{text}"
        );
    }

    #[test]
    fn the_installed_data_dir_comes_from_the_service_command_line() {
        for (line, want) in [
            (
                r#""C:\Program Files\Fresa\fresa.exe" service run --data-dir D:\Fresa"#,
                Some(r"D:\Fresa"),
            ),
            (
                r#"C:\Fresa\fresa.exe service run --data-dir "D:\My Data\Fresa\\""#,
                Some(r"D:\My Data\Fresa\"),
            ),
            (
                r#"fresa.exe service run --data-dir "D:\odd\"quote""#,
                Some(r#"D:\odd"quote"#),
            ),
            (r#""C:\Program Files\Fresa\fresa.exe" service run"#, None),
        ] {
            assert_eq!(data_dir_argument(line), want.map(PathBuf::from), "{line}");
        }
        let scm = FakeScm {
            command_line: Some("fresa.exe service run --data-dir E:\\F".into()),
            ..FakeScm::with_states(&[Some(State::Stopped)])
        };
        assert_eq!(
            installed_data_dir(&scm, Some("C:/ProgramData/Fresa".into())).unwrap(),
            Some(PathBuf::from("E:\\F"))
        );
        let scm = FakeScm::with_states(&[None]);
        assert_eq!(
            installed_data_dir(&scm, Some("C:/ProgramData/Fresa".into())).unwrap(),
            Some(PathBuf::from("C:/ProgramData/Fresa"))
        );
    }

    #[test]
    fn start_waits_until_running() {
        let scm = FakeScm::with_states(&[
            Some(State::Stopped),
            Some(State::StartPending),
            Some(State::StartPending),
            Some(State::Running),
        ]);
        let mut out = Vec::new();
        start(&scm, quick(), Path::new("L"), &mut out).unwrap();
        assert_eq!(scm.calls(), ["start"]);
        assert!(String::from_utf8(out).unwrap().contains("running"));
    }

    #[test]
    fn a_service_that_stops_while_starting_points_at_the_logs() {
        let scm = FakeScm::with_states(&[
            Some(State::Stopped),
            Some(State::StartPending),
            Some(State::Stopped),
        ]);
        let e = start(
            &scm,
            quick(),
            Path::new("C:/ProgramData/Fresa/logs"),
            &mut Vec::new(),
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("stopped while starting") && e.contains("C:/ProgramData/Fresa/logs"),
            "{e}"
        );
    }

    #[test]
    fn start_gives_up_at_its_deadline_naming_the_state() {
        let scm = FakeScm::with_states(&[Some(State::Stopped), Some(State::StartPending)]);
        let waits = Waits {
            start: Duration::from_millis(50),
            ..quick()
        };
        let e = start(&scm, waits, Path::new("L"), &mut Vec::new())
            .unwrap_err()
            .to_string();
        assert!(e.contains("still starting"), "{e}");
    }

    #[test]
    fn start_and_stop_are_idempotent_and_name_a_missing_service() {
        let scm = FakeScm::with_states(&[Some(State::Running)]);
        start(&scm, quick(), Path::new("L"), &mut Vec::new()).unwrap();
        let scm2 = FakeScm::with_states(&[Some(State::Stopped)]);
        stop(&scm2, quick(), &mut Vec::new()).unwrap();
        assert!(scm.calls().is_empty() && scm2.calls().is_empty());
        let none = FakeScm::with_states(&[None]);
        for e in [
            start(&none, quick(), Path::new("L"), &mut Vec::new()).unwrap_err(),
            stop(&none, quick(), &mut Vec::new()).unwrap_err(),
            uninstall(&none, quick(), Path::new("D"), &mut Vec::new()).unwrap_err(),
        ] {
            assert!(e.to_string().contains("not installed"), "{e}");
        }
        let mut out = Vec::new();
        status(&none, &mut out).unwrap();
        assert_eq!(
            String::from_utf8(out).unwrap(),
            "service Fresa: not installed\n"
        );
    }

    #[test]
    fn uninstall_stops_a_running_service_first_and_keeps_the_data() {
        let scm = FakeScm::with_states(&[
            Some(State::Running),
            Some(State::Running),
            Some(State::StopPending),
            Some(State::Stopped),
        ]);
        let mut out = Vec::new();
        uninstall(&scm, quick(), Path::new("C:/ProgramData/Fresa"), &mut out).unwrap();
        assert_eq!(scm.calls(), ["stop", "delete", "deregister_event_source"]);
        let text = String::from_utf8(out).unwrap();
        assert!(
            text.contains("C:/ProgramData/Fresa") && text.contains("kept"),
            "{text}"
        );
    }

    /// Records what the service reported.
    #[derive(Default)]
    struct Reports(Mutex<Vec<(State, u32)>>);

    impl StatusReporter for Reports {
        fn report(&self, state: State, _wait_hint: Duration, exit_code: u32) {
            self.0.lock().unwrap().push((state, exit_code));
        }
    }

    impl Reports {
        fn states(&self) -> Vec<(State, u32)> {
            self.0.lock().unwrap().clone()
        }
    }

    #[test]
    fn controls_stop_and_shutdown_cancel_interrogate_is_answered_others_are_not() {
        let t = CancellationToken::new();
        assert!(handle_control(Control::Interrogate, &t));
        assert!(!handle_control(Control::Other, &t));
        assert!(!t.is_cancelled());
        assert!(handle_control(Control::Shutdown, &t));
        assert!(t.is_cancelled());
        let t = CancellationToken::new();
        assert!(handle_control(Control::Stop, &t));
        assert!(t.is_cancelled());
    }

    /// The real server under the service wrapper: start pending, running once `/healthz`
    /// answers, and a stop control goes through `serve`'s shutdown (motion, then drain) to a
    /// clean stopped.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn the_real_server_reports_running_when_serving_and_stops_on_the_stop_control() {
        let dir = tempfile::tempdir().unwrap();
        let settings = fresa_core::config::Settings::resolve(fresa_core::config::Overrides {
            listen: Some("127.0.0.1:0".into()),
            data_dir: Some(dir.path().join("data")),
            config: Some(write_empty_config(dir.path())),
            ..Default::default()
        })
        .unwrap();
        let reports = Arc::new(Reports::default());
        let stop = CancellationToken::new();
        let (addr_tx, addr_rx) = tokio::sync::oneshot::channel();
        let service = tokio::spawn(run_service(
            reports.clone(),
            stop.clone(),
            STOP_WAIT,
            move |shutdown, ready| async move {
                crate::serve::run(settings, shutdown, move |addr| {
                    ready(addr);
                    let _ = addr_tx.send(addr);
                })
                .await
                .map_err(|e| e.to_string())
            },
        ));
        let addr = tokio::time::timeout(Duration::from_secs(60), addr_rx)
            .await
            .expect("ready within 60 s")
            .unwrap();
        assert_eq!(
            reports.states(),
            [(State::StartPending, 0), (State::Running, 0)]
        );
        let health = http_get(addr, "/healthz").await;
        assert!(health.starts_with("HTTP/1.1 200"), "{health}");

        assert!(handle_control(Control::Stop, &stop));
        let result = tokio::time::timeout(Duration::from_secs(30), service)
            .await
            .expect("stopped within 30 s")
            .unwrap();
        assert_eq!(result, Ok(()));
        assert_eq!(
            reports.states(),
            [
                (State::StartPending, 0),
                (State::Running, 0),
                (State::StopPending, 0),
                (State::Stopped, 0)
            ]
        );
        // Stopped means stopped: the port is closed and the data directory free again.
        assert!(tokio::net::TcpStream::connect(addr).await.is_err());
        fresa_core::datadir::DataDirLock::acquire(&dir.path().join("data")).unwrap();
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_server_that_cannot_start_reports_stopped_with_a_failure_code_never_running() {
        let dir = tempfile::tempdir().unwrap();
        // The data directory is a file: the store cannot be opened.
        let data = dir.path().join("data");
        std::fs::write(&data, "not a directory").unwrap();
        let settings = fresa_core::config::Settings::resolve(fresa_core::config::Overrides {
            listen: Some("127.0.0.1:0".into()),
            data_dir: Some(data),
            config: Some(write_empty_config(dir.path())),
            ..Default::default()
        })
        .unwrap();
        let reports = Arc::new(Reports::default());
        let result = run_service(
            reports.clone(),
            CancellationToken::new(),
            STOP_WAIT,
            move |shutdown, ready| async move {
                crate::serve::run(settings, shutdown, ready)
                    .await
                    .map_err(|e| e.to_string())
            },
        )
        .await;
        assert!(result.is_err());
        assert_eq!(
            reports.states(),
            [(State::StartPending, 0), (State::Stopped, EXIT_FAILED)]
        );
    }

    fn write_empty_config(dir: &Path) -> PathBuf {
        let f = dir.join("fresa.toml");
        std::fs::write(&f, "").unwrap();
        f
    }

    async fn http_get(addr: std::net::SocketAddr, path: &str) -> String {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
        s.write_all(
            format!("GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
                .as_bytes(),
        )
        .await
        .unwrap();
        let mut buf = String::new();
        s.read_to_string(&mut buf).await.unwrap();
        buf
    }
}

//! The Windows side of `fresa service`: the service manager's calls through the
//! `windows-service` crate, the service's entry point, and errors to the Event Log.

use super::{
    handle_control, run_service, Control, Error, ServiceManager, ServiceSpec, State,
    StatusReporter, SERVICE_NAME,
};
use crate::logging;
use std::ffi::OsString;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, OnceLock};
use std::time::Duration;
use tokio_util::sync::CancellationToken;
use windows_service::service::{
    ServiceAccess, ServiceAction, ServiceActionType, ServiceControl, ServiceControlAccept,
    ServiceErrorControl, ServiceExitCode, ServiceFailureActions, ServiceFailureResetPeriod,
    ServiceInfo, ServiceStartType, ServiceState, ServiceStatus, ServiceType,
};
use windows_service::service_control_handler::{self, ServiceControlHandlerResult};
use windows_service::service_manager::{ServiceManager as Manager, ServiceManagerAccess};

/// `ERROR_SERVICE_DOES_NOT_EXIST`
const NO_SUCH_SERVICE: i32 = 1060;

/// The local service manager. Keeps the handle of the service it created, so configuring it
/// does not depend on opening it again.
#[derive(Default)]
pub struct Scm {
    created: std::cell::RefCell<Option<windows_service::service::Service>>,
}

impl Scm {
    fn manager(access: ServiceManagerAccess) -> Result<Manager, Error> {
        Manager::local_computer(None::<&str>, access).map_err(|e| {
            format!(
                "cannot open the service manager ({}); run this from an administrator prompt",
                describe(e)
            )
            .into()
        })
    }

    /// Runs `f` on the service created by `create`, or else on the service opened with `access`.
    fn with_created<T>(
        &self,
        access: ServiceAccess,
        f: impl FnOnce(&windows_service::service::Service) -> Result<T, Error>,
    ) -> Result<T, Error> {
        if let Some(service) = self.created.borrow().as_ref() {
            return f(service);
        }
        f(&Self::open(access)?)
    }

    fn open(access: ServiceAccess) -> Result<windows_service::service::Service, Error> {
        Self::manager(ServiceManagerAccess::CONNECT)?
            .open_service(SERVICE_NAME, access)
            .map_err(|e| format!("cannot open service {SERVICE_NAME}: {}", describe(e)).into())
    }
}

/// The crate's error with the Windows error behind it ("IO error in winapi call" alone says
/// nothing).
fn describe(e: windows_service::Error) -> Error {
    match &e {
        windows_service::Error::Winapi(io) => format!("{e}: {io}").into(),
        _ => e.to_string().into(),
    }
}

fn is_missing(e: &windows_service::Error) -> bool {
    matches!(e, windows_service::Error::Winapi(io) if io.raw_os_error() == Some(NO_SUCH_SERVICE))
}

impl ServiceManager for Scm {
    fn state(&self) -> Result<Option<State>, Error> {
        let service = match Self::manager(ServiceManagerAccess::CONNECT)?
            .open_service(SERVICE_NAME, ServiceAccess::QUERY_STATUS)
        {
            Ok(s) => s,
            Err(e) if is_missing(&e) => return Ok(None),
            Err(e) => {
                return Err(format!("cannot open service {SERVICE_NAME}: {}", describe(e)).into())
            }
        };
        let status = service.query_status().map_err(describe)?;
        Ok(Some(match status.current_state {
            ServiceState::Stopped => State::Stopped,
            ServiceState::StartPending => State::StartPending,
            ServiceState::Running => State::Running,
            ServiceState::StopPending => State::StopPending,
            _ => State::Other,
        }))
    }

    fn command_line(&self) -> Result<Option<String>, Error> {
        let service = match Self::manager(ServiceManagerAccess::CONNECT)?
            .open_service(SERVICE_NAME, ServiceAccess::QUERY_CONFIG)
        {
            Ok(s) => s,
            Err(e) if is_missing(&e) => return Ok(None),
            Err(e) => {
                return Err(format!("cannot open service {SERVICE_NAME}: {}", describe(e)).into())
            }
        };
        let config = service.query_config().map_err(describe)?;
        // The crate names the whole command line `executable_path`.
        Ok(Some(config.executable_path.to_string_lossy().into_owned()))
    }

    fn create(&self, spec: &ServiceSpec) -> Result<(), Error> {
        let manager =
            Self::manager(ServiceManagerAccess::CONNECT | ServiceManagerAccess::CREATE_SERVICE)?;
        let info = ServiceInfo {
            name: SERVICE_NAME.into(),
            display_name: super::DISPLAY_NAME.into(),
            service_type: ServiceType::OWN_PROCESS,
            start_type: ServiceStartType::AutoStart,
            error_control: ServiceErrorControl::Normal,
            executable_path: spec.exe.clone(),
            launch_arguments: spec.args.iter().map(OsString::from).collect(),
            dependencies: vec![],
            // LocalSystem: owns %ProgramData%\Fresa and may bind the port.
            account_name: None,
            account_password: None,
        };
        let service = manager
            .create_service(
                &info,
                ServiceAccess::CHANGE_CONFIG | ServiceAccess::START | ServiceAccess::DELETE,
            )
            .map_err(|e| format!("cannot create service {SERVICE_NAME}: {}", describe(e)))?;
        let _ = service.set_description(super::DESCRIPTION);
        *self.created.borrow_mut() = Some(service);
        Ok(())
    }

    fn restart_on_failure(&self, delay: Duration) -> Result<(), Error> {
        let restart = ServiceAction {
            action_type: ServiceActionType::Restart,
            delay,
        };
        let actions = ServiceFailureActions {
            reset_period: ServiceFailureResetPeriod::After(Duration::from_secs(24 * 3600)),
            reboot_msg: None,
            command: None,
            actions: Some(vec![restart.clone(), restart.clone(), restart]),
        };
        // A restart action needs the START right as well.
        self.with_created(ServiceAccess::CHANGE_CONFIG | ServiceAccess::START, |s| {
            s.update_failure_actions(actions).map_err(describe)
        })
    }

    fn restart_on_error_exit(&self) -> Result<(), Error> {
        self.with_created(ServiceAccess::CHANGE_CONFIG, |s| {
            s.set_failure_actions_on_non_crash_failures(true)
                .map_err(describe)
        })
    }

    fn delete(&self) -> Result<(), Error> {
        let result = self.with_created(ServiceAccess::DELETE, |s| s.delete().map_err(describe));
        *self.created.borrow_mut() = None;
        result
    }

    fn start(&self) -> Result<(), Error> {
        Self::open(ServiceAccess::START)?
            .start::<&str>(&[])
            .map_err(describe)
    }

    fn stop(&self) -> Result<(), Error> {
        Self::open(ServiceAccess::STOP)?.stop().map_err(describe)?;
        Ok(())
    }

    fn register_event_source(&self) -> Result<(), Error> {
        eventlog::register(SERVICE_NAME).map_err(|e| e.to_string().into())
    }

    fn deregister_event_source(&self) -> Result<(), Error> {
        eventlog::deregister(SERVICE_NAME).map_err(|e| e.to_string().into())
    }
}

/// The running service's status, told to the service manager.
struct ScmStatus {
    handle: service_control_handler::ServiceStatusHandle,
    checkpoint: AtomicU32,
}

impl StatusReporter for ScmStatus {
    fn report(&self, state: State, wait_hint: Duration, exit_code: u32) {
        let (current_state, pending) = match state {
            State::Stopped => (ServiceState::Stopped, false),
            State::StartPending => (ServiceState::StartPending, true),
            State::Running => (ServiceState::Running, false),
            State::StopPending | State::Other => (ServiceState::StopPending, true),
        };
        let controls_accepted = match state {
            State::StartPending | State::Running => {
                ServiceControlAccept::STOP | ServiceControlAccept::SHUTDOWN
            }
            _ => ServiceControlAccept::empty(),
        };
        let checkpoint = if pending {
            self.checkpoint.fetch_add(1, Ordering::Relaxed) + 1
        } else {
            0
        };
        let status = ServiceStatus {
            service_type: ServiceType::OWN_PROCESS,
            current_state,
            controls_accepted,
            exit_code: if exit_code == 0 {
                ServiceExitCode::NO_ERROR
            } else {
                ServiceExitCode::ServiceSpecific(exit_code)
            },
            checkpoint,
            wait_hint,
            process_id: None,
        };
        if let Err(e) = self.handle.set_service_status(status) {
            tracing::error!("cannot report the service status {state}: {e}");
        }
    }
}

/// ERROR events into the Event Log, source `Fresa` (registered by `fresa service install`).
struct EventLogSink(eventlog::EventLog);

impl logging::ErrorSink for EventLogSink {
    fn error(&self, message: &str) {
        use log::Log;
        self.0.log(
            &log::Record::builder()
                .level(log::Level::Error)
                .args(format_args!("{message}"))
                .build(),
        );
    }
}

/// `service run`'s own arguments, for the service's entry point (which the dispatcher calls
/// with the manager's start parameters, not the command line).
static DATA_DIR: OnceLock<PathBuf> = OnceLock::new();

windows_service::define_windows_service!(ffi_service_main, service_main);

/// `fresa service run`: hands the process to the service manager, which calls
/// `service_main`. Returns when the service has stopped.
pub fn dispatch(data_dir: PathBuf) -> Result<(), Error> {
    let _ = DATA_DIR.set(data_dir);
    windows_service::service_dispatcher::start(SERVICE_NAME, ffi_service_main).map_err(|e| {
        format!(
            "`fresa service run` is started by the service manager ({e}); to run the server \
             in this console use `fresa serve`"
        )
        .into()
    })
}

fn service_main(_arguments: Vec<OsString>) {
    let stop = CancellationToken::new();
    let handler_stop = stop.clone();
    let handle = match service_control_handler::register(SERVICE_NAME, move |control| {
        let control = match control {
            ServiceControl::Stop => Control::Stop,
            ServiceControl::Shutdown | ServiceControl::Preshutdown => Control::Shutdown,
            ServiceControl::Interrogate => Control::Interrogate,
            _ => Control::Other,
        };
        if handle_control(control, &handler_stop) {
            ServiceControlHandlerResult::NoError
        } else {
            ServiceControlHandlerResult::NotImplemented
        }
    }) {
        Ok(h) => h,
        // Not started by the service manager: nothing to report to, nowhere to log.
        Err(_) => return,
    };
    let reporter: Arc<dyn StatusReporter> = Arc::new(ScmStatus {
        handle,
        checkpoint: AtomicU32::new(0),
    });
    let Some(data_dir) = DATA_DIR.get().cloned() else {
        reporter.report(State::Stopped, Duration::ZERO, super::EXIT_FAILED);
        return;
    };
    let config = data_dir.join("fresa.toml");
    let settings = fresa_core::config::Settings::resolve(fresa_core::config::Overrides {
        data_dir: Some(data_dir.clone()),
        config: config.is_file().then_some(config),
        ..Default::default()
    });
    let filter = settings
        .as_ref()
        .ok()
        .and_then(|s| s.log.clone())
        .unwrap_or_else(|| logging::DEFAULT_FILTER.to_string());
    let errors = eventlog::EventLog::new(SERVICE_NAME, log::Level::Error)
        .ok()
        .map(|e| Box::new(EventLogSink(e)) as Box<dyn logging::ErrorSink>);
    // Without a log file the errors still reach the Event Log (the sink reports them directly).
    let _guard = match logging::init_service(&filter, &data_dir.join("logs"), errors) {
        Ok(g) => Some(g),
        Err(e) => {
            if let Ok(log) = eventlog::EventLog::new(SERVICE_NAME, log::Level::Error) {
                logging::ErrorSink::error(&EventLogSink(log), &e);
            }
            None
        }
    };
    let settings = match settings {
        Ok(s) => s,
        Err(e) => {
            tracing::error!("service {SERVICE_NAME} cannot start: {e}");
            reporter.report(State::Stopped, Duration::ZERO, super::EXIT_FAILED);
            return;
        }
    };
    let runtime = match tokio::runtime::Runtime::new() {
        Ok(rt) => rt,
        Err(e) => {
            tracing::error!("cannot start the async runtime: {e}");
            reporter.report(State::Stopped, Duration::ZERO, super::EXIT_FAILED);
            return;
        }
    };
    // Motion stops within 5 s, then connections get the grace period.
    let stop_wait = Duration::from_secs(10) + settings.shutdown_grace;
    let _ = runtime.block_on(run_service(
        reporter,
        stop,
        stop_wait,
        move |shutdown, ready| async move {
            crate::serve::run(settings, shutdown, ready)
                .await
                .map_err(|e| e.to_string())
        },
    ));
    runtime.shutdown_timeout(Duration::from_secs(1));
}

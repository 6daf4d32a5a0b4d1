//! `fresa`: the daemon (`fresa serve`) and its command-line client.

mod client;
// The service's logic and its log file are compiled on every platform so their tests run on
// Linux too; only Windows runs them.
#[cfg_attr(not(windows), allow(dead_code))]
mod logging;
mod serve;
#[cfg_attr(not(windows), allow(dead_code))]
mod service;

use fresa_core::config;

#[cfg(all(target_os = "linux", feature = "mimalloc"))]
mod alloc;
#[cfg(target_os = "linux")]
mod resident;

/// mimalloc on Linux (README: Measurements, "Status reads"): glibc's malloc and free were about
/// a fifth of a status request's instructions. Plugins keep their own allocator: the C ABI has
/// whoever allocates a buffer free it (`plugin-api/src/abi.rs`), so no buffer crosses heaps.
#[cfg(all(target_os = "linux", feature = "mimalloc"))]
#[global_allocator]
static ALLOCATOR: alloc::MiMalloc = alloc::MiMalloc;

use clap::{Parser, Subcommand};
use std::process::ExitCode;

#[derive(Parser)]
#[command(
    name = "fresa",
    version,
    about = "Fresa shop-floor motion-control server"
)]
struct Cli {
    #[command(subcommand)]
    command: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Run the daemon.
    Serve(ServeArgs),
    /// Machines on a running server.
    Machine {
        #[command(flatten)]
        server: client::ServerArgs,
        #[command(subcommand)]
        command: client::MachineCmd,
    },
    /// Jobs on a running server.
    Job {
        #[command(flatten)]
        server: client::ServerArgs,
        #[command(subcommand)]
        command: client::JobCmd,
    },
    /// Job queues per machine (confirm between parts) and dispatch to a free machine.
    Queue {
        #[command(flatten)]
        server: client::ServerArgs,
        #[command(subcommand)]
        command: client::queue::QueueCmd,
    },
    /// Part records: every run that ended, newest first (a table, --json or --csv).
    Parts {
        #[command(flatten)]
        server: client::ServerArgs,
        #[command(flatten)]
        args: client::PartsArgs,
    },
    /// Reports from the shop's records.
    Report {
        #[command(flatten)]
        server: client::ServerArgs,
        #[command(subcommand)]
        command: client::ReportCmd,
    },
    /// Follow a running server's event stream, one line per event.
    Events {
        #[command(flatten)]
        server: client::ServerArgs,
        #[command(flatten)]
        filter: client::EventsArgs,
    },
    /// G-code tools that need no server.
    Gcode {
        #[command(subcommand)]
        command: client::GcodeCmd,
    },
    /// API tokens (written straight to the database; run on the server host).
    Token {
        #[command(subcommand)]
        command: client::TokenCmd,
    },
    /// Copy the database to FILE (which must not exist), also while the server runs.
    Backup {
        file: std::path::PathBuf,
        #[command(flatten)]
        data: client::DataArgs,
    },
    /// The Windows service `Fresa` (run from an administrator prompt). On Linux, systemd runs
    /// the server: contrib/systemd/fresa.service.
    Service {
        #[command(subcommand)]
        command: ServiceCmd,
    },
}

#[derive(Subcommand)]
enum ServiceCmd {
    /// Register the service (starts at boot, restarts on failure) and its Event Log source.
    Install(ServiceDirArgs),
    /// Stop the service if it runs and remove it; the data directory is kept.
    Uninstall(ServiceDirArgs),
    /// Start the service and wait until it serves.
    Start(ServiceDirArgs),
    /// Stop the service (motion stopped, running jobs interrupted) and wait until it has.
    Stop,
    /// Say whether the service is installed and running.
    Status,
    /// The service's entry point, started by the service manager.
    #[command(hide = true)]
    Run(ServiceDirArgs),
}

#[derive(clap::Args)]
struct ServiceDirArgs {
    /// The service's data directory (database, programs, fresa.toml, logs\); default
    /// %ProgramData%\Fresa.
    #[arg(long)]
    data_dir: Option<std::path::PathBuf>,
}

impl ServiceDirArgs {
    /// The given directory, else the installed service's, else the default.
    #[cfg(windows)]
    fn of_installed(
        self,
        scm: &dyn service::ServiceManager,
    ) -> Result<std::path::PathBuf, Box<dyn std::error::Error>> {
        match self.data_dir {
            Some(d) => Ok(d),
            None => service::installed_data_dir(scm, config::default_data_dir())
                .map_err(|e| e.to_string())?
                .ok_or_else(|| "no data directory: pass --data-dir".into()),
        }
    }

    #[cfg_attr(not(windows), allow(dead_code))]
    fn resolve(self) -> Result<std::path::PathBuf, Box<dyn std::error::Error>> {
        self.data_dir
            .or_else(config::default_data_dir)
            .ok_or_else(|| "no data directory: pass --data-dir".into())
    }
}

#[cfg(windows)]
fn service_command(command: ServiceCmd) -> Result<(), Box<dyn std::error::Error>> {
    use service::{ServiceSpec, Waits, RESTART_DELAY};
    let scm = service::windows::Scm::default();
    let waits = Waits::default();
    let mut out = std::io::stdout();
    let r = match command {
        ServiceCmd::Install(d) => {
            let explicit = d.data_dir.is_some();
            let data_dir = d.resolve()?;
            let mut args = vec!["service".to_string(), "run".to_string()];
            if explicit {
                args.push("--data-dir".into());
                args.push(data_dir.display().to_string());
            }
            let spec = ServiceSpec {
                exe: std::env::current_exe()?,
                args,
                restart_delay: RESTART_DELAY,
            };
            service::install(&scm, &spec, &data_dir, &mut out)
        }
        ServiceCmd::Uninstall(d) => {
            let data_dir = d.of_installed(&scm)?;
            service::uninstall(&scm, waits, &data_dir, &mut out)
        }
        ServiceCmd::Start(d) => {
            let logs = d.of_installed(&scm)?.join("logs");
            service::start(&scm, waits, &logs, &mut out)
        }
        ServiceCmd::Stop => service::stop(&scm, waits, &mut out),
        ServiceCmd::Status => service::status(&scm, &mut out),
        ServiceCmd::Run(d) => service::windows::dispatch(d.resolve()?),
    };
    r.map_err(|e| e.to_string().into())
}

#[cfg(not(windows))]
fn service_command(_command: ServiceCmd) -> Result<(), Box<dyn std::error::Error>> {
    Err(
        "`fresa service` manages the Windows service; on Linux install \
         contrib/systemd/fresa.service and use systemctl"
            .into(),
    )
}

/// Command-line/environment values for `fresa serve` (clap merges them: CLI beats env).
#[derive(Debug, Default, Clone, clap::Args)]
struct ServeArgs {
    /// Address to listen on; port 0 picks a free one (the log says which).
    #[arg(long, env = "FRESA_LISTEN")]
    listen: Option<String>,
    #[arg(long, env = "FRESA_DATA_DIR")]
    data_dir: Option<std::path::PathBuf>,
    /// `postgres://USER[:PASSWORD]@HOST:PORT/DB` for a store shared by several nodes;
    /// default: the SQLite file in the data directory.
    #[arg(long, env = "FRESA_DATABASE_URL")]
    database_url: Option<String>,
    /// This node's name among nodes sharing one PostgreSQL store (default: the host name).
    #[arg(long, env = "FRESA_NODE_NAME")]
    node_name: Option<String>,
    #[arg(long, env = "FRESA_CONFIG")]
    config: Option<std::path::PathBuf>,
    /// Extra plugin directory, searched before the defaults (repeatable).
    #[arg(long = "plugin-dir", env = "FRESA_PLUGIN_DIR")]
    plugin_dirs: Vec<std::path::PathBuf>,
    #[arg(long, env = "FRESA_MAX_UPLOAD_BYTES")]
    max_upload_bytes: Option<u64>,
    /// Create a simulated machine named "demo" (real-time motion) if there is none.
    #[arg(long)]
    demo: bool,
    /// MQTT broker to bridge events to, e.g. mqtt://broker.lan:1883 (beats `[mqtt] url`).
    #[arg(long, env = "FRESA_MQTT_URL")]
    mqtt_url: Option<String>,
}

impl From<ServeArgs> for config::Overrides {
    fn from(a: ServeArgs) -> Self {
        config::Overrides {
            listen: a.listen,
            data_dir: a.data_dir,
            database_url: a.database_url,
            node_name: a.node_name,
            config: a.config,
            plugin_dirs: a.plugin_dirs,
            max_upload_bytes: a.max_upload_bytes,
            demo: a.demo,
            mqtt_url: a.mqtt_url,
        }
    }
}

/// Rust starts programs with SIGPIPE ignored, so a client command whose reader went away
/// (`fresa job watch 4 | head -2`) got EPIPE from its next `println!`, which panics. The
/// client commands take the default, as Unix tools do: the process ends quietly when its
/// output is closed. Not the server: it must outlive a client that hangs up.
fn restore_default_sigpipe() {
    #[cfg(unix)]
    // SAFETY: sets this process's disposition of one signal to the default, before any other
    // thread exists; no handler of ours is replaced.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    // The service manager's calls block (they wait for the service), and `service run` builds
    // its own runtime inside the service's thread: neither runs on this one.
    if let Cmd::Service { command } = cli.command {
        return match service_command(command) {
            Ok(()) => ExitCode::SUCCESS,
            Err(e) => {
                eprintln!("fresa: {e}");
                ExitCode::FAILURE
            }
        };
    }
    if !matches!(cli.command, Cmd::Serve(_)) {
        restore_default_sigpipe();
    }
    let rt = match tokio::runtime::Runtime::new() {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("fresa: cannot start the async runtime: {e}");
            return ExitCode::FAILURE;
        }
    };
    let result: Result<(), Box<dyn std::error::Error>> = rt.block_on(async move {
        match cli.command {
            Cmd::Serve(args) => {
                // First: a stop sent at any moment from here on shuts down cleanly.
                let shutdown = serve::wait_for_signal();
                let settings = config::Settings::resolve(args.into())?;
                logging::init_console(settings.log.as_deref().unwrap_or(logging::DEFAULT_FILTER));
                serve::run(settings, shutdown, |_| {}).await
            }
            Cmd::Machine { server, command } => client::machine(server, command).await,
            Cmd::Job { server, command } => client::job(server, command).await,
            Cmd::Queue { server, command } => client::queue::run(server, command).await,
            Cmd::Events { server, filter } => client::events(server, filter).await,
            Cmd::Parts { server, args } => client::parts(server, args).await,
            Cmd::Report { server, command } => client::report(server, command).await,
            Cmd::Token { command } => client::token(command).await,
            Cmd::Backup { file, data } => client::backup(file, data).await,
            Cmd::Gcode { command } => client::gcode(command),
            // Handled before the runtime was built.
            Cmd::Service { .. } => Ok(()),
        }
    });
    // A backend call that never returns holds its machine's call thread; those are plain OS
    // threads and do not keep the process alive, and nothing else may: exit promptly.
    rt.shutdown_timeout(std::time::Duration::from_secs(1));
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("fresa: {e}");
            ExitCode::FAILURE
        }
    }
}

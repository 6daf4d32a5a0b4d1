//! `fresa`: the daemon (`fresa serve`) and its command-line client.

mod client;
mod serve;

use fresa_core::config;

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
}

/// Command-line/environment values for `fresa serve` (clap merges them: CLI beats env).
#[derive(Debug, Default, Clone, clap::Args)]
struct ServeArgs {
    /// Address to listen on; port 0 picks a free one (the log says which).
    #[arg(long, env = "FRESA_LISTEN")]
    listen: Option<String>,
    #[arg(long, env = "FRESA_DATA_DIR")]
    data_dir: Option<std::path::PathBuf>,
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
            config: a.config,
            plugin_dirs: a.plugin_dirs,
            max_upload_bytes: a.max_upload_bytes,
            demo: a.demo,
            mqtt_url: a.mqtt_url,
        }
    }
}

fn init_logging(default: &str) {
    let filter = tracing_subscriber::EnvFilter::try_from_env("FRESA_LOG")
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default));
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
}

fn main() -> ExitCode {
    let cli = Cli::parse();
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
                let settings = config::Settings::resolve(args.into())?;
                init_logging(
                    settings
                        .log
                        .as_deref()
                        .unwrap_or("info,tower_http=warn,sqlx=warn"),
                );
                serve::run(settings).await
            }
            Cmd::Machine { server, command } => client::machine(server, command).await,
            Cmd::Job { server, command } => client::job(server, command).await,
            Cmd::Events { server, filter } => client::events(server, filter).await,
            Cmd::Token { command } => client::token(command).await,
            Cmd::Backup { file, data } => client::backup(file, data).await,
            Cmd::Gcode { command } => client::gcode(command),
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

//! `fresa`: the daemon (`fresa serve`) and its command-line client.

mod api;
mod app;
mod client;
mod config;
mod demo;
mod events;
mod jobs;
mod machines;
mod pendants;
mod plugins;
mod serve;
mod store;

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
    Serve(config::Overrides),
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
            Cmd::Serve(overrides) => {
                let settings = config::Settings::resolve(overrides)?;
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
            Cmd::Token { command } => client::token(command).await,
            Cmd::Gcode { command } => client::gcode(command),
        }
    });
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("fresa: {e}");
            ExitCode::FAILURE
        }
    }
}

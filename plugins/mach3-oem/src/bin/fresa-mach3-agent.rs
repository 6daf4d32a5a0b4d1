//! `fresa-mach3-agent`: runs in the operator's desktop session on the Mach3 PC and lets a
//! Fresa server drive Mach3 (see the crate README). `--simulate` serves a simulated Mach3
//! instead, on any OS, for tests and demos.

use clap::Parser;
use fresa_mach3_oem::agent::{Agent, AgentConfig, Mach3Factory};
use fresa_mach3_oem::mach3::Mach3;
use fresa_mach3_oem::sim::{Mach3Sim, ProbeSwitch, SimConfig};
use std::io::{BufRead, Write};
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

#[derive(Parser, Debug)]
#[command(version, about)]
struct Args {
    /// Address to listen on. Use the PC's LAN address (or 0.0.0.0) for a remote server.
    #[arg(long, default_value = "127.0.0.1:5873")]
    listen: String,
    /// File holding the shared secret (the server's machine config has the same one).
    #[arg(long, env = "FRESA_MACH3_SECRET_FILE")]
    secret_file: Option<PathBuf>,
    /// The shared secret itself; prefer --secret-file (command lines are visible to others).
    #[arg(long, env = "FRESA_MACH3_SECRET", hide_env_values = true)]
    secret: Option<String>,
    /// Where programs sent by the server are stored for Mach3's LoadFile.
    #[arg(long)]
    program_dir: Option<PathBuf>,
    /// Longest wait for one Mach3 call, in milliseconds.
    #[arg(long, default_value_t = 2000)]
    call_timeout_ms: u64,
    /// A connection silent this long is dropped and its jogs stopped, in milliseconds.
    #[arg(long, default_value_t = 3000)]
    watchdog_ms: u64,
    /// Serve a simulated Mach3 instead of the real one. Reads operator actions from stdin:
    /// `button <code>` presses an OEM button on the simulated screen, `close` / `open` quit
    /// and restart the simulated Mach3, `probe z<=-20` / `probe off` place or remove the
    /// probe's touch plate.
    #[arg(long)]
    simulate: bool,
    /// Simulator only: multiplies every motion time (0.01 = 100x faster, 0 = instant).
    #[arg(long, default_value_t = 1.0)]
    time_scale: f64,
    /// Simulator only: a probe input active while an axis's machine position is at or below
    /// (`z<=-20`) or at or above (`x>=35`) a point, e.g. a touch plate under the tool.
    #[arg(long, value_parser = ProbeSwitch::parse)]
    probe: Option<ProbeSwitch>,
}

fn secret(args: &Args) -> Result<String, String> {
    let s = match (&args.secret_file, &args.secret) {
        (Some(path), _) => std::fs::read_to_string(path)
            .map_err(|e| format!("cannot read --secret-file {}: {e}", path.display()))?,
        (None, Some(s)) => s.clone(),
        (None, None) => {
            return Err(
                "a shared secret is required: --secret-file PATH (or FRESA_MACH3_SECRET)".into(),
            )
        }
    };
    let s = s.trim().to_string();
    if s.len() < 8 {
        return Err("the shared secret must be at least 8 characters".into());
    }
    Ok(s)
}

/// Operator actions on the simulated Mach3 screen, one per stdin line.
fn operator(mut sim: Mach3Sim) {
    for line in std::io::stdin().lock().lines() {
        let Ok(line) = line else { return };
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            ["button", code] => match code.parse::<i16>() {
                Ok(c) => {
                    let _ = sim.do_oem_button(c);
                }
                Err(_) => eprintln!("simulator: `button` needs a code, got {code:?}"),
            },
            ["close"] => sim.set_running(false),
            ["open"] => sim.set_running(true),
            ["probe", "off"] => sim.set_probe(None),
            ["probe", switch] => match ProbeSwitch::parse(switch) {
                Ok(p) => sim.set_probe(Some(p)),
                Err(e) => eprintln!("simulator: {e}"),
            },
            [] => {}
            _ => eprintln!(
                "simulator: unknown operator action {line:?} (known: button <code>, close, open, \
                 probe <axis><=|>=<pos>, probe off)"
            ),
        }
    }
}

fn factory(args: &Args) -> Result<Mach3Factory, String> {
    if args.simulate {
        if !(args.time_scale.is_finite() && args.time_scale >= 0.0) {
            return Err(format!(
                "--time-scale must be 0 or more, got {}",
                args.time_scale
            ));
        }
        let sim = Mach3Sim::new(SimConfig {
            time_scale: args.time_scale,
            probe: args.probe,
            ..Default::default()
        });
        let screen = sim.clone();
        std::thread::Builder::new()
            .name("operator".into())
            .spawn(move || operator(screen))
            .map_err(|e| e.to_string())?;
        return Ok(Box::new(move || Box::new(sim) as Box<dyn Mach3>));
    }
    #[cfg(windows)]
    {
        Ok(Box::new(|| {
            Box::new(fresa_mach3_oem::com::ComMach3::new()) as Box<dyn Mach3>
        }))
    }
    #[cfg(not(windows))]
    {
        Err(
            "Mach3 is reached through COM, which exists only on Windows; use --simulate here"
                .into(),
        )
    }
}

fn main() -> ExitCode {
    let args = Args::parse();
    let run = || -> Result<(), String> {
        let secret = secret(&args)?;
        let program_dir = args
            .program_dir
            .clone()
            .unwrap_or_else(|| std::env::temp_dir().join("fresa-mach3"));
        let cfg = AgentConfig {
            secret,
            call_timeout: Duration::from_millis(args.call_timeout_ms.max(1)),
            watchdog: Duration::from_millis(args.watchdog_ms.max(100)),
            program_dir,
        };
        let agent = Agent::bind(&args.listen, cfg, factory(&args)?)
            .map_err(|e| format!("cannot listen on {}: {e}", args.listen))?;
        let addr = agent.local_addr().map_err(|e| e.to_string())?;
        // Tests and scripts read the port from this line.
        println!("listening on {addr}");
        let _ = std::io::stdout().flush();
        agent.serve();
        Ok(())
    };
    match run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("fresa-mach3-agent: {e}");
            ExitCode::FAILURE
        }
    }
}

//! `fresa serve --demo`: a simulated machine so a newcomer can try everything with curl.

use crate::app::App;
use crate::store::ToolRow;

pub const DEMO_MACHINE: &str = "demo";

pub async fn ensure_demo_machine(app: &App) {
    match app.store.machine_by_name(DEMO_MACHINE).await {
        Ok(Some(_)) => {}
        Ok(None) => {
            if app.plugins.get("sim-machine").is_none() {
                tracing::error!("--demo needs the sim-machine plugin, which is not loaded");
                return;
            }
            // Limit switches far out on X and Y, and a touch plate's probe 10 mm under Z 0, so
            // the I/O lamps have something to show (jog onto one to see an input trip) and a
            // touch-off finds the plate.
            let config = serde_json::json!({
                "time_scale": 1.0,
                "execution_log": app.settings.data_dir.join("demo-execution.log"),
                "switches": {
                    "limit_x_min": {"axis": "x", "at_or_below": -1000},
                    "limit_x_max": {"axis": "x", "at_or_above": 1000},
                    "limit_y_min": {"axis": "y", "at_or_below": -1000},
                    "limit_y_max": {"axis": "y", "at_or_above": 1000},
                    "probe": {"axis": "z", "at_or_below": -10},
                },
            });
            match app
                .store
                .insert_machine(DEMO_MACHINE, "sim-machine", &config, 50.0, 5000.0, 300.0)
                .await
            {
                Ok(id) => {
                    tracing::info!(
                        machine = id,
                        "demo machine created (sim-machine, real time)"
                    );
                    // A small tool table, so G41/G42 D1..D3 programs run on the demo.
                    let tools: Vec<ToolRow> = [
                        (1, 6.0, "6 mm flat end mill"),
                        (2, 3.0, "3 mm flat end mill"),
                        (3, 10.0, "10 mm flat end mill"),
                    ]
                    .into_iter()
                    .map(|(tool, diameter_mm, d)| ToolRow {
                        tool,
                        diameter_mm,
                        length_mm: 0.0,
                        description: d.to_string(),
                    })
                    .collect();
                    if let Err(e) = app.store.replace_tools(id, &tools).await {
                        tracing::error!(error = %e, "could not store the demo tool table");
                    }
                    // A maintenance interval, so the counters and "done" have one to show.
                    let maintenance = r#"[{"name":"lubricate","every_spindle_hours":40}]"#;
                    if let Err(e) = app.store.set_machine_maintenance(id, maintenance).await {
                        tracing::error!(error = %e, "could not store the demo maintenance interval");
                    }
                    // A tool setter on the touch plate's switch, at work zero, so "measure
                    // tool" works on the demo (T1 is the reference).
                    let settings = crate::store::RunSettings {
                        tool_setter: Some(crate::store::ToolSetter {
                            x: 0.0,
                            y: 0.0,
                            z: 0.0,
                            distance_mm: 20.0,
                            feed_mm_min: 300.0,
                            reference_tool: 1,
                        }),
                        ..Default::default()
                    };
                    if let Err(e) = app.store.set_run_settings(id, &settings, false).await {
                        tracing::error!(error = %e, "could not store the demo run settings");
                    }
                }
                Err(e) => tracing::error!(error = %e, "could not create the demo machine"),
            }
        }
        Err(e) => tracing::error!(error = %e, "could not look up the demo machine"),
    }
}

pub const DEMO_PENDANT: &str = "demo-pendant";

/// The demo pendant's simulator process, started early (see [`start_pendant_sim`]).
pub struct PendantSim {
    child: tokio::process::Child,
    lines: tokio::io::Lines<tokio::io::BufReader<tokio::process::ChildStdout>>,
}

/// Starts `mpg-pendant-sim` (found next to this executable) on a free loopback port. Called at
/// the very start, so the process starts while the store opens rather than after it (a few
/// milliseconds of a first start). The simulator exits when this process does (its stdin is a
/// pipe we hold). Missing simulator: log and go on.
pub fn start_pendant_sim() -> Option<PendantSim> {
    match spawn_pendant_sim() {
        Ok(sim) => Some(sim),
        Err(e) => {
            tracing::warn!("demo pendant not started: {e}");
            None
        }
    }
}

fn spawn_pendant_sim() -> Result<PendantSim, String> {
    use tokio::io::AsyncBufReadExt;
    let exe = std::env::current_exe().map_err(|e| e.to_string())?;
    let sim = exe
        .parent()
        .map(|d| d.join(format!("mpg-pendant-sim{}", std::env::consts::EXE_SUFFIX)))
        .filter(|p| p.is_file())
        .ok_or("mpg-pendant-sim is not next to the fresa executable (build the workspace)")?;
    let mut child = tokio::process::Command::new(&sim)
        .args(["--listen", "127.0.0.1:0", "--quiet-polls", "--exit-on-eof"])
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .kill_on_drop(true)
        .spawn()
        .map_err(|e| format!("cannot start {}: {e}", sim.display()))?;
    let stdout = child.stdout.take().ok_or("no stdout")?;
    let lines = tokio::io::BufReader::new(stdout).lines();
    Ok(PendantSim { child, lines })
}

/// Makes sure a pendant named `demo-pendant` points at the simulator `sim` started, bound to
/// the demo machine.
pub async fn ensure_demo_pendant(app: &App, sim: PendantSim) {
    if let Err(e) = try_demo_pendant(app, sim).await {
        tracing::warn!("demo pendant not started: {e}");
    }
}

async fn try_demo_pendant(app: &App, sim: PendantSim) -> Result<(), String> {
    let PendantSim {
        mut child,
        mut lines,
    } = sim;
    let first = tokio::time::timeout(std::time::Duration::from_secs(10), lines.next_line())
        .await
        .map_err(|_| "the simulator did not say where it listens".to_string())?
        .map_err(|e| e.to_string())?
        .unwrap_or_default();
    let addr = first
        .strip_prefix("listening on ")
        .ok_or_else(|| format!("unexpected simulator output {first:?}"))?
        .to_string();
    // Keep the simulator (and its stdin pipe) alive for the life of the server; show its output.
    tokio::spawn(async move {
        while let Ok(Some(l)) = lines.next_line().await {
            tracing::debug!(target: "demo_pendant", "{l}");
        }
        let _ = child.wait().await;
    });
    let machine = app
        .store
        .machine_by_name(DEMO_MACHINE)
        .await
        .map_err(|e| e.to_string())?
        .map(|m| m.id);
    let existing = app
        .store
        .list_pendants()
        .await
        .map_err(|e| e.to_string())?
        .into_iter()
        .find(|p| p.name == DEMO_PENDANT);
    match existing {
        Some(p) => app
            .store
            .set_pendant_address(p.id, &addr, machine)
            .await
            .map_err(|e| e.to_string())?,
        None => {
            app.store
                .insert_pendant(
                    DEMO_PENDANT,
                    &addr,
                    "firmware",
                    machine,
                    // The 15 mm plate of the pendant's design: Set cero leaves Z reading 15.
                    &serde_json::json!({"touch_plate_mm": 15}),
                    &[],
                )
                .await
                .map_err(|e| e.to_string())?;
        }
    }
    tracing::info!(address = %addr, "demo pendant simulator started (mpg-pendant-sim)");
    Ok(())
}

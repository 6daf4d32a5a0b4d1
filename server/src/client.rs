//! The command-line client: a thin layer over the HTTP API (and, for tokens, the database).

use clap::{Args, Subcommand};
use futures_util::StreamExt;
use serde_json::Value;
use std::path::PathBuf;

type Res = Result<(), Box<dyn std::error::Error>>;

mod heightmap;
pub mod queue;
mod records;
pub use records::{PartsArgs, ReportCmd};

#[derive(Args)]
pub struct ServerArgs {
    /// Server URL.
    #[arg(
        long,
        env = "FRESA_URL",
        default_value = "http://127.0.0.1:7878",
        global = true
    )]
    server: String,
    /// API token (needed when the server is not loopback-only).
    #[arg(long, env = "FRESA_TOKEN", global = true, hide_env_values = true)]
    token: Option<String>,
}

#[derive(Subcommand)]
pub enum MachineCmd {
    /// List machines with their state.
    List,
    /// One machine's status: state, positions, run, and its inputs and outputs.
    Status { id: i64 },
    /// End the jog under way and drop every jog still queued for the machine (from anyone);
    /// returns once motion has stopped.
    JogCancel { id: i64 },
    /// A probing move: until the probe touches (or releases), at most --distance mm. Prints
    /// the machine position where it tripped; exits 1 if the whole distance ran without
    /// contact.
    Probe {
        id: i64,
        #[arg(long, default_value = "Z")]
        axis: String,
        /// `+` or `-`.
        #[arg(long, default_value = "-", allow_hyphen_values = true)]
        toward: String,
        /// mm, at most the machine's max_jog_mm.
        #[arg(long)]
        distance: f64,
        /// mm/min, at most the machine's max_probe_feed_mm_min.
        #[arg(long)]
        feed: f64,
        /// Stop when the probe opens instead of when it closes (G38.4).
        #[arg(long)]
        release: bool,
        /// Print the server's JSON answer.
        #[arg(long)]
        json: bool,
    },
    /// Touch-off on a plate: probe down onto it, set the active work offset so Z reads the
    /// plate's thickness there, retract. Nothing changes if it does not touch. With --axis X
    /// or Y (and --toward, --tool-diameter): edge finding, the part's edge becomes 0.
    /// Find a bore's (`--kind bore`: the tool inside the hole at the probing depth) or a
    /// boss's (`--kind boss`: the tool above it) centre by probing; ends on the centre and,
    /// unless --no-zero, puts the active work offset's X/Y zero there. Prints the centre and
    /// both diameters.
    FindCentre {
        id: i64,
        /// `bore` or `boss`.
        #[arg(long, default_value = "bore")]
        kind: String,
        /// The tool's diameter, mm.
        #[arg(long)]
        tool_diameter: f64,
        /// Bore: mm to probe out each way; boss: mm to probe in (default 2 x clearance).
        #[arg(long)]
        distance: Option<f64>,
        /// mm/min, at most the machine's max_probe_feed_mm_min.
        #[arg(long)]
        feed: f64,
        /// Leave the work offset as it is.
        #[arg(long)]
        no_zero: bool,
        /// Boss: its diameter roughly, mm.
        #[arg(long)]
        boss_diameter: Option<f64>,
        /// Boss: how far outside it the tool goes down, mm.
        #[arg(long)]
        clearance: Option<f64>,
        /// Boss: how far below the start Z to probe, mm.
        #[arg(long)]
        depth: Option<f64>,
        /// Print the server's JSON answer.
        #[arg(long)]
        json: bool,
    },
    TouchOff {
        id: i64,
        #[arg(long, default_value = "Z")]
        axis: String,
        /// `+` or `-` (default `-` on Z; required on X/Y).
        #[arg(long, allow_hyphen_values = true)]
        toward: Option<String>,
        /// The tool's diameter, mm (X/Y).
        #[arg(long)]
        tool_diameter: Option<f64>,
        /// The plate's thickness, mm (0: the part itself).
        #[arg(long)]
        plate: f64,
        /// mm to probe at most.
        #[arg(long)]
        distance: f64,
        /// mm/min, at most the machine's max_probe_feed_mm_min.
        #[arg(long)]
        feed: f64,
        /// mm to move back up afterwards.
        #[arg(long, default_value_t = 5.0)]
        retract: f64,
        /// Print the server's JSON answer.
        #[arg(long)]
        json: bool,
    },
    /// Set the feed, spindle and/or rapid override in percent (also while a job runs); prints
    /// the overrides in force. Without any option, prints them.
    Override {
        id: i64,
        /// Feed override, % (the machine's range, default 10-200).
        #[arg(long)]
        feed: Option<f64>,
        /// Spindle override, % (default 50-150).
        #[arg(long)]
        spindle: Option<f64>,
        /// Rapid override, % (default 25-100).
        #[arg(long)]
        rapid: Option<f64>,
    },
    /// Measure the tool in the spindle (taken to be --tool) on the machine's tool setter and
    /// store its length (relative to the reference tool); during a tool-change hold for it,
    /// Z is zeroed again for it. Prints the length.
    MeasureTool {
        id: i64,
        #[arg(long)]
        tool: i64,
        /// Print the server's JSON answer.
        #[arg(long)]
        json: bool,
    },
    /// A machine's run settings (optional stop, what M6 does, tool-change position, tool
    /// setter); with options, change those first.
    RunSettings {
        id: i64,
        /// `on` or `off`: whether M1 holds the run.
        #[arg(long)]
        optional_stop: Option<String>,
        /// What M6 does: `hold`, `ignore` or `refuse`.
        #[arg(long)]
        tool_change: Option<String>,
    },
    /// Probe a height map: a grid over an area of the work coordinates (probe down at each
    /// point from the clearance Z). Follows it until it ends and prints the heights; exits 1
    /// unless it completed.
    HeightMap {
        id: i64,
        #[command(flatten)]
        grid: heightmap::GridArgs,
    },
    /// A machine's tool table (what G41/G42 D<n> offset by); with --load, replace it first.
    Tools {
        id: i64,
        /// A JSON file with the whole table, as `GET /api/v1/machines/{id}/tools` gives it:
        /// `[{"tool": 1, "diameter_mm": 6.0, "length_mm": 0, "description": "..."}, ...]`.
        #[arg(long)]
        load: Option<PathBuf>,
    },
}

/// Filters of `fresa events`.
#[derive(Args)]
pub struct EventsArgs {
    /// Comma-separated event types; `job` matches `job.*` (e.g. `job,machine.alarm`). Without
    /// it every type but `status`, which repeats up to 10 times a second per machine while one
    /// moves (ask for it with `--types status`).
    #[arg(long)]
    types: Option<String>,
    /// Only this machine's events.
    #[arg(long)]
    machine: Option<i64>,
    /// Replay persisted events after this id first (0: the whole log), then follow.
    #[arg(long)]
    after: Option<i64>,
    /// One JSON object per line (the stream's `data`), for scripts.
    #[arg(long)]
    json: bool,
}

#[derive(Subcommand)]
pub enum JobCmd {
    /// Upload a G-code file as a job.
    Submit {
        file: PathBuf,
        #[arg(long)]
        machine: i64,
        #[arg(long)]
        name: Option<String>,
        /// Start the job right after the upload.
        #[arg(long)]
        start: bool,
    },
    /// Follow a job's progress until it ends.
    Watch { id: i64 },
    // --- start at a line (issue 26), height maps (issue 25) ---
    /// Start a job: from its first line, or with `--from-line N` from line N (the lines
    /// before it are interpreted without motion; the machine goes up to a safe Z, takes their
    /// work offset, spindle and coolant, moves across to the start point and down at feed,
    /// then runs from N; see `start-preview`).
    Start {
        id: i64,
        #[arg(long)]
        from_line: Option<u32>,
        /// Apply this height map of the job's machine (`fresa machine height-map`): every
        /// move's Z follows the probed surface.
        #[arg(long)]
        height_map: Option<i64>,
    },
    /// Show what `start --from-line N` would do from where the machine stands: the modal
    /// state before line N and the preamble, as G-code-like text (or `--json`). Moves nothing.
    StartPreview {
        id: i64,
        #[arg(long)]
        from_line: u32,
        /// The server's whole answer as JSON.
        #[arg(long)]
        json: bool,
    },
}

/// Where the database is: the same settings `fresa serve` resolves.
#[derive(Args)]
pub struct DataArgs {
    #[arg(long, env = "FRESA_DATA_DIR")]
    data_dir: Option<PathBuf>,
    #[arg(long, env = "FRESA_DATABASE_URL")]
    database_url: Option<String>,
    #[arg(long, env = "FRESA_CONFIG")]
    config: Option<PathBuf>,
}

impl DataArgs {
    fn settings(self) -> Result<fresa_core::config::Settings, Box<dyn std::error::Error>> {
        Ok(fresa_core::config::Settings::resolve(
            fresa_core::config::Overrides {
                data_dir: self.data_dir,
                database_url: self.database_url,
                config: self.config,
                ..Default::default()
            },
        )?)
    }
}

#[derive(Subcommand)]
pub enum TokenCmd {
    /// Create a token and print its secret (shown once). Names are unique.
    Create {
        #[arg(long, value_parser = ["viewer", "operator", "admin"])]
        role: String,
        #[arg(long, default_value = "cli")]
        name: String,
        /// The token stops working this many days from now (default: never); fractions are
        /// allowed (0.5 = 12 hours).
        #[arg(long, value_parser = parse_days)]
        expires_in_days: Option<f64>,
        #[command(flatten)]
        data: DataArgs,
    },
    /// List tokens: name, role, created, expires, last used (UTC). Secrets are never shown.
    List {
        #[command(flatten)]
        data: DataArgs,
    },
    /// Revoke a token by name: it stops working at once, also for a running server.
    Revoke {
        name: String,
        #[command(flatten)]
        data: DataArgs,
    },
}

/// A rate in mm/min that an estimate can divide by: finite and more than 0.
fn positive_mm_min(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        Ok(v) => Err(format!("{v} is not a rate: it must be more than 0 mm/min")),
        Err(_) => Err(format!("{s:?} is not a number of mm/min")),
    }
}

/// Why a request did not reach the server, and what to do about it.
fn unreachable(base: &str, e: impl std::fmt::Display) -> String {
    format!(
        "cannot reach the server at {base}: {e}; is `fresa serve` running there? Name another \
         one with --server URL or the FRESA_URL environment variable"
    )
}

#[derive(Subcommand)]
pub enum GcodeCmd {
    /// Interpret a whole program as the server would on upload: print its analysis, or the first
    /// error with line and column (exit status 1).
    Check {
        file: PathBuf,
        /// Rapid rate assumed for the time estimate, mm/min (more than 0).
        #[arg(long, default_value_t = 5000.0, value_parser = positive_mm_min)]
        rapid: f64,
        /// Print the analysis as JSON.
        #[arg(long)]
        json: bool,
        /// The tool table for G41/G42 D<n>: a JSON file as `fresa machine tools` loads and the
        /// API gives (`[{"tool": 1, "diameter_mm": 6.0}, ...]`). Without it: no tools.
        #[arg(long)]
        tools: Option<PathBuf>,
        /// The work budget: most segments (moves, and arcs as 0.002 mm chords) the program
        /// may linearise to; the server's `max_program_segments`.
        #[arg(long, default_value_t = fresa_gcode::DEFAULT_MAX_SEGMENTS)]
        max_segments: u64,
    },
}

struct Client {
    http: reqwest::Client,
    base: String,
    token: Option<String>,
}

impl Client {
    fn new(a: ServerArgs) -> Self {
        Client {
            http: reqwest::Client::new(),
            base: a.server.trim_end_matches('/').to_string(),
            token: a.token,
        }
    }

    fn req(&self, method: reqwest::Method, path: &str) -> reqwest::RequestBuilder {
        let r = self.http.request(method, format!("{}{}", self.base, path));
        match &self.token {
            Some(t) => r.bearer_auth(t),
            None => r,
        }
    }

    async fn send(&self, rb: reqwest::RequestBuilder) -> Result<Value, Box<dyn std::error::Error>> {
        let resp = rb.send().await.map_err(|e| unreachable(&self.base, e))?;
        let status = resp.status();
        let body: Value = resp.json().await.unwrap_or(Value::Null);
        if !status.is_success() {
            let msg = body
                .get("message")
                .and_then(Value::as_str)
                .unwrap_or("request failed");
            let code = body.get("code").and_then(Value::as_str).unwrap_or("");
            return Err(format!("{status} {code}: {msg}").into());
        }
        Ok(body)
    }
}

/// `fresa parts`.
pub async fn parts(server: ServerArgs, args: PartsArgs) -> Res {
    records::parts(Client::new(server), args).await
}

/// `fresa report ...`.
pub async fn report(server: ServerArgs, cmd: ReportCmd) -> Res {
    records::report(Client::new(server), cmd).await
}

pub async fn machine(server: ServerArgs, cmd: MachineCmd) -> Res {
    let c = Client::new(server);
    match cmd {
        MachineCmd::List => {
            let v = c
                .send(c.req(reqwest::Method::GET, "/api/v1/machines"))
                .await?;
            let mut rows = vec![["ID", "NAME", "BACKEND", "NODE", "STATE"].map(String::from)];
            for m in v.as_array().into_iter().flatten() {
                let text = |k: &str| m[k].as_str().unwrap_or("").to_string();
                rows.push([
                    m["id"].to_string(),
                    text("name"),
                    text("backend"),
                    text("node"),
                    text("state"),
                ]);
            }
            print!("{}", columns(&rows));
        }
        MachineCmd::Status { id } => {
            let s = c
                .send(c.req(
                    reqwest::Method::GET,
                    &format!("/api/v1/machines/{id}/status"),
                ))
                .await?;
            print!("{}", status_text(&s));
        }
        MachineCmd::HeightMap { id, grid } => return heightmap::probe(&c, id, grid).await,
        MachineCmd::JogCancel { id } => {
            let v = c
                .send(c.req(
                    reqwest::Method::POST,
                    &format!("/api/v1/machines/{id}/jog/cancel"),
                ))
                .await?;
            if v["stopped"] == true {
                println!("machine {id}: jog stopped, queued jogs dropped");
            } else {
                println!("machine {id}: was not moving; queued jogs dropped");
            }
        }
        MachineCmd::Probe {
            id,
            axis,
            toward,
            distance,
            feed,
            release,
            json,
        } => {
            let body = serde_json::json!({
                "axis": axis.to_ascii_uppercase(), "toward": toward, "distance": distance,
                "feed": feed, "until": if release { "release" } else { "contact" },
            });
            let v = c
                .send(
                    c.req(
                        reqwest::Method::POST,
                        &format!("/api/v1/machines/{id}/probe"),
                    )
                    .json(&body),
                )
                .await?;
            if json {
                println!("{v}");
            }
            if v["outcome"] != "tripped" {
                return Err(format!(
                    "machine {id}: no {} within {distance} mm (stopped at {})",
                    if release { "release" } else { "contact" },
                    position_text(&v["position"])
                )
                .into());
            }
            if !json {
                println!(
                    "machine {id}: probe tripped at {} (came to rest {:.4} mm past it)",
                    position_text(&v["trip"]),
                    v["overshoot_mm"].as_f64().unwrap_or_default()
                );
            }
        }
        MachineCmd::FindCentre {
            id,
            kind,
            tool_diameter,
            distance,
            feed,
            no_zero,
            boss_diameter,
            clearance,
            depth,
            json,
        } => {
            let mut body = serde_json::json!({
                "kind": kind, "tool_diameter_mm": tool_diameter, "feed": feed,
                "set_zero": !no_zero,
            });
            for (k, v) in [
                ("distance", distance),
                ("boss_diameter_mm", boss_diameter),
                ("clearance_mm", clearance),
                ("depth_mm", depth),
            ] {
                if let Some(v) = v {
                    body[k] = v.into();
                }
            }
            let v = c
                .send(
                    c.req(
                        reqwest::Method::POST,
                        &format!("/api/v1/machines/{id}/find-centre"),
                    )
                    .json(&body),
                )
                .await?;
            if json {
                println!("{v}");
            } else {
                let n = |k: &str| v[k].as_f64().unwrap_or_default();
                println!(
                    "machine {id}: {kind} centre at machine X{:.4} Y{:.4}, diameter X {:.4} Y {:.4}{}",
                    v["centre"]["x"].as_f64().unwrap_or_default(),
                    v["centre"]["y"].as_f64().unwrap_or_default(),
                    n("diameter_x"),
                    n("diameter_y"),
                    v["offset"]
                        .as_str()
                        .map(|o| format!("; {o} X/Y zero set there"))
                        .unwrap_or_default()
                );
            }
        }
        MachineCmd::TouchOff {
            id,
            axis,
            toward,
            tool_diameter,
            plate,
            distance,
            feed,
            retract,
            json,
        } => {
            let axis = axis.to_ascii_uppercase();
            let mut body = serde_json::json!({
                "axis": axis, "plate_mm": plate, "distance": distance, "feed": feed,
                "retract_mm": retract,
            });
            if let Some(t) = toward {
                body["toward"] = t.into();
            }
            if let Some(d) = tool_diameter {
                body["tool_diameter_mm"] = d.into();
            }
            let v = c
                .send(
                    c.req(
                        reqwest::Method::POST,
                        &format!("/api/v1/machines/{id}/touch-off"),
                    )
                    .json(&body),
                )
                .await?;
            if json {
                println!("{v}");
            } else {
                let a = axis.to_ascii_lowercase();
                let n = |k: &str| v[k][a.as_str()].as_f64().unwrap_or_default();
                println!(
                    "machine {id}: touched the {plate} mm plate at machine {axis} {:.4}; {} {axis} {:.4} -> {:.4}; {axis} now reads {:.4}",
                    n("trip"),
                    v["offset"].as_str().unwrap_or("offset"),
                    n("before"),
                    n("after"),
                    n("work_position"),
                );
            }
        }
        MachineCmd::MeasureTool { id, tool, json } => {
            let v = c
                .send(c.req(
                    reqwest::Method::POST,
                    &format!("/api/v1/machines/{id}/tools/{tool}/measure"),
                ))
                .await?;
            if json {
                println!("{v}");
            } else {
                let n = |k: &str| v[k].as_f64().unwrap_or_default();
                println!(
                    "machine {id}: T{tool} tripped the setter at machine Z {:.4}; length {:.4} mm (reference Z {:.4})",
                    n("trip_z"),
                    n("length_mm"),
                    n("reference_z"),
                );
                if let Some(r) = v.get("rezero").filter(|r| !r.is_null()) {
                    println!(
                        "Z zeroed again for T{tool}: {} Z {:.4} -> {:.4} (T{} was {:.4} mm)",
                        r["offset"].as_str().unwrap_or("offset"),
                        r["before"]["z"].as_f64().unwrap_or_default(),
                        r["after"]["z"].as_f64().unwrap_or_default(),
                        r["from_tool"],
                        r["from_length_mm"].as_f64().unwrap_or_default(),
                    );
                }
                if let Some(note) = v["note"].as_str() {
                    println!("{note}");
                }
            }
        }
        MachineCmd::RunSettings {
            id,
            optional_stop,
            tool_change,
        } => {
            let mut changes = serde_json::Map::new();
            if let Some(o) = optional_stop {
                let on = match o.as_str() {
                    "on" | "true" => true,
                    "off" | "false" => false,
                    other => {
                        return Err(
                            format!("--optional-stop takes `on` or `off`, got {other:?}").into(),
                        )
                    }
                };
                changes.insert("optional_stop".into(), on.into());
            }
            if let Some(t) = tool_change {
                changes.insert("tool_change".into(), t.into());
            }
            let path = format!("/api/v1/machines/{id}/run-settings");
            let v = if changes.is_empty() {
                c.send(c.req(reqwest::Method::GET, &path)).await?
            } else {
                c.send(c.req(reqwest::Method::PATCH, &path).json(&changes))
                    .await?
            };
            println!("{}", serde_json::to_string_pretty(&v)?);
        }
        MachineCmd::Override {
            id,
            feed,
            spindle,
            rapid,
        } => {
            let v = if feed.is_none() && spindle.is_none() && rapid.is_none() {
                let st = c
                    .send(c.req(
                        reqwest::Method::GET,
                        &format!("/api/v1/machines/{id}/status"),
                    ))
                    .await?;
                serde_json::json!({"feed": st["feed_override"], "spindle": st["spindle_override"], "rapid": st["rapid_override"]})
            } else {
                let mut body = serde_json::json!({});
                for (k, v) in [("feed", feed), ("spindle", spindle), ("rapid", rapid)] {
                    if let Some(v) = v {
                        body[k] = v.into();
                    }
                }
                c.send(
                    c.req(
                        reqwest::Method::POST,
                        &format!("/api/v1/machines/{id}/overrides"),
                    )
                    .json(&body),
                )
                .await?
            };
            let pct = |k: &str| v[k].as_f64().unwrap_or(100.0);
            println!(
                "machine {id}: feed {}%, spindle {}%, rapid {}%",
                pct("feed"),
                pct("spindle"),
                pct("rapid")
            );
        }
        MachineCmd::Tools { id, load } => {
            let path = format!("/api/v1/machines/{id}/tools");
            let v = match load {
                Some(file) => {
                    let table = read_tool_file(&file)?;
                    c.send(c.req(reqwest::Method::PUT, &path).json(&table))
                        .await?
                }
                None => c.send(c.req(reqwest::Method::GET, &path)).await?,
            };
            let mut rows =
                vec![["TOOL", "DIAMETER MM", "LENGTH MM", "DESCRIPTION"].map(String::from)];
            for t in v.as_array().into_iter().flatten() {
                rows.push([
                    t["tool"].to_string(),
                    t["diameter_mm"].to_string(),
                    t["length_mm"].to_string(),
                    t["description"].as_str().unwrap_or("").to_string(),
                ]);
            }
            print!("{}", columns(&rows));
        }
    }
    Ok(())
}

/// `X1.0000 Y2.0000 Z3.0000` from an `{"x", "y", "z"}` object.
fn position_text(v: &Value) -> String {
    ["x", "y", "z"]
        .map(|a| {
            format!(
                "{}{:.4}",
                a.to_ascii_uppercase(),
                v[a].as_f64().unwrap_or_default()
            )
        })
        .join(" ")
}

/// A tool-table file: the API's JSON array. Errors name the file and what is wrong.
fn read_tool_file(file: &std::path::Path) -> Result<Value, Box<dyn std::error::Error>> {
    let text = std::fs::read_to_string(file)
        .map_err(|e| format!("cannot read {}: {e}", file.display()))?;
    let v: Value = serde_json::from_str(&text)
        .map_err(|e| format!("{}: not a JSON tool table: {e}", file.display()))?;
    if !v.is_array() {
        return Err(format!(
            "{}: a tool table is a JSON array of {{\"tool\", \"diameter_mm\", ...}}",
            file.display()
        )
        .into());
    }
    Ok(v)
}

/// A tool-table file as the interpreter takes it (for `fresa gcode check --tools`).
fn gcode_tools(
    file: &std::path::Path,
) -> Result<fresa_gcode::ToolTable, Box<dyn std::error::Error>> {
    #[derive(serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    struct Entry {
        tool: u32,
        diameter_mm: f64,
        #[serde(default)]
        length_mm: f64,
        #[serde(default)]
        #[allow(dead_code)] // accepted so the API's own output loads
        description: String,
    }
    let v = read_tool_file(file)?;
    let entries: Vec<Entry> =
        serde_json::from_value(v).map_err(|e| format!("{}: {e}", file.display()))?;
    Ok(fresa_gcode::tool_table(
        entries
            .into_iter()
            .map(|e| (e.tool, e.diameter_mm, e.length_mm)),
    ))
}

/// `fresa machine status`: what an operator reads at a glance, lamps last.
fn status_text(s: &serde_json::Value) -> String {
    let axes = |p: &serde_json::Value| {
        ["x", "y", "z", "a"]
            .iter()
            .map(|a| format!("{}{:.3}", a.to_uppercase(), p[*a].as_f64().unwrap_or(0.0)))
            .collect::<Vec<_>>()
            .join(" ")
    };
    let mut out = format!("state:    {}", s["state"].as_str().unwrap_or("?"));
    for why in ["alarm", "reason"] {
        if let Some(m) = s[why].as_str() {
            out.push_str(&format!(" ({m})"));
        }
    }
    out.push_str(&format!(
        "\nwork:     {}  [{}]\nmachine:  {}\nfeed:     {} mm/min ({}%)\n",
        axes(&s["work_position"]),
        s["active_offset"].as_str().unwrap_or("?"),
        axes(&s["machine_position"]),
        s["feed"].as_f64().unwrap_or(0.0),
        s["feed_override"].as_f64().unwrap_or(100.0),
    ));
    if let Some(run) = s["run"].as_i64() {
        out.push_str(&format!("run:      {run} at line {}\n", s["line"]));
    }
    // A lamp per supported name: ON / off, `?` while unknown; none at all when unsupported.
    for (label, key) in [("inputs:  ", "inputs"), ("outputs: ", "outputs")] {
        let lamps: Vec<String> = s[key]
            .as_object()
            .into_iter()
            .flatten()
            .map(|(name, v)| match v {
                serde_json::Value::Bool(true) => format!("{name} ON"),
                serde_json::Value::Bool(false) => format!("{name} off"),
                serde_json::Value::Null => format!("{name} ?"),
                other => format!("{name} {other}"),
            })
            .collect();
        let shown = if lamps.is_empty() {
            "none reported".to_string()
        } else {
            lamps.join(", ")
        };
        out.push_str(&format!("{label} {shown}\n"));
    }
    out
}

/// Rows as left-aligned columns, each as wide as its widest cell (the last one unpadded).
fn columns<const N: usize>(rows: &[[String; N]]) -> String {
    let mut widths = [0usize; N];
    for r in rows {
        for (w, cell) in widths.iter_mut().zip(r) {
            *w = (*w).max(cell.chars().count());
        }
    }
    let mut out = String::new();
    for r in rows {
        let cells: Vec<String> = r
            .iter()
            .zip(widths)
            .enumerate()
            .map(|(i, (cell, w))| {
                if i + 1 == N {
                    cell.clone()
                } else {
                    format!("{cell:<w$}")
                }
            })
            .collect();
        out.push_str(&cells.join("  "));
        out.push('\n');
    }
    out
}

/// `H:MM:SS`.
fn clock(d: std::time::Duration) -> String {
    let t = d.as_secs();
    format!("{}:{:02}:{:02}", t / 3600, t / 60 % 60, t % 60)
}

/// How `job watch` shows progress: a bar on a terminal, one line per update otherwise (logs,
/// pipes, CI).
enum Progress {
    Bar(indicatif::ProgressBar),
    Lines,
}

impl Progress {
    fn new(total: u64, line: u64, elapsed: std::time::Duration) -> Progress {
        use std::io::IsTerminal;
        if !std::io::stdout().is_terminal() {
            return Progress::Lines;
        }
        let bar = indicatif::ProgressBar::new(total.max(1)).with_elapsed(elapsed);
        // The time left is the server's (its estimate by line, under the overrides in
        // force), not a rate extrapolated from the lines so far, which swings with every
        // short or long stretch of the program.
        let style = indicatif::ProgressStyle::with_template(
            "[{bar:30}] line {pos}/{len} {percent}%  elapsed {elapsed_precise}  remaining {msg}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
        .progress_chars("=> ");
        bar.set_style(style);
        bar.set_position(line);
        bar.set_message("?");
        Progress::Bar(bar)
    }

    /// `remaining_s`: the server's time left (`remaining_s` of the job's progress; absent
    /// for a job without an estimate).
    fn update(
        &self,
        line: u64,
        total: u64,
        percent: &Value,
        elapsed: std::time::Duration,
        remaining_s: Option<f64>,
    ) {
        let remaining = remaining_s
            .filter(|r| r.is_finite() && *r >= 0.0)
            .map(|r| clock(std::time::Duration::from_secs_f64(r)))
            .unwrap_or_else(|| "?".into());
        match self {
            Progress::Bar(bar) => {
                bar.set_length(total.max(1));
                bar.set_position(line);
                bar.set_message(remaining);
            }
            Progress::Lines => {
                println!(
                    "line {line}/{total} ({percent}%)  elapsed {}  remaining {remaining}",
                    clock(elapsed)
                );
            }
        }
    }

    fn finish(&self) {
        if let Progress::Bar(bar) = self {
            bar.finish_and_clear();
        }
    }
}

/// Reads a Server-Sent Events response; `on_event` gets each event's `data` as JSON and returns
/// false to stop. Errs when the stream breaks; Ok(false) when the server ended it.
async fn follow_events(
    resp: reqwest::Response,
    mut on_event: impl FnMut(Value) -> bool,
) -> Result<bool, Box<dyn std::error::Error>> {
    let mut stream = resp.bytes_stream();
    let mut buf = String::new();
    while let Some(chunk) = stream.next().await {
        buf.push_str(&String::from_utf8_lossy(&chunk?));
        while let Some(end) = buf.find("\n\n") {
            let block: String = buf.drain(..end + 2).collect();
            let data: String = block
                .lines()
                .filter_map(|l| l.strip_prefix("data:"))
                .map(str::trim_start)
                .collect();
            let Ok(ev) = serde_json::from_str::<Value>(&data) else {
                continue;
            };
            if !on_event(ev) {
                return Ok(true);
            }
        }
    }
    Ok(false)
}

/// `fresa events`: follows the event stream, one line per event.
pub async fn events(server: ServerArgs, f: EventsArgs) -> Res {
    let c = Client::new(server);
    let mut query: Vec<(&str, String)> = Vec::new();
    if let Some(t) = &f.types {
        query.push(("types", t.clone()));
    }
    if let Some(m) = f.machine {
        query.push(("machine", m.to_string()));
    }
    if let Some(a) = f.after {
        query.push(("after", a.to_string()));
    }
    let resp = c
        .req(reqwest::Method::GET, "/api/v1/events")
        .query(&query)
        .send()
        .await
        .map_err(|e| unreachable(&c.base, e))?;
    if !resp.status().is_success() {
        let status = resp.status();
        let body: Value = resp.json().await.unwrap_or(Value::Null);
        return Err(format!(
            "{status} {}: {}",
            body["code"].as_str().unwrap_or(""),
            body["message"].as_str().unwrap_or("events refused")
        )
        .into());
    }
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    let hide_status = f.types.is_none();
    let ended = !follow_events(resp, |ev| {
        if hide_status && ev["type"] == "status" {
            return true;
        }
        let line = if f.json {
            ev.to_string()
        } else {
            let id = ev["id"]
                .as_i64()
                .map(|i| format!("#{i} "))
                .unwrap_or_default();
            let machine = ev["machine"]
                .as_i64()
                .map(|m| format!(" machine={m}"))
                .unwrap_or_default();
            let actor = ev["actor"]
                .as_str()
                .map(|a| format!(" actor={a}"))
                .unwrap_or_default();
            format!(
                "{}{} {}{machine}{actor} {}",
                id,
                fresa_core::store::utc_text(ev["time"].as_i64().unwrap_or(0), true),
                ev["type"].as_str().unwrap_or("?"),
                ev["data"]
            )
        };
        // A closed pipe (`| head`) ends the command instead of failing it.
        writeln!(out, "{line}").and_then(|_| out.flush()).is_ok()
    })
    .await?;
    if ended {
        return Err("the server closed the event stream".into());
    }
    Ok(())
}

/// How `job watch` ends once the job has: success only for `completed`, so a script's
/// `fresa job watch 4 && next-step` does not go on after a cancelled or failed job.
fn ended(id: i64, state: &str) -> Res {
    if state == "completed" {
        Ok(())
    } else {
        Err(format!("job {id} ended {state}").into())
    }
}

fn is_terminal(state: &str) -> bool {
    matches!(state, "completed" | "failed" | "cancelled" | "interrupted")
}

pub async fn job(server: ServerArgs, cmd: JobCmd) -> Res {
    let c = Client::new(server);
    match cmd {
        JobCmd::Submit {
            file,
            machine,
            name,
            start,
        } => {
            let f = tokio::fs::File::open(&file)
                .await
                .map_err(|e| format!("cannot open {}: {e}", file.display()))?;
            let name = name.unwrap_or_else(|| {
                file.file_name()
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_default()
            });
            let body = reqwest::Body::wrap_stream(tokio_util::io::ReaderStream::new(f));
            let v = c
                .send(
                    c.req(reqwest::Method::POST, "/api/v1/jobs")
                        .query(&[("machine", machine.to_string()), ("name", name)])
                        .body(body),
                )
                .await?;
            let id = v["id"].as_i64().ok_or("server answered without a job id")?;
            println!(
                "job {id} stored ({} lines, sha256 {})",
                v["line_count"],
                v["sha256"].as_str().unwrap_or("")
            );
            if start {
                let r = c
                    .send(c.req(reqwest::Method::POST, &format!("/api/v1/jobs/{id}/start")))
                    .await?;
                println!("job {id} {}", r["state"].as_str().unwrap_or("?"));
            }
        }
        JobCmd::Start {
            id,
            from_line,
            height_map,
        } => {
            let mut body = serde_json::json!({});
            if let Some(n) = from_line {
                body["from_line"] = n.into();
            }
            if let Some(h) = height_map {
                body["height_map"] = h.into();
            }
            let r = c
                .send(
                    c.req(reqwest::Method::POST, &format!("/api/v1/jobs/{id}/start"))
                        .json(&body),
                )
                .await?;
            let from = r["run"]["from_line"]
                .as_i64()
                .map(|n| format!(" from line {n}"))
                .unwrap_or_default();
            println!(
                "job {id} {} (run {}{from}{})",
                r["state"].as_str().unwrap_or("?"),
                r["run"]["id"],
                height_map
                    .map(|h| format!(", height map {h}"))
                    .unwrap_or_default()
            );
        }
        JobCmd::StartPreview {
            id,
            from_line,
            json,
        } => {
            let r = c
                .send(
                    c.req(
                        reqwest::Method::GET,
                        &format!("/api/v1/jobs/{id}/start-preview"),
                    )
                    .query(&[("from_line", from_line)]),
                )
                .await?;
            if json {
                println!("{}", serde_json::to_string_pretty(&r)?);
            } else {
                println!("{}", r["gcode"].as_str().unwrap_or(""));
            }
        }
        JobCmd::Watch { id } => {
            // Subscribe first, then read the current state, so no transition falls in between.
            let resp = c
                .req(reqwest::Method::GET, "/api/v1/events")
                .query(&[("types", "job")])
                .send()
                .await
                .map_err(|e| unreachable(&c.base, e))?;
            if !resp.status().is_success() {
                return Err(format!("events: {}", resp.status()).into());
            }
            let job = c
                .send(c.req(reqwest::Method::GET, &format!("/api/v1/jobs/{id}")))
                .await?;
            let state = job["state"].as_str().unwrap_or("?").to_string();
            println!(
                "job {id} {}: {state}, line {}/{}",
                job["name"].as_str().unwrap_or(""),
                job["line"],
                job["line_count"]
            );
            if is_terminal(&state) {
                return ended(id, &state);
            }
            // Elapsed counts from the run's start (it may have started before watch did).
            let now_ms = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map(|d| d.as_millis() as i64)
                .unwrap_or(0);
            let started = job["run"]["started_at"]
                .as_i64()
                .map(|t| std::time::Duration::from_millis(now_ms.saturating_sub(t).max(0) as u64))
                .unwrap_or_default();
            let watch_start = std::time::Instant::now();
            let elapsed = move || started + watch_start.elapsed();
            let progress = Progress::new(
                job["line_count"].as_u64().unwrap_or(0),
                job["line"].as_u64().unwrap_or(0),
                started,
            );
            let mut end: Option<(String, String)> = None;
            follow_events(resp, |ev| {
                if ev["data"]["job"].as_i64() != Some(id) {
                    return true;
                }
                let d = &ev["data"];
                match ev["type"].as_str() {
                    Some("job.progress") => {
                        progress.update(
                            d["line"].as_u64().unwrap_or(0),
                            d["total_lines"].as_u64().unwrap_or(0),
                            &d["percent"],
                            elapsed(),
                            d["remaining_s"].as_f64(),
                        );
                        true
                    }
                    Some("job.state") => {
                        let s = d["state"].as_str().unwrap_or("?").to_string();
                        let line = format!(
                            "{s} at line {}{}  elapsed {}",
                            d["line"],
                            d["message"]
                                .as_str()
                                .map(|m| format!(": {m}"))
                                .unwrap_or_default(),
                            clock(elapsed())
                        );
                        let done = is_terminal(&s);
                        if done {
                            end = Some((line, s));
                        } else if let Progress::Bar(bar) = &progress {
                            bar.println(line);
                        } else {
                            println!("{line}");
                        }
                        !done
                    }
                    _ => true,
                }
            })
            .await?;
            progress.finish();
            if let Some((line, state)) = end {
                println!("{line}");
                return ended(id, &state);
            }
            return Err("the server closed the event stream".into());
        }
    }
    Ok(())
}

fn parse_days(s: &str) -> Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(d) if d.is_finite() && d > 0.0 && d <= 36_500.0 => Ok(d),
        _ => Err(format!(
            "expected a number of days above 0 and at most 36500, got {s:?}"
        )),
    }
}

async fn open_store(
    settings: &fresa_core::config::Settings,
) -> Result<fresa_core::store::Store, Box<dyn std::error::Error>> {
    std::fs::create_dir_all(&settings.data_dir)
        .map_err(|e| format!("cannot create {}: {e}", settings.data_dir.display()))?;
    settings
        .open_store()
        .await
        .map_err(|e| format!("cannot open database {}: {e}", settings.database_label()).into())
}

pub async fn token(cmd: TokenCmd) -> Res {
    match cmd {
        TokenCmd::Create {
            role,
            name,
            expires_in_days,
            data,
        } => {
            let settings = data.settings()?;
            let store = open_store(&settings).await?;
            let secret = fresa_http::auth::new_secret();
            let expires_at = expires_in_days
                .map(|d| fresa_core::store::now_ms() + (d * 86_400_000.0).round() as i64);
            store
                .insert_token(
                    &name,
                    &role,
                    fresa_core::store::TokenHash::of(&secret).as_str(),
                    expires_at,
                )
                .await
                .map_err(|e| {
                    if fresa_core::store::is_unique_violation(&e) {
                        format!(
                            "a token named {name:?} exists; choose another name, or revoke it \
                             first with `fresa token revoke {name}`"
                        )
                    } else {
                        format!("cannot store the token: {e}")
                    }
                })?;
            let until = match expires_in_days {
                Some(d) => format!(", expires in {d} day(s)"),
                None => String::new(),
            };
            eprintln!(
                "token {name:?} ({role}{until}) created in {}; it is shown only now:",
                settings.database_label()
            );
            println!("{secret}");
        }
        TokenCmd::List { data } => {
            let store = open_store(&data.settings()?).await?;
            println!(
                "{:<24} {:<9} {:<17} {:<26} LAST USED",
                "NAME", "ROLE", "CREATED", "EXPIRES"
            );
            for t in store.list_tokens().await? {
                let expires = match (&t.expires, t.expired) {
                    (None, _) => "never".to_string(),
                    (Some(e), true) => format!("{e} (expired)"),
                    (Some(e), false) => e.clone(),
                };
                println!(
                    "{:<24} {:<9} {:<17} {:<26} {}",
                    t.name,
                    t.role,
                    t.created,
                    expires,
                    t.last_used.as_deref().unwrap_or("never")
                );
            }
        }
        TokenCmd::Revoke { name, data } => {
            let store = open_store(&data.settings()?).await?;
            if !store.revoke_token(&name).await? {
                return Err(format!(
                    "no token named {name:?} (`fresa token list` shows the names)"
                )
                .into());
            }
            eprintln!("token {name:?} revoked");
        }
    }
    Ok(())
}

/// `fresa backup FILE`: an online copy of the database, safe while the server runs.
pub async fn backup(file: PathBuf, data: DataArgs) -> Res {
    let settings = data.settings()?;
    if settings.database_url.is_some() {
        return Err(format!(
            "`fresa backup` copies the embedded store in the data directory; this server uses \
             {} (database_url): back that up with its own tools (pg_dump for PostgreSQL)",
            settings.database_label()
        )
        .into());
    }
    let db = settings.db_path();
    let bytes = fresa_core::store::backup_database(&db, &file).await?;
    eprintln!(
        "backed up {} to {} ({bytes} bytes); programs are in {} (copy them too)",
        db.display(),
        file.display(),
        settings.programs_dir().display()
    );
    Ok(())
}

/// The checks an upload makes as the program streams in (`fresa_core::programs`), on `f`.
fn upload_checks(mut f: std::fs::File) -> Result<(), Box<dyn std::error::Error>> {
    use std::io::Read;
    let mut checker = fresa_core::programs::ProgramChecker::default();
    let mut buf = vec![0u8; 1 << 16];
    loop {
        let n = f.read(&mut buf)?;
        if n == 0 {
            break;
        }
        checker.feed(&buf[..n]).map_err(|e| e.message)?;
    }
    checker.finish().map_err(|e| e.message)?;
    Ok(())
}

pub fn gcode(cmd: GcodeCmd) -> Res {
    match cmd {
        GcodeCmd::Check {
            file,
            rapid,
            json,
            tools,
            max_segments,
        } => {
            let tools = match tools {
                Some(t) => gcode_tools(&t)?,
                None => fresa_gcode::ToolTable::new(),
            };
            // The upload's own first checks (UTF-8, no binary, not empty), in its words, before
            // the interpreter: `gcode check` and an upload fail on the same first error.
            if std::fs::metadata(&file).is_ok_and(|m| m.is_dir()) {
                return Err(format!("{} is a directory, not a G-code file", file.display()).into());
            }
            let open = || {
                std::fs::File::open(&file)
                    .map_err(|e| format!("cannot open {}: {e}", file.display()))
            };
            upload_checks(open()?).map_err(|e| format!("{}: {e}", file.display()))?;
            let f = open()?;
            let opts = fresa_gcode::AnalysisOptions {
                rapid_mm_min: rapid,
                config: fresa_gcode::Config {
                    tools,
                    ..Default::default()
                },
                max_segments,
                profile: None,
            };
            let mut a = fresa_gcode::analyse(std::io::BufReader::with_capacity(1 << 16, f), &opts)
                .map_err(|e| match e.kind {
                    fresa_gcode::ErrorKind::Budget => format!(
                        "{}: {e}; raise it with --max-segments (on the server: \
                         max_program_segments)",
                        file.display()
                    ),
                    _ => format!("{}: {e}", file.display()),
                })?;
            if a.probe_moves > 0 {
                let reader = || open().map(|f| std::io::BufReader::with_capacity(1 << 16, f));
                a.merge_probe_spread(&fresa_gcode::probe_spread(reader()?, reader()?, &opts));
            }
            if json {
                println!("{}", serde_json::to_string_pretty(&a)?);
                return Ok(());
            }
            let fmt_b = |b: &Option<fresa_gcode::Bounds>| match b {
                Some(b) => format!(
                    "X {:.3}..{:.3}  Y {:.3}..{:.3}  Z {:.3}..{:.3} mm",
                    b.min[0], b.max[0], b.min[1], b.max[1], b.min[2], b.max[2]
                ),
                None => "none".into(),
            };
            println!("{}: OK", file.display());
            println!("  lines            {}", a.lines);
            println!(
                "  moves            {} rapid, {} linear, {} arc",
                a.rapid_moves, a.linear_moves, a.arc_moves
            );
            println!(
                "  segments         {} (moves and arc chords; budget {max_segments})",
                a.segments
            );
            println!("  cutting bounds   {}", fmt_b(&a.cutting_bounds));
            println!("  rapid bounds     {}", fmt_b(&a.rapid_bounds));
            if let (Some(b), Some(line)) = (a.a_bounds, a.first_a_line) {
                println!(
                    "  A axis           {:.3}..{:.3} deg (first A move on line {line})",
                    b.min, b.max
                );
            }
            if let Some(line) = a.first_probe_line {
                println!(
                    "  probing          {} probing moves, first on line {line}",
                    a.probe_moves
                );
                if let Some(dep) = a.first_probe_dependent_line {
                    println!(
                        "  probe-dependent  {} moves, first on line {dep} (bounds above cover \
                         a probe touching at once and not at all)",
                        a.probe_dependent_moves
                    );
                }
                if let Some(from) = a.probe_paths_unchecked_from {
                    println!(
                        "  warning: from line {from} the path depends on a probe's result \
                         through a loop or branch: checked as if no probe touched (the \
                         machine checks each move before it starts)"
                    );
                }
            }
            println!(
                "  path length      {:.1} mm cutting, {:.1} mm rapid",
                a.cutting_length_mm, a.rapid_length_mm
            );
            let t = a.estimated_seconds.round() as u64;
            println!(
                "  estimated time   {}:{:02}:{:02} (rapids at {rapid} mm/min, no acceleration)",
                t / 3600,
                t / 60 % 60,
                t % 60
            );
            if a.units_inch_seen {
                println!("  units            inch (G20) converted to mm");
            }
            let tools: Vec<String> = a.tools.iter().map(|t| format!("T{t}")).collect();
            println!(
                "  tools            {}",
                if tools.is_empty() {
                    "none".to_string()
                } else {
                    tools.join(" ")
                }
            );
            println!("  dwell            {:.1} s", a.dwell_seconds);
            println!("  max feed         {:.1} mm/min", a.max_feed_mm_min);
            println!("  max spindle      {:.0} rpm", a.max_spindle_rpm);
            if a.motion_lines == 0 {
                println!("  warning: the program moves nothing (no motion on any line)");
            }
            if !a.program_end {
                println!("  warning: no program end (M2 or M30): the run ends at the last line");
            }
            for w in &a.warnings {
                println!(
                    "  warning: line {}, column {}: {}",
                    w.line, w.column, w.message
                );
            }
        }
    }
    Ok(())
}

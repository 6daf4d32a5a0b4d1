//! What the API shows of the domain: one type per view, used as the HTTP response body, the
//! SSE event data and the MQTT message alike, and deriving its OpenAPI schema, so the three
//! cannot disagree and the description cannot drift from what is sent.

use crate::store::{JobRow, MachineRow, RunRow};
use fresa_plugin_api::contract::{MachineState, MachineStatus};
use serde::Serialize;
use serde_json::Value;
use utoipa::ToSchema;

/// The active run's progress: the `job` of a status, and the data of `job.progress`.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct JobProgress {
    pub job: i64,
    pub run: i64,
    /// Last acknowledged line.
    pub line: i64,
    pub total_lines: i64,
    /// `line` of `total_lines`, to one decimal.
    pub percent: f64,
    /// Seconds of motion left after `line` by the program's time estimate (the machine's
    /// rapid rate, acceleration and cornering), under the feed and rapid overrides in force;
    /// pauses not counted. Absent without an estimate.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub remaining_s: Option<f64>,
}

impl JobProgress {
    pub fn new(
        job: i64,
        run: i64,
        line: i64,
        total_lines: i64,
        remaining_s: Option<f64>,
    ) -> JobProgress {
        let percent = if total_lines > 0 {
            (line as f64 / total_lines as f64 * 100.0).min(100.0)
        } else {
            0.0
        };
        JobProgress {
            job,
            run,
            line,
            total_lines,
            percent: (percent * 10.0).round() / 10.0,
            // To the tenth of a second: the status is only re-sent when it changes.
            remaining_s: remaining_s.map(|r| (r * 10.0).round() / 10.0),
        }
    }
}

/// A machine's status: what the backend reports, plus the machine id and the running job.
/// `GET /machines/{id}/status`, the data of a `status` event and the retained MQTT status are
/// this, serialised.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
#[schema(as = Status)]
pub struct StatusView {
    #[serde(flatten)]
    pub status: MachineStatus,
    pub machine: i64,
    /// The active run's progress; null when none.
    pub job: Option<JobProgress>,
}

impl StatusView {
    /// A live machine's status now: `Machine::status_view`, the one function HTTP, the status
    /// events and the MQTT bridge's announcement use.
    ///
    /// A machine another node drives, as this node knows it: no job.
    pub fn remote(machine: i64, status: MachineStatus) -> StatusView {
        StatusView {
            status,
            machine,
            job: None,
        }
    }
}

/// A machine: its stored row and live state.
#[derive(Debug, Clone, Serialize, ToSchema)]
#[schema(as = Machine)]
pub struct MachineView {
    pub id: i64,
    pub name: String,
    /// The plugin that drives it, e.g. `sim-machine`.
    pub backend: String,
    /// The backend's own settings, as given at creation.
    #[schema(value_type = Object)]
    pub config: Value,
    pub max_jog_mm: f64,
    pub max_feed_mm_min: f64,
    pub max_probe_feed_mm_min: f64,
    /// The overrides an operator may set, percent.
    pub override_limits: crate::machine::limits::OverrideLimits,
    /// The machine Z a start at a line goes up to at least (machine coordinates, mm).
    pub safe_z_mm: Option<f64>,
    pub state: MachineState,
    /// Why the machine is offline or unresponsive, when it is.
    pub reason: Option<String>,
    /// Milliseconds since the Unix epoch.
    pub created_at: i64,
    /// The node that drives it (see `GET /nodes`); requests for it are carried out there.
    pub node: Option<String>,
}

impl MachineView {
    pub fn new(row: MachineRow, status: MachineStatus) -> MachineView {
        let limits = crate::machine::limits::OverrideLimits::of(&row);
        MachineView {
            id: row.id,
            config: row.config_json(),
            name: row.name,
            backend: row.backend,
            max_jog_mm: row.max_jog_mm,
            max_feed_mm_min: row.max_feed_mm_min,
            max_probe_feed_mm_min: row.max_probe_feed_mm_min,
            override_limits: limits,
            safe_z_mm: row.safe_z_mm,
            state: status.state,
            reason: status.reason,
            created_at: row.created_at,
            node: row.node,
        }
    }
}

/// A stored analysis as the API shows it: without the time table, which is the server's (a
/// running job's `remaining_s` comes from it) and which a job list would carry for every job.
pub fn public_analysis(mut analysis: Value) -> Value {
    if let Some(a) = analysis.as_object_mut() {
        a.remove("time_table");
    }
    analysis
}

/// A job as the API shows it: the job row, its analysis and its latest run.
#[derive(Debug, Clone, Serialize, ToSchema)]
#[schema(as = Job)]
pub struct JobView {
    pub id: i64,
    pub name: String,
    pub machine: i64,
    pub sha256: String,
    pub size_bytes: i64,
    pub line_count: i64,
    pub source: String,
    pub created_at: i64,
    /// Bounds, lengths, time estimate; null before the analysis is stored.
    #[schema(value_type = Option<Object>)]
    pub analysis: Value,
    /// `ready` before the first start, then the latest run's state: `running`, `paused`,
    /// `completed`, `failed`, `cancelled`, `interrupted`.
    #[schema(value_type = String)]
    pub state: &'static str,
    /// Last acknowledged line of the latest run.
    pub line: i64,
    pub percent: f64,
    /// The latest run, or null.
    #[schema(value_type = Option<Object>)]
    pub run: Option<RunRow>,
    /// Why the run holds, while it is `paused` and its machine holds it (the machine status's
    /// `hold`); absent otherwise.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub hold: Option<fresa_plugin_api::contract::Hold>,
}

impl JobView {
    pub fn new(job: &JobRow, run: Option<&RunRow>) -> JobView {
        let analysis = job
            .analysis
            .as_deref()
            .and_then(|a| serde_json::from_str(a).ok())
            .unwrap_or(Value::Null);
        let analysis = public_analysis(analysis);
        let (state, line) = match run {
            Some(r) => (r.state.as_str(), r.last_line),
            None => ("ready", 0),
        };
        let percent = if job.line_count > 0 {
            ((line as f64 / job.line_count as f64) * 1000.0).round() / 10.0
        } else {
            0.0
        };
        JobView {
            id: job.id,
            name: job.name.clone(),
            machine: job.machine_id,
            sha256: job.sha256.clone(),
            size_bytes: job.size_bytes,
            line_count: job.line_count,
            source: job.source.clone(),
            created_at: job.created_at,
            analysis,
            state,
            line,
            percent,
            run: run.cloned(),
            hold: None,
        }
    }

    /// The view with the live reason its run holds (`jobs::live_hold` finds it).
    pub fn with_hold(mut self, hold: Option<fresa_plugin_api::contract::Hold>) -> JobView {
        self.hold = hold.filter(|_| self.state == "paused");
        self
    }
}

//! The shop's records (issue 28, part 2): what the raw facts (runs, the audit log, the machine's
//! published status) are turned into. A part record is written by the machine's task once a
//! run's end is stored ([`record_part`]); state changes and maintenance counters are kept by
//! each machine's tracker (`machine::counters`); the API's reads are in `reports`.

use crate::error::{Error, Result};
use crate::store::{CountersRow, PartRow, RunRow, Store};
use fresa_plugin_api::contract::MachineState;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use sha2::{Digest, Sha256};
use utoipa::ToSchema;

/// The states utilisation is counted in, in the order reports show them.
pub const STATES: [&str; 6] = [
    "cutting",
    "idle",
    "held",
    "alarm",
    "unresponsive",
    "offline",
];

/// The utilisation state of a machine state: running a program or MDI is cutting; jogging and
/// homing are setting up, counted as idle; a hold (feed hold, M0/M1/M6) is held.
pub fn util_state(s: MachineState) -> &'static str {
    match s {
        MachineState::Running => "cutting",
        MachineState::Idle | MachineState::Jogging | MachineState::Homing => "idle",
        MachineState::Paused => "held",
        MachineState::Alarm => "alarm",
        MachineState::Unresponsive => "unresponsive",
        MachineState::Offline => "offline",
    }
}

/// Most maintenance intervals one machine may have.
pub const MAX_MAINTENANCE_ITEMS: usize = 32;

/// One maintenance interval of a machine (`maintenance` in `POST /machines`): a name and
/// exactly one `every_*`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct MaintenanceItem {
    /// 1 to 64 letters, digits, `-`, `_` (it is a path segment of `.../maintenance/{name}/done`).
    #[schema(example = "lubricate")]
    pub name: String,
    /// Due every this many hours with the spindle on.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(example = 40.0)]
    pub every_spindle_hours: Option<f64>,
    /// Due every this many hours of motion (running, jogging, homing).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub every_motion_hours: Option<f64>,
    /// Due every this many jobs run (runs ended).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub every_jobs: Option<f64>,
}

impl MaintenanceItem {
    /// Which counter it follows (`spindle_hours`, `motion_hours`, `jobs`) and its interval.
    pub fn interval(&self) -> (&'static str, f64) {
        match (
            self.every_spindle_hours,
            self.every_motion_hours,
            self.every_jobs,
        ) {
            (Some(h), _, _) => ("spindle_hours", h),
            (_, Some(h), _) => ("motion_hours", h),
            (_, _, Some(n)) => ("jobs", n),
            _ => ("jobs", f64::INFINITY),
        }
    }

    /// The value of the counter it follows.
    pub fn value(&self, c: &CountersRow) -> f64 {
        counter_value(self.interval().0, c)
    }

    /// Checks a machine's intervals: names valid and distinct, exactly one positive `every_*`
    /// each, at most [`MAX_MAINTENANCE_ITEMS`].
    pub fn check_all(items: &[MaintenanceItem]) -> Result<()> {
        if items.len() > MAX_MAINTENANCE_ITEMS {
            return Err(Error::invalid(
                "invalid_field",
                format!("field `maintenance`: at most {MAX_MAINTENANCE_ITEMS} intervals"),
            ));
        }
        for (i, item) in items.iter().enumerate() {
            let field = format!("maintenance[{i}]");
            let n = &item.name;
            if n.is_empty()
                || n.len() > 64
                || !n
                    .bytes()
                    .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_')
            {
                return Err(Error::invalid(
                    "invalid_field",
                    format!("field `{field}.name`: 1 to 64 letters, digits, '-' or '_', got {n:?}"),
                ));
            }
            if items[..i].iter().any(|o| &o.name == n) {
                return Err(Error::invalid(
                    "invalid_field",
                    format!("field `{field}.name`: {n:?} is listed twice"),
                ));
            }
            let given = [
                item.every_spindle_hours,
                item.every_motion_hours,
                item.every_jobs,
            ];
            if given.iter().flatten().count() != 1 {
                return Err(Error::invalid(
                    "invalid_field",
                    format!(
                        "field `{field}`: give exactly one of every_spindle_hours, \
                         every_motion_hours, every_jobs"
                    ),
                ));
            }
            let (_, every) = item.interval();
            if !(every.is_finite() && every > 0.0 && every <= 1e9) {
                return Err(Error::invalid(
                    "invalid_field",
                    format!("field `{field}`: the interval must be above 0 and at most 1e9, got {every}"),
                ));
            }
        }
        Ok(())
    }
}

/// A counter's value in the unit maintenance intervals use (hours, or jobs).
pub fn counter_value(counter: &str, c: &CountersRow) -> f64 {
    match counter {
        "spindle_hours" => c.spindle_ms as f64 / 3_600_000.0,
        "motion_hours" => c.motion_ms as f64 / 3_600_000.0,
        _ => c.jobs as f64,
    }
}

/// A part record as `GET /parts` shows it.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct PartView {
    pub id: i64,
    pub run: i64,
    pub job: i64,
    pub machine: i64,
    pub machine_name: String,
    /// The node that drove the machine.
    pub node: Option<String>,
    pub program_name: String,
    pub program_sha256: String,
    /// The work offset in force at the end (`G54`..`G59`) and its zero (machine coordinates).
    pub work_offset: String,
    #[schema(value_type = Object)]
    pub work_zero: Option<Value>,
    /// The part zero in force (the controller's for the run, else the latest recorded).
    #[schema(value_type = Object)]
    pub part_zero: Option<Value>,
    /// The machine's tool table at the end, and the SHA-256 of its JSON.
    #[schema(value_type = Object)]
    pub tool_table: Value,
    pub tool_table_sha256: String,
    /// Who started, resumed or confirmed it (the audit log), in order of first appearance.
    pub operators: Vec<String>,
    /// The queue's confirmations for this run (`queue.confirm`): `actor`, `time` (ms), `entry`.
    #[schema(value_type = Object)]
    pub confirmations: Value,
    /// `completed`, `failed`, `cancelled`.
    pub outcome: String,
    pub message: Option<String>,
    pub line_count: i64,
    pub from_line: Option<i64>,
    pub last_line: i64,
    /// Lines acknowledged in this run (from its start line to its last acknowledged line).
    pub lines_run: i64,
    /// The analysis' run-time estimate of the whole program, seconds at 100 %.
    pub estimate_s: Option<f64>,
    /// From start to end, seconds (holds included).
    pub actual_s: Option<f64>,
    /// Unix ms.
    pub started_at: Option<i64>,
    pub ended_at: i64,
}

impl PartView {
    pub fn from_row(r: PartRow) -> PartView {
        let parse = |t: &str| serde_json::from_str::<Value>(t).unwrap_or(Value::Null);
        PartView {
            id: r.id,
            run: r.run_id,
            job: r.job_id,
            machine: r.machine_id,
            machine_name: r.machine_name,
            node: r.node,
            program_name: r.program_name,
            program_sha256: r.program_sha256,
            work_offset: r.work_offset,
            work_zero: r.work_zero.as_deref().map(parse),
            part_zero: r.part_zero.as_deref().map(parse),
            tool_table: parse(&r.tool_table),
            tool_table_sha256: r.tool_table_sha256,
            operators: serde_json::from_str(&r.operators).unwrap_or_default(),
            confirmations: parse(&r.confirmations),
            outcome: r.outcome,
            message: r.message,
            line_count: r.line_count,
            from_line: r.from_line,
            last_line: r.last_line,
            lines_run: r.lines_run,
            estimate_s: r.estimate_s,
            actual_s: r.actual_s,
            started_at: r.started_at,
            ended_at: r.ended_at,
        }
    }
}

/// The CSV columns of `GET /parts` (`Accept: text/csv`), one row per part.
pub const PART_CSV_HEADER: &str = "id,run,job,machine,machine_name,node,program_name,program_sha256,work_offset,outcome,line_count,from_line,last_line,lines_run,estimate_s,actual_s,started_at,ended_at,operators,confirmations,tool_table_sha256,message";

/// One CSV row (no newline): operators joined with `;`, confirmations counted.
pub fn part_csv_row(p: &PartView) -> String {
    let opt = |v: Option<String>| v.unwrap_or_default();
    let confirmations = p.confirmations.as_array().map_or(0, Vec::len);
    [
        p.id.to_string(),
        p.run.to_string(),
        p.job.to_string(),
        p.machine.to_string(),
        csv_field(&p.machine_name),
        csv_field(p.node.as_deref().unwrap_or("")),
        csv_field(&p.program_name),
        p.program_sha256.clone(),
        csv_field(&p.work_offset),
        p.outcome.clone(),
        p.line_count.to_string(),
        opt(p.from_line.map(|v| v.to_string())),
        p.last_line.to_string(),
        p.lines_run.to_string(),
        opt(p.estimate_s.map(|v| format!("{v:.3}"))),
        opt(p.actual_s.map(|v| format!("{v:.3}"))),
        opt(p.started_at.map(|v| v.to_string())),
        p.ended_at.to_string(),
        csv_field(&p.operators.join(";")),
        confirmations.to_string(),
        p.tool_table_sha256.clone(),
        csv_field(p.message.as_deref().unwrap_or("")),
    ]
    .join(",")
}

/// A CSV field (RFC 4180): quoted when it holds a comma, quote or line break. A leading `=`,
/// `+`, `-` or `@` gets a `'` so a spreadsheet does not run it as a formula.
pub fn csv_field(s: &str) -> String {
    let s = if s.starts_with(['=', '+', '-', '@']) {
        format!("'{s}")
    } else {
        s.to_string()
    };
    if s.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s
    }
}

/// How many audit events are read to find a run's operators and confirmations.
const RUN_AUDIT_LIMIT: i64 = 5000;

/// Writes the part record of `run`, which has just ended (its end is stored). Reads what was in
/// force from the store: the job, the machine's work offset and tool table, the part zero, and
/// who ran it from the audit log.
pub async fn record_part(store: &Store, run: &RunRow) -> std::result::Result<(), sqlx::Error> {
    // The stored run: a line the backend acknowledged as it stopped may have landed since.
    let run = &match store.run(run.id).await? {
        Some(r) if r.state.is_active() => return Ok(()),
        Some(r) => r,
        None => run.clone(),
    };
    let Some(job) = store.job(run.job_id).await? else {
        return Ok(());
    };
    let Some(machine) = store.machine(run.machine_id).await? else {
        return Ok(());
    };
    let offsets = store.offsets(run.machine_id).await?;
    let work_zero = offsets
        .iter()
        .find(|(o, _)| o.name() == machine.active_offset)
        .map(|(_, v)| json!(v));
    let part_zero = match store.run_part_zero(run.id).await? {
        Some(z) => Some(json!(z)),
        None => store
            .latest_part_zero(run.machine_id)
            .await?
            .map(|z| json!({"x": z.x, "y": z.y, "z": z.z, "a": z.a})),
    };
    let tools = json!(store.tools(run.machine_id).await?).to_string();
    let tools_sha = hex(&Sha256::digest(tools.as_bytes()));
    let events = store
        .run_audit(run.machine_id, run.created_at - 1000, RUN_AUDIT_LIMIT)
        .await?;
    let mut operators: Vec<String> = Vec::new();
    let mut confirmations = Vec::new();
    for e in events {
        let Ok(data) = serde_json::from_str::<Value>(&e.data) else {
            continue;
        };
        if data["run"].as_i64() != Some(run.id) {
            continue;
        }
        let operator = match e.kind.as_str() {
            "queue.confirm" => {
                confirmations.push(json!({
                    "actor": e.actor, "time": e.created_at, "entry": data.get("entry"),
                }));
                true
            }
            // Who started or resumed it (a hold the machine went into and out of by itself
            // has no actor).
            _ => data["state"] == "running",
        };
        if let Some(a) = e.actor.filter(|_| operator) {
            if !operators.contains(&a) {
                operators.push(a);
            }
        }
    }
    let estimate_s = job
        .analysis
        .as_deref()
        .and_then(|a| serde_json::from_str::<Value>(a).ok())
        .and_then(|a| a["estimated_seconds"].as_f64());
    let ended_at = run.ended_at.unwrap_or(run.updated_at);
    let from_line = run.from_line.unwrap_or(1);
    let row = PartRow {
        id: 0,
        run_id: run.id,
        job_id: run.job_id,
        machine_id: run.machine_id,
        machine_name: machine.name,
        node: machine.node,
        program_name: job.name,
        program_sha256: job.sha256,
        work_offset: machine.active_offset,
        work_zero: work_zero.map(|v| v.to_string()),
        part_zero: part_zero.map(|v| v.to_string()),
        tool_table: tools,
        tool_table_sha256: tools_sha,
        operators: json!(operators).to_string(),
        confirmations: json!(confirmations).to_string(),
        outcome: run.state.as_str().to_string(),
        message: run.message.clone(),
        line_count: job.line_count,
        from_line: run.from_line,
        last_line: run.last_line,
        lines_run: (run.last_line - from_line + 1).max(0),
        estimate_s,
        actual_s: run
            .started_at
            .map(|s| (ended_at - s).max(0) as f64 / 1000.0),
        started_at: run.started_at,
        ended_at,
    };
    store.upsert_part(&row).await
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// Seconds per state of one machine on one UTC day.
#[derive(Debug, Clone, Default, PartialEq, Serialize, ToSchema)]
pub struct DayUse {
    /// `YYYY-MM-DD` (UTC).
    pub day: String,
    pub cutting: f64,
    pub idle: f64,
    pub held: f64,
    pub alarm: f64,
    pub unresponsive: f64,
    pub offline: f64,
}

impl DayUse {
    fn add(&mut self, state: &str, secs: f64) {
        let slot = match state {
            "cutting" => &mut self.cutting,
            "idle" => &mut self.idle,
            "held" => &mut self.held,
            "alarm" => &mut self.alarm,
            "unresponsive" => &mut self.unresponsive,
            _ => &mut self.offline,
        };
        *slot += secs;
    }
}

const DAY_MS: i64 = 86_400_000;

/// Splits the time in `[from, to)` between states by day: `changes` are `(state, since)` in
/// order, the first possibly before `from` (the state in force at `from`). Time before the
/// first change is unknown and not counted; the last state lasts until `to` (the caller clips
/// `to` at now). Days with no counted time are left out.
pub fn split_by_day(changes: &[(String, i64)], from: i64, to: i64) -> Vec<DayUse> {
    let mut days: Vec<DayUse> = Vec::new();
    let mut current_day = i64::MIN;
    for (i, (state, since)) in changes.iter().enumerate() {
        let start = (*since).max(from);
        let end = changes.get(i + 1).map_or(to, |(_, next)| *next).min(to);
        let mut t = start;
        while t < end {
            let day_start = t.div_euclid(DAY_MS) * DAY_MS;
            let piece_end = (day_start + DAY_MS).min(end);
            if day_start != current_day {
                current_day = day_start;
                days.push(DayUse {
                    day: crate::store::utc_text(day_start, false)[..10].to_string(),
                    ..Default::default()
                });
            }
            if let Some(d) = days.last_mut() {
                d.add(state, (piece_end - t) as f64 / 1000.0);
            }
            t = piece_end;
        }
    }
    days
}

/// A time given as Unix ms, `YYYY-MM-DD` (that day's start, UTC) or `YYYY-MM-DDTHH:MM:SS[.fff]Z`.
pub fn parse_time(field: &str, text: &str) -> Result<i64> {
    let bad = || {
        Error::bad_request(
            "invalid_query",
            format!(
                "{field}: {text:?} is no time (Unix ms, YYYY-MM-DD or YYYY-MM-DDTHH:MM:SSZ, UTC)"
            ),
        )
    };
    if let Ok(ms) = text.parse::<i64>() {
        return Ok(ms);
    }
    let num = |s: &str| s.parse::<i64>().map_err(|_| bad());
    let (date, time) = match text.split_once('T') {
        Some((d, t)) => (d, Some(t.strip_suffix('Z').ok_or_else(bad)?)),
        None => (text, None),
    };
    let parts: Vec<&str> = date.split('-').collect();
    let [y, m, d] = parts.as_slice() else {
        return Err(bad());
    };
    if y.len() != 4 || m.len() != 2 || d.len() != 2 {
        return Err(bad());
    }
    let (y, m, d) = (num(y)?, num(m)?, num(d)?);
    if !(1..=12).contains(&m) || !(1..=31).contains(&d) {
        return Err(bad());
    }
    let mut ms = days_from_civil(y, m, d) * DAY_MS;
    if let Some(t) = time {
        let (hms, frac) = t.split_once('.').unwrap_or((t, ""));
        let hms: Vec<&str> = hms.split(':').collect();
        let [h, mi, s] = hms.as_slice() else {
            return Err(bad());
        };
        let (h, mi, s) = (num(h)?, num(mi)?, num(s)?);
        if h > 23 || mi > 59 || s > 60 {
            return Err(bad());
        }
        let frac_ms = if frac.is_empty() {
            0
        } else {
            let digits: String = frac.chars().chain("000".chars()).take(3).collect();
            num(&digits)?
        };
        ms += ((h * 60 + mi) * 60 + s) * 1000 + frac_ms;
    }
    Ok(ms)
}

/// Days since 1970-01-01 of a civil date (Howard Hinnant's algorithm).
fn days_from_civil(y: i64, m: i64, d: i64) -> i64 {
    let y = if m <= 2 { y - 1 } else { y };
    let era = y.div_euclid(400);
    let yoe = y - era * 400;
    let mp = (m + 9) % 12;
    let doy = (153 * mp + 2) / 5 + d - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    era * 146_097 + doe - 719_468
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    #[test]
    fn times_parse_in_every_documented_form() {
        assert_eq!(parse_time("from", "0").unwrap(), 0);
        assert_eq!(
            parse_time("from", "2026-11-30T21:14:03Z").unwrap(),
            1_796_073_243_000
        );
        assert_eq!(
            parse_time("from", "2026-11-30T21:14:03.456Z").unwrap(),
            1_796_073_243_456
        );
        assert_eq!(parse_time("from", "2000-02-29").unwrap(), 951_782_400_000);
        for bad in ["2026-13-01", "yesterday", "2026-11-30T21:14:03", "2026-1-1"] {
            let e = parse_time("from", bad).unwrap_err();
            assert!(e.message.contains("from"), "{}", e.message);
        }
    }

    #[test]
    fn time_is_split_by_state_and_day() {
        let day = DAY_MS;
        let changes = vec![
            ("idle".to_string(), -5000),
            ("cutting".to_string(), day - 2000),
            ("held".to_string(), day + 1000),
            ("cutting".to_string(), day + 3000),
        ];
        let days = split_by_day(&changes, 0, day + 4000);
        assert_eq!(days.len(), 2);
        assert_eq!(days[0].day, "1970-01-01");
        assert_eq!(days[0].idle, (day - 2000) as f64 / 1000.0);
        assert_eq!(days[0].cutting, 2.0);
        assert_eq!(days[1].day, "1970-01-02");
        assert_eq!((days[1].cutting, days[1].held), (2.0, 2.0));
        // Nothing is known before the first change.
        assert!(split_by_day(&changes[1..], 0, day)
            .iter()
            .all(|d| d.idle == 0.0));
    }

    #[test]
    fn maintenance_items_are_checked_naming_the_field() {
        let item = |name: &str, h: Option<f64>, j: Option<f64>| MaintenanceItem {
            name: name.into(),
            every_spindle_hours: h,
            every_motion_hours: None,
            every_jobs: j,
        };
        assert!(MaintenanceItem::check_all(&[item("lube", Some(40.0), None)]).is_ok());
        let e = MaintenanceItem::check_all(&[item("lube", Some(1.0), Some(2.0))]).unwrap_err();
        assert!(e.message.contains("maintenance[0]"), "{}", e.message);
        let e =
            MaintenanceItem::check_all(&[item("a", Some(1.0), None), item("a", None, Some(3.0))])
                .unwrap_err();
        assert!(e.message.contains("maintenance[1].name"), "{}", e.message);
        let e = MaintenanceItem::check_all(&[item("a b", Some(1.0), None)]).unwrap_err();
        assert!(e.message.contains("name"), "{}", e.message);
        let e = MaintenanceItem::check_all(&[item("a", Some(-1.0), None)]).unwrap_err();
        assert!(e.message.contains("above 0"), "{}", e.message);
    }

    #[test]
    fn csv_fields_are_quoted_and_defused() {
        assert_eq!(csv_field("plain"), "plain");
        assert_eq!(csv_field("a,b"), "\"a,b\"");
        assert_eq!(csv_field("say \"hi\""), "\"say \"\"hi\"\"\"");
        assert_eq!(csv_field("=1+1"), "'=1+1");
    }
}

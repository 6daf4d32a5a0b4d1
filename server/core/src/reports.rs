//! The shop's records as the API reads them (issue 28, part 2): part records by page,
//! utilisation per machine and day, a machine's counters and marking maintenance done.

use crate::app::App;
use crate::error::{Error, Result};
use crate::machine::counters::{CountersView, MaintenanceView};
use crate::records::{split_by_day, DayUse, PartView};
use crate::store::{now_ms, PartFilter};
use serde::Serialize;
use utoipa::ToSchema;

/// Part records per page by default, and at most.
pub const DEFAULT_PARTS_LIMIT: i64 = 100;
pub const MAX_PARTS_LIMIT: i64 = 1000;
/// The longest utilisation report, in days.
pub const MAX_REPORT_DAYS: i64 = 366;
const DAY_MS: i64 = 86_400_000;

/// What `GET /parts` asks for (times already parsed, see `records::parse_time`).
#[derive(Debug, Clone, Default)]
pub struct PartsQuery {
    pub job: Option<i64>,
    pub machine: Option<i64>,
    pub from: Option<i64>,
    pub to: Option<i64>,
    pub limit: Option<i64>,
    /// `next` of the previous page.
    pub cursor: Option<String>,
}

/// One page of part records, newest first.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct PartsPage {
    pub parts: Vec<PartView>,
    /// Pass as `cursor` for the next (older) page; absent on the last.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub next: Option<String>,
}

pub async fn parts(app: &App, q: PartsQuery) -> Result<PartsPage> {
    let limit = q.limit.unwrap_or(DEFAULT_PARTS_LIMIT);
    if !(1..=MAX_PARTS_LIMIT).contains(&limit) {
        return Err(Error::bad_request(
            "invalid_query",
            format!("limit: 1 to {MAX_PARTS_LIMIT}, got {limit}"),
        ));
    }
    let before = match q.cursor.as_deref() {
        None => None,
        Some(c) => {
            let parsed = c
                .split_once('.')
                .and_then(|(a, b)| Some((a.parse().ok()?, b.parse().ok()?)));
            Some(parsed.ok_or_else(|| {
                Error::bad_request(
                    "invalid_query",
                    format!("cursor: {c:?} is not a page cursor"),
                )
            })?)
        }
    };
    let filter = PartFilter {
        job: q.job,
        machine: q.machine,
        from: q.from,
        to: q.to,
        before,
        limit: limit + 1,
    };
    let mut rows = app.store.health().read(app.store.parts(&filter)).await?;
    let next = if rows.len() as i64 > limit {
        rows.truncate(limit as usize);
        rows.last().map(|r| format!("{}.{}", r.ended_at, r.id))
    } else {
        None
    };
    Ok(PartsPage {
        parts: rows.into_iter().map(PartView::from_row).collect(),
        next,
    })
}

/// One machine's utilisation.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct MachineUse {
    pub machine: i64,
    pub name: String,
    /// Days with recorded time, oldest first.
    pub days: Vec<DayUse>,
    /// The whole range (`day` is empty).
    pub total: DayUse,
}

/// `GET /reports/utilisation`.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct UtilisationReport {
    /// Unix ms; `to` is clipped at now.
    pub from: i64,
    pub to: i64,
    pub machines: Vec<MachineUse>,
}

/// Seconds per state, machine and UTC day in `[from, to)` (default: the last 7 days), from the
/// recorded state changes. At most [`MAX_REPORT_DAYS`].
pub async fn utilisation(
    app: &App,
    from: Option<i64>,
    to: Option<i64>,
) -> Result<UtilisationReport> {
    let now = now_ms();
    let to = to.unwrap_or(now).min(now);
    let from = from.unwrap_or(to - 7 * DAY_MS);
    if from >= to {
        return Err(Error::bad_request(
            "invalid_query",
            "from: must be before `to` (and before now)",
        ));
    }
    if to - from > MAX_REPORT_DAYS * DAY_MS {
        return Err(Error::bad_request(
            "invalid_query",
            format!("from/to: at most {MAX_REPORT_DAYS} days in one report"),
        ));
    }
    let health = app.store.health();
    let machines = health.read(app.store.list_machines()).await?;
    let mut out = Vec::with_capacity(machines.len());
    for m in machines {
        let changes = health
            .read(app.store.machine_states(m.id, from, to))
            .await?;
        let days = split_by_day(&changes, from, to);
        let mut total = DayUse::default();
        for d in &days {
            total.cutting += d.cutting;
            total.idle += d.idle;
            total.held += d.held;
            total.alarm += d.alarm;
            total.unresponsive += d.unresponsive;
            total.offline += d.offline;
        }
        out.push(MachineUse {
            machine: m.id,
            name: m.name,
            days,
            total,
        });
    }
    Ok(UtilisationReport {
        from,
        to,
        machines: out,
    })
}

/// The CSV of a utilisation report: one row per machine and day.
pub fn utilisation_csv(r: &UtilisationReport) -> String {
    let mut out =
        String::from("machine,name,day,cutting_s,idle_s,held_s,alarm_s,unresponsive_s,offline_s\n");
    for m in &r.machines {
        for d in &m.days {
            out.push_str(&format!(
                "{},{},{},{:.3},{:.3},{:.3},{:.3},{:.3},{:.3}\n",
                m.machine,
                crate::records::csv_field(&m.name),
                d.day,
                d.cutting,
                d.idle,
                d.held,
                d.alarm,
                d.unresponsive,
                d.offline
            ));
        }
    }
    out
}

/// The machine this node drives, or why not.
async fn local(app: &App, id: i64) -> Result<std::sync::Arc<crate::machine::Machine>> {
    if let Some(m) = app.machines.get(id) {
        return Ok(m);
    }
    match app.store.health().read(app.store.machine(id)).await? {
        // Reached only while its node is unreachable (otherwise the request was forwarded).
        Some(_) => Err(Error::new(
            crate::error::ErrorKind::Unavailable,
            "node_unreachable",
            format!("machine {id} is driven by another node, which does not answer"),
        )),
        None => Err(Error::not_found(
            "unknown_machine",
            format!("no machine with id {id}"),
        )),
    }
}

pub async fn counters(app: &App, id: i64) -> Result<CountersView> {
    Ok(local(app, id).await?.counters())
}

pub async fn maintenance_done(
    app: &App,
    id: i64,
    name: &str,
    actor: &str,
) -> Result<MaintenanceView> {
    local(app, id)
        .await?
        .maintenance_done(&app.store, name, actor)
        .await
}

//! Height maps (issue 25): probing a grid of surface heights over an area of the work
//! coordinates, keeping it with the machine, and handing it to a job's backend, which adds the
//! surface's height under the tool to every move's Z (`fresa_plugin_api::heightmap`).
//!
//! **Probing a grid** ([`Machine::start_height_map`]) runs on a task of its own, like a job
//! (the request that started it is answered at once with the map's id): Z up to the clearance,
//! then for each point (rows in a serpentine) X and Y there, Z down to the clearance, a probing
//! move down at most `distance`, the work Z where it tripped recorded, Z back up to the
//! clearance. Every move is a jog or probe of its own, within `max_jog_mm` (longer travel is
//! cut into several), carrying the gate ticket taken when the grid began: a STOP or feed hold
//! anywhere ends the grid and nothing it would have sent moves. Before the first move the
//! grid's whole extent (from the tool's place to every point, clearance down to the probe's
//! end) is checked against the machine's configured `travel` (the soft limits of the kit
//! backends); the backend checks each move again. After each move the tool must be where it
//! was sent (someone else jogging in between, or a stop, ends the grid), and the work offset
//! must be the one the grid started with.
//!
//! A map ends `complete`, or `stopped` (STOP, feed hold, shutdown) / `failed` (an alarm, a
//! probe that never touched, naming the point, a move refused): then what it probed is kept
//! and shown, the rest `null`, and it is never applied to a job. A server that stops while a
//! grid runs leaves it `failed` at its next start.
//!
//! **Applying a map** ([`applied_for_job`]): the map is stored in the work coordinates it was
//! probed in, with that work zero in machine coordinates; a job gets it expressed in the work
//! zero in force when it starts (so re-zeroing Z on the surface after probing moves the
//! correction with it), and only if it is complete and the program's cutting moves (XY, from
//! the stored analysis) lie inside its area.

use super::probing::ProbeAsk;
use super::Machine;
use crate::error::{Error, ErrorKind, Result};
use crate::events::EventKind;
use crate::store::{HeightMapRow, JobRow, NewHeightMap, Store};
use fresa_plugin_api::contract::{Axis, AxisValues, MachineState, MachineStatus, ProbeUntil};
use fresa_plugin_api::heightmap::{HeightMap, MAX_POINTS_PER_AXIS};
use serde::Serialize;
use serde_json::json;
use std::sync::Arc;
use std::time::Duration;

/// Most maps kept per machine: a new grid is refused (`height_map_limit`) until one is deleted.
pub const MAX_MAPS_PER_MACHINE: i64 = 100;

/// How far from where it was sent the tool may end a move and still count as there, mm.
const POSITION_TOLERANCE_MM: f64 = 0.01;

/// Slack on a program's extent against a map's area, mm (decimal round trips).
const AREA_EPS: f64 = 1e-6;

/// Longest a single travel move of a grid may take beyond twice its nominal time.
const MOVE_GRACE: Duration = Duration::from_secs(30);

/// Longest a travel move at the backend's own jog feed (not known here) may take.
const MOVE_LIMIT_UNKNOWN_FEED: Duration = Duration::from_secs(600);

/// The map being probed on a machine, if any: one grid at a time.
#[derive(Default)]
pub(crate) struct Slot(std::sync::Mutex<Option<i64>>);

impl Slot {
    fn take(&self, id: i64) -> std::result::Result<(), i64> {
        let mut s = self.0.lock().unwrap_or_else(|e| e.into_inner());
        match *s {
            Some(other) => Err(other),
            None => {
                *s = Some(id);
                Ok(())
            }
        }
    }
    fn release(&self) {
        *self.0.lock().unwrap_or_else(|e| e.into_inner()) = None;
    }
    pub(crate) fn current(&self) -> Option<i64> {
        *self.0.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// A grid to probe, as asked (`POST /machines/{id}/height-maps`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GridAsk {
    /// Work X/Y of the area: `[x0, x1, y0, y1]`, `x0 < x1`, `y0 < y1`.
    pub area: [f64; 4],
    /// Points along X and along Y, 2..=[`MAX_POINTS_PER_AXIS`].
    pub nx: u32,
    pub ny: u32,
    /// Work Z the tool travels at between points, and probes down from.
    pub clearance: f64,
    /// How far below the clearance each probe goes at most, mm (within `max_jog_mm`).
    pub distance: f64,
    /// Probing feed, mm/min (within `max_probe_feed_mm_min`).
    pub feed: f64,
    /// Feed of the travel moves, mm/min (within `max_feed_mm_min`); the backend's jog feed
    /// when absent.
    pub travel_feed: Option<f64>,
}

/// A height map as the API shows it.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct HeightMapView {
    pub id: i64,
    pub machine: i64,
    /// `probing`, `complete`, `stopped` (a stop or feed hold ended it) or `failed` (an alarm,
    /// a probe that did not touch, a refused move: `message` says which). Only a `complete`
    /// map can be applied to a job.
    pub state: String,
    /// The area, work coordinates, mm.
    pub x0: f64,
    pub x1: f64,
    pub y0: f64,
    pub y1: f64,
    pub nx: i64,
    pub ny: i64,
    pub clearance: f64,
    pub distance: f64,
    pub feed: f64,
    /// The work Z where the probe touched at each point, row by row (`y0` first, X from `x0`
    /// up in each row); null where the grid did not get to.
    pub points: Vec<Option<f64>>,
    /// Points probed so far.
    pub probed: usize,
    /// Lowest and highest height probed (null before the first point).
    pub min: Option<f64>,
    pub max: Option<f64>,
    /// The work zero in machine coordinates while it was probed (machine minus work
    /// position); a job in another work zero gets the map moved by the difference.
    pub work_zero: AxisValues,
    pub message: Option<String>,
    pub created_by: String,
    /// Unix ms.
    pub created_at: i64,
    pub finished_at: Option<i64>,
}

impl HeightMapView {
    pub fn from_row(row: &HeightMapRow) -> HeightMapView {
        let points: Vec<Option<f64>> = serde_json::from_str(&row.points).unwrap_or_default();
        let probed: Vec<f64> = points.iter().flatten().copied().collect();
        HeightMapView {
            id: row.id,
            machine: row.machine_id,
            state: row.state.clone(),
            x0: row.x0,
            x1: row.x1,
            y0: row.y0,
            y1: row.y1,
            nx: row.nx,
            ny: row.ny,
            clearance: row.clearance,
            distance: row.distance,
            feed: row.feed,
            probed: probed.len(),
            min: probed.iter().copied().reduce(f64::min),
            max: probed.iter().copied().reduce(f64::max),
            points,
            work_zero: AxisValues {
                x: row.offset_x,
                y: row.offset_y,
                z: row.offset_z,
                a: 0.0,
            },
            message: row.message.clone(),
            created_by: row.created_by.clone(),
            created_at: row.created_at,
            finished_at: row.finished_at,
        }
    }
}

/// The work zero in machine coordinates, as the status shows it (machine minus work position).
fn work_zero(status: &MachineStatus) -> [f64; 3] {
    let (m, w) = (status.machine_position, status.work_position);
    [m.x - w.x, m.y - w.y, m.z - w.z]
}

/// Where grid point `k` (row by row) lies, work X and Y.
fn point_xy(ask: &GridAsk, k: usize) -> [f64; 2] {
    let (i, j) = (k % ask.nx as usize, k / ask.nx as usize);
    let [x0, x1, y0, y1] = ask.area;
    [
        x0 + (x1 - x0) * i as f64 / f64::from(ask.nx - 1),
        y0 + (y1 - y0) * j as f64 / f64::from(ask.ny - 1),
    ]
}

/// The points in the order the grid visits them: row by row, every other row backwards, so
/// the tool never travels back across the area between two rows.
fn serpentine(nx: u32, ny: u32) -> impl Iterator<Item = usize> {
    let (nx, ny) = (nx as usize, ny as usize);
    (0..ny).flat_map(move |j| {
        (0..nx).map(move |i| {
            let i = if j % 2 == 0 { i } else { nx - 1 - i };
            j * nx + i
        })
    })
}

fn check_ask(ask: &GridAsk, row: &crate::store::MachineRow) -> Result<()> {
    let invalid = |m: String| Err(Error::invalid("invalid_field", m));
    let max = super::limits::MAX_COORDINATE_MM;
    let names = ["x0", "x1", "y0", "y1"];
    for (name, v) in names.iter().zip(ask.area) {
        if !(v.is_finite() && v.abs() <= max) {
            return invalid(format!(
                "field `{name}` must be a coordinate in mm (at most {max} from the origin), got {v}"
            ));
        }
    }
    let [x0, x1, y0, y1] = ask.area;
    if x0 >= x1 || y0 >= y1 {
        return invalid(format!(
            "the area must have x0 < x1 and y0 < y1, got X {x0}..{x1}, Y {y0}..{y1}"
        ));
    }
    for (name, n) in [("nx", ask.nx), ("ny", ask.ny)] {
        if !(2..=MAX_POINTS_PER_AXIS).contains(&n) {
            return invalid(format!(
                "field `{name}`: {n} points; a grid has 2 to {MAX_POINTS_PER_AXIS} points per axis"
            ));
        }
    }
    if !(ask.clearance.is_finite() && ask.clearance.abs() <= max) {
        return invalid(format!(
            "field `clearance` must be a work Z in mm, got {}",
            ask.clearance
        ));
    }
    if !(ask.distance.is_finite() && ask.distance > 0.0) {
        return invalid(format!(
            "field `distance` must be a positive number of mm (how far below the clearance a \
             probe may go), got {}",
            ask.distance
        ));
    }
    super::limits::check_probe(row, ask.distance, ask.feed)?;
    if let Some(f) = ask.travel_feed {
        if !(f.is_finite() && f > 0.0 && f <= row.max_feed_mm_min) {
            return Err(Error::invalid(
                "feed_out_of_range",
                format!(
                    "field `travel_feed`: {f} mm/min is outside 0..{} mm/min (the machine's \
                     `max_feed_mm_min`)",
                    row.max_feed_mm_min
                ),
            ));
        }
    }
    Ok(())
}

/// The grid's whole extent in machine coordinates (from where the tool is to every point, the
/// clearance down to the deepest probe) against the machine's configured `travel`, before the
/// first move.
fn check_travel(
    ask: &GridAsk,
    row: &crate::store::MachineRow,
    status: &MachineStatus,
) -> Result<()> {
    let config = row.config_json();
    let Some(travel) = config.get("travel") else {
        return Ok(()); // the backend checks each move itself
    };
    let Ok(travel) = fresa_plugin_api::kit::travel_from_json(travel, &Axis::ALL) else {
        return Ok(()); // not the kit's shape: the backend's own
    };
    let zero = work_zero(status);
    let w = status.work_position;
    let [x0, x1, y0, y1] = ask.area;
    let low = [
        x0.min(w.x) + zero[0],
        y0.min(w.y) + zero[1],
        (ask.clearance - ask.distance).min(w.z) + zero[2],
        status.machine_position.a,
    ];
    let high = [
        x1.max(w.x) + zero[0],
        y1.max(w.y) + zero[1],
        ask.clearance.max(w.z) + zero[2],
        status.machine_position.a,
    ];
    for corner in [low, high] {
        fresa_plugin_api::kit::check_travel(&travel, corner).map_err(|m| {
            Error::invalid(
                "out_of_travel",
                format!(
                    "the grid's moves (X {x0}..{x1}, Y {y0}..{y1}, Z {} down to {} in work \
                     coordinates, from where the tool is) leave the travel: {m}; nothing moved",
                    ask.clearance,
                    ask.clearance - ask.distance
                ),
            )
        })?;
    }
    Ok(())
}

/// Why a grid ended early: its state (`stopped` or `failed`) and the message.
fn ended_by(e: &Error) -> &'static str {
    if matches!(e.code, "stopped" | "shutting_down") {
        "stopped"
    } else {
        "failed"
    }
}

impl Machine {
    /// The map being probed on this machine, if any.
    pub fn height_map_probing(&self) -> Option<i64> {
        self.grid.current()
    }

    /// Starts probing a grid (see the module doc) and answers with its map, `probing`; the
    /// grid goes on on its own task, reporting `height_map.progress` after each point and
    /// `height_map.ended` (audit) at its end. Refused before anything moves: a bad area, count,
    /// distance or feed (naming the field), a grid leaving the travel, a machine that is not
    /// idle, runs a job or probes another grid (`machine_busy`), or has
    /// [`MAX_MAPS_PER_MACHINE`] maps.
    pub async fn start_height_map(
        self: &Arc<Self>,
        store: &Store,
        ask: GridAsk,
        actor: &str,
    ) -> Result<HeightMapView> {
        let row = self.row();
        check_ask(&ask, &row)?;
        if let Some(other) = self.grid.current() {
            return Err(Error::conflict(
                "machine_busy",
                format!("machine {} is probing height map {other}", self.id),
            ));
        }
        if let Some(r) = self.run() {
            return Err(Error::conflict(
                "machine_busy",
                format!(
                    "machine {} is running job {} (run {}); a grid is probed on an idle machine",
                    self.id, r.job_id, r.run_id
                ),
            ));
        }
        let status = self.status();
        match status.state {
            MachineState::Idle => {}
            s if s.is_busy() => {
                return Err(Error::conflict(
                    "machine_busy",
                    format!(
                        "machine {} is {}; wait for it to be idle",
                        self.id,
                        s.as_str()
                    ),
                ))
            }
            s => {
                return Err(Error::conflict(
                    "machine_not_ready",
                    format!(
                        "machine {} is {}{}; a grid is probed on an idle machine",
                        self.id,
                        s.as_str(),
                        status
                            .alarm
                            .as_deref()
                            .or(status.reason.as_deref())
                            .map(|r| format!(" ({r})"))
                            .unwrap_or_default()
                    ),
                ))
            }
        }
        check_travel(&ask, &row, &status)?;
        store.health().check()?;
        if store.count_height_maps(self.id).await? >= MAX_MAPS_PER_MACHINE {
            return Err(Error::conflict(
                "height_map_limit",
                format!(
                    "machine {} keeps {MAX_MAPS_PER_MACHINE} height maps, the most it may: \
                     delete one first",
                    self.id
                ),
            ));
        }
        // Taken before the row exists: a stop from now on ends the grid before its first move.
        let ticket = self.gate.ticket();
        let zero = work_zero(&status);
        let total = ask.nx as usize * ask.ny as usize;
        let blank = serde_json::to_string(&vec![Option::<f64>::None; total])
            .map_err(|e| Error::internal(e.to_string()))?;
        let id = store
            .insert_height_map(NewHeightMap {
                machine_id: self.id,
                area: ask.area,
                nx: i64::from(ask.nx),
                ny: i64::from(ask.ny),
                clearance: ask.clearance,
                distance: ask.distance,
                feed: ask.feed,
                offset: zero,
                points: &blank,
                created_by: actor,
            })
            .await?;
        if let Err(other) = self.grid.take(id) {
            let _ = store
                .finish_height_map(id, "failed", &blank, Some("another grid started first"))
                .await;
            return Err(Error::conflict(
                "machine_busy",
                format!("machine {} is probing height map {other}", self.id),
            ));
        }
        let view = store
            .height_map(id)
            .await?
            .map(|r| HeightMapView::from_row(&r))
            .ok_or_else(|| Error::internal(format!("height map {id} vanished")))?;
        let (m, store, actor) = (self.clone(), store.clone(), actor.to_string());
        tokio::spawn(async move {
            let mut grid = Grid {
                m: &m,
                store: &store,
                id,
                ask,
                ticket,
                actor: &actor,
                zero,
                points: vec![None; total],
            };
            let result = grid.run().await;
            grid.finish(result).await;
            m.grid.release();
        });
        Ok(view)
    }
}

/// One grid being probed (see the module doc).
struct Grid<'a> {
    m: &'a Arc<Machine>,
    store: &'a Store,
    id: i64,
    ask: GridAsk,
    ticket: u64,
    actor: &'a str,
    /// The work zero the grid started with.
    zero: [f64; 3],
    points: Vec<Option<f64>>,
}

impl Grid<'_> {
    async fn run(&mut self) -> Result<()> {
        let total = self.points.len();
        // Up to the clearance first (never down here: the tool may be above anything).
        if self.work().z < self.ask.clearance {
            self.move_axis(Axis::Z, self.ask.clearance).await?;
        }
        for (done, k) in serpentine(self.ask.nx, self.ask.ny).enumerate() {
            let [x, y] = point_xy(&self.ask, k);
            let (i, j) = (k % self.ask.nx as usize, k / self.ask.nx as usize);
            self.move_axis(Axis::X, x).await?;
            self.move_axis(Axis::Y, y).await?;
            // Only above the first point can the tool still be above the clearance.
            self.move_axis(Axis::Z, self.ask.clearance).await?;
            let report = self
                .m
                .probe_ticketed(
                    ProbeAsk {
                        axis: Axis::Z,
                        positive: false,
                        distance: self.ask.distance,
                        feed: self.ask.feed,
                        until: ProbeUntil::Contact,
                    },
                    self.actor,
                    self.ticket,
                )
                .await?;
            let Some(trip) = report.trip else {
                return Err(Error::invalid(
                    "probe_not_tripped",
                    format!(
                        "point ({i}, {j}) at X{x:.3} Y{y:.3}: the probe ran its whole {} mm below \
                         the clearance Z{} without touching",
                        self.ask.distance, self.ask.clearance
                    ),
                ));
            };
            self.check_zero()?;
            let z = trip.z - self.zero[2];
            self.points[k] = Some(z);
            self.m.bus.transient(
                EventKind::HeightMapProgress,
                Some(self.m.id),
                json!({"map": self.id, "done": done + 1, "total": total,
                       "i": i, "j": j, "x": x, "y": y, "z": z}),
            );
            if let Err(e) = self
                .store
                .update_height_map_points(self.id, &self.points_json())
                .await
            {
                // Kept in memory: the end writes them all (and start-up fails a map left
                // probing).
                tracing::warn!(machine = self.m.id, map = self.id, error = %e, "could not store a probed point yet");
            }
            self.move_axis(Axis::Z, self.ask.clearance).await?;
        }
        Ok(())
    }

    fn work(&self) -> AxisValues {
        self.m.status().work_position
    }

    /// The work offset must stay the one the grid started with: its heights are in it.
    fn check_zero(&self) -> Result<()> {
        let now = work_zero(&self.m.status());
        if now.iter().zip(self.zero).any(|(a, b)| (a - b).abs() > 1e-9) {
            return Err(Error::conflict(
                "offset_changed",
                format!(
                    "the work zero moved while the grid was probed (from machine {:?} to {:?})",
                    self.zero, now
                ),
            ));
        }
        Ok(())
    }

    /// Moves `axis` to work position `to` with as few jogs as `max_jog_mm` allows, each
    /// waited for; the tool must then be there.
    async fn move_axis(&self, axis: Axis, to: f64) -> Result<()> {
        let from = self.work().get(axis);
        let delta = to - from;
        if delta.abs() <= POSITION_TOLERANCE_MM / 10.0 {
            return Ok(());
        }
        let reach = self.m.row().max_jog_mm;
        let n = (delta.abs() / reach).ceil().max(1.0);
        let step = delta / n;
        for k in 1..=(n as u32) {
            self.check_zero()?;
            let mut watch = self.m.subscribe_status();
            self.m
                .jog_ticketed(axis, step, self.ask.travel_feed, self.actor, self.ticket)
                .await?;
            self.m.sync().await;
            let bound = match self.ask.travel_feed {
                Some(f) => Duration::from_secs_f64(step.abs() / f * 60.0) * 2 + MOVE_GRACE,
                None => MOVE_LIMIT_UNKNOWN_FEED,
            };
            let still = watch.wait_for(|s| s.state != MachineState::Jogging);
            if tokio::time::timeout(bound, still).await.is_err() {
                if let Err(e) = self.m.cancel_jogs(&format!("height_map:{}", self.id)).await {
                    tracing::error!(machine = self.m.id, error = %e, "could not stop an overdue grid move");
                }
                return Err(Error::new(
                    ErrorKind::Timeout,
                    "machine_moving",
                    format!(
                        "a {} move of the grid had not ended after {bound:?}; the machine was \
                         stopped",
                        axis.letter()
                    ),
                ));
            }
            let want = from + step * f64::from(k);
            let st = self.m.status();
            let at = st.work_position.get(axis);
            if (at - want).abs() > POSITION_TOLERANCE_MM {
                // A stop or feed hold ended the move: the grid ends as stopped.
                self.m.gate.check(self.ticket)?;
                let why = match st.state {
                    MachineState::Alarm => format!(
                        " (alarm: {})",
                        st.alarm.as_deref().unwrap_or("no reason given")
                    ),
                    _ => String::new(),
                };
                return Err(Error::conflict(
                    "height_map_moved",
                    format!(
                        "the {} move to work {want:.4} ended at {at:.4}{why}; something else \
                         moved the machine",
                        axis.letter()
                    ),
                ));
            }
        }
        Ok(())
    }

    fn points_json(&self) -> String {
        serde_json::to_string(&self.points).unwrap_or_else(|_| "[]".into())
    }

    /// Stores the end (complete, or what was probed with why it ended) and records it.
    async fn finish(&self, result: Result<()>) {
        let (state, message) = match &result {
            Ok(()) => ("complete", None),
            Err(e) => (ended_by(e), Some(format!("{}: {}", e.code, e.message))),
        };
        let points = self.points_json();
        let health = self.store.health().clone();
        let stored = health
            .guard(
                self.store
                    .finish_height_map(self.id, state, &points, message.as_deref()),
            )
            .await;
        if let Err(e) = stored {
            tracing::error!(machine = self.m.id, map = self.id, error = %e, "could not store the end of a height map; it is failed at the next start");
        }
        let probed: Vec<f64> = self.points.iter().flatten().copied().collect();
        self.m
            .bus
            .record_or_log(
                EventKind::HeightMapEnded,
                Some(self.m.id),
                Some(self.actor),
                json!({"map": self.id, "state": state, "probed": probed.len(),
                       "total": self.points.len(), "nx": self.ask.nx, "ny": self.ask.ny,
                       "area": self.ask.area,
                       "min": probed.iter().copied().reduce(f64::min),
                       "max": probed.iter().copied().reduce(f64::max),
                       "message": message}),
            )
            .await;
    }
}

/// A map ready for a job: its id and the grid in the work coordinates the job starts in.
#[derive(Debug, Clone, PartialEq)]
pub struct Applied {
    pub id: i64,
    pub map: HeightMap,
}

/// How a map fits a job's program (`GET /machines/{id}/height-maps/{hid}/fit?job=J`, and the
/// check a start with the map makes).
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct HeightMapFit {
    pub job: i64,
    pub height_map: i64,
    /// The program's cutting moves' XY extent, work coordinates `[x_min, x_max, y_min,
    /// y_max]` (null when it has no cutting move).
    pub program_area: Option<[f64; 4]>,
    /// The map's area in the work coordinates in force now, `[x_min, x_max, y_min, y_max]`.
    pub map_area: [f64; 4],
    /// The program's cutting moves lie inside the map's area.
    pub fits: bool,
    /// Where they leave it, when they do.
    pub overhang: Option<String>,
    /// Lowest and highest Z correction over the program's area (over the map's, without
    /// cutting moves), mm, in the work coordinates in force now.
    pub correction_min: f64,
    pub correction_max: f64,
}

/// The cutting XY extent of a job's stored analysis.
fn cutting_area(job: &JobRow) -> Option<[f64; 4]> {
    let a: serde_json::Value = serde_json::from_str(job.analysis.as_deref()?).ok()?;
    let b = a.get("cutting_bounds")?;
    let v = |k: &str, i: usize| b.get(k)?.get(i)?.as_f64();
    Some([v("min", 0)?, v("max", 0)?, v("min", 1)?, v("max", 1)?])
}

/// A complete map as the grid the backend applies, in the work zero `zero_now` (machine
/// coordinates of the work zero in force).
fn grid_of(row: &HeightMapRow, zero_now: [f64; 3]) -> Result<HeightMap> {
    if row.state != "complete" {
        return Err(Error::conflict(
            "height_map_incomplete",
            format!(
                "height map {} is {}{}; only a complete map is applied",
                row.id,
                row.state,
                row.message
                    .as_deref()
                    .map(|m| format!(" ({m})"))
                    .unwrap_or_default()
            ),
        ));
    }
    let points: Vec<Option<f64>> = serde_json::from_str(&row.points).map_err(|e| {
        Error::internal(format!("height map {} has unreadable points: {e}", row.id))
    })?;
    let z: Option<Vec<f64>> = points.into_iter().collect();
    let (nx, ny) = (
        u32::try_from(row.nx).unwrap_or(0),
        u32::try_from(row.ny).unwrap_or(0),
    );
    let stored = HeightMap {
        x0: row.x0,
        y0: row.y0,
        dx: (row.x1 - row.x0) / f64::from(nx.max(2) - 1),
        dy: (row.y1 - row.y0) / f64::from(ny.max(2) - 1),
        nx,
        ny,
        z: z.ok_or_else(|| {
            Error::conflict(
                "height_map_incomplete",
                format!("height map {} has points it never probed", row.id),
            )
        })?,
    };
    let map = stored.shifted([
        row.offset_x - zero_now[0],
        row.offset_y - zero_now[1],
        row.offset_z - zero_now[2],
    ]);
    map.validate()
        .map_err(|m| Error::internal(format!("height map {}: {m}", row.id)))?;
    Ok(map)
}

/// How map `row` fits `job` with the machine's work zero as `status` shows it.
pub fn fit(
    row: &HeightMapRow,
    job: &JobRow,
    status: &MachineStatus,
) -> Result<(HeightMapFit, HeightMap)> {
    if row.machine_id != job.machine_id {
        return Err(Error::invalid(
            "height_map_other_machine",
            format!(
                "height map {} belongs to machine {}, job {} to machine {}",
                row.id, row.machine_id, job.id, job.machine_id
            ),
        ));
    }
    let map = grid_of(row, work_zero(status))?;
    let area = map.area();
    let program = cutting_area(job);
    let mut overhang = Vec::new();
    if let Some([x_min, x_max, y_min, y_max]) = program {
        for (what, v, limit, beyond) in [
            ("X", x_min, area[0], x_min < area[0] - AREA_EPS),
            ("X", x_max, area[1], x_max > area[1] + AREA_EPS),
            ("Y", y_min, area[2], y_min < area[2] - AREA_EPS),
            ("Y", y_max, area[3], y_max > area[3] + AREA_EPS),
        ] {
            if beyond {
                overhang.push(format!(
                    "{what} {v:.3} is {:.3} mm past the map's edge {what} {limit:.3}",
                    (v - limit).abs()
                ));
            }
        }
    }
    let (correction_min, correction_max) = map.range_over(match program {
        Some([x_min, x_max, y_min, y_max]) => [
            x_min.max(area[0]),
            x_max.min(area[1]).max(x_min.max(area[0])),
            y_min.max(area[2]),
            y_max.min(area[3]).max(y_min.max(area[2])),
        ],
        None => area,
    });
    let overhang = (!overhang.is_empty()).then(|| {
        format!(
            "the program's cutting moves (X {:.3}..{:.3}, Y {:.3}..{:.3}) leave height map {}'s \
             area (X {:.3}..{:.3}, Y {:.3}..{:.3}): {}",
            program.map_or(0.0, |p| p[0]),
            program.map_or(0.0, |p| p[1]),
            program.map_or(0.0, |p| p[2]),
            program.map_or(0.0, |p| p[3]),
            row.id,
            area[0],
            area[1],
            area[2],
            area[3],
            overhang.join("; ")
        )
    });
    Ok((
        HeightMapFit {
            job: job.id,
            height_map: row.id,
            program_area: program,
            map_area: area,
            fits: overhang.is_none(),
            overhang,
            correction_min,
            correction_max,
        },
        map,
    ))
}

/// Map `id` for a run of `job`, as of `status`: refused (before anything moves) when it does
/// not exist on the job's machine, is not complete, or the program's cutting moves leave its
/// area (`outside_height_map`, naming the overhang).
pub async fn applied_for_job(
    store: &Store,
    job: &JobRow,
    id: i64,
    status: &MachineStatus,
) -> Result<Applied> {
    let row = store
        .height_map(id)
        .await?
        .filter(|r| r.machine_id == job.machine_id)
        .ok_or_else(|| {
            Error::not_found(
                "unknown_height_map",
                format!("machine {} has no height map {id}", job.machine_id),
            )
        })?;
    let (fit, map) = fit(&row, job, status)?;
    if let Some(overhang) = fit.overhang {
        return Err(Error::invalid(
            "outside_height_map",
            format!("{overhang}; nothing was moved"),
        ));
    }
    Ok(Applied { id, map })
}

/// Deletes map `id` of machine `machine` (not one being probed) and records it.
pub async fn delete(
    store: &Store,
    bus: &crate::events::EventBus,
    machine: i64,
    id: i64,
    actor: &str,
) -> Result<()> {
    let row = store
        .height_map(id)
        .await?
        .filter(|r| r.machine_id == machine)
        .ok_or_else(|| {
            Error::not_found(
                "unknown_height_map",
                format!("machine {machine} has no height map {id}"),
            )
        })?;
    if row.state == "probing" {
        return Err(Error::conflict(
            "height_map_probing",
            format!("height map {id} is being probed: stop the machine to end it first"),
        ));
    }
    if store.delete_height_map(id).await?.is_none() {
        return Err(Error::conflict(
            "height_map_probing",
            format!("height map {id} is being probed"),
        ));
    }
    bus.record_or_log(
        EventKind::HeightMapDeleted,
        Some(machine),
        Some(actor),
        json!({"map": id, "state": row.state, "nx": row.nx, "ny": row.ny,
               "area": [row.x0, row.x1, row.y0, row.y1]}),
    )
    .await;
    Ok(())
}

/// Start-up: grids of `node`'s machines that a stopped process left `probing` are `failed`
/// (what they probed is kept), each recorded as `height_map.ended`.
pub async fn fail_leftovers(
    store: &Store,
    bus: &crate::events::EventBus,
    node: &str,
) -> std::result::Result<(), sqlx::Error> {
    for (id, machine) in store.fail_probing_height_maps_of(node).await? {
        tracing::warn!(
            machine,
            map = id,
            "height map was being probed when the server stopped; it is failed (what it probed is kept)"
        );
        bus.record_or_log(
            EventKind::HeightMapEnded,
            Some(machine),
            None,
            json!({"map": id, "state": "failed",
                   "message": "the server stopped while the grid was being probed"}),
        )
        .await;
    }
    Ok(())
}

/// A backend's refusal of a program sent with a height map it cannot apply, under its own
/// code (`height_map_unsupported`, the backend's reason kept).
pub(crate) fn refusal(e: Error, mapped: bool) -> Error {
    match e.message.strip_prefix("unsupported: ") {
        Some(why) if mapped && e.code == "backend_rejected" => {
            Error::invalid("height_map_unsupported", why.to_string())
        }
        _ => e,
    }
}

/// A backend that loaded a program without saying it applies the height map sent with it
/// (one built before height maps ignores the field).
pub(crate) fn not_confirmed() -> Error {
    Error::invalid(
        "height_map_unsupported",
        "the machine's backend loaded the program without confirming it applies the height \
         map (it was built before height maps); nothing was started",
    )
}

/// Why a resume of run `run`, started with map `map`, cannot apply it again.
pub(crate) fn for_resume(e: Error, run: i64, map: i64) -> Error {
    Error::new(
        e.kind,
        e.code,
        format!("run {run} was started with height map {map}: {}", e.message),
    )
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn ask() -> GridAsk {
        GridAsk {
            area: [0.0, 30.0, -10.0, 10.0],
            nx: 4,
            ny: 3,
            clearance: 2.0,
            distance: 5.0,
            feed: 100.0,
            travel_feed: None,
        }
    }

    #[test]
    fn points_lie_on_the_grid_and_the_serpentine_visits_each_once() {
        let a = ask();
        assert_eq!(point_xy(&a, 0), [0.0, -10.0]);
        assert_eq!(point_xy(&a, 3), [30.0, -10.0]);
        assert_eq!(point_xy(&a, 5), [10.0, 0.0]);
        assert_eq!(point_xy(&a, 11), [30.0, 10.0]);
        let order: Vec<usize> = serpentine(4, 3).collect();
        assert_eq!(order, vec![0, 1, 2, 3, 7, 6, 5, 4, 8, 9, 10, 11]);
    }

    fn row(points: Vec<Option<f64>>, state: &str) -> HeightMapRow {
        HeightMapRow {
            id: 7,
            machine_id: 1,
            state: state.into(),
            x0: 0.0,
            x1: 20.0,
            y0: 0.0,
            y1: 10.0,
            nx: 3,
            ny: 2,
            clearance: 2.0,
            distance: 5.0,
            feed: 100.0,
            offset_x: 0.0,
            offset_y: 0.0,
            offset_z: 0.0,
            points: serde_json::to_string(&points).unwrap(),
            message: None,
            created_by: "t".into(),
            created_at: 0,
            finished_at: None,
        }
    }

    fn job(bounds: Option<([f64; 3], [f64; 3])>) -> JobRow {
        JobRow {
            id: 3,
            name: "j".into(),
            machine_id: 1,
            sha256: String::new(),
            size_bytes: 0,
            line_count: 1,
            analysis: Some(
                json!({"cutting_bounds": bounds.map(|(min, max)| json!({"min": min, "max": max}))})
                    .to_string(),
            ),
            source: "http".into(),
            created_at: 0,
        }
    }

    #[test]
    fn a_map_fits_a_program_inside_it_and_names_the_overhang_otherwise() {
        let r = row(
            vec![
                Some(0.0),
                Some(0.1),
                Some(0.2),
                Some(-0.1),
                Some(0.3),
                Some(0.4),
            ],
            "complete",
        );
        let st = MachineStatus::default();
        let (f, map) = fit(&r, &job(Some(([1.0, 1.0, -1.0], [19.0, 9.0, 0.0]))), &st).unwrap();
        assert!(f.fits && f.overhang.is_none(), "{f:?}");
        assert_eq!(map.nx, 3);
        assert!(f.correction_min >= -0.1 && f.correction_max <= 0.4, "{f:?}");
        let (f, _) = fit(&r, &job(Some(([-1.5, 1.0, -1.0], [19.0, 12.0, 0.0]))), &st).unwrap();
        let o = f.overhang.unwrap();
        assert!(
            o.contains("X -1.500 is 1.500 mm past") && o.contains("Y 12.000"),
            "{o}"
        );
        // Without cutting moves: fits, the range over the whole map.
        let (f, _) = fit(&r, &job(None), &st).unwrap();
        assert!(f.fits);
        assert_eq!((f.correction_min, f.correction_max), (-0.1, 0.4));
        // The machine's work zero moved 5 mm in X and 1 mm down since the grid was probed:
        // the map moves with it (it stays on the stock).
        let moved = MachineStatus {
            machine_position: AxisValues {
                x: 5.0,
                z: -1.0,
                ..Default::default()
            },
            ..Default::default()
        };
        let (f, map) = fit(&r, &job(None), &moved).unwrap();
        assert_eq!(f.map_area, [-5.0, 15.0, 0.0, 10.0]);
        assert!((map.correction(-5.0, 0.0) - 1.0).abs() < 1e-12);
        // Incomplete maps are never applied.
        let e = fit(&row(vec![Some(0.0); 6], "stopped"), &job(None), &st).unwrap_err();
        assert_eq!(e.code, "height_map_incomplete");
    }
}

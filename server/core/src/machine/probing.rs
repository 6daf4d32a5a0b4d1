//! Probing and touch-off. A probing move is a contract operation like a jog (the operation
//! table gates and audits it); its outcome comes later as the backend's `probe_ended` event,
//! which the machine's task publishes here. [`Machine::probe`] sends the move and waits for
//! its end; [`Machine::touch_off`] probes toward a plate, sets the active work offset so the
//! axis reads the plate's thickness where it touched, and retracts.
//!
//! Whoever asked is watched for as long as the machine moves for them: if the caller goes away
//! (an HTTP client's connection drops and its request future is dropped) the motion is
//! stopped, as a lost pendant's is.

use super::moves::StopIfDropped;
use super::{limits, Machine, Msg};
use crate::error::{Error, ErrorKind, Result};
use crate::events::EventKind;
use fresa_plugin_api::contract::{
    Axis, AxisValues, Probe, ProbeOutcome, ProbeUntil, Request, WorkOffset,
};
use serde::Serialize;
use serde_json::json;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

/// The thickest touch plate a touch-off (or a pendant's `config.touch_plate_mm`) may name:
/// anything above is a typo (cm for mm), and would put the first cut that far above the part.
pub const MAX_TOUCH_PLATE_MM: f64 = 100.0;

/// The largest tool diameter an edge touch-off accepts, mm.
pub const MAX_TOOL_DIAMETER_MM: f64 = 100.0;

/// How long a probe may overrun its nominal time (distance at feed) before the host stops it
/// and says the backend never reported its end. Doubled, plus this.
const PROBE_GRACE: Duration = Duration::from_secs(10);

/// A probing move's end as the backend reported it.
#[derive(Debug, Clone, PartialEq)]
pub struct ProbeEnd {
    pub id: u64,
    pub outcome: ProbeOutcome,
    pub trip: Option<AxisValues>,
    pub position: AxisValues,
    pub message: Option<String>,
}

/// A probing move as asked: toward `positive` or negative `axis`, at most `distance` mm, at
/// `feed` mm/min, until the probe reads `until`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProbeAsk {
    pub axis: Axis,
    pub positive: bool,
    pub distance: f64,
    pub feed: f64,
    pub until: ProbeUntil,
}

/// What a probing move found (`POST /machines/{id}/probe`).
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct ProbeReport {
    /// `tripped` or `not_tripped` (the whole distance ran without contact).
    pub outcome: ProbeOutcome,
    /// Machine position where the probe input changed (only when tripped).
    pub trip: Option<AxisValues>,
    /// Machine position where motion came to rest.
    pub position: AxisValues,
    /// How far past the trip the axis came to rest, mm (only when tripped).
    pub overshoot_mm: Option<f64>,
}

/// A touch-off as asked: probe `axis` toward `positive`/negative onto a plate `plate_mm`
/// thick (0: the part itself), then retract `retract_mm` back. On X or Y the tool's side
/// touches: `tool_diameter_mm` says how far its centre is from the surface.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TouchOffAsk {
    pub axis: Axis,
    pub positive: bool,
    pub plate_mm: f64,
    /// X/Y: the tool's (or probe tip's) diameter, mm; required there, ignored on Z.
    pub tool_diameter_mm: Option<f64>,
    pub distance: f64,
    pub feed: f64,
    pub retract_mm: f64,
}

/// What a touch-off did (`POST /machines/{id}/touch-off`).
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct TouchOffReport {
    /// Machine position where the tool touched the plate.
    pub trip: AxisValues,
    pub overshoot_mm: f64,
    /// The work offset that was changed (the active one).
    pub offset: WorkOffset,
    pub before: AxisValues,
    pub after: AxisValues,
    /// Work position once retracted: the axis reads the plate's thickness plus the retract.
    pub work_position: AxisValues,
}

/// A backend refusal of the probe under its own code where the API has one.
fn probe_refusal(e: Error) -> Error {
    if e.code != "backend_rejected" {
        return e;
    }
    let code = e.message.split(':').next().unwrap_or_default();
    match code {
        "probe_already_in_state" => Error::conflict("probe_already_in_state", e.message),
        "unsupported" => Error::invalid("probe_unsupported", e.message),
        "out_of_travel" => Error::invalid("out_of_travel", e.message),
        _ => e,
    }
}

impl Machine {
    /// Work offset `offset` as the backend holds it now.
    pub(super) async fn offset_values(
        &self,
        offset: WorkOffset,
        actor: &str,
    ) -> Result<AxisValues> {
        let table: fresa_plugin_api::contract::OffsetTable =
            serde_json::from_value(self.call(Request::GetOffsets, actor).await?).map_err(|e| {
                Error::new(
                    ErrorKind::Backend,
                    "backend_error",
                    format!("the backend's offset table is unreadable: {e}"),
                )
            })?;
        Ok(table
            .offsets
            .iter()
            .find(|(o, _)| *o == offset)
            .map(|(_, v)| *v)
            .unwrap_or_default())
    }

    /// Sends one probing move and waits for its end. Refused before anything moves when the
    /// distance or feed is outside the machine's limits (`max_jog_mm`, `max_probe_feed_mm_min`),
    /// and by the backend when the probe already reads what it looks for, the whole distance
    /// is not inside the travel, or it cannot probe that axis. A stop or feed hold during it
    /// answers `stopped` once motion ended; a fault, `probe_failed`.
    pub async fn probe(self: &Arc<Self>, ask: ProbeAsk, actor: &str) -> Result<ProbeReport> {
        self.probe_ticketed(ask, actor, self.gate.ticket()).await
    }

    /// [`Machine::probe`] as part of a longer operation that took the gate's `ticket` when it
    /// began: a stop since then refuses it (`stopped`).
    pub(crate) async fn probe_ticketed(
        self: &Arc<Self>,
        ask: ProbeAsk,
        actor: &str,
        ticket: u64,
    ) -> Result<ProbeReport> {
        let row = self.row();
        if !(ask.distance.is_finite() && ask.distance > 0.0) {
            return Err(Error::invalid(
                "invalid_field",
                format!(
                    "field `distance` must be a positive number of mm (`toward` gives the \
                     direction), got {}",
                    ask.distance
                ),
            ));
        }
        limits::check_probe(&row, ask.distance, ask.feed)?;
        let id = self.probe_ids.fetch_add(1, Ordering::Relaxed);
        let mut ended = self.probe_ended.clone();
        let probe = Probe {
            id,
            axis: ask.axis,
            distance: if ask.positive {
                ask.distance
            } else {
                -ask.distance
            },
            feed: ask.feed,
            until: ask.until,
        };
        // Armed before the request is sent: a caller dropped while it waits in the queue
        // leaves a probe that nobody would watch.
        let guard = StopIfDropped::arm(self, actor);
        let sent = self
            .ask(|reply| Msg::Call {
                request: Request::Probe(probe),
                actor: actor.into(),
                ticket,
                reply,
            })
            .await;
        if let Err(e) = sent {
            guard.disarm();
            return Err(probe_refusal(e));
        }
        let nominal = Duration::from_secs_f64(ask.distance / ask.feed * 60.0);
        let bound = nominal * 2 + PROBE_GRACE;
        let waited = tokio::time::timeout(
            bound,
            ended.wait_for(|e| e.as_ref().is_some_and(|e| e.id == id)),
        )
        .await;
        let end = match waited {
            Ok(Ok(e)) => e.clone(),
            Ok(Err(_)) => None,
            Err(_) => {
                drop(guard); // stops it
                return Err(Error::new(
                    ErrorKind::Timeout,
                    "probe_unconfirmed",
                    format!(
                        "the backend did not report the end of the probe within {bound:?}; \
                         the machine was stopped"
                    ),
                ));
            }
        };
        guard.disarm();
        let end = end.ok_or_else(|| Error::internal("the machine's task ended during a probe"))?;
        let i = ask.axis.index();
        let overshoot = |t: AxisValues| (end.position.to_array()[i] - t.to_array()[i]).abs();
        match end.outcome {
            ProbeOutcome::Tripped | ProbeOutcome::NotTripped => Ok(ProbeReport {
                outcome: end.outcome,
                trip: end.trip,
                position: end.position,
                overshoot_mm: end.trip.map(overshoot),
            }),
            ProbeOutcome::Stopped => Err(Error::conflict(
                "stopped",
                format!(
                    "the probe was stopped before it tripped: {}",
                    end.message.as_deref().unwrap_or("stop")
                ),
            )),
            ProbeOutcome::Failed => Err(Error::conflict(
                "probe_failed",
                format!(
                    "the probe ended in a fault: {}",
                    end.message.as_deref().unwrap_or("no reason given")
                ),
            )),
        }
    }

    /// Touch-off on a plate: probes toward it; where the tool touches, the active work offset
    /// is moved so the part's surface behind the plate reads 0: on Z the tool tip reads the
    /// plate's thickness (it rests on the plate's top, `plate_mm` above the part); on X/Y
    /// (edge finding) the tool's centre reads minus (plate + tool radius) when it probed
    /// toward +, plus that toward -. Then it retracts and answers once the retract ended. A
    /// probe that does not trip changes nothing (`probe_not_tripped`). Recorded as
    /// `machine.touch_off` with the offset before and after (and the offset change itself as
    /// `machine.offsets`).
    pub async fn touch_off(
        self: &Arc<Self>,
        ask: TouchOffAsk,
        actor: &str,
    ) -> Result<TouchOffReport> {
        let radius = match (ask.axis, ask.tool_diameter_mm) {
            (Axis::Z, _) => 0.0,
            (Axis::A, _) => {
                return Err(Error::invalid(
                    "probe_unsupported",
                    "field `axis`: a touch-off is on X, Y or Z (A is a rotary axis)",
                ))
            }
            (_, Some(d)) if d.is_finite() && (0.0..=MAX_TOOL_DIAMETER_MM).contains(&d) => d / 2.0,
            (a, Some(d)) => {
                return Err(Error::invalid(
                    "invalid_field",
                    format!(
                        "field `tool_diameter_mm`: {d} is not a tool's diameter in mm (0 to \
                         {MAX_TOOL_DIAMETER_MM}) for the {} touch-off",
                        a.letter()
                    ),
                ))
            }
            (a, None) => {
                return Err(Error::invalid(
                    "invalid_field",
                    format!(
                        "field `tool_diameter_mm` is needed for an {} touch-off: the tool's \
                         radius lies between its centre and the edge it touches",
                        a.letter()
                    ),
                ))
            }
        };
        if !(ask.plate_mm.is_finite() && (0.0..=MAX_TOUCH_PLATE_MM).contains(&ask.plate_mm)) {
            return Err(Error::invalid(
                "invalid_field",
                format!(
                    "field `plate_mm`: {} is not a touch plate's thickness in mm (0 to \
                     {MAX_TOUCH_PLATE_MM})",
                    ask.plate_mm
                ),
            ));
        }
        let max_retract = self.row().max_jog_mm;
        if !(ask.retract_mm.is_finite() && (0.0..=max_retract).contains(&ask.retract_mm)) {
            return Err(Error::invalid(
                "invalid_field",
                format!(
                    "field `retract_mm`: {} must be 0 to {max_retract} mm (the machine's \
                     `max_jog_mm`)",
                    ask.retract_mm
                ),
            ));
        }
        // One ticket for the whole touch-off: a stop at any point in it (during the probe, while
        // the offset is set) also cancels the retract that would follow.
        let ticket = self.gate.ticket();
        let report = self
            .probe_ticketed(
                ProbeAsk {
                    axis: ask.axis,
                    positive: ask.positive,
                    distance: ask.distance,
                    feed: ask.feed,
                    until: ProbeUntil::Contact,
                },
                actor,
                ticket,
            )
            .await?;
        let Some(trip) = report.trip else {
            return Err(Error::invalid(
                "probe_not_tripped",
                format!(
                    "the probe ran its whole {} mm without touching the plate; no offset was \
                     changed (is the clip on and the plate under the tool?)",
                    ask.distance
                ),
            ));
        };
        // From the work position at rest, so whatever else the backend folds into the work
        // position (tool length, G92) stays as it was: only the offset moves.
        let status = self.status();
        let i = ask.axis.index();
        let rest_work = status.work_position.to_array()[i];
        let work_at_trip = rest_work - (status.machine_position.to_array()[i] - trip.to_array()[i]);
        let offset = status.active_offset;
        let before = self.offset_values(offset, actor).await?;
        // Where the tool's controlled point is, seen from the part's surface behind the plate.
        let toward = if ask.positive { 1.0 } else { -1.0 };
        let reads = -toward * (ask.plate_mm + radius);
        let mut after = before;
        after.set(ask.axis, before.get(ask.axis) + (work_at_trip - reads));
        self.set_offset(offset, after, actor).await?;
        self.bus
            .record_or_log(
                EventKind::MachineTouchOff,
                Some(self.id),
                Some(actor),
                json!({
                    "axis": ask.axis, "plate_mm": ask.plate_mm, "offset": offset,
                    "tool_diameter_mm": ask.tool_diameter_mm.filter(|_| ask.axis != Axis::Z),
                    "before": before, "after": after, "trip": trip,
                    "overshoot_mm": report.overshoot_mm, "source": "probe",
                }),
            )
            .await;
        if ask.retract_mm > 0.0 {
            let back = if ask.positive {
                -ask.retract_mm
            } else {
                ask.retract_mm
            };
            self.move_by(ask.axis, back, actor, ticket)
                .await
                .map_err(|e| {
                    Error::new(
                        e.kind,
                        e.code,
                        format!(
                            "the offset was set ({} {} {:.4} -> {:.4}), but the retract \
                             was not carried out: {}",
                            offset.name(),
                            ask.axis.letter(),
                            before.get(ask.axis),
                            after.get(ask.axis),
                            e.message
                        ),
                    )
                })?;
        }
        Ok(TouchOffReport {
            trip,
            overshoot_mm: report.overshoot_mm.unwrap_or_default(),
            offset,
            before,
            after,
            work_position: self.status().work_position,
        })
    }
}

//! Finding the centre of a bore (the tool inside a hole) or a boss (the tool above a round
//! stud) with probing moves, and optionally putting the active work offset's X/Y zero there.
//!
//! The rule both use: the midpoint of any chord of a circle lies on the diameter square to it.
//! Probing X both ways gives a chord whose midpoint is the centre's X whatever the Y; probing Y
//! both ways from there gives a chord through the centre (a diameter, so the centre's Y and the
//! Y diameter); a second X chord from the centre gives the X diameter. Every move is a jog or a
//! probe carrying the gate ticket taken when the operation began, so a stop at any point ends
//! it; a probe that finds no wall within its distance ends it naming the direction, and nothing
//! is changed. A caller that goes away has the motion stopped (see `moves`).

use super::probing::ProbeAsk;
use super::Machine;
use crate::error::{Error, Result};
use crate::events::EventKind;
use fresa_plugin_api::contract::{Axis, AxisValues, ProbeUntil, WorkOffset};
use serde::{Deserialize, Serialize};
use serde_json::json;
use std::sync::Arc;

/// The largest bore or boss a centre finding accepts, mm.
pub const MAX_DIAMETER_MM: f64 = 1000.0;

/// What is probed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum CentreKind {
    /// A hole: the tool starts inside it, at the probing depth.
    Bore,
    /// A round stud: the tool starts above it, roughly centred.
    Boss,
}

/// A centre finding as asked.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CentreAsk {
    pub kind: CentreKind,
    /// The tool's (or probe tip's) diameter, mm.
    pub tool_diameter_mm: f64,
    /// Bore: how far to probe out from the start each way; boss: how far to probe in from
    /// outside it (default twice `clearance_mm`). mm.
    pub distance: f64,
    /// Probing feed, mm/min (at most the machine's `max_probe_feed_mm_min`).
    pub feed: f64,
    /// Put the active work offset's X and Y zero on the centre.
    pub set_zero: bool,
    /// Boss: its diameter roughly (the tool goes down `clearance_mm` outside it), mm.
    pub boss_diameter_mm: Option<f64>,
    /// Boss: how far outside the boss the tool goes down, mm.
    pub clearance_mm: f64,
    /// Boss: how far below the start Z to probe, mm.
    pub depth_mm: Option<f64>,
}

/// What a centre finding found (`POST /machines/{id}/find-centre`).
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct CentreReport {
    pub kind: CentreKind,
    /// The centre, machine X/Y (Z and A where the tool ends).
    pub centre: AxisValues,
    /// Diameter along X and along Y, mm (the tool's diameter accounted for).
    pub diameter_x: f64,
    pub diameter_y: f64,
    /// With `set_zero`: the offset changed, before and after.
    pub offset: Option<WorkOffset>,
    pub before: Option<AxisValues>,
    pub after: Option<AxisValues>,
    /// Work position at the end (on the centre; X/Y 0 with `set_zero`).
    pub work_position: AxisValues,
}

/// Where both ends of a chord along one axis lie (the tool's centre where it touched), machine mm.
struct Chord {
    plus: f64,
    minus: f64,
}

impl Chord {
    fn mid(&self) -> f64 {
        (self.plus + self.minus) / 2.0
    }
}

fn invalid(field: &str, m: String) -> Error {
    Error::invalid("invalid_field", format!("field `{field}`: {m}"))
}

impl CentreAsk {
    /// Each field within what a tool, a bore and the machine allow; the boss's fields given.
    fn check(&self, max_jog: f64) -> Result<()> {
        if !(self.tool_diameter_mm.is_finite() && (0.0..=100.0).contains(&self.tool_diameter_mm)) {
            return Err(invalid(
                "tool_diameter_mm",
                format!(
                    "{} is not a tool's diameter in mm (0 to 100)",
                    self.tool_diameter_mm
                ),
            ));
        }
        if self.kind == CentreKind::Boss {
            let d = self.boss_diameter_mm.ok_or_else(|| {
                invalid(
                    "boss_diameter_mm",
                    "is needed to find a boss's centre: the tool goes down outside it".into(),
                )
            })?;
            if !(d.is_finite() && d > 0.0 && d <= MAX_DIAMETER_MM) {
                return Err(invalid(
                    "boss_diameter_mm",
                    format!("{d} is not a diameter in mm (0 to {MAX_DIAMETER_MM})"),
                ));
            }
            let depth = self.depth_mm.ok_or_else(|| {
                invalid(
                    "depth_mm",
                    "is needed to find a boss's centre: how far below the start to probe".into(),
                )
            })?;
            if !(depth.is_finite() && depth > 0.0 && depth <= max_jog) {
                return Err(invalid(
                    "depth_mm",
                    format!("{depth} must be more than 0 and at most {max_jog} mm (`max_jog_mm`)"),
                ));
            }
            if !(self.clearance_mm.is_finite()
                && self.clearance_mm > 0.0
                && self.clearance_mm <= 100.0)
            {
                return Err(invalid(
                    "clearance_mm",
                    format!(
                        "{} must be more than 0 and at most 100 mm",
                        self.clearance_mm
                    ),
                ));
            }
        }
        Ok(())
    }
}

impl Machine {
    /// Finds the centre of a bore or a boss (see the module's description) and, with
    /// `set_zero`, moves the active work offset so X and Y read 0 there; ends on the centre.
    /// Recorded as `machine.touch_off` (`source` `bore_centre` / `boss_centre`, with the
    /// diameters and, when set, the offset before and after).
    pub async fn find_centre(
        self: &Arc<Self>,
        ask: CentreAsk,
        actor: &str,
    ) -> Result<CentreReport> {
        ask.check(self.row().max_jog_mm)?;
        let ticket = self.gate.ticket();
        let tool = ask.tool_diameter_mm;
        let (x, y) = match ask.kind {
            CentreKind::Bore => {
                // The first X chord only finds the centre's X (its Y was anywhere).
                self.bore_chord(Axis::X, &ask, actor, ticket).await?;
                let y = self.bore_chord(Axis::Y, &ask, actor, ticket).await?;
                let x = self.bore_chord(Axis::X, &ask, actor, ticket).await?;
                (x, y)
            }
            CentreKind::Boss => {
                self.boss_chord(Axis::X, &ask, actor, ticket).await?;
                let y = self.boss_chord(Axis::Y, &ask, actor, ticket).await?;
                let x = self.boss_chord(Axis::X, &ask, actor, ticket).await?;
                (x, y)
            }
        };
        // A bore's wall is a radius beyond the tool's centre; a boss's, a radius short of it.
        let diameter = |c: &Chord| match ask.kind {
            CentreKind::Bore => c.plus - c.minus + tool,
            CentreKind::Boss => c.plus - c.minus - tool,
        };
        let (diameter_x, diameter_y) = (diameter(&x), diameter(&y));
        let status = self.status();
        let centre = status.machine_position;
        let (mut offset, mut before, mut after) = (None, None, None);
        if ask.set_zero {
            let active = status.active_offset;
            let was = self.offset_values(active, actor).await?;
            // The work position there, plus the offset: X and Y read 0 (whatever else the
            // backend folds into the work position stays as it was).
            let mut now = was;
            now.set(Axis::X, was.x + status.work_position.x);
            now.set(Axis::Y, was.y + status.work_position.y);
            self.set_offset(active, now, actor).await?;
            (offset, before, after) = (Some(active), Some(was), Some(now));
        }
        let source = match ask.kind {
            CentreKind::Bore => "bore_centre",
            CentreKind::Boss => "boss_centre",
        };
        self.bus
            .record_or_log(
                EventKind::MachineTouchOff,
                Some(self.id),
                Some(actor),
                json!({
                    "source": source, "centre": centre, "diameter_x": diameter_x,
                    "diameter_y": diameter_y, "tool_diameter_mm": tool,
                    "offset": offset, "before": before, "after": after,
                }),
            )
            .await;
        Ok(CentreReport {
            kind: ask.kind,
            centre,
            diameter_x,
            diameter_y,
            offset,
            before,
            after,
            work_position: self.status().work_position,
        })
    }

    /// One probing move along `axis` toward `positive` for at most `distance`: where it
    /// touched, or an error naming the direction when nothing was there.
    async fn touch(
        self: &Arc<Self>,
        axis: Axis,
        positive: bool,
        ask: &CentreAsk,
        actor: &str,
        ticket: u64,
    ) -> Result<f64> {
        let distance = ask.distance;
        let found = self
            .probe_ticketed(
                ProbeAsk {
                    axis,
                    positive,
                    distance,
                    feed: ask.feed,
                    until: ProbeUntil::Contact,
                },
                actor,
                ticket,
            )
            .await?;
        let toward = if positive { "+" } else { "-" };
        found.trip.map(|t| t.get(axis)).ok_or_else(|| {
            Error::invalid(
                "probe_not_tripped",
                format!(
                    "no wall within {distance} mm probing {}{toward}; nothing was changed \
                     (is the tool where it should start?)",
                    axis.letter()
                ),
            )
        })
    }

    /// Inside a bore: probes `axis` both ways from here and ends on the chord's midpoint.
    async fn bore_chord(
        self: &Arc<Self>,
        axis: Axis,
        ask: &CentreAsk,
        actor: &str,
        ticket: u64,
    ) -> Result<Chord> {
        let here = self.status().machine_position.get(axis);
        let plus = self.touch(axis, true, ask, actor, ticket).await?;
        let rest = self.status().machine_position.get(axis);
        self.move_by(axis, here - rest, actor, ticket).await?;
        let minus = self.touch(axis, false, ask, actor, ticket).await?;
        let chord = Chord { plus, minus };
        let rest = self.status().machine_position.get(axis);
        self.move_by(axis, chord.mid() - rest, actor, ticket)
            .await?;
        Ok(chord)
    }

    /// Above a boss: on each side of it along `axis`, out past it, down, probes back in, out
    /// again, up and back; ends above the chord's midpoint.
    async fn boss_chord(
        self: &Arc<Self>,
        axis: Axis,
        ask: &CentreAsk,
        actor: &str,
        ticket: u64,
    ) -> Result<Chord> {
        let (Some(d), Some(depth)) = (ask.boss_diameter_mm, ask.depth_mm) else {
            return Err(Error::internal(
                "a boss's centre without its diameter or depth",
            ));
        };
        let out = d / 2.0 + ask.clearance_mm + ask.tool_diameter_mm / 2.0;
        let here = self.status().machine_position.get(axis);
        let mut ends = [0.0; 2];
        for (k, sign) in [1.0, -1.0].into_iter().enumerate() {
            self.move_by(axis, sign * out, actor, ticket).await?;
            self.move_by(Axis::Z, -depth, actor, ticket).await?;
            ends[k] = self.touch(axis, sign < 0.0, ask, actor, ticket).await?;
            let rest = self.status().machine_position.get(axis);
            self.move_by(axis, here + sign * out - rest, actor, ticket)
                .await?;
            self.move_by(Axis::Z, depth, actor, ticket).await?;
            self.move_by(axis, -sign * out, actor, ticket).await?;
        }
        let chord = Chord {
            plus: ends[0],
            minus: ends[1],
        };
        let rest = self.status().machine_position.get(axis);
        self.move_by(axis, chord.mid() - rest, actor, ticket)
            .await?;
        Ok(chord)
    }
}

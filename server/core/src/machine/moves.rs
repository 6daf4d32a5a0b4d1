//! Moves a longer operation makes and waits for (a touch-off's retract, centre finding): a jog
//! of any length sent in pieces of at most `max_jog_mm`, each carrying the operation's gate
//! ticket (a stop since the operation began refuses the rest), answered once the machine has
//! come to rest where it was sent. Whoever asked is watched while the machine moves for them:
//! a caller that goes away (an HTTP client's request future dropped) has the motion stopped.

use super::Machine;
use crate::error::{Error, ErrorKind, Result};
use fresa_plugin_api::contract::{Axis, MachineState};
use std::sync::Arc;
use std::time::Duration;

/// How far from its target a finished move may rest, mm (the backends end moves exactly; this
/// is rounding).
const AT_TARGET_MM: f64 = 1e-3;

/// How long a move may take beyond its nominal time before the host stops it and says so.
const MOVE_GRACE: Duration = Duration::from_secs(10);

/// Stops the machine if dropped while armed: the caller of a motion went away.
pub(super) struct StopIfDropped {
    machine: Arc<Machine>,
    actor: String,
    armed: bool,
}

impl StopIfDropped {
    pub(super) fn arm(machine: &Arc<Machine>, actor: &str) -> StopIfDropped {
        StopIfDropped {
            machine: machine.clone(),
            actor: actor.to_string(),
            armed: true,
        }
    }

    pub(super) fn disarm(mut self) {
        self.armed = false;
    }
}

impl Drop for StopIfDropped {
    fn drop(&mut self) {
        if !self.armed {
            return;
        }
        let (m, actor) = (self.machine.clone(), format!("lost:{}", self.actor));
        // Dropped inside the runtime (a request future); outside it there is no caller to lose.
        if let Ok(rt) = tokio::runtime::Handle::try_current() {
            rt.spawn(async move {
                tracing::warn!(
                    machine = m.id,
                    "the caller of a motion went away; stopping it"
                );
                if let Err(e) = m.cancel_jogs(&actor).await {
                    tracing::error!(machine = m.id, error = %e, "could not stop a motion whose caller went away");
                }
            });
        }
    }
}

impl Machine {
    /// Moves `axis` by `distance` (mm, machine frame) at the backend's jog feed as part of the
    /// operation that took the gate's `ticket`, and waits until it has come to rest there. A
    /// stop or feed hold that ended it answers `stopped`; anything else that left the machine
    /// short of the target (an alarm, another client's jog cancel), `machine_moved`.
    pub(super) async fn move_by(
        self: &Arc<Self>,
        axis: Axis,
        distance: f64,
        actor: &str,
        ticket: u64,
    ) -> Result<()> {
        if distance.abs() <= AT_TARGET_MM / 10.0 {
            return Ok(());
        }
        let row = self.row();
        let want = self.status().machine_position.get(axis) + distance;
        let guard = StopIfDropped::arm(self, actor);
        let mut watch = self.subscribe_status();
        let n = (distance.abs() / row.max_jog_mm).ceil().max(1.0);
        let step = distance / n;
        for _ in 0..(n as u32) {
            if let Err(e) = self.jog_ticketed(axis, step, None, actor, ticket).await {
                // Refused (a stop came first, a limit): nothing of ours to stop.
                guard.disarm();
                return Err(e);
            }
        }
        self.sync().await;
        // The backend's jog feed is not known here: bounded by the slowest a jog may be asked
        // to go, the machine's `max_feed_mm_min` being its fastest.
        let nominal = Duration::from_secs_f64(distance.abs() / row.max_feed_mm_min.max(1.0) * 60.0);
        let bound = nominal * 20 + MOVE_GRACE;
        let still = watch.wait_for(|s| s.state != MachineState::Jogging);
        if tokio::time::timeout(bound, still).await.is_err() {
            drop(guard); // stops it
            return Err(Error::new(
                ErrorKind::Timeout,
                "machine_moving",
                format!(
                    "a {} move of {distance} mm had not ended after {bound:?}; the machine was \
                     stopped",
                    axis.letter()
                ),
            ));
        }
        guard.disarm();
        let st = self.status();
        let at = st.machine_position.get(axis);
        if (at - want).abs() > AT_TARGET_MM {
            self.gate.check(ticket)?;
            let why = match st.state {
                MachineState::Alarm => format!(
                    " (alarm: {})",
                    st.alarm.as_deref().unwrap_or("no reason given")
                ),
                _ => String::new(),
            };
            return Err(Error::conflict(
                "machine_moved",
                format!(
                    "the {} move to machine {want:.4} ended at {at:.4}{why}",
                    axis.letter()
                ),
            ));
        }
        Ok(())
    }
}

//! What a pendant asked for that the core has not carried out yet: the queue between the
//! transport plugin (whose thread pushes, and must never block) and the pendant's two tasks.
//!
//! * Bounded by construction: at most [`MAX_QUEUED_INPUTS`] ordinary inputs. Consecutive wheel
//!   counts for the same axis and step are added into one entry (their sum is exact: nothing
//!   lost, nothing counted twice), so a wheel flood is one entry, however many frames.
//! * STOP, feed hold (`Pause`) and reset never enter that queue: they go to the urgent one,
//!   which another task serves, so they never wait behind a jog. STOP and feed hold, and the loss
//!   of the link, drop every queued motion input (wheel counts, Start, HOME, macros) at once.
//! * Every motion input carries the bound machine's gate ticket from when it arrived: a stop
//!   or feed hold from anywhere (HTTP, MQTT, CLI, another pendant, `jog/cancel`) moves the
//!   gate, and what was queued before it is dropped instead of carried out.
//! * Full: a new motion input is dropped (dropping motion is safe); another input (a zero key,
//!   an upload) takes the place of the newest queued motion input, or is dropped if there is
//!   none. Either way the drop is logged, rate-limited.
//! * `connected` follows the link as the transport reports it, not the backlog.

use super::registry::lock;
use crate::machine::Gate;
use fresa_plugin_api::contract::{Axis, PendantEvent, PendantKey};
use fresa_plugin_api::quiet::Quiet;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex as StdMutex};
use tokio::sync::Notify;

/// Ordinary pendant inputs waiting at most (per pendant).
pub const MAX_QUEUED_INPUTS: usize = 64;
/// Urgent inputs waiting at most; a repeated STOP, feed hold or reset adds nothing, so only
/// a link that flaps faster than its events are recorded could reach it.
const MAX_URGENT: usize = 16;

/// The machine's gate epoch when an input arrived, and which machine it was for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Ticket {
    pub machine: i64,
    pub epoch: u64,
}

/// An ordinary input, in arrival order.
#[derive(Debug)]
pub(crate) enum Input {
    /// `count` detents of `step` on `axis` (signed), the sum of consecutive wheel events.
    Jog {
        axis: Axis,
        step: f64,
        count: i64,
        /// A single event over the machine's `max_jog_mm`: kept apart, so it is refused on its
        /// own (refused, not clamped) and never takes allowed counts with it.
        alone: bool,
        ticket: Option<Ticket>,
    },
    Key {
        key: PendantKey,
        ticket: Option<Ticket>,
    },
    /// Uploads and their failures: not motion, never dropped by a stop.
    Other(PendantEvent),
}

impl Input {
    fn is_motion(&self) -> bool {
        match self {
            Input::Jog { .. } => true,
            Input::Key { key, .. } => moves(*key),
            Input::Other(_) => false,
        }
    }
    fn ticket(&self) -> Option<Ticket> {
        match self {
            Input::Jog { ticket, .. } | Input::Key { ticket, .. } => *ticket,
            Input::Other(_) => None,
        }
    }
}

/// Keys that start motion (or switch the spindle, for a macro): dropped by a stop.
pub(crate) fn moves(key: PendantKey) -> bool {
    matches!(
        key,
        PendantKey::Start
            | PendantKey::Home
            | PendantKey::M1
            | PendantKey::M2
            | PendantKey::M3
            | PendantKey::M4
    )
}

/// Keys that overtake the queue.
pub(crate) fn urgent(key: PendantKey) -> bool {
    matches!(
        key,
        PendantKey::Stop | PendantKey::Pause | PendantKey::Reset
    )
}

#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Urgent {
    Key(PendantKey),
    Connected { address: String },
    Lost { reason: String },
}

/// The machine the pendant is bound to, as the inbox needs it when an input arrives.
pub(crate) struct Binding {
    pub machine: i64,
    pub gate: Arc<Gate>,
    pub max_jog_mm: f64,
}

/// A wheel move taken from the queue to be sent as one jog.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct WheelJog {
    pub axis: Axis,
    pub step: f64,
    pub count: i64,
    pub alone: bool,
    pub ticket: Option<Ticket>,
}

#[derive(Default)]
struct Queues {
    ordinary: VecDeque<Input>,
    urgent: VecDeque<Urgent>,
    binding: Option<Binding>,
}

impl Queues {
    /// The ticket a motion input arriving now gets.
    fn ticket_now(&self) -> Option<Ticket> {
        self.binding.as_ref().map(|b| Ticket {
            machine: b.machine,
            epoch: b.gate.ticket(),
        })
    }

    /// Drops motion inputs a stop has overtaken (or that were for another machine).
    fn drop_overtaken(&mut self) -> usize {
        let now = self.ticket_now();
        let before = self.ordinary.len();
        self.ordinary
            .retain(|i| !i.is_motion() || i.ticket().is_none() || i.ticket() == now);
        before - self.ordinary.len()
    }

    fn drop_motion(&mut self) -> usize {
        let before = self.ordinary.len();
        self.ordinary.retain(|i| !i.is_motion());
        before - self.ordinary.len()
    }
}

pub struct Inbox {
    pendant: i64,
    q: StdMutex<Queues>,
    connected: AtomicBool,
    pub(crate) ordinary_ready: Notify,
    pub(crate) urgent_ready: Notify,
    quiet: Quiet,
}

impl Inbox {
    pub fn new(pendant: i64) -> Inbox {
        Inbox {
            pendant,
            q: StdMutex::new(Queues::default()),
            connected: AtomicBool::new(false),
            ordinary_ready: Notify::new(),
            urgent_ready: Notify::new(),
            quiet: Quiet::per_minute(),
        }
    }

    /// Whether the link to the pendant is up, as the transport last reported it.
    pub fn connected(&self) -> bool {
        self.connected.load(Ordering::SeqCst)
    }

    /// Sets the machine new inputs are for. A different machine (or none) drops the queued
    /// motion inputs: they were meant for the machine it was bound to.
    pub(crate) fn bind(&self, binding: Option<Binding>) {
        let mut q = lock(&self.q);
        let same = match (&q.binding, &binding) {
            (Some(a), Some(b)) => a.machine == b.machine,
            (None, None) => true,
            _ => false,
        };
        q.binding = binding;
        if !same {
            q.drop_motion();
        }
    }

    /// Queues one event from the transport. Called on the plugin's thread: never blocks
    /// (one short lock), never grows past its bounds.
    pub fn push(&self, event: PendantEvent) {
        let mut q = lock(&self.q);
        match event {
            PendantEvent::Connected { address } => {
                self.connected.store(true, Ordering::SeqCst);
                self.push_urgent(&mut q, Urgent::Connected { address });
            }
            PendantEvent::Lost { reason } => {
                // Before anything else: motion asked for just before the link died is not
                // started, nobody could stop it from that pendant any more.
                self.connected.store(false, Ordering::SeqCst);
                let n = q.drop_motion();
                self.log_dropped(n, "the pendant's link was lost");
                self.push_urgent(&mut q, Urgent::Lost { reason });
            }
            PendantEvent::Key { key } if urgent(key) => {
                if matches!(key, PendantKey::Stop | PendantKey::Pause) {
                    let n = q.drop_motion();
                    self.log_dropped(n, "STOP or feed hold was pressed");
                }
                self.push_urgent(&mut q, Urgent::Key(key));
            }
            PendantEvent::Jog { axis, count, step } => {
                self.push_jog(&mut q, axis, i64::from(count), step)
            }
            PendantEvent::Key { key } => {
                let ticket = q.ticket_now();
                self.push_ordinary(&mut q, Input::Key { key, ticket });
            }
            other => self.push_ordinary(&mut q, Input::Other(other)),
        }
    }

    fn push_urgent(&self, q: &mut Queues, u: Urgent) {
        // A STOP already waiting covers another one; likewise feed hold and reset.
        if matches!(u, Urgent::Key(_)) && q.urgent.contains(&u) {
            return;
        }
        if q.urgent.len() >= MAX_URGENT {
            // Only link changes can pile up: the oldest of them goes (its successors say
            // where the link is now); keys stay.
            match q.urgent.iter().position(|u| !matches!(u, Urgent::Key(_))) {
                Some(i) => {
                    q.urgent.remove(i);
                }
                None => return,
            }
        }
        q.urgent.push_back(u);
        self.urgent_ready.notify_one();
    }

    fn push_jog(&self, q: &mut Queues, axis: Axis, count: i64, step: f64) {
        if count == 0 || !step.is_finite() {
            return;
        }
        q.drop_overtaken();
        let ticket = q.ticket_now();
        let alone = q
            .binding
            .as_ref()
            .is_some_and(|b| (count as f64 * step).abs() > b.max_jog_mm + 1e-9);
        if !alone {
            if let Some(Input::Jog {
                axis: a,
                step: s,
                count: c,
                alone: false,
                ticket: t,
            }) = q.ordinary.back_mut()
            {
                if *a == axis && *s == step && *t == ticket {
                    *c = c.saturating_add(count);
                    self.ordinary_ready.notify_one();
                    return;
                }
            }
        }
        self.push_ordinary(
            q,
            Input::Jog {
                axis,
                step,
                count,
                alone,
                ticket,
            },
        );
    }

    fn push_ordinary(&self, q: &mut Queues, input: Input) {
        if input.is_motion() {
            q.drop_overtaken();
        }
        if q.ordinary.len() >= MAX_QUEUED_INPUTS {
            let newest_motion = q.ordinary.iter().rposition(Input::is_motion);
            match newest_motion {
                Some(i) if !input.is_motion() => {
                    if let Some(dropped) = q.ordinary.remove(i) {
                        self.log_full(&dropped);
                    }
                }
                _ => {
                    self.log_full(&input);
                    return;
                }
            }
        }
        q.ordinary.push_back(input);
        self.ordinary_ready.notify_one();
    }

    /// Built only when logged, and short: an upload's program is never put in the log.
    fn log_full(&self, dropped: &Input) {
        let pendant = self.pendant;
        if let Some(line) = self.quiet.admit("full", || {
            let what = match dropped {
                Input::Jog {
                    axis, step, count, ..
                } => format!("a wheel move of {count} x {step} mm on {axis:?}"),
                Input::Key { key, .. } => format!("the key {key:?}"),
                Input::Other(_) => "an upload message".to_string(),
            };
            format!(
                "pendant input dropped: {MAX_QUEUED_INPUTS} inputs are already waiting \
                 (the pendant sends faster than the machine moves; stop turning the wheel or \
                 pressing keys until it catches up): {what}"
            )
        }) {
            tracing::warn!(pendant, "{line}");
        }
    }

    fn log_dropped(&self, n: usize, why: &str) {
        if n > 0 {
            tracing::info!(
                pendant = self.pendant,
                dropped = n,
                "queued pendant motion inputs dropped: {why}"
            );
        }
    }

    pub(crate) fn pop_urgent(&self) -> Option<Urgent> {
        lock(&self.q).urgent.pop_front()
    }

    /// Whether the next ordinary input is a wheel move (which waits for the machine to finish
    /// the previous one while later counts join it).
    pub(crate) fn next_is_wheel(&self) -> Option<bool> {
        let mut q = lock(&self.q);
        q.drop_overtaken();
        q.ordinary.front().map(|i| matches!(i, Input::Jog { .. }))
    }

    /// Takes the front wheel move's detents, as many as fit in `max_distance_mm` (all of it
    /// when it is `alone`); the rest stays at the front. None when the front is not a wheel
    /// move (a stop dropped it meanwhile).
    pub(crate) fn take_wheel(&self, max_distance_mm: f64) -> Option<WheelJog> {
        let mut q = lock(&self.q);
        q.drop_overtaken();
        let Some(Input::Jog {
            axis,
            step,
            count,
            alone,
            ticket,
            ..
        }) = q.ordinary.front_mut()
        else {
            return None;
        };
        // Whole detents only, so the sum stays exact; at least one (a single detent over the
        // limit was queued `alone` and is refused whole).
        let max_count = (((max_distance_mm + 1e-9) / *step).floor() as i64).max(1);
        let taken = if *alone || count.abs() <= max_count {
            *count
        } else {
            max_count * count.signum()
        };
        let jog = WheelJog {
            axis: *axis,
            step: *step,
            count: taken,
            alone: *alone,
            ticket: *ticket,
        };
        *count -= taken;
        if *count == 0 {
            q.ordinary.pop_front();
        }
        Some(jog)
    }

    /// The next input that is not a wheel move.
    pub(crate) fn pop_other(&self) -> Option<Input> {
        let mut q = lock(&self.q);
        q.drop_overtaken();
        match q.ordinary.front() {
            Some(Input::Jog { .. }) | None => None,
            Some(_) => q.ordinary.pop_front(),
        }
    }

    /// Ordinary inputs waiting (for tests and the status).
    #[cfg(test)]
    fn queued(&self) -> usize {
        lock(&self.q).ordinary.len()
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn jog(axis: Axis, count: i32, step: f64) -> PendantEvent {
        PendantEvent::Jog { axis, count, step }
    }

    fn bound(inbox: &Inbox, max_jog_mm: f64) -> Arc<Gate> {
        let gate = Arc::new(Gate::default());
        inbox.bind(Some(Binding {
            machine: 1,
            gate: gate.clone(),
            max_jog_mm,
        }));
        gate
    }

    /// Every detent taken from the queue, chunk by chunk.
    fn drain_wheel(inbox: &Inbox, max_distance_mm: f64) -> Vec<WheelJog> {
        let mut out = Vec::new();
        while inbox.next_is_wheel() == Some(true) {
            out.push(inbox.take_wheel(max_distance_mm).unwrap());
        }
        out
    }

    #[test]
    fn a_wheel_flood_is_one_entry_with_the_exact_sum() {
        let inbox = Inbox::new(1);
        bound(&inbox, 50.0);
        for _ in 0..300_000 {
            inbox.push(jog(Axis::X, 1, 0.01));
        }
        inbox.push(jog(Axis::X, -7, 0.01));
        assert_eq!(inbox.queued(), 1);
        // Taken in chunks of at most max_jog_mm (5000 detents of 0.01): 299993 in all.
        let chunks = drain_wheel(&inbox, 50.0);
        assert_eq!(chunks.iter().map(|c| c.count).sum::<i64>(), 299_993);
        assert!(chunks.iter().all(|c| c.count <= 5000 && c.axis == Axis::X));
        assert_eq!(chunks.len(), 60);
    }

    #[test]
    fn another_axis_or_step_starts_a_new_entry_and_order_is_kept() {
        let inbox = Inbox::new(1);
        bound(&inbox, 50.0);
        inbox.push(jog(Axis::X, 1, 0.01));
        inbox.push(jog(Axis::X, 2, 0.01));
        inbox.push(jog(Axis::Y, 3, 0.01));
        inbox.push(jog(Axis::Y, 4, 0.1));
        inbox.push(PendantEvent::Key {
            key: PendantKey::ZeroX,
        });
        inbox.push(jog(Axis::Y, 5, 0.1));
        let got: Vec<(Axis, i64)> = drain_wheel(&inbox, 1000.0)
            .iter()
            .map(|j| (j.axis, j.count))
            .collect();
        assert_eq!(got, [(Axis::X, 3), (Axis::Y, 3), (Axis::Y, 4)]);
        assert!(matches!(
            inbox.pop_other(),
            Some(Input::Key {
                key: PendantKey::ZeroX,
                ..
            })
        ));
        assert_eq!(inbox.take_wheel(1000.0).unwrap().count, 5);
        assert!(inbox.next_is_wheel().is_none());
    }

    #[test]
    fn a_frame_over_the_jog_limit_stays_alone_and_whole() {
        let inbox = Inbox::new(1);
        bound(&inbox, 5.0);
        inbox.push(jog(Axis::X, 100, 0.01));
        inbox.push(jog(Axis::X, 600, 0.01));
        inbox.push(jog(Axis::X, 100, 0.01));
        let got: Vec<(i64, bool)> = drain_wheel(&inbox, 5.0)
            .iter()
            .map(|j| (j.count, j.alone))
            .collect();
        assert_eq!(got, [(100, false), (600, true), (100, false)]);
    }

    #[test]
    fn stop_feed_hold_and_loss_drop_queued_motion_but_not_other_inputs() {
        for drop_by in [
            PendantEvent::Key {
                key: PendantKey::Stop,
            },
            PendantEvent::Key {
                key: PendantKey::Pause,
            },
            PendantEvent::Lost {
                reason: "closed".into(),
            },
        ] {
            let inbox = Inbox::new(1);
            bound(&inbox, 50.0);
            inbox.push(PendantEvent::Connected {
                address: "a".into(),
            });
            assert!(inbox.connected());
            inbox.push(jog(Axis::X, 1, 0.01));
            inbox.push(PendantEvent::Key {
                key: PendantKey::Home,
            });
            inbox.push(PendantEvent::Key {
                key: PendantKey::ZeroY,
            });
            inbox.push(jog(Axis::X, 1, 0.01));
            inbox.push(drop_by.clone());
            assert_eq!(inbox.queued(), 1, "{drop_by:?}");
            assert!(matches!(
                inbox.pop_other(),
                Some(Input::Key {
                    key: PendantKey::ZeroY,
                    ..
                })
            ));
            assert_eq!(
                inbox.pop_urgent(),
                Some(Urgent::Connected {
                    address: "a".into()
                })
            );
            let second = inbox.pop_urgent().unwrap();
            match drop_by {
                PendantEvent::Lost { .. } => {
                    assert!(matches!(second, Urgent::Lost { .. }));
                    assert!(!inbox.connected(), "the link, not the backlog");
                }
                PendantEvent::Key { key } => assert_eq!(second, Urgent::Key(key)),
                _ => unreachable!(),
            }
        }
    }

    #[test]
    fn a_stop_from_anywhere_moves_the_gate_and_overtakes_what_was_queued() {
        let inbox = Inbox::new(1);
        let gate = bound(&inbox, 50.0);
        inbox.push(jog(Axis::X, 10, 0.01));
        inbox.push(PendantEvent::Key {
            key: PendantKey::Start,
        });
        gate.overtake();
        assert_eq!(inbox.next_is_wheel(), None, "both dropped");
        // Input after the stop is carried out, with the new ticket.
        inbox.push(jog(Axis::X, 2, 0.01));
        let j = inbox.take_wheel(100.0).unwrap();
        assert_eq!(j.count, 2);
        assert_eq!(j.ticket.map(|t| t.epoch), Some(gate.ticket()));
    }

    #[test]
    fn bounded_when_inputs_do_not_coalesce_and_a_non_motion_input_takes_a_motion_slot() {
        let inbox = Inbox::new(1);
        bound(&inbox, 50.0);
        for i in 0..10_000 {
            let axis = if i % 2 == 0 { Axis::X } else { Axis::Y };
            inbox.push(jog(axis, 1, 0.01));
        }
        assert_eq!(inbox.queued(), MAX_QUEUED_INPUTS);
        inbox.push(PendantEvent::Key {
            key: PendantKey::ZeroZ,
        });
        assert_eq!(inbox.queued(), MAX_QUEUED_INPUTS);
        let wheel = drain_wheel(&inbox, 1000.0);
        assert_eq!(wheel.len(), MAX_QUEUED_INPUTS - 1);
        assert!(matches!(
            inbox.pop_other(),
            Some(Input::Key {
                key: PendantKey::ZeroZ,
                ..
            })
        ));
        // Urgent keys are never dropped and a repeated STOP adds nothing.
        for _ in 0..1000 {
            inbox.push(PendantEvent::Key {
                key: PendantKey::Stop,
            });
        }
        assert_eq!(inbox.pop_urgent(), Some(Urgent::Key(PendantKey::Stop)));
        assert_eq!(inbox.pop_urgent(), None);
    }

    #[test]
    fn rebinding_drops_motion_meant_for_the_old_machine() {
        let inbox = Inbox::new(1);
        bound(&inbox, 50.0);
        inbox.push(jog(Axis::X, 10, 0.01));
        inbox.bind(None);
        assert_eq!(inbox.next_is_wheel(), None);
    }
}

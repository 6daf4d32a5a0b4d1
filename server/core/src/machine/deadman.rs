//! Continuous jogs held by a deadman: the jog moves (at most the machine's `max_jog_mm`) while
//! its client keeps saying "still holding", a keep-alive at least every [`DEADMAN`]; when one
//! is missing (key released without a word, tab closed, link lost) it is cancelled as
//! `jog/cancel` does. This holds the one continuous jog per machine; the machine starts, feeds
//! and watches it.

use std::sync::Mutex as StdMutex;
use std::time::{Duration, Instant};

/// The longest a continuous jog moves after its last keep-alive (before the cancel's own stop).
pub const DEADMAN: Duration = Duration::from_millis(250);

#[derive(Default)]
pub struct Deadman {
    held: StdMutex<Option<Held>>,
    next_id: StdMutex<u64>,
}

struct Held {
    id: u64,
    deadline: Instant,
}

fn lock<T>(m: &StdMutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl Deadman {
    /// Holds a new continuous jog; `None` if one is held already.
    pub(super) fn arm(&self) -> Option<u64> {
        let mut held = lock(&self.held);
        if held.is_some() {
            return None;
        }
        let mut next = lock(&self.next_id);
        *next += 1;
        *held = Some(Held {
            id: *next,
            deadline: Instant::now() + DEADMAN,
        });
        Some(*next)
    }

    /// A keep-alive: false when no continuous jog is held (it ended, or was never started).
    pub(super) fn feed(&self) -> bool {
        match lock(&self.held).as_mut() {
            Some(h) => {
                h.deadline = Instant::now() + DEADMAN;
                true
            }
            None => false,
        }
    }

    /// When jog `id` is due, if it is still the one held.
    pub(super) fn deadline(&self, id: u64) -> Option<Instant> {
        lock(&self.held)
            .as_ref()
            .filter(|h| h.id == id)
            .map(|h| h.deadline)
    }

    /// Lets go of jog `id` (or any, with `None`), e.g. once it ended or was cancelled.
    pub(super) fn release(&self, id: Option<u64>) {
        let mut held = lock(&self.held);
        if id.is_none() || held.as_ref().map(|h| h.id) == id {
            *held = None;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_jog_is_held_fed_and_released() {
        let d = Deadman::default();
        let Some(id) = d.arm() else {
            panic!("the first jog is held")
        };
        assert!(d.arm().is_none(), "a second is refused while one is held");
        let first = d.deadline(id);
        assert!(d.feed());
        assert!(d.deadline(id) >= first);
        d.release(Some(id + 1));
        assert!(d.deadline(id).is_some(), "another id releases nothing");
        d.release(Some(id));
        assert!(!d.feed() && d.deadline(id).is_none());
        assert!(d.arm().is_some());
    }
}

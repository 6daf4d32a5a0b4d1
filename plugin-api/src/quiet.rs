//! Rate-limited warnings, for anything that can repeat per frame, per event or per status push
//! (a clamped LCD field, garbage on a pendant link, a refused wheel input): the first one of a
//! kind is logged, then at most one per period, saying how many like it were left out since.
//! Used by the server and by plugins (which log through the host) alike.
//!
//! ```
//! use fresa_plugin_api::quiet::Quiet;
//! let quiet = Quiet::per_minute();
//! for _ in 0..1000 {
//!     if let Some(line) = quiet.admit("clamp", || "value clamped".to_string()) {
//!         eprintln!("{line}"); // printed once, not 1000 times
//!     }
//! }
//! ```

use std::collections::HashMap;
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// The period [`Quiet::per_minute`] uses.
pub const PER_MINUTE: Duration = Duration::from_secs(60);
/// Kinds tracked at once; a caller's keys are kinds (`"clamp"`, `"skipped"`), not messages, so
/// this is never reached in practice. Beyond it, new kinds share one slot (still rate-limited).
const MAX_KINDS: usize = 256;
const OVERFLOW_KIND: &str = "(other kinds)";

struct Slot {
    logged_at: Instant,
    left_out: u64,
}

/// Decides, per kind of message, whether to log now. Cheap when it says no: the message is
/// only built for lines that are logged. Shareable between threads.
pub struct Quiet {
    period: Duration,
    kinds: Mutex<HashMap<String, Slot>>,
}

impl Quiet {
    pub fn new(period: Duration) -> Quiet {
        Quiet {
            period,
            kinds: Mutex::new(HashMap::new()),
        }
    }

    /// First one of a kind at once, then at most one a minute.
    pub fn per_minute() -> Quiet {
        Quiet::new(PER_MINUTE)
    }

    /// The line to log now for a message of kind `kind`, or `None` to stay quiet. A line logged
    /// after some were left out ends with how many: `... (412 more like this since the last one logged)`
    /// (since then, which may be longer ago than the period).
    pub fn admit(&self, kind: &str, message: impl FnOnce() -> String) -> Option<String> {
        self.admit_at(kind, Instant::now()).map(|left_out| {
            let m = message();
            if left_out == 0 {
                m
            } else {
                format!("{m} ({left_out} more like this since the last one logged)")
            }
        })
    }

    /// `Some(left out since the last logged one)` when a line of `kind` may be logged at `now`.
    fn admit_at(&self, kind: &str, now: Instant) -> Option<u64> {
        let mut kinds = self.kinds.lock().unwrap_or_else(|p| p.into_inner());
        if !kinds.contains_key(kind) && kinds.len() >= MAX_KINDS {
            let period = self.period;
            kinds.retain(|_, s| now.duration_since(s.logged_at) < period || s.left_out > 0);
        }
        let key = if kinds.contains_key(kind) || kinds.len() < MAX_KINDS {
            kind
        } else {
            OVERFLOW_KIND
        };
        match kinds.get_mut(key) {
            None => {
                kinds.insert(
                    key.to_string(),
                    Slot {
                        logged_at: now,
                        left_out: 0,
                    },
                );
                Some(0)
            }
            Some(slot) if now.duration_since(slot.logged_at) >= self.period => {
                let left_out = std::mem::take(&mut slot.left_out);
                slot.logged_at = now;
                Some(left_out)
            }
            Some(slot) => {
                slot.left_out += 1;
                None
            }
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn the_first_is_logged_then_one_a_period_with_the_count_left_out() {
        let q = Quiet::new(Duration::from_secs(60));
        let t0 = Instant::now();
        assert_eq!(q.admit_at("clamp", t0), Some(0));
        for i in 1..=2569 {
            assert_eq!(q.admit_at("clamp", t0 + Duration::from_millis(i)), None);
        }
        // Another kind is not held back by the first.
        assert_eq!(q.admit_at("skipped", t0 + Duration::from_secs(1)), Some(0));
        assert_eq!(
            q.admit_at("clamp", t0 + Duration::from_secs(60)),
            Some(2569)
        );
        assert_eq!(q.admit_at("clamp", t0 + Duration::from_secs(61)), None);
        assert_eq!(q.admit_at("clamp", t0 + Duration::from_secs(120)), Some(1));
    }

    #[test]
    fn the_line_says_how_many_were_left_out_and_is_built_only_when_logged() {
        let q = Quiet::new(Duration::ZERO);
        assert_eq!(q.admit("k", || "first".into()).as_deref(), Some("first"));
        let q = Quiet::new(Duration::from_secs(3600));
        assert!(q.admit("k", || "a".into()).is_some());
        let mut built = 0;
        for _ in 0..10 {
            assert!(q
                .admit("k", || {
                    built += 1;
                    "b".into()
                })
                .is_none());
        }
        assert_eq!(built, 0);
        let slot_count = q.kinds.lock().unwrap().get("k").map(|s| s.left_out);
        assert_eq!(slot_count, Some(10));
    }

    #[test]
    fn too_many_kinds_share_one_slot_instead_of_growing() {
        let q = Quiet::new(Duration::from_secs(60));
        let t0 = Instant::now();
        for i in 0..MAX_KINDS + 100 {
            q.admit_at(&format!("kind-{i}"), t0);
        }
        assert!(q.kinds.lock().unwrap().len() <= MAX_KINDS + 1);
        // The overflow slot is rate-limited like any other.
        assert_eq!(q.admit_at("yet another", t0), None);
    }
}

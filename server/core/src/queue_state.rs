//! What this node knows of its machines' job queues without the database (issue 28): the
//! lock that orders their changes, and a summary per machine for the pendants' LCD. Kept apart
//! from `queue` so `app` can hold it without depending on the queue's logic.

use std::collections::HashMap;
use std::sync::Arc;

/// The queues' shared state on this node: a lock per machine orders the changes of its queue
/// (an operator's and the runner's), and what the pendants' LCD and status read without the
/// database.
#[derive(Default)]
pub struct Queues {
    /// One per machine that had a queue change (so at most one per machine of the node): a
    /// start that waits on a slow backend holds up that machine's queue only.
    locks: std::sync::Mutex<HashMap<i64, Arc<tokio::sync::Mutex<()>>>>,
    summary: std::sync::Mutex<HashMap<i64, Summary>>,
}

/// A queue as the pendant's LCD needs it.
#[derive(Debug, Clone, PartialEq)]
pub struct Summary {
    pub state: String,
    /// The next part (1-based) and the entry's count, while a part waits.
    pub part: Option<(i64, i64)>,
}

impl Queues {
    /// Held across each change of `machine`'s queue (and the start it may make).
    pub(crate) async fn lock(&self, machine: i64) -> tokio::sync::OwnedMutexGuard<()> {
        let lock = match self.locks.lock() {
            Ok(mut m) => m.entry(machine).or_default().clone(),
            // A panic while inserting leaves the map as it was: a fresh lock is as good.
            Err(poisoned) => poisoned.into_inner().entry(machine).or_default().clone(),
        };
        lock.lock_owned().await
    }

    pub(crate) fn note(&self, machine: i64, summary: Summary) {
        if let Ok(mut m) = self.summary.lock() {
            m.insert(machine, summary);
        }
    }

    /// The machine's queue as last seen by this node.
    pub fn summary(&self, machine: i64) -> Option<Summary> {
        self.summary.lock().ok()?.get(&machine).cloned()
    }

    /// One LCD line (at most 20 characters) while the queue waits for the operator.
    pub fn lcd_line(&self, machine: i64) -> Option<String> {
        let s = self.summary(machine)?;
        match (s.state.as_str(), s.part) {
            // START only where it fits: the part's number matters more.
            ("waiting_confirm", Some((n, of))) => Some(
                Some(format!("PART {n}/{of} START"))
                    .filter(|l| l.len() <= 20)
                    .unwrap_or_else(|| format!("PART {n}/{of}")),
            ),
            ("waiting_confirm", None) => Some("NEXT PART START".into()),
            ("held", _) => Some("QUEUE HELD".into()),
            _ => None,
        }
        .map(|l| l.chars().take(20).collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_lcd_line_names_the_part_waiting_or_the_hold_and_fits_the_lcd() {
        let q = Queues::default();
        assert_eq!(q.lcd_line(1), None);
        let waiting = |part| Summary {
            state: "waiting_confirm".into(),
            part,
        };
        q.note(1, waiting(Some((2, 20))));
        assert_eq!(q.lcd_line(1).as_deref(), Some("PART 2/20 START"));
        q.note(1, waiting(Some((9999, 10000))));
        let line = q.lcd_line(1).unwrap_or_default();
        assert!(
            line.len() <= 20 && line.starts_with("PART 9999/10000"),
            "{line}"
        );
        q.note(1, waiting(None));
        assert_eq!(q.lcd_line(1).as_deref(), Some("NEXT PART START"));
        for (state, want) in [
            ("held", Some("QUEUE HELD")),
            ("running", None),
            ("idle", None),
        ] {
            q.note(
                1,
                Summary {
                    state: state.into(),
                    part: None,
                },
            );
            assert_eq!(q.lcd_line(1).as_deref(), want, "{state}");
        }
    }
}

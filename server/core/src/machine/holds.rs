//! Why a machine holds, as the host shows it (issue 26). The backend says what it knows in its
//! status's `hold` (M0 and its message, M1, M6 and the tools, feed hold, pause); the host adds
//! what only it knows: the tool table's descriptions of the tools of a change, the reason it
//! paused a run itself (a pendant lost), and that going on waits for the database. Shared by
//! the machine's task, which sets the host's part, and its handle, which reads every status
//! through [`HostHolds::explain`]. Also: what the hold allows (a tool-change hold lets the
//! operator jog, probe and touch off), and the line a pendant's LCD shows for it.

use crate::store::{DbHealth, ToolRow};
use fresa_plugin_api::contract::{
    ContinueWith, Hold, HoldKind, MachineState, MachineStatus, PENDANT_STATUS_LINE,
};
use std::collections::BTreeMap;
use std::sync::Mutex;

/// The host's part of a machine's holds.
pub struct HostHolds {
    health: DbHealth,
    inner: Mutex<Inner>,
}

#[derive(Default)]
struct Inner {
    /// The tool table's descriptions for the current run, by tool number.
    descriptions: BTreeMap<u32, String>,
    /// A pause the host asked for itself, and why: shown instead of the backend's `pause` or
    /// `feed_hold` until the run goes on.
    reason: Option<(HoldKind, String)>,
}

impl HostHolds {
    pub fn new(health: DbHealth) -> HostHolds {
        HostHolds {
            health,
            inner: Mutex::new(Inner::default()),
        }
    }

    fn inner(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The tool table a run was loaded with (for the descriptions of a tool change).
    pub fn set_tools(&self, tools: &[ToolRow]) {
        self.inner().descriptions = tools
            .iter()
            .filter(|t| !t.description.trim().is_empty())
            .filter_map(|t| Some((u32::try_from(t.tool).ok()?, t.description.clone())))
            .collect();
    }

    /// The host pauses the run itself, for `kind` (`pendant_lost`), saying `message`.
    pub fn set_reason(&self, kind: HoldKind, message: String) {
        self.inner().reason = Some((kind, message));
    }

    /// The reason of a pause the host asked for, while it applies.
    pub fn reason(&self) -> Option<(HoldKind, String)> {
        self.inner().reason.clone()
    }

    /// The run goes on (or the host's pause did not happen): its reason no longer applies.
    pub fn clear_reason(&self) {
        self.inner().reason = None;
    }

    /// `s` with the host's part of its hold: the host's reason for a pause it asked for, the
    /// descriptions of a tool change's tools, and whether going on waits for the database.
    pub fn explain(&self, s: &mut MachineStatus) {
        let Some(hold) = s.hold.as_mut() else {
            return;
        };
        {
            let inner = self.inner();
            if let Some((kind, message)) = &inner.reason {
                if matches!(hold.kind, HoldKind::Pause | HoldKind::FeedHold) {
                    hold.kind = *kind;
                    hold.message = message.clone();
                }
            }
            if let Some(tc) = hold.tool_change.as_mut() {
                let describe = |t: Option<u32>| t.and_then(|t| inner.descriptions.get(&t).cloned());
                tc.from_description = tc.from_description.take().or_else(|| describe(tc.from));
                tc.to_description = tc.to_description.take().or_else(|| describe(Some(tc.to)));
                if let Some(d) = &tc.to_description {
                    if !hold.message.contains(d.as_str()) {
                        hold.message = format!("{} ({d})", hold.message);
                    }
                }
            }
        }
        if s.state == MachineState::Paused && !self.health.is_up() && hold.blocked.is_none() {
            hold.blocked = Some(format!(
                "going on waits for the database: {}",
                self.health.unavailable_error().message
            ));
        }
    }
}

/// Held for a manual tool change: jogs and probing moves (and so touch-off and the tool
/// setter) and offset changes are allowed while it lasts.
pub fn in_tool_change(s: &MachineStatus) -> bool {
    matches!(s.state, MachineState::Paused | MachineState::Jogging)
        && s.hold
            .as_ref()
            .is_some_and(|h| h.kind == HoldKind::ToolChange)
}

/// The hold a pause the host asked for shows in a `job.state` event when the backend's status
/// has not said yet.
pub fn operator_pause(actor: &str, reason: Option<&(HoldKind, String)>) -> Hold {
    let (kind, message) = match reason {
        Some((k, m)) => (*k, m.clone()),
        None => (HoldKind::Pause, format!("paused by {actor}")),
    };
    Hold {
        kind,
        message,
        line: None,
        program_message: None,
        continue_with: ContinueWith::Resume,
        tool_change: None,
        blocked: None,
    }
}

/// One LCD line (at most [`PENDANT_STATUS_LINE`] ASCII characters) for a hold, e.g.
/// `M0 change clamp`, `M6 T2 3mm drill`, `HOLD feed hold`.
pub fn lcd_line(hold: &Hold) -> String {
    let text = match (hold.kind, &hold.tool_change) {
        (HoldKind::ToolChange, Some(tc)) => match &tc.to_description {
            Some(d) => format!("M6 T{} {d}", tc.to),
            None => format!("M6 T{} CYCLE START", tc.to),
        },
        (HoldKind::ProgramPause | HoldKind::OptionalStop, _) => {
            let code = if hold.kind == HoldKind::OptionalStop {
                "M1"
            } else {
                "M0"
            };
            match &hold.program_message {
                Some(m) => format!("{code} {m}"),
                None => format!("{code} CYCLE START"),
            }
        }
        (HoldKind::FeedHold, _) => "HOLD feed hold".to_string(),
        (HoldKind::Pause, _) => "PAUSED".to_string(),
        (HoldKind::PendantLost, _) => "PAUSED pendant lost".to_string(),
        (HoldKind::ToolChange, None) => "M6 CYCLE START".to_string(),
    };
    let text = if hold.blocked.is_some() {
        "WAIT database".to_string()
    } else {
        text
    };
    // ASCII only (the pendant's LCD), `*` is the frame's padding: shown as `x`.
    text.chars()
        .map(|c| match c {
            '*' => 'x',
            c if c.is_ascii_graphic() || c == ' ' => c,
            _ => '?',
        })
        .take(PENDANT_STATUS_LINE)
        .collect::<String>()
        .trim_end()
        .to_string()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use fresa_plugin_api::contract::ToolChangeHold;

    fn hold(kind: HoldKind) -> Hold {
        Hold {
            kind,
            message: "m".into(),
            line: Some(3),
            program_message: None,
            continue_with: ContinueWith::CycleStart,
            tool_change: None,
            blocked: None,
        }
    }

    #[test]
    fn lcd_lines_fit_the_display_and_say_why() {
        let mut h = hold(HoldKind::ProgramPause);
        h.program_message = Some("change clamp * ñ and more text".into());
        let line = lcd_line(&h);
        assert_eq!(line, "M0 change clamp x ?");
        assert!(line.len() <= PENDANT_STATUS_LINE);
        let mut h = hold(HoldKind::ToolChange);
        h.tool_change = Some(ToolChangeHold {
            from: Some(1),
            to: 2,
            length_compensation: false,
            from_description: None,
            to_description: Some("3 mm drill".into()),
        });
        assert_eq!(lcd_line(&h), "M6 T2 3 mm drill");
        h.blocked = Some("db".into());
        assert_eq!(lcd_line(&h), "WAIT database");
    }

    #[test]
    fn the_host_names_what_it_knows() {
        let holds = HostHolds::new(DbHealth::new("test.db".into()));
        holds.set_tools(&[ToolRow {
            tool: 2,
            diameter_mm: 3.0,
            length_mm: 0.0,
            description: "3 mm drill".into(),
        }]);
        let mut h = hold(HoldKind::ToolChange);
        h.message = "M6 at line 3: change tool T1 for T2".into();
        h.tool_change = Some(ToolChangeHold {
            from: Some(1),
            to: 2,
            length_compensation: false,
            from_description: None,
            to_description: None,
        });
        let mut s = MachineStatus {
            state: MachineState::Paused,
            hold: Some(Box::new(h)),
            ..Default::default()
        };
        holds.explain(&mut s);
        let h = s.hold.clone().unwrap();
        assert_eq!(
            h.message,
            "M6 at line 3: change tool T1 for T2 (3 mm drill)"
        );
        assert_eq!(h.tool_change.unwrap().to_description.unwrap(), "3 mm drill");
        assert!(h.blocked.is_none());
        assert!(in_tool_change(&s));

        holds.set_reason(HoldKind::PendantLost, "pendant 1 lost".into());
        let mut s = MachineStatus {
            state: MachineState::Paused,
            hold: Some(Box::new(hold(HoldKind::Pause))),
            ..Default::default()
        };
        holds.health.mark_down("test outage");
        holds.explain(&mut s);
        let h = s.hold.unwrap();
        assert_eq!(
            (h.kind, h.message.as_str()),
            (HoldKind::PendantLost, "pendant 1 lost")
        );
        assert!(h.blocked.unwrap().contains("test.db"));
    }
}

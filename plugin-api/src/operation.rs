//! The operation table: how the host treats every request and command of the contract, decided
//! once per operation, here. The host's machine task reads these properties instead of keeping
//! its own lists: which lane a call takes, whether it must pass the stop gate, whether it needs
//! the database, and so on. Both matches below are exhaustive with no catch-all arm and build an
//! [`Operation`] with every field, so a new request or command does not compile until each
//! property is decided for it. This is where a new operation starts (see ARCHITECTURE.md).
//!
//! A property left out is a compile error:
//!
//! ```compile_fail
//! use fresa_plugin_api::operation::{AuditEvent, Lane, Operation};
//! // A "probe toward Z" whose author forgot to say whether it starts motion:
//! let probe = Operation {
//!     name: "probe",
//!     lane: Lane::Ordinary,
//!     needs_store: true,
//!     changes_offsets: false,
//!     refused_during_run: true,
//!     audit: Some(AuditEvent::Command),
//!     refreshes_status: false,
//! };
//! ```
//!
//! and with every property decided it compiles:
//!
//! ```
//! use fresa_plugin_api::operation::{AuditEvent, Lane, Operation};
//! let probe = Operation {
//!     name: "probe",
//!     lane: Lane::Ordinary,
//!     starts_motion: true,
//!     needs_store: true,
//!     changes_offsets: false,
//!     refused_during_run: true,
//!     audit: Some(AuditEvent::Command),
//!     refreshes_status: false,
//! };
//! assert!(probe.starts_motion);
//! ```

use crate::contract::{Command, Request, RunAction};

/// Which of a backend instance's two call threads an operation travels on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Lane {
    /// One call at a time, in the order the machine task sends them.
    Ordinary,
    /// Stop, feed hold, reset, pause, cancel and shutdown: never wait behind an ordinary call.
    Urgent,
}

/// How the host treats one operation. Every field has to be given (no `Default`): that is the
/// point.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Operation {
    /// The request's `op` (a command's `command`) as on the wire, for messages and logs.
    pub name: &'static str,
    pub lane: Lane,
    /// Starts motion: must pass the machine's stop gate (refused with `stopped` if a stop came
    /// after it was asked for, stopped again if a stop raced it into the backend).
    pub starts_motion: bool,
    /// Refused while the database is unreachable (`database_unavailable`): new motion, or a
    /// change the store must keep.
    pub needs_store: bool,
    /// Changes the work offsets: refused while the machine moves (`machine_moving`), and the
    /// store is given the new offsets afterwards (a command's as the backend reports them).
    pub changes_offsets: bool,
    /// Refused while a job runs on the machine (`machine_busy`).
    pub refused_during_run: bool,
    /// The audit event recorded when it succeeds; `None` when it records nothing itself (reads,
    /// and run control, whose run transitions are the record).
    pub audit: Option<AuditEvent>,
    /// What it changes shows in the status as soon as the backend answers (state, offsets,
    /// outputs): the host takes a fresh status before answering. A jog or MDI line reports its
    /// own progress as it moves; a read changes nothing.
    pub refreshes_status: bool,
}

/// The audit event an operation records when it succeeds. The host's event types are its own
/// (`fresa_core::events::EventKind`, which maps each of these to one); here only which one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AuditEvent {
    /// `machine.jog`
    Jog,
    /// `machine.mdi`
    Mdi,
    /// `machine.offsets`
    Offsets,
    /// `machine.command`
    Command,
    /// `machine.probe`
    Probe,
}

impl Operation {
    /// A read or connection call: ordinary lane, no gate, no store, nothing recorded.
    const fn read(name: &'static str) -> Operation {
        Operation {
            name,
            lane: Lane::Ordinary,
            starts_motion: false,
            needs_store: false,
            changes_offsets: false,
            refused_during_run: false,
            audit: None,
            refreshes_status: false,
        }
    }
}

impl Request {
    /// How the host treats this request.
    pub fn operation(&self) -> Operation {
        match self {
            Request::Connect => Operation::read("connect"),
            Request::Status => Operation::read("status"),
            Request::GetOffsets => Operation::read("get_offsets"),
            Request::GetArtifact { .. } => Operation::read("get_artifact"),
            Request::MotionProfile => Operation::read("motion_profile"),
            Request::Jog { .. } => Operation {
                name: "jog",
                lane: Lane::Ordinary,
                starts_motion: true,
                needs_store: true,
                changes_offsets: false,
                refused_during_run: true,
                audit: Some(AuditEvent::Jog),
                refreshes_status: false,
            },
            Request::Mdi { .. } => Operation {
                name: "mdi",
                lane: Lane::Ordinary,
                starts_motion: true,
                needs_store: true,
                changes_offsets: false,
                refused_during_run: true,
                audit: Some(AuditEvent::Mdi),
                refreshes_status: false,
            },
            Request::Command(c) => c.operation(),
            // A motion like a jog; its outcome comes later, as an event, and the host records
            // the probe (and any offset it sets) when that arrives.
            Request::Probe(_) => Operation {
                name: "probe",
                lane: Lane::Ordinary,
                starts_motion: true,
                needs_store: true,
                changes_offsets: false,
                refused_during_run: true,
                audit: Some(AuditEvent::Probe),
                refreshes_status: false,
            },
            Request::SetOffset { .. } => Operation {
                name: "set_offset",
                lane: Lane::Ordinary,
                starts_motion: false,
                needs_store: true,
                changes_offsets: true,
                refused_during_run: false,
                audit: Some(AuditEvent::Offsets),
                refreshes_status: true,
            },
            // Run control: the run's own lifecycle in the host records its transitions.
            Request::LoadProgram { .. } => Operation {
                name: "load_program",
                lane: Lane::Ordinary,
                starts_motion: false,
                needs_store: true,
                changes_offsets: false,
                refused_during_run: true,
                audit: None,
                refreshes_status: false,
            },
            Request::Run { action } => {
                let (name, lane, starts_motion) = match action {
                    RunAction::Start => ("run start", Lane::Ordinary, true),
                    RunAction::Resume => ("run resume", Lane::Ordinary, true),
                    RunAction::Pause => ("run pause", Lane::Urgent, false),
                    RunAction::Cancel => ("run cancel", Lane::Urgent, false),
                };
                Operation {
                    name,
                    lane,
                    starts_motion,
                    needs_store: starts_motion,
                    changes_offsets: false,
                    refused_during_run: false,
                    audit: None,
                    refreshes_status: false,
                }
            }
            Request::Shutdown => Operation {
                lane: Lane::Urgent,
                ..Operation::read("shutdown")
            },
            // The host stores the table and records `machine.tools` itself; this only tells
            // the backend. Allowed during a run: a tool measured during a tool-change hold.
            Request::SetTools { .. } => Operation::read("set_tools"),
        }
    }

    /// The lane this request travels on.
    pub fn lane(&self) -> Lane {
        self.operation().lane
    }
}

impl Command {
    /// How the host treats this command.
    pub fn operation(&self) -> Operation {
        // Stop, feed hold and reset overtake every queue and are never refused: the store, the
        // gate and a running job do not matter to them.
        let urgent = |name| Operation {
            name,
            lane: Lane::Urgent,
            starts_motion: false,
            needs_store: false,
            changes_offsets: false,
            refused_during_run: false,
            audit: Some(AuditEvent::Command),
            refreshes_status: true,
        };
        let moves = |name| Operation {
            name,
            lane: Lane::Ordinary,
            starts_motion: true,
            needs_store: true,
            changes_offsets: false,
            refused_during_run: false,
            audit: Some(AuditEvent::Command),
            refreshes_status: true,
        };
        let offsets = |name| Operation {
            name,
            lane: Lane::Ordinary,
            starts_motion: false,
            needs_store: true,
            changes_offsets: true,
            refused_during_run: false,
            audit: Some(AuditEvent::Command),
            refreshes_status: true,
        };
        // Outputs: spindle and coolant are refused while a job cuts, by the host's own check
        // (other outputs are not, so this is not `refused_during_run`).
        let output = |name| Operation {
            name,
            lane: Lane::Ordinary,
            starts_motion: false,
            needs_store: false,
            changes_offsets: false,
            refused_during_run: false,
            audit: Some(AuditEvent::Command),
            refreshes_status: true,
        };
        match self {
            Command::Stop => urgent("stop"),
            Command::FeedHold => urgent("feed_hold"),
            Command::Reset => urgent("reset"),
            Command::CycleStart => moves("cycle_start"),
            Command::Resume => moves("resume"),
            Command::Home { .. } => moves("home"),
            Command::GoToZero => moves("go_to_zero"),
            Command::Zero { .. } => offsets("zero"),
            Command::SelectOffset { .. } => offsets("select_offset"),
            Command::SetOutput { .. } => output("set_output"),
            Command::ToggleOutput { .. } => output("toggle_output"),
            // Allowed during a run (that is when it matters) and during a database outage (an
            // operator slowing a cut down must not wait for the store); never starts motion.
            Command::SetOverrides { .. } => output("set_overrides"),
        }
    }

    /// Commands that must overtake any queue of pending calls.
    pub fn is_urgent(&self) -> bool {
        self.operation().lane == Lane::Urgent
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::contract::{Axis, AxisValues, OutputName, WorkOffset};

    /// One of each request and command.
    fn every_request() -> Vec<Request> {
        let mut v = vec![
            Request::Connect,
            Request::Status,
            Request::GetOffsets,
            Request::GetArtifact { name: "x".into() },
            Request::MotionProfile,
            Request::Jog {
                axis: Axis::X,
                distance: 1.0,
                feed: None,
            },
            Request::Mdi { line: "G0".into() },
            Request::Probe(crate::contract::Probe {
                id: 1,
                axis: Axis::Z,
                distance: -10.0,
                feed: 100.0,
                until: Default::default(),
            }),
            Request::SetOffset {
                offset: WorkOffset::G55,
                values: AxisValues::default(),
            },
            Request::LoadProgram {
                run: 1,
                path: "p".into(),
                start_line: 1,
                expected_part_zero: None,
                tools: vec![],
                max_segments: None,
                optional_stop: false,
                tool_change: None,
                preamble: None,
                height_map: None,
            },
            Request::Shutdown,
            Request::SetTools { tools: vec![] },
        ];
        for action in [
            RunAction::Start,
            RunAction::Pause,
            RunAction::Resume,
            RunAction::Cancel,
        ] {
            v.push(Request::Run { action });
        }
        for c in [
            Command::CycleStart,
            Command::FeedHold,
            Command::Resume,
            Command::Stop,
            Command::Reset,
            Command::Home { axis: None },
            Command::Zero { axis: None },
            Command::GoToZero,
            Command::SelectOffset {
                offset: WorkOffset::G54,
            },
            Command::SetOutput {
                name: OutputName::Spindle,
                on: true,
            },
            Command::SetOverrides {
                feed: Some(50.0),
                spindle: None,
                rapid: None,
            },
            Command::ToggleOutput {
                name: OutputName::Coolant,
            },
        ] {
            v.push(Request::Command(c));
        }
        v
    }

    #[test]
    fn names_are_the_wire_names() {
        for r in every_request() {
            let wire = serde_json::to_value(&r).unwrap_or_default();
            let name = match &r {
                Request::Command(_) => wire["command"].as_str().map(str::to_string),
                Request::Run { .. } => wire["action"]
                    .as_str()
                    .map(|a| format!("{} {a}", wire["op"].as_str().unwrap_or_default())),
                _ => wire["op"].as_str().map(str::to_string),
            };
            assert_eq!(name.as_deref(), Some(r.operation().name), "{wire}");
        }
    }

    #[test]
    fn what_stops_motion_is_urgent_and_never_refused() {
        for r in every_request() {
            let op = r.operation();
            let stops = matches!(
                r,
                Request::Command(Command::Stop | Command::FeedHold | Command::Reset)
                    | Request::Run {
                        action: RunAction::Pause | RunAction::Cancel
                    }
                    | Request::Shutdown
            );
            assert_eq!(op.lane == Lane::Urgent, stops, "{op:?}");
            if stops {
                assert!(!op.needs_store && !op.refused_during_run && !op.starts_motion);
            }
            // New motion is never started without the store that records it.
            if op.starts_motion {
                assert!(op.needs_store, "{op:?}");
            }
        }
    }
}

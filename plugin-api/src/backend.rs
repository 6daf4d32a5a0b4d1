//! The typed machine-backend trait: implement [`MachineBackend`], export it with
//! [`export_machine_backend!`], and the request decoding and dispatch are done here, once.
//!
//! Required methods are what every backend must really do (report, start/stop programs, stop
//! motion). Every other contract operation has a default that answers the error code
//! `unsupported` naming the operation, so a new optional operation needs no edit in backends
//! that do not support it.

use crate::contract::{
    Artifact, Axis, AxisValues, Command, MachineStatus, OffsetTable, OutputName, ProgramLoaded,
    Request, RunAction, RunAnswer, WorkOffset,
};
use crate::plugin::{Host, Plugin};
use crate::PluginError;
use serde::ser::{Serialize, SerializeMap, Serializer};

/// The arguments of `load_program` (see [`Request::LoadProgram`]).
#[derive(Debug, Clone, PartialEq)]
pub struct LoadProgram {
    pub run: i64,
    pub path: String,
    pub start_line: u32,
    pub expected_part_zero: Option<AxisValues>,
    /// The machine's tool table (see [`Request::LoadProgram`]).
    pub tools: Vec<crate::contract::ProgramTool>,
    /// The work budget (see [`Request::LoadProgram`]).
    pub max_segments: Option<u64>,
    /// M1 holds like M0 (see [`Request::LoadProgram`]).
    pub optional_stop: bool,
    /// M6 holds for a manual tool change (see [`Request::LoadProgram`]).
    pub tool_change: Option<crate::contract::ToolChangeSetup>,
    /// What to do before `start_line` (see [`crate::contract::Preamble`]).
    pub preamble: Option<crate::contract::Preamble>,
    /// A height map to apply (see [`Request::LoadProgram`]); a backend that cannot refuses it.
    pub height_map: Option<crate::heightmap::HeightMap>,
}

/// A machine backend. Methods may be called concurrently from several host threads (so that
/// stop and feed hold are never stuck behind a slow request).
pub trait MachineBackend: Send + Sync + Sized + 'static {
    fn create(host: Host, config: serde_json::Value) -> Result<Self, PluginError>;

    // ----- required -----

    /// Open the link to the controller (idempotent).
    fn connect(&self) -> Result<MachineStatus, PluginError>;
    fn status(&self) -> Result<MachineStatus, PluginError>;
    fn load_program(&self, program: LoadProgram) -> Result<ProgramLoaded, PluginError>;
    /// `run` requests. `Pause` and `Cancel` must only answer Ok once no new program line will
    /// start (see the README's safety section).
    fn run(&self, action: RunAction) -> Result<RunAnswer, PluginError>;
    /// `command stop`: abort all motion and the program; Ok only once motion ended.
    fn stop(&self) -> Result<(), PluginError>;
    /// `command feed_hold`: hold a running program, end a jog; Ok only once held.
    fn feed_hold(&self) -> Result<(), PluginError>;
    /// `command reset`: stop, then clear a latched alarm if the cause is gone.
    fn reset(&self) -> Result<(), PluginError>;
    /// The host is about to destroy the instance: stop motion, close links.
    fn shutdown(&self) -> Result<(), PluginError>;

    // ----- optional: defaults answer `unsupported` (or delegate, where said) -----

    /// `command cycle_start`; by default the same as `run start`.
    fn cycle_start(&self) -> Result<RunAnswer, PluginError> {
        self.run(RunAction::Start)
    }
    /// `command resume`; by default the same as `run resume`.
    fn resume(&self) -> Result<(), PluginError> {
        self.run(RunAction::Resume).map(drop)
    }
    fn jog(&self, axis: Axis, distance: f64, feed: Option<f64>) -> Result<(), PluginError> {
        let _ = (axis, distance, feed);
        Err(PluginError::unsupported("jog"))
    }
    fn home(&self, axis: Option<Axis>) -> Result<(), PluginError> {
        let _ = axis;
        Err(PluginError::unsupported("home"))
    }
    /// Answers the new offset table when the backend knows it (sent as `{"offsets": ...}`).
    fn zero(&self, axis: Option<Axis>) -> Result<Option<OffsetTable>, PluginError> {
        let _ = axis;
        Err(PluginError::unsupported("zero"))
    }
    fn go_to_zero(&self) -> Result<(), PluginError> {
        Err(PluginError::unsupported("go_to_zero"))
    }
    fn select_offset(&self, offset: WorkOffset) -> Result<(), PluginError> {
        let _ = offset;
        Err(PluginError::unsupported("select_offset"))
    }
    /// Answer: `{"output": name, "on": bool}` plus anything the backend adds.
    fn set_output(&self, name: OutputName, on: bool) -> Result<serde_json::Value, PluginError> {
        let _ = (name, on);
        Err(PluginError::unsupported("set_output"))
    }
    /// Answer: `{"output": name, "on": bool}` (the new state) where the backend knows it.
    fn toggle_output(&self, name: OutputName) -> Result<serde_json::Value, PluginError> {
        let _ = name;
        Err(PluginError::unsupported("toggle_output"))
    }
    fn get_offsets(&self) -> Result<OffsetTable, PluginError> {
        Err(PluginError::unsupported("get_offsets"))
    }
    fn set_offset(&self, offset: WorkOffset, values: AxisValues) -> Result<(), PluginError> {
        let _ = (offset, values);
        Err(PluginError::unsupported("set_offset"))
    }
    fn get_artifact(&self, name: &str) -> Result<Artifact, PluginError> {
        let _ = name;
        Err(PluginError::unsupported("get_artifact"))
    }
    fn mdi(&self, line: &str) -> Result<(), PluginError> {
        let _ = line;
        Err(PluginError::unsupported("mdi"))
    }
    /// Set the overrides given (percent; `None` leaves one as it is), applied from the next
    /// planning interval on. A backend that cannot apply one of them refuses the whole
    /// command, saying which and why, and changes nothing.
    fn set_overrides(
        &self,
        feed: Option<f64>,
        spindle: Option<f64>,
        rapid: Option<f64>,
    ) -> Result<(), PluginError> {
        let _ = (feed, spindle, rapid);
        Err(PluginError::unsupported("set_overrides"))
    }
    /// How this machine moves (its rapid rate, acceleration, cornering), for run-time
    /// estimates.
    fn motion_profile(&self) -> Result<crate::contract::MotionProfile, PluginError> {
        Err(PluginError::unsupported("motion_profile"))
    }
    /// A probing move (see [`crate::contract::Probe`]): queue it and answer; report its end
    /// with a `probe_ended` event.
    fn probe(&self, probe: crate::contract::Probe) -> Result<(), PluginError> {
        let _ = probe;
        Err(PluginError::unsupported("probe"))
    }
    /// The machine's tool table changed (see [`Request::SetTools`]).
    fn set_tools(&self, tools: Vec<crate::contract::ProgramTool>) -> Result<(), PluginError> {
        let _ = tools;
        Err(PluginError::unsupported("set_tools"))
    }

    // ----- provided -----

    /// Handles one JSON request in process (tests, tools); the ABI path uses bytes.
    fn request(&self, request: serde_json::Value) -> Result<serde_json::Value, PluginError> {
        handle_json(self, request)
    }
}

/// What a dispatched request answers, serialised once into the call's answer bytes.
#[derive(Debug, Clone, PartialEq)]
pub enum Answer {
    /// `{}`
    Empty,
    Status(MachineStatus),
    Offsets(OffsetTable),
    /// `{"offsets": table}`, or `{}` without one.
    Zeroed(Option<OffsetTable>),
    Loaded(ProgramLoaded),
    Run(RunAnswer),
    Artifact(Artifact),
    Value(serde_json::Value),
}

impl Serialize for Answer {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            Answer::Empty | Answer::Zeroed(None) => s.serialize_map(Some(0))?.end(),
            Answer::Zeroed(Some(t)) => {
                let mut m = s.serialize_map(Some(1))?;
                m.serialize_entry("offsets", t)?;
                m.end()
            }
            Answer::Status(v) => v.serialize(s),
            Answer::Offsets(v) => v.serialize(s),
            Answer::Loaded(v) => v.serialize(s),
            Answer::Run(v) => v.serialize(s),
            Answer::Artifact(v) => v.serialize(s),
            Answer::Value(v) => v.serialize(s),
        }
    }
}

/// Calls the trait method a request names. The only `match` on [`Request`] a backend needs.
pub fn dispatch<B: MachineBackend>(b: &B, request: Request) -> Result<Answer, PluginError> {
    let empty = |r: Result<(), PluginError>| r.map(|()| Answer::Empty);
    match request {
        Request::Connect => b.connect().map(Answer::Status),
        Request::Status => b.status().map(Answer::Status),
        Request::Jog {
            axis,
            distance,
            feed,
        } => empty(b.jog(axis, distance, feed)),
        Request::Command(c) => match c {
            Command::CycleStart => b.cycle_start().map(Answer::Run),
            Command::FeedHold => empty(b.feed_hold()),
            Command::Resume => empty(b.resume()),
            Command::Stop => empty(b.stop()),
            Command::Reset => empty(b.reset()),
            Command::Home { axis } => empty(b.home(axis)),
            Command::Zero { axis } => b.zero(axis).map(Answer::Zeroed),
            Command::GoToZero => empty(b.go_to_zero()),
            Command::SelectOffset { offset } => empty(b.select_offset(offset)),
            Command::SetOutput { name, on } => b.set_output(name, on).map(Answer::Value),
            Command::ToggleOutput { name } => b.toggle_output(name).map(Answer::Value),
            Command::SetOverrides {
                feed,
                spindle,
                rapid,
            } => empty(b.set_overrides(feed, spindle, rapid)),
        },
        Request::GetOffsets => b.get_offsets().map(Answer::Offsets),
        Request::SetOffset { offset, values } => empty(b.set_offset(offset, values)),
        Request::LoadProgram {
            run,
            path,
            start_line,
            expected_part_zero,
            tools,
            max_segments,
            optional_stop,
            tool_change,
            preamble,
            height_map,
        } => b
            .load_program(LoadProgram {
                run,
                path,
                start_line,
                expected_part_zero,
                tools,
                max_segments,
                optional_stop,
                tool_change,
                preamble,
                height_map,
            })
            .map(Answer::Loaded),
        Request::Run { action } => b.run(action).map(Answer::Run),
        Request::Shutdown => empty(b.shutdown()),
        Request::GetArtifact { name } => b.get_artifact(&name).map(Answer::Artifact),
        Request::Mdi { line } => empty(b.mdi(&line)),
        Request::Probe(p) => empty(b.probe(p)),
        Request::MotionProfile => b
            .motion_profile()
            .and_then(|p| {
                serde_json::to_value(p).map_err(|e| PluginError::new("internal", e.to_string()))
            })
            .map(Answer::Value),
        Request::SetTools { tools } => empty(b.set_tools(tools)),
    }
}

/// Handles one JSON request (for in-process callers and tests); the ABI path uses bytes.
pub fn handle_json<B: MachineBackend>(
    b: &B,
    request: serde_json::Value,
) -> Result<serde_json::Value, PluginError> {
    PluginError::encode(&dispatch(b, Request::from_json(request)?)?)
}

/// Handles one call as the ABI carries it: bytes decoded straight into [`Request`], the
/// answer serialised straight to bytes.
pub fn handle_bytes<B: MachineBackend>(b: &B, request: &[u8]) -> Result<Vec<u8>, PluginError> {
    let answer = dispatch(b, Request::from_slice(request)?)?;
    serde_json::to_vec(&answer)
        .map_err(|e| PluginError::new("internal", format!("cannot encode answer: {e}")))
}

/// Adapts a [`MachineBackend`] to the lower-level [`Plugin`] the ABI glue exports.
pub struct Exported<B>(pub B);

impl<B: MachineBackend> Plugin for Exported<B> {
    fn create(host: Host, config: serde_json::Value) -> Result<Self, PluginError> {
        B::create(host, config).map(Exported)
    }
    fn call(&self, request: serde_json::Value) -> Result<serde_json::Value, PluginError> {
        handle_json(&self.0, request)
    }
    fn call_bytes(&self, request: &[u8]) -> Result<Vec<u8>, PluginError> {
        handle_bytes(&self.0, request)
    }
}

/// Exports the `fresa_plugin_v1` descriptor of a machine backend (kind `machine_backend`).
///
/// ```text
/// fresa_plugin_api::export_machine_backend!(MyMachine, name = "my-machine");
/// ```
/// (Not a doctest: the export needs a `cdylib` crate; `plugins/sim-machine` is a full example.)
#[macro_export]
macro_rules! export_machine_backend {
    ($ty:ty, name = $name:literal) => {
        $crate::export_plugin!(
            $crate::backend::Exported<$ty>,
            name = $name,
            kinds = $crate::abi::KIND_MACHINE_BACKEND
        );
    };
}

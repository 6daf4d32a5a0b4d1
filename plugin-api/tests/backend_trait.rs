//! A backend that implements only the required `MachineBackend` methods: every optional
//! operation of the contract answers `unsupported` naming it, with no code in the backend. If
//! a new optional request is added to the contract, add it to `OPTIONAL` below.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_plugin_api::backend::{self, Exported, LoadProgram};
use fresa_plugin_api::contract::{MachineStatus, ProgramLoaded, RunAction, RunAnswer};
use fresa_plugin_api::{Host, MachineBackend, Plugin, PluginError};
use serde_json::{json, Value};
use std::sync::Mutex;

/// Remembers the last required operation it was asked for.
struct Minimal {
    last: Mutex<String>,
}

impl Minimal {
    fn new() -> Minimal {
        Minimal {
            last: Mutex::new(String::new()),
        }
    }
    fn note(&self, what: &str) {
        *self.last.lock().unwrap() = what.to_string();
    }
}

impl MachineBackend for Minimal {
    fn create(_host: Host, _config: Value) -> Result<Self, PluginError> {
        Ok(Minimal::new())
    }
    fn connect(&self) -> Result<MachineStatus, PluginError> {
        self.note("connect");
        Ok(MachineStatus::default())
    }
    fn status(&self) -> Result<MachineStatus, PluginError> {
        self.note("status");
        Ok(MachineStatus::default())
    }
    fn load_program(&self, p: LoadProgram) -> Result<ProgramLoaded, PluginError> {
        self.note(&format!("load {} {}", p.run, p.path));
        Ok(ProgramLoaded {
            lines: 3,
            start_line: p.start_line,
            height_map: false,
        })
    }
    fn run(&self, action: RunAction) -> Result<RunAnswer, PluginError> {
        self.note(&format!("run {action:?}"));
        Ok(RunAnswer::default())
    }
    fn stop(&self) -> Result<(), PluginError> {
        self.note("stop");
        Ok(())
    }
    fn feed_hold(&self) -> Result<(), PluginError> {
        self.note("feed_hold");
        Ok(())
    }
    fn reset(&self) -> Result<(), PluginError> {
        self.note("reset");
        Ok(())
    }
    fn shutdown(&self) -> Result<(), PluginError> {
        self.note("shutdown");
        Ok(())
    }
}

/// Every optional operation of the contract, as the host sends it, and the name the
/// `unsupported` answer must give.
const OPTIONAL: &[(&str, &str)] = &[
    (r#"{"op":"jog","axis":"X","distance":1}"#, "jog"),
    (r#"{"op":"command","command":"home"}"#, "home"),
    (r#"{"op":"command","command":"zero","axis":"Y"}"#, "zero"),
    (r#"{"op":"command","command":"go_to_zero"}"#, "go_to_zero"),
    (
        r#"{"op":"command","command":"select_offset","offset":"G55"}"#,
        "select_offset",
    ),
    (
        r#"{"op":"command","command":"set_output","name":"spindle","on":true}"#,
        "set_output",
    ),
    (
        r#"{"op":"command","command":"toggle_output","name":"coolant"}"#,
        "toggle_output",
    ),
    (r#"{"op":"get_offsets"}"#, "get_offsets"),
    (
        r#"{"op":"set_offset","offset":"G54","values":{"x":1}}"#,
        "set_offset",
    ),
    (
        r#"{"op":"get_artifact","name":"as-program"}"#,
        "get_artifact",
    ),
    (r#"{"op":"mdi","line":"G0 X1"}"#, "mdi"),
];

#[test]
fn optional_operations_answer_unsupported_without_backend_code() {
    let m = Exported(Minimal::new());
    for (request, op) in OPTIONAL {
        // The ABI path: bytes straight into the typed request.
        let e = m.call_bytes(request.as_bytes()).unwrap_err();
        assert_eq!(e.code, "unsupported", "{request}: {e}");
        assert!(e.message.contains(&format!("`{op}`")), "{request}: {e}");
        // The in-process path answers the same.
        let v: Value = serde_json::from_str(request).unwrap();
        assert_eq!(m.0.request(v).unwrap_err(), e);
    }
}

#[test]
fn required_operations_and_the_delegating_defaults_reach_the_backend() {
    let m = Minimal::new();
    let call = |req: Value| backend::handle_json(&m, req).unwrap();
    assert_eq!(call(json!({"op":"status"}))["state"], "offline");
    assert_eq!(
        call(json!({"op":"load_program","run":4,"path":"/p.nc","start_line":2})),
        json!({"lines":3,"start_line":2})
    );
    assert_eq!(*m.last.lock().unwrap(), "load 4 /p.nc");
    for (req, noted) in [
        (json!({"op":"run","action":"cancel"}), "run Cancel"),
        // cycle_start and resume default to the run actions.
        (json!({"op":"command","command":"cycle_start"}), "run Start"),
        (json!({"op":"command","command":"resume"}), "run Resume"),
        (json!({"op":"command","command":"feed_hold"}), "feed_hold"),
        (json!({"op":"command","command":"stop"}), "stop"),
        (json!({"op":"command","command":"reset"}), "reset"),
        (json!({"op":"shutdown"}), "shutdown"),
    ] {
        assert_eq!(call(req.clone()), json!({}), "{req}");
        assert_eq!(*m.last.lock().unwrap(), noted, "{req}");
    }
}

#[test]
fn malformed_requests_are_invalid_requests_on_both_paths() {
    let m = Exported(Minimal::new());
    for bad in [
        &b"{"[..],
        br#"{"op":"jog","axis":"Q","distance":1}"#,
        br#"{"op":"jog"}"#,
        br#"{"op":"command","command":"home","axis":"Q"}"#,
        br#"{"op":7}"#,
    ] {
        let e = m.call_bytes(bad).unwrap_err();
        assert_eq!(e.code, "invalid_request", "{e}");
        let e = m
            .call(serde_json::from_slice(bad).unwrap_or_default())
            .unwrap_err();
        assert_eq!(e.code, "invalid_request", "{e}");
    }
}

/// A host newer than the plugin sends operations the plugin's contract does not have: the
/// plugin answers `unsupported`, as for an operation it does not implement, on both paths.
#[test]
fn operations_a_plugin_does_not_know_are_unsupported() {
    let m = Exported(Minimal::new());
    // A probe the Minimal backend does not implement is `unsupported` too (the trait default).
    let e = m
        .call(serde_json::json!({"op":"probe","id":1,"axis":"Z","distance":-10,"feed":100}))
        .unwrap_err();
    assert_eq!(e.code, "unsupported", "{e}");
    assert!(e.message.contains("probe"), "{e}");
    for (unknown, name) in [
        (&br#"{"op":"height_map","rows":3}"#[..], "height_map"),
        (
            br#"{"op":"command","command":"tool_change","tool":3}"#,
            "tool_change",
        ),
    ] {
        let e = m.call_bytes(unknown).unwrap_err();
        assert_eq!(e.code, "unsupported", "{e}");
        assert!(e.message.contains(name), "{e}");
        let e = m
            .call(serde_json::from_slice(unknown).unwrap())
            .unwrap_err();
        assert_eq!(e.code, "unsupported", "{e}");
    }
}

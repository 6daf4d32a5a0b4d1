//! `sim-machine`: a simulated 4-axis (X Y Z A) machine backend.
//!
//! Feed-rate-true motion timing (scalable with `time_scale`), program execution line by line
//! on a thread the plugin owns, progress events, and an append-only execution log that makes
//! resuming a run idempotent. See the crate README for the configuration and behaviour.

mod config;
mod machine;
mod program;

pub use config::Config;
pub use machine::{EventSink, SimMachine};

use fresa_plugin_api::{Host, Plugin, PluginError};
use std::sync::Arc;

impl Plugin for SimMachine {
    fn create(host: Host, config: serde_json::Value) -> Result<Self, PluginError> {
        SimMachine::new(&config, Arc::new(move |event| host.emit(event)))
    }

    fn call(&self, request: serde_json::Value) -> Result<serde_json::Value, PluginError> {
        self.request(request)
    }
}

fresa_plugin_api::export_plugin!(
    SimMachine,
    name = "sim-machine",
    kinds = fresa_plugin_api::abi::KIND_MACHINE_BACKEND
);

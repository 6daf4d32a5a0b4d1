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

fresa_plugin_api::export_machine_backend!(SimMachine, name = "sim-machine");

//! `parport-stepper`: two bipolar steppers (X, Y) and a tool lift (Z) driven straight from a PC
//! parallel port through Linux `ppdev`, or from a simulated port that records every write.
//!
//! A pure [`planner`] turns the program into straight-line step moves on a tick grid; one output
//! thread writes them on absolute deadlines, reads the inputs every tick and reports progress.
//! See the crate README for the configuration and behaviour.

pub mod coils;
pub mod config;
mod machine;
pub mod output;
pub mod pins;
pub mod planner;
pub mod port;

pub use config::Config;
pub use machine::{EventSink, LogLevel, LogSink, Stepper, Timing};

use fresa_plugin_api::{Host, Plugin, PluginError};
use std::sync::Arc;

impl Plugin for Stepper {
    fn create(host: Host, config: serde_json::Value) -> Result<Self, PluginError> {
        Stepper::new(
            &config,
            Arc::new(move |event| host.emit(event)),
            Arc::new(move |level, message| match level {
                LogLevel::Info => host.info(message),
                LogLevel::Warn => host.warn(message),
            }),
            Timing::Real,
        )
    }

    fn call(&self, request: serde_json::Value) -> Result<serde_json::Value, PluginError> {
        self.request(request)
    }
}

fresa_plugin_api::export_plugin!(
    Stepper,
    name = "parport-stepper",
    kinds = fresa_plugin_api::abi::KIND_MACHINE_BACKEND
);

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

fresa_plugin_api::export_machine_backend!(Stepper, name = "parport-stepper");

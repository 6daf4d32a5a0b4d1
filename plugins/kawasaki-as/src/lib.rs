//! `kawasaki-as`: a Kawasaki robot (AS language) used as a 3-axis mill, fed from the server.
//!
//! * [`convert`]: G-code -> robot commands (fresa-gcode, arcs by tolerance, axis mapping,
//!   F -> clamped SPEED, envelope check of every point).
//! * [`codec`] and [`link`]: both robot protocols (`legacy` = the seed's program as printed,
//!   `fresa-v1` = sequence numbers, SPEED, a window).
//! * [`machine`]: the machine backend (exported as the `kawasaki-as` plugin).
//! * [`as_program`]: the AS program for fresa-v1.
//! * [`sim`]: the controller simulator behind the `kawasaki-as-sim` binary.
//!
//! See the crate README for configuration, protocols and guarantees.

pub mod as_program;
pub mod codec;
pub mod config;
pub mod convert;
pub mod link;
pub mod machine;
pub mod sim;

pub use config::{Config, Protocol};
pub use machine::{EventSink, KawasakiMachine, LogSink};

fresa_plugin_api::export_machine_backend!(KawasakiMachine, name = "kawasaki-as");

//! Mach3 through its OEM buttons, DROs and LEDs.
//!
//! * [`mach3::Mach3`]: the `IMyScriptObject` methods used, as a trait; implemented by the
//!   Windows COM client (`com`, Windows only) and by [`sim::Mach3Sim`].
//! * [`agent`]: the `fresa-mach3-agent` server that runs beside Mach3 and makes every Mach3
//!   call on one thread; [`protocol`]: its versioned JSON-lines protocol; [`client`]: the
//!   plugin's side of it.
//! * [`backend`]: the `mach3-oem` machine-backend plugin (this library's cdylib).
//! * [`codes`]: the OEM codes used, overridable per machine.
//!
//! See the crate README for deployment, configuration and the protocol.

pub mod agent;
pub mod backend;
pub mod client;
pub mod codes;
#[cfg(windows)]
pub mod com;
pub mod config;
pub mod mach3;
pub mod protocol;
pub mod sim;

fresa_plugin_api::export_machine_backend!(backend::Mach3Backend, name = "mach3-oem");

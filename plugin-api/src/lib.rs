//! Fresa plugin API, ABI v1.
//!
//! * [`abi`]: the raw `repr(C)` contract, mirrored by `include/fresa_plugin.h`.
//! * [`contract`]: the JSON requests, responses and events of a machine backend.
//! * [`operation`]: how the host treats each request and command (lane, stop gate, store, ...),
//!   decided once per operation.
//! * [`backend`]: for machine backends in Rust: the typed [`MachineBackend`] trait and
//!   [`export_machine_backend!`] (request decoding and dispatch done once).
//! * [`kit`]: for Rust backends that plan motion locally: the shared state machine, run
//!   bookkeeping, offsets, execution log use and event emission.
//! * [`plugin`]: the lower-level [`Plugin`] trait and [`export_plugin!`] (any plugin kind).
//! * [`config_fields`]: for Rust plugins: config values read with errors naming the key.
//! * [`exec_log`]: for Rust machine backends: the execution log behind idempotent resume.
//! * [`heightmap`]: height maps (a probed grid of Z corrections) and how a backend applies one
//!   to a program's path (bilinear interpolation, moves split at grid lines).
//! * [`host`]: for the server: load a library, check it, create and call instances.
//! * [`priority`]: a plugin thread's scheduling priority (nice value), for threads whose
//!   latency an operator feels.
//! * [`quiet`]: rate-limited warnings (first one, then one a minute with a count), for plugins
//!   and the server.

pub mod abi;
pub mod backend;
pub mod config_fields;
pub mod contract;
mod error;
pub mod exec_log;
pub mod heightmap;
pub mod host;
pub mod kit;
pub mod operation;
pub mod plugin;
pub mod priority;
pub mod quiet;

pub use backend::MachineBackend;
pub use error::PluginError;
pub use plugin::{Host, Plugin};

/// The target triple this crate (and so the plugin or host using it) was built for.
pub const TARGET: &str = env!("FRESA_BUILD_TARGET");
/// `TARGET` with a NUL terminator, for the descriptor.
pub const TARGET_CSTR: &std::ffi::CStr =
    match std::ffi::CStr::from_bytes_with_nul(concat!(env!("FRESA_BUILD_TARGET"), "\0").as_bytes())
    {
        Ok(s) => s,
        Err(_) => panic!("target triple contains a NUL byte"),
    };

/// File name of a plugin library on this platform, e.g. `libfresa_sim_machine.so`.
pub fn library_file_name(crate_lib_name: &str) -> String {
    format!(
        "{}{}{}",
        std::env::consts::DLL_PREFIX,
        crate_lib_name,
        std::env::consts::DLL_SUFFIX
    )
}

/// For tests and benches of a plugin crate: its library as cargo built it beside the running
/// executable (`target/<profile>/deps`, or one level up after `cargo build`).
pub fn built_library(crate_lib_name: &str) -> Option<std::path::PathBuf> {
    let exe = std::env::current_exe().ok()?;
    let deps = exe.parent()?;
    let name = library_file_name(crate_lib_name);
    [Some(deps.join(&name)), deps.parent().map(|d| d.join(&name))]
        .into_iter()
        .flatten()
        .find(|p| p.exists())
}

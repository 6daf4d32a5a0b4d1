//! The raw C ABI, version 1. Mirrors `include/fresa_plugin.h` exactly; change both together.
//!
//! Everything that crosses the boundary is either a plain integer, a pointer with an explicit
//! length, or a function pointer. Payloads are UTF-8 JSON. Whoever allocates a buffer frees it:
//! buffers returned by a plugin go back through that plugin's `free`.

use std::ffi::{c_char, c_void};

/// `"FRESAPL1"` read as a little-endian u64; guards against loading an unrelated library that
/// happens to export a symbol of the same name.
pub const MAGIC: u64 = u64::from_le_bytes(*b"FRESAPL1");
pub const ABI_MAJOR: u16 = 1;
pub const ABI_MINOR: u16 = 0;
/// Name of the one exported symbol: `const FrPluginDescriptor *fresa_plugin_v1(void)`.
pub const DESCRIPTOR_SYMBOL: &str = "fresa_plugin_v1";

/// Kinds a plugin can provide (bit flags).
pub const KIND_MACHINE_BACKEND: u32 = 1;
pub const KIND_PENDANT_TRANSPORT: u32 = 2;

/// Status codes returned by `create` and `call`.
pub const STATUS_OK: i32 = 0;
/// The output buffer holds a JSON `{"code": ..., "message": ...}` error.
pub const STATUS_ERROR: i32 = 1;
/// The plugin panicked (caught at the boundary); the output buffer holds a JSON error.
pub const STATUS_PANIC: i32 = 2;

/// Log levels for `FrHost::log`.
pub const LOG_ERROR: u32 = 1;
pub const LOG_WARN: u32 = 2;
pub const LOG_INFO: u32 = 3;
pub const LOG_DEBUG: u32 = 4;
pub const LOG_TRACE: u32 = 5;

/// A byte buffer owned by whoever allocated it.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct FrBuf {
    pub ptr: *mut u8,
    pub len: usize,
}

impl FrBuf {
    pub const EMPTY: FrBuf = FrBuf {
        ptr: std::ptr::null_mut(),
        len: 0,
    };
}

/// Functions the host offers a plugin instance. Valid from `create` until `destroy` returns and
/// callable from any thread. `ctx` is opaque to the plugin and is passed back on every call.
#[repr(C)]
pub struct FrHost {
    pub struct_size: usize,
    pub ctx: *mut c_void,
    /// Emit one event: a JSON object. The host copies the bytes before returning.
    pub emit_event: unsafe extern "C" fn(ctx: *mut c_void, json: *const u8, len: usize),
    /// Log one UTF-8 message at a `LOG_*` level. The host copies the bytes before returning.
    pub log: unsafe extern "C" fn(ctx: *mut c_void, level: u32, msg: *const u8, len: usize),
}

/// Creates an instance from a JSON config. On success writes `*out_instance` and returns
/// `STATUS_OK`; otherwise writes a JSON error into `*out_error` (freed with `free`).
pub type CreateFn = unsafe extern "C" fn(
    host: *const FrHost,
    config: *const u8,
    config_len: usize,
    out_instance: *mut *mut c_void,
    out_error: *mut FrBuf,
) -> i32;

/// Handles one JSON request. May be called concurrently from several threads and may block.
/// The response (or JSON error) is written into `*out_response` (freed with `free`).
pub type CallFn = unsafe extern "C" fn(
    instance: *mut c_void,
    request: *const u8,
    request_len: usize,
    out_response: *mut FrBuf,
) -> i32;

pub type DestroyFn = unsafe extern "C" fn(instance: *mut c_void);
pub type FreeFn = unsafe extern "C" fn(buf: FrBuf);

/// What `fresa_plugin_v1()` returns: a pointer to a static descriptor.
///
/// Minor versions may only append fields; `struct_size` tells the host how much is there.
#[repr(C)]
pub struct FrPluginDescriptor {
    pub magic: u64,
    pub abi_major: u16,
    pub abi_minor: u16,
    pub struct_size: u32,
    /// NUL-terminated target triple the plugin was built for, e.g. `x86_64-unknown-linux-gnu`.
    pub target: *const c_char,
    /// NUL-terminated plugin name (the `backend` name users configure, e.g. `sim-machine`).
    pub name: *const c_char,
    /// NUL-terminated plugin version.
    pub version: *const c_char,
    /// `KIND_*` bit flags.
    pub kinds: u32,
    pub create: CreateFn,
    pub call: CallFn,
    pub destroy: DestroyFn,
    pub free: FreeFn,
}

// The descriptor is immutable static data: sharing it between threads is sound.
unsafe impl Sync for FrPluginDescriptor {}
unsafe impl Send for FrPluginDescriptor {}

pub type DescriptorFn = unsafe extern "C" fn() -> *const FrPluginDescriptor;

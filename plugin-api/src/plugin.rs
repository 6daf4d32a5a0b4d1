//! Helpers for plugin authors writing in Rust: implement [`Plugin`] and call [`export_plugin!`].

use crate::abi::{self, FrBuf, FrHost};
use crate::error::PluginError;
use serde::Serialize;
use std::ffi::c_void;
use std::panic::{catch_unwind, AssertUnwindSafe};

/// The host's functions, as seen by a plugin instance. Cheap to clone, usable from any thread.
#[derive(Clone, Copy)]
pub struct Host {
    table: *const FrHost,
}

// The host guarantees the table stays valid and its functions thread-safe until `destroy` returns.
unsafe impl Send for Host {}
unsafe impl Sync for Host {}

impl Host {
    /// Emits an event (any serialisable value that becomes a JSON object).
    pub fn emit<T: Serialize>(&self, event: &T) {
        match serde_json::to_vec(event) {
            Ok(bytes) => {
                // SAFETY: the table is valid for the instance's life (host contract).
                unsafe {
                    ((*self.table).emit_event)((*self.table).ctx, bytes.as_ptr(), bytes.len())
                }
            }
            Err(e) => self.log(abi::LOG_ERROR, &format!("event not serialisable: {e}")),
        }
    }

    pub fn log(&self, level: u32, message: &str) {
        // SAFETY: as above.
        unsafe { ((*self.table).log)((*self.table).ctx, level, message.as_ptr(), message.len()) }
    }

    pub fn info(&self, message: &str) {
        self.log(abi::LOG_INFO, message)
    }
    pub fn warn(&self, message: &str) {
        self.log(abi::LOG_WARN, message)
    }
    pub fn error(&self, message: &str) {
        self.log(abi::LOG_ERROR, message)
    }
}

/// One plugin instance (e.g. one machine). `call` may run concurrently on several host threads,
/// so that stop and feed hold are never stuck behind a slow request.
pub trait Plugin: Send + Sync + Sized + 'static {
    fn create(host: Host, config: serde_json::Value) -> Result<Self, PluginError>;
    fn call(&self, request: serde_json::Value) -> Result<serde_json::Value, PluginError>;

    /// The call as the ABI carries it: request bytes in, answer bytes out. The default goes
    /// through [`Plugin::call`]; a plugin with typed requests overrides it to decode the bytes
    /// straight into its request type (see [`crate::backend`]).
    fn call_bytes(&self, request: &[u8]) -> Result<Vec<u8>, PluginError> {
        let value: serde_json::Value = serde_json::from_slice(request).map_err(|e| {
            PluginError::new("invalid_request", format!("request is not JSON: {e}"))
        })?;
        let answer = self.call(value)?;
        serde_json::to_vec(&answer)
            .map_err(|e| PluginError::new("internal", format!("cannot encode answer: {e}")))
    }
}

fn into_buf(bytes: Vec<u8>) -> FrBuf {
    let boxed = bytes.into_boxed_slice();
    let len = boxed.len();
    let ptr = Box::into_raw(boxed) as *mut u8;
    FrBuf { ptr, len }
}

fn error_buf(e: &PluginError) -> FrBuf {
    into_buf(
        serde_json::to_vec(e)
            .unwrap_or_else(|_| b"{\"code\":\"internal\",\"message\":\"?\"}".to_vec()),
    )
}

fn panic_message(p: Box<dyn std::any::Any + Send>) -> String {
    if let Some(s) = p.downcast_ref::<&str>() {
        (*s).to_string()
    } else if let Some(s) = p.downcast_ref::<String>() {
        s.clone()
    } else {
        "unknown panic".to_string()
    }
}

/// # Safety
/// `ptr`/`len` must describe a readable byte range (or `len == 0`).
unsafe fn bytes<'a>(ptr: *const u8, len: usize) -> &'a [u8] {
    if len == 0 || ptr.is_null() {
        &[]
    } else {
        // SAFETY: guaranteed by the caller.
        unsafe { std::slice::from_raw_parts(ptr, len) }
    }
}

/// The `create` entry point for plugin type `P`. Used by [`export_plugin!`].
///
/// # Safety
/// Called by the host per the ABI contract.
pub unsafe extern "C" fn create<P: Plugin>(
    host: *const FrHost,
    config: *const u8,
    config_len: usize,
    out_instance: *mut *mut c_void,
    out_error: *mut FrBuf,
) -> i32 {
    // SAFETY: the host passes valid pointers.
    let cfg = unsafe { bytes(config, config_len) };
    let result = catch_unwind(AssertUnwindSafe(|| {
        let value: serde_json::Value = if cfg.is_empty() {
            serde_json::Value::Object(Default::default())
        } else {
            serde_json::from_slice(cfg).map_err(|e| {
                PluginError::new("invalid_config", format!("config is not JSON: {e}"))
            })?
        };
        P::create(Host { table: host }, value)
    }));
    match result {
        Ok(Ok(instance)) => {
            // SAFETY: out pointers are valid per the contract.
            unsafe { *out_instance = Box::into_raw(Box::new(instance)) as *mut c_void };
            abi::STATUS_OK
        }
        Ok(Err(e)) => {
            unsafe { *out_error = error_buf(&e) };
            abi::STATUS_ERROR
        }
        Err(p) => {
            let e = PluginError::new("panic", format!("in create: {}", panic_message(p)));
            unsafe { *out_error = error_buf(&e) };
            abi::STATUS_PANIC
        }
    }
}

/// # Safety
/// `instance` must come from `create::<P>` and not be destroyed.
pub unsafe extern "C" fn call<P: Plugin>(
    instance: *mut c_void,
    request: *const u8,
    request_len: usize,
    out_response: *mut FrBuf,
) -> i32 {
    // SAFETY: per the contract, instance is a live `P` and the request bytes are readable.
    let plugin = unsafe { &*(instance as *const P) };
    let req = unsafe { bytes(request, request_len) };
    let result = catch_unwind(AssertUnwindSafe(|| plugin.call_bytes(req)));
    let (status, buf) = match result {
        Ok(Ok(bytes)) => (abi::STATUS_OK, into_buf(bytes)),
        Ok(Err(e)) => (abi::STATUS_ERROR, error_buf(&e)),
        Err(p) => (
            abi::STATUS_PANIC,
            error_buf(&PluginError::new("panic", panic_message(p))),
        ),
    };
    unsafe { *out_response = buf };
    status
}

/// # Safety
/// `instance` must come from `create::<P>`; it is not used afterwards.
pub unsafe extern "C" fn destroy<P: Plugin>(instance: *mut c_void) {
    if instance.is_null() {
        return;
    }
    // A panic in Drop must not unwind into the host; the instance is leaked in that case.
    let _ = catch_unwind(AssertUnwindSafe(|| {
        // SAFETY: the pointer came from Box::into_raw in `create`.
        drop(unsafe { Box::from_raw(instance as *mut P) });
    }));
}

/// # Safety
/// `buf` must come from this plugin.
pub unsafe extern "C" fn free(buf: FrBuf) {
    if buf.ptr.is_null() {
        return;
    }
    // SAFETY: built by `into_buf` from a boxed slice of exactly this length.
    drop(unsafe { Box::from_raw(std::ptr::slice_from_raw_parts_mut(buf.ptr, buf.len)) });
}

/// Exports the `fresa_plugin_v1` descriptor for a [`Plugin`] type.
///
/// ```text
/// fresa_plugin_api::export_plugin!(MyMachine, name = "my-machine",
///     kinds = fresa_plugin_api::abi::KIND_MACHINE_BACKEND);
/// ```
/// (Not a doctest: the export needs a `cdylib` crate; `plugins/mpg-pendant` is a full example.)
/// The version is the plugin crate's `CARGO_PKG_VERSION`.
#[macro_export]
macro_rules! export_plugin {
    ($ty:ty, name = $name:literal, kinds = $kinds:expr) => {
        const _: () = {
            static DESCRIPTOR: $crate::abi::FrPluginDescriptor = $crate::abi::FrPluginDescriptor {
                magic: $crate::abi::MAGIC,
                abi_major: $crate::abi::ABI_MAJOR,
                abi_minor: $crate::abi::ABI_MINOR,
                struct_size: ::core::mem::size_of::<$crate::abi::FrPluginDescriptor>() as u32,
                target: $crate::TARGET_CSTR.as_ptr(),
                name: concat!($name, "\0").as_ptr() as *const ::core::ffi::c_char,
                version: concat!(env!("CARGO_PKG_VERSION"), "\0").as_ptr()
                    as *const ::core::ffi::c_char,
                kinds: $kinds,
                create: $crate::plugin::create::<$ty>,
                call: $crate::plugin::call::<$ty>,
                destroy: $crate::plugin::destroy::<$ty>,
                free: $crate::plugin::free,
            };

            #[no_mangle]
            pub extern "C" fn fresa_plugin_v1() -> *const $crate::abi::FrPluginDescriptor {
                &DESCRIPTOR
            }
        };
    };
}

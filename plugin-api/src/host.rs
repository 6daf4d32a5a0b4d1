//! The host side: load a plugin library, check its descriptor, create and call instances.

use crate::abi::{self, FrBuf, FrHost, FrPluginDescriptor};
use crate::error::PluginError;
use std::ffi::{c_void, CStr};
use std::path::{Path, PathBuf};

/// Why a plugin library could not be loaded. Every message names the file.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    #[error("plugin file not found: {0}")]
    NotFound(PathBuf),
    #[error("cannot open plugin {path}: {message}")]
    Open { path: PathBuf, message: String },
    #[error("{path} is not a Fresa plugin: it does not export the symbol `{symbol}`")]
    MissingSymbol { path: PathBuf, symbol: &'static str },
    #[error("{path} is not a Fresa plugin: descriptor magic is {found:#018x}, expected {expected:#018x}")]
    BadMagic {
        path: PathBuf,
        found: u64,
        expected: u64,
    },
    #[error(
        "{path}: plugin ABI {plugin_major}.{plugin_minor} is not compatible with this server's ABI \
         {host_major}.{host_minor} (the major versions must match and the plugin's minor must not be newer)"
    )]
    AbiMismatch {
        path: PathBuf,
        plugin_major: u16,
        plugin_minor: u16,
        host_major: u16,
        host_minor: u16,
    },
    #[error("{path} was built for target {plugin_target}, but this server runs on {host_target}")]
    WrongTarget {
        path: PathBuf,
        plugin_target: String,
        host_target: String,
    },
    #[error("{path}: invalid descriptor: {message}")]
    BadDescriptor { path: PathBuf, message: String },
}

/// A plugin call or create that did not succeed.
#[derive(Debug, thiserror::Error)]
pub enum CallError {
    /// The plugin answered with an error.
    #[error("{0}")]
    Plugin(PluginError),
    /// The plugin panicked; the panic was caught at the boundary.
    #[error("plugin panicked: {0}")]
    Panic(String),
    /// The plugin broke the protocol (bad JSON, unknown status).
    #[error("plugin protocol error: {0}")]
    Protocol(String),
}

/// Receives what plugin instances send to the host. Must be callable from any thread.
pub trait HostSink: Send + Sync + 'static {
    /// An event the instance emitted, as a JSON value.
    fn event(&self, event: serde_json::Value);
    /// An event as the instance emitted it: its JSON bytes. A sink that decodes events into a
    /// type of its own overrides this to decode them straight from the bytes, with no `Value`
    /// in between; the default parses a `Value` for [`event`](Self::event). `Err`: the bytes
    /// are not JSON; the host logs that (rate limited) and drops them.
    fn event_json(&self, bytes: &[u8]) -> Result<(), serde_json::Error> {
        self.event(serde_json::from_slice(bytes)?);
        Ok(())
    }
    fn log(&self, level: u32, message: &str);
}

/// For a sink's [`HostSink::event_json`] that decodes into a type of its own: `Err` only when the
/// bytes are not JSON at all (the host reports that); JSON of another shape is `Ok(Err(..))`, for
/// the sink to report as an event it does not know.
pub fn decode_event<T: serde::de::DeserializeOwned>(
    bytes: &[u8],
) -> Result<Result<T, serde_json::Error>, serde_json::Error> {
    match serde_json::from_slice::<T>(bytes) {
        Err(e) if e.is_syntax() || e.is_eof() => Err(e),
        decoded => Ok(decoded),
    }
}

/// A loaded, checked plugin library. The library is never unloaded: code from it may still be
/// referenced by threads the plugin started, and unloading buys nothing for a daemon.
#[derive(Clone)]
pub struct PluginLibrary {
    path: PathBuf,
    descriptor: &'static FrPluginDescriptor,
    name: String,
    version: String,
    target: String,
}

impl std::fmt::Debug for PluginLibrary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PluginLibrary")
            .field("path", &self.path)
            .field("name", &self.name)
            .field("version", &self.version)
            .finish()
    }
}

/// The `arch` and `os` of a target triple, the parts that decide binary compatibility here.
fn arch_os(triple: &str) -> (&str, &str) {
    let arch = triple.split('-').next().unwrap_or("");
    // Android first: "aarch64-linux-android" contains "linux" too.
    let os = [
        "android", "linux", "windows", "darwin", "freebsd", "netbsd", "openbsd",
    ]
    .into_iter()
    .find(|os| triple.contains(os))
    .unwrap_or("");
    (arch, os)
}

/// Whether a plugin built for `plugin` can run in a host built for `host`.
pub fn targets_compatible(plugin: &str, host: &str) -> bool {
    let (pa, po) = arch_os(plugin);
    let (ha, ho) = arch_os(host);
    !pa.is_empty() && pa == ha && po == ho
}

/// # Safety
/// `p` must be null or point at a NUL-terminated string that outlives the program.
unsafe fn c_string(
    p: *const std::ffi::c_char,
    what: &str,
    path: &Path,
) -> Result<String, LoadError> {
    if p.is_null() {
        return Err(LoadError::BadDescriptor {
            path: path.to_path_buf(),
            message: format!("{what} is null"),
        });
    }
    // SAFETY: guaranteed by the caller.
    let s = unsafe { CStr::from_ptr(p) };
    s.to_str()
        .map(str::to_owned)
        .map_err(|_| LoadError::BadDescriptor {
            path: path.to_path_buf(),
            message: format!("{what} is not UTF-8"),
        })
}

/// The smallest descriptor a v1.0 plugin can have: everything up to and including `free`.
const V1_0_DESCRIPTOR_SIZE: usize = std::mem::size_of::<FrPluginDescriptor>();

impl PluginLibrary {
    /// Loads and checks a plugin library.
    pub fn load(path: &Path) -> Result<Self, LoadError> {
        if !path.exists() {
            return Err(LoadError::NotFound(path.to_path_buf()));
        }
        // SAFETY: loading a library runs its initialisers; plugins are trusted code by design
        // (an admin chose the plugin directory).
        let lib = unsafe { libloading::Library::new(path) }.map_err(|e| LoadError::Open {
            path: path.to_path_buf(),
            message: e.to_string(),
        })?;
        // Never unload (see the type's docs).
        let lib: &'static libloading::Library = Box::leak(Box::new(lib));
        // SAFETY: the symbol's type is fixed by the ABI.
        let get: libloading::Symbol<abi::DescriptorFn> = unsafe {
            lib.get(abi::DESCRIPTOR_SYMBOL.as_bytes())
        }
        .map_err(|_| LoadError::MissingSymbol {
            path: path.to_path_buf(),
            symbol: abi::DESCRIPTOR_SYMBOL,
        })?;
        // SAFETY: calling the exported descriptor function, per the ABI.
        let ptr = unsafe { get() };
        if ptr.is_null() {
            return Err(LoadError::BadDescriptor {
                path: path.to_path_buf(),
                message: "fresa_plugin_v1() returned null".into(),
            });
        }
        // Read the fixed-layout head first: a foreign library may have a smaller struct.
        // SAFETY: every descriptor version starts with magic (u64) and the version fields.
        let magic = unsafe { std::ptr::read_unaligned(ptr as *const u64) };
        if magic != abi::MAGIC {
            return Err(LoadError::BadMagic {
                path: path.to_path_buf(),
                found: magic,
                expected: abi::MAGIC,
            });
        }
        // Only the head (magic, versions, struct_size) is read through the raw pointer: a
        // reference to the whole descriptor is made only once struct_size says it is all there.
        // SAFETY: magic matched, so this is a Fresa descriptor with at least the v1 head.
        let (abi_major, abi_minor, struct_size) = unsafe {
            (
                std::ptr::addr_of!((*ptr).abi_major).read_unaligned(),
                std::ptr::addr_of!((*ptr).abi_minor).read_unaligned(),
                std::ptr::addr_of!((*ptr).struct_size).read_unaligned(),
            )
        };
        if abi_major != abi::ABI_MAJOR || abi_minor > abi::ABI_MINOR {
            return Err(LoadError::AbiMismatch {
                path: path.to_path_buf(),
                plugin_major: abi_major,
                plugin_minor: abi_minor,
                host_major: abi::ABI_MAJOR,
                host_minor: abi::ABI_MINOR,
            });
        }
        if (struct_size as usize) < V1_0_DESCRIPTOR_SIZE {
            return Err(LoadError::BadDescriptor {
                path: path.to_path_buf(),
                message: format!(
                    "struct_size {struct_size} is smaller than the v1.0 descriptor ({V1_0_DESCRIPTOR_SIZE} bytes)"
                ),
            });
        }
        // SAFETY: the library promises at least a full v1.0 descriptor, which is static data.
        let descriptor: &'static FrPluginDescriptor = unsafe { &*ptr };
        // SAFETY: the descriptor's strings are static per the ABI.
        let target = unsafe { c_string(descriptor.target, "target", path) }?;
        if !targets_compatible(&target, crate::TARGET) {
            return Err(LoadError::WrongTarget {
                path: path.to_path_buf(),
                plugin_target: target,
                host_target: crate::TARGET.to_string(),
            });
        }
        let name = unsafe { c_string(descriptor.name, "name", path) }?;
        let version = unsafe { c_string(descriptor.version, "version", path) }?;
        if name.is_empty() {
            return Err(LoadError::BadDescriptor {
                path: path.to_path_buf(),
                message: "empty name".into(),
            });
        }
        Ok(PluginLibrary {
            path: path.to_path_buf(),
            descriptor,
            name,
            version,
            target,
        })
    }

    pub fn name(&self) -> &str {
        &self.name
    }
    pub fn version(&self) -> &str {
        &self.version
    }
    pub fn path(&self) -> &Path {
        &self.path
    }
    pub fn target(&self) -> &str {
        &self.target
    }
    pub fn kinds(&self) -> u32 {
        self.descriptor.kinds
    }
    pub fn abi_version(&self) -> (u16, u16) {
        (self.descriptor.abi_major, self.descriptor.abi_minor)
    }

    /// Creates an instance. `sink` receives the instance's events and logs.
    pub fn create(
        &self,
        config: &serde_json::Value,
        sink: std::sync::Arc<dyn HostSink>,
    ) -> Result<Instance, CallError> {
        let config = serde_json::to_vec(config).map_err(|e| CallError::Protocol(e.to_string()))?;
        // The context lives in a Box whose address is stable for the instance's life.
        let ctx = Box::new(SinkCtx {
            sink,
            quiet: crate::quiet::Quiet::per_minute(),
        });
        let mut table = Box::new(FrHost {
            struct_size: std::mem::size_of::<FrHost>(),
            ctx: std::ptr::null_mut(),
            emit_event: host_emit_event,
            log: host_log,
        });
        table.ctx = &*ctx as *const SinkCtx as *mut c_void;
        let mut instance: *mut c_void = std::ptr::null_mut();
        let mut err = FrBuf::EMPTY;
        // SAFETY: all pointers are valid for the call; the table outlives the instance (owned below).
        let status = unsafe {
            (self.descriptor.create)(
                &*table,
                config.as_ptr(),
                config.len(),
                &mut instance,
                &mut err,
            )
        };
        if status != abi::STATUS_OK {
            let bytes = self.take(err);
            return Err(decode_error(status, &bytes));
        }
        if instance.is_null() {
            return Err(CallError::Protocol(
                "create returned OK but no instance".into(),
            ));
        }
        Ok(Instance {
            library: self.clone(),
            ptr: instance,
            _table: table,
            _ctx: ctx,
        })
    }

    /// Copies a plugin-owned buffer and gives it back to the plugin.
    fn take(&self, buf: FrBuf) -> Vec<u8> {
        if buf.ptr.is_null() {
            return Vec::new();
        }
        // SAFETY: the plugin wrote a valid buffer; we copy it before freeing.
        let v = unsafe { std::slice::from_raw_parts(buf.ptr, buf.len) }.to_vec();
        unsafe { (self.descriptor.free)(buf) };
        v
    }
}

fn decode_error(status: i32, bytes: &[u8]) -> CallError {
    let parsed: Option<PluginError> = serde_json::from_slice(bytes).ok();
    match (status, parsed) {
        (abi::STATUS_PANIC, Some(e)) => CallError::Panic(e.message),
        (abi::STATUS_PANIC, None) => CallError::Panic(String::from_utf8_lossy(bytes).into_owned()),
        (abi::STATUS_ERROR, Some(e)) => CallError::Plugin(e),
        (abi::STATUS_ERROR, None) => CallError::Plugin(PluginError::new(
            "plugin_error",
            String::from_utf8_lossy(bytes).into_owned(),
        )),
        (other, _) => CallError::Protocol(format!("unknown status code {other}")),
    }
}

struct SinkCtx {
    sink: std::sync::Arc<dyn HostSink>,
    /// A plugin that emits garbage does it per event: logged once a minute with a count.
    quiet: crate::quiet::Quiet,
}

unsafe extern "C" fn host_emit_event(ctx: *mut c_void, json: *const u8, len: usize) {
    if ctx.is_null() || (json.is_null() && len > 0) {
        return;
    }
    // SAFETY: ctx is the SinkCtx we created; json/len describe the plugin's bytes.
    let ctx = unsafe { &*(ctx as *const SinkCtx) };
    let bytes = if len == 0 {
        &[][..]
    } else {
        unsafe { std::slice::from_raw_parts(json, len) }
    };
    // Never unwind into the plugin.
    let _ = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        match ctx.sink.event_json(bytes) {
            Ok(()) => {}
            Err(e) => {
                if let Some(line) = ctx.quiet.admit("not-json", || {
                    format!("plugin emitted an event that is not JSON ({e}); dropped")
                }) {
                    ctx.sink.log(abi::LOG_WARN, &line)
                }
            }
        }
    }));
}

unsafe extern "C" fn host_log(ctx: *mut c_void, level: u32, msg: *const u8, len: usize) {
    if ctx.is_null() || (msg.is_null() && len > 0) {
        return;
    }
    // SAFETY: as above.
    let ctx = unsafe { &*(ctx as *const SinkCtx) };
    let bytes = if len == 0 {
        &[][..]
    } else {
        unsafe { std::slice::from_raw_parts(msg, len) }
    };
    let text = String::from_utf8_lossy(bytes);
    let _ = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| ctx.sink.log(level, &text)));
}

/// A live plugin instance. Calls may be made from several threads at once (the ABI requires
/// plugins to allow it); `Drop` destroys the instance.
pub struct Instance {
    library: PluginLibrary,
    ptr: *mut c_void,
    _table: Box<FrHost>,
    _ctx: Box<SinkCtx>,
}

// The ABI requires instances to be callable from any thread, concurrently.
unsafe impl Send for Instance {}
unsafe impl Sync for Instance {}

impl Instance {
    pub fn library(&self) -> &PluginLibrary {
        &self.library
    }

    /// Sends one request already encoded as JSON bytes; answers the plugin's answer bytes.
    /// Blocks: call from a blocking thread.
    pub fn call_bytes(&self, request: &[u8]) -> Result<Vec<u8>, CallError> {
        let mut out = FrBuf::EMPTY;
        // SAFETY: instance is live (we own it); buffers are valid for the call.
        let status = unsafe {
            (self.library.descriptor.call)(self.ptr, request.as_ptr(), request.len(), &mut out)
        };
        let bytes = self.library.take(out);
        if status != abi::STATUS_OK {
            return Err(decode_error(status, &bytes));
        }
        Ok(bytes)
    }

    /// Sends one JSON request and waits for the answer. Blocks: call from a blocking thread.
    /// For machine backends prefer [`Instance::call_request`], which skips the `Value` step.
    pub fn call(&self, request: &serde_json::Value) -> Result<serde_json::Value, CallError> {
        let req = serde_json::to_vec(request).map_err(|e| CallError::Protocol(e.to_string()))?;
        decode_answer(&self.call_bytes(&req)?)
    }

    /// Sends one machine-backend request, serialised straight to the call's bytes. Blocks.
    pub fn call_request(
        &self,
        request: &crate::contract::Request,
    ) -> Result<serde_json::Value, CallError> {
        let req = serde_json::to_vec(request).map_err(|e| CallError::Protocol(e.to_string()))?;
        decode_answer(&self.call_bytes(&req)?)
    }

    /// Typed convenience: the answer decoded straight into `T` (e.g. `MachineStatus`).
    pub fn request<T: serde::de::DeserializeOwned>(
        &self,
        request: &crate::contract::Request,
    ) -> Result<T, CallError> {
        let req = serde_json::to_vec(request).map_err(|e| CallError::Protocol(e.to_string()))?;
        let bytes = self.call_bytes(&req)?;
        // An empty answer means `{}` (the ABI allows a plugin to return nothing).
        let bytes: &[u8] = if bytes.is_empty() { b"{}" } else { &bytes };
        serde_json::from_slice(bytes)
            .map_err(|e| CallError::Protocol(format!("unexpected response shape: {e}")))
    }
}

/// An answer's bytes as JSON; an empty answer is `{}`.
fn decode_answer(bytes: &[u8]) -> Result<serde_json::Value, CallError> {
    if bytes.is_empty() {
        return Ok(serde_json::Value::Object(Default::default()));
    }
    serde_json::from_slice(bytes)
        .map_err(|e| CallError::Protocol(format!("response is not JSON: {e}")))
}

impl Drop for Instance {
    fn drop(&mut self) {
        // SAFETY: the pointer came from create and is destroyed exactly once.
        unsafe { (self.library.descriptor.destroy)(self.ptr) };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn target_compatibility_compares_arch_and_os() {
        assert!(targets_compatible(
            "x86_64-unknown-linux-gnu",
            "x86_64-unknown-linux-gnu"
        ));
        assert!(targets_compatible(
            "x86_64-pc-linux-gnu",
            "x86_64-unknown-linux-gnu"
        ));
        assert!(!targets_compatible(
            "aarch64-unknown-linux-gnu",
            "x86_64-unknown-linux-gnu"
        ));
        assert!(!targets_compatible(
            "x86_64-pc-windows-msvc",
            "x86_64-unknown-linux-gnu"
        ));
        assert!(!targets_compatible("", "x86_64-unknown-linux-gnu"));
        assert!(!targets_compatible(
            "aarch64-linux-android",
            "aarch64-unknown-linux-gnu"
        ));
    }

    #[test]
    fn missing_file_is_named() {
        let e = PluginLibrary::load(Path::new("/nonexistent/libnope.so")).err();
        let msg = e.map(|e| e.to_string()).unwrap_or_default();
        assert!(
            msg.contains("not found") && msg.contains("/nonexistent/libnope.so"),
            "{msg}"
        );
    }
}

//! The Rust side of the ABI: `plugin::{create, call, destroy, free}` for a `Plugin` type, driven
//! through a hand-built `FrHost` exactly as the host would, and the descriptor that
//! `export_plugin!` generates.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_plugin_api::abi::{self, FrBuf, FrHost, FrPluginDescriptor};
use fresa_plugin_api::contract::Event;
use fresa_plugin_api::{plugin, Host, Plugin, PluginError};
use serde_json::{json, Value};
use std::ffi::{c_void, CStr};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::Mutex;

/// Ids of `Counter`s that were dropped (tests run in parallel, so each uses its own id).
static DROPPED: Mutex<Vec<u64>> = Mutex::new(Vec::new());

fn dropped(id: u64) -> bool {
    DROPPED.lock().unwrap().contains(&id)
}

/// A small plugin: answers with what it was sent, emits a contract event per call, and
/// panics or fails on request.
struct Counter {
    host: Host,
    id: u64,
    calls: AtomicU32,
}

impl Plugin for Counter {
    fn create(host: Host, config: Value) -> Result<Self, PluginError> {
        if config.get("refuse").is_some() {
            return Err(PluginError::new("refused", "config says no"));
        }
        if config.get("panic").is_some() {
            panic!("create exploded");
        }
        host.info("counter created");
        Ok(Counter {
            host,
            id: config["id"].as_u64().unwrap_or(0),
            calls: AtomicU32::new(0),
        })
    }

    fn call(&self, request: Value) -> Result<Value, PluginError> {
        let n = self.calls.fetch_add(1, Ordering::SeqCst) + 1;
        match request["op"].as_str() {
            Some("panic") => panic!("kaboom in call {n} of {}", self.id),
            Some("panic_static") => panic!("static kaboom"),
            Some("fail") => Err(PluginError::invalid("op fail is not supported")),
            _ => {
                self.host.emit(&Event::LineAcknowledged { run: 7, line: n });
                self.host.log(abi::LOG_DEBUG, &format!("call {n}"));
                Ok(json!({"you_sent": request, "n": n}))
            }
        }
    }
}

impl Drop for Counter {
    fn drop(&mut self) {
        DROPPED.lock().unwrap().push(self.id);
        if self.id == 666 {
            panic!("drop exploded");
        }
    }
}

// ------------------------------------------------------------------------------------------
// A hand-built host table
// ------------------------------------------------------------------------------------------

#[derive(Default)]
struct Recorder {
    events: Mutex<Vec<Value>>,
    logs: Mutex<Vec<(u32, String)>>,
}

unsafe extern "C" fn record_event(ctx: *mut c_void, json: *const u8, len: usize) {
    // SAFETY: ctx is the Recorder the table was built from; json/len are the plugin's bytes.
    let (rec, bytes) = unsafe {
        (
            &*(ctx as *const Recorder),
            std::slice::from_raw_parts(json, len),
        )
    };
    let value = serde_json::from_slice(bytes).unwrap_or(Value::Null);
    rec.events.lock().unwrap().push(value);
}

unsafe extern "C" fn record_log(ctx: *mut c_void, level: u32, msg: *const u8, len: usize) {
    // SAFETY: as above.
    let (rec, bytes) = unsafe {
        (
            &*(ctx as *const Recorder),
            std::slice::from_raw_parts(msg, len),
        )
    };
    let text = String::from_utf8_lossy(bytes).into_owned();
    rec.logs.lock().unwrap().push((level, text));
}

fn table(rec: &Recorder) -> FrHost {
    FrHost {
        struct_size: std::mem::size_of::<FrHost>(),
        ctx: rec as *const Recorder as *mut c_void,
        emit_event: record_event,
        log: record_log,
    }
}

/// Copies a plugin buffer and hands it back to the plugin's `free`.
fn take(buf: FrBuf) -> Value {
    assert!(!buf.ptr.is_null(), "the plugin wrote no buffer");
    // SAFETY: the plugin wrote a valid buffer.
    let bytes = unsafe { std::slice::from_raw_parts(buf.ptr, buf.len) }.to_vec();
    // SAFETY: the buffer came from this plugin and is freed once.
    unsafe { plugin::free(buf) };
    serde_json::from_slice(&bytes).unwrap()
}

/// `create::<Counter>` with a JSON config (raw bytes, so invalid JSON can be sent too).
fn create_raw(host: &FrHost, config: &[u8]) -> (i32, *mut c_void, FrBuf) {
    let mut instance: *mut c_void = std::ptr::null_mut();
    let mut err = FrBuf::EMPTY;
    // SAFETY: all pointers are valid for the call.
    let status = unsafe {
        plugin::create::<Counter>(host, config.as_ptr(), config.len(), &mut instance, &mut err)
    };
    (status, instance, err)
}

fn create(host: &FrHost, config: Value) -> *mut c_void {
    let (status, instance, err) = create_raw(host, &serde_json::to_vec(&config).unwrap());
    assert_eq!(status, abi::STATUS_OK);
    assert!(err.ptr.is_null());
    assert!(!instance.is_null());
    instance
}

fn call_raw(instance: *mut c_void, request: &[u8]) -> (i32, Value) {
    let mut out = FrBuf::EMPTY;
    // SAFETY: instance is live, buffers are valid for the call.
    let status =
        unsafe { plugin::call::<Counter>(instance, request.as_ptr(), request.len(), &mut out) };
    (status, take(out))
}

fn call(instance: *mut c_void, request: Value) -> (i32, Value) {
    call_raw(instance, &serde_json::to_vec(&request).unwrap())
}

fn destroy(instance: *mut c_void) {
    // SAFETY: instance came from create::<Counter> and is destroyed once.
    unsafe { plugin::destroy::<Counter>(instance) };
}

// ------------------------------------------------------------------------------------------
// Tests
// ------------------------------------------------------------------------------------------

#[test]
fn create_call_destroy_through_the_host_table() {
    let rec = Recorder::default();
    let host = table(&rec);
    let instance = create(&host, json!({"id": 1}));
    assert_eq!(
        rec.logs.lock().unwrap().clone(),
        vec![(abi::LOG_INFO, "counter created".to_string())]
    );

    let (status, answer) = call(instance, json!({"op": "status"}));
    assert_eq!(status, abi::STATUS_OK);
    assert_eq!(answer, json!({"you_sent": {"op": "status"}, "n": 1}));
    let (status, answer) = call(instance, json!({"op": "jog", "axis": "X"}));
    assert_eq!(status, abi::STATUS_OK);
    assert_eq!(answer["n"], 2);

    assert_eq!(
        rec.events.lock().unwrap().clone(),
        vec![
            json!({"event": "line_acknowledged", "run": 7, "line": 1}),
            json!({"event": "line_acknowledged", "run": 7, "line": 2}),
        ]
    );
    assert_eq!(
        rec.logs.lock().unwrap()[1..].to_vec(),
        vec![
            (abi::LOG_DEBUG, "call 1".to_string()),
            (abi::LOG_DEBUG, "call 2".to_string()),
        ]
    );

    assert!(!dropped(1));
    destroy(instance);
    assert!(dropped(1), "destroy did not drop the instance");
}

#[test]
fn empty_config_means_an_empty_object() {
    let rec = Recorder::default();
    let host = table(&rec);
    let (status, instance, err) = create_raw(&host, b"");
    assert_eq!(status, abi::STATUS_OK);
    assert!(err.ptr.is_null());
    let (status, _) = call(instance, json!({}));
    assert_eq!(status, abi::STATUS_OK);
    destroy(instance);
}

#[test]
fn create_errors_come_back_as_json() {
    let rec = Recorder::default();
    let host = table(&rec);

    let (status, instance, err) = create_raw(&host, br#"{"refuse": true}"#);
    assert_eq!(status, abi::STATUS_ERROR);
    assert!(instance.is_null());
    assert_eq!(
        take(err),
        json!({"code": "refused", "message": "config says no"})
    );

    let (status, instance, err) = create_raw(&host, b"{not json");
    assert_eq!(status, abi::STATUS_ERROR);
    assert!(instance.is_null());
    let err = take(err);
    assert_eq!(err["code"], "invalid_config");
    assert!(
        err["message"].as_str().unwrap().contains("not JSON"),
        "{err}"
    );
}

#[test]
fn a_panicking_create_returns_status_panic() {
    let rec = Recorder::default();
    let host = table(&rec);
    let result = catch_unwind(AssertUnwindSafe(|| {
        create_raw(&host, br#"{"panic": true}"#)
    }));
    let (status, instance, err) = result.expect("the panic unwound out of create");
    assert_eq!(status, abi::STATUS_PANIC);
    assert!(instance.is_null());
    let err = take(err);
    assert_eq!(err["code"], "panic");
    assert!(
        err["message"].as_str().unwrap().contains("create exploded"),
        "{err}"
    );
}

#[test]
fn call_errors_come_back_as_json() {
    let rec = Recorder::default();
    let host = table(&rec);
    let instance = create(&host, json!({"id": 2}));

    let (status, err) = call(instance, json!({"op": "fail"}));
    assert_eq!(status, abi::STATUS_ERROR);
    assert_eq!(
        err,
        json!({"code": "invalid_request", "message": "op fail is not supported"})
    );

    let (status, err) = call_raw(instance, b"[1, 2");
    assert_eq!(status, abi::STATUS_ERROR);
    assert_eq!(err["code"], "invalid_request");
    assert!(
        err["message"].as_str().unwrap().contains("not JSON"),
        "{err}"
    );
    destroy(instance);
}

#[test]
fn a_panicking_call_returns_status_panic_and_does_not_unwind() {
    let rec = Recorder::default();
    let host = table(&rec);
    let instance = create(&host, json!({"id": 3}));

    // A formatted (String) panic payload and a static (&str) one both keep their message.
    let result = catch_unwind(AssertUnwindSafe(|| call(instance, json!({"op": "panic"}))));
    let (status, err) = result.expect("the panic unwound out of call");
    assert_eq!(status, abi::STATUS_PANIC);
    assert_eq!(err["code"], "panic");
    assert!(
        err["message"]
            .as_str()
            .unwrap()
            .contains("kaboom in call 1 of 3"),
        "{err}"
    );

    let result = catch_unwind(AssertUnwindSafe(|| {
        call(instance, json!({"op": "panic_static"}))
    }));
    let (status, err) = result.expect("the panic unwound out of call");
    assert_eq!(status, abi::STATUS_PANIC);
    assert!(
        err["message"].as_str().unwrap().contains("static kaboom"),
        "{err}"
    );

    // The instance is still usable afterwards.
    let (status, answer) = call(instance, json!({"op": "status"}));
    assert_eq!(status, abi::STATUS_OK);
    assert_eq!(answer["n"], 3);
    destroy(instance);
    assert!(dropped(3));
}

#[test]
fn a_panicking_drop_does_not_unwind_out_of_destroy() {
    let rec = Recorder::default();
    let host = table(&rec);
    let instance = create(&host, json!({"id": 666}));
    let result = catch_unwind(AssertUnwindSafe(|| destroy(instance)));
    assert!(result.is_ok(), "the panic unwound out of destroy");
    assert!(dropped(666));
}

#[test]
fn destroy_and_free_accept_null() {
    destroy(std::ptr::null_mut());
    // SAFETY: the empty buffer is always accepted.
    unsafe { plugin::free(FrBuf::EMPTY) };
}

#[test]
fn concurrent_calls_on_one_instance() {
    let rec = Recorder::default();
    let host = table(&rec);
    let instance = create(&host, json!({"id": 4}));
    // Raw pointers are not Send; the ABI says instances are callable from any thread.
    let addr = instance as usize;
    std::thread::scope(|s| {
        for t in 0..4 {
            s.spawn(move || {
                for i in 0..25 {
                    let (status, answer) = call(addr as *mut c_void, json!({"t": t, "i": i}));
                    assert_eq!(status, abi::STATUS_OK);
                    assert_eq!(answer["you_sent"], json!({"t": t, "i": i}));
                }
            });
        }
    });
    let mut lines: Vec<u64> = rec
        .events
        .lock()
        .unwrap()
        .iter()
        .map(|e| e["line"].as_u64().unwrap())
        .collect();
    lines.sort_unstable();
    assert_eq!(lines, (1..=100).collect::<Vec<u64>>());
    destroy(instance);
}

// ------------------------------------------------------------------------------------------
// export_plugin!
// ------------------------------------------------------------------------------------------

fresa_plugin_api::export_plugin!(
    Counter,
    name = "rust-counter",
    kinds = abi::KIND_MACHINE_BACKEND
);

extern "C" {
    // Defined by export_plugin! above, in this test binary.
    fn fresa_plugin_v1() -> *const FrPluginDescriptor;
}

#[test]
fn export_plugin_builds_a_valid_descriptor() {
    // SAFETY: the symbol is the one export_plugin! defined.
    let d = unsafe { &*fresa_plugin_v1() };
    assert_eq!(d.magic, abi::MAGIC);
    assert_eq!(d.magic.to_le_bytes(), *b"FRESAPL1");
    assert_eq!((d.abi_major, d.abi_minor), (abi::ABI_MAJOR, abi::ABI_MINOR));
    assert_eq!(
        d.struct_size as usize,
        std::mem::size_of::<FrPluginDescriptor>()
    );
    assert_eq!(d.kinds, abi::KIND_MACHINE_BACKEND);
    // SAFETY: the descriptor's strings are static and NUL-terminated.
    let (target, name, version) = unsafe {
        (
            CStr::from_ptr(d.target).to_str().unwrap(),
            CStr::from_ptr(d.name).to_str().unwrap(),
            CStr::from_ptr(d.version).to_str().unwrap(),
        )
    };
    assert_eq!(target, fresa_plugin_api::TARGET);
    assert_eq!(name, "rust-counter");
    assert_eq!(version, env!("CARGO_PKG_VERSION"));

    // The function pointers are the generic entry points for Counter.
    let rec = Recorder::default();
    let host = table(&rec);
    let config = br#"{"id": 5}"#;
    let mut instance: *mut c_void = std::ptr::null_mut();
    let mut err = FrBuf::EMPTY;
    // SAFETY: per the ABI; pointers are valid for the calls.
    unsafe {
        assert_eq!(
            (d.create)(
                &host,
                config.as_ptr(),
                config.len(),
                &mut instance,
                &mut err
            ),
            abi::STATUS_OK
        );
        let req = br#"{"op":"status"}"#;
        let mut out = FrBuf::EMPTY;
        assert_eq!(
            (d.call)(instance, req.as_ptr(), req.len(), &mut out),
            abi::STATUS_OK
        );
        let answer: Value =
            serde_json::from_slice(std::slice::from_raw_parts(out.ptr, out.len)).unwrap();
        (d.free)(out);
        assert_eq!(answer, json!({"you_sent": {"op": "status"}, "n": 1}));
        (d.destroy)(instance);
    }
    assert!(dropped(5));
}

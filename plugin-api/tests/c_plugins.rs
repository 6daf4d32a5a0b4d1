//! Plugins written in C (and C++) against `include/fresa_plugin.h`, compiled with the system
//! compiler and loaded through `PluginLibrary::load`: the header matches `abi.rs`, a working
//! plugin round-trips, and each kind of broken library is refused with a message naming the
//! problem.
#![cfg(unix)]
#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_plugin_api::abi::{self, FrBuf, FrHost, FrPluginDescriptor};
use fresa_plugin_api::contract::{Command, Request};
use fresa_plugin_api::host::{CallError, HostSink, PluginLibrary};
use serde_json::{json, Value};
use std::ffi::{c_char, c_long, CStr};
use std::mem::{align_of, offset_of, size_of};
use std::path::{Path, PathBuf};
use std::process::Command as Process;
use std::sync::{Arc, Mutex};

const MANIFEST_DIR: &str = env!("CARGO_MANIFEST_DIR");

fn include_dir() -> PathBuf {
    Path::new(MANIFEST_DIR).join("include")
}

fn c_source(name: &str) -> PathBuf {
    Path::new(MANIFEST_DIR).join("tests").join("c").join(name)
}

/// Where this test process puts the libraries it builds.
fn out_dir() -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR"))
        .join("fresa-c-plugins")
        .join(std::process::id().to_string());
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// The C (or C++) compiler: `$CC`/`$CXX` if set, else `cc`/`c++`.
fn compiler(cxx: bool) -> String {
    let (var, default) = if cxx { ("CXX", "c++") } else { ("CC", "cc") };
    let cc = std::env::var(var).unwrap_or_else(|_| default.to_string());
    match Process::new(&cc).arg("--version").output() {
        Ok(o) if o.status.success() => cc,
        Ok(o) => panic!(
            "the {} compiler `{cc}` does not work (`{cc} --version` failed: {}); these tests build \
             plugins from C sources: install gcc/g++ or set ${var}",
            if cxx { "C++" } else { "C" },
            String::from_utf8_lossy(&o.stderr)
        ),
        Err(e) => panic!(
            "no {} compiler found (`{cc}`: {e}); these tests build plugins from C sources: \
             install gcc/g++ (e.g. `apt-get install build-essential`) or set ${var}",
            if cxx { "C++" } else { "C" }
        ),
    }
}

/// Compiles `source` into a shared library named after `lib_name`, with extra `-D` defines.
/// Warnings are errors, so the header must be clean under `-Wall -Wextra -Wpedantic`.
fn build(lib_name: &str, source: &str, defines: &[&str]) -> PathBuf {
    let cxx = source.ends_with(".cpp");
    let cc = compiler(cxx);
    let out = out_dir().join(fresa_plugin_api::library_file_name(lib_name));
    let mut cmd = Process::new(&cc);
    cmd.arg(if cxx { "-std=c++11" } else { "-std=c11" })
        .args(["-Wall", "-Wextra", "-Wpedantic", "-Werror"])
        .args(["-shared", "-fPIC"])
        .arg("-I")
        .arg(include_dir());
    for d in defines {
        cmd.arg(format!("-D{d}"));
    }
    cmd.arg(c_source(source)).arg("-o").arg(&out);
    let output = cmd.output().unwrap();
    assert!(
        output.status.success(),
        "compiling {source} with {defines:?} failed:\n{cmd:?}\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    out
}

/// A function a test library exports besides the descriptor, looked up by name.
/// `dlopen` of an already loaded path returns the same handle, so this reads the plugin's globals.
fn extra<T: Copy>(path: &Path, symbol: &str) -> T {
    // SAFETY: the test libraries are ours; the caller names the symbol's real type.
    unsafe {
        let lib: &'static libloading::Library =
            Box::leak(Box::new(libloading::Library::new(path).unwrap()));
        *lib.get::<T>(symbol.as_bytes()).unwrap()
    }
}

fn counter(path: &Path, symbol: &str) -> c_long {
    let f: unsafe extern "C" fn() -> c_long = extra(path, symbol);
    // SAFETY: the echo plugin's counters take no arguments.
    unsafe { f() }
}

/// Records what plugin instances send to the host.
#[derive(Default)]
struct Recorder {
    events: Mutex<Vec<Value>>,
    logs: Mutex<Vec<(u32, String)>>,
}

impl HostSink for Recorder {
    fn event(&self, event: Value) {
        self.events.lock().unwrap().push(event);
    }
    fn log(&self, level: u32, message: &str) {
        self.logs.lock().unwrap().push((level, message.to_string()));
    }
}

impl Recorder {
    fn events(&self) -> Vec<Value> {
        self.events.lock().unwrap().clone()
    }
    fn logs(&self) -> Vec<(u32, String)> {
        self.logs.lock().unwrap().clone()
    }
}

fn host_arch() -> &'static str {
    fresa_plugin_api::TARGET.split('-').next().unwrap()
}

// ------------------------------------------------------------------------------------------
// The header
// ------------------------------------------------------------------------------------------

#[test]
fn header_layout_and_constants_match_abi_rs() {
    let path = build("fresa_layout", "layout.c", &[]);
    let layout: unsafe extern "C" fn(*mut usize) -> *const u64 = extra(&path, "fresa_layout");
    let mut n = 0usize;
    // SAFETY: fresa_layout returns a static array of `n` u64.
    let c = unsafe { std::slice::from_raw_parts(layout(&mut n), n) };

    type D = FrPluginDescriptor;
    let rust: Vec<(&str, u64)> = vec![
        ("sizeof FrBuf", size_of::<FrBuf>() as u64),
        ("alignof FrBuf", align_of::<FrBuf>() as u64),
        ("FrBuf.ptr", offset_of!(FrBuf, ptr) as u64),
        ("FrBuf.len", offset_of!(FrBuf, len) as u64),
        ("sizeof FrHost", size_of::<FrHost>() as u64),
        ("alignof FrHost", align_of::<FrHost>() as u64),
        ("FrHost.struct_size", offset_of!(FrHost, struct_size) as u64),
        ("FrHost.ctx", offset_of!(FrHost, ctx) as u64),
        ("FrHost.emit_event", offset_of!(FrHost, emit_event) as u64),
        ("FrHost.log", offset_of!(FrHost, log) as u64),
        ("sizeof FrPluginDescriptor", size_of::<D>() as u64),
        ("alignof FrPluginDescriptor", align_of::<D>() as u64),
        ("D.magic", offset_of!(D, magic) as u64),
        ("D.abi_major", offset_of!(D, abi_major) as u64),
        ("D.abi_minor", offset_of!(D, abi_minor) as u64),
        ("D.struct_size", offset_of!(D, struct_size) as u64),
        ("D.target", offset_of!(D, target) as u64),
        ("D.name", offset_of!(D, name) as u64),
        ("D.version", offset_of!(D, version) as u64),
        ("D.kinds", offset_of!(D, kinds) as u64),
        ("D.create", offset_of!(D, create) as u64),
        ("D.call", offset_of!(D, call) as u64),
        ("D.destroy", offset_of!(D, destroy) as u64),
        ("D.free", offset_of!(D, free) as u64),
        ("FRESA_PLUGIN_MAGIC", abi::MAGIC),
        ("FRESA_ABI_MAJOR", u64::from(abi::ABI_MAJOR)),
        ("FRESA_ABI_MINOR", u64::from(abi::ABI_MINOR)),
        (
            "FRESA_KIND_MACHINE_BACKEND",
            u64::from(abi::KIND_MACHINE_BACKEND),
        ),
        (
            "FRESA_KIND_PENDANT_TRANSPORT",
            u64::from(abi::KIND_PENDANT_TRANSPORT),
        ),
        ("FRESA_STATUS_OK", abi::STATUS_OK as u64),
        ("FRESA_STATUS_ERROR", abi::STATUS_ERROR as u64),
        ("FRESA_STATUS_PANIC", abi::STATUS_PANIC as u64),
        ("FRESA_LOG_ERROR", u64::from(abi::LOG_ERROR)),
        ("FRESA_LOG_WARN", u64::from(abi::LOG_WARN)),
        ("FRESA_LOG_INFO", u64::from(abi::LOG_INFO)),
        ("FRESA_LOG_DEBUG", u64::from(abi::LOG_DEBUG)),
        ("FRESA_LOG_TRACE", u64::from(abi::LOG_TRACE)),
    ];
    assert_eq!(
        c.len(),
        rust.len(),
        "layout.c and this test list different items"
    );
    for (i, (what, expected)) in rust.iter().enumerate() {
        assert_eq!(
            c[i], *expected,
            "{what}: header says {}, abi.rs says {expected}",
            c[i]
        );
    }

    let symbol: unsafe extern "C" fn() -> *const c_char = extra(&path, "fresa_symbol");
    // SAFETY: returns a static NUL-terminated string.
    let symbol = unsafe { CStr::from_ptr(symbol()) }.to_str().unwrap();
    assert_eq!(symbol, abi::DESCRIPTOR_SYMBOL);

    let typedefs: unsafe extern "C" fn() -> i32 = extra(&path, "fresa_typedefs_ok");
    // SAFETY: no arguments.
    assert_eq!(unsafe { typedefs() }, 1);
}

#[test]
fn header_target_triple_is_accepted_by_this_host() {
    let path = build("fresa_layout_target", "layout.c", &[]);
    let target: unsafe extern "C" fn() -> *const c_char = extra(&path, "fresa_target");
    // SAFETY: returns a static NUL-terminated string.
    let target = unsafe { CStr::from_ptr(target()) }.to_str().unwrap();
    assert!(
        fresa_plugin_api::host::targets_compatible(target, fresa_plugin_api::TARGET),
        "FRESA_TARGET_TRIPLE is {target}, host is {}",
        fresa_plugin_api::TARGET
    );
    // Where the header's spelling is exactly Rust's, check it exactly.
    if cfg!(all(
        target_os = "linux",
        target_env = "gnu",
        any(target_arch = "x86_64", target_arch = "aarch64")
    )) {
        assert_eq!(target, fresa_plugin_api::TARGET);
    }
}

#[test]
fn header_compiles_as_c99_and_as_cxx() {
    for (lang, std, cxx) in [("c", "-std=c99", false), ("c++", "-std=c++11", true)] {
        let cc = compiler(cxx);
        let output = Process::new(&cc)
            .args(["-x", lang, std, "-Wall", "-Wextra", "-Wpedantic", "-Werror"])
            .arg("-fsyntax-only")
            .arg(include_dir().join("fresa_plugin.h"))
            .output()
            .unwrap();
        assert!(
            output.status.success(),
            "fresa_plugin.h does not compile as {lang} ({std}):\n{}",
            String::from_utf8_lossy(&output.stderr)
        );
    }
}

#[test]
fn header_target_triple_can_be_overridden() {
    let path = build(
        "fresa_layout_override",
        "layout.c",
        &["FRESA_TARGET_TRIPLE=\"riscv64gc-unknown-linux-gnu\""],
    );
    let target: unsafe extern "C" fn() -> *const c_char = extra(&path, "fresa_target");
    // SAFETY: returns a static NUL-terminated string.
    let target = unsafe { CStr::from_ptr(target()) }.to_str().unwrap();
    assert_eq!(target, "riscv64gc-unknown-linux-gnu");
}

// ------------------------------------------------------------------------------------------
// A working C plugin
// ------------------------------------------------------------------------------------------

#[test]
fn c_echo_plugin_round_trip() {
    let path = build("echo_round_trip", "echo_plugin.c", &[]);
    let lib = PluginLibrary::load(&path).unwrap();
    assert_eq!(lib.name(), "c-echo");
    assert_eq!(lib.version(), "0.3.1");
    assert_eq!(
        lib.kinds(),
        abi::KIND_MACHINE_BACKEND | abi::KIND_PENDANT_TRANSPORT
    );
    assert_eq!(lib.abi_version(), (abi::ABI_MAJOR, abi::ABI_MINOR));
    assert!(fresa_plugin_api::host::targets_compatible(
        lib.target(),
        fresa_plugin_api::TARGET
    ));

    let sink = Arc::new(Recorder::default());
    let instance = lib
        .create(&json!({"port": "/dev/null"}), sink.clone())
        .unwrap();
    assert_eq!(
        counter(&path, "echo_host_struct_size"),
        size_of::<FrHost>() as c_long,
        "the plugin saw a host table of the wrong size"
    );
    assert_eq!(counter(&path, "echo_live_instances"), 1);

    // Round trip: the answer contains the request.
    let request = json!({"op": "status", "nested": {"list": [1, 2.5, "três"]}});
    let answer = instance.call(&request).unwrap();
    assert_eq!(answer, json!({"echo": request, "call": 1}));
    assert_eq!(sink.events(), vec![json!({"event": "echoed", "call": 1})]);
    assert_eq!(
        sink.logs(),
        vec![(abi::LOG_INFO, "echo call 1".to_string())]
    );

    // Typed requests go out in the contract's wire shape.
    let answer: Value = instance
        .request(&Request::Command(Command::FeedHold))
        .unwrap();
    assert_eq!(
        answer["echo"],
        json!({"op": "command", "command": "feed_hold"})
    );

    // An error status comes back as CallError::Plugin with the plugin's code and message.
    match instance.call(&json!({"op": "fail"})) {
        Err(CallError::Plugin(e)) => {
            assert_eq!(e.code, "echo_failed");
            assert_eq!(e.message, "asked to fail");
        }
        other => panic!("expected CallError::Plugin, got {other:?}"),
    }

    // A status the ABI does not define is a protocol error.
    match instance.call(&json!({"op": "bogus_status"})) {
        Err(CallError::Protocol(m)) => assert!(m.contains("42"), "{m}"),
        other => panic!("expected CallError::Protocol, got {other:?}"),
    }

    // An OK call with an empty answer means {}.
    assert_eq!(instance.call(&json!({"op": "empty"})).unwrap(), json!({}));

    // Every call emitted an event and a log line, in order.
    let events = sink.events();
    assert_eq!(events.len(), 5);
    for (i, e) in events.iter().enumerate() {
        assert_eq!(e, &json!({"event": "echoed", "call": i + 1}));
    }
    assert_eq!(sink.logs().len(), 5);

    // The host gave every plugin buffer back through the plugin's free.
    assert_eq!(counter(&path, "echo_live_buffers"), 0);

    assert_eq!(counter(&path, "echo_destroyed"), 0);
    drop(instance);
    assert_eq!(counter(&path, "echo_destroyed"), 1, "destroy did not run");
    assert_eq!(counter(&path, "echo_live_instances"), 0);
}

#[test]
fn c_echo_plugin_serves_concurrent_calls() {
    let path = build("echo_concurrent", "echo_plugin.c", &[]);
    let lib = PluginLibrary::load(&path).unwrap();
    let sink = Arc::new(Recorder::default());
    let instance = lib.create(&json!({}), sink.clone()).unwrap();
    const THREADS: usize = 4;
    const CALLS: usize = 50;
    std::thread::scope(|s| {
        for t in 0..THREADS {
            let instance = &instance;
            s.spawn(move || {
                for i in 0..CALLS {
                    let request = json!({"op": "status", "thread": t, "i": i});
                    let answer = instance.call(&request).unwrap();
                    assert_eq!(answer["echo"], request);
                }
            });
        }
    });
    // Each call got its own number: the plugin's counter is shared and atomic.
    let mut numbers: Vec<u64> = sink
        .events()
        .iter()
        .map(|e| e["call"].as_u64().unwrap())
        .collect();
    numbers.sort_unstable();
    let expected: Vec<u64> = (1..=(THREADS * CALLS) as u64).collect();
    assert_eq!(numbers, expected);
    assert_eq!(counter(&path, "echo_live_buffers"), 0);
    drop(instance);
    assert_eq!(counter(&path, "echo_destroyed"), 1);
}

#[test]
fn c_plugin_create_error_is_reported_and_nothing_is_destroyed() {
    let path = build("echo_create_error", "echo_plugin.c", &[]);
    let lib = PluginLibrary::load(&path).unwrap();
    let sink = Arc::new(Recorder::default());
    match lib.create(&json!({"fail_create": true}), sink) {
        Err(CallError::Plugin(e)) => {
            assert_eq!(e.code, "bad_config");
            assert!(e.message.contains("fail_create"), "{}", e.message);
        }
        Err(other) => panic!("expected CallError::Plugin, got {other:?}"),
        Ok(_) => panic!("create should have failed"),
    }
    assert_eq!(counter(&path, "echo_live_instances"), 0);
    assert_eq!(counter(&path, "echo_destroyed"), 0);
    assert_eq!(counter(&path, "echo_live_buffers"), 0);
}

#[test]
fn cxx_plugin_exports_an_unmangled_symbol_and_keeps_exceptions_inside() {
    let path = build("cxx_plugin", "cxx_plugin.cpp", &[]);
    let lib = PluginLibrary::load(&path).unwrap();
    assert_eq!(lib.name(), "cxx-plugin");
    let instance = lib
        .create(&json!({}), Arc::new(Recorder::default()))
        .unwrap();
    assert_eq!(
        instance.call(&json!({"op": "status"})).unwrap(),
        json!({"ok": true})
    );
    match instance.call(&json!({"op": "throw"})) {
        Err(CallError::Panic(m)) => assert!(m.contains("thrown on purpose"), "{m}"),
        other => panic!("expected CallError::Panic, got {other:?}"),
    }
}

// ------------------------------------------------------------------------------------------
// Libraries the host refuses
// ------------------------------------------------------------------------------------------

fn load_error(path: &Path) -> String {
    PluginLibrary::load(path).unwrap_err().to_string()
}

fn assert_names(message: &str, parts: &[&str]) {
    for p in parts {
        assert!(message.contains(p), "`{message}` does not mention `{p}`");
    }
}

#[test]
fn refuses_a_missing_file() {
    let path = out_dir().join("libdoes_not_exist.so");
    let m = load_error(&path);
    assert_names(&m, &["not found", &path.display().to_string()]);
}

#[test]
fn refuses_a_file_that_is_not_a_library() {
    let path = out_dir().join(fresa_plugin_api::library_file_name("not_a_library"));
    std::fs::write(&path, "this is a text file, not ELF").unwrap();
    let m = load_error(&path);
    assert_names(&m, &["cannot open plugin", &path.display().to_string()]);
}

#[test]
fn refuses_a_library_without_the_descriptor_symbol() {
    let path = build("no_symbol", "echo_plugin.c", &["NO_DESCRIPTOR"]);
    let m = load_error(&path);
    assert_names(
        &m,
        &[
            "does not export the symbol",
            "fresa_plugin_v1",
            &path.display().to_string(),
        ],
    );
}

#[test]
fn refuses_a_wrong_magic() {
    let path = build(
        "bad_magic",
        "echo_plugin.c",
        &["PLUGIN_MAGIC=UINT64_C(0x1122334455667788)"],
    );
    let m = load_error(&path);
    assert_names(
        &m,
        &[
            "not a Fresa plugin",
            "magic",
            "0x1122334455667788",
            &format!("{:#018x}", abi::MAGIC),
            &path.display().to_string(),
        ],
    );
}

#[test]
fn refuses_another_abi_major() {
    let path = build("abi_major_2", "echo_plugin.c", &["PLUGIN_ABI_MAJOR=2"]);
    let m = load_error(&path);
    assert_names(
        &m,
        &[
            "plugin ABI 2.0",
            &format!("server's ABI {}.{}", abi::ABI_MAJOR, abi::ABI_MINOR),
            &path.display().to_string(),
        ],
    );
}

#[test]
fn refuses_a_newer_abi_minor() {
    let minor = abi::ABI_MINOR + 7;
    let define = format!("PLUGIN_ABI_MINOR={minor}");
    let path = build("abi_minor_newer", "echo_plugin.c", &[&define]);
    let m = load_error(&path);
    assert_names(
        &m,
        &[
            &format!("plugin ABI {}.{minor}", abi::ABI_MAJOR),
            &format!("server's ABI {}.{}", abi::ABI_MAJOR, abi::ABI_MINOR),
        ],
    );
}

#[test]
fn refuses_another_architecture() {
    let other = if host_arch() == "aarch64" {
        "x86_64-unknown-linux-gnu"
    } else {
        "aarch64-unknown-linux-gnu"
    };
    let define = format!("PLUGIN_TARGET=\"{other}\"");
    let path = build("wrong_arch", "echo_plugin.c", &[&define]);
    let m = load_error(&path);
    assert_names(
        &m,
        &[
            &format!("built for target {other}"),
            &format!("runs on {}", fresa_plugin_api::TARGET),
            &path.display().to_string(),
        ],
    );
}

#[test]
fn refuses_another_operating_system() {
    let other = format!("{}-pc-windows-msvc", host_arch());
    let define = format!("PLUGIN_TARGET=\"{other}\"");
    let path = build("wrong_os", "echo_plugin.c", &[&define]);
    let m = load_error(&path);
    assert_names(
        &m,
        &[
            &format!("built for target {other}"),
            &format!("runs on {}", fresa_plugin_api::TARGET),
        ],
    );
}

#[test]
fn refuses_a_descriptor_smaller_than_v1_0() {
    let path = build(
        "small_struct",
        "echo_plugin.c",
        &["PLUGIN_STRUCT_SIZE=(sizeof(FrPluginDescriptor)-8)"],
    );
    let full = size_of::<FrPluginDescriptor>();
    let m = load_error(&path);
    assert_names(
        &m,
        &[
            "invalid descriptor",
            &format!("struct_size {}", full - 8),
            &format!("({full} bytes)"),
            &path.display().to_string(),
        ],
    );
}

#[test]
fn refuses_a_descriptor_that_is_only_the_head() {
    // The host must read only magic, versions and struct_size before trusting the size.
    let path = build("head_only", "echo_plugin.c", &["HEAD_ONLY"]);
    let m = load_error(&path);
    assert_names(&m, &["invalid descriptor", "struct_size 16 is smaller"]);
}

#[test]
fn refuses_a_null_target_and_an_empty_name() {
    let path = build("null_target", "echo_plugin.c", &["PLUGIN_TARGET=NULL"]);
    assert_names(
        &load_error(&path),
        &["invalid descriptor", "target is null"],
    );

    let path = build("empty_name", "echo_plugin.c", &["PLUGIN_NAME=\"\""]);
    assert_names(&load_error(&path), &["invalid descriptor", "empty name"]);
}

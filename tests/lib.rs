//! Helpers shared by the black-box tests: build `fresa` and the sim-machine plugin once per test
//! process, start real servers on `127.0.0.1:0` with a fresh data directory each, and talk HTTP
//! (JSON and Server-Sent Events) to them. Servers are killed when their [`Server`] is dropped, so
//! a failing test leaves no process behind.
//!
//! Synchronisation is by polling with a deadline ([`wait_for`]) or by reading SSE, never by
//! sleeping for a guessed time.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use serde_json::{json, Value};
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::{mpsc, Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

pub use serde_json;

#[path = "support/wine.rs"]
pub mod wine;

/// How long a server may take to print its `listening on` line and answer `/healthz`.
const START_TIMEOUT: Duration = Duration::from_secs(60);

/// The Cargo workspace root (`tests/..`).
pub fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("tests/ has a parent")
        .to_path_buf()
}

/// A corpus G-code file, read in place from `<workspace>/../shared/corpus/gcode/`.
pub fn corpus(name: &str) -> PathBuf {
    let p = workspace_root().join("../shared/corpus/gcode").join(name);
    assert!(p.is_file(), "corpus file {} is missing", p.display());
    p
}

/// The directory of the test executable's profile (`<target>/debug`): the parent of `deps/`.
fn profile_dir() -> PathBuf {
    let exe = std::env::current_exe().expect("current_exe");
    let deps = exe.parent().expect("test executable has a directory");
    if deps.file_name().is_some_and(|n| n == "deps") {
        return deps.parent().expect("deps/ has a parent").to_path_buf();
    }
    let target = std::env::var_os("CARGO_TARGET_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace_root().join("target"));
    let target = if target.is_relative() {
        workspace_root().join(target)
    } else {
        target
    };
    target.join(if cfg!(debug_assertions) {
        "debug"
    } else {
        "release"
    })
}

/// Builds `fresa`, every plugin library and every simulator binary of the workspace (once per
/// test process; `cargo test` does not build them) and returns the directory holding them.
pub fn bin_dir() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let profile = profile_dir();
        let target_dir = profile.parent().expect("profile dir has a parent");
        let mut cmd = Command::new(env!("CARGO"));
        cmd.current_dir(workspace_root())
            .args(["build", "--workspace"])
            .arg("--target-dir")
            .arg(target_dir);
        if !cfg!(debug_assertions) {
            cmd.arg("--release");
        }
        let out = cmd.output().expect("run cargo build");
        assert!(
            out.status.success(),
            "cargo build of the server, plugins and simulators failed:\n{}",
            String::from_utf8_lossy(&out.stderr)
        );
        assert!(
            profile.join("fresa").is_file(),
            "no fresa binary in {}",
            profile.display()
        );
        profile
    })
}

/// The `fresa` binary (built on first use).
pub fn fresa_bin() -> PathBuf {
    bin_dir().join("fresa")
}

/// A `fresa` command with no `FRESA_*` variable inherited from the environment.
pub fn fresa_cmd() -> Command {
    let mut cmd = Command::new(fresa_bin());
    without_fresa_env(&mut cmd).stdin(Stdio::null());
    cmd
}

/// `cmd` without the `FRESA_*` variables of the test's environment (a developer's own settings
/// must not reach the servers under test).
pub fn without_fresa_env(cmd: &mut Command) -> &mut Command {
    for (k, _) in std::env::vars_os() {
        if k.to_string_lossy().starts_with("FRESA_") {
            cmd.env_remove(k);
        }
    }
    cmd
}

/// Sends `kill -SIGNAL PID` (e.g. `"TERM"`, `"HUP"`) and returns at once.
#[track_caller]
pub fn send_signal(pid: u32, signal: &str) {
    let ok = Command::new("kill")
        .arg(format!("-{signal}"))
        .arg(pid.to_string())
        .status()
        .expect("run kill")
        .success();
    assert!(ok, "kill -{signal} {pid} failed");
}

/// Polls `f` until it returns `Some`, or panics after `timeout` naming `what`.
pub fn wait_for<T>(timeout: Duration, what: &str, mut f: impl FnMut() -> Option<T>) -> T {
    let deadline = Instant::now() + timeout;
    loop {
        if let Some(v) = f() {
            return v;
        }
        assert!(
            Instant::now() < deadline,
            "timed out after {timeout:?} waiting for {what}"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// A response: status and body (JSON when it parses, `Null` otherwise, and the raw text).
#[derive(Debug)]
pub struct Resp {
    pub status: u16,
    pub body: Value,
    pub text: String,
}

impl Resp {
    /// Asserts the status and returns the JSON body.
    #[track_caller]
    pub fn expect(self, status: u16) -> Value {
        assert_eq!(
            self.status, status,
            "expected HTTP {status}, got {}: {}",
            self.status, self.text
        );
        self.body
    }

    /// Asserts a JSON error `{"code","message"}` with this status and code; returns the message.
    #[track_caller]
    pub fn expect_error(self, status: u16, code: &str) -> String {
        assert_eq!(
            self.status, status,
            "expected HTTP {status} {code}, got {}: {}",
            self.status, self.text
        );
        assert_eq!(
            self.body["code"].as_str(),
            Some(code),
            "wrong error code in {}",
            self.text
        );
        let msg = self.body["message"]
            .as_str()
            .unwrap_or_else(|| panic!("error without a message: {}", self.text))
            .to_string();
        assert!(!msg.is_empty(), "empty error message");
        msg
    }
}

/// How to start a server.
#[derive(Debug, Clone)]
pub struct Opts {
    pub listen: String,
    pub demo: bool,
    pub max_upload_bytes: Option<u64>,
    /// Plugin directories searched before the workspace's own (`--plugin-dir`, in this order).
    pub extra_plugin_dirs: Vec<PathBuf>,
    /// `FRESA_LOG` for the server (default `info,tower_http=warn,sqlx=warn`).
    pub log: Option<String>,
    /// Run the cross-built `fresa.exe` with its DLL plugins under Wine ([`wine`]).
    pub wine: bool,
}

impl Default for Opts {
    fn default() -> Self {
        Opts {
            listen: "127.0.0.1:0".into(),
            demo: false,
            max_upload_bytes: None,
            extra_plugin_dirs: Vec::new(),
            log: None,
            wine: false,
        }
    }
}

/// A running `fresa serve` with its own temporary directory (data dir, config, execution logs).
pub struct Server {
    root: tempfile::TempDir,
    opts: Opts,
    child: Option<Child>,
    /// `http://127.0.0.1:PORT`
    pub base: String,
    /// Sent as `Authorization: Bearer` when set.
    pub token: Option<String>,
    log: Arc<Mutex<Vec<String>>>,
    http: reqwest::blocking::Client,
}

impl Drop for Server {
    fn drop(&mut self) {
        self.kill();
    }
}

fn new_root() -> tempfile::TempDir {
    let root = tempfile::Builder::new()
        .prefix("fresa-test-")
        .tempdir()
        .expect("temp dir");
    std::fs::write(root.path().join("fresa.toml"), "").expect("write empty config");
    root
}

impl Server {
    /// Starts a loopback server with a fresh data directory.
    pub fn start() -> Server {
        Server::start_with(Opts::default())
    }

    /// Starts `fresa serve --demo`.
    pub fn start_demo() -> Server {
        Server::start_with(Opts {
            demo: true,
            ..Opts::default()
        })
    }

    pub fn start_with(opts: Opts) -> Server {
        let mut s = Server::unstarted(opts);
        s.spawn()
            .unwrap_or_else(|e| panic!("server did not start: {e}"));
        s
    }

    /// A server started with this config file (`fresa.toml`, TOML text) and default options.
    pub fn start_with_config(toml: &str) -> Server {
        let mut s = Server::unstarted(Opts::default());
        s.write_config(toml);
        s.spawn()
            .unwrap_or_else(|e| panic!("server did not start with {toml:?}: {e}"));
        s
    }

    /// A server whose directory exists (so tokens can be created) but that is not running yet.
    pub fn unstarted(opts: Opts) -> Server {
        Server {
            root: new_root(),
            opts,
            child: None,
            base: String::new(),
            token: None,
            log: Arc::new(Mutex::new(Vec::new())),
            // A pooled connection is dropped after 1 s idle: the server closes an idle
            // keep-alive connection at its header read timeout (hyper runs it while waiting for
            // the next request; `slow_clients` sets 2 s), and reusing one the server is closing
            // at that moment fails the request ("error sending request"), a race of the test's
            // client, not of the server.
            http: reqwest::blocking::Client::builder()
                .timeout(Duration::from_secs(60))
                .pool_idle_timeout(Duration::from_secs(1))
                .build()
                .expect("http client"),
        }
    }

    /// The temporary directory: `data/` (the data dir), `fresa.toml`, execution logs.
    pub fn root(&self) -> &Path {
        self.root.path()
    }

    /// A path as the server process sees it (under Wine: on drive `Z:`).
    pub fn host_path(&self, p: &Path) -> String {
        if self.opts.wine {
            wine::path(p)
        } else {
            p.display().to_string()
        }
    }

    pub fn data_dir(&self) -> PathBuf {
        self.root.path().join("data")
    }

    pub fn programs_dir(&self) -> PathBuf {
        self.data_dir().join("programs")
    }

    pub fn config_file(&self) -> PathBuf {
        self.root.path().join("fresa.toml")
    }

    /// Everything the server (all its processes so far) wrote to stderr.
    pub fn log(&self) -> String {
        self.log.lock().unwrap().join("\n")
    }

    /// Starts the process and waits until it is listening and healthy. On failure (the process
    /// exited, or never got ready) returns its stderr.
    pub fn spawn(&mut self) -> Result<(), String> {
        assert!(self.child.is_none(), "server already running");
        let (mut cmd, plugins) = if self.opts.wine {
            let dir = wine::windows_bin_dir();
            (wine::command(&dir.join("fresa.exe")), dir)
        } else {
            (fresa_cmd(), bin_dir())
        };
        cmd.arg("serve")
            .arg("--listen")
            .arg(&self.opts.listen)
            .arg("--data-dir")
            .arg(self.host_path(&self.data_dir()))
            .arg("--config")
            .arg(self.host_path(&self.config_file()));
        for dir in &self.opts.extra_plugin_dirs {
            cmd.arg("--plugin-dir").arg(self.host_path(dir));
        }
        cmd.arg("--plugin-dir")
            .arg(self.host_path(plugins))
            .env(
                "FRESA_LOG",
                self.opts
                    .log
                    .as_deref()
                    .unwrap_or("info,tower_http=warn,sqlx=warn"),
            )
            .stdout(Stdio::null())
            .stderr(Stdio::piped());
        if self.opts.demo {
            cmd.arg("--demo");
        }
        if let Some(n) = self.opts.max_upload_bytes {
            cmd.arg("--max-upload-bytes").arg(n.to_string());
        }
        let mut child = cmd
            .spawn()
            .map_err(|e| format!("cannot spawn fresa: {e}"))?;
        let stderr = child.stderr.take().expect("piped stderr");
        let (tx, rx) = mpsc::channel::<String>();
        let log = self.log.clone();
        std::thread::spawn(move || {
            // Keeps draining stderr for the life of the process so it never blocks on a pipe.
            for line in BufReader::new(stderr).lines() {
                let Ok(line) = line else { break };
                log.lock().unwrap().push(line.clone());
                if tx.send(line).is_err() {
                    // Nobody waits for the start line any more; keep draining into the log.
                }
            }
        });
        self.child = Some(child);
        let deadline = Instant::now() + START_TIMEOUT;
        let port = loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match rx.recv_timeout(left) {
                Ok(line) => {
                    if let Some(rest) = line.split("listening on http://").nth(1) {
                        let addr = rest.split_whitespace().next().unwrap_or("");
                        let port: u16 = addr
                            .rsplit(':')
                            .next()
                            .and_then(|p| p.parse().ok())
                            .ok_or_else(|| format!("cannot parse the address in {line:?}"))?;
                        break port;
                    }
                }
                Err(_) => {
                    let status = self
                        .child
                        .as_mut()
                        .and_then(|c| c.try_wait().ok().flatten());
                    if let Some(status) = status {
                        self.child = None;
                        return Err(format!("fresa serve exited ({status}):\n{}", self.log()));
                    }
                    if Instant::now() >= deadline {
                        self.kill();
                        return Err(format!("no `listening on` line:\n{}", self.log()));
                    }
                    // The channel closed (stderr EOF) before the process was reaped: wait for it.
                    if let Some(c) = self.child.as_mut() {
                        let status = c.wait().map_err(|e| e.to_string())?;
                        self.child = None;
                        return Err(format!("fresa serve exited ({status}):\n{}", self.log()));
                    }
                }
            }
        };
        self.base = format!("http://127.0.0.1:{port}");
        let url = format!("{}/healthz", self.base);
        let deadline = Instant::now() + START_TIMEOUT;
        loop {
            if let Ok(r) = self.http.get(&url).send() {
                if r.status().as_u16() == 200 {
                    return Ok(());
                }
            }
            if Instant::now() >= deadline {
                return Err(format!("/healthz never answered 200:\n{}", self.log()));
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }

    /// SIGKILLs the server (on Unix `Child::kill` is SIGKILL) and reaps it.
    pub fn kill(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }

    /// SIGTERM: the server shuts down cleanly. Waits for it to exit.
    pub fn terminate(&mut self) -> std::process::ExitStatus {
        let mut c = self.child.take().expect("server running");
        send_signal(c.id(), "TERM");
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            if let Some(s) = c.try_wait().expect("try_wait") {
                return s;
            }
            if Instant::now() >= deadline {
                let _ = c.kill();
                let _ = c.wait();
                panic!("server did not exit after SIGTERM:\n{}", self.log());
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }

    /// The server process's id, while it runs.
    pub fn pid(&self) -> Option<u32> {
        self.child.as_ref().map(Child::id)
    }

    /// Replaces the config file (`fresa.toml`); takes effect at the next start.
    pub fn write_config(&self, toml: &str) {
        std::fs::write(self.config_file(), toml).expect("write fresa.toml");
    }

    /// Sends `kill -SIGNAL` (e.g. `"INT"`: Ctrl-C, also under Wine) and returns at once.
    pub fn send_signal(&self, signal: &str) {
        send_signal(self.pid().expect("server running"), signal);
    }

    /// Sends SIGTERM and returns at once (see [`Server::wait_exit`]).
    pub fn send_sigterm(&self) {
        self.send_signal("TERM");
    }

    /// Whether the server process has exited (reaping it if so), without waiting.
    pub fn try_exit_status(&mut self) -> Option<std::process::ExitStatus> {
        let status = self.child.as_mut()?.try_wait().expect("try_wait")?;
        self.child = None;
        Some(status)
    }

    /// Waits (polling) until the process exits and returns its status. On timeout it is killed
    /// and the test fails naming `what`, with the server's log.
    #[track_caller]
    pub fn wait_exit(&mut self, timeout: Duration, what: &str) -> std::process::ExitStatus {
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(s) = self.try_exit_status() {
                return s;
            }
            if Instant::now() >= deadline {
                self.kill();
                panic!(
                    "server did not exit within {timeout:?} ({what}); killed it. Log:\n{}",
                    self.log()
                );
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }

    /// Kills (SIGKILL) and starts again on the same data directory.
    pub fn restart_after_kill(&mut self) {
        self.kill();
        self.spawn()
            .unwrap_or_else(|e| panic!("server did not restart: {e}"));
    }

    pub fn url(&self, path: &str) -> String {
        format!("{}{}", self.base, path)
    }

    /// A request with the server's token (if any).
    pub fn req(&self, method: reqwest::Method, path: &str) -> reqwest::blocking::RequestBuilder {
        let rb = self.http.request(method, self.url(path));
        match &self.token {
            Some(t) => rb.bearer_auth(t),
            None => rb,
        }
    }

    pub fn send(&self, rb: reqwest::blocking::RequestBuilder) -> Resp {
        let r = rb.send().unwrap_or_else(|e| {
            panic!("request failed: {e}\nserver log:\n{}", self.log());
        });
        let status = r.status().as_u16();
        let text = r.text().unwrap_or_default();
        let body = serde_json::from_str(&text).unwrap_or(Value::Null);
        Resp { status, body, text }
    }

    pub fn get(&self, path: &str) -> Resp {
        self.send(self.req(reqwest::Method::GET, path))
    }

    pub fn post(&self, path: &str, body: &Value) -> Resp {
        self.send(self.req(reqwest::Method::POST, path).json(body))
    }

    pub fn post_empty(&self, path: &str) -> Resp {
        self.send(self.req(reqwest::Method::POST, path))
    }

    pub fn put(&self, path: &str, body: &Value) -> Resp {
        self.send(self.req(reqwest::Method::PUT, path).json(body))
    }

    pub fn post_bytes(&self, path: &str, body: impl Into<Vec<u8>>) -> Resp {
        self.send(
            self.req(reqwest::Method::POST, path)
                .header("content-type", "text/plain")
                .body(body.into()),
        )
    }

    /// Creates a machine (`POST /api/v1/machines`), returns its id.
    #[track_caller]
    pub fn create_machine(&self, body: &Value) -> i64 {
        let v = self.post("/api/v1/machines", body).expect(201);
        v["id"].as_i64().expect("machine id")
    }

    /// A sim-machine with an execution log in the test's directory.
    #[track_caller]
    pub fn sim(&self, name: &str, time_scale: f64) -> Sim {
        self.sim_with(name, time_scale, json!({}))
    }

    /// A sim-machine; `extra` is merged into the machine body (e.g. `max_jog_mm`).
    #[track_caller]
    pub fn sim_with(&self, name: &str, time_scale: f64, extra: Value) -> Sim {
        // Backend files must live in the data directory (the server refuses others).
        let log = self.data_dir().join(format!("exec-{name}.log"));
        let mut body = json!({
            "name": name,
            "backend": "sim-machine",
            "config": {"time_scale": time_scale, "execution_log": self.host_path(&log)},
        });
        if let (Some(b), Some(e)) = (body.as_object_mut(), extra.as_object()) {
            for (k, v) in e {
                b.insert(k.clone(), v.clone());
            }
        }
        let id = self.create_machine(&body);
        Sim { id, log }
    }

    #[track_caller]
    pub fn status(&self, machine: i64) -> Value {
        self.get(&format!("/api/v1/machines/{machine}/status"))
            .expect(200)
    }

    /// Waits until the machine reports `state`.
    #[track_caller]
    pub fn wait_machine_state(&self, machine: i64, state: &str, timeout: Duration) -> Value {
        wait_for(timeout, &format!("machine {machine} to be {state}"), || {
            let s = self.status(machine);
            (s["state"] == state).then_some(s)
        })
    }

    /// Polls the machine status until `pred` holds; on timeout panics showing the last status.
    #[track_caller]
    pub fn wait_status(
        &self,
        machine: i64,
        timeout: Duration,
        what: &str,
        mut pred: impl FnMut(&Value) -> bool,
    ) -> Value {
        let deadline = Instant::now() + timeout;
        loop {
            let st = self.status(machine);
            if pred(&st) {
                return st;
            }
            assert!(
                Instant::now() < deadline,
                "timed out after {timeout:?} waiting for machine {machine}: {what}; last status {st}"
            );
            std::thread::sleep(Duration::from_millis(10));
        }
    }

    /// `POST /api/v1/machines/{id}/commands` with `{"command": command, ...extra}`.
    pub fn command(&self, machine: i64, command: &str, extra: Value) -> Resp {
        let mut body = json!({ "command": command });
        if let (Some(b), Some(e)) = (body.as_object_mut(), extra.as_object()) {
            for (k, v) in e {
                b.insert(k.clone(), v.clone());
            }
        }
        self.post(&format!("/api/v1/machines/{machine}/commands"), &body)
    }

    /// `POST /api/v1/machines/{id}/jog` of `distance` mm along `axis` at the default feed.
    pub fn jog(&self, machine: i64, axis: &str, distance: f64) -> Resp {
        self.post(
            &format!("/api/v1/machines/{machine}/jog"),
            &json!({"axis": axis, "distance": distance}),
        )
    }

    /// `POST /api/v1/machines/{id}/mdi` with one line.
    pub fn mdi(&self, machine: i64, line: &str) -> Resp {
        self.post(
            &format!("/api/v1/machines/{machine}/mdi"),
            &json!({ "line": line }),
        )
    }

    /// Waits until a line of the server's log contains `needle`; returns that line.
    #[track_caller]
    pub fn wait_log(&self, timeout: Duration, needle: &str) -> String {
        wait_for(
            timeout,
            &format!("a log line containing {needle:?}"),
            || {
                self.log
                    .lock()
                    .unwrap()
                    .iter()
                    .find(|l| l.contains(needle))
                    .cloned()
            },
        )
    }

    /// Uploads a program and starts it; returns `(job, run)`.
    #[track_caller]
    pub fn upload_and_start(&self, machine: i64, name: &str, program: &str) -> (i64, i64) {
        let job = self.upload(machine, name, program)["id"]
            .as_i64()
            .expect("job id");
        let run = self.job_action(job, "start").expect(200)["run"]["id"]
            .as_i64()
            .expect("run id");
        (job, run)
    }

    /// Names of the `.upload-*.tmp` files (uploads in progress or left behind) in
    /// `DATA_DIR/programs`.
    pub fn upload_temp_files(&self) -> Vec<String> {
        self.program_files()
            .into_iter()
            .filter(|n| n.starts_with(".upload-") && n.ends_with(".tmp"))
            .collect()
    }

    /// Uploads a program as raw body; asserts 201.
    #[track_caller]
    pub fn upload(&self, machine: i64, name: &str, program: impl Into<Vec<u8>>) -> Value {
        self.post_bytes(
            &format!("/api/v1/jobs?machine={machine}&name={name}"),
            program,
        )
        .expect(201)
    }

    /// Asserts that no job was stored (after a rejected upload or request).
    #[track_caller]
    pub fn assert_no_jobs(&self) {
        let jobs = self.get("/api/v1/jobs").expect(200);
        assert!(jobs.as_array().is_some_and(Vec::is_empty), "{jobs}");
    }

    #[track_caller]
    pub fn job(&self, id: i64) -> Value {
        self.get(&format!("/api/v1/jobs/{id}")).expect(200)
    }

    /// `POST /api/v1/jobs/{id}/{action}`.
    pub fn job_action(&self, id: i64, action: &str) -> Resp {
        self.post_empty(&format!("/api/v1/jobs/{id}/{action}"))
    }

    /// Polls the job until `pred` holds; returns it.
    #[track_caller]
    pub fn wait_job(
        &self,
        id: i64,
        timeout: Duration,
        what: &str,
        mut pred: impl FnMut(&Value) -> bool,
    ) -> Value {
        wait_for(timeout, &format!("job {id}: {what}"), || {
            let j = self.job(id);
            pred(&j).then_some(j)
        })
    }

    /// Waits until the job is in `state`; fails early if it ends in another terminal state.
    #[track_caller]
    pub fn wait_job_state(&self, id: i64, state: &str, timeout: Duration) -> Value {
        self.wait_job(id, timeout, &format!("state {state}"), |j| {
            let s = j["state"].as_str().unwrap_or("");
            if s != state && matches!(s, "completed" | "failed" | "cancelled") {
                panic!("job {id} ended {s} while waiting for {state}: {j}");
            }
            s == state
        })
    }

    /// Opens `GET /api/v1/events?{query}`, optionally with `Last-Event-ID`. Returns once the
    /// response headers arrived, i.e. once the server has subscribed this client.
    pub fn events(&self, query: &str, last_event_id: Option<i64>) -> Sse {
        let client = reqwest::blocking::Client::builder()
            .timeout(None)
            .build()
            .expect("sse client");
        let mut rb = client.get(self.url(&format!("/api/v1/events?{query}")));
        if let Some(t) = &self.token {
            rb = rb.bearer_auth(t);
        }
        if let Some(id) = last_event_id {
            rb = rb.header("Last-Event-ID", id.to_string());
        }
        let resp = rb.send().expect("connect to /events");
        assert_eq!(resp.status().as_u16(), 200, "events stream refused");
        Sse::new(resp)
    }

    /// Runs the CLI against this server (`--server` and `--token` added).
    pub fn cli(&self, args: &[&str]) -> Output {
        let mut cmd = fresa_cmd();
        cmd.args(args).arg("--server").arg(&self.base);
        if let Some(t) = &self.token {
            cmd.arg("--token").arg(t);
        }
        cmd.output().expect("run fresa")
    }

    /// `fresa token create` on this server's data directory; returns the secret.
    pub fn create_token(&self, role: &str, name: &str) -> String {
        let out = fresa_cmd()
            .args(["token", "create", "--role", role, "--name", name])
            .arg("--data-dir")
            .arg(self.data_dir())
            .arg("--config")
            .arg(self.config_file())
            .output()
            .expect("run fresa token create");
        assert!(
            out.status.success(),
            "token create failed: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let secret = String::from_utf8(out.stdout).expect("utf-8 secret");
        let secret = secret.trim().to_string();
        assert!(!secret.is_empty() && !secret.contains('\n'), "{secret:?}");
        secret
    }

    /// Names of the files in `DATA_DIR/programs`.
    pub fn program_files(&self) -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(self.programs_dir())
            .map(|d| {
                d.filter_map(|e| e.ok())
                    .map(|e| e.file_name().to_string_lossy().into_owned())
                    .collect()
            })
            .unwrap_or_default();
        v.sort();
        v
    }
}

/// A sim-machine created by a test.
#[derive(Debug, Clone)]
pub struct Sim {
    pub id: i64,
    /// Its execution log.
    pub log: PathBuf,
}

impl Sim {
    /// The execution log as `(run, line)`; torn or unparsable lines are ignored.
    pub fn executed(&self) -> Vec<(i64, i64)> {
        read_exec_log(&self.log)
    }

    /// The lines of `run` in the execution log, in the order they were logged.
    pub fn lines_of(&self, run: i64) -> Vec<i64> {
        self.executed()
            .into_iter()
            .filter(|(r, _)| *r == run)
            .map(|(_, l)| l)
            .collect()
    }

    /// `(line, ms)`: when each line of `run` finished, by the sim's own clock (ms since the
    /// Unix epoch, as it logged them).
    pub fn line_times(&self, run: i64) -> Vec<(i64, u64)> {
        let text = std::fs::read_to_string(&self.log).unwrap_or_default();
        text.lines()
            .filter_map(|l| serde_json::from_str::<Value>(l).ok())
            .filter(|v| v["run"].as_i64() == Some(run))
            .filter_map(|v| Some((v["line"].as_i64()?, v["at_ms"].as_u64()?)))
            .collect()
    }

    /// `(line, [x, y, z, a])`: where the machine was (machine coordinates) when each line of
    /// `run` finished, as the sim logged it.
    pub fn line_positions(&self, run: i64) -> Vec<(i64, [f64; 4])> {
        let text = std::fs::read_to_string(&self.log).unwrap_or_default();
        text.lines()
            .filter_map(|l| serde_json::from_str::<Value>(l).ok())
            .filter(|v| v["run"].as_i64() == Some(run))
            .filter_map(|v| {
                let p = v["pos"].as_array()?;
                let at = |i: usize| p.get(i).and_then(Value::as_f64);
                Some((v["line"].as_i64()?, [at(0)?, at(1)?, at(2)?, at(3)?]))
            })
            .collect()
    }

    /// How many lines of `run` the execution log holds.
    pub fn count_of(&self, run: i64) -> usize {
        self.lines_of(run).len()
    }
}

/// The number of threads of process `pid` (`Threads:` in `/proc/PID/status`).
pub fn thread_count(pid: u32) -> usize {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status"))
        .unwrap_or_else(|e| panic!("cannot read /proc/{pid}/status: {e}"));
    status
        .lines()
        .find_map(|l| l.strip_prefix("Threads:"))
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or_else(|| panic!("no Threads: line in /proc/{pid}/status"))
}

/// The resident set size of process `pid` in KiB (`VmRSS:` in `/proc/PID/status`).
pub fn rss_kib(pid: u32) -> u64 {
    status_kib(pid, "VmRSS")
}

/// utime + stime of `pid`, in clock ticks (100 per second on Linux).
pub fn cpu_ticks(pid: u32) -> u64 {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat"))
        .unwrap_or_else(|e| panic!("cannot read /proc/{pid}/stat: {e}"));
    // Fields after the command name (which may hold spaces) start at ") ".
    let rest = &stat[stat.rfind(") ").unwrap() + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    f[11].parse::<u64>().unwrap() + f[12].parse::<u64>().unwrap()
}

/// A `kB` field of `/proc/PID/status` (`VmRSS`, `RssAnon`, `RssFile`, ...), in KiB.
pub fn status_kib(pid: u32, field: &str) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status"))
        .unwrap_or_else(|e| panic!("cannot read /proc/{pid}/status: {e}"));
    status
        .lines()
        .find_map(|l| l.strip_prefix(field)?.strip_prefix(':'))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .unwrap_or_else(|| panic!("no {field}: line in /proc/{pid}/status"))
}

/// One mapping of `/proc/PID/smaps`: permissions, path (empty for anonymous memory, `[name]`
/// for the stack, heap and vDSO) and its `Name: N kB` fields.
pub struct SmapsMapping {
    pub perms: String,
    pub path: String,
    fields: Vec<(String, u64)>,
}

impl SmapsMapping {
    /// The field `name` (e.g. `"Rss"`), KiB; 0 if absent.
    pub fn kib(&self, name: &str) -> u64 {
        self.fields
            .iter()
            .find(|(n, _)| n == name)
            .map_or(0, |(_, v)| *v)
    }
}

/// The mappings of process `pid`, from `/proc/PID/smaps`.
pub fn smaps(pid: u32) -> Vec<SmapsMapping> {
    let text = std::fs::read_to_string(format!("/proc/{pid}/smaps"))
        .unwrap_or_else(|e| panic!("cannot read /proc/{pid}/smaps: {e}"));
    let mut all: Vec<SmapsMapping> = Vec::new();
    for line in text.lines() {
        let mut fields = line.split_whitespace();
        let first = fields.next().unwrap_or("");
        if let Some(name) = first.strip_suffix(':') {
            // "Name: N kB" (VmFlags and THPeligible do not parse as a number and are skipped).
            let value = fields.next().and_then(|v| v.parse().ok());
            if let (Some(m), Some(v)) = (all.last_mut(), value) {
                m.fields.push((name.to_string(), v));
            }
        } else {
            // "start-end perms offset dev inode [path]": the path may hold blanks.
            let perms = fields.next().unwrap_or("").to_string();
            let path = fields.skip(3).collect::<Vec<_>>().join(" ");
            all.push(SmapsMapping {
                perms,
                path,
                fields: Vec::new(),
            });
        }
    }
    all
}

/// A small deterministic pseudo-random generator (xorshift64*), so a failing randomised test
/// can be replayed from the seed it prints.
#[derive(Debug, Clone)]
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Rng {
        Rng(seed.max(1))
    }

    /// A seed from the clock (printed by the tests that use it).
    pub fn clock_seed() -> u64 {
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos() as u64)
            .unwrap_or(1)
    }

    pub fn next_u64(&mut self) -> u64 {
        let mut x = self.0;
        x ^= x >> 12;
        x ^= x << 25;
        x ^= x >> 27;
        self.0 = x;
        x.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    /// A number in `0..n` (`n` > 0).
    pub fn below(&mut self, n: u64) -> u64 {
        self.next_u64() % n
    }
}

/// Whether a run in `from` may next be in `to`, per the job-run state machine: running <->
/// paused; running|paused -> completed|failed|cancelled|interrupted; failed|interrupted ->
/// running (resume), cancelled, or completed (nothing left to run). Nothing follows completed or
/// cancelled.
pub fn legal_run_transition(from: &str, to: &str) -> bool {
    matches!(
        (from, to),
        ("running", "paused")
            | ("paused", "running")
            | (
                "running" | "paused",
                "completed" | "failed" | "cancelled" | "interrupted"
            )
            | ("failed" | "interrupted", "running" | "cancelled")
            // A resume that finds every line already acknowledged.
            | ("failed" | "interrupted", "completed")
    )
}

pub fn read_exec_log(path: &Path) -> Vec<(i64, i64)> {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    text.lines()
        .filter_map(|l| serde_json::from_str::<Value>(l).ok())
        .filter_map(|v| Some((v["run"].as_i64()?, v["line"].as_i64()?)))
        .collect()
}

/// Asserts that the log holds, for `run`, exactly the lines `1..=lines` once each, in order.
#[track_caller]
pub fn assert_every_line_once(log: &[(i64, i64)], run: i64, lines: i64) {
    let got: Vec<i64> = log
        .iter()
        .filter(|(r, _)| *r == run)
        .map(|(_, l)| *l)
        .collect();
    if got.len() == lines as usize && got.iter().copied().eq(1..=lines) {
        return;
    }
    let mut seen = std::collections::HashMap::new();
    for l in &got {
        *seen.entry(*l).or_insert(0) += 1;
    }
    let twice: Vec<_> = seen
        .iter()
        .filter(|(_, n)| **n > 1)
        .map(|(l, _)| *l)
        .take(10)
        .collect();
    let missing: Vec<_> = (1..=lines)
        .filter(|l| !seen.contains_key(l))
        .take(10)
        .collect();
    let out_of_order = got.windows(2).position(|w| w[1] <= w[0]);
    panic!(
        "run {run}: expected lines 1..={lines} once each in order; got {} entries; \
         repeated (first few): {twice:?}; missing (first few): {missing:?}; \
         first out-of-order index: {out_of_order:?}",
        got.len()
    );
}

/// A program of `lines` lines, each a feed move of `mm` along X (back and forth), at `feed`.
pub fn back_and_forth(lines: usize, mm: f64, feed: f64) -> String {
    let mut s = String::new();
    for i in 1..=lines {
        let x = if i % 2 == 1 { mm } else { 0.0 };
        if i == 1 {
            s.push_str(&format!("G21 G90 G1 X{x} F{feed}\n"));
        } else {
            s.push_str(&format!("G1 X{x}\n"));
        }
    }
    s
}

pub fn sha256_hex(data: &[u8]) -> String {
    use sha2::Digest;
    hex::encode(sha2::Sha256::digest(data))
}

/// One Server-Sent Event.
#[derive(Debug, Clone)]
pub struct SseEvent {
    pub event: String,
    pub id: Option<i64>,
    /// The `data:` payload parsed as JSON (`Null` if it is not JSON).
    pub data: Value,
}

impl SseEvent {
    /// `data.data.job`: the job an event is about.
    pub fn job(&self) -> Option<i64> {
        self.data["data"]["job"].as_i64()
    }
    pub fn state(&self) -> Option<&str> {
        self.data["data"]["state"].as_str()
    }
}

/// An open event stream, parsed on a reader thread.
pub struct Sse {
    rx: mpsc::Receiver<SseEvent>,
}

impl Sse {
    fn new(resp: reqwest::blocking::Response) -> Sse {
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            let reader = BufReader::new(resp);
            let (mut event, mut id, mut data) = (String::new(), None, Vec::<String>::new());
            for line in reader.lines() {
                let Ok(line) = line else { return };
                if line.is_empty() {
                    if !data.is_empty() || !event.is_empty() {
                        let joined = data.join("\n");
                        let ev = SseEvent {
                            event: if event.is_empty() {
                                "message".into()
                            } else {
                                std::mem::take(&mut event)
                            },
                            id: id.take(),
                            data: serde_json::from_str(&joined).unwrap_or(Value::Null),
                        };
                        data.clear();
                        if tx.send(ev).is_err() {
                            return;
                        }
                    }
                    continue;
                }
                if line.starts_with(':') {
                    continue;
                }
                let (field, value) = match line.split_once(':') {
                    Some((f, v)) => (f, v.strip_prefix(' ').unwrap_or(v)),
                    None => (line.as_str(), ""),
                };
                match field {
                    "event" => event = value.to_string(),
                    "id" => id = value.trim().parse().ok(),
                    "data" => data.push(value.to_string()),
                    _ => {}
                }
            }
        });
        Sse { rx }
    }

    /// The next event, or `None` after `timeout` (or when the stream ended).
    pub fn next(&self, timeout: Duration) -> Option<SseEvent> {
        self.rx.recv_timeout(timeout).ok()
    }

    /// Reads events until one matches `pred`; returns all read, the matching one last. Panics
    /// after `timeout` with what was seen.
    #[track_caller]
    pub fn until(
        &self,
        timeout: Duration,
        what: &str,
        mut pred: impl FnMut(&SseEvent) -> bool,
    ) -> Vec<SseEvent> {
        let deadline = Instant::now() + timeout;
        let mut seen = Vec::new();
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.rx.recv_timeout(left) {
                Ok(e) => {
                    let done = pred(&e);
                    seen.push(e);
                    if done {
                        return seen;
                    }
                }
                Err(e) => {
                    let kinds: Vec<String> = seen
                        .iter()
                        .map(|e| format!("{}#{:?} {}", e.event, e.id, e.data["data"]))
                        .collect();
                    panic!("no SSE event {what} ({e:?}); seen: {kinds:#?}");
                }
            }
        }
    }
}

/// Output of a CLI run as text, for assertions.
pub fn output_text(o: &Output) -> String {
    format!(
        "status: {}\nstdout:\n{}\nstderr:\n{}",
        o.status,
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

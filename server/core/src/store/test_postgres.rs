//! A throwaway PostgreSQL server for tests: Debian's `postgresql` binaries, a cluster in a
//! temporary directory, listening on a free loopback port, one per test process; every caller
//! gets a fresh database in it. The server stops when the test process exits (it is started by
//! a shell that holds a pipe from this process and stops it when the pipe closes), and its
//! directory is removed then.
//!
//! A test that stops and restarts its database (an outage under a running job) gets a
//! [`DedicatedPostgres`] of its own instead, so no other test loses the shared one.
//!
//! A missing PostgreSQL is a failure naming the package, never a skipped test.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::io::Write;
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Mutex, OnceLock};
use std::time::{Duration, Instant};

/// The running server: its port, and the shell whose stdin we hold open.
pub struct TestPostgres {
    pub port: u16,
    _keeper: Mutex<Child>,
}

static SERVER: OnceLock<TestPostgres> = OnceLock::new();

/// A new, empty database on the shared test server: its URL (`postgres://fresa@127.0.0.1:P/tN`).
pub async fn fresh_database() -> String {
    let pg = SERVER.get_or_init(start);
    create_database(pg.port).await
}

/// A new, empty database on the server at `port`: its URL.
async fn create_database(port: u16) -> String {
    let name = format!("t{}_{}", std::process::id(), rand::random::<u32>());
    let admin = format!("postgres://fresa@127.0.0.1:{port}/postgres");
    sqlx::any::install_default_drivers();
    // Listening is not ready: "the database system is starting up" until recovery is done.
    let deadline = Instant::now() + Duration::from_secs(60);
    let mut conn = loop {
        match <sqlx::AnyConnection as sqlx::Connection>::connect(&admin).await {
            Ok(c) => break c,
            Err(e) if Instant::now() < deadline => {
                tracing::debug!(error = %e, "test PostgreSQL not ready yet");
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
            Err(e) => panic!("connect to the test PostgreSQL at {admin}: {e}"),
        }
    };
    sqlx::Executor::execute(&mut conn, format!("CREATE DATABASE {name}").as_str())
        .await
        .unwrap_or_else(|e| panic!("create database {name}: {e}"));
    format!("postgres://fresa@127.0.0.1:{port}/{name}")
}

/// A PostgreSQL server of one test's own, which it may stop and start again (same data, same
/// port). Stopped and removed when dropped; stopped in any case when the test process exits.
pub struct DedicatedPostgres {
    pub port: u16,
    dir: PathBuf,
    data: PathBuf,
    keeper: Mutex<Option<Child>>,
}

impl DedicatedPostgres {
    pub fn start() -> DedicatedPostgres {
        let (dir, data) = init_cluster();
        let port = free_port();
        let keeper = launch(&dir, &data, port, false, true);
        DedicatedPostgres {
            port,
            dir,
            data,
            keeper: Mutex::new(Some(keeper)),
        }
    }

    /// A new, empty database on this server: its URL.
    pub async fn fresh_database(&self) -> String {
        create_database(self.port).await
    }

    /// Stops the server the way a crash does (`pg_ctl stop -m immediate`): connections drop at
    /// once, and the next start recovers from the WAL.
    pub fn stop(&self) {
        let out = as_server_user(&binary("pg_ctl"))
            .arg("-D")
            .arg(&self.data)
            .args(["stop", "-m", "immediate", "-w", "-t", "60"])
            .output()
            .unwrap_or_else(|e| panic!("run pg_ctl stop: {e}"));
        assert!(
            out.status.success(),
            "pg_ctl stop failed: {}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
        // Its keeper's shell has nothing left to stop; closing its stdin ends it.
        if let Some(mut k) = self.keeper.lock().unwrap().take() {
            drop(k.stdin.take());
            let _ = k.wait();
        }
    }

    /// Starts the stopped server again on the same port and data; returns once it listens.
    pub fn restart(&self) {
        let mut keeper = self.keeper.lock().unwrap();
        assert!(keeper.is_none(), "the dedicated PostgreSQL is running");
        *keeper = Some(launch(&self.dir, &self.data, self.port, false, true));
    }
}

impl Drop for DedicatedPostgres {
    fn drop(&mut self) {
        if let Ok(mut keeper) = self.keeper.lock() {
            if let Some(mut k) = keeper.take() {
                // Closing stdin: the keeper stops the server and waits for it.
                drop(k.stdin.take());
                let _ = k.wait();
            }
        }
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// Where Debian keeps a PostgreSQL binary (`/usr/lib/postgresql/<version>/bin` is not on PATH).
fn binary(name: &str) -> PathBuf {
    let on_path = std::env::var_os("PATH")
        .into_iter()
        .flat_map(|p| std::env::split_paths(&p).collect::<Vec<_>>())
        .map(|d| d.join(name))
        .find(|p| p.is_file());
    if let Some(p) = on_path {
        return p;
    }
    let mut versions: Vec<PathBuf> = std::fs::read_dir("/usr/lib/postgresql")
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.path().join("bin").join(name))
        .filter(|p| p.is_file())
        .collect();
    versions.sort();
    versions.pop().unwrap_or_else(|| {
        panic!(
            "PostgreSQL's `{name}` was not found (on PATH or in /usr/lib/postgresql/*/bin): the \
             PostgreSQL store tests need Debian's postgresql package: apt-get install postgresql"
        )
    })
}

fn is_root() -> bool {
    Command::new("id")
        .arg("-u")
        .output()
        .map(|o| String::from_utf8_lossy(&o.stdout).trim() == "0")
        .unwrap_or(false)
}

/// `cmd` as the `postgres` user when we are root (PostgreSQL refuses to run as root).
fn as_server_user(program: &Path) -> Command {
    if is_root() {
        let mut c = Command::new("runuser");
        c.args(["-u", "postgres", "--"]).arg(program);
        c
    } else {
        Command::new(program)
    }
}

fn start() -> TestPostgres {
    let (dir, data) = init_cluster();
    let port = free_port();
    let keeper = launch(&dir, &data, port, true, false);
    TestPostgres {
        port,
        _keeper: Mutex::new(keeper),
    }
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .unwrap()
}

/// A new cluster in a temporary directory: (the directory, its data directory).
fn init_cluster() -> (PathBuf, PathBuf) {
    let initdb = binary("initdb");
    let dir = std::env::temp_dir().join(format!(
        "fresa-pg-{}-{}",
        std::process::id(),
        rand::random::<u32>()
    ));
    std::fs::create_dir_all(&dir).unwrap();
    if is_root() {
        let ok = Command::new("chown")
            .args(["postgres:postgres"])
            .arg(&dir)
            .status()
            .map(|s| s.success())
            .unwrap_or(false);
        assert!(
            ok,
            "chown {} to the postgres user (does the user exist? apt-get install postgresql)",
            dir.display()
        );
    }
    let data = dir.join("data");
    let out = as_server_user(&initdb)
        .arg("-D")
        .arg(&data)
        .args(["-U", "fresa", "--auth=trust", "-E", "UTF8", "--no-sync"])
        .output()
        .unwrap_or_else(|e| panic!("run {}: {e}", initdb.display()));
    assert!(
        out.status.success(),
        "initdb failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    (dir, data)
}

/// Starts the server on `data` and returns once it listens on `port`. It runs under a keeper
/// shell that holds a pipe from this process: when the pipe closes (the returned child's stdin
/// dropped, or this process exiting however it exits) the keeper stops the server fast, and
/// removes `dir` if `remove_dir`.
/// `durable`: commits are on disk (the OS's) before they are answered, so a crash-like stop
/// loses none; the shared server trades that for speed.
fn launch(dir: &Path, data: &Path, port: u16, remove_dir: bool, durable: bool) -> Child {
    let postgres = binary("postgres");
    // The shell starts the server, then waits for its stdin to close and stops the server.
    let script = format!(
        "{runas} '{pg}' -D '{data}' -p {port} -k '{dir}' -c listen_addresses=127.0.0.1 \
         -c fsync=off -c synchronous_commit={sync} -c full_page_writes=off -c max_connections=200 \
         >>'{dir}/log' 2>&1 & pid=$!; cat >/dev/null; kill -INT $pid; wait $pid; {cleanup}",
        // setpriv execs the server itself, so `$!` is the server's pid (runuser would stay in
        // between and not pass the signal on).
        runas = if is_root() {
            "setpriv --reuid=postgres --regid=postgres --init-groups"
        } else {
            ""
        },
        pg = postgres.display(),
        sync = if durable { "on" } else { "off" },
        data = data.display(),
        dir = dir.display(),
        cleanup = if remove_dir {
            format!("rm -rf '{}'", dir.display())
        } else {
            String::new()
        },
    );
    let mut keeper = Command::new("sh")
        .arg("-c")
        .arg(&script)
        .stdin(Stdio::piped())
        // Not the test's own output: whoever reads it would wait for the keeper too.
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("start the test PostgreSQL");
    // Keep the write end open for the life of the process; never written to.
    if let Some(stdin) = keeper.stdin.as_mut() {
        let _ = stdin.flush();
    }
    let deadline = Instant::now() + Duration::from_secs(60);
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(
            Instant::now() < deadline,
            "the test PostgreSQL did not start listening on port {port}; its log: {}",
            std::fs::read_to_string(dir.join("log")).unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    keeper
}

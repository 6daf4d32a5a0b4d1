//! Running the cross-built Windows programs (`fresa.exe`, `fresa-mach3-agent.exe`, the
//! `fresa_*.dll` plugins) under Wine, for `tests/backends/wine.rs`.
//!
//! The programs are built by `tests/run` (`cargo build --workspace --target
//! x86_64-pc-windows-gnu`) before `cargo test`; a test fails naming that command when they are
//! missing, and names the Debian package when `wine` or the MinGW compiler is. The Wine prefix
//! lives in `target/wine-prefix`, so its slow first start (wineboot) happens once per checkout.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

pub const WINDOWS_TARGET: &str = "x86_64-pc-windows-gnu";
/// What builds the programs the Wine tests run.
pub const BUILD_COMMAND: &str = "cargo build --workspace --target x86_64-pc-windows-gnu";

/// How long a fresh Wine prefix may take to set itself up.
const WINEBOOT_TIMEOUT: Duration = Duration::from_secs(300);

/// `<target>/x86_64-pc-windows-gnu/<profile>`, checked to hold the programs the tests run.
pub fn windows_bin_dir() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let profile = crate::profile_dir();
        let dir = profile
            .parent()
            .expect("profile dir has a parent")
            .join(WINDOWS_TARGET)
            .join(profile.file_name().expect("profile dir has a name"));
        for f in [
            "fresa.exe",
            "fresa-mach3-agent.exe",
            "fresa_sim_machine.dll",
            "fresa_mach3_oem.dll",
        ] {
            assert!(
                dir.join(f).is_file(),
                "{} is missing: build the Windows programs first with `{BUILD_COMMAND}{}` \
                 (tests/run does)",
                dir.join(f).display(),
                if cfg!(debug_assertions) {
                    ""
                } else {
                    " --release"
                }
            );
        }
        dir
    })
}

/// Runs `cmd` to completion within `timeout` (polling; killed and a panic naming `what` past
/// it) and returns its exit status and its stdout and stderr together. Panics with
/// `install_hint` when it cannot start.
pub fn output_within(
    mut cmd: Command,
    timeout: Duration,
    what: &str,
    install_hint: &str,
) -> (std::process::ExitStatus, String) {
    let out = tempfile::NamedTempFile::new().expect("temp file");
    let mut child = cmd
        .stdin(Stdio::null())
        .stdout(out.reopen().expect("reopen temp file"))
        .stderr(out.reopen().expect("reopen temp file"))
        .spawn()
        .unwrap_or_else(|e| panic!("cannot run {what} ({e}): {install_hint}"));
    let deadline = Instant::now() + timeout;
    let status = loop {
        if let Some(s) = child.try_wait().expect("try_wait") {
            break s;
        }
        if Instant::now() >= deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!("{what} did not finish within {timeout:?}");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    (
        status,
        std::fs::read_to_string(out.path()).unwrap_or_default(),
    )
}

/// [`output_within`], failing the test unless it succeeds.
fn run(cmd: Command, timeout: Duration, what: &str, install_hint: &str) -> String {
    let (status, text) = output_within(cmd, timeout, what, install_hint);
    assert!(
        status.success(),
        "{what} failed ({status}): {install_hint}\n{text}"
    );
    text
}

/// The Wine prefix the tests use (`<target>/wine-prefix`), set up on first use.
pub fn prefix() -> &'static Path {
    static PREFIX: OnceLock<PathBuf> = OnceLock::new();
    PREFIX.get_or_init(|| set_up("wine-prefix"))
}

/// A prefix of its own for the service test (`<target>/wine-prefix-service`): Wine starts an
/// installed automatic service whenever a prefix boots, which must not touch the other tests.
pub fn service_prefix() -> &'static Path {
    static PREFIX: OnceLock<PathBuf> = OnceLock::new();
    PREFIX.get_or_init(|| set_up("wine-prefix-service"))
}

/// `<target>/NAME`, set up once: `wineboot`, and the `bcryptprimitives.dll` stand-in where Wine
/// has none (`tests/fixtures/wine/`).
fn set_up(name: &str) -> PathBuf {
    let target = crate::profile_dir()
        .parent()
        .expect("profile dir has a parent")
        .to_path_buf();
    let prefix = target.join(name);
    if !prefix.join("system.reg").is_file() {
        let mut cmd = Command::new("wine");
        cmd.args(["wineboot", "--init"])
            .env("WINEPREFIX", &prefix)
            .env("WINEDEBUG", "-all");
        run(
            cmd,
            WINEBOOT_TIMEOUT,
            "`wine wineboot --init`",
            "install Wine with `apt-get install wine wine64`",
        );
        // wineboot returns while the new prefix is still settling (its services restart);
        // the prefix is ready once its server has exited.
        let mut cmd = Command::new("wineserver");
        cmd.arg("-w").env("WINEPREFIX", &prefix);
        run(
            cmd,
            WINEBOOT_TIMEOUT,
            "`wineserver -w`",
            "install Wine with `apt-get install wine wine64`",
        );
    }
    let system32 = prefix.join("drive_c/windows/system32");
    let shim = system32.join("bcryptprimitives.dll");
    if !shim.is_file() {
        let src = crate::workspace_root().join("tests/fixtures/wine/bcryptprimitives.c");
        // Built beside and renamed into place: another test process may be doing the same.
        let tmp = system32.join(format!("bcryptprimitives.{}.tmp", std::process::id()));
        let mut cmd = Command::new("x86_64-w64-mingw32-gcc");
        cmd.args(["-shared", "-O2", "-Wall", "-Werror", "-o"])
            .arg(&tmp)
            .arg(&src)
            .arg("-ladvapi32");
        run(
            cmd,
            Duration::from_secs(120),
            "the MinGW C compiler x86_64-w64-mingw32-gcc",
            "install it with `apt-get install mingw-w64`",
        );
        std::fs::rename(&tmp, &shim).expect("move bcryptprimitives.dll into place");
    }
    prefix
}

/// `wine EXE` in the tests' prefix, with no `FRESA_*` variable inherited.
pub fn command(exe: &Path) -> Command {
    command_in(prefix(), exe)
}

/// `wine EXE` in `prefix`, with no `FRESA_*` variable inherited.
pub fn command_in(prefix: &Path, exe: &Path) -> Command {
    let mut cmd = Command::new("wine");
    cmd.arg(exe)
        .env("WINEPREFIX", prefix)
        .env("WINEDEBUG", "-all")
        .stdin(Stdio::null());
    for (k, _) in std::env::vars_os() {
        if k.to_string_lossy().starts_with("FRESA_") {
            cmd.env_remove(k);
        }
    }
    cmd
}

/// A Linux path as the Windows program sees it (Wine's drive `Z:` is `/`).
pub fn path(p: &Path) -> String {
    format!("Z:{}", p.display())
}

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
/// The 32-bit Windows 7 agent's target, and what builds it.
pub const WIN7_TARGET: &str = "i686-win7-windows-gnu";
pub const WIN7_BUILD_COMMAND: &str = "plugins/mach3-oem/build-win7-agent";
/// The loaders Debian's `wine32:i386` and `wine64` install. Each program is started by its own
/// loader, not through `/usr/bin/wine`: that script picks the 32-bit loader whenever `wine32` is
/// installed, which starts a 64-bit program as a second process, so the child a test holds
/// (and signals or kills) would not be the program.
const WINE32_LOADER: &str = "/usr/lib/wine/wine";
const WINE64_LOADER: &str = "/usr/lib/wine/wine64";

/// How long a fresh Wine prefix may take to set itself up.
const WINEBOOT_TIMEOUT: Duration = Duration::from_secs(300);

/// `<target>/<triple>/<profile>`: where cargo puts what it builds for `triple` in this profile.
fn cross_profile_dir(triple: &str) -> PathBuf {
    let profile = crate::profile_dir();
    profile
        .parent()
        .expect("profile dir has a parent")
        .join(triple)
        .join(profile.file_name().expect("profile dir has a name"))
}

/// `<target>/x86_64-pc-windows-gnu/<profile>`, checked to hold the programs the tests run.
pub fn windows_bin_dir() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir = cross_profile_dir(WINDOWS_TARGET);
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

/// `<target>/i686-win7-windows-gnu/<profile>/fresa-mach3-agent.exe`, checked to exist.
pub fn win7_agent_exe() -> &'static Path {
    static EXE: OnceLock<PathBuf> = OnceLock::new();
    EXE.get_or_init(|| {
        let exe = cross_profile_dir(WIN7_TARGET).join("fresa-mach3-agent.exe");
        assert!(
            exe.is_file(),
            "{} is missing: build it first with `{WIN7_BUILD_COMMAND}{}` (tests/run does)",
            exe.display(),
            if cfg!(debug_assertions) {
                ""
            } else {
                " --release"
            }
        );
        exe
    })
}

/// `wine EXE` for a 32-bit program, in the tests' (WoW64) prefix; fails naming the package
/// when 32-bit Wine is missing.
pub fn command32(exe: &Path) -> Command {
    assert!(
        Path::new(WINE32_LOADER).is_file(),
        "{WINE32_LOADER} is missing: 32-bit programs need Debian's 32-bit Wine \
         (`dpkg --add-architecture i386 && apt-get update && apt-get install wine32:i386`; \
         .ci/install-deps does)"
    );
    loader_command(WINE32_LOADER, prefix(), exe)
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
    // A prefix made before 32-bit Wine was installed has an empty `syswow64`, and 32-bit
    // programs then die at once ("could not load kernel32.dll"); `wineboot --update` does not
    // fill it, so such a prefix is made again.
    let lacks_32_bit = Path::new(WINE32_LOADER).is_file()
        && prefix.join("system.reg").is_file()
        && !prefix
            .join("drive_c/windows/syswow64/kernel32.dll")
            .is_file();
    if lacks_32_bit {
        std::fs::remove_dir_all(&prefix).expect("remove a Wine prefix made without 32-bit Wine");
    }
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

/// `wine EXE` for a 64-bit program in the tests' prefix, with no `FRESA_*` variable inherited.
pub fn command(exe: &Path) -> Command {
    command_in(prefix(), exe)
}

/// `wine EXE` for a 64-bit program in `prefix`, with no `FRESA_*` variable inherited.
pub fn command_in(prefix: &Path, exe: &Path) -> Command {
    assert!(
        Path::new(WINE64_LOADER).is_file(),
        "{WINE64_LOADER} is missing: install Wine with `apt-get install wine wine64`"
    );
    loader_command(WINE64_LOADER, prefix, exe)
}

fn loader_command(loader: &str, prefix: &Path, exe: &Path) -> Command {
    let mut cmd = Command::new(loader);
    cmd.arg(exe)
        .env("WINELOADER", loader)
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

/// What a Windows program's PE headers say about where it can load.
#[derive(Debug)]
pub struct PeFacts {
    /// PE32 (32-bit), not PE32+.
    pub pe32: bool,
    /// `IMAGE_FILE_MACHINE_*` (0x14c is i386).
    pub machine: u16,
    /// The loader refuses a program whose subsystem version is above the running Windows.
    pub subsystem_version: (u16, u16),
    pub os_version: (u16, u16),
    /// Every imported function (ordinary and delay-loaded) as `dll!name`, DLL in lower case,
    /// an import by ordinal as `dll!#N`.
    pub imports: Vec<String>,
}

/// Reads `exe`'s PE headers and import tables (32- or 64-bit).
pub fn pe_facts(exe: &Path) -> PeFacts {
    use object::pe::{ImageNtHeaders32, ImageNtHeaders64};
    use object::read::pe::{ImageNtHeaders, ImageOptionalHeader, PeFile};
    use object::LittleEndian as LE;

    fn import_name(dll: &str, import: object::read::pe::Import<'_>) -> String {
        match import {
            object::read::pe::Import::Name(_, name) => {
                format!("{dll}!{}", String::from_utf8_lossy(name))
            }
            object::read::pe::Import::Ordinal(n) => format!("{dll}!#{n}"),
        }
    }

    fn read<H: ImageNtHeaders>(data: &[u8], pe32: bool) -> object::Result<PeFacts> {
        let file = PeFile::<H>::parse(data)?;
        let nt = file.nt_headers();
        let opt = nt.optional_header();
        let mut imports = Vec::new();
        if let Some(table) = file.import_table()? {
            let mut descriptors = table.descriptors()?;
            while let Some(d) = descriptors.next()? {
                let dll = String::from_utf8_lossy(table.name(d.name.get(LE))?).to_lowercase();
                let first = match d.original_first_thunk.get(LE) {
                    0 => d.first_thunk.get(LE),
                    t => t,
                };
                let mut thunks = table.thunks(first)?;
                while let Some(thunk) = thunks.next::<H>()? {
                    imports.push(import_name(&dll, table.import::<H>(thunk)?));
                }
            }
        }
        if let Some(table) = file
            .data_directories()
            .delay_load_import_table(data, &file.section_table())?
        {
            let mut descriptors = table.descriptors()?;
            while let Some(d) = descriptors.next()? {
                let dll =
                    String::from_utf8_lossy(table.name(d.dll_name_rva.get(LE))?).to_lowercase();
                let mut thunks = table.thunks(d.import_name_table_rva.get(LE))?;
                while let Some(thunk) = thunks.next::<H>()? {
                    imports.push(import_name(&dll, table.import::<H>(thunk)?));
                }
            }
        }
        imports.sort();
        imports.dedup();
        Ok(PeFacts {
            pe32,
            machine: nt.file_header().machine.get(LE),
            subsystem_version: (opt.major_subsystem_version(), opt.minor_subsystem_version()),
            os_version: (
                opt.major_operating_system_version(),
                opt.minor_operating_system_version(),
            ),
            imports,
        })
    }

    let data = std::fs::read(exe).unwrap_or_else(|e| panic!("read {}: {e}", exe.display()));
    let kind = object::FileKind::parse(&data[..])
        .unwrap_or_else(|e| panic!("{} is not an executable: {e}", exe.display()));
    let facts = match kind {
        object::FileKind::Pe32 => read::<ImageNtHeaders32>(&data, true),
        object::FileKind::Pe64 => read::<ImageNtHeaders64>(&data, false),
        other => panic!("{} is not a PE program but {other:?}", exe.display()),
    };
    facts.unwrap_or_else(|e| panic!("{}: bad PE headers: {e}", exe.display()))
}

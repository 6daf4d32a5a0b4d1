//! Release builds for x86-64 Linux link the functions in `link/hot-functions.txt` first in the
//! daemon's code, so the pages an idle server keeps mapped are few (see `link/README.md`).

use std::env;

fn main() {
    println!("cargo:rerun-if-changed=link/hot-functions.txt");
    println!("cargo:rerun-if-env-changed=FRESA_NO_LINK_ORDER");
    println!("cargo:rerun-if-env-changed=CARGO_TARGET_X86_64_UNKNOWN_LINUX_GNU_LINKER");
    let target = env::var("TARGET").unwrap_or_default();
    let release = env::var("PROFILE").as_deref() == Ok("release");
    // FRESA_NO_LINK_ORDER: for before-and-after measurements, or a linker without the option.
    let wanted = env::var_os("FRESA_NO_LINK_ORDER").is_none();
    if release && wanted && target == "x86_64-unknown-linux-gnu" && rust_lld_links() {
        let dir = env::var("CARGO_MANIFEST_DIR").unwrap_or_default();
        println!(
            "cargo:rustc-link-arg-bin=fresa=-Wl,--symbol-ordering-file={dir}/link/hot-functions.txt"
        );
        // Names recorded before a rename are not in the binary: skipped without a word.
        println!("cargo:rustc-link-arg-bin=fresa=-Wl,--no-warn-symbol-ordering");
    }
}

/// Whether the binary is linked by rust-lld, which reads an ordering file (GNU ld does not):
/// this target's default linker since Rust 1.90, unless a linker is chosen by hand.
fn rust_lld_links() -> bool {
    let flags = env::var("CARGO_ENCODED_RUSTFLAGS").unwrap_or_default();
    // `-C linker=…`, `-C linker-features=…`, `-C link-arg=-fuse-ld=…`: chosen by hand.
    if env::var_os("CARGO_TARGET_X86_64_UNKNOWN_LINUX_GNU_LINKER").is_some()
        || flags.contains("linker")
        || flags.contains("fuse-ld")
    {
        return false;
    }
    let rustc = env::var("RUSTC").unwrap_or_else(|_| "rustc".into());
    let Ok(out) = std::process::Command::new(rustc).arg("-vV").output() else {
        return false;
    };
    // "release: 1.95.0" (or "1.96.0-beta.3", "1.97.0-nightly").
    let text = String::from_utf8_lossy(&out.stdout);
    let Some(release) = text.lines().find_map(|l| l.strip_prefix("release: ")) else {
        return false;
    };
    let mut numbers = release
        .split(['.', '-'])
        .map(|n| n.parse::<u32>().unwrap_or(0));
    let version = (numbers.next().unwrap_or(0), numbers.next().unwrap_or(0));
    version >= (1, 90)
}

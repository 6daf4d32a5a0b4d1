//! Release builds for x86-64 Linux link the functions in `link/hot-functions.txt` first in the
//! daemon's code, so the pages an idle server keeps mapped are few (see `link/README.md`).

fn main() {
    println!("cargo:rerun-if-changed=link/hot-functions.txt");
    println!("cargo:rerun-if-env-changed=FRESA_NO_LINK_ORDER");
    let target = std::env::var("TARGET").unwrap_or_default();
    let release = std::env::var("PROFILE").as_deref() == Ok("release");
    // rust-lld is this target's default linker; GNU ld has no ordering file, so a build linked
    // with it sets FRESA_NO_LINK_ORDER (as does a before-and-after measurement).
    let wanted = std::env::var_os("FRESA_NO_LINK_ORDER").is_none();
    if release && wanted && target == "x86_64-unknown-linux-gnu" {
        let dir = std::env::var("CARGO_MANIFEST_DIR").unwrap_or_default();
        println!(
            "cargo:rustc-link-arg-bin=fresa=-Wl,--symbol-ordering-file={dir}/link/hot-functions.txt"
        );
        // Names recorded before a rename are not in the binary: skipped without a word.
        println!("cargo:rustc-link-arg-bin=fresa=-Wl,--no-warn-symbol-ordering");
    }
}

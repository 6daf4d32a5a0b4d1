// The target triple is baked into every plugin descriptor so the host can refuse a library built
// for another platform with a clear message instead of crashing on a bad call.
fn main() {
    let target = std::env::var("TARGET").unwrap_or_else(|_| "unknown".to_string());
    println!("cargo:rustc-env=FRESA_BUILD_TARGET={target}");
    println!("cargo:rerun-if-changed=build.rs");
}

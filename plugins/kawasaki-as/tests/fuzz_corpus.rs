//! Replays the saved fuzz inputs through the checks of the `replies` fuzz target
//! (`fuzz/check.rs`, the same function the target calls), so an input that once found a bug
//! keeps being checked by `cargo test` on stable Rust: `fuzz/corpus/replies` (the minimised corpus)
//! and `fuzz/regressions` (inputs that crashed, named after what they found).
#![allow(clippy::unwrap_used, clippy::expect_used)]

#[path = "../fuzz/check.rs"]
mod check;

use std::path::Path;

#[test]
fn the_saved_fuzz_inputs_still_pass() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz");
    let mut n = 0;
    for dir in ["corpus/replies", "regressions"] {
        let Ok(entries) = std::fs::read_dir(root.join(dir)) else {
            continue;
        };
        let mut paths: Vec<_> = entries.map(|e| e.unwrap().path()).collect();
        paths.sort();
        for path in paths
            .into_iter()
            .filter(|p| p.is_file() && !p.file_name().unwrap().to_string_lossy().starts_with('.'))
        {
            let data = std::fs::read(&path).unwrap();
            let name = path.display().to_string();
            if let Err(e) = std::panic::catch_unwind(|| check::replies(&data)) {
                panic!("{name} fails the Kawasaki reply and command parsers's fuzz checks: {e:?}");
            }
            n += 1;
        }
    }
    assert!(n > 0, "no saved fuzz inputs under {}", root.display());
}

/// The fuzzer's finding of 2026-11-30: `0,SPEED,2E-55` parsed as a positive speed, but
/// `V1Cmd::encode` writes six decimals (`0.000000`), which the robot side refuses. Fixed: the
/// parser refuses speeds under the wire's resolution and the config refuses speeds under
/// 0.01 mm/s, naming the key.
#[test]
fn known_findings_are_fixed() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/findings");
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        check::replies(&std::fs::read(&path).unwrap());
    }
}

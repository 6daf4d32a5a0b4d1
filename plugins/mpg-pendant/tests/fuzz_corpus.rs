//! Replays the saved fuzz inputs through the checks of the `codec` fuzz target
//! (`fuzz/check.rs`, the same function the target calls), so an input that once found a bug
//! keeps being checked by `cargo test` on stable Rust: `fuzz/corpus/codec` (the minimised corpus)
//! and `fuzz/regressions` (inputs that crashed, named after what they found).
#![allow(clippy::unwrap_used, clippy::expect_used)]

#[path = "../fuzz/check.rs"]
mod check;

use std::path::Path;

#[test]
fn the_saved_fuzz_inputs_still_pass() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz");
    let mut n = 0;
    for dir in ["corpus/codec", "regressions"] {
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
            if let Err(e) = std::panic::catch_unwind(|| check::codec(&data)) {
                panic!("{name} fails the pendant frame decoder's fuzz checks: {e:?}");
            }
            n += 1;
        }
    }
    assert!(n > 0, "no saved fuzz inputs under {}", root.display());
}

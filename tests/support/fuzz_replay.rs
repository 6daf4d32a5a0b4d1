//! Replays a crate's saved fuzz inputs through its fuzz target's check function, so an input
//! that once found a bug keeps being checked by `cargo test` on stable Rust:
//! `fuzz/corpus/<target>` (the minimised corpus), `fuzz/regressions/<target>` and the files
//! directly in `fuzz/regressions` (inputs that crashed, named after what they found; the flat
//! ones are replayed through every target of the crate). Included with `#[path]` by each
//! crate's `tests/fuzz_corpus.rs`.

use std::path::Path;

/// Runs `check` on every saved input of `target` under `<crate>/fuzz`; `what` names the code
/// under test in a failure.
pub fn replay(crate_dir: &str, target: &str, what: &str, check: fn(&[u8])) {
    let root = Path::new(crate_dir).join("fuzz");
    let mut n = 0;
    for dir in [
        format!("corpus/{target}"),
        format!("regressions/{target}"),
        "regressions".to_string(),
    ] {
        let Ok(entries) = std::fs::read_dir(root.join(dir)) else {
            continue;
        };
        let mut paths: Vec<_> = entries.filter_map(|e| e.ok().map(|e| e.path())).collect();
        paths.sort();
        for path in paths.into_iter().filter(|p| {
            p.is_file()
                && !p
                    .file_name()
                    .is_some_and(|n| n.to_string_lossy().starts_with('.'))
        }) {
            let data = std::fs::read(&path)
                .unwrap_or_else(|e| panic!("cannot read {}: {e}", path.display()));
            if let Err(e) = std::panic::catch_unwind(|| check(&data)) {
                panic!("{} fails {what}'s fuzz checks: {e:?}", path.display());
            }
            n += 1;
        }
    }
    assert!(n > 0, "no saved fuzz inputs under {}", root.display());
}

//! Replays the saved fuzz inputs of the `replies` fuzz target (see `tests/support/fuzz_replay.rs`).
#![allow(clippy::unwrap_used, clippy::expect_used)]

#[path = "../fuzz/check.rs"]
mod check;
#[path = "../../../tests/support/fuzz_replay.rs"]
mod fuzz_replay;

use std::path::Path;

#[test]
fn the_saved_fuzz_inputs_still_pass() {
    fuzz_replay::replay(
        env!("CARGO_MANIFEST_DIR"),
        "replies",
        "the Kawasaki reply and command parsers",
        check::replies,
    );
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

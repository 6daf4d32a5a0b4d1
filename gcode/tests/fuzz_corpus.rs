//! Replays the saved fuzz inputs of the `interp` fuzz target (see `tests/support/fuzz_replay.rs`).
#![allow(clippy::unwrap_used, clippy::expect_used)]

#[path = "../fuzz/check.rs"]
mod check;
#[path = "../../tests/support/fuzz_replay.rs"]
mod fuzz_replay;

#[test]
fn the_saved_fuzz_inputs_still_pass() {
    fuzz_replay::replay(
        env!("CARGO_MANIFEST_DIR"),
        "interp",
        "the G-code lexer, interpreter, lineariser and analysis",
        check::interp,
    );
}

//! Replays the saved fuzz inputs of the `codec` fuzz target (see `tests/support/fuzz_replay.rs`).
#![allow(clippy::unwrap_used, clippy::expect_used)]

#[path = "../fuzz/check.rs"]
mod check;
#[path = "../../../tests/support/fuzz_replay.rs"]
mod fuzz_replay;

#[test]
fn the_saved_fuzz_inputs_still_pass() {
    fuzz_replay::replay(
        env!("CARGO_MANIFEST_DIR"),
        "codec",
        "the pendant frame decoder",
        check::codec,
    );
}

#[test]
fn the_saved_upload_fuzz_inputs_still_pass() {
    fuzz_replay::replay(
        env!("CARGO_MANIFEST_DIR"),
        "upload",
        "the pendant decoder and the G-code analysis of what it uploads",
        check::upload,
    );
}

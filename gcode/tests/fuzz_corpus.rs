//! Replays the saved fuzz inputs of the `interp` and `grammar` fuzz targets (see
//! `tests/support/fuzz_replay.rs`).
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

#[test]
fn the_saved_grammar_fuzz_inputs_still_pass() {
    fuzz_replay::replay(
        env!("CARGO_MANIFEST_DIR"),
        "grammar",
        "the G-code reader on generated programs (deep nests, huge numbers), the lineariser, \
         the analysis and the toolpath preview",
        check::grammar,
    );
}

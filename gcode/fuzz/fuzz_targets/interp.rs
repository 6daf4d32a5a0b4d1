//! Arbitrary bytes as a G-code program through the lexer, the interpreter, the arc
//! lineariser and the analysis. The checks are in `../check.rs`, shared with the corpus
//! replay test `gcode/tests/fuzz_corpus.rs`.
#![no_main]

#[path = "../check.rs"]
mod check;

libfuzzer_sys::fuzz_target!(|data: &[u8]| check::interp_within(
    data,
    Some(check::budget::FUZZ_CPU_BUDGET)
));

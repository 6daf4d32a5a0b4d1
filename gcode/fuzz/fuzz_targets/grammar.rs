//! The fuzzer's bytes as choices in a small G-code grammar (`../grammar.rs`): deep nests, huge
//! numbers, values on every limit, long repeats, through the lexer, the interpreter, the arc
//! lineariser, the analysis and the toolpath preview. The checks are in `../check.rs`, shared
//! with the corpus replay test `gcode/tests/fuzz_corpus.rs`.
#![no_main]

#[path = "../check.rs"]
mod check;

libfuzzer_sys::fuzz_target!(|data: &[u8]| check::grammar_within(
    data,
    Some(check::budget::FUZZ_CPU_BUDGET)
));

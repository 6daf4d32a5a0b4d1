//! A pendant session from the fuzzer's bytes (frames, uploads of generated G-code that nests
//! deep and holds huge numbers, garbage, any read boundaries) through the frame decoder and,
//! for each completed upload, the G-code analysis the core runs on it. The checks are in
//! `../check.rs`, shared with the corpus replay test `plugins/mpg-pendant/tests/fuzz_corpus.rs`.
#![no_main]

#[path = "../check.rs"]
mod check;

libfuzzer_sys::fuzz_target!(|data: &[u8]| check::upload_within(
    data,
    Some(check::budget::FUZZ_CPU_BUDGET)
));

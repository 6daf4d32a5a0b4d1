//! Arbitrary bytes, cut into arbitrary reads, through the frame decoder. The checks are in
//! `../check.rs`, shared with the corpus replay test `plugins/mpg-pendant/tests/fuzz_corpus.rs`.
#![no_main]

#[path = "../check.rs"]
mod check;

libfuzzer_sys::fuzz_target!(|data: &[u8]| check::codec(data));

//! Arbitrary bytes as what the robot sends (legacy stream, cut into reads, and fresa-v1
//! lines) and as commands the robot side parses. The checks are in `../check.rs`, shared with
//! the corpus replay test `plugins/kawasaki-as/tests/fuzz_corpus.rs`.
#![no_main]

#[path = "../check.rs"]
mod check;

libfuzzer_sys::fuzz_target!(|data: &[u8]| check::replies(data));

//! Arbitrary bytes as the agent protocol's JSON-lines stream, decoded as each side does. The
//! checks are in `../check.rs`, shared with the corpus replay test
//! `plugins/mach3-oem/tests/fuzz_corpus.rs`.
#![no_main]

#[path = "../check.rs"]
mod check;

libfuzzer_sys::fuzz_target!(|data: &[u8]| check::protocol(data));

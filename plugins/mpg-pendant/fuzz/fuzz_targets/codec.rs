//! Feeds arbitrary bytes, cut into arbitrary reads, to the frame decoder: it must never panic,
//! every frame it yields must re-encode to exactly 53 bytes that parse back to the same frame,
//! and the same bytes in one read must give the same frames outside an upload.
#![no_main]

use fresa_mpg_pendant::codec::{Decoded, Decoder, Frame, FRAME_LEN};
use libfuzzer_sys::fuzz_target;

fn frames(chunks: &[&[u8]]) -> Vec<Frame> {
    let mut d = Decoder::new();
    let mut out = Vec::new();
    for c in chunks {
        d.push(c);
        while let Some(x) = d.pop() {
            if let Decoded::Frame(f) = x {
                out.push(f);
            }
        }
    }
    out
}

fuzz_target!(|data: &[u8]| {
    let Some((&cut, data)) = data.split_first() else { return };
    let at = (cut as usize * data.len()) / 256;
    let split = frames(&[&data[..at], &data[at..]]);
    for f in &split {
        let bytes = f.encode();
        assert_eq!(bytes.len(), FRAME_LEN);
        assert_eq!(Frame::parse(&bytes).as_ref(), Ok(f));
    }
    // Read boundaries only matter inside uploads (they delimit raw lines).
    if !data.windows(3).any(|w| w == b"N03") {
        assert_eq!(frames(&[data]), split);
    }
});

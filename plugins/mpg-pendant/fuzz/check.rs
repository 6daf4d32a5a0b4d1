//! What the `codec` fuzz target checks for one input. Shared (by `#[path]`) between the fuzz
//! target and the replay test `plugins/mpg-pendant/tests/fuzz_corpus.rs`.

use fresa_mpg_pendant::codec::{Decoded, Decoder, Frame, FRAME_LEN, MAX_LINE_LEN};

fn frames(chunks: &[&[u8]]) -> Vec<Frame> {
    let mut d = Decoder::new();
    let mut out = Vec::new();
    for c in chunks {
        d.push(c);
        // Memory stays bounded whatever arrives: at most a partial frame, or one pending line.
        assert!(
            d.buffered() <= MAX_LINE_LEN + FRAME_LEN,
            "decoder holds {} bytes",
            d.buffered()
        );
        while let Some(x) = d.pop() {
            if let Decoded::Frame(f) = x {
                out.push(f);
            }
        }
    }
    out
}

/// The first byte picks where the rest is cut into two reads. Never panics; every frame it
/// yields re-encodes to exactly 53 bytes that parse back to the same frame; the decoder's
/// buffers stay bounded; and outside uploads the read boundary does not change the frames.
pub fn codec(data: &[u8]) {
    let Some((&cut, data)) = data.split_first() else {
        return;
    };
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
}

//! What the `replies` fuzz target checks for one input. Shared (by `#[path]`) between the
//! fuzz target and the replay test `plugins/kawasaki-as/tests/fuzz_corpus.rs`.

use fresa_kawasaki_as::codec::{parse_legacy_cmd, LegacyMsg, LegacyReader, V1Cmd, V1Msg};

/// The first byte picks where the bytes are cut into two reads; the rest is the stream.
///
/// * `LegacyReader` never panics, always makes progress (a bounded number of messages per
///   byte) and keeps no more than it was given;
/// * every fresa-v1 line parses or fails without a panic, and what parses re-encodes to a line
///   that parses back and re-encodes to the same line (robot -> PC and PC -> robot);
/// * the seed's robot-side command parser never panics.
pub fn replies(data: &[u8]) {
    let Some((&cut, data)) = data.split_first() else {
        return;
    };
    let at = (cut as usize * data.len()) / 256;
    let mut r = LegacyReader::default();
    let mut count = 0usize;
    for (i, chunk) in [&data[..at], &data[at..]].into_iter().enumerate() {
        r.push(chunk);
        let last = i == 1;
        while let Some(m) = r.next(true) {
            count += 1;
            assert!(
                count <= data.len() + 2,
                "the legacy reader does not make progress"
            );
            if let Ok(LegacyMsg::PartZero(p)) = m {
                assert!(p.iter().all(|v| !v.is_nan()), "part zero with NaN: {p:?}");
            }
        }
        if last {
            // At the end of the input, with the read ended, nothing but separators is left.
            assert!(r.next(true).is_none());
        }
    }
    let text = String::from_utf8_lossy(data);
    for line in text.split('\n') {
        let _ = parse_legacy_cmd(line);
        // Numbers go on the wire with 6 decimals, so compare what is sent again.
        if let Ok(m) = V1Msg::parse(line) {
            let wire = m.encode();
            let again = V1Msg::parse(&wire).map(|m| m.encode());
            assert_eq!(
                again,
                Ok(wire),
                "V1Msg {line:?} does not survive re-encoding"
            );
        }
        if let Ok(c) = V1Cmd::parse(line) {
            // A SPEED under the wire's 6 decimals used to parse and encode as 0.000000, which
            // the robot side refuses (the finding in `findings/`, now fixed in the parser).
            let wire = c.encode();
            let again = V1Cmd::parse(&wire).map(|c| c.encode());
            assert_eq!(
                again,
                Ok(wire),
                "V1Cmd {line:?} does not survive re-encoding"
            );
        }
    }
}

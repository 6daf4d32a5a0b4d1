//! What the `protocol` fuzz target checks for one input. Shared (by `#[path]`) between the
//! fuzz target and the replay test `plugins/mach3-oem/tests/fuzz_corpus.rs`.

use fresa_mach3_oem::protocol::{
    frame_excerpt, read_frame, verify, Auth, Hello, Request, Response, Welcome,
};
use std::io::BufReader;

/// The first byte picks the reader's buffer size (frames cut at every place); the rest is the
/// stream. Frames are read as both ends read them (`read_frame`, then each message type, then
/// the agent's fallback that digs the `id` out of a malformed request): no panic, every frame
/// ends at `\n` or at the end of the stream, and whatever decodes serialises again to JSON that
/// decodes.
pub fn protocol(data: &[u8]) {
    let Some((&cap, data)) = data.split_first() else {
        return;
    };
    let mut r = BufReader::with_capacity(usize::from(cap).max(1), data);
    let mut buf = Vec::new();
    let mut seen = 0usize;
    while let Ok(true) = read_frame(&mut r, &mut buf) {
        seen += buf.len();
        assert!(seen <= data.len());
        assert!(
            buf.ends_with(b"\n") || seen == data.len(),
            "a frame cut short"
        );
        let _ = frame_excerpt(&buf);
        if let Ok(h) = serde_json::from_slice::<Hello>(&buf) {
            again(&h);
        }
        if let Ok(a) = serde_json::from_slice::<Auth>(&buf) {
            let _ = verify("secret", "nonce", &a.auth);
            again(&a);
        }
        if let Ok(w) = serde_json::from_slice::<Welcome>(&buf) {
            again(&w);
        }
        if let Ok(resp) = serde_json::from_slice::<Response>(&buf) {
            again(&resp);
        }
        match serde_json::from_slice::<Request>(&buf) {
            Ok(req) => again(&req),
            Err(_) => {
                let _ = serde_json::from_slice::<serde_json::Value>(&buf)
                    .ok()
                    .and_then(|v| v["id"].as_u64());
            }
        }
    }
}

fn again<T: serde::Serialize + serde::de::DeserializeOwned>(v: &T) {
    let json = serde_json::to_vec(v).unwrap_or_default();
    assert!(
        serde_json::from_slice::<T>(&json).is_ok(),
        "decoded, but its own serialisation does not decode: {}",
        String::from_utf8_lossy(&json)
    );
}

//! The agent protocol, version 1: JSON lines over TCP. Documented in the crate README
//! ("Agent protocol"); both ends use these types, so they cannot drift apart.

use crate::mach3::{Call, ErrorKind, Mach3Error};
use hmac::{Hmac, Mac};
use serde::{Deserialize, Serialize};
use serde_json::Value;
use sha2::Sha256;
use std::io::{self, BufRead, Read, Write};

pub const PROTOCOL_VERSION: u32 = 1;
pub const AGENT_NAME: &str = "fresa-mach3-agent";
/// Longest frame either side accepts (a program chunk is at most [`PROGRAM_CHUNK_BYTES`]).
pub const MAX_LINE_BYTES: usize = 4 << 20;
/// Program text sent per `write_program` call.
pub const PROGRAM_CHUNK_BYTES: usize = 1 << 20;

/// What this agent can do beyond protocol 1 as first released, named in its hello. A feature
/// adds calls (never changes one), so the version stays 1 and either side may be older: a
/// client asks for a feature's calls only when the agent named it, and an older client ignores
/// the list. `get_var`: the `get_var {var}` call (Mach3's `GetVar`).
pub const FEATURES: &[&str] = &[FEATURE_GET_VAR];
pub const FEATURE_GET_VAR: &str = "get_var";

/// First frame, agent -> client.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Hello {
    pub agent: String,
    pub protocol: u32,
    /// 32 random bytes, hex.
    pub nonce: String,
    /// [`FEATURES`] of the agent (absent from agents older than the list).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub features: Vec<String>,
}

/// Second frame, client -> agent: proves the shared secret without sending it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Auth {
    pub protocol: u32,
    /// hex(HMAC-SHA256(key = secret, message = nonce as sent)).
    pub auth: String,
}

/// Third frame, agent -> client. After `ok: false` the agent closes the connection.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Welcome {
    pub ok: bool,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<Mach3Error>,
}

/// A batch of Mach3 calls, run in order on the agent's Mach3 thread with no other call in
/// between. Every call runs even if an earlier one failed (so a restoring MDI line always runs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Request {
    pub id: u64,
    /// Stop / feed hold / reset: queued ahead of every non-urgent batch.
    #[serde(default)]
    pub urgent: bool,
    pub calls: Vec<Call>,
}

/// One call's outcome: `{"ok": value}` or `{"err": {"kind": ..., "message": ...}}`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CallResult {
    Ok(Value),
    Err(Mach3Error),
}

/// The answer to a [`Request`]: one result per call, or `error` for a frame that could not
/// be understood (`id` is then the request's id if it could be read).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Response {
    pub id: Option<u64>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub results: Vec<CallResult>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<Mach3Error>,
}

type HmacSha256 = Hmac<Sha256>;

/// HMAC accepts keys of any length, so this is always `Some`; no panic path either way.
fn mac(secret: &str, nonce: &str) -> Option<HmacSha256> {
    let mut mac = HmacSha256::new_from_slice(secret.as_bytes()).ok()?;
    mac.update(nonce.as_bytes());
    Some(mac)
}

/// The `auth` a client sends for `nonce`.
pub fn sign(secret: &str, nonce: &str) -> String {
    mac(secret, nonce)
        .map(|m| hex::encode(m.finalize().into_bytes()))
        .unwrap_or_default()
}

/// Checks `auth` in constant time.
pub fn verify(secret: &str, nonce: &str, auth: &str) -> bool {
    match (hex::decode(auth), mac(secret, nonce)) {
        (Ok(bytes), Some(mac)) => mac.verify_slice(&bytes).is_ok(),
        _ => false,
    }
}

pub fn new_nonce() -> String {
    hex::encode(rand::random::<[u8; 32]>())
}

/// Reads one `\n`-terminated frame into `buf` (cleared first). `Ok(false)` at end of stream.
pub fn read_frame(r: &mut impl BufRead, buf: &mut Vec<u8>) -> io::Result<bool> {
    buf.clear();
    let n = r.take(MAX_LINE_BYTES as u64 + 1).read_until(b'\n', buf)?;
    if n == 0 {
        return Ok(false);
    }
    if buf.len() > MAX_LINE_BYTES {
        return Err(io::Error::new(
            io::ErrorKind::InvalidData,
            format!("frame longer than {MAX_LINE_BYTES} bytes"),
        ));
    }
    Ok(true)
}

/// Writes `value` as one frame.
pub fn write_frame(w: &mut impl Write, value: &impl Serialize) -> io::Result<()> {
    let mut bytes = serde_json::to_vec(value)?;
    bytes.push(b'\n');
    w.write_all(&bytes)?;
    w.flush()
}

pub fn protocol_error(message: impl Into<String>) -> Mach3Error {
    Mach3Error::new(ErrorKind::Protocol, message)
}

/// A short, printable view of a bad frame for logs and errors.
pub fn frame_excerpt(frame: &[u8]) -> String {
    let text = String::from_utf8_lossy(&frame[..frame.len().min(120)]);
    format!(
        "{:?}{}",
        text.trim_end(),
        if frame.len() > 120 { "..." } else { "" }
    )
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use serde_json::json;

    #[test]
    fn wire_shapes() {
        let r: Request = serde_json::from_value(json!({"id": 3, "calls": [
            {"op": "get_oem_dro", "code": 800}, {"op": "do_oem_button", "code": 1021},
            {"op": "code", "line": "G90"}, {"op": "is_moving"}]}))
        .unwrap();
        assert!(!r.urgent);
        assert_eq!(r.calls[0], Call::GetOemDro { code: 800 });
        assert_eq!(r.calls[3], Call::IsMoving);
        let r: Request =
            serde_json::from_value(json!({"id": 4, "calls": [{"op": "get_var", "var": 2002}]}))
                .unwrap();
        assert_eq!(r.calls[0], Call::GetVar { var: 2002 });
        // An agent older than the feature list says hello without one.
        let h: Hello =
            serde_json::from_value(json!({"agent": AGENT_NAME, "protocol": 1, "nonce": "ab"}))
                .unwrap();
        assert!(h.features.is_empty());
        let resp = Response {
            id: Some(3),
            results: vec![
                CallResult::Ok(json!(1.5)),
                CallResult::Err(Mach3Error::new(ErrorKind::NotRunning, "no Mach3")),
            ],
            error: None,
        };
        assert_eq!(
            serde_json::to_value(&resp).unwrap(),
            json!({"id": 3, "results": [{"ok": 1.5},
                {"err": {"kind": "not_running", "message": "no Mach3"}}]})
        );
        assert!(
            serde_json::from_value::<Request>(json!({"id": 1, "calls": [{"op": "launch"}]}))
                .is_err()
        );
        assert!(serde_json::from_value::<Request>(json!({"id": 1, "calls": [], "x": 1})).is_err());
    }

    #[test]
    fn hmac_handshake() {
        let nonce = new_nonce();
        assert_eq!(nonce.len(), 64);
        let auth = sign("s3cret-s3cret", &nonce);
        assert!(verify("s3cret-s3cret", &nonce, &auth));
        assert!(!verify("s3cret-s3creT", &nonce, &auth));
        assert!(!verify("s3cret-s3cret", &new_nonce(), &auth));
        assert!(!verify("s3cret-s3cret", &nonce, "zz"));
    }

    #[test]
    fn frames_are_bounded() {
        let mut buf = Vec::new();
        let mut r = io::Cursor::new(b"{\"a\":1}\n{\"b\"".to_vec());
        assert!(read_frame(&mut r, &mut buf).unwrap());
        assert_eq!(buf, b"{\"a\":1}\n");
        assert!(read_frame(&mut r, &mut buf).unwrap());
        assert!(!read_frame(&mut r, &mut buf).unwrap());
        let long = vec![b'x'; MAX_LINE_BYTES + 10];
        let e = read_frame(&mut io::Cursor::new(long), &mut buf).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::InvalidData);
    }
}

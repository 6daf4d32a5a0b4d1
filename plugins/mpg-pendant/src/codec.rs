//! The 53-byte frame codec: typed frames, their exact encoding, and a stream decoder that
//! reassembles frames from arbitrary TCP reads, resynchronises after garbage and switches to
//! raw-line mode between `N03START` and `N03FIN`.

use fresa_plugin_api::contract::{Axis, AxisValues, PendantJob, PendantKey};
use std::collections::VecDeque;

/// Every framed message is exactly this long: `N`, two type digits, 49 payload bytes, `F`.
pub const FRAME_LEN: usize = 53;
/// Largest absolute value a position field can hold (`00000.0000` is 10 characters).
pub const MAX_POSITION: f64 = 99_999.999_9;
/// A raw upload line longer than this is not G-code: the upload is abandoned.
pub const MAX_LINE_LEN: usize = 64 * 1024;

/// Which hello/heartbeat frames the server sends. Both are accepted on input.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Dialect {
    /// The shipped firmware: `N04Conected...` hello, `N05Vivo...` heartbeat.
    #[default]
    Firmware,
    /// The design document: `N54` hello, `N55` heartbeat.
    Document,
}

/// What a pendant asks for with `N04xx`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Info {
    /// `N0451`: axis positions, answered by `N51`.
    Positions,
    /// `N0452`: job progress, answered by `N52`.
    Job,
}

/// One decoded frame, in either direction.
#[derive(Debug, Clone, PartialEq)]
pub enum Frame {
    // Pendant -> server.
    /// `count` is signed: the direction character is folded in.
    Jog {
        step: f64,
        axis: Axis,
        count: i32,
    },
    Key(PendantKey),
    UploadStart {
        lines: u32,
    },
    UploadEnd {
        chars: u64,
    },
    Request(Info),
    // Server -> pendant.
    Hello(Dialect),
    Heartbeat {
        dialect: Dialect,
        counter: u32,
    },
    Positions(AxisValues),
    Progress(PendantJob),
    /// An `N52` whose padding after the line number carries a status line for the LCD (a
    /// Fresa extension, issue 26): at most [`STATUS_LEN`] ASCII characters (spaces allowed,
    /// no `*`), `*`-padded. Firmware that does not show it reads the fields before it as
    /// before.
    ProgressWithStatus {
        job: PendantJob,
        status: String,
    },
    UploadConfirmed,
}

/// The longest status line an `N52` carries (one line of the pendant's 20x4 LCD).
pub const STATUS_LEN: usize = fresa_plugin_api::contract::PENDANT_STATUS_LINE;

/// Where an `N52`'s status line starts (0-based byte index, after `LA0000`).
const STATUS_AT: usize = 29;

/// The words of an `N02` action frame, as the firmware spells them.
const KEY_WORDS: [(&str, PendantKey); 15] = [
    ("Zero", PendantKey::Zero),
    ("ZeroX", PendantKey::ZeroX),
    ("ZeroY", PendantKey::ZeroY),
    ("ZeroZ", PendantKey::ZeroZ),
    ("ZeroA", PendantKey::ZeroA),
    ("Reset", PendantKey::Reset),
    ("Stop", PendantKey::Stop),
    ("Rewind", PendantKey::Rewind),
    ("Start", PendantKey::Start),
    ("Pause", PendantKey::Pause),
    ("HOME", PendantKey::Home),
    ("M1", PendantKey::M1),
    ("M2", PendantKey::M2),
    ("M3", PendantKey::M3),
    ("M4", PendantKey::M4),
];

pub fn key_word(key: PendantKey) -> &'static str {
    KEY_WORDS
        .iter()
        .find(|(_, k)| *k == key)
        .map(|(w, _)| *w)
        .unwrap_or("Stop")
}

pub fn parse_key_word(word: &str) -> Option<PendantKey> {
    KEY_WORDS.iter().find(|(w, _)| *w == word).map(|(_, k)| *k)
}

fn axis_from(c: u8) -> Option<Axis> {
    match c {
        b'X' => Some(Axis::X),
        b'Y' => Some(Axis::Y),
        b'Z' => Some(Axis::Z),
        b'A' => Some(Axis::A),
        _ => None,
    }
}

/// Builds a frame from its two-digit type, a head and a tail; `*` fills the middle. Parts that
/// would not fit are cut (the callers' fields are fixed-width, so this never happens for them).
fn build(kind: &str, head: &str, tail: &str) -> [u8; FRAME_LEN] {
    let mut out = [b'*'; FRAME_LEN];
    out[0] = b'N';
    out[FRAME_LEN - 1] = b'F';
    let kind = kind.as_bytes();
    out[1..3].copy_from_slice(&kind[..2]);
    let payload = FRAME_LEN - 4;
    let head = &head.as_bytes()[..head.len().min(payload)];
    out[3..3 + head.len()].copy_from_slice(head);
    let tail = &tail.as_bytes()[..tail.len().min(payload - head.len())];
    let end = FRAME_LEN - 1;
    out[end - tail.len()..end].copy_from_slice(tail);
    out
}

/// `v` as sign + `00000.0000`: exactly 11 characters. Returns whether it had to be clamped.
fn position_field(v: f64) -> (String, bool) {
    let (v, clamped) = if !v.is_finite() {
        (0.0, true)
    } else if v.abs() > MAX_POSITION {
        (MAX_POSITION.copysign(v), true)
    } else {
        (v, false)
    };
    // Round first so 99999.99996 does not print as 100000.0000.
    let rounded = (v.abs() * 10_000.0).round() / 10_000.0;
    let sign = if v < 0.0 && rounded != 0.0 { '-' } else { '+' };
    (
        format!("{sign}{:010.4}", rounded.min(MAX_POSITION)),
        clamped,
    )
}

fn mm_ss(seconds: u64) -> (String, bool) {
    let max = 99 * 60 + 59;
    let s = seconds.min(max);
    (format!("{:02}:{:02}", s / 60, s % 60), seconds > max)
}

fn four_digits(n: u64) -> (String, bool) {
    (format!("{:04}", n.min(9999)), n > 9999)
}

impl Frame {
    /// The frame's bytes. Numbers that do not fit their field are clamped; see [`Frame::encode_checked`].
    pub fn encode(&self) -> [u8; FRAME_LEN] {
        self.encode_checked().0
    }

    /// The frame's bytes, always exactly [`FRAME_LEN`], and a note when a value had to be clamped.
    pub fn encode_checked(&self) -> ([u8; FRAME_LEN], Option<String>) {
        let mut note = None;
        let bytes = match self {
            Frame::Jog { step, axis, count } => {
                let dir = if *count < 0 { '-' } else { '+' };
                let n = count.unsigned_abs().min(9999);
                if count.unsigned_abs() > 9999 {
                    note = Some(format!("jog count {count} clamped to {n}"));
                }
                let step_s = format!("{:06.4}", step.clamp(0.0, 9.9999));
                if step_s.len() != 6 || *step != step.clamp(0.0, 9.9999) {
                    note = Some(format!("jog step {step} clamped"));
                }
                build(
                    "01",
                    &format!(
                        "S{}{}{dir}{n:04}",
                        &step_s[..6.min(step_s.len())],
                        axis.letter()
                    ),
                    "",
                )
            }
            Frame::Key(k) => {
                let w = key_word(*k);
                build("02", w, w)
            }
            Frame::UploadStart { lines } => {
                let n = (*lines).min(99_999);
                if *lines > 99_999 {
                    note = Some(format!("line count {lines} clamped to {n}"));
                }
                build("03", "START", &format!("{n:05}"))
            }
            Frame::UploadEnd { chars } => {
                let n = (*chars).min(9_999_999_999);
                if *chars > n {
                    note = Some(format!("character count {chars} clamped to {n}"));
                }
                build("03", "FIN", &format!("L{n:010}"))
            }
            Frame::Request(i) => {
                let code = match i {
                    Info::Positions => "51",
                    Info::Job => "52",
                };
                build("04", code, code)
            }
            Frame::Hello(Dialect::Firmware) => build("04", "Conected", ""),
            Frame::Hello(Dialect::Document) => build("54", "Conected", ""),
            Frame::Heartbeat { dialect, counter } => {
                let kind = match dialect {
                    Dialect::Firmware => "05",
                    Dialect::Document => "55",
                };
                build(kind, &format!("Vivo{:07}", counter % 10_000_000), "")
            }
            Frame::Positions(p) => {
                let mut s = String::from("E");
                let mut clamped = Vec::new();
                for (axis, v) in Axis::ALL.iter().zip(p.to_array()) {
                    let (field, c) = position_field(v);
                    if c {
                        clamped.push(format!("{}={v}", axis.letter()));
                    }
                    s.push_str(&field);
                    s.push(axis.letter().to_ascii_lowercase());
                }
                if !clamped.is_empty() {
                    note = Some(format!(
                        "positions do not fit the N51 frame and were clamped to +-{MAX_POSITION}: {}",
                        clamped.join(", ")
                    ));
                }
                build("51", &s, "")
            }
            Frame::Progress(j) => progress(j, "", &mut note),
            Frame::ProgressWithStatus { job, status } => {
                // Only what the LCD can show and the frame can carry.
                let shown: String = status
                    .chars()
                    .map(|c| match c {
                        '*' => 'x',
                        c if c.is_ascii_graphic() || c == ' ' => c,
                        _ => '?',
                    })
                    .take(STATUS_LEN)
                    .collect();
                if shown != *status {
                    note = Some(format!("status line {status:?} shown as {shown:?} in N52"));
                }
                progress(job, &shown, &mut note)
            }
            Frame::UploadConfirmed => build("53", "Confirm:Gcode-load", ""),
        };
        (bytes, note)
    }

    /// Parses exactly one frame. The error names what is wrong.
    pub fn parse(b: &[u8; FRAME_LEN]) -> Result<Frame, String> {
        if b[0] != b'N' || b[FRAME_LEN - 1] != b'F' {
            return Err("does not start with N and end with F".into());
        }
        // An N52's status line may have spaces.
        let spaces_from = if &b[1..3] == b"52" {
            STATUS_AT
        } else {
            FRAME_LEN
        };
        let printable = b
            .iter()
            .enumerate()
            .all(|(i, c)| c.is_ascii_graphic() || (*c == b' ' && i >= spaces_from));
        if !printable {
            return Err("contains a byte that is not printable ASCII".into());
        }
        let kind = &b[1..3];
        let p = &b[3..FRAME_LEN - 1];
        let text = std::str::from_utf8(p).map_err(|_| "not ASCII".to_string())?;
        let stars = |s: &[u8]| s.iter().all(|&c| c == b'*');
        let digits = |s: &[u8]| -> Option<u64> {
            if s.is_empty() || !s.iter().all(u8::is_ascii_digit) {
                return None;
            }
            std::str::from_utf8(s).ok()?.parse().ok()
        };
        match kind {
            b"01" => {
                if p[0] != b'S' {
                    return Err(format!("jog: C4 is {:?}, expected 'S'", p[0] as char));
                }
                // `%06.4f`: one digit, a point, four digits.
                let step: f64 = Some(&p[1..7])
                    .filter(|f| f[0].is_ascii_digit() && f[1] == b'.' && all_digits(&f[2..]))
                    .and_then(|_| text[1..7].parse().ok())
                    .filter(|s: &f64| *s > 0.0)
                    .ok_or_else(|| format!("jog: step {:?} is not d.dddd above 0", &text[1..7]))?;
                let axis = axis_from(p[7])
                    .ok_or_else(|| format!("jog: axis {:?} is not X, Y, Z or A", p[7] as char))?;
                let sign = match p[8] {
                    b'+' => 1,
                    b'-' => -1,
                    c => return Err(format!("jog: direction {:?} is not + or -", c as char)),
                };
                let n = digits(&p[9..13])
                    .ok_or_else(|| format!("jog: count {:?} is not 4 digits", &text[9..13]))?;
                if n == 0 {
                    return Err("jog: count is 0".into());
                }
                if !stars(&p[13..]) {
                    return Err("jog: C17-C52 are not all '*'".into());
                }
                Ok(Frame::Jog {
                    step,
                    axis,
                    count: sign * n as i32,
                })
            }
            b"02" => {
                let head = text.split('*').next().unwrap_or("");
                let tail = text.rsplit('*').next().unwrap_or("");
                // Without any '*' head and tail are the whole text and overlap: no middle.
                let middle = text.get(head.len()..text.len().saturating_sub(tail.len()));
                let padded = middle.is_some_and(|m| m.bytes().all(|c| c == b'*'));
                if head.is_empty() || head != tail || !padded {
                    return Err(format!(
                        "action: expected the same word at both ends, got {head:?} and {tail:?}"
                    ));
                }
                parse_key_word(head)
                    .map(Frame::Key)
                    .ok_or_else(|| format!("action: unknown word {head:?}"))
            }
            b"03" if text.starts_with("START") => {
                let n = digits(&p[44..49]).ok_or_else(|| {
                    format!(
                        "upload start: line count {:?} is not 5 digits",
                        &text[44..49]
                    )
                })?;
                if !stars(&p[5..44]) {
                    return Err("upload start: C9-C47 are not all '*'".into());
                }
                Ok(Frame::UploadStart { lines: n as u32 })
            }
            b"03" if text.starts_with("FIN") => {
                if p[38] != b'L' {
                    return Err("upload end: C42 is not 'L'".into());
                }
                let n = digits(&p[39..49]).ok_or_else(|| {
                    format!(
                        "upload end: character count {:?} is not 10 digits",
                        &text[39..49]
                    )
                })?;
                if !stars(&p[3..38]) {
                    return Err("upload end: C7-C41 are not all '*'".into());
                }
                Ok(Frame::UploadEnd { chars: n })
            }
            b"03" => Err("upload: expected START or FIN".into()),
            b"04" if text.starts_with("Conected") => Ok(Frame::Hello(Dialect::Firmware)),
            b"54" => Ok(Frame::Hello(Dialect::Document)),
            b"04" => {
                let (a, b2) = (&text[..2], &text[47..49]);
                if a != b2 || !stars(&p[2..47]) {
                    return Err(format!(
                        "request: {a:?} and {b2:?} differ or padding is wrong"
                    ));
                }
                match a {
                    "51" => Ok(Frame::Request(Info::Positions)),
                    "52" => Ok(Frame::Request(Info::Job)),
                    other => Err(format!("request: unknown information {other:?}")),
                }
            }
            b"05" | b"55" => {
                let dialect = if kind == b"05" {
                    Dialect::Firmware
                } else {
                    Dialect::Document
                };
                let counter = text
                    .strip_prefix("Vivo")
                    .and_then(|r| r.get(..7))
                    .and_then(|d| d.parse().ok())
                    .unwrap_or(0);
                Ok(Frame::Heartbeat { dialect, counter })
            }
            b"51" => {
                if p[0] != b'E' {
                    return Err("positions: C4 is not 'E'".into());
                }
                let mut v = [0.0; 4];
                for (i, axis) in Axis::ALL.iter().enumerate() {
                    let f = &text[1 + i * 12..1 + (i + 1) * 12];
                    if !f.ends_with(axis.letter().to_ascii_lowercase()) {
                        return Err(format!(
                            "positions: field {f:?} does not end with the axis letter"
                        ));
                    }
                    let b = f.as_bytes();
                    let shape = matches!(b[0], b'+' | b'-')
                        && all_digits(&b[1..6])
                        && b[6] == b'.'
                        && all_digits(&b[7..11]);
                    v[i] = Some(&f[..11])
                        .filter(|_| shape)
                        .and_then(|n| n.parse().ok())
                        .ok_or_else(|| format!("positions: {:?} is not +00000.0000", &f[..11]))?;
                }
                Ok(Frame::Positions(AxisValues::from_array(v)))
            }
            b"52" => {
                let bad =
                    || format!("progress: {text:?} does not match ELmm:ssESmm:ssNL0000LA0000");
                if &text[..2] != "EL"
                    || &text[7..9] != "ES"
                    || &text[14..16] != "NL"
                    || &text[20..22] != "LA"
                {
                    return Err(bad());
                }
                let secs = |s: &str| -> Option<u64> {
                    let (m, s) = s.split_once(':')?;
                    if !(all_digits(m.as_bytes()) && all_digits(s.as_bytes())) {
                        return None;
                    }
                    let (m, s) = (m.parse::<u64>().ok()?, s.parse::<u64>().ok()?);
                    (s < 60).then_some(m * 60 + s)
                };
                let four = |s: &str| all_digits(s.as_bytes()).then(|| s.parse().ok()).flatten();
                let job = PendantJob {
                    elapsed_s: secs(&text[2..7]).ok_or_else(bad)?,
                    estimated_s: secs(&text[9..14]).ok_or_else(bad)?,
                    total_lines: four(&text[16..20]).ok_or_else(bad)?,
                    line: four(&text[22..26]).ok_or_else(bad)?,
                };
                // The rest: a status line, then `*` to the end.
                let tail = &text[26..];
                let status = tail.trim_end_matches('*');
                if status.is_empty() {
                    return Ok(Frame::Progress(job));
                }
                if status.contains('*') || status.len() > STATUS_LEN {
                    return Err(format!(
                        "progress: the status line {tail:?} is not at most {STATUS_LEN} \
                         characters then `*` padding"
                    ));
                }
                Ok(Frame::ProgressWithStatus {
                    job,
                    status: status.to_string(),
                })
            }
            b"53" => Ok(Frame::UploadConfirmed),
            other => Err(format!(
                "unknown message type {:?}",
                String::from_utf8_lossy(other)
            )),
        }
    }
}

/// An `N52` frame: the job's fields, then `status` (already fitted), then `*`.
fn progress(j: &PendantJob, status: &str, note: &mut Option<String>) -> [u8; FRAME_LEN] {
    let (el, c1) = mm_ss(j.elapsed_s);
    let (es, c2) = mm_ss(j.estimated_s);
    let (nl, c3) = four_digits(j.total_lines);
    let (la, c4) = four_digits(j.line);
    if c1 || c2 || c3 || c4 {
        *note = Some(format!("job progress {j:?} clamped to fit the N52 frame"));
    }
    build("52", &format!("EL{el}ES{es}NL{nl}LA{la}{status}"), "")
}

fn all_digits(s: &[u8]) -> bool {
    !s.is_empty() && s.iter().all(u8::is_ascii_digit)
}

/// What the decoder found in the byte stream.
#[derive(Debug, Clone, PartialEq)]
pub enum Decoded {
    Frame(Frame),
    /// One raw G-code line of an upload (between `UploadStart` and `UploadEnd`), without newline.
    Line(Vec<u8>),
    /// Bytes that were not part of any valid frame, with the reason the last candidate failed.
    Skipped {
        bytes: Vec<u8>,
        reason: String,
    },
    /// Raw-line mode was abandoned (line too long); the decoder is back in frame mode.
    UploadAborted {
        reason: String,
    },
}

#[derive(Debug, Default)]
struct Raw {
    /// Whether the sender ends lines with `\n`; then a line may span reads. Otherwise (the
    /// firmware, one send per line) the end of a read is the end of a line.
    terminated: bool,
    pending: Vec<u8>,
}

/// Reassembles frames from a byte stream. Feed each read with [`Decoder::push`] (the end of a
/// push is a read boundary, which delimits raw upload lines), then drain [`Decoder::pop`].
#[derive(Debug, Default)]
pub struct Decoder {
    buf: Vec<u8>,
    raw: Option<Raw>,
    skipped: Vec<u8>,
    skip_reason: String,
    out: VecDeque<Decoded>,
}

impl Decoder {
    pub fn new() -> Self {
        Self::default()
    }

    /// Whether the decoder is between `N03START` and `N03FIN`.
    pub fn in_upload(&self) -> bool {
        self.raw.is_some()
    }

    /// Leaves raw-line mode (upload timed out or was cancelled).
    pub fn abort_upload(&mut self) {
        self.raw = None;
    }

    /// Bytes held back for the next read (a partial frame, or a partial upload line).
    pub fn buffered(&self) -> usize {
        self.buf.len() + self.raw.as_ref().map_or(0, |r| r.pending.len())
    }

    pub fn pop(&mut self) -> Option<Decoded> {
        self.out.pop_front()
    }

    pub fn push(&mut self, chunk: &[u8]) {
        let mut input = chunk.to_vec();
        loop {
            if self.raw.is_some() {
                match self.push_raw(input) {
                    Some(rest) => input = rest,
                    None => break,
                }
            } else {
                self.buf.extend_from_slice(&input);
                match self.scan_frames() {
                    // An upload started: what followed the START frame in this read is raw.
                    Some(rest) => input = rest,
                    None => break,
                }
            }
        }
        self.flush_skipped();
    }

    fn flush_skipped(&mut self) {
        if !self.skipped.is_empty() {
            let reason = if self.skip_reason.is_empty() {
                "no frame starts here (looking for 'N')".to_string()
            } else {
                std::mem::take(&mut self.skip_reason)
            };
            self.out.push_back(Decoded::Skipped {
                bytes: std::mem::take(&mut self.skipped),
                reason,
            });
        }
    }

    /// Decodes whole frames from `buf`. Returns the bytes after an upload START frame.
    fn scan_frames(&mut self) -> Option<Vec<u8>> {
        let mut pos = 0;
        let result = loop {
            match self.buf[pos..].iter().position(|&b| b == b'N') {
                Some(p) => {
                    self.skipped.extend_from_slice(&self.buf[pos..pos + p]);
                    pos += p;
                }
                None => {
                    self.skipped.extend_from_slice(&self.buf[pos..]);
                    pos = self.buf.len();
                    break None;
                }
            }
            if self.buf.len() - pos < FRAME_LEN {
                break None;
            }
            let mut cand = [0u8; FRAME_LEN];
            cand.copy_from_slice(&self.buf[pos..pos + FRAME_LEN]);
            match Frame::parse(&cand) {
                Ok(frame) => {
                    self.flush_skipped();
                    pos += FRAME_LEN;
                    let start = matches!(frame, Frame::UploadStart { .. });
                    self.out.push_back(Decoded::Frame(frame));
                    if start {
                        self.raw = Some(Raw::default());
                        break Some(self.buf[pos..].to_vec());
                    }
                }
                Err(e) => {
                    // Not a frame here: drop one byte and look for the next 'N', so a valid
                    // frame that starts inside the bad bytes is still found.
                    self.skip_reason = format!("{e} (frame {:?})", String::from_utf8_lossy(&cand));
                    self.skipped.push(b'N');
                    pos += 1;
                }
            }
        };
        match result {
            Some(rest) => {
                self.buf.clear();
                Some(rest)
            }
            None => {
                self.buf.drain(..pos);
                None
            }
        }
    }

    /// Handles one read in raw-line mode. Returns the bytes to decode in frame mode when raw
    /// mode ended in this read: after a FIN frame, or from a pendant frame that abandoned the
    /// upload (that frame included, so it is decoded and answered).
    fn push_raw(&mut self, input: Vec<u8>) -> Option<Vec<u8>> {
        let raw = self.raw.as_mut()?;
        // Firmware style: `pending` is the whole previous read, held back because it ended with
        // what may be the start of a frame; it is still a line of its own unless a frame starts
        // in it.
        let mut data = std::mem::take(&mut raw.pending);
        let boundary = if raw.terminated { 0 } else { data.len() };
        // The held bytes were searched last time: only a frame that reaches into this read can
        // be new (so a long line arriving in many small reads costs linear time).
        let scan_from = data.len().saturating_sub(FRAME_LEN - 1);
        data.extend_from_slice(&input);
        let hit = find_frame_in_upload(&data, scan_from);
        let body_end = hit.as_ref().map_or(data.len(), |(i, _)| *i);
        if data[..body_end].contains(&b'\n') {
            raw.terminated = true;
        }
        let mut lines: Vec<Vec<u8>> = Vec::new();
        let mut pending = Vec::new();
        if raw.terminated {
            let mut segments: Vec<&[u8]> = data[..body_end].split(|&b| b == b'\n').collect();
            let last = segments.pop().unwrap_or(&[]);
            lines.extend(segments.iter().map(|s| strip_cr(s).to_vec()));
            if hit.is_some() {
                // A frame merged with the last line ends that line.
                if !last.is_empty() {
                    lines.push(strip_cr(last).to_vec());
                }
            } else {
                pending.extend_from_slice(last);
            }
        } else {
            // Firmware style: each read is one line.
            let cut = boundary.min(body_end);
            if cut > 0 {
                lines.push(strip_cr(&data[..cut]).to_vec());
            }
            let rest = &data[cut..body_end];
            if hit.is_none() && may_end_in_frame_start(rest) {
                pending.extend_from_slice(rest);
            } else if !rest.is_empty() {
                lines.push(strip_cr(rest).to_vec());
            }
        }
        for l in lines {
            self.out.push_back(Decoded::Line(l));
        }
        if pending.len() > MAX_LINE_LEN {
            self.raw = None;
            self.out.push_back(Decoded::UploadAborted {
                reason: format!("an upload line is longer than {MAX_LINE_LEN} bytes"),
            });
            return None;
        }
        match hit {
            Some((i, frame @ Frame::UploadEnd { .. })) => {
                self.raw = None;
                self.out.push_back(Decoded::Frame(frame));
                Some(data[i + FRAME_LEN..].to_vec())
            }
            Some((i, frame)) => {
                self.raw = None;
                self.out.push_back(Decoded::UploadAborted {
                    reason: format!(
                        "the pendant sent {} instead of the next line or N03FIN: it abandoned \
                         the upload (STOP key)",
                        describe(&frame)
                    ),
                });
                Some(data[i..].to_vec())
            }
            None => {
                raw.pending = pending;
                None
            }
        }
    }
}

/// Frames a pendant sends that end raw-line mode: FIN, and the frames of its main loop (a
/// poll, a key, the wheel, a new START) that show it left its upload routine. Their fields and
/// `*` padding are checked strictly, so no G-code line is mistaken for one. The server's own
/// frame types (N05, N5x) are not among them: a pendant never sends them and their payload is
/// free-form, so a compact G-code line could look like one.
fn ends_upload(f: &Frame) -> bool {
    matches!(
        f,
        Frame::UploadEnd { .. }
            | Frame::Request(_)
            | Frame::Key(_)
            | Frame::Jog { .. }
            | Frame::UploadStart { .. }
    )
}

fn describe(f: &Frame) -> String {
    let bytes = f.encode();
    let text = String::from_utf8_lossy(&bytes);
    match f {
        Frame::Request(Info::Positions) => format!("its N0451 poll ({text})"),
        Frame::Request(Info::Job) => format!("its N0452 poll ({text})"),
        _ => format!("the frame {text}"),
    }
}

/// The first place in `data`, from `from` on, where a frame that ends an upload starts.
fn find_frame_in_upload(data: &[u8], mut from: usize) -> Option<(usize, Frame)> {
    while let Some(i) = data[from..]
        .iter()
        .position(|&b| b == b'N')
        .map(|i| i + from)
    {
        if data.len() - i < FRAME_LEN {
            return None;
        }
        if data[i + FRAME_LEN - 1] == b'F' {
            let mut cand = [0u8; FRAME_LEN];
            cand.copy_from_slice(&data[i..i + FRAME_LEN]);
            if let Ok(f) = Frame::parse(&cand) {
                if ends_upload(&f) {
                    return Some((i, f));
                }
            }
        }
        from = i + 1;
    }
    None
}

/// Whether `read` ends with a proper prefix (3 bytes or more) of a frame that would end the
/// upload: then the read is held back until the next one shows whether a frame was split.
fn may_end_in_frame_start(read: &[u8]) -> bool {
    let from = read.len().saturating_sub(FRAME_LEN - 1);
    (from..read.len().saturating_sub(2)).any(|i| read[i] == b'N' && is_frame_prefix(&read[i..]))
}

/// Whether `p` (shorter than a frame) can be completed into a frame that ends an upload: it is
/// completed with the rest of each template (every variable field of a template is filled with
/// a value that is valid whatever precedes it) and parsed.
fn is_frame_prefix(p: &[u8]) -> bool {
    use std::sync::OnceLock;
    static TEMPLATES: OnceLock<Vec<[u8; FRAME_LEN]>> = OnceLock::new();
    let templates = TEMPLATES.get_or_init(|| {
        let mut t = vec![
            Frame::UploadEnd { chars: 0 }.encode(),
            Frame::UploadStart { lines: 0 }.encode(),
            Frame::Request(Info::Positions).encode(),
            Frame::Request(Info::Job).encode(),
            Frame::Jog {
                step: 0.0001,
                axis: Axis::X,
                count: 1,
            }
            .encode(),
        ];
        t.extend(KEY_WORDS.iter().map(|(_, k)| Frame::Key(*k).encode()));
        t
    });
    if p.len() >= FRAME_LEN || !p.iter().all(u8::is_ascii_graphic) {
        return false;
    }
    templates.iter().any(|t| {
        let mut cand = *t;
        cand[..p.len()].copy_from_slice(p);
        Frame::parse(&cand).is_ok_and(|f| ends_upload(&f))
    })
}

fn strip_cr(s: &[u8]) -> &[u8] {
    s.strip_suffix(b"\r").unwrap_or(s)
}

#[cfg(test)]
mod tests;

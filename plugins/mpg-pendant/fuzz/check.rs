//! What the `codec` and `upload` fuzz targets check for one input. Shared (by `#[path]`)
//! between the fuzz targets and the replay test `plugins/mpg-pendant/tests/fuzz_corpus.rs`.
// Each fuzz target uses its part of this file.
#![allow(dead_code)]

use fresa_mpg_pendant::codec::{Decoded, Decoder, Frame, Info, FRAME_LEN, MAX_LINE_LEN};
use fresa_plugin_api::contract::{Axis, PendantKey};
use std::time::Duration;

// The G-code generator of the gcode crate's `grammar` target: upload lines that nest deep,
// hold huge numbers and repeat constructs.
#[path = "../../../gcode/fuzz/grammar.rs"]
mod grammar;
// The stack and CPU budget of the gcode crate's checks.
#[path = "../../../gcode/fuzz/budget.rs"]
pub mod budget;

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

/// Most bytes of one generated session.
const MAX_SESSION_BYTES: usize = 256 * 1024;

const KEYS: [PendantKey; 15] = [
    PendantKey::Zero,
    PendantKey::ZeroX,
    PendantKey::ZeroY,
    PendantKey::ZeroZ,
    PendantKey::ZeroA,
    PendantKey::Reset,
    PendantKey::Stop,
    PendantKey::Rewind,
    PendantKey::Start,
    PendantKey::Pause,
    PendantKey::Home,
    PendantKey::M1,
    PendantKey::M2,
    PendantKey::M3,
    PendantKey::M4,
];

/// What a pendant sends, from the fuzzer's bytes; see [`upload_within`].
pub fn upload(data: &[u8]) {
    upload_within(data, None);
}

/// A pendant session from the fuzzer's bytes: the frames its main loop sends (polls, keys,
/// wheel), uploads of generated G-code (`N03START`, lines, `N03FIN`, with right or wrong
/// counts, lines up to past the 64 KiB line limit) and garbage. The first choice picks how the
/// session reaches the decoder:
/// * `Reads::Terminated`: each frame and each whole upload one read, lines ending in `\n`;
/// * `Reads::Firmware`: as the shipped firmware sends, each upload line a read of its own
///   without newline (blank lines not sent);
/// * `Reads::Anywhere`: garbage in between, and everything cut into reads at any byte.
///
/// Checked:
/// * in the first two, with no line that could hold a frame (no `N`, no `\r`) and none over
///   the limit, the decoder gives back exactly the frames and lines sent;
/// * in any session: never a panic, the decoder's buffers stay bounded, every frame
///   re-encodes to itself;
/// * every upload the decoder completes goes, joined as the core stores it, through the G-code
///   analysis the core runs on every upload.
///
/// All of it on a thread with half the upload thread's stack; with `budget`, in less CPU time.
pub fn upload_within(data: &[u8], budget: Option<Duration>) {
    let data = data.to_vec();
    budget::on_small_stack(budget, move || session(&data));
}

/// How a session's bytes are cut into the reads the decoder is fed.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Reads {
    Terminated,
    Firmware,
    Anywhere,
}

fn session(data: &[u8]) {
    let mut c = grammar::Choices::new(data);
    let reads_mode = c.pick(&[Reads::Terminated, Reads::Firmware, Reads::Anywhere]);
    let clean = reads_mode != Reads::Anywhere;
    // Whether the decoded stream must equal what was sent (clean, and no line over the limit).
    let mut exact = clean;
    let mut reads: Vec<Vec<u8>> = Vec::new();
    let mut expected: Vec<Decoded> = Vec::new();
    let mut total = 0;
    while !c.done() && total < MAX_SESSION_BYTES {
        let mut read = Vec::new();
        match c.below(8) {
            0..=2 => {
                let text = grammar::program(&mut grammar::Choices::new(&take(&mut c)));
                let mut lines: Vec<String> = text.split('\n').map(str::to_string).collect();
                if lines.last().is_some_and(String::is_empty) {
                    lines.pop();
                }
                if clean {
                    // No line may hold something a pendant frame could start with.
                    for l in &mut lines {
                        *l = l.replace(['N', '\r'], "");
                    }
                }
                let declared = if c.below(4) == 0 {
                    c.below(1000) as u32
                } else {
                    lines.len() as u32
                };
                let chars: u64 = lines.iter().map(|l| l.len() as u64).sum();
                let start_frame = Frame::UploadStart { lines: declared };
                let end_frame = Frame::UploadEnd { chars };
                read.extend_from_slice(&start_frame.encode());
                expected.push(Decoded::Frame(canonical(&start_frame)));
                for l in &lines {
                    if reads_mode == Reads::Firmware {
                        // The firmware sends no blank line, and each line as a read of its own:
                        // the first one after the START frame, in the same read.
                        if l.is_empty() {
                            continue;
                        }
                        read.extend_from_slice(l.as_bytes());
                        total += read.len();
                        reads.push(std::mem::take(&mut read));
                    } else {
                        read.extend_from_slice(l.as_bytes());
                        read.push(b'\n');
                    }
                    expected.push(Decoded::Line(l.clone().into_bytes()));
                }
                read.extend_from_slice(&end_frame.encode());
                exact &= lines.iter().all(|l| l.len() <= MAX_LINE_LEN);
                expected.push(Decoded::Frame(canonical(&end_frame)));
            }
            3..=5 => {
                let f = match c.below(4) {
                    0 => Frame::Request(if c.below(2) == 0 {
                        Info::Positions
                    } else {
                        Info::Job
                    }),
                    1 => Frame::Key(c.pick(&KEYS)),
                    _ => Frame::Jog {
                        step: f64::from(c.pick(&[1u16, 10, 100, 1000, 10000])) / 10000.0,
                        axis: c.pick(&Axis::ALL),
                        // Never 0 (not a frame); past 9999 it is clamped.
                        count: (1 + c.below(20_000) as i32) * if c.below(2) == 0 { 1 } else { -1 },
                    },
                };
                read.extend_from_slice(&f.encode());
                expected.push(Decoded::Frame(canonical(&f)));
            }
            _ => {
                if clean {
                    continue;
                }
                read.extend(take(&mut c));
            }
        }
        total += read.len();
        reads.push(read);
    }
    if reads_mode == Reads::Anywhere {
        // Merge and cut the reads anywhere.
        let all: Vec<u8> = reads.concat();
        reads.clear();
        let mut at = 0;
        while at < all.len() {
            let n = if c.done() { 4096 } else { 1 + c.below(4096) }.min(all.len() - at);
            reads.push(all[at..at + n].to_vec());
            at += n;
        }
    }
    let mut d = Decoder::new();
    let mut got = Vec::new();
    for r in &reads {
        d.push(r);
        assert!(
            d.buffered() <= MAX_LINE_LEN + FRAME_LEN,
            "decoder holds {} bytes",
            d.buffered()
        );
        while let Some(x) = d.pop() {
            if let Decoded::Frame(f) = &x {
                assert_eq!(Frame::parse(&f.encode()).as_ref(), Ok(f));
            }
            got.push(x);
        }
    }
    if exact {
        assert_eq!(
            got.len(),
            expected.len(),
            "clean session decoded differently"
        );
        for (g, e) in got.iter().zip(&expected) {
            assert!(same(g, e), "decoded {g:?}, sent {e:?}");
        }
    }
    // Every completed upload through the analysis the core runs on it.
    let mut lines: Option<Vec<u8>> = None;
    for x in got {
        match x {
            Decoded::Frame(Frame::UploadStart { .. }) => lines = Some(Vec::new()),
            Decoded::Line(l) => {
                if let Some(p) = lines.as_mut() {
                    p.extend_from_slice(&l);
                    p.push(b'\n');
                }
            }
            Decoded::Frame(Frame::UploadEnd { .. }) => {
                if let Some(program) = lines.take() {
                    analyse(&program);
                }
            }
            Decoded::UploadAborted { .. } => lines = None,
            _ => {}
        }
    }
}

/// The next 1..256 choice bytes, as the input of something nested.
fn take(c: &mut grammar::Choices) -> Vec<u8> {
    let n = 1 + c.below(256);
    (0..n).map(|_| c.byte()).collect()
}

/// A frame as it comes back from its own encoding (numbers clamped, step rounded).
fn canonical(f: &Frame) -> Frame {
    Frame::parse(&f.encode()).unwrap_or_else(|e| panic!("{f:?} does not parse back: {e}"))
}

fn same(a: &Decoded, b: &Decoded) -> bool {
    match (a, b) {
        (Decoded::Frame(x), Decoded::Frame(y)) => x == y,
        (Decoded::Line(x), Decoded::Line(y)) => x == y,
        _ => false,
    }
}

/// What the core does with a finished upload before it becomes a job.
fn analyse(program: &[u8]) {
    let opts = fresa_gcode::AnalysisOptions {
        config: fresa_gcode::Config {
            // Loops in fuzz input must end quickly: what a loop costs grows linearly with the
            // limit, and 10,000 passes of a loop of messages took the 2 s CPU budget under
            // AddressSanitizer (30 ms optimised): the budget is there for work that grows faster.
            max_loop_iterations: 1_000,
            ..fresa_gcode::Config::default()
        },
        ..fresa_gcode::AnalysisOptions::default()
    };
    let _ = fresa_gcode::analyse(program, &opts);
}

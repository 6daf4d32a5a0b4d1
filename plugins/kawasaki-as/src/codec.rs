//! The wire formats of both robot programs, both directions (the client uses one half, the
//! simulator the other). ASCII, comma separated.
//!
//! * legacy (the seed's `FRESADORA`): PC -> robot lines end with CR LF (as the seed's
//!   `WriteLine`); robot -> PC messages are bare strings with no terminator (`TCP_SEND` of
//!   `"done"`), one per send: `Esperando inicio`, the part zero `x y z`, `done`.
//! * fresa-v1 (ours): every message is one line ending in LF, both ways.

/// Decimals sent for coordinates: 1e-6 mm, far below the robot's 0.02 mm repeatability, so a
/// point survives the text round trip within 5e-7 mm.
pub fn num(v: f64) -> String {
    let s = format!("{v:.6}");
    // "-0.000000" reads as 0 anyway; keep the wire tidy.
    if s.trim_start_matches('-')
        .bytes()
        .all(|b| b == b'0' || b == b'.')
    {
        "0.000000".to_string()
    } else {
        s
    }
}

// ---------------------------------------------------------------- legacy, PC -> robot

pub const LEGACY_START: &str = "inicio\r\n";
pub const LEGACY_EXIT: &str = "EXIT\r\n";

/// `JMOVE,x,y,z` / `LMOVE,x,y,z` for robot point `r` (relative to part zero). The seed's robot
/// program applies `TRANS(x, -y, -z)` to what it receives, so Y and Z are sent negated: the
/// robot then moves to exactly `r`.
pub fn legacy_move(rapid: bool, r: [f64; 3]) -> String {
    format!(
        "{},{},{},{}\r\n",
        if rapid { "JMOVE" } else { "LMOVE" },
        num(r[0]),
        num(-r[1]),
        num(-r[2])
    )
}

// ---------------------------------------------------------------- legacy, robot -> PC

/// A message of the seed's robot program.
/// Smallest SPEED the fresa-v1 wire can carry (it writes 6 decimals).
pub const MIN_SPEED_MM_S: f64 = 0.000_001;

#[derive(Debug, Clone, PartialEq)]
pub enum LegacyMsg {
    /// `Esperando inicio`
    Waiting,
    /// `x y z`: part zero in robot base coordinates.
    PartZero([f64; 3]),
    /// `done`
    Done,
}

pub const LEGACY_WAITING: &str = "Esperando inicio";
pub const LEGACY_DONE: &str = "done";

fn is_separator(b: u8) -> bool {
    matches!(b, b'\r' | b'\n' | b'\0' | b' ' | b'\t')
}

fn is_number_byte(b: u8) -> bool {
    b.is_ascii_digit() || matches!(b, b'+' | b'-' | b'.' | b' ')
}

/// Splits the robot's byte stream into messages. The robot sends no terminator, so messages
/// are told apart by content: the two fixed words, and a part zero of three numbers that ends
/// at a terminator, at the next word, or at the end of what one read returned (the robot sends
/// it with one `TCP_SEND`, as the seed's client also assumed).
#[derive(Debug, Default)]
pub struct LegacyReader {
    buf: Vec<u8>,
}

impl LegacyReader {
    pub fn push(&mut self, bytes: &[u8]) {
        self.buf.extend_from_slice(bytes);
    }

    /// The next message, `Some(Err(text))` for bytes that are no message (skipped), `None`
    /// when more bytes are needed. `read_ended`: the buffer ends where a read ended.
    pub fn next(&mut self, read_ended: bool) -> Option<Result<LegacyMsg, String>> {
        let start = self.buf.iter().position(|b| !is_separator(*b))?;
        self.buf.drain(..start);
        for (word, msg) in [
            (LEGACY_WAITING, LegacyMsg::Waiting),
            (LEGACY_DONE, LegacyMsg::Done),
        ] {
            if self.buf.starts_with(word.as_bytes()) {
                self.buf.drain(..word.len());
                return Some(Ok(msg));
            }
            if word.as_bytes().starts_with(&self.buf) {
                return None; // a word cut by the read; wait for the rest
            }
        }
        if is_number_byte(self.buf[0]) {
            let end = self.buf.iter().position(|b| !is_number_byte(*b));
            let end = match end {
                Some(e) => e,
                None if read_ended => self.buf.len(),
                None => return None,
            };
            let text: String = String::from_utf8_lossy(&self.buf[..end]).into_owned();
            self.buf.drain(..end);
            let nums: Vec<f64> = text
                .split_whitespace()
                .filter_map(|t| t.parse().ok())
                .collect();
            return Some(match nums.as_slice() {
                [x, y, z] if text.split_whitespace().count() == 3 => {
                    Ok(LegacyMsg::PartZero([*x, *y, *z]))
                }
                _ => Err(text),
            });
        }
        // Garbage: up to the next terminator or the next word.
        let end = (1..self.buf.len())
            .find(|&i| {
                matches!(self.buf[i], b'\r' | b'\n' | b'\0')
                    || self.buf[i..].starts_with(LEGACY_DONE.as_bytes())
                    || self.buf[i..].starts_with(LEGACY_WAITING.as_bytes())
            })
            .unwrap_or(self.buf.len());
        if end == self.buf.len() && !read_ended {
            return None;
        }
        let text = String::from_utf8_lossy(&self.buf[..end]).into_owned();
        self.buf.drain(..end);
        Some(Err(text))
    }
}

/// A command as the seed's robot program decodes it (`$DECODE(buf, ",", 0)` and the rest).
#[derive(Debug, Clone, PartialEq)]
pub enum LegacyCmd {
    Start,
    Exit,
    /// The point as received (before the program's `TRANS(x, -y, -z)`).
    Move {
        rapid: bool,
        xyz: [f64; 3],
    },
    /// Anything else: the program ignores it without an answer.
    Unknown(String),
}

pub fn parse_legacy_cmd(line: &str) -> LegacyCmd {
    let line = line.trim_end_matches(['\r', '\n']);
    let (comm, rest) = line.split_once(',').unwrap_or((line, ""));
    match comm {
        "inicio" if rest.is_empty() => LegacyCmd::Start,
        "EXIT" => LegacyCmd::Exit,
        "JMOVE" | "LMOVE" => match parse_xyz(rest) {
            Some(xyz) => LegacyCmd::Move {
                rapid: comm == "JMOVE",
                xyz,
            },
            None => LegacyCmd::Unknown(line.to_string()),
        },
        _ => LegacyCmd::Unknown(line.to_string()),
    }
}

fn parse_xyz(s: &str) -> Option<[f64; 3]> {
    let mut it = s.split(',').map(|t| t.trim().parse::<f64>().ok());
    let xyz = [it.next()??, it.next()??, it.next()??];
    (it.next().is_none() && xyz.iter().all(|v| v.is_finite())).then_some(xyz)
}

// ---------------------------------------------------------------- fresa-v1

/// PC -> robot (fresa-v1). `seq` 0 = a control command that does not count as progress.
#[derive(Debug, Clone, PartialEq)]
pub enum V1Cmd {
    /// Start or continue the run tagged `tag`; answered with the last sequence number done for it.
    Run {
        tag: String,
    },
    Speed {
        seq: u64,
        mm_s: f64,
    },
    Move {
        seq: u64,
        rapid: bool,
        to: [f64; 3],
    },
    Exit,
}

impl V1Cmd {
    pub fn encode(&self) -> String {
        match self {
            V1Cmd::Run { tag } => format!("0,RUN,{tag}\n"),
            V1Cmd::Speed { seq, mm_s } => format!("{seq},SPEED,{}\n", num(*mm_s)),
            V1Cmd::Move { seq, rapid, to } => format!(
                "{seq},{},{},{},{}\n",
                if *rapid { "JMOVE" } else { "LMOVE" },
                num(to[0]),
                num(to[1]),
                num(to[2])
            ),
            V1Cmd::Exit => "0,EXIT\n".to_string(),
        }
    }

    /// What the robot side makes of one line: the command, or `(seq, reason)` for an error
    /// answer (seq 0 when even that was unreadable).
    pub fn parse(line: &str) -> Result<V1Cmd, (u64, String)> {
        let line = line.trim_end_matches(['\r', '\n']);
        let mut parts = line.splitn(3, ',');
        let seq = parts
            .next()
            .and_then(|s| s.trim().parse::<u64>().ok())
            .ok_or_else(|| (0, format!("no sequence number in {line:?}")))?;
        let cmd = parts.next().unwrap_or("");
        let rest = parts.next().unwrap_or("");
        match cmd {
            "RUN" if !rest.is_empty() && rest.len() <= 64 => Ok(V1Cmd::Run {
                tag: rest.to_string(),
            }),
            "EXIT" => Ok(V1Cmd::Exit),
            "SPEED" => match rest.trim().parse::<f64>() {
                // The wire carries 6 decimals: a speed that would encode as 0.000000 is no
                // speed (the fuzzer found `2E-55` parsed here but not after re-encoding).
                Ok(v) if v >= MIN_SPEED_MM_S && v.is_finite() => Ok(V1Cmd::Speed { seq, mm_s: v }),
                _ => Err((seq, format!("bad SPEED value {rest:?}"))),
            },
            "JMOVE" | "LMOVE" => match parse_xyz(rest) {
                Some(to) => Ok(V1Cmd::Move {
                    seq,
                    rapid: cmd == "JMOVE",
                    to,
                }),
                None => Err((seq, format!("bad {cmd} point {rest:?}"))),
            },
            other => Err((seq, format!("unknown command {other:?}"))),
        }
    }
}

/// Robot -> PC (fresa-v1).
#[derive(Debug, Clone, PartialEq)]
pub enum V1Msg {
    /// `HELLO,fresa-v1,x,y,z`: sent on connect; part zero in robot base coordinates.
    Hello { part_zero: [f64; 3] },
    /// `0,run,<tag>,<last_seq>`
    Run { tag: String, last_seq: u64 },
    /// `<seq>,done`
    Done(u64),
    /// `<seq>,err,<message>`
    Err { seq: u64, message: String },
    /// `0,bye`
    Bye,
}

impl V1Msg {
    pub fn encode(&self) -> String {
        match self {
            V1Msg::Hello { part_zero: z } => {
                format!("HELLO,fresa-v1,{},{},{}\n", num(z[0]), num(z[1]), num(z[2]))
            }
            V1Msg::Run { tag, last_seq } => format!("0,run,{tag},{last_seq}\n"),
            V1Msg::Done(seq) => format!("{seq},done\n"),
            V1Msg::Err { seq, message } => format!("{seq},err,{message}\n"),
            V1Msg::Bye => "0,bye\n".to_string(),
        }
    }

    pub fn parse(line: &str) -> Result<V1Msg, String> {
        let line = line.trim_end_matches(['\r', '\n']);
        if let Some(rest) = line.strip_prefix("HELLO,fresa-v1,") {
            return parse_xyz(rest)
                .map(|part_zero| V1Msg::Hello { part_zero })
                .ok_or_else(|| format!("bad part zero in greeting {line:?}"));
        }
        let mut parts = line.splitn(3, ',');
        let seq = parts
            .next()
            .and_then(|s| s.parse::<u64>().ok())
            .ok_or_else(|| format!("unreadable robot message {line:?}"))?;
        match (parts.next(), parts.next()) {
            (Some("done"), None) => Ok(V1Msg::Done(seq)),
            (Some("bye"), None) => Ok(V1Msg::Bye),
            (Some("err"), msg) => Ok(V1Msg::Err {
                seq,
                message: msg.unwrap_or("").to_string(),
            }),
            (Some("run"), Some(rest)) => {
                let (tag, last) = rest
                    .rsplit_once(',')
                    .ok_or_else(|| format!("bad run answer {line:?}"))?;
                let last_seq = last
                    .parse()
                    .map_err(|_| format!("bad sequence number in {line:?}"))?;
                Ok(V1Msg::Run {
                    tag: tag.to_string(),
                    last_seq,
                })
            }
            _ => Err(format!("unreadable robot message {line:?}")),
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;
    use proptest::prelude::*;

    fn all(r: &mut LegacyReader, read_ended: bool) -> Vec<Result<LegacyMsg, String>> {
        std::iter::from_fn(|| r.next(read_ended)).collect()
    }

    #[test]
    fn legacy_messages_without_terminators() {
        let mut r = LegacyReader::default();
        r.push(b"Esperando inicio-400.5 0 -30");
        assert_eq!(
            all(&mut r, true),
            vec![
                Ok(LegacyMsg::Waiting),
                Ok(LegacyMsg::PartZero([-400.5, 0.0, -30.0]))
            ]
        );
        r.push(b"donedone\r\ndo");
        assert_eq!(
            all(&mut r, true),
            vec![Ok(LegacyMsg::Done), Ok(LegacyMsg::Done)]
        );
        r.push(b"ne");
        assert_eq!(all(&mut r, true), vec![Ok(LegacyMsg::Done)]);
    }

    #[test]
    fn legacy_number_waits_for_the_end_of_the_read() {
        let mut r = LegacyReader::default();
        r.push(b"-400 0 -3");
        assert_eq!(r.next(false), None);
        r.push(b"0\0");
        assert_eq!(
            r.next(false),
            Some(Ok(LegacyMsg::PartZero([-400.0, 0.0, -30.0])))
        );
    }

    #[test]
    fn legacy_garbage_is_skipped_and_reported() {
        let mut r = LegacyReader::default();
        r.push(b"\xff\xfegarbage\ndone1 2\r\n");
        let got = all(&mut r, true);
        assert!(
            matches!(&got[0], Err(t) if t.contains("garbage")),
            "{got:?}"
        );
        assert_eq!(got[1], Ok(LegacyMsg::Done));
        assert!(matches!(&got[2], Err(t) if t == "1 2"), "{got:?}");
        assert_eq!(got.len(), 3);
    }

    #[test]
    fn legacy_move_is_inverse_of_the_robots_trans() {
        assert_eq!(
            legacy_move(false, [1.0, -2.5, 3.0]),
            "LMOVE,1.000000,2.500000,-3.000000\r\n"
        );
        assert_eq!(
            parse_legacy_cmd("JMOVE,1.000000,2.500000,-3.000000\r\n"),
            LegacyCmd::Move {
                rapid: true,
                xyz: [1.0, 2.5, -3.0]
            }
        );
        assert_eq!(parse_legacy_cmd("inicio\r"), LegacyCmd::Start);
        assert_eq!(parse_legacy_cmd("EXIT"), LegacyCmd::Exit);
        assert_eq!(
            parse_legacy_cmd("SPEED,10"),
            LegacyCmd::Unknown("SPEED,10".into())
        );
        assert_eq!(
            parse_legacy_cmd("LMOVE,1,2"),
            LegacyCmd::Unknown("LMOVE,1,2".into())
        );
    }

    #[test]
    fn v1_round_trips() {
        for c in [
            V1Cmd::Run {
                tag: "7-abcdef01".into(),
            },
            V1Cmd::Speed { seq: 3, mm_s: 12.5 },
            V1Cmd::Move {
                seq: 4,
                rapid: false,
                to: [1.5, -2.0, 0.25],
            },
            V1Cmd::Exit,
        ] {
            assert_eq!(V1Cmd::parse(&c.encode()), Ok(c));
        }
        for m in [
            V1Msg::Hello {
                part_zero: [-400.0, 1.0, -30.0],
            },
            V1Msg::Run {
                tag: "7-ab".into(),
                last_seq: 12,
            },
            V1Msg::Done(9),
            V1Msg::Err {
                seq: 2,
                message: "unknown command \"X\"".into(),
            },
            V1Msg::Bye,
        ] {
            assert_eq!(V1Msg::parse(&m.encode()), Ok(m));
        }
        assert_eq!(V1Cmd::parse("5,FOO,1").unwrap_err().0, 5);
        assert_eq!(V1Cmd::parse("x,LMOVE").unwrap_err().0, 0);
        assert!(V1Msg::parse("garbage").is_err());
    }

    proptest! {
        #[test]
        fn points_survive_the_wire(p in proptest::array::uniform3(-1000f64..1000.0), rapid: bool) {
            match parse_legacy_cmd(&legacy_move(rapid, p)) {
                LegacyCmd::Move { rapid: r, xyz } => {
                    prop_assert_eq!(r, rapid);
                    // The robot program's TRANS(x, -y, -z) gives back p.
                    let back = [xyz[0], -xyz[1], -xyz[2]];
                    for i in 0..3 { prop_assert!((back[i] - p[i]).abs() <= 5e-7); }
                }
                other => prop_assert!(false, "{:?}", other),
            }
            let c = V1Cmd::Move { seq: 1, rapid, to: p };
            match V1Cmd::parse(&c.encode()) {
                Ok(V1Cmd::Move { to, .. }) => for i in 0..3 { prop_assert!((to[i] - p[i]).abs() <= 5e-7); },
                other => prop_assert!(false, "{:?}", other),
            }
        }

        #[test]
        fn legacy_reader_never_panics(chunks in proptest::collection::vec(proptest::collection::vec(any::<u8>(), 0..20), 0..10)) {
            let mut r = LegacyReader::default();
            for c in chunks {
                r.push(&c);
                while r.next(true).is_some() {}
            }
        }
    }
}

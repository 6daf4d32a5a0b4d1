#![allow(clippy::unwrap_used, clippy::expect_used)]
use super::*;
use proptest::prelude::*;

fn frame(s: &str) -> [u8; FRAME_LEN] {
    assert_eq!(s.len(), FRAME_LEN, "{s}");
    s.as_bytes().try_into().unwrap()
}

fn decode_all(chunks: &[&[u8]]) -> Vec<Decoded> {
    let mut d = Decoder::new();
    let mut out = Vec::new();
    for c in chunks {
        d.push(c);
        while let Some(x) = d.pop() {
            out.push(x);
        }
    }
    out
}

fn frames_only(v: Vec<Decoded>) -> Vec<Frame> {
    v.into_iter()
        .filter_map(|d| match d {
            Decoded::Frame(f) => Some(f),
            _ => None,
        })
        .collect()
}

#[test]
fn spec_examples_parse() {
    assert_eq!(
        Frame::parse(&frame(
            "N01S0.0001X+1000************************************F"
        ))
        .unwrap(),
        Frame::Jog {
            step: 0.0001,
            axis: Axis::X,
            count: 1000
        }
    );
    assert_eq!(
        Frame::parse(&frame(
            "N01S0.0001Z-0100************************************F"
        ))
        .unwrap(),
        Frame::Jog {
            step: 0.0001,
            axis: Axis::Z,
            count: -100
        }
    );
    assert_eq!(
        Frame::parse(&frame(
            "N02ZeroX***************************************ZeroXF"
        ))
        .unwrap(),
        Frame::Key(PendantKey::ZeroX)
    );
    assert_eq!(
        Frame::parse(&frame(
            "N03START***************************************40000F"
        ))
        .unwrap(),
        Frame::UploadStart { lines: 40000 }
    );
    assert_eq!(
        Frame::parse(&frame(
            "N03FIN***********************************L0001234567F"
        ))
        .unwrap(),
        Frame::UploadEnd { chars: 1234567 }
    );
    assert_eq!(
        Frame::parse(&frame(
            "N0451*********************************************51F"
        ))
        .unwrap(),
        Frame::Request(Info::Positions)
    );
    assert_eq!(
        Frame::parse(&frame(
            "N04Conected*****************************************F"
        ))
        .unwrap(),
        Frame::Hello(Dialect::Firmware)
    );
}

#[test]
fn encodings_match_the_spec_byte_for_byte() {
    let e = |f: Frame| String::from_utf8(f.encode().to_vec()).unwrap();
    assert_eq!(
        e(Frame::Positions(AxisValues {
            x: 0.0,
            y: -12.5,
            z: 3.25,
            a: 0.0
        })),
        "N51E+00000.0000x-00012.5000y+00003.2500z+00000.0000aF"
    );
    assert_eq!(
        e(Frame::Progress(PendantJob {
            elapsed_s: 65,
            estimated_s: 600,
            total_lines: 40,
            line: 7
        })),
        "N52EL01:05ES10:00NL0040LA0007***********************F"
    );
    // Issue 26: a status line for the LCD rides in the padding after the line number.
    assert_eq!(
        e(Frame::ProgressWithStatus {
            job: PendantJob {
                elapsed_s: 65,
                estimated_s: 600,
                total_lines: 40,
                line: 7
            },
            status: "M0 change clamp".into()
        }),
        "N52EL01:05ES10:00NL0040LA0007M0 change clamp********F"
    );
    assert_eq!(
        Frame::parse(b"N52EL01:05ES10:00NL0040LA0007M0 change clamp********F").unwrap(),
        Frame::ProgressWithStatus {
            job: PendantJob {
                elapsed_s: 65,
                estimated_s: 600,
                total_lines: 40,
                line: 7
            },
            status: "M0 change clamp".into()
        }
    );
    // Too long, or a `*` inside it, or a space anywhere else: not a frame.
    assert!(Frame::parse(b"N52EL01:05ES10:00NL0040LA0007M0 change clamp now to*F").is_err());
    assert!(Frame::parse(b"N52EL01:05ES10:00NL0040LA0007M0*change clamp********F").is_err());
    assert!(Frame::parse(b"N51E+00000.0000x-00012.5000y+00003.2500z+00000.000 aF").is_err());
    let (b, note) = Frame::ProgressWithStatus {
        job: PendantJob::default(),
        status: "M6 T2 3 mm drill * 0.5 flute".into(),
    }
    .encode_checked();
    assert_eq!(&b[29..52], b"M6 T2 3 mm drill x 0***");
    assert!(note.is_some());
    assert_eq!(
        e(Frame::UploadConfirmed),
        "N53Confirm:Gcode-load*******************************F"
    );
    assert_eq!(
        e(Frame::Hello(Dialect::Firmware)),
        "N04Conected*****************************************F"
    );
    assert_eq!(
        e(Frame::Heartbeat {
            dialect: Dialect::Firmware,
            counter: 0
        }),
        "N05Vivo0000000**************************************F"
    );
    assert_eq!(
        e(Frame::Jog {
            step: 0.0001,
            axis: Axis::X,
            count: 1000
        }),
        "N01S0.0001X+1000************************************F"
    );
    assert_eq!(
        e(Frame::Key(PendantKey::ZeroX)),
        "N02ZeroX***************************************ZeroXF"
    );
    assert!(e(Frame::Hello(Dialect::Document)).starts_with("N54"));
    assert!(e(Frame::Heartbeat {
        dialect: Dialect::Document,
        counter: 3
    })
    .starts_with("N55Vivo0000003"));
}

#[test]
fn out_of_range_numbers_are_clamped_and_reported() {
    let (b, note) = Frame::Positions(AxisValues {
        x: 123456.0,
        y: -1e9,
        z: f64::NAN,
        a: 1.0,
    })
    .encode_checked();
    assert_eq!(b.len(), FRAME_LEN);
    let s = String::from_utf8(b.to_vec()).unwrap();
    assert_eq!(s, "N51E+99999.9999x-99999.9999y+00000.0000z+00001.0000aF");
    assert!(note.unwrap().contains("X=123456"));
    let (b, note) = Frame::Progress(PendantJob {
        elapsed_s: 1 << 40,
        estimated_s: 0,
        total_lines: 40000,
        line: 12,
    })
    .encode_checked();
    assert!(String::from_utf8(b.to_vec())
        .unwrap()
        .starts_with("N52EL99:59ES00:00NL9999LA0012"));
    assert!(note.is_some());
    // Rounding up must not overflow the field.
    let s = Frame::Positions(AxisValues {
        x: 99999.99996,
        ..Default::default()
    })
    .encode();
    assert_eq!(&s[4..16], b"+99999.9999x");
}

#[test]
fn every_frame_round_trips() {
    for f in sample_frames() {
        assert_eq!(Frame::parse(&f.encode()).unwrap(), f);
    }
}

fn sample_frames() -> Vec<Frame> {
    let mut v = vec![
        Frame::Jog {
            step: 0.01,
            axis: Axis::Y,
            count: -3,
        },
        Frame::Jog {
            step: 1.0,
            axis: Axis::A,
            count: 9999,
        },
        Frame::UploadEnd { chars: 0 },
        Frame::Request(Info::Positions),
        Frame::Request(Info::Job),
        Frame::Hello(Dialect::Firmware),
        Frame::Hello(Dialect::Document),
        Frame::Heartbeat {
            dialect: Dialect::Document,
            counter: 42,
        },
        Frame::Positions(AxisValues {
            x: 1.5,
            y: -2.25,
            z: 0.0001,
            a: -99999.0,
        }),
        Frame::Progress(PendantJob {
            elapsed_s: 5,
            estimated_s: 3000,
            total_lines: 10,
            line: 9,
        }),
        Frame::ProgressWithStatus {
            job: PendantJob {
                elapsed_s: 5,
                estimated_s: 3000,
                total_lines: 10,
                line: 9,
            },
            status: "M0 change clamp".into(),
        },
        Frame::UploadConfirmed,
    ];
    v.extend(KEY_WORDS.iter().map(|(_, k)| Frame::Key(*k)));
    v
}

#[test]
fn malformed_frames_are_skipped_with_a_reason() {
    let bad = b"N01S0.0001Q+1000************************************F";
    let good = Frame::Key(PendantKey::Stop).encode();
    let out = decode_all(&[bad, &good]);
    assert!(
        matches!(&out[0], Decoded::Skipped { reason, .. } if reason.contains("axis")),
        "{out:?}"
    );
    assert_eq!(frames_only(out), vec![Frame::Key(PendantKey::Stop)]);
}

/// Found by the re-encode proptest: an action frame with no '*' padding used to panic on an
/// overlapping slice (the whole transport thread with it) instead of being skipped.
#[test]
fn an_action_frame_without_padding_is_an_error_not_a_panic() {
    let text = "::q+.&0+f0+#:4+d....++:+.:y.+9+9:~9+.i+9.f.0+h9.:";
    let b = frame(&format!("N02{text}F"));
    let e = Frame::parse(&b).unwrap_err();
    assert!(e.contains("action"), "{e}");
    // The same word with no padding between its two copies is refused too.
    let b = frame(&format!("N02{}F", "STOP".repeat(12) + "S"));
    assert!(Frame::parse(&b).is_err());
}

fn lines_of(out: &[Decoded]) -> Vec<String> {
    out.iter()
        .filter_map(|d| match d {
            Decoded::Line(l) => Some(String::from_utf8(l.clone()).unwrap()),
            _ => None,
        })
        .collect()
}

#[test]
fn upload_lines_starting_with_n_are_lines_not_frames() {
    // Firmware style: one read per line, no newline. Lines that start with N, even with a
    // frame's type digits, or that end like the start of a frame, are program text.
    let start = Frame::UploadStart { lines: 5 }.encode();
    let fin = Frame::UploadEnd { chars: 20 }.encode();
    let poll = Frame::Request(Info::Positions).encode();
    let out = decode_all(&[
        &start,
        b"N10 G1 X5",
        b"N0451G0Z1",
        b"(SECTION N04",
        b"N01",
        b"G0 Z1",
        &fin,
        &poll,
    ]);
    assert_eq!(
        lines_of(&out),
        ["N10 G1 X5", "N0451G0Z1", "(SECTION N04", "N01", "G0 Z1"]
    );
    let frames = frames_only(out);
    assert_eq!(frames.last(), Some(&Frame::Request(Info::Positions)));
    assert!(frames.contains(&Frame::UploadEnd { chars: 20 }));
}

#[test]
fn a_poll_during_an_upload_aborts_it_and_is_decoded() {
    // The firmware's STOP key leaves its upload loop without N03FIN; its main loop then polls.
    let start = Frame::UploadStart { lines: 9 }.encode();
    let poll = Frame::Request(Info::Positions).encode();
    let key = Frame::Key(PendantKey::Stop).encode();
    let mut merged = b"G1 X2".to_vec();
    merged.extend_from_slice(&poll);
    merged.extend_from_slice(&poll);
    let cases: Vec<Vec<&[u8]>> = vec![
        // One poll per read.
        vec![&start, b"G1 X1", &poll, &poll],
        // A poll merged with the last line and with the next poll.
        vec![&start, b"G1 X1", &merged],
        // A poll split over two reads (firmware style and newline style).
        vec![&start, b"G1 X1", &poll[..20], &poll[20..], &poll],
        vec![&start, b"G1 X1\n", &poll[..3], &poll[3..], &poll],
        // Any key.
        vec![&start, b"G1 X1", &key, &poll],
    ];
    for (n, chunks) in cases.iter().enumerate() {
        // The last poll decoded as a frame shows raw-line mode ended.
        let out = decode_all(chunks);
        let aborted = out
            .iter()
            .position(|x| matches!(x, Decoded::UploadAborted { .. }))
            .unwrap_or_else(|| panic!("case {n}: not aborted: {out:?}"));
        let lines = lines_of(&out[..aborted]);
        assert!(lines[0] == "G1 X1", "case {n}: {lines:?}");
        assert!(
            lines.iter().all(|l| !l.contains("N04")),
            "case {n}: {lines:?}"
        );
        let after = frames_only(out[aborted..].to_vec());
        // Every frame sent after the last line is decoded: two in each case.
        assert_eq!(after.len(), 2, "case {n}: {out:?}");
        assert_eq!(after[1], Frame::Request(Info::Positions), "case {n}");
    }
}

#[test]
fn a_heartbeat_shaped_line_is_program_text() {
    // N05/N5x payloads are free-form and a pendant never sends them: no abort.
    let start = Frame::UploadStart { lines: 1 }.encode();
    let line = format!("N05G1X1Y2Z3{}F", "0".repeat(41));
    assert_eq!(line.len(), FRAME_LEN);
    let mut d = Decoder::new();
    d.push(&start);
    d.push(line.as_bytes());
    assert!(d.in_upload());
}

#[test]
fn two_lines_in_one_read_and_lines_split_across_reads() {
    let start = Frame::UploadStart { lines: 3 }.encode();
    let fin = Frame::UploadEnd { chars: 0 }.encode();
    let mut stream = start.to_vec();
    stream.extend_from_slice(b"N10 G1 X5\nG1 Y2\r\nG1 Z3\n");
    stream.extend_from_slice(&fin);
    // Split at every position: the result must not change.
    for cut in 0..stream.len() {
        let out = decode_all(&[&stream[..cut], &stream[cut..]]);
        let lines: Vec<_> = out
            .iter()
            .filter_map(|d| match d {
                Decoded::Line(l) => Some(l.as_slice()),
                _ => None,
            })
            .collect();
        // A cut inside the first line before any newline was seen splits it in the firmware
        // (unterminated) reading; from the first newline on, lines are reassembled.
        if cut <= FRAME_LEN || cut > FRAME_LEN + 9 {
            assert_eq!(
                lines,
                vec![&b"N10 G1 X5"[..], b"G1 Y2", b"G1 Z3"],
                "cut at {cut}"
            );
        }
        assert!(
            frames_only(out.clone()).contains(&Frame::UploadEnd { chars: 0 }),
            "cut {cut}"
        );
    }
}

#[test]
fn fin_merged_with_the_last_line_ends_it() {
    let start = Frame::UploadStart { lines: 1 }.encode();
    let fin = Frame::UploadEnd { chars: 5 }.encode();
    let mut last = b"G0 X1".to_vec();
    last.extend_from_slice(&fin[..20]);
    let out = decode_all(&[&start, &last, &fin[20..]]);
    assert_eq!(out[1], Decoded::Line(b"G0 X1".to_vec()), "{out:?}");
    assert_eq!(out[2], Decoded::Frame(Frame::UploadEnd { chars: 5 }));
}

#[test]
fn overlong_raw_line_aborts_the_upload() {
    let start = Frame::UploadStart { lines: 1 }.encode();
    let mut d = Decoder::new();
    d.push(&start);
    d.push(b"G1\n");
    d.push(&vec![b'X'; MAX_LINE_LEN + 1]);
    let mut aborted = false;
    while let Some(x) = d.pop() {
        aborted |= matches!(x, Decoded::UploadAborted { .. });
    }
    assert!(aborted);
    assert!(!d.in_upload());
}

fn any_frame() -> impl Strategy<Value = Frame> {
    let axis = prop_oneof![Just(Axis::X), Just(Axis::Y), Just(Axis::Z), Just(Axis::A)];
    let step = prop_oneof![Just(0.0001), Just(0.001), Just(0.01), Just(0.1), Just(1.0)];
    let pos = -99999.0f64..99999.0;
    prop_oneof![
        (step, axis, 1i32..=9999, any::<bool>()).prop_map(|(step, axis, n, neg)| Frame::Jog {
            step,
            axis,
            count: if neg { -n } else { n }
        }),
        (0..KEY_WORDS.len()).prop_map(|i| Frame::Key(KEY_WORDS[i].1)),
        Just(Frame::Request(Info::Positions)),
        Just(Frame::Request(Info::Job)),
        any::<u32>().prop_map(|c| Frame::Heartbeat {
            dialect: Dialect::Document,
            counter: c % 10_000_000
        }),
        (pos.clone(), pos.clone(), pos.clone(), pos).prop_map(|(x, y, z, a)| {
            // Compare after one encode/parse, which rounds to 4 decimals.
            let p = AxisValues { x, y, z, a };
            Frame::parse(&Frame::Positions(p).encode()).unwrap()
        }),
    ]
}

proptest! {
    #[test]
    fn any_split_or_merge_decodes_to_the_same_frames(
        frames in proptest::collection::vec(any_frame(), 1..20),
        cuts in proptest::collection::vec(any::<prop::sample::Index>(), 0..10),
    ) {
        let stream: Vec<u8> = frames.iter().flat_map(|f| f.encode()).collect();
        let mut points: Vec<usize> = cuts.iter().map(|i| i.index(stream.len() + 1)).collect();
        points.push(0);
        points.push(stream.len());
        points.sort_unstable();
        let chunks: Vec<&[u8]> = points.windows(2).map(|w| &stream[w[0]..w[1]]).collect();
        let out = decode_all(&chunks);
        prop_assert!(out.iter().all(|d| matches!(d, Decoded::Frame(_))), "{:?}", out);
        prop_assert_eq!(frames_only(out), frames);
    }

    #[test]
    fn garbage_then_a_valid_frame_resynchronises(
        garbage in proptest::collection::vec(any::<u8>(), 0..200),
        frames in proptest::collection::vec(any_frame(), 1..5),
        cut in any::<prop::sample::Index>(),
    ) {
        let mut stream = garbage.clone();
        for f in &frames {
            stream.extend_from_slice(&f.encode());
        }
        let c = cut.index(stream.len() + 1);
        let out = frames_only(decode_all(&[&stream[..c], &stream[c..]]));
        // Random garbage essentially never holds a whole valid frame (and never an upload
        // start, which would change the mode); the real frames must all come out, in order.
        prop_assert!(out.ends_with(&frames), "{:?} does not end with {:?}", out, frames);
    }

    #[test]
    fn whatever_parses_re_encodes_to_itself(
        kind in 0usize..10,
        payload in proptest::collection::vec(
            prop_oneof![Just(b'*'), Just(b'0'), Just(b'9'), Just(b'.'), Just(b':'), Just(b'+'), 32u8..127],
            49,
        ),
    ) {
        let kinds = ["01", "02", "03", "04", "05", "51", "52", "53", "54", "55"];
        let mut b = [0u8; FRAME_LEN];
        b[0] = b'N';
        b[1..3].copy_from_slice(kinds[kind].as_bytes());
        b[3..52].copy_from_slice(&payload);
        b[52] = b'F';
        if let Ok(f) = Frame::parse(&b) {
            prop_assert_eq!(Frame::parse(&f.encode()), Ok(f));
        }
    }

    #[test]
    fn parse_never_panics(bytes in proptest::collection::vec(any::<u8>(), FRAME_LEN..=FRAME_LEN)) {
        let mut b = [0u8; FRAME_LEN];
        b.copy_from_slice(&bytes);
        b[0] = b'N';
        b[FRAME_LEN - 1] = b'F';
        let _ = Frame::parse(&b);
    }
}

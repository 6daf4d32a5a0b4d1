//! Unit tests per modal group, per word, and for the error paths.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::needless_range_loop)]

use fresa_gcode::*;
use std::io::{BufRead, BufReader, Read};

fn run_cfg(src: &str, cfg: Config) -> Result<Vec<Motion>, GcodeError> {
    Interpreter::new(src.as_bytes(), cfg).collect()
}

fn run(src: &str) -> Result<Vec<Motion>, GcodeError> {
    run_cfg(src, Config::default())
}

fn err(src: &str) -> GcodeError {
    match run(src) {
        Ok(m) => panic!("expected an error for {src:?}, got {m:?}"),
        Err(e) => e,
    }
}

fn moves(src: &str) -> Vec<Motion> {
    run(src)
        .unwrap()
        .into_iter()
        .filter(|m| m.end_point().is_some())
        .collect()
}

fn close(a: Point, b: Point) -> bool {
    (0..3).all(|i| (a[i] - b[i]).abs() < 1e-9)
}

#[test]
fn rapid_and_linear_with_modal_continuation() {
    let m = moves("G0 X1 Y2\nZ3\nG1 X4 F100\nY5\n");
    assert_eq!(
        m[0],
        Motion::Rapid {
            line: 1,
            from: [0.0; 3],
            to: [1.0, 2.0, 0.0],
            a: None
        }
    );
    assert_eq!(
        m[1],
        Motion::Rapid {
            line: 2,
            from: [1.0, 2.0, 0.0],
            to: [1.0, 2.0, 3.0],
            a: None
        }
    );
    assert_eq!(
        m[3],
        Motion::Linear {
            line: 4,
            from: [4.0, 2.0, 3.0],
            to: [4.0, 5.0, 3.0],
            feed_mm_min: 100.0,
            a: None
        }
    );
}

#[test]
fn lower_case_no_spaces_and_mid_line_comments() {
    let m = moves("g0x1y2(comment)z3;tail\ng1z-.1f24");
    assert_eq!(m[0].end_point(), Some([1.0, 2.0, 3.0]));
    assert_eq!(m[1].end_point(), Some([1.0, 2.0, -0.1]));
}

#[test]
fn feed_is_units_per_minute() {
    let m = moves("G21 G1 X1 F600\nG20 G1 X1 F10\n");
    match m[0] {
        Motion::Linear { feed_mm_min, .. } => assert_eq!(feed_mm_min, 600.0),
        _ => panic!(),
    }
    match m[1] {
        Motion::Linear {
            feed_mm_min, to, ..
        } => {
            assert!((feed_mm_min - 254.0).abs() < 1e-9);
            assert!(close(to, [25.4, 0.0, 0.0]));
        }
        _ => panic!(),
    }
}

#[test]
fn unit_change_keeps_the_physical_feed() {
    let m = moves("G21 F254\nG20 G1 X1\nG21 G1 X2\n");
    for mv in &m {
        match mv {
            Motion::Linear { feed_mm_min, .. } => assert!((feed_mm_min - 254.0).abs() < 1e-9),
            _ => panic!("{mv:?}"),
        }
    }
}

#[test]
fn feed_missing_or_zero_is_an_error() {
    let e = err("G1 X1\n");
    assert_eq!((e.line, e.kind), (1, ErrorKind::Invalid));
    assert!(e.message.contains("feed"), "{e}");
    assert!(err("F0\nG1 X1\n").message.contains("zero"));
}

#[test]
fn distance_modes_g90_g91() {
    let m = moves("G91 G0 X1 Y1\nX1\nG90 X0\n");
    assert_eq!(m[1].end_point(), Some([2.0, 1.0, 0.0]));
    assert_eq!(m[2].end_point(), Some([0.0, 1.0, 0.0]));
}

#[test]
fn units_g20_g21() {
    let m = moves("G20 G0 X1\nG21 X1\n");
    assert!(close(m[0].end_point().unwrap(), [25.4, 0.0, 0.0]));
    assert!(close(m[1].end_point().unwrap(), [1.0, 0.0, 0.0]));
    let a = analyse("G20 G0 X1".as_bytes(), &AnalysisOptions::default()).unwrap();
    assert!(a.units_inch_seen);
}

#[test]
fn axis_words_without_motion_mode_are_an_error() {
    let e = err("X10\n");
    assert_eq!((e.line, e.column, e.kind), (1, 1, ErrorKind::Invalid));
    let e = err("G0 X1\nG80\nY2\n");
    assert_eq!(e.line, 3);
}

#[test]
fn same_modal_group_twice_is_an_error() {
    let e = err("G0 G1 X1 F1\n");
    assert_eq!((e.line, e.column), (1, 4));
    assert!(e.message.contains("G0 and G1"), "{e}");
    assert!(err("G90 G91\n").message.contains("same modal group"));
    assert!(err("G17 G18\n").message.contains("same modal group"));
    assert!(err("M3 M5\n").message.contains("same modal group"));
    assert!(err("X1 X2\n").message.contains("repeated"));
}

#[test]
fn g80_beside_another_motion_code_is_dropped_as_rs274_does() {
    let m = moves("G0 G80 X1 Y2\nG1 G80 X3 F100\nG80 G0 X4\n");
    assert!(matches!(m[0], Motion::Rapid { line: 1, .. }), "{m:?}");
    assert!(matches!(m[1], Motion::Linear { line: 2, .. }), "{m:?}");
    assert!(matches!(m[2], Motion::Rapid { line: 3, .. }), "{m:?}");
    assert!(close(m[2].end_point().unwrap(), [4.0, 2.0, 0.0]));
    // Two motion codes that are not G80 still conflict; G80 twice is G80 (axis words refused).
    assert!(err("G0 G1 X1 F1\n").message.contains("same modal group"));
    assert!(!err("G80 G80 X1\n").message.contains("same modal group"));
}

#[test]
fn several_groups_on_one_line() {
    let m = run("G17 G21 G90 G54 G0 X1 Y2 Z3 S1000 M3 M8 T2 M6\n").unwrap();
    // LinuxCNC order: tool change, spindle, coolant, work offset, motion.
    assert!(matches!(m[0], Motion::ToolChange { tool: 2, .. }));
    assert!(matches!(
        m[1],
        Motion::Spindle {
            direction: SpindleDirection::Clockwise,
            rpm,
            ..
        } if rpm == 1000.0
    ));
    assert!(matches!(
        m[2],
        Motion::Coolant {
            mist: false,
            flood: true,
            ..
        }
    ));
    assert!(matches!(m[3], Motion::WorkOffset { system: 1, .. }));
    assert!(matches!(m[4], Motion::Rapid { .. }));
}

#[test]
fn spindle_coolant_and_stops() {
    let m = run("S500 M4\nS600\nM5\nM7 M8\nM9\nM1\nM0 (msg, check tool)\n(MSG,hello)\nG4 P1.5\nM30\nG0 X99\n")
        .unwrap();
    let want = vec![
        Motion::Spindle {
            line: 1,
            direction: SpindleDirection::CounterClockwise,
            rpm: 500.0,
        },
        Motion::Spindle {
            line: 2,
            direction: SpindleDirection::CounterClockwise,
            rpm: 600.0,
        },
        Motion::Spindle {
            line: 3,
            direction: SpindleDirection::Off,
            rpm: 600.0,
        },
        Motion::Coolant {
            line: 4,
            mist: true,
            flood: true,
        },
        Motion::Coolant {
            line: 5,
            mist: false,
            flood: false,
        },
        Motion::Pause {
            line: 6,
            optional: true,
            message: None,
        },
        Motion::Pause {
            line: 7,
            optional: false,
            message: Some("check tool".into()),
        },
        Motion::Message {
            line: 8,
            text: "hello".into(),
        },
        Motion::Dwell {
            line: 9,
            seconds: 1.5,
        },
        Motion::ProgramEnd { line: 10 },
    ];
    assert_eq!(m, want, "nothing after M30 runs");
}

#[test]
fn program_end_can_continue_when_configured() {
    let cfg = Config {
        stop_at_program_end: false,
        ..Config::default()
    };
    let m = run_cfg("G0 X1\nM2\nG91 G0 X1\n", cfg).unwrap();
    assert_eq!(m.len(), 3);
    assert_eq!(m[2].end_point(), Some([2.0, 0.0, 0.0]));
}

#[test]
fn percent_and_block_delete() {
    let m = moves("%\nG0 X1\n/G0 X5\nX2\n%\nG0 X3\n");
    assert_eq!(m.len(), 2);
    assert_eq!(m[1].end_point(), Some([2.0, 0.0, 0.0]));
    let cfg = Config {
        block_delete: false,
        ..Config::default()
    };
    let m = run_cfg("G0 X1\n/G0 X5\n", cfg).unwrap();
    assert_eq!(m[1].end_point(), Some([5.0, 0.0, 0.0]));
}

#[test]
fn work_offsets_and_g53() {
    let mut cfg = Config::default();
    cfg.work_offsets[1] = [100.0, 0.0, 0.0]; // G55 origin at machine X100
    let m = run_cfg("G55 G0 X1\nG53 G0 X0\nG0 X2\n", cfg).unwrap();
    assert!(matches!(m[0], Motion::WorkOffset { system: 2, .. }));
    // G53 X0 is machine X0 = program X-100 in G55; non-modal.
    assert_eq!(m[2].end_point(), Some([-100.0, 0.0, 0.0]));
    assert_eq!(m[3].end_point(), Some([2.0, 0.0, 0.0]));
    assert!(err("G53 X1\n").message.contains("G53"));
    assert!(err("G53 G2 X1 I1 F1\n").message.contains("G53"));
}

#[test]
fn g28_g30_go_to_stored_positions() {
    let cfg = Config {
        g28_position: [1.0, 2.0, 30.0],
        g30_position: [5.0, 5.0, 5.0],
        ..Config::default()
    };
    // No axis words: all axes to the stored position.
    let m = run_cfg("G0 X10 Y10 Z10\nG28\n", cfg.clone()).unwrap();
    assert_eq!(m[1].end_point(), Some([1.0, 2.0, 30.0]));
    // Axis words: via the intermediate point, then only those axes.
    let m = run_cfg("G0 X10 Y10 Z10\nG91 G28 Z5\n", cfg.clone()).unwrap();
    assert_eq!(m[1].end_point(), Some([10.0, 10.0, 15.0]));
    assert_eq!(m[2].end_point(), Some([10.0, 10.0, 30.0]));
    let m = run_cfg("G30\n", cfg.clone()).unwrap();
    assert_eq!(m[0].end_point(), Some([5.0, 5.0, 5.0]));
    // G28.1 stores the current position.
    let m = run_cfg("G0 X7\nG28.1\nG0 X0\nG28\n", cfg).unwrap();
    assert_eq!(m[2].end_point(), Some([7.0, 0.0, 0.0]));
    assert!(err("G28 G1 X1 F1\n").message.contains("axis words"));
}

#[test]
fn tool_length_offset_is_reported_not_applied() {
    let m = run("T3 M6\nG43 H3 G0 Z10\nG49\n").unwrap();
    assert!(matches!(m[0], Motion::ToolChange { tool: 3, .. }));
    assert!(matches!(
        m[1],
        Motion::ToolLengthOffset { tool: Some(3), .. }
    ));
    assert_eq!(m[2].end_point(), Some([0.0, 0.0, 10.0]));
    assert!(matches!(m[3], Motion::ToolLengthOffset { tool: None, .. }));
}

#[test]
fn path_control_and_retract_modes_are_accepted() {
    assert!(run("G64 P0.01\nG61\nG61.1\nG98\nG99\nG40\nG94\n").is_ok());
}

#[test]
fn inverse_time_and_unsupported_words_are_clear_errors() {
    // G93/G95 run (tests/cycles.rs); G93 needs F on each feed move.
    let e = err("G1 X1 F1\nG93 G1 X2\n");
    assert_eq!((e.line, e.column, e.kind), (2, 8, ErrorKind::Invalid));
    assert!(e.message.contains("no feed rate"), "{e}");
    let e = err("G93 G1 X1 F2\nG1 X2\n");
    assert_eq!((e.line, e.column), (2, 4));
    assert!(e.message.contains("inverse-time"), "{e}");
    // O-words, parameters and expressions are interpreted (tests/params.rs);
    // their errors are syntax errors, not "unsupported".
    let e = err("G0 X[1+2\n");
    assert_eq!((e.column, e.kind), (5, ErrorKind::Syntax), "at the '['");
    let e = err("G0 X#<nope>\n");
    assert!(e.message.contains("not defined"), "{e}");
    let e = err("G0 B5\n");
    assert_eq!(e.column, 4);
    assert!(e.message.contains("axis word B"), "{e}");
    for w in ["C", "U", "V", "W"] {
        let e = err(&format!("G0 X1 {w}2\n"));
        assert_eq!(e.column, 7);
        assert!(e.message.contains(&format!("axis word {w}")), "{e}");
    }
    assert!(err("G41 D1\n").message.contains("tool table"));
    assert!(err("G10 L10 P1 Z0\n").message.contains("G10 L10"));
    assert!(err("M62 P1\n").message.contains("M62"));
}

#[test]
fn skip_with_warning_skips_whole_line_and_canned_cycle_lines() {
    let cfg = Config {
        unsupported: Unsupported::SkipWithWarning,
        ..Config::default()
    };
    let mut it = Interpreter::new(
        "G0 X1\nG84 X5 Y5 Z-1 R1 F100\nX6\nG80\nG0 X2 B1\nG0 X3\n".as_bytes(),
        cfg,
    );
    let m: Vec<Motion> = it.by_ref().collect::<Result<_, _>>().unwrap();
    let ends: Vec<Point> = m.iter().filter_map(Motion::end_point).collect();
    assert_eq!(ends, vec![[1.0, 0.0, 0.0], [3.0, 0.0, 0.0]]);
    let w = it.warnings();
    assert_eq!(w.len(), 3, "{w:?}");
    assert_eq!((w[0].line, w[0].column), (2, 1));
    assert_eq!(w[1].line, 3, "canned-cycle continuation is skipped too");
    assert_eq!((w[2].line, w[2].column), (5, 7));
}

#[test]
fn syntax_errors_have_line_and_column() {
    let e = err("G0 X1\nG1 X2 (unclosed\n");
    assert_eq!((e.line, e.column, e.kind), (2, 7, ErrorKind::Syntax));
    let e = err("G0 X\n");
    assert_eq!((e.line, e.column), (1, 4));
    let e = err("G0 X1 $\n");
    assert_eq!(e.column, 7);
    assert_eq!(e.to_string(), "line 1, column 7: unexpected character '$'");
    let e = err("G1.55\n");
    assert_eq!(e.kind, ErrorKind::Syntax);
    let e = err("G0 X1 % \n");
    assert_eq!(e.column, 7);
}

#[test]
fn invalid_utf8_names_line_and_column() {
    let bytes: &[u8] = b"G0 X1\n(caf\xc3\xa9)\nG0 \xffX2\n";
    let r: Result<Vec<Motion>, GcodeError> = Interpreter::new(bytes, Config::default()).collect();
    let e = r.unwrap_err();
    assert_eq!((e.line, e.column, e.kind), (3, 4, ErrorKind::Utf8));
    assert_eq!(e.to_string(), "line 3, column 4: invalid UTF-8");
    // Valid UTF-8 in a comment is fine; outside a comment it is an error.
    let e = err("G0 X1 é\n");
    assert_eq!((e.line, e.column), (1, 7));
}

#[test]
fn crlf_and_missing_final_newline() {
    let m = moves("G0 X1\r\nG0 X2");
    assert_eq!(m.len(), 2);
    assert_eq!(m[1].line(), 2);
}

struct FailingReader {
    sent: bool,
}
impl Read for FailingReader {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        if self.sent {
            Err(std::io::Error::other("disk gone"))
        } else {
            self.sent = true;
            let s = b"G0 X1\nG0 X2\nG0";
            buf[..s.len()].copy_from_slice(s);
            Ok(s.len())
        }
    }
}

#[test]
fn read_errors_become_gcode_errors() {
    let r = BufReader::new(FailingReader { sent: false });
    let out: Vec<_> = Interpreter::new(r, Config::default()).collect();
    assert_eq!(out.len(), 3);
    let e = out[2].clone().unwrap_err();
    assert_eq!((e.line, e.kind), (3, ErrorKind::Io));
    assert!(e.message.contains("disk gone"));
}

#[test]
fn overlong_line_is_an_error_not_unbounded_memory() {
    let cfg = Config {
        max_line_bytes: 100,
        ..Config::default()
    };
    let mut src = String::from("G0 X1\n(");
    src.push_str(&"a".repeat(10_000));
    let r = BufReader::with_capacity(16, src.as_bytes());
    let e = Interpreter::new(r, cfg).find_map(Result::err).unwrap();
    assert_eq!((e.line, e.kind), (2, ErrorKind::Io));
}

#[test]
fn lines_split_across_small_buffers() {
    let src = "G0 X1.25 Y-3\nG1 Z-0.5 F100\nG2 X3.25 Y-3 I1 J0\n";
    let a: Vec<_> = run(src).unwrap();
    let r: &mut dyn BufRead = &mut BufReader::with_capacity(3, src.as_bytes());
    let b: Vec<_> = Interpreter::new(r, Config::default())
        .collect::<Result<_, _>>()
        .unwrap();
    assert_eq!(a, b);
}

#[test]
fn errors_and_analysis_serialise_to_json() {
    let e = err("G0 X1 $\n");
    let j = serde_json::to_string(&e).unwrap();
    assert!(
        j.contains("\"line\":1") && j.contains("\"column\":7"),
        "{j}"
    );
    let a = analyse("G0 X1\nG1 X2 F60\n".as_bytes(), &AnalysisOptions::default()).unwrap();
    let j = serde_json::to_string(&a).unwrap();
    assert!(j.contains("cutting_bounds"), "{j}");
}

#[test]
fn analysis_lengths_and_time() {
    let src = "G0 X0 Y0 Z0\nG0 X50\nG1 Y100 F600\nG4 P2\nG2 X50 Y100 I10 J0\nM2\n";
    let opts = AnalysisOptions {
        rapid_mm_min: 3000.0,
        ..AnalysisOptions::default()
    };
    let a = analyse(src.as_bytes(), &opts).unwrap();
    assert_eq!(a.lines, 6);
    assert_eq!(a.motion_lines, 4);
    assert_eq!((a.rapid_moves, a.linear_moves, a.arc_moves), (2, 1, 1));
    assert!((a.rapid_length_mm - 50.0).abs() < 1e-9);
    let circle = 2.0 * std::f64::consts::PI * 10.0;
    assert!((a.cutting_length_mm - (100.0 + circle)).abs() < 1e-9);
    let want = 50.0 / 3000.0 * 60.0 + (100.0 + circle) / 600.0 * 60.0 + 2.0;
    assert!((a.estimated_seconds - want).abs() < 1e-9);
    let cb = a.cutting_bounds.unwrap();
    assert!(close(cb.min, [50.0, 0.0, 0.0]));
    assert!(close(cb.max, [70.0, 110.0, 0.0]));
    let rb = a.rapid_bounds.unwrap();
    assert_eq!((rb.min, rb.max), ([0.0; 3], [50.0, 0.0, 0.0]));
    assert!(a.program_end);
}

#[test]
fn byte_order_mark_is_ignored() {
    let m = moves("\u{feff}G0 X1\n");
    assert_eq!(m[0].end_point(), Some([1.0, 0.0, 0.0]));
}

#[test]
fn motions_serialise_with_a_type_tag() {
    let m = moves("G0 X1\n");
    let j = serde_json::to_string(&m[0]).unwrap();
    assert!(j.starts_with("{\"type\":\"Rapid\",\"line\":1"), "{j}");
}

#[test]
fn linearised_uses_the_config_tolerance() {
    let cfg = Config {
        arc_tolerance_mm: 0.1,
        ..Config::default()
    };
    let n = Interpreter::new("G0 X10\nG2 I-10 F100\n".as_bytes(), cfg)
        .linearised()
        .count();
    assert_eq!(n as u64, 1 + segments_for(10.0, std::f64::consts::TAU, 0.1));
}

#[test]
fn config_deserialises_with_defaults() {
    let cfg: Config =
        serde_json::from_str(r#"{"unsupported":"SkipWithWarning","g28_position":[0,0,50]}"#)
            .unwrap();
    assert_eq!(cfg.unsupported, Unsupported::SkipWithWarning);
    assert_eq!(cfg.g28_position, [0.0, 0.0, 50.0]);
    assert_eq!(cfg.arc_tolerance_mm, 0.002);
    let opts: AnalysisOptions = serde_json::from_str(r#"{"rapid_mm_min":8000}"#).unwrap();
    assert_eq!(opts.rapid_mm_min, 8000.0);
    assert_eq!(opts.config, Config::default());
}

#[test]
fn skipping_never_changes_what_later_lines_do() {
    let skip = Config {
        unsupported: Unsupported::SkipWithWarning,
        ..Config::default()
    };
    // A skipped line that sets a modal group later lines depend on is an error.
    for src in ["G91 G0 X1 B5\n", "G20 B1\n", "G18 B1\n", "G55 C2\n"] {
        let e = run_cfg(src, skip.clone()).unwrap_err();
        assert!(e.message.contains("cannot be skipped"), "{src}: {e}");
    }
    // An incremental move cannot be skipped either.
    let e = run_cfg("G91\nG0 X1 B5\n", skip.clone()).unwrap_err();
    assert!(e.message.contains("incremental"), "{e}");
    // Also when only A moves: skipping it would shift every later incremental A move.
    let e = run_cfg("G91\nG0 A5 B5\n", skip.clone()).unwrap_err();
    assert!(e.message.contains("incremental"), "{e}");
    // A skipped motion mode makes the following modal lines skip too.
    let mut it = Interpreter::new("G1 X1 F1\nG0 X5 B5\nX6\nG1 X7\n".as_bytes(), skip);
    let ends: Vec<Point> = it.by_ref().filter_map(|m| m.unwrap().end_point()).collect();
    assert_eq!(ends, vec![[1.0, 0.0, 0.0], [7.0, 0.0, 0.0]]);
    assert_eq!(it.warnings().len(), 2);
    assert!(it.warnings()[1].message.contains("motion mode is unknown"));
}

#[test]
fn analysis_warns_where_work_systems_mix() {
    let a = analyse(
        "G54 G0 X1\nG55\nG0 X2\n".as_bytes(),
        &AnalysisOptions::default(),
    )
    .unwrap();
    assert_eq!(a.warnings.len(), 1);
    assert_eq!(a.warnings[0].line, 3);
    assert!(a.warnings[0].message.contains("G55"));
    let a = analyse("G55\nG0 X2\n".as_bytes(), &AnalysisOptions::default()).unwrap();
    assert!(a.warnings.is_empty(), "one system only: {:?}", a.warnings);
}

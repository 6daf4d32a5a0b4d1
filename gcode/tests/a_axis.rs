//! The rotary A axis (degrees): the motion stream's `a` field, the analysis's A range, and
//! what a consumer without an A axis relies on (`Motion::rotary` is `Some` exactly on moves
//! that turn A). tests/conformance.rs compares the moves with rs274's.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_gcode::{analyse, AnalysisOptions, Config, Interpreter, Motion, RotaryMove};

fn run(src: &str) -> Vec<Motion> {
    Interpreter::new(src.as_bytes(), Config::default())
        .collect::<Result<_, _>>()
        .unwrap()
}

#[test]
fn moves_carry_a_only_when_it_turns_and_json_stays_as_before_without_it() {
    let m = run("G0 X1\nG1 X2 A90 F100\nG1 Y1\nG91 G0 A-10\nG90 G20 G1 X0 A0 F1\n");
    let rot: Vec<Option<RotaryMove>> = m.iter().map(Motion::rotary).collect();
    assert_eq!(
        rot,
        [
            None,
            Some(RotaryMove {
                from: 0.0,
                to: 90.0
            }),
            None,
            Some(RotaryMove {
                from: 90.0,
                to: 80.0
            }),
            // G20 scales lengths, never degrees.
            Some(RotaryMove {
                from: 80.0,
                to: 0.0
            }),
        ]
    );
    let plain = serde_json::to_value(&m[0]).unwrap();
    assert!(plain.get("a").is_none(), "{plain}");
    let turned = serde_json::to_value(&m[1]).unwrap();
    assert_eq!(turned["a"], serde_json::json!({"from": 0.0, "to": 90.0}));
}

#[test]
fn parameters_offsets_and_program_end_keep_a() {
    // #5423 / #<_a> read the A position; G92 A shifts the frame (#5214), G28 homes A.
    let m =
        run("G0 A30\nG0 X[#5423] Y#<_a>\nG92 A0\nG0 A10\nG0 X#5214\nG28.1\nG0 A50\nG28 A0\nM2\n");
    let ends: Vec<(u32, [f64; 3], Option<f64>)> = m
        .iter()
        .filter_map(|m| Some((m.line(), m.end_point()?, m.rotary().map(|r| r.to))))
        .collect();
    assert_eq!(
        ends,
        [
            (1, [0.0, 0.0, 0.0], Some(30.0)),
            (2, [30.0, 30.0, 0.0], None),
            // Work frame: A10 after G92 A0 at A30 is A40.
            (4, [30.0, 30.0, 0.0], Some(40.0)),
            (5, [30.0, 30.0, 0.0], None),
            (7, [30.0, 30.0, 0.0], Some(80.0)),
            // G28 A0: via A0 (program, i.e. 30 in the work frame) to the stored A (40).
            (8, [30.0, 30.0, 0.0], Some(30.0)),
            (8, [30.0, 30.0, 0.0], Some(40.0)),
        ]
    );
    let offset_a = m.iter().find_map(|m| match m {
        Motion::OffsetChange { offset_a, .. } => Some(*offset_a),
        _ => None,
    });
    assert_eq!(offset_a, Some(30.0));
}

#[test]
fn analysis_reports_the_a_range_its_first_line_and_rotary_time() {
    let a = analyse(
        "G21 G90\nG0 X10\nG1 A-30 F600\nG1 A330\nG0 A0\n".as_bytes(),
        &AnalysisOptions::default(),
    )
    .unwrap();
    assert_eq!(a.first_a_line, Some(3));
    let b = a.a_bounds.unwrap();
    assert_eq!((b.min, b.max), (-30.0, 330.0));
    // Rotary-only feeds are degrees per minute: 30 + 360 degrees at 600/min = 39 s.
    let rapid_s = 10.0 / 5000.0 * 60.0;
    assert!(
        (a.estimated_seconds - rapid_s - 39.0).abs() < 1e-9,
        "{}",
        a.estimated_seconds
    );
    let none = analyse("G0 X1\n".as_bytes(), &AnalysisOptions::default()).unwrap();
    assert_eq!((none.a_bounds, none.first_a_line), (None, None));
}

#[test]
fn a_with_arcs_and_canned_cycles_is_a_clear_error() {
    let e = Interpreter::new("G1 F100\nG2 X10 I5 A90\n".as_bytes(), Config::default())
        .find_map(Result::err)
        .unwrap();
    assert_eq!((e.line, e.column), (2, 11));
    assert!(e.message.contains("A axis"), "{e}");
    let e = Interpreter::new("G81 X1 Y1 Z-1 R1 A5 F100\n".as_bytes(), Config::default())
        .find_map(Result::err)
        .unwrap();
    assert!(e.message.contains("canned cycle"), "{e}");
}

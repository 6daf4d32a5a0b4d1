//! Canned cycles: the moves themselves are compared with rs274 in
//! tests/conformance/canned-cycles*.ngc; here, the rules and errors.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_gcode::*;

fn run(src: &str) -> Result<Vec<Motion>, GcodeError> {
    Interpreter::new(src.as_bytes(), Config::default()).collect()
}

fn err(src: &str) -> GcodeError {
    run(src).unwrap_err()
}

#[test]
fn g81_drills_each_hole_and_retracts_to_r_by_default() {
    // LinuxCNC starts in G99: retract to R.
    let m = run("G0 Z5 F100\nG81 X1 Y2 Z-1 R1\nX3\n").unwrap();
    let ends: Vec<Point> = m.iter().filter_map(Motion::end_point).collect();
    assert_eq!(
        ends,
        vec![
            [0.0, 0.0, 5.0],
            [1.0, 2.0, 5.0],
            [1.0, 2.0, 1.0],
            [1.0, 2.0, -1.0],
            [1.0, 2.0, 1.0],
            [3.0, 2.0, 1.0],
            [3.0, 2.0, -1.0],
            [3.0, 2.0, 1.0],
        ]
    );
    assert!(matches!(m[3], Motion::Linear { feed_mm_min, .. } if feed_mm_min == 100.0));
    // G98: back to the initial level (Z5).
    let m = run("G0 Z5 F100\nG98 G81 X1 Y2 Z-1 R1\n").unwrap();
    assert_eq!(m.last().unwrap().end_point(), Some([1.0, 2.0, 5.0]));
}

#[test]
fn dwell_and_peck_cycles() {
    let m = run("G0 Z5 F100\nG82 X1 Z-1 R1 P0.5\n").unwrap();
    assert!(m
        .iter()
        .any(|m| matches!(m, Motion::Dwell { seconds, .. } if *seconds == 0.5)));
    // G83 Q2 from R1 to Z-4: pecks at -1 and -3, then the bottom.
    let m = run("G0 Z5 F100\nG83 X1 Z-4 R1 Q2\n").unwrap();
    let feeds: Vec<f64> = m
        .iter()
        .filter_map(|m| match m {
            Motion::Linear { to, .. } => Some(to[2]),
            _ => None,
        })
        .collect();
    assert_eq!(feeds, vec![-1.0, -3.0, -4.0]);
}

#[test]
fn incremental_repeats_step_the_hole_position() {
    let m = run("G0 Z5 F100\nG91 G81 X10 Z-3 R-4 L3\n").unwrap();
    let bottoms: Vec<Point> = m
        .iter()
        .filter_map(|m| match m {
            Motion::Linear { to, .. } => Some(*to),
            _ => None,
        })
        .collect();
    // R = 5 - 4 = 1, bottom = 1 - 3 = -2.
    assert_eq!(
        bottoms,
        vec![[10.0, 0.0, -2.0], [20.0, 0.0, -2.0], [30.0, 0.0, -2.0]]
    );
}

#[test]
fn cycle_errors_name_line_and_column() {
    let e = err("G0 Z5 F100\nG81 X1 R1\n");
    assert_eq!((e.line, e.column), (2, 5));
    assert!(e.message.contains("needs Z"), "{e}");
    let e = err("G0 Z5 F100\nG81 X1 Z-1\n");
    assert!(e.message.contains("needs R"), "{e}");
    let e = err("G0 Z5 F100\nG81 X1 Z2 R1\n");
    assert!(e.message.contains("below Z"), "{e}");
    let e = err("G0 Z5 F100\nG83 X1 Z-1 R1 Q0\n");
    assert_eq!((e.line, e.column), (2, 15));
    let e = err("G0 Z5 F100\nG81 X1 Z-1 R1 L0\n");
    assert!(e.message.contains("L (repeats)"), "{e}");
    let e = err("G0 Z5\nG81 X1 Z-1 R1\n");
    assert!(e.message.contains("feed"), "{e}");
    let e = err("G0 Z5 F100\nG18 G81 X1 Z-1 R1\n");
    assert_eq!(e.kind, ErrorKind::Unsupported);
    let e = err("G0 Z5 F100\nG83 X1 Z-1000 R1 Q0.0001 L100\n");
    assert!(e.message.contains("moves"), "{e}");
    // Tapping and spindle-stop boring stay clear errors.
    for g in ["G84", "G74", "G86", "G87", "G88", "G76"] {
        let e = err(&format!("G0 Z5 F100\n{g} X1 Z-1 R1\n"));
        assert_eq!((e.line, e.kind), (2, ErrorKind::Unsupported), "{g}");
    }
}

#[test]
fn g92_and_g52_shift_the_origin_and_the_analysis_shows_it() {
    // Motions stay in the work system's frame: G92 X0 at X10 makes X5 land at 15.
    let src =
        "G0 X10\nG92 X0\nG1 X5 F100\nG92.1\nG0 X1\nG52 Y-2\nG0 Y0\nG92.2\nG0 Y0\nG92.3\nG0 Y1\n";
    let m = run(src).unwrap();
    let ends: Vec<Point> = m.iter().filter_map(Motion::end_point).collect();
    assert_eq!(
        ends,
        vec![
            [10.0, 0.0, 0.0],
            [15.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [1.0, -2.0, 0.0],
            [1.0, 0.0, 0.0],
            [1.0, -1.0, 0.0],
        ]
    );
    assert!(matches!(
        m[1],
        Motion::OffsetChange { line: 2, code: 920, offset, .. } if offset == [10.0, 0.0, 0.0]
    ));
    let a = analyse(src.as_bytes(), &AnalysisOptions::default()).unwrap();
    assert_eq!(a.offset_change_count, 5);
    let cmds: Vec<&str> = a
        .offset_changes
        .iter()
        .map(|o| o.command.as_str())
        .collect();
    assert_eq!(cmds, ["G92", "G92.1", "G52", "G92.2", "G92.3"]);
    assert_eq!(a.offset_changes[2].offset, [0.0, -2.0, 0.0]);
    assert_eq!(a.cutting_bounds.unwrap().max[0], 15.0);
    let json = serde_json::to_value(&a).unwrap();
    assert_eq!(json["offset_changes"][0]["line"], 2);
    assert!(json["cutting_length_mm"].is_number(), "old fields stay");
    // G92 needs an axis word; G10 L10/L11 (tool table from the position) are refused.
    let e = err("G0 X1\nG92\n");
    assert_eq!((e.line, e.column), (2, 1));
    let e = err("G10 L11 P1 Z5\n");
    assert_eq!(e.kind, ErrorKind::Unsupported);
}

#[test]
fn polar_coordinates_about_the_origin() {
    let close = |a: Point, b: Point| (0..3).all(|i| (a[i] - b[i]).abs() < 1e-9);
    let ends: Vec<Point> = run("G0 X2 Y0\n^90\n@1\nG91 ^90\n@1\n")
        .unwrap()
        .iter()
        .filter_map(Motion::end_point)
        .collect();
    let want = [
        [2.0, 0.0, 0.0],
        [0.0, 2.0, 0.0],
        [0.0, 1.0, 0.0],
        [-1.0, 0.0, 0.0],
        [-2.0, 0.0, 0.0],
    ];
    assert!(ends.iter().zip(want).all(|(a, b)| close(*a, b)), "{ends:?}");
    // Holes on a circle: G91 ^ steps the angle on every L repeat.
    let m = run("G0 X1 Y0 Z1 F100\nG91 G81 ^90 R-0.5 Z-1 L4\n").unwrap();
    let holes: Vec<Point> = m
        .iter()
        .filter_map(|m| match m {
            Motion::Linear { to, .. } => Some(*to),
            _ => None,
        })
        .collect();
    assert_eq!(holes.len(), 4);
    assert!(close(holes[3], [1.0, 0.0, -0.5]), "{holes:?}");
    let e = err("G0 X1 @2\n");
    assert!(e.message.contains("polar"), "{e}");
    let e = err("G0 @2\n");
    assert_eq!((e.line, e.column), (1, 4));
}

#[test]
fn inverse_time_and_feed_per_revolution_become_mm_per_minute() {
    let feeds = |src: &str| -> Vec<f64> {
        run(src)
            .unwrap()
            .iter()
            .filter_map(|m| match m {
                Motion::Linear { feed_mm_min, .. } | Motion::Arc { feed_mm_min, .. } => {
                    Some(*feed_mm_min)
                }
                _ => None,
            })
            .collect()
    };
    // G93: 10 mm in 1/2 minute = 20 mm/min; a half circle of radius 5 in 1/3 minute.
    let f = feeds("G93 G1 X10 F2\nG2 X20 I5 F3\n");
    assert_eq!(f[0], 20.0);
    assert!(
        (f[1] - 5.0 * std::f64::consts::PI * 3.0).abs() < 1e-9,
        "{f:?}"
    );
    // G95: 0.1 mm per revolution at 1000 rpm; inch F is per revolution too.
    assert_eq!(
        feeds("S1000 M3 G95 F0.1\nG1 X10\nG20 G1 X1 F0.004\n"),
        vec![100.0, 0.004 * 25.4 * 1000.0]
    );
    // A new feed mode needs a new F; G94 in G94 keeps it.
    assert!(err("G1 X1 F100\nG95\nS100 M3\nG1 X2\n")
        .message
        .contains("no feed rate"));
    assert_eq!(feeds("G94 F100\nG94\nG1 X1\n"), vec![100.0]);
    let e = err("G95 F0.1\nG1 X1\n");
    assert!(e.message.contains("spindle stopped"), "{e}");
    let e = err("G0 Z5\nG93 G81 X1 Z-1 R1 F2\n");
    assert!(e.message.contains("inverse-time"), "{e}");
}

//! G5 (cubic) and G5.1 (quadratic) splines: chords within the arc tolerance of the exact
//! curve (evaluated here independently, by de Casteljau), exact end points, LinuxCNC's
//! continuation rule for G5 without I/J, and errors naming line and column.
//! tests/conformance.rs compares the same programs' moves with rs274's.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_gcode::{Config, Interpreter, Motion};

fn run(src: &str, tol: f64) -> Vec<Motion> {
    let cfg = Config {
        arc_tolerance_mm: tol,
        ..Config::default()
    };
    Interpreter::new(src.as_bytes(), cfg)
        .collect::<Result<_, _>>()
        .unwrap()
}

fn err(src: &str) -> fresa_gcode::GcodeError {
    Interpreter::new(src.as_bytes(), Config::default())
        .find_map(Result::err)
        .unwrap_or_else(|| panic!("no error for {src:?}"))
}

fn de_casteljau(ctrl: &[[f64; 2]], t: f64) -> [f64; 2] {
    let mut p = ctrl.to_vec();
    while p.len() > 1 {
        p = p
            .windows(2)
            .map(|w| {
                [
                    w[0][0] + (w[1][0] - w[0][0]) * t,
                    w[0][1] + (w[1][1] - w[0][1]) * t,
                ]
            })
            .collect();
    }
    p[0]
}

fn dist_to_segment(p: [f64; 2], a: [f64; 2], b: [f64; 2]) -> f64 {
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    let l2 = dx * dx + dy * dy;
    let t = if l2 == 0.0 {
        0.0
    } else {
        (((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / l2).clamp(0.0, 1.0)
    };
    (p[0] - a[0] - t * dx).hypot(p[1] - a[1] - t * dy)
}

/// The chords of `line` as a polyline, checked against the curve both ways: every chord
/// vertex lies on the curve, and every curve point lies within `tol` of the polyline.
fn check_curve(moves: &[Motion], line: u32, ctrl: &[[f64; 2]], tol: f64) -> usize {
    let chords: Vec<([f64; 3], [f64; 3], f64)> = moves
        .iter()
        .filter_map(|m| match *m {
            Motion::Linear {
                line: l,
                from,
                to,
                feed_mm_min,
                a: None,
            } if l == line => Some((from, to, feed_mm_min)),
            _ => None,
        })
        .collect();
    assert!(!chords.is_empty(), "no chords on line {line}");
    let first = chords[0].0;
    let last = chords[chords.len() - 1].1;
    let end = ctrl[ctrl.len() - 1];
    assert_eq!([first[0], first[1]], ctrl[0], "starts where the tool is");
    assert_eq!([last[0], last[1]], end, "ends exactly on X/Y");
    for w in chords.windows(2) {
        assert_eq!(w[0].1, w[1].0, "chords join");
    }
    let poly: Vec<[f64; 2]> = std::iter::once([first[0], first[1]])
        .chain(chords.iter().map(|c| [c.1[0], c.1[1]]))
        .collect();
    let samples = 20_000;
    let mut worst = 0.0f64;
    for k in 0..=samples {
        let p = de_casteljau(ctrl, k as f64 / samples as f64);
        let d = poly
            .windows(2)
            .map(|s| dist_to_segment(p, s[0], s[1]))
            .fold(f64::INFINITY, f64::min);
        worst = worst.max(d);
    }
    assert!(
        worst <= tol * 1.0001,
        "line {line}: {worst} mm off the curve (tolerance {tol})"
    );
    // Not absurdly fine either: within 4x of the chords an ideal split would need.
    assert!(
        worst > tol / 16.0 || chords.len() <= 2,
        "line {line}: {} chords for {worst}",
        chords.len()
    );
    chords.len()
}

#[test]
fn quadratic_and_cubic_splines_stay_within_the_tolerance() {
    for tol in [0.1, 0.002] {
        let m = run(
            "G21 G90 G17 F600\nG5.1 X10 Y10 I5 J0\nG5 X30 Y10 I3 J0 P0 Q-4\nG5 X40 Y0 P2 Q4\n",
            tol,
        );
        check_curve(&m, 2, &[[0.0, 0.0], [5.0, 0.0], [10.0, 10.0]], tol);
        check_curve(
            &m,
            3,
            &[[10.0, 10.0], [13.0, 10.0], [30.0, 6.0], [30.0, 10.0]],
            tol,
        );
        // Continuation: I/J are the previous P/Q reflected (LinuxCNC).
        check_curve(
            &m,
            4,
            &[[30.0, 10.0], [30.0, 14.0], [42.0, 4.0], [40.0, 0.0]],
            tol,
        );
    }
}

#[test]
fn splines_keep_z_feed_and_units() {
    // Inch: I/J/P/Q are inches too; Z stays where it was; the feed is the F in effect.
    let m = run("G20 G90 G0 Z0.1\nG1 F10\nG5.1 X1 Y1 I1 J0\n", 0.002);
    let mm = 25.4;
    check_curve(&m, 3, &[[0.0, 0.0], [mm, 0.0], [mm, mm]], 0.002);
    for mv in m.iter().filter(|m| m.line() == 3) {
        let Motion::Linear {
            from,
            to,
            feed_mm_min,
            ..
        } = mv
        else {
            panic!("{mv:?}")
        };
        assert_eq!((from[2], to[2]), (0.1 * mm, 0.1 * mm));
        assert!((feed_mm_min - 254.0).abs() < 1e-9);
    }
}

#[test]
fn spline_errors_name_line_and_column() {
    let e = err("G0 X0 Y0\nG1 F100\nG5 X10 Y10 I1 J1\n");
    assert_eq!(e.line, 3);
    assert!(e.message.contains("P and Q"), "{e}");
    let e = err("F100 G5 X10 Y10 P1 Q1\n");
    assert!(e.message.contains("continues a previous G5"), "{e}");
    let e = err("F100 G5 X10 Y10 I1 P1 Q1\n");
    assert!(e.message.contains("both I and J"), "{e}");
    let e = err("F100 G5.1 X10 Y10 I0 J0\n");
    assert!(e.message.contains("not both zero"), "{e}");
    let e = err("F100 G18 G5.1 X10 Y10 I1\n");
    assert!(e.message.contains("XY plane"), "{e}");
    let e = err("F100 G5.1 X10 Y10 Z1 I1\n");
    assert_eq!(e.column, 19, "at the Z");
    let e = err("F100 G5.1 X10 A5 I1\n");
    assert!(e.message.contains("A axis"), "{e}");
    let e = err("G5.1 X10 Y10 I1\n");
    assert!(e.message.contains("no feed rate"), "{e}");
}

//! Arc construction (R and IJK forms, planes, turns, tolerances) and linearisation.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::needless_range_loop)]

use fresa_gcode::*;
use std::f64::consts::{FRAC_PI_2, PI, TAU};

fn arcs(src: &str) -> Vec<Motion> {
    Interpreter::new(src.as_bytes(), Config::default())
        .collect::<Result<Vec<_>, _>>()
        .unwrap()
        .into_iter()
        .filter(|m| matches!(m, Motion::Arc { .. }))
        .collect()
}

fn one_arc(src: &str) -> (Point, f64, bool) {
    match arcs(src).pop().unwrap() {
        Motion::Arc {
            centre,
            sweep_rad,
            clockwise,
            ..
        } => (centre, sweep_rad, clockwise),
        _ => unreachable!(),
    }
}

fn err(src: &str) -> GcodeError {
    Interpreter::new(src.as_bytes(), Config::default())
        .find_map(Result::err)
        .unwrap_or_else(|| panic!("expected an error for {src:?}"))
}

fn near(a: f64, b: f64) -> bool {
    (a - b).abs() < 1e-9
}

fn near_p(a: Point, b: Point) -> bool {
    (0..3).all(|i| near(a[i], b[i]))
}

#[test]
fn r_arcs_both_signs_both_directions() {
    // Minor arc: positive R.
    let (c, s, cw) = one_arc("F100 G2 X10 Y10 R10");
    assert!(near_p(c, [10.0, 0.0, 0.0]) && near(s, FRAC_PI_2) && cw);
    // Negative R: the long way round (> 180 degrees).
    let (c, s, _) = one_arc("F100 G2 X10 Y10 R-10");
    assert!(
        near_p(c, [0.0, 10.0, 0.0]) && near(s, 3.0 * FRAC_PI_2),
        "{c:?} {s}"
    );
    let (c, s, cw) = one_arc("F100 G3 X10 Y10 R10");
    assert!(near_p(c, [0.0, 10.0, 0.0]) && near(s, FRAC_PI_2) && !cw);
    let (c, s, _) = one_arc("F100 G3 X10 Y10 R-10");
    assert!(near_p(c, [10.0, 0.0, 0.0]) && near(s, 3.0 * FRAC_PI_2));
}

#[test]
fn r_half_circle_and_radius_slightly_too_small() {
    // Exactly 180 degrees: no +0.001 fudge needed.
    let (c, s, _) = one_arc("F100 G2 X10 R5");
    assert!(near_p(c, [5.0, 0.0, 0.0]) && near(s, PI));
    // R 0.002 too small (within 0.005 mm): taken as a half circle (LinuxCNC).
    let (c, s, _) = one_arc("F100 G2 X10 R4.998");
    assert!(near_p(c, [5.0, 0.0, 0.0]) && near(s, PI));
    let e = err("F100 G2 X10 R4.9");
    assert_eq!((e.line, e.column, e.kind), (1, 13, ErrorKind::Arc));
    assert!(err("F100 G2 X0 Y0 R5")
        .message
        .contains("same start and end"));
    assert!(err("F100 G2 Z5 R5").message.contains("end point in the XY"));
}

#[test]
fn ijk_arcs_in_all_three_planes() {
    // G17: quarter circle CCW from (10,0) around origin to (0,10).
    let (c, s, _) = one_arc("G0 X10\nF100 G3 X0 Y10 I-10 J0");
    assert!(near_p(c, [0.0; 3]) && near(s, FRAC_PI_2));
    // G18 (Z first, X second, normal +Y): from Z=20 to X=20 clockwise is 270
    // degrees, as in grbl and LinuxCNC.
    let (c, s, cw) = one_arc("G18\nG1 X0 Z20 F200\nG2 X20 Z0 I0 K-20");
    assert!(near_p(c, [0.0, 0.0, 0.0]) && near(s, 3.0 * FRAC_PI_2) && cw);
    let (_, s, _) = one_arc("G18\nG1 X0 Z20 F200\nG3 X20 Z0 I0 K-20");
    assert!(near(s, FRAC_PI_2));
    // G19 (Y first, Z second, normal +X).
    let (c, s, _) = one_arc("G19\nG1 Y0 Z20 F200\nG2 Y20 Z0 J0 K-20");
    assert!(near_p(c, [0.0, 0.0, 0.0]) && near(s, FRAC_PI_2), "{s}");
    // Offset along the plane normal is rejected (LinuxCNC), zero tolerated.
    let e = err("G0 X10\nF100 G2 X-10 I-10 K1");
    assert_eq!((e.line, e.column), (2, 19));
    assert!(e.message.contains("K word"));
    assert_eq!(arcs("G0 X10\nF100 G2 X-10 I-10 K0").len(), 1);
}

#[test]
fn full_circles_without_axis_words_and_turns() {
    let m = arcs("G0 X-2 Y.75\nG1 Y.5 F30\nG2 J-1.1\n");
    match &m[0] {
        Motion::Arc {
            from,
            to,
            centre,
            sweep_rad,
            turns,
            ..
        } => {
            assert_eq!(from, to);
            assert!(near_p(*centre, [-2.0, -0.6, 0.0]));
            assert!(near(*sweep_rad, TAU) && *turns == 1);
        }
        _ => unreachable!(),
    }
    // P = number of turns; helix with Z.
    let m = arcs("G0 X5\nG3 X5 Y0 Z-3 I-5 P3 F100\n");
    match &m[0] {
        Motion::Arc {
            sweep_rad, turns, ..
        } => assert!(near(*sweep_rad, 3.0 * TAU) && *turns == 3),
        _ => unreachable!(),
    }
    assert!(err("G0 X5\nG3 I-5 P1.5 F100").message.contains("turns"));
}

#[test]
fn tiny_arc_is_not_a_full_circle() {
    let (_, s, _) = one_arc("G0 X10\nG3 X9.9999999995 Y0.0001 I-10 F100");
    assert!(s < 1e-4 && s > 0.0, "{s}");
}

#[test]
fn radius_mismatch_follows_grbl_linuxcnc_rule() {
    // 0.004 mm difference: accepted (a tiny spiral).
    assert_eq!(arcs("G2 X10.004 I5 F100").len(), 1);
    // 0.2 mm on r=5: above 0.005 mm and 0.1 % -> error.
    let e = err("G2 X10.2 I5 F100");
    assert_eq!((e.line, e.column, e.kind), (1, 4, ErrorKind::Arc));
    assert!(e.message.contains("differs"), "{e}");
    // r = 1000: 0.4 mm is within 0.1 %, 0.8 mm is past the 0.5 mm cap.
    assert_eq!(arcs("G2 X2000.4 I1000 F100").len(), 1);
    assert!(err("G2 X2000.8 I1000 F100").message.contains("differs"));
    assert!(err("G2 X1 I0 J0 F100").message.contains("zero radius"));
    assert!(err("G2 X1 R1 I1 F100").message.contains("both R"));
    assert!(err("G2 X1 F100").message.contains("offsets"));
}

#[test]
fn absolute_arc_centres_g90_1() {
    let (c, s, _) = one_arc("G90.1\nG0 X10 Y5\nG3 X-10 Y5 I0 J5 F100");
    assert!(near_p(c, [0.0, 5.0, 0.0]) && near(s, PI));
    assert!(err("G90.1\nG0 X10\nG3 X-10 I0 F100")
        .message
        .contains("G90.1"));
}

#[test]
fn inch_arcs_are_scaled() {
    let (c, _, _) = one_arc("G20 G0 X-0.5\nG2 X0 Y0.5 I0.5 J0 F2.5");
    assert!(near_p(c, [0.0; 3]));
}

#[test]
fn linearise_exact_endpoint_and_pass_through() {
    let src = "G0 X10\nG3 X0 Y10 Z-2 I-10 F300\nG1 X-5\nM2";
    let it = Interpreter::new(src.as_bytes(), Config::default());
    let out: Vec<Motion> = linearise(it, 0.002).collect::<Result<_, _>>().unwrap();
    assert!(matches!(out[0], Motion::Rapid { .. }));
    let segs: Vec<&Motion> = out.iter().filter(|m| m.line() == 2).collect();
    // r=10, tol 0.002: step 2*acos(1-0.0002) -> 40 chords for 90 degrees.
    assert_eq!(segs.len() as u64, segments_for(10.0, FRAC_PI_2, 0.002));
    assert_eq!(segs.len(), 40);
    assert_eq!(segs.last().unwrap().end_point(), Some([0.0, 10.0, -2.0]));
    for m in &segs {
        assert!(matches!(m, Motion::Linear { feed_mm_min, .. } if *feed_mm_min == 300.0));
    }
    assert!(matches!(out.last(), Some(Motion::ProgramEnd { line: 4 })));
}

#[test]
fn linearise_chains_segments() {
    let src = "G0 X10\nG2 I-10 F300\n";
    let it = Interpreter::new(src.as_bytes(), Config::default());
    let mut prev = [10.0, 0.0, 0.0];
    let mut n = 0;
    for m in linearise(it, 0.01).skip(1) {
        match m.unwrap() {
            Motion::Linear { from, to, .. } => {
                assert_eq!(from, prev);
                prev = to;
                n += 1;
            }
            m => panic!("{m:?}"),
        }
    }
    assert_eq!(prev, [10.0, 0.0, 0.0], "full circle closes exactly");
    assert!(n > 4);
}

#[test]
fn arc_bounds_are_analytic() {
    // Quarter arc crossing +Y only.
    let m = arcs("G0 X10\nG3 X-10 Y0 I-10 F100").pop().unwrap();
    let (lo, hi) = ArcGeometry::from_motion(&m).unwrap().bounds();
    assert!(near_p(lo, [-10.0, 0.0, 0.0]) && near_p(hi, [10.0, 10.0, 0.0]));
}

#[test]
fn tolerance_is_clamped() {
    let it = Interpreter::new("G0 X1\nG2 I-1 F1".as_bytes(), Config::default());
    let l = linearise(it, 0.0);
    assert_eq!(l.tolerance(), MIN_TOLERANCE_MM);
    assert_eq!(segments_for(1.0, 0.0, 0.1), 1);
    assert_eq!(segments_for(0.001, TAU, 1.0), 4);
}

#[test]
fn g18_direction_matches_the_smoothieware_fix_example() {
    // From Smoothieware PR #1226 (Vectorcam output): a 90 degree arc over the
    // top (+Z) in each plane; G2 is clockwise seen from +Y for G18.
    let m = arcs("G0 X0.7071068 Y0\nG1 Z0.7071068 F100\nG18 G2 X-0.7071068 Z0.7071068 I-0.7071068 K-0.7071068")
        .pop()
        .unwrap();
    let g = ArcGeometry::from_motion(&m).unwrap();
    assert!((g.sweep.abs() - FRAC_PI_2).abs() < 1e-6, "{}", g.sweep);
    let (_, hi) = g.bounds();
    assert!((hi[2] - 1.0).abs() < 1e-6, "{hi:?}");
    let m = arcs("G0 X0 Y-0.7071068\nG1 Z0.7071068 F100\nG19 G2 Y0.7071068 Z0.7071068 J0.7071068 K-0.7071068")
        .pop()
        .unwrap();
    let g = ArcGeometry::from_motion(&m).unwrap();
    assert!((g.sweep.abs() - FRAC_PI_2).abs() < 1e-6, "{}", g.sweep);
    assert!((g.bounds().1[2] - 1.0).abs() < 1e-6);
}

#[test]
fn absurd_radius_and_turns_are_rejected() {
    let e = err("G2 X2000000000 I1000000000 F100");
    assert!(e.message.contains("limit"), "{e}");
    // Every word within reach, the radius not: a full circle of radius 1.27e6 mm.
    let e = err("G2 I900000 J900000 F100");
    assert!(
        e.message.contains("arc radius") && e.message.contains("limit"),
        "{e}"
    );
    assert!(err("G0 X5\nG3 I-5 P20000 F100").message.contains("turns"));
}

/// Every move's analytic segment count against what `linearise` actually makes of it.
fn assert_counts_match(src: &str, tolerance: f64) -> u64 {
    let motions: Vec<Motion> = Interpreter::new(src.as_bytes(), Config::default())
        .collect::<Result<_, _>>()
        .unwrap();
    let mut total = 0;
    for m in &motions {
        let made = linearise(std::iter::once(Ok(m.clone())), tolerance)
            .filter(|c| matches!(c, Ok(Motion::Linear { .. } | Motion::Rapid { .. })))
            .count() as u64;
        assert_eq!(
            segments_of(m, tolerance),
            made,
            "{src:?} at {tolerance}: {m:?}"
        );
        total += made;
    }
    total
}

#[test]
fn analytic_segment_counts_equal_the_linearisation() {
    let programs = [
        // Quarter, half and three-quarter arcs, both directions, R and IJK.
        "G0 X10\nG3 X0 Y10 I-10 F100\nG2 X10 Y0 R10\nG3 X0 Y-10 R-10\n",
        // Full circles (no axis words), several turns, all planes.
        "G0 X5\nG2 I-5 F100\nG3 I-5 P3\nG18 G2 X5 Z0 I-5 K0\nG19 G0 X0 Y5 Z0\nG2 J-5 K0 P2\n",
        // Helices: the normal axis rises with the angle.
        "G0 X3\nG3 I-3 Z-10 P5 F100\nG18 G0 X0 Y0 Z3\nG2 K-3 Y-4 P2\n",
        // Tiny radii: fewer than four chords never, one quarter turn at most per chord.
        "G0 X0.0001\nG2 I-0.0001 F100\nG0 X0.001\nG3 X0 Y0.001 I-0.001\n",
        // Huge radii (the interpreter's limit is 1e6 mm).
        "G0 X999999\nG3 X0 Y999999 I-999999 F100\nG0 X0 Y0\nG2 X0 Y0.002 J0.001\n",
        // A spiral: start and end radius differ within the tolerance.
        "G0 X10\nG3 X-10.004 Y0 I-10 F100\n",
        // Straight moves and things that do not move.
        "G0 X1\nG1 X2 F100\nG4 P1\nM3 S1000\nG1 Y3\nM30\n",
    ];
    for src in programs {
        for tolerance in [0.002, 0.01, 0.1, 1.0, 0.0] {
            assert_counts_match(src, tolerance);
        }
    }
    // Counted through a whole program the same way (the analysis's `segments`).
    for src in programs {
        let a = analyse(src.as_bytes(), &AnalysisOptions::default()).unwrap();
        let made = Interpreter::new(src.as_bytes(), Config::default())
            .linearised()
            .filter(|m| matches!(m, Ok(Motion::Linear { .. } | Motion::Rapid { .. })))
            .count() as u64;
        assert_eq!(a.segments, made, "{src:?}");
    }
}

#[test]
fn a_huge_arc_is_refused_at_its_line_before_any_chord() {
    // ~3e8 chords at 0.002 mm: counted from radius, sweep and tolerance, never made.
    let src = "G21 G90\nG0 X0 Y0\nG1 F100\nG2 X0 Y0 I400000 J0 P10000\nG0 X1\n";
    let n = match arcs(src).pop().unwrap() {
        m @ Motion::Arc { .. } => segments_of(&m, 0.002),
        _ => unreachable!(),
    };
    assert!(n > 250_000_000, "{n}");
    let e = analyse(src.as_bytes(), &AnalysisOptions::default()).unwrap_err();
    assert_eq!((e.line, e.column, e.kind), (4, 1, ErrorKind::Budget), "{e}");
    assert!(e.message.contains(&n.to_string()), "{e}");
    assert!(e.message.contains(&DEFAULT_MAX_SEGMENTS.to_string()), "{e}");
    // In front of `linearise`, the stream ends with the error in place of the first chord.
    let out: Vec<_> = linearise(
        budgeted(
            Interpreter::new(src.as_bytes(), Config::default()),
            WorkBudget::new(1000, 0.002),
        ),
        0.002,
    )
    .collect();
    assert_eq!(out.len(), 2, "{out:?}");
    assert!(matches!(&out[1], Err(e) if e.kind == ErrorKind::Budget && e.line == 4));
}

#[test]
fn the_budget_counts_every_segment_and_names_the_line_that_passes_it() {
    // Line 1: one rapid; line 2: a full circle of 4 chords at a coarse tolerance; line 3: one.
    let src = "G0 X1\nG2 I-1 F100\nG1 X2\n";
    let tol = 1.0;
    let opts = |max_segments| AnalysisOptions {
        max_segments,
        config: Config {
            arc_tolerance_mm: tol,
            ..Config::default()
        },
        ..AnalysisOptions::default()
    };
    let a = analyse(src.as_bytes(), &opts(6)).unwrap();
    assert_eq!(a.segments, 6);
    for (limit, line) in [(5, 3), (4, 2), (1, 2), (0, 1)] {
        let e = analyse(src.as_bytes(), &opts(limit)).unwrap_err();
        assert_eq!((e.line, e.kind), (line, ErrorKind::Budget), "{limit}: {e}");
    }
    // Loops count every pass.
    let looped = "#1=0\nO100 while [#1 LT 10]\nG0 X#1\n#1=[#1+1]\nO100 endwhile\n";
    let a = analyse(looped.as_bytes(), &opts(10)).unwrap();
    assert_eq!(a.segments, 10);
    let e = analyse(looped.as_bytes(), &opts(9)).unwrap_err();
    assert_eq!((e.line, e.kind), (3, ErrorKind::Budget), "{e}");
    // Canned cycles: every rapid and feed of every hole.
    let drill = "G0 X0 Y0 Z5\nG81 X1 Y1 Z-1 R1 F100\nX2\nG80\n";
    let made = Interpreter::new(drill.as_bytes(), Config::default())
        .filter(|m| matches!(m, Ok(Motion::Linear { .. } | Motion::Rapid { .. })))
        .count() as u64;
    assert_eq!(
        analyse(drill.as_bytes(), &opts(u64::MAX)).unwrap().segments,
        made
    );
    // Splines: every chord.
    let spline = "G0 X0 Y0\nG5.1 X10 Y0 I5 J5 F100\n";
    let made = Interpreter::new(spline.as_bytes(), Config::default())
        .filter(|m| matches!(m, Ok(Motion::Linear { .. })))
        .count() as u64;
    assert!(made > 10, "{made}");
    let a = analyse(spline.as_bytes(), &AnalysisOptions::default()).unwrap();
    assert_eq!(a.segments, made + 1);
}

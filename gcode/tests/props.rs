//! Property tests for linearisation, the interpreter and the lexer.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::needless_range_loop)]

use fresa_gcode::*;
use proptest::prelude::*;
use std::f64::consts::{FRAC_PI_2, TAU};

fn plane_strategy() -> impl Strategy<Value = Plane> {
    prop_oneof![Just(Plane::XY), Just(Plane::ZX), Just(Plane::YZ)]
}

#[derive(Debug, Clone)]
struct ArcCase {
    centre: Point,
    radius: f64,
    start_angle: f64,
    sweep: f64,
    clockwise: bool,
    plane: Plane,
    rise: f64,
    tol: f64,
    full: bool,
}

fn arc_case() -> impl Strategy<Value = ArcCase> {
    (
        (-100.0..100.0f64, -100.0..100.0f64, -50.0..50.0f64),
        prop_oneof![0.01..1.0f64, 1.0..500.0f64],
        0.0..TAU,
        prop_oneof![1e-4..0.01f64, 0.01..TAU],
        any::<bool>(),
        plane_strategy(),
        prop_oneof![Just(0.0), -20.0..20.0f64],
        prop_oneof![Just(0.002), 1e-4..0.1f64],
        prop::bool::weighted(0.2),
    )
        .prop_map(
            |(c, radius, start_angle, sweep, clockwise, plane, rise, tol, full)| ArcCase {
                centre: [c.0, c.1, c.2],
                radius,
                start_angle,
                sweep: if full { TAU } else { sweep },
                clockwise,
                plane,
                rise,
                tol,
                full,
            },
        )
}

fn build(c: &ArcCase) -> Motion {
    let (a, b, n) = c.plane.axes();
    let mut from = c.centre;
    from[a] += c.radius * c.start_angle.cos();
    from[b] += c.radius * c.start_angle.sin();
    let end_angle = if c.clockwise {
        c.start_angle - c.sweep
    } else {
        c.start_angle + c.sweep
    };
    let mut to = if c.full { from } else { c.centre };
    if !c.full {
        to[a] += c.radius * end_angle.cos();
        to[b] += c.radius * end_angle.sin();
    }
    to[n] = from[n] + c.rise;
    Motion::Arc {
        line: 7,
        from,
        to,
        centre: [
            if n == 0 { from[0] } else { c.centre[0] },
            if n == 1 { from[1] } else { c.centre[1] },
            if n == 2 { from[2] } else { c.centre[2] },
        ],
        plane: c.plane,
        clockwise: c.clockwise,
        feed_mm_min: 100.0,
        turns: 1,
        sweep_rad: c.sweep,
    }
}

fn planar(p: Point, q: Point, a: usize, b: usize) -> f64 {
    (p[a] - q[a]).hypot(p[b] - q[b])
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(300))]

    /// Points lie on the arc, chords stay within tolerance of it, steps are
    /// no longer than the chord that tolerance allows, endpoints are exact,
    /// full circles close.
    #[test]
    fn linearised_arcs_stay_within_tolerance(c in arc_case()) {
        let arc = build(&c);
        let Motion::Arc { from, to, centre, .. } = arc.clone() else { unreachable!() };
        let (a, b, n) = c.plane.axes();
        let segs: Vec<Motion> = linearise(std::iter::once(Ok(arc)), c.tol)
            .collect::<Result<_, _>>()
            .unwrap();
        prop_assert!(!segs.is_empty());
        let count = segs.len() as f64;
        let max_step = if c.tol >= c.radius {
            FRAC_PI_2
        } else {
            (2.0 * (1.0 - c.tol / c.radius).acos()).min(FRAC_PI_2)
        };
        let chord_max = 2.0 * c.radius * (max_step / 2.0).sin();
        let eps = 1e-9 * (1.0 + c.radius + centre.iter().fold(0.0f64, |m, v| m.max(v.abs())));
        let mut prev = from;
        for (k, m) in segs.iter().enumerate() {
            let Motion::Linear { from: f, to: t, feed_mm_min, line, a: _ } = *m else {
                return Err(TestCaseError::fail("not a line"));
            };
            prop_assert_eq!(line, 7);
            prop_assert_eq!(feed_mm_min, 100.0);
            prop_assert_eq!(f, prev, "segments chain");
            // On the circle (in the plane) and on the helix (normal axis).
            prop_assert!((planar(t, centre, a, b) - c.radius).abs() <= eps,
                "point off the arc by {}", planar(t, centre, a, b) - c.radius);
            let frac = (k + 1) as f64 / count;
            prop_assert!((t[n] - (from[n] + c.rise * frac)).abs() <= eps);
            // Chord midpoint within tolerance of the arc (sagitta).
            let mid = [(f[0] + t[0]) / 2.0, (f[1] + t[1]) / 2.0, (f[2] + t[2]) / 2.0];
            prop_assert!(c.radius - planar(mid, centre, a, b) <= c.tol + eps,
                "sagitta {} > {}", c.radius - planar(mid, centre, a, b), c.tol);
            // Never further apart than the allowed chord.
            prop_assert!(planar(f, t, a, b) <= chord_max + eps);
            let rise = c.rise / count;
            let d3 = ((t[0]-f[0]).powi(2) + (t[1]-f[1]).powi(2) + (t[2]-f[2]).powi(2)).sqrt();
            prop_assert!(d3 <= chord_max.hypot(rise) + eps);
            prev = t;
        }
        prop_assert_eq!(prev, to, "exact end point");
        if c.full {
            let mut start = from;
            start[n] = to[n];
            prop_assert_eq!(prev, start, "full circle closes");
        }
        prop_assert_eq!(segs.len() as u64, segments_for(c.radius, c.sweep, c.tol));
    }

    /// Arcs whose end radius differs from the start radius (within the
    /// grbl/LinuxCNC 0.1 % rule) are spirals: every chord stays within the
    /// tolerance of the spiral and the end point is exact.
    #[test]
    fn linearised_spirals_stay_within_tolerance(c in arc_case(), grow in -0.001..0.001f64) {
        let mut c = c;
        if c.full {
            // A spiral cannot close; use a nearly full turn instead.
            c.full = false;
            c.sweep = TAU - 0.1;
        }
        let Motion::Arc { from, mut to, centre, plane, clockwise, sweep_rad, .. } = build(&c) else {
            unreachable!()
        };
        let (a, b, _) = plane.axes();
        to[a] = centre[a] + (to[a] - centre[a]) * (1.0 + grow);
        to[b] = centre[b] + (to[b] - centre[b]) * (1.0 + grow);
        let arc = Motion::Arc { line: 1, from, to, centre, plane, clockwise, feed_mm_min: 1.0, turns: 1, sweep_rad };
        let g = ArcGeometry::from_motion(&arc).unwrap();
        let segs: Vec<Motion> = linearise(std::iter::once(Ok(arc)), c.tol).collect::<Result<_, _>>().unwrap();
        let n = segs.len() as f64;
        let eps = 1e-9 * (1.0 + c.radius + 200.0);
        let mut last = from;
        for (k, m) in segs.iter().enumerate() {
            let Motion::Linear { from: f, to: t, .. } = *m else { unreachable!() };
            let mid = [(f[0] + t[0]) / 2.0, (f[1] + t[1]) / 2.0, (f[2] + t[2]) / 2.0];
            let on_curve = g.point_at((k as f64 + 0.5) / n);
            let d = ((mid[0] - on_curve[0]).powi(2) + (mid[1] - on_curve[1]).powi(2) + (mid[2] - on_curve[2]).powi(2)).sqrt();
            prop_assert!(d <= c.tol + eps, "chord {k} is {d} from the spiral (tol {})", c.tol);
            last = t;
        }
        prop_assert_eq!(last, to);
    }

    /// Analytic arc bounds contain every linearised point and are reached by
    /// dense sampling.
    #[test]
    fn arc_bounds_are_tight(c in arc_case()) {
        let arc = build(&c);
        let g = ArcGeometry::from_motion(&arc).unwrap();
        let (lo, hi) = g.bounds();
        let eps = 1e-9 * (1.0 + c.radius + 200.0);
        let mut slo = g.from;
        let mut shi = g.from;
        for k in 0..=4000 {
            let p = g.point_at(k as f64 / 4000.0);
            for i in 0..3 {
                prop_assert!(p[i] >= lo[i] - eps && p[i] <= hi[i] + eps);
                slo[i] = slo[i].min(p[i]);
                shi[i] = shi[i].max(p[i]);
            }
        }
        // Sampling step TAU/4000 misses an extremum by at most r(1-cos(step/2)).
        let slack = c.radius * (1.0 - (c.sweep / 8000.0).cos()) + eps;
        for i in 0..3 {
            prop_assert!(slo[i] - lo[i] <= slack && hi[i] - shi[i] <= slack);
        }
    }

    /// G-code text in every plane, R and IJK forms: the interpreter's arc ends
    /// exactly at the programmed point, and linearised points stay on it.
    #[test]
    fn interpreted_arcs_from_text(
        plane in 0usize..3,
        sx in -50i32..50, sy in -50i32..50, sz in -50i32..50,
        ci in -30i32..30, cj in -30i32..30,
        end_angle in 0.0..TAU,
        g3 in any::<bool>(),
        use_r in any::<bool>(),
        rise in -5i32..5,
    ) {
        prop_assume!(ci != 0 || cj != 0);
        let (pl, (a, b, n), letters) = match plane {
            0 => ("G17", (0usize, 1usize, 2usize), ('I', 'J')),
            1 => ("G18", (2, 0, 1), ('K', 'I')),
            _ => ("G19", (1, 2, 0), ('J', 'K')),
        };
        let start = [f64::from(sx), f64::from(sy), f64::from(sz)];
        let (oi, oj) = (f64::from(ci), f64::from(cj));
        let mut centre = start;
        centre[a] += oi;
        centre[b] += oj;
        let r = oi.hypot(oj);
        // End point on the circle, rounded to 4 decimals as CAM output is.
        let mut end = start;
        end[a] = ((centre[a] + r * end_angle.cos()) * 1e4).round() / 1e4;
        end[b] = ((centre[b] + r * end_angle.sin()) * 1e4).round() / 1e4;
        end[n] = start[n] + f64::from(rise);
        let chord = (end[a] - start[a]).hypot(end[b] - start[b]);
        prop_assume!(!use_r || chord > 1e-3);
        let axis = ['X', 'Y', 'Z'];
        let mut words = format!("{} {} X{} Y{} Z{}\n{} F500 {}", pl, "G0", sx, sy, sz, if g3 { "G3" } else { "G2" }, pl);
        for i in 0..3 {
            words.push_str(&format!(" {}{:.4}", axis[i], end[i]));
        }
        if use_r {
            // Choose the R sign that gives this centre.
            let cross = (end[a] - start[a]) * (centre[b] - start[b]) - (end[b] - start[b]) * (centre[a] - start[a]);
            let left = cross > 0.0;
            // Minor arc: centre left of the chord for G3, right for G2.
            let minor = left == g3;
            let rr = (start[a] - centre[a]).hypot(start[b] - centre[b]);
            words.push_str(&format!(" R{:.6}", if minor { rr } else { -rr }));
        } else {
            let off = |axis_idx: usize| if axis_idx == a { oi } else { oj };
            words.push_str(&format!(" {}{} {}{}", letters.0, off(a), letters.1, off(b)));
        }
        let motions: Vec<Motion> = Interpreter::new(words.as_bytes(), Config::default())
            .collect::<Result<_, _>>()
            .map_err(|e| TestCaseError::fail(format!("{words}: {e}")))?;
        let arc = motions.last().unwrap().clone();
        let Motion::Arc { to, centre: c, .. } = arc else {
            return Err(TestCaseError::fail("no arc"));
        };
        for i in 0..3 {
            prop_assert_eq!(to[i], format!("{:.4}", end[i]).parse::<f64>().unwrap());
        }
        let g = ArcGeometry::from_motion(&arc).unwrap();
        let tol = 0.002;
        let mut last = None;
        for m in linearise(std::iter::once(Ok(arc)), tol) {
            let Motion::Linear { to: t, .. } = m.unwrap() else { unreachable!() };
            let rad = (t[a] - c[a]).hypot(t[b] - c[b]);
            prop_assert!(rad >= g.r0.min(g.r1) - 1e-6 && rad <= g.r0.max(g.r1) + 1e-6);
            last = Some(t);
        }
        prop_assert_eq!(last, Some(to));
    }

    /// The fast number parser is correctly rounded like `str::parse`.
    #[test]
    fn numbers_round_like_std(int in 0u64..10_000_000, frac in 0u64..100_000_000, digits in 0usize..9, neg in any::<bool>()) {
        let text = if digits == 0 {
            format!("{}{}", if neg { "-" } else { "" }, int)
        } else {
            format!("{}{}.{:0width$}", if neg { "-" } else { "" }, int, frac % 10u64.pow(digits as u32), width = digits)
        };
        let src = format!("G0 X{text}");
        let expect = text.parse::<f64>().unwrap();
        let m: Result<Vec<Motion>, _> = Interpreter::new(src.as_bytes(), Config::default()).collect();
        if expect.abs() <= fresa_gcode::MAX_COORDINATE_MM {
            prop_assert_eq!(m.unwrap()[0].end_point().unwrap()[0], expect);
        } else {
            // Beyond any machine's reach: refused at the word, naming the limit.
            let e = m.unwrap_err();
            prop_assert_eq!((e.line, e.column), (1, 4));
            prop_assert!(e.message.contains("limit of 1000000 mm"), "{}", e);
        }
    }

    /// Arbitrary bytes never panic; every error names a line >= 1 and column >= 1.
    #[test]
    fn garbage_never_panics(bytes in prop::collection::vec(any::<u8>(), 0..300)) {
        for r in Interpreter::new(&bytes[..], Config::default()) {
            if let Err(e) = r {
                prop_assert!(e.line >= 1 && e.column >= 1);
            }
        }
    }

    /// Arbitrary lines made of G-code-ish tokens never panic either.
    #[test]
    fn gcode_like_text_never_panics(src in "([GMXYZIJKRFSPTN][-]?[0-9]{0,3}(\\.[0-9]{0,3})? ?|\\(|\\)|;|\n){0,60}") {
        for r in linearise(Interpreter::new(src.as_bytes(), Config::default()), 0.01).take(100_000) {
            if let Err(e) = r {
                prop_assert!(e.line >= 1 && e.column >= 1);
            }
        }
    }
}

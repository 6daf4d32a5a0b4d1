//! Golden tests on the shared corpus of real CAM output.
//!
//! Every file either parses, or fails with the expected clear error; bounding
//! boxes and lengths are checked against a deliberately simple and slow
//! reference interpreter written independently below (string splitting,
//! `str::parse`, dense sampling of arcs), and against the linearised output.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::needless_range_loop)]

use fresa_gcode::*;
use std::collections::BTreeMap;
use std::fs;
use std::io::BufReader;
use std::path::PathBuf;

fn corpus_dir() -> PathBuf {
    let dir = PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../shared/corpus/gcode"
    ));
    assert!(
        dir.is_dir(),
        "G-code corpus not found at {} (expected shared/ beside the workspace root)",
        dir.display()
    );
    dir
}

fn corpus_files() -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = fs::read_dir(corpus_dir())
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.is_file())
        .collect();
    v.sort();
    assert!(!v.is_empty(), "corpus folder is empty");
    v
}

/// Expected outcome with the default config: None = parses, Some((line, kind,
/// message fragment)) = fails there.
fn expected(name: &str) -> Option<(u32, ErrorKind, &'static str)> {
    match name {
        // N624: I20 J21 puts the centre at (40,0): radii 29 vs 27.59 mm.
        "cncjs-Circle_Diamond_Square_Calibration.gcode" => {
            Some((624, ErrorKind::Arc, "differs from radius to start"))
        }
        // N55 "X.75" while G2 is still modal and no I/J: not a valid arc.
        "cncjs-full-circle-without-xyz.gcode" => Some((11, ErrorKind::Arc, "needs R or I/J")),
        // G42 D08: tool 8 is not in the (default, empty) tool table.
        "cncjs-helical-thread-milling.gcode" => Some((5, ErrorKind::Unsupported, "tool table")),
        _ => None,
    }
}

fn open(p: &PathBuf) -> BufReader<fs::File> {
    BufReader::new(fs::File::open(p).unwrap())
}

// ---------------------------------------------------------------------------
// Reference: simple, slow, independent.

#[derive(Default, Clone, Copy)]
struct Bx {
    lo: [f64; 3],
    hi: [f64; 3],
    set: bool,
}
impl Bx {
    fn add(&mut self, p: [f64; 3]) {
        if !self.set {
            self.lo = p;
            self.hi = p;
            self.set = true;
        }
        for i in 0..3 {
            self.lo[i] = self.lo[i].min(p[i]);
            self.hi[i] = self.hi[i].max(p[i]);
        }
    }
}

struct RefResult {
    cut: Bx,
    rapid: Bx,
    cut_len: f64,
    rapid_len: f64,
}

/// Interprets lines `1..stop_line` (exclusive) with the corpus subset of G-code.
fn reference(text: &str, stop_line: u32) -> RefResult {
    let mut pos = [0.0f64; 3];
    let mut mode = -1i32;
    let mut plane = 17;
    let mut inch = false;
    let mut abs = true;
    let mut r = RefResult {
        cut: Bx::default(),
        rapid: Bx::default(),
        cut_len: 0.0,
        rapid_len: 0.0,
    };
    for (idx, raw) in text.lines().enumerate() {
        if idx as u32 + 1 >= stop_line {
            break;
        }
        // Strip comments.
        let mut s = String::new();
        let mut in_paren = false;
        for ch in raw.chars() {
            match ch {
                '(' => in_paren = true,
                ')' => in_paren = false,
                ';' if !in_paren => break,
                c if !in_paren && !c.is_whitespace() => s.push(c.to_ascii_uppercase()),
                _ => {}
            }
        }
        // Split into (letter, value).
        let mut words: Vec<(char, f64)> = Vec::new();
        let chars: Vec<char> = s.chars().collect();
        let mut i = 0;
        while i < chars.len() {
            let l = chars[i];
            let mut j = i + 1;
            while j < chars.len() && !chars[j].is_ascii_alphabetic() {
                j += 1;
            }
            let num: String = chars[i + 1..j].iter().collect();
            words.push((l, num.parse().unwrap()));
            i = j;
        }
        let get = |c: char| words.iter().find(|w| w.0 == c).map(|w| w.1);
        for &(l, v) in &words {
            if l == 'G' {
                match (v * 10.0).round() as i32 {
                    0 => mode = 0,
                    10 => mode = 1,
                    20 => mode = 2,
                    30 => mode = 3,
                    170 => plane = 17,
                    180 => plane = 18,
                    190 => plane = 19,
                    200 => inch = true,
                    210 => inch = false,
                    900 => abs = true,
                    910 => abs = false,
                    _ => {}
                }
            }
        }
        let k = if inch { 25.4 } else { 1.0 };
        let mut to = pos;
        let mut any = false;
        for (n, c) in ['X', 'Y', 'Z'].iter().enumerate() {
            if let Some(v) = get(*c) {
                to[n] = if abs { v * k } else { pos[n] + v * k };
                any = true;
            }
        }
        let offsets = ['I', 'J', 'K'].iter().any(|c| get(*c).is_some()) || get('R').is_some();
        if !(any || (mode >= 2 && offsets)) {
            continue;
        }
        match mode {
            0 | 1 => {
                let b = if mode == 0 { &mut r.rapid } else { &mut r.cut };
                b.add(pos);
                b.add(to);
                let d = ((to[0] - pos[0]).powi(2)
                    + (to[1] - pos[1]).powi(2)
                    + (to[2] - pos[2]).powi(2))
                .sqrt();
                if mode == 0 {
                    r.rapid_len += d;
                } else {
                    r.cut_len += d;
                }
            }
            2 | 3 => {
                // Plane axes as (horizontal, vertical, normal) seen from +normal.
                let (h, v, n) = match plane {
                    17 => (0, 1, 2),
                    18 => (2, 0, 1),
                    _ => (1, 2, 0),
                };
                let ccw = mode == 3;
                let angle = |c: [f64; 2], p: [f64; 2]| (p[1] - c[1]).atan2(p[0] - c[0]);
                let sweep_of = |c: [f64; 2]| {
                    let a0 = angle(c, [pos[h], pos[v]]);
                    let a1 = angle(c, [to[h], to[v]]);
                    let mut d = if ccw { a1 - a0 } else { a0 - a1 };
                    while d <= 1e-12 {
                        d += std::f64::consts::TAU;
                    }
                    while d > std::f64::consts::TAU + 1e-12 {
                        d -= std::f64::consts::TAU;
                    }
                    d
                };
                let centre: [f64; 2] = if let Some(rr) = get('R') {
                    // Both circle centres through the two points; keep the one
                    // whose sweep is minor for R > 0 and major for R < 0.
                    let rad = rr.abs() * k;
                    let (mx, my) = ((pos[h] + to[h]) / 2.0, (pos[v] + to[v]) / 2.0);
                    let (dx, dy) = (to[h] - pos[h], to[v] - pos[v]);
                    let half = (dx * dx + dy * dy).sqrt() / 2.0;
                    let off = (rad * rad - half * half).max(0.0).sqrt();
                    let (nx, ny) = (-dy / (2.0 * half), dx / (2.0 * half));
                    let c1 = [mx + off * nx, my + off * ny];
                    let c2 = [mx - off * nx, my - off * ny];
                    let want_major = rr < 0.0;
                    if (sweep_of(c1) > std::f64::consts::PI + 1e-9) == want_major {
                        c1
                    } else {
                        c2
                    }
                } else {
                    let letter = |axis: usize| ['I', 'J', 'K'][axis];
                    [
                        pos[h] + get(letter(h)).unwrap_or(0.0) * k,
                        pos[v] + get(letter(v)).unwrap_or(0.0) * k,
                    ]
                };
                let sweep = sweep_of(centre);
                let a0 = angle(centre, [pos[h], pos[v]]);
                let r0 = ((pos[h] - centre[0]).powi(2) + (pos[v] - centre[1]).powi(2)).sqrt();
                let r1 = ((to[h] - centre[0]).powi(2) + (to[v] - centre[1]).powi(2)).sqrt();
                let steps = (sweep / 0.002).ceil() as usize;
                let mut prev = pos;
                for s in 0..=steps {
                    let t = s as f64 / steps as f64;
                    let a = if ccw { a0 + sweep * t } else { a0 - sweep * t };
                    let rad = r0 + (r1 - r0) * t;
                    let mut p = [0.0; 3];
                    p[h] = centre[0] + rad * a.cos();
                    p[v] = centre[1] + rad * a.sin();
                    p[n] = pos[n] + (to[n] - pos[n]) * t;
                    r.cut.add(p);
                    r.cut_len += ((p[0] - prev[0]).powi(2)
                        + (p[1] - prev[1]).powi(2)
                        + (p[2] - prev[2]).powi(2))
                    .sqrt();
                    prev = p;
                }
                r.cut.add(to);
            }
            _ => panic!("reference: motion with no mode at line {}", idx + 1),
        }
        pos = to;
    }
    r
}

// ---------------------------------------------------------------------------

/// Bounds and lengths from our own motions, up to (not including) an error.
fn ours(p: &PathBuf, cfg: Config) -> (Bx, Bx, f64, f64, Option<GcodeError>, Vec<Motion>) {
    let mut cut = Bx::default();
    let mut rapid = Bx::default();
    let (mut cl, mut rl) = (0.0, 0.0);
    let mut all = Vec::new();
    let mut error = None;
    for m in Interpreter::new(open(p), cfg) {
        let m = match m {
            Ok(m) => m,
            Err(e) => {
                error = Some(e);
                break;
            }
        };
        match &m {
            Motion::Rapid { from, to, .. } => {
                rapid.add(*from);
                rapid.add(*to);
                rl += dist(*from, *to);
            }
            Motion::Linear { from, to, .. } => {
                cut.add(*from);
                cut.add(*to);
                cl += dist(*from, *to);
            }
            Motion::Arc { .. } => {
                let g = ArcGeometry::from_motion(&m).unwrap();
                let (lo, hi) = g.bounds();
                cut.add(lo);
                cut.add(hi);
                cl += g.length();
            }
            _ => {}
        }
        all.push(m);
    }
    (cut, rapid, cl, rl, error, all)
}

fn dist(a: Point, b: Point) -> f64 {
    ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2) + (b[2] - a[2]).powi(2)).sqrt()
}

fn assert_box_close(name: &str, what: &str, a: &Bx, b: &Bx, tol: f64) {
    assert_eq!(a.set, b.set, "{name}: {what} presence");
    for i in 0..3 {
        assert!(
            (a.lo[i] - b.lo[i]).abs() <= tol && (a.hi[i] - b.hi[i]).abs() <= tol,
            "{name}: {what} axis {i}: ours {:?}..{:?} reference {:?}..{:?}",
            a.lo,
            a.hi,
            b.lo,
            b.hi
        );
    }
}

#[test]
fn every_corpus_file_parses_or_fails_clearly() {
    let mut seen = BTreeMap::new();
    for p in corpus_files() {
        let name = p.file_name().unwrap().to_string_lossy().to_string();
        let r = analyse(open(&p), &AnalysisOptions::default());
        match (expected(&name), r) {
            (None, Ok(a)) => {
                let text = fs::read_to_string(&p).unwrap();
                assert_eq!(a.lines, text.lines().count() as u64, "{name}: line count");
                assert!(a.cutting_bounds.is_some(), "{name}: no cutting moves?");
            }
            (Some((line, kind, msg)), Err(e)) => {
                assert_eq!((e.line, e.kind), (line, kind), "{name}: {e}");
                assert!(e.column >= 1);
                assert!(e.message.contains(msg), "{name}: {e}");
            }
            (want, got) => panic!("{name}: expected {want:?}, got {got:?}"),
        }
        seen.insert(name, ());
    }
    // The files the issue names are all there.
    for f in [
        "cncjs-tball-pocket.gcode",
        "fusion-1055_utab_265bit.nc",
        "linuxcnc-tort.ngc",
        "cncjs-arc-xz-plane.gcode",
    ] {
        assert!(seen.contains_key(f), "corpus file {f} missing");
    }
}

#[test]
fn bounds_and_lengths_match_reference() {
    for p in corpus_files() {
        let name = p.file_name().unwrap().to_string_lossy().to_string();
        let cfg = Config {
            unsupported: Unsupported::SkipWithWarning,
            ..Config::default()
        };
        let (cut, rapid, cl, rl, error, _) = ours(&p, cfg);
        let stop = error.as_ref().map_or(u32::MAX, |e| e.line);
        let text = fs::read_to_string(&p).unwrap();
        let r = reference(&text, stop);
        // Sampling every 0.002 rad: the reference may be inside by r*(1-cos(0.001)).
        assert_box_close(&name, "cutting bounds", &cut, &r.cut, 1e-4);
        assert_box_close(&name, "rapid bounds", &rapid, &r.rapid, 1e-9);
        assert!(
            (rl - r.rapid_len).abs() < 1e-6,
            "{name}: rapid length {rl} vs {}",
            r.rapid_len
        );
        assert!(
            (cl - r.cut_len).abs() <= 1e-5 * r.cut_len.max(1.0),
            "{name}: cutting length {cl} vs {}",
            r.cut_len
        );
    }
}

#[test]
fn analysis_bounds_equal_streamed_bounds() {
    for p in corpus_files() {
        let name = p.file_name().unwrap().to_string_lossy().to_string();
        if expected(&name).is_some() {
            continue;
        }
        let a = analyse(open(&p), &AnalysisOptions::default()).unwrap();
        let (cut, rapid, cl, _, _, _) = ours(&p, Config::default());
        let cb = a.cutting_bounds.unwrap();
        assert_eq!((cb.min, cb.max), (cut.lo, cut.hi), "{name}");
        if let Some(rb) = a.rapid_bounds {
            assert_eq!((rb.min, rb.max), (rapid.lo, rapid.hi), "{name}");
        }
        assert!((a.cutting_length_mm - cl).abs() < 1e-6);
        assert!(a.estimated_seconds > 0.0);
        // The work budget's count, from each arc's geometry, is what linearising makes.
        let made = linearise(Interpreter::new(open(&p), Config::default()), 0.002)
            .map(Result::unwrap)
            .filter(|m| matches!(m, Motion::Linear { .. } | Motion::Rapid { .. }))
            .count() as u64;
        assert_eq!(a.segments, made, "{name}");
    }
}

#[test]
fn linearised_corpus_stays_within_tolerance_and_hits_endpoints() {
    let tol = 0.002;
    for p in corpus_files() {
        let name = p.file_name().unwrap().to_string_lossy().to_string();
        let cfg = Config {
            unsupported: Unsupported::SkipWithWarning,
            ..Config::default()
        };
        let (cut, _, _, _, _, motions) = ours(&p, cfg.clone());
        let mut lin = Bx::default();
        let mut lin_ends = Vec::new();
        for m in linearise(Interpreter::new(open(&p), cfg), tol) {
            let Ok(m) = m else { break };
            if let Motion::Linear { from, to, .. } = m {
                lin.add(from);
                lin.add(to);
            }
            push_end(&mut lin_ends, &m);
        }
        let mut ends = Vec::new();
        for m in &motions {
            push_end(&mut ends, m);
        }
        // Bit-for-bit the same end point for every source line with a move.
        assert_eq!(lin_ends, ends, "{name}");
        if lin.set {
            assert_box_close(&name, "linearised cutting bounds", &lin, &cut, tol + 1e-9);
        }
    }
}

/// Records the end point of the last move of each source line.
fn push_end(ends: &mut Vec<(u32, Point)>, m: &Motion) {
    if let Some(e) = m.end_point() {
        match ends.last_mut() {
            Some(last) if last.0 == m.line() => last.1 = e,
            _ => ends.push((m.line(), e)),
        }
    }
}

#[test]
fn skip_with_warning_runs_the_helical_thread_file() {
    let p = corpus_dir().join("cncjs-helical-thread-milling.gcode");
    let opts = AnalysisOptions {
        config: Config {
            unsupported: Unsupported::SkipWithWarning,
            ..Config::default()
        },
        ..AnalysisOptions::default()
    };
    let a = analyse(open(&p), &opts).unwrap();
    assert_eq!(a.warnings.len(), 1);
    assert_eq!(a.warnings[0].line, 5);
    assert!(a.units_inch_seen);
    assert_eq!(a.arc_moves, 10);
    // Incremental inch program: plunge from Z0 by 0.6533 in, then ten helix
    // turns each rising 0.0179 in, ending at Z -0.4743 in.
    let b = a.cutting_bounds.unwrap();
    assert!((b.min[2] - (-0.6533 * 25.4)).abs() < 1e-9, "{b:?}");
    assert!((b.max[2] - 0.0).abs() < 1e-9, "{b:?}");
}

#[test]
fn fusion_zmin_header_matches_cutting_bounds() {
    // Fusion 360 states the deepest Z of each tool in a header comment
    // "(T1  D=2.65 CR=0 - ZMIN=-12.55 - flat end mill)": an independent
    // statement of the lower cutting bound.
    let mut checked = 0;
    for p in corpus_files() {
        let name = p.file_name().unwrap().to_string_lossy().to_string();
        if !name.starts_with("fusion-") {
            continue;
        }
        let text = fs::read_to_string(&p).unwrap();
        let zmin: f64 = text
            .lines()
            .find_map(|l| l.split("ZMIN=").nth(1))
            .and_then(|rest| rest.split_whitespace().next())
            .and_then(|v| v.parse().ok())
            .unwrap_or_else(|| panic!("{name}: no ZMIN in header"));
        let a = analyse(open(&p), &AnalysisOptions::default()).unwrap();
        assert_eq!(a.cutting_bounds.unwrap().min[2], zmin, "{name}");
        checked += 1;
    }
    assert!(checked >= 2);
}

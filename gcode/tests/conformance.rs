//! Conformance: Fresa's interpreter against LinuxCNC's own, `rs274 -g`.
//!
//! For every program of the corpus (LinuxCNC's mill sample programs read from
//! the installed `linuxcnc-uspace` package, `../shared/corpus/gcode/`, and the
//! focused programs in `tests/conformance/`), both interpreters run and their
//! motion streams are compared: the sequence of rapids, feeds and arcs (end
//! points, arc centres, direction, turns, feed rate) within 1e-4 of the units
//! rs274 prints (it prints 4 decimals), and an error where rs274 errors.
//!
//! Normalisation, the same on both sides: coordinates in mm (rs274 prints the
//! program's units), zero-length straight moves dropped (a canned cycle's first
//! rapid to where the tool already is moves nothing).
//!
//! Programs on which Fresa knowingly differs are listed in [`KNOWN`] with the
//! reason; the test fails if one of them starts to match (so the list stays
//! current) or if any other program differs. Run with `--nocapture` to see the
//! per-file table.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_gcode::{Config, Interpreter, Motion, Plane, Tool, ToolTable};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::Command;

const NCFILES: &str = "/usr/share/linuxcnc/ncfiles";
/// rs274 prints 4 decimals in the program's units.
const TOL: f64 = 1e-4;

/// Programs where Fresa's result differs from rs274's, and why. Keys are file
/// names; `ncfiles/` ones come from the LinuxCNC package.
const KNOWN: &[(&str, &str)] = &[
    // Deliberate: Fresa drives X/Y/Z (and the pendant's A); 5-axis words are refused.
    (
        "ncfiles/b-index.ngc",
        "B axis: refused by design (X/Y/Z machines)",
    ),
    (
        "ncfiles/cone.ngc",
        "B and C axes: refused by design (X/Y/Z machines)",
    ),
    // Deliberate: no backend has a spindle encoder.
    (
        "ncfiles/threading.ngc",
        "G33 spindle-synchronised motion: no backend has a spindle encoder",
    ),
    (
        "ncfiles/comp.ngc",
        "G41/G42 in the XZ plane (G18, lathe-style compensation): deliberately only XY (G17), the plane a mill compensates in",
    ),
    (
        "ncfiles/mmount.ngc",
        "G33.1 rigid tapping: no backend has a spindle encoder (its G41/G42 parts match)",
    ),
];

#[derive(Debug, Clone, Copy, PartialEq)]
enum Canon {
    /// `a`: the A axis (degrees).
    Rapid {
        to: [f64; 3],
        a: f64,
    },
    Feed {
        to: [f64; 3],
        a: f64,
        feed: f64,
    },
    /// A G5/G5.1 spline: rs274 prints `NURBS_FEED(order, ...)` without its
    /// points, Fresa its chords (collapsed here to one entry per line).
    /// Compared by order; the end point shows in the moves that follow
    /// (the focused spline programs continue with incremental moves), and
    /// tests/splines.rs checks the chords against the curve.
    Spline {
        order: u8,
    },
    /// G38.x: rs274 prints `STRAIGHT_PROBE(x, y, z, ...)` and then assumes the probe did
    /// not trip (see `Motion::Probe`); compared by target and feed, never dropped as
    /// zero-length (both print one that starts where the tool is).
    Probe {
        to: [f64; 3],
        feed: f64,
    },
    /// End and centre in XYZ; `rotation` > 0 counter-clockwise turns, < 0 clockwise.
    Arc {
        to: [f64; 3],
        centre: [f64; 2],
        plane: u8,
        rotation: i32,
        feed: f64,
    },
}

/// What one interpreter made of a program.
#[derive(Debug)]
struct Outcome {
    moves: Vec<Canon>,
    /// Error text, if the program stopped with one.
    error: Option<String>,
    /// Motions other than straight/arc moves (probing, splines): count of those Fresa cannot express.
    other: Vec<String>,
}

fn rs274() -> PathBuf {
    let found = std::env::var_os("PATH").and_then(|p| {
        std::env::split_paths(&p)
            .map(|d| d.join("rs274"))
            .find(|f| f.is_file())
    });
    found.unwrap_or_else(|| {
        panic!(
            "rs274 (LinuxCNC's standalone interpreter, the reference for this test) is not installed: \
             apt-get install linuxcnc-uspace"
        )
    })
}

/// A tool table with tools 1..=99 (zero length, diameter 0.1), so programs
/// that change tools run as they would on a configured machine. rs274 reads
/// the table in inches (its G41 offsets by 0.05 in = 1.27 mm); Fresa's is in
/// mm ([`fresa_tools`]).
fn tool_table(dir: &Path) -> PathBuf {
    let p = dir.join("fresa-conformance.tbl");
    let mut s = String::new();
    for t in 1..=99 {
        writeln!(s, "T{t} P{t} Z0 D0.1 ;").unwrap();
    }
    std::fs::write(&p, s).unwrap();
    p
}

fn args_of(line: &str) -> Option<(&str, Vec<&str>)> {
    // "   12 N..... NAME(a, b, c)"
    let rest = line.trim_start();
    let rest = rest.split_once(' ')?.1.trim_start();
    let rest = rest.split_once(' ')?.1.trim_start();
    let open = rest.find('(')?;
    let name = &rest[..open];
    let inner = rest[open + 1..].strip_suffix(')')?;
    Some((name, inner.split(',').map(str::trim).collect()))
}

fn run_rs274(exe: &Path, table: &Path, dir: &Path, file: &Path) -> Outcome {
    let first = run_rs274_once(exe, table, dir, file);
    if !first.1 {
        return first.0;
    }
    // rs274 insists on M2/M30 or a closing `%`; Fresa (like grbl and CAM
    // output in the wild) takes the end of the file as the end of the
    // program, which (as M2 does) releases the moves cutter compensation
    // still holds. Deliberate difference: such a program is compared with
    // rs274's run of it with M2 appended.
    let with_end = dir.join("with-m2.ngc");
    let mut text = std::fs::read(file).unwrap();
    text.extend_from_slice(b"\nM2\n");
    std::fs::write(&with_end, text).unwrap();
    run_rs274_once(exe, table, dir, &with_end).0
}

/// One run; also says whether the only complaint was a missing program end.
fn run_rs274_once(exe: &Path, table: &Path, dir: &Path, file: &Path) -> (Outcome, bool) {
    let out = Command::new(exe)
        .arg("-t")
        .arg(table)
        .arg("-g")
        .arg(file)
        .current_dir(dir)
        .stdin(std::process::Stdio::null())
        .output()
        .expect("run rs274");
    let text = String::from_utf8_lossy(&out.stdout);
    let mut scale = 1.0; // mm per unit
    let mut feed = 0.0; // mm/min
    let mut feed_number = None; // a feed set since the last move
                                // rs274 prints program coordinates (G92/G52 offset taken off); Fresa's
                                // motions are in the work system's frame (offset included).
    let mut g92 = [0.0; 3];
    let mut g92_a = 0.0;
    // Likewise the active work system's origin: Fresa's config has all
    // offsets zero (the machine's own), so what G10 L2/L20 set is folded
    // into its motions; rs274 prints coordinates without it.
    let mut g5x = [0.0; 3];
    // G95: rs274 prints the feed per revolution; Fresa's motions carry mm/min.
    let (mut per_rev, mut rpm) = (false, 0.0);
    let mut plane = 0u8;
    let mut moves = Vec::new();
    let mut other = Vec::new();
    let num = |s: &str| -> f64 { s.parse().unwrap_or(f64::NAN) };
    for line in text.lines() {
        let Some((name, a)) = args_of(line) else {
            continue;
        };
        match name {
            "USE_LENGTH_UNITS" => {
                let new = if a[0] == "CANON_UNITS_INCHES" {
                    25.4
                } else {
                    1.0
                };
                // rs274 sets the feed before the units of the same line
                // (`G20 F12`: 12 mm/min, then inches). Fresa reads every
                // number of a line in that line's units (grbl; documented):
                // a deliberate difference, so the feed is read again in the
                // new units when no move came between.
                if let Some(number) = feed_number.take() {
                    feed = number * new;
                }
                scale = new;
            }
            "SET_FEED_MODE" => per_rev = a.get(1) == Some(&"1"),
            "SET_SPINDLE_SPEED" => rpm = num(a[1]),
            "SET_G92_OFFSET" => {
                g92 = [num(a[0]) * scale, num(a[1]) * scale, num(a[2]) * scale];
                g92_a = num(a[3]);
            }
            "SET_G5X_OFFSET" => {
                g5x = [num(a[1]) * scale, num(a[2]) * scale, num(a[3]) * scale];
            }
            "SET_FEED_RATE" => {
                feed = num(a[0]) * scale;
                feed_number = Some(num(a[0]));
            }
            "SELECT_PLANE" => {
                plane = match a[0] {
                    "CANON_PLANE_XZ" => 1,
                    "CANON_PLANE_YZ" => 2,
                    _ => 0,
                }
            }
            "STRAIGHT_TRAVERSE" | "STRAIGHT_FEED" => {
                feed_number = None;
                let to = [
                    num(a[0]) * scale + g92[0] + g5x[0],
                    num(a[1]) * scale + g92[1] + g5x[1],
                    num(a[2]) * scale + g92[2] + g5x[2],
                ];
                if a.len() > 3 && a[4..6].iter().any(|v| num(v) != 0.0) {
                    other.push(format!("{name} with B/C"));
                }
                // A is in degrees whatever the length units.
                let a_deg = num(a[3]) + g92_a;
                let feed = if per_rev { feed * rpm } else { feed };
                moves.push(if name == "STRAIGHT_FEED" {
                    Canon::Feed { to, a: a_deg, feed }
                } else {
                    Canon::Rapid { to, a: a_deg }
                });
            }
            "ARC_FEED" => {
                feed_number = None;
                let (e1, e2, c1, c2, rot, n) = (
                    num(a[0]) * scale,
                    num(a[1]) * scale,
                    num(a[2]) * scale,
                    num(a[3]) * scale,
                    num(a[4]) as i32,
                    num(a[5]) * scale,
                );
                let (i1, i2, i3) = match plane {
                    0 => (0, 1, 2),
                    1 => (2, 0, 1),
                    _ => (1, 2, 0),
                };
                let off = [g92[0] + g5x[0], g92[1] + g5x[1], g92[2] + g5x[2]];
                let (e1, e2, n) = (e1 + off[i1], e2 + off[i2], n + off[i3]);
                let (c1, c2) = (c1 + off[i1], c2 + off[i2]);
                let to = match plane {
                    0 => [e1, e2, n],
                    1 => [e2, n, e1],
                    _ => [n, e1, e2],
                };
                moves.push(Canon::Arc {
                    to,
                    centre: [c1, c2],
                    plane,
                    rotation: rot,
                    feed: if per_rev { feed * rpm } else { feed },
                });
            }
            "NURBS_FEED" => {
                feed_number = None;
                moves.push(Canon::Spline {
                    order: num(a[0]) as u8,
                })
            }
            "STRAIGHT_PROBE" => {
                feed_number = None;
                let to = [
                    num(a[0]) * scale + g92[0] + g5x[0],
                    num(a[1]) * scale + g92[1] + g5x[1],
                    num(a[2]) * scale + g92[2] + g5x[2],
                ];
                moves.push(Canon::Probe { to, feed });
            }
            "RIGID_TAP" => other.push(name.to_string()),
            _ => {}
        }
    }
    let stderr = String::from_utf8_lossy(&out.stderr);
    let eof_only = stderr.contains("File ended with no percent sign or program end");
    let error = if out.status.success() || eof_only {
        None
    } else {
        Some(format!(
            "{} ({})",
            stderr
                .lines()
                .filter(|l| !l.trim().is_empty() && l.trim() != "executing")
                .collect::<Vec<_>>()
                .join(" / "),
            out.status
        ))
    };
    (
        Outcome {
            moves,
            error,
            other,
        },
        eof_only,
    )
}

/// The same tool table as [`tool_table`], for Fresa (mm).
fn fresa_tools() -> ToolTable {
    (1..=99)
        .map(|t| {
            (
                t,
                Tool {
                    diameter_mm: 0.1 * 25.4,
                    length_mm: 0.0,
                },
            )
        })
        .collect()
}

/// Order of the spline a source line programs (G5: 4, G5.1: 3), if any.
fn spline_order(line: &str) -> Option<u8> {
    let t: String = line
        .split(['(', ';'])
        .next()
        .unwrap_or("")
        .chars()
        .filter(|c| !c.is_whitespace())
        .collect::<String>()
        .to_uppercase();
    let mut rest = t.as_str();
    while let Some(i) = rest.find("G5") {
        let after = &rest[i + 2..];
        if after.starts_with(".1") {
            return Some(3);
        }
        if !after.starts_with(|c: char| c.is_ascii_digit() || c == '.') {
            return Some(4);
        }
        rest = after;
    }
    None
}

fn run_fresa(file: &Path) -> Outcome {
    let f = std::fs::File::open(file).unwrap();
    let source: Vec<String> = String::from_utf8_lossy(&std::fs::read(file).unwrap())
        .lines()
        .map(str::to_string)
        .collect();
    let mut moves = Vec::new();
    let mut error = None;
    let config = Config {
        tools: fresa_tools(),
        ..Config::default()
    };
    let mut a_deg = 0.0;
    let mut spline_line = None;
    for m in Interpreter::new(std::io::BufReader::new(f), config) {
        if let Ok(Motion::Linear { line, .. }) = &m {
            if spline_line == Some(*line) {
                continue;
            }
            let order = source.get(*line as usize - 1).and_then(|l| spline_order(l));
            if let Some(order) = order {
                spline_line = Some(*line);
                moves.push(Canon::Spline { order });
                continue;
            }
        }
        spline_line = None;
        if let Ok(m) = &m {
            if let Some(r) = m.rotary() {
                a_deg = r.to;
            }
        }
        match m {
            Ok(Motion::Rapid { to, .. }) => moves.push(Canon::Rapid { to, a: a_deg }),
            Ok(Motion::Probe {
                to, feed_mm_min, ..
            }) => moves.push(Canon::Probe {
                to,
                feed: feed_mm_min,
            }),
            Ok(Motion::Linear {
                to, feed_mm_min, ..
            }) => moves.push(Canon::Feed {
                to,
                a: a_deg,
                feed: feed_mm_min,
            }),
            Ok(Motion::Arc {
                to,
                centre,
                plane,
                clockwise,
                feed_mm_min,
                turns,
                ..
            }) => {
                let (a, b, _) = plane.axes();
                moves.push(Canon::Arc {
                    to,
                    centre: [centre[a], centre[b]],
                    plane: match plane {
                        Plane::XY => 0,
                        Plane::ZX => 1,
                        Plane::YZ => 2,
                    },
                    rotation: if clockwise {
                        -(turns as i32)
                    } else {
                        turns as i32
                    },
                    feed: feed_mm_min,
                })
            }
            Ok(_) => {}
            Err(e) => {
                error = Some(e.to_string());
                break;
            }
        }
    }
    Outcome {
        moves,
        error,
        other: Vec::new(),
    }
}

/// Drops straight moves that do not move (from the previous end point).
fn normalise(moves: &[Canon]) -> Vec<Canon> {
    let mut out = Vec::with_capacity(moves.len());
    // Both start at program zero.
    let mut at: Option<[f64; 4]> = Some([0.0; 4]);
    for m in moves {
        let to = match *m {
            Canon::Rapid { to, a } | Canon::Feed { to, a, .. } => [to[0], to[1], to[2], a],
            Canon::Arc { to, .. } | Canon::Probe { to, .. } => {
                [to[0], to[1], to[2], at.map_or(0.0, |p| p[3])]
            }
            Canon::Spline { .. } => {
                out.push(*m);
                at = None;
                continue;
            }
        };
        let still = at.is_some_and(|p| (0..4).all(|i| (p[i] - to[i]).abs() < 1e-9));
        if still && !matches!(m, Canon::Arc { .. } | Canon::Probe { .. }) {
            continue;
        }
        out.push(*m);
        at = Some(to);
    }
    out
}

fn close(a: f64, b: f64, scale: f64) -> bool {
    (a - b).abs() <= TOL * scale + 1e-9 * a.abs().max(b.abs())
}

/// Compares two motion streams; `None` if they agree, else the first difference.
fn compare(reference: &[Canon], ours: &[Canon], scale: f64) -> Option<String> {
    let pt = |a: &[f64], b: &[f64]| a.iter().zip(b).all(|(x, y)| close(*x, *y, scale));
    for (i, (r, o)) in reference.iter().zip(ours).enumerate() {
        let same = match (r, o) {
            (Canon::Rapid { to: a, a: aa }, Canon::Rapid { to: b, a: ab }) => {
                pt(a, b) && close(*aa, *ab, 1.0)
            }
            (
                Canon::Feed {
                    to: a,
                    a: aa,
                    feed: fa,
                },
                Canon::Feed {
                    to: b,
                    a: ab,
                    feed: fb,
                },
            ) => pt(a, b) && close(*aa, *ab, 1.0) && close(*fa, *fb, scale),
            (Canon::Spline { order: a }, Canon::Spline { order: b }) => a == b,
            (Canon::Probe { to: a, feed: fa }, Canon::Probe { to: b, feed: fb }) => {
                pt(a, b) && close(*fa, *fb, scale)
            }
            (
                Canon::Arc {
                    to: a,
                    centre: ca,
                    plane: pa,
                    rotation: ra,
                    feed: fa,
                },
                Canon::Arc {
                    to: b,
                    centre: cb,
                    plane: pb,
                    rotation: rb,
                    feed: fb,
                },
            ) => pa == pb && ra == rb && pt(a, b) && pt(ca, cb) && close(*fa, *fb, scale),
            _ => false,
        };
        if !same {
            return Some(format!("move {}: rs274 {:?}, fresa {:?}", i + 1, r, o));
        }
    }
    if reference.len() != ours.len() {
        return Some(format!(
            "rs274 made {} moves, fresa {}{}",
            reference.len(),
            ours.len(),
            match (reference.get(ours.len()), ours.get(reference.len())) {
                (Some(r), _) => format!("; next rs274 move {r:?}"),
                (_, Some(o)) => format!("; next fresa move {o:?}"),
                _ => String::new(),
            }
        ));
    }
    None
}

/// Mill programs among LinuxCNC's samples: lathe programs (file name, or G7/G8
/// diameter/radius mode, G18 lathe threading G76) are left out.
fn is_mill_program(path: &Path) -> bool {
    let name = path.file_name().unwrap().to_string_lossy().to_lowercase();
    if name.contains("lathe") || name == "g76.ngc" {
        return false;
    }
    true
}

fn corpus() -> Vec<(String, PathBuf)> {
    let mut v = Vec::new();
    let nc = Path::new(NCFILES);
    assert!(
        nc.is_dir(),
        "LinuxCNC's sample programs not found at {NCFILES}: apt-get install linuxcnc-uspace"
    );
    let mut files: Vec<PathBuf> = std::fs::read_dir(nc)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "ngc") && p.is_file())
        .filter(|p| is_mill_program(p))
        .collect();
    files.sort();
    v.extend(files.into_iter().map(|p| {
        (
            format!("ncfiles/{}", p.file_name().unwrap().to_string_lossy()),
            p,
        )
    }));
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    for (label, dir) in [
        ("shared", root.join("../../shared/corpus/gcode")),
        ("conformance", root.join("tests/conformance")),
    ] {
        assert!(dir.is_dir(), "corpus folder {} missing", dir.display());
        let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.is_file())
            .collect();
        files.sort();
        v.extend(files.into_iter().map(|p| {
            (
                format!("{label}/{}", p.file_name().unwrap().to_string_lossy()),
                p,
            )
        }));
    }
    v
}

#[test]
fn motion_streams_match_rs274() {
    let exe = rs274();
    let dir = std::env::temp_dir().join(format!("fresa-conformance-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let table = tool_table(&dir);

    let mut report = String::new();
    let mut problems = Vec::new();
    let (mut nc_total, mut nc_ran, mut nc_match) = (0, 0, 0);
    let mut nc_unmatched = Vec::new();
    let mut matched = 0;
    let files = corpus();
    for (name, path) in &files {
        let reference = run_rs274(&exe, &table, &dir, path);
        let ours = run_fresa(path);
        // Inch programs: rs274's 4 decimals are 1e-4 inch.
        let text = std::fs::read_to_string(path)
            .unwrap_or_default()
            .to_lowercase();
        let scale = if text.contains("g20") { 25.4 } else { 1.0 };
        let (r, o) = (normalise(&reference.moves), normalise(&ours.moves));
        let diff = match (&reference.error, &ours.error) {
            (None, None) => compare(&r, &o, scale),
            (Some(re), Some(_)) => compare(&r, &o, scale)
                .map(|d| format!("both stop with an error (rs274: {re}), but before it: {d}")),
            (Some(re), None) => Some(format!("rs274 stops with an error, fresa does not: {re}")),
            (None, Some(oe)) => Some(format!("fresa: {oe}")),
        };
        let diff = match (diff, reference.other.first()) {
            (None, Some(other)) => Some(format!("rs274 also made {other} motion")),
            (d, _) => d,
        };
        let known = KNOWN.iter().find(|k| k.0 == name).map(|k| k.1);
        if name.starts_with("ncfiles/") {
            nc_total += 1;
            if reference.error.is_none() && !reference.moves.is_empty() {
                nc_ran += 1;
                if diff.is_none() {
                    nc_match += 1;
                } else {
                    nc_unmatched.push(name.trim_start_matches("ncfiles/").to_string());
                }
            }
        }
        let verdict = match (&diff, known) {
            (None, None) => {
                matched += 1;
                "PASS".to_string()
            }
            (None, Some(_)) => {
                problems.push(format!(
                    "{name} now matches rs274: remove it from KNOWN in tests/conformance.rs"
                ));
                "PASS (listed as known difference)".to_string()
            }
            (Some(d), Some(why)) => format!("KNOWN DIFFERENCE ({why}): {d}"),
            (Some(d), None) => {
                problems.push(format!("{name}: {d}"));
                format!("FAIL: {d}")
            }
        };
        writeln!(report, "{name:<60} {verdict}").unwrap();
    }
    if !nc_unmatched.is_empty() {
        writeln!(
            report,
            "\nLinuxCNC samples rs274 runs but Fresa does not match: {}",
            nc_unmatched.join(", ")
        )
        .unwrap();
    }
    writeln!(
        report,
        "\n{matched} of {} programs match; LinuxCNC mill samples: {nc_total}, rs274 runs {nc_ran} \
         to the end with motion, fresa matches {nc_match} of those",
        files.len()
    )
    .unwrap();
    println!("{report}");
    let _ = std::fs::remove_dir_all(&dir);
    assert!(
        problems.is_empty(),
        "{report}\n{} problem(s):\n{}",
        problems.len(),
        problems.join("\n")
    );
}

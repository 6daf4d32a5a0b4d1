//! Plain move lines (`[N..] [G0|G1] X.. Y.. Z.. [F..]`) take a short path through the
//! interpreter (issue #29); it must do exactly what the general path does. Each program here
//! runs as written and with ` G61` added to its move lines: G61 (exact path mode) changes
//! nothing in the path, but a line with it takes the general path. Motions, errors (message,
//! line and column: G61 goes at the end of the line, after every word that can be named),
//! warnings and the analysis must be the same.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_gcode::*;

#[path = "../benches/support/synth.rs"]
mod synth;

/// The program with ` G61` after every line that could be a plain move.
fn general(src: &str) -> String {
    src.lines()
        .map(|l| {
            let t = l.trim_start().to_ascii_uppercase();
            let candidate = t.starts_with(['X', 'Y', 'Z', 'N', 'F'])
                || t.starts_with("G0 ")
                || t.starts_with("G1 ")
                || t.starts_with("G0X")
                || t.starts_with("G1X");
            if candidate {
                format!("{l} G61\n")
            } else {
                format!("{l}\n")
            }
        })
        .collect()
}

fn events(src: &str, cfg: &Config) -> (Vec<String>, Vec<Warning>, u64) {
    let mut it = Interpreter::new(src.as_bytes(), cfg.clone());
    let out: Vec<String> = it.by_ref().map(|m| format!("{m:?}")).collect();
    (out, it.warnings().to_vec(), it.lines_read())
}

fn same_either_way(src: &str, cfg: &Config) {
    let other = general(src);
    assert_ne!(src.trim_end(), other.trim_end(), "no plain line in {src:?}");
    assert_eq!(events(src, cfg), events(&other, cfg), "{src:?}");
    let opts = AnalysisOptions {
        config: cfg.clone(),
        ..AnalysisOptions::default()
    };
    let json = |s: &str| match analyse(s.as_bytes(), &opts) {
        Ok(a) => serde_json::to_string(&a).unwrap(),
        Err(e) => format!("error {e}"),
    };
    assert_eq!(json(src), json(&other), "{src:?}");
}

const PROGRAMS: &[&str] = &[
    // Modal continuation, explicit G0/G1, N numbers, comments, lower case, blanks in numbers.
    "G21 G90\nG0 X1 Y2\nZ3\nG1 X4 F100\nY5 (a comment)\nN10 x-1.5y2 z.5\ng1x3 F2 00\nG0X1\n",
    // Incremental and inch moves, feed given in inches.
    "G20 G91\nG0 X1 Y1\nX1\nG1 Z-0.1 F10\nX0.5 Y-0.25\nG90\nX0 Y0\n",
    // A feed move with no feed, a zero feed, a negative feed.
    "G0 X1\nG1 X2\n",
    "G1 F0\nX1\n",
    "G1 X1 F100\nX2 F-5\n",
    // Words and positions beyond reach, and a word within reach that G91 takes beyond.
    "G0 X1\nX2000000\n",
    "G1 F100 X1\nY1 Z-3000000\n",
    "G1 X1 F200000000\n",
    "G91 G0 X900000\nX900000\n",
    // Axis words with no motion mode, and after G80.
    "X1\n",
    "G0 X1\nG80\nY1\n",
    // Modes that keep lines off the short path, with plain-looking lines among them.
    "G93 G1 X1 F2\nX2 F3\nG94 G1 X3 F100\nX4\n",
    "G92 X5\nG0 X1\nX2\nG92.1\nX3\n",
    "G10 L20 P1 X3\nG0 X1\nX2\n",
    "G0 X0 Y0 Z5\nG81 X1 Y1 Z-1 R1 F100\nX2\nG0 X5\nX6\n",
    "G0 A10 X1\nX2\nG1 A20 F100\nX3\n",
    "G41.1 D2\nG1 X10 F100\nY10\nG40\nX0 Y0\nX5\n",
    // Warnings, block delete, a program end with carrying on.
    "G0 X1\n/X5\nB3\nX2\nM2\nX3\n",
];

#[test]
fn plain_move_lines_run_as_the_general_path_runs_them() {
    for src in PROGRAMS {
        same_either_way(src, &Config::default());
    }
    let carry_on = Config {
        stop_at_program_end: false,
        unsupported: Unsupported::SkipWithWarning,
        ..Config::default()
    };
    for src in PROGRAMS {
        same_either_way(src, &carry_on);
    }
}

#[test]
fn the_synthetic_cam_program_runs_the_same_on_both_paths() {
    let mut src = Vec::new();
    synth::cam(200_000, &mut src).unwrap();
    same_either_way(&String::from_utf8(src).unwrap(), &Config::default());
}

//! Cutter radius compensation (G41/G42/G40 with D from the tool table).
//! The geometry itself is compared with LinuxCNC's rs274 in
//! tests/conformance.rs (tests/conformance/comp-*.ngc and LinuxCNC's comp
//! samples); these tests pin the tool-table contract and the errors.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_gcode::{Config, ErrorKind, Interpreter, Motion, Tool, ToolTable};

fn table(entries: &[(u32, f64)]) -> ToolTable {
    entries
        .iter()
        .map(|&(t, d)| {
            (
                t,
                Tool {
                    diameter_mm: d,
                    length_mm: 0.0,
                },
            )
        })
        .collect()
}

fn run(program: &str, tools: ToolTable) -> Result<Vec<Motion>, fresa_gcode::GcodeError> {
    let cfg = Config {
        tools,
        ..Config::default()
    };
    Interpreter::new(program.as_bytes(), cfg).collect()
}

fn ends(motions: &[Motion]) -> Vec<[f64; 3]> {
    motions.iter().filter_map(Motion::end_point).collect()
}

const SQUARE: &str =
    "G21 G90 F100\nG0 X-10 Y-10\nG41 D3 G1 X0 Y0\nG1 X20\nY20\nX0\nY0\nG40 G1 X-10 Y-10\nM2\n";

#[test]
fn the_d_word_picks_the_radius_from_the_tool_table() {
    let small = run(SQUARE, table(&[(3, 2.0)])).unwrap();
    let big = run(SQUARE, table(&[(3, 6.0)])).unwrap();
    // Left of a counter-clockwise square is inside: the first side (X0..20
    // at Y0, after the entry) runs at Y = radius.
    let y_of_first_side = |m: &[Motion]| {
        m.iter()
            .find(|m| m.line() == 4)
            .and_then(Motion::end_point)
            .unwrap()[1]
    };
    assert!((y_of_first_side(&small) - 1.0).abs() < 1e-9, "{small:?}");
    assert!((y_of_first_side(&big) - 3.0).abs() < 1e-9, "{big:?}");
    assert_ne!(ends(&small), ends(&big));
    // Without compensation the path is the programmed one.
    let plain = run(&SQUARE.replace("G41 D3 ", ""), ToolTable::new()).unwrap();
    assert_eq!(
        ends(&plain)[2..6],
        [
            [20.0, 0.0, 0.0],
            [20.0, 20.0, 0.0],
            [0.0, 20.0, 0.0],
            [0.0, 0.0, 0.0]
        ]
    );
}

#[test]
fn a_tool_missing_from_the_table_names_line_and_d_word() {
    let err = run(SQUARE, table(&[(1, 2.0)])).unwrap_err();
    assert_eq!((err.line, err.column), (3, 5), "{err}");
    assert_eq!(err.kind, ErrorKind::Unsupported);
    assert!(
        err.message.contains("D3") && err.message.contains("tool table"),
        "{err}"
    );
}

#[test]
fn without_d_the_tool_in_the_spindle_is_used() {
    let p = "G21 F100\nT4 M6\nG0 X-10 Y0\nG42 G1 X0 Y0\nG1 X20\nM2\n";
    let m = run(p, table(&[(4, 4.0)])).unwrap();
    // Right of +X is -Y: the line runs at Y = -2.
    assert!(
        ends(&m)
            .iter()
            .any(|e| (e[0] - 20.0).abs() < 1e-9 && (e[1] + 2.0).abs() < 1e-9),
        "{m:?}"
    );
    // The tool in the spindle must be in the table too.
    let err = run(p, table(&[(5, 4.0)])).unwrap_err();
    assert_eq!(err.line, 4);
    assert!(err.message.contains("T4"), "{err}");
}

#[test]
fn compensated_moves_wait_for_the_next_move() {
    // The first side's end depends on the corner that follows, so a line's
    // move comes out only after the next line was read; the stream still
    // carries every move in order, with each move starting where the last ended.
    let m = run(SQUARE, table(&[(3, 2.0)])).unwrap();
    let moves: Vec<&Motion> = m.iter().filter(|m| m.end_point().is_some()).collect();
    for w in moves.windows(2) {
        let from = match w[1] {
            Motion::Rapid { from, .. } | Motion::Linear { from, .. } | Motion::Arc { from, .. } => {
                *from
            }
            _ => unreachable!(),
        };
        let prev = w[0].end_point().unwrap();
        assert!((0..3).all(|i| (from[i] - prev[i]).abs() < 1e-9), "{w:?}");
    }
    assert!(matches!(m.last(), Some(Motion::ProgramEnd { line: 9 })));
}

#[test]
fn errors_while_compensation_is_on() {
    let t = table(&[(1, 2.0)]);
    for (program, line, fragment) in [
        ("G21 F100\nG0 X0\nG1 X5 D1\n", 3, "D word with no G41"),
        (
            "G21 F100\nG0 X0\nG41 D1 G1 X10\nG92 X0\n",
            4,
            "cannot change axis offsets",
        ),
        (
            "G21 F100\nG0 X0\nG41 D1 G1 X10\nG18\n",
            4,
            "cannot change planes",
        ),
        (
            "G21 F100\nG0 X0\nG41 D1 G1 X10\nG41 D1 G1 X20\n",
            4,
            "already on",
        ),
        (
            "G21 F100\nG0 X0\nG41 D1 G1 X10\nG81 Z-1 R1\n",
            4,
            "canned cycles",
        ),
        ("G21 F100\nG0 X0\nG41.1 G1 X10\n", 3, "no D word"),
        (
            "G21 F100\nG0 X0\nG41 D1 G1 X10\nX20\nG40\nG2 X40 R5\n",
            6,
            "must be straight",
        ),
    ] {
        let err = run(program, t.clone()).unwrap_err();
        assert_eq!(err.line, line, "{program}: {err}");
        assert!(err.message.contains(fragment), "{program}: {err}");
    }
}

#[test]
fn a_skipped_line_leaves_what_compensation_holds_as_it_was() {
    // Line 6 changes the tool (which releases the held move and message) and then moves A,
    // which compensation does not support: skipped, it must change nothing, so the stream is
    // that of the program without it. Compensation undoes a line without copying what it holds.
    let with = "G21 F100\nG0 X-10 Y-10\nG41.1 D2 G1 X0 Y0\nG1 X10\n(msg, held)\nM6 T1 A10\n\
                (msg, after)\nG1 X10 Y10\nG40 G1 X20 Y20\nM2\n";
    let without = with.replace("M6 T1 A10", "");
    let interp = |program: &str| {
        let cfg = Config {
            unsupported: fresa_gcode::Unsupported::SkipWithWarning,
            ..Config::default()
        };
        let mut it = Interpreter::new(program.as_bytes(), cfg);
        let motions: Vec<Motion> = it.by_ref().collect::<Result<_, _>>().unwrap();
        (motions, it.warnings().len())
    };
    let (skipped, warnings) = interp(with);
    assert_eq!(
        warnings, 1,
        "the A move under compensation is skipped with a warning"
    );
    assert_eq!(skipped, interp(&without).0);
    assert!(skipped.iter().any(|m| matches!(m, Motion::Message { .. })));
}

#[test]
fn the_tool_table_deserialises_from_settings() {
    let cfg: Config = serde_json::from_str(r#"{"tools": {"3": {"diameter_mm": 6.0}}}"#).unwrap();
    assert_eq!(cfg.tools[&3].diameter_mm, 6.0);
    assert_eq!(cfg.tools[&3].length_mm, 0.0);
}

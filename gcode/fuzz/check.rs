//! What the `interp` and `grammar` fuzz targets check for one input. Shared (by `#[path]`)
//! between the fuzz targets and the replay test `gcode/tests/fuzz_corpus.rs`, so a saved input
//! is checked the same way in both.
// Each fuzz target uses its part of this file.
#![allow(dead_code)]

use fresa_gcode::{
    analyse, linearise, AnalysisOptions, Config, Interpreter, Motion, Unsupported,
    MAX_COORDINATE_MM, MAX_DWELL_SECONDS, MAX_SPINDLE_RPM,
};
use std::time::Duration;

#[path = "budget.rs"]
pub mod budget;
#[path = "grammar.rs"]
pub mod grammar;

// The server's preview (fresa_core::toolpath) depends on nothing but this crate: fuzzed here.
#[allow(dead_code)]
#[path = "../../server/core/src/toolpath.rs"]
mod toolpath;

/// Motions taken from one input at most: a helix with a huge `P` is legal and long.
const MAX_MOTIONS: usize = 5_000;
/// Vertex budget of the toolpath check.
const TOOLPATH_VERTICES: usize = 1_000;

/// The first byte picks the configuration; the rest is the program.
pub fn interp(data: &[u8]) {
    interp_within(data, None);
}

/// [`interp`], failing when the input takes more CPU time than `budget`.
pub fn interp_within(data: &[u8], budget: Option<Duration>) {
    let Some((&sel, text)) = data.split_first() else {
        return;
    };
    let text = text.to_vec();
    budget::on_small_stack(budget, move || program(config(sel), &text));
}

/// The first byte picks the configuration; the rest are the choices of [`grammar::program`],
/// which writes the program: deep nests, huge numbers, values on every limit, long repeats.
pub fn grammar(data: &[u8]) {
    grammar_within(data, None);
}

/// [`grammar`], failing when the input takes more CPU time than `budget`.
pub fn grammar_within(data: &[u8], budget: Option<Duration>) {
    let Some((&sel, choices)) = data.split_first() else {
        return;
    };
    let text = grammar::program(&mut grammar::Choices::new(choices));
    budget::on_small_stack(budget, move || program(config(sel), text.as_bytes()));
}

fn config(sel: u8) -> Config {
    Config {
        unsupported: if sel & 1 == 1 {
            Unsupported::SkipWithWarning
        } else {
            Unsupported::Error
        },
        stop_at_program_end: sel & 2 == 0,
        block_delete: sel & 4 == 0,
        max_line_bytes: if sel & 8 == 0 { 64 * 1024 } else { 64 },
        max_warnings: 16,
        // Loops in fuzz input must end quickly: what a loop costs grows linearly with the
        // limit, and 10,000 passes of a loop of messages took the 2 s CPU budget under
        // AddressSanitizer (30 ms optimised): the budget is there for work that grows faster.
        max_loop_iterations: 1_000,
        ..Config::default()
    }
}

/// Never panics; every motion's line number is within the lines read, in order (unless
/// O-words or M98 jump back); an error names a line and column and ends the stream; every
/// number in a motion is finite and within the crate's bounds; the lineariser and the
/// toolpath preview take the same program.
fn program(cfg: Config, text: &[u8]) {
    // Loops and subroutines go back to earlier lines; without O-words or M98
    // the line numbers never decrease.
    let may_jump = text.iter().any(|&c| c == b'o' || c == b'O' || c == b'9');
    let mut it = Interpreter::new(text, cfg.clone());
    let mut last_line = 0u32;
    let mut n = 0;
    let mut errored = false;
    for r in it.by_ref() {
        assert!(!errored, "the stream went on after an error");
        match r {
            Ok(m) => {
                assert!(
                    m.line() >= 1 && (may_jump || m.line() >= last_line),
                    "line {} after {last_line}",
                    m.line()
                );
                last_line = m.line();
                check_motion(&m);
            }
            Err(e) => {
                assert!(e.line >= 1 && e.column >= 1, "error without a place: {e:?}");
                errored = true;
            }
        }
        n += 1;
        if n >= MAX_MOTIONS {
            break;
        }
    }
    assert!(u64::from(last_line) <= it.lines_read().max(1));
    assert!(it.warnings().len() <= cfg.max_warnings);
    // Work: execution runs forward from the start or from a jump (a counted loop pass or call,
    // or the return of one), so lines executed stay within lines read times the jumps allowed.
    assert!(
        it.lines_executed() <= it.lines_read().max(1) * (2 * cfg.max_loop_iterations + 3),
        "{} lines executed of {} read",
        it.lines_executed(),
        it.lines_read()
    );
    for m in linearise(Interpreter::new(text, cfg.clone()), 0.05).take(MAX_MOTIONS) {
        match m {
            Ok(m @ Motion::Arc { .. }) => panic!("an arc came out of linearise: {m:?}"),
            Ok(m) => check_motion(&m),
            Err(_) => break,
        }
    }
    // The analysis and the preview of a short program (both read all of it).
    if text.len() <= 4096 {
        let _ = analyse(
            text,
            &AnalysisOptions {
                config: cfg.clone(),
                ..AnalysisOptions::default()
            },
        );
        if let Ok(t) = toolpath::Toolpath::build(text, cfg, TOOLPATH_VERTICES) {
            assert!(t.len() <= TOOLPATH_VERTICES, "{} vertices", t.len());
            let bytes = t.encode();
            assert_eq!(bytes.len(), toolpath::HEADER_BYTES + 17 * t.len());
            assert_eq!(&bytes[..4], toolpath::MAGIC);
        }
    }
}

/// Within ±MAX_COORDINATE_MM (and so finite).
fn within(v: f64) -> bool {
    v.abs() <= MAX_COORDINATE_MM
}

fn check_motion(m: &Motion) {
    match m {
        Motion::Rapid { from, to, a, .. } | Motion::Linear { from, to, a, .. } => {
            assert!(
                from.iter().all(|v| v.is_finite()) && to.iter().copied().all(within),
                "a move beyond reach: {m:?}"
            );
            assert!(a.map_or(true, |a| within(a.to)), "A beyond reach: {m:?}");
        }
        Motion::Arc {
            from, to, centre, ..
        } => {
            assert!(
                from.iter().all(|v| v.is_finite())
                    && to.iter().copied().all(within)
                    && centre.iter().copied().all(within),
                "an arc beyond reach: {m:?}"
            );
        }
        Motion::Dwell { seconds, .. } => assert!(
            (0.0..=MAX_DWELL_SECONDS).contains(seconds),
            "a dwell beyond the limit: {m:?}"
        ),
        Motion::Spindle { rpm, .. } => assert!(
            (0.0..=MAX_SPINDLE_RPM).contains(rpm),
            "a spindle speed beyond the limit: {m:?}"
        ),
        Motion::OffsetChange {
            offset, offset_a, ..
        } => assert!(
            offset.iter().copied().all(within) && within(*offset_a),
            "an offset beyond reach: {m:?}"
        ),
        Motion::WorkOffsetChange { origin, .. } => assert!(
            origin.iter().copied().all(within),
            "a work offset beyond reach: {m:?}"
        ),
        _ => {}
    }
    if let Motion::Linear { feed_mm_min, .. } | Motion::Arc { feed_mm_min, .. } = m {
        assert!(
            feed_mm_min.is_finite() && *feed_mm_min > 0.0,
            "a feed that is not a positive number: {m:?}"
        );
    }
}

//! What the `interp` fuzz target checks for one input. Shared (by `#[path]`) between the fuzz
//! target and the replay test `gcode/tests/fuzz_corpus.rs`, so a saved input is checked the same
//! way in both.

use fresa_gcode::{analyse, linearise, AnalysisOptions, Config, Interpreter, Motion, Unsupported};

/// Motions taken from one input at most: a helix with a huge `P` is legal and long.
const MAX_MOTIONS: usize = 5_000;

/// The first byte picks the configuration; the rest is the program. Never panics; every
/// motion's line number is within the lines read, in order (unless O-words or M98 jump
/// back); an error names a line and column
/// and ends the stream; moves are finite.
pub fn interp(data: &[u8]) {
    let Some((&sel, text)) = data.split_first() else {
        return;
    };
    let cfg = Config {
        unsupported: if sel & 1 == 1 {
            Unsupported::SkipWithWarning
        } else {
            Unsupported::Error
        },
        stop_at_program_end: sel & 2 == 0,
        block_delete: sel & 4 == 0,
        max_line_bytes: if sel & 8 == 0 { 64 * 1024 } else { 64 },
        max_warnings: 16,
        // Loops in fuzz input must end quickly.
        max_loop_iterations: 10_000,
        ..Config::default()
    };
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
                assert!(e.line >= 1, "error without a line: {e:?}");
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
    for m in linearise(Interpreter::new(text, cfg.clone()), 0.05).take(MAX_MOTIONS) {
        match m {
            Ok(m @ Motion::Arc { .. }) => panic!("an arc came out of linearise: {m:?}"),
            Ok(m) => check_motion(&m),
            Err(_) => break,
        }
    }
    // The analysis of a short program (it keeps arcs exact, so it is linear in the input).
    if text.len() <= 4096 {
        let _ = analyse(
            text,
            &AnalysisOptions {
                config: cfg,
                ..AnalysisOptions::default()
            },
        );
    }
}

fn check_motion(m: &Motion) {
    if let Motion::Rapid { from, to, .. }
    | Motion::Linear { from, to, .. }
    | Motion::Arc { from, to, .. } = m
    {
        assert!(
            from.iter().chain(to).all(|v| v.is_finite()),
            "a move that is not finite: {m:?}"
        );
    }
}

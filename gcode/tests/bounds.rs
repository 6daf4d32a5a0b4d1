//! Input bounds: no program can make the reader recurse past `MAX_EXPRESSION_DEPTH` (so no
//! input overflows a thread's stack) or put a number no machine can run into a motion. Each
//! refusal names line, column and the limit.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_gcode::{
    analyse, AnalysisOptions, Config, GcodeError, Interpreter, Motion, MAX_BLOCK_NESTING,
    MAX_EXPRESSION_DEPTH, MAX_HELD_EVENTS,
};

fn run(src: &str) -> Result<Vec<Motion>, GcodeError> {
    Interpreter::new(src.as_bytes(), Config::default()).collect()
}

#[track_caller]
fn err(src: &str) -> GcodeError {
    match run(src) {
        Ok(m) => panic!("accepted: {src:.80}... gave {} motions", m.len()),
        Err(e) => e,
    }
}

/// Runs `f` on a thread with `stack` bytes: a recursion the bound did not stop overflows it
/// and aborts the test binary.
fn on_stack<T: Send + 'static>(stack: usize, f: impl FnOnce() -> T + Send + 'static) -> T {
    std::thread::Builder::new()
        .stack_size(stack)
        .spawn(f)
        .unwrap()
        .join()
        .unwrap()
}

/// One nesting construct: what opens a level, what closes it, and how many levels one
/// repetition opens.
struct Nest {
    open: &'static str,
    close: &'static str,
    levels: usize,
}

const NESTS: [Nest; 7] = [
    Nest {
        open: "[",
        close: "]",
        levels: 1,
    },
    Nest {
        open: "#[",
        close: "]",
        levels: 2,
    },
    Nest {
        open: "ABS[",
        close: "]",
        levels: 1,
    },
    Nest {
        open: "[1+",
        close: "]",
        levels: 1,
    },
    Nest {
        open: "#",
        close: "",
        levels: 1,
    },
    Nest {
        open: "-",
        close: "",
        levels: 1,
    },
    Nest {
        open: "ATAN[1]/[1 OR 1 EQ 1 + 1 * 1 ** ",
        close: "]",
        levels: 1,
    },
];

/// `G1 X<nest n times>[1]`, with `#1 = 1` so that every indirection is defined.
fn nested(n: &Nest, reps: usize, closed: bool) -> String {
    let close = if closed {
        n.close.repeat(reps)
    } else {
        String::new()
    };
    format!("#1=1\nG1 X{}[1]{close} F100\n", n.open.repeat(reps))
}

#[test]
fn the_deepest_allowed_nesting_is_accepted_and_one_more_level_is_refused_at_its_column() {
    for n in &NESTS {
        // [1] at the end is one level itself.
        let fits = (MAX_EXPRESSION_DEPTH - 1) / n.levels;
        let ok = nested(n, fits, true);
        let m = run(&ok).unwrap_or_else(|e| panic!("{:?}: {e}", n.open));
        assert_eq!(m.len(), 1, "{:?}", n.open);
        let reps = MAX_EXPRESSION_DEPTH / n.levels + 1;
        let e = err(&nested(n, reps, true));
        assert_eq!(e.line, 2, "{:?}: {e}", n.open);
        assert!(
            e.message
                .contains(&format!("limit of {MAX_EXPRESSION_DEPTH} levels")),
            "{:?}: {e}",
            n.open
        );
        // The column of the level past the limit: inside the nest, never before it.
        assert!(e.column > 4, "{:?}: {e}", n.open);
        assert!(
            (e.column as usize) <= 4 + (MAX_EXPRESSION_DEPTH / n.levels + 1) * n.open.len() + 3,
            "{:?}: {e}",
            n.open
        );
    }
    assert_eq!(err(&nested(&NESTS[0], 65, true)).column, 4 + 65);
}

#[test]
fn nesting_bombs_are_refused_on_a_small_stack_instead_of_overflowing_it() {
    // Before the bound, 3,000 to 12,000 levels overflowed the server's 2 MiB upload thread;
    // here half of that is enough for every bomb up to the longest line the reader takes.
    for n in &NESTS {
        for reps in [4_000, 12_000, 60_000 / n.open.len()] {
            for closed in [true, false] {
                let src = nested(n, reps, closed);
                if src.len() > Config::default().max_line_bytes {
                    continue;
                }
                let e = on_stack(1024 * 1024, move || run(&src).unwrap_err());
                assert_eq!(e.line, 2, "{:?} x{reps}: {e}", n.open);
                assert!(
                    e.message.contains("limit of 64 levels"),
                    "{:?} x{reps}: {e}",
                    n.open
                );
            }
        }
    }
    // The same in an O-word condition, a call argument, an assignment and a polar word.
    let deep = format!("{}1{}", "[".repeat(30_000), "]".repeat(30_000));
    for src in [
        format!("o1 if {deep}\no1 endif\n"),
        format!("o<s> sub\no<s> endsub\no<s> call {deep}\n"),
        format!("#1 = {deep}\n"),
        format!("##{}1 = 2\n", "#".repeat(50_000)),
        format!("G1 X1 F100\n@{deep} ^0\n"),
    ] {
        let e = on_stack(1024 * 1024, move || run(&src).unwrap_err());
        assert!(e.message.contains("limit of 64 levels"), "{e}");
    }
}

#[test]
fn the_costliest_allowed_nesting_fits_well_within_a_default_thread_stack() {
    // The costliest construct per level (a function, its second argument and every binary
    // precedence level), at the limit, through the whole analysis: measured ~570 KB in a
    // debug build and ~150 KB in release; the server's upload thread has 2 MiB.
    let worst = &NESTS[6];
    let src = nested(worst, MAX_EXPRESSION_DEPTH - 1, true);
    let a = on_stack(1024 * 1024, move || {
        analyse(src.as_bytes(), &AnalysisOptions::default()).map(|a| a.linear_moves)
    });
    assert_eq!(a.unwrap(), 1);
}

#[test]
fn expression_results_that_overflow_are_refused_at_the_operator() {
    for (src, col, what) in [
        ("G1 X[10**300*10**300] F100", 13, "'*'"),
        ("G1 X[10**400] F100", 8, "'**'"),
        ("G1 X[1-10**308-10**308] F100", 15, "'-'"),
        ("#1=EXP[1000]", 4, "EXP"),
        ("o1 if [[10**300*10**300] GT 1]\no1 endif", 16, "'*'"),
        ("G4 P[10**300/10**-300]", 13, "'/'"),
    ] {
        let e = err(src);
        assert_eq!((e.line, e.column), (1, col), "{src}: {e}");
        assert!(
            e.message.contains(what) && e.message.contains("not a finite number"),
            "{src}: {e}"
        );
    }
    // Big but finite intermediate results are fine.
    let m = run("G1 X[10**300/10**300] F100").unwrap();
    assert_eq!(m[0].end_point().unwrap()[0], 1.0);
}

#[test]
fn coordinates_beyond_any_machine_are_refused_at_their_word() {
    for (src, line, col, what) in [
        ("G0 X2000000", 1, 4, "X=2000000 mm"),
        ("G0 X[10**300]", 1, 4, "X=1e300 mm"),
        ("G20\nG0 Y40000", 2, 4, "Y=1016000 mm"),
        ("G0 A-1000001", 1, 4, "A=-1000001 degrees"),
        ("G0 X0\nG2 X1 I1000001 F100", 2, 7, "I=1000001 mm"),
        ("G0 X0\nG2 X1 R1000001 F100", 2, 7, "R=1000001 mm"),
        ("G92 Z1000001", 1, 5, "Z=1000001 mm"),
        ("G10 L2 P1 X1000001", 1, 11, "X=1000001 mm"),
        ("G0 @1000001 ^0", 1, 4, "@=1000001 mm"),
    ] {
        let e = err(src);
        assert_eq!((e.line, e.column), (line, col), "{src}: {e}");
        assert!(e.message.contains(what), "{src}: {e}");
    }
    // R1e6 is R1 and an E word (no exponents in G-code): refused as such.
    assert!(err("G0 X0\nG2 X1 R1e6").message.contains("E word"));
    // Exactly at the bound is fine.
    assert!(run("G0 X1000000 Y-1000000 A1000000").is_ok());
}

#[test]
fn positions_and_offsets_that_add_up_beyond_reach_are_refused_at_the_line() {
    for (src, line, col, what) in [
        // G91 steps: the second one ends beyond the bound.
        (
            "G91 G0 X600000\nX600000",
            2,
            1,
            "the move ends at X=1200000",
        ),
        ("G91 G0 Z-600000\nG0 Z-600000", 2, 4, "Z=-1200000"),
        ("G91 G0 A700000\nG0 A700000", 2, 4, "A=1400000 degrees"),
        // A G92 offset that shifts the frame past the bound.
        (
            "G0 X900000\nG92 X-900000",
            2,
            5,
            "the origin offset is X=1800000",
        ),
        // Canned-cycle repeats stepping out.
        ("G0 Z5\nG91 G81 X300000 Z-1 R1 L4 F100", 2, 9, "X=1200000"),
        // An arc that bulges out of reach although its ends and centre do not.
        ("G0 X0\nG2 I600000 F100", 2, 4, "the arc reaches X=1200000"),
        (
            "G0 Y-900000\nG18 G2 Y-900000 K-600000 F100",
            2,
            8,
            "the arc reaches Z=-1200000",
        ),
        // An arc whose centre is out of reach although its ends are not.
        (
            "G0 X900000\nG2 X900000 Y1 I900000 J0.5 F100",
            2,
            4,
            "the arc centre is at X=1800000",
        ),
    ] {
        let e = err(src);
        assert_eq!((e.line, e.column), (line, col), "{src}: {e}");
        assert!(e.message.contains(what), "{src}: {e}");
        assert!(
            e.message.contains("limit of 1000000 mm")
                || e.message.contains("limit of 1000000 degrees"),
            "{src}: {e}"
        );
    }
    // A move that cutter compensation holds to the end of the file, in a frame that a G10
    // shifted (found by the grammar fuzz target).
    let e = err("G10 L20 P0 Y-1000000\nG42.1 D2\nG0 Y1\n");
    assert_eq!((e.line, e.column), (3, 1), "{e}");
    assert!(e.message.contains("the move ends at Y=1000001 mm"), "{e}");
    // Nothing of the refused line comes out.
    let m: Vec<_> = Interpreter::new(
        "G91 G0 X600000\nM3 S100 X600000\n".as_bytes(),
        Config::default(),
    )
    .collect();
    assert_eq!(m.len(), 2, "{m:?}");
    assert!(m[0].is_ok() && m[1].is_err(), "{m:?}");
}

#[test]
fn dwell_feed_and_spindle_speed_beyond_their_limits_are_refused() {
    for (src, col, what) in [
        (
            "G4 P86401",
            4,
            "dwell P=86401 s is longer than the limit of 86400 s",
        ),
        ("G4 P[10**300]", 4, "dwell P=1e300 s"),
        ("G0 Z5\nG82 X1 Z-1 R1 P100000 F100", 15, "dwell P=100000 s"),
        (
            "G1 X1 F100000001",
            7,
            "F=100000001 mm/min is beyond the limit of 100000000 mm/min",
        ),
        ("G20 G1 X1 F4000000", 11, "F=101600000 mm/min"),
        ("G93 G1 X1 F[10**9]", 11, "F=1000000000 /min (G93)"),
        (
            "S1000001 M3",
            1,
            "S=1000001 rpm is beyond the limit of 1000000 rpm",
        ),
    ] {
        let e = err(src);
        assert_eq!(e.column, col, "{src}: {e}");
        assert!(e.message.contains(what), "{src}: {e}");
    }
    assert!(run("G4 P86400\nG1 X1 F100000000\nS1000000 M3").is_ok());
}

#[test]
fn o_word_blocks_nest_at_most_the_limit() {
    let program = |depth: usize| {
        let mut s = String::new();
        for i in 0..depth {
            s.push_str(&format!("o{i} if [1]\n"));
        }
        s.push_str("G0 X1\n");
        for i in (0..depth).rev() {
            s.push_str(&format!("o{i} endif\n"));
        }
        s
    };
    assert_eq!(run(&program(MAX_BLOCK_NESTING)).unwrap().len(), 1);
    let e = err(&program(MAX_BLOCK_NESTING + 1));
    assert_eq!((e.line, e.column), (MAX_BLOCK_NESTING as u32 + 1, 1), "{e}");
    assert!(e.message.contains("limit of 64"), "{e}");
    // Loops count too (the limit is per call level: a subroutine starts with none open).
    let dos: String = (0..70).map(|i| format!("o{i} do\n")).collect();
    let e = err(&format!("{dos}G0 X1\n"));
    assert_eq!(e.line, MAX_BLOCK_NESTING as u32 + 1, "{e}");
    assert!(
        e.message.contains("o<64> do") && e.message.contains("limit of 64"),
        "{e}"
    );
}

#[test]
fn nested_calls_count_against_the_loop_budget_and_cannot_multiply() {
    // Eight levels of 1,000 calls each: 10^21 lines if calls were free.
    let mut src = String::new();
    for i in 0..8 {
        src.push_str(&format!("o<s{i}> sub\n"));
        let body = if i < 7 {
            format!("o<s{}> call\n", i + 1).repeat(1000)
        } else {
            "G0 X1\n".to_string()
        };
        src.push_str(&body);
        src.push_str(&format!("o<s{i}> endsub\n"));
    }
    src.push_str("o<s0> call\nM30\n");
    let cfg = Config {
        max_loop_iterations: 10_000,
        ..Config::default()
    };
    let r: Result<Vec<Motion>, GcodeError> = Interpreter::new(src.as_bytes(), cfg).collect();
    let e = r.unwrap_err();
    assert!(
        e.message
            .contains("more than 10000 loop passes and subroutine calls"),
        "{e}"
    );
    // The 10,001st call is on a line of s6's body, at its O-word.
    assert_eq!(e.column, 1, "{e}");
    assert!(
        src.lines()
            .nth(e.line as usize - 1)
            .unwrap()
            .contains("call"),
        "{e}"
    );
}

#[test]
fn events_waiting_behind_compensated_moves_are_bounded() {
    // Found by the grammar fuzz target: a loop of messages with compensation on and no move
    // piled up every message behind the held move, and each line copied them all (minutes).
    let program = |n: usize| {
        format!(
            "G0 X-10 Y-10\nG42.1 D2\nG0 X0 Y0\nG1 X10 F100\no1 repeat [{n}]\n(msg, hi)\no1 endrepeat\nG1 X20\nG40 G0 X30\n"
        )
    };
    let m = run(&program(MAX_HELD_EVENTS - 10)).unwrap();
    let messages = m
        .iter()
        .filter(|m| matches!(m, Motion::Message { .. }))
        .count();
    assert_eq!(messages, MAX_HELD_EVENTS - 10);
    let e = err(&program(MAX_HELD_EVENTS + 10));
    assert_eq!(e.line, 6, "{e}");
    assert!(
        e.message
            .contains("more than 1000 events wait for the next move under cutter compensation"),
        "{e}"
    );
}

#[test]
fn a_closing_percent_releases_what_compensation_holds_like_m2() {
    // Found by the grammar fuzz target: the move compensation held came out after the
    // ProgramEnd of a closing '%' or, as the stream stops there by default, never.
    let src = "%\nG0 X-10 Y-10\nG42.1 D2\nG0 X0 Y0\nG1 X10 F100\nM5\n%\n";
    let m = run(src).unwrap();
    let lines: Vec<u32> = m.iter().map(Motion::line).collect();
    assert_eq!(m.last(), Some(&Motion::ProgramEnd { line: 7 }), "{m:?}");
    assert!(
        lines.contains(&5),
        "the held G1 X10 of line 5 is lost: {m:?}"
    );
    assert!(lines.windows(2).all(|w| w[0] <= w[1]), "{lines:?}");
    let m2 = run(&src.replace("M5\n%", "M5\nM2")).unwrap();
    assert_eq!(m.len(), m2.len(), "{m:?} / {m2:?}");
}

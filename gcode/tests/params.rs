//! Parameters, expressions and O-word control flow (LinuxCNC semantics; the
//! same programs are compared with rs274 in tests/conformance/).
#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_gcode::*;

fn ends(src: &str) -> Vec<Point> {
    Interpreter::new(src.as_bytes(), Config::default())
        .map(|m| m.unwrap_or_else(|e| panic!("{src}: {e}")))
        .filter_map(|m| m.end_point())
        .collect()
}

fn xs(src: &str) -> Vec<f64> {
    ends(src).iter().map(|p| p[0]).collect()
}

fn err(src: &str) -> GcodeError {
    err_cfg(src, Config::default())
}

fn err_cfg(src: &str, cfg: Config) -> GcodeError {
    Interpreter::new(src.as_bytes(), cfg)
        .find_map(Result::err)
        .unwrap_or_else(|| panic!("no error for {src}"))
}

#[test]
fn expressions_and_functions() {
    assert_eq!(
        xs("G0 X[1+2*3]\nX[10 MOD -3]\nX[-10 MOD 3]\nX[2**3]\nX[-2**2]\nX[ROUND[-2.5]]\nX[FIX[-2.5]]\nX[FUP[2.1]]\n"),
        vec![7.0, 1.0, 2.0, 8.0, 4.0, -3.0, -3.0, 3.0]
    );
    let v = xs("G0 X[ATAN[1]/[1]]\nX[SIN[30]]\nX[COS[60]]\nX[SQRT[16]]\nX[ABS[-2]]\nX[EXP[0]]\nX[LN[1]]\nX[ASIN[1]]\nX[ACOS[1]]\nX[TAN[45]]\n");
    let want = [45.0, 0.5, 0.5, 4.0, 2.0, 1.0, 0.0, 90.0, 0.0, 1.0];
    for (a, b) in v.iter().zip(want) {
        assert!((a - b).abs() < 1e-12, "{v:?}");
    }
    assert_eq!(
        xs("G0 X[1 EQ 1]\nX[1 NE 1]\nX[2 GT 1]\nX[2 GE 2]\nX[1 LT 2]\nX[3 LE 2]\nX[1 AND 0]\nX[1 OR 0]\nX[1 XOR 1]\n"),
        vec![1.0, 0.0, 1.0, 1.0, 1.0, 0.0, 0.0, 1.0, 0.0]
    );
    // Blanks and case do not matter; unary minus before brackets and parameters.
    assert_eq!(
        xs("#1=2\ng0 x - [ 1 + #1 ]\nx-#1\nxabs[-#1]\n"),
        vec![-3.0, -2.0, 2.0]
    );
}

#[test]
fn parameters_and_the_assignment_after_the_line_rule() {
    // LinuxCNC: assignments take effect after the whole line is read.
    assert_eq!(xs("#1=5\n#1=7 G0 X#1\nX#1\n"), vec![5.0, 7.0]);
    assert_eq!(
        xs("#1=1 #2=[#1+1]\nG0 X#2\n"),
        vec![1.0],
        "#2 read the old #1 (0)"
    );
    // Indirect and named, local and global.
    assert_eq!(
        xs("#2=3 #3=9\nG0 X##2\n#<a>=4 #<_bb>=5\nX[#<a>+#<_bb>]\nX#<A>\n"),
        vec![9.0, 9.0, 4.0]
    );
    // System parameters read the interpreter's state: position (#5420, #<_x>) in program units.
    assert_eq!(xs("G0 X4\nX[#5420+1]\nX[#<_x>*2]\n"), vec![4.0, 5.0, 10.0]);
    assert_eq!(xs("G20 G0 X1\nX[#<_x>+1]\n"), vec![25.4, 50.8]);
    // Values are read with the line, before its G55 runs (as in LinuxCNC).
    assert_eq!(xs("G55 G0 X[#5220]\nX#5220\n"), vec![1.0, 2.0]);
    // EXISTS does not fail on an undefined name.
    assert_eq!(
        xs("G0 X[EXISTS[#<nope>]]\n#<yes>=1\nX[EXISTS[#<yes>]]\n"),
        vec![0.0, 1.0]
    );
}

#[test]
fn debug_and_print_messages_substitute_parameters() {
    let m: Vec<Motion> = Interpreter::new(
        "#1=2.5 #<n>=3\n(debug, one #1 two #<n> three #<missing>)\n(print,#1)\n".as_bytes(),
        Config::default(),
    )
    .collect::<Result<_, _>>()
    .unwrap();
    let texts: Vec<&str> = m
        .iter()
        .filter_map(|m| match m {
            Motion::Message { text, .. } => Some(text.as_str()),
            _ => None,
        })
        .collect();
    assert_eq!(
        texts,
        ["one 2.500000 two 3.000000 three #<missing>", "2.500000"]
    );
}

#[test]
fn errors_name_line_and_column() {
    let e = err("G0 X1\nG0 X[1/0]\n");
    assert_eq!((e.line, e.column, e.kind), (2, 7, ErrorKind::Invalid));
    assert!(e.message.contains("division by zero"), "{e}");
    let e = err("G0 X[SQRT[-1]]\n");
    assert_eq!((e.line, e.column), (1, 10));
    assert!(e.message.contains("SQRT"), "{e}");
    let e = err("G0 X[LN[0]]\n");
    assert!(e.message.contains("LN"), "{e}");
    let e = err("G0 X[ACOS[2]]\n");
    assert!(e.message.contains("ACOS"), "{e}");
    let e = err("\nG0 X#<undefined>\n");
    assert_eq!((e.line, e.column), (2, 5));
    assert!(e.message.contains("#<undefined> is not defined"), "{e}");
    let e = err("#6000=1\n");
    assert!(e.message.contains("out of range"), "{e}");
    let e = err("G0 X[1 + FOO[2]]\n");
    assert!(e.message.contains("unknown function"), "{e}");
    let e = err("#1 5\n");
    assert_eq!(e.kind, ErrorKind::Syntax);
}

#[test]
fn subroutines_with_arguments_locals_and_return_values() {
    let src = "o<sq> sub\n#<r>=[#1*#1]\no<sq> endsub [#<r>]\n\
               #1=7\no<sq> call [3]\nG0 X#<_value> Y#1\n\
               o<sq> call [4]\nG0 X#<_value>\n";
    // #1 is the caller's again after the call (local #1..#30).
    assert_eq!(ends(src), vec![[9.0, 7.0, 0.0], [16.0, 7.0, 0.0]]);
    // Named locals do not leak out of the subroutine.
    let e = err("o1 sub\n#<x>=1\no1 endsub\no1 call\nG0 X#<x>\n");
    assert!(e.message.contains("#<x>"), "{e}");
    // A subroutine defined after its call is found by reading ahead.
    assert_eq!(
        xs("o<later> call [5]\nG0 X1\nM2\no<later> sub\nG0 X#1\no<later> endsub\n"),
        vec![5.0, 1.0]
    );
    // return from inside an if (any o-name), as LinuxCNC's retval.ngc does.
    let src = "o1 sub\no2 if [#1 GT 0]\no2 return [1]\no2 endif\no1 endsub [2]\n\
               o1 call [1]\nG0 X#<_value>\no1 call [0]\nG0 X#<_value>\n";
    assert_eq!(xs(src), vec![1.0, 2.0]);
    // Recursion (factorial).
    let src = "o<f> sub\no<t> if [#1 LE 1]\no<f> return [1]\no<t> endif\n\
               o<f> call [#1-1]\no<f> endsub [#1*#<_value>]\no<f> call [5]\nG0 X#<_value>\n";
    assert_eq!(xs(src), vec![120.0]);
}

#[test]
fn if_while_do_repeat_break_continue() {
    let src = "#1=2\no1 if [#1 EQ 1]\nG0 X1\no1 elseif [#1 EQ 2]\nG0 X2\no1 elseif [#1 EQ 2]\nG0 X3\no1 else\nG0 X4\no1 endif\n";
    assert_eq!(xs(src), vec![2.0]);
    assert_eq!(
        xs("o1 if [0]\nG0 X1\no1 else\nG0 X5\no1 endif\n"),
        vec![5.0]
    );
    assert_eq!(
        xs("#1=0\no1 while [#1 LT 3]\n#1=[#1+1]\nG0 X#1\no1 endwhile\n"),
        vec![1.0, 2.0, 3.0]
    );
    assert_eq!(
        xs("#1=5\no1 do\nG0 X#1\n#1=[#1+1]\no1 while [#1 LT 3]\n"),
        vec![5.0]
    );
    assert_eq!(
        xs("G91\no1 repeat [3]\nG0 X1\no1 endrepeat\n"),
        vec![1.0, 2.0, 3.0]
    );
    assert_eq!(xs("o1 repeat [0]\nG0 X1\no1 endrepeat\nG0 X9\n"), vec![9.0]);
    let src = "#1=0\no1 while [1]\n#1=[#1+1]\no2 if [#1 EQ 2]\no1 continue\no2 endif\no3 if [#1 GT 3]\no1 break\no3 endif\nG0 X#1\no1 endwhile\nG0 Y1\n";
    assert_eq!(
        ends(src),
        vec![[1.0, 0.0, 0.0], [3.0, 0.0, 0.0], [3.0, 1.0, 0.0]]
    );
}

#[test]
fn fanuc_m98_m99_subprograms() {
    // M98 P<n> L<count> calls O<n> (after the main program's M30), M99 returns.
    let src = "G21 G90\nG0 X0\nM98 P1000 L2\nG0 Y1\nM30\nO1000\nG91 G0 X1\nG90\nM99\n";
    assert_eq!(
        ends(src),
        vec![[0.0; 3], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [2.0, 1.0, 0.0]]
    );
    let e = err("G0 X1\nM99\n");
    assert_eq!((e.line, e.column), (2, 1));
    let e = err("M98 P5\nM30\n");
    assert!(e.message.contains("o<5>"), "{e}");
}

#[test]
fn limits_are_errors_not_hangs() {
    let cfg = Config {
        max_loop_iterations: 1000,
        ..Config::default()
    };
    let e = err_cfg("o1 while [1]\nG0 X1\no1 endwhile\n", cfg.clone());
    assert_eq!(e.line, 3);
    assert!(e.message.contains("max_loop_iterations"), "{e}");
    let e = err_cfg("o1 sub\no1 call\no1 endsub\no1 call\n", cfg.clone());
    assert_eq!(e.line, 2);
    assert!(e.message.contains("max_call_depth"), "{e}");
    // Unclosed blocks and missing subroutines name what is open.
    let e = err("o1 if [1]\nG0 X1\n");
    assert!(e.message.contains("o<1> if"), "{e}");
    let e = err("o<nowhere> call\n");
    assert!(e.message.contains("o<nowhere>"), "{e}");
    let e = err("o1 endwhile\n");
    assert_eq!((e.line, e.column), (1, 1));
    let e = err("o1 frobnicate\n");
    assert_eq!((e.line, e.column), (1, 4));
    let e = err("o1 if [1] G0 X1\n");
    assert_eq!((e.line, e.column), (1, 11));
    // The text kept for jumps is bounded too.
    let small = Config {
        max_kept_program_bytes: 64,
        ..Config::default()
    };
    let long = format!("o1 repeat [2]\n{}o1 endrepeat\n", "G0 X1\n".repeat(20));
    let e = err_cfg(&long, small);
    assert_eq!(e.kind, ErrorKind::Io);
    assert!(e.message.contains("max_kept_program_bytes"), "{e}");
}

#[test]
fn plain_programs_are_not_buffered() {
    // A program without O-words streams: the interpreter keeps no text, which
    // tests/alloc.rs checks by allocation count; here, line numbers stay right
    // across jumps.
    let src = "G0 X1\no1 repeat [2]\nG0 X[1/0]\no1 endrepeat\n";
    let e = err(src);
    assert_eq!(e.line, 3);
}

#[test]
fn linuxcnc_only_syntax_is_reported_by_line() {
    let line = |src: &str| {
        let mut it = Interpreter::new(src.as_bytes(), Config::default());
        for m in it.by_ref() {
            m.unwrap();
        }
        it.linuxcnc_only_line()
    };
    // Numbered parameters, expressions and M98 subprograms are common ground (Mach3 runs them).
    assert_eq!(
        line("#1=2\nG0 X[#1*2]\nM98 P100\nM30\nO100\nG0 X1\nM99\n"),
        None
    );
    assert_eq!(line("G0 X1\n#<a>=1\n"), Some(2));
    assert_eq!(line("G0 X1\nG0 X1\no1 if [1]\no1 endif\n"), Some(3));
    assert_eq!(line("G0 X1\n(debug, hi)\n"), Some(2));
    assert_eq!(line("G0 X[EXISTS[#<a>]]\n"), Some(1));
}

#[test]
fn modal_state_save_restore_and_m61() {
    // M70 saves, M72 restores (units, distance mode, feed), M71 forgets.
    let m: Vec<Motion> = Interpreter::new(
        "G21 G90 F200\nM70\nG20 G91 F10\nG1 X1\nM72\nG1 X5\nM71\n".as_bytes(),
        Config::default(),
    )
    .collect::<Result<_, _>>()
    .unwrap();
    match (&m[0], &m[1]) {
        (
            Motion::Linear {
                to: a,
                feed_mm_min: fa,
                ..
            },
            Motion::Linear {
                to: b,
                feed_mm_min: fb,
                ..
            },
        ) => {
            assert_eq!((a[0], *fa), (25.4, 254.0));
            assert_eq!((b[0], *fb), (5.0, 200.0), "absolute mm at F200 again");
        }
        other => panic!("{other:?}"),
    }
    let e = err("M72\n");
    assert!(e.message.contains("M70"), "{e}");
    // M73 restores when the subroutine returns.
    assert_eq!(
        xs("o1 sub\nM73\nG91\no1 endsub\nG0 X1\no1 call\nG0 X1\n"),
        vec![1.0, 1.0]
    );
    // M61 Q sets the tool without a change; G43 then uses it.
    let m: Vec<Motion> = Interpreter::new("M61 Q4\nG43\n".as_bytes(), Config::default())
        .collect::<Result<_, _>>()
        .unwrap();
    assert_eq!(
        m,
        vec![Motion::ToolLengthOffset {
            line: 2,
            tool: Some(4)
        }]
    );
    assert!(err("M61\n").message.contains("M61"));
}

/// G38.2-G38.5: the probing move, and its result fed back by the machine that ran it (the
/// trip in #5061..#5063 and #5070, the tool at rest) into the rest of the program; without a
/// machine, LinuxCNC's stand-alone assumption (no contact, 0.254 mm back from the end).
#[test]
fn probe_results_feed_the_rest_of_the_program() {
    let src = "G21 G90 F100\nG38.2 Z-50\nG0 Z[#5063 + 5] X[#5070]\nG91 G0 X1\n";
    // Fed back: tripped at Z -20.25, came to rest at -20.3.
    let mut it = Interpreter::new(src.as_bytes(), Config::default());
    let probe = it.next().unwrap().unwrap();
    assert!(
        matches!(
            probe,
            Motion::Probe { line: 2, to, feed_mm_min, contact: true, must_trip: true, .. }
                if to == [0.0, 0.0, -50.0] && feed_mm_min == 100.0
        ),
        "{probe:?}"
    );
    it.probe_result(ProbeResult {
        tripped: true,
        trip: [0.0, 0.0, -20.25],
        rest: [0.0, 0.0, -20.3],
    });
    let rest: Vec<Motion> = it.map(Result::unwrap).collect();
    let fed: Vec<Point> = rest.iter().filter_map(Motion::end_point).collect();
    assert_eq!(
        fed,
        vec![[1.0, 0.0, -15.25], [2.0, 0.0, -15.25]],
        "{rest:?}"
    );
    // The next move starts where the tool rested, not at the probe's end.
    assert!(
        matches!(rest[0], Motion::Rapid { from, .. } if from == [0.0, 0.0, -20.3]),
        "{rest:?}"
    );
    // Not fed back (an upload check): untripped at the end, resting 0.254 mm back.
    let alone: Vec<Motion> = Interpreter::new(src.as_bytes(), Config::default())
        .map(Result::unwrap)
        .collect();
    assert!(
        matches!(alone[1], Motion::Rapid { from, to, .. }
            if (from[2] + 49.746).abs() < 1e-12 && to == [0.0, 0.0, -45.0]),
        "{alone:?}"
    );
    // In an inch program the parameters are in inches.
    let mut it = Interpreter::new(
        "G20 F10\nG38.3 X-2\nG0 Y[#5061]\n".as_bytes(),
        Config::default(),
    );
    assert!(matches!(
        it.next(),
        Some(Ok(Motion::Probe {
            contact: true,
            must_trip: false,
            ..
        }))
    ));
    it.probe_result(ProbeResult {
        tripped: true,
        trip: [-25.4, 0.0, 0.0],
        rest: [-25.4, 0.0, 0.0],
    });
    let end = it.find_map(|m| m.unwrap().end_point()).unwrap();
    assert!((end[1] + 25.4).abs() < 1e-9, "Y = #5061 = -1 in: {end:?}");
    // G38.4/G38.5 look for the release.
    assert!(matches!(
        Interpreter::new("F10\nG38.5 Z5\n".as_bytes(), Config::default()).next(),
        Some(Ok(Motion::Probe {
            contact: false,
            must_trip: false,
            ..
        }))
    ));
}

/// Mach3's G31 (autolevellers such as pcb2gcode's Mach3 output read #2000..#2002): a
/// contact probe that is no error when the whole move runs (as G38.3), modal like G1, whose
/// trip goes to #2000..#2002 (program coordinates) as well as #5061..#5063.
#[test]
fn mach3_g31_probes_and_leaves_the_trip_in_2000_to_2002() {
    let src =
        "G21 G90 F50\nG31 Z-10\nG0 Z[#2002 + 1] X[#2000] Y[#2001]\nG31 X5 Y6 Z-9\nG0 Z[#2002]\n";
    let mut it = Interpreter::new(src.as_bytes(), Config::default());
    assert!(
        matches!(
            it.next(),
            Some(Ok(Motion::Probe { line: 2, to, contact: true, must_trip: false, .. }))
                if to == [0.0, 0.0, -10.0]
        ),
        "G31 is a contact probe that may run its whole way"
    );
    it.probe_result(ProbeResult {
        tripped: true,
        trip: [0.0, 0.0, -3.5],
        rest: [0.0, 0.0, -3.55],
    });
    let next = it.next().unwrap().unwrap();
    assert_eq!(next.end_point(), Some([0.0, 0.0, -2.5]), "{next:?}");
    // Modal: the next line with axis words probes again.
    let again = it.next().unwrap().unwrap();
    assert!(
        matches!(again, Motion::Probe { line: 4, to, .. } if to == [5.0, 6.0, -9.0]),
        "{again:?}"
    );
    // Not tripped (the whole move ran): no error, #2002 the end point.
    it.probe_result(ProbeResult {
        tripped: false,
        trip: [5.0, 6.0, -9.0],
        rest: [5.0, 6.0, -9.0],
    });
    let last = it.next().unwrap().unwrap();
    assert_eq!(last.end_point(), Some([5.0, 6.0, -9.0]), "{last:?}");
    assert!(it.next().is_none());
}

/// Which moves depend on where a probe trips: the program run side by side as if every
/// probe found nothing and as if every probe touched at once. The moves after `G0
/// Z[#5063 + 20]` differ (Z -30 against Z 25: a touch at the start, Z 5), the probe's own
/// does not; the bounds of
/// both cases are merged into the analysis (the worst case); a loop on #5070 (LinuxCNC's
/// smartprobe.ngc) makes the two cases part ways, and the analysis says from which line.
#[test]
fn the_analysis_names_the_moves_that_depend_on_a_probe() {
    let src = "G21 G90 F100\nG0 Z5\nG38.2 Z-50\nG0 Z[#5063 + 20]\nG0 X10\nG1 X20\nM2\n";
    let opts = fresa_gcode::AnalysisOptions::default();
    let spread = fresa_gcode::probe_spread(src.as_bytes(), src.as_bytes(), &opts);
    assert_eq!(spread.dependent_moves, 3, "{spread:?}");
    assert_eq!(spread.first_dependent_line, Some(4), "{spread:?}");
    assert_eq!(spread.unchecked_from_line, None, "{spread:?}");
    let mut a = fresa_gcode::analyse(src.as_bytes(), &opts).unwrap();
    // Without the spread: the probe from Z 5 down, the cut at Z -30.
    let cut = a.cutting_bounds.unwrap();
    assert!((cut.max[2] - 5.0).abs() < 1e-9, "{cut:?}");
    a.merge_probe_spread(&spread);
    // The G1 X20 runs at Z -30 (no contact) or Z 25 (contact at once): both count.
    let cut = a.cutting_bounds.unwrap();
    assert!((cut.max[2] - 25.0).abs() < 1e-9, "{cut:?}");
    assert!((cut.min[2] + 50.0).abs() < 1e-9, "{cut:?}");
    assert_eq!(a.probe_dependent_moves, 3);
    assert_eq!(a.first_probe_dependent_line, Some(4));

    let smart = "G20 F20\n#5070=1\nO4 while [#5070 NE 0]\nG38.5 z1\nG38.3 x1\nO4 endwhile\n\
                 G38.2 Z-0.1\nM2\n";
    let spread = fresa_gcode::probe_spread(smart.as_bytes(), smart.as_bytes(), &opts);
    assert!(spread.unchecked_from_line.is_some(), "{spread:?}");
}

/// What LinuxCNC refuses in a probing move is refused here, naming the line.
#[test]
fn probing_moves_refuse_what_linuxcnc_refuses() {
    for (src, needle) in [
        ("G38.2 Z-5\n", "no feed rate"),
        ("F100\nG38.4 Z0\n", "too close"),
        ("F100 G93\nG38.2 Z-5\n", "inverse time"),
        ("F100\nG38.2 Z-5 A10\n", "A axis"),
        (
            "F100\nG41 D1 G1 X10\nG38.2 Z-5\n",
            "cutter radius compensation",
        ),
        ("F100\nG53 G38.2 Z-5\n", "G53"),
    ] {
        let e = err_cfg(
            src,
            Config {
                tools: [(
                    1,
                    Tool {
                        diameter_mm: 2.0,
                        length_mm: 0.0,
                    },
                )]
                .into_iter()
                .collect(),
                ..Config::default()
            },
        );
        assert!(e.message.contains(needle), "{src:?}: {e}");
    }
}

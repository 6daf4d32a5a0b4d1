//! Fixed work for load-independent measurements: interprets (and
//! linearises) FILE REPS times and prints the motions. Run under
//! `valgrind --tool=cachegrind --cache-sim=no` with two REPS values; the
//! difference of the instruction counts divided by the difference of REPS is
//! the cost of one pass, free of start-up and of other load on the machine.
//!
//!   cargo build --release -p fresa-gcode --example instructions
//!   valgrind --tool=cachegrind --cache-sim=no target/release/examples/instructions FILE 2 [lin|an]
//!
//! `json` prints the analysis as JSON (one pass) instead, so two builds can be
//! compared byte for byte: `instructions FILE 1 json > a.json`.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_gcode::{linearise, Config, Interpreter};
use std::hint::black_box;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let path = args.get(1).expect("usage: instructions FILE REPS [lin|an]");
    let reps: usize = args.get(2).map_or(1, |r| r.parse().expect("REPS"));
    let lin = args.get(3).is_some_and(|a| a == "lin");
    // `an`: the whole analysis, as an upload runs it.
    let an = args.get(3).is_some_and(|a| a == "an");
    let src = std::fs::read(path).expect("read FILE");
    if args.get(3).is_some_and(|a| a == "json") {
        // An error is part of the result too: print it the same way.
        match fresa_gcode::analyse(&src[..], &fresa_gcode::AnalysisOptions::default()) {
            Ok(a) => println!("{}", serde_json::to_string(&a).unwrap()),
            Err(e) => println!("error: {}", serde_json::to_string(&e).unwrap()),
        }
        return;
    }
    let mut n = 0u64;
    for _ in 0..reps {
        if an {
            let a = fresa_gcode::analyse(&src[..], &fresa_gcode::AnalysisOptions::default());
            n += a.unwrap().motion_lines;
        } else if lin {
            for m in linearise(Interpreter::new(&src[..], Config::default()), 0.002) {
                black_box(m.unwrap());
                n += 1;
            }
        } else {
            for m in Interpreter::new(&src[..], Config::default()) {
                black_box(m.unwrap());
                n += 1;
            }
        }
    }
    println!("{n} motions");
}

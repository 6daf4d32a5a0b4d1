//! The hot path does not allocate per line: a counting global allocator
//! (this test binary only) sees the same small number of allocations for one
//! copy of a program as for twenty. Counting is per thread, so the test harness's own threads
//! (result collection, slow-test reporting under load) cannot add to it.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_gcode::*;
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

struct Counting;
thread_local! {
    static ALLOCS: Cell<u64> = const { Cell::new(0) };
}

fn counted() {
    // `try_with`: no panic if a thread allocates while its locals are being torn down.
    let _ = ALLOCS.try_with(|c| c.set(c.get() + 1));
}

fn allocs() -> u64 {
    ALLOCS.with(Cell::get)
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        counted();
        // SAFETY: forwarded unchanged to the system allocator.
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: forwarded unchanged to the system allocator.
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        counted();
        // SAFETY: forwarded unchanged to the system allocator.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

fn count(src: &[u8]) -> (u64, u64) {
    let cfg = Config {
        stop_at_program_end: false,
        ..Config::default()
    };
    let before = allocs();
    let mut n = 0u64;
    for m in linearise(Interpreter::new(src, cfg), 0.002) {
        m.unwrap();
        n += 1;
    }
    (allocs() - before, n)
}

#[test]
fn interpret_and_linearise_do_not_allocate_per_line() {
    // Fusion-style program with arcs in all planes, modal lines, spindle and
    // coolant words and comments (no (msg,...) comments: those allocate their text).
    let unit =
        "G90 G94 G17 G21\n(comment)\nT1\nS5000 M3\nG54\nG0 X10 Y0\nZ5 ; note\nG1 Z-1 F1000\n\
        G3 X0 Y10 I-10 J0\nG2 X-10 Y0 R10\nG18 G2 X10 Z-1 I10 K0\nG19 G3 Y0 Z-1 J-10 K0\nG17\n\
        G1 X10 Y0\nM8\nM9\nG4 P0.1\nM5\nM2\n";
    let one = unit.to_string();
    let many = unit.repeat(20);
    let (a1, n1) = count(one.as_bytes());
    let (a20, n20) = count(many.as_bytes());
    assert!(n20 > 19 * n1, "{n1} {n20}");
    assert_eq!(a1, a20, "allocations grew with the program: {a1} vs {a20}");
    assert!(a1 < 10, "{a1} allocations");
    // The interpreter's line buffer is allocated once: a counter that saw nothing is broken.
    assert!(a1 > 0, "the counting allocator saw no allocation at all");
}

/// Allocations for a program of `n` events waiting behind a move cutter compensation holds,
/// then a move that releases them.
fn held_events(n: usize, events: &str) -> u64 {
    let mut src = String::from("G21 G90 F100\nG0 X-10 Y-10\nG41.1 D2 G1 X0 Y0\nG1 X10\n");
    for _ in 0..n {
        src.push_str(events);
    }
    src.push_str("G1 X20\nG40 G1 X30 Y-10\nM2\n");
    let (a, m) = count(src.as_bytes());
    assert!(m as usize > n, "{m} motions for {n} events");
    a
}

#[test]
fn events_behind_a_held_move_cost_the_same_each() {
    // Every line under compensation used to copy all the events waiting behind the held move:
    // 1,000 messages were a million copies (found by the grammar fuzz target, 2.3 s of CPU under
    // AddressSanitizer for one 270-byte program).
    for (events, per) in [("(msg, hi)\n", 1), ("M8\n", 1), ("M8\nM9\nG4 P0\n", 3)] {
        let (small, large) = (
            held_events(100 / per, events),
            held_events(800 / per, events),
        );
        // Linear: 8 times the events, about 8 times the allocations (each message allocates its
        // text); a copy per line would be about 64 times.
        assert!(
            large <= 10 * small.max(1),
            "{events:?}: {small} allocations for 100 events, {large} for 800"
        );
    }
}

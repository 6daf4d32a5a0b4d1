//! Per-input stack and CPU budget of the fuzz checks, shared by `#[path]` between the fuzz
//! crates of `gcode` and `mpg-pendant` (and so their replay tests).
//!
//! A check runs on a thread with [`STACK_BYTES`] of stack, half the server's upload thread (a
//! tokio blocking thread, 2 MiB), so a recursion the input drives deeper is found long before
//! it could overflow the server. The deepest nesting the G-code reader accepts needs ~570 KB in
//! a debug build (the replay tests) and ~150 KB optimised.
//!
//! The fuzz targets also give a CPU-time budget: the check thread's own CPU time (user +
//! system, from `/proc/thread-self/stat`), not wall time, which a loaded shared machine
//! stretches several-fold. The replay tests give none: tests must not time.

use std::time::Duration;

pub const STACK_BYTES: usize = 1 << 20;
/// CPU time one input may take while fuzzing: a slow input is a finding even when it ends
/// before libFuzzer's `-timeout`.
pub const FUZZ_CPU_BUDGET: Duration = Duration::from_secs(2);

/// Runs `f` on a thread with [`STACK_BYTES`] of stack (an overflow there aborts the fuzzer and
/// the replay test alike) and re-raises its panic here; with `budget`, fails when the thread
/// used more CPU time than that.
pub fn on_small_stack(budget: Option<Duration>, f: impl FnOnce() + Send + 'static) {
    let joined = std::thread::Builder::new()
        .stack_size(STACK_BYTES)
        .spawn(move || {
            f();
            thread_cpu_time()
        })
        .map(|t| t.join());
    match joined {
        Ok(Ok(used)) => {
            if let (Some(budget), Some(used)) = (budget, used) {
                assert!(
                    used < budget,
                    "one input took {used:?} of CPU (budget {budget:?})"
                );
            }
        }
        Ok(Err(panic)) => std::panic::resume_unwind(panic),
        Err(e) => panic!("cannot start the check thread: {e}"),
    }
}

/// User + system CPU time of the calling thread (Linux; `None` elsewhere or if unreadable).
fn thread_cpu_time() -> Option<Duration> {
    let stat = std::fs::read_to_string("/proc/thread-self/stat").ok()?;
    // Fields after the command name (which may hold spaces) start with field 3, the state;
    // utime and stime are fields 14 and 15, in clock ticks (100 per second on Linux).
    let rest = &stat[stat.rfind(')')? + 1..];
    let mut f = rest.split_whitespace().skip(11);
    let ticks: u64 = f.next()?.parse::<u64>().ok()? + f.next()?.parse::<u64>().ok()?;
    Some(Duration::from_millis(ticks * 10))
}

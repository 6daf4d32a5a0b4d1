//! `gcode-bench`: throughput of fresa-gcode on the shared corpus, side by side
//! with the independent `gcode` crate (crates.io, parse only, zero-allocation
//! visitor API), plus peak RSS while streaming a large synthetic program.
//!
//! Run (from the workspace root):
//!   CARGO_TARGET_DIR=/work/target-gcode cargo bench -p fresa-gcode --bench gcode-bench
//! Options after `--`: `--mem-mb N` (synthetic program size, default 1024,
//! 0 to skip), `--synth-mb N` (the generated CAM-style program analysed as an
//! upload analyses it, default 200; the parametric one is a quarter of it;
//! 0 to skip), `--secs S` (time per measurement, default 0.5), `--python P`
//! (a python with pygcode installed: adds pygcode as a second independent
//! parser; `benches/with-pygcode.sh` sets that up).
#![allow(clippy::unwrap_used, clippy::expect_used)]

#[path = "support/synth.rs"]
mod synth;

use fresa_gcode::{analyse, linearise, AnalysisOptions, Config, Interpreter, Motion};
use std::hint::black_box;
use std::io::{BufReader, Read};
use std::path::PathBuf;
use std::time::{Duration, Instant};

fn corpus_dir() -> PathBuf {
    let dir = PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../shared/corpus/gcode"
    ));
    assert!(
        dir.is_dir(),
        "G-code corpus not found at {} (expected shared/ beside the workspace root)",
        dir.display()
    );
    dir
}

/// Peak resident set size of this process so far (VmHWM), in KiB.
fn peak_rss_kib() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

fn current_rss_kib() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmRSS:"))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

/// Best time per run of `f` over several rounds of at least `budget` each.
fn measure(budget: Duration, mut f: impl FnMut() -> u64) -> Duration {
    black_box(f()); // warm-up
    let mut best = Duration::MAX;
    for _ in 0..3 {
        let start = Instant::now();
        let mut n = 0u32;
        while start.elapsed() < budget || n == 0 {
            black_box(f());
            n += 1;
        }
        best = best.min(start.elapsed() / n);
    }
    best
}

// --- fresa-gcode workloads ---------------------------------------------------

fn fresa_interpret(src: &[u8]) -> u64 {
    let mut n = 0;
    for m in Interpreter::new(src, bench_config()) {
        black_box(&m);
        n += 1;
    }
    n
}

fn fresa_linearise(src: &[u8]) -> u64 {
    let mut n = 0;
    for m in linearise(Interpreter::new(src, bench_config()), 0.002) {
        if let Ok(Motion::Linear { to, .. }) = m {
            black_box(to);
        }
        n += 1;
    }
    n
}

fn fresa_analyse(src: &[u8]) -> u64 {
    let opts = AnalysisOptions {
        config: bench_config(),
        ..AnalysisOptions::default()
    };
    match analyse(src, &opts) {
        Ok(a) => a.motion_lines,
        Err(_) => 0,
    }
}

fn bench_config() -> Config {
    // One corpus file uses G42; skipping that line lets the whole file run.
    // (Files with a genuinely bad arc stop there, in every column alike.)
    Config {
        unsupported: fresa_gcode::Unsupported::SkipWithWarning,
        ..Config::default()
    }
}

// --- the independent `gcode` crate (parse only) -------------------------------

mod other {
    use gcode::core::{
        BlockVisitor, CommandVisitor, ControlFlow, Diagnostics, HasDiagnostics, Noop, Number,
        ProgramVisitor, Span, Value,
    };

    /// Touches every number so the parse cannot be optimised away.
    #[derive(Default)]
    pub struct Sum {
        pub words: u64,
        pub acc: f64,
        diag: Noop,
    }
    impl HasDiagnostics for Sum {
        fn diagnostics(&mut self) -> &mut dyn Diagnostics {
            &mut self.diag
        }
    }
    pub struct B<'a>(&'a mut Sum);
    pub struct C<'a>(&'a mut Sum);
    // Concrete return types instead of the trait's `impl Trait`, as in the
    // crate's own docs.
    #[allow(refining_impl_trait)]
    impl ProgramVisitor for Sum {
        fn start_block(&mut self) -> ControlFlow<B<'_>> {
            ControlFlow::Continue(B(self))
        }
    }
    impl HasDiagnostics for B<'_> {
        fn diagnostics(&mut self) -> &mut dyn Diagnostics {
            &mut self.0.diag
        }
    }
    impl HasDiagnostics for C<'_> {
        fn diagnostics(&mut self) -> &mut dyn Diagnostics {
            &mut self.0.diag
        }
    }
    fn val(v: Value<'_>) -> f64 {
        match v {
            Value::Literal(x) => f64::from(x),
            Value::Variable(_) => 0.0,
        }
    }
    #[allow(refining_impl_trait)]
    impl BlockVisitor for B<'_> {
        fn word_address(&mut self, _letter: char, value: Value<'_>, _span: Span) {
            self.0.words += 1;
            self.0.acc += val(value);
        }
        fn start_general_code(&mut self, _n: Number) -> ControlFlow<C<'_>> {
            self.0.words += 1;
            ControlFlow::Continue(C(self.0))
        }
        fn start_miscellaneous_code(&mut self, _n: Number) -> ControlFlow<C<'_>> {
            self.0.words += 1;
            ControlFlow::Continue(C(self.0))
        }
        fn start_tool_change_code(&mut self, _n: Number) -> ControlFlow<C<'_>> {
            self.0.words += 1;
            ControlFlow::Continue(C(self.0))
        }
    }
    impl CommandVisitor for C<'_> {
        fn argument(&mut self, _letter: char, value: Value<'_>, _span: Span) {
            self.0.words += 1;
            self.0.acc += val(value);
        }
    }

    pub fn parse(src: &str) -> u64 {
        let mut s = Sum::default();
        gcode::core::parse(src, &mut s);
        std::hint::black_box(s.acc);
        s.words
    }
}

// --- large synthetic program ---------------------------------------------------

/// Repeats `unit` until `total` bytes have been produced, without ever
/// holding more than one copy: a stand-in for a huge file on disk.
struct Repeat<'a> {
    unit: &'a [u8],
    pos: usize,
    left: u64,
}
impl Read for Repeat<'_> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        if self.left == 0 {
            return Ok(0);
        }
        let avail = &self.unit[self.pos..];
        let n = avail.len().min(buf.len()).min(self.left as usize);
        buf[..n].copy_from_slice(&avail[..n]);
        self.pos = (self.pos + n) % self.unit.len();
        self.left -= n as u64;
        Ok(n)
    }
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let opt = |name: &str, default: f64| -> f64 {
        args.iter()
            .position(|a| a == name)
            .and_then(|i| args.get(i + 1))
            .and_then(|v| v.parse().ok())
            .unwrap_or(default)
    };
    // `cargo bench` passes --bench; `cargo test --all-targets` runs this
    // binary without it, where a quick smoke run is enough.
    let smoke = !args.iter().any(|a| a == "--bench");
    let mem_mb = opt("--mem-mb", if smoke { 1.0 } else { 1024.0 });
    let budget = Duration::from_secs_f64(opt("--secs", if smoke { 0.001 } else { 0.5 }));
    if smoke {
        println!("(smoke run: use `cargo bench` for real numbers)");
    }
    let dir = corpus_dir();
    let pocket = std::fs::read(dir.join("cncjs-tball-pocket.gcode")).unwrap();

    let synth_mb = opt("--synth-mb", if smoke { 1.0 } else { 200.0 });
    if synth_mb > 0.0 {
        synthetic(synth_mb, smoke);
    }

    // Memory first, so that nothing else has raised the high-water mark.
    if mem_mb > 0.0 {
        let mut unit = pocket.clone();
        if unit.last() != Some(&b'\n') {
            unit.push(b'\n');
        }
        let total = (mem_mb * 1024.0 * 1024.0) as u64;
        let before = peak_rss_kib().unwrap_or(0);
        let rss_before = current_rss_kib().unwrap_or(0);
        let cfg = Config {
            // The pocket file ends with M2; keep going through every copy.
            stop_at_program_end: false,
            ..Config::default()
        };
        let reader = BufReader::with_capacity(
            64 * 1024,
            Repeat {
                unit: &unit,
                pos: 0,
                left: total,
            },
        );
        let start = Instant::now();
        let mut it = linearise(Interpreter::new(reader, cfg), 0.002);
        let mut motions = 0u64;
        for m in it.by_ref() {
            m.unwrap();
            motions += 1;
        }
        let secs = start.elapsed().as_secs_f64();
        let lines = it.inner().lines_read();
        let after = peak_rss_kib().unwrap_or(0);
        println!("## Streaming a large synthetic program (cncjs-tball-pocket.gcode repeated)");
        println!();
        println!(
            "{:.0} MiB, {} lines, {} motions, interpret + linearise in {:.2} s: {:.2} M lines/s, {:.1} MB/s",
            total as f64 / 1048576.0,
            lines,
            motions,
            secs,
            lines as f64 / secs / 1e6,
            total as f64 / secs / 1e6
        );
        println!(
            "peak RSS (VmHWM): {:.1} MiB before, {:.1} MiB after (RSS before {:.1} MiB; includes the 0.9 MB pocket file held twice by the bench)",
            before as f64 / 1024.0,
            after as f64 / 1024.0,
            rss_before as f64 / 1024.0
        );
        println!();
    }

    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.is_file())
        .collect();
    files.sort();
    // Tiny files measure call overhead, not throughput; keep them out of the table.
    files.retain(|p| {
        std::fs::metadata(p)
            .map(|m| m.len() > 8 * 1024)
            .unwrap_or(false)
    });

    let python = args
        .iter()
        .position(|a| a == "--python")
        .and_then(|i| args.get(i + 1))
        .cloned();
    println!(
        "## Throughput per file (best of 3 rounds of {:.1} s, one core)",
        budget.as_secs_f64()
    );
    println!();
    let mut head = String::from("| file | lines | MB | fresa interpret | fresa interpret+linearise (motions out) | fresa analyse | `gcode` 0.7 parse-only | lin / `gcode` |");
    let mut rule = String::from("|---|---:|---:|---:|---:|---:|---:|---:|");
    if python.is_some() {
        head.push_str(" pygcode 0.2 parse-only | lin / pygcode |");
        rule.push_str("---:|---:|");
    }
    println!("{head}");
    println!("{rule}");
    let (mut tot_bytes, mut tot_lines) = (0u64, 0u64);
    let (mut t_int, mut t_lin, mut t_an, mut t_oth, mut t_py) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for p in &files {
        let src = std::fs::read(p).unwrap();
        let text = std::str::from_utf8(&src).unwrap();
        let lines = text.lines().count() as u64;
        let mb = src.len() as f64 / 1e6;
        let ti = measure(budget, || fresa_interpret(&src)).as_secs_f64();
        let tl = measure(budget, || fresa_linearise(&src)).as_secs_f64();
        let ta = measure(budget, || fresa_analyse(&src)).as_secs_f64();
        let to = measure(budget, || other::parse(text)).as_secs_f64();
        let fmt = |t: f64| {
            format!(
                "{:.2} M lines/s, {:.0} MB/s",
                lines as f64 / t / 1e6,
                mb / t
            )
        };
        let out = fresa_linearise(&src);
        let mut row = format!(
            "| {} | {} | {:.2} | {} | {} ({} = {:.1} M/s) | {} | {} | {:.1}x |",
            p.file_name().unwrap().to_string_lossy(),
            lines,
            mb,
            fmt(ti),
            fmt(tl),
            out,
            out as f64 / tl / 1e6,
            fmt(ta),
            fmt(to),
            to / tl
        );
        if let Some(py) = &python {
            let tp = pygcode_seconds(py, p);
            row.push_str(&format!(
                " {:.3} M lines/s, {:.2} MB/s | {:.0}x |",
                lines as f64 / tp / 1e6,
                mb / tp,
                tp / tl
            ));
            t_py += tp;
        }
        println!("{row}");
        tot_bytes += src.len() as u64;
        tot_lines += lines;
        t_int += ti;
        t_lin += tl;
        t_an += ta;
        t_oth += to;
    }
    let mb = tot_bytes as f64 / 1e6;
    let fmt = |t: f64| {
        format!(
            "{:.2} M lines/s, {:.0} MB/s",
            tot_lines as f64 / t / 1e6,
            mb / t
        )
    };
    let mut row = format!(
        "| **all of the above** | {} | {:.2} | {} | {} | {} | {} | {:.1}x |",
        tot_lines,
        mb,
        fmt(t_int),
        fmt(t_lin),
        fmt(t_an),
        fmt(t_oth),
        t_oth / t_lin
    );
    if python.is_some() {
        row.push_str(&format!(
            " {:.3} M lines/s, {:.2} MB/s | {:.0}x |",
            tot_lines as f64 / t_py / 1e6,
            mb / t_py,
            t_py / t_lin
        ));
    }
    println!("{row}");
    parametric(budget, smoke);
}

/// Parametric programs (O-word loops, expressions) from LinuxCNC's samples:
/// lines executed per second (a loop body counts every pass), side by side
/// with LinuxCNC's own `rs274 -g` on the same file (a separate process, so
/// its time includes start-up; best of 3 wall-clock runs).
fn parametric(budget: Duration, smoke: bool) {
    let dir = std::path::Path::new("/usr/share/linuxcnc/ncfiles");
    // daisy.ngc turns the A axis, systems.ngc draws with G5.1 splines.
    let files = ["3D_Chips.ngc", "flowsnake.ngc", "daisy.ngc", "systems.ngc"];
    if !dir.is_dir() {
        println!("\n(parametric programs skipped: /usr/share/linuxcnc/ncfiles missing; apt-get install linuxcnc-uspace)");
        return;
    }
    println!();
    println!(
        "## Parametric programs (best of 3 rounds of {:.1} s, one core)",
        budget.as_secs_f64()
    );
    println!();
    println!("| file | source lines | lines executed | motions | fresa interpret | rs274 -g (process, best of 3) | ratio |");
    println!("|---|---:|---:|---:|---:|---:|---:|");
    for name in files {
        let path = dir.join(name);
        let Ok(src) = std::fs::read(&path) else {
            continue;
        };
        let run = || {
            let mut it = Interpreter::new(&src[..], Config::default());
            let mut n = 0u64;
            for m in it.by_ref() {
                black_box(m.unwrap());
                n += 1;
            }
            (it.lines_executed(), n)
        };
        if let Some(e) = Interpreter::new(&src[..], Config::default()).find_map(Result::err) {
            println!("| {name} | not interpreted: {e} | | | | | |");
            continue;
        }
        let (executed, motions) = run();
        let t = measure(budget, || run().0).as_secs_f64();
        let rs = if smoke { None } else { rs274_seconds(&path) };
        let lines = src.split(|&b| b == b'\n').count();
        let rs_col = rs.map_or("n/a".to_string(), |r| {
            format!(
                "{:.1} ms = {:.3} M lines/s",
                r * 1e3,
                executed as f64 / r / 1e6
            )
        });
        let ratio = rs.map_or("".to_string(), |r| format!("{:.0}x", r / t));
        println!(
            "| {name} | {lines} | {executed} | {motions} | {:.2} ms = {:.2} M lines/s | {rs_col} | {ratio} |",
            t * 1e3,
            executed as f64 / t / 1e6
        );
    }
}

/// Best of 3 wall-clock runs of `rs274 -g FILE` (output discarded).
fn rs274_seconds(path: &std::path::Path) -> Option<f64> {
    let mut best = f64::MAX;
    for _ in 0..3 {
        let start = Instant::now();
        let ok = std::process::Command::new("rs274")
            .arg("-g")
            .arg(path)
            .stdin(std::process::Stdio::null())
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .status()
            .ok()?
            .success();
        if !ok {
            return None;
        }
        best = best.min(start.elapsed().as_secs_f64());
    }
    Some(best)
}

/// Best-of-3 parse time of pygcode on `file`, via benches/pygcode_parse.py.
fn pygcode_seconds(python: &str, file: &std::path::Path) -> f64 {
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/benches/pygcode_parse.py");
    let out = std::process::Command::new(python)
        .arg(script)
        .arg(file)
        .output()
        .expect("run python");
    assert!(
        out.status.success(),
        "pygcode bench failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout);
    text.split_whitespace()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .expect("pygcode bench output")
}

/// The upload's analysis (`analyse`, default options) of the generated programs of
/// `benches/support/synth.rs`: a CAM-style one of `mb` MB and a parametric one of a quarter
/// of that, held in memory; best of 3 runs (1 in a smoke run).
fn synthetic(mb: f64, smoke: bool) {
    println!(
        "## Generated programs, analysed as an upload is (`analyse`, best of {})",
        if smoke { 1 } else { 3 }
    );
    println!();
    println!("| program | MB | lines | motion lines | analyse | MB/s | M lines/s |");
    println!("|---|---:|---:|---:|---:|---:|---:|");
    for (name, size) in [
        ("CAM (G0/G1/G2/G3, comments)", mb),
        ("parametric (expressions, parameters, O-words)", mb / 4.0),
    ] {
        let mut src = Vec::new();
        let bytes = (size * 1e6) as u64;
        if name.starts_with("CAM") {
            synth::cam(bytes, &mut src).unwrap();
        } else {
            synth::parametric(bytes, &mut src).unwrap();
        }
        let lines = memchr_count(&src);
        let mut best = f64::MAX;
        let mut motion_lines = 0;
        for _ in 0..if smoke { 1 } else { 3 } {
            let start = Instant::now();
            let a = analyse(&src[..], &AnalysisOptions::default()).unwrap();
            best = best.min(start.elapsed().as_secs_f64());
            motion_lines = a.motion_lines;
        }
        println!(
            "| {name} | {:.1} | {lines} | {motion_lines} | {:.3} s | {:.0} | {:.2} |",
            src.len() as f64 / 1e6,
            best,
            src.len() as f64 / best / 1e6,
            lines as f64 / best / 1e6
        );
    }
    println!();
}

fn memchr_count(b: &[u8]) -> usize {
    b.iter().filter(|&&c| c == b'\n').count()
}

//! `mpg-pendant-sim`: plays an ESP32 MPG pendant for demos and tests. It is the TCP server (as
//! the real pendant is), polls `N0451` like the firmware's main loop, and runs commands from a
//! script file or stdin, one per line:
//!
//! ```text
//! jog AXIS COUNT STEP        e.g. `jog X 25 0.01`, `jog Z -100 0.0001` (split into <=9999 detents)
//! flood AXIS FRAMES COUNT STEP
//!                            FRAMES wheel frames of COUNT detents each, back to back as fast as
//!                            the link takes them (a misbehaving pendant), e.g.
//!                            `flood X 300000 1 0.01`
//! key WORD                   Zero ZeroX ZeroY ZeroZ ZeroA Reset Stop Rewind Start Pause HOME M1..M4
//! upload PATH [gap=50-70] [end=none|lf] [lines+=N] [chars+=N] [blank=send|drop]
//!        [stop-after=N] [wrap8]
//!                            START, each line (one send each, `gap` ms apart), FIN; `end=lf` ends
//!                            lines with \n (lets gap=0 work); `lines+=`/`chars+=` falsify counts.
//!                            The published firmware's quirks: `blank=drop` counts blank lines
//!                            but sends nothing for them (with `end=none` a blank line is a
//!                            zero-length send, which is nothing on the wire anyway);
//!                            `stop-after=N` presses STOP after N lines: no FIN, and the main
//!                            loop's N0451 polls start again; `wrap8` counts lines in a u8, so a
//!                            file over 255 lines is re-sent from the start forever, without FIN
//!                            (until `stop-after` or the link ends).
//! set-cero PLATE_Z [STEPS]   the firmware's touch-plate routine ("Set cero"): Z down 0.01 a
//!                            frame (`N01S0.0001Z-0100`) until the plate closes, then `ZeroZ`.
//!                            The plate closes when the Z the LCD shows (N51) is at or below
//!                            PLATE_Z; at most STEPS frames (default 10000, 100 mm), then an
//!                            error and no ZeroZ
//! poll HZ                    N0451 polls per second (0 stops); `poll-job HZ` for N0452
//! raw TEXT                   send TEXT as is
//! wait-connected             block until a server is connected
//! drop                       close the server's connection
//! sleep MS
//! quit
//! ```
//! With `--exit-on-eof` the simulator exits when its input ends; otherwise it keeps playing the
//! pendant until killed. Everything received is printed as `recv FRAME`; each command ends with `ok ...` or `error ...`.

use clap::Parser;
use fresa_mpg_pendant::codec::{parse_key_word, Decoded, Decoder, Frame, Info};
use fresa_plugin_api::contract::{Axis, AxisValues};
use std::io::{BufRead, Write};
use std::net::{Shutdown, TcpListener, TcpStream};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;

#[derive(Parser)]
#[command(about = "A simulated MPG pendant (TCP server speaking the 53-character protocol)")]
struct Args {
    /// Address to listen on (the real pendant uses port 8001).
    #[arg(long, default_value = "127.0.0.1:8001")]
    listen: String,
    /// N0451 polls per second (the firmware polls every main-loop pass).
    #[arg(long, default_value_t = 10.0)]
    poll_hz: f64,
    /// Run commands from this file instead of stdin.
    #[arg(long)]
    script: Option<std::path::PathBuf>,
    /// Print an N51 answer only when it differs from the previous one (they arrive at the poll rate).
    #[arg(long)]
    quiet_polls: bool,
    /// Exit when the command input ends (for a parent that holds our stdin, e.g. `fresa serve --demo`).
    #[arg(long)]
    exit_on_eof: bool,
}

struct Sim {
    client: Mutex<Option<TcpStream>>,
    connected: Condvar,
    /// Generation of the current client, so a reader of an old one does not clear a new one.
    generation: AtomicU64,
    poll_mhz: AtomicU64,
    poll_job_mhz: AtomicU64,
    /// In the firmware's upload routine: no polls. A lock, not a flag, so no poll is sent
    /// between START and the end of the upload (the firmware is one loop).
    uploading: Mutex<bool>,
    quiet_polls: bool,
    out: Mutex<()>,
    /// The newest N51 answer (what the LCD shows) and how many have arrived.
    lcd: Mutex<(u64, Option<AxisValues>)>,
    lcd_changed: Condvar,
}

impl Sim {
    fn say(&self, line: &str) {
        let _g = self.out.lock();
        let mut o = std::io::stdout().lock();
        let _ = writeln!(o, "{line}");
        let _ = o.flush();
    }

    fn send(&self, bytes: &[u8]) -> Result<(), String> {
        let mut c = self.client.lock().map_err(|_| "poisoned")?;
        match c.as_mut() {
            Some(s) => s.write_all(bytes).map_err(|e| format!("send failed: {e}")),
            None => Err("no server is connected".into()),
        }
    }
}

fn main() {
    let args = Args::parse();
    let listener = match TcpListener::bind(&args.listen) {
        Ok(l) => l,
        Err(e) => {
            eprintln!("mpg-pendant-sim: cannot listen on {}: {e}", args.listen);
            std::process::exit(2);
        }
    };
    let sim = Arc::new(Sim {
        client: Mutex::new(None),
        connected: Condvar::new(),
        generation: AtomicU64::new(0),
        poll_mhz: AtomicU64::new((args.poll_hz.max(0.0) * 1000.0) as u64),
        poll_job_mhz: AtomicU64::new(0),
        uploading: Mutex::new(false),
        quiet_polls: args.quiet_polls,
        out: Mutex::new(()),
        lcd: Mutex::new((0, None)),
        lcd_changed: Condvar::new(),
    });
    match listener.local_addr() {
        Ok(a) => sim.say(&format!("listening on {a}")),
        Err(e) => {
            eprintln!("mpg-pendant-sim: {e}");
            std::process::exit(2);
        }
    }
    {
        let sim = sim.clone();
        std::thread::spawn(move || accept_loop(&sim, listener));
    }
    for (mhz, info) in [(0, Info::Positions), (1, Info::Job)] {
        let sim = sim.clone();
        std::thread::spawn(move || poll_loop(&sim, mhz, info));
    }
    let input: Box<dyn BufRead> = match &args.script {
        Some(p) => match std::fs::File::open(p) {
            Ok(f) => Box::new(std::io::BufReader::new(f)),
            Err(e) => {
                eprintln!("mpg-pendant-sim: cannot read script {}: {e}", p.display());
                std::process::exit(2);
            }
        },
        None => Box::new(std::io::stdin().lock()),
    };
    for line in input.lines() {
        let Ok(line) = line else { break };
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        if line == "quit" {
            sim.say("ok quit");
            return;
        }
        match command(&sim, line) {
            Ok(()) => sim.say(&format!("ok {line}")),
            Err(e) => sim.say(&format!("error {line}: {e}")),
        }
    }
    if args.exit_on_eof {
        return;
    }
    // Input ended: keep playing the pendant (polls, answers) until killed.
    loop {
        std::thread::park();
    }
}

fn accept_loop(sim: &Arc<Sim>, listener: TcpListener) {
    for conn in listener.incoming() {
        let Ok(stream) = conn else { continue };
        let _ = stream.set_nodelay(true);
        let peer = stream
            .peer_addr()
            .map(|a| a.to_string())
            .unwrap_or_default();
        let Ok(reader) = stream.try_clone() else {
            continue;
        };
        let gen = sim.generation.fetch_add(1, Ordering::SeqCst) + 1;
        if let Ok(mut c) = sim.client.lock() {
            // One client at a time, like the firmware: a new server replaces the old one.
            if let Some(old) = c.replace(stream) {
                let _ = old.shutdown(Shutdown::Both);
            }
            sim.connected.notify_all();
        }
        sim.say(&format!("connected {peer}"));
        let sim = sim.clone();
        std::thread::spawn(move || read_loop(&sim, reader, gen));
    }
}

fn read_loop(sim: &Sim, mut stream: TcpStream, gen: u64) {
    use std::io::Read;
    let mut decoder = Decoder::new();
    let mut buf = [0u8; 4096];
    let mut last_positions = None;
    let reason = loop {
        match stream.read(&mut buf) {
            Ok(0) => break "closed by the server".to_string(),
            Ok(n) => {
                decoder.push(&buf[..n]);
                while let Some(d) = decoder.pop() {
                    match d {
                        Decoded::Frame(f) => {
                            if let (Frame::Positions(p), Ok(mut lcd)) = (&f, sim.lcd.lock()) {
                                *lcd = (lcd.0 + 1, Some(*p));
                                sim.lcd_changed.notify_all();
                            }
                            if sim.quiet_polls && matches!(f, Frame::Positions(_)) {
                                if last_positions.as_ref() == Some(&f) {
                                    continue;
                                }
                                last_positions = Some(f.clone());
                            }
                            let text = String::from_utf8_lossy(&f.encode()).into_owned();
                            sim.say(&format!("recv {text}"));
                        }
                        other => sim.say(&format!("garbage {other:?}")),
                    }
                }
            }
            Err(e) => break e.to_string(),
        }
    };
    if let Ok(mut c) = sim.client.lock() {
        if sim.generation.load(Ordering::SeqCst) == gen {
            *c = None;
        }
    }
    sim.say(&format!("disconnected {reason}"));
}

fn poll_loop(sim: &Sim, which: u8, info: Info) {
    let frame = Frame::Request(info).encode();
    loop {
        let mhz = if which == 0 {
            sim.poll_mhz.load(Ordering::Relaxed)
        } else {
            sim.poll_job_mhz.load(Ordering::Relaxed)
        };
        if mhz == 0 {
            std::thread::sleep(Duration::from_millis(20));
            continue;
        }
        // The firmware's upload routine does not poll.
        if let Ok(uploading) = sim.uploading.lock() {
            if !*uploading {
                let _ = sim.send(&frame);
            }
        }
        std::thread::sleep(Duration::from_micros(1_000_000_000 / mhz));
    }
}

fn parse_axis(s: &str) -> Result<Axis, String> {
    match s.to_ascii_uppercase().as_str() {
        "X" => Ok(Axis::X),
        "Y" => Ok(Axis::Y),
        "Z" => Ok(Axis::Z),
        "A" => Ok(Axis::A),
        _ => Err(format!("axis {s:?} is not X, Y, Z or A")),
    }
}

fn command(sim: &Sim, line: &str) -> Result<(), String> {
    let words: Vec<&str> = line.split_whitespace().collect();
    match words.as_slice() {
        ["jog", axis, count, step] => {
            let axis = parse_axis(axis)?;
            let count: i64 = count.parse().map_err(|_| format!("count {count:?} is not an integer"))?;
            let step: f64 = step.parse().map_err(|_| format!("step {step:?} is not a number"))?;
            let mut left = count;
            while left != 0 {
                let n = left.clamp(-9999, 9999);
                sim.send(&Frame::Jog { step, axis, count: n as i32 }.encode())?;
                left -= n;
            }
            Ok(())
        }
        ["flood", axis, frames, count, step] => {
            let axis = parse_axis(axis)?;
            let frames: u64 = frames.parse().map_err(|_| format!("frames {frames:?} is not a count"))?;
            let count: i32 = count.parse().map_err(|_| format!("count {count:?} is not an integer"))?;
            let step: f64 = step.parse().map_err(|_| format!("step {step:?} is not a number"))?;
            let frame = Frame::Jog { step, axis, count }.encode();
            // 1000 frames a write: fast, without holding the whole flood in memory.
            let chunk: Vec<u8> = frame.iter().copied().cycle().take(frame.len() * 1000).collect();
            let mut left = frames;
            while left > 0 {
                let n = left.min(1000);
                sim.send(&chunk[..frame.len() * n as usize])?;
                left -= n;
            }
            Ok(())
        }
        ["key", word] => {
            let key = parse_key_word(word).ok_or_else(|| format!("unknown key {word:?}"))?;
            sim.send(&Frame::Key(key).encode())
        }
        ["upload", path, opts @ ..] => upload(sim, path, opts),
        ["set-cero", plate_z, rest @ ..] => {
            let plate_z: f64 = plate_z.parse().map_err(|_| format!("plate Z {plate_z:?} is not a number"))?;
            let steps: u32 = match rest {
                [] => 10_000,
                [n] => n.parse().map_err(|_| format!("steps {n:?} is not a count"))?,
                _ => return Err("usage: set-cero PLATE_Z [STEPS]".into()),
            };
            set_cero(sim, plate_z, steps)
        }
        ["poll", hz] | ["poll-job", hz] => {
            let hz: f64 = hz.parse().map_err(|_| format!("rate {hz:?} is not a number"))?;
            let target = if words[0] == "poll" { &sim.poll_mhz } else { &sim.poll_job_mhz };
            target.store((hz.max(0.0) * 1000.0) as u64, Ordering::Relaxed);
            Ok(())
        }
        ["raw", ..] => sim.send(line["raw".len()..].trim_start().as_bytes()),
        ["wait-connected"] => {
            let mut c = sim.client.lock().map_err(|_| "poisoned")?;
            while c.is_none() {
                c = sim.connected.wait(c).map_err(|_| "poisoned")?;
            }
            Ok(())
        }
        ["drop"] => {
            let c = sim.client.lock().map_err(|_| "poisoned")?;
            match c.as_ref() {
                Some(s) => s.shutdown(Shutdown::Both).map_err(|e| e.to_string()),
                None => Err("no server is connected".into()),
            }
        }
        ["sleep", ms] => {
            let ms: u64 = ms.parse().map_err(|_| format!("{ms:?} is not a number of ms"))?;
            std::thread::sleep(Duration::from_millis(ms));
            Ok(())
        }
        _ => Err("unknown command (jog, flood, key, upload, set-cero, poll, poll-job, raw, wait-connected, drop, sleep, quit)".into()),
    }
}

/// The LCD's Z from an N51 answer newer than `after` (asking with N0451 every 20 ms, as the
/// firmware's main loop does), within `timeout`.
fn lcd_z_after(sim: &Sim, after: u64, timeout: Duration) -> Result<(u64, f64), String> {
    let ask = Frame::Request(Info::Positions).encode();
    let deadline = std::time::Instant::now() + timeout;
    loop {
        sim.send(&ask)?;
        let lcd = sim.lcd.lock().map_err(|_| "poisoned")?;
        let (lcd, _) = sim
            .lcd_changed
            .wait_timeout_while(lcd, Duration::from_millis(20), |l| l.0 <= after)
            .map_err(|_| "poisoned")?;
        if let (seq, Some(p)) = *lcd {
            if seq > after {
                return Ok((seq, p.z));
            }
        }
        drop(lcd);
        if std::time::Instant::now() >= deadline {
            return Err(format!(
                "no position (N51) from the server within {timeout:?}"
            ));
        }
    }
}

/// The firmware's "Set cero": one Z-down step, then its plate input is read (here: the LCD's Z
/// against `plate_z`), until the plate closes; then `ZeroZ`.
fn set_cero(sim: &Sim, plate_z: f64, steps: u32) -> Result<(), String> {
    const STEP_MM: f64 = 0.01;
    let wait = Duration::from_secs(5);
    let (mut seq, mut z) = lcd_z_after(sim, 0, wait)?;
    for _ in 0..steps {
        if z <= plate_z + 1e-9 {
            return sim.send(&Frame::Key(fresa_plugin_api::contract::PendantKey::ZeroZ).encode());
        }
        sim.send(
            &Frame::Jog {
                step: 0.0001,
                axis: Axis::Z,
                count: -100,
            }
            .encode(),
        )?;
        // The next position that shows the step done (the plate is sensed where the tool is).
        let target = z - STEP_MM / 2.0;
        let deadline = std::time::Instant::now() + wait;
        loop {
            (seq, z) = lcd_z_after(sim, seq, wait)?;
            if z <= target {
                break;
            }
            if std::time::Instant::now() >= deadline {
                return Err(format!("set-cero: Z stayed at {z} after a step down (is the pendant bound to an idle machine?)"));
            }
        }
    }
    Err(format!(
        "set-cero: the plate never closed in {steps} steps (Z at {z}, plate at {plate_z})"
    ))
}

struct UploadOpts {
    gap_min: u64,
    gap_max: u64,
    lf: bool,
    lines_delta: i64,
    chars_delta: i64,
    drop_blank: bool,
    stop_after: Option<u64>,
    wrap8: bool,
}

fn upload_opts(opts: &[&str]) -> Result<UploadOpts, String> {
    let mut o = UploadOpts {
        gap_min: 50,
        gap_max: 70,
        lf: false,
        lines_delta: 0,
        chars_delta: 0,
        drop_blank: false,
        stop_after: None,
        wrap8: false,
    };
    for opt in opts {
        let bad = || {
            format!(
                "option {opt:?} (gap=MIN-MAX, end=none|lf, lines+=N, chars+=N, blank=send|drop, \
                 stop-after=N, wrap8)"
            )
        };
        if let Some(v) = opt.strip_prefix("gap=") {
            let (a, b) = v.split_once('-').unwrap_or((v, v));
            o.gap_min = a.parse().map_err(|_| bad())?;
            o.gap_max = b.parse().map_err(|_| bad())?;
        } else if let Some(v) = opt.strip_prefix("end=") {
            o.lf = match v {
                "lf" => true,
                "none" => false,
                _ => return Err(bad()),
            };
        } else if let Some(v) = opt.strip_prefix("lines+=") {
            o.lines_delta = v.parse().map_err(|_| bad())?;
        } else if let Some(v) = opt.strip_prefix("chars+=") {
            o.chars_delta = v.parse().map_err(|_| bad())?;
        } else if let Some(v) = opt.strip_prefix("blank=") {
            o.drop_blank = match v {
                "drop" => true,
                "send" => false,
                _ => return Err(bad()),
            };
        } else if let Some(v) = opt.strip_prefix("stop-after=") {
            o.stop_after = Some(v.parse().map_err(|_| bad())?);
        } else if *opt == "wrap8" {
            o.wrap8 = true;
        } else {
            return Err(bad());
        }
    }
    Ok(o)
}

fn upload(sim: &Sim, path: &str, opts: &[&str]) -> Result<(), String> {
    let o = upload_opts(opts)?;
    let text = std::fs::read_to_string(path).map_err(|e| format!("cannot read {path}: {e}"))?;
    let lines: Vec<&str> = text.lines().collect();
    let chars: u64 = lines.iter().map(|l| l.len() as u64).sum();
    let mut uploading = sim.uploading.lock().map_err(|_| "poisoned")?;
    *uploading = true;
    drop(uploading);
    let result = (|| {
        let declared = (lines.len() as i64 + o.lines_delta).max(0) as u32;
        sim.send(&Frame::UploadStart { lines: declared }.encode())?;
        let mut seed = 0x9e37_79b9_7f4a_7c15u64;
        let mut sent = 0u64;
        // `Cargar_gcode`: `for (uint8_t j = 1; j < cant_lines + 1; j++)` with `wrap8`.
        let mut j: u64 = 1;
        let mut j8: u8 = 1;
        loop {
            let (more, index) = if o.wrap8 {
                (
                    u64::from(j8) < lines.len() as u64 + 1,
                    usize::from(j8.wrapping_sub(1)),
                )
            } else {
                (j < lines.len() as u64 + 1, (j - 1) as usize)
            };
            if !more || lines.is_empty() {
                break;
            }
            if o.stop_after.is_some_and(|n| sent >= n) {
                sim.say(&format!("upload-stopped lines={sent}"));
                return Ok(());
            }
            let l = lines.get(index).copied().unwrap_or("");
            if o.gap_max > 0 {
                // Spread the gaps like the firmware's loop timing (50-70 ms).
                seed ^= seed << 13;
                seed ^= seed >> 7;
                seed ^= seed << 17;
                let gap = o.gap_min + seed % (o.gap_max.saturating_sub(o.gap_min) + 1);
                std::thread::sleep(Duration::from_millis(gap));
            }
            if !(l.is_empty() && o.drop_blank) {
                let mut b = l.as_bytes().to_vec();
                if o.lf {
                    b.push(b'\n');
                }
                sim.send(&b)?;
            }
            sent += 1;
            j += 1;
            j8 = j8.wrapping_add(1);
        }
        if o.stop_after.is_some_and(|n| sent >= n) {
            sim.say(&format!("upload-stopped lines={sent}"));
            return Ok(());
        }
        if o.gap_max > 0 {
            std::thread::sleep(Duration::from_millis(o.gap_min));
        }
        let declared_chars = (chars as i64 + o.chars_delta).max(0) as u64;
        sim.send(
            &Frame::UploadEnd {
                chars: declared_chars,
            }
            .encode(),
        )?;
        sim.say(&format!("upload-sent lines={} chars={chars}", lines.len()));
        Ok(())
    })();
    if let Ok(mut u) = sim.uploading.lock() {
        *u = false;
    }
    result
}

//! The web console at `/`: its files (types, caching, gzip, the guard), the toolpath endpoint,
//! and what an operator does in it, driven in a real headless Chromium against a real
//! `fresa serve --demo`. Screenshots of every page go to `target/console-screenshots/`.

#![allow(clippy::unwrap_used, clippy::expect_used)]

#[path = "../support/browser.rs"]
mod browser;

use browser::Browser;
use fresa_tests::serde_json::{json, Value};
use fresa_tests::{corpus, wait_for, Opts, Server};
use std::fmt::Write as _;
use std::time::Duration;

const T: Duration = Duration::from_secs(60);

fn raw_get(s: &Server, path: &str, headers: &[(&str, &str)]) -> reqwest::blocking::Response {
    // No automatic decompression: the test sees what travels.
    let mut rb = reqwest::blocking::Client::new().get(s.url(path));
    for (k, v) in headers {
        rb = rb.header(*k, *v);
    }
    rb.send().unwrap()
}

#[test]
fn console_files_are_typed_cached_compressed_and_guarded() {
    let s = Server::start_demo();
    let index = raw_get(&s, "/", &[]);
    assert_eq!(index.status(), 200);
    let h = index.headers().clone();
    assert_eq!(h["content-type"], "text/html; charset=utf-8");
    assert_eq!(h["cache-control"], "no-cache");
    assert!(h["content-security-policy"]
        .to_str()
        .unwrap()
        .contains("default-src 'self'"));
    let etag = h["etag"].to_str().unwrap().to_string();
    let body = index.text().unwrap();
    assert!(body.contains("/assets/app.js"), "{body}");

    // Unchanged: 304 without a body.
    let again = raw_get(&s, "/", &[("if-none-match", &etag)]);
    assert_eq!(again.status(), 304);
    assert!(again.bytes().unwrap().is_empty());

    // Every file with its type, gzipped; the whole first visit stays under 300 KB.
    let mut transferred = 0usize;
    for a in fresa_console::ASSETS {
        let path = if a.name == "index.html" {
            "/".to_string()
        } else {
            format!("/assets/{}", a.name)
        };
        let r = raw_get(&s, &path, &[("accept-encoding", "gzip")]);
        assert_eq!(r.status(), 200, "{path}");
        assert_eq!(r.headers()["content-type"], a.content_type, "{path}");
        if a.bytes.len() > 1024 {
            assert_eq!(r.headers()["content-encoding"], "gzip", "{path}");
        }
        let n = r.bytes().unwrap().len();
        assert!(
            a.bytes.len() < 1024 || n < a.bytes.len(),
            "{path}: gzip did not shrink it"
        );
        transferred += n;
    }
    assert!(
        transferred < 300 * 1024,
        "a first visit transfers {transferred} bytes"
    );

    // Unknown files are JSON 404s; the guard applies to the console like the API.
    let missing = s.get("/assets/nope.js");
    assert_eq!(missing.status, 404);
    assert_eq!(missing.body["code"], "not_found");
    let rebound = raw_get(&s, "/", &[("host", "evil.example:7878")]);
    assert_eq!(rebound.status(), 403);
}

/// A toolpath as the README documents it.
struct Decoded {
    n: usize,
    moves: u32,
    decimation: f32,
    bounds: [f32; 6],
    pts: Vec<[f32; 3]>,
    lines: Vec<u32>,
    kinds: Vec<u8>,
}

fn decode(b: &[u8]) -> Decoded {
    assert_eq!(&b[..4], b"FTP1");
    let u = |o: usize| u32::from_le_bytes(b[o..o + 4].try_into().unwrap());
    let f = |o: usize| f32::from_le_bytes(b[o..o + 4].try_into().unwrap());
    let n = u(4) as usize;
    assert_eq!(b.len(), 48 + 17 * n, "size for {n} vertices");
    let bounds = [f(16), f(20), f(24), f(28), f(32), f(36)];
    let pts = (0..n)
        .map(|i| [f(48 + 12 * i), f(52 + 12 * i), f(56 + 12 * i)])
        .collect();
    let lines = (0..n).map(|i| u(48 + 12 * n + 4 * i)).collect();
    Decoded {
        n,
        moves: u(8),
        decimation: f(12),
        bounds,
        pts,
        lines,
        kinds: b[48 + 16 * n..].to_vec(),
    }
}

#[test]
fn toolpath_is_the_programs_path_bounded_in_size() {
    let s = Server::start_demo();
    let program = std::fs::read(corpus("linuxcnc-tort.ngc")).unwrap();
    let job = s.upload(1, "tort", program.clone());
    let id = job["id"].as_i64().unwrap();
    let get = |q: &str| {
        let r = raw_get(&s, &format!("/api/v1/jobs/{id}/toolpath{q}"), &[]);
        assert_eq!(r.status(), 200);
        assert_eq!(r.headers()["content-type"], "application/octet-stream");
        r.bytes().unwrap().to_vec()
    };
    let full = get("");
    let Decoded {
        n,
        moves,
        bounds,
        decimation: _,
        pts,
        lines,
        kinds,
    } = decode(&full);
    // Against the gcode crate itself: every move, ending where the program ends.
    let reference: Vec<fresa_gcode::Motion> = fresa_gcode::Interpreter::new(
        program.as_slice(),
        fresa_gcode::Config {
            arc_tolerance_mm: 0.01,
            ..Default::default()
        },
    )
    .linearised()
    .collect::<Result<_, _>>()
    .unwrap();
    let moves_ref: Vec<_> = reference.iter().filter_map(|m| m.end_point()).collect();
    assert_eq!(moves as usize, moves_ref.len());
    assert_eq!(n, moves_ref.len() + 1, "small enough to keep every vertex");
    let last = moves_ref.last().unwrap();
    let got = pts.last().unwrap();
    for i in 0..3 {
        assert!(
            (got[i] as f64 - last[i]).abs() < 1e-3,
            "{got:?} vs {last:?}"
        );
    }
    assert_eq!(kinds[0], 0);
    assert!(kinds[1..].iter().all(|&k| k == 1 || k == 2));
    assert!(kinds.contains(&1) && kinds.contains(&2));
    assert!(lines.windows(2).all(|w| w[0] <= w[1]));
    // Bounds cover the analysis' cutting bounds (less what chords of 0.01 mm cut off arcs).
    let cut = &job["analysis"]["cutting_bounds"];
    for i in 0..3 {
        assert!(bounds[i] as f64 <= cut["min"][i].as_f64().unwrap() + 0.02);
        assert!(bounds[3 + i] as f64 >= cut["max"][i].as_f64().unwrap() - 0.02);
    }

    // Decimated to the budget asked for, keeping the ends.
    let small = get("?max_vertices=1000");
    let d = decode(&small);
    let (n2, moves2, pts2, lines2) = (d.n, d.moves, d.pts, d.lines);
    assert!(n2 <= 1000 && n2 > 100, "{n2}");
    assert_eq!(moves2, moves);
    assert_eq!(lines2.last(), lines.last());
    assert_eq!(pts2.last(), pts.last());

    let bad = s.get(&format!("/api/v1/jobs/{id}/toolpath?max_vertices=5"));
    assert_eq!(bad.status, 400);
    assert!(bad.text.contains("max_vertices"), "{}", bad.text);
    assert_eq!(s.get("/api/v1/jobs/999/toolpath").status, 404);
}

/// The DRO's text for `axis`, once it shows a number (it shows a dash until a status came).
fn dro(b: &Browser, axis: &str) -> String {
    b.wait(
        &format!("the DRO of {axis}"),
        T,
        &format!(
            "const e = document.querySelector('[data-dro=\"{axis}\"]'); \
             return e && /^-?[0-9]/.test(e.textContent) ? e.textContent : null;"
        ),
    )
    .as_str()
    .unwrap()
    .to_string()
}

#[test]
fn an_operator_drives_the_demo_in_a_browser() {
    let s = Server::start_demo();
    let mill = s.sim("mill-2", 0.05);
    let b = Browser::start();

    // Overview: the demo machine's card, live.
    b.goto(&s.base);
    b.wait(
        "the demo machine's card",
        T,
        "const c = document.querySelector('[data-machine=\"1\"]'); return c && c.textContent.includes('idle');",
    );
    b.wait(
        "the live stream",
        T,
        "return document.getElementById('conn').hidden;",
    );
    b.wait(
        "the demo pendant on its machine's card",
        T,
        "return document.querySelector('[data-machine=\"1\"] .pendants-line').textContent.includes('demo-pendant');",
    );
    b.screenshot("overview");

    // Machine page: jog X+ 1 mm; the DRO and GET /status agree.
    b.goto(&format!("{}/#/machines/1", s.base));
    assert_eq!(dro(&b, "x"), "0.000");
    b.select("#jog-step", "1");
    b.click("[data-jog=\"X+\"]");
    b.wait(
        "the DRO to show X 1.000",
        T,
        "return document.querySelector('[data-dro=\"x\"]').textContent === '1.000';",
    );
    let status = s.wait_status(1, T, "idle after the jog", |st| st["state"] == "idle");
    let x = status["work_position"]["x"].as_f64().unwrap();
    assert_eq!(format!("{x:.3}"), dro(&b, "x"));
    assert_eq!(format!("{x:.3}"), "1.000");
    // A jog beyond the machine's limit is not offered: steps stop at max_jog_mm.
    let steps = b.js(
        "return [...document.querySelectorAll('#jog-step option')].filter(o => o.value !== 'hold').map(o => +o.value);",
    );
    let max_jog = s.get("/api/v1/machines/1").body["max_jog_mm"]
        .as_f64()
        .unwrap();
    assert!(steps
        .as_array()
        .unwrap()
        .iter()
        .all(|v| v.as_f64().unwrap() <= max_jog));

    // Offsets are editable; part zero is recorded here and listed.
    b.type_into(
        "tr[data-offset=\"G55\"] input[aria-label=\"G55 x\"]",
        "12.5",
    );
    b.click("tr[data-offset=\"G55\"] td.row button:first-child");
    wait_for(T, "G55 to be stored", || {
        let o = s.get("/api/v1/machines/1/offsets").body;
        (o["offsets"]["G55"]["x"].as_f64() == Some(12.5)).then_some(())
    });
    b.type_into("input[aria-label=\"part zero note\"]", "vise jaw");
    b.click("#record-part-zero");
    wait_for(T, "the part zero to be recorded", || {
        let h = s.get("/api/v1/machines/1/part-zero").body;
        (h[0]["note"] == "vise jaw" && h[0]["x"].as_f64() == Some(1.0)).then_some(())
    });
    b.wait(
        "the part-zero history to list it",
        T,
        "return [...document.querySelectorAll('td')].some(td => td.textContent === 'vise jaw');",
    );

    // MDI: the server's 422 is shown with its column marked.
    b.type_into("#mdi", "G1 X(");
    b.click("form:has(#mdi) button[type=submit]");
    let marked = b.wait_text("#mdi-error mark.col", T);
    let message = b.wait_text("#mdi-error p", T);
    let col: usize = message
        .split("column ")
        .nth(1)
        .and_then(|r| r.split(|c: char| !c.is_ascii_digit()).next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no column in {message:?}"));
    assert_eq!(marked, "G1 X(".chars().nth(col - 1).unwrap().to_string());
    b.type_into("#mdi", "");
    b.screenshot("machine");
    // On a tablet in portrait the controls stay at least 44 px and STOP stays in view.
    b.resize(820, 1180);
    let small = b.js(
        "return [...document.querySelectorAll('button, select, input:not([type=file])')] \
           .filter(e => e.offsetParent !== null) \
           .filter(e => e.getBoundingClientRect().height < 44 || e.getBoundingClientRect().width < 44) \
           .map(e => e.outerHTML.slice(0, 80));",
    );
    assert_eq!(small, json!([]), "touch targets under 44 px");
    b.screenshot("machine-tablet");
    b.resize(1280, 1000);

    // Jobs: upload a corpus program through the file input to the fast sim machine.
    b.goto(&format!("{}/#/jobs", s.base));
    b.wait_text("#upload-file", T);
    b.select("#upload-machine", &mill.id.to_string());
    b.choose_file("#upload-file", &corpus("cncjs-circle-inch.gcode"));
    let analysis = b.wait_text("#analysis", T);
    assert!(analysis.contains("Cutting length"), "{analysis}");
    let job = b.wait_text("#open-job", T);
    let job_id: i64 = job
        .split_whitespace()
        .nth(2)
        .and_then(|n| n.parse().ok())
        .unwrap();
    assert_eq!(s.job(job_id)["name"], "cncjs-circle-inch");
    let progress = b.js("return document.getElementById('upload-progress').value;");
    assert_eq!(progress.as_f64(), Some(1.0), "upload progress bar");
    b.screenshot("jobs-uploaded");
    b.click("#upload-result [data-action=\"start\"]");
    b.goto(&format!("{}/#/jobs/{job_id}", s.base));
    b.wait(
        "the job to complete at 100 %",
        T,
        "const s = document.getElementById('job-state'), p = document.getElementById('job-percent'); \
         return s && p && s.textContent === 'completed' && p.textContent === '100.0 %';",
    );
    assert_eq!(s.job(job_id)["state"], "completed");
    b.wait(
        "the toolpath to be drawn",
        T,
        "const c = document.querySelector('canvas.toolpath'); return c && +c.dataset.vertices > 10;",
    );
    b.screenshot("job-toolpath");
    // The path is really drawn (not a blank canvas), in the top view and in 3D.
    let coloured = "const c = document.querySelector('canvas.toolpath'); \
        const t = document.createElement('canvas'); t.width = c.width; t.height = c.height; \
        const g = t.getContext('2d'); g.drawImage(c, 0, 0); \
        const d = g.getImageData(0, 0, t.width, t.height).data; let n = 0; \
        for (let i = 0; i < d.length; i += 4) if (d[i + 1] > d[i] + 60 && d[i + 1] > d[i + 2]) n++; \
        return n;";
    let green_top = b.wait("green (executed) pixels in the top view", T, coloured);
    b.click("[data-view=\"3d\"]");
    b.wait(
        "the 3D view",
        T,
        "return document.querySelector('[data-view=\"3d\"]').classList.contains('active');",
    );
    let green_3d = b.wait("green (executed) pixels in the 3D view", T, coloured);
    assert!(green_top.as_u64().unwrap() > 100 && green_3d.as_u64().unwrap() > 100);
    b.screenshot("job-toolpath-3d");

    // Drag and drop: a file dropped on the zone is uploaded like a chosen one.
    b.goto(&format!("{}/#/jobs", s.base));
    b.wait_text("#drop-zone", T);
    b.js("const dt = new DataTransfer(); \
          dt.items.add(new File(['G21 G90\\nG1 X1 F100\\nM30\\n'], 'dropped.nc')); \
          document.getElementById('drop-zone').dispatchEvent(new DragEvent('drop', {dataTransfer: dt, bubbles: true}));");
    let stored = b.wait(
        "the dropped file to be stored",
        T,
        "const h = document.querySelector('#upload-result h3'); return h && h.textContent.includes('dropped.nc') ? h.textContent : null;",
    );
    assert!(
        stored.as_str().unwrap().starts_with("Stored as job"),
        "{stored}"
    );
    let jobs = s.get("/api/v1/jobs").body;
    assert!(
        jobs.as_array()
            .unwrap()
            .iter()
            .any(|j| j["name"] == "dropped" && j["line_count"] == 3),
        "{jobs}"
    );

    // A broken corpus program: refused, its line and column shown in the program.
    b.goto(&format!("{}/#/jobs", s.base));
    b.wait_text("#upload-file", T);
    b.choose_file(
        "#upload-file",
        &corpus("cncjs-helical-thread-milling.gcode"),
    );
    let refusal = b.wait_text("#refusal", T);
    assert!(refusal.contains("line 5, column 5"), "{refusal}");
    let marked = b.wait_text(
        "#gcode-view [data-line=\"5\"] mark.col[data-column=\"5\"]",
        T,
    );
    let line5 = std::fs::read_to_string(corpus("cncjs-helical-thread-milling.gcode"))
        .unwrap()
        .lines()
        .nth(4)
        .unwrap()
        .to_string();
    assert_eq!(marked, line5.chars().nth(4).unwrap().to_string());
    b.screenshot("jobs-refused");

    // Pendants: bind the demo pendant to the other machine and back.
    b.goto(&format!("{}/#/pendants", s.base));
    b.wait_text("[data-pendant=\"1\"]", T);
    let plate = b.wait_text("[data-touch-plate=\"1\"]", T);
    assert!(plate.contains("Touch plate 15 mm"), "{plate}");
    for target in [mill.id, 1] {
        b.select("[data-bind-select=\"1\"]", &target.to_string());
        b.click("[data-bind=\"1\"]");
        wait_for(T, "the pendant to be bound", || {
            (s.get("/api/v1/pendants/1").body["machine"] == target).then_some(())
        });
        let name = if target == 1 { "demo" } else { "mill-2" };
        b.wait(
            "the page to show the binding",
            T,
            &format!(
                "return document.querySelector('[data-bound-to=\"1\"]').textContent === '{name}';"
            ),
        );
    }

    // An M1 macro: a valid one is stored, an invalid one is refused with the server's reason.
    b.select("[data-pendant=\"1\"] [data-macro-type=\"M1\"]", "mdi");
    b.type_into("[data-pendant=\"1\"] [data-macro-line=\"M1\"]", "G91 G0 Z5");
    b.click("[data-pendant=\"1\"] [data-macro-save=\"M1\"]");
    b.wait_text("[data-pendant=\"1\"] [data-macro-saved=\"M1\"]", T);
    let stored = s.get("/api/v1/pendants/1").body["macros"]["M1"].clone();
    assert_eq!(stored, json!({"type": "mdi", "line": "G91 G0 Z5"}));
    b.type_into("[data-pendant=\"1\"] [data-macro-line=\"M1\"]", "G1 X(");
    b.click("[data-pendant=\"1\"] [data-macro-save=\"M1\"]");
    let err = b.wait(
        "the macro refusal",
        T,
        "const e = document.querySelector('[data-pendant=\"1\"] [data-macro-error=\"M1\"]'); \
         return e && e.textContent.includes('invalid_field') ? e.textContent : null;",
    );
    assert!(err.as_str().unwrap().contains("macros.M1"), "{err}");
    assert_eq!(s.get("/api/v1/pendants/1").body["macros"]["M1"], stored);
    b.screenshot("pendants");

    // Events: history and live, with what was just done.
    b.goto(&format!("{}/#/events", s.base));
    b.wait(
        "the audit log",
        T,
        "const t = document.querySelector('table.events').textContent; \
         return t.includes('pendant.macro') && t.includes('job.state') && t.includes('machine.jog');",
    );
    b.screenshot("events");
    // Filtered by type (the server filters): only pendant events remain.
    b.type_into("#events-types", "pendant");
    b.click("#events-types ~ button[type=submit]");
    b.wait(
        "only pendant events",
        T,
        "const rows = [...document.querySelectorAll('table.events tbody tr')]; \
         return rows.length > 0 && rows.every(r => r.dataset.type.startsWith('pendant.')) && \
           rows.some(r => r.dataset.type === 'pendant.macro');",
    );
    b.goto(&format!("{}/#/plugins", s.base));
    b.wait_text("[data-plugin=\"sim-machine\"]", T);
    b.screenshot("plugins");

    // The stream lost: the page says so and greys out motion, STOP stays.
    b.goto(&format!("{}/#/machines/1", s.base));
    b.wait_enabled("[data-jog=\"X+\"]", T);
    let mut s = s;
    s.kill();
    b.wait(
        "the lost-connection banner",
        T,
        "const c = document.getElementById('conn'); return !c.hidden && c.textContent.includes('lost');",
    );
    assert!(b.disabled("[data-jog=\"X+\"]"));
    assert!(b.disabled("[data-cmd=\"cycle_start\"]"));
    assert!(!b.disabled("[data-cmd=\"stop\"]"));
    assert!(!b.disabled("[data-cmd=\"feed_hold\"]"));
    b.screenshot("machine-stream-lost");
}

#[test]
fn a_network_server_asks_for_a_token_and_a_viewer_cannot_move() {
    let mut s = Server::unstarted(Opts {
        listen: "0.0.0.0:0".into(),
        demo: true,
        ..Opts::default()
    });
    let viewer = s.create_token("viewer", "victor");
    let operator = s.create_token("operator", "olga");
    s.spawn().unwrap();
    // The page itself needs no token; the API does.
    assert_eq!(raw_get(&s, "/", &[]).status(), 200);
    assert_eq!(s.get("/api/v1/machines").status, 401);

    let b = Browser::start();
    b.goto(&s.base);
    b.wait_text("#signin", T);
    b.screenshot("sign-in");
    b.type_into("#token", "fresa_wrong");
    b.click("#signin button[type=submit]");
    // The error line exists (empty) from the start: wait for the server's answer in it.
    let err = b.wait(
        "the sign-in error",
        T,
        "const e = document.getElementById('signin-error'); return e && e.textContent.trim();",
    );
    assert!(err.as_str().unwrap().contains("invalid_token"), "{err}");

    b.type_into("#token", &viewer);
    b.click("#signin button[type=submit]");
    assert_eq!(b.wait_text("#role", T), "victor · viewer");
    b.goto(&format!("{}/#/machines/1", s.base));
    assert_eq!(dro(&b, "x"), "0.000");
    // The event stream works with the token (no lost-connection banner) ...
    b.wait(
        "the live stream",
        T,
        "return document.getElementById('conn').hidden;",
    );
    // ... and every control that changes something is disabled, not failing.
    for css in [
        "[data-jog=\"X+\"]",
        "[data-cmd=\"stop\"]",
        "[data-cmd=\"feed_hold\"]",
        "[data-cmd=\"cycle_start\"]",
        "form:has(#mdi) button[type=submit]",
    ] {
        assert!(b.disabled(css), "{css} is enabled for a viewer");
    }
    b.screenshot("machine-viewer");

    // Sign out; an operator may jog.
    b.click("#who button");
    b.wait_text("#signin", T);
    b.type_into("#token", &operator);
    b.click("#signin button[type=submit]");
    assert_eq!(b.wait_text("#role", T), "olga · operator");
    b.goto(&format!("{}/#/machines/1", s.base));
    b.click("[data-jog=\"X+\"]");
    b.wait(
        "the DRO to show X 1.000",
        T,
        "return document.querySelector('[data-dro=\"x\"]').textContent === '1.000';",
    );
    s.token = Some(operator);
    assert_eq!(s.status(1)["work_position"]["x"].as_f64(), Some(1.0));
}

/// The simulated Kawasaki controller (`kawasaki-as-sim`), which can drop the link after N moves
/// and report another part zero when the server reconnects.
struct Robot {
    child: std::process::Child,
    addr: String,
}

impl Drop for Robot {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

#[test]
fn a_changed_part_zero_is_confirmed_in_a_dialog() {
    use std::io::BufRead;
    let s = Server::start();
    let mut child = std::process::Command::new(fresa_tests::bin_dir().join("kawasaki-as-sim"))
        .args(["--listen", "127.0.0.1:0", "--protocol", "fresa-v1"])
        .args([
            "--drop-after",
            "20",
            "--part-zero-after-reconnect",
            "-390,5,-30",
        ])
        .arg("--log")
        .arg(s.root().join("robot.log"))
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::piped())
        .spawn()
        .expect("start kawasaki-as-sim");
    let mut line = String::new();
    std::io::BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let robot = Robot {
        addr: line.trim().trim_start_matches("listening on ").to_string(),
        child,
    };
    let m = s.create_machine(&json!({"name": "robot", "backend": "kawasaki-as",
        "config": {"address": robot.addr, "protocol": "fresa-v1"}}));
    let mut program = String::from("G21 G90\nG0 X0 Y0 Z5\nG1 Z-1 F300\n");
    for i in 0..40 {
        program.push_str(&format!("G1 X{} Y{} F300\n", 10 + i % 7, i % 10));
    }
    program.push_str("G0 Z5\nM30\n");
    let job = s.upload(m, "robot-job", program)["id"].as_i64().unwrap();
    s.job_action(job, "start").expect(200);
    s.wait_job_state(job, "failed", T);

    let b = Browser::start();
    b.goto(&format!("{}/#/jobs/{job}", s.base));
    b.click("[data-action=\"resume\"]");
    b.wait(
        "the dialog",
        T,
        "return document.getElementById('dialog').open;",
    );
    let dialog = b.wait_text("#part-zero-dialog", T);
    assert!(
        dialog.contains("-400.000, 0.000, -30.000") && dialog.contains("-390.000, 5.000, -30.000"),
        "{dialog}"
    );
    b.screenshot("part-zero-dialog");
    // Declined: nothing moves, the run stays as it was.
    b.click("#dialog button[value=\"no\"]");
    b.wait(
        "the dialog to close",
        T,
        "return !document.getElementById('dialog').open;",
    );
    assert_eq!(s.job(job)["state"], "failed");
    // Confirmed: the run resumes with the new part zero and completes.
    b.click("[data-action=\"resume\"]");
    b.wait(
        "the dialog again",
        T,
        "const d = document.getElementById('dialog'); return d.open && !!d.querySelector('#part-zero-dialog');",
    );
    b.click("#dialog button[value=\"yes\"]");
    // The click only sends the resume: the run is still `failed` until the server has it.
    s.wait_job(job, T, "completed after the confirmed resume", |j| {
        j["state"] == "completed"
    });
    b.wait(
        "the page to show completed",
        T,
        "const e = document.getElementById('job-state'); return e && e.textContent === 'completed';",
    );
}

/// Machine I/O lamps on the machine page: a limit switch pressed by moving onto it lights its
/// lamp (and the page shows the alarm naming it), a switched output lights, and the overview
/// card shows the same lamps.
#[test]
fn io_lamps_follow_the_machines_inputs_and_outputs() {
    let s = Server::start();
    let m = s.create_machine(&json!({
        "name": "switched", "backend": "sim-machine", "max_jog_mm": 20.0,
        "config": {"time_scale": 0.05, "switches": {
            "limit_x_max": {"axis": "x", "at_or_above": 5},
            "probe": {"axis": "z", "at_or_below": -20}}}
    }));
    s.wait_machine_state(m, "idle", T);
    let b = Browser::start();
    // JS answering the class list of the lamp named `name` once it has class `cls`.
    let lamp_is = |name: &str, cls: &str| {
        format!(
            "const l = [...document.querySelectorAll('.lamp')].find(l => l.textContent === '{name}'); \
             return l && l.classList.contains('{cls}') ? l.className : null;"
        )
    };
    b.goto(&format!("{}/#/machines/{m}", s.base));
    b.wait("the limit lamp, off", T, &lamp_is("limit_x_max", "off"));
    b.wait("the probe lamp, off", T, &lamp_is("probe", "off"));

    // Press the switch by jogging onto it (through the API, as a pendant would): the page
    // follows the live stream.
    s.jog(m, "X", 10.0).expect(200);
    let lit = b.wait("the limit lamp lit", T, &lamp_is("limit_x_max", "on"));
    assert!(
        lit.as_str().unwrap_or("").contains("in"),
        "an input lamp: {lit}"
    );
    b.wait(
        "the alarm naming the input",
        T,
        "return document.body.textContent.includes('limit_x_max tripped');",
    );

    // An output switched through the API lights its lamp.
    s.command(m, "reset", json!({})).expect(200);
    s.command(m, "toggle_output", json!({"name": "spindle"}))
        .expect(200);
    b.wait("the spindle lamp lit", T, &lamp_is("spindle", "on"));
    // Reset cleared the alarm: the page must not keep showing it.
    b.wait(
        "the alarm gone after reset",
        T,
        "return !document.body.textContent.includes('limit_x_max tripped');",
    );
    b.screenshot("io-lamps");

    // The overview card shows the same lamps.
    b.goto(&s.base);
    b.wait("the card's spindle lamp", T, &lamp_is("spindle", "on"));
}

/// The machine page's touch-off panel: the probe lamp beside the button, a touch-off that sets
/// Z from the plate and says what it changed, the plate remembered for the machine, and on a
/// machine with no probe input a disabled button that says why.
#[test]
fn the_touch_off_panel_sets_z_from_the_plate_and_remembers_it() {
    let s = Server::start();
    let m = s.create_machine(&json!({
        "name": "router", "backend": "sim-machine",
        "config": {"time_scale": 0, "travel": {"z": [-100, 0]},
                   "switches": {"probe": {"axis": "z", "at_or_below": -20}}}
    }));
    let plain = s.create_machine(&json!({"name": "plain", "backend": "sim-machine"}));
    s.wait_machine_state(m, "idle", T);
    let b = Browser::start();
    b.goto(&format!("{}/#/machines/{m}", s.base));
    b.wait(
        "the probe lamp, open",
        T,
        "const l = document.querySelector('#probe-lamp'); return l && l.classList.contains('off');",
    );
    b.type_into("#touch-plate", "12");
    b.click("#touch-off");
    let result = b.wait(
        "the touch-off's result",
        T,
        "const r = document.querySelector('#touch-result'); \
         return r && r.textContent.includes('→') ? r.textContent : null;",
    );
    let text = result.as_str().unwrap();
    assert!(
        text.contains("machine Z -20.000") && text.contains("→ -32.000"),
        "{text}"
    );
    assert!(
        text.contains("Z reads 17.000"),
        "12 mm plate + 5 mm retract: {text}"
    );
    let offsets = s.get(&format!("/api/v1/machines/{m}/offsets")).expect(200);
    assert_eq!(offsets["offsets"]["G54"]["z"], -32.0, "{offsets}");
    b.screenshot("touch-off");
    // An edge: the tool's diameter is asked for, and a probe that finds no edge says so
    // (this machine's probe is under Z: moving along X never closes it).
    assert!(b
        .js("return document.querySelector('#touch-diameter').closest('label').hidden;")
        .as_bool()
        .unwrap());
    b.select("#touch-axis", "X+");
    assert!(!b
        .js("return document.querySelector('#touch-diameter').closest('label').hidden;")
        .as_bool()
        .unwrap());
    assert_eq!(b.wait_text("#touch-off", T), "Touch off X+");
    b.click("#touch-off");
    b.wait(
        "the missed edge reported",
        T,
        "const r = document.querySelector('#touch-result'); \
         return r && r.textContent.includes('probe_not_tripped') ? r.textContent : null;",
    );
    let offsets = s.get(&format!("/api/v1/machines/{m}/offsets")).expect(200);
    assert_eq!(
        offsets["offsets"]["G54"]["x"], 0.0,
        "nothing changed: {offsets}"
    );
    // Remembered for this machine in this browser.
    b.goto(&format!("{}/#/machines/{plain}", s.base));
    b.goto(&format!("{}/#/machines/{m}", s.base));
    b.wait(
        "the plate remembered",
        T,
        "const i = document.querySelector('#touch-plate'); return i && i.value === '12';",
    );
    // No probe input: the button is disabled and says why.
    b.goto(&format!("{}/#/machines/{plain}", s.base));
    b.wait_text("#touch-result", T);
    b.wait(
        "the reason shown",
        T,
        "return document.querySelector('#touch-result').textContent.includes('no probe input');",
    );
    assert!(b.disabled("#touch-off"));
    let tip = b.js("return document.querySelector('#touch-off').title;");
    assert!(
        tip.as_str().unwrap_or("").contains("no probe input"),
        "{tip}"
    );
}

/// The machine page's overrides card: +10 and the slider set the feed override, rapid buttons
/// the rapid one, within the machine's range; what the machine reports is what is shown, also
/// a change from elsewhere (the API); at the top of the range +10 is refused and says why.
#[test]
fn the_override_card_sets_feed_and_rapid_and_shows_what_the_machine_reports() {
    let s = Server::start();
    let m = s.create_machine(&json!({
        "name": "router", "backend": "sim-machine", "config": {"time_scale": 0},
        "override_limits": {"feed_max": 150},
    }));
    s.wait_machine_state(m, "idle", T);
    let b = Browser::start();
    b.goto(&format!("{}/#/machines/{m}", s.base));
    b.wait_text("[data-override-value=\"feed\"]", T);
    b.click("[data-override=\"feed+\"]");
    s.wait_status(m, T, "feed override 110", |st| st["feed_override"] == 110.0);
    b.wait(
        "110 % shown",
        T,
        "return document.querySelector('[data-override-value=\"feed\"]').textContent === '110 %';",
    );
    b.click("[data-override=\"rapid25\"]");
    s.wait_status(m, T, "rapid override 25", |st| st["rapid_override"] == 25.0);
    b.wait(
        "the 25 % rapid button active",
        T,
        "return document.querySelector('[data-override=\"rapid25\"]').classList.contains('active');",
    );
    // The slider, released at 140 %.
    b.js(
        "const i = document.querySelector('#override-feed'); i.value = 140; \
         i.dispatchEvent(new Event('change')); return true;",
    );
    s.wait_status(m, T, "feed override 140", |st| st["feed_override"] == 140.0);
    // A change from the API shows too.
    s.post(
        &format!("/api/v1/machines/{m}/overrides"),
        &json!({"feed": 150}),
    )
    .expect(200);
    b.wait(
        "150 % from the API shown",
        T,
        "return document.querySelector('[data-override-value=\"feed\"]').textContent === '150 %';",
    );
    // The slider's range is the machine's; +10 past it is clamped, and nothing changes.
    let max = b.js("return document.querySelector('#override-feed').max;");
    assert_eq!(max, json!("150"));
    b.click("[data-override=\"feed+\"]");
    assert_eq!(s.status(m)["feed_override"], 150.0);
    b.screenshot("overrides");
}

/// The machine's position on `axis`, from the API.
fn machine_axis(s: &Server, axis: &str) -> f64 {
    s.status(1)["machine_position"][axis].as_f64().unwrap()
}

/// Hold-to-jog and keyboard jog: a held button (and, with the keyboard switch on, a held
/// arrow key) keeps the axis moving past what one keep-alive period allows, and its release
/// stops it well short of `max_jog_mm`; keys do nothing with the switch off; a tab that goes
/// away mid-hold stops sending keep-alives and the server's deadman stops the machine.
#[test]
fn the_console_jogs_while_a_button_or_key_is_held_and_stops_when_let_go() {
    let s = Server::start_demo();
    let b = Browser::start();
    b.goto(&format!("{}/#/machines/1", s.base));
    b.wait_enabled("[data-jog=\"X+\"]", T);
    b.select("#jog-step", "hold");
    b.js("const f = document.getElementById('jog-feed'); f.value = '600'; f.dispatchEvent(new Event('input'));");
    let press = |css: &str, ty: &str| {
        b.js(&format!(
            "document.querySelector('{css}').dispatchEvent(new PointerEvent('{ty}', {{bubbles: true, pointerId: 1}}));"
        ));
    };
    let max_jog = s.get("/api/v1/machines/1").body["max_jog_mm"]
        .as_f64()
        .unwrap();

    // Held: 10 mm/s, so 5 mm takes 0.5 s, twice the deadman's 250 ms: the keep-alives work.
    press("[data-jog=\"X+\"]", "pointerdown");
    s.wait_status(1, T, "X moving past 5 mm while held", |st| {
        st["machine_position"]["x"].as_f64().unwrap_or(0.0) > 5.0
    });
    press("[data-jog=\"X+\"]", "pointerup");
    let st = s.wait_status(1, T, "idle after the release", |st| st["state"] == "idle");
    let x = st["machine_position"]["x"].as_f64().unwrap();
    assert!(x > 5.0 && x < max_jog, "stopped on release: x = {x}");

    // Keys do nothing while the keyboard switch is off (a marker step jog on Z afterwards
    // shows the page handled both).
    let key = |ty: &str, k: &str| {
        b.js(&format!(
            "document.dispatchEvent(new KeyboardEvent('{ty}', {{key: '{k}', bubbles: true}}));"
        ));
    };
    assert!(b.js("return document.getElementById('keyboard-jog-on').hidden;") == true);
    key("keydown", "ArrowUp");
    key("keyup", "ArrowUp");
    assert_eq!(machine_axis(&s, "y"), 0.0);

    // Switched on: the badge says so, and a held ArrowUp moves Y+ until released.
    b.click("#keyboard-jog");
    assert!(b.js("return document.getElementById('keyboard-jog-on').hidden;") == false);
    key("keydown", "ArrowUp");
    s.wait_status(1, T, "Y moving past 5 mm while the key is held", |st| {
        st["machine_position"]["y"].as_f64().unwrap_or(0.0) > 5.0
    });
    key("keyup", "ArrowUp");
    let st = s.wait_status(1, T, "idle after the key's release", |st| {
        st["state"] == "idle"
    });
    let y = st["machine_position"]["y"].as_f64().unwrap();
    assert!(
        y > 5.0 && y < max_jog,
        "stopped on the key's release: y = {y}"
    );
    assert_eq!(machine_axis(&s, "x"), x, "the key moved Y only");

    // The link goes mid-hold (nothing the page sends arrives any more, not even a cancel):
    // no keep-alive comes, and the server's deadman stops the machine.
    let events = s.events("types=machine.jog_cancel", Some(0));
    press("[data-jog=\"X-\"]", "pointerdown");
    s.wait_status(1, T, "X moving back while held", |st| {
        st["machine_position"]["x"].as_f64().unwrap_or(x) < x - 2.0
    });
    b.js("window.fetch = () => new Promise(() => {});");
    let st = s.wait_status(1, T, "idle once the link is gone", |st| {
        st["state"] == "idle"
    });
    let back = st["machine_position"]["x"].as_f64().unwrap();
    assert!(back > x - max_jog, "stopped by the deadman: x = {back}");
    let cancels = events.until(T, "the deadman's cancel", |e| {
        e.data["actor"]
            .as_str()
            .is_some_and(|a| a.starts_with("deadman:"))
    });
    assert!(!cancels.is_empty());

    // The tab closes mid-hold: the page lets go as it is hidden (or, failing that, the
    // deadman does); either way the machine stops short of max_jog_mm. (A fresh page: this
    // one's fetch is cut off.)
    b.goto("about:blank");
    b.goto(&format!("{}/#/machines/1", s.base));
    b.wait_enabled("[data-jog=\"X+\"]", T);
    b.select("#jog-step", "hold");
    let from = machine_axis(&s, "x");
    press("[data-jog=\"X+\"]", "pointerdown");
    s.wait_status(1, T, "X moving while held", |st| {
        st["machine_position"]["x"].as_f64().unwrap_or(from) > from + 2.0
    });
    b.goto("about:blank");
    let st = s.wait_status(1, T, "idle once the tab is gone", |st| {
        st["state"] == "idle"
    });
    let end = st["machine_position"]["x"].as_f64().unwrap();
    assert!(end < from + max_jog, "stopped once the tab went: x = {end}");
}

/// Issue 26: a run held at M0 shows why on the machine page (with the Cycle start button
/// marked as the one that applies) and on the job page (whose resume button says Cycle
/// start); the hold card's button goes on. Measure tool (issue 25) on a machine with a setter
/// shows the length.
#[test]
fn the_hold_card_and_the_job_page_say_why_the_run_holds_and_what_goes_on() {
    let s = Server::start();
    let m = s.create_machine(&json!({
        "name": "router", "backend": "sim-machine",
        "config": {"time_scale": 0, "travel": {"z": [-100, 0]},
                   "switches": {"probe": {"axis": "z", "at_or_below": -20}}}
    }));
    s.wait_machine_state(m, "idle", T);
    s.send(
        s.req(
            reqwest::Method::PATCH,
            &format!("/api/v1/machines/{m}/run-settings"),
        )
        .json(
            &json!({"tool_setter": {"x": 0, "y": 0, "z": 0, "distance_mm": 40,
                                      "feed_mm_min": 300, "reference_tool": 1}}),
        ),
    )
    .expect(200);
    let job = s.upload(m, "clamp", "G0 X1\nM0 (MSG, change clamp)\nG0 X2\n")["id"]
        .as_i64()
        .unwrap();
    s.job_action(job, "start").expect(200);
    s.wait_job_state(job, "paused", T);
    let b = Browser::start();
    b.goto(&format!("{}/#/machines/{m}", s.base));
    let reason = b.wait(
        "the hold's reason",
        T,
        "const r = document.querySelector('#hold-reason'); \
         return r && r.textContent.includes('change clamp') ? r.textContent : null;",
    );
    assert!(
        reason.as_str().unwrap().starts_with("Held: M0 at line 2"),
        "{reason}"
    );
    assert_eq!(b.wait_text("#hold-continue", T), "Cycle start");
    assert!(b
        .js("return document.querySelector('[data-cmd=\"cycle_start\"]').classList.contains('applies') \
             && !document.querySelector('[data-cmd=\"resume\"]').classList.contains('applies');")
        .as_bool()
        .unwrap());
    b.screenshot("hold-card");
    b.goto(&format!("{}/#/jobs/{job}", s.base));
    let held = b.wait_text("#job-hold", T);
    assert!(
        held.contains("change clamp") && held.contains("Cycle start goes on"),
        "{held}"
    );
    assert_eq!(b.wait_text("[data-action=\"resume\"]", T), "Cycle start");
    b.goto(&format!("{}/#/machines/{m}", s.base));
    b.wait_enabled("#hold-continue", T);
    b.click("#hold-continue");
    s.wait_job_state(job, "completed", T);
    b.wait(
        "no longer held",
        T,
        "return document.querySelector('#hold-reason').textContent === 'Not held';",
    );
    b.click("#measure-tool");
    let result = b.wait(
        "the measure's result",
        T,
        "const r = document.querySelector('#measure-result'); \
         return r && r.textContent.includes('length') ? r.textContent : null;",
    );
    assert!(
        result.as_str().unwrap().contains("machine Z -20.000"),
        "{result}"
    );
}

/// The job page's "Start at line…": the preview of the state and the preamble comes first (a
/// line that cannot be started at shows why instead), and only then the start, which runs
/// lines N.. of the program.
#[test]
fn the_job_page_previews_a_start_at_a_line_before_it_starts() {
    let s = Server::start();
    let m = s.sim("m", 0.0);
    let program = "G21 G90\nG0 Z5\nG0 X10 Y10\nS1000 M3\nG1 Z-1 F200\nG1 X20\nG1 Y20\nM30\n";
    let job = s.upload(m.id, "start-at", program)["id"].as_i64().unwrap();
    let b = Browser::start();
    b.goto(&format!("{}/#/jobs/{job}", s.base));
    b.click("#start-at summary");
    b.wait_enabled("#start-at-preview", T);
    b.type_into("#start-line", "99");
    b.click("#start-at-preview");
    let refused = b.wait_text("#start-refusal", T);
    assert!(refused.contains("start_past_end"), "{refused}");
    assert!(b.js("return document.getElementById('start-at-go') === null;") == true);

    b.type_into("#start-line", "6");
    b.click("#start-at-preview");
    let gcode = b.wait_text("#start-preview-gcode", T);
    assert!(
        gcode.contains("S1000 M3") && gcode.contains("G53 G0 X10 Y10\nG53 G1 Z-1 F200"),
        "{gcode}"
    );
    b.screenshot("job-start-at-line");
    assert_eq!(s.job(job)["state"], "ready", "the preview starts nothing");
    b.wait_enabled("#start-at-go", T);
    b.click("#start-at-go");
    let j = s.wait_job_state(job, "completed", T);
    assert_eq!(j["run"]["from_line"], 6, "{j}");
    let run = j["run"]["id"].as_i64().unwrap();
    assert_eq!(m.lines_of(run), vec![6, 7, 8]);
}

/// The height-map page: a grid probed from its form, followed live, shown as a colour plot
/// with the range in its legend; on the job's page the map is offered for the start, with how
/// it fits the program, and the run uses it.
#[test]
fn a_height_map_is_probed_plotted_and_chosen_for_a_job_in_the_browser() {
    let s = Server::start();
    let m = s.create_machine(&json!({
        "name": "pcb", "backend": "sim-machine", "max_jog_mm": 60.0,
        "config": {"time_scale": 0, "travel": {"z": [-20, 10]},
                   "switches": {"probe": {"axis": "z", "at_or_below": -1,
                                          "slope_x": 0.01, "slope_y": -0.02}}}
    }));
    s.wait_machine_state(m, "idle", T);
    let b = Browser::start();
    b.goto(&format!("{}/#/machines/{m}", s.base));
    b.click("#height-maps-link");
    b.wait_text("#hm-form", T);
    for (field, value) in [
        ("x1", "20"),
        ("y1", "10"),
        ("nx", "3"),
        ("ny", "3"),
        ("feed", "300"),
    ] {
        b.type_into(&format!("#hm-{field}"), value);
    }
    b.click("#hm-start");
    let title = b.wait(
        "the map complete",
        T,
        "const t = document.querySelector('#hm-title'); \
         return t && t.textContent.includes('complete') ? t.textContent : null;",
    );
    let hid: i64 = title.as_str().unwrap()[4..]
        .split(' ')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    let map = s
        .get(&format!("/api/v1/machines/{m}/height-maps/{hid}"))
        .expect(200);
    assert_eq!(map["probed"], 9, "{map}");
    // The legend shows the range the API reports; the plot is drawn in colour.
    let shown = b.js(
        "const l = document.querySelector('#hm-legend'); \
         return [+l.querySelector('[data-min]').dataset.min, +l.querySelector('[data-max]').dataset.max];",
    );
    assert_eq!(shown, json!([map["min"], map["max"]]), "{map}");
    let coloured = b.js(
        "const c = document.querySelector('#hm-plot'); const d = c.getContext('2d') \
         .getImageData(0, 0, c.width, c.height).data; let n = 0; \
         for (let k = 0; k < d.length; k += 4) if (d[k] !== d[k + 1] || d[k + 1] !== d[k + 2]) n++; \
         return n > c.width * c.height / 2;",
    );
    assert_eq!(coloured, json!(true));
    assert!(b.wait_text("#hm-list", T).contains("9/9"));
    b.screenshot("height-map");

    // A job on the map's area: the start offers the map and shows its correction range.
    let job = s.upload(
        m,
        "trace.nc",
        "G0 Z2\nG0 X2 Y2\nG1 Z-0.1 F300\nG1 X18 Y8\nG0 Z2\n",
    )["id"]
        .as_i64()
        .unwrap();
    b.goto(&format!("{}/#/jobs/{job}", s.base));
    b.wait(
        "the map offered",
        T,
        &format!("return !!document.querySelector('#start-height-map option[value=\"{hid}\"]');"),
    );
    b.select("#start-height-map", &hid.to_string());
    let fit = b.wait(
        "the fit shown",
        T,
        "const f = document.querySelector('#height-map-fit'); \
         return f && f.textContent.includes('Z correction') ? f.textContent : null;",
    );
    assert!(fit.as_str().unwrap().starts_with("fits"), "{fit}");
    b.click("button[data-action=start]");
    s.wait_job_state(job, "completed", T);
    assert_eq!(s.job(job)["run"]["height_map_id"], hid);
    b.wait_text("#job-height-map", T);
}

// --- The toolpath's shape, the run screen and shop-floor legibility (issue 27) -----------------

/// Distance from `p` to the segment `a`-`b`.
fn segment_distance(p: [f64; 3], a: [f64; 3], b: [f64; 3]) -> f64 {
    let ab: [f64; 3] = std::array::from_fn(|i| b[i] - a[i]);
    let ap: [f64; 3] = std::array::from_fn(|i| p[i] - a[i]);
    let len2: f64 = ab.iter().map(|c| c * c).sum();
    let t = if len2 > 0.0 {
        (ap.iter().zip(&ab).map(|(x, y)| x * y).sum::<f64>() / len2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    ap.iter()
        .zip(&ab)
        .map(|(x, y)| (x - t * y) * (x - t * y))
        .sum::<f64>()
        .sqrt()
}

/// Checks a served toolpath against the exact path (start, then each move's end with its
/// line): its vertices are points of the path in order, every exact point lies within the
/// decimation distance of the drawn segment that stands for it, and points along every drawn
/// segment lie within that distance of the moves it stands for.
fn assert_within_decimation(d: &Decoded, exact: &[([f64; 3], u32)]) {
    let tol = d.decimation as f64 + 1e-3;
    let mut at = Vec::with_capacity(d.n);
    let mut i = 0;
    for (k, (p, line)) in d.pts.iter().zip(&d.lines).enumerate() {
        while i < exact.len() {
            let (q, l) = exact[i];
            if l == *line && (0..3).all(|c| q[c] as f32 == p[c]) {
                break;
            }
            i += 1;
        }
        assert!(
            i < exact.len(),
            "vertex {k} {p:?} (line {line}) is not a point of the path, in order"
        );
        at.push(i);
        i += 1;
    }
    assert_eq!(
        at.last(),
        Some(&(exact.len() - 1)),
        "the path's end is drawn"
    );
    let f64s = |p: [f32; 3]| p.map(|c| c as f64);
    for k in 1..d.n {
        let (a, b) = (f64s(d.pts[k - 1]), f64s(d.pts[k]));
        let moves = &exact[at[k - 1]..=at[k]];
        for (p, line) in moves {
            let e = segment_distance(*p, a, b);
            assert!(
                e <= tol,
                "line {line} {p:?} is {e} mm from the drawn path (decimation {tol})"
            );
        }
        for s in 1..4 {
            let f = s as f64 / 4.0;
            let q: [f64; 3] = std::array::from_fn(|c| a[c] + f * (b[c] - a[c]));
            let e = moves
                .windows(2)
                .map(|w| segment_distance(q, w[0].0, w[1].0))
                .fold(f64::INFINITY, f64::min);
            assert!(
                e <= tol,
                "drawn point {q:?} is {e} mm from the path (decimation {tol})"
            );
        }
    }
}

/// A zig-zag of 200 mm strokes, one stroke a line, a million lines in all (Y 0.0002 mm further
/// each stroke), and its exact path.
fn million_line_zigzag() -> (String, Vec<([f64; 3], u32)>) {
    let mut p = String::with_capacity(16 << 20);
    p.push_str("G21 G90\nG1 F3000\n");
    let mut exact = Vec::with_capacity(1_000_000);
    exact.push(([0.0, 0.0, 0.0], 0));
    for i in 0..999_997u32 {
        let x = if i % 2 == 0 { 200.0 } else { 0.0 };
        let y = format!("{:.4}", i as f64 * 0.0002);
        let _ = writeln!(p, "X{x} Y{y}");
        exact.push(([x, y.parse().unwrap(), 0.0], i + 3));
    }
    p.push_str("M30\n");
    (p, exact)
}

/// Pixels of the cut colour (blue) on the toolpath canvas: their bounding box [x0, y0, x1, y1].
const BLUE_BOX: &str = "const c = document.querySelector('canvas.toolpath'); \
    const t = document.createElement('canvas'); t.width = c.width; t.height = c.height; \
    const g = t.getContext('2d'); g.drawImage(c, 0, 0); \
    const d = g.getImageData(0, 0, t.width, t.height).data; \
    let x0 = 1e9, y0 = 1e9, x1 = -1, y1 = -1; \
    for (let y = 0; y < t.height; y++) for (let x = 0; x < t.width; x++) { \
      const i = 4 * (y * t.width + x); \
      if (d[i + 2] > d[i] + 60 && d[i + 2] > d[i + 1] + 20) { x0 = Math.min(x0, x); x1 = Math.max(x1, x); y0 = Math.min(y0, y); y1 = Math.max(y1, y); } } \
    return x1 < 0 ? null : [x0, y0, x1, y1];";

/// Issue 27: the million-line zig-zag the old decimation drew as an empty box (every vertex on
/// X = 0) is served within its decimation distance of the exact path, keeping its strokes, and
/// the console draws those vertices across the part's 200 mm.
#[test]
fn a_million_line_zigzag_is_served_and_drawn_across_its_strokes() {
    let s = Server::start();
    let m = s.sim("mill", 0.0);
    let (program, exact) = million_line_zigzag();
    let job = s.upload(m.id, "zigzag", program)["id"].as_i64().unwrap();
    let r = raw_get(&s, &format!("/api/v1/jobs/{job}/toolpath"), &[]);
    assert_eq!(r.status(), 200);
    let d = decode(&r.bytes().unwrap());
    assert_eq!(d.moves as usize, exact.len() - 1);
    assert!(d.n <= 250_000, "{} vertices", d.n);
    assert!(
        d.decimation > 0.0 && d.decimation < 0.5,
        "decimation {} mm",
        d.decimation
    );
    assert_within_decimation(&d, &exact);
    let left = d.pts.iter().filter(|p| p[0] == 0.0).count();
    let right = d.pts.iter().filter(|p| p[0] == 200.0).count();
    assert!(
        left > d.n / 3 && right > d.n / 3,
        "strokes kept: {left} vertices at X0, {right} at X200 of {}",
        d.n
    );

    let b = Browser::start();
    b.goto(&format!("{}/#/jobs/{job}", s.base));
    let drawn = b.wait(
        "the toolpath drawn",
        Duration::from_secs(120),
        "const c = document.querySelector('canvas.toolpath'); \
         if (!c || !c.dataset.drawMs) return null; const p = c.toolpath; let l = 0, r = 0; \
         for (let i = 0; i < p.n; i++) { const x = p.positions[3 * i]; if (x === 0) l++; else if (x === 200) r++; } \
         return [p.n, p.decimation, l, r];",
    );
    assert_eq!(
        drawn,
        json!([d.n, d.decimation, left, right]),
        "the page draws what the server sent"
    );
    // The picture: the cut colour fills the part's square, not a line at X = 0.
    let bbox = b.wait("the path's pixels", T, BLUE_BOX);
    let (w, h) = (
        bbox[2].as_f64().unwrap() - bbox[0].as_f64().unwrap(),
        bbox[3].as_f64().unwrap() - bbox[1].as_f64().unwrap(),
    );
    assert!(
        h > 100.0 && w / h > 0.9 && w / h < 1.1,
        "the 200 x 200 mm zig-zag spans {w} x {h} px"
    );
    let dims = b.wait_text("#toolpath-dims", T);
    assert_eq!(dims, "200.00 × 200.00 × 0.00 mm");
    b.screenshot("million-line-zigzag");
}

/// The text of `css` once it matches `re`-like `test` (a JS expression on `t`).
fn wait_js(b: &Browser, what: &str, script: &str) -> Value {
    b.wait(what, T, script)
}

/// Issue 27: the machine page is the run screen: the job's name, line of total, elapsed and the
/// server's remaining time move while a real-time sim job runs, the listing follows the line
/// executing (its text is the program's), and so does the job page's line.
#[test]
fn the_run_screen_follows_a_real_time_job() {
    let s = Server::start();
    let m = s.sim("mill", 1.0);
    // 300 moves of 2 mm at 600 mm/min: 0.2 s each, a minute in all.
    let program = fresa_tests::back_and_forth(300, 2.0, 600.0);
    let job = s.upload(m.id, "real-time", program.clone())["id"]
        .as_i64()
        .unwrap();
    let b = Browser::start();
    b.goto(&format!("{}/#/machines/{}", s.base, m.id));
    b.wait_text("#run-none", T);
    s.job_action(job, "start").expect(200);
    let name = b.wait(
        "the run screen to show the job",
        T,
        "const n = document.querySelector('#run-job'); const c = document.querySelector('#run-card > div:not([hidden])'); \
         return n && n.textContent.includes('real-time') ? n.textContent : null;",
    );
    assert_eq!(name, json!(format!("{job} · real-time")));
    let figures = "const l = document.querySelector('#run-line'), r = document.querySelector('#run-remaining'), \
         e = document.querySelector('#run-elapsed'); \
         return [+l.dataset.line, r.dataset.seconds === '' ? null : +r.dataset.seconds, e.textContent, l.textContent];";
    let first = wait_js(
        &b,
        "the line and the time left",
        &format!(
            "const v = (() => {{ {figures} }})(); return v[0] >= 2 && v[1] !== null ? v : null;"
        ),
    );
    let (line0, left0) = (first[0].as_i64().unwrap(), first[1].as_f64().unwrap());
    assert!(first[3].as_str().unwrap().ends_with("/ 300"), "{first}");
    let later = wait_js(
        &b,
        "the line to move on and the time left to fall",
        &format!(
            "const v = (() => {{ {figures} }})(); return v[0] >= {} && v[1] < {left0} && v[2] !== '—' ? v : null;",
            line0 + 5
        ),
    );
    assert!(later[1].as_f64().unwrap() > 0.0, "{later}");
    // The server agrees on where it is (it acknowledges lines as they end).
    let server_line = s.job(job)["line"].as_i64().unwrap();
    assert!(
        server_line >= later[0].as_i64().unwrap() - 1,
        "page {later} vs server {server_line}"
    );
    // The listing shows the line executing, with the program's text.
    let row = wait_js(
        &b,
        "the listing's current line",
        "const r = document.querySelector('#run-listing .current'); \
         return r ? [+r.dataset.line, r.textContent] : null;",
    );
    let n = row[0].as_i64().unwrap();
    let text = program.lines().nth(n as usize - 1).unwrap();
    assert_eq!(row[1], json!(format!("{n}{text}")));
    assert!(n >= line0, "listing at {n}, run at {line0}");
    let scrolled = b.js(
        "const l = document.querySelector('#run-listing'), r = l.querySelector('.current'); \
         return r.offsetTop >= l.scrollTop && r.offsetTop + r.offsetHeight <= l.scrollTop + l.clientHeight;",
    );
    assert_eq!(scrolled, json!(true), "the current line is in view");
    // The toolpath shows the executed part over the rest.
    b.wait(
        "executed vertices drawn",
        T,
        "const c = document.querySelector('#run-card canvas.toolpath'); return c && +c.dataset.executed > 2;",
    );
    b.screenshot("run-screen");
    // The job page's line moves too.
    b.goto(&format!("{}/#/jobs/{job}", s.base));
    let a = wait_js(
        &b,
        "the job page's line",
        "const l = document.querySelector('#job-line'); return l && +l.dataset.line > 0 ? +l.dataset.line : null;",
    );
    wait_js(
        &b,
        "the job page's line to move",
        &format!(
            "const l = document.querySelector('#job-line'), r = document.querySelector('#job-remaining'); \
             return +l.dataset.line > {} && r.textContent !== '—';",
            a.as_i64().unwrap()
        ),
    );
    s.job_action(job, "cancel").expect(200);
}

/// `[disabled, title, the why line of its card]` of `css`.
fn why(b: &Browser, css: &str) -> (bool, String, String) {
    let v = b.js(&format!(
        "const e = document.querySelector({}); const g = e.closest('[data-why-group]'); \
         const w = g && g.querySelector('.why'); \
         return [e.disabled, e.title, w && !w.hidden ? w.textContent : ''];",
        json!(css)
    ));
    (
        v[0].as_bool().unwrap(),
        v[1].as_str().unwrap_or("").to_string(),
        v[2].as_str().unwrap_or("").to_string(),
    )
}

/// Issue 27: during a run, controls the run forbids are disabled with the reason beside them;
/// pause, a feed hold (job and machine both `paused`, with the reason), a cancel that asks
/// first, its event in a sentence with who did it; and with the stream lost everything that
/// moves or changes state is disabled, saying why, except STOP and feed hold.
#[test]
fn controls_that_cannot_act_are_disabled_with_the_reason() {
    let mut s = Server::start();
    let m = s.sim("mill", 1.0);
    let program = fresa_tests::back_and_forth(600, 2.0, 600.0);
    let job = s.upload(m.id, "long", program)["id"].as_i64().unwrap();
    let b = Browser::start();
    b.goto(&format!("{}/#/machines/{}", s.base, m.id));
    b.wait_enabled("[data-jog=\"X+\"]", T);
    s.job_action(job, "start").expect(200);
    b.wait(
        "the run screen running",
        T,
        "const e = document.querySelector('#run-state'); return e && e.textContent === 'running';",
    );
    b.wait(
        "the jog disabled",
        T,
        "return document.querySelector('[data-jog=\"X+\"]').disabled;",
    );
    let running = format!("job {job} is running on this machine");
    for css in [
        "[data-jog=\"X+\"]",
        "[data-cmd=\"home\"]",
        "[data-cmd=\"go_to_zero\"]",
        "form:has(#mdi) button[type=submit]",
    ] {
        let (off, title, line) = why(&b, css);
        assert!(off, "{css} enabled during a run");
        assert_eq!(title, running, "{css}");
        assert!(line.contains(&running), "{css}: {line}");
    }
    for css in [
        "[data-cmd=\"zero\"]",
        "tr[data-offset=\"G55\"] td.row button:first-child",
        "#record-part-zero",
    ] {
        let (off, title, line) = why(&b, css);
        assert!(off, "{css} enabled during a run");
        assert!(title.contains("the machine is running"), "{css}: {title}");
        assert!(line.contains("the machine is running"), "{css}: {line}");
    }
    for css in [
        "[data-cmd=\"stop\"]",
        "[data-cmd=\"feed_hold\"]",
        "[data-run=\"pause\"]",
        "[data-run=\"cancel\"]",
        "[data-override=\"feed+\"]",
        "#jog-cancel",
    ] {
        assert!(!b.disabled(css), "{css} disabled during a run");
    }
    // Resume shows (instead of Pause) only once the job is paused.
    assert_eq!(
        b.js("return [document.querySelector('[data-run=\"pause\"]').hidden, document.querySelector('[data-run=\"resume\"]').hidden];"),
        json!([false, true])
    );
    b.screenshot("run-screen-disabled");

    // Pause from the run screen: the job and the machine are paused, and the screen says why.
    b.click("[data-run=\"pause\"]");
    s.wait_job_state(job, "paused", T);
    s.wait_status(m.id, T, "the machine paused", |st| st["state"] == "paused");
    let held = b.wait(
        "the pause's reason",
        T,
        "const h = document.querySelector('#run-hold'); return h && !h.hidden && h.textContent.includes('paused by') ? h.textContent : null;",
    );
    assert!(held.as_str().unwrap().contains("Resume goes on"), "{held}");
    assert_eq!(b.wait_text("#run-state", T), "paused");
    b.click("[data-run=\"resume\"]");
    s.wait_job_state(job, "running", T);

    // A feed hold: the machine and the job both say paused, with the reason.
    b.wait_enabled("[data-cmd=\"feed_hold\"]", T);
    b.click("[data-cmd=\"feed_hold\"]");
    // The job's `hold` is the machine status's, which follows the run's pause at the next
    // status poll: wait for both.
    let j = s.wait_job(job, T, "paused with its hold", |j| {
        j["state"] == "paused" && j["hold"].is_object()
    });
    let st = s.wait_status(m.id, T, "the machine paused", |st| st["state"] == "paused");
    assert_eq!(j["hold"]["kind"], "feed_hold", "{j}");
    assert_eq!(st["hold"]["message"], j["hold"]["message"]);
    let reason = j["hold"]["message"].as_str().unwrap().to_string();
    b.wait(
        "the feed hold's reason on the run screen",
        T,
        &format!(
            "const h = document.querySelector('#run-hold'); return !h.hidden && h.textContent.includes({}) \
             && document.querySelector('#run-state').textContent === 'paused';",
            json!(reason)
        ),
    );
    b.goto(&format!("{}/#/jobs/{job}", s.base));
    let on_job = b.wait_text("#job-hold", T);
    assert!(on_job.contains(&reason), "{on_job}");
    assert_eq!(b.wait_text("#job-state", T), "paused");
    b.goto(&format!("{}/#/machines/{}", s.base, m.id));
    b.click("[data-run=\"resume\"]");
    s.wait_job_state(job, "running", T);

    // Cancel asks first; kept, the job runs on; confirmed, it is cancelled.
    b.click("[data-run=\"cancel\"]");
    b.wait(
        "the dialog",
        T,
        "return document.getElementById('dialog').open;",
    );
    assert!(b.wait_text("#cancel-dialog", T).contains("stops at line"));
    b.screenshot("run-screen-cancel-dialog");
    b.click("#dialog button[value=\"no\"]");
    b.wait(
        "the dialog closed",
        T,
        "return !document.getElementById('dialog').open;",
    );
    assert_eq!(s.job(job)["state"], "running");
    b.click("[data-run=\"cancel\"]");
    b.wait(
        "the dialog",
        T,
        "return document.getElementById('dialog').open;",
    );
    b.click("#dialog button[value=\"yes\"]");
    let j = s.wait_job_state(job, "cancelled", T);
    let line = j["line"].as_i64().unwrap();
    let pct = (100.0 * line as f64 / 600.0).round() as i64;

    // The events page says it in a sentence, with who.
    b.goto(&format!("{}/#/events", s.base));
    let sentence = format!("local cancelled job {job} at line {line}, {pct} %");
    b.wait(
        "the cancel in words",
        T,
        &format!(
            "return [...document.querySelectorAll('table.events td.what')].some(td => td.textContent === {});",
            json!(sentence)
        ),
    );
    b.wait(
        "the start and the feed hold in words",
        T,
        &format!(
            "const t = [...document.querySelectorAll('table.events td.what')].map(td => td.textContent); \
             return t.includes('local started job {job}') && t.includes('local sent a feed hold');"
        ),
    );
    b.screenshot("events-sentences");

    // The stream lost: what moves or changes state is disabled and says why; STOP and feed
    // hold are not.
    b.goto(&format!("{}/#/machines/{}", s.base, m.id));
    b.wait_enabled("[data-cmd=\"zero\"]", T);
    s.kill();
    b.wait(
        "the lost-connection banner",
        T,
        "const c = document.getElementById('conn'); return !c.hidden;",
    );
    for css in [
        "[data-jog=\"X+\"]",
        "[data-cmd=\"zero\"]",
        "[data-cmd=\"reset\"]",
        "[data-cmd=\"cycle_start\"]",
        "tr[data-offset=\"G55\"] td.row button:first-child",
        "[data-override=\"feed+\"]",
        "#record-part-zero",
        "form:has(#mdi) button[type=submit]",
        "#keyboard-jog",
    ] {
        let (off, title, line) = why(&b, css);
        assert!(off, "{css} enabled with the stream lost");
        assert!(title.contains("live connection is lost"), "{css}: {title}");
        assert!(line.contains("live connection is lost"), "{css}: {line}");
    }
    assert!(!b.disabled("[data-cmd=\"stop\"]"));
    assert!(!b.disabled("[data-cmd=\"feed_hold\"]"));
    b.screenshot("machine-stream-lost-reasons");
}

/// The pages a phone or tablet visits, with what shows each is there.
fn pages(s: &Server, mill: i64, job: i64) -> Vec<(String, &'static str)> {
    vec![
        (format!("{}/#/", s.base), "[data-machine]"),
        (format!("{}/#/machines/1", s.base), "[data-dro=\"x\"]"),
        (
            format!("{}/#/machines/{mill}", s.base),
            "#run-listing .current",
        ),
        (format!("{}/#/jobs", s.base), "table.jobs tbody tr"),
        (
            format!("{}/#/jobs/{job}", s.base),
            "canvas.toolpath[data-draw-ms]",
        ),
        (format!("{}/#/pendants", s.base), "[data-pendant]"),
        (format!("{}/#/events", s.base), "table.events tbody tr"),
        (format!("{}/#/plugins", s.base), "[data-plugin]"),
        (format!("{}/#/machines/1/height-maps", s.base), "#hm-form"),
    ]
}

/// Issue 27: no page scrolls sideways on a 390 px phone or an 820 px tablet; on the phone the
/// navigation takes one short band and the DRO and the jog pad fit one screen.
#[test]
fn every_page_fits_a_phone_and_a_tablet_without_scrolling_sideways() {
    let s = Server::start_demo();
    let mill = s.sim("mill-2", 1.0);
    let job = s.upload(
        mill.id,
        "phone",
        fresa_tests::back_and_forth(2000, 2.0, 600.0),
    )["id"]
        .as_i64()
        .unwrap();
    s.job_action(job, "start").expect(200);
    let b = Browser::start();
    b.goto(&s.base);
    for (w, h, device) in [(390, 844, "phone"), (820, 1180, "tablet")] {
        b.viewport(w, h);
        for (url, ready) in pages(&s, mill.id, job) {
            b.goto(&url);
            b.wait(
                &format!("{url} at {w} px"),
                T,
                &format!("return !!document.querySelector({});", json!(ready)),
            );
            let wide = b.js(
                "const w = innerWidth; if (document.documentElement.scrollWidth <= w) return null; \
                 return [document.documentElement.scrollWidth, [...document.querySelectorAll('body *')] \
                   .filter(e => e.getBoundingClientRect().right > w + 0.5) \
                   .map(e => e.tagName + '.' + e.className + '#' + e.id).slice(0, 8)];",
            );
            assert_eq!(wide, Value::Null, "{url} scrolls sideways at {w} px");
            let name = url.rsplit('#').next().unwrap().replace('/', "-");
            b.screenshot(&format!("{device}{name}"));
        }
    }
    // The phone: a short navigation band; DRO and jog pad on one screen under the sticky bar.
    b.viewport(390, 844);
    b.goto(&format!("{}/#/machines/1", s.base));
    dro(&b, "x");
    let fit = b.js(
        "const top = document.querySelector('header.top').getBoundingClientRect().height; \
         const bar = document.querySelector('.sticky-bar').getBoundingClientRect().height; \
         const dro = document.querySelector('.dro').closest('.card').getBoundingClientRect(); \
         const pad = document.querySelector('.jog').getBoundingClientRect(); \
         return [top, bar + pad.bottom - dro.top, innerHeight];",
    );
    let (nav, both, screen) = (
        fit[0].as_f64().unwrap(),
        fit[1].as_f64().unwrap(),
        fit[2].as_f64().unwrap(),
    );
    assert!(nav <= 100.0, "the navigation takes {nav} px");
    assert!(
        both <= screen,
        "DRO and jog pad take {both} px under the sticky bar, the screen {screen}"
    );
    b.js("document.querySelector('.dro').closest('.card').scrollIntoView(); \
          window.scrollBy(0, -document.querySelector('.sticky-bar').getBoundingClientRect().height);");
    b.screenshot("phone-dro-and-jog");
    s.job_action(job, "cancel").expect(200);
}

/// The relative luminance (0 black .. 1 white) of a CSS colour `rgb(r, g, b)`.
fn luminance(css: &Value) -> f64 {
    let v: Vec<f64> = css
        .as_str()
        .unwrap()
        .trim_start_matches("rgba(")
        .trim_start_matches("rgb(")
        .trim_end_matches(')')
        .split(',')
        .take(3)
        .map(|c| c.trim().parse::<f64>().unwrap() / 255.0)
        .collect();
    0.2126 * v[0] + 0.7152 * v[1] + 0.0722 * v[2]
}

/// Issue 27: dark mode by the switch (remembered) or the system's; disabled controls distinct
/// from enabled ones in both themes; positions in mm or inch; numbers at a fixed resolution;
/// MDI history per machine with ↑ and ↓.
#[test]
fn dark_mode_units_number_formats_and_mdi_history() {
    let s = Server::start_demo();
    let b = Browser::start();
    b.goto(&format!("{}/#/machines/1", s.base));
    assert_eq!(dro(&b, "x"), "0.000");
    let bg = "return getComputedStyle(document.body).backgroundColor;";
    assert!(luminance(&b.js(bg)) > 0.8, "light by default here");
    // Enabled and disabled buttons side by side: the disabled one is hatched and dashed.
    let contrast = "const c = document.querySelector('.card'); \
        const on = document.createElement('button'), off = document.createElement('button'); \
        off.disabled = true; c.append(on, off); \
        const a = getComputedStyle(on), d = getComputedStyle(off); \
        const r = [a.borderTopStyle, d.borderTopStyle, a.color, d.color, d.backgroundImage !== 'none']; \
        on.remove(); off.remove(); return r;";
    let light = b.js(contrast);
    assert_eq!(
        (light[0].clone(), light[1].clone()),
        (json!("solid"), json!("dashed"))
    );
    assert!(light[4].as_bool().unwrap(), "disabled is hatched: {light}");
    assert!(
        (luminance(&light[2]) - luminance(&light[3])).abs() > 0.25,
        "{light}"
    );

    b.click("#theme-switch");
    b.wait(
        "the dark theme",
        T,
        "return document.documentElement.dataset.theme === 'dark';",
    );
    assert!(luminance(&b.js(bg)) < 0.1, "dark: {}", b.js(bg));
    let dark = b.js(contrast);
    assert_eq!(
        (dark[0].clone(), dark[1].clone()),
        (json!("solid"), json!("dashed"))
    );
    assert!(
        (luminance(&dark[2]) - luminance(&dark[3])).abs() > 0.25,
        "{dark}"
    );
    b.reload();
    b.wait(
        "the dark theme remembered",
        T,
        "return document.documentElement.dataset.theme === 'dark' && !!document.querySelector('[data-dro]');",
    );
    b.screenshot("machine-dark");
    // Back to light for the rest; a system in dark mode gives a dark page with no choice made.
    b.click("#theme-switch");
    let system = Browser::start_with(&["--force-dark-mode"]);
    system.goto(&s.base);
    system.wait(
        "the overview",
        T,
        "return !!document.querySelector('[data-machine]');",
    );
    assert_eq!(
        system.js("return [matchMedia('(prefers-color-scheme: dark)').matches, document.documentElement.dataset.theme || null];"),
        json!([true, null])
    );
    assert!(luminance(&system.js(bg)) < 0.1);
    drop(system);

    // Units: 25.4 mm is shown as 1.0000 in once switched, and stays so.
    s.jog(1, "X", 25.4).expect(200);
    s.wait_status(1, T, "idle at X 25.4", |st| st["state"] == "idle");
    b.wait(
        "X 25.400",
        T,
        "return document.querySelector('[data-dro=\"x\"]').textContent === '25.400';",
    );
    b.click("#units-switch");
    b.wait(
        "X in inches",
        T,
        "return document.querySelector('[data-dro=\"x\"]').textContent === '1.0000';",
    );
    b.reload();
    assert_eq!(dro(&b, "x"), "1.0000");
    // The switch re-renders on its next frame: wait for it rather than read at once.
    b.click("#units-switch");
    b.wait(
        "X back in mm",
        T,
        "return document.querySelector('[data-dro=\"x\"]').textContent === '25.400';",
    );

    // An inch program: its analysis at a fixed resolution (610 mm/min, not 609.5999999999999),
    // and it says it is in inches.
    let job = s.upload(
        1,
        "inch",
        std::fs::read(corpus("cncjs-circle-inch.gcode")).unwrap(),
    );
    let feed = job["analysis"]["max_feed_mm_min"].as_f64().unwrap();
    b.goto(&format!("{}/#/jobs/{}", s.base, job["id"]));
    let analysis = b.wait_text("#analysis", T);
    assert!(analysis.contains("inch program"), "{analysis}");
    assert!(
        analysis.contains(&format!("{} mm/min", feed.round() as i64)),
        "feed {feed}: {analysis}"
    );
    let length = b.js(
        "const r = [...document.querySelectorAll('#analysis tr')].find(r => r.textContent.startsWith('Cutting length')); \
         return r.querySelector('td').textContent;",
    );
    assert!(
        length.as_str().is_some_and(
            |t| t.ends_with(" mm") && t.split('.').nth(1).is_some_and(|f| f.len() == 4)
        ),
        "one decimal: {length}"
    );

    // MDI history: ↑ brings back the lines sent, newest first; ↓ goes forward again; kept per
    // machine in this browser.
    b.goto(&format!("{}/#/machines/1", s.base));
    for line in ["G91 G0 Z1", "G91 G0 Z-1"] {
        b.type_into("#mdi", line);
        b.click("form:has(#mdi) button[type=submit]");
        b.wait(
            "the MDI line sent",
            T,
            "return document.querySelector('#mdi').value === '';",
        );
        s.wait_status(1, T, "idle after the MDI", |st| st["state"] == "idle");
        b.wait_enabled("form:has(#mdi) button[type=submit]", T);
    }
    b.reload();
    b.wait_text("#mdi", T);
    let key = |k: &str| {
        b.js(&format!(
            "const i = document.querySelector('#mdi'); i.focus(); \
             i.dispatchEvent(new KeyboardEvent('keydown', {{key: '{k}', bubbles: true}})); return i.value;"
        ))
    };
    assert_eq!(key("ArrowUp"), json!("G91 G0 Z-1"));
    assert_eq!(key("ArrowUp"), json!("G91 G0 Z1"));
    assert_eq!(key("ArrowUp"), json!("G91 G0 Z1"), "the oldest stays");
    assert_eq!(key("ArrowDown"), json!("G91 G0 Z-1"));
    assert_eq!(key("ArrowDown"), json!(""), "back to what was typed");
}

/// Issue 27: the program listing's window of lines (`GET /jobs/{id}/gcode?from_line=&lines=`)
/// is those lines of the stored program, anywhere in a long one; bad windows are refused.
#[test]
fn a_window_of_a_programs_lines_is_served() {
    let s = Server::start();
    let m = s.sim("mill", 0.0);
    let program = fresa_tests::back_and_forth(5000, 2.0, 600.0);
    let job = s.upload(m.id, "window", program.clone())["id"]
        .as_i64()
        .unwrap();
    let lines: Vec<&str> = program.lines().collect();
    for (from, n) in [(1, 5), (1024, 3), (4990, 20)] {
        let r = s.get(&format!(
            "/api/v1/jobs/{job}/gcode?from_line={from}&lines={n}"
        ));
        assert_eq!(r.status, 200, "{}", r.text);
        let want: String = lines[from - 1..]
            .iter()
            .take(n)
            .map(|l| format!("{l}\n"))
            .collect();
        assert_eq!(r.text, want, "from {from}");
    }
    assert_eq!(
        s.get(&format!("/api/v1/jobs/{job}/gcode?from_line=6000&lines=5"))
            .text,
        ""
    );
    s.get(&format!("/api/v1/jobs/{job}/gcode?from_line=0"))
        .expect_error(400, "invalid_query");
    s.get(&format!("/api/v1/jobs/{job}/gcode?from_line=1&lines=501"))
        .expect_error(400, "invalid_query");
    s.get(&format!("/api/v1/jobs/{job}/gcode?bogus=1"))
        .expect_error(400, "invalid_query");
    // Without a window: the whole program, as before.
    assert_eq!(s.get(&format!("/api/v1/jobs/{job}/gcode")).text, program);
}

/// Issue 28: the machine page's queue banner says which part waits for its confirm, and its
/// button starts that part; the banner follows the queue to the next part.
#[test]
fn the_queue_banner_says_which_part_waits_and_its_button_starts_it() {
    let s = Server::start();
    let m = s.sim("mill", 0.0);
    let job = s.upload(m.id, "bracket", "G21 G90\nG0 X1\nG0 X2\n")["id"]
        .as_i64()
        .unwrap();
    s.post(
        &format!("/api/v1/machines/{}/queue", m.id),
        &json!({"job": job, "count": 2}),
    )
    .expect(200);
    let b = Browser::start();
    b.goto(&format!("{}/#/machines/{}", s.base, m.id));
    let banner = |part: &str| {
        b.wait(
            &format!("the banner for part {part}"),
            T,
            &format!(
                "const e = document.querySelector('#queue-banner'); \
                 const t = document.querySelector('#queue-text'); \
                 return e && !e.hidden && t.textContent.includes('part {part} of 2') \
                   ? t.textContent : null;"
            ),
        )
    };
    banner("1");
    assert!(m.executed().is_empty(), "nothing ran before the confirm");
    b.screenshot("queue-banner");
    b.wait_enabled("#queue-confirm", T);
    b.click("#queue-confirm");
    banner("2");
    let runs: std::collections::BTreeSet<i64> = m.executed().iter().map(|e| e.0).collect();
    assert_eq!(runs.len(), 1, "the confirmed part ran, once: {runs:?}");
}

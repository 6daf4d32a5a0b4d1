//! The web console at `/`: its files (types, caching, gzip, the guard), the toolpath endpoint,
//! and what an operator does in it, driven in a real headless Chromium against a real
//! `fresa serve --demo`. Screenshots of every page go to `target/console-screenshots/`.

#![allow(clippy::unwrap_used, clippy::expect_used)]

#[path = "../support/browser.rs"]
mod browser;

use browser::Browser;
use fresa_tests::serde_json::json;
use fresa_tests::{corpus, wait_for, Opts, Server};
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

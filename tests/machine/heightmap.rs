//! Height maps over the REST API, on sim machines whose probe switch is an uneven surface
//! (`slope_x`, `slope_y`, `slope_xy`): the heights a grid stores, a job run with a map (its
//! executed Z, from the sim's own execution log, follows the surface), what is refused before
//! anything moves, STOP during a grid, and a map kept across a restart.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::serde_json::{json, Value};
use fresa_tests::{Server, Sim};
use std::time::Duration;

const T: Duration = Duration::from_secs(60);

/// The surface under the probe, machine coordinates: a tilt and a twist (bilinear, so a
/// map's bilinear interpolation reproduces it exactly between its points).
fn surface(x: f64, y: f64) -> f64 {
    -1.0 + 0.01 * x - 0.02 * y + 0.001 * x * y
}

/// A sim machine with the surface under its probe and a travel of X -5..40, Y -5..20,
/// Z -10..10.
fn mapped_sim(s: &Server, name: &str, time_scale: f64) -> Sim {
    let log = s.data_dir().join(format!("exec-{name}.log"));
    let id = s.create_machine(&json!({
        "name": name,
        "backend": "sim-machine",
        "max_jog_mm": 60.0,
        "max_probe_feed_mm_min": 1500.0,
        "config": {
            "time_scale": time_scale,
            "execution_log": s.host_path(&log),
            "travel": {"x": [-5, 40], "y": [-5, 20], "z": [-10, 10]},
            "switches": {"probe": {"axis": "z", "at_or_below": -1,
                                   "slope_x": 0.01, "slope_y": -0.02, "slope_xy": 0.001}},
        },
    }));
    s.wait_machine_state(id, "idle", T);
    Sim { id, log }
}

/// The grid of these tests: X 0..20 (3 points), Y 0..10 (3 points), from Z 2 down 5 mm.
fn grid() -> Value {
    json!({"x0": 0, "x1": 20, "y0": 0, "y1": 10, "nx": 3, "ny": 3,
           "clearance": 2, "distance": 5, "feed": 600})
}

fn start_grid(s: &Server, m: i64, body: &Value) -> i64 {
    let r = s
        .post(&format!("/api/v1/machines/{m}/height-maps"), body)
        .expect(202);
    assert_eq!(r["state"], "probing", "{r}");
    r["id"].as_i64().unwrap()
}

fn map_of(s: &Server, m: i64, hid: i64) -> Value {
    s.get(&format!("/api/v1/machines/{m}/height-maps/{hid}"))
        .expect(200)
}

fn wait_map_end(s: &Server, m: i64, hid: i64) -> Value {
    fresa_tests::wait_for(T, &format!("height map {hid} to end"), || {
        let v = map_of(s, m, hid);
        (v["state"] != "probing").then_some(v)
    })
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() < 1e-6
}

/// The heights of a complete grid match the surface at every point (the sim latches the trip
/// at the surface itself, so within one motion step means exactly here), with the range and
/// who made it; the progress and the end are events. While it probes, another grid and a job
/// are refused; a grid leaving the travel or too fine is refused before anything moves.
#[test]
fn a_grid_on_a_tilted_surface_stores_the_surface_heights() {
    let s = Server::start();
    let m = mapped_sim(&s, "leveller", 0.1);
    let events = s.events("types=height_map.progress,height_map.ended", None);
    let maps = format!("/api/v1/machines/{}/height-maps", m.id);
    // Refused before anything moves (the tool stays at 0, 0, 0).
    for (patch, status, code) in [
        (json!({"x1": 50}), 422, "out_of_travel"),
        (json!({"nx": 51}), 422, "invalid_field"),
        (json!({"x1": -1}), 422, "invalid_field"),
        (json!({"distance": 61}), 422, "probe_too_far"),
        (json!({"feed": 2000}), 422, "feed_out_of_range"),
    ] {
        let mut body = grid();
        for (k, v) in patch.as_object().unwrap() {
            body[k] = v.clone();
        }
        s.post(&maps, &body).expect_error(status, code);
    }
    let st = s.status(m.id);
    assert_eq!(
        st["machine_position"],
        json!({"x": 0.0, "y": 0.0, "z": 0.0, "a": 0.0})
    );
    assert_eq!(s.get(&maps).expect(200), json!([]), "nothing stored");

    let hid = start_grid(&s, m.id, &grid());
    // One grid at a time, and no job while it probes.
    s.post(&maps, &grid()).expect_error(409, "machine_busy");
    let job = s.upload(m.id, "cut.nc", "G0 X1\n")["id"].as_i64().unwrap();
    s.job_action(job, "start").expect_error(409, "machine_busy");

    let map = wait_map_end(&s, m.id, hid);
    assert_eq!(map["state"], "complete", "{map}");
    assert_eq!(map["probed"], 9, "{map}");
    let points = map["points"].as_array().unwrap();
    for j in 0..3 {
        for i in 0..3 {
            let (x, y) = (10.0 * f64::from(i), 5.0 * f64::from(j));
            let z = points[(j * 3 + i) as usize].as_f64().unwrap();
            assert!(
                close(z, surface(x, y)),
                "({i}, {j}): {z} != {}",
                surface(x, y)
            );
        }
    }
    let (lo, hi) = (map["min"].as_f64().unwrap(), map["max"].as_f64().unwrap());
    assert!(
        close(lo, surface(0.0, 10.0)) && close(hi, surface(20.0, 0.0)),
        "{map}"
    );
    assert_eq!(map["created_by"], "local");
    assert!(map["finished_at"].is_i64(), "{map}");
    // It ended over the last point of its serpentine (row 2 forward: X 20, Y 10), at Z 2.
    let st = s.wait_machine_state(m.id, "idle", T);
    let at = &st["work_position"];
    assert!(close(at["x"].as_f64().unwrap(), 20.0) && close(at["y"].as_f64().unwrap(), 10.0));
    assert!(close(at["z"].as_f64().unwrap(), 2.0), "{st}");
    // A progress event per point, then the end (audit, with who).
    let seen = events.until(T, "height_map.ended", |e| e.event == "height_map.ended");
    let progress: Vec<&Value> = seen
        .iter()
        .filter(|e| e.event == "height_map.progress")
        .map(|e| &e.data["data"])
        .collect();
    assert_eq!(progress.len(), 9, "{progress:?}");
    assert_eq!(progress[8]["done"], 9);
    assert_eq!(progress[8]["total"], 9);
    let end = seen.last().unwrap();
    assert!(end.id.is_some(), "persisted");
    assert_eq!(end.data["data"]["state"], "complete");
    assert_eq!(end.data["data"]["map"], hid);
    assert_eq!(end.data["actor"], "local");
    // Listed, newest first.
    let list = s.get(&maps).expect(200);
    assert_eq!(list[0]["id"], hid, "{list}");
}

/// A map survives a restart, and a job run with it cuts along the surface: the executed Z at
/// the end of each line (the sim's own record) is the programmed Z plus the surface's height
/// there, at probed points and between them. The run records the map; the fit shows the
/// correction range over the program's area.
#[test]
fn a_job_run_with_a_map_kept_across_a_restart_follows_the_surface() {
    let mut s = Server::start();
    let m = mapped_sim(&s, "router", 0.0);
    let hid = start_grid(&s, m.id, &grid());
    let before = wait_map_end(&s, m.id, hid);
    assert_eq!(before["state"], "complete", "{before}");
    s.terminate();
    s.spawn().unwrap();
    s.wait_machine_state(m.id, "idle", T);
    let after = map_of(&s, m.id, hid);
    assert_eq!(after, before, "the same map after a restart");

    let program = "G21 G90\nG0 Z3\nG0 X0 Y0\nG1 Z-0.2 F600\nG1 X5 Y2.5\nG1 X10 Y5\n\
                   G1 X15 Y7.5 Z-0.3\nG1 X20 Y10\nG1 X20 Y0\nG1 X0 Y10\nG0 Z3\nM2\n";
    // Where each line ends, in program coordinates (the work zero is the machine's; line 2
    // rises where the tool is: the restarted sim starts at its origin).
    let here = s.status(m.id)["work_position"].clone();
    let (hx, hy) = (here["x"].as_f64().unwrap(), here["y"].as_f64().unwrap());
    let ends: [(i64, [f64; 3]); 10] = [
        (2, [hx, hy, 3.0]),
        (3, [0.0, 0.0, 3.0]),
        (4, [0.0, 0.0, -0.2]),
        (5, [5.0, 2.5, -0.2]),
        (6, [10.0, 5.0, -0.2]),
        (7, [15.0, 7.5, -0.3]),
        (8, [20.0, 10.0, -0.3]),
        (9, [20.0, 0.0, -0.3]),
        (10, [0.0, 10.0, -0.3]),
        (11, [0.0, 10.0, 3.0]),
    ];
    let up = s.upload(m.id, "pcb.nc", program);
    let job = up["id"].as_i64().unwrap();
    let fit = s
        .get(&format!(
            "/api/v1/machines/{}/height-maps/{hid}/fit?job={job}",
            m.id
        ))
        .expect(200);
    assert_eq!(fit["fits"], true, "{fit}");
    assert_eq!(fit["program_area"], json!([0.0, 20.0, 0.0, 10.0]), "{fit}");
    assert!(
        close(fit["correction_min"].as_f64().unwrap(), surface(0.0, 10.0)),
        "{fit}"
    );
    assert!(
        close(fit["correction_max"].as_f64().unwrap(), surface(20.0, 0.0)),
        "{fit}"
    );

    let started = s
        .post(
            &format!("/api/v1/jobs/{job}/start"),
            &json!({"height_map": hid}),
        )
        .expect(200);
    let run = started["run"]["id"].as_i64().unwrap();
    assert_eq!(started["run"]["height_map_id"], hid, "{started}");
    s.wait_job_state(job, "completed", T);
    fresa_tests::assert_every_line_once(&m.executed(), run, 12);
    let logged = m.line_positions(run);
    for (line, [x, y, z]) in ends {
        let (_, pos) = logged
            .iter()
            .find(|(l, _)| *l == line)
            .unwrap_or_else(|| panic!("line {line} not logged with a position: {logged:?}"));
        assert!(close(pos[0], x) && close(pos[1], y), "line {line}: {pos:?}");
        let want = z + surface(x, y);
        assert!(
            close(pos[2], want),
            "line {line} at X{x} Y{y}: executed Z {} != programmed {z} + surface {}",
            pos[2],
            surface(x, y)
        );
    }
    // The job shows the map its run used.
    assert_eq!(s.job(job)["run"]["height_map_id"], hid);
    // Without the map the same program cuts flat (Z as programmed).
    let plain = s
        .post_empty(&format!("/api/v1/jobs/{job}/start"))
        .expect(200);
    let run2 = plain["run"]["id"].as_i64().unwrap();
    assert!(plain["run"]["height_map_id"].is_null(), "{plain}");
    s.wait_job_state(job, "completed", T);
    let flat = m.line_positions(run2);
    let (_, p6) = flat.iter().find(|(l, _)| *l == 6).unwrap();
    assert!(close(p6[2], -0.2), "{p6:?}");
}

/// Refused before anything moves: a program whose cutting moves leave the map's area (the
/// answer names the overhang), a map that is not complete, one of another machine, one that
/// does not exist. No run is created and the machine stays where it is.
#[test]
fn a_job_that_leaves_the_map_is_refused_before_anything_moves() {
    let s = Server::start();
    let m = mapped_sim(&s, "small", 0.0);
    let hid = start_grid(&s, m.id, &grid());
    assert_eq!(wait_map_end(&s, m.id, hid)["state"], "complete");
    let st = s.status(m.id);
    let job = s.upload(m.id, "wide.nc", "G0 Z3\nG1 Z-0.1 F300\nG1 X25 Y5\nG0 Z3\n")["id"]
        .as_i64()
        .unwrap();
    let fit = s
        .get(&format!(
            "/api/v1/machines/{}/height-maps/{hid}/fit?job={job}",
            m.id
        ))
        .expect(200);
    assert_eq!(fit["fits"], false, "{fit}");
    let start = format!("/api/v1/jobs/{job}/start");
    let msg = s
        .post(&start, &json!({"height_map": hid}))
        .expect_error(422, "outside_height_map");
    assert!(
        msg.contains("X 25.000 is 5.000 mm past the map's edge X 20.000"),
        "{msg}"
    );
    s.post(&start, &json!({"height_map": 999}))
        .expect_error(404, "unknown_height_map");
    s.post(&start, &json!({"height_mapp": hid}))
        .expect_error(400, "invalid_json");
    // Another machine's map is not this job's.
    let other = mapped_sim(&s, "other", 0.0);
    let theirs = start_grid(&s, other.id, &grid());
    wait_map_end(&s, other.id, theirs);
    s.post(&start, &json!({"height_map": theirs}))
        .expect_error(404, "unknown_height_map");
    assert_eq!(s.job(job)["state"], "ready", "no run was created");
    assert_eq!(s.status(m.id)["machine_position"], st["machine_position"]);
    assert!(m.executed().is_empty());
}

/// STOP during a grid ends it `stopped` once motion ended: what was probed is kept, the rest
/// is null, and no grid move (jog or probe) is recorded after its end. A stopped map is never
/// applied; deleting it is recorded.
#[test]
fn stop_during_a_grid_ends_it_and_nothing_moves_after() {
    let s = Server::start();
    let m = mapped_sim(&s, "stopped", 1.0);
    let events = s.events("types=height_map.progress", None);
    let hid = start_grid(&s, m.id, &grid());
    events.until(T, "the first point", |e| e.data["data"]["done"] == 1);
    s.command(m.id, "stop", json!({})).expect(200);
    let map = wait_map_end(&s, m.id, hid);
    assert_eq!(map["state"], "stopped", "{map}");
    let probed = map["probed"].as_u64().unwrap();
    assert!((1..9).contains(&probed), "{map}");
    assert!(
        close(map["points"][0].as_f64().unwrap(), surface(0.0, 0.0)),
        "{map}"
    );
    assert!(map["points"][8].is_null(), "{map}");
    assert!(
        map["message"]
            .as_str()
            .unwrap_or_default()
            .contains("stopped"),
        "{map}"
    );
    let st = s.wait_machine_state(m.id, "idle", T);
    // The audit log: nothing the grid sends moves after its end.
    let log = s.events(
        "types=height_map.ended,machine.jog,machine.probe,machine.command",
        Some(0),
    );
    let seen = log.until(T, "the end of the grid", |e| e.event == "height_map.ended");
    let end_id = seen.last().unwrap().id.unwrap();
    assert_eq!(seen.last().unwrap().data["data"]["state"], "stopped");
    assert!(seen.iter().any(|e| e.event == "machine.probe"), "it probed");
    // Every event recorded up to now (a sync point: the next one comes from this request).
    s.command(m.id, "reset", json!({})).expect(200);
    let later = log.until(T, "the reset", |e| {
        e.event == "machine.command" && e.data["data"]["command"] == "reset"
    });
    let moved: Vec<_> = seen
        .iter()
        .chain(&later)
        .filter(|e| e.event != "machine.command" && e.id.unwrap_or(0) > end_id)
        .map(|e| (e.event.clone(), e.data["data"].clone()))
        .collect();
    assert!(moved.is_empty(), "grid moves after its end: {moved:?}");
    assert_eq!(
        s.status(m.id)["machine_position"],
        st["machine_position"],
        "the tool stayed where the stop left it"
    );
    // Never applied; deleted (and recorded).
    let job = s.upload(m.id, "cut.nc", "G1 X1 Y1 Z-0.1 F100\n")["id"]
        .as_i64()
        .unwrap();
    s.post(
        &format!("/api/v1/jobs/{job}/start"),
        &json!({"height_map": hid}),
    )
    .expect_error(409, "height_map_incomplete");
    let maps = format!("/api/v1/machines/{}/height-maps", m.id);
    let r = s.send(s.req(reqwest::Method::DELETE, &format!("{maps}/{hid}")));
    assert_eq!(r.status, 204, "{}", r.text);
    s.get(&format!("{maps}/{hid}"))
        .expect_error(404, "unknown_height_map");
    let del = s.events("types=height_map.deleted", Some(0));
    let d = del.until(T, "height_map.deleted", |e| e.event == "height_map.deleted");
    assert_eq!(d.last().unwrap().data["data"]["map"], hid);
}

/// A probe that runs its whole distance without touching fails the map, naming the point;
/// the points before it are kept.
#[test]
fn a_probe_that_never_touches_fails_the_map_naming_the_point() {
    let s = Server::start();
    let m = mapped_sim(&s, "short", 0.0);
    // From Z 2 down 2.9 mm reaches Z -0.9; the surface at the first point (X 0, Y 0) is at
    // Z -1, below that.
    let mut body = grid();
    body["distance"] = json!(2.9);
    let hid = start_grid(&s, m.id, &body);
    let map = wait_map_end(&s, m.id, hid);
    assert_eq!(map["state"], "failed", "{map}");
    let msg = map["message"].as_str().unwrap();
    assert!(
        msg.starts_with("probe_not_tripped: point (0, 0) at X0.000 Y0.000"),
        "{msg}"
    );
    assert_eq!(map["probed"], 0, "{map}");
    // It stopped where the probe ended (2.9 mm below the clearance), nothing after.
    let st = s.wait_machine_state(m.id, "idle", T);
    assert!(
        close(st["work_position"]["z"].as_f64().unwrap(), -0.9),
        "{st}"
    );
}

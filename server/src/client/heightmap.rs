//! `fresa machine height-map`: probe a grid and follow it to its end (issue 25).

use super::{follow_events, unreachable, Client, Res};
use clap::Args;
use serde_json::{json, Value};

/// The grid of `fresa machine height-map` (`POST /api/v1/machines/{id}/height-maps`).
#[derive(Args)]
pub struct GridArgs {
    /// The area, work X/Y, mm.
    #[arg(long, allow_hyphen_values = true)]
    x0: f64,
    #[arg(long, allow_hyphen_values = true)]
    x1: f64,
    #[arg(long, allow_hyphen_values = true)]
    y0: f64,
    #[arg(long, allow_hyphen_values = true)]
    y1: f64,
    /// Points along X and along Y (2 to 50).
    #[arg(long)]
    nx: u32,
    #[arg(long)]
    ny: u32,
    /// Work Z to travel at and probe down from.
    #[arg(long, default_value_t = 2.0, allow_hyphen_values = true)]
    clearance: f64,
    /// How far below the clearance each probe goes at most, mm.
    #[arg(long, default_value_t = 5.0)]
    distance: f64,
    /// Probing feed, mm/min.
    #[arg(long, default_value_t = 100.0)]
    feed: f64,
    /// Feed of the moves between points, mm/min (the machine's jog feed by default).
    #[arg(long)]
    travel_feed: Option<f64>,
    /// Print the finished map as JSON instead of a table.
    #[arg(long)]
    json: bool,
}

pub(super) async fn probe(c: &Client, id: i64, g: GridArgs) -> Res {
    // Subscribe first, so no point's progress falls between the start and the stream.
    let events = c
        .req(reqwest::Method::GET, "/api/v1/events")
        .query(&[
            ("types", "height_map.progress,height_map.ended"),
            ("machine", &id.to_string()),
        ])
        .send()
        .await
        .map_err(|e| unreachable(&c.base, e))?;
    if !events.status().is_success() {
        return Err(format!("events: {}", events.status()).into());
    }
    let mut body = json!({"x0": g.x0, "x1": g.x1, "y0": g.y0, "y1": g.y1, "nx": g.nx,
                          "ny": g.ny, "clearance": g.clearance, "distance": g.distance,
                          "feed": g.feed});
    if let Some(f) = g.travel_feed {
        body["travel_feed"] = f.into();
    }
    let started = c
        .send(
            c.req(
                reqwest::Method::POST,
                &format!("/api/v1/machines/{id}/height-maps"),
            )
            .json(&body),
        )
        .await?;
    let map = started["id"]
        .as_i64()
        .ok_or("server answered without a height map id")?;
    eprintln!(
        "machine {id}: probing height map {map}, {} x {} points",
        g.nx, g.ny
    );
    let ended = follow_events(events, |ev| {
        let d = &ev["data"];
        if d["map"].as_i64() != Some(map) {
            return true;
        }
        match ev["type"].as_str() {
            Some("height_map.progress") => {
                eprintln!(
                    "  {}/{}  X{:.3} Y{:.3}  Z {:.4}",
                    d["done"],
                    d["total"],
                    d["x"].as_f64().unwrap_or_default(),
                    d["y"].as_f64().unwrap_or_default(),
                    d["z"].as_f64().unwrap_or_default()
                );
                true
            }
            Some("height_map.ended") => false,
            _ => true,
        }
    })
    .await?;
    if !ended {
        return Err("the server closed the event stream before the grid ended".into());
    }
    let v = c
        .send(c.req(
            reqwest::Method::GET,
            &format!("/api/v1/machines/{id}/height-maps/{map}"),
        ))
        .await?;
    if g.json {
        println!("{v}");
    } else {
        print!("{}", table(&v));
    }
    match v["state"].as_str() {
        Some("complete") => Ok(()),
        other => Err(format!(
            "height map {map} ended {}: {}",
            other.unwrap_or("?"),
            v["message"].as_str().unwrap_or("no reason given")
        )
        .into()),
    }
}

/// The heights as a table: rows from the highest Y down (as on a drawing), X across.
fn table(v: &Value) -> String {
    let (nx, ny) = (
        v["nx"].as_u64().unwrap_or(0) as usize,
        v["ny"].as_u64().unwrap_or(0) as usize,
    );
    let at = |k: &str| v[k].as_f64().unwrap_or_default();
    let coord =
        |lo: f64, hi: f64, n: usize, i: usize| lo + (hi - lo) * i as f64 / (n.max(2) - 1) as f64;
    let points = v["points"].as_array().cloned().unwrap_or_default();
    let mut out = format!(
        "height map {} ({}): {} of {} points, Z {} .. {}\n",
        v["id"],
        v["state"].as_str().unwrap_or("?"),
        v["probed"],
        nx * ny,
        v["min"],
        v["max"]
    );
    out.push_str(&format!("{:>10}", "Y \\ X"));
    for i in 0..nx {
        out.push_str(&format!("{:>10.3}", coord(at("x0"), at("x1"), nx, i)));
    }
    out.push('\n');
    for j in (0..ny).rev() {
        out.push_str(&format!("{:>10.3}", coord(at("y0"), at("y1"), ny, j)));
        for i in 0..nx {
            match points.get(j * nx + i).and_then(Value::as_f64) {
                Some(z) => out.push_str(&format!("{z:>10.4}")),
                None => out.push_str(&format!("{:>10}", "-")),
            }
        }
        out.push('\n');
    }
    out
}

//! `fresa parts` and `fresa report utilisation` (issue 28, part 2): the shop's records as a
//! table, JSON or CSV (the server's own CSV, `Accept: text/csv`).

use super::{columns, Client, Res};
use clap::{Args, Subcommand};
use serde_json::Value;

/// `fresa parts`: `GET /api/v1/parts`.
#[derive(Args)]
pub struct PartsArgs {
    /// Only this job's parts.
    #[arg(long)]
    job: Option<i64>,
    /// Only this machine's parts.
    #[arg(long)]
    machine: Option<i64>,
    /// Ended at or after: YYYY-MM-DD, YYYY-MM-DDTHH:MM:SSZ or Unix ms (UTC).
    #[arg(long)]
    from: Option<String>,
    /// Ended before (same forms).
    #[arg(long)]
    to: Option<String>,
    /// At most this many, newest first (1..1000).
    #[arg(long, default_value_t = 100)]
    limit: i64,
    /// Print the server's CSV.
    #[arg(long, conflicts_with = "json")]
    csv: bool,
    /// Print the JSON page.
    #[arg(long)]
    json: bool,
}

#[derive(Subcommand)]
pub enum ReportCmd {
    /// Seconds per machine, day and state (cutting, idle, held, alarm, unresponsive,
    /// offline): `GET /api/v1/reports/utilisation`.
    Utilisation {
        /// From (default: 7 days ago): YYYY-MM-DD, YYYY-MM-DDTHH:MM:SSZ or Unix ms (UTC).
        #[arg(long)]
        from: Option<String>,
        /// To (default: now).
        #[arg(long)]
        to: Option<String>,
        /// Print the server's CSV.
        #[arg(long, conflicts_with = "json")]
        csv: bool,
        /// Print the JSON report.
        #[arg(long)]
        json: bool,
    },
}

fn query(pairs: &[(&str, Option<String>)]) -> String {
    let q: Vec<String> = pairs
        .iter()
        .filter_map(|(k, v)| v.as_ref().map(|v| format!("{k}={}", percent_encode(v))))
        .collect();
    if q.is_empty() {
        String::new()
    } else {
        format!("?{}", q.join("&"))
    }
}

fn percent_encode(s: &str) -> String {
    s.bytes()
        .map(|b| {
            if b.is_ascii_alphanumeric() || b"-._~".contains(&b) {
                (b as char).to_string()
            } else {
                format!("%{b:02X}")
            }
        })
        .collect()
}

async fn get_csv(c: &Client, path: &str) -> Result<String, Box<dyn std::error::Error>> {
    let resp = c
        .req(reqwest::Method::GET, path)
        .header("accept", "text/csv")
        .send()
        .await
        .map_err(|e| super::unreachable(&c.base, e))?;
    let status = resp.status();
    let text = resp.text().await?;
    if !status.is_success() {
        let body: Value = serde_json::from_str(&text).unwrap_or(Value::Null);
        let msg = body["message"].as_str().unwrap_or("request failed");
        let code = body["code"].as_str().unwrap_or("");
        return Err(format!("{status} {code}: {msg}").into());
    }
    Ok(text)
}

pub async fn parts(c: Client, a: PartsArgs) -> Res {
    let path = format!(
        "/api/v1/parts{}",
        query(&[
            ("job", a.job.map(|v| v.to_string())),
            ("machine", a.machine.map(|v| v.to_string())),
            ("from", a.from),
            ("to", a.to),
            ("limit", Some(a.limit.to_string())),
        ])
    );
    if a.csv {
        print!("{}", get_csv(&c, &path).await?);
        return Ok(());
    }
    let page = c.send(c.req(reqwest::Method::GET, &path)).await?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&page)?);
        return Ok(());
    }
    let mut rows = vec![[
        "RUN".to_string(),
        "JOB".into(),
        "MACHINE".into(),
        "PROGRAM".into(),
        "OUTCOME".into(),
        "LINES".into(),
        "ESTIMATE".into(),
        "ACTUAL".into(),
        "ENDED".into(),
        "OPERATORS".into(),
    ]];
    let secs = |v: &Value| v.as_f64().map_or("-".to_string(), |s| format!("{s:.1}s"));
    for p in page["parts"].as_array().into_iter().flatten() {
        rows.push([
            p["run"].to_string(),
            p["job"].to_string(),
            p["machine_name"].as_str().unwrap_or("").to_string(),
            p["program_name"].as_str().unwrap_or("").to_string(),
            p["outcome"].as_str().unwrap_or("").to_string(),
            format!("{}/{}", p["lines_run"], p["line_count"]),
            secs(&p["estimate_s"]),
            secs(&p["actual_s"]),
            p["ended_at"]
                .as_i64()
                .map_or(String::new(), |t| fresa_core::store::utc_text(t, false)),
            p["operators"]
                .as_array()
                .map(|o| {
                    o.iter()
                        .filter_map(Value::as_str)
                        .collect::<Vec<_>>()
                        .join(",")
                })
                .unwrap_or_default(),
        ]);
    }
    print!("{}", columns(&rows));
    if page.get("next").is_some() {
        eprintln!("(more: narrow with --from/--to or raise --limit)");
    }
    Ok(())
}

pub async fn report(c: Client, cmd: ReportCmd) -> Res {
    let ReportCmd::Utilisation {
        from,
        to,
        csv,
        json,
    } = cmd;
    let path = format!(
        "/api/v1/reports/utilisation{}",
        query(&[("from", from), ("to", to)])
    );
    if csv {
        print!("{}", get_csv(&c, &path).await?);
        return Ok(());
    }
    let r = c.send(c.req(reqwest::Method::GET, &path)).await?;
    if json {
        println!("{}", serde_json::to_string_pretty(&r)?);
        return Ok(());
    }
    let hours = |v: &Value| format!("{:.2}", v.as_f64().unwrap_or(0.0) / 3600.0);
    let mut rows = vec![[
        "MACHINE".to_string(),
        "DAY".into(),
        "CUTTING_H".into(),
        "IDLE_H".into(),
        "HELD_H".into(),
        "ALARM_H".into(),
        "UNRESPONSIVE_H".into(),
        "OFFLINE_H".into(),
    ]];
    for m in r["machines"].as_array().into_iter().flatten() {
        let name = m["name"].as_str().unwrap_or("").to_string();
        let days = m["days"].as_array().into_iter().flatten();
        for d in days.chain(std::iter::once(&m["total"])) {
            let day = d["day"]
                .as_str()
                .filter(|s| !s.is_empty())
                .unwrap_or("total");
            rows.push([
                name.clone(),
                day.to_string(),
                hours(&d["cutting"]),
                hours(&d["idle"]),
                hours(&d["held"]),
                hours(&d["alarm"]),
                hours(&d["unresponsive"]),
                hours(&d["offline"]),
            ]);
        }
    }
    print!("{}", columns(&rows));
    Ok(())
}

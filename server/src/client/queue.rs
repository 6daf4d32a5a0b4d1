//! `fresa queue`: a machine's job queue and dispatch to a free machine (issue 28).

use super::{columns, Client, Res, ServerArgs};
use clap::Subcommand;
use serde_json::{json, Value};

#[derive(Subcommand)]
pub enum QueueCmd {
    /// Add parts of a job to a machine's queue. The first part waits for `confirm`.
    Add {
        /// The machine.
        machine: i64,
        /// A job of that machine.
        #[arg(long)]
        job: i64,
        /// How many parts.
        #[arg(long, default_value_t = 1)]
        count: i64,
        /// Start each part after the first without waiting for a confirm.
        #[arg(long)]
        no_confirm: bool,
    },
    /// Show a machine's queue: its state and entries.
    List {
        machine: i64,
        /// The server's whole answer as JSON.
        #[arg(long)]
        json: bool,
    },
    /// The next part is loaded: start it.
    Confirm { machine: i64 },
    /// End a hold: the next part then waits for a confirm.
    Release { machine: i64 },
    /// Remove an entry.
    Remove { machine: i64, entry: i64 },
    /// Move an entry to a position (1-based).
    Move {
        machine: i64,
        entry: i64,
        #[arg(long)]
        position: i64,
    },
    /// Give one part of a job to the first free machine of a list.
    Dispatch {
        /// The job.
        job: i64,
        /// Machines to try, in order.
        #[arg(long, value_delimiter = ',', required = true)]
        machines: Vec<i64>,
    },
}

pub async fn run(server: ServerArgs, cmd: QueueCmd) -> Res {
    let c = Client::new(server);
    let post = reqwest::Method::POST;
    let queue = |m: i64| format!("/api/v1/machines/{m}/queue");
    let v = match cmd {
        QueueCmd::Add {
            machine,
            job,
            count,
            no_confirm,
        } => {
            let body = json!({"job": job, "count": count, "confirm_between": !no_confirm});
            c.send(c.req(post, &queue(machine)).json(&body)).await?
        }
        QueueCmd::List { machine, json } => {
            let v = c.send(c.req(reqwest::Method::GET, &queue(machine))).await?;
            if json {
                println!("{v}");
                return Ok(());
            }
            v
        }
        QueueCmd::Confirm { machine } => {
            let v = c
                .send(c.req(post, &format!("{}/confirm", queue(machine))))
                .await?;
            println!(
                "machine {machine}: job {} started, run {}",
                v["job"], v["run"]
            );
            return Ok(());
        }
        QueueCmd::Release { machine } => {
            c.send(c.req(post, &format!("{}/release", queue(machine))))
                .await?
        }
        QueueCmd::Remove { machine, entry } => {
            c.send(c.req(
                reqwest::Method::DELETE,
                &format!("{}/{entry}", queue(machine)),
            ))
            .await?
        }
        QueueCmd::Move {
            machine,
            entry,
            position,
        } => {
            c.send(
                c.req(post, &format!("{}/{entry}/move", queue(machine)))
                    .json(&json!({"position": position})),
            )
            .await?
        }
        QueueCmd::Dispatch { job, machines } => {
            let v = c
                .send(
                    c.req(post, "/api/v1/queue")
                        .json(&json!({"job": job, "machines": machines})),
                )
                .await?;
            println!(
                "machine {}: job {} started, run {}",
                v["machine"], v["job"], v["run"]
            );
            return Ok(());
        }
    };
    print!("{}", queue_text(&v));
    Ok(())
}

/// The queue as text: its state line, then one row per entry.
fn queue_text(v: &Value) -> String {
    let mut out = format!(
        "machine {}: {}",
        v["machine"],
        v["state"].as_str().unwrap_or("?")
    );
    if let Some(r) = v["reason"].as_str() {
        out.push_str(&format!(" ({r})"));
    }
    if let Some(run) = v["run"].as_i64() {
        out.push_str(&format!(", run {run}"));
    }
    out.push('\n');
    let mut rows = vec![["ENTRY", "JOB", "DONE", "COUNT", "CONFIRM", "STATE"].map(String::from)];
    for e in v["entries"].as_array().into_iter().flatten() {
        rows.push([
            e["id"].to_string(),
            e["job"].to_string(),
            e["done"].to_string(),
            e["count"].to_string(),
            e["confirm_between"].to_string(),
            e["state"].as_str().unwrap_or("").to_string(),
        ]);
    }
    out.push_str(&columns(&rows));
    out
}

//! The machine task's side of a run that goes on from inside its program (a start at a line, a
//! resume after an interruption): the plan (`crate::start_at`) from where the machine stands
//! now, and the load that carries its preamble to the backend, planned again when the backend
//! starts at another line than asked (its execution log shows more done).

use super::actor::Task;
use crate::error::{Error, Result};
use crate::start_at::StartPlan;
use crate::store::{JobRow, RunRow};
use fresa_plugin_api::contract::{AxisValues, ProgramLoaded, Request};
use std::future::Future;
use std::path::Path;
use std::pin::Pin;

/// Where a run is launched from.
pub(super) struct Launch {
    pub start_line: u32,
    /// The plan for `start_line` when it is past the first line (made before the run was
    /// created or reopened, so a refusal leaves it as it was).
    pub plan: Option<StartPlan>,
    /// A resume of a run started from its first line: a backend that cannot carry out a
    /// preamble resumes it as it does itself (from the line, with no approach), as before
    /// preambles existed. A start at a line on such a backend is refused, and so is a resume
    /// of a run started at a line (nothing of it ran: there is nothing to go on with).
    pub resuming: bool,
}

/// Loads at most this many times (a backend that keeps starting later than asked).
const MAX_LOADS: usize = 3;

type Boxed<'a, T> = Pin<Box<dyn Future<Output = Result<T>> + Send + 'a>>;

impl Task {
    /// Plans a start of `job` at `line` from where the machine stands now. Pause and cancel are
    /// served while the program is interpreted (as during an ordinary backend call).
    /// Boxed: serving them goes back through the task's message handling.
    pub(super) fn plan_start<'a>(&'a mut self, job: &'a JobRow, line: u32) -> Boxed<'a, StartPlan> {
        Box::pin(async move {
            let path =
                crate::programs::local_copy(&self.store, &self.programs_dir, &job.sha256).await?;
            let status = self.refresh_status().await?;
            let row = self.row.borrow().clone();
            let setup = crate::start_at::setup(&self.store, &row, &status).await?;
            let work = crate::start_at::plan(path, line, setup);
            let Some(mut urgent) = self.urgent.clone().try_lock_owned().ok() else {
                return work.await;
            };
            tokio::pin!(work);
            let plan = loop {
                tokio::select! {
                    biased;
                    plan = &mut work => break plan,
                    Some(msg) = urgent.recv() => self.handle(msg).await,
                }
            };
            drop(urgent);
            plan
        })
    }

    /// Loads `job`'s program at `path` into the backend for `run` from `from.start_line`, with
    /// the preamble of its plan; plans again for the line the backend answers when that is
    /// another (a preamble leads to one line only).
    pub(super) async fn load_from(
        &mut self,
        job: &JobRow,
        run: &RunRow,
        path: &Path,
        mut from: Launch,
        expected_part_zero: Option<AxisValues>,
        height_map: Option<&fresa_plugin_api::heightmap::HeightMap>,
    ) -> Result<()> {
        // The table the backend interprets with: the one the upload check used, unless it was
        // edited since (then the backend's own check decides).
        let rows = self.store.tools(self.id).await?;
        self.holds.set_tools(&rows);
        let (optional_stop, tool_change) = self.run_options().await?;
        let tools: Vec<_> = rows
            .iter()
            .filter_map(|t| {
                Some(fresa_plugin_api::contract::ProgramTool {
                    tool: u32::try_from(t.tool).ok()?,
                    diameter_mm: t.diameter_mm,
                    length_mm: t.length_mm,
                })
            })
            .collect();
        // A pause meanwhile holds the run before it starts (see `Task::pause`).
        self.loading = Some(run.id);
        let mut preambles = true;
        for _ in 0..MAX_LOADS {
            let wanted = from.start_line > 1 && preambles;
            if wanted && from.plan.as_ref().map(|p| p.from_line) != Some(from.start_line) {
                from.plan = Some(self.plan_start(job, from.start_line).await?);
            }
            let preamble = from
                .plan
                .as_ref()
                .filter(|_| wanted)
                .map(|p| p.preamble.clone());
            let answer = self
                .call(&Request::LoadProgram {
                    run: run.id,
                    path: path.to_string_lossy().into_owned(),
                    start_line: from.start_line,
                    expected_part_zero,
                    tools: tools.clone(),
                    max_segments: Some(self.max_program_segments),
                    preamble: preamble.clone(),
                    optional_stop,
                    tool_change,
                    height_map: height_map.cloned(),
                })
                .await
                // An `unsupported` refusal with a preamble sent is the preamble's (handled
                // below); without one, a mapped program's is the map's.
                .map_err(|e| match preamble {
                    Some(_) => e,
                    None => super::heightmap::refusal(e, height_map.is_some()),
                });
            let answer = match answer {
                Err(e) if preamble.is_some() && unsupported(&e).is_some() => {
                    let why = unsupported(&e).unwrap_or_default().to_string();
                    if !from.resuming {
                        return Err(Error::invalid("unsupported", why));
                    }
                    tracing::warn!(
                        machine = self.id,
                        run = run.id,
                        line = from.start_line,
                        "the backend cannot carry out a start preamble ({why}); it resumes from \
                         the line as it does itself"
                    );
                    preambles = false;
                    continue;
                }
                other => other?,
            };
            // A backend whose answer says nothing of lines (`{}`, as a minimal C plugin may
            // answer) starts where asked and carries out no preamble.
            let loaded = serde_json::from_value::<ProgramLoaded>(answer)
                .unwrap_or_else(|_| ProgramLoaded::new(0, from.start_line));
            // A backend that does not know height maps ignores one: it must not cut
            // uncorrected.
            if height_map.is_some() && !loaded.height_map {
                return Err(super::heightmap::not_confirmed());
            }
            if loaded.start_line != from.start_line {
                tracing::info!(
                    run = run.id,
                    asked = from.start_line,
                    actual = loaded.start_line,
                    "backend resumes later: it had already executed earlier lines"
                );
                from.start_line = loaded.start_line;
                if preambles && loaded.start_line > 1 && loaded.start_line <= loaded.lines {
                    continue;
                }
                return Ok(());
            }
            if preamble.is_some() && !loaded.preamble {
                // A backend built before preambles existed ignores the field.
                let why = "the backend does not carry out a start preamble (it was built \
                           against an older plugin contract)";
                if !from.resuming {
                    return Err(Error::invalid("unsupported", why));
                }
                tracing::warn!(
                    machine = self.id,
                    run = run.id,
                    "{why}; it resumes as it does itself"
                );
            }
            return Ok(());
        }
        Err(Error::conflict(
            "start_line_moved",
            format!(
                "the backend started run {} later than asked {MAX_LOADS} times while it was loaded",
                run.id
            ),
        ))
    }
}

/// The backend's reason when an error is its `unsupported` refusal.
fn unsupported(e: &Error) -> Option<&str> {
    (e.code == "backend_rejected")
        .then(|| e.message.strip_prefix("unsupported: "))
        .flatten()
}

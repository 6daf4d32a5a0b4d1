//! The black-box tests: each starts the real `fresa` binary (and real plugins, simulators,
//! brokers, databases or browsers) and talks to it as its users do. They are one test binary,
//! grouped by feature, so the dependency tree is linked once and `fresa` built once
//! (`fresa_tests`, `lib.rs`, holds the shared helpers).
//!
//! Where a new test goes, by what it is about (not by how it tests it):
//!
//! | module | what its tests are about |
//! |---|---|
//! | `machine::api` | a machine over the REST API: listing, jog, zero, work offsets, part zero, MDI |
//! | `machine::probing` | probing moves and touch-off: the offset set, refusals, STOP and a lost client during a probe |
//! | `machine::heightmap` | height maps: a grid probed and stored, a job run with one, what is refused, STOP during a grid |
//! | `machine::limits` | what is refused before anything moves: soft limits, jog/feed limits, the work a program may cause |
//! | `machine::overrides` | feed, spindle and rapid overrides: their effect on a run, the machine's range, the record |
//! | `machine::tools` | tool tables and cutter compensation with them |
//! | `machine::toolchange` | pauses that say why (M0, M1, feed hold), manual tool changes (M6) and the tool setter |
//! | `machine::io` | inputs and outputs: switches, alarms, `machine.io` |
//! | `jobs::runs` | upload, run to completion, download, pause / resume / cancel of a job |
//! | `jobs::races` | cancel, stop and pause racing a running job: nothing moves after the answer |
//! | `jobs::estimate` | the run-time estimate and the time left against real-time sim runs |
//! | `jobs::chaos` | many clients sending random run control at once: the run state machine holds |
//! | `jobs::resume` | a server killed or stopped mid-job: the run comes back and resumes exactly once |
//! | `jobs::queue` | job queues per machine: parts one after another after each confirm, holds, restarts, dispatch to a free machine |
//! | `jobs::records` | the shop's records: part records, utilisation, maintenance counters and their events |
//! | `jobs::start_at` | start at a line: the preview, the preamble, refusals, a resume through the preamble |
//! | `backends::mach3`, `parport`, `kawasaki`, `wine` | one backend (or the Windows build) end to end against its simulator |
//! | `pendants` | MPG pendants: the plugin, its simulator, keys, wheel, uploads, a lost link |
//! | `server::auth` | tokens and roles |
//! | `server::hardening` | hostile web pages, secrets in logs, loose fields and paths |
//! | `server::bad_input` | refused input names the problem and leaves nothing half-written |
//! | `server::slow_clients` | connection, stream and header limits: STOP always gets through |
//! | `server::lifecycle` | SIGTERM (also while starting and right after ready), SIGHUP, a second server on one data directory, the start's pages unmapped once ready (and the binary's after the API is described) |
//! | `server::faults` | a plugin that hangs or misbehaves |
//! | `store::db_outage` | the database or its disk failing under a running job |
//! | `store::nodes` | several nodes on one PostgreSQL |
//! | `store::retention`, `leftovers` | event pruning; what a crash leaves behind, backups |
//! | `integrations::events`, `webhooks`, `mqtt` | what goes out: SSE, webhooks, the MQTT bridge |
//! | `clients::cli`, `console`, `openapi` | the CLI and the README's curl walk-through, the web console (real Chromium), the OpenAPI description |
//!
//! Run one group with `cargo test -p fresa-tests --test blackbox pendants::` (a module path is a
//! test-name filter).

mod machine {
    mod api;
    mod heightmap;
    mod io;
    mod limits;
    mod overrides;
    mod probing;
    mod toolchange;
    mod tools;
}

mod jobs {
    mod chaos;
    mod estimate;
    mod queue;
    mod races;
    mod records;
    mod resume;
    mod runs;
    mod start_at;
}

mod backends {
    mod kawasaki;
    mod mach3;
    mod parport;
    mod wine;
}

mod pendants;

mod server {
    mod auth;
    mod bad_input;
    mod faults;
    mod hardening;
    mod lifecycle;
    mod slow_clients;
}

mod store {
    mod db_outage;
    mod leftovers;
    mod nodes;
    mod retention;
}

mod integrations {
    mod events;
    mod mqtt;
    mod webhooks;
}

mod clients {
    mod cli;
    mod console;
    mod openapi;
}

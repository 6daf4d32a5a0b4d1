//! Fresa's core: everything the server knows and does, with no HTTP in it.
//!
//! * [`store`]: the SQLite database, one module per concern.
//! * [`machine`]: a task per machine that owns its run lifecycle, and the lanes its backend
//!   calls travel on.
//! * [`programs`]: uploaded programs on disk. [`jobs`]: from a program to a job; run control
//!   goes to the job's machine; [`toolpath`]: a program's path for previews, [`previews`]: their
//!   cache, concurrency bound and cancellation.
//! * [`pendants`]: handwheel pendants; their keys call the same functions the HTTP layer does.
//! * [`events`]: the event bus and audit log. [`plugins`]: the plugin registry.
//! * [`views`]: what the API shows (status, machine, job), the same on HTTP, SSE and MQTT.
//! * [`webhooks`]: webhook registrations; [`integrations`]: what webhook deliveries and the MQTT
//!   bridge (crate `fresa-integrations`) count, for `/metrics`.
//! * [`nodes`]: several nodes on one store: which node drives a machine, heartbeats.
//! * [`admin`]: creating machines and pendants, moving them between nodes, part zeros.
//! * [`queue`]: job queues per machine (parts with a confirm between them) and dispatch.
//! * [`start_at`]: a start at a line (and a resume): the state before it and the preamble.
//! * [`app`]: the whole; `startup`: its start-up and shutdown. [`error`]: the core's errors.

pub mod admin;
pub mod app;
pub mod config;
pub mod datadir;
pub mod demo;
pub mod error;
pub mod events;
pub mod integrations;
pub mod jobs;
pub mod listing;
pub mod machine;
pub mod nodes;
pub mod pendants;
pub mod plugins;
pub mod previews;
pub mod programs;
pub mod queue;
pub mod queue_state;
pub mod records;
pub mod reports;
pub mod run_settings;
pub mod start_at;
mod startup;
pub mod store;
pub mod tool_setter;
pub mod toolpath;
pub mod tools;
pub mod views;
pub mod webhooks;

pub use app::{App, SharedApp};
pub use error::{Error, ErrorKind, Result};
pub use startup::StartError;

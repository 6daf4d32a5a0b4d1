//! Several nodes on one store. Each process is a node with a name; a machine belongs to the node
//! that drives it (the one next to its hardware). Every node lists every machine and job from
//! the store; requests that need a remote machine's task are forwarded by the HTTP layer to its
//! node, found here. Each node writes a heartbeat with its machines' status, so the others show
//! those machines without asking, and `offline` ("node X unreachable since ...") once the
//! heartbeat stops.

use crate::app::{App, SharedApp};
use crate::store::{utc_text, MachineRow, NodeRow};
use fresa_plugin_api::contract::{MachineState, MachineStatus};
use serde::Serialize;
use std::collections::{BTreeMap, HashSet};

/// A node as `GET /api/v1/nodes` shows it.
#[derive(Debug, Clone, Serialize)]
pub struct NodeView {
    pub name: String,
    /// Where the other nodes reach it.
    pub url: String,
    pub version: String,
    /// Milliseconds since the Unix epoch.
    pub started_at: i64,
    pub last_heartbeat: i64,
    /// Whether its heartbeat is recent (within `node_offline_after_ms`).
    pub reachable: bool,
    /// The node answering this request.
    pub this_node: bool,
    /// Ids of the machines it drives.
    pub machines: Vec<i64>,
}

/// Where a machine's requests go.
#[derive(Debug, Clone)]
pub enum Owner {
    /// This node drives it.
    Local,
    /// Another node does.
    Remote(RemoteNode),
    /// No such machine.
    Unknown,
}

#[derive(Debug, Clone)]
pub struct RemoteNode {
    pub name: String,
    /// `None`: the node never registered (its machine was moved to a name no node has yet).
    pub url: Option<String>,
    /// Why it cannot be reached now ("node hall-2 unreachable since ..."); `None` when it can.
    pub down: Option<String>,
}

impl App {
    fn node_is_fresh(&self, row: &NodeRow) -> bool {
        row.age_ms <= self.settings.node.offline_after.as_millis() as i64
    }

    /// Why node `name` (its row, if it ever registered) cannot be reached now; `None` when it
    /// can. The one wording of "unreachable" for status, lists and refused requests.
    fn node_down(&self, name: &str, row: Option<&NodeRow>) -> Option<String> {
        match row {
            None => Some(format!("node {name} has not started yet")),
            Some(r) if !self.node_is_fresh(r) => Some(format!(
                "node {name} unreachable since {} (no heartbeat in the store since then; \
                 check that its fresa service runs and reaches the database)",
                utc_text(r.heartbeat_at, false)
            )),
            Some(_) => None,
        }
    }

    /// Which node drives machine `id`. A machine this node has loaded is local whatever the
    /// store says a moment later (its task ends only once idle).
    pub async fn machine_owner(&self, id: i64) -> crate::Result<Owner> {
        if self.machines.is_local(id) {
            return Ok(Owner::Local);
        }
        let Some(row) = self.store.machine(id).await? else {
            return Ok(Owner::Unknown);
        };
        let name = row.node.unwrap_or_else(|| self.settings.node.name.clone());
        if name == self.settings.node.name {
            return Ok(Owner::Local);
        }
        let node = self.store.node_row(&name).await?;
        Ok(Owner::Remote(RemoteNode {
            down: self.node_down(&name, node.as_ref()),
            url: node.map(|n| n.url),
            name,
        }))
    }

    /// The status of a machine another node drives, as of that node's last heartbeat; offline
    /// with the reason once the node is unreachable.
    pub async fn remote_status(&self, row: &MachineRow) -> MachineStatus {
        let node = match row.node.as_deref() {
            Some(name) => match self.store.node_row(name).await {
                Ok(n) => n,
                Err(e) => return offline(format!("cannot read node {name} from the store: {e}")),
            },
            None => None,
        };
        self.remote_status_from(row, node.as_ref())
    }

    /// [`remote_status`](Self::remote_status) with the node's row already read (a list reads
    /// every node once, not once per machine).
    pub fn remote_status_from(&self, row: &MachineRow, node: Option<&NodeRow>) -> MachineStatus {
        let Some(name) = row.node.as_deref() else {
            return offline("no node drives this machine yet".into());
        };
        if let Some(why) = self.node_down(name, node) {
            return offline(why);
        }
        node.and_then(|n| serde_json::from_str::<BTreeMap<String, MachineStatus>>(&n.machines).ok())
            .and_then(|mut m| m.remove(&row.id.to_string()))
            .unwrap_or_else(|| offline(format!("node {name} does not report this machine")))
    }

    /// Every node in the store, with its machines.
    pub async fn nodes(&self) -> crate::Result<Vec<NodeView>> {
        let rows = self.store.list_nodes().await?;
        let machines = self.store.list_machines().await?;
        Ok(rows
            .into_iter()
            .map(|r| NodeView {
                reachable: r.name == self.settings.node.name || self.node_is_fresh(&r),
                this_node: r.name == self.settings.node.name,
                machines: machines
                    .iter()
                    .filter(|m| m.node.as_deref() == Some(r.name.as_str()))
                    .map(|m| m.id)
                    .collect(),
                name: r.name,
                url: r.url,
                version: r.version,
                started_at: r.started_at,
                last_heartbeat: r.heartbeat_at,
            })
            .collect())
    }
}

/// The URL other nodes use: `node_url` if set, else the bound address (the host name when
/// bound to every address, which no other host can dial).
pub fn url_for(configured: Option<&str>, bound: std::net::SocketAddr) -> String {
    if let Some(u) = configured {
        return u.to_string();
    }
    if bound.ip().is_unspecified() {
        return format!("http://{}:{}", crate::config::host_name(), bound.port());
    }
    format!("http://{bound}")
}

/// Registers this node (with the address it is reachable at, known once bound) and starts its
/// heartbeat, which also picks up machines moved to this node and lets go of machines moved
/// away.
pub async fn start(app: &SharedApp, bound: std::net::SocketAddr) -> crate::Result<Heartbeat> {
    let url = url_for(app.settings.node.url.as_deref(), bound);
    app.store
        .register_node(&app.settings.node.name, &url, env!("CARGO_PKG_VERSION"))
        .await?;
    tracing::info!(node = %app.settings.node.name, url = %url, "node registered");
    let stop = app.shutdown.child_token();
    let app = app.clone();
    let cancelled = stop.clone();
    let task = tokio::spawn(async move {
        let mut tick = tokio::time::interval(app.settings.node.heartbeat);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let mut failing = false;
        loop {
            tokio::select! {
                _ = cancelled.cancelled() => return,
                _ = tick.tick() => {}
            }
            // Raced with the stop: a beat waiting on the database must not hold up shutdown
            // (nor start a machine moved here once motion is being stopped).
            let beat = tokio::select! {
                _ = cancelled.cancelled() => return,
                r = beat(&app) => r,
            };
            match beat {
                Ok(()) if failing => {
                    failing = false;
                    tracing::info!("node heartbeat written again");
                }
                Ok(()) => {}
                Err(e) if !failing => {
                    failing = true;
                    tracing::error!(error = %e, "cannot write the node heartbeat: other nodes will show this node's machines offline");
                }
                Err(_) => {}
            }
        }
    });
    Ok(Heartbeat { stop, task })
}

/// The running heartbeat; [`Heartbeat::stop`] ends it before motion is stopped on shutdown.
pub struct Heartbeat {
    stop: tokio_util::sync::CancellationToken,
    task: tokio::task::JoinHandle<()>,
}

impl Heartbeat {
    /// Ends the heartbeat and waits for its task, which holds the `App` (and with it the data
    /// directory's lock): once this returns, nothing of it runs any more.
    pub async fn stop(self) {
        self.stop.cancel();
        let _ = self.task.await;
    }
}

async fn beat(app: &SharedApp) -> crate::Result<()> {
    let local = app.machines.all();
    let statuses: BTreeMap<String, MachineStatus> = local
        .iter()
        .map(|m| (m.id.to_string(), m.status()))
        .collect();
    let json = serde_json::to_string(&statuses).unwrap_or_else(|_| "{}".into());
    app.store
        .node_heartbeat(&app.settings.node.name, &json)
        .await?;
    reconcile(app).await
}

/// Loads machines the store says are ours but are not running here (moved to this node), and
/// lets go of idle machines moved to another node.
async fn reconcile(app: &SharedApp) -> crate::Result<()> {
    let me = app.settings.node.name.as_str();
    let rows = app.store.list_machines().await?;
    let ours: HashSet<i64> = rows
        .iter()
        .filter(|r| r.node.as_deref() == Some(me))
        .map(|r| r.id)
        .collect();
    let loaded = app.machines.all();
    let loaded_ids: HashSet<i64> = loaded.iter().map(|m| m.id).collect();
    for row in rows {
        if ours.contains(&row.id) && !loaded_ids.contains(&row.id) {
            tracing::info!(machine = row.id, name = %row.name, "machine moved to this node: starting it");
            crate::startup::load_machine(app, row).await;
        }
    }
    reconcile_pendants(app).await?;
    for m in loaded {
        if !ours.contains(&m.id) && m.run().is_none() {
            tracing::info!(
                machine = m.id,
                "machine moved to another node: letting it go"
            );
            app.machines.remove(m.id);
            m.close_gate();
            if let Err(e) = m.shutdown_backend().await {
                tracing::error!(machine = m.id, error = %e, "shutdown of a machine moved away failed");
            }
        }
    }
    Ok(())
}

/// The same for pendants: start the ones moved here, close the links of the ones moved away.
async fn reconcile_pendants(app: &SharedApp) -> crate::Result<()> {
    let me = app.settings.node.name.as_str();
    let rows = app.store.list_pendants().await?;
    let ours: HashSet<i64> = rows
        .iter()
        .filter(|r| r.node.as_deref() == Some(me))
        .map(|r| r.id)
        .collect();
    let running: HashSet<i64> = app.pendants.all().await.iter().map(|p| p.id).collect();
    for id in running.difference(&ours) {
        tracing::info!(
            pendant = id,
            "pendant moved to another node: closing its link"
        );
        app.pendants.remove(*id).await;
    }
    for row in rows {
        if ours.contains(&row.id) && !running.contains(&row.id) {
            tracing::info!(pendant = row.id, name = %row.name, "pendant moved to this node: starting its link");
            let created = crate::pendants::create_instance(app, &row).await;
            crate::pendants::attach(app, row, created).await;
        }
    }
    Ok(())
}

fn offline(reason: String) -> MachineStatus {
    MachineStatus {
        state: MachineState::Offline,
        reason: Some(reason),
        ..MachineStatus::default()
    }
}

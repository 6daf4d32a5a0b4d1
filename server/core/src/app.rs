//! The server's shared state: one `App` per process, shared by the HTTP layer and the pendants.
//! Its start-up and shutdown are in `startup`.

use crate::config::Settings;
use crate::datadir::DataDirLock;
use crate::events::EventBus;
use crate::machine::{MachineOptions, Machines};
use crate::pendants::registry::Pendants;
use crate::plugins::Registry;
use crate::store::Store;
use std::sync::Arc;
use tokio_util::sync::CancellationToken;

pub struct App {
    pub settings: Settings,
    pub store: Store,
    pub bus: EventBus,
    pub plugins: Registry,
    pub machines: Machines,
    pub pendants: Pendants,
    /// Cancelled on shutdown: ends SSE streams and background loops.
    pub shutdown: CancellationToken,
    /// Counters of the webhook deliveries and the MQTT bridge, for `/metrics`.
    pub integrations: crate::integrations::IntegrationStats,
    /// Toolpath previews: cached, bounded, abandoned when their clients leave.
    pub previews: crate::previews::Previews,
    /// Job queues: the lock that orders their changes, and what the pendants' LCD shows.
    pub queues: crate::queue_state::Queues,
    /// Whether requests must carry a token (any non-loopback bind).
    pub auth_required: bool,
    /// The secret nodes of one store vouch for forwarded requests with (from the store).
    pub node_secret: String,
    /// Held while the process lives: one server per data directory.
    pub(crate) _lock: DataDirLock,
}

pub type SharedApp = Arc<App>;

impl App {
    pub fn machine_options(&self) -> MachineOptions {
        MachineOptions {
            timeout: self.settings.plugin_call_timeout,
            status_interval: self.settings.status_interval,
            programs_dir: self.settings.programs_dir(),
            unstored_dir: self.settings.data_dir.join(crate::machine::unstored::DIR),
            max_program_segments: self.settings.max_program_segments,
        }
    }
}

//! Settings: built-in defaults < TOML file < environment < command line.

use serde::Deserialize;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

pub const DEFAULT_LISTEN: &str = "127.0.0.1:7878";
pub const DEFAULT_HEADER_READ_TIMEOUT_SECS: u64 = 30;
pub const DEFAULT_IDLE_TIMEOUT_SECS: u64 = 15;
pub const DEFAULT_UPLOAD_IDLE_TIMEOUT_SECS: u64 = 60;
/// Fits under the usual soft limit of 1,024 open files with room for the database, plugins and
/// pendant links; the systemd unit's `LimitNOFILE` leaves room to raise it.
pub const DEFAULT_MAX_CONNECTIONS: usize = 512;
pub const MAX_MAX_CONNECTIONS: usize = 100_000;

/// What the TOML file may contain. Unknown keys are an error so a typo is not silently ignored.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FileConfig {
    pub listen: Option<String>,
    pub data_dir: Option<PathBuf>,
    /// `postgres://USER[:PASSWORD]@HOST:PORT/DB` to share one store between nodes; default:
    /// the embedded SQLite file `fresa.db` in the data directory.
    pub database_url: Option<String>,
    /// This node's name among the nodes sharing the store (default: the host name).
    pub node_name: Option<String>,
    /// The URL other nodes reach this one at, e.g. `http://hall2.lan:7878` (default: the
    /// listen address, with the host name when listening on every address).
    pub node_url: Option<String>,
    /// How often this node writes its heartbeat (and its machines' status) to the store.
    pub node_heartbeat_ms: Option<u64>,
    /// A node whose heartbeat is older than this is shown unreachable, its machines offline.
    pub node_offline_after_ms: Option<u64>,
    pub plugin_dirs: Option<Vec<PathBuf>>,
    pub max_upload_bytes: Option<u64>,
    pub status_rate_hz: Option<f64>,
    pub plugin_call_timeout_ms: Option<u64>,
    /// Accepted so older config files still load; calls into one backend are now ordered by its
    /// machine's task (one at a time, plus the urgent lane), so the value is not used.
    pub plugin_max_concurrent_calls: Option<usize>,
    pub sse_keepalive_secs: Option<u64>,
    pub shutdown_grace_secs: Option<u64>,
    pub event_retention_days: Option<u32>,
    pub event_retention_count: Option<u64>,
    pub audit_retention_days: Option<u32>,
    pub event_prune_interval_secs: Option<u64>,
    pub header_read_timeout_secs: Option<u64>,
    pub idle_timeout_secs: Option<u64>,
    pub max_connections: Option<usize>,
    pub upload_idle_timeout_secs: Option<u64>,
    pub log: Option<String>,
    /// Host names (or `name:port`) besides the listen address and `localhost` that requests may
    /// be addressed to, e.g. the name a reverse proxy or the shop's DNS gives this server.
    pub allowed_hosts: Option<Vec<String>>,
    /// Origins (`http://tablet.lan:8080`) of other sites' pages allowed to call the API from a
    /// browser; none by default.
    pub cors_origins: Option<Vec<String>>,
    pub webhooks: Option<WebhooksFile>,
    pub mqtt: Option<MqttFile>,
    // ---- HTTP edges (issue 23): what one client may hold, so control always gets through ----
    /// Event streams open at once; below `max_connections` so the rest stay for short requests.
    pub max_event_streams: Option<usize>,
    /// Event streams one token may hold (tokenless local callers count only against the cap).
    pub max_event_streams_per_client: Option<usize>,
    /// Connections one non-loopback address may hold.
    pub max_connections_per_client: Option<usize>,
    /// Failed token attempts one address may make a minute before it is refused for a while.
    pub max_auth_failures_per_minute: Option<u32>,
    // Work budget and toolpath previews (issue #23, work budget).
    /// Most segments (moves, and arcs as chords at 0.002 mm) a program may linearise to:
    /// checked at upload, by the backend at start and by the toolpath.
    pub max_program_segments: Option<u64>,
    /// Toolpaths kept in memory, at most this many bytes and this many entries.
    pub toolpath_cache_bytes: Option<u64>,
    pub toolpath_cache_entries: Option<usize>,
    /// Toolpath computations at a time; more requests wait for one to finish.
    pub toolpath_max_concurrent: Option<usize>,
}

/// `[webhooks]`: how deliveries are retried.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WebhooksFile {
    pub max_attempts: Option<u32>,
    pub retry_initial_ms: Option<u64>,
    pub timeout_ms: Option<u64>,
    pub queue: Option<usize>,
    // Integrations (webhook targets): hosts a webhook may target although their addresses are
    // refused by default (loopback, link-local, ...), e.g. a receiver on this machine.
    pub allowed_hosts: Option<Vec<String>>,
}

/// `[mqtt]`: the bridge to an external broker (off unless `url` or `FRESA_MQTT_URL` is set).
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MqttFile {
    pub url: Option<String>,
    pub topic_prefix: Option<String>,
    pub username: Option<String>,
    pub password: Option<String>,
    /// PEM file of the CA that signed the broker's certificate (`mqtts://`); default: the
    /// system's roots.
    pub ca_file: Option<PathBuf>,
    pub client_id: Option<String>,
    /// Accept commands on `<prefix>/machines/<id>/commands/...` (each with a token).
    pub commands: Option<bool>,
    pub queue: Option<usize>,
    // Integrations (MQTT commands): a command message's payload at most, in bytes; larger
    // ones are dropped (and answered) without losing the connection.
    pub max_command_bytes: Option<usize>,
}

/// Webhook delivery: attempts per event, the first retry's delay (doubling, at most 5 min),
/// each request's timeout, and how many events may wait per webhook before new ones are dropped.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WebhookSettings {
    pub max_attempts: u32,
    pub retry_initial: Duration,
    pub timeout: Duration,
    pub queue: usize,
    /// Hosts (as in a URL: a name, an IPv4 address or a bracketed IPv6 one) a webhook may
    /// target although their addresses are refused by default.
    pub allowed_hosts: Vec<String>,
}

impl Default for WebhookSettings {
    fn default() -> Self {
        WebhookSettings {
            max_attempts: 6,
            retry_initial: Duration::from_secs(1),
            timeout: Duration::from_secs(10),
            queue: 1000,
            allowed_hosts: Vec::new(),
        }
    }
}

/// Command payloads larger than this are dropped by the MQTT bridge (a command's JSON is a
/// few hundred bytes).
pub const DEFAULT_MQTT_MAX_COMMAND_BYTES: usize = 64 * 1024;

/// The MQTT bridge's settings, resolved.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MqttSettings {
    pub host: String,
    pub port: u16,
    pub tls: bool,
    pub ca_file: Option<PathBuf>,
    pub topic_prefix: String,
    pub username: Option<String>,
    pub password: Option<String>,
    pub client_id: String,
    /// The node name in `<prefix>/nodes/<node>/online`: the host name.
    pub node: String,
    pub commands: bool,
    pub queue: usize,
    pub max_command_bytes: usize,
}

/// `mqtt://host[:1883]` or `mqtts://host[:8883]` (TLS).
pub fn parse_mqtt_url(url: &str) -> Result<(String, u16, bool), ConfigError> {
    let bad = |why: &str| {
        ConfigError::Invalid(format!(
            "mqtt url {url:?}: {why} (expected mqtt://host:port or mqtts://host:port)"
        ))
    };
    let (tls, rest) = if let Some(r) = url.strip_prefix("mqtt://") {
        (false, r)
    } else if let Some(r) = url.strip_prefix("mqtts://") {
        (true, r)
    } else {
        return Err(bad("the scheme must be mqtt or mqtts"));
    };
    let rest = rest.trim_end_matches('/');
    if rest.contains('/') || rest.contains('@') {
        return Err(bad(
            "no path or credentials in the URL (use username/password)",
        ));
    }
    let default_port = if tls { 8883 } else { 1883 };
    let (host, port) = match rest.rsplit_once(':') {
        Some((h, p)) if !h.ends_with(']') || rest.starts_with('[') => {
            let port = p
                .parse::<u16>()
                .map_err(|_| bad(&format!("port {p:?} is not a number 1..65535")))?;
            (h.trim_start_matches('[').trim_end_matches(']'), port)
        }
        _ => (rest, default_port),
    };
    if host.is_empty() || port == 0 {
        return Err(bad("no host"));
    }
    Ok((host.to_string(), port, tls))
}

pub(crate) fn host_name() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .ok()
        .or_else(|| std::env::var("HOSTNAME").ok())
        .or_else(|| std::env::var("COMPUTERNAME").ok())
        .map(|h| h.trim().to_string())
        .filter(|h| !h.is_empty())
        .unwrap_or_else(|| "fresa".into())
}

fn node_settings(file: &FileConfig, env_name: Option<String>) -> Result<NodeSettings, ConfigError> {
    let name = env_name
        .or_else(|| file.node_name.clone())
        .unwrap_or_else(host_name);
    if !NodeSettings::valid_name(&name) {
        return Err(ConfigError::Invalid(format!(
            "node_name {name:?}: use 1 to 63 letters, digits, '-', '_' or '.' (set node_name, \
             FRESA_NODE_NAME or --node-name)"
        )));
    }
    if let Some(url) = &file.node_url {
        if !(url.starts_with("http://") || url.starts_with("https://"))
            || url_authority(url).is_none()
        {
            return Err(ConfigError::Invalid(format!(
                "node_url {url:?}: expected http://HOST:PORT (the address other nodes reach this one at)"
            )));
        }
    }
    let heartbeat_ms = bounded(
        "node_heartbeat_ms",
        file.node_heartbeat_ms,
        1000,
        50,
        60_000,
    )?;
    let offline_ms = bounded(
        "node_offline_after_ms",
        file.node_offline_after_ms,
        (5 * heartbeat_ms).max(5000),
        2 * heartbeat_ms,
        600_000,
    )?;
    Ok(NodeSettings {
        name,
        url: file
            .node_url
            .clone()
            .map(|u| u.trim_end_matches('/').to_string()),
        heartbeat: Duration::from_millis(heartbeat_ms),
        offline_after: Duration::from_millis(offline_ms),
    })
}

/// `host:port` of `scheme://host:port/...`.
fn url_authority(url: &str) -> Option<String> {
    let rest = url.split_once("://")?.1;
    let authority = rest.split(['/', '?', '#']).next()?;
    (!authority.is_empty()).then(|| authority.to_string())
}

fn webhooks(file: Option<&WebhooksFile>) -> Result<WebhookSettings, ConfigError> {
    let d = WebhookSettings::default();
    let Some(f) = file else { return Ok(d) };
    Ok(WebhookSettings {
        max_attempts: bounded(
            "webhooks.max_attempts",
            f.max_attempts,
            d.max_attempts,
            1,
            20,
        )?,
        retry_initial: Duration::from_millis(bounded(
            "webhooks.retry_initial_ms",
            f.retry_initial_ms,
            1000,
            10,
            600_000,
        )?),
        timeout: Duration::from_millis(bounded(
            "webhooks.timeout_ms",
            f.timeout_ms,
            10_000,
            100,
            60_000,
        )?),
        queue: bounded("webhooks.queue", f.queue, d.queue, 1, 100_000)?,
        allowed_hosts: f
            .allowed_hosts
            .iter()
            .flatten()
            .map(|h| webhook_allowed_host(h))
            .collect::<Result<_, _>>()?,
    })
}

/// One `webhooks.allowed_hosts` entry in the form a URL's host takes once parsed (lower case,
/// IPv4 in dotted form, IPv6 in brackets), so it compares with what the URL parser gives.
fn webhook_allowed_host(entry: &str) -> Result<String, ConfigError> {
    let bad = |why: &str| {
        ConfigError::Invalid(format!(
            "webhooks.allowed_hosts: {entry:?} {why} (expected a host name or an IP address, \
             e.g. \"127.0.0.1\", \"::1\" or \"erp.lan\")"
        ))
    };
    let trimmed = entry.trim().trim_end_matches('.');
    let host = if trimmed.contains(':') && !trimmed.starts_with('[') {
        format!("[{trimmed}]")
    } else {
        trimmed.to_string()
    };
    if host.is_empty() || host.contains(['/', '?', '#', '@']) {
        return Err(bad("is not a host"));
    }
    let parsed = url::Url::parse(&format!("http://{host}/")).map_err(|e| bad(&e.to_string()))?;
    if parsed.port().is_some() {
        return Err(bad("has a port; list the host alone"));
    }
    parsed
        .host_str()
        .map(str::to_string)
        .ok_or_else(|| bad("is not a host"))
}

fn mqtt(
    file: Option<MqttFile>,
    env_url: Option<String>,
) -> Result<Option<MqttSettings>, ConfigError> {
    let file = file.unwrap_or_default();
    let Some(url) = env_url.or(file.url) else {
        return Ok(None);
    };
    let (host, port, tls) = parse_mqtt_url(&url)?;
    let topic_prefix = file.topic_prefix.unwrap_or_else(|| "fresa".into());
    if topic_prefix.is_empty()
        || topic_prefix.contains(['+', '#', '\0'])
        || topic_prefix.starts_with('/')
        || topic_prefix.ends_with('/')
    {
        return Err(ConfigError::Invalid(format!(
            "mqtt.topic_prefix {topic_prefix:?}: must be a topic without wildcards (+ #) or \
             leading/trailing /"
        )));
    }
    if file.ca_file.is_some() && !tls {
        return Err(ConfigError::Invalid(
            "mqtt.ca_file is set but the url is mqtt://; use mqtts:// for TLS".into(),
        ));
    }
    let node = host_name();
    Ok(Some(MqttSettings {
        host,
        port,
        tls,
        ca_file: file.ca_file,
        topic_prefix,
        username: file.username,
        password: file.password,
        client_id: file
            .client_id
            .unwrap_or_else(|| format!("fresa-{node}-{}", std::process::id())),
        node,
        commands: file.commands.unwrap_or(false),
        queue: bounded("mqtt.queue", file.queue, 10_000, 1, 1_000_000)?,
        max_command_bytes: bounded(
            "mqtt.max_command_bytes",
            file.max_command_bytes,
            DEFAULT_MQTT_MAX_COMMAND_BYTES,
            256,
            16 << 20,
        )?,
    }))
}

/// Command-line/environment values for `fresa serve` (the binary parses them: CLI beats env).
#[derive(Debug, Default, Clone)]
pub struct Overrides {
    pub listen: Option<String>,
    pub data_dir: Option<PathBuf>,
    pub database_url: Option<String>,
    /// `FRESA_NODE_NAME` / `--node-name`: beats `node_name`.
    pub node_name: Option<String>,
    pub config: Option<PathBuf>,
    pub plugin_dirs: Vec<PathBuf>,
    pub max_upload_bytes: Option<u64>,
    pub demo: bool,
    /// `FRESA_MQTT_URL`: beats `[mqtt] url`.
    pub mqtt_url: Option<String>,
}

#[derive(Debug, Clone)]
pub struct Settings {
    pub listen: SocketAddr,
    pub data_dir: PathBuf,
    /// The store: `Some` PostgreSQL (or explicit `sqlite://`) URL, `None` the embedded SQLite
    /// file [`Settings::db_path`].
    pub database_url: Option<String>,
    pub node: NodeSettings,
    pub plugin_dirs: Vec<PathBuf>,
    pub max_upload_bytes: u64,
    pub status_interval: Duration,
    pub plugin_call_timeout: Duration,
    pub sse_keepalive: Duration,
    /// How long open connections may drain on shutdown, after motion has stopped.
    pub shutdown_grace: Duration,
    pub event_retention: EventRetention,
    /// How long a client may take to send a request's head (from connecting, or from the end of
    /// the previous response on a kept-alive connection).
    pub header_read_timeout: Duration,
    /// A connection with no request in progress and no bytes moving for this long is closed.
    pub idle_timeout: Duration,
    /// Open connections at most; beyond it new ones wait in the kernel's backlog.
    pub max_connections: usize,
    /// An upload whose body sends nothing for this long is dropped.
    pub upload_idle_timeout: Duration,
    pub demo: bool,
    pub config_file: Option<PathBuf>,
    pub log: Option<String>,
    pub allowed_hosts: Vec<String>,
    pub cors_origins: Vec<String>,
    pub webhooks: WebhookSettings,
    /// None: no MQTT bridge.
    pub mqtt: Option<MqttSettings>,
    /// What the config file says that deserves a word in the log; resolved before logging is
    /// set up (the log filter comes from the file), so `serve` logs them.
    pub warnings: Vec<String>,
    // Work budget and toolpath previews (issue #23, work budget).
    /// `max_program_segments`: the work budget of one program.
    pub max_program_segments: u64,
    pub toolpath: ToolpathSettings,
    // ---- HTTP edges (issue 23) ----
    pub edges: EdgeLimits,
}

/// What one client may hold of the server (issue 23): a stop or feed hold must always find a
/// connection slot, whatever else is open.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EdgeLimits {
    /// Event streams open at once, always below `max_connections`: a stream holds its
    /// connection for as long as it lasts, so the difference is kept for everything else.
    pub max_event_streams: usize,
    /// Event streams one token may hold.
    pub max_event_streams_per_client: usize,
    /// Connections one address may hold (loopback addresses are not counted: every local
    /// process and a local reverse proxy share them).
    pub max_connections_per_client: usize,
    /// Failed token attempts an address may make a minute (a burst of this many, then one every
    /// 60/N s); beyond it its requests that carry a token get 429 without being looked up.
    pub max_auth_failures_per_minute: u32,
}

struct EdgeKeys {
    max_event_streams: Option<usize>,
    max_event_streams_per_client: Option<usize>,
    max_connections_per_client: Option<usize>,
    max_auth_failures_per_minute: Option<u32>,
}

pub const DEFAULT_MAX_EVENT_STREAMS_PER_CLIENT: usize = 32;
pub const DEFAULT_MAX_CONNECTIONS_PER_CLIENT: usize = 64;
pub const DEFAULT_MAX_AUTH_FAILURES_PER_MINUTE: u32 = 20;

/// Half the connections may be event streams (256 of the default 512): plenty for a shop's
/// screens (one stream each), and the other half is kept for short requests.
/// `file`: the four keys as the config file gives them.
fn edge_limits(file: EdgeKeys, max_connections: usize) -> Result<EdgeLimits, ConfigError> {
    // Not bounded by `max_connections`: a stream's connection leaves that cap for this one
    // once the stream is admitted, so streams never take the connections a stop needs.
    let max_event_streams = bounded(
        "max_event_streams",
        file.max_event_streams,
        max_connections / 2,
        0,
        MAX_MAX_CONNECTIONS,
    )?;
    Ok(EdgeLimits {
        max_event_streams,
        max_event_streams_per_client: bounded(
            "max_event_streams_per_client",
            file.max_event_streams_per_client,
            DEFAULT_MAX_EVENT_STREAMS_PER_CLIENT.min(max_event_streams.max(1)),
            1,
            MAX_MAX_CONNECTIONS,
        )?,
        max_connections_per_client: bounded(
            "max_connections_per_client",
            file.max_connections_per_client,
            DEFAULT_MAX_CONNECTIONS_PER_CLIENT.min(max_connections),
            1,
            MAX_MAX_CONNECTIONS,
        )?,
        max_auth_failures_per_minute: bounded(
            "max_auth_failures_per_minute",
            file.max_auth_failures_per_minute,
            DEFAULT_MAX_AUTH_FAILURES_PER_MINUTE,
            1,
            100_000,
        )?,
    })
}

/// How toolpath previews are computed and kept.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ToolpathSettings {
    pub cache_bytes: u64,
    pub cache_entries: usize,
    pub max_concurrent: usize,
}

impl Default for ToolpathSettings {
    fn default() -> Self {
        ToolpathSettings {
            cache_bytes: DEFAULT_TOOLPATH_CACHE_BYTES,
            cache_entries: DEFAULT_TOOLPATH_CACHE_ENTRIES,
            max_concurrent: DEFAULT_TOOLPATH_MAX_CONCURRENT,
        }
    }
}

/// The largest toolpath (2,000,000 vertices, 34 MB) fits twice; a typical one (250,000
/// vertices, 4.25 MB) about 15 times.
pub const DEFAULT_TOOLPATH_CACHE_BYTES: u64 = 64 << 20;
pub const DEFAULT_TOOLPATH_CACHE_ENTRIES: usize = 32;
/// One core of the usual two for previews, one left for everything else.
pub const DEFAULT_TOOLPATH_MAX_CONCURRENT: usize = 1;

/// This process among the nodes that share one store.
#[derive(Debug, Clone)]
pub struct NodeSettings {
    /// Unique among the nodes: machines and pendants belong to a node by this name.
    pub name: String,
    /// Where other nodes reach this one; `None`: derived from the bound address at start.
    pub url: Option<String>,
    pub heartbeat: Duration,
    pub offline_after: Duration,
}

impl NodeSettings {
    /// A node name: what a host name may hold, so it reads well in URLs, logs and metrics.
    pub fn valid_name(name: &str) -> bool {
        !name.is_empty()
            && name.len() <= 63
            && name
                .bytes()
                .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_' || b == b'.')
    }
}

/// How long the event log keeps what. Routine events (jogs, commands, MDI, pendant traffic:
/// the high-volume ones) go after `routine_days` or beyond the newest `routine_count`; the
/// audit events (see `events::Keeping::Audit`) are kept `audit_days`, whatever the count.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EventRetention {
    pub routine_days: u32,
    pub routine_count: u64,
    pub audit_days: u32,
    /// How often the background pass runs (it also runs once at start-up).
    pub prune_interval: Duration,
}

impl Default for EventRetention {
    fn default() -> Self {
        EventRetention {
            routine_days: 30,
            routine_count: 100_000,
            audit_days: 730,
            prune_interval: Duration::from_secs(60),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("cannot read config file {path}: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("config file {path}: {message}")]
    Parse { path: PathBuf, message: String },
    #[error(
        "invalid listen address {value:?}: {message} (expected ADDR:PORT, e.g. 127.0.0.1:7878)"
    )]
    Listen { value: String, message: String },
    #[error("{0}")]
    Invalid(String),
    #[error("no data directory: set --data-dir or FRESA_DATA_DIR (no home directory found)")]
    NoDataDir,
}

/// `cors_origins` entries must be origins (`scheme://host[:port]`), not patterns.
fn cors_origins(list: Vec<String>) -> Result<Vec<String>, ConfigError> {
    for o in &list {
        let ok = (o.starts_with("http://") || o.starts_with("https://"))
            && !o.contains('*')
            && o.split("://")
                .nth(1)
                .is_some_and(|r| !r.is_empty() && !r.contains('/'));
        if !ok {
            return Err(ConfigError::Invalid(format!(
                "cors_origins: {o:?} is not an origin like \"http://tablet.lan:8080\" (no paths, no wildcards)"
            )));
        }
    }
    Ok(list)
}

/// Where the config file is looked for when `--config` is not given: the machine-wide file
/// first (`/etc/fresa/fresa.toml`; on Windows `%ProgramData%\Fresa\fresa.toml`, beside the
/// service's data), then the user's (`~/.config/fresa/`, `%APPDATA%\fresa\config\`).
pub fn default_config_candidates() -> Vec<PathBuf> {
    let mut v = Vec::new();
    if cfg!(windows) {
        v.extend(
            windows_machine_dir(std::env::var_os("ProgramData")).map(|d| d.join("fresa.toml")),
        );
    } else {
        v.push(PathBuf::from("/etc/fresa/fresa.toml"));
    }
    if let Some(p) = directories::ProjectDirs::from("", "", "fresa") {
        v.push(p.config_dir().join("fresa.toml"));
    }
    v
}

/// The data directory by default: on Windows the machine-wide `%ProgramData%\Fresa` (where the
/// service keeps its data, so `fresa token` and `fresa backup` on the same PC find it);
/// elsewhere the user's XDG data directory (the systemd unit sets its own).
pub fn default_data_dir() -> Option<PathBuf> {
    if cfg!(windows) {
        return windows_machine_dir(std::env::var_os("ProgramData"));
    }
    directories::ProjectDirs::from("", "", "fresa").map(|p| p.data_dir().to_path_buf())
}

/// `%ProgramData%\Fresa`, given the value of `%ProgramData%` (always set on Windows).
pub fn windows_machine_dir(program_data: Option<std::ffi::OsString>) -> Option<PathBuf> {
    program_data
        .filter(|p| !p.is_empty())
        .map(|p| PathBuf::from(p).join("Fresa"))
}

/// Plugins are looked for beside the `fresa` executable first: that is where cargo puts the
/// workspace's plugin libraries, and where a package would install them (on Windows the
/// `fresa_*.dll` files go beside `fresa.exe`); then its `plugins` folder, and on Linux
/// `/usr/lib/fresa/plugins`.
pub fn default_plugin_dirs() -> Vec<PathBuf> {
    let mut v = Vec::new();
    if let Ok(exe) = std::env::current_exe() {
        if let Some(dir) = exe.parent() {
            v.push(dir.to_path_buf());
            v.push(dir.join("plugins"));
        }
    }
    if cfg!(unix) {
        v.push(PathBuf::from("/usr/lib/fresa/plugins"));
    }
    v
}

fn read_file(path: &Path) -> Result<FileConfig, ConfigError> {
    let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    toml::from_str(&text).map_err(|e| ConfigError::Parse {
        path: path.to_path_buf(),
        message: e.to_string(),
    })
}

/// `key`'s value (or `default` when unset), refused outside `lo..=hi` naming the key.
fn bounded<T>(key: &str, value: Option<T>, default: T, lo: T, hi: T) -> Result<T, ConfigError>
where
    T: PartialOrd + std::fmt::Display + Copy,
{
    let v = value.unwrap_or(default);
    if lo <= v && v <= hi {
        Ok(v)
    } else {
        Err(ConfigError::Invalid(format!(
            "{key} must be between {lo} and {hi}, got {v}"
        )))
    }
}

fn retention(file: &FileConfig) -> Result<EventRetention, ConfigError> {
    let d = EventRetention::default();
    let routine_days = bounded(
        "event_retention_days",
        file.event_retention_days,
        d.routine_days,
        1,
        36_500,
    )?;
    let routine_count = bounded(
        "event_retention_count",
        file.event_retention_count,
        d.routine_count,
        1,
        1_000_000_000,
    )?;
    // Unset, the audit is kept at least as long as the routine events; set, never shorter: the
    // audit trail is what retention must never lose before the routine traffic.
    let audit_days = bounded(
        "audit_retention_days",
        file.audit_retention_days,
        d.audit_days.max(routine_days),
        routine_days,
        36_500,
    )
    .map_err(|e| {
        ConfigError::Invalid(format!(
            "{e} (it may not be shorter than event_retention_days)"
        ))
    })?;
    let interval = bounded(
        "event_prune_interval_secs",
        file.event_prune_interval_secs,
        d.prune_interval.as_secs(),
        1,
        86_400,
    )?;
    Ok(EventRetention {
        routine_days,
        routine_count,
        audit_days,
        prune_interval: Duration::from_secs(interval),
    })
}

impl Settings {
    pub fn resolve(o: Overrides) -> Result<Settings, ConfigError> {
        let (file, config_file) = match &o.config {
            Some(p) => (read_file(p)?, Some(p.clone())),
            None => match default_config_candidates()
                .into_iter()
                .find(|p| p.is_file())
            {
                Some(p) => (read_file(&p)?, Some(p)),
                None => (FileConfig::default(), None),
            },
        };
        let event_retention = retention(&file)?;
        let node = node_settings(&file, o.node_name)?;
        let listen_str = o
            .listen
            .or(file.listen)
            .unwrap_or_else(|| DEFAULT_LISTEN.to_string());
        let listen: SocketAddr =
            listen_str
                .parse()
                .map_err(|e: std::net::AddrParseError| ConfigError::Listen {
                    value: listen_str.clone(),
                    message: e.to_string(),
                })?;
        let data_dir = o
            .data_dir
            .or(file.data_dir)
            .or_else(default_data_dir)
            .ok_or(ConfigError::NoDataDir)?;
        let database_url = o.database_url.or(file.database_url);
        if let Some(url) = &database_url {
            if !["sqlite:", "postgres:", "postgresql:"]
                .iter()
                .any(|s| url.starts_with(s))
            {
                return Err(ConfigError::Invalid(format!(
                    "database_url must start with postgres:// (or sqlite://), got {:?}",
                    crate::store::redact_url(url)
                )));
            }
        }
        let mut allowed_hosts = file.allowed_hosts.unwrap_or_default();
        // Other nodes address this one by its node URL: requests naming it are for us.
        if let Some(host) = node.url.as_deref().and_then(url_authority) {
            allowed_hosts.push(host);
        }
        let mut plugin_dirs = o.plugin_dirs;
        plugin_dirs.extend(file.plugin_dirs.unwrap_or_default());
        plugin_dirs.extend(default_plugin_dirs());
        let rate = file.status_rate_hz.unwrap_or(10.0);
        if !(rate.is_finite() && rate > 0.0 && rate <= 1000.0) {
            return Err(ConfigError::Invalid(format!(
                "status_rate_hz must be between 0 and 1000, got {rate}"
            )));
        }
        let mut warnings = Vec::new();
        if file.plugin_max_concurrent_calls.is_some() {
            warnings.push(
                "plugin_max_concurrent_calls is no longer used (each machine's calls are ordered \
                 by its task); remove it from the config file"
                    .to_string(),
            );
        }
        let timeout_ms = bounded(
            "plugin_call_timeout_ms",
            file.plugin_call_timeout_ms,
            10_000,
            1,
            600_000,
        )?;
        let grace = file.shutdown_grace_secs.unwrap_or(5);
        if grace > 60 {
            return Err(ConfigError::Invalid(format!(
                "shutdown_grace_secs must be at most 60 (systemd stops waiting at 90 s), got {grace}"
            )));
        }
        let secs = |key: &str, v: Option<u64>, default: u64| {
            bounded(key, v, default, 1, 3600).map(Duration::from_secs)
        };
        let header_read_timeout = secs(
            "header_read_timeout_secs",
            file.header_read_timeout_secs,
            DEFAULT_HEADER_READ_TIMEOUT_SECS,
        )?;
        let idle_timeout = secs(
            "idle_timeout_secs",
            file.idle_timeout_secs,
            DEFAULT_IDLE_TIMEOUT_SECS,
        )?;
        let upload_idle_timeout = secs(
            "upload_idle_timeout_secs",
            file.upload_idle_timeout_secs,
            DEFAULT_UPLOAD_IDLE_TIMEOUT_SECS,
        )?;
        // Bounded by what one semaphore can hand out at once (shutdown waits for all permits).
        let max_connections = bounded(
            "max_connections",
            file.max_connections,
            DEFAULT_MAX_CONNECTIONS,
            1,
            MAX_MAX_CONNECTIONS,
        )?;
        let edges = edge_limits(
            EdgeKeys {
                max_event_streams: file.max_event_streams,
                max_event_streams_per_client: file.max_event_streams_per_client,
                max_connections_per_client: file.max_connections_per_client,
                max_auth_failures_per_minute: file.max_auth_failures_per_minute,
            },
            max_connections,
        )?;
        let max_program_segments = bounded(
            "max_program_segments",
            file.max_program_segments,
            fresa_gcode::DEFAULT_MAX_SEGMENTS,
            1,
            1_000_000_000_000,
        )?;
        let t = ToolpathSettings::default();
        let toolpath = ToolpathSettings {
            cache_bytes: bounded(
                "toolpath_cache_bytes",
                file.toolpath_cache_bytes,
                t.cache_bytes,
                0,
                1 << 40,
            )?,
            cache_entries: bounded(
                "toolpath_cache_entries",
                file.toolpath_cache_entries,
                t.cache_entries,
                0,
                100_000,
            )?,
            max_concurrent: bounded(
                "toolpath_max_concurrent",
                file.toolpath_max_concurrent,
                t.max_concurrent,
                1,
                64,
            )?,
        };
        Ok(Settings {
            listen,
            data_dir,
            database_url,
            node,
            plugin_dirs,
            max_upload_bytes: o
                .max_upload_bytes
                .or(file.max_upload_bytes)
                .unwrap_or(1 << 30),
            status_interval: Duration::from_secs_f64(1.0 / rate),
            plugin_call_timeout: Duration::from_millis(timeout_ms),
            sse_keepalive: Duration::from_secs(file.sse_keepalive_secs.unwrap_or(15)),
            shutdown_grace: Duration::from_secs(grace),
            event_retention,
            header_read_timeout,
            idle_timeout,
            max_connections,
            upload_idle_timeout,
            demo: o.demo,
            config_file,
            log: file.log,
            allowed_hosts,
            cors_origins: cors_origins(file.cors_origins.unwrap_or_default())?,
            webhooks: webhooks(file.webhooks.as_ref())?,
            mqtt: mqtt(file.mqtt, o.mqtt_url)?,
            warnings,
            edges,
            max_program_segments,
            toolpath,
        })
    }

    pub fn db_path(&self) -> PathBuf {
        self.data_dir.join("fresa.db")
    }

    /// What the store is, for messages: the URL without its password, or the SQLite file.
    pub fn database_label(&self) -> String {
        match &self.database_url {
            Some(url) => crate::store::redact_url(url),
            None => self.db_path().display().to_string(),
        }
    }

    /// Opens the configured store.
    pub async fn open_store(&self) -> Result<crate::store::Store, sqlx::Error> {
        match &self.database_url {
            Some(url) => crate::store::Store::connect(url).await,
            None => crate::store::Store::open(&self.db_path()).await,
        }
    }
    pub fn programs_dir(&self) -> PathBuf {
        self.data_dir.join("programs")
    }
    pub fn loopback_only(&self) -> bool {
        self.listen.ip().is_loopback()
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn platform_default_paths() {
        assert_eq!(
            windows_machine_dir(Some("C:\\ProgramData".into())),
            Some(PathBuf::from("C:\\ProgramData").join("Fresa"))
        );
        assert_eq!(windows_machine_dir(None), None);
        assert_eq!(windows_machine_dir(Some("".into())), None);
        let candidates = default_config_candidates();
        let plugins = default_plugin_dirs();
        if cfg!(windows) {
            assert!(
                candidates.iter().all(|p| !p.starts_with("/etc")),
                "{candidates:?}"
            );
            assert!(
                plugins.iter().all(|p| !p.starts_with("/usr")),
                "{plugins:?}"
            );
        } else {
            assert_eq!(candidates[0], PathBuf::from("/etc/fresa/fresa.toml"));
            assert_eq!(
                plugins.last(),
                Some(&PathBuf::from("/usr/lib/fresa/plugins"))
            );
        }
        assert_eq!(
            plugins[0],
            std::env::current_exe().unwrap().parent().unwrap()
        );
    }

    #[test]
    fn cli_beats_file_and_file_beats_defaults() {
        let dir = std::env::temp_dir().join(format!("fresa-cfg-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let f = dir.join("f.toml");
        std::fs::write(
            &f,
            "listen = \"127.0.0.1:9000\"\nmax_upload_bytes = 100\nstatus_rate_hz = 20.0\n",
        )
        .unwrap();
        let s = Settings::resolve(Overrides {
            config: Some(f.clone()),
            data_dir: Some(dir.clone()),
            max_upload_bytes: Some(5),
            ..Default::default()
        })
        .unwrap();
        assert_eq!(s.listen.port(), 9000);
        assert_eq!(s.max_upload_bytes, 5);
        assert_eq!(s.status_interval, Duration::from_millis(50));
        std::fs::remove_dir_all(dir).ok();
    }

    #[test]
    fn unknown_keys_and_bad_addresses_are_named() {
        let dir = std::env::temp_dir().join(format!("fresa-cfg2-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let f = dir.join("f.toml");
        std::fs::write(&f, "lisen = \"x\"\n").unwrap();
        let e = Settings::resolve(Overrides {
            config: Some(f),
            data_dir: Some(dir.clone()),
            ..Default::default()
        })
        .unwrap_err()
        .to_string();
        assert!(e.contains("lisen"), "{e}");
        let e = Settings::resolve(Overrides {
            listen: Some("localhost".into()),
            data_dir: Some(dir.clone()),
            config: None,
            ..Default::default()
        })
        .unwrap_err()
        .to_string();
        assert!(e.contains("localhost") && e.contains("ADDR:PORT"), "{e}");
        std::fs::remove_dir_all(dir).ok();
    }

    /// A scratch directory (`tag` keeps parallel tests apart) and a function that resolves the
    /// settings of a config file with the given TOML in it.
    fn toml_resolver(
        tag: &str,
    ) -> (
        std::path::PathBuf,
        impl Fn(&str) -> Result<Settings, ConfigError>,
    ) {
        let dir = std::env::temp_dir().join(format!("{tag}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let f = dir.join("f.toml");
        let data_dir = dir.clone();
        let resolve = move |toml: &str| {
            std::fs::write(&f, toml).unwrap();
            Settings::resolve(Overrides {
                config: Some(f.clone()),
                data_dir: Some(data_dir.clone()),
                ..Default::default()
            })
        };
        (dir, resolve)
    }

    #[test]
    fn retention_defaults_and_bounds() {
        let (dir, resolve) = toml_resolver("fresa-cfg3");
        assert_eq!(
            resolve("").unwrap().event_retention,
            EventRetention::default()
        );
        let r = resolve("event_retention_count = 5\nevent_prune_interval_secs = 1\n")
            .unwrap()
            .event_retention;
        assert_eq!((r.routine_count, r.prune_interval.as_secs()), (5, 1));
        let e = resolve("event_retention_days = 90\naudit_retention_days = 30\n")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("audit_retention_days") && e.contains("30"),
            "{e}"
        );
        let e = resolve("event_retention_count = 0\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("event_retention_count"), "{e}");
        std::fs::remove_dir_all(dir).ok();
    }

    #[test]
    fn edge_limits_keep_connections_for_control() {
        let (dir, resolve) = toml_resolver("fresa-cfg-edges");
        let e = resolve("").unwrap().edges;
        assert_eq!(
            e,
            EdgeLimits {
                max_event_streams: 256,
                max_event_streams_per_client: 32,
                max_connections_per_client: 64,
                max_auth_failures_per_minute: 20,
            }
        );
        // By default half the connection cap; a cap of its own when given (streams leave
        // `max_connections` once admitted), so it may be far above it.
        let e = resolve("max_connections = 8\n").unwrap().edges;
        assert_eq!((e.max_event_streams, e.max_connections_per_client), (4, 8));
        let e = resolve("max_connections = 1\n").unwrap().edges;
        assert_eq!(e.max_event_streams, 0);
        let e = resolve("max_event_streams = 10000\n").unwrap().edges;
        assert_eq!(e.max_event_streams, 10_000);
        for (toml, needle) in [
            ("max_event_streams = 100001\n", "max_event_streams"),
            (
                "max_event_streams_per_client = 0\n",
                "max_event_streams_per_client",
            ),
            (
                "max_connections_per_client = 0\n",
                "max_connections_per_client",
            ),
            (
                "max_auth_failures_per_minute = 0\n",
                "max_auth_failures_per_minute",
            ),
        ] {
            let e = resolve(toml).unwrap_err().to_string();
            assert!(e.contains(needle), "{toml}: {e}");
        }
        std::fs::remove_dir_all(dir).ok();
    }

    #[test]
    fn mqtt_and_webhook_settings() {
        let (dir, resolve) = toml_resolver("fresa-cfg5");
        let s = resolve("").unwrap();
        assert_eq!(s.mqtt, None);
        assert_eq!(s.webhooks, WebhookSettings::default());
        let m = resolve("[mqtt]\nurl = \"mqtt://broker.lan\"\n")
            .unwrap()
            .mqtt
            .unwrap();
        assert_eq!(
            (m.host.as_str(), m.port, m.tls),
            ("broker.lan", 1883, false)
        );
        assert_eq!(m.topic_prefix, "fresa");
        assert!(!m.commands);
        let m = resolve("[mqtt]\nurl = \"mqtts://10.0.0.2:9000\"\ntopic_prefix = \"shop/fresa\"\n")
            .unwrap()
            .mqtt
            .unwrap();
        assert_eq!((m.host.as_str(), m.port, m.tls), ("10.0.0.2", 9000, true));
        for (toml, needle) in [
            ("[mqtt]\nurl = \"http://x\"\n", "scheme"),
            ("[mqtt]\nurl = \"mqtt://x:99999\"\n", "port"),
            (
                "[mqtt]\nurl = \"mqtt://x\"\ntopic_prefix = \"a/#\"\n",
                "topic_prefix",
            ),
            ("[mqtt]\nurl = \"mqtt://x\"\nqos = 1\n", "qos"),
            ("[webhooks]\nmax_attempts = 0\n", "webhooks.max_attempts"),
            (
                "[webhooks]\nallowed_hosts = [\"127.0.0.1:8080\"]\n",
                "webhooks.allowed_hosts",
            ),
            (
                "[webhooks]\nallowed_hosts = [\"http://erp/\"]\n",
                "webhooks.allowed_hosts",
            ),
            (
                "[mqtt]\nurl = \"mqtt://x\"\nmax_command_bytes = 10\n",
                "mqtt.max_command_bytes",
            ),
        ] {
            let e = resolve(toml).unwrap_err().to_string();
            assert!(e.contains(needle), "{toml}: {e}");
        }
        assert_eq!(m.max_command_bytes, DEFAULT_MQTT_MAX_COMMAND_BYTES);
        // Entries take the form the URL parser gives a host, so they compare with it.
        let w = resolve("[webhooks]\nallowed_hosts = [\"127.0.0.1\", \"::1\", \"ERP.lan.\", \"[::ffff:127.0.0.2]\"]\n")
            .unwrap()
            .webhooks;
        assert_eq!(
            w.allowed_hosts,
            ["127.0.0.1", "[::1]", "erp.lan", "[::ffff:7f00:2]"]
        );
        std::fs::remove_dir_all(dir).ok();
    }

    #[test]
    fn connection_settings_have_defaults_and_bounds() {
        let (dir, resolve) = toml_resolver("fresa-cfg4");
        let s = resolve("").unwrap();
        assert_eq!(s.header_read_timeout, Duration::from_secs(30));
        assert_eq!(s.idle_timeout, Duration::from_secs(15));
        assert_eq!(s.max_connections, 512);
        assert_eq!(s.upload_idle_timeout, Duration::from_secs(60));
        let s = resolve("header_read_timeout_secs = 2\nmax_connections = 64\n").unwrap();
        assert_eq!(s.header_read_timeout, Duration::from_secs(2));
        assert_eq!(s.max_connections, 64);
        for (toml, key) in [
            ("header_read_timeout_secs = 0\n", "header_read_timeout_secs"),
            ("idle_timeout_secs = 4000\n", "idle_timeout_secs"),
            ("upload_idle_timeout_secs = 0\n", "upload_idle_timeout_secs"),
            ("max_connections = 0\n", "max_connections"),
        ] {
            let e = resolve(toml).unwrap_err().to_string();
            assert!(e.contains(key), "{toml}: {e}");
        }
        std::fs::remove_dir_all(dir).ok();
    }

    #[test]
    fn work_budget_and_toolpath_settings_have_defaults_and_bounds() {
        let (dir, resolve) = toml_resolver("fresa-cfg-budget");
        let s = resolve("").unwrap();
        assert_eq!(s.max_program_segments, fresa_gcode::DEFAULT_MAX_SEGMENTS);
        assert_eq!(s.toolpath, ToolpathSettings::default());
        let s = resolve("max_program_segments = 1000\ntoolpath_max_concurrent = 3\ntoolpath_cache_entries = 0\n")
            .unwrap();
        assert_eq!(s.max_program_segments, 1000);
        assert_eq!(s.toolpath.max_concurrent, 3);
        assert_eq!(s.toolpath.cache_entries, 0);
        for (toml, key) in [
            ("max_program_segments = 0\n", "max_program_segments"),
            ("toolpath_max_concurrent = 0\n", "toolpath_max_concurrent"),
            (
                "toolpath_cache_entries = 1000000\n",
                "toolpath_cache_entries",
            ),
        ] {
            let e = resolve(toml).unwrap_err().to_string();
            assert!(e.contains(key), "{toml}: {e}");
        }
        std::fs::remove_dir_all(dir).ok();
    }
}

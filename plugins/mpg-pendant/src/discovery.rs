//! mDNS: pendants announce `MPGnnnnnn.local` with service `_http._tcp`. Resolving a `.local`
//! name (when a connect fails, the address may have changed) and browsing for pendants.

use serde::Serialize;
use std::collections::BTreeMap;
use std::net::{IpAddr, SocketAddr};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// The service the pendants announce.
pub const SERVICE: &str = "_http._tcp.local.";

/// Resolves a `.local` host name by mDNS; waits at most `timeout`.
pub fn resolve_mdns(host: &str, port: u16, timeout: Duration) -> Result<Vec<SocketAddr>, String> {
    let daemon =
        mdns_sd::ServiceDaemon::new().map_err(|e| format!("mDNS is not available: {e}"))?;
    let name = if host.ends_with('.') {
        host.to_string()
    } else {
        format!("{host}.")
    };
    let result = (|| {
        let rx = daemon
            .resolve_hostname(&name, Some(timeout.as_millis() as u64))
            .map_err(|e| format!("mDNS query for {host:?} failed: {e}"))?;
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match rx.recv_timeout(left) {
                Ok(mdns_sd::HostnameResolutionEvent::AddressesFound(_, ips)) => {
                    let mut v: Vec<SocketAddr> = ips
                        .iter()
                        .map(|ip| SocketAddr::new(ip.to_ip_addr(), port))
                        .collect();
                    // IPv4 first: the ESP32 pendants are IPv4-only.
                    v.sort_by_key(|a| !a.is_ipv4());
                    return Ok(v);
                }
                Ok(_) => continue,
                Err(_) => return Err(format!("no mDNS answer for {host:?} within {timeout:?}")),
            }
        }
    })();
    let _ = daemon.shutdown();
    result
}

/// A pendant seen on the LAN.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Found {
    /// mDNS instance name, e.g. `MPG000001`.
    pub name: String,
    /// e.g. `MPG000001.local`
    pub host: String,
    pub addresses: Vec<IpAddr>,
    /// The pendant's TCP port (the protocol's 8001; the HTTP service port is not it).
    pub port: u16,
    /// What to put in `POST /api/v1/pendants` `address`.
    pub address: String,
}

/// Browses for pendants in the background until dropped.
pub struct Browser {
    daemon: mdns_sd::ServiceDaemon,
    found: Arc<Mutex<BTreeMap<String, Found>>>,
}

fn is_pendant(name: &str) -> bool {
    name.get(..3).is_some_and(|p| p.eq_ignore_ascii_case("MPG"))
}

impl Browser {
    pub fn start() -> Result<Browser, String> {
        let daemon =
            mdns_sd::ServiceDaemon::new().map_err(|e| format!("mDNS is not available: {e}"))?;
        let rx = daemon
            .browse(SERVICE)
            .map_err(|e| format!("mDNS browse failed: {e}"))?;
        let found: Arc<Mutex<BTreeMap<String, Found>>> = Arc::default();
        let f = found.clone();
        std::thread::Builder::new()
            .name("mpg-mdns".into())
            .spawn(move || {
                // Ends when the daemon shuts down and closes the channel.
                while let Ok(ev) = rx.recv() {
                    let mut map = f.lock().unwrap_or_else(|p| p.into_inner());
                    match ev {
                        mdns_sd::ServiceEvent::ServiceResolved(s) => {
                            let instance = s
                                .get_fullname()
                                .split('.')
                                .next()
                                .unwrap_or_default()
                                .to_string();
                            let host = s.get_hostname().trim_end_matches('.').to_string();
                            if !(is_pendant(&instance) || is_pendant(&host)) {
                                continue;
                            }
                            let mut addresses: Vec<IpAddr> =
                                s.get_addresses().iter().map(|a| a.to_ip_addr()).collect();
                            addresses.sort();
                            let port = crate::transport::DEFAULT_PORT;
                            map.insert(
                                s.get_fullname().to_string(),
                                Found {
                                    name: instance,
                                    address: format!("{host}:{port}"),
                                    host,
                                    addresses,
                                    port,
                                },
                            );
                        }
                        mdns_sd::ServiceEvent::ServiceRemoved(_, fullname) => {
                            map.remove(&fullname);
                        }
                        _ => {}
                    }
                }
            })
            .map_err(|e| format!("cannot start the mDNS thread: {e}"))?;
        Ok(Browser { daemon, found })
    }

    pub fn list(&self) -> Vec<Found> {
        self.found
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .values()
            .cloned()
            .collect()
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.daemon.shutdown();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pendant_names_are_recognised() {
        assert!(is_pendant("MPG000001"));
        assert!(is_pendant("mpg000042.local"));
        assert!(!is_pendant("printer"));
        assert!(!is_pendant("MP"));
    }
}

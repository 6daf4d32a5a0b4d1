//! mDNS: pendants announce `MPGnnnnnn.local` with service `_http._tcp`.

use std::net::SocketAddr;
use std::time::Duration;

/// Resolves a `.local` host name. Without an mDNS responder library this is a stub that reports
/// why; see README.
pub fn resolve_mdns(host: &str, _port: u16, _timeout: Duration) -> Result<Vec<SocketAddr>, String> {
    Err(format!(
        "cannot resolve {host:?}: mDNS lookup is not available"
    ))
}

//! Registering webhooks (the HTTP admin routes call these). Deliveries are made by
//! `fresa-integrations`, which rereads the list when it sees `webhook.created` or
//! `webhook.deleted` on the event bus.

use crate::app::App;
use crate::error::{Error, Result};
use crate::events::EventKind;
use crate::store::WebhookRow;
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr};

/// Longest URL accepted.
const MAX_URL: usize = 2000;
/// Most event types in one filter.
const MAX_FILTER: usize = 100;

/// A new webhook and its signing secret (shown to the caller once, never again).
pub struct NewWebhook {
    pub row: WebhookRow,
    pub secret: String,
}

/// Host names that always mean this machine's loopback (RFC 6761), and the names cloud
/// providers give their instance-metadata services.
const LOOPBACK_NAMES: [&str; 1] = ["localhost"];
const METADATA_NAMES: [&str; 5] = [
    "metadata.google.internal",
    "metadata.goog",
    "metadata",
    "instance-data",
    "instance-data.ec2.internal",
];

/// Metadata services at addresses outside the classes refused anyway (169.254.169.254 is
/// link-local): Alibaba's, and AWS's IPv6 one.
const METADATA_ADDRESSES: [IpAddr; 2] = [
    IpAddr::V4(Ipv4Addr::new(100, 100, 100, 200)),
    IpAddr::V6(Ipv6Addr::new(0xfd00, 0xec2, 0, 0, 0, 0, 0, 0x254)),
];

const REFUSED_CLASSES: &str = "this server's own addresses, loopback, link-local, unspecified, \
     multicast or broadcast addresses, or a cloud metadata service";

/// Why connecting to an address of this class is refused, or `None`: the address's class, as
/// a phrase (`"a loopback address"`). Private LAN ranges pass: a receiver (an ERP) on the shop's
/// network is the normal case.
pub fn address_class(ip: IpAddr) -> Option<&'static str> {
    if METADATA_ADDRESSES.contains(&ip) {
        return Some("a cloud metadata service's address");
    }
    match ip {
        IpAddr::V4(v4) => ipv4_class(v4),
        IpAddr::V6(v6) => {
            if v6.is_unspecified() {
                return Some("an unspecified address");
            }
            if v6.is_loopback() {
                return Some("a loopback address");
            }
            // `::ffff:a.b.c.d` reaches the IPv4 address; so did the deprecated `::a.b.c.d`.
            if let Some(v4) = v6.to_ipv4() {
                return ipv4_class(v4);
            }
            let first = v6.segments()[0];
            if first & 0xffc0 == 0xfe80 {
                return Some("a link-local address");
            }
            if first & 0xff00 == 0xff00 {
                return Some("a multicast address");
            }
            None
        }
    }
}

fn ipv4_class(ip: Ipv4Addr) -> Option<&'static str> {
    let o = ip.octets();
    if o[0] == 0 {
        // 0.0.0.0/8 "this network": Linux connects 0.0.0.0 to the loopback interface.
        Some("an unspecified address")
    } else if ip.is_loopback() {
        Some("a loopback address")
    } else if ip.is_link_local() {
        Some("a link-local address")
    } else if ip.is_multicast() {
        Some("a multicast address")
    } else if ip.is_broadcast() {
        Some("a broadcast address")
    } else if o[0] >= 240 {
        Some("a reserved address")
    } else {
        None
    }
}

/// Whether `ip` is assigned to this host: a socket can be bound to an address only then. Not
/// reliable where non-local binds are allowed (`ip_nonlocal_bind`), which a bind to a
/// documentation address (never assigned) shows; there only the listen address counts.
fn assigned_here(ip: IpAddr) -> bool {
    static NONLOCAL_BIND: std::sync::OnceLock<(bool, bool)> = std::sync::OnceLock::new();
    let (v4, v6) = *NONLOCAL_BIND.get_or_init(|| {
        let probe = |ip: IpAddr| std::net::UdpSocket::bind((ip, 0)).is_ok();
        (
            probe(IpAddr::V4(Ipv4Addr::new(203, 0, 113, 254))),
            probe(IpAddr::V6(Ipv6Addr::new(
                0x2001, 0xdb8, 0xffff, 0, 0, 0, 0, 0xfe,
            ))),
        )
    });
    let unreliable = if ip.is_ipv4() { v4 } else { v6 };
    !unreliable && std::net::UdpSocket::bind((ip, 0)).is_ok()
}

/// Where webhooks may be delivered: the refused address classes, this server's own addresses,
/// and the config's `webhooks.allowed_hosts` that opt some of them in. Registration checks a
/// URL's host as written; each delivery checks every address the host resolves to.
#[derive(Debug, Clone)]
pub struct TargetPolicy {
    /// As the URL parser writes hosts (`127.0.0.1`, `[::1]`, `erp.lan`).
    allowed_hosts: Vec<String>,
    /// The allowed hosts that are addresses: any name resolving to them passes too.
    allowed_addresses: Vec<IpAddr>,
    listen: IpAddr,
}

impl TargetPolicy {
    pub fn new(settings: &crate::config::Settings) -> Self {
        let allowed_hosts = settings.webhooks.allowed_hosts.clone();
        let allowed_addresses = allowed_hosts
            .iter()
            .filter_map(|h| h.trim_start_matches('[').trim_end_matches(']').parse().ok())
            .collect();
        TargetPolicy {
            allowed_hosts,
            allowed_addresses,
            listen: settings.listen.ip(),
        }
    }

    /// Whether the config lists this host (as the URL parser gives it).
    pub fn host_allowed(&self, host: &str) -> bool {
        self.allowed_hosts.iter().any(|h| h == host)
    }

    /// Why delivering to `ip` is refused (`"127.0.0.1 is a loopback address"`), if it is.
    pub fn refused_address(&self, ip: IpAddr) -> Option<String> {
        if self.allowed_addresses.contains(&ip) {
            return None;
        }
        let class = address_class(ip).or_else(|| {
            (ip == self.listen || assigned_here(ip)).then_some("this server's own address")
        })?;
        Some(format!("{ip} is {class}"))
    }

    /// Why a host name is refused before any lookup (`localhost`, metadata services), if it is.
    fn refused_name(&self, name: &str) -> Option<String> {
        let name = name.trim_end_matches('.').to_ascii_lowercase();
        if LOOPBACK_NAMES
            .iter()
            .any(|l| name == *l || name.ends_with(&format!(".{l}")))
        {
            return Some(format!("{name} names a loopback address"));
        }
        if METADATA_NAMES.contains(&name.as_str()) {
            return Some(format!("{name} names a cloud metadata service"));
        }
        None
    }

    /// Why a URL's host is refused as written (an address of a refused class, or a refused
    /// name), if it is; names are resolved and checked again at each delivery.
    pub fn refused_host(&self, host: &url::Host<&str>) -> Option<String> {
        let written = host.to_string();
        if self.host_allowed(&written) {
            return None;
        }
        match host {
            url::Host::Ipv4(ip) => self.refused_address(IpAddr::V4(*ip)),
            url::Host::Ipv6(ip) => self.refused_address(IpAddr::V6(*ip)),
            url::Host::Domain(name) => self.refused_name(name),
        }
    }

    /// Checks a webhook URL: http(s), a host and a port in range, no user name or password,
    /// and a host that is not refused. Parsed as the HTTP client parses it (WHATWG), so
    /// `http://2130706433/`, `http://127.1/` and `http://0x7f.1/` are all 127.0.0.1 here too.
    pub fn check_url(&self, url: &str) -> Result<url::Url> {
        let field = |m: String| Error::invalid("invalid_field", format!("field `url`: {m}"));
        if url.len() > MAX_URL || url.chars().any(|c| c.is_whitespace() || c.is_control()) {
            return Err(field(format!(
                "at most {MAX_URL} characters, no spaces or control characters"
            )));
        }
        let lower = url.get(..8).unwrap_or(url).to_ascii_lowercase();
        let Some(rest) = ["http://", "https://"]
            .iter()
            .find(|p| lower.starts_with(**p))
            .map(|p| &url[p.len()..])
        else {
            return Err(field(format!(
                "{url:?} must start with http:// or https://"
            )));
        };
        // The parser would skip extra slashes (`http:///x` is host `x`): a URL with no host
        // as written is refused, not reinterpreted.
        if rest.is_empty() || rest.starts_with(['/', '\\', '?', '#']) {
            return Err(field(format!("{url:?} has no host")));
        }
        let parsed =
            url::Url::parse(url).map_err(|e| field(format!("{url:?} is not a valid URL: {e}")))?;
        if !parsed.username().is_empty() || parsed.password().is_some() {
            return Err(field(format!(
                "{url:?} has a user name or password in it; they are not accepted (the URL is \
                 shown to every admin): receivers authenticate deliveries by their signature"
            )));
        }
        let Some(host) = parsed.host() else {
            return Err(field(format!("{url:?} has no host")));
        };
        if parsed.port() == Some(0) {
            return Err(field(format!(
                "{url:?}: port 0 is not a port to connect to"
            )));
        }
        if let Some(why) = self.refused_host(&host) {
            return Err(Error::invalid(
                "webhook_target_refused",
                format!(
                    "field `url`: {url:?} is refused: {why}. Webhooks may not target \
                     {REFUSED_CLASSES}; list the host in webhooks.allowed_hosts to allow it"
                ),
            ));
        }
        Ok(parsed)
    }
}

/// What a delivery refused by the [`TargetPolicy`] records as its error.
pub fn refusal_message(why: &str) -> String {
    format!(
        "refused: {why}; webhooks may not target {REFUSED_CLASSES} (webhooks.allowed_hosts \
         opts a host in)"
    )
}

fn check_filter(events: &[String]) -> Result<()> {
    if events.len() > MAX_FILTER {
        return Err(Error::invalid(
            "invalid_field",
            format!("field `events`: at most {MAX_FILTER} types"),
        ));
    }
    for (i, t) in events.iter().enumerate() {
        let ok = !t.is_empty()
            && t.len() <= 100
            && t.chars()
                .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '.' || c == '_');
        if !ok {
            return Err(Error::invalid(
                "invalid_field",
                format!(
                    "field `events[{i}]`: {t:?} is not an event type (e.g. \"job.state\" or \"job\")"
                ),
            ));
        }
    }
    Ok(())
}

/// Whether an event of type `kind` passes `filter` (`job` matches `job.*`; empty passes all).
pub fn matches(filter: &[String], kind: &str) -> bool {
    filter.is_empty()
        || filter.iter().any(|t| {
            kind == t
                || (kind.starts_with(t.as_str()) && kind.as_bytes().get(t.len()) == Some(&b'.'))
        })
}

pub async fn create(app: &App, url: &str, events: Vec<String>, actor: &str) -> Result<NewWebhook> {
    TargetPolicy::new(&app.settings).check_url(url)?;
    check_filter(&events)?;
    let secret = format!("whsec_{}", hex::encode(rand::random::<[u8; 32]>()));
    let row = app
        .store
        .insert_webhook(url, &events, &secret, actor)
        .await?;
    app.bus
        .record_or_log(
            EventKind::WebhookCreated,
            None,
            Some(actor),
            serde_json::json!({"id": row.id, "url": row.url, "events": events}),
        )
        .await;
    Ok(NewWebhook { row, secret })
}

pub async fn delete(app: &App, id: i64, actor: &str) -> Result<()> {
    if !app.store.delete_webhook(id).await? {
        return Err(Error::not_found(
            "unknown_webhook",
            format!("no webhook with id {id}"),
        ));
    }
    app.bus
        .record_or_log(
            EventKind::WebhookDeleted,
            None,
            Some(actor),
            serde_json::json!({"id": id}),
        )
        .await;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn filters_match_by_type_or_prefix() {
        let f = vec!["job".to_string(), "machine.alarm".to_string()];
        assert!(matches(&f, "job.state"));
        assert!(matches(&f, "machine.alarm"));
        assert!(!matches(&f, "jobs.x"));
        assert!(!matches(&f, "machine.jog"));
        assert!(matches(&[], "anything"));
    }

    fn policy(allowed: &[&str]) -> TargetPolicy {
        TargetPolicy {
            allowed_hosts: allowed.iter().map(|s| s.to_string()).collect(),
            allowed_addresses: allowed
                .iter()
                .filter_map(|h| h.trim_start_matches('[').trim_end_matches(']').parse().ok())
                .collect(),
            listen: "127.0.0.1".parse().unwrap_or_else(|_| unreachable!()),
        }
    }

    #[test]
    fn bad_urls_and_filters_are_named() {
        let p = policy(&[]);
        for bad in [
            "ftp://x",
            "http://",
            "http:// x",
            "x",
            "http:///x",
            "http:\\\\x/",
        ] {
            assert!(p.check_url(bad).is_err(), "{bad}");
        }
        assert!(p.check_url("http://10.1.2.3:9/hook").is_ok());
        assert!(check_filter(&["Job!".into()]).is_err());
    }

    #[test]
    fn addresses_are_classified_after_the_parser_normalised_them() {
        let p = policy(&[]);
        let code = |url: &str| p.check_url(url).err().map(|e| e.code);
        for url in [
            "http://2130706433/",
            "http://127.1/",
            "http://0x7f.1/",
            "http://017700000001/",
            "http://[::ffff:7f00:1]/",
            "http://[::127.0.0.1]/",
            "http://LOCALHOST./",
            "http://240.0.0.1/",
            "http://[fd00:ec2::254]/",
        ] {
            assert_eq!(code(url), Some("webhook_target_refused"), "{url}");
        }
        for url in [
            "http://10.0.0.1/",
            "http://[fd12::1]/",
            "http://[2001:db8::1]/",
            "http://erp/",
        ] {
            assert_eq!(code(url), None, "{url}");
        }
    }

    #[test]
    fn the_allow_list_opts_hosts_and_addresses_in() {
        let p = policy(&["127.0.0.1", "[::1]"]);
        assert!(p.check_url("http://127.0.0.1:9/").is_ok());
        assert!(p.check_url("http://127.1:9/").is_ok(), "the same address");
        assert!(p.check_url("http://[::1]:9/").is_ok());
        assert!(p.check_url("http://127.0.0.2:9/").is_err());
        assert!(
            p.check_url("http://localhost:9/").is_err(),
            "names are listed by name"
        );
        assert_eq!(
            p.refused_address("127.0.0.1".parse().unwrap_or_else(|_| unreachable!())),
            None
        );
        let why = p.refused_address("169.254.169.254".parse().unwrap_or_else(|_| unreachable!()));
        assert_eq!(
            why.as_deref(),
            Some("169.254.169.254 is a link-local address")
        );
    }
}

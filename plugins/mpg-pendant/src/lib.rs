//! `mpg-pendant`: the transport for ESP32 MPG handwheel pendants that speak the 53-character
//! protocol (see README.md). One plugin instance per pendant: it connects (the pendant is the
//! TCP server), keeps the link alive, decodes what the operator does into `PendantEvent`s for
//! the core, and answers the pendant's position/progress polls from a status cache the core
//! pushes, so a poll never waits on the machine.

pub mod codec;
pub mod discovery;
pub mod transport;

pub use codec::{Decoded, Decoder, Dialect, Frame, Info, FRAME_LEN};
pub use transport::{Config, Transport};

use fresa_plugin_api::contract::PendantRequest;
use fresa_plugin_api::{Host, Plugin, PluginError};
use serde_json::{json, Value};

/// An instance is either the link to one pendant or, with config `{"discover": true}`, an mDNS
/// browser that lists the pendants on the LAN.
pub enum MpgPendant {
    Link(Transport),
    Discovery(discovery::Browser),
}

impl Plugin for MpgPendant {
    fn create(host: Host, config: Value) -> Result<Self, PluginError> {
        if config.get("discover") == Some(&Value::Bool(true)) {
            return discovery::Browser::start()
                .map(MpgPendant::Discovery)
                .map_err(|e| PluginError::new("unavailable", e));
        }
        let cfg: Config = serde_json::from_value(config)
            .map_err(|e| PluginError::new("invalid_config", format!("pendant config: {e}")))?;
        let transport = Transport::start(
            cfg,
            Box::new(move |e| host.emit(e)),
            Box::new(move |level, msg| host.log(level, msg)),
        )
        .map_err(|e| PluginError::new("invalid_config", e))?;
        Ok(MpgPendant::Link(transport))
    }

    fn call(&self, request: Value) -> Result<Value, PluginError> {
        if request.get("op").and_then(Value::as_str) == Some("shutdown") {
            return Ok(json!({}));
        }
        let req: PendantRequest = serde_json::from_value(request).map_err(|e| {
            PluginError::new(
                "invalid_request",
                format!(
                    "{e} (ops: pendant_status, confirm_upload, link_state, discovered, shutdown)"
                ),
            )
        })?;
        let transport = match (self, req) {
            (MpgPendant::Discovery(b), PendantRequest::Discovered) => {
                return Ok(json!({"pendants": b.list()}))
            }
            (MpgPendant::Discovery(_), _) => {
                return Err(PluginError::new(
                    "invalid_request",
                    "this is a discovery instance: only `discovered` is supported",
                ))
            }
            (MpgPendant::Link(_), PendantRequest::Discovered) => {
                return Err(PluginError::new(
                    "invalid_request",
                    "`discovered` needs an instance created with {\"discover\": true}",
                ))
            }
            (MpgPendant::Link(t), req) => (t, req),
        };
        let (t, req) = transport;
        Ok(match req {
            PendantRequest::PendantStatus {
                position,
                job,
                status_line,
            } => {
                t.set_status(position, job, status_line);
                json!({})
            }
            PendantRequest::ConfirmUpload { upload } => {
                json!({"sent": t.confirm_upload(upload)})
            }
            PendantRequest::LinkState => {
                json!({"connected": t.connected(), "address": t.address()})
            }
            PendantRequest::Discovered => json!({}),
        })
    }
}

fresa_plugin_api::export_plugin!(
    MpgPendant,
    name = "mpg-pendant",
    kinds = fresa_plugin_api::abi::KIND_PENDANT_TRANSPORT
);

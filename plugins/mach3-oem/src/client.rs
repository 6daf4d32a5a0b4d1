//! The plugin's side of the agent protocol: one TCP connection, handshake, batches. Every
//! socket operation has a timeout; any failure drops the connection (its state is unknown),
//! and the next batch reconnects.

use crate::mach3::{Call, Mach3Error};
use crate::protocol::{self, Auth, CallResult, Hello, Request, Response, Welcome};
use serde::de::DeserializeOwned;
use std::io::{BufReader, BufWriter};
use std::net::{TcpStream, ToSocketAddrs};
use std::time::Duration;

#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    #[error("cannot reach the Mach3 agent at {addr}: {message}")]
    Unreachable { addr: String, message: String },
    #[error("the Mach3 agent at {addr} refused the connection: {error}")]
    Refused { addr: String, error: Mach3Error },
}

struct Conn {
    reader: BufReader<TcpStream>,
    writer: BufWriter<TcpStream>,
}

pub struct AgentClient {
    addr: String,
    secret: String,
    timeout: Duration,
    conn: Option<Conn>,
    next_id: u64,
    /// The protocol features the agent named in its last hello.
    features: Vec<String>,
}

impl AgentClient {
    pub fn new(addr: String, secret: String, timeout: Duration) -> Self {
        AgentClient {
            addr,
            secret,
            timeout,
            conn: None,
            next_id: 1,
            features: Vec::new(),
        }
    }

    pub fn is_connected(&self) -> bool {
        self.conn.is_some()
    }

    /// Whether the agent of the current (or last) connection named `feature` in its hello.
    pub fn has_feature(&self, feature: &str) -> bool {
        self.features.iter().any(|f| f == feature)
    }

    pub fn disconnect(&mut self) {
        self.conn = None;
    }

    fn unreachable(&self, message: impl std::fmt::Display) -> LinkError {
        LinkError::Unreachable {
            addr: self.addr.clone(),
            message: message.to_string(),
        }
    }

    fn read<T: DeserializeOwned>(&self, conn: &mut Conn, what: &str) -> Result<T, LinkError> {
        let mut buf = Vec::new();
        match protocol::read_frame(&mut conn.reader, &mut buf) {
            Ok(true) => serde_json::from_slice(&buf).map_err(|e| {
                self.unreachable(format!(
                    "unexpected {what} from the agent ({e}): {}",
                    protocol::frame_excerpt(&buf)
                ))
            }),
            Ok(false) => {
                Err(self.unreachable(format!("connection closed while waiting for {what}")))
            }
            Err(e) => Err(self.unreachable(format!("while waiting for {what}: {e}"))),
        }
    }

    /// Connects and authenticates.
    pub fn connect(&mut self) -> Result<(), LinkError> {
        self.conn = None;
        let addrs: Vec<_> = self
            .addr
            .to_socket_addrs()
            .map_err(|e| self.unreachable(format!("bad address: {e}")))?
            .collect();
        let mut last = None;
        let mut stream = None;
        for a in addrs {
            match TcpStream::connect_timeout(&a, self.timeout) {
                Ok(s) => {
                    stream = Some(s);
                    break;
                }
                Err(e) => last = Some(e),
            }
        }
        let stream = stream.ok_or_else(|| {
            self.unreachable(
                last.map_or("the address resolves to nothing".into(), |e| e.to_string()),
            )
        })?;
        let setup = stream
            .set_read_timeout(Some(self.timeout))
            .and_then(|_| stream.set_write_timeout(Some(self.timeout)))
            .and_then(|_| stream.set_nodelay(true))
            .and_then(|_| stream.try_clone());
        let clone = setup.map_err(|e| self.unreachable(e))?;
        let mut conn = Conn {
            reader: BufReader::new(clone),
            writer: BufWriter::new(stream),
        };
        let hello: Hello = self.read(&mut conn, "the agent's hello")?;
        if hello.agent != protocol::AGENT_NAME {
            return Err(self.unreachable(format!(
                "{:?} answered, not {}: wrong port?",
                hello.agent,
                protocol::AGENT_NAME
            )));
        }
        let auth = Auth {
            protocol: protocol::PROTOCOL_VERSION,
            auth: protocol::sign(&self.secret, &hello.nonce),
        };
        protocol::write_frame(&mut conn.writer, &auth).map_err(|e| self.unreachable(e))?;
        let welcome: Welcome = self.read(&mut conn, "the handshake answer")?;
        if !welcome.ok {
            return Err(LinkError::Refused {
                addr: self.addr.clone(),
                error: welcome
                    .error
                    .unwrap_or_else(|| protocol::protocol_error("refused without a reason")),
            });
        }
        self.features = hello.features;
        self.conn = Some(conn);
        Ok(())
    }

    /// Sends one batch (connecting first if needed) and returns one result per call.
    pub fn batch(&mut self, calls: Vec<Call>, urgent: bool) -> Result<Vec<CallResult>, LinkError> {
        if self.conn.is_none() {
            self.connect()?;
        }
        let id = self.next_id;
        self.next_id += 1;
        let n = calls.len();
        let result = self.exchange(&Request { id, urgent, calls });
        let response = match result {
            Ok(r) => r,
            Err(e) => {
                self.conn = None;
                return Err(e);
            }
        };
        if let Some(e) = response.error {
            self.conn = None;
            return Err(self.unreachable(format!("the agent rejected a request: {e}")));
        }
        if response.id != Some(id) || response.results.len() != n {
            self.conn = None;
            return Err(self.unreachable(format!(
                "answer out of step (id {:?} with {} results for id {id} with {n} calls)",
                response.id,
                response.results.len()
            )));
        }
        Ok(response.results)
    }

    fn exchange(&mut self, req: &Request) -> Result<Response, LinkError> {
        let mut conn = self
            .conn
            .take()
            .ok_or_else(|| self.unreachable("not connected"))?;
        protocol::write_frame(&mut conn.writer, req).map_err(|e| self.unreachable(e))?;
        let r = self.read(&mut conn, "an answer");
        self.conn = Some(conn);
        r
    }
}

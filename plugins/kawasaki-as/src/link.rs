//! The PC side of both robot protocols over one TCP connection, with timeouts. Malformed robot
//! messages are reported to the caller (to log) and skipped.

use crate::codec::{self, LegacyMsg, LegacyReader, V1Cmd, V1Msg};
use std::io::{ErrorKind, Read, Write};
use std::net::{Shutdown, TcpStream, ToSocketAddrs};
use std::time::{Duration, Instant};

/// Why talking to the robot failed.
#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    #[error("cannot connect to the robot at {address}: {message}")]
    Connect { address: String, message: String },
    #[error("no answer from the robot within {0:?} while waiting for {1}")]
    Timeout(Duration, &'static str),
    #[error("the robot closed the connection while waiting for {0}")]
    Closed(&'static str),
    #[error("connection to the robot failed: {0}")]
    Io(#[from] std::io::Error),
    #[error("the robot answered {seq},err: {message}")]
    Refused { seq: u64, message: String },
    #[error("protocol error: {0}")]
    Protocol(String),
}

/// Opens the connection (first address that answers).
pub fn connect(address: &str, timeout: Duration) -> Result<TcpStream, LinkError> {
    let err = |message: String| LinkError::Connect {
        address: address.to_string(),
        message,
    };
    let addrs: Vec<_> = address
        .to_socket_addrs()
        .map_err(|e| err(e.to_string()))?
        .collect();
    let mut last = String::from("the address resolved to nothing");
    for a in addrs {
        match TcpStream::connect_timeout(&a, timeout) {
            Ok(s) => {
                // One small message per motion: never wait for Nagle.
                s.set_nodelay(true)?;
                return Ok(s);
            }
            Err(e) => last = e.to_string(),
        }
    }
    Err(err(last))
}

/// A socket whose read timeout is only changed when it must be (one system call less per
/// message on the hot path).
struct Socket {
    stream: TcpStream,
    timeout: Option<Duration>,
}

impl Socket {
    fn new(stream: TcpStream) -> Socket {
        Socket {
            stream,
            timeout: None,
        }
    }

    /// Reads with a deadline; `Ok(0)` is end of stream. The socket's timeout is the whole
    /// limit, so one read that trickles may overrun the deadline by up to one limit; the
    /// deadline is checked again between reads.
    fn read_some(
        &mut self,
        buf: &mut [u8],
        deadline: Instant,
        what: &'static str,
        limit: Duration,
    ) -> Result<usize, LinkError> {
        let left = deadline.saturating_duration_since(Instant::now());
        if left.is_zero() {
            return Err(LinkError::Timeout(limit, what));
        }
        if self.timeout != Some(limit) || left < limit / 2 {
            let t = if left < limit / 2 { left } else { limit };
            self.stream.set_read_timeout(Some(t))?;
            self.timeout = if t == limit { Some(limit) } else { None };
        }
        read_some(&mut self.stream, buf, deadline, what, limit)
    }
}

fn read_some(
    stream: &mut TcpStream,
    buf: &mut [u8],
    deadline: Instant,
    what: &'static str,
    limit: Duration,
) -> Result<usize, LinkError> {
    loop {
        if Instant::now() >= deadline {
            return Err(LinkError::Timeout(limit, what));
        }
        match stream.read(buf) {
            Ok(n) => return Ok(n),
            Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {
                return Err(LinkError::Timeout(limit, what))
            }
            Err(e) if e.kind() == ErrorKind::Interrupted => continue,
            Err(e) => return Err(e.into()),
        }
    }
}

/// The seed's robot program.
pub struct LegacyLink {
    sock: Socket,
    reader: LegacyReader,
    buf: Vec<u8>,
    /// Malformed messages seen (for the caller to log).
    pub garbage: Vec<String>,
}

impl LegacyLink {
    pub fn new(stream: TcpStream) -> LegacyLink {
        LegacyLink {
            sock: Socket::new(stream),
            reader: LegacyReader::default(),
            buf: vec![0; 4096],
            garbage: Vec::new(),
        }
    }

    fn recv(&mut self, limit: Duration, what: &'static str) -> Result<LegacyMsg, LinkError> {
        let deadline = Instant::now() + limit;
        let mut read_ended = true;
        loop {
            while let Some(m) = self.reader.next(read_ended) {
                match m {
                    Ok(m) => return Ok(m),
                    Err(text) => self.garbage.push(text),
                }
            }
            let n = self.sock.read_some(&mut self.buf, deadline, what, limit)?;
            if n == 0 {
                return Err(LinkError::Closed(what));
            }
            self.reader.push(&self.buf[..n]);
            read_ended = true;
        }
    }

    /// Waits for `Esperando inicio` and the part zero, in either order.
    pub fn greeting(&mut self, limit: Duration) -> Result<[f64; 3], LinkError> {
        let deadline = Instant::now() + limit;
        let (mut waiting, mut zero) = (false, None);
        while !(waiting && zero.is_some()) {
            let left = deadline.saturating_duration_since(Instant::now());
            let what = if waiting {
                "the part zero `x y z`"
            } else {
                "`Esperando inicio`"
            };
            match self.recv(left.max(Duration::from_millis(1)), what)? {
                LegacyMsg::Waiting => waiting = true,
                LegacyMsg::PartZero(z) => zero = Some(z),
                LegacyMsg::Done => {
                    return Err(LinkError::Protocol(
                        "the robot said `done` before the handshake (is another client streaming?)"
                            .into(),
                    ))
                }
            }
        }
        zero.ok_or(LinkError::Closed("the part zero"))
    }

    /// `inicio` -> `done`.
    pub fn start(&mut self, limit: Duration) -> Result<(), LinkError> {
        self.sock.stream.write_all(codec::LEGACY_START.as_bytes())?;
        self.expect_done(limit, "`done` after `inicio`")
    }

    pub fn send_move(&mut self, rapid: bool, to: [f64; 3]) -> Result<(), LinkError> {
        self.sock
            .stream
            .write_all(codec::legacy_move(rapid, to).as_bytes())?;
        Ok(())
    }

    pub fn expect_done(&mut self, limit: Duration, what: &'static str) -> Result<(), LinkError> {
        loop {
            match self.recv(limit, what)? {
                LegacyMsg::Done => return Ok(()),
                other => self.garbage.push(format!("{other:?}")),
            }
        }
    }

    /// `EXIT`, then close. Only when the robot waits for a command (nothing in flight).
    pub fn exit(mut self) {
        let _ = self.sock.stream.write_all(codec::LEGACY_EXIT.as_bytes());
        let _ = self.sock.stream.shutdown(Shutdown::Both);
    }

    /// Closes without a word (the robot program's receive fails and it ends).
    pub fn close(self) {
        let _ = self.sock.stream.shutdown(Shutdown::Both);
    }
}

/// The generated fresa-v1 program.
pub struct V1Link {
    sock: Socket,
    pending: Vec<u8>,
    buf: Vec<u8>,
    out: Vec<u8>,
    pub garbage: Vec<String>,
}

impl V1Link {
    pub fn new(stream: TcpStream) -> V1Link {
        V1Link {
            sock: Socket::new(stream),
            pending: Vec::new(),
            buf: vec![0; 4096],
            out: Vec::new(),
            garbage: Vec::new(),
        }
    }

    /// The next well-formed message; malformed lines are collected in `garbage`.
    pub fn recv(&mut self, limit: Duration, what: &'static str) -> Result<V1Msg, LinkError> {
        let deadline = Instant::now() + limit;
        loop {
            while let Some(nl) = self.pending.iter().position(|b| *b == b'\n') {
                let line: Vec<u8> = self.pending.drain(..=nl).collect();
                let text = String::from_utf8_lossy(&line);
                match V1Msg::parse(&text) {
                    Ok(m) => return Ok(m),
                    Err(e) => self.garbage.push(e),
                }
            }
            if self.pending.len() > 4096 {
                let junk: Vec<u8> = std::mem::take(&mut self.pending);
                self.garbage.push(format!(
                    "{} bytes without a line end: {:?}",
                    junk.len(),
                    String::from_utf8_lossy(&junk[..64])
                ));
            }
            let n = self.sock.read_some(&mut self.buf, deadline, what, limit)?;
            if n == 0 {
                return Err(LinkError::Closed(what));
            }
            self.pending.extend_from_slice(&self.buf[..n]);
        }
    }

    pub fn hello(&mut self, limit: Duration) -> Result<[f64; 3], LinkError> {
        match self.recv(limit, "the fresa-v1 greeting")? {
            V1Msg::Hello { part_zero } => Ok(part_zero),
            other => Err(LinkError::Protocol(format!(
                "expected the greeting `HELLO,fresa-v1,x,y,z`, got {other:?} (is the fresa-v1 program running?)"
            ))),
        }
    }

    /// `RUN,<tag>` -> the last sequence number the robot executed for that tag.
    pub fn run(&mut self, tag: &str, limit: Duration) -> Result<u64, LinkError> {
        self.send(&V1Cmd::Run {
            tag: tag.to_string(),
        })?;
        self.flush()?;
        loop {
            match self.recv(limit, "the answer to RUN")? {
                V1Msg::Run { tag: t, last_seq } if t == tag => return Ok(last_seq),
                V1Msg::Err { seq, message } => return Err(LinkError::Refused { seq, message }),
                other => self.garbage.push(format!("unexpected {other:?}")),
            }
        }
    }

    /// Queues a command; `flush` writes everything queued in one system call.
    pub fn send(&mut self, cmd: &V1Cmd) -> Result<(), LinkError> {
        self.out.extend_from_slice(cmd.encode().as_bytes());
        Ok(())
    }

    pub fn flush(&mut self) -> Result<(), LinkError> {
        if !self.out.is_empty() {
            self.sock.stream.write_all(&self.out)?;
            self.out.clear();
        }
        Ok(())
    }

    pub fn exit(mut self, limit: Duration) {
        let _ = self.send(&V1Cmd::Exit);
        if self.flush().is_ok() {
            let deadline = Instant::now() + limit;
            while let Ok(m) = self.recv(
                deadline
                    .saturating_duration_since(Instant::now())
                    .max(Duration::from_millis(1)),
                "bye",
            ) {
                if m == V1Msg::Bye {
                    break;
                }
            }
        }
        let _ = self.sock.stream.shutdown(Shutdown::Both);
    }

    pub fn close(self) {
        let _ = self.sock.stream.shutdown(Shutdown::Both);
    }
}

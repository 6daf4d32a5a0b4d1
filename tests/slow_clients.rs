//! Slow clients cannot exhaust the server (issue 12). With a 2 s header read timeout, a cap of
//! 64 connections and a 2 s upload idle timeout: a few hundred slowloris connections (silent,
//! half a request line, half a head) hold at most the cap of the server's sockets while
//! `/healthz` and a machine stop still answer 200; a half-sent request is closed by the server;
//! a stalled upload is dropped with a JSON error and leaves no temporary file; reaching the cap
//! (and clearing it) is logged.

#![cfg(unix)]
#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::{wait_for, Server};
use serde_json::json;
use std::io::{ErrorKind, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::time::Duration;

const T: Duration = Duration::from_secs(30);
const MAX_CONNECTIONS: usize = 64;
const SLOWLORIS: usize = 300;

/// A server whose connection limits are small enough to hit quickly. The idle timeout is long,
/// so a connection closed within seconds was closed by the header read timeout.
fn server(max_connections: usize) -> Server {
    let mut s = Server::unstarted(Default::default());
    s.write_config(&format!(
        "header_read_timeout_secs = 2\nidle_timeout_secs = 60\nupload_idle_timeout_secs = 2\n\
         max_connections = {max_connections}\n"
    ));
    s.spawn()
        .unwrap_or_else(|e| panic!("server did not start: {e}"));
    s
}

fn addr(s: &Server) -> SocketAddr {
    let port: u16 = s.base.rsplit(':').next().unwrap().parse().unwrap();
    SocketAddr::from(([127, 0, 0, 1], port))
}

/// A raw connection that sent `head` (possibly nothing) and then stalls.
fn stalled(s: &Server, head: &[u8]) -> TcpStream {
    let mut c = TcpStream::connect_timeout(&addr(s), T).expect("connect");
    if !head.is_empty() {
        c.write_all(head).expect("send a partial request");
    }
    c.set_read_timeout(Some(Duration::from_millis(50))).unwrap();
    c
}

/// Reads what is there; `Some(all bytes read so far)` once the server closed the connection.
fn closed_by_server(c: &mut TcpStream, got: &mut Vec<u8>) -> Option<Vec<u8>> {
    let mut buf = [0u8; 4096];
    match c.read(&mut buf) {
        Ok(0) => Some(got.clone()),
        Ok(n) => {
            got.extend_from_slice(&buf[..n]);
            None
        }
        Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => None,
        Err(e) if e.kind() == ErrorKind::ConnectionReset => Some(got.clone()),
        Err(e) => panic!("reading from the server: {e}"),
    }
}

/// Sockets the server process has open (its listener, clients, plugin links).
fn server_sockets(s: &Server) -> usize {
    let pid = s.pid().expect("server running");
    std::fs::read_dir(format!("/proc/{pid}/fd"))
        .expect("list the server's descriptors")
        .filter_map(|e| std::fs::read_link(e.ok()?.path()).ok())
        .filter(|l| l.to_string_lossy().starts_with("socket:"))
        .count()
}

/// A client with no connection pool: every request queues like a new client would.
fn fresh_client() -> reqwest::blocking::Client {
    reqwest::blocking::Client::builder()
        .pool_max_idle_per_host(0)
        .timeout(Duration::from_secs(60))
        .build()
        .unwrap()
}

#[test]
fn slowloris_holds_at_most_the_cap_and_healthz_and_stop_still_answer() {
    let s = server(MAX_CONNECTIONS);
    let m = s.sim("m", 0.0);
    let heads: [&[u8]; 3] = [
        b"",
        b"GET /healthz HT",
        b"GET /healthz HTTP/1.1\r\nHost: x\r\n",
    ];
    let flood: Vec<TcpStream> = (0..SLOWLORIS)
        .map(|i| stalled(&s, heads[i % heads.len()]))
        .collect();
    s.wait_log(T, "connection limit reached");
    // The server holds the cap's worth of them, not all: the rest wait in the kernel backlog.
    let sockets = server_sockets(&s);
    assert!(
        sockets <= MAX_CONNECTIONS + 8,
        "{sockets} sockets open in the server with max_connections = {MAX_CONNECTIONS}"
    );

    let http = fresh_client();
    let r = http.get(s.url("/healthz")).send().expect("GET /healthz");
    assert_eq!(r.status().as_u16(), 200, "/healthz under a slowloris flood");
    let r = http
        .post(s.url(&format!("/api/v1/machines/{}/commands", m.id)))
        .json(&json!({"command": "stop"}))
        .send()
        .expect("POST stop");
    let status = r.status().as_u16();
    assert_eq!(status, 200, "stop under a slowloris flood: {:?}", r.text());
    drop(flood);
    assert!(
        !s.log().contains("Too many open files"),
        "the server ran out of descriptors:\n{}",
        s.log()
    );
}

#[test]
fn a_half_sent_request_is_closed_after_the_header_read_timeout() {
    let s = server(MAX_CONNECTIONS);
    let mut c = stalled(&s, b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ");
    let mut got = Vec::new();
    let answer = wait_for(T, "the server to close a half-sent request", || {
        closed_by_server(&mut c, &mut got)
    });
    // Whatever it said before closing, it did not serve the request.
    let text = String::from_utf8_lossy(&answer);
    assert!(
        !text.contains("\"status\""),
        "served a half-sent request: {text}"
    );
    // The server is fine afterwards.
    s.get("/healthz").expect(200);
}

#[test]
fn a_stalled_upload_is_dropped_with_a_json_error_and_leaves_no_temp_file() {
    let s = server(MAX_CONNECTIONS);
    let m = s.sim("m", 0.0);
    let mut c = stalled(
        &s,
        format!(
            "POST /api/v1/jobs?machine={}&name=stalled HTTP/1.1\r\nHost: 127.0.0.1\r\n\
             Content-Type: text/plain\r\nContent-Length: 100000\r\n\r\nG21 G90\nG0 X1\n",
            m.id
        )
        .as_bytes(),
    );
    let mut got = Vec::new();
    let answer = wait_for(T, "the stalled upload's answer", || {
        let closed = closed_by_server(&mut c, &mut got);
        let text = String::from_utf8_lossy(&got).into_owned();
        (closed.is_some() || text.contains("upload_timeout")).then_some(text)
    });
    assert!(
        answer.starts_with("HTTP/1.1 408") && answer.contains("\"code\":\"upload_timeout\""),
        "expected 408 upload_timeout, got {answer:?}"
    );
    wait_for(T, "no .upload-*.tmp in the programs directory", || {
        s.upload_temp_files().is_empty().then_some(())
    });
    s.assert_no_jobs();
}

#[test]
fn reaching_the_connection_cap_is_logged_and_so_is_clearing_it() {
    let s = server(8);
    let held: Vec<TcpStream> = (0..20).map(|_| stalled(&s, b"")).collect();
    let line = s.wait_log(T, "connection limit reached");
    assert!(line.contains("max_connections"), "{line}");
    drop(held);
    s.wait_log(T, "connection limit cleared");
    s.get("/healthz").expect(200);
}

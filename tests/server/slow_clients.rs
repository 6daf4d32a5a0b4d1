//! Slow clients cannot exhaust the server (issue 12). With a 2 s header read timeout, a cap of
//! 64 connections and a 2 s upload idle timeout: a few hundred slowloris connections (silent,
//! half a request line, half a head) hold at most the cap of the server's sockets while
//! `/healthz` and a machine stop still answer 200; a half-sent request is closed by the server;
//! a stalled upload is dropped with a JSON error and leaves no temporary file; reaching the cap
//! (and clearing it) is logged; idle connections are closed, a quiet event stream is not.

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
    Server::start_with_config(&format!(
        "header_read_timeout_secs = 2\nidle_timeout_secs = 60\nupload_idle_timeout_secs = 2\n\
         max_connections = {max_connections}\n"
    ))
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

/// A connection that sends nothing, and one kept alive after its answer that sends nothing
/// more, are closed by the idle check (`idle_timeout_secs`, here 1 s) long before the header
/// read timeout (here 60 s) would; a connection whose request is in progress (an event stream
/// quiet for longer than that) is not.
#[test]
fn idle_connections_are_closed_and_a_quiet_event_stream_is_not() {
    let s = Server::start_with_config("header_read_timeout_secs = 60\nidle_timeout_secs = 1\n");
    let mut silent = stalled(&s, b"");
    let mut kept = stalled(&s, b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n");
    // An event stream from the end of the log: nothing to send while nothing happens.
    let mut stream = stalled(
        &s,
        b"GET /api/v1/events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n",
    );
    let (mut silent_got, mut kept_got, mut stream_got) = (Vec::new(), Vec::new(), Vec::new());
    let kept_answer = wait_for(T, "the idle connections to be closed", || {
        let silent_closed = closed_by_server(&mut silent, &mut silent_got);
        let kept_closed = closed_by_server(&mut kept, &mut kept_got);
        assert!(
            closed_by_server(&mut stream, &mut stream_got).is_none(),
            "the event stream was closed while its request was in progress: {}",
            String::from_utf8_lossy(&stream_got)
        );
        silent_closed.and(kept_closed)
    });
    assert!(silent_got.is_empty(), "{silent_got:?}");
    assert!(
        kept_answer.starts_with(b"HTTP/1.1 200"),
        "{}",
        String::from_utf8_lossy(&kept_answer)
    );
    assert!(
        stream_got.starts_with(b"HTTP/1.1 200"),
        "{}",
        String::from_utf8_lossy(&stream_got)
    );
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

/// A head sent a byte at a time keeps bytes moving, so the idle check (60 s here) never closes
/// the connection; the head check does, once the header read timeout (2 s) has passed since the
/// previous response ended, and not before. A kept-alive connection, so the wait counts from
/// that response, not from connecting.
#[test]
fn a_head_sent_a_byte_at_a_time_is_closed_after_the_header_read_timeout() {
    let s = server(MAX_CONNECTIONS);
    let mut c = stalled(&s, b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n");
    let mut got = Vec::new();
    wait_for(T, "the first request's answer", || {
        assert!(closed_by_server(&mut c, &mut got).is_none(), "closed early");
        String::from_utf8_lossy(&got)
            .contains("\"ok\"")
            .then_some(())
    });
    let answered = std::time::Instant::now();
    got.clear();
    c.write_all(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
        .unwrap();
    let answer = wait_for(
        T,
        "the server to close a head sent a byte at a time",
        || {
            // One byte about every 50 ms (the read timeout); a write after the close may fail.
            let _ = c.write_all(b"a");
            closed_by_server(&mut c, &mut got)
        },
    );
    assert!(
        answered.elapsed() >= Duration::from_secs(2),
        "closed {:?} after the previous answer, before the header read timeout",
        answered.elapsed()
    );
    let text = String::from_utf8_lossy(&answer);
    assert!(
        !text.contains("HTTP/1.1 200"),
        "served the slow head: {text}"
    );
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

// ---- Event streams cannot take the connection slots a stop needs (issue 23) ----

/// Event streams the tests open: more than `max_connections` (512) at its default.
const STREAMS: usize = 600;
/// `max_event_streams` at the defaults: half of `max_connections`.
const DEFAULT_MAX_EVENT_STREAMS: usize = 256;

/// A raw `GET /api/v1/events` on its own connection (no reader thread: hundreds are cheap).
fn raw_stream(s: &Server, extra_headers: &str) -> TcpStream {
    let a = addr(s);
    let mut c = TcpStream::connect_timeout(&a, T).expect("connect");
    write!(
        c,
        "GET /api/v1/events HTTP/1.1\r\nHost: {a}\r\n{extra_headers}\r\n"
    )
    .expect("send the stream request");
    c.set_read_timeout(Some(Duration::from_millis(5))).unwrap();
    c
}

/// What a raw stream request got: its status, and what arrived of the answer by then (for a
/// refusal: all of it, since the server closes the connection after it).
#[derive(Debug)]
struct Answer {
    status: u16,
    text: String,
}

/// Reads every connection's answer head; a refused one (not 200) is read to its end, which
/// also checks that the server closes it. Panics after the deadline naming how many got none.
fn answers(conns: &mut [TcpStream], deadline: Duration) -> Vec<Answer> {
    let start = std::time::Instant::now();
    let mut got: Vec<Vec<u8>> = vec![Vec::new(); conns.len()];
    let mut done: Vec<Option<Answer>> = (0..conns.len()).map(|_| None).collect();
    let mut buf = [0u8; 4096];
    while done.iter().any(Option::is_none) {
        let left = done.iter().filter(|d| d.is_none()).count();
        assert!(
            start.elapsed() < deadline,
            "{left} of {} stream requests got no answer within {deadline:?}",
            conns.len()
        );
        for (i, c) in conns.iter_mut().enumerate() {
            if done[i].is_some() {
                continue;
            }
            let closed = match c.read(&mut buf) {
                Ok(0) => true,
                Ok(n) => {
                    got[i].extend_from_slice(&buf[..n]);
                    false
                }
                Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => false,
                Err(e) if e.kind() == ErrorKind::ConnectionReset => true,
                Err(e) => panic!("reading a stream's answer: {e}"),
            };
            let text = String::from_utf8_lossy(&got[i]).into_owned();
            if !text.contains("\r\n\r\n") {
                assert!(!closed, "closed without an answer: {text:?}");
                continue;
            }
            let status: u16 = text
                .get(9..12)
                .and_then(|s| s.parse().ok())
                .unwrap_or_else(|| panic!("not an HTTP answer: {text:?}"));
            if status == 200 || closed {
                done[i] = Some(Answer { status, text });
            }
        }
    }
    done.into_iter().map(Option::unwrap).collect()
}

/// Reads a raw stream until `needle` arrives.
fn read_until(c: &mut TcpStream, needle: &str, what: &str) -> String {
    let mut got = Vec::new();
    wait_for(T, what, || {
        let mut buf = [0u8; 4096];
        match c.read(&mut buf) {
            Ok(0) => panic!("stream closed while waiting for {what}"),
            Ok(n) => got.extend_from_slice(&buf[..n]),
            Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {}
            Err(e) => panic!("reading the stream: {e}"),
        }
        let text = String::from_utf8_lossy(&got);
        text.contains(needle).then(|| text.into_owned())
    })
}

/// A client whose every request must be answered within a generous 5 s (a stop that waits in
/// the listen backlog behind event streams never is).
fn prompt_client() -> reqwest::blocking::Client {
    reqwest::blocking::Client::builder()
        .pool_max_idle_per_host(0)
        .timeout(Duration::from_secs(5))
        .build()
        .unwrap()
}

#[test]
fn a_stop_is_answered_with_600_event_streams_open_at_the_defaults() {
    let s = Server::start();
    let m = s.sim("m", 0.0);
    let mut conns: Vec<TcpStream> = (0..STREAMS).map(|_| raw_stream(&s, "")).collect();
    let got = answers(&mut conns, Duration::from_secs(60));
    let open: Vec<usize> = (0..STREAMS).filter(|&i| got[i].status == 200).collect();
    assert_eq!(
        open.len(),
        DEFAULT_MAX_EVENT_STREAMS,
        "streams accepted at the defaults"
    );
    for a in got.iter().filter(|a| a.status != 200) {
        assert!(
            a.text.starts_with("HTTP/1.1 503")
                && a.text.contains("\"code\":\"too_many_streams\"")
                && a.text.contains("max_event_streams")
                && a.text.to_ascii_lowercase().contains("retry-after:"),
            "a stream beyond the cap: {:?}",
            a.text
        );
    }

    // Every stream is still open, and control gets through.
    let http = prompt_client();
    let r = http.get(s.url("/healthz")).send().expect("GET /healthz");
    assert_eq!(r.status().as_u16(), 200);
    let r = http
        .post(s.url(&format!("/api/v1/machines/{}/commands", m.id)))
        .json(&json!({"command": "stop"}))
        .send()
        .expect("POST stop with 600 event streams open");
    assert_eq!(r.status().as_u16(), 200, "stop: {:?}", r.text());
    // The audit log says it was carried out, on a stream that was open all along.
    let first = &mut conns[open[0]];
    let seen = read_until(first, "event: machine.command", "the stop's audit event");
    assert!(seen.contains("\"stop\""), "{seen}");

    // A closed stream's slot is free again.
    for &i in &open[..8] {
        let _ = conns[i].shutdown(std::net::Shutdown::Both);
    }
    wait_for(T, "a new stream once others closed", || {
        let mut c = [raw_stream(&s, "")];
        let a = answers(&mut c, T).pop().unwrap();
        (a.status == 200).then_some(())
    });
    assert!(
        s.log().contains("event stream limit reached"),
        "{}",
        s.log()
    );
}

#[test]
fn a_stop_is_answered_while_streams_and_silent_clients_hold_every_connection() {
    // The defaults: 512 connections, 256 of them streams, a 30 s header read timeout.
    let s = Server::start();
    let m = s.sim("m", 0.0);
    let mut streams: Vec<TcpStream> = (0..300).map(|_| raw_stream(&s, "")).collect();
    let got = answers(&mut streams, Duration::from_secs(60));
    let open: Vec<usize> = (0..got.len()).filter(|&i| got[i].status == 200).collect();
    assert_eq!(open.len(), DEFAULT_MAX_EVENT_STREAMS);
    // More silent connections than the connection slots: every one is taken, and more wait.
    let silent: Vec<TcpStream> = (0..600).map(|_| stalled(&s, b"")).collect();
    s.wait_log(T, "connection limit reached");

    let http = prompt_client();
    let r = http
        .post(s.url(&format!("/api/v1/machines/{}/commands", m.id)))
        .json(&json!({"command": "stop"}))
        .send()
        .expect("POST stop while every connection is held");
    assert_eq!(r.status().as_u16(), 200, "stop: {:?}", r.text());
    let r = http.get(s.url("/healthz")).send().expect("GET /healthz");
    assert_eq!(r.status().as_u16(), 200);
    let seen = read_until(
        &mut streams[open[0]],
        "event: machine.command",
        "the stop's audit event",
    );
    assert!(seen.contains("\"stop\""), "{seen}");
    // Room was made by closing silent connections, never a stream, and the server holds
    // about the caps: the streams' connections hold places of their own (`max_event_streams`),
    // outside `max_connections`.
    let sockets = server_sockets(&s);
    assert!(
        sockets <= 512 + DEFAULT_MAX_EVENT_STREAMS + 40,
        "{sockets} sockets open"
    );
    let metrics = http.get(s.url("/metrics")).send().unwrap().text().unwrap();
    assert!(metrics.contains("fresa_event_streams 256\n"), "{metrics}");
    assert!(
        !metrics.contains("fresa_connections_closed_at_cap_total 0\n"),
        "{metrics}"
    );
    drop(silent);
}

/// Streams have a cap of their own (issue 29): with `max_event_streams` far above
/// `max_connections`, every stream is served, and the connection slots all stay for short
/// requests: a stop is answered while silent clients hold more than the connection cap.
#[test]
fn streams_beyond_max_connections_leave_every_connection_slot_for_a_stop() {
    let s = Server::start_with_config("max_connections = 16\nmax_event_streams = 64\n");
    let m = s.sim("m", 0.0);
    // Eight at a time, each batch answered before the next: at the connection cap the oldest
    // connection without a request in progress makes room, which a stream whose head was not
    // read yet could be.
    let mut streams: Vec<TcpStream> = Vec::new();
    for _ in 0..8 {
        let mut batch: Vec<TcpStream> = (0..8).map(|_| raw_stream(&s, "")).collect();
        let statuses: Vec<u16> = answers(&mut batch, T).iter().map(|a| a.status).collect();
        assert!(statuses.iter().all(|&c| c == 200), "{statuses:?}");
        streams.extend(batch);
    }
    // A 65th is over the stream cap.
    let mut extra = [raw_stream(&s, "")];
    assert_eq!(answers(&mut extra, T)[0].status, 503);
    let silent: Vec<TcpStream> = (0..24).map(|_| stalled(&s, b"")).collect();
    s.wait_log(T, "connection limit reached");
    let http = prompt_client();
    let r = http
        .post(s.url(&format!("/api/v1/machines/{}/commands", m.id)))
        .json(&json!({"command": "stop"}))
        .send()
        .expect("POST stop while streams and silent clients are open");
    assert_eq!(r.status().as_u16(), 200, "stop: {:?}", r.text());
    let seen = read_until(
        &mut streams[63],
        "event: machine.command",
        "the stop's audit event",
    );
    assert!(seen.contains("\"stop\""), "{seen}");
    let metrics = http.get(s.url("/metrics")).send().unwrap().text().unwrap();
    assert!(metrics.contains("fresa_event_streams 64\n"), "{metrics}");
    drop(silent);
}

#[test]
fn one_token_cannot_take_every_event_stream() {
    let s = Server::start();
    let viewer = s.create_token("viewer", "screens");
    let auth = format!("Authorization: Bearer {viewer}\r\n");
    let mut conns: Vec<TcpStream> = (0..33).map(|_| raw_stream(&s, &auth)).collect();
    let got = answers(&mut conns, T);
    let statuses: Vec<u16> = got.iter().map(|a| a.status).collect();
    assert_eq!(
        statuses.iter().filter(|&&c| c == 200).count(),
        32,
        "{statuses:?}"
    );
    let refused = got.iter().find(|a| a.status != 200).unwrap();
    assert!(
        refused.text.starts_with("HTTP/1.1 429")
            && refused.text.contains("\"code\":\"too_many_streams\"")
            && refused.text.contains("max_event_streams_per_client")
            && refused.text.contains("screens"),
        "{:?}",
        refused.text
    );
    // Others still stream.
    let mut other = [raw_stream(&s, "")];
    assert_eq!(answers(&mut other, T)[0].status, 200);
}

/// Not a test: STOP latency with nothing else open, with 600 event streams, and with 300
/// streams and 600 silent connections (the figures in issue 23).
/// Run with `cargo test -p fresa-tests --test blackbox -- --ignored --nocapture server::slow_clients::stop_latency`.
#[test]
#[ignore]
fn stop_latency_with_600_event_streams_open() {
    for (streams, silent) in [(0, 0), (STREAMS, 0), (300, 600)] {
        let s = Server::start();
        let m = s.sim("m", 0.0);
        let conns: Vec<TcpStream> = (0..streams).map(|_| raw_stream(&s, "")).collect();
        let quiet: Vec<TcpStream> = (0..silent).map(|_| stalled(&s, b"")).collect();
        if streams > 0 {
            // Until the server has taken what it will of them.
            wait_for(T, "a connection or stream limit reached", || {
                let log = s.log();
                (log.contains("connection limit reached")
                    || log.contains("event stream limit reached"))
                .then_some(())
            });
        }
        let http = reqwest::blocking::Client::builder()
            .pool_max_idle_per_host(0)
            .timeout(Duration::from_secs(10))
            .build()
            .unwrap();
        let mut took = Vec::new();
        let mut unanswered = 0;
        for _ in 0..100 {
            let t = std::time::Instant::now();
            let r = http
                .post(s.url(&format!("/api/v1/machines/{}/commands", m.id)))
                .json(&json!({"command": "stop"}))
                .send();
            match r {
                Ok(r) if r.status().is_success() => took.push(t.elapsed()),
                _ => {
                    unanswered += 1;
                    if unanswered == 3 {
                        break;
                    }
                }
            }
        }
        took.sort();
        let pct = |p: usize| took.get((took.len() * p / 100).min(took.len().saturating_sub(1)));
        println!(
            "STOP with {streams} event streams and {silent} silent connections open: {} \
             answered, {unanswered} not within 10 s; \
             p50 {:?}, p99 {:?}, max {:?}",
            took.len(),
            pct(50),
            pct(99),
            took.last()
        );
        drop((conns, quiet));
    }
}

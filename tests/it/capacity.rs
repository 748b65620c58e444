//! Capacity the operator can always reach (issue 29, findings 4 and 5), against `hydrolens serve` run as the real
//! binary (its memory is its own) over real sockets: a flood of event streams, a crowd of idle connections, slow and
//! stalled downloads. Each prints what the closing note reports.

use std::time::{Duration, Instant};

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

use crate::support::{ServeProcess, TOKEN, metric, wait_for};

/// `hydrolens serve` on a drive in speed mode at a closed Modbus port, recording into `dir/rec`.
struct Serve(ServeProcess);

impl std::ops::Deref for Serve {
    type Target = ServeProcess;
    fn deref(&self) -> &ServeProcess {
        &self.0
    }
}

impl Serve {
    fn start(dir: &std::path::Path, http_extra: &str) -> Serve {
        let text = format!(
            "[http]\nbind = \"127.0.0.1:0\"\ntoken = \"{TOKEN}\"\n{http_extra}\n[recording]\ndir = {d:?}\n\n\
             [[drives]]\nname = \"pump1\"\naddress = \"127.0.0.1:9\"\npoll_ms = 10\ntimeout_ms = 100\n\
             [drives.control]\nmode = \"speed\"\ntarget_omega_rad_s = 30.0\n",
            d = dir.join("rec").display().to_string()
        );
        Serve(ServeProcess::start(dir, &text))
    }
}

/// Sends `request` on a new connection and reads up to the end of the response headers (5 s at most): the status
/// code and the still-open connection.
async fn open(addr: std::net::SocketAddr, request: &str) -> Option<(u16, TcpStream)> {
    let go = async {
        let mut s = TcpStream::connect(addr).await.ok()?;
        s.write_all(request.as_bytes()).await.ok()?;
        response_head(s).await
    };
    tokio::time::timeout(Duration::from_secs(5), go).await.ok().flatten()
}

/// As [`open`], from the loopback address `from`.
async fn open_from(addr: std::net::SocketAddr, from: [u8; 4], request: &str) -> Option<(u16, TcpStream)> {
    let go = async { response_head(connect_from(addr, from, request).await).await };
    tokio::time::timeout(Duration::from_secs(5), go).await.ok().flatten()
}

/// Reads up to the end of the response headers: the status code and the still-open connection.
async fn response_head(mut s: TcpStream) -> Option<(u16, TcpStream)> {
    let mut head = Vec::new();
    let mut byte = [0u8; 1];
    while !head.ends_with(b"\r\n\r\n") {
        if s.read(&mut byte).await.ok()? == 0 {
            break;
        }
        head.push(byte[0]);
    }
    let code = String::from_utf8_lossy(&head).split_whitespace().nth(1)?.parse().ok()?;
    Some((code, s))
}

/// A connection from the loopback address `from` (a crowd spread over many addresses) that has sent `request`.
async fn connect_from(addr: std::net::SocketAddr, from: [u8; 4], request: &str) -> TcpStream {
    let socket = tokio::net::TcpSocket::new_v4().expect("socket");
    socket.bind(std::net::SocketAddr::from((from, 0))).expect("a loopback address");
    let mut c = socket.connect(addr).await.expect("connect");
    c.write_all(request.as_bytes()).await.expect("write");
    c
}

/// Three times: the operator's `/api/status` on a new connection (an ordinary one: 200, not the reserve's 503), and
/// its `/healthz` and target POST, beside `crowd` (printed).
async fn operator_gets_in(s: &Serve, crowd: &str) {
    for _ in 0..3 {
        let t = Instant::now();
        let status = open(s.addr, "GET /api/status HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n").await.map(|(c, _)| c);
        let took = t.elapsed();
        let [(health, _), (target, _)] = operator(&s.url).await;
        eprintln!("{crowd}: /api/status {status:?} in {took:?}, /healthz {health}, target {target}");
        assert_eq!(status, Some(200), "an ordinary connection for the operator, on every route");
        assert_eq!((health, target), (200, 200));
    }
}

const EVENTS: &str = "GET /api/events HTTP/1.1\r\nHost: 127.0.0.1\r\nAccept: text/event-stream\r\n\r\n";

/// A `/healthz` and a target POST, each on a new connection, 5 s at most: their codes and times.
async fn operator(url: &str) -> [(u16, Duration); 2] {
    let client =
        reqwest::Client::builder().timeout(Duration::from_secs(5)).pool_max_idle_per_host(0).build().expect("client");
    let t = Instant::now();
    let health = client.get(format!("{url}/healthz")).send().await.map_or(0, |r| r.status().as_u16());
    let health_took = t.elapsed();
    let t = Instant::now();
    let target = client
        .post(format!("{url}/api/drives/pump1/target"))
        .bearer_auth(TOKEN)
        .json(&serde_json::json!({ "target_omega_rad_s": 20.0 }))
        .send()
        .await
        .map_or(0, |r| r.status().as_u16());
    [(health, health_took), (target, t.elapsed())]
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flood_of_event_streams_gets_503_beyond_the_cap_and_the_operator_still_gets_through() {
    let dir = tempfile::tempdir().expect("tmp");
    let s = Serve::start(dir.path(), "");
    let rss_before = s.rss_mb();
    let mut held = Vec::new();
    let (mut ok, mut busy, mut lost) = (0, 0, 0);
    for _ in 0..520 {
        match open(s.addr, EVENTS).await {
            Some((200, c)) => {
                ok += 1;
                held.push(c);
            }
            Some((503, _)) => busy += 1,
            _ => lost += 1,
        }
    }
    // one address holds its share (three quarters of the cap), another the rest
    assert_eq!((ok, busy, lost), (48, 472, 0), "one address's share (48 of 64) answers the rest at once");
    let (mut other_ok, mut other_busy) = (0, 0);
    for _ in 0..20 {
        let c = connect_from(s.addr, [127, 0, 0, 2], EVENTS).await;
        match tokio::time::timeout(Duration::from_secs(5), response_head(c)).await.ok().flatten() {
            Some((200, c)) => {
                other_ok += 1;
                held.push(c);
            }
            Some((503, _)) => other_busy += 1,
            _ => lost += 1,
        }
    }
    let rss_during = s.rss_mb();
    let [(health, health_took), (target, target_took)] = operator(&s.url).await;
    eprintln!(
        "520 event streams asked from one address: {ok} open, {busy} refused with 503; 20 from another: \
         {other_ok} open, {other_busy} refused; {lost} unanswered; RSS {rss_before:.1} → {rss_during:.1} MB; \
         meanwhile /healthz {health} in {health_took:?}, target POST {target} in {target_took:?}"
    );
    assert_eq!((other_ok, other_busy, lost), (16, 4, 0), "the cap (http.max_event_streams = 64) answers the rest");
    assert_eq!((health, target), (200, 200), "the operator gets through");
    let m = s.metrics().await;
    assert_eq!(metric(&m, "hydrolens_http_event_streams"), Some(64.0), "{m}");
    // a closed stream frees its place (four of the first address's)
    held.drain(..4);
    let mut reopened = None;
    for _ in 0..100 {
        if let Some((200, c)) = open(s.addr, EVENTS).await {
            reopened = Some(c);
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert!(reopened.is_some(), "a place freed is taken again");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn with_every_connection_held_the_control_and_health_routes_keep_a_reserve() {
    let dir = tempfile::tempdir().expect("tmp");
    let s = Serve::start(dir.path(), "max_connections = 16\nmax_event_streams = 16\n");
    // sixteen streams hold every ordinary connection (from two addresses: one holds at most 12)
    let mut held = Vec::new();
    for k in 0..16 {
        let c = connect_from(s.addr, [127, 0, 0, 2 + k % 2], EVENTS).await;
        let (code, c) =
            tokio::time::timeout(Duration::from_secs(5), response_head(c)).await.ok().flatten().expect("a stream");
        assert_eq!(code, 200);
        held.push(c);
    }
    let [(health, health_took), (target, target_took)] = operator(&s.url).await;
    let status = open(s.addr, "GET /api/status HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n").await.map(|(c, _)| c);
    let ready = open(s.addr, "GET /readyz HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n").await.map(|(c, _)| c);
    eprintln!(
        "16 of 16 connections held: /healthz {health} in {health_took:?}, target POST {target} in \
         {target_took:?}, /readyz {ready:?}, /api/status {status:?}"
    );
    assert_eq!((health, target), (200, 200), "the reserve serves the control and health routes");
    assert_eq!(ready, Some(503), "/readyz answers (not ready: the drive is down)");
    assert_eq!(status, Some(503), "the read-only side waits for an ordinary connection");
    drop(held);
}

/// As many slow downloads as may run at once (`MAX_DOWNLOADS`, 8, from two addresses: one holds at most six) hold a
/// small buffer each, and the next waits (503).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn slow_downloads_of_a_64_mb_recording_hold_a_small_buffer_each_and_the_next_waits() {
    let dir = tempfile::tempdir().expect("tmp");
    let s = Serve::start(dir.path(), "");
    const SIZE: usize = 64 << 20;
    let row = "1.0,2.0,3.0,4.0,5.0,6.0,7.0,8.0,9.0,10.0,11.0,12.0,13.0,14.0,15.0,16.0\n";
    let mut text = String::with_capacity(SIZE);
    while text.len() + row.len() <= SIZE {
        text.push_str(row);
    }
    std::fs::write(dir.path().join("rec").join("pump1-1.csv"), &text).expect("a large recording");
    let rss_before = s.rss_mb();
    let get = "GET /api/recordings/pump1-1.csv HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n";
    // one address holds its share (three quarters), another the rest
    let share = hydrolens::http::bounded::address_share(hydrolens::http::MAX_DOWNLOADS);
    let mut readers = Vec::new();
    for k in 0..hydrolens::http::MAX_DOWNLOADS {
        let from = if k < share { [127, 0, 0, 1] } else { [127, 0, 0, 2] };
        let (code, mut c) = open_from(s.addr, from, get).await.expect("a download starts");
        assert_eq!(code, 200);
        let mut first = vec![0u8; 64 * 1024];
        c.read_exact(&mut first).await.expect("the first bytes");
        readers.push(c);
    }
    let next = open_from(s.addr, [127, 0, 0, 3], get).await.map(|(c, _)| c);
    assert_eq!(next, Some(503), "the next download waits");
    // the eight now read nothing: what the service holds for them, once its memory has stopped moving (the same
    // to 0.1 MB over ten looks, 200 ms; a service that read whole files in would still be growing)
    let (last, same) = (std::cell::Cell::new(f64::NAN), std::cell::Cell::new(0u32));
    let settled = wait_for(Duration::from_secs(15), || {
        let (last, same, rss) = (&last, &same, s.rss_mb());
        async move {
            same.set(if (rss - last.replace(rss)).abs() <= 0.1 { same.get() + 1 } else { 0 });
            same.get() >= 10
        }
    })
    .await;
    assert!(settled.is_some(), "the service's memory settles with eight stalled downloads: {} MB", s.rss_mb());
    let rss_held = s.rss_mb();
    let [(health, _), (target, _)] = operator(&s.url).await;
    // then all eight read their files to the end, side by side (one after another, the last would sit unread for
    // as long as the others take, and a loaded machine takes longer than the service waits for a stalled reader)
    let len = text.len();
    let reads: Vec<_> = readers
        .into_iter()
        .map(|mut c| {
            tokio::spawn(async move {
                let mut n = 64 * 1024;
                let mut buf = vec![0u8; 1 << 20];
                while n < len {
                    match c.read(&mut buf).await.expect("reads") {
                        0 => break,
                        k => n += k,
                    }
                }
                n
            })
        })
        .collect();
    let mut sizes = Vec::new();
    for r in reads {
        sizes.push(r.await.expect("a reader"));
    }
    eprintln!(
        "8 slow downloads of {:.0} MB: RSS {rss_before:.1} → {rss_held:.1} MB; /healthz {health}, target {target}",
        text.len() as f64 / 1048576.0
    );
    assert!(sizes.iter().all(|&n| n == text.len()), "every download whole: {sizes:?}");
    assert!(rss_held - rss_before < 64.0, "bounded memory: {rss_before:.1} → {rss_held:.1} MB");
    assert_eq!((health, target), (200, 200));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_stops_reading_is_closed() {
    let dir = tempfile::tempdir().expect("tmp");
    let s = Serve::start(dir.path(), "header_timeout_ms = 1000\n");
    let text = "t_s\n".to_string() + &"0.001\n".repeat(4 << 20);
    std::fs::write(dir.path().join("rec").join("pump1-2.csv"), &text).expect("a large recording");
    let (code, mut c) =
        open(s.addr, "GET /api/recordings/pump1-2.csv HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n").await.expect("a download");
    assert_eq!(code, 200);
    // reads nothing until the service has given up on it (bounded), then finds the connection closed early
    let closed = wait_for(Duration::from_secs(10), || async {
        metric(&s.metrics().await, "hydrolens_http_refused_total{reason=\"stalled\"}").unwrap_or(0.0) >= 1.0
    })
    .await;
    assert!(closed.is_some(), "the stalled connection is counted closed");
    let mut rest = Vec::new();
    let _ = tokio::time::timeout(Duration::from_secs(5), c.read_to_end(&mut rest)).await.expect("EOF");
    assert!(rest.len() < text.len(), "the download was cut: {} of {} bytes", rest.len(), text.len());
}

/// An event stream whose client stops reading is closed within seconds: each connection's send buffer is capped
/// (`http::conn::WRITE_BUFFER_BYTES`, in hyper and in the kernel), so its writes stall soon. At the kernel's own
/// sizing (4 MB) a stream of snapshots nobody read took minutes to stall, and held its place meanwhile.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_event_stream_nobody_reads_is_closed_within_seconds() {
    let dir = tempfile::tempdir().expect("tmp");
    let s = Serve::start(dir.path(), "header_timeout_ms = 1000\n");
    let socket = tokio::net::TcpSocket::new_v4().expect("socket");
    socket.set_recv_buffer_size(4096).expect("a small receive buffer");
    let mut c = socket.connect(s.addr).await.expect("connect");
    c.write_all(b"GET /api/events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n").await.expect("write");
    let t = Instant::now();
    // bounded: at the kernel's sizing this took minutes
    let closed = wait_for(Duration::from_secs(90), || async {
        metric(&s.metrics().await, "hydrolens_http_refused_total{reason=\"stalled\"}").unwrap_or(0.0) >= 1.0
    })
    .await;
    eprintln!("an event stream nobody reads: closed after {:?}", t.elapsed());
    assert!(closed.is_some(), "the stream nobody reads is closed");
    assert_eq!(metric(&s.metrics().await, "hydrolens_http_event_streams "), Some(0.0), "its place is free");
    drop(c);
}

/// Whether the server's open-connection gauge reaches `n` within 15 s, read from another address (127.0.0.2, whose
/// share is its own): the connections a test opened are taken by the server, not waiting in the backlog.
async fn connections_reach(url: &str, n: f64) -> bool {
    let other =
        reqwest::Client::builder().local_address(std::net::IpAddr::from([127, 0, 0, 2])).build().expect("client");
    wait_for(Duration::from_secs(15), || async {
        let Ok(r) = other.get(format!("{url}/metrics")).send().await else { return false };
        metric(&r.text().await.unwrap_or_default(), "hydrolens_http_connections ").unwrap_or(0.0) >= n
    })
    .await
    .is_some()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_address_holds_at_most_its_share_and_then_reaches_only_the_reserve() {
    let dir = tempfile::tempdir().expect("tmp");
    let s = Serve::start(dir.path(), "max_connections_per_client = 4\n");
    // four kept-alive connections that each carried a request: a client's, not to be closed for a newer one
    let mut held = Vec::new();
    for _ in 0..4 {
        let (code, stream) = open(s.addr, "GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n").await.expect("served");
        assert_eq!(code, 200);
        held.push(stream);
    }
    // all four taken by the server (the gauge counts them and the connection that asks)
    assert!(connections_reach(&s.url, 5.0).await, "the four connections are taken by the server");
    let status = open(s.addr, "GET /api/status HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n").await.map(|(c, _)| c);
    let [(health, _), (target, _)] = operator(&s.url).await;
    assert_eq!(status, Some(503), "a fifth connection from the address is a reserved one");
    assert_eq!((health, target), (200, 200));
    drop(held);
    let mut fine = None;
    for _ in 0..100 {
        fine = open(s.addr, "GET /api/status HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n").await.map(|(c, _)| c);
        if fine == Some(200) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(fine, Some(200), "its share comes back as its connections close");
    let m = s.metrics().await;
    assert!(metric(&m, "hydrolens_http_refused_total{reason=\"reserved\"}").unwrap_or(0.0) >= 1.0, "{m}");
}

/// One address holding its share half-sent (a flood from the operator's own address, a proxy or a NAT): the
/// operator's new connections close the oldest of them and are served (300 such connections reset 60 of 64
/// operator requests before).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn connections_held_half_sent_give_way_to_the_operator_on_the_same_address() {
    let dir = tempfile::tempdir().expect("tmp");
    let s = Serve::start(dir.path(), "max_connections_per_client = 8\n");
    // its share and the operator's reserve: 8 + 32, each holding half a request
    let mut held = Vec::new();
    for _ in 0..40 {
        let mut c = TcpStream::connect(s.addr).await.expect("connect");
        c.write_all(b"GET /api/status HTTP/1.1\r\nHost: 127.0.0.1\r\n").await.expect("half a request");
        held.push(c);
    }
    assert!(connections_reach(&s.url, 9.0).await, "half-sent connections are taken by the server");
    for _ in 0..3 {
        let [(health, _), (target, _)] = operator(&s.url).await;
        assert_eq!((health, target), (200, 200), "the operator on the flooded address");
    }
    // a full request on a new connection too (not only the reserve's routes)
    let status = open(s.addr, "GET /api/status HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n").await.map(|(c, _)| c);
    assert_eq!(status, Some(200));
    let m = s.metrics().await;
    assert!(metric(&m, "hydrolens_http_refused_total{reason=\"evicted\"}").unwrap_or(0.0) >= 1.0, "{m}");
    drop(held);
}

/// A crowd spread over many addresses, each within its share, holding every connection half-sent (a reviewer's 700
/// from twenty addresses, reconnecting as each timed out): the operator's connection waited in the kernel's backlog
/// and `/healthz`, `/api/status` and the target POST timed out. Now, with every connection held, the oldest one that
/// never carried a request is closed for the new one, and the operator is served on every route.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_crowd_from_many_addresses_gives_way_to_the_operator() {
    let dir = tempfile::tempdir().expect("tmp");
    let s = Serve::start(dir.path(), "max_connections = 16\nmax_connections_per_client = 4\n");
    // sixteen addresses, four connections each, holding half a request: the sixteen ordinary connections, the
    // reserve's 32 and more in the backlog
    let mut crowd = Vec::new();
    for k in 0..64u8 {
        crowd.push(
            connect_from(s.addr, [127, 0, 1, 1 + k / 4], "GET /api/status HTTP/1.1\r\nHost: 127.0.0.1\r\n").await,
        );
    }
    operator_gets_in(&s, "a crowd of 64 from 16 addresses").await;
    let m = s.metrics().await;
    assert!(metric(&m, "hydrolens_http_refused_total{reason=\"evicted\"}").unwrap_or(0.0) >= 1.0, "{m}");
    drop(crowd);
}

/// A reviewer's two-part crowd: connections kept alive with a request every 8 s held every ordinary connection
/// (never closed for a newer one: they had carried a request) and a silent crowd the reserve; every operator request
/// timed out. Now, with none left that never carried a request, the one kept alive longest between requests is
/// closed for the new one; a connection answering a request (an event stream) keeps its place.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn kept_alive_connections_give_way_to_the_operator_and_streams_keep_their_place() {
    let dir = tempfile::tempdir().expect("tmp");
    let s = Serve::start(dir.path(), "max_connections = 16\nmax_connections_per_client = 4\n");
    // four dashboards' event streams, then twelve connections kept alive after a request each, from six addresses
    let mut streams = Vec::new();
    for k in 0..4u8 {
        let (code, c) = response_head(connect_from(s.addr, [127, 0, 4, 1 + k], EVENTS).await).await.expect("a head");
        assert_eq!(code, 200);
        streams.push(c);
    }
    let mut kept = Vec::new();
    for k in 0..12u8 {
        let mut c =
            connect_from(s.addr, [127, 0, 3, 1 + k / 2], "GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n").await;
        let mut buf = [0u8; 512];
        let n = c.read(&mut buf).await.expect("answered");
        assert!(String::from_utf8_lossy(&buf[..n]).starts_with("HTTP/1.1 200"));
        kept.push(c);
    }
    // and a silent crowd of 40 from ten more addresses: the reserve's 32 and more
    let mut silent = Vec::new();
    for k in 0..40u8 {
        silent.push(
            connect_from(s.addr, [127, 0, 5, 1 + k / 4], "GET /api/status HTTP/1.1\r\nHost: 127.0.0.1\r\n").await,
        );
    }
    operator_gets_in(&s, "kept alive, streams and a silent crowd").await;
    // the streams were not closed for anyone (each still open: data, or nothing yet, but no end)
    for c in &mut streams {
        let mut buf = [0u8; 256];
        let r = tokio::time::timeout(Duration::from_millis(200), c.read(&mut buf)).await;
        assert!(!matches!(r, Ok(Ok(0)) | Ok(Err(_))), "a stream was closed: {r:?}");
    }
    drop((kept, silent));
}

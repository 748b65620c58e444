//! What a hostile tester found (issue 20), each as a test through real parts: a misbehaving Modbus device of our
//! own (`device.rs`), real sockets on 127.0.0.1, the real router and config parser.

use hydrolens::recording::simulated;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use hydrolens::modbus::Table;
use hydrolens::modbus::client::DriveClient;
use hydrolens::server::Server;
use hydrolens::service;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

use crate::device::{self, Device};
use crate::support::{TOKEN, get_json, metric, root, start_service, stop_service, wait_exit, wait_for, wait_polls};

const SPEED: &str = crate::support::SPEED_30;

/// A service on one drive at `modbus` (a closed port is fine), with HTTP on 127.0.0.1:0.
struct Svc {
    svc: Option<Server>,
    url: String,
    dir: tempfile::TempDir,
}

impl Svc {
    async fn start(modbus: SocketAddr, http_extra: &str, drive_extra: &str) -> Svc {
        let dir = tempfile::tempdir().expect("tmp");
        Svc::start_in(dir, modbus, http_extra, drive_extra).await
    }

    async fn start_in(dir: tempfile::TempDir, modbus: SocketAddr, http_extra: &str, drive_extra: &str) -> Svc {
        let text = format!(
            "[http]\nbind = \"127.0.0.1:0\"\ntoken = \"{TOKEN}\"\n{http_extra}\n[recording]\ndir = {d:?}\n\n\
             [[drives]]\nname = \"pump1\"\naddress = \"{modbus}\"\npoll_ms = 10\ntimeout_ms = 100\n{drive_extra}\n",
            d = dir.path().display().to_string()
        );
        let svc = start_service(&text).await;
        let url = svc.url.clone();
        Svc { svc: Some(svc), url, dir }
    }

    fn state(&self) -> &Arc<service::ServiceState> {
        &self.svc.as_ref().expect("running").state
    }

    async fn readyz(&self) -> u16 {
        reqwest::get(format!("{}/readyz", self.url)).await.expect("GET readyz").status().as_u16()
    }

    async fn metrics(&self) -> String {
        reqwest::get(format!("{}/metrics", self.url)).await.expect("GET metrics").text().await.expect("text")
    }

    async fn stop(mut self) {
        if let Some(s) = self.svc.take() {
            stop_service(s).await;
        }
    }
}

// ---- item 4: one definition of fresh ----

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn late_replies_that_readiness_calls_stale_never_lead_to_writes() {
    let run = async {
        let dev = Device::start(device::healthy()).await;
        let s = Svc::start(dev.addr, "", SPEED).await;
        wait_for(Duration::from_secs(15), || async { dev.lock().writes > 5 }).await.expect("writing while healthy");
        // replies 70 ms late: inside timeout_ms = 100, beyond the default stale_ms = 50
        dev.lock().delay = Duration::from_millis(70);
        let drive = &s.state().drives[0];
        wait_for(Duration::from_secs(15), || async { s.readyz().await == 503 }).await.expect("late data are stale");
        wait_polls(drive, 2, "what was in flight lands").await;
        let before = dev.lock().writes;
        for _ in 0..8 {
            wait_polls(drive, 1, "late replies").await;
            assert_eq!(s.readyz().await, 503, "late data are stale for readiness");
        }
        assert_eq!(dev.lock().writes, before, "nothing written from data readiness calls stale");
        dev.lock().delay = Duration::ZERO;
        wait_for(Duration::from_secs(15), || async { dev.lock().writes > before }).await.expect("writes resume");
        s.stop().await;
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("bounded");
}

/// A device that echoes writes with the wrong address (a well-formed frame that does not match the request): the
/// poll thread treats it as a protocol error and reconnects, and never dies (tokio-modbus's own check of the echo is
/// a debug assertion that panicked the poll thread).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_write_echo_that_does_not_match_is_an_error_not_a_dead_poll_thread() {
    let run = async {
        let dev = Device::start(device::healthy()).await;
        let s = Svc::start(dev.addr, "", SPEED).await;
        wait_for(Duration::from_secs(15), || async { dev.lock().writes > 5 }).await.expect("writing while healthy");
        let status = || async { get_json(format!("{}/api/status", s.url)).await["drives"][0]["link"].clone() };
        let (errors, reconnects) = {
            let l = status().await;
            (l["errors"].as_u64().expect("errors"), l["reconnects"].as_u64().expect("reconnects"))
        };
        dev.lock().bad_echo = true;
        wait_for(Duration::from_secs(15), || async {
            let l = status().await;
            l["errors"].as_u64().expect("errors") > errors + 2 && l["reconnects"].as_u64().expect("n") > reconnects
        })
        .await
        .expect("mismatched echoes counted as errors, the link re-opened");
        dev.lock().bad_echo = false;
        let reads = dev.lock().reads;
        wait_for(Duration::from_secs(15), || async { dev.lock().reads > reads + 20 && s.readyz().await == 200 })
            .await
            .expect("the poll thread is alive: polling and ready again");
        s.stop().await;
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("bounded");
}

// ---- item 5: impossible counters ----

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_counter_running_backwards_or_alternating_is_stale_and_a_device_fault() {
    let run = async {
        let scripts: [(&str, device::Script); 2] = [
            ("backwards", Box::new(|n| [5000, 300, 3820, 2550, 3, 60000u16.wrapping_sub(n as u16)])),
            ("alternating", Box::new(|n| [5000, 300, 3820, 2550, 3, 100 + (n % 2) as u16])),
        ];
        for (name, script) in scripts {
            let dev = Device::start(device::healthy()).await;
            let s = Svc::start(dev.addr, "", SPEED).await;
            wait_for(Duration::from_secs(15), || async { s.readyz().await == 200 && dev.lock().writes > 5 })
                .await
                .expect("ready and writing while healthy");
            dev.lock().script = script;
            let drive = &s.state().drives[0];
            wait_for(Duration::from_secs(15), || async { s.readyz().await == 503 })
                .await
                .unwrap_or_else(|| panic!("{name}: not ready"));
            wait_polls(drive, 2, "a write in flight lands").await;
            let before = dev.lock().writes;
            wait_polls(drive, 40, name).await;
            assert_eq!(dev.lock().writes, before, "{name}: nothing written");
            assert_eq!(s.readyz().await, 503, "{name}: not ready");
            let m = s.metrics().await;
            let faults = metric(&m, "hydrolens_errors_total{drive=\"pump1\",kind=\"counter\"}").unwrap_or(0.0);
            assert!(faults >= 1.0, "{name}: counted as a device fault\n{m}");
            dev.lock().script = device::healthy();
            wait_for(Duration::from_secs(15), || async { dev.lock().writes > before })
                .await
                .unwrap_or_else(|| panic!("{name}: writes resume with a healthy counter"));
            s.stop().await;
        }
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("bounded");
}

// ---- item 6: back-off resets only after a good poll ----

/// On tokio's paused clock (the 3 s are virtual; device and client share the runtime, the sockets are real).
#[tokio::test(start_paused = true)]
async fn backoff_keeps_growing_when_each_connect_is_followed_by_garbage() {
    let dev = Device::start(device::healthy()).await;
    dev.lock().garbage = true;
    let mut client = DriveClient::new(&dev.addr.to_string(), 1, Duration::from_millis(100));
    let start = tokio::time::Instant::now();
    let mut calls = 0;
    while start.elapsed() < Duration::from_secs(3) && calls < 10_000 {
        assert!(client.read(Table::Input, 0, 6).await.is_err(), "garbage is never a reply");
        tokio::time::sleep(Duration::from_millis(5)).await;
        calls += 1;
    }
    // back-off 50, 100, 200, 400, 500, 500 … ms: about 7 connections in 3 s; reset at each connect: 20 or more
    let connections = dev.lock().connections;
    assert!(connections <= 12, "{connections} connections in 3 s: back-off was reset by each connect");
    assert!(connections >= 3, "{connections}: the client keeps trying");
    dev.lock().garbage = false;
    let mut good = false;
    for _ in 0..200 {
        if client.read(Table::Input, 0, 6).await.is_ok() {
            good = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    assert!(good, "reads succeed again once the device answers properly");
}

// ---- item 7: implausible jumps ----

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_implausible_jump_in_speed_is_rejected_and_counted() {
    let run = async {
        let dev = Device::start(device::healthy()).await;
        let s = Svc::start(dev.addr, "", "").await;
        wait_for(Duration::from_secs(15), || async { s.readyz().await == 200 }).await.expect("ready");
        let at = dev.lock().reads + 3;
        // 343 rad/s (32755 × 0.1 rpm) in one sample, from 40: inside limits.max_speed_rad_s = 1000
        dev.lock().script = Box::new(move |n| {
            let rpm = if n == at { 32755 } else { 3820 };
            [5000 + (n % 7) as u16, 300, rpm, 2550, 3, (n * 10) as u16]
        });
        wait_for(Duration::from_secs(15), || async { dev.lock().reads > at + 10 }).await.expect("polled past it");
        let drive = &s.state().drives[0];
        let snap = drive.snapshot();
        assert!(snap.link.rejected_samples >= 1, "the jump is rejected and counted: {:?}", snap.link);
        let worst = drive.history(60.0, 100_000).iter().map(|p| p.sample.omega_rad_s).fold(0.0, f64::max);
        assert!(worst < 100.0, "the jump never reached the history: {worst}");
        let m = s.metrics().await;
        assert!(metric(&m, "hydrolens_rejected_samples_total{drive=\"pump1\"}").unwrap_or(0.0) >= 1.0, "{m}");
        s.stop().await;
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("bounded");
}

// ---- item 1: recordings download ----

#[tokio::test]
async fn recording_download_serves_only_regular_files_inside_the_directory() {
    let dir = tempfile::tempdir().expect("tmp");
    let outside = tempfile::tempdir().expect("tmp");
    let secret = outside.path().join("secret.csv");
    std::fs::write(&secret, "t_s\nSECRET\n").expect("write");
    std::os::unix::fs::symlink(&secret, dir.path().join("link.csv")).expect("symlink");
    // not a file of the drive `pump1`, so the recorder does not compress it as an earlier run's leftover
    std::fs::write(dir.path().join("bench-1.csv"), "t_s\n1\n").expect("write");
    std::os::unix::fs::symlink(dir.path().join("bench-1.csv"), dir.path().join("inner-link.csv")).expect("symlink");
    std::fs::create_dir(dir.path().join("dir.csv")).expect("mkdir");
    let fifo = std::process::Command::new("mkfifo").arg(dir.path().join("fifo.csv")).status().expect("mkfifo");
    assert!(fifo.success());
    let s = Svc::start_in(dir, "127.0.0.1:9".parse().expect("addr"), "", "").await;
    let client = reqwest::Client::builder().timeout(Duration::from_secs(5)).build().expect("client");
    let get = |f: &str| client.get(format!("{}/api/recordings/{f}", s.url)).send();
    let ok = get("bench-1.csv").await.expect("answered");
    assert_eq!(ok.status(), 200);
    assert_eq!(ok.text().await.expect("body"), "t_s\n1\n");
    for f in ["link.csv", "inner-link.csv", "fifo.csv", "dir.csv"] {
        let r = get(f).await.unwrap_or_else(|e| panic!("{f}: no answer: {e}"));
        assert_eq!(r.status(), 404, "{f}");
        assert!(!r.text().await.expect("body").contains("SECRET"));
    }
    let list: serde_json::Value =
        client.get(format!("{}/api/recordings", s.url)).send().await.expect("list").json().await.expect("json");
    let names: Vec<&str> = list["files"].as_array().expect("files").iter().filter_map(|f| f["name"].as_str()).collect();
    assert!(names.contains(&"bench-1.csv"), "{names:?}");
    for f in ["link.csv", "inner-link.csv", "fifo.csv", "dir.csv"] {
        assert!(!names.contains(&f), "{f} listed: {names:?}");
    }
    s.stop().await;
}

// ---- item 2: slow and idle HTTP clients ----

/// Reads until the server closes the connection; true if it did within `limit`.
async fn closed_within(s: &mut TcpStream, limit: Duration) -> bool {
    let mut buf = [0u8; 4096];
    let deadline = tokio::time::Instant::now() + limit;
    loop {
        match tokio::time::timeout_at(deadline, s.read(&mut buf)).await {
            Err(_) => return false,
            Ok(Ok(0)) | Ok(Err(_)) => return true,
            Ok(Ok(_)) => {}
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idle_and_half_sent_requests_are_closed() {
    let run = async {
        let http = "header_timeout_ms = 300\nrequest_timeout_ms = 300\nmax_connections = 16\n";
        let s = Svc::start("127.0.0.1:9".parse().expect("addr"), http, SPEED).await;
        let addr = s.url.trim_start_matches("http://").to_string();
        let connect = || TcpStream::connect(addr.clone());
        let mut idle = connect().await.expect("connect");
        let mut partial = connect().await.expect("connect");
        partial.write_all(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n").await.expect("write");
        let mut no_body = connect().await.expect("connect");
        no_body
            .write_all(
                b"POST /api/drives/pump1/target HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n\
                  Content-Length: 100\r\nAuthorization: Bearer test-token-7f3a\r\n\r\n{",
            )
            .await
            .expect("write");
        let mut kept_alive = connect().await.expect("connect");
        kept_alive.write_all(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n").await.expect("write");
        let mut trickle = connect().await.expect("connect");
        let trickler = tokio::spawn(async move {
            let _ = trickle.write_all(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n").await;
            for _ in 0..100 {
                tokio::time::sleep(Duration::from_millis(50)).await;
                if trickle.write_all(b"X").await.is_err() {
                    return true;
                }
            }
            false
        });
        for (name, sock) in
            [("idle", &mut idle), ("partial", &mut partial), ("no body", &mut no_body), ("kept alive", &mut kept_alive)]
        {
            assert!(closed_within(sock, Duration::from_secs(3)).await, "{name}: still open after 3 s");
        }
        assert!(trickler.await.expect("joins"), "a trickled header is cut off");
        // and the server still answers
        let ok = reqwest::get(format!("{}/healthz", s.url)).await.expect("healthz").status();
        assert_eq!(ok, 200);
        s.stop().await;
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("bounded");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_connections_are_bounded() {
    let run = async {
        let http = "header_timeout_ms = 10000\nmax_connections = 2\n";
        let s = Svc::start("127.0.0.1:9".parse().expect("addr"), http, "").await;
        let addr = s.url.trim_start_matches("http://").to_string();
        // two ordinary connections answering a request each (event streams: never closed for a newer one), then
        // the operator's reserve (issue 29, finding 4) held idle
        let mut held = Vec::new();
        for _ in 0..2 {
            let mut c = TcpStream::connect(&addr).await.expect("connect");
            c.write_all(b"GET /api/events HTTP/1.1\r\nHost: 127.0.0.1\r\nAccept: text/event-stream\r\n\r\n")
                .await
                .expect("write");
            let mut buf = [0u8; 256];
            let n = c.read(&mut buf).await.expect("answered");
            assert!(String::from_utf8_lossy(&buf[..n]).starts_with("HTTP/1.1 200"));
            held.push(c);
        }
        for _ in 0..hydrolens::http::conn::RESERVED_CONNECTIONS {
            held.push(TcpStream::connect(&addr).await.expect("connect"));
        }
        let taken = (2 + hydrolens::http::conn::RESERVED_CONNECTIONS) as i64;
        wait_for(Duration::from_secs(15), || async { open_connections(s.state()) >= taken })
            .await
            .expect("all taken by the server");
        let mut next = TcpStream::connect(&addr).await.expect("the kernel queues it");
        next.write_all(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n").await.expect("write");
        let mut buf = [0u8; 256];
        let early = tokio::time::timeout(Duration::from_millis(500), next.read(&mut buf)).await;
        assert!(early.is_err(), "a connection beyond the limit and the reserve is served: {early:?}");
        drop(held);
        let n = tokio::time::timeout(Duration::from_secs(3), next.read(&mut buf))
            .await
            .expect("served once a slot is free")
            .expect("read");
        assert!(String::from_utf8_lossy(&buf[..n]).starts_with("HTTP/1.1 200"));
        s.stop().await;
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("bounded");
}

// ---- item 3: wrong tokens ----

#[derive(Clone, Default)]
struct Log(Arc<Mutex<Vec<u8>>>);

impl std::io::Write for Log {
    fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
        self.0.lock().unwrap_or_else(|e| e.into_inner()).extend_from_slice(b);
        Ok(b.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

#[tokio::test]
async fn wrong_tokens_are_throttled_counted_and_logged_without_the_token_and_the_right_one_still_works() {
    let log = Log::default();
    let sink = log.clone();
    let subscriber = tracing_subscriber::fmt()
        .with_max_level(tracing::Level::DEBUG)
        .with_ansi(false)
        .with_writer(move || sink.clone())
        .finish();
    let _guard = tracing::subscriber::set_default(subscriber);
    let s = Svc::start("127.0.0.1:9".parse().expect("addr"), "", SPEED).await;
    let client = reqwest::Client::new();
    let post = |token: String| {
        client
            .post(format!("{}/api/drives/pump1/target", s.url))
            .header("Authorization", format!("Bearer {token}"))
            .json(&serde_json::json!({ "target_omega_rad_s": 20.0 }))
            .send()
    };
    let mut codes = Vec::new();
    for i in 0..40 {
        codes.push(post(format!("guess-{i:04}")).await.expect("answered").status().as_u16());
    }
    assert!(codes[..5].iter().all(|&c| c == 401), "{codes:?}");
    assert_eq!(codes.last(), Some(&429), "a burst of failures is throttled: {codes:?}");
    let wrong = post("guess-more".to_string()).await.expect("answered");
    assert_eq!(wrong.status(), 429, "while throttled a wrong token waits");
    // the header says what is left of the block, as the body does (it said 60 always)
    let header: u64 = wrong.headers()["retry-after"].to_str().expect("ascii").parse().expect("seconds");
    let body: serde_json::Value = wrong.json().await.expect("json");
    let said = body["error"].as_str().expect("error").to_string();
    assert!(said.contains(&format!("try again in {header} s")) && (1..=60).contains(&header), "{header}: {said}");
    // issue 29, finding 6: behind a reverse proxy the operator shares the stranger's address
    let right = post(TOKEN.to_string()).await.expect("answered");
    assert_eq!(right.status(), 200, "the right token is never refused for others' failures");
    assert_eq!(post("guess-again".to_string()).await.expect("answered").status(), 429, "nor does it lift the block");
    let m = s.metrics().await;
    let failures = metric(&m, "hydrolens_http_auth_failures_total").unwrap_or(0.0);
    assert!(failures >= 5.0, "failures counted: {failures}\n{m}");
    assert!(metric(&m, "hydrolens_http_auth_throttled_total").unwrap_or(0.0) >= 1.0, "{m}");
    s.stop().await;
    let text = String::from_utf8_lossy(&log.0.lock().unwrap_or_else(|e| e.into_inner())).into_owned();
    assert!(text.contains("wrong token"), "failures are logged:\n{text}");
    assert!(!text.contains("guess-0"), "never with the token:\n{text}");
    assert!(!text.contains(TOKEN), "never with the token:\n{text}");
}

// ---- item 8: config that must be refused ----

fn refused(text: &str) -> String {
    match service::config::parse(text, "t.toml", Some(&root())) {
        Ok(_) => panic!("accepted:\n{text}"),
        Err(e) => {
            assert!(e.is_bad_input());
            e.to_string()
        }
    }
}

const DRIVE: &str = "[[drives]]\nname = \"pump1\"\naddress = \"127.0.0.1:5020\"\n";

#[test]
fn configs_that_must_be_refused_name_their_key() {
    let writing = |name: &str, unit: u8| {
        format!("[[drives]]\nname = \"{name}\"\naddress = \"127.0.0.1:5020\"\nunit_id = {unit}\n{SPEED}")
    };
    let e = refused(&format!("{}{}", writing("a", 1), writing("b", 1)));
    assert!(e.contains("drives[1].address") && e.contains("unit_id"), "{e}");
    // the same address and unit watched by a monitor is fine, and so are two writers on two units
    let monitor = "[[drives]]\nname = \"m\"\naddress = \"127.0.0.1:5020\"\nunit_id = 1\n";
    service::config::parse(&format!("{}{monitor}", writing("a", 1)), "t", None).expect("monitor beside a writer");
    service::config::parse(&format!("{}{}", writing("a", 1), writing("b", 2)), "t", None).expect("two units");

    let e = refused(&format!("[recording]\nmax_file_mb = 0.001\n{DRIVE}"));
    assert!(e.contains("recording.max_file_mb"), "{e}");
    let e = refused(&format!("[recording]\nrotate_hours = 0.0001\n{DRIVE}"));
    assert!(e.contains("recording.rotate_hours"), "{e}");

    let e = refused(&format!("{DRIVE}watchdog_ms = 1000\n"));
    assert!(e.contains("drives[0].watchdog_ms"), "{e}");
    let e = refused(&format!("{DRIVE}watchdog_ms = 300\ncomm_timeout_ms = 600\n"));
    assert!(e.contains("drives[0].watchdog_ms"), "{e}");
    service::config::parse(&format!("{DRIVE}watchdog_ms = 300\ncomm_timeout_ms = 1000\n"), "t", None)
        .expect("a third of the comm timeout");

    let e = refused(&format!("{DRIVE}[drives.control]\nmax_hz = 700.0\n"));
    assert!(e.contains("drives[0].control.max_hz") && e.contains("655.35"), "{e}");
    let e = refused(&format!("{DRIVE}[drives.control]\nmode = \"manual\"\nmax_hz = 50.0\nfixed_hz = 700.0\n"));
    assert!(e.contains("drives[0].control.fixed_hz"), "{e}");
    let e = refused(&format!("{DRIVE}[drives.control]\nfixed_hz = 700.0\n"));
    assert!(e.contains("drives[0].control.fixed_hz"), "{e}");

    let e = refused(&format!("{DRIVE}[drives.control]\nkp = 1e308\n"));
    assert!(e.contains("drives[0].control.kp"), "{e}");
    let e = refused(&format!("{DRIVE}[drives.control]\nki = 1e308\n"));
    assert!(e.contains("drives[0].control.ki"), "{e}");
    let e = refused(&format!("{DRIVE}[drives.control]\nramp_hz_per_s = 1e300\n"));
    assert!(e.contains("drives[0].control.ramp_hz_per_s"), "{e}");

    let file = tempfile::NamedTempFile::new().expect("tmp");
    let e = refused(&format!("[recording]\ndir = {:?}\n{DRIVE}", file.path().display().to_string()));
    assert!(e.contains("recording.dir"), "{e}");
    let e = refused(&format!("[recording]\ndir = {:?}\n{DRIVE}", file.path().join("sub").display().to_string()));
    assert!(e.contains("recording.dir"), "{e}");

    let e = refused(&format!("{DRIVE}[drives.limits]\nmax_speed_rate_rad_per_s2 = -1.0\n"));
    assert!(e.contains("drives[0].limits.max_speed_rate_rad_per_s2"), "{e}");
}

#[test]
fn serve_with_a_recording_dir_that_is_a_file_or_cannot_be_made_exits_2_naming_the_key() {
    let dir = tempfile::tempdir().expect("tmp");
    let file = dir.path().join("not-a-dir");
    std::fs::write(&file, "x").expect("write");
    // a directory no one may make (root included): it exited 1 with "Permission denied" or "No such file", no path
    for target in [file, PathBuf::from("/proc/self/hydrolens-rec")] {
        refused_naming_recording_dir(dir.path(), &target);
    }
}

fn refused_naming_recording_dir(dir: &Path, target: &Path) {
    let config = dir.join("c.toml");
    let text = format!("[recording]\ndir = {:?}\n{DRIVE}", target.display().to_string());
    std::fs::write(&config, text).expect("write");
    let mut child = std::process::Command::new(crate::support::bin())
        .args(["serve", "--config"])
        .arg(&config)
        .args(["--http", "127.0.0.1:0"])
        .stderr(std::process::Stdio::piped())
        .stdout(std::process::Stdio::null())
        .spawn()
        .expect("starts");
    let status = wait_exit(&mut child, Duration::from_secs(10));
    if status.is_none() {
        let _ = child.kill();
        let _ = child.wait();
    }
    let mut err = String::new();
    std::io::Read::read_to_string(&mut child.stderr.take().expect("stderr"), &mut err).expect("utf-8");
    let status = status.expect("refused at once");
    assert_eq!(status.code(), Some(2), "{err}");
    assert!(err.contains("recording.dir") && err.contains(&*target.to_string_lossy()), "{err}");
}

// ---- item 9: a recording cut mid-row ----

#[test]
fn a_recording_cut_mid_row_at_its_end_is_read_without_that_line_and_a_cut_inside_is_an_error() {
    use hydrolens::plant::PlantModel;
    use hydrolens::recording::{self, Batch, StreamReader};
    let rec = simulated::test_stand(&PlantModel::reference(), 2.0, 3, &mut |_| {}).expect("simulate");
    let mut text = Vec::new();
    recording::write_csv(&mut text, &rec).expect("write");
    let rows = rec.len();
    let dir = tempfile::tempdir().expect("tmp");
    // cut in the middle of the last row, as a SIGTERM on a full disk left it
    let last_line_start = text[..text.len() - 1].iter().rposition(|&b| b == b'\n').expect("lines") + 1;
    let cut_at = last_line_start + (text.len() - last_line_start) / 2;
    let cut = dir.path().join("cut.csv");
    std::fs::write(&cut, &text[..cut_at]).expect("write");
    let loaded = recording::load(&cut).expect("a cut last line is dropped, not an error");
    assert_eq!(loaded.len(), rows - 1);
    let mut reader = StreamReader::open(&cut).expect("opens");
    let mut batch = Batch::default();
    let mut streamed = 0;
    loop {
        match reader.read_batch(&mut batch, 4096).expect("streams without the cut line") {
            0 => break,
            n => streamed += n,
        }
    }
    assert_eq!(streamed, rows - 1);
    let out = dir.path().join("est.csv");
    let o = std::process::Command::new(crate::support::bin())
        .arg("estimate")
        .arg(&cut)
        .arg("--model")
        .arg(root().join("config/plant.toml"))
        .arg("--out")
        .arg(&out)
        .output()
        .expect("runs");
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(0), "{err}");
    assert!(err.contains("cut mid-row"), "a warning: {err}");
    // a file written without a final newline: its last row is whole, and read (it was dropped as cut)
    let unterminated = dir.path().join("unterminated.csv");
    std::fs::write(&unterminated, &text[..text.len() - 1]).expect("write");
    assert_eq!(recording::load(&unterminated).expect("reads").len(), rows, "every row");
    let mut reader = StreamReader::open(&unterminated).expect("opens");
    let mut streamed = 0;
    while let n @ 1.. = reader.read_batch(&mut batch, 4096).expect("streams") {
        streamed += n;
    }
    assert_eq!(streamed, rows, "every row, streamed");
    // a row cut in the middle of the file is still an error
    let mid_start = text[..text.len() / 2].iter().rposition(|&b| b == b'\n').expect("lines") + 1;
    let mut broken = text[..mid_start + 5].to_vec();
    broken.push(b'\n');
    broken.extend_from_slice(&text[mid_start..]);
    let inside = dir.path().join("inside.csv");
    std::fs::write(&inside, &broken).expect("write");
    assert!(recording::load(&inside).is_err(), "a cut inside the file is an error");
}

// ---- item 9: the disk fills ----

/// A config of the drive `pump1` on `modbus`, recording to `rec_dir`, polled every `poll_ms`, written to `dir`.
fn serve_config(dir: &std::path::Path, rec_dir: &std::path::Path, modbus: SocketAddr, poll_ms: u64) -> PathBuf {
    let config = dir.join("c.toml");
    let text = format!(
        "[recording]\ndir = {:?}\n[[drives]]\nname = \"pump1\"\naddress = \"{modbus}\"\npoll_ms = {poll_ms}\n",
        rec_dir.display().to_string()
    );
    std::fs::write(&config, text).expect("write");
    config
}

/// `hydrolens serve` under a file-size limit (the kernel refuses writes past it, as a full disk does; SIGXFSZ
/// ignored so that the write fails instead): the recorder's trouble shows in /api/status, /metrics and readiness
/// while polling goes on, and recording resumes once the limit is lifted (`prlimit`), as when space returns.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_disk_shows_in_status_metrics_and_readiness_and_recording_resumes() {
    let (_sim, modbus, sim_stop, _task) = crate::support::start_sim(crate::support::test_plant(5.0), 0).await;
    let dir = tempfile::tempdir().expect("tmp");
    let rec_dir = dir.path().join("rec");
    let config = serve_config(dir.path(), &rec_dir, modbus, 2);
    let mut serve = crate::support::ServeProcess::start_limited("trap '' XFSZ; ulimit -S -f 64", &config);
    let pid = serve.pid();
    let run = async {
        let url = &serve.url;
        let status = || serve.drive_status();
        let failing = wait_for(Duration::from_secs(10), || async { status().await["recording"]["ok"] == false }).await;
        assert!(failing.is_some(), "recording trouble shows in /api/status: {}", status().await);
        let s = status().await;
        assert!(s["recording"]["last_error"].as_str().is_some_and(|e| !e.is_empty()), "{s}");
        let polls = s["link"]["polls"].as_u64().expect("polls");
        let ready = reqwest::get(format!("{url}/readyz")).await.expect("readyz");
        assert_eq!(ready.status(), 503, "not ready while rows are lost");
        let m = reqwest::get(format!("{url}/metrics")).await.expect("metrics").text().await.expect("text");
        assert!(metric(&m, "hydrolens_recording_errors_total{drive=\"pump1\"}").unwrap_or(0.0) >= 1.0, "{m}");
        assert_eq!(metric(&m, "hydrolens_recording_ok{drive=\"pump1\"}"), Some(0.0), "{m}");
        let on = wait_for(Duration::from_secs(15), || async {
            status().await["link"]["polls"].as_u64().expect("polls") > polls
        })
        .await;
        assert!(on.is_some(), "polling goes on");
        // space returns
        let lifted = std::process::Command::new("prlimit")
            .args([format!("--pid={pid}"), "--fsize=unlimited:unlimited".to_string()])
            .status()
            .expect("prlimit");
        assert!(lifted.success());
        let back = wait_for(Duration::from_secs(10), || async { status().await["recording"]["ok"] == true }).await;
        assert!(back.is_some(), "recording resumes: {}", status().await);
        let ready = wait_for(Duration::from_secs(15), || async {
            reqwest::get(format!("{url}/readyz")).await.expect("readyz").status() == 200
        })
        .await;
        assert!(ready.is_some(), "ready again");
    };
    let finished = tokio::time::timeout(Duration::from_secs(40), run).await;
    let code = serve.stop();
    finished.expect("bounded");
    assert!(code.is_some_and(|c| c.success()), "stops cleanly on SIGTERM: {code:?}");
    sim_stop.cancel();
    // every file left behind reads, cut last lines and all
    for f in std::fs::read_dir(&rec_dir).expect("dir") {
        let p = f.expect("entry").path();
        if std::fs::metadata(&p).expect("meta").len() > 300 {
            hydrolens::recording::load(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
        }
    }
}

/// The recordings in `dir` (`.csv` and `.csv.gz`) and their sizes.
fn recordings_in(dir: &std::path::Path) -> Vec<(PathBuf, u64)> {
    let Ok(entries) = std::fs::read_dir(dir) else { return Vec::new() };
    let mut files: Vec<(PathBuf, u64)> = entries
        .filter_map(Result::ok)
        .filter(|e| {
            let name = e.file_name().to_string_lossy().into_owned();
            name.ends_with(".csv") || name.ends_with(".csv.gz")
        })
        .map(|e| (e.path(), e.metadata().map_or(0, |m| m.len())))
        .collect();
    files.sort();
    files
}

/// A disk with no room at all (a file-size limit of 0, and no help from the shell with SIGXFSZ: the service takes
/// the signal itself, and the lock file's pid is best-effort): rows are lost and shown as lost, and the tries at a
/// new file, one a second, leave no empty files behind (issue 29, finding 8).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_disk_with_no_room_leaves_no_empty_recordings_and_shows_the_rows_lost() {
    let (_sim, modbus, sim_stop, _task) = crate::support::start_sim(crate::support::test_plant(5.0), 0).await;
    let dir = tempfile::tempdir().expect("tmp");
    let rec_dir = dir.path().join("rec");
    let config = serve_config(dir.path(), &rec_dir, modbus, 10);
    let mut serve = crate::support::ServeProcess::start_limited("ulimit -f 0", &config);
    let run = async {
        let status = || serve.drive_status();
        // three tries at a file, a second apart
        let tried = wait_for(Duration::from_secs(15), || async {
            status().await["recording"]["errors"].as_u64().is_some_and(|e| e >= 3)
        })
        .await;
        assert!(tried.is_some(), "{}\n{}", status().await, serve.log());
        let r = status().await["recording"].clone();
        assert_eq!(r["ok"], false, "{r}");
        assert!(r["rows_lost"].as_u64().is_some_and(|n| n > 0), "{r}");
        assert!(r["last_error"].as_str().is_some_and(|e| !e.is_empty()), "{r}");
        // a file exists only for the instant a try takes
        let files = recordings_in(&rec_dir);
        assert!(
            files.len() <= 1 && files.iter().all(|(p, b)| *b == 0 && !p.to_string_lossy().ends_with(".gz")),
            "{files:?}"
        );
    };
    let finished = tokio::time::timeout(Duration::from_secs(30), run).await;
    let code = serve.stop();
    finished.expect("bounded");
    assert!(code.is_some_and(|c| c.success()), "stops cleanly on SIGTERM: {code:?}\n{}", serve.log());
    sim_stop.cancel();
    assert_eq!(recordings_in(&rec_dir), vec![], "no empty recordings left");
}

/// The open recording deleted, then the whole recordings directory removed, while the service runs: each loss
/// shows in /api/status (rows and files lost, the last error naming the file), and a new file takes the rows
/// (issue 29, finding 8).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_recording_deleted_while_open_or_its_directory_removed_shows_in_status_and_a_new_file_grows() {
    let run = async {
        let (_sim, modbus, sim_stop, _task) = crate::support::start_sim(crate::support::test_plant(5.0), 0).await;
        let s = Svc::start(modbus, "", "").await;
        let dir = s.dir.path().to_path_buf();
        let recording = || async { get_json(format!("{}/api/status", s.url)).await["drives"][0]["recording"].clone() };
        let count = |r: &serde_json::Value, key: &str| r[key].as_u64().unwrap_or_else(|| panic!("{key}: {r}"));
        // the open (plain) file once it holds rows; then that it grows
        let open_file_grows = || async {
            let with_rows = || {
                recordings_in(&dir).into_iter().find(|(p, _)| {
                    p.extension().is_some_and(|x| x == "csv")
                        && hydrolens::recording::holds_no_rows(p).is_ok_and(|none| !none)
                })
            };
            let found = wait_for(Duration::from_secs(10), || async { with_rows().is_some() }).await;
            assert!(found.is_some(), "a file with rows: {:?}", recordings_in(&dir));
            let (path, bytes) = with_rows().expect("found");
            let grew =
                wait_for(Duration::from_secs(10), || async { std::fs::metadata(&path).is_ok_and(|m| m.len() > bytes) })
                    .await;
            assert!(grew.is_some(), "{} grows past {bytes} bytes", path.display());
            path
        };
        let first = open_file_grows().await;
        let r = recording().await;
        assert!(count(&r, "rows_lost") == 0 && count(&r, "files_lost") == 0 && r["ok"] == true, "{r}");

        std::fs::remove_file(&first).expect("rm");
        let noticed =
            wait_for(Duration::from_secs(15), || async { count(&recording().await, "files_lost") >= 1 }).await;
        assert!(noticed.is_some(), "{}", recording().await);
        let r = recording().await;
        assert!(count(&r, "rows_lost") > 0, "{r}");
        let name = first.file_name().expect("name").to_string_lossy().into_owned();
        assert!(r["last_error"].as_str().is_some_and(|e| e.contains(&name)), "names the file: {r}");
        open_file_grows().await;
        let m = s.metrics().await;
        assert!(metric(&m, "hydrolens_recording_files_lost_total{drive=\"pump1\"}").unwrap_or(0.0) >= 1.0, "{m}");

        let lost = count(&recording().await, "rows_lost");
        std::fs::remove_dir_all(&dir).expect("rm -r");
        let noticed =
            wait_for(Duration::from_secs(15), || async { count(&recording().await, "files_lost") >= 2 }).await;
        assert!(noticed.is_some(), "{}", recording().await);
        assert!(count(&recording().await, "rows_lost") > lost, "{}", recording().await);
        open_file_grows().await;
        // the lock went with the directory and is taken again: a second instance is still refused
        assert!(dir.join(hydrolens::service::recorder::LOCK_FILE).exists(), "the lock file is back");
        let text = format!(
            "[http]\nbind = \"127.0.0.1:0\"\n[recording]\ndir = {:?}\n[[drives]]\nname = \"pump2\"\naddress = \"{modbus}\"\n",
            dir.display().to_string()
        );
        let settings = service::config::parse(&text, "test config", Some(&root())).expect("config");
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind");
        let second = hydrolens::server::start(listener, &settings, tokio_util::sync::CancellationToken::new());
        assert!(second.is_err_and(|e| hydrolens::is_bad_input(&e)), "a second instance is refused");
        s.stop().await;
        sim_stop.cancel();
    };
    tokio::time::timeout(Duration::from_secs(60), run).await.expect("bounded");
}

// ---- item 10: retention ----

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn retention_keeps_the_recordings_within_max_total_mb_and_never_deletes_the_open_file() {
    let run = async {
        let (_sim, modbus, sim_stop, _task) = crate::support::start_sim(crate::support::test_plant(5.0), 0).await;
        let dir = tempfile::tempdir().expect("tmp");
        // an older file of another drive whose name starts alike: never touched
        std::fs::write(dir.path().join("pump1-b-1000.csv"), "t_s\n1\n").expect("write");
        let text = format!(
            "[http]\nbind = \"127.0.0.1:0\"\n[recording]\ndir = {:?}\nmax_file_mb = 0.1\nmax_total_mb = 0.3\n\
             compress = false\n[[drives]]\nname = \"pump1\"\naddress = \"{modbus}\"\npoll_ms = 1\n",
            dir.path().display().to_string()
        );
        let svc = start_service(&text).await;
        let url = svc.url.clone();
        let deleted = || async {
            let m = reqwest::get(format!("{url}/metrics")).await.expect("metrics").text().await.expect("text");
            metric(&m, "hydrolens_recording_files_deleted_total{drive=\"pump1\"}").unwrap_or(0.0)
        };
        let went = wait_for(Duration::from_secs(20), || async { deleted().await >= 3.0 }).await;
        assert!(went.is_some(), "old files deleted and counted");
        let ours = || -> Vec<(String, u64)> {
            std::fs::read_dir(dir.path())
                .expect("dir")
                .map(|e| e.expect("entry"))
                .map(|e| (e.file_name().to_string_lossy().into_owned(), e.metadata().expect("meta").len()))
                .filter(|(n, _)| n.starts_with("pump1-1") || n.starts_with("pump1-2"))
                .collect()
        };
        let total: u64 = ours().iter().map(|(_, b)| b).sum();
        // the budget, plus the open file growing past it until the next rotation
        assert!(total <= (0.3 * 1048576.0) as u64 + 110_000, "{total} bytes: {:?}", ours());
        assert!(dir.path().join("pump1-b-1000.csv").exists(), "another drive's file is not ours");
        stop_service(svc).await;
        sim_stop.cancel();
        // the newest file (open until the stop) is still there and whole
        let mut names: Vec<String> = ours().into_iter().map(|(n, _)| n).collect();
        names.sort();
        let newest = dir.path().join(names.last().expect("files left"));
        hydrolens::recording::load(&newest).expect("the open file was kept and closed cleanly");
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("bounded");
}

/// One writer per recordings directory: a second service on the same `recording.dir` does not start (a bad-input
/// error naming the directory and the first one's pid), and the first one's open recording is untouched; once the
/// first has stopped, the directory can be taken again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_second_instance_on_the_same_recordings_directory_is_refused() {
    let run = async {
        use crate::support;
        let (_sim, modbus, sim_stop, _task) = support::start_sim(support::test_plant(5.0), 0).await;
        let dir = tempfile::tempdir().expect("tmp");
        let text = support::config_text(modbus, dir.path(), 10, "");
        let first = support::start_service(&text).await;
        let csv_files = || -> Vec<std::path::PathBuf> {
            std::fs::read_dir(dir.path())
                .expect("dir")
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.extension().is_some_and(|x| x == "csv"))
                .collect()
        };
        support::wait_for(Duration::from_secs(15), || async { !csv_files().is_empty() }).await.expect("recording");
        let open = csv_files();
        assert_eq!(open.len(), 1, "{open:?}");
        let settings = service::config::parse(&text, "test config", Some(&support::root())).expect("config");
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind");
        let second = hydrolens::server::start(listener, &settings, tokio_util::sync::CancellationToken::new());
        let Err(e) = second else { panic!("a second instance started on the same directory") };
        let message = e.to_string();
        assert!(hydrolens::is_bad_input(&e), "exit 2: {message}");
        assert!(message.contains(&dir.path().display().to_string()), "names the directory: {message}");
        assert!(message.contains(&format!("pid {}", std::process::id())), "names the holder: {message}");
        assert!(open[0].exists(), "the first instance's open recording is untouched");
        support::stop_service(first).await;
        let again = support::start_service(&text).await;
        support::stop_service(again).await;
        sim_stop.cancel();
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("bounded");
}

/// `hydrolens_http_connections` as the service's exposition says it.
fn open_connections(state: &hydrolens::service::ServiceState) -> i64 {
    let text = hydrolens::metrics::exposition(state, hydrolens::metrics::Format::Text);
    let line = text.lines().find_map(|l| l.strip_prefix("hydrolens_http_connections ")).expect("the gauge is exposed");
    line.trim().parse().expect("an integer")
}

/// Errors the router or the timeout answer themselves (a method a route does not take, a body not complete in time)
/// came back with no body; every other error is JSON (docs/http.md): now these are too.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_wrong_method_and_a_late_body_are_answered_with_a_json_error() {
    let run = async {
        let s = Svc::start("127.0.0.1:9".parse().expect("addr"), "request_timeout_ms = 300\n", SPEED).await;
        let r = reqwest::Client::new().delete(format!("{}/api/status", s.url)).send().await.expect("DELETE");
        assert_eq!(r.status(), 405);
        let body: serde_json::Value = r.json().await.expect("a JSON body");
        assert!(body["error"].as_str().is_some_and(|e| e.contains("method")), "{body}");
        // a body promised and not sent within request_timeout_ms
        let addr = s.url.trim_start_matches("http://").to_string();
        let mut late = TcpStream::connect(addr).await.expect("connect");
        late.write_all(
            b"POST /api/drives/pump1/target HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n\
              Content-Length: 100\r\nAuthorization: Bearer test-token-7f3a\r\n\r\n{",
        )
        .await
        .expect("write");
        let mut answer = Vec::new();
        let _ = tokio::time::timeout(Duration::from_secs(5), late.read_to_end(&mut answer)).await;
        let answer = String::from_utf8_lossy(&answer);
        assert!(answer.starts_with("HTTP/1.1 408") && answer.contains("{\"error\":"), "{answer}");
        s.stop().await;
    };
    tokio::time::timeout(Duration::from_secs(60), run).await.expect("bounded");
}

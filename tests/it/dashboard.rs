//! The dashboard in a real headless browser (Debian `chromium`; .ci/run installs it): the charts receive live points
//! and the drive card shows the drive's state, and says so when the page loses the service. A missing browser fails
//! the test.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio_util::sync::CancellationToken;

use crate::support::Stack;

fn chromium() -> PathBuf {
    for name in ["chromium", "chromium-browser"] {
        for dir in ["/usr/bin", "/usr/local/bin", "/snap/bin"] {
            let p = Path::new(dir).join(name);
            if p.exists() {
                return p;
            }
        }
    }
    panic!("no chromium found: install Debian's `chromium` (apt-get install -y chromium); .ci/run does this");
}

/// Runs headless chromium with `args` and the URL, killing it after `limit`; returns its stdout.
pub(crate) fn run_chromium(url: &str, args: &[&str], limit: Duration) -> String {
    let profile = tempfile::tempdir().expect("tmp");
    let out_path = profile.path().join("stdout.txt");
    let out = std::fs::File::create(&out_path).expect("stdout file");
    let mut child = Command::new(chromium())
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-dev-shm-usage",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--hide-scrollbars",
        ])
        .arg(format!("--user-data-dir={}", profile.path().join("profile").display()))
        .args(args)
        .arg(url)
        .stdin(Stdio::null())
        .stdout(out)
        .stderr(Stdio::null())
        .spawn()
        .expect("chromium starts");
    let start = Instant::now();
    loop {
        match child.try_wait().expect("wait") {
            Some(_) => break,
            None if start.elapsed() > limit => {
                let _ = child.kill();
                let _ = child.wait();
                panic!("chromium did not finish within {limit:?}");
            }
            None => std::thread::sleep(Duration::from_millis(50)),
        }
    }
    std::fs::read_to_string(&out_path).expect("stdout")
}

/// The value of the first `attr="..."` after `anchor` in the DOM.
pub(crate) fn attr_after<'a>(dom: &'a str, anchor: &str, attr: &str) -> Option<&'a str> {
    let at = dom.find(anchor)?;
    let rest = &dom[at..];
    let key = format!("{attr}=\"");
    let from = rest.find(&key)? + key.len();
    rest[from..].split('"').next()
}

/// The text after `anchor` up to the next tag.
fn text_after<'a>(dom: &'a str, anchor: &str) -> Option<&'a str> {
    let at = dom.find(anchor)? + anchor.len();
    dom[at..].split('<').next()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dashboard_shows_live_points_and_the_drive_state() {
    let stack = Stack::start(8.0, 10, "[drives.control]\nmode = \"speed\"\ntarget_omega_rad_s = 35.0\n").await;
    // some history to load, its target moving (35, 30, 40, 35 rad/s, 60 polls each): the history keeps it
    let drive = &stack.state.drives[0];
    for target in [35.0, 30.0, 40.0, 35.0] {
        drive.set_target(target);
        stack.wait_polls(60, "a step of the target program").await;
    }
    // the page closes its event stream after 15 snapshots (≈1.5 s) so that the virtual-time budget can run out
    let url = format!("{}/?close_after=15", stack.url);
    let dom = tokio::task::spawn_blocking(move || {
        run_chromium(&url, &["--virtual-time-budget=5000", "--dump-dom"], Duration::from_secs(60))
    })
    .await
    .expect("joins");
    let points: Vec<u64> = dom
        .match_indices("class=\"chart\" data-points=\"")
        .filter_map(|(i, m)| dom[i + m.len()..].split('"').next()?.parse().ok())
        .collect();
    assert_eq!(points.len(), 3, "three charts: {dom:.2000}");
    assert!(points.iter().all(|&n| n > 50), "charts got history and live points: {points:?}");
    // the speed chart's target line, drawn from the history, moves as the target did: 30 to 40 rad/s, not flat
    let drawn: Vec<f64> = dom
        .split("data-target-history=\"")
        .nth(1)
        .and_then(|rest| rest.split('"').next())
        .map(|v| v.split(' ').filter_map(|x| x.parse().ok()).collect())
        .unwrap_or_default();
    assert_eq!(drawn.len(), 2, "the target drawn over the history (min max): {dom:.3000}");
    assert!((drawn[0] - 30.0).abs() < 1e-9 && (drawn[1] - 40.0).abs() < 1e-9, "drawn from 30 to 40 rad/s: {drawn:?}");
    assert_eq!(attr_after(&dom, "data-drive=\"pump1\"", "data-link"), Some("up"), "{dom:.2000}");
    assert_eq!(attr_after(&dom, "data-drive=\"pump1\"", "data-mode"), Some("speed"));
    assert_eq!(attr_after(&dom, "id=\"ready\"", "data-ready"), Some("true"));
    let events: u64 = attr_after(&dom, "id=\"events\"", "data-events").and_then(|v| v.parse().ok()).expect("count");
    assert_eq!(events, 15, "SSE snapshots that reached the page");
    assert!(dom.contains("ready, running"), "the card shows the status word");
    // J and B with their confidence (rls-sgd): a value ± a standard deviation, flagged while not identified
    for (class, unit) in [("inertia", "kg·m²"), ("viscous", "N·m·s/rad")] {
        let text = text_after(&dom, &format!("class=\"{class}\">")).unwrap_or_default();
        assert!(text.contains('±') && text.contains(unit), "{class}: {text:?}");
    }

    let shot_dir = tempfile::tempdir().expect("tmp");
    let shot = shot_dir.path().join("dashboard.png");
    let (url, arg) = (format!("{}/?close_after=15", stack.url), format!("--screenshot={}", shot.display()));
    tokio::task::spawn_blocking(move || {
        run_chromium(&url, &["--virtual-time-budget=5000", "--window-size=1280,900", &arg], Duration::from_secs(60))
    })
    .await
    .expect("joins");
    let png = std::fs::read(&shot).expect("a screenshot");
    assert!(png.starts_with(b"\x89PNG") && png.len() > 10_000, "{} bytes", png.len());
    if let Ok(keep) = std::env::var("HYDROLENS_SCREENSHOT") {
        std::fs::copy(&shot, keep).expect("copy the screenshot");
    }
    stack.stop().await;
}

/// A network line between the browser and the service on 127.0.0.1 that can be cut: every connection it carries
/// is dropped and new ones are refused, as when the control room loses the cabinet's network. It counts the
/// server-sent snapshots it has carried to the browser.
struct Line {
    addr: SocketAddr,
    snapshots: Arc<AtomicUsize>,
    cut: CancellationToken,
}

const SNAPSHOT_FIELD: &[u8] = b"event: snapshot\n";

impl Line {
    async fn start(upstream: SocketAddr) -> Line {
        let listener = TcpListener::bind("127.0.0.1:0").await.expect("bind the line");
        let addr = listener.local_addr().expect("addr");
        let (snapshots, cut) = (Arc::new(AtomicUsize::new(0)), CancellationToken::new());
        let (count, stop) = (snapshots.clone(), cut.clone());
        tokio::spawn(async move {
            loop {
                let client = tokio::select! {
                    _ = stop.cancelled() => return, // the listener goes with this task: new connections are refused
                    accepted = listener.accept() => match accepted {
                        Ok((client, _)) => client,
                        Err(_) => return,
                    },
                };
                let Ok(server) = TcpStream::connect(upstream).await else { continue };
                let (count, stop) = (count.clone(), stop.clone());
                tokio::spawn(async move {
                    tokio::select! {
                        _ = stop.cancelled() => {} // both sockets are dropped here
                        _ = carry(client, server, &count) => {}
                    }
                });
            }
        });
        Line { addr, snapshots, cut }
    }
}

/// Carries one connection both ways until either side closes it, counting the snapshot events going down.
async fn carry(client: TcpStream, server: TcpStream, snapshots: &AtomicUsize) {
    let (mut client_rx, mut client_tx) = client.into_split();
    let (mut server_rx, mut server_tx) = server.into_split();
    let up = tokio::io::copy(&mut client_rx, &mut server_tx);
    let down = async {
        let mut buf = vec![0u8; 64 * 1024];
        // the last bytes of the previous read, so that a field split across two reads is still counted once
        let mut tail: Vec<u8> = Vec::new();
        loop {
            let n = match server_rx.read(&mut buf).await {
                Ok(0) | Err(_) => return,
                Ok(n) => n,
            };
            if client_tx.write_all(&buf[..n]).await.is_err() {
                return;
            }
            tail.extend_from_slice(&buf[..n]);
            let found = tail.windows(SNAPSHOT_FIELD.len()).filter(|w| *w == SNAPSHOT_FIELD).count();
            snapshots.fetch_add(found, Ordering::SeqCst);
            let keep = tail.len().min(SNAPSHOT_FIELD.len() - 1);
            tail.drain(..tail.len() - keep);
        }
    };
    tokio::select! {
        _ = up => {}
        _ = down => {}
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_page_that_loses_the_service_says_so_on_every_card() {
    let stack = Stack::start(8.0, 10, "[drives.control]\nmode = \"speed\"\ntarget_omega_rad_s = 35.0\n").await;
    let upstream: SocketAddr = stack.url.trim_start_matches("http://").parse().expect("the service's address");
    let line = Line::start(upstream).await;
    // no close_after: the open event stream holds the browser's virtual time still until the line is cut
    let url = format!("http://{}/", line.addr);
    let browser = tokio::task::spawn_blocking(move || {
        run_chromium(&url, &["--virtual-time-budget=5000", "--dump-dom"], Duration::from_secs(90))
    });
    let deadline = Instant::now() + Duration::from_secs(60);
    while line.snapshots.load(Ordering::SeqCst) < 5 {
        assert!(Instant::now() < deadline, "the page never received 5 snapshots through the line");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    line.cut.cancel();
    let dom = browser.await.expect("joins");

    // the page took live snapshots before the cut (the last ones carried may die in the sockets' buffers with it)
    let events: u64 = attr_after(&dom, "id=\"events\"", "data-events").and_then(|v| v.parse().ok()).expect("count");
    assert!(events >= 1, "the page had live snapshots before the cut: {dom:.2000}");
    assert_eq!(attr_after(&dom, "id=\"ready\"", "data-ready"), Some("false"), "{dom:.2000}");
    assert!(dom.contains(">disconnected<"), "the header says the page lost the service");
    assert_eq!(attr_after(&dom, "data-drive=\"pump1\"", "data-link"), Some("unknown"), "{dom:.2000}");
    assert!(dom.contains("class=\"card lost\""), "the card greys its old values: {dom:.2000}");
    assert!(dom.contains(">no data<"), "the card's link badge no longer says up");
    assert!(stack.state.drives[0].snapshot().link.connected, "the drive itself was fine all along");
    stack.stop().await;
}

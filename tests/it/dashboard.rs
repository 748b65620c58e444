//! The dashboard in a real headless browser (Debian `chromium`; .ci/run installs it): the charts receive live points
//! and the drive card shows the drive's state. A missing browser fails the test.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

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
fn run_chromium(url: &str, args: &[&str], limit: Duration) -> String {
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
fn attr_after<'a>(dom: &'a str, anchor: &str, attr: &str) -> Option<&'a str> {
    let at = dom.find(anchor)?;
    let rest = &dom[at..];
    let key = format!("{attr}=\"");
    let from = rest.find(&key)? + key.len();
    rest[from..].split('"').next()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dashboard_shows_live_points_and_the_drive_state() {
    let stack = Stack::start(8.0, 10, "[drives.control]\nmode = \"speed\"\ntarget_omega_rad_s = 35.0\n").await;
    tokio::time::sleep(Duration::from_secs(2)).await; // some history to load
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
    assert_eq!(attr_after(&dom, "data-drive=\"pump1\"", "data-link"), Some("up"), "{dom:.2000}");
    assert_eq!(attr_after(&dom, "data-drive=\"pump1\"", "data-mode"), Some("speed"));
    assert_eq!(attr_after(&dom, "id=\"ready\"", "data-ready"), Some("true"));
    let events: u64 = attr_after(&dom, "id=\"events\"", "data-events").and_then(|v| v.parse().ok()).expect("count");
    assert_eq!(events, 15, "SSE snapshots that reached the page");
    assert!(dom.contains("ready, running"), "the card shows the status word");

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

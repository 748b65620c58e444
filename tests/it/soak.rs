//! The soak run (ignored; `HYDROLENS_SOAK_S` seconds, default 600): faults every 5 s through the proxy and the
//! simulator, for long enough to see memory stay flat and the recording keep a row for every sample outside the
//! outages. Run: `HYDROLENS_SOAK_S=600 cargo test --release --test it soak -- --ignored --nocapture`.

use std::time::{Duration, Instant};

use crate::proxy::Fault;
use crate::support::{Stack, wait_for};

const SPEED: &str = crate::support::SPEED_30;

fn rss_kib() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| s.lines().find(|l| l.starts_with("VmRSS:")).map(str::to_string))
        .and_then(|l| l.split_whitespace().nth(1).and_then(|v| v.parse().ok()))
        .unwrap_or(0)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "a 10-minute soak; run on purpose (see the module doc)"]
async fn soak_with_faults_every_few_seconds() {
    let total = Duration::from_secs(std::env::var("HYDROLENS_SOAK_S").ok().and_then(|v| v.parse().ok()).unwrap_or(600));
    let (stack, proxy) = Stack::start_behind_proxy(6.0, 10, SPEED).await;
    let started = Instant::now();
    wait_for(Duration::from_secs(10), || async {
        !stack.sim.lock().truth().tripped && stack.status().await["link"]["stale"] == false
    })
    .await
    .expect("running");
    let faults = [
        Fault::Drop,
        Fault::Garbage,
        Fault::Slow(Duration::from_millis(300)),
        Fault::Refuse,
        Fault::WrongTransactionId,
    ];
    let outage = Duration::from_millis(600); // shorter than the drive's 1 s watchdog: no trips, regulation resumes
    let mut windows: Vec<(f64, f64)> = Vec::new();
    let (mut rss_warm, mut k) = (None, 0usize);
    while started.elapsed() < total {
        tokio::time::sleep(Duration::from_secs(5).saturating_sub(outage)).await;
        let from = started.elapsed().as_secs_f64();
        if k % 6 == 5 {
            stack.sim.lock().faults.freeze_counter = true;
            tokio::time::sleep(outage).await;
            stack.sim.lock().faults.freeze_counter = false;
        } else {
            proxy.set(faults[k % 6 % faults.len()]);
            tokio::time::sleep(outage).await;
            proxy.set(Fault::Pass);
        }
        windows.push((from, started.elapsed().as_secs_f64()));
        k += 1;
        // after the history ring (120 s) has filled
        if rss_warm.is_none() && started.elapsed() > Duration::from_secs(150.min(total.as_secs() / 2)) {
            rss_warm = Some(rss_kib());
        }
    }
    let rss_end = rss_kib();
    let status = stack.status().await;
    let dir = stack.stop().await;
    let mut rows: Vec<f64> = Vec::new();
    for entry in std::fs::read_dir(dir.path()).expect("recordings") {
        let path = entry.expect("entry").path();
        // the recordings, not the directory's lock (`.hydrolens.lock`)
        if path.file_name().is_some_and(|n| n.to_string_lossy().starts_with('.')) {
            continue;
        }
        let rec = hydrolens::recording::load(&path).expect("every recording is valid");
        rows.extend_from_slice(rec.t_s());
    }
    rows.sort_by(f64::total_cmp);
    // a gap longer than 100 ms must lie in (or just after) an outage: reconnecting takes up to ~1 s
    let in_outage = |a: f64, b: f64| windows.iter().any(|&(s, e)| a < e + 1.5 && b > s - 0.2);
    let bad_gaps: Vec<(f64, f64)> =
        rows.windows(2).filter(|w| w[1] - w[0] > 0.1 && !in_outage(w[0], w[1])).map(|w| (w[0], w[1])).collect();
    let outage_s: f64 = windows.iter().map(|(s, e)| e - s + 1.0).sum();
    let expected = (total.as_secs_f64() - outage_s) / 0.010;
    let growth_kib = rss_end as i64 - rss_warm.unwrap_or(rss_end) as i64;
    eprintln!(
        "soak {:.0} s, {} outages: {} rows (≥ {expected:.0} expected outside outages), gaps outside outages {}, \
         RSS {} KiB after warm-up → {rss_end} KiB at the end ({growth_kib:+} KiB); link {}",
        total.as_secs_f64(),
        windows.len(),
        rows.len(),
        bad_gaps.len(),
        rss_warm.unwrap_or(0),
        status["link"]
    );
    assert!(bad_gaps.is_empty(), "rows missing outside outages: {bad_gaps:?}");
    assert!(rows.len() as f64 >= 0.95 * expected, "{} rows, expected ≥ {expected:.0}", rows.len());
    assert!(growth_kib < 8 * 1024, "memory grew {growth_kib} KiB after warm-up");
}

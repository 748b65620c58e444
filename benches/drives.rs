//! The service as the number of drives grows: `cargo bench --bench drives`.
//!
//! Per case (N drives polled every P ms) it starts N `hydrolens sim` processes on 127.0.0.1 (plant sample period =
//! P, so each simulator's counter moves once per poll) and one `hydrolens serve` with every drive in speed mode and
//! recording, as in production. After a warm-up it measures, over a window of whole status windows (1000 polls
//! each):
//! - the service's CPU time, split by thread (`poll-*`, `http*`, `rec-*`, the rest), from /proc, as a share of one
//!   core;
//! - its RSS at the end and its peak (VmHWM);
//! - polls per second, errors and overruns over the window;
//! - jitter |period − P|: p50 and p99 of each drive's last 1000 periods as `/api/status` reports them, read once
//!   per status window; the table gives the median over drives and windows and the worst.
//!
//! Environment: `HYDROLENS_BENCH_CASES` (default `1x1,10x10,50x10`: drives × poll ms), `HYDROLENS_BENCH_SECONDS`
//! (window, default 20, rounded up to whole status windows), `HYDROLENS_BENCH_RT` (a SCHED_FIFO priority for the
//! poll threads and, through `chrt`, the simulators; default none), `HYDROLENS_BENCH_WRK=1` (wrk -t1 -c32 on /api/status throughout the window; the
//! table then gives its requests/s). Linux only (/proc).

use std::collections::BTreeMap;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

const BIN: &str = env!("CARGO_BIN_EXE_hydrolens");

/// Children that are stopped however the bench ends.
struct Children {
    sims: Vec<Child>,
    serve: Option<Child>,
}

impl Drop for Children {
    fn drop(&mut self) {
        if let Some(mut s) = self.serve.take() {
            terminate(&mut s);
        }
        for c in &mut self.sims {
            terminate(c);
        }
    }
}

/// SIGTERM, then SIGKILL after 5 s.
fn terminate(c: &mut Child) {
    let _ = Command::new("kill").args(["-TERM", &c.id().to_string()]).status();
    let deadline = Instant::now() + Duration::from_secs(5);
    while matches!(c.try_wait(), Ok(None)) && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(10));
    }
    let _ = c.kill();
    let _ = c.wait();
}

/// Reads a child's stderr until a line containing `marker`; returns the text after it. Keeps draining the pipe on
/// a thread so that the child never blocks on a full pipe.
fn announced(child: &mut Child, marker: &'static str) -> String {
    let stderr = child.stderr.take().expect("piped stderr");
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut tx = Some(tx);
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if let Some(i) = line.find(marker)
                && let Some(tx) = tx.take()
            {
                let _ = tx.send(line[i + marker.len()..].trim().to_string());
            }
        }
    });
    rx.recv_timeout(Duration::from_secs(20)).unwrap_or_else(|_| panic!("no {marker:?} from the child within 20 s"))
}

/// GET over a fresh connection; the body.
fn get(addr: &str, path: &str) -> Option<String> {
    let mut s = TcpStream::connect(addr).ok()?;
    s.set_read_timeout(Some(Duration::from_secs(5))).ok()?;
    write!(s, "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n").ok()?;
    let mut text = String::new();
    s.read_to_string(&mut text).ok()?;
    let (head, body) = text.split_once("\r\n\r\n")?;
    head.starts_with("HTTP/1.1 200").then(|| body.to_string())
}

/// CPU seconds of a process's threads, summed by kind (from the thread name).
fn cpu_by_kind(pid: u32) -> BTreeMap<&'static str, f64> {
    let ticks = rustix::param::clock_ticks_per_second() as f64;
    let mut out = BTreeMap::new();
    let Ok(tasks) = std::fs::read_dir(format!("/proc/{pid}/task")) else { return out };
    for t in tasks.flatten() {
        let Ok(stat) = std::fs::read_to_string(t.path().join("stat")) else { continue };
        let Some((head, rest)) = stat.rsplit_once(')') else { continue };
        let name = head.split_once('(').map_or("", |(_, n)| n);
        let f: Vec<&str> = rest.split_whitespace().collect();
        // utime and stime are fields 14 and 15; the fields after ")" start at field 3
        let secs = (f[14 - 3].parse::<f64>().unwrap_or(0.0) + f[15 - 3].parse::<f64>().unwrap_or(0.0)) / ticks;
        let kind = if name.starts_with("poll-") {
            "poll"
        } else if name.starts_with("http") {
            "http"
        } else if name.starts_with("rec-") {
            "recorder"
        } else {
            "other"
        };
        *out.entry(kind).or_insert(0.0) += secs;
    }
    out
}

fn status_kb(pid: u32, key: &str) -> f64 {
    let text = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    text.lines().find_map(|l| l.strip_prefix(key)?.trim().strip_suffix("kB")?.trim().parse().ok()).unwrap_or(f64::NAN)
}

/// One drive's line of `/api/status`.
struct DriveLine {
    polls: f64,
    errors: f64,
    overruns: f64,
    p50_ms: f64,
    p99_ms: f64,
    realtime_priority: Option<u64>,
}

fn drive_status(http: &str) -> Vec<DriveLine> {
    let Some(body) = get(http, "/api/status") else { return Vec::new() };
    let v: serde_json::Value = serde_json::from_str(&body).expect("status JSON");
    v["drives"]
        .as_array()
        .expect("drives")
        .iter()
        .map(|d| {
            let n = |x: &serde_json::Value| x.as_f64().unwrap_or(f64::NAN);
            DriveLine {
                polls: n(&d["link"]["polls"]),
                errors: n(&d["link"]["errors"]),
                overruns: n(&d["timing"]["overruns"]),
                p50_ms: n(&d["timing"]["jitter_p50_ms"]),
                p99_ms: n(&d["timing"]["jitter_p99_ms"]),
                realtime_priority: d["timing"]["realtime_priority"].as_u64(),
            }
        })
        .collect()
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    if v.is_empty() { f64::NAN } else { v[v.len() / 2] }
}

fn model_file(dir: &Path, poll_ms: u64) -> PathBuf {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let text = std::fs::read_to_string(root.join("config/plant.toml")).expect("config/plant.toml");
    assert!(text.contains("sample_ms = 1.0"), "config/plant.toml no longer has `sample_ms = 1.0`");
    let path = dir.join("plant.toml");
    std::fs::write(&path, text.replace("sample_ms = 1.0", &format!("sample_ms = {poll_ms}.0"))).expect("write model");
    path
}

/// `HYDROLENS_BENCH_CONDITION=S`: every drive runs condition checks every S seconds on the last 2·S (issue 19's
/// ten drives with checks every 60 s: `HYDROLENS_BENCH_CASES=10x10 HYDROLENS_BENCH_SECONDS=180
/// HYDROLENS_BENCH_CONDITION=60`; the checks' thread counts under "other").
fn condition_every_s() -> Option<f64> {
    std::env::var("HYDROLENS_BENCH_CONDITION").ok().and_then(|s| s.parse().ok())
}

fn run_case(drives: usize, poll_ms: u64, seconds: f64, rt: Option<u8>, wrk: bool) -> String {
    let dir = tempfile::tempdir().expect("tmp");
    let model = model_file(dir.path(), poll_ms);
    let mut children = Children { sims: Vec::new(), serve: None };
    let mut addrs = Vec::new();
    for i in 0..drives {
        // with real-time poll threads the simulators get the same priority (`chrt`), as PLCs have CPUs of their own
        let mut cmd = match rt {
            Some(p) => {
                let mut c = Command::new("chrt");
                c.args(["-f", &p.to_string(), BIN]);
                c
            }
            None => Command::new(BIN),
        };
        let mut c = cmd
            .args(["sim", "--listen", "127.0.0.1:0", "--seed", &(i + 1).to_string(), "--model"])
            .arg(&model)
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("hydrolens sim");
        addrs.push(announced(&mut c, "modbus tcp://"));
        children.sims.push(c);
    }
    // rls-sgd is tuned for 1 kHz; slower polls use the Kalman filter (docs/estimator.md)
    let method = if poll_ms <= 5 { "rls-sgd" } else { "kalman" };
    let mut cfg = format!(
        "[http]\nbind = \"127.0.0.1:0\"\ntoken = \"bench\"\n[recording]\ndir = {:?}\n",
        dir.path().join("rec").display().to_string()
    );
    for (i, a) in addrs.iter().enumerate() {
        cfg += &format!(
            "[[drives]]\nname = \"d{i}\"\naddress = \"{a}\"\npoll_ms = {poll_ms}\ntimeout_ms = 200\n{}\
             [drives.control]\nmode = \"speed\"\ntarget_omega_rad_s = 30.0\n\
             [drives.estimator]\nmethod = \"{method}\"\nmodel = {:?}\n{}",
            rt.map_or(String::new(), |p| format!("realtime_priority = {p}\n")),
            model.display().to_string(),
            condition_every_s().map_or(String::new(), |e| format!(
                "[drives.condition]\nenabled = true\nwindow_s = {}\nevery_s = {e}\n",
                2.0 * e
            )),
        );
    }
    let cfg_path = dir.path().join("svc.toml");
    std::fs::write(&cfg_path, cfg).expect("write config");
    let mut serve = Command::new(BIN)
        .args(["serve", "--config"])
        .arg(&cfg_path)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("hydrolens serve");
    let http = announced(&mut serve, "dashboard on http://");
    let pid = serve.id();
    children.serve = Some(serve);

    let ready = Instant::now();
    while get(&http, "/readyz").is_none() {
        assert!(ready.elapsed() < Duration::from_secs(20), "the service is not ready after 20 s");
        std::thread::sleep(Duration::from_millis(50));
    }
    std::thread::sleep(Duration::from_secs(3));

    let status_window = Duration::from_millis(1000 * poll_ms);
    let windows = (seconds / status_window.as_secs_f64()).ceil().max(1.0) as u32;
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    let wrk_child = wrk.then(|| {
        Command::new("wrk")
            .args(["-t1", "-c32", &format!("-d{}s", (status_window * windows).as_secs_f64().ceil())])
            .arg(format!("http://{http}/api/status"))
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("wrk (apt-get install wrk)")
    });
    let cpu0 = cpu_by_kind(pid);
    let s0 = drive_status(&http);
    let t0 = Instant::now();
    let (mut p50s, mut p99s) = (Vec::new(), Vec::new());
    for w in 1..=windows {
        std::thread::sleep((status_window * w).saturating_sub(t0.elapsed()));
        for d in drive_status(&http) {
            p50s.push(d.p50_ms);
            p99s.push(d.p99_ms);
        }
    }
    let wall = t0.elapsed().as_secs_f64();
    let cpu1 = cpu_by_kind(pid);
    let s1 = drive_status(&http);
    let (rss, hwm) = (status_kb(pid, "VmRSS:") / 1024.0, status_kb(pid, "VmHWM:") / 1024.0);
    let wrk_rate = wrk_child.map(|c| {
        let out = c.wait_with_output().expect("wrk");
        let text = String::from_utf8_lossy(&out.stdout).into_owned();
        text.lines().find_map(|l| l.strip_prefix("Requests/sec:")?.trim().parse::<f64>().ok()).unwrap_or(f64::NAN)
    });

    let share = |kind: &str| (cpu1.get(kind).unwrap_or(&0.0) - cpu0.get(kind).unwrap_or(&0.0)) / wall * 100.0;
    let total: f64 = ["poll", "http", "recorder", "other"].iter().map(|k| share(k)).sum();
    let delta = |f: fn(&DriveLine) -> f64| s1.iter().map(f).sum::<f64>() - s0.iter().map(f).sum::<f64>();
    let polls = delta(|d| d.polls);
    let errors = delta(|d| d.errors);
    let overruns = delta(|d| d.overruns);
    let granted = s1.iter().filter(|d| d.realtime_priority.is_some()).count();
    let worst99 = p99s.iter().copied().fold(0.0, f64::max);
    format!(
        "| {drives} × {poll_ms} ms | {} | {:.1} s | {total:.1} % (poll {:.1}, http {:.1}, rec {:.1}, other {:.1}) | \
         {rss:.1} / {hwm:.1} MB | {:.1} (nominal {:.0}) | {:.0} µs | {:.0} µs | {:.0} µs | {overruns:.0} | {errors:.0} | {} | {} |",
        match rt {
            Some(p) => format!("FIFO {p} ({granted}/{drives} granted)"),
            None => "normal".into(),
        },
        wall,
        share("poll"),
        share("http"),
        share("recorder"),
        share("other"),
        polls / wall,
        drives as f64 * 1000.0 / poll_ms as f64,
        median(&mut p50s) * 1e3,
        median(&mut p99s) * 1e3,
        worst99 * 1e3,
        wrk_rate.map_or("—".into(), |r| format!("{r:.0}")),
        load.split_whitespace().take(3).collect::<Vec<_>>().join(" "),
    )
}

fn main() {
    let cases = std::env::var("HYDROLENS_BENCH_CASES").unwrap_or_else(|_| "1x1,10x10,50x10".into());
    let seconds: f64 = std::env::var("HYDROLENS_BENCH_SECONDS").ok().and_then(|s| s.parse().ok()).unwrap_or(20.0);
    let rt: Option<u8> = std::env::var("HYDROLENS_BENCH_RT").ok().and_then(|s| s.parse().ok());
    let wrk = std::env::var("HYDROLENS_BENCH_WRK").is_ok_and(|v| v == "1");
    println!(
        "| drives × poll | poll threads | window | service CPU (% of one core) | RSS end / peak | polls/s | \
         jitter p50 (median) | p99 (median) | p99 (worst window) | overruns | errors | wrk req/s | load avg |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    for case in cases.split(',').filter(|c| !c.trim().is_empty()) {
        let (n, p) = case.trim().split_once('x').expect("a case is DRIVESxPOLL_MS, e.g. 50x10");
        let (n, p): (usize, u64) = (n.parse().expect("drives"), p.parse().expect("poll ms"));
        println!("{}", run_case(n, p, seconds, rt, wrk));
    }
}

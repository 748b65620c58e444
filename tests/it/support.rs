//! Helpers shared by the integration tests.
#![allow(dead_code)]

use std::path::PathBuf;

/// The project's root (where Cargo.toml is).
pub fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The `hydrolens` binary built for these tests.
pub fn bin() -> PathBuf {
    PathBuf::from(env!("CARGO_BIN_EXE_hydrolens"))
}

/// Normalised RMS error ‖a − b‖ / ‖b − mean(b)‖ over finite pairs.
pub fn nrmse(a: &[f64], b: &[f64]) -> f64 {
    let pairs: Vec<(f64, f64)> =
        a.iter().zip(b).filter(|(x, y)| x.is_finite() && y.is_finite()).map(|(x, y)| (*x, *y)).collect();
    let mean = pairs.iter().map(|p| p.1).sum::<f64>() / pairs.len() as f64;
    let num: f64 = pairs.iter().map(|(x, y)| (x - y).powi(2)).sum();
    let den: f64 = pairs.iter().map(|(_, y)| (y - mean).powi(2)).sum();
    (num / den).sqrt()
}

/// RMS of a − b over finite pairs.
pub fn rmse(a: &[f64], b: &[f64]) -> f64 {
    let d: Vec<f64> =
        a.iter().zip(b).filter(|(x, y)| x.is_finite() && y.is_finite()).map(|(x, y)| (x - y).powi(2)).collect();
    (d.iter().sum::<f64>() / d.len() as f64).sqrt()
}

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use hydrolens::modbus::simulator::{SimHandle, Simulator};
use hydrolens::plant::{LoadSpec, PlantModel};
use hydrolens::server::{self, Server};
use hydrolens::service::{self, ServiceState};
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

/// The write token of every test stack.
pub const TOKEN: &str = "test-token-7f3a";

/// The reference plant under a constant load (the tests' plant).
pub fn test_plant(load_nm: f64) -> PlantModel {
    let mut m = PlantModel::reference();
    m.load = LoadSpec::Constant { torque_nm: load_nm };
    m
}

/// A simulator on 127.0.0.1:`port` (0: any), stopped by its own token.
pub async fn start_sim(model: PlantModel, port: u16) -> (SimHandle, SocketAddr, CancellationToken, JoinHandle<()>) {
    let sim = Simulator::new(model, 7).expect("a hydraulic model");
    let handle = sim.handle();
    let listener = tokio::net::TcpListener::bind(("127.0.0.1", port)).await.expect("bind modbus");
    let addr = listener.local_addr().expect("addr");
    let stop = CancellationToken::new();
    let s = stop.clone();
    let task = tokio::spawn(async move {
        let _ = sim.run(listener, s).await;
    });
    (handle, addr, stop, task)
}

/// Simulator + service + HTTP, all on loopback port 0.
/// A drive regulating to 30 rad/s (`[drives.control]` in speed mode), for the fault and hardening tests.
pub const SPEED_30: &str = "[drives.control]\nmode = \"speed\"\ntarget_omega_rad_s = 30.0\n";

pub struct Stack {
    pub sim: SimHandle,
    pub modbus_addr: SocketAddr,
    pub url: String,
    pub state: Arc<ServiceState>,
    dir: tempfile::TempDir,
    pub sim_stop: CancellationToken,
    pub sim_task: Option<JoinHandle<()>>,
    server: Option<Server>,
}

/// The config of the test drive `pump1`; `drive_extra` goes under `[[drives]]` (e.g. a `[drives.control]` table).
pub fn config_text(modbus: SocketAddr, dir: &std::path::Path, poll_ms: u64, drive_extra: &str) -> String {
    format!(
        "[http]\nbind = \"127.0.0.1:0\"\ntoken = \"{TOKEN}\"\nmax_body_bytes = 1024\n\n[recording]\ndir = {dir:?}\n\n\
         [[drives]]\nname = \"pump1\"\naddress = \"{modbus}\"\npoll_ms = {poll_ms}\ntimeout_ms = 100\n{drive_extra}\n",
        dir = dir.display().to_string()
    )
}

/// Starts a service from config text and serves HTTP on 127.0.0.1:0 ([`server::start`], as `serve` does).
pub async fn start_service(text: &str) -> Server {
    let settings = service::config::parse(text, "test config", Some(&root())).expect("valid test config");
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind http");
    server::start(listener, &settings, CancellationToken::new()).expect("service starts")
}

/// Stops a service started by [`start_service`], waiting (30 s at most: a loop's last flush waits on a disk that
/// the machine's other work may be filling) for its loops to close their recordings.
pub async fn stop_service(server: Server) {
    tokio::time::timeout(Duration::from_secs(30), server.stop()).await.expect("service stops").expect("http server");
}

/// Moves `drive`'s target through the demo's program (around 40 rad/s, every 100 ms) for `seconds`.
pub async fn follow_demo_program(drive: &hydrolens::service::DriveState, seconds: u64) {
    let start = std::time::Instant::now();
    while start.elapsed() < Duration::from_secs(seconds) {
        let t = start.elapsed().as_secs_f64();
        drive.set_target(hydrolens::service::program::demo_target_rad_s(t, 40.0, drive.max_target_omega_rad_s));
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

impl Stack {
    /// The status code of `GET /readyz`.
    pub async fn readyz(&self) -> u16 {
        reqwest::get(format!("{}/readyz", self.url)).await.expect("GET readyz").status().as_u16()
    }

    /// A stack on a plant with a constant load; `drive_extra` as in [`config_text`].
    pub async fn start(load_nm: f64, poll_ms: u64, drive_extra: &str) -> Stack {
        let (sim, modbus_addr, sim_stop, sim_task) = start_sim(test_plant(load_nm), 0).await;
        Stack::assemble(sim, modbus_addr, modbus_addr, sim_stop, sim_task, poll_ms, drive_extra).await
    }

    /// A stack on any plant model (a load program, say).
    pub async fn start_on(model: PlantModel, poll_ms: u64, drive_extra: &str) -> Stack {
        let (sim, modbus_addr, sim_stop, sim_task) = start_sim(model, 0).await;
        Stack::assemble(sim, modbus_addr, modbus_addr, sim_stop, sim_task, poll_ms, drive_extra).await
    }

    /// As [`Stack::start`], with the service reaching the simulator through a fault-injecting proxy.
    pub async fn start_behind_proxy(
        load_nm: f64,
        poll_ms: u64,
        drive_extra: &str,
    ) -> (Stack, crate::proxy::FaultProxy) {
        let (sim, modbus_addr, sim_stop, sim_task) = start_sim(test_plant(load_nm), 0).await;
        let proxy = crate::proxy::FaultProxy::start(modbus_addr).await;
        let stack = Stack::assemble(sim, modbus_addr, proxy.addr, sim_stop, sim_task, poll_ms, drive_extra).await;
        (stack, proxy)
    }

    async fn assemble(
        sim: SimHandle,
        modbus_addr: SocketAddr,
        service_reaches: SocketAddr,
        sim_stop: CancellationToken,
        sim_task: JoinHandle<()>,
        poll_ms: u64,
        drive_extra: &str,
    ) -> Stack {
        let dir = tempfile::tempdir().expect("tmp");
        let text = config_text(service_reaches, dir.path(), poll_ms, drive_extra);
        let server = start_service(&text).await;
        Stack {
            sim,
            modbus_addr,
            url: server.url.clone(),
            state: server.state.clone(),
            dir,
            sim_stop,
            sim_task: Some(sim_task),
            server: Some(server),
        }
    }

    /// Stops everything, waiting (bounded) for the loops to close their recordings; hands back the recording dir.
    pub async fn stop(mut self) -> tempfile::TempDir {
        self.sim_stop.cancel();
        let bounded = Duration::from_secs(10);
        if let Some(s) = self.server.take() {
            stop_service(s).await;
        }
        if let Some(t) = self.sim_task.take() {
            let _ = tokio::time::timeout(bounded, t).await.expect("simulator stops");
        }
        self.dir
    }

    pub fn recording_dir(&self) -> &std::path::Path {
        self.dir.path()
    }

    /// The drive's snapshot as JSON from /api/status.
    pub async fn status(&self) -> serde_json::Value {
        get_json(format!("{}/api/status", self.url)).await["drives"][0].clone()
    }

    pub async fn metrics(&self) -> String {
        reqwest::get(format!("{}/metrics", self.url)).await.expect("GET metrics").text().await.expect("text")
    }

    /// As [`wait_polls`], for the stack's drive.
    pub async fn wait_polls(&self, n: u64, what: &str) {
        wait_polls(&self.state.drives[0], n, what).await;
    }
}

/// Waits until `drive` has run `n` more poll cycles (each counted when it starts, whatever its outcome, and
/// published when it ends): a window measured in the loop's own cycles, not in a guess of how fast this machine is.
/// Panics (naming `what`) if they do not come within 10 s.
pub async fn wait_polls(drive: &hydrolens::service::DriveState, n: u64, what: &str) {
    let from = drive.snapshot().link.polls;
    wait_for(Duration::from_secs(10), || async { drive.snapshot().link.polls >= from + n })
        .await
        .unwrap_or_else(|| panic!("{what}: {n} poll cycles did not run within 10 s (from {from})"));
}

/// `GET url`, its body as JSON.
/// `POST {url}/api/drives/pump1/reset` with the test token: the status code.
pub async fn post_reset(url: &str) -> u16 {
    reqwest::Client::new()
        .post(format!("{url}/api/drives/pump1/reset"))
        .bearer_auth(TOKEN)
        .send()
        .await
        .expect("POST reset")
        .status()
        .as_u16()
}

pub async fn get_json(url: impl AsRef<str>) -> serde_json::Value {
    let url = url.as_ref();
    let r = reqwest::get(url).await.unwrap_or_else(|e| panic!("GET {url}: {e}"));
    r.json().await.unwrap_or_else(|e| panic!("GET {url}: not JSON: {e}"))
}

/// Polls `cond` every 20 ms until it holds or `limit` passes; returns the time it took.
pub async fn wait_for<F, Fut>(limit: Duration, mut cond: F) -> Option<Duration>
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = bool>,
{
    let start = tokio::time::Instant::now();
    while start.elapsed() < limit {
        if cond().await {
            return Some(start.elapsed());
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    None
}

/// As [`wait_for`], for tests whose parts are separate processes or threads: polls `cond` every 10 ms until it
/// holds or `limit` passes; returns the time it took.
pub fn wait_for_sync(limit: Duration, mut cond: impl FnMut() -> bool) -> Option<Duration> {
    let start = std::time::Instant::now();
    loop {
        if cond() {
            return Some(start.elapsed());
        }
        if start.elapsed() >= limit {
            return None;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// Waits (polled, `limit` at most) for `child` to exit: its status, or None if it is still running.
pub fn wait_exit(child: &mut std::process::Child, limit: Duration) -> Option<std::process::ExitStatus> {
    let mut status = None;
    wait_for_sync(limit, || {
        status = child.try_wait().expect("wait");
        status.is_some()
    });
    status
}

/// The value of a metric line that starts with `prefix` (name and labels), if present.
pub fn metric(text: &str, prefix: &str) -> Option<f64> {
    text.lines().find(|l| l.starts_with(prefix)).and_then(|l| l.rsplit(' ').next()).and_then(|v| v.parse().ok())
}

/// `hydrolens serve` run as the real binary from config text (written to `dir/serve.toml`), its memory its own and
/// its log collected; killed on drop.
pub struct ServeProcess {
    child: std::process::Child,
    pub url: String,
    pub addr: SocketAddr,
    log: Arc<std::sync::Mutex<String>>,
}

impl ServeProcess {
    pub fn start(dir: &std::path::Path, config_text: &str) -> ServeProcess {
        let config = dir.join("serve.toml");
        std::fs::write(&config, config_text).expect("config");
        let mut command = std::process::Command::new(bin());
        command.args(["serve", "--config"]).arg(&config);
        ServeProcess::spawn(command)
    }

    /// `serve --config <config> --http 127.0.0.1:0` run by `sh -c` after `limits` (shell commands such as
    /// `ulimit -f 0`).
    pub fn start_limited(limits: &str, config: &std::path::Path) -> ServeProcess {
        let script =
            format!("{limits}; exec {} serve --config {} --http 127.0.0.1:0", bin().display(), config.display());
        let mut command = std::process::Command::new("sh");
        command.args(["-c", &script]);
        ServeProcess::spawn(command)
    }

    /// Runs `command` and reads its stderr until it announces its URL (which it must).
    fn spawn(mut command: std::process::Command) -> ServeProcess {
        use std::io::{BufRead, BufReader};
        // the log's own default filter (not the caller's RUST_LOG)
        let mut child = command
            .env_remove("RUST_LOG")
            .env("NO_COLOR", "1")
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .expect("serve starts");
        let mut lines = BufReader::new(child.stderr.take().expect("stderr")).lines();
        let log = Arc::new(std::sync::Mutex::new(String::new()));
        let url = loop {
            let Some(Ok(line)) = lines.next() else {
                panic!("serve ended without announcing its address:\n{}", log.lock().expect("log"))
            };
            log.lock().expect("log").push_str(&format!("{line}\n"));
            if let Some(url) = line.split("dashboard on ").nth(1) {
                break url.trim().trim_end_matches('/').to_string();
            }
        };
        // keep reading the log so that the child never blocks on a full pipe
        let sink = log.clone();
        std::thread::spawn(move || {
            for line in lines.map_while(Result::ok) {
                let mut l = sink.lock().unwrap_or_else(|e| e.into_inner());
                l.push_str(&line);
                l.push('\n');
            }
        });
        let addr = url.trim_start_matches("http://").parse().expect("an address");
        ServeProcess { child, url, addr, log }
    }

    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// SIGTERM, then waits (10 s at most) for it to exit: its exit status, None if it had to be killed.
    pub fn stop(&mut self) -> Option<std::process::ExitStatus> {
        let _ = std::process::Command::new("kill").args(["-TERM", &self.pid().to_string()]).status();
        let code = wait_exit(&mut self.child, Duration::from_secs(10));
        if code.is_none() {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
        code
    }

    /// SIGKILL (a crash, an OOM kill: no clean stop), and waits for it.
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// The log so far (stderr).
    pub fn log(&self) -> String {
        self.log.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }

    /// The resident memory of the service, in MB.
    pub fn rss_mb(&self) -> f64 {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.child.id())).expect("proc status");
        let kb: f64 = status
            .lines()
            .find_map(|l| l.strip_prefix("VmRSS:"))
            .and_then(|v| v.split_whitespace().next())
            .and_then(|v| v.parse().ok())
            .expect("VmRSS");
        kb / 1024.0
    }

    pub async fn metrics(&self) -> String {
        reqwest::get(format!("{}/metrics", self.url)).await.expect("GET metrics").text().await.expect("text")
    }

    pub async fn status(&self) -> serde_json::Value {
        reqwest::get(format!("{}/api/status", self.url)).await.expect("GET status").json().await.expect("json")
    }

    /// The first drive's entry in /api/status.
    pub async fn drive_status(&self) -> serde_json::Value {
        self.status().await["drives"][0].clone()
    }

    /// `GET /readyz`: its code and body.
    pub async fn readyz(&self) -> (u16, serde_json::Value) {
        let r = reqwest::get(format!("{}/readyz", self.url)).await.expect("GET readyz");
        let code = r.status().as_u16();
        (code, r.json().await.unwrap_or(serde_json::Value::Null))
    }
}

impl Drop for ServeProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

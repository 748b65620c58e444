//! Modbus RTU end to end: the service against the simulator over a virtual serial line (a `socat` pty pair, started
//! and stopped here), two drives with unit ids 1 and 2 taking turns on one line, the line unplugged (socat killed)
//! and back, RTU framing over TCP, and the configs a line cannot carry refused by `hydrolens serve` with exit 2.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use hydrolens::modbus::line::{Parity, SerialLine};
use hydrolens::modbus::simulator::{SimHandle, Simulator};
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

use crate::support::{TOKEN, bin, get_json, start_service, stop_service, test_plant, wait_for};

/// A virtual serial line: two ptys joined by socat, reached through the links `a` (the service's end) and `b`
/// (the simulator's). Dropping it unplugs the line.
struct SocatLine {
    dir: PathBuf,
    child: Option<Child>,
}

impl SocatLine {
    /// Starts socat and waits (at most 5 s) until both links exist. Fails if socat is missing: tests/run.sh
    /// installs it from Debian.
    fn plug(dir: &Path) -> SocatLine {
        let mut line = SocatLine { dir: dir.to_path_buf(), child: None };
        line.replug();
        line
    }

    fn end(&self, name: &str) -> PathBuf {
        self.dir.join(name)
    }

    fn replug(&mut self) {
        assert!(self.child.is_none(), "the line is already plugged");
        let pty = |name: &str| format!("pty,raw,echo=0,link={}", self.end(name).display());
        let child = Command::new("socat")
            .args(["-d", "-d", &pty("a"), &pty("b")])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start socat ({e}): install Debian's socat (tests/run.sh does)"));
        self.child = Some(child);
        let deadline = std::time::Instant::now() + Duration::from_secs(5);
        while !(self.end("a").exists() && self.end("b").exists()) {
            assert!(std::time::Instant::now() < deadline, "socat made no pty links within 5 s");
            std::thread::sleep(Duration::from_millis(10));
        }
    }

    /// Kills socat (the ptys go, and with them both ends of the line) and waits until its links are gone.
    fn unplug(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
        // socat removes its links on a clean exit only; a killed one may leave them
        for name in ["a", "b"] {
            let _ = std::fs::remove_file(self.end(name));
        }
    }
}

impl Drop for SocatLine {
    fn drop(&mut self) {
        self.unplug();
    }
}

/// The test line's settings (a pty ignores them, but both ends set them as a real line would).
const LINE: SerialLine = SerialLine { baud_rate: 115_200, parity: Parity::Even, stop_bits: 1 };

/// The simulated drives' own watchdog (ms). Longer than the plant file's 1 s: the simulator, the service and the
/// pty relay share this test process's two cores with the rest of the suite, and a second without a write while the
/// machine is loaded tripped the drives before they had regulated once (seen at load 7, every run). A trip still
/// comes within this much of the last write.
const WATCHDOG_MS: u64 = 3000;

/// A simulator with one plant per unit id, and the token that stops it.
fn serial_sim(units: &[u8]) -> (Simulator, CancellationToken) {
    let mut model = test_plant(5.0);
    if let Some(d) = model.drive.as_mut() {
        d.comm_timeout_ms = WATCHDOG_MS;
    }
    (Simulator::with_units(model, 7, units).expect("a hydraulic model"), CancellationToken::new())
}

fn plant(sim: &Simulator, unit: u8) -> SimHandle {
    sim.handle_for(unit).expect("a plant at that unit id")
}

fn spawn_serial(sim: Simulator, path: &Path, stop: &CancellationToken) -> JoinHandle<()> {
    let path = path.display().to_string();
    let stop = stop.clone();
    tokio::spawn(async move {
        let _ = sim.run_serial(&path, LINE, stop).await;
    })
}

/// An RTU drive on the line's `a` end: `[[drives]]` text.
fn rtu_drive(name: &str, port: &Path, unit: u8, poll_ms: u64, target: f64) -> String {
    format!(
        "[[drives]]\nname = \"{name}\"\ntransport = \"rtu\"\nserial_port = {port:?}\nbaud_rate = {}\nparity = \"even\"\n\
         stop_bits = 1\nunit_id = {unit}\npoll_ms = {poll_ms}\ntimeout_ms = 100\n\
         [drives.control]\nmode = \"speed\"\ntarget_omega_rad_s = {target}\n",
        LINE.baud_rate,
        port = port.display().to_string()
    )
}

fn service_text(dir: &Path, drives: &str) -> String {
    format!(
        "[http]\nbind = \"127.0.0.1:0\"\ntoken = \"{TOKEN}\"\n\n[recording]\ndir = {:?}\n\n{drives}",
        dir.display().to_string()
    )
}

async fn status(url: &str) -> serde_json::Value {
    get_json(format!("{url}/api/status")).await
}

async fn readyz(url: &str) -> u16 {
    reqwest::get(format!("{url}/readyz")).await.expect("GET readyz").status().as_u16()
}

/// The service's drive `i` regulates its own plant to `target` and its estimate follows.
async fn regulates(url: &str, i: usize, sim: &SimHandle, target: f64, limit: Duration) -> bool {
    let held = wait_for(limit, || async {
        let truth = sim.lock().truth();
        let s = status(url).await;
        let d = &s["drives"][i];
        let omega_hat = d["estimate"]["omega_hat_rad_s"].as_f64().unwrap_or(f64::NAN);
        !truth.tripped
            && (truth.omega_rad_s - target).abs() < 2.0
            && (omega_hat - target).abs() < 3.0
            && d["link"]["stale"] == false
    })
    .await
    .is_some();
    if !held {
        let s = status(url).await;
        eprintln!("drive {i} does not regulate to {target}: truth {:?}; status {}", sim.lock().truth(), s["drives"][i]);
    }
    held
}

/// Two drives on one RTU line (units 1 and 2 of one serial simulator, polled every 40 ms), each asserted to regulate
/// to its own target (30 and 20 rad/s) before this returns.
struct TwoOnOneLine {
    _dir: tempfile::TempDir,
    line: SocatLine,
    one: SimHandle,
    two: SimHandle,
    sim_stop: CancellationToken,
    sim_task: JoinHandle<()>,
    service: hydrolens::server::Server,
}

impl TwoOnOneLine {
    async fn regulating() -> TwoOnOneLine {
        let dir = tempfile::tempdir().expect("tmp");
        let line = SocatLine::plug(dir.path());
        let (sim, sim_stop) = serial_sim(&[1, 2]);
        let (one, two) = (plant(&sim, 1), plant(&sim, 2));
        let sim_task = spawn_serial(sim, &line.end("b"), &sim_stop);
        let drives = format!(
            "{}{}",
            rtu_drive("vfd1", &line.end("a"), 1, 40, 30.0),
            rtu_drive("vfd2", &line.end("a"), 2, 40, 20.0)
        );
        let service = start_service(&service_text(dir.path(), &drives)).await;
        let url = &service.url;
        assert!(regulates(url, 0, &one, 30.0, Duration::from_secs(15)).await, "vfd1 (unit 1) regulates");
        assert!(regulates(url, 1, &two, 20.0, Duration::from_secs(15)).await, "vfd2 (unit 2) regulates");
        TwoOnOneLine { _dir: dir, line, one, two, sim_stop, sim_task, service }
    }

    async fn stop(self) {
        stop_service(self.service).await;
        self.sim_stop.cancel();
        tokio::time::timeout(Duration::from_secs(5), self.sim_task).await.expect("sim stops").expect("sim task");
        drop(self.line);
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_drives_on_one_line_take_turns() {
    let run = async {
        // each unit id reaches its own plant: two different targets are both met
        let pair = TwoOnOneLine::regulating().await;
        let (url, line) = (pair.service.url.clone(), &pair.line);
        let s = status(&url).await;
        for d in s["drives"].as_array().expect("drives") {
            assert_eq!(d["link"]["connected"], true, "{d}");
            assert!(d["link"]["polls"].as_u64().unwrap_or(0) > 20, "{d}");
            assert_eq!(d["address"], line.end("a").display().to_string(), "{d}");
        }
        assert_eq!(readyz(&url).await, 200);
        pair.stop().await;
    };
    tokio::time::timeout(Duration::from_secs(60), run).await.expect("within 60 s");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_silent_device_does_not_starve_its_neighbour_on_the_line() {
    let run = async {
        let pair = TwoOnOneLine::regulating().await;
        let (url, one, two) = (pair.service.url.clone(), pair.one.clone(), pair.two.clone());
        // vfd1's polls a second with both devices answering, the reference for the rate beside a silent one below
        // (a rate of the same machine at the same time, so that a loaded machine slows both alike)
        let answering = vfd1_rate(&url).await;

        // unit 2 stops answering: it goes stale and trips; unit 1 keeps being polled and regulated throughout
        two.lock().faults.no_reply = true;
        let polls_before = link_count(&url, 0, "polls").await;
        // vfd1 fresh at (almost) every look: a starved vfd1 would be stale at most of them; one or two stale looks
        // are a machine that stalled the test beyond vfd1's stale_ms, not the line
        let (fresh_checks, stale_checks) =
            (std::sync::atomic::AtomicUsize::new(0), std::sync::atomic::AtomicUsize::new(0));
        let tripped = wait_for(Duration::from_secs(15), || {
            let (url, two, fresh, stale) = (&url, &two, &fresh_checks, &stale_checks);
            async move {
                let s = status(url).await;
                let counter = if s["drives"][0]["link"]["stale"] == false { fresh } else { stale };
                counter.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                s["drives"][1]["link"]["stale"] == true && two.lock().truth().tripped
            }
        })
        .await;
        let (fresh_checks, stale_checks) = (fresh_checks.into_inner(), stale_checks.into_inner());
        assert!(tripped.is_some(), "vfd2 stale and tripped: {}", status(&url).await);
        // a starved vfd1 is stale at (almost) every look. vfd1 is stale when 200 ms pass without a fresh sample, and
        // each of vfd2's probes holds the line for its 100 ms timeout, so a machine that stalls this process makes
        // vfd1 stale at some looks (seen at load 12: 6 of 115; beside a build and estimator runs: 56 of 138; six test
        // threads beside a release build: 71 of 128). What tells the designs apart is counted below (vfd2's timeouts
        // against vfd1's polls); here, fresh at a quarter of the looks at least
        eprintln!("vfd1 stale at {stale_checks} of {} looks beside a silent vfd2", fresh_checks + stale_checks);
        assert!(
            4 * fresh_checks >= fresh_checks + stale_checks,
            "vfd1 stale at {stale_checks} of {} looks beside a silent vfd2",
            fresh_checks + stale_checks
        );
        let s = status(&url).await;
        assert!(s["drives"][1]["link"]["errors"].as_u64().unwrap_or(0) >= 1, "vfd2's timeouts counted: {s}");
        assert!(s["drives"][0]["link"]["polls"].as_u64().unwrap_or(0) > polls_before + 10, "{s}");
        assert!(fresh_checks > 10, "vfd1 checked {fresh_checks} times");
        let t = one.lock().truth();
        assert!(!t.tripped && (t.omega_rad_s - 30.0).abs() < 2.0, "vfd1 still regulated: {t:?}");
        // the silent device is held back on its own: it is asked (and times out) far less often than vfd1 is polled.
        // Counted, not timed: held back alone (its back-off doubling to 500 ms) it timed out once per 12 of vfd1's
        // polls on an idle machine; a line that asked it every cycle, or backed off as a whole after each of its
        // timeouts, would give about one each, however fast the machine. vfd1's rate is printed beside: 25 a second
        // before and beside the silent device on an idle machine, 7 with the whole line backing off, but a loaded
        // machine slows it alone (6.1 a second against 25.0 measured just before, on a fresh clone beside a build)
        let (polls_at, timeouts_at) = (link_count(&url, 0, "polls").await, link_count(&url, 1, "errors").await);
        let per_s = vfd1_rate(&url).await;
        let polls = link_count(&url, 0, "polls").await - polls_at;
        let timeouts = link_count(&url, 1, "errors").await - timeouts_at;
        eprintln!(
            "vfd1 kept {per_s:.1} polls a second beside a silent vfd2, {answering:.1} with both answering; vfd2 timed \
             out {timeouts} times over vfd1's {polls} polls"
        );
        assert!(
            2 * timeouts <= polls,
            "vfd2 timed out {timeouts} times over vfd1's {polls} polls: not held back alone"
        );
        assert_eq!(readyz(&url).await, 503, "not ready while vfd2 is stale");

        pair.stop().await;
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("within 120 s");
}

/// vfd1's polls a second over its next 25 fresh samples, in the service's own time stamps.
async fn vfd1_rate(url: &str) -> f64 {
    let t0 = vfd1_times(url, f64::NEG_INFINITY).await.last().copied().unwrap_or(0.0);
    wait_for(Duration::from_secs(15), || async { vfd1_times(url, t0).await.len() >= 25 })
        .await
        .expect("vfd1 keeps being polled");
    25.0 / (vfd1_times(url, t0).await[24] - t0)
}

/// A counter of drive `index`'s link in `/api/status` (`polls`, `errors`); missing, the test fails rather than count
/// zero (a zero of timeouts would pass the hold-back's assertion unseen).
async fn link_count(url: &str, index: usize, counter: &str) -> u64 {
    status(url).await["drives"][index]["link"][counter].as_u64().unwrap_or_else(|| panic!("link counter {counter}"))
}

/// The time stamps (`t_s`) of vfd1's samples in the last 10 s of its history, those after `after_s`.
async fn vfd1_times(url: &str, after_s: f64) -> Vec<f64> {
    let h = get_json(format!("{url}/api/history?drive=vfd1&seconds=10")).await;
    h["t_s"].as_array().map_or(Vec::new(), |a| a.iter().filter_map(|v| v.as_f64()).filter(|t| *t > after_s).collect())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unplugged_line_goes_stale_trips_the_drive_and_comes_back() {
    let run = async {
        let dir = tempfile::tempdir().expect("tmp");
        let mut line = SocatLine::plug(dir.path());
        let (sim, sim_stop) = serial_sim(&[1]);
        let drive = plant(&sim, 1);
        let sim_task = spawn_serial(sim, &line.end("b"), &sim_stop);
        let text = service_text(dir.path(), &rtu_drive("vfd1", &line.end("a"), 1, 20, 30.0));
        let service = start_service(&text).await;
        let url = service.url.clone();
        assert!(regulates(&url, 0, &drive, 30.0, Duration::from_secs(15)).await, "regulates before the fault");

        line.unplug();
        let down = wait_for(Duration::from_secs(10), || async {
            let s = status(&url).await;
            readyz(&url).await == 503 && s["drives"][0]["link"]["stale"] == true
        })
        .await;
        assert!(down.is_some(), "stale and not ready without the line: {}", status(&url).await);
        // nothing reaches the drive, so its own watchdog trips it and it ramps down: its safe state
        let writes = drive.lock().writes;
        let tripped = wait_for(Duration::from_secs(15), || async { drive.lock().truth().tripped }).await;
        assert!(tripped.is_some(), "the drive's watchdog trips without writes");
        assert_eq!(drive.lock().writes, writes, "nothing written while the line is down");
        let s = status(&url).await;
        assert_eq!(s["drives"][0]["link"]["connected"], false, "{s}");

        line.replug();
        let back = wait_for(Duration::from_secs(10), || async {
            let s = status(&url).await;
            readyz(&url).await == 200 && s["drives"][0]["link"]["stale"] == false
        })
        .await;
        assert!(back.is_some(), "polling resumes with the line back: {}", status(&url).await);
        let s = status(&url).await;
        assert!(s["drives"][0]["link"]["reconnects"].as_u64().unwrap_or(0) >= 1, "{s}");
        assert_eq!(s["drives"][0]["tripped"], true, "the service never re-arms a tripped drive by itself: {s}");
        let reset = reqwest::Client::new()
            .post(format!("{url}/api/drives/vfd1/reset"))
            .bearer_auth(TOKEN)
            .send()
            .await
            .expect("POST reset");
        assert!(reset.status().is_success(), "{}", reset.status());
        assert!(regulates(&url, 0, &drive, 30.0, Duration::from_secs(10)).await, "regulates after the reset");

        stop_service(service).await;
        sim_stop.cancel();
        tokio::time::timeout(Duration::from_secs(5), sim_task).await.expect("sim stops").expect("sim task");
    };
    tokio::time::timeout(Duration::from_secs(60), run).await.expect("within 60 s");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rtu_over_tcp_reaches_the_simulator() {
    let run = async {
        let dir = tempfile::tempdir().expect("tmp");
        let sim = Simulator::with_units(test_plant(5.0), 7, &[3]).expect("model");
        let drive = plant(&sim, 3);
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind");
        let addr = listener.local_addr().expect("addr");
        let sim_stop = CancellationToken::new();
        let s = sim_stop.clone();
        let sim_task = tokio::spawn(async move {
            let _ = sim.run_rtu_over_tcp(listener, s).await;
        });
        let drives = format!(
            "[[drives]]\nname = \"gw3\"\ntransport = \"rtu-over-tcp\"\naddress = \"{addr}\"\nbaud_rate = 115200\n\
             unit_id = 3\npoll_ms = 20\ntimeout_ms = 100\n[drives.control]\nmode = \"speed\"\ntarget_omega_rad_s = 25.0\n"
        );
        let service = start_service(&service_text(dir.path(), &drives)).await;
        let url = service.url.clone();
        assert!(regulates(&url, 0, &drive, 25.0, Duration::from_secs(15)).await, "regulates over rtu-over-tcp");
        assert_eq!(readyz(&url).await, 200);
        stop_service(service).await;
        sim_stop.cancel();
        tokio::time::timeout(Duration::from_secs(5), sim_task).await.expect("sim stops").expect("sim task");
    };
    tokio::time::timeout(Duration::from_secs(60), run).await.expect("within 60 s");
}

/// `hydrolens serve` on a config it must refuse: exit 2, and the message.
fn refused(dir: &Path, name: &str, drives: &str) -> String {
    let path = dir.join(name);
    std::fs::write(&path, service_text(dir, drives)).expect("write config");
    let out = Command::new(bin()).args(["serve", "--config"]).arg(&path).output().expect("runs");
    let text = String::from_utf8_lossy(&out.stderr).into_owned();
    assert_eq!(out.status.code(), Some(2), "{name}: {text}");
    text
}

#[test]
fn configs_a_line_cannot_serve_are_refused() {
    let dir = tempfile::tempdir().expect("tmp");
    let port = dir.path().join("ttyS9");
    // three writing drives every 10 ms at 19200 baud: far beyond the line
    let slow = |name: &str, unit: u8| {
        rtu_drive(name, &port, unit, 10, 20.0).replace("baud_rate = 115200", "baud_rate = 19200")
    };
    let text = refused(dir.path(), "over.toml", &format!("{}{}{}", slow("vfd1", 1), slow("vfd2", 2), slow("vfd3", 3)));
    assert!(text.contains("cannot carry"), "{text}");
    for name in ["vfd1", "vfd2", "vfd3"] {
        assert!(text.contains(name), "names every drive on the line: {text}");
    }
    let text = refused(dir.path(), "noport.toml", "[[drives]]\nname = \"vfd1\"\ntransport = \"rtu\"\nunit_id = 1\n");
    assert!(text.contains("drives[0].serial_port"), "{text}");
    let text =
        refused(dir.path(), "parity.toml", &rtu_drive("vfd1", &port, 1, 50, 20.0).replace("\"even\"", "\"mark\""));
    assert!(text.contains("drives[0].parity"), "{text}");
    let mixed = format!(
        "{}{}",
        rtu_drive("vfd1", &port, 1, 100, 20.0),
        rtu_drive("vfd2", &port, 2, 100, 20.0).replace("parity = \"even\"", "parity = \"odd\"")
    );
    let text = refused(dir.path(), "mixed.toml", &mixed);
    assert!(text.contains("one setting") && text.contains("vfd2"), "{text}");
}

/// A device that answers every read with zeros and notes when each request reached it.
#[derive(Clone)]
struct Stopwatch(std::sync::Arc<std::sync::Mutex<Vec<std::time::Instant>>>);

impl tokio_modbus::server::Service for Stopwatch {
    type Request = tokio_modbus::SlaveRequest<'static>;
    type Response = tokio_modbus::Response;
    type Exception = tokio_modbus::ExceptionCode;
    type Future = std::future::Ready<Result<tokio_modbus::Response, tokio_modbus::ExceptionCode>>;

    fn call(&self, req: Self::Request) -> Self::Future {
        self.0.lock().unwrap_or_else(|e| e.into_inner()).push(std::time::Instant::now());
        std::future::ready(match req.request {
            tokio_modbus::Request::ReadInputRegisters(_, n) => {
                Ok(tokio_modbus::Response::ReadInputRegisters(vec![0; usize::from(n)]))
            }
            _ => Err(tokio_modbus::ExceptionCode::IllegalFunction),
        })
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn requests_on_a_line_keep_the_inter_frame_gap() {
    use hydrolens::modbus::client::{DriveClient, Endpoint, open_serial};
    use hydrolens::modbus::map::Table;
    let run = async {
        let dir = tempfile::tempdir().expect("tmp");
        let line = SocatLine::plug(dir.path());
        // at 9600 baud, even parity: 3.5 characters of 11 bits = 4.0 ms of silence between frames
        let slow = SerialLine { baud_rate: 9600, parity: Parity::Even, stop_bits: 1 };
        let gap = slow.inter_frame_gap();
        assert!((gap.as_secs_f64() - 3.5 * 11.0 / 9600.0).abs() < 1e-6);
        let seen = Stopwatch(Default::default());
        let device = tokio_modbus::server::rtu::Server::new(
            open_serial(&line.end("b").display().to_string(), &slow).expect("open b"),
        );
        let stop = CancellationToken::new();
        let s = stop.clone();
        let served = seen.clone();
        let task = tokio::spawn(async move { device.serve_until(served, async move { s.cancelled().await }).await });
        let endpoint = Endpoint::Serial { port: line.end("a").display().to_string(), line: slow };
        // a reply's deadline far beyond the line's time (20 ms a frame pair at 9600 baud): the test measures the
        // gaps, and on a loaded machine socat and the device task can be scheduled late (a 500 ms deadline timed
        // out once in the repeated suite runs, beside a release build)
        let mut client = DriveClient::on(endpoint, 1, Duration::from_secs(10));
        for _ in 0..20 {
            client.read(Table::Input, 0, 6).await.expect("a reply");
        }
        client.close().await;
        stop.cancel();
        let _ = tokio::time::timeout(Duration::from_secs(5), task).await.expect("device stops");
        let times = seen.0.lock().unwrap_or_else(|e| e.into_inner()).clone();
        assert_eq!(times.len(), 20);
        // each request reached the device at least a gap after it had answered the one before (the answer went
        // out after the time noted, so this is a lower bound that holds however slow the machine)
        let shortest = times.windows(2).map(|w| w[1] - w[0]).min().expect("pairs");
        eprintln!("requests at least {shortest:?} apart on the line, the gap is {gap:?}");
        assert!(shortest >= gap, "requests {shortest:?} apart, the gap is {gap:?}");
        drop(line);
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("within 120 s");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sim_serves_rtu_on_a_serial_device_from_the_command_line() {
    use hydrolens::modbus::client::{ClientError, DriveClient, Endpoint};
    use hydrolens::modbus::map::Table;
    let dir = tempfile::tempdir().expect("tmp");
    let line = SocatLine::plug(dir.path());
    let bad = Command::new(bin())
        .args(["sim", "--serial"])
        .arg(line.end("b"))
        .args(["--parity", "mark"])
        .output()
        .expect("runs");
    assert_eq!(bad.status.code(), Some(2), "{}", String::from_utf8_lossy(&bad.stderr));
    assert!(String::from_utf8_lossy(&bad.stderr).contains("--parity"));
    let mut sim = Command::new(bin())
        .args(["sim", "--model"])
        .arg(crate::support::root().join("config/plant.toml"))
        .args(["--serial"])
        .arg(line.end("b"))
        .args(["--baud", "115200", "--parity", "even", "--units", "1,2"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("sim starts");
    let run = async {
        let a = line.end("a").display().to_string();
        let endpoint = Endpoint::Serial { port: a, line: LINE };
        let mut client = DriveClient::on(endpoint, 2, Duration::from_millis(100));
        let mut answered = false;
        for _ in 0..250 {
            if client.read(Table::Input, 0, 6).await.is_ok() {
                answered = true;
                break;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        assert!(answered, "unit 2 answers");
        // a unit id the simulator does not serve: nobody answers
        client.set_unit_id(5);
        let mut last = None;
        for _ in 0..20 {
            match client.read(Table::Input, 0, 6).await {
                Err(ClientError::Backoff(d)) => tokio::time::sleep(d).await,
                other => {
                    last = Some(other);
                    break;
                }
            }
        }
        assert!(matches!(last, Some(Err(ClientError::Timeout(_)))), "unit 5: {last:?}");
        client.close().await;
    };
    let result = tokio::time::timeout(Duration::from_secs(20), run).await;
    let _ = Command::new("kill").args(["-TERM", &sim.id().to_string()]).status();
    if crate::support::wait_exit(&mut sim, Duration::from_secs(5)).is_none() {
        let _ = sim.kill();
        panic!("sim did not stop on SIGTERM");
    }
    result.expect("within 20 s");
}

/// Noise on an RTU line (the device's end sending random bytes without a pause) fills the log at the service's own
/// pace only: tokio-modbus logged every frame it could not decode, with its bytes, at WARN and ERROR: 730 lines a
/// second (a hostile tester's line), past the service's once-per-10-s warning of the same fault.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn noise_on_the_line_does_not_flood_the_log() {
    let dir = tempfile::tempdir().expect("tmp");
    let line = SocatLine::plug(dir.path());
    let text = service_text(&dir.path().join("rec"), &rtu_drive("vfd1", &line.end("a"), 1, 40, 30.0));
    let s = crate::support::ServeProcess::start(dir.path(), &text);
    let device = line.end("b");
    // 3 s of noise (a bounded loop; the assertions are on what the log holds, not on time)
    let noise = std::thread::spawn(move || {
        use std::io::Write;
        let mut port = std::fs::OpenOptions::new().write(true).open(device).expect("the device's end");
        let mut x: u64 = 0x9e37_79b9_7f4a_7c15;
        for _ in 0..3000 {
            let bytes: Vec<u8> = (0..32)
                .map(|_| {
                    x ^= x << 13;
                    x ^= x >> 7;
                    x ^= x << 17;
                    x as u8
                })
                .collect();
            let _ = port.write_all(&bytes);
            std::thread::sleep(Duration::from_millis(1));
        }
    });
    tokio::task::spawn_blocking(move || noise.join()).await.expect("join").expect("the noise");
    let errors = |m: String| -> f64 {
        let total = m.lines().filter(|l| l.starts_with("hydrolens_errors_total{") && l.contains("vfd1"));
        total.filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok()).sum()
    };
    let counted = wait_for(Duration::from_secs(10), || async { errors(s.metrics().await) > 0.0 }).await;
    assert!(counted.is_some(), "the noise is counted as errors: {}", s.metrics().await);
    let log = s.log();
    let lines = log.lines().count();
    eprintln!("3 s of noise on the line: {lines} log lines");
    assert!(!log.contains("tokio_modbus"), "the library's own lines: {}", &log[..log.len().min(2000)]);
    assert!(lines < 200, "{lines} lines: {}", &log[..log.len().min(2000)]);
}

/// A neighbour that answers past its timeout (130 ms against 100): its late reply comes while the healthy drive is
/// asked, and is not that drive's error. Charged to it, a hostile tester's healthy drive counted one protocol error
/// ("mismatching headers: expected slave_id 1, actual slave_id 2") for each of the late one's timeouts; resent at
/// once after such a stray, the healthy drive's own reply to the first request answered its next (on a loaded
/// machine, 2 errors for 5 timeouts). Counted, not timed: vfd2's timeouts against vfd1's errors over the same
/// stretch.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_neighbours_late_reply_is_not_the_healthy_drives_error() {
    let run = async {
        let pair = TwoOnOneLine::regulating().await;
        let url = pair.service.url.clone();
        let errors = |i: usize| link_count(&url, i, "errors");
        let (one_before, two_before) = (errors(0).await, errors(1).await);
        pair.two.lock().faults.reply_delay = Some(Duration::from_millis(130));
        let late = wait_for(Duration::from_secs(60), || async { errors(1).await >= two_before + 8 }).await;
        assert!(late.is_some(), "vfd2's late replies time out: {}", status(&url).await);
        pair.two.lock().faults.reply_delay = None;
        let (one, two) = (errors(0).await - one_before, errors(1).await - two_before);
        eprintln!("vfd2 timed out {two} times; vfd1 counted {one} errors meanwhile");
        let s = status(&url).await;
        // one error of vfd1 for each of vfd2's timeouts before; a machine that stalls this process can make one of
        // vfd1's own replies late now and then (its own error, and seen as such)
        assert!(4 * one <= two, "vfd1 charged {one} errors beside {two} late replies: {}", s["drives"][0]["link"]);
        pair.stop().await;
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("within 120 s");
}

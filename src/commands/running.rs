//! The running subcommands: `sim` (the simulator on Modbus TCP, RTU or RTU over TCP), `serve` and `demo`.

use std::path::Path;

use anyhow::Context;
use hydrolens::modbus::simulator::Simulator;
use hydrolens::plant::PlantModel;
use hydrolens::service::Settings;
use hydrolens::{BadInput, server, service};
use tokio_util::sync::CancellationToken;

use super::{file_size_limit_is_an_error, http_runtime, load_model, runtime, shutdown_on_signal};

/// Where `sim` serves.
pub enum SimTransport {
    Tcp,
    RtuOverTcp,
    Serial { path: String, baud: u32, parity: String, stop_bits: u8 },
}

pub fn sim(model_path: &Path, listen: &str, seed: u64, transport: SimTransport, units: &[u8]) -> anyhow::Result<()> {
    use hydrolens::modbus::line::{Parity, SerialLine};
    let model = load_model(model_path)?;
    if let Some(u) = units.iter().find(|&&u| !(1..=247).contains(&u)) {
        return Err(BadInput(format!("--units: unit id {u} is outside 1 ..= 247")).into());
    }
    let simulator = Simulator::with_units(model, seed, units)
        .map_err(|e| BadInput(format!("model file {}: {e}", model_path.display())))?;
    if let SimTransport::Serial { path, baud, parity, stop_bits } = transport {
        if baud == 0 {
            return Err(BadInput("--baud: must be positive, got 0".into()).into());
        }
        let parity = Parity::parse(&parity)
            .ok_or_else(|| BadInput(format!("--parity {parity:?}: expected none, even or odd")))?;
        if !(1..=2).contains(&stop_bits) {
            return Err(BadInput(format!("--stop-bits {stop_bits}: expected 1 or 2")).into());
        }
        let line = SerialLine { baud_rate: baud, parity, stop_bits };
        return runtime()?.block_on(async move {
            // a device that is not there, or not a serial line, at start is a wrong --serial (it retried for ever);
            // once served, a line that goes away is waited for (an adapter unplugged comes back)
            drop(
                hydrolens::modbus::client::open_serial(&path, &line)
                    .map_err(|e| BadInput(format!("--serial {path}: cannot open it as a serial line: {e}")))?,
            );
            let shutdown = shutdown_on_signal();
            eprintln!("hydrolens sim: plant simulator on modbus rtu {path} ({baud} baud, parity {})", parity.name());
            simulator.run_serial(&path, line, shutdown).await.context("simulator")
        });
    }
    let addr: std::net::SocketAddr = listen
        .parse()
        .map_err(|e| BadInput(format!("--listen {listen:?}: not an address such as 127.0.0.1:5020 ({e})")))?;
    runtime()?.block_on(async move {
        let listener = tokio::net::TcpListener::bind(addr).await.with_context(|| format!("binding {addr}"))?;
        let shutdown = shutdown_on_signal();
        if let SimTransport::RtuOverTcp = transport {
            eprintln!("hydrolens sim: plant simulator on modbus rtu-over-tcp://{}", listener.local_addr()?);
            simulator.run_rtu_over_tcp(listener, shutdown).await.context("simulator")
        } else {
            eprintln!("hydrolens sim: plant simulator on modbus tcp://{}", listener.local_addr()?);
            simulator.run(listener, shutdown).await.context("simulator")
        }
    })
}

fn parse_addr(flag: &str, value: &str) -> anyhow::Result<std::net::SocketAddr> {
    Ok(value.parse().map_err(|e| BadInput(format!("{flag} {value:?}: not an address such as 127.0.0.1:8080 ({e})")))?)
}

pub fn serve(config: &Path, http_override: Option<&str>) -> anyhow::Result<()> {
    let mut settings = service::config::load(config)?;
    if settings.http.token.is_some() {
        warn_if_others_read(config);
    }
    if let Some(h) = http_override {
        settings.http.bind = parse_addr("--http", h)?;
    }
    http_runtime()?.block_on(async move {
        file_size_limit_is_an_error();
        let shutdown = shutdown_on_signal();
        run_service(settings, shutdown, |url, _| eprintln!("hydrolens serve: dashboard on {url}")).await
    })
}

/// Warns when the config, which holds the write token, is readable by its group or by others.
fn warn_if_others_read(config: &Path) {
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        if let Ok(meta) = std::fs::metadata(config)
            && meta.permissions().mode() & 0o077 != 0
        {
            tracing::warn!(
                "config {} holds http.token and is open to its group or others (mode {:o}): chmod 600 it",
                config.display(),
                meta.permissions().mode() & 0o777
            );
        }
    }
}

/// Binds the HTTP listener, starts the service ([`server::start`]), tells `announce` where it is, and serves until
/// `shutdown`; then waits for every loop to close its recording.
async fn run_service(
    settings: Settings,
    shutdown: CancellationToken,
    announce: impl FnOnce(&str, &std::sync::Arc<service::ServiceState>),
) -> anyhow::Result<()> {
    let bind = settings.http.bind;
    let listener = tokio::net::TcpListener::bind(bind).await.with_context(|| format!("binding http {bind}"))?;
    let server = server::start(listener, &settings, shutdown).context("starting the service")?;
    announce(&server.url, &server.state);
    server.wait().await.context("http server")
}

/// A random token for the demo (std's randomly keyed hasher: no extra dependency).
fn demo_token() -> String {
    use std::hash::{BuildHasher, Hasher};
    let mut out = String::new();
    for _ in 0..2 {
        let mut h = std::collections::hash_map::RandomState::new().build_hasher();
        h.write_u128(std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_nanos()));
        out.push_str(&format!("{:016x}", h.finish()));
    }
    out
}

/// The SCHED_FIFO priority of the demo's poll thread and plant simulator, where the kernel allows it.
const DEMO_REALTIME_PRIORITY: u8 = 20;

/// The demo's service config: one drive in speed mode against the embedded simulator.
fn demo_config(
    modbus: std::net::SocketAddr,
    http: std::net::SocketAddr,
    recordings: &Path,
    target: f64,
    token: &str,
) -> String {
    format!(
        r#"[http]
bind = "{http}"
token = "{token}"

[recording]
dir = {recordings:?}

[[drives]]
name = "pump1"
address = "{modbus}"
unit_id = 1
# every plant sample (the simulator runs at 1 kHz)
poll_ms = 1
timeout_ms = 200
# the poll thread ahead of everything else, where the kernel allows it (else a warning and normal priority)
realtime_priority = {DEMO_REALTIME_PRIORITY}

[drives.control]
mode = "speed"
target_omega_rad_s = {target:?}
min_hz = 0.0
max_hz = 50.0
ramp_hz_per_s = 20.0

# the service checks its own data: short so that a newcomer sees checks (and, with a wearing --plant, an alarm)
# within minutes; a plant in service would check every few minutes
[drives.condition]
enabled = true
window_s = 60.0
every_s = 30.0

[drives.condition.limits]
internal_leakage = {{ l_min_per_bar = 0.02 }}
dead_time = {{ ms = 50.0 }}
entrained_air = {{ bulk_modulus_bar = 8000.0 }}
"#,
        recordings = recordings.display().to_string(),
    )
}

/// What the demo's simulator runs and how its target moves.
pub struct DemoPlant<'a> {
    pub target: f64,
    pub hold: bool,
    pub plant: Option<&'a Path>,
    pub seed: u64,
}

/// Moves the drive's target through the demo program ([`service::program`]) every 100 ms until `stop`, or until
/// a target is posted through the API (the program then leaves the target to the user).
async fn run_demo_program(drive: std::sync::Arc<service::DriveState>, base: f64, stop: CancellationToken) {
    let start = tokio::time::Instant::now();
    let mut tick = tokio::time::interval(std::time::Duration::from_millis(100));
    let mut last: Option<f64> = None;
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            () = stop.cancelled() => break,
        }
        if last.is_some_and(|v| v != drive.snapshot().target_omega_rad_s) {
            tracing::info!("a target was set through the API: the demo's target program stops");
            break;
        }
        let t = start.elapsed().as_secs_f64();
        let target = service::program::demo_target_rad_s(t, base, drive.max_target_omega_rad_s);
        drive.set_target(target);
        last = Some(target);
    }
}

pub fn demo(http_addr: &str, modbus_addr: &str, recordings: &Path, plant: DemoPlant<'_>) -> anyhow::Result<()> {
    let DemoPlant { target, hold, plant: plant_path, seed } = plant;
    let http_addr = parse_addr("--http", http_addr)?;
    let modbus_addr = parse_addr("--modbus", modbus_addr)?;
    let overlap = |a: std::net::IpAddr, b: std::net::IpAddr| a == b || a.is_unspecified() || b.is_unspecified();
    if http_addr.port() != 0 && http_addr.port() == modbus_addr.port() && overlap(http_addr.ip(), modbus_addr.ip()) {
        return Err(BadInput(format!(
            "--http {http_addr} and --modbus {modbus_addr}: one port for both; give each its own"
        ))
        .into());
    }
    if !(target.is_finite() && (0.0..=75.0).contains(&target)) {
        return Err(BadInput(format!("--target {target}: expected rad/s in 0 ..= 75")).into());
    }
    let (model, plant_name) = match plant_path {
        Some(p) => (load_model(p)?, p.display().to_string()),
        None => (PlantModel::reference(), "reference plant".to_string()),
    };
    let simulator = Simulator::new(model, seed).map_err(|e| match plant_path {
        Some(p) => anyhow::Error::new(BadInput(format!("model file {}: {e}", p.display()))),
        None => anyhow::anyhow!("the reference plant: {e}"),
    })?;
    let modbus_listener =
        std::net::TcpListener::bind(modbus_addr).with_context(|| format!("binding modbus {modbus_addr}"))?;
    let modbus_addr = modbus_listener.local_addr()?;
    modbus_listener.set_nonblocking(true)?;
    let shutdown = CancellationToken::new();
    // the plant on a thread and runtime of its own, as a PLC would be: the dashboard's load cannot slow it. It
    // stops after the service, which tells the drive to stop on its way out
    let plant_token = CancellationToken::new();
    let plant_stop = plant_token.clone();
    let plant = std::thread::Builder::new().name("plant-sim".into()).spawn(move || -> anyhow::Result<()> {
        // as the poll thread: a PLC answers in its own time, whatever the dashboard does
        service::timing::use_realtime_priority(DEMO_REALTIME_PRIORITY, "plant-sim");
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
        rt.block_on(async move {
            let listener = tokio::net::TcpListener::from_std(modbus_listener)?;
            simulator.run(listener, plant_stop).await
        })
        .context("simulator")
    })?;
    // the plant stops however the service ends: a bad config returns from the block below before its own cancel,
    // and the join would then wait for ever
    let stop_plant = plant_token;
    let result = http_runtime()?.block_on(async move {
        file_size_limit_is_an_error();
        let signalled = shutdown_on_signal();
        let stop = shutdown.clone();
        tokio::spawn(async move {
            signalled.cancelled().await;
            stop.cancel();
        });
        let token = demo_token();
        let text = demo_config(modbus_addr, http_addr, recordings, target, &token);
        let settings = service::config::parse(&text, "demo config", None)?;
        let program_stop = shutdown.clone();
        let result = run_service(settings, shutdown.clone(), |url, state| {
            eprintln!("hydrolens demo: plant simulator on modbus tcp://{modbus_addr} ({plant_name}, brake-load steps)");
            if hold {
                eprintln!("hydrolens demo: speed mode, target {target} rad/s, recordings in {}", recordings.display());
            } else {
                eprintln!(
                    "hydrolens demo: speed mode, target program around {target} rad/s (0.3 to 1.3 times, every \
                     {} s), recordings in {}",
                    service::program::CYCLE_S,
                    recordings.display()
                );
                if let Some(drive) = state.drives.first() {
                    tokio::spawn(run_demo_program(drive.clone(), target, program_stop));
                }
            }
            eprintln!("hydrolens demo: write token (for POST /api/drives/pump1/target): {token}");
            println!("dashboard: {url}/");
        })
        .await;
        shutdown.cancel();
        result
    });
    stop_plant.cancel();
    match plant.join() {
        Ok(r) => r?,
        Err(_) => tracing::error!("the simulator thread panicked"),
    }
    result
}

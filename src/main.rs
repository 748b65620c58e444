//! The `hydrolens` command line: parses arguments and wires the rooms together. Exit 0 ok, 2 bad input, 1 other.

use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::Context;
use clap::{Parser, Subcommand};
use hydrolens::modbus::simulator::Simulator;
use hydrolens::plant::PlantModel;
use hydrolens::service::Settings;
use hydrolens::{BadInput, output, plant, recording, replay_file, server, service};
use tokio_util::sync::CancellationToken;

#[derive(Parser)]
#[command(name = "hydrolens", version, about = "Watch, estimate, regulate and explain an electro-hydraulic drive")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// The plant simulator as a Modbus TCP server (or RTU on a serial device, or RTU over TCP), in real time.
    Sim {
        #[arg(long, default_value = "config/plant.toml")]
        model: PathBuf,
        #[arg(long, default_value = "127.0.0.1:5020")]
        listen: String,
        /// Seed of the sensor noise.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Serve Modbus RTU on this serial device instead of TCP (e.g. one end of a `socat` pty pair).
        #[arg(long, conflicts_with = "rtu_over_tcp")]
        serial: Option<String>,
        /// The serial line's baud rate (with --serial).
        #[arg(long, default_value_t = 19200, requires = "serial")]
        baud: u32,
        /// The serial line's parity: none, even or odd (with --serial).
        #[arg(long, default_value = "even", requires = "serial")]
        parity: String,
        /// The serial line's stop bits: 1 or 2 (with --serial).
        #[arg(long, default_value_t = 1, requires = "serial")]
        stop_bits: u8,
        /// Serve RTU framing over TCP on --listen (what a serial gateway passes through) instead of Modbus TCP.
        #[arg(long)]
        rtu_over_tcp: bool,
        /// One plant per unit id, e.g. `--units 1,2` (several drives on one line); the others get no answer.
        /// Default: one plant answering every unit id.
        #[arg(long, value_delimiter = ',')]
        units: Vec<u8>,
    },
    /// Offline test-stand run (setpoint steps and ramps, brake-load steps) written as a recording CSV.
    Simulate {
        #[arg(long)]
        model: PathBuf,
        /// Length of the run in seconds.
        #[arg(long)]
        duration: f64,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        #[arg(long)]
        out: PathBuf,
    },
    /// Offline replay of a recording through the estimator: speed, load torque, J and B per row.
    Estimate {
        /// The recording CSV.
        recording: PathBuf,
        /// Nominal plant model: displacement, initial J and B, optional `[estimator]` settings.
        #[arg(long)]
        model: PathBuf,
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        flags: EstimateFlags,
    },
    /// Find where the model and a recording disagree, name the missing physics, fit it, show the gain.
    Analyze {
        /// The recording CSV; several files of one drive (rotated) are joined in time order; a recordings
        /// directory with `--drive NAME` takes that drive's files of the last service run.
        #[arg(required = true, num_args = 1..)]
        recording: Vec<PathBuf>,
        /// With a recordings directory: the drive whose files to analyse.
        #[arg(long)]
        drive: Option<String>,
        /// The nominal plant model.
        #[arg(long)]
        model: PathBuf,
        /// Where to write the analysis JSON.
        #[arg(long)]
        json: PathBuf,
        /// A self-contained HTML report with SVG plots.
        #[arg(long)]
        report: Option<PathBuf>,
        /// The improved model, as a plant TOML that `sim` and `simulate` accept.
        #[arg(long)]
        model_out: Option<PathBuf>,
    },
    /// The monitoring service against a real PLC / drive (or a simulator): poll, estimate, regulate, record, serve.
    Serve {
        #[arg(long, default_value = "config/hydrolens.toml")]
        config: PathBuf,
        /// Overrides `http.bind` of the config.
        #[arg(long)]
        http: Option<String>,
    },
    /// The main job: the plant simulator and the service (speed mode) in one process, with the dashboard.
    Demo {
        /// Where the dashboard and API listen.
        #[arg(long, default_value = "127.0.0.1:8080")]
        http: String,
        /// Where the simulator serves Modbus TCP (port 0: any free port).
        #[arg(long, default_value = "127.0.0.1:0")]
        modbus: String,
        /// Where recordings go.
        #[arg(long, default_value = "recordings")]
        recordings: PathBuf,
        /// Speed target (rad/s): the base of the target program (0.3 to 1.3 times it, repeating every 30 s).
        #[arg(long, default_value_t = 40.0)]
        target: f64,
        /// Hold the target fixed instead of running the program.
        #[arg(long)]
        hold: bool,
        /// The plant model the simulator runs (default: the reference plant); the service keeps its nominal
        /// model (the reference plant, as in config/plant.toml), so an effect hidden here is what `analyze` of
        /// the demo's recording against config/plant.toml should find, and what the demo's condition checks
        /// (every 30 s on the last 60 s) name: config/plant_wearing.toml raises a leakage alarm within minutes.
        #[arg(long)]
        plant: Option<PathBuf>,
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
}

/// Estimator settings on the command line; each overrides the model file's `[estimator]` table.
#[derive(clap::Args)]
struct EstimateFlags {
    /// rls-sgd | kalman | paper-literal.
    #[arg(long)]
    method: Option<hydrolens::estimator::Method>,
    /// RLS forgetting factor λ (paper: 0.99).
    #[arg(long)]
    lambda: Option<f64>,
    /// SGD learning rate η (paper: 0.05).
    #[arg(long)]
    eta: Option<f64>,
    /// Initial RLS covariance (normalised parameters).
    #[arg(long)]
    initial_covariance: Option<f64>,
    /// σ of the speed measurement (rad/s).
    #[arg(long)]
    speed_noise: Option<f64>,
    /// Kalman: random-walk intensity of the load (N·m/√s).
    #[arg(long)]
    load_rate: Option<f64>,
}

fn main() -> ExitCode {
    // colour only for a person at a terminal who has not asked for none (https://no-color.org)
    let colour = std::io::stderr().is_terminal() && std::env::var_os("NO_COLOR").is_none_or(|v| v.is_empty());
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .with_ansi(colour)
        .init();
    stop_on_panic();
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("error: {err:#}");
            if hydrolens::is_bad_input(err.as_ref()) { ExitCode::from(2) } else { ExitCode::from(1) }
        }
    }
}

/// A panic in any thread stops the process (exit by SIGABRT) rather than leave it half alive: the release profile
/// aborts on panic, and this hook makes the debug build (and the tests against it) do the same.
fn stop_on_panic() {
    let report = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        report(info);
        eprintln!("error: a thread of hydrolens panicked (a bug; please report it): the process stops");
        std::process::abort();
    }));
    // fault injection for the tests of this hook, in debug builds only
    #[cfg(debug_assertions)]
    if let Some(ms) = std::env::var("HYDROLENS_DEBUG_PANIC_AFTER_MS").ok().and_then(|v| v.parse::<u64>().ok()) {
        let _ = std::thread::Builder::new().name("debug-panic".into()).spawn(move || {
            std::thread::sleep(std::time::Duration::from_millis(ms));
            panic!("HYDROLENS_DEBUG_PANIC_AFTER_MS: a panic injected after {ms} ms");
        });
    }
}

fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Sim { model, listen, seed, serial, baud, parity, stop_bits, rtu_over_tcp, units } => {
            let transport = match serial {
                Some(path) => SimTransport::Serial { path, baud, parity, stop_bits },
                None if rtu_over_tcp => SimTransport::RtuOverTcp,
                None => SimTransport::Tcp,
            };
            sim(&model, &listen, seed, transport, &units)
        }
        Command::Simulate { model, duration, seed, out } => simulate(&model, duration, seed, &out),
        Command::Estimate { recording, model, out, flags } => estimate(&recording, &model, &out, &flags),
        Command::Analyze { recording, drive, model, json, report, model_out } => {
            analyze(&recording, drive.as_deref(), &model, &json, report.as_deref(), model_out.as_deref())
        }
        Command::Serve { config, http } => serve(&config, http.as_deref()),
        Command::Demo { http, modbus, recordings, target, hold, plant, seed } => {
            demo(&http, &modbus, &recordings, DemoPlant { target, hold, plant: plant.as_deref(), seed })
        }
    }
}

fn runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread().enable_all().build().context("starting the async runtime")
}

/// The runtime of `serve` and `demo`, which carries the HTTP side. Its workers run at a lower priority than the
/// poll threads (each on a thread and runtime of its own, started from the main thread), so that HTTP load cannot
/// delay the loops.
fn http_runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("http")
        .on_thread_start(service::timing::lower_thread_priority)
        .build()
        .context("starting the async runtime")
}

/// A file-size limit (`ulimit -f`) fails a write past it with EFBIG and sends SIGXFSZ, whose default kills the
/// process: handled for the process's lifetime, the limit is an error the recorder reports and survives, as it does
/// a full disk. Called inside the runtime, before any file is written.
fn file_size_limit_is_an_error() {
    #[cfg(target_os = "linux")]
    {
        use tokio::signal::unix::{SignalKind, signal};
        match signal(SignalKind::from_raw(rustix::process::Signal::XFSZ.as_raw())) {
            Ok(mut xfsz) => {
                tokio::spawn(async move { while xfsz.recv().await.is_some() {} });
            }
            Err(e) => tracing::warn!(error = %e, "cannot handle SIGXFSZ: a file-size limit would stop the process"),
        }
    }
}

/// A token cancelled on Ctrl-C or SIGTERM.
fn shutdown_on_signal() -> CancellationToken {
    let token = CancellationToken::new();
    let t = token.clone();
    // The handlers are registered here, before the caller announces itself, so that a SIGTERM sent right after the
    // announcement is caught (registered inside the task, it could arrive first and kill the process).
    #[cfg(unix)]
    let handlers = {
        use tokio::signal::unix::{SignalKind, signal};
        signal(SignalKind::terminate()).and_then(|term| Ok((term, signal(SignalKind::interrupt())?)))
    };
    tokio::spawn(async move {
        #[cfg(unix)]
        match handlers {
            Ok((mut term, mut int)) => {
                tokio::select! {
                    _ = term.recv() => {}
                    _ = int.recv() => {}
                }
            }
            Err(e) => {
                tracing::warn!(error = %e, "cannot listen for SIGTERM");
                let _ = tokio::signal::ctrl_c().await;
            }
        }
        #[cfg(not(unix))]
        let _ = tokio::signal::ctrl_c().await;
        tracing::info!("shutting down");
        t.cancel();
        // whatever holds the shutdown up, the process ends: after a grace period, on a thread of its own
        let _ = std::thread::Builder::new().name("shutdown-deadline".into()).spawn(|| {
            std::thread::sleep(SHUTDOWN_GRACE);
            eprintln!("error: not stopped {} s after the signal: exiting", SHUTDOWN_GRACE.as_secs());
            std::process::exit(1);
        });
    });
    token
}

/// How long a signalled shutdown may take (the loops close their recordings) before the process exits anyway.
const SHUTDOWN_GRACE: std::time::Duration = std::time::Duration::from_secs(15);

fn load_model(path: &Path) -> anyhow::Result<PlantModel> {
    Ok(PlantModel::load(path)?)
}

/// Where `sim` serves.
enum SimTransport {
    Tcp,
    RtuOverTcp,
    Serial { path: String, baud: u32, parity: String, stop_bits: u8 },
}

fn sim(model_path: &Path, listen: &str, seed: u64, transport: SimTransport, units: &[u8]) -> anyhow::Result<()> {
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

/// Progress on a terminal, nothing when piped.
fn progress(label: &'static str) -> impl FnMut(f64) {
    let tty = std::io::stderr().is_terminal();
    let mut last = -1i64;
    move |fraction: f64| {
        let pct = (fraction * 100.0).floor() as i64;
        if tty && pct != last {
            last = pct;
            eprint!("\r{label}: {pct:3}%");
            if pct >= 100 {
                eprintln!();
            }
        }
    }
}

/// The most rows `simulate` writes (`--duration` over the model's `sensors.sample_ms`): about 10 GB of CSV.
const MAX_SIMULATE_ROWS: f64 = 1e8;

fn simulate(model_path: &Path, duration: f64, seed: u64, out: &Path) -> anyhow::Result<()> {
    if !(duration.is_finite() && duration > 0.0 && duration <= 1e6) {
        return Err(BadInput(format!("--duration {duration}: expected seconds, > 0 and ≤ 1e6")).into());
    }
    output::check(&[model_path], &[("--out", out)])?;
    let model = load_model(model_path)?;
    let rows = duration / model.sample_s();
    if rows > MAX_SIMULATE_ROWS {
        return Err(BadInput(format!(
            "--duration {duration}: at sensors.sample_ms = {} (model file {}) that is {rows:.3e} rows, more than \
             {MAX_SIMULATE_ROWS:e}; simulate less or sample slower",
            model.sensors.sample_ms,
            model_path.display()
        ))
        .into());
    }
    let mut file = output::Replacement::create(out).with_context(|| format!("creating {}", out.display()))?;
    let mut writer =
        recording::RowWriter::new(std::io::BufWriter::with_capacity(1 << 16, file.file()), &plant::simulate::COLUMNS)
            .with_context(|| format!("writing {}", out.display()))?;
    let load = model.load.clone();
    let inputs = plant::simulate::Inputs {
        setpoint_hz: &plant::excitation::setpoint_hz,
        load_nm: &move |t, w, a| load.torque_at(t, w, a),
    };
    let mut sink = |row: &[f64; plant::simulate::COLUMNS.len()]| writer.write_row(row.iter().copied());
    let rows = plant::simulate::run_into(&model, duration, seed, &inputs, &mut progress("simulate"), &mut sink)
        .map_err(|e| match e {
            plant::simulate::RunError::Model(e) => {
                anyhow::Error::new(BadInput(format!("model file {}: {e}", model_path.display())))
            }
            plant::simulate::RunError::Sink(e) => anyhow::Error::new(e).context(format!("writing {}", out.display())),
        })?;
    writer.flush().with_context(|| format!("writing {}", out.display()))?;
    drop(writer);
    file.commit().with_context(|| format!("writing {}", out.display()))?;
    eprintln!("simulate: {rows} samples written to {}", out.display());
    Ok(())
}

fn estimate(rec_path: &Path, model_path: &Path, out: &Path, flags: &EstimateFlags) -> anyhow::Result<()> {
    use hydrolens::estimator::{self, EstimatorSettings};
    output::check(&[rec_path, model_path], &[("--out", out)])?;
    let model = load_model(model_path)?;
    let origin = model_path.display().to_string();
    let mut settings = EstimatorSettings::from_model(&model, &origin)?;
    let f = flags;
    settings.method = f.method.unwrap_or(settings.method);
    settings.lambda = f.lambda.unwrap_or(settings.lambda);
    settings.eta = f.eta.unwrap_or(settings.eta);
    settings.initial_covariance = f.initial_covariance.unwrap_or(settings.initial_covariance);
    settings.speed_noise_rad_s = f.speed_noise.or(settings.speed_noise_rad_s);
    settings.load_rate_nm_per_s = f.load_rate.unwrap_or(settings.load_rate_nm_per_s);
    let est = estimator::try_build(&settings, &model).map_err(|hydrolens::error::KeyError { key, message: msg }| {
        BadInput(format!("{key} (command line or model file {origin}) {msg}"))
    })?;
    let rows = replay_file::estimate_file(rec_path, &model, &origin, est.as_ref(), out)?;
    eprintln!("estimate ({}): {rows} rows written to {}", settings.method, out.display());
    Ok(())
}

/// The recording files `analyze` reads: one file, several files of one drive joined in time order, or a directory's
/// files of `--drive` (the last service run; earlier runs are named on stderr and left out).
fn analysis_files(paths: &[PathBuf], drive: Option<&str>) -> anyhow::Result<Vec<PathBuf>> {
    Ok(match (paths, drive) {
        ([dir], Some(drive)) if dir.is_dir() => recording::drive_files(dir, drive)?,
        ([dir], None) if dir.is_dir() => {
            return Err(BadInput(format!(
                "{} is a directory: name the drive whose recordings to analyse with --drive NAME",
                dir.display()
            ))
            .into());
        }
        (_, Some(_)) => {
            return Err(BadInput("--drive goes with a single recordings directory, not with files".into()).into());
        }
        (files, None) => files.to_vec(),
    })
}

/// The files of [`analysis_files`] read and joined.
fn analysis_recording(files: &[PathBuf], drive: Option<&str>) -> anyhow::Result<recording::Recording> {
    let columns = hydrolens::analysis::RECORDING_COLUMNS;
    let parts = files.iter().map(|p| recording::load_columns(p, &columns)).collect::<Result<Vec<_>, _>>()?;
    let parts = if drive.is_some() {
        let (run, left_out) = recording::last_run(parts);
        if left_out > 0 {
            eprintln!(
                "analyze: {left_out} older file(s) of earlier service runs left out (t_s restarts with each run); \
                 pass files to analyse them"
            );
        }
        run
    } else {
        parts
    };
    if parts.len() > 1 {
        eprintln!("analyze: {} files joined in time order", parts.len());
    }
    Ok(recording::join(parts)?)
}

fn analyze(
    rec_paths: &[PathBuf],
    drive: Option<&str>,
    model_path: &Path,
    json: &Path,
    report: Option<&Path>,
    model_out: Option<&Path>,
) -> anyhow::Result<()> {
    use hydrolens::analysis;
    let files = analysis_files(rec_paths, drive)?;
    let mut inputs: Vec<&Path> = files.iter().map(PathBuf::as_path).collect();
    inputs.push(model_path);
    let mut outputs = vec![("--json", json)];
    outputs.extend(report.map(|p| ("--report", p)));
    outputs.extend(model_out.map(|p| ("--model-out", p)));
    output::check(&inputs, &outputs)?;
    let model = load_model(model_path)?;
    // every output is opened before the analysis runs, and replaces its file only once all are written
    let create = |p: &Path| output::Replacement::create(p).with_context(|| format!("creating {}", p.display()));
    let mut json_file = create(json)?;
    let mut model_file = model_out.map(create).transpose()?;
    let mut report_file = report.map(create).transpose()?;
    let rec = analysis_recording(&files, drive)?;
    let source = rec.source.clone();
    let result = analysis::analyze_owned(rec, &model, &analysis::Options::default(), &mut progress("analyze"))?;
    if result.load == "unknown" && model.load == plant::LoadSpec::Recorded {
        eprintln!(
            "analyze: note: {} has no `load_nm` although the model's [load] kind is \"recorded\": analysed with the \
             load unknown (the flow balance only: leakage, slip, entrained air, dead time); friction, torque offset, \
             J and B are not determined (see `ambiguities` and `not_identified`). `kind = \"unknown\"` says so \
             without this note",
            source
        );
    }
    let text = serde_json::to_string_pretty(&result).context("serialising the analysis")?;
    let write = |file: &mut output::Replacement, path: &Path, text: &str| {
        file.file().write_all(text.as_bytes()).with_context(|| format!("writing {}", path.display()))
    };
    write(&mut json_file, json, &(text + "\n"))?;
    if let (Some(file), Some(path)) = (model_file.as_mut(), model_out) {
        let header = format!("# Fitted by `hydrolens analyze {}` from {}\n", source, model_path.display());
        write(file, path, &(header + &result.improved_model.to_toml()))?;
    }
    if let (Some(file), Some(path)) = (report_file.as_mut(), report) {
        write(file, path, &analysis::report::html(&result))?;
    }
    let commit =
        |file: output::Replacement, path: &Path| file.commit().with_context(|| format!("writing {}", path.display()));
    commit(json_file, json)?;
    if let (Some(file), Some(path)) = (model_file, model_out) {
        commit(file, path)?;
    }
    if let (Some(file), Some(path)) = (report_file, report) {
        commit(file, path)?;
    }
    let named: Vec<&str> = result.findings.iter().map(|f| f.effect.as_str()).collect();
    eprintln!(
        "analyze: {} samples; validation from {:.1} s; named: {}",
        result.samples,
        result.validation_from_s,
        if named.is_empty() { "nothing".to_string() } else { named.join(", ") }
    );
    Ok(())
}

fn parse_addr(flag: &str, value: &str) -> anyhow::Result<std::net::SocketAddr> {
    Ok(value.parse().map_err(|e| BadInput(format!("{flag} {value:?}: not an address such as 127.0.0.1:8080 ({e})")))?)
}

fn serve(config: &Path, http_override: Option<&str>) -> anyhow::Result<()> {
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
struct DemoPlant<'a> {
    target: f64,
    hold: bool,
    plant: Option<&'a Path>,
    seed: u64,
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

fn demo(http_addr: &str, modbus_addr: &str, recordings: &Path, plant: DemoPlant<'_>) -> anyhow::Result<()> {
    let DemoPlant { target, hold, plant: plant_path, seed } = plant;
    let http_addr = parse_addr("--http", http_addr)?;
    let modbus_addr = parse_addr("--modbus", modbus_addr)?;
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
    // the plant on a thread and runtime of its own, as a PLC would be: the dashboard's load cannot slow it
    let plant_stop = shutdown.clone();
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
    match plant.join() {
        Ok(r) => r?,
        Err(_) => tracing::error!("the simulator thread panicked"),
    }
    result
}

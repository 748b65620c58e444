//! The `hydrolens` command line: parses the arguments and dispatches to the subcommands (`commands`). Exit 0 ok,
//! 2 bad input, 1 other.

use std::io::{IsTerminal, Write};
use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

mod commands;

use commands::{DemoPlant, SimTransport, analyze, demo, estimate, serve, sim, simulate};
use hydrolens::output::dash_is_stdout;

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
        /// The recording CSV to write (`-`: the standard output).
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
        /// The estimates CSV to write (`-`: the standard output).
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
        /// Where to write the analysis JSON (`-`: the standard output).
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

/// The log's default filter (`RUST_LOG` replaces it). tokio-modbus logs every frame it cannot decode, with its
/// bytes, at WARN and ERROR: noise on an RTU line gave 730 lines a second, past the service's own once-per-10-s
/// warnings of the same faults (`errors_total{kind}`, `last_error`).
const DEFAULT_LOG: &str = "info,tokio_modbus=off";

fn main() -> ExitCode {
    // colour only for a person at a terminal who has not asked for none (https://no-color.org)
    let colour = std::io::stderr().is_terminal() && std::env::var_os("NO_COLOR").is_none_or(|v| v.is_empty());
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(DEFAULT_LOG)),
        )
        .with_writer(std::io::stderr)
        .with_ansi(colour)
        // a log line that cannot be written (stderr's reader went away: a `| head`, a log shipper restarted) is
        // lost, not reported with eprintln!, whose panic on the closed pipe ended the process without a clean stop
        .log_internal_errors(false)
        .init();
    stop_on_panic();
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            let _ = writeln!(std::io::stderr(), "error: {err:#}");
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
        Command::Simulate { model, duration, seed, out } => simulate(&model, duration, seed, &dash_is_stdout(out)),
        Command::Estimate { recording, model, out, flags } => {
            estimate(&recording, &model, &dash_is_stdout(out), &flags)
        }
        Command::Analyze { recording, drive, model, json, report, model_out } => {
            let (report, model_out) = (report.map(dash_is_stdout), model_out.map(dash_is_stdout));
            analyze(
                &recording,
                drive.as_deref(),
                &model,
                &dash_is_stdout(json),
                report.as_deref(),
                model_out.as_deref(),
            )
        }
        Command::Serve { config, http } => serve(&config, http.as_deref()),
        Command::Demo { http, modbus, recordings, target, hold, plant, seed } => {
            demo(&http, &modbus, &recordings, DemoPlant { target, hold, plant: plant.as_deref(), seed })
        }
    }
}

//! The files' subcommands: `simulate` (a model run to a recording), `estimate` (an estimator over a recording) and
//! `analyze` (a recording explained against a model).

use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};

use anyhow::Context;
use hydrolens::{BadInput, output, plant, recording, replay_file};

use super::{load_model, remove_temporaries_on_signal};
use crate::EstimateFlags;

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

/// An output's [`output::Replacement`]; a path it cannot be created at is bad input ([`output::path_refused`]).
fn create_output(path: &Path) -> anyhow::Result<output::Replacement> {
    output::Replacement::create(path).map_err(|e| {
        if output::path_refused(&e) {
            BadInput(format!("creating {}: {e}", path.display())).into()
        } else {
            anyhow::Error::new(e).context(format!("creating {}", path.display()))
        }
    })
}

/// The most rows `simulate` writes (`--duration` over the model's `sensors.sample_ms`): about 10 GB of CSV.
const MAX_SIMULATE_ROWS: f64 = 1e8;
/// A `simulate` row's size on disk, about: 140–150 bytes measured on the reference plant, rounded up.
const SIMULATE_BYTES_PER_ROW: f64 = 160.0;

pub fn simulate(model_path: &Path, duration: f64, seed: u64, out: &Path) -> anyhow::Result<()> {
    remove_temporaries_on_signal();
    if !(duration.is_finite() && duration > 0.0 && duration <= 1e6) {
        let duration = hydrolens::units::shown(duration);
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
    if let Some(free) = output::free_bytes(out) {
        let need = rows * SIMULATE_BYTES_PER_ROW;
        if need > free as f64 {
            let size = |b: f64| if b >= 1e9 { format!("{:.1} GB", b / 1e9) } else { format!("{:.1} MB", b / 1e6) };
            return Err(BadInput(format!(
                "--duration {duration}: {rows:.0} rows take about {}, and {} has room for {} (its disk's free \
                 space, or the file-size limit); simulate less or sample slower",
                size(need),
                out.display(),
                size(free as f64)
            ))
            .into());
        }
    }
    let mut file = create_output(out)?;
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
            e @ (plant::simulate::RunError::Model(_) | plant::simulate::RunError::Diverged(..)) => {
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

pub fn estimate(rec_path: &Path, model_path: &Path, out: &Path, flags: &EstimateFlags) -> anyhow::Result<()> {
    use hydrolens::estimator::{self, EstimatorSettings};
    remove_temporaries_on_signal();
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
    if settings.speed_noise_rad_s.is_none() && model.sensors.speed_noise_rad_s <= 0.0 {
        // the observer's gain and every window's weight come from it: a reviewer's torque-only model (no [sensors])
        // ran on 0.1 rad/s against a tachometer of 0.8, T̂_L 17× worse, without a word
        eprintln!(
            "estimate: the model file {origin} gives no speed noise ([sensors] speed_noise_rad_s): assuming {} rad/s; \
             set it, or pass --speed-noise, for the recording's tachometer",
            estimator::DEFAULT_SPEED_NOISE_RAD_S
        );
    }
    let max_gap_s = settings.resolve(&model).map(|r| r.max_gap_s).unwrap_or(f64::INFINITY);
    let done = replay_file::estimate_file(rec_path, &model, &origin, est.as_ref(), out, Some(max_gap_s))?;
    eprintln!("estimate ({}): {} rows written to {}{}", settings.method, done.rows, out.display(), done.filled());
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
    // the last run is found from the files' time spans before any is read whole: older runs cost no memory
    let files = if drive.is_some() {
        let (run, left_out) = recording::last_run(files);
        if left_out > 0 {
            eprintln!(
                "analyze: {left_out} older file(s) of earlier service runs left out (t_s restarts with each run); \
                 pass files to analyse them"
            );
        }
        run
    } else {
        files.to_vec()
    };
    // the rows are counted as they are read, never past the analysis's cap (its memory grows with them)
    let mut left = hydrolens::analysis::MAX_ROWS;
    let mut parts = Vec::with_capacity(files.len());
    for p in &files {
        let part = recording::load_columns(p, &columns, left)?;
        left -= part.len();
        parts.push(part);
    }
    if parts.len() > 1 {
        eprintln!("analyze: {} files joined in time order", parts.len());
    }
    Ok(recording::join(parts)?)
}

pub fn analyze(
    rec_paths: &[PathBuf],
    drive: Option<&str>,
    model_path: &Path,
    json: &Path,
    report: Option<&Path>,
    model_out: Option<&Path>,
) -> anyhow::Result<()> {
    use hydrolens::analysis;
    remove_temporaries_on_signal();
    let files = analysis_files(rec_paths, drive)?;
    let mut inputs: Vec<&Path> = files.iter().map(PathBuf::as_path).collect();
    inputs.push(model_path);
    let mut outputs = vec![("--json", json)];
    outputs.extend(report.map(|p| ("--report", p)));
    outputs.extend(model_out.map(|p| ("--model-out", p)));
    output::check(&inputs, &outputs)?;
    let model = load_model(model_path)?;
    // every output is opened before the analysis runs, and replaces its file only once all are written
    let create = create_output;
    let mut json_file = create(json)?;
    let mut model_file = model_out.map(create).transpose()?;
    let mut report_file = report.map(create).transpose()?;
    let rec = analysis_recording(&files, drive)?;
    let source = rec.source.clone();
    let result = analysis::analyze_owned(rec, &model, &analysis::Options::default(), &mut progress("analyze"))
        // the analysis says `model: …` of what the model lacks for this recording; the user needs its path
        .map_err(|BadInput(m)| match m.strip_prefix("model: ") {
            Some(rest) => BadInput(format!("model file {}: {rest}", model_path.display())),
            None => BadInput(m),
        })?;
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
    if let Some(m) = &result.model_misfit {
        eprintln!("analyze: warning: {}", m.explanation);
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

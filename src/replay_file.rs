//! `hydrolens estimate` as a library: a recording file streamed through an estimator into an estimates CSV, in
//! flat memory, on two threads: one reads, parses and writes the file, the other estimates and formats.
//!
//! The output is byte for byte what replaying the whole [`crate::recording::load`]ed recording and writing every
//! row with [`crate::recording::RowWriter`] gives, and the errors are the ones that path reports, in its order:
//! the recording's (first bad line), then the replay's (no torque or speed column, no displacement), then the
//! output file's. The estimates are written under a temporary name beside the output (`.NAME.PID.tmp`) and renamed
//! to it when everything is done, so on any error the output path is left as it was and the temporary file is
//! removed. A path that is not a regular file, such as `/dev/null`, is written directly.
//!
//! The replay takes `torque_nm` only if it holds a value somewhere, else the pressures (and `omega_rad_s` before
//! `theta_rad` likewise). When both are in the header, the file is first read until the column shows a value,
//! which is the first row as a rule; a column that is empty all the way costs a second pass over the file.

use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::mpsc;

use crate::estimator::{Estimator, Plan, ReplayError, Replayer};
use crate::plant::PlantModel;
use crate::recording::{Batch, RecordingError, StreamReader, push_value};

/// The columns of an estimates file.
pub const COLUMNS: [&str; 5] = ["t_s", "omega_hat_rad_s", "load_hat_nm", "inertia_hat_kg_m2", "viscous_hat_nm_s_rad"];

/// Rows per batch handed from the reading thread to the estimating one, and batches under way at once: enough to
/// keep both threads busy, little enough to stay in cache (4 k rows × 4 columns × 8 bytes = 128 KiB a batch).
const BATCH_ROWS: usize = 4096;
const BATCHES_IN_FLIGHT: usize = 4;
/// Output text handed back to the reading thread to write, in pieces of about this size.
const TEXT_BYTES: usize = 1 << 18;

/// Why an estimates file was not written.
#[derive(Debug, thiserror::Error)]
pub enum EstimateError {
    /// Bad recording (or one that cannot be read).
    #[error(transparent)]
    Recording(RecordingError),
    /// A recording without the columns the replay needs, or a model without the displacement: bad input.
    #[error(transparent)]
    Replay(ReplayError),
    #[error("{action} {path}: {source}")]
    Output { action: &'static str, path: String, source: std::io::Error },
}

/// Replays the recording at `recording` through `estimator` into an estimates CSV at `out` ([`COLUMNS`], one row
/// per recorded row); `model_origin` names the model in messages. Returns the number of rows.
pub fn estimate_file(
    recording: &Path,
    model: &PlantModel,
    model_origin: &str,
    estimator: &mut dyn Estimator,
    out: &Path,
) -> Result<u64, EstimateError> {
    let mut reader = StreamReader::open(recording).map_err(EstimateError::Recording)?;
    let plan = Plan::choose(reader.names(), |columns| holds_values(recording, columns));
    let selected: Vec<usize> = plan.columns().iter().filter_map(|c| reader.index_of(c)).collect();
    reader.select(&selected);
    let name = recording.display().to_string();
    let mut replayer = Replayer::new(plan, model, model_origin, &name, estimator);
    // an output error waits until the recording and the replay are known to be good
    let output = Output::create(out);

    let (recording_error, output) = std::thread::scope(|s| {
        let (batch_tx, batch_rx) = mpsc::sync_channel::<Result<Batch, RecordingError>>(BATCHES_IN_FLIGHT);
        let (spare_batch_tx, spare_batch_rx) = mpsc::channel::<Batch>();
        // unbounded, but never long: the reading thread empties it before each batch it reads
        let (text_tx, text_rx) = mpsc::channel::<Vec<u8>>();
        let (spare_text_tx, spare_text_rx) = mpsc::channel::<Vec<u8>>();
        let io = s.spawn(move || {
            let mut output = output;
            let write = |mut text: Vec<u8>, output: &mut Result<Output, EstimateError>| {
                if let Ok(o) = output {
                    o.write(&text);
                }
                text.clear();
                let _ = spare_text_tx.send(text);
            };
            loop {
                while let Ok(text) = text_rx.try_recv() {
                    write(text, &mut output);
                }
                let mut batch = spare_batch_rx.try_recv().unwrap_or_default();
                match reader.read_batch(&mut batch, BATCH_ROWS) {
                    Ok(0) => break,
                    Ok(_) => {
                        if batch_tx.send(Ok(batch)).is_err() {
                            break;
                        }
                    }
                    Err(e) => {
                        let _ = batch_tx.send(Err(e));
                        break;
                    }
                }
            }
            drop(batch_tx);
            for text in text_rx {
                write(text, &mut output);
            }
            output
        });

        let mut text = Vec::with_capacity(TEXT_BYTES + 1024);
        let mut recording_error = None;
        for message in batch_rx {
            let batch = match message {
                Ok(batch) => batch,
                Err(e) => {
                    recording_error = Some(e);
                    break;
                }
            };
            replayer.push(&batch.t_s, &batch.columns, |t, e| {
                for v in [t, e.omega_hat_rad_s, e.load_hat_nm, e.inertia_hat_kg_m2] {
                    push_value(&mut text, v);
                    text.push(b',');
                }
                push_value(&mut text, e.viscous_hat_nm_s_rad);
                text.push(b'\n');
            });
            if text.len() >= TEXT_BYTES {
                let spare = spare_text_rx.try_recv().unwrap_or_else(|_| Vec::with_capacity(TEXT_BYTES + 1024));
                let _ = text_tx.send(std::mem::replace(&mut text, spare));
            }
            let _ = spare_batch_tx.send(batch);
        }
        if recording_error.is_none() && !text.is_empty() {
            let _ = text_tx.send(text);
        }
        drop(text_tx);
        let output = io.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic));
        (recording_error, output)
    });

    let failed = match (recording_error, replayer.finish(), output) {
        (Some(e), _, output) => (EstimateError::Recording(e), output.ok()),
        (None, Err(e), output) => (EstimateError::Replay(e), output.ok()),
        (None, Ok(_), Err(e)) => (e, None),
        (None, Ok(rows), Ok(o)) => return o.commit().map(|()| rows),
    };
    if let (_, Some(o)) = failed {
        o.discard();
    }
    Err(failed.0)
}

/// For each column, whether it holds a finite value somewhere in the file. Reads only as far as it needs to (the
/// first row, as a rule); a file that cannot be read answers `false`, and the replay then reports why.
fn holds_values(recording: &Path, columns: &[&str]) -> Vec<bool> {
    let mut held = vec![false; columns.len()];
    let Ok(mut reader) = StreamReader::open(recording) else { return held };
    let indices: Vec<usize> = columns.iter().map(|c| reader.index_of(c).unwrap_or(usize::MAX)).collect();
    reader.select(&indices);
    let mut batch = Batch::default();
    while !held.iter().all(|h| *h) {
        match reader.read_batch(&mut batch, BATCH_ROWS) {
            Ok(0) | Err(_) => break,
            Ok(_) => {
                for (h, values) in held.iter_mut().zip(&batch.columns) {
                    *h = *h || values.iter().any(|v| v.is_finite());
                }
            }
        }
    }
    held
}

/// The estimates file under construction: a temporary file beside the final path, renamed over it by
/// [`Output::commit`]. The first write error is kept and reported there.
struct Output {
    file: File,
    /// The temporary file, or `None` when writing directly to `path` (not a regular file).
    temp: Option<PathBuf>,
    path: PathBuf,
    error: Option<std::io::Error>,
}

impl Output {
    /// Creates the file and writes the header row.
    fn create(path: &Path) -> Result<Output, EstimateError> {
        let special = std::fs::metadata(path).is_ok_and(|m| !m.is_file());
        let temp = match path.file_name() {
            Some(name) if !special => {
                let mut temp_name = std::ffi::OsString::from(".");
                temp_name.push(name);
                temp_name.push(format!(".{}.tmp", std::process::id()));
                Some(path.with_file_name(temp_name))
            }
            _ => None,
        };
        let file = File::create(temp.as_deref().unwrap_or(path)).map_err(|source| EstimateError::Output {
            action: "creating",
            path: path.display().to_string(),
            source,
        })?;
        let mut output = Output { file, temp, path: path.to_path_buf(), error: None };
        output.write(format!("{}\n", COLUMNS.join(",")).as_bytes());
        Ok(output)
    }

    fn write(&mut self, bytes: &[u8]) {
        if self.error.is_none()
            && let Err(e) = self.file.write_all(bytes)
        {
            self.error = Some(e);
        }
    }

    /// Renames the temporary file to the final path, or reports the first write error.
    fn commit(mut self) -> Result<(), EstimateError> {
        let done = match (self.error.take(), &self.temp) {
            (Some(e), _) => Err(e),
            (None, Some(temp)) => std::fs::rename(temp, &self.path),
            (None, None) => Ok(()),
        };
        done.map_err(|source| {
            let path = self.path.display().to_string();
            self.discard();
            EstimateError::Output { action: "writing", path, source }
        })
    }

    /// Removes the temporary file.
    fn discard(self) {
        if let Some(temp) = &self.temp {
            let _ = std::fs::remove_file(temp);
        }
    }
}

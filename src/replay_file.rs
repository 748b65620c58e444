//! `hydrolens estimate` as a library: a recording file streamed through an estimator into an estimates CSV, one
//! thread parsing while the other estimates and writes, in flat memory.
//!
//! The output is byte for byte what replaying the whole [`crate::recording::load`]ed recording and writing every
//! row with [`RowWriter`] gives, and the errors are the ones that path reports, in its order: the recording's
//! (first bad line), then the replay's (no torque or speed column, no displacement), then the output file's. The
//! estimates are written under a temporary name beside the output and renamed to it when everything is done, so on
//! any error the output path is left as it was and no partial file remains. (A path that is not a regular file,
//! such as `/dev/null`, is written directly.)

use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::sync::mpsc;

use crate::estimator::{Estimator, Plan, ReplayError, Replayer};
use crate::plant::PlantModel;
use crate::recording::{Batch, RecordingError, RowWriter, StreamReader};

/// The columns of an estimates file.
pub const COLUMNS: [&str; 5] = ["t_s", "omega_hat_rad_s", "load_hat_nm", "inertia_hat_kg_m2", "viscous_hat_nm_s_rad"];

/// Rows per batch handed from the parsing thread to the estimating one, and batches under way at once: enough to
/// keep both threads busy, little enough to stay in cache (4 k rows × 4 columns × 8 bytes = 128 KiB a batch).
const BATCH_ROWS: usize = 4096;
const BATCHES_IN_FLIGHT: usize = 4;

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

    // Errors of the output file wait until the recording and the replay are known to be good.
    let mut output = Output::create(out);
    let recording_error = std::thread::scope(|s| {
        let (full_tx, full_rx) = mpsc::sync_channel::<Result<Batch, RecordingError>>(BATCHES_IN_FLIGHT);
        let (empty_tx, empty_rx) = mpsc::sync_channel::<Batch>(BATCHES_IN_FLIGHT + 1);
        s.spawn(move || {
            loop {
                let mut batch = empty_rx.try_recv().unwrap_or_default();
                match reader.read_batch(&mut batch, BATCH_ROWS) {
                    Ok(0) => return,
                    Ok(_) => {
                        if full_tx.send(Ok(batch)).is_err() {
                            return;
                        }
                    }
                    Err(e) => {
                        let _ = full_tx.send(Err(e));
                        return;
                    }
                }
            }
        });
        for message in full_rx {
            let batch = match message {
                Ok(batch) => batch,
                Err(e) => return Some(e),
            };
            match &mut output {
                Ok(o) => {
                    replayer.push(&batch.t_s, &batch.columns, |t, e| {
                        o.write_row([t, e.omega_hat_rad_s, e.load_hat_nm, e.inertia_hat_kg_m2, e.viscous_hat_nm_s_rad])
                    });
                }
                Err(_) => replayer.push(&batch.t_s, &batch.columns, |_, _| {}),
            }
            let _ = empty_tx.send(batch);
        }
        None
    });
    let result = match (recording_error, replayer.finish(), output) {
        (Some(e), _, output) => Err((EstimateError::Recording(e), output.ok())),
        (None, Err(e), output) => Err((EstimateError::Replay(e), output.ok())),
        (None, Ok(_), Err(e)) => Err((e, None)),
        (None, Ok(rows), Ok(o)) => o.commit().map(|()| rows).map_err(|e| (e, None)),
    };
    result.map_err(|(e, output)| {
        if let Some(o) = output {
            o.discard();
        }
        e
    })
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

/// The estimates file under construction: rows go to a temporary file beside the final path, renamed over it by
/// [`Output::commit`]. The first write error is kept and reported at the end.
struct Output {
    writer: RowWriter<BufWriter<File>>,
    /// The temporary file, or `None` when writing directly to `path` (not a regular file).
    temp: Option<PathBuf>,
    path: PathBuf,
    error: Option<std::io::Error>,
}

impl Output {
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
        let error = |action, source| EstimateError::Output { action, path: path.display().to_string(), source };
        let file = File::create(temp.as_deref().unwrap_or(path)).map_err(|e| error("creating", e))?;
        let writer = RowWriter::new(BufWriter::with_capacity(1 << 18, file), &COLUMNS).map_err(|e| error("writing", e));
        let output = Output { writer: writer?, temp, path: path.to_path_buf(), error: None };
        Ok(output)
    }

    fn write_row(&mut self, row: [f64; COLUMNS.len()]) {
        if self.error.is_none()
            && let Err(e) = self.writer.write_row(row)
        {
            self.error = Some(e);
        }
    }

    /// Flushes, and renames the temporary file to the final path.
    fn commit(mut self) -> Result<(), EstimateError> {
        let path = self.path.display().to_string();
        let written = match self.error.take() {
            Some(e) => Err(e),
            None => self.writer.flush(),
        };
        let written = written.and_then(|()| match &self.temp {
            Some(temp) => std::fs::rename(temp, &self.path),
            None => Ok(()),
        });
        written.map_err(|source| {
            if let Some(temp) = &self.temp {
                let _ = std::fs::remove_file(temp);
            }
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

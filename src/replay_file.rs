//! `hydrolens estimate` as a library: a recording file streamed through an estimator into an estimates CSV, in
//! flat memory, on two threads.
//!
//! One thread reads the recording batch by batch with [`StreamReader`] (the reader `load` and `analyze` use, with its
//! grammar and its errors) and writes the estimates text it is handed back; the other runs the estimator over each
//! batch (the one step that must go row after row) and formats the estimates. The output is byte for byte what
//! replaying the whole [`crate::recording::load`]ed recording and writing every row with
//! [`crate::recording::RowWriter`] gives, and the errors are the ones that path reports, in its order: the
//! recording's (first bad line), then the replay's (no torque or speed column, no displacement), then the output
//! file's.
//!
//! The estimates are written through a [`Replacement`] (a temporary file beside the output, renamed to it when
//! everything is done), so on any error the output path is left as it was and the temporary file is removed.
//!
//! The replay takes `torque_nm` only if it holds a value somewhere, else the pressures (and `omega_rad_s` before
//! `theta_rad` likewise). When both are in the header, the file is first read until the column shows a value,
//! which is the first row as a rule; a column that is empty all the way costs a second pass over the file.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::mpsc;

use crate::estimator::{Estimate, Estimator};
use crate::output::Replacement;
use crate::plant::PlantModel;
use crate::recording::{Batch, RecordingError, StreamReader, push_value};
use crate::replay::{Plan, ReplayError, Replayed, Replayer};

/// The columns of an estimates file.
pub const COLUMNS: [&str; 10] = crate::recording::concat(["t_s"], crate::recording::ESTIMATE_COLUMNS);

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
    #[error("{action} {path}")]
    Output { action: &'static str, path: String, source: std::io::Error },
}

impl EstimateError {
    /// A bad recording or model is the user's to fix (exit 2), and so is an output path that cannot be created
    /// ([`crate::output::path_refused`]); an output that fails while being written (a full disk) is not.
    pub fn is_bad_input(&self) -> bool {
        match self {
            EstimateError::Recording(e) => e.is_bad_input(),
            EstimateError::Replay(_) => true,
            EstimateError::Output { action, source, .. } => {
                *action == "creating" && crate::output::path_refused(source)
            }
        }
    }
}

/// Replays the recording at `recording` through a copy of `estimator` (its state is where the replay starts)
/// into an estimates CSV at `out` ([`COLUMNS`], one row per recorded row); `model_origin` names the model in
/// messages. With `max_gap_s`, a recording whose time step (the median of its first 2000) is longer (every row a gap
/// the estimator restarts at: a clock in ms read as s, a 1 Hz recording) or shorter than 10 µs (a clock in the wrong
/// unit) is refused, checked as the rows pass: the recording is read once, so that a pipe or a FIFO works. Returns
/// the rows and how many were filled in.
pub fn estimate_file(
    recording: &Path,
    model: &PlantModel,
    model_origin: &str,
    estimator: &dyn Estimator,
    out: &Path,
    max_gap_s: Option<f64>,
) -> Result<Replayed, EstimateError> {
    estimate_file_in_batches(recording, model, model_origin, estimator, out, max_gap_s, BATCH_ROWS)
}

/// [`estimate_file`], handing `batch_rows` rows at a time from one thread to the other (tests make it small).
#[doc(hidden)]
pub fn estimate_file_in_batches(
    recording: &Path,
    model: &PlantModel,
    model_origin: &str,
    estimator: &dyn Estimator,
    out: &Path,
    max_gap_s: Option<f64>,
    batch_rows: usize,
) -> Result<Replayed, EstimateError> {
    let mut estimator = estimator.boxed_clone();
    let (reader, plan) = open_planned(recording)?;
    let name = recording.display().to_string();
    let mut replayer = Replayer::new(plan, model, model_origin, &name, estimator.as_mut());
    if let Some(max_gap_s) = max_gap_s {
        replayer.check_time_step(max_gap_s, model_origin);
    }
    // an output error waits until the recording and the replay are known to be good
    let output = Output::create(out);

    let (recording_error, output) = std::thread::scope(|s| {
        let (batch_tx, batch_rx) = mpsc::sync_channel::<Result<Batch, RecordingError>>(BATCHES_IN_FLIGHT);
        let (spare_batch_tx, spare_batch_rx) = mpsc::channel::<Batch>();
        // unbounded, but never long: the reading thread empties it before each batch it reads
        let (text_tx, text_rx) = mpsc::channel::<Vec<u8>>();
        let (spare_text_tx, spare_text_rx) = mpsc::channel::<Vec<u8>>();
        let io = s.spawn(move || {
            read_and_write(reader, batch_rows, output, batch_tx, spare_batch_rx, text_rx, spare_text_tx)
        });
        let recording_error = replay_batches(&mut replayer, batch_rx, &spare_batch_tx, text_tx, &spare_text_rx);
        let output = io.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic));
        (recording_error, output)
    });

    // errors in the order the whole-file path reports them: the recording's, the replay's, the output's; the
    // estimates are renamed into place only when all is well, otherwise the temporary file goes with `output`
    if let Some(e) = recording_error {
        return Err(EstimateError::Recording(e));
    }
    let done = replayer.finish().map_err(EstimateError::Replay)?;
    output?.commit().map(|()| done)
}

/// The reading and writing thread: reads the recording `batch_rows` rows at a time into `batches` (reusing the
/// batches the replay hands back), writing the estimates' text that waits in `texts` before each; once the
/// recording ends (or fails), writes the rest of the text as it comes. Hands back the output.
fn read_and_write(
    mut reader: StreamReader<crate::recording::RecordingFile>,
    batch_rows: usize,
    mut output: Result<Output, EstimateError>,
    batches: mpsc::SyncSender<Result<Batch, RecordingError>>,
    spare_batches: mpsc::Receiver<Batch>,
    texts: mpsc::Receiver<Vec<u8>>,
    spare_texts: mpsc::Sender<Vec<u8>>,
) -> Result<Output, EstimateError> {
    let write = |mut text: Vec<u8>, output: &mut Result<Output, EstimateError>| {
        if let Ok(o) = output {
            o.write(&text);
        }
        text.clear();
        let _ = spare_texts.send(text);
    };
    loop {
        while let Ok(text) = texts.try_recv() {
            write(text, &mut output);
        }
        let mut batch = spare_batches.try_recv().unwrap_or_default();
        match reader.read_batch(&mut batch, batch_rows) {
            Ok(0) => break,
            Ok(_) => {
                if batches.send(Ok(batch)).is_err() {
                    break;
                }
            }
            Err(e) => {
                let _ = batches.send(Err(e));
                break;
            }
        }
    }
    drop(batches);
    for text in texts {
        write(text, &mut output);
    }
    output
}

/// The replaying side: each batch from `batches` through `replayer`, the estimates as CSV text into `texts` (in
/// pieces of about [`TEXT_BYTES`]), the batch handed back for reuse. The recording's error, if it had one (the
/// text after it is not sent).
fn replay_batches(
    replayer: &mut Replayer<'_>,
    batches: mpsc::Receiver<Result<Batch, RecordingError>>,
    spare_batches: &mpsc::Sender<Batch>,
    texts: mpsc::Sender<Vec<u8>>,
    spare_texts: &mpsc::Receiver<Vec<u8>>,
) -> Option<RecordingError> {
    let mut text = Vec::with_capacity(TEXT_BYTES + 1024);
    let mut rows = RowText::default();
    let mut recording_error = None;
    for message in batches {
        let batch = match message {
            Ok(batch) => batch,
            Err(e) => {
                recording_error = Some(e);
                break;
            }
        };
        replayer.push(&batch.t_s, &batch.columns, |t, e| rows.push(&mut text, t, e));
        if text.len() >= TEXT_BYTES {
            let spare = spare_texts.try_recv().unwrap_or_else(|_| Vec::with_capacity(TEXT_BYTES + 1024));
            let _ = texts.send(std::mem::replace(&mut text, spare));
        }
        let _ = spare_batches.send(batch);
    }
    if recording_error.is_none() && !text.is_empty() {
        let _ = texts.send(text);
    }
    // dropping `texts` tells the writing thread that the text is complete
    recording_error
}

/// The recording's reader with the replay's columns selected, and the replay's plan.
fn open_planned(recording: &Path) -> Result<(StreamReader<crate::recording::RecordingFile>, Plan), EstimateError> {
    let mut reader = StreamReader::open(recording).map_err(EstimateError::Recording)?;
    let plan = Plan::choose(reader.names(), |columns| holds_values(recording, columns));
    let selected: Vec<usize> = plan.columns().iter().filter_map(|c| reader.index_of(c)).collect();
    reader.select(&selected);
    Ok((reader, plan))
}

/// Rows of the estimates file as [`crate::recording::RowWriter`] writes them ([`push_value`] is its formatter). J
/// and B and their deviations, which the RLS changes once a block and the Kalman filter never, are formatted when
/// they change and copied while they stay the same (the same bits, the same text): half the formatting, the larger
/// half of the estimating thread's work.
#[derive(Default)]
struct RowText {
    tail_bits: Option<[u64; 7]>,
    /// `,J,B,σ_J,σ_B,J's and B's identification,load character\n` of the row before.
    tail: Vec<u8>,
}

impl RowText {
    fn push(&mut self, text: &mut Vec<u8>, t: f64, e: &Estimate) {
        push_value(text, t);
        for v in [e.omega_hat_rad_s, e.load_hat_nm] {
            text.push(b',');
            push_value(text, v);
        }
        let tail = [
            e.inertia_hat_kg_m2,
            e.viscous_hat_nm_s_rad,
            e.inertia_sd_kg_m2,
            e.viscous_sd_nm_s_rad,
            e.inertia_identified,
            e.viscous_identified,
            e.load_character,
        ];
        let bits = tail.map(f64::to_bits);
        if self.tail_bits != Some(bits) {
            self.tail.clear();
            for v in tail {
                self.tail.push(b',');
                push_value(&mut self.tail, v);
            }
            self.tail.push(b'\n');
            self.tail_bits = Some(bits);
        }
        text.extend_from_slice(&self.tail);
    }
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

/// The estimates file under construction ([`Replacement`]). The first write error is kept and reported by
/// [`Output::commit`].
struct Output {
    file: Replacement,
    path: PathBuf,
    error: Option<std::io::Error>,
}

impl Output {
    /// Creates the file and writes the header row.
    fn create(path: &Path) -> Result<Output, EstimateError> {
        let file = Replacement::create(path).map_err(|source| EstimateError::Output {
            action: "creating",
            path: path.display().to_string(),
            source,
        })?;
        let mut output = Output { file, path: path.to_path_buf(), error: None };
        output.write(format!("{}\n", COLUMNS.join(",")).as_bytes());
        Ok(output)
    }

    fn write(&mut self, bytes: &[u8]) {
        if self.error.is_none()
            && let Err(e) = self.file.file().write_all(bytes)
        {
            self.error = Some(e);
        }
    }

    /// Renames the temporary file to the final path, or reports the first write error (and removes the file).
    fn commit(mut self) -> Result<(), EstimateError> {
        let done = match self.error.take() {
            Some(e) => Err(e),
            None => self.file.commit(),
        };
        done.map_err(|source| EstimateError::Output {
            action: "writing",
            path: self.path.display().to_string(),
            source,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::{EstimatorSettings, Method, try_build};
    use crate::output::file_names;
    use crate::recording::simulated;

    fn estimator(method: Method) -> Box<dyn Estimator> {
        let settings = EstimatorSettings { method, ..EstimatorSettings::default() };
        try_build(&settings, &PlantModel::reference()).expect("default settings fit the reference plant")
    }

    /// A test-stand recording of `seconds` as CSV text.
    fn stand_csv(seconds: f64) -> String {
        let rec = simulated::test_stand(&PlantModel::reference(), seconds, 7, &mut |_| {}).expect("simulate");
        let mut text = Vec::new();
        crate::recording::write_csv(&mut text, &rec).expect("to memory");
        String::from_utf8(text).expect("UTF-8")
    }

    #[test]
    fn batches_of_any_size_write_the_same_estimates() {
        let dir = tempfile::tempdir().expect("tmp");
        let rec = dir.path().join("r.csv");
        std::fs::write(&rec, stand_csv(2.0)).expect("write");
        let model = PlantModel::reference();
        for method in [Method::RlsSgd, Method::Kalman] {
            let out = dir.path().join("est.csv");
            let done = estimate_file(&rec, &model, "model", estimator(method).as_ref(), &out, None).expect("valid");
            assert_eq!(done.rows, 2001);
            let expected = std::fs::read(&out).expect("output");
            for batch_rows in [1, 7, 100] {
                let est = estimator(method);
                estimate_file_in_batches(&rec, &model, "model", est.as_ref(), &out, None, batch_rows).expect("valid");
                let got = std::fs::read(&out).expect("output");
                assert!(got == expected, "{method}, batches of {batch_rows}: the output differs");
            }
        }
        assert_eq!(file_names(dir.path()), ["est.csv", "r.csv"]);
    }

    #[test]
    fn the_temporary_file_goes_unless_renamed_into_place() {
        let dir = tempfile::tempdir().expect("tmp");
        let out = dir.path().join("est.csv");
        std::fs::write(&out, "before").expect("write");
        let o = Output::create(&out).expect("create");
        assert_eq!(file_names(dir.path()).len(), 2, "a temporary file beside the output");
        drop(o); // as on an error or a panic
        assert_eq!(file_names(dir.path()), ["est.csv"]);
        assert_eq!(std::fs::read(&out).expect("output"), b"before");
        let mut o = Output::create(&out).expect("create");
        o.write(b"0,1,2,3,4\n");
        o.commit().expect("commit");
        assert_eq!(file_names(dir.path()), ["est.csv"]);
        assert!(std::fs::read_to_string(&out).expect("output").starts_with("t_s,"));
        // written in place: no temporary file
        use crate::output::written_in_place;
        assert!(written_in_place(Path::new("/dev/null")) && !written_in_place(&out));
        assert!(!written_in_place(&dir.path().join("not there yet.csv")));
    }

    #[test]
    fn errors_found_across_batches_leave_nothing_behind() {
        let dir = tempfile::tempdir().expect("tmp");
        let model = PlantModel::reference();
        let head = "t_s,omega_rad_s,torque_nm,f_set_hz\n";
        let rows: String = (0..40).map(|k| format!("{},{}.5,2,10\n", k as f64 * 0.001, k)).collect();
        for (tail, parts) in [
            ("0.01,1,2,10\n", ["line 42", "`t_s`", "backwards"]),
            ("0.05,1,2,1x0\n", ["line 42", "`f_set_hz`", "1x0"]),
            ("0.05,1,2\n", ["line 42", "3 fields", "expected 4"]),
        ] {
            let rec = dir.path().join("bad.csv");
            std::fs::write(&rec, format!("{head}{rows}{tail}")).expect("write");
            let out = dir.path().join("est.csv");
            std::fs::write(&out, "before").expect("write");
            for batch_rows in [1, 30, 4096] {
                let est = estimator(Method::Kalman);
                let err = estimate_file_in_batches(&rec, &model, "model", est.as_ref(), &out, None, batch_rows)
                    .expect_err("bad input")
                    .to_string();
                for p in parts {
                    assert!(err.contains(p), "batches of {batch_rows}: `{p}` not in {err}");
                }
                assert_eq!(std::fs::read(&out).expect("output"), b"before");
                assert_eq!(file_names(dir.path()), ["bad.csv", "est.csv"]);
            }
        }
    }
}

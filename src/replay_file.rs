//! `hydrolens estimate` as a library: a recording file streamed through an estimator into an estimates CSV, in
//! flat memory, on two threads.
//!
//! The fast way, for the files `simulate` and `serve` write (and any other that the reader's fast path takes
//! whole): the two threads are alike. Each takes the next chunk of lines from the file, parses it, waits for its
//! turn to run the estimator over it (the one step that must go row after row), formats the estimates and waits
//! for its turn to write them. So parsing and formatting, nine tenths of the work, run on both cores. A chunk the
//! fast path turns down (quotes, `nan`, a bad cell, `t_s` not increasing) stops both, and the file is read again
//! from the start the careful way, with a copy of the estimator as it was given: one thread reads, parses and
//! writes, the other estimates and formats, and every rule and error message of the reader applies.
//!
//! Either way the output is byte for byte what replaying the whole [`crate::recording::load`]ed recording and
//! writing every row with [`crate::recording::RowWriter`] gives, and the errors are the ones that path reports, in
//! its order: the recording's (first bad line), then the replay's (no torque or speed column, no displacement),
//! then the output file's. The estimates are written under a temporary name beside the output (`.NAME.PID.tmp`)
//! and renamed to it when everything is done, so on any error the output path is left as it was and the temporary
//! file is removed. A path that is there and is not a regular file (`/dev/null`, a pipe, a symbolic link such as
//! `/dev/stdout`) is written directly, and the careful way only: what went out cannot be taken back.
//!
//! The replay takes `torque_nm` only if it holds a value somewhere, else the pressures (and `omega_rad_s` before
//! `theta_rad` likewise). When both are in the header, the file is first read until the column shows a value,
//! which is the first row as a rule; a column that is empty all the way costs a second pass over the file.

use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Condvar, Mutex, PoisonError, mpsc};
use std::time::{Duration, Instant};

use crate::estimator::{Estimate, Estimator};
use crate::plant::PlantModel;
use crate::recording::{
    Batch, Chunk, ChunkParser, ChunkSource, RecordingError, StreamReader, TimeText, push_parsed_value, push_value,
};
use crate::replay::{Plan, ReplayError, Replayer};

/// The columns of an estimates file.
pub const COLUMNS: [&str; 7] = crate::recording::concat(["t_s"], crate::recording::ESTIMATE_COLUMNS);

/// Rows per batch handed from the reading thread to the estimating one, and batches under way at once: enough to
/// keep both threads busy, little enough to stay in cache (4 k rows × 4 columns × 8 bytes = 128 KiB a batch).
const BATCH_ROWS: usize = 4096;
const BATCHES_IN_FLIGHT: usize = 4;
/// Output text handed back to the reading thread to write, in pieces of about this size.
const TEXT_BYTES: usize = 1 << 18;
/// Bytes of the recording a thread takes at a time on the fast way: its text, parsed columns, estimates and
/// output (about 1 600 rows) stay in the core's own caches.
const CHUNK_BYTES: usize = 1 << 18;

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
    /// A bad recording or model is the user's to fix (exit 2); an output that cannot be written is not.
    pub fn is_bad_input(&self) -> bool {
        match self {
            EstimateError::Recording(e) => e.is_bad_input(),
            EstimateError::Replay(_) => true,
            EstimateError::Output { .. } => false,
        }
    }
}

/// Replays the recording at `recording` through a copy of `estimator` (its state is where the replay starts)
/// into an estimates CSV at `out` ([`COLUMNS`], one row per recorded row); `model_origin` names the model in
/// messages. Returns the number of rows.
pub fn estimate_file(
    recording: &Path,
    model: &PlantModel,
    model_origin: &str,
    estimator: &dyn Estimator,
    out: &Path,
) -> Result<u64, EstimateError> {
    estimate_file_in_chunks(recording, model, model_origin, estimator, out, CHUNK_BYTES)
}

/// [`estimate_file`], taking `chunk_bytes` of the file at a time on the fast way (tests make it small).
#[doc(hidden)]
pub fn estimate_file_in_chunks(
    recording: &Path,
    model: &PlantModel,
    model_origin: &str,
    estimator: &dyn Estimator,
    out: &Path,
    chunk_bytes: usize,
) -> Result<u64, EstimateError> {
    // what is written in place cannot be taken back, and the fast way may have to start over
    if !written_in_place(out)
        && let Some(done) =
            estimate_fast(recording, model, model_origin, estimator.boxed_clone().as_mut(), out, chunk_bytes)
    {
        return done;
    }
    estimate_careful(recording, model, model_origin, estimator.boxed_clone().as_mut(), out)
}

/// Whether the estimates go straight to `out` rather than to a temporary file renamed over it: for anything that
/// is there and is not a regular file, such as `/dev/null`, a pipe, or a symbolic link (`/dev/stdout` is one, to
/// whatever standard output is: renaming over it would replace the link).
fn written_in_place(out: &Path) -> bool {
    std::fs::symlink_metadata(out).is_ok_and(|m| !m.is_file())
}

/// The recording's reader with the replay's columns selected, and the replay's plan.
fn open_planned(recording: &Path) -> Result<(StreamReader<crate::recording::RecordingFile>, Plan), EstimateError> {
    let mut reader = StreamReader::open(recording).map_err(EstimateError::Recording)?;
    let plan = Plan::choose(reader.names(), |columns| holds_values(recording, columns));
    let selected: Vec<usize> = plan.columns().iter().filter_map(|c| reader.index_of(c)).collect();
    reader.select(&selected);
    Ok((reader, plan))
}

/// Where the replay is, in the fast way: taken by one thread at a time, chunk after chunk.
struct Estimating<'e> {
    replayer: Replayer<'e>,
    /// `t_s` of the last row replayed (−∞ before the first).
    last_t: f64,
}

/// The fast way (see the module doc): `None` if the file is not for it, and nothing is left behind then.
fn estimate_fast(
    recording: &Path,
    model: &PlantModel,
    model_origin: &str,
    estimator: &mut dyn Estimator,
    out: &Path,
    chunk_bytes: usize,
) -> Option<Result<u64, EstimateError>> {
    let (reader, plan) = match open_planned(recording) {
        Ok(opened) => opened,
        Err(e) => return Some(Err(e)),
    };
    let (source, parser) = reader.into_chunks()?;
    let name = recording.display().to_string();
    let replayer = Replayer::new(plan, model, model_origin, &name, estimator);
    let shared = Shared {
        source: Mutex::new((source, 0)),
        parser,
        chunk_bytes,
        estimating: Turns::new(Estimating { replayer, last_t: f64::NEG_INFINITY }),
        // an output error waits until the recording and the replay are known to be good
        writing: Turns::new(Output::create(out)),
        stop: AtomicBool::new(false),
    };
    std::thread::scope(|s| {
        s.spawn(|| work(&shared));
        work(&shared);
    });
    let estimating = shared.estimating.into_inner();
    let output = shared.writing.into_inner();
    if shared.stop.into_inner() || estimating.last_t == f64::NEG_INFINITY {
        // not for the fast way (or no rows, which the careful way names); dropping the output removes its file
        return None;
    }
    Some(conclude(None, estimating.replayer.finish(), output))
}

/// The outcome, errors in the order the whole-file path reports them: the recording's, the replay's, the output's.
/// The estimates are renamed into place only when all is well; otherwise the temporary file goes with `output`.
fn conclude(
    recording: Option<RecordingError>,
    replay: Result<u64, ReplayError>,
    output: Result<Output, EstimateError>,
) -> Result<u64, EstimateError> {
    if let Some(e) = recording {
        return Err(EstimateError::Recording(e));
    }
    let rows = replay.map_err(EstimateError::Replay)?;
    output?.commit().map(|()| rows)
}

/// What the two threads of the fast way share.
struct Shared<'e, R> {
    /// The file, and the number of the next chunk.
    source: Mutex<(ChunkSource<R>, u64)>,
    parser: ChunkParser,
    chunk_bytes: usize,
    estimating: Turns<Estimating<'e>>,
    writing: Turns<Result<Output, EstimateError>>,
    /// Set when a chunk is not for the fast way (or a thread panicked): every thread stops.
    stop: AtomicBool,
}

impl<R> Shared<'_, R> {
    fn stop(&self) {
        self.stop.store(true, Ordering::SeqCst);
        self.estimating.wake_all();
        self.writing.wake_all();
    }
}

/// Stops the other thread if this one panics, so that it does not wait for a turn that never comes.
struct StopOnPanic<'a, 'e, R>(&'a Shared<'e, R>);

impl<R> Drop for StopOnPanic<'_, '_, R> {
    fn drop(&mut self) {
        if std::thread::panicking() {
            self.0.stop();
        }
    }
}

/// One thread of the fast way: chunk after chunk, read and parse, estimate (in turn), format, write (in turn).
fn work<R: std::io::Read>(shared: &Shared<'_, R>) {
    let _stop_on_panic = StopOnPanic(shared);
    let mut chunk = Chunk::default();
    let mut batch = Batch::default();
    let mut times: Vec<TimeText> = Vec::new();
    let mut estimates: Vec<(f64, Estimate)> = Vec::new();
    let mut text = Vec::new();
    let mut rows = RowFormatter::default();
    while !shared.stop.load(Ordering::Relaxed) {
        let k = {
            let mut source = shared.source.lock().unwrap_or_else(PoisonError::into_inner);
            match source.0.next_chunk(&mut chunk, shared.chunk_bytes) {
                Ok(true) => {
                    source.1 += 1;
                    source.1 - 1
                }
                Ok(false) => return,
                // the careful way reads the file again and reports it
                Err(_) => return shared.stop(),
            }
        };
        if !shared.parser.parse(chunk.bytes(), &mut batch, &mut times) {
            return shared.stop();
        }
        let in_order = shared.estimating.take(k, &shared.stop, |e| {
            if batch.t_s.first().is_some_and(|&t| t <= e.last_t) {
                return false;
            }
            e.last_t = batch.t_s.last().copied().unwrap_or(e.last_t);
            estimates.clear();
            e.replayer.push(&batch.t_s, &batch.columns, |t, estimate| estimates.push((t, *estimate)));
            true
        });
        match in_order {
            Some(true) => {}
            Some(false) => return shared.stop(),
            None => return,
        }
        text.clear();
        // one estimate a row (none if the replay is sure to fail): `t_s` is copied from the recording where it can be
        let times = if times.len() == estimates.len() { times.as_slice() } else { &[] };
        for (row, (t, e)) in estimates.iter().enumerate() {
            debug_assert!(times.is_empty() || batch.t_s[row].to_bits() == t.to_bits(), "an estimate a row, in order");
            let t_text = times.get(row).map_or(&[][..], |text| text.in_lines(chunk.bytes()));
            rows.push(&mut text, *t, t_text, e);
        }
        let written = shared.writing.take(k, &shared.stop, |output| {
            if let Ok(o) = output {
                o.write(&text);
            }
        });
        if written.is_none() {
            return;
        }
    }
}

/// A value used by turns: turn `k` comes after turns `0..k`, whichever thread takes them.
struct Turns<T> {
    state: Mutex<(u64, T)>,
    next: Condvar,
    /// The turn under way or next, readable without the lock, for waiting by spinning first.
    now: AtomicU64,
}

/// How long a thread spins for its turn before it sleeps. A turn is short (estimating or writing one chunk takes
/// tens of microseconds), and a thread that sleeps leaves its core idle: in a virtual machine, waking an idle core
/// took up to a millisecond here, so the two threads went in step at 1.5-1.6 cores instead of 1.9.
const SPIN: Duration = Duration::from_micros(300);

impl<T> Turns<T> {
    fn new(value: T) -> Turns<T> {
        Turns { state: Mutex::new((0, value)), next: Condvar::new(), now: AtomicU64::new(0) }
    }

    /// Waits for turn `k` and runs `f` on the value; `None`, without running it, once `stop` is set.
    fn take<U>(&self, k: u64, stop: &AtomicBool, f: impl FnOnce(&mut T) -> U) -> Option<U> {
        let start = Instant::now();
        'spin: while self.now.load(Ordering::Acquire) != k && !stop.load(Ordering::Relaxed) {
            for _ in 0..64 {
                std::hint::spin_loop();
            }
            if start.elapsed() > SPIN {
                break 'spin;
            }
        }
        let mut state = self.state.lock().unwrap_or_else(PoisonError::into_inner);
        while state.0 != k && !stop.load(Ordering::SeqCst) {
            state = self.next.wait(state).unwrap_or_else(PoisonError::into_inner);
        }
        if stop.load(Ordering::SeqCst) {
            return None;
        }
        let done = f(&mut state.1);
        state.0 += 1;
        self.now.store(state.0, Ordering::Release);
        drop(state);
        self.next.notify_all();
        Some(done)
    }

    /// Wakes every thread waiting for a turn (to see `stop`).
    fn wake_all(&self) {
        drop(self.state.lock().unwrap_or_else(PoisonError::into_inner));
        self.next.notify_all();
    }

    fn into_inner(self) -> T {
        self.state.into_inner().unwrap_or_else(PoisonError::into_inner).1
    }
}

/// Formats rows of estimates as the estimates file has them. `t_s` is copied from the recording's text where that is
/// what formatting it would give ([`push_parsed_value`]). J and B, which the RLS changes once a block and the
/// Kalman filter never, are formatted once and copied while they stay the same (the same bits, the same text).
#[derive(Default)]
struct RowFormatter {
    tail_bits: Option<[u64; 4]>,
    /// `J,B,σ_J,σ_B\n` of the row before.
    tail: Vec<u8>,
}

impl RowFormatter {
    /// One row; `t_text` is the recording's text of `t` (or empty).
    fn push(&mut self, text: &mut Vec<u8>, t: f64, t_text: &[u8], e: &Estimate) {
        push_parsed_value(text, t, t_text);
        text.push(b',');
        for v in [e.omega_hat_rad_s, e.load_hat_nm] {
            push_value(text, v);
            text.push(b',');
        }
        let tail = [e.inertia_hat_kg_m2, e.viscous_hat_nm_s_rad, e.inertia_sd_kg_m2, e.viscous_sd_nm_s_rad];
        let bits = tail.map(f64::to_bits);
        if self.tail_bits != Some(bits) {
            self.tail.clear();
            for (i, v) in tail.into_iter().enumerate() {
                if i > 0 {
                    self.tail.push(b',');
                }
                push_value(&mut self.tail, v);
            }
            self.tail.push(b'\n');
            self.tail_bits = Some(bits);
        }
        text.extend_from_slice(&self.tail);
    }
}

/// The careful way (see the module doc).
fn estimate_careful(
    recording: &Path,
    model: &PlantModel,
    model_origin: &str,
    estimator: &mut dyn Estimator,
    out: &Path,
) -> Result<u64, EstimateError> {
    let (mut reader, plan) = open_planned(recording)?;
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
        let mut rows = RowFormatter::default();
        let mut recording_error = None;
        for message in batch_rx {
            let batch = match message {
                Ok(batch) => batch,
                Err(e) => {
                    recording_error = Some(e);
                    break;
                }
            };
            replayer.push(&batch.t_s, &batch.columns, |t, e| rows.push(&mut text, t, &[], e));
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

    conclude(recording_error, replayer.finish(), output)
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
    /// The temporary file, or `None` when writing directly to `path` (see [`written_in_place`]) or once renamed.
    temp: Option<PathBuf>,
    path: PathBuf,
    error: Option<std::io::Error>,
}

impl Output {
    /// Creates the file and writes the header row.
    fn create(path: &Path) -> Result<Output, EstimateError> {
        let special = written_in_place(path);
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

    /// Renames the temporary file to the final path, or reports the first write error (and removes the file).
    fn commit(mut self) -> Result<(), EstimateError> {
        let done = match (self.error.take(), &self.temp) {
            (Some(e), _) => Err(e),
            (None, Some(temp)) => replace(temp, &self.path),
            (None, None) => Ok(()),
        };
        match done {
            Ok(()) => {
                self.temp = None;
                Ok(())
            }
            Err(source) => {
                Err(EstimateError::Output { action: "writing", path: self.path.display().to_string(), source })
            }
        }
    }
}

/// Puts the file at `temp` in the place of `path`, in one step: while the machine runs, `path` holds the old
/// estimates or the new ones, never neither. A regular file already at `path` is swapped with `temp` ([`exchange`])
/// and then removed under the temporary name, rather than renamed over: ext4 (with its default `auto_da_alloc`)
/// starts writing the whole new file out to disk inside a rename that replaces a file, and that held the run up by
/// 60-150 ms for an hour's estimates (313 MB), a quarter of it. That flush is a guard for programs that do not
/// `fsync`, and `estimate` gives it up: after a power cut in the seconds after a run, the path may hold an empty or
/// partial file (the old one is gone); running `estimate` again makes it from the recording. Anything else (no
/// file there, no exchange on this system) is a plain rename. A kill between the swap and the removal leaves the
/// old estimates under the temporary name, as a kill before the rename leaves the new ones.
fn replace(temp: &Path, path: &Path) -> std::io::Result<()> {
    if std::fs::symlink_metadata(path).is_ok_and(|m| m.is_file()) && exchange(temp, path) {
        let swapped_out = std::fs::symlink_metadata(temp);
        if !swapped_out.as_ref().is_ok_and(|m| m.is_file()) {
            // something else took the path between the look and the swap: put it back, and fail as rename would
            exchange(temp, path);
            return Err(swapped_out.err().unwrap_or_else(|| std::io::ErrorKind::IsADirectory.into()));
        }
        // `temp` now names the old estimates; the new ones are in place whether or not they go
        if let Err(e) = std::fs::remove_file(temp) {
            tracing::warn!(
                "the new estimates are in {}, but the old ones stay in {}: {e}",
                path.display(),
                temp.display()
            );
        }
        return Ok(());
    }
    std::fs::rename(temp, path)
}

/// Swaps the files at `a` and `b` in one step (`renameat2` with `RENAME_EXCHANGE`); `false`, and nothing changed, where
/// that cannot be done (either one missing, a file system, kernel or sandbox without it, or not Linux).
fn exchange(a: &Path, b: &Path) -> bool {
    #[cfg(target_os = "linux")]
    {
        use rustix::fs::{CWD, RenameFlags, renameat_with};
        renameat_with(CWD, a, CWD, b, RenameFlags::EXCHANGE).is_ok()
    }
    #[cfg(not(target_os = "linux"))]
    {
        let _ = (a, b);
        false
    }
}

impl Drop for Output {
    /// Removes the temporary file unless it was renamed into place: on an error, and on a panic.
    fn drop(&mut self) {
        if let Some(temp) = self.temp.take() {
            let _ = std::fs::remove_file(temp);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::{EstimatorSettings, Method, try_build};
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

    /// The estimates file the careful way writes for `rec`.
    fn careful(rec: &Path, out: &Path, method: Method) -> Result<Vec<u8>, String> {
        let model = PlantModel::reference();
        estimate_careful(rec, &model, "model", estimator(method).as_mut(), out).map_err(|e| e.to_string())?;
        Ok(std::fs::read(out).expect("output"))
    }

    fn files_in(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(dir)
            .expect("dir")
            .map(|e| e.expect("entry").file_name().to_string_lossy().into())
            .collect();
        names.sort();
        names
    }

    #[test]
    fn the_fast_way_writes_what_the_careful_way_writes_in_chunks_of_any_size() {
        let dir = tempfile::tempdir().expect("tmp");
        let rec = dir.path().join("r.csv");
        std::fs::write(&rec, stand_csv(2.0)).expect("write");
        let model = PlantModel::reference();
        for method in [Method::RlsSgd, Method::Kalman] {
            let expected = careful(&rec, &dir.path().join("careful.csv"), method).expect("valid");
            for chunk_bytes in [1, 100, 4096, CHUNK_BYTES] {
                let out = dir.path().join("fast.csv");
                let done = estimate_fast(&rec, &model, "model", estimator(method).as_mut(), &out, chunk_bytes);
                let rows = done.expect("a clean recording goes the fast way").expect("valid");
                assert_eq!(rows, 2001);
                let got = std::fs::read(&out).expect("output");
                assert!(got == expected, "{method}, chunks of {chunk_bytes}: the fast way's output differs");
            }
        }
        assert_eq!(files_in(dir.path()), ["careful.csv", "fast.csv", "r.csv"]);
    }

    #[test]
    fn times_written_in_any_form_come_out_as_the_careful_way_formats_them() {
        // `t_s` as people write it: padded, with an exponent, a sign, trailing or leading zeros, more digits than needed;
        // the fast way copies a time's text only where it is what formatting would give
        let text = stand_csv(0.5);
        let forms = |k: usize, t: &str| -> String {
            let v: f64 = t.parse().expect("a time");
            match k % 8 {
                0 => format!(" {t} "),
                1 => format!("{v:e}"),
                2 => format!("+{t}"),
                3 => format!("{v:.6}"),
                4 => format!("{v:.20}"),
                5 => format!("0{t}"),
                _ => t.to_string(),
            }
        };
        let rewritten: String = text
            .lines()
            .enumerate()
            .map(|(k, line)| match (k, line.split_once(',')) {
                (1.., Some((t, rest))) => format!("{},{rest}\n", forms(k, t)),
                _ => format!("{line}\n"),
            })
            .collect();
        // and the same with `t_s` as the last column, padded, in a file with CRLF line ends
        let last_crlf: String = rewritten
            .lines()
            .map(|line| {
                let (t, rest) = line.split_once(',').expect("cells");
                format!("{rest},{t}  \r\n")
            })
            .collect();
        let dir = tempfile::tempdir().expect("tmp");
        let model = PlantModel::reference();
        let mut outputs = Vec::new();
        for (name, text) in [("r.csv", rewritten), ("last_crlf.csv", last_crlf)] {
            let rec = dir.path().join(name);
            std::fs::write(&rec, text).expect("write");
            let expected = careful(&rec, &dir.path().join("careful.csv"), Method::RlsSgd).expect("valid");
            let out = dir.path().join("fast.csv");
            for chunk_bytes in [4096, CHUNK_BYTES] {
                let done = estimate_fast(&rec, &model, "model", estimator(Method::RlsSgd).as_mut(), &out, chunk_bytes);
                done.expect("the fast way takes these").expect("valid");
                let got = String::from_utf8(std::fs::read(&out).expect("output")).expect("ASCII");
                assert!(got.as_bytes() == expected, "{name}, chunks of {chunk_bytes}: the fast way's output differs");
            }
            outputs.push(expected);
        }
        assert!(outputs[0] == outputs[1], "the column order and line ends change nothing");
        let got = String::from_utf8(outputs.swap_remove(0)).expect("ASCII");
        // the forms are in the file, and the times come out formatted
        let times: Vec<&str> = got.lines().skip(1).map(|l| l.split(',').next().expect("t_s")).collect();
        assert_eq!(times[1..9], ["0.001", "0.002", "0.003", "0.004", "0.005", "0.006", "0.007", "0.008"]);
    }

    #[test]
    fn a_file_the_fast_way_turns_down_late_is_read_again_the_careful_way() {
        let dir = tempfile::tempdir().expect("tmp");
        let text = stand_csv(2.0);
        let lines: Vec<&str> = text.lines().collect();
        let model = PlantModel::reference();
        // at line 1501 of 2002: `nan` in a column the replay does not parse; quoted cells
        let at = 1500;
        let mut shapes = Vec::new();
        for (name, line) in [
            ("nan.csv", {
                let mut cells: Vec<&str> = lines[at].split(',').collect();
                cells[1] = "nan";
                cells.join(",")
            }),
            ("quote.csv", lines[at].split(',').map(|c| format!("\"{c}\"")).collect::<Vec<_>>().join(",")),
        ] {
            let mut changed = lines.clone();
            changed[at] = &line;
            shapes.push((name, changed.join("\n") + "\n"));
        }
        for (name, text) in shapes {
            let rec = dir.path().join(name);
            std::fs::write(&rec, &text).expect("write");
            let out = dir.path().join("out.csv");
            assert!(estimate_fast(&rec, &model, "model", estimator(Method::RlsSgd).as_mut(), &out, 4096).is_none());
            assert!(!out.exists(), "{name}: the fast way leaves nothing behind");
            let expected = careful(&rec, &dir.path().join("careful.csv"), Method::RlsSgd).expect("valid");
            let est = estimator(Method::RlsSgd);
            estimate_file_in_chunks(&rec, &model, "model", est.as_ref(), &out, 4096).expect("valid");
            assert!(std::fs::read(&out).expect("output") == expected, "{name}: not the careful way's output");
            std::fs::remove_file(&out).expect("remove");
        }
    }

    #[test]
    fn the_temporary_file_goes_unless_renamed_into_place() {
        let dir = tempfile::tempdir().expect("tmp");
        let out = dir.path().join("est.csv");
        std::fs::write(&out, "before").expect("write");
        let o = Output::create(&out).expect("create");
        assert_eq!(files_in(dir.path()).len(), 2, "a temporary file beside the output");
        drop(o); // as on an error or a panic
        assert_eq!(files_in(dir.path()), ["est.csv"]);
        assert_eq!(std::fs::read(&out).expect("output"), b"before");
        let mut o = Output::create(&out).expect("create");
        o.write(b"0,1,2,3,4\n");
        o.commit().expect("commit");
        assert_eq!(files_in(dir.path()), ["est.csv"]);
        assert!(std::fs::read_to_string(&out).expect("output").starts_with("t_s,"));
        // written in place: no temporary file
        assert!(written_in_place(Path::new("/dev/null")) && !written_in_place(&out));
        assert!(!written_in_place(&dir.path().join("not there yet.csv")));
    }

    #[test]
    fn replace_puts_the_new_file_in_place_of_whatever_is_there() {
        let dir = tempfile::tempdir().expect("tmp");
        let (temp, out, link) = (dir.path().join(".new"), dir.path().join("est.csv"), dir.path().join("link.csv"));
        // nothing there yet
        std::fs::write(&temp, "first").expect("write");
        replace(&temp, &out).expect("replace");
        assert_eq!(std::fs::read(&out).expect("output"), b"first");
        // the swap itself, where replacing a file goes through it
        std::fs::write(&temp, "new").expect("write");
        if cfg!(target_os = "linux") {
            assert!(exchange(&temp, &out), "ext4, xfs, btrfs and tmpfs can swap two files");
            assert_eq!(std::fs::read(&out).expect("output"), b"new");
            assert_eq!(std::fs::read(&temp).expect("temp"), b"first", "the old file under the temporary name");
            assert!(exchange(&temp, &out));
        }
        assert!(!exchange(&dir.path().join("missing"), &out), "nothing to swap with");
        assert_eq!(std::fs::read(&out).expect("output"), b"first");
        // a file with a second name: this name gets the new file, the other keeps the old one
        std::fs::hard_link(&out, &link).expect("link");
        std::fs::write(&temp, "second").expect("write");
        replace(&temp, &out).expect("replace");
        assert_eq!(std::fs::read(&out).expect("output"), b"second");
        assert_eq!(std::fs::read(&link).expect("link"), b"first");
        assert_eq!(files_in(dir.path()), ["est.csv", "link.csv"], "the old file is not left under the temporary name");
        // a directory is not replaced, and the new file stays where it was
        let sub = dir.path().join("sub");
        std::fs::create_dir(&sub).expect("mkdir");
        std::fs::write(&temp, "third").expect("write");
        assert!(replace(&temp, &sub).is_err());
        assert!(sub.is_dir() && temp.is_file());
    }

    #[test]
    fn errors_found_across_chunks_are_the_careful_ways_and_leave_nothing_behind() {
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
            for chunk_bytes in [1, 30, 4096] {
                let est = estimator(Method::Kalman);
                let err = estimate_file_in_chunks(&rec, &model, "model", est.as_ref(), &out, chunk_bytes)
                    .expect_err("bad input")
                    .to_string();
                for p in parts {
                    assert!(err.contains(p), "chunks of {chunk_bytes}: `{p}` not in {err}");
                }
                assert_eq!(std::fs::read(&out).expect("output"), b"before");
                assert_eq!(files_in(dir.path()), ["bad.csv", "est.csv"]);
            }
        }
    }
}

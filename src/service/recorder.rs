//! Recording a drive's fresh samples to rotated CSV files on a thread of its own, so that file I/O never delays
//! the poll loop. Rows are flushed at least every 500 ms; [`Recorder::finish`] drains, closes and syncs the file.

use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, mpsc};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crate::recording::RotatingWriter;

use super::retention::{Retention, prune};
use super::state::{COLUMNS, Point, RecordingHealth};

/// How often buffered rows reach the file.
const FLUSH_EVERY: Duration = Duration::from_millis(500);
/// How often the writer thread takes the rows sent since its last turn.
const DRAIN_EVERY: Duration = Duration::from_millis(100);

/// Retention runs at each new file and at least this often (for `keep_days`).
const PRUNE_EVERY: Duration = Duration::from_secs(60);

/// After a failed write, rows are dropped (and counted) for this long before a new file is tried: a full disk is
/// not hammered with a new file per row.
const RETRY_EVERY: Duration = Duration::from_secs(1);

/// The recorder's health, written by its thread and read by the poll loop for the snapshot and metrics.
#[derive(Debug, Default)]
pub struct Health {
    failing: AtomicBool,
    errors: AtomicU64,
    rows_lost: AtomicU64,
    last_error: Mutex<Option<String>>,
    files_deleted: AtomicU64,
}

impl Health {
    pub fn snapshot(&self) -> RecordingHealth {
        RecordingHealth {
            ok: !self.failing.load(Ordering::Relaxed),
            errors: self.errors.load(Ordering::Relaxed),
            rows_lost: self.rows_lost.load(Ordering::Relaxed),
            // never wait for the writer thread: a busy lock shows no message this time
            last_error: self.last_error.try_lock().ok().and_then(|e| e.clone()),
            files_deleted: self.files_deleted.load(Ordering::Relaxed),
        }
    }
}

/// The sending side; rows go to the writer thread.
pub struct Recorder {
    tx: Option<mpsc::Sender<Point>>,
    thread: Option<JoinHandle<()>>,
    pub health: Arc<Health>,
}

/// The writer thread's handling of failures: logged once per spell, counted, the file given up, retried after
/// [`RETRY_EVERY`], and the recovery logged.
struct Spell<'a> {
    name: &'a str,
    health: &'a Health,
    retry_at: Option<Instant>,
}

impl Spell<'_> {
    fn failed(&mut self, writer: &mut RotatingWriter, e: &std::io::Error) {
        if !self.health.failing.swap(true, Ordering::Relaxed) {
            tracing::error!(drive = %self.name, error = %e, "recording failed; rows are lost until it recovers");
        }
        self.health.errors.fetch_add(1, Ordering::Relaxed);
        self.health.rows_lost.fetch_add(1, Ordering::Relaxed);
        if let Ok(mut last) = self.health.last_error.lock() {
            *last = Some(e.to_string());
        }
        writer.abandon();
        self.retry_at = Some(Instant::now() + RETRY_EVERY);
    }

    fn succeeded(&mut self) {
        if self.health.failing.swap(false, Ordering::Relaxed) {
            tracing::info!(drive = %self.name, "recording resumed");
        }
    }

    /// True while rows are to be dropped rather than tried.
    fn waiting(&mut self) -> bool {
        match self.retry_at {
            Some(t) if Instant::now() < t => {
                self.health.rows_lost.fetch_add(1, Ordering::Relaxed);
                true
            }
            _ => {
                self.retry_at = None;
                false
            }
        }
    }
}

impl Recorder {
    /// Starts writing `<dir>/<drive>-<unix ms>.csv` files, rotated after `rotate_after` or `max_bytes`.
    pub fn start(
        dir: &Path,
        drive: &str,
        rotate_after: Duration,
        max_bytes: u64,
        retention: Retention,
    ) -> std::io::Result<Recorder> {
        std::fs::create_dir_all(dir)?;
        let mut writer = RotatingWriter::new(dir, drive, &COLUMNS, rotate_after, max_bytes);
        let (tx, rx) = mpsc::channel::<Point>();
        let name = drive.to_string();
        let health = Arc::new(Health::default());
        let shared = health.clone();
        let dir = dir.to_path_buf();
        let thread = std::thread::Builder::new().name(format!("rec-{drive}")).spawn(move || {
            let mut spell = Spell { name: &name, health: &shared, retry_at: None };
            // the thread drains the channel on its own clock rather than blocking in `recv`: a blocked receiver
            // would be woken by every row, a context switch per poll per drive (a tenth of a 50-drive service's CPU)
            let mut flushed = Instant::now();
            let mut pruned: Option<(Instant, Option<std::path::PathBuf>)> = None;
            loop {
                std::thread::sleep(DRAIN_EVERY);
                let mut open = true;
                let mut wrote = false;
                loop {
                    match rx.try_recv() {
                        Ok(p) => {
                            if spell.waiting() {
                                continue;
                            }
                            match writer.write_row(Instant::now(), p.values()) {
                                Ok(()) => wrote = true,
                                Err(e) => spell.failed(&mut writer, &e),
                            }
                        }
                        Err(mpsc::TryRecvError::Empty) => break,
                        Err(mpsc::TryRecvError::Disconnected) => {
                            open = false;
                            break;
                        }
                    }
                }
                if flushed.elapsed() >= FLUSH_EVERY || !open {
                    match writer.flush() {
                        // only a flush proves the rows reached the file
                        Ok(()) if wrote || spell.retry_at.is_none() => spell.succeeded(),
                        Ok(()) => {}
                        Err(e) => spell.failed(&mut writer, &e),
                    }
                    flushed = Instant::now();
                }
                // retention: when a new file was opened, and at least every PRUNE_EVERY for keep_days
                let current = writer.current_path().map(Path::to_path_buf);
                let due = pruned.as_ref().is_none_or(|(at, path)| *path != current || at.elapsed() >= PRUNE_EVERY);
                if due && !retention.is_off() {
                    match prune(&dir, &name, current.as_deref(), retention) {
                        Ok(n) => {
                            shared.files_deleted.fetch_add(n, Ordering::Relaxed);
                        }
                        Err(e) => tracing::warn!(drive = %name, error = %e, "retention: cannot list the recordings"),
                    }
                    pruned = Some((Instant::now(), current));
                }
                if !open {
                    break;
                }
            }
            if let Err(e) = writer.close() {
                spell.failed(&mut writer, &e);
            }
        })?;
        Ok(Recorder { tx: Some(tx), thread: Some(thread), health })
    }

    pub fn record(&self, p: Point) {
        if let Some(tx) = &self.tx {
            let _ = tx.send(p);
        }
    }

    /// Writes everything sent so far, closes and syncs the file. Blocks until done.
    pub fn finish(mut self) {
        self.tx.take();
        if let Some(t) = self.thread.take()
            && t.join().is_err()
        {
            tracing::error!("the recording thread panicked");
        }
    }
}

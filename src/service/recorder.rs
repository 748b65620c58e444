//! Recording a drive's fresh samples to rotated CSV files on a thread of its own, so that file I/O never delays
//! the poll loop. Rows are flushed at least every 500 ms; [`Recorder::finish`] drains, closes and syncs the file.
//! A second thread keeps the directory: it compresses each closed file (`recording.compress`) and applies
//! retention, so that neither delays the rows; it alone deletes and compresses, so the two never meet on a file.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, mpsc};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crate::recording::{RotatingWriter, drive_file_key, gz};

use super::retention::{Retention, prune};
use super::state::{COLUMNS, Point, RecordingHealth};

/// How often buffered rows reach the file.
const FLUSH_EVERY: Duration = Duration::from_millis(500);
/// How often the writer thread takes the rows sent since its last turn.
const DRAIN_EVERY: Duration = Duration::from_millis(100);

/// Compression and retention run at each new file and at least this often (for `keep_days`, and to try again a
/// compression that failed).
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
    files_compressed: AtomicU64,
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
            files_compressed: self.files_compressed.load(Ordering::Relaxed),
        }
    }
}

/// The sending side; rows go to the writer thread.
pub struct Recorder {
    tx: Option<mpsc::Sender<Point>>,
    thread: Option<JoinHandle<()>>,
    keeper: Option<JoinHandle<()>>,
    pub health: Arc<Health>,
}

/// What the writer thread tells the keeper when its file changes: the file now open (None: none).
struct Opened(Option<PathBuf>);

/// The keeper thread's state: the open file (never touched), and closed files still to compress.
struct Keeper {
    dir: PathBuf,
    drive: String,
    compress: bool,
    retention: Retention,
    open: Option<PathBuf>,
    to_compress: Vec<PathBuf>,
    health: Arc<Health>,
}

impl Keeper {
    /// Compresses what is due (a failure is logged and tried again at the next turn), then applies retention.
    fn turn(&mut self) {
        let mut failed = Vec::new();
        for path in std::mem::take(&mut self.to_compress) {
            if !path.exists() {
                continue;
            }
            match gz::compress(&path) {
                Ok(gz) => {
                    tracing::info!(drive = %self.drive, file = %gz.display(), "compressed a closed recording");
                    self.health.files_compressed.fetch_add(1, Ordering::Relaxed);
                }
                Err(e) => {
                    tracing::warn!(drive = %self.drive, file = %path.display(), error = %e,
                        "cannot compress a closed recording; kept as it is, tried again later");
                    failed.push(path);
                }
            }
        }
        self.to_compress = failed;
        if !self.retention.is_off() {
            match prune(&self.dir, &self.drive, self.open.as_deref(), self.retention) {
                Ok(n) => {
                    self.health.files_deleted.fetch_add(n, Ordering::Relaxed);
                }
                Err(e) => tracing::warn!(drive = %self.drive, error = %e, "retention: cannot list the recordings"),
            }
        }
    }

    /// The file changed: the one that was open is closed, and compressed at this turn.
    fn opened(&mut self, now: Option<PathBuf>) {
        if let Some(closed) = std::mem::replace(&mut self.open, now)
            && self.compress
            && !self.to_compress.contains(&closed)
        {
            self.to_compress.push(closed);
        }
    }

    /// Runs until the writer thread has gone, then compresses its last file.
    fn run(mut self, rx: mpsc::Receiver<Opened>) {
        self.turn();
        loop {
            match rx.recv_timeout(PRUNE_EVERY) {
                Ok(Opened(now)) => {
                    self.opened(now);
                    // a burst of changes (rows abandoned on a full disk) makes one turn
                    while let Ok(Opened(now)) = rx.try_recv() {
                        self.opened(now);
                    }
                }
                Err(mpsc::RecvTimeoutError::Timeout) => {}
                Err(mpsc::RecvTimeoutError::Disconnected) => break,
            }
            self.turn();
        }
        self.opened(None);
        self.turn();
    }
}

/// What a recorder found of `drive` in `dir` from earlier runs: closed plain files (none of them is open: the
/// recorder has not started), and temporary files of a compression cut short, which are removed.
fn leftovers(dir: &Path, drive: &str) -> std::io::Result<Vec<PathBuf>> {
    let mut plain = Vec::new();
    for entry in std::fs::read_dir(dir)? {
        let entry = entry?;
        let name = entry.file_name().to_string_lossy().into_owned();
        if !entry.file_type().is_ok_and(|t| t.is_file()) {
            continue;
        }
        if gz::is_temp_of(&name, drive) {
            match std::fs::remove_file(entry.path()) {
                Ok(()) => tracing::info!(drive, file = %name, "removed a compression cut short"),
                Err(e) => tracing::warn!(drive, file = %name, error = %e, "cannot remove a compression cut short"),
            }
        } else if drive_file_key(&name, drive).is_some_and(|(_, compressed)| !compressed) {
            plain.push(entry.path());
        }
    }
    plain.sort();
    Ok(plain)
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

/// The lock file of a recordings directory.
pub const LOCK_FILE: &str = ".hydrolens.lock";

/// One writer per recordings directory: an exclusive lock on `<dir>/.hydrolens.lock`, held as long as the returned
/// file is open (the service keeps it for its lifetime; the OS drops it if the process dies), with the holder's pid
/// in it. A second instance gets a bad-input error naming the directory and that pid, before it touches any file.
pub fn lock_dir(dir: &Path) -> std::io::Result<std::fs::File> {
    use std::io::{Read, Seek, Write};
    std::fs::create_dir_all(dir)?;
    let path = dir.join(LOCK_FILE);
    let mut f = std::fs::OpenOptions::new().read(true).write(true).create(true).truncate(false).open(&path)?;
    match f.try_lock() {
        Ok(()) => {
            f.set_len(0)?;
            f.rewind()?;
            writeln!(f, "{}", std::process::id())?;
            f.sync_all()?;
            Ok(f)
        }
        Err(std::fs::TryLockError::WouldBlock) => {
            let mut holder = String::new();
            let _ = f.read_to_string(&mut holder);
            let holder = holder.trim();
            let holder = if holder.is_empty() { "unknown".to_string() } else { holder.to_string() };
            Err(std::io::Error::other(crate::error::BadInput(format!(
                "recording.dir {}: another hydrolens (pid {holder}) records there ({}); one writer per directory",
                dir.display(),
                path.display()
            ))))
        }
        Err(std::fs::TryLockError::Error(e)) => Err(e),
    }
}

impl Recorder {
    /// Starts writing `<dir>/<drive>-<unix ms>.csv` files, rotated after `rotate_after` or `max_bytes`; closed
    /// files are compressed to `.csv.gz` when `compress` (those of earlier runs too).
    pub fn start(
        dir: &Path,
        drive: &str,
        rotate_after: Duration,
        max_bytes: u64,
        retention: Retention,
        compress: bool,
    ) -> std::io::Result<Recorder> {
        std::fs::create_dir_all(dir)?;
        let found = leftovers(dir, drive)?;
        let mut writer = RotatingWriter::new(dir, drive, &COLUMNS, rotate_after, max_bytes);
        let (tx, rx) = mpsc::channel::<Point>();
        let (keeper_tx, keeper_rx) = mpsc::channel::<Opened>();
        let name = drive.to_string();
        let health = Arc::new(Health::default());
        let keeper = Keeper {
            dir: dir.to_path_buf(),
            drive: drive.to_string(),
            compress,
            retention,
            open: None,
            to_compress: if compress { found } else { Vec::new() },
            health: health.clone(),
        };
        let keeper = std::thread::Builder::new().name(format!("keep-{drive}")).spawn(move || keeper.run(keeper_rx))?;
        let shared = health.clone();
        let thread = std::thread::Builder::new().name(format!("rec-{drive}")).spawn(move || {
            let mut spell = Spell { name: &name, health: &shared, retry_at: None };
            // the thread drains the channel on its own clock rather than blocking in `recv`: a blocked receiver
            // would be woken by every row, a context switch per poll per drive (a tenth of a 50-drive service's CPU)
            let mut flushed = Instant::now();
            let mut told: Option<PathBuf> = None;
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
                // the keeper hears of each new file: the one before it is closed
                let current = writer.current_path().map(Path::to_path_buf);
                if current != told {
                    told.clone_from(&current);
                    let _ = keeper_tx.send(Opened(current));
                }
                if !open {
                    break;
                }
            }
            if let Err(e) = writer.close() {
                spell.failed(&mut writer, &e);
            }
            // dropping `keeper_tx` tells the keeper the last file is closed
        })?;
        Ok(Recorder { tx: Some(tx), thread: Some(thread), keeper: Some(keeper), health })
    }

    pub fn record(&self, p: Point) {
        if let Some(tx) = &self.tx {
            let _ = tx.send(p);
        }
    }

    /// Writes everything sent so far, closes and syncs the file, and compresses it. Blocks until done.
    pub fn finish(mut self) {
        self.tx.take();
        if let Some(t) = self.thread.take()
            && t.join().is_err()
        {
            tracing::error!("the recording thread panicked");
        }
        if let Some(t) = self.keeper.take()
            && t.join().is_err()
        {
            tracing::error!("the recordings keeper thread panicked");
        }
    }
}

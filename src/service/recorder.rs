//! Recording a drive's fresh samples to rotated CSV files on a thread of its own, so that file I/O never delays
//! the poll loop. Rows are flushed at least every 500 ms, and at each flush the open file is checked to be still
//! where it was (a file deleted while open would take every row with it until the next rotation);
//! [`Recorder::finish`] drains, closes and syncs the file. A second thread keeps the directory: it compresses each
//! closed file (`recording.compress`; one that holds no row is removed instead) and applies retention, so that
//! neither delays the rows; it alone deletes and compresses, so the two never meet on a file.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, mpsc};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crate::recording::{LostFile, RotatingWriter, drive_file_key, gz, holds_no_rows};

use super::retention::{Retention, WallClock, prune};
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
    files_lost: AtomicU64,
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
            files_lost: self.files_lost.load(Ordering::Relaxed),
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

/// What the writer thread tells the keeper of its files.
enum FileEvent {
    /// A file was opened: written to until it is closed, and never touched by the keeper meanwhile.
    Opened(PathBuf),
    /// A file was closed: compressed at the keeper's next turn. Every file closed is told, however many closed
    /// in one drain.
    Closed(PathBuf),
}

/// The keeper thread's state: the open file (never touched), and closed files still to compress.
struct Keeper {
    dir: PathBuf,
    drive: String,
    compress: bool,
    retention: Retention,
    /// Whether the wall clock can still age files (not once stepped while the service ran).
    clock: WallClock,
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
            // a file with no row (a full disk left it) is worth nothing, and an empty .csv.gz would be worse
            if holds_no_rows(&path).unwrap_or(false) {
                match std::fs::remove_file(&path) {
                    Ok(()) => tracing::info!(drive = %self.drive, file = %path.display(),
                        "removed a closed recording that holds no rows"),
                    Err(e) => tracing::warn!(drive = %self.drive, file = %path.display(), error = %e,
                        "cannot remove a closed recording that holds no rows"),
                }
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
            // the clock is judged only where files go for their age (its WARN says no age deletes)
            let ages_trusted = self.retention.keep.is_none() || self.clock.trusted();
            match prune(&self.dir, &self.drive, self.open.as_deref(), self.retention, ages_trusted) {
                Ok(n) => {
                    self.health.files_deleted.fetch_add(n, Ordering::Relaxed);
                }
                Err(e) => tracing::warn!(drive = %self.drive, error = %e, "retention: cannot list the recordings"),
            }
        }
    }

    fn heard(&mut self, event: FileEvent) {
        match event {
            FileEvent::Opened(path) => self.open = Some(path),
            FileEvent::Closed(path) => {
                if self.open.as_ref() == Some(&path) {
                    self.open = None;
                }
                if self.compress && !self.to_compress.contains(&path) {
                    self.to_compress.push(path);
                }
            }
        }
    }

    /// Runs until the writer thread has gone, then compresses its last file.
    fn run(mut self, rx: mpsc::Receiver<FileEvent>) {
        self.turn();
        loop {
            match rx.recv_timeout(PRUNE_EVERY) {
                Ok(event) => {
                    self.heard(event);
                    // a burst of changes (rotations in one drain, rows abandoned on a full disk) makes one turn
                    while let Ok(event) = rx.try_recv() {
                        self.heard(event);
                    }
                }
                Err(mpsc::RecvTimeoutError::Timeout) => {}
                Err(mpsc::RecvTimeoutError::Disconnected) => break,
            }
            self.turn();
        }
        // a writer that went without closing its file (it panicked; dropping it closed the file)
        if let Some(open) = self.open.take() {
            self.heard(FileEvent::Closed(open));
        }
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

    /// The open file was lost (deleted, its directory removed, or replaced): told once, its rows counted as lost.
    fn lost(&mut self, lost: &LostFile) {
        let how = if lost.replaced { "was replaced by another file" } else { "was deleted (or its directory removed)" };
        let message = format!(
            "recording file {} {how} while open: the {} row(s) written to it are lost; recording goes on in a new file",
            lost.path.display(),
            lost.rows
        );
        tracing::warn!(drive = %self.name, file = %lost.path.display(), rows_lost = lost.rows, "{message}");
        self.health.files_lost.fetch_add(1, Ordering::Relaxed);
        self.health.rows_lost.fetch_add(lost.rows, Ordering::Relaxed);
        if let Ok(mut last) = self.health.last_error.lock() {
            *last = Some(message);
        }
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

/// One writer per recordings directory: an exclusive lock on the directory itself, held as long as the returned
/// [`Held`] lives (the service keeps it for its lifetime; the OS drops it if the process dies), and the holder's pid
/// in `<dir>/.hydrolens.lock`. A second instance gets a bad-input error naming the directory and that pid, before it
/// touches any file. The lock was on the pid file: once that was deleted (by hand, by a cron job clearing old
/// files), a second instance took the directory, compressed the first one's open recording and both wrote there.
/// The pid is a courtesy: a full disk that refuses it is logged, and the lock holds without it.
pub fn lock_dir(dir: &Path) -> std::io::Result<Held> {
    // a directory the service may not make or write in (permissions, a read-only or virtual file system) is the
    // config's to fix: said naming the key and the path
    let named = |what: &str, path: &Path, e: std::io::Error| {
        use std::io::ErrorKind as K;
        let fixable = matches!(
            e.kind(),
            K::PermissionDenied | K::NotFound | K::NotADirectory | K::ReadOnlyFilesystem | K::AlreadyExists
        );
        if !fixable {
            return e;
        }
        std::io::Error::other(crate::error::BadInput(format!(
            "recording.dir {}: cannot {what} {}: {e}",
            dir.display(),
            path.display()
        )))
    };
    std::fs::create_dir_all(dir).map_err(|e| named("make the directory", dir, e))?;
    let locked = std::fs::File::open(dir).map_err(|e| named("open the directory", dir, e))?;
    let path = dir.join(LOCK_FILE);
    match locked.try_lock() {
        Ok(()) => {
            let note = write_pid(&path).map_err(|e| named("write its lock file", &path, e))?;
            Ok(Held { dir: locked, note })
        }
        Err(std::fs::TryLockError::WouldBlock) => {
            let holder = std::fs::read_to_string(&path).unwrap_or_default();
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

/// A recordings directory's lock ([`lock_dir`]): the directory, locked, and the file that says who holds it.
#[derive(Debug)]
pub struct Held {
    dir: std::fs::File,
    note: std::fs::File,
}

/// Writes this process's pid into the lock file at `path` (made if missing); a write that fails is logged.
fn write_pid(path: &Path) -> std::io::Result<std::fs::File> {
    use std::io::{Seek, Write};
    let mut f = std::fs::OpenOptions::new().read(true).write(true).create(true).truncate(false).open(path)?;
    let pid = f.set_len(0).and_then(|()| f.rewind()).and_then(|()| writeln!(f, "{}", std::process::id()));
    if let Err(e) = pid.and_then(|()| f.sync_all()) {
        tracing::warn!(file = %path.display(), error = %e,
            "cannot write the pid to the recordings directory's lock file; the lock holds without it");
    }
    Ok(f)
}

/// The recordings directory's lock ([`lock_dir`]) as the service holds it: taken again when the directory is no
/// longer the one held (removed and made again), and its pid file written again when that was deleted, so that a
/// second instance is still refused, naming this one.
#[derive(Debug)]
pub struct DirLock {
    dir: PathBuf,
    held: Mutex<Held>,
}

impl DirLock {
    pub fn take(dir: &Path) -> std::io::Result<DirLock> {
        Ok(DirLock { dir: dir.to_path_buf(), held: Mutex::new(lock_dir(dir)?) })
    }

    /// Takes the lock again (making the directory again) if `dir` is not the directory held; writes the pid file
    /// again if it is not the one written.
    pub fn keep(&self) {
        use std::os::unix::fs::MetadataExt;
        let mut held = self.held.lock().unwrap_or_else(|e| e.into_inner());
        let same = |path: &Path, file: &std::fs::File| match (std::fs::metadata(path), file.metadata()) {
            (Ok(a), Ok(b)) => a.dev() == b.dev() && a.ino() == b.ino(),
            _ => false,
        };
        if !same(&self.dir, &held.dir) {
            match lock_dir(&self.dir) {
                Ok(h) => {
                    *held = h;
                    tracing::warn!(dir = %self.dir.display(), "the recordings directory was gone: made and locked again");
                }
                Err(e) => tracing::error!(dir = %self.dir.display(), error = %e,
                    "the recordings directory was gone and cannot be locked again"),
            }
            return;
        }
        let path = self.dir.join(LOCK_FILE);
        if !same(&path, &held.note) {
            match write_pid(&path) {
                Ok(f) => {
                    held.note = f;
                    tracing::warn!(dir = %self.dir.display(),
                        "the recordings directory's lock file was gone: written again (the directory stays locked)");
                }
                Err(e) => tracing::warn!(dir = %self.dir.display(), error = %e,
                    "the recordings directory's lock file was gone and cannot be written again (the directory \
                     stays locked)"),
            }
        }
    }
}

/// The recorder thread: every [`DRAIN_EVERY`] writes the rows waiting in `rx`, flushes every [`FLUSH_EVERY`] (and
/// at the end), tells the keeper of each file it closes and opens, and when `rx` closes closes the last file.
fn write_rows(
    name: &str,
    health: &Health,
    mut writer: RotatingWriter,
    rx: &mpsc::Receiver<Point>,
    keeper_tx: &mpsc::Sender<FileEvent>,
    lock: Option<&DirLock>,
) {
    let mut spell = Spell { name, health, retry_at: None };
    // the thread drains the channel on its own clock rather than blocking in `recv`: a blocked receiver
    // would be woken by every row, a context switch per poll per drive (a tenth of a 50-drive service's CPU)
    let mut flushed = Instant::now();
    let mut told: Option<PathBuf> = None;
    let tell_closed = |writer: &mut RotatingWriter| {
        for path in writer.take_closed() {
            let _ = keeper_tx.send(FileEvent::Closed(path));
        }
    };
    loop {
        std::thread::sleep(DRAIN_EVERY);
        let (open, wrote) = drain(rx, &mut writer, &mut spell);
        if flushed.elapsed() >= FLUSH_EVERY || !open {
            match writer.flush() {
                // only a flush proves the rows reached the file
                Ok(()) if wrote || spell.retry_at.is_none() => spell.succeeded(),
                Ok(()) => {}
                Err(e) => spell.failed(&mut writer, &e),
            }
            if let Some(lost) = writer.give_up_if_lost() {
                spell.lost(&lost);
                // the directory may have gone with it: the next row makes it again, and the lock is kept
                if let Some(l) = lock {
                    let _ = std::fs::create_dir_all(&l.dir);
                    l.keep();
                }
            }
            flushed = Instant::now();
        }
        // the keeper hears of each file closed, then of the one open now
        tell_closed(&mut writer);
        let current = writer.current_path().map(Path::to_path_buf);
        if current != told {
            told.clone_from(&current);
            if let Some(path) = current {
                let _ = keeper_tx.send(FileEvent::Opened(path));
            }
        }
        if !open {
            break;
        }
    }
    if let Err(e) = writer.close() {
        spell.failed(&mut writer, &e);
    }
    tell_closed(&mut writer);
}

/// Writes the rows waiting in `rx` (none while a failure's retry is not due): whether `rx` is still open, and
/// whether a row was written.
fn drain(rx: &mpsc::Receiver<Point>, writer: &mut RotatingWriter, spell: &mut Spell<'_>) -> (bool, bool) {
    let mut wrote = false;
    loop {
        match rx.try_recv() {
            Ok(p) => {
                if spell.waiting() {
                    continue;
                }
                match writer.write_row(Instant::now(), p.values()) {
                    Ok(()) => wrote = true,
                    Err(e) => spell.failed(writer, &e),
                }
            }
            Err(mpsc::TryRecvError::Empty) => return (true, wrote),
            Err(mpsc::TryRecvError::Disconnected) => return (false, wrote),
        }
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
        lock: Option<Arc<DirLock>>,
    ) -> std::io::Result<Recorder> {
        std::fs::create_dir_all(dir)?;
        let found = leftovers(dir, drive)?;
        let writer = RotatingWriter::new(dir, drive, &COLUMNS, rotate_after, max_bytes);
        let (tx, rx) = mpsc::channel::<Point>();
        let (keeper_tx, keeper_rx) = mpsc::channel::<FileEvent>();
        let name = drive.to_string();
        let health = Arc::new(Health::default());
        let keeper = Keeper {
            dir: dir.to_path_buf(),
            drive: drive.to_string(),
            compress,
            retention,
            clock: WallClock::default(),
            open: None,
            to_compress: if compress { found } else { Vec::new() },
            health: health.clone(),
        };
        let keeper = std::thread::Builder::new().name(format!("keep-{drive}")).spawn(move || keeper.run(keeper_rx))?;
        let shared = health.clone();
        let thread = std::thread::Builder::new()
            .name(format!("rec-{drive}"))
            .spawn(move || write_rows(&name, &shared, writer, &rx, &keeper_tx, lock.as_deref()))?;
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::Estimate;
    use crate::output::file_names;
    use crate::service::state::Measured;

    fn point(t_s: f64) -> Point {
        let estimate = Estimate {
            omega_hat_rad_s: 1.0,
            load_hat_nm: 2.0,
            inertia_hat_kg_m2: 3.0,
            viscous_hat_nm_s_rad: 4.0,
            inertia_sd_kg_m2: 5.0,
            viscous_sd_nm_s_rad: 6.0,
            inertia_identified: 1.0,
            viscous_identified: 1.0,
            load_character: 1.0,
        };
        let sample = Measured {
            t_s,
            f_set_hz: 1.0,
            f_drive_hz: 1.0,
            p_in_bar: 8.0,
            p_out_bar: 2.0,
            omega_rad_s: 10.0,
            drive_power_w: f64::NAN,
        };
        Point { sample, estimate, status_word: 3, target_omega_rad_s: f64::NAN }
    }

    /// The drive's plain files in `dir` that hold rows.
    fn with_rows(dir: &Path) -> Vec<PathBuf> {
        let Ok(entries) = std::fs::read_dir(dir) else { return Vec::new() };
        let mut files: Vec<PathBuf> = entries
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|x| x == "csv") && holds_no_rows(p).is_ok_and(|none| !none))
            .collect();
        files.sort();
        files
    }

    /// Sends a row every 5 ms until `done` holds (true) or 10 s pass (false).
    fn record_until(rec: &Recorder, t: &mut f64, mut done: impl FnMut() -> bool) -> bool {
        let deadline = Instant::now() + Duration::from_secs(10);
        while Instant::now() < deadline {
            rec.record(point(*t));
            *t += 0.005;
            if done() {
                return true;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        false
    }

    #[test]
    fn a_recording_deleted_while_open_or_its_directory_removed_is_counted_and_a_new_file_started() {
        let tmp = tempfile::tempdir().expect("tmp");
        let dir = tmp.path().join("rec");
        let rec = Recorder::start(&dir, "pump1", Duration::from_secs(3600), 1 << 30, Retention::default(), false, None)
            .expect("starts");
        let mut t = 0.0;
        assert!(record_until(&rec, &mut t, || !with_rows(&dir).is_empty()), "rows reach a file");
        let first = with_rows(&dir).remove(0);
        std::fs::remove_file(&first).expect("rm");
        assert!(record_until(&rec, &mut t, || rec.health.snapshot().files_lost == 1), "the loss is noticed");
        let h = rec.health.snapshot();
        assert!(h.rows_lost > 0, "{h:?}");
        let name = first.file_name().expect("name").to_string_lossy().into_owned();
        assert!(h.last_error.as_deref().is_some_and(|e| e.contains(&name) && e.contains("deleted")), "{h:?}");
        assert!(h.ok && h.errors == 0, "a lost file is no write failure: {h:?}");
        assert!(record_until(&rec, &mut t, || !with_rows(&dir).is_empty()), "a new file is started and takes rows");

        let lost_before = rec.health.snapshot().rows_lost;
        std::fs::remove_dir_all(&dir).expect("rm -r");
        assert!(record_until(&rec, &mut t, || rec.health.snapshot().files_lost == 2), "the loss is noticed");
        assert!(rec.health.snapshot().rows_lost > lost_before);
        assert!(record_until(&rec, &mut t, || !with_rows(&dir).is_empty()), "the directory is made again");
        rec.finish();
        let files = with_rows(&dir);
        assert_eq!(files.len(), 1, "{files:?}");
        crate::recording::load(&files[0]).expect("a valid recording");
    }

    /// Rows that come faster than the writer drains them (its thread starved) fill several files in one drain: each
    /// file closed is compressed, not only the last (the middle ones were once left plain for good).
    #[test]
    fn every_closed_file_is_compressed_however_many_close_in_one_drain() {
        let dir = tempfile::tempdir().expect("tmp");
        let rec =
            Recorder::start(dir.path(), "pump1", Duration::from_secs(3600), 2_000, Retention::default(), true, None)
                .expect("starts");
        // all sent long before the writer's first drain: a drain of many rotations
        for i in 0..400 {
            rec.record(point(f64::from(i) * 1e-3));
        }
        rec.finish();
        let names = file_names(dir.path());
        assert!(names.len() > 3, "several files: {names:?}");
        assert!(names.iter().all(|n| n.ends_with(".csv.gz")), "every closed file compressed: {names:?}");
        let rows: usize = names.iter().map(|n| crate::recording::load(&dir.path().join(n)).expect("loads").len()).sum();
        assert_eq!(rows, 400, "every row kept");
    }

    #[test]
    fn the_keeper_removes_closed_files_that_hold_no_rows_instead_of_compressing_them() {
        let dir = tempfile::tempdir().expect("tmp");
        let empty = dir.path().join("pump1-1.csv");
        let header = dir.path().join("pump1-2.csv");
        let good = dir.path().join("pump1-3.csv");
        std::fs::write(&empty, "").expect("write");
        std::fs::write(&header, format!("{}\n", COLUMNS.join(","))).expect("write");
        std::fs::write(&good, "t_s,omega_rad_s\n0,1\n").expect("write");
        let mut keeper = Keeper {
            dir: dir.path().to_path_buf(),
            drive: "pump1".into(),
            compress: true,
            retention: Retention::default(),
            clock: WallClock::default(),
            open: None,
            to_compress: vec![empty.clone(), header.clone(), good.clone()],
            health: Arc::new(Health::default()),
        };
        keeper.turn();
        let names = file_names(dir.path());
        assert_eq!(names, vec!["pump1-3.csv.gz"], "the empty and header-only files are removed, not compressed");
        assert_eq!(keeper.health.snapshot().files_compressed, 1);
    }

    /// The lock is on the directory: with its pid file deleted (a cron job clearing old files) a second instance is
    /// still refused, and the holder writes the file again. On the file, a second instance took the directory and
    /// compressed the first one's open recording.
    #[test]
    fn the_directory_stays_locked_when_its_lock_file_is_deleted() {
        let dir = tempfile::tempdir().expect("tmp");
        let lock = DirLock::take(dir.path()).expect("the first takes it");
        let pid_file = dir.path().join(LOCK_FILE);
        std::fs::remove_file(&pid_file).expect("rm");
        let e = lock_dir(dir.path()).expect_err("a second is refused").to_string();
        assert!(e.contains("another hydrolens") && e.contains("pid unknown"), "{e}");
        lock.keep();
        let pid = std::process::id().to_string();
        assert_eq!(std::fs::read_to_string(&pid_file).expect("written again").trim(), pid);
        let e = lock_dir(dir.path()).expect_err("still refused").to_string();
        assert!(e.contains(&format!("pid {pid}")), "{e}");
        drop(lock);
        lock_dir(dir.path()).expect("free once the holder is gone");
    }
}

//! Retention of a drive's recordings (plain and compressed alike, each counted at its size on disk): the oldest
//! closed files go first, when they are older than
//! `recording.keep_days` or while the drive's files together exceed its share of `recording.max_total_mb`; the open
//! file never goes. [`expired`] is the pure choice, [`prune`] lists the directory and deletes.
//!
//! Ages come from the wall clock, which a cabinet PC can have wrong: booted at 1970 before NTP set it, or stepped
//! by hand. A file dated before [`PLAUSIBLE_SINCE`] has no known age, and once the wall clock has stepped while the
//! service ran ([`WallClock`]) no age is trusted until the next start: such files go only under the size budget, so
//! a clock set right (or wrong) never deletes the history at once.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant, SystemTime};

/// No recording is dated earlier (2024-01-01 UTC): a file that is was written while the clock was not yet set, and
/// its age is unknown.
pub const PLAUSIBLE_SINCE: Duration = Duration::from_secs(1_704_067_200);
/// The wall clock moved this much more (or less) than the monotonic clock since the start: it was stepped.
const CLOCK_STEP: Duration = Duration::from_secs(3600);

/// Whether the wall clock can age files: not once it has been stepped (by NTP after a boot at 1970, or by hand)
/// since the service started, as the monotonic clock tells; said once at WARN.
#[derive(Debug, Clone)]
pub struct WallClock {
    wall: SystemTime,
    mono: Instant,
    stepped: bool,
}

impl Default for WallClock {
    fn default() -> Self {
        WallClock { wall: SystemTime::now(), mono: Instant::now(), stepped: false }
    }
}

impl WallClock {
    /// Whether the wall clock still moves with the monotonic one, now.
    pub fn trusted(&mut self) -> bool {
        self.trusted_at(SystemTime::now(), Instant::now())
    }

    fn trusted_at(&mut self, wall: SystemTime, mono: Instant) -> bool {
        if !self.stepped {
            let ran = mono.saturating_duration_since(self.mono);
            let moved = wall.duration_since(self.wall).map_err(|e| e.duration());
            let step = match moved {
                Ok(ahead) => ahead.abs_diff(ran),
                Err(behind) => behind + ran,
            };
            if step > CLOCK_STEP {
                self.stepped = true;
                tracing::warn!(
                    step_s = step.as_secs(),
                    "retention: the wall clock was stepped while the service ran; no recording is deleted for its age \
                     until the next start (the size budget still applies)"
                );
            }
        }
        !self.stepped
    }
}

/// What bounds a drive's recordings; None: unbounded.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Retention {
    pub max_bytes: Option<u64>,
    pub keep: Option<Duration>,
}

impl Retention {
    pub fn is_off(&self) -> bool {
        self.max_bytes.is_none() && self.keep.is_none()
    }
}

/// A recording file of the drive: its path, size and last modification.
#[derive(Debug, Clone, PartialEq)]
pub struct FileInfo {
    pub path: PathBuf,
    pub bytes: u64,
    pub modified: SystemTime,
}

/// The files to delete, oldest first. `files` are the drive's; `open` is never chosen, but its size counts.
pub fn expired(mut files: Vec<FileInfo>, open: Option<&Path>, rule: Retention, now: SystemTime) -> Vec<PathBuf> {
    files.sort_by(|a, b| a.modified.cmp(&b.modified).then_with(|| a.path.cmp(&b.path)));
    let mut total: u64 = files.iter().map(|f| f.bytes).sum();
    let mut out = Vec::new();
    let dated = |f: &FileInfo| f.modified >= SystemTime::UNIX_EPOCH + PLAUSIBLE_SINCE;
    for f in files.iter().filter(|f| Some(f.path.as_path()) != open) {
        let too_old = rule.keep.is_some_and(|k| dated(f) && now.duration_since(f.modified).is_ok_and(|age| age > k));
        let too_much = rule.max_bytes.is_some_and(|m| total > m);
        if too_old || too_much {
            total -= f.bytes;
            out.push(f.path.clone());
        }
    }
    out
}

/// Whether `name` is one of `drive`'s recording files: `<drive>-<digits>[-<digits>].csv[.gz]`.
fn is_drive_file(name: &str, drive: &str) -> bool {
    crate::recording::drive_file_key(name, drive).is_some()
}

/// Deletes what [`expired`] chooses among `drive`'s files in `dir`; returns how many went. Each deletion is logged.
/// Without `ages_trusted` (the wall clock was stepped) only the size budget deletes.
pub fn prune(
    dir: &Path,
    drive: &str,
    open: Option<&Path>,
    rule: Retention,
    ages_trusted: bool,
) -> std::io::Result<u64> {
    let rule = if ages_trusted { rule } else { Retention { keep: None, ..rule } };
    if rule.is_off() {
        return Ok(0);
    }
    let mut files = Vec::new();
    for entry in std::fs::read_dir(dir)? {
        let entry = entry?;
        let name = entry.file_name();
        if !name.to_str().is_some_and(|n| is_drive_file(n, drive)) {
            continue;
        }
        let Ok(meta) = entry.metadata() else { continue };
        if meta.is_file() {
            files.push(FileInfo { path: entry.path(), bytes: meta.len(), modified: meta.modified()? });
        }
    }
    let mut deleted = 0;
    for path in expired(files, open, rule, SystemTime::now()) {
        match std::fs::remove_file(&path) {
            Ok(()) => {
                tracing::info!(drive, file = %path.display(), "retention: deleted an old recording");
                deleted += 1;
            }
            Err(e) => tracing::warn!(drive, file = %path.display(), error = %e, "retention: cannot delete"),
        }
    }
    Ok(deleted)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn file(name: &str, bytes: u64, age_s: u64, now: SystemTime) -> FileInfo {
        FileInfo { path: PathBuf::from(name), bytes, modified: now - Duration::from_secs(age_s) }
    }

    #[test]
    fn oldest_closed_files_go_first_and_never_the_open_one() {
        let now = SystemTime::now();
        let files = vec![file("c", 10, 10, now), file("a", 10, 30, now), file("b", 10, 20, now), file("d", 10, 0, now)];
        let rule = Retention { max_bytes: Some(25), keep: None };
        assert_eq!(expired(files.clone(), Some(Path::new("d")), rule, now), [PathBuf::from("a"), PathBuf::from("b")]);
        // the open file is kept even when it alone is over the budget
        let rule = Retention { max_bytes: Some(5), keep: None };
        assert_eq!(expired(files.clone(), Some(Path::new("a")), rule, now).len(), 3);
        let rule = Retention { max_bytes: None, keep: Some(Duration::from_secs(15)) };
        assert_eq!(expired(files, Some(Path::new("d")), rule, now), [PathBuf::from("a"), PathBuf::from("b")]);
    }

    #[test]
    fn a_file_dated_before_the_clock_was_set_goes_only_under_the_size_budget() {
        let now = SystemTime::now();
        let booted = FileInfo {
            path: PathBuf::from("a"),
            bytes: 10,
            modified: SystemTime::UNIX_EPOCH + Duration::from_secs(600),
        };
        let files = vec![booted, file("b", 10, 3 * 86_400, now), file("c", 10, 0, now)];
        let rule = Retention { max_bytes: None, keep: Some(Duration::from_secs(86_400)) };
        assert_eq!(expired(files.clone(), Some(Path::new("c")), rule, now), [PathBuf::from("b")]);
        let rule = Retention { max_bytes: Some(15), keep: Some(Duration::from_secs(86_400)) };
        assert_eq!(expired(files, Some(Path::new("c")), rule, now), [PathBuf::from("a"), PathBuf::from("b")]);
    }

    #[test]
    fn a_wall_clock_stepped_while_running_ages_no_file_until_the_next_start() {
        let (wall, mono) = (SystemTime::now(), Instant::now());
        let at = |w: i64, m: u64| {
            let w = if w >= 0 { wall + Duration::from_secs(w as u64) } else { wall - Duration::from_secs((-w) as u64) };
            (w, mono + Duration::from_secs(m))
        };
        let mut clock = WallClock { wall, mono, stepped: false };
        // drift within the hour (NTP slewing, a slow RTC) is no step
        for (w, m) in [(600, 600), (86_400 + 1200, 86_400), (86_400, 86_400 + 1200)] {
            let (w, m) = at(w, m);
            assert!(clock.trusted_at(w, m));
        }
        // a step forward (a boot at 1970 set by NTP: decades) and it stays untrusted, even if the clock comes back
        let (w, m) = at(20 * 365 * 86_400, 90_000);
        assert!(!clock.trusted_at(w, m));
        let (w, m) = at(90_000, 90_000);
        assert!(!clock.trusted_at(w, m));
        // a step backwards likewise
        let mut clock = WallClock { wall, mono, stepped: false };
        let (w, m) = at(-7200, 60);
        assert!(!clock.trusted_at(w, m));
    }

    #[test]
    fn prune_with_a_stepped_clock_deletes_only_for_size() {
        let dir = tempfile::tempdir().expect("tempdir");
        let old = SystemTime::now() - Duration::from_secs(10 * 86_400);
        for name in ["p-1.csv", "p-2.csv"] {
            let f = std::fs::File::create(dir.path().join(name)).expect("create");
            std::io::Write::write_all(&mut &f, b"t_s\n1\n").expect("write");
            f.set_modified(old).expect("set mtime");
        }
        let rule = Retention { max_bytes: None, keep: Some(Duration::from_secs(86_400)) };
        assert_eq!(prune(dir.path(), "p", None, rule, false).expect("prune"), 0);
        assert_eq!(prune(dir.path(), "p", None, rule, true).expect("prune"), 2);
    }

    #[test]
    fn only_the_drives_own_files() {
        assert!(is_drive_file("pump1-1700000000000.csv", "pump1"));
        assert!(is_drive_file("pump1-1700000000000-2.csv", "pump1"));
        assert!(is_drive_file("pump1-1700000000000-2.csv.gz", "pump1"));
        for other in [
            "pump1-b-1700000000000.csv",
            "pump12-1.csv",
            "pump1-.csv",
            "pump1-1.txt",
            "x.csv",
            ".pump1-1.csv.gz.tmp",
            "pump1-1.gz",
        ] {
            assert!(!is_drive_file(other, "pump1"), "{other}");
        }
    }
}

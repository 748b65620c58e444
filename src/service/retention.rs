//! Retention of a drive's recordings (plain and compressed alike, each counted at its size on disk): the oldest
//! closed files go first, when they are older than
//! `recording.keep_days` or while the drive's files together exceed its share of `recording.max_total_mb`; the open
//! file never goes. [`expired`] is the pure choice, [`prune`] lists the directory and deletes.

use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

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
    for f in files.iter().filter(|f| Some(f.path.as_path()) != open) {
        let too_old = rule.keep.is_some_and(|k| now.duration_since(f.modified).is_ok_and(|age| age > k));
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
pub fn prune(dir: &Path, drive: &str, open: Option<&Path>, rule: Retention) -> std::io::Result<u64> {
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

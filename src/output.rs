//! The files a command writes: checked before any work, written beside their final path and renamed into place.
//!
//! [`check`] refuses an output that is one of the run's inputs (the same file by path or by device and inode),
//! that another output also names, that is a directory, or whose directory is missing or not writable: bad input,
//! naming the flag and the path. [`Replacement`] writes `.NAME.PID.tmp` beside `NAME` and renames it over `NAME`
//! on [`Replacement::commit`], so a run that fails leaves the old file as it was; it removes its temporary file
//! when dropped uncommitted, and on creation the temporaries of `NAME` left by killed runs (whose process is gone).
//! A path that is there and is not a regular file (`/dev/null`, a pipe, a symbolic link such as `/dev/stdout`) is
//! written directly.

use std::ffi::OsString;
use std::fs::File;
use std::path::{Path, PathBuf};

use crate::error::BadInput;

/// `-`, as an output, is the standard output (the commands' messages go to the standard error).
pub fn dash_is_stdout(path: std::path::PathBuf) -> std::path::PathBuf {
    if path.as_os_str() == "-" { PathBuf::from("/dev/stdout") } else { path }
}

/// Checks the outputs of a run (`(flag, path)`) against its inputs and each other; see the module's doc.
pub fn check(inputs: &[&Path], outputs: &[(&str, &Path)]) -> Result<(), BadInput> {
    let bad = |flag: &str, path: &Path, what: String| Err(BadInput(format!("{flag} {}: {what}", path.display())));
    for (i, &(flag, path)) in outputs.iter().enumerate() {
        if path.file_name().is_none() {
            return bad(flag, path, "names no file".into());
        }
        // `out/`: Path drops the trailing separator, and the file would be `out`, which the user meant as a directory
        if path.as_os_str().as_encoded_bytes().ends_with(b"/") {
            return bad(flag, path, "ends in '/': name a file, not a directory".into());
        }
        if path.is_dir() {
            return bad(flag, path, "is a directory; name a file".into());
        }
        let dir = parent(path);
        if !dir.is_dir() {
            return bad(flag, path, format!("its directory {} does not exist", dir.display()));
        }
        // a link to nowhere: the file is written where it points
        if let Ok(target) = std::fs::read_link(path)
            && !path.exists()
        {
            let target = dir.join(target);
            if !parent(&target).is_dir() {
                return bad(flag, path, format!("links to {}, whose directory does not exist", target.display()));
            }
        }
        if let Some(input) = inputs.iter().find(|input| same_file(path, input)) {
            return bad(flag, path, format!("is an input of this run ({}); name another file", input.display()));
        }
        if let Some(&(other, _)) = outputs[..i].iter().find(|(_, o)| !written_in_place(path) && same_file(path, o)) {
            return bad(flag, path, format!("{other} names the same file; give each output its own"));
        }
        if !written_in_place(path) && !writable(&dir) {
            return bad(flag, path, format!("its directory {} is not writable", dir.display()));
        }
    }
    Ok(())
}

/// The directory `path` goes in (`.` for a bare file name).
fn parent(path: &Path) -> PathBuf {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

/// Where `path` is, with every symbolic link resolved (the file's own, if it is there; else its directory's).
fn resolved(path: &Path) -> Option<PathBuf> {
    std::fs::canonicalize(path).ok().or_else(|| Some(std::fs::canonicalize(parent(path)).ok()?.join(path.file_name()?)))
}

/// Whether `a` and `b` are one file: one resolved path, or (both there) one device and inode (hard links).
fn same_file(a: &Path, b: &Path) -> bool {
    if resolved(a).is_some_and(|r| Some(r) == resolved(b)) {
        return true;
    }
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        if let (Ok(x), Ok(y)) = (std::fs::metadata(a), std::fs::metadata(b)) {
            return x.dev() == y.dev() && x.ino() == y.ino();
        }
    }
    false
}

/// The most this process may write to one file at `path`: the room left on its disk for an unprivileged writer, and
/// the file-size limit (`ulimit -f`), where the system says.
/// None for an output written in place (a pipe, `/dev/null`, `/dev/stdout`): its room is not the room of the disk
/// its name is on (in a container `/dev` is a tmpfs of 64 MB, and `simulate --out /dev/null` was refused by it).
#[cfg(target_os = "linux")]
pub fn free_bytes(path: &Path) -> Option<u64> {
    if written_in_place(path) {
        return None;
    }
    let disk = rustix::fs::statvfs(parent(path)).ok().and_then(|s| s.f_bavail.checked_mul(s.f_frsize));
    let limit = rustix::process::getrlimit(rustix::process::Resource::Fsize).current;
    match (disk, limit) {
        (Some(d), Some(l)) => Some(d.min(l)),
        (d, l) => d.or(l),
    }
}

#[cfg(not(target_os = "linux"))]
pub fn free_bytes(_path: &Path) -> Option<u64> {
    None
}

#[cfg(target_os = "linux")]
fn writable(dir: &Path) -> bool {
    use rustix::fs::{Access, access};
    access(dir, Access::WRITE_OK | Access::EXEC_OK).is_ok()
}

#[cfg(not(target_os = "linux"))]
fn writable(dir: &Path) -> bool {
    !std::fs::metadata(dir).is_ok_and(|m| m.permissions().readonly())
}

/// Whether `out` is written directly rather than through a temporary file renamed over it: anything that is there
/// and is not a regular file (renaming over `/dev/stdout`, a symbolic link, would replace the link).
pub fn written_in_place(out: &Path) -> bool {
    std::fs::symlink_metadata(out).is_ok_and(|m| !m.is_file())
}

/// An output under construction; see the module's doc.
#[derive(Debug)]
pub struct Replacement {
    file: File,
    /// The temporary file, or `None` when writing directly to `path` or once renamed.
    temp: Option<PathBuf>,
    path: PathBuf,
}

/// The temporary files of this process's uncommitted [`Replacement`]s: what [`remove_temporaries`] removes when a
/// signal ends the process, which runs no `Drop`.
static LIVE: std::sync::Mutex<Vec<PathBuf>> = std::sync::Mutex::new(Vec::new());

fn live() -> std::sync::MutexGuard<'static, Vec<PathBuf>> {
    LIVE.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// Removes the temporary files of every uncommitted [`Replacement`]: for a signal handler, before the process exits
/// (a `simulate` stopped by Ctrl-C left its 20 MB `.NAME.PID.tmp` until the next run into that path).
pub fn remove_temporaries() {
    for temp in live().drain(..) {
        let _ = std::fs::remove_file(temp);
    }
}

impl Replacement {
    /// Removes the stale temporaries of `path` and creates this run's.
    pub fn create(path: &Path) -> std::io::Result<Replacement> {
        let temp = match path.file_name() {
            Some(name) if !written_in_place(path) => {
                remove_stale_temporaries(path, name);
                Some(path.with_file_name(temp_name(name, std::process::id())))
            }
            _ => None,
        };
        // registered before it exists: a signal between the two leaves nothing behind
        if let Some(temp) = &temp {
            live().push(temp.clone());
        }
        let file = File::create(temp.as_deref().unwrap_or(path)).inspect_err(|_| Replacement::forget(&temp))?;
        Ok(Replacement { file, temp, path: path.to_path_buf() })
    }

    /// Takes `temp` off the files a signal removes.
    fn forget(temp: &Option<PathBuf>) {
        if let Some(temp) = temp {
            live().retain(|t| t != temp);
        }
    }

    /// The file being written.
    pub fn file(&mut self) -> &mut File {
        &mut self.file
    }

    /// Renames the temporary file over the final path.
    pub fn commit(mut self) -> std::io::Result<()> {
        if let Some(temp) = &self.temp {
            std::fs::rename(temp, &self.path)?;
        }
        Replacement::forget(&self.temp.take());
        Ok(())
    }
}

impl Drop for Replacement {
    /// Removes the temporary file unless it was renamed into place: on an error, and on a panic.
    fn drop(&mut self) {
        if let Some(temp) = self.temp.take() {
            let _ = std::fs::remove_file(&temp);
            Replacement::forget(&Some(temp));
        }
    }
}

/// Whether creating an output failed for its path (missing, not writable, read-only, not a directory where one is
/// needed): the user's to fix, exit 2. [`check`] catches the ordinary cases first; `/proc/x.csv` or a read-only mount
/// get past it and exited 1.
pub fn path_refused(e: &std::io::Error) -> bool {
    use std::io::ErrorKind::{IsADirectory, NotADirectory, NotFound, PermissionDenied, ReadOnlyFilesystem};
    matches!(e.kind(), NotFound | PermissionDenied | ReadOnlyFilesystem | IsADirectory | NotADirectory)
}

/// Writes `bytes` to `path` through a [`Replacement`].
pub fn replace(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    use std::io::Write;
    let mut r = Replacement::create(path)?;
    r.file().write_all(bytes)?;
    r.commit()
}

fn temp_name(name: &std::ffi::OsStr, pid: u32) -> OsString {
    let mut temp = OsString::from(".");
    temp.push(name);
    temp.push(format!(".{pid}.tmp"));
    temp
}

/// Removes `.NAME.PID.tmp` beside `path` for every PID that is not a running process.
fn remove_stale_temporaries(path: &Path, name: &std::ffi::OsStr) {
    let Ok(entries) = std::fs::read_dir(parent(path)) else { return };
    let mut prefix = OsString::from(".");
    prefix.push(name);
    prefix.push(".");
    let Some(prefix) = prefix.to_str() else { return };
    for entry in entries.flatten() {
        let file_name = entry.file_name();
        let pid = file_name
            .to_str()
            .and_then(|n| n.strip_prefix(prefix))
            .and_then(|rest| rest.strip_suffix(".tmp"))
            .and_then(|pid| pid.parse::<u32>().ok());
        if let Some(pid) = pid
            && pid != std::process::id()
            && !process_alive(pid)
        {
            let _ = std::fs::remove_file(entry.path());
        }
    }
}

#[cfg(target_os = "linux")]
fn process_alive(pid: u32) -> bool {
    Path::new("/proc").join(pid.to_string()).exists()
}

/// Elsewhere a temporary file is never taken for stale.
#[cfg(not(target_os = "linux"))]
fn process_alive(_pid: u32) -> bool {
    true
}

/// The names of the files in `dir`, sorted: what the tests of the rooms that write files look at.
#[cfg(test)]
pub(crate) fn file_names(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .expect("dir")
        .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg(target_os = "linux")]
    #[test]
    fn the_room_of_an_output_written_in_place_is_not_its_directorys() {
        // `/dev` is a tmpfs of 64 MB in a container: `simulate --out /dev/null` was refused by its free space
        for path in ["/dev/null", "/dev/stdout"] {
            assert_eq!(free_bytes(Path::new(path)), None, "{path}");
        }
        let dir = tempfile::tempdir().expect("tmp");
        assert!(free_bytes(&dir.path().join("new.csv")).is_some());
        assert_eq!(dash_is_stdout(PathBuf::from("-")), Path::new("/dev/stdout"));
        assert_eq!(dash_is_stdout(PathBuf::from("./-")), Path::new("./-"));
    }

    #[test]
    fn an_output_that_is_an_input_or_another_output_or_nowhere_is_refused_by_flag() {
        let dir = tempfile::tempdir().expect("tmp");
        let rec = dir.path().join("rec.csv");
        std::fs::write(&rec, "t_s\n0\n").expect("write");
        let linked = dir.path().join("linked.csv");
        std::fs::hard_link(&rec, &linked).expect("link");
        let json = dir.path().join("out.json");
        let refused = |outputs: &[(&str, &Path)], needles: &[&str]| {
            let msg = check(&[&rec], outputs).expect_err("refused").0;
            assert!(needles.iter().all(|n| msg.contains(n)), "{needles:?}: {msg}");
        };
        refused(&[("--out", &rec)], &["--out", "rec.csv", "input"]);
        // the same file by another path, and by a hard link
        refused(&[("--out", &dir.path().join(".").join("rec.csv"))], &["--out", "input"]);
        refused(&[("--out", &linked)], &["--out", "linked.csv", "input"]);
        refused(&[("--json", &json), ("--report", &json)], &["--report", "--json", "out.json"]);
        refused(&[("--json", &dir.path().join("nodir/x.json"))], &["--json", "nodir", "does not exist"]);
        refused(&[("--json", dir.path())], &["--json", "directory"]);
        let dangling = dir.path().join("dangling.csv");
        std::os::unix::fs::symlink(dir.path().join("nodir/x.csv"), &dangling).expect("link");
        refused(&[("--out", &dangling)], &["--out", "dangling.csv", "links to", "does not exist"]);
        let slashed = format!("{}/", dir.path().join("sub").display());
        refused(&[("--json", Path::new(&slashed))], &["--json", "sub/", "ends in '/'"]);
        check(&[&rec], &[("--json", &json), ("--report", &dir.path().join("r.html"))]).expect("distinct");
        check(&[&rec], &[("--json", Path::new("/dev/null")), ("--report", Path::new("/dev/null"))])
            .expect("/dev/null takes everything");
    }

    #[test]
    fn a_replacement_leaves_the_old_file_until_committed_and_clears_stale_temporaries() {
        let dir = tempfile::tempdir().expect("tmp");
        let out = dir.path().join("est.csv");
        std::fs::write(&out, "old").expect("write");
        // a killed run's temporary (no process has pid u32::MAX) and a live one's (ours, seen as another run's)
        let stale = dir.path().join(temp_name("est.csv".as_ref(), u32::MAX));
        std::fs::write(&stale, "half").expect("write");
        let mut r = Replacement::create(&out).expect("create");
        assert!(!stale.exists(), "the stale temporary is gone");
        std::io::Write::write_all(r.file(), b"new").expect("write");
        assert_eq!(std::fs::read_to_string(&out).expect("read"), "old");
        drop(r); // as on an error
        assert_eq!(file_names(dir.path()), ["est.csv"]);
        assert_eq!(std::fs::read_to_string(&out).expect("read"), "old");
        replace(&out, b"new").expect("replace");
        assert_eq!(file_names(dir.path()), ["est.csv"]);
        assert_eq!(std::fs::read_to_string(&out).expect("read"), "new");
    }
}

//! Opening a recording for download: only a regular file that really lies in the recordings directory. A symbolic
//! link (to a system file, say), a FIFO (which would hang the request) or a directory is "not there".

use std::path::Path;

/// `dir/name` opened for reading, with its length now, if it is a regular file there (not a link to one); None for
/// anything else. Blocking: run it off the async workers.
pub fn open_regular(dir: &Path, name: &str) -> std::io::Result<Option<(std::fs::File, u64)>> {
    let path = dir.join(name);
    match std::fs::symlink_metadata(&path) {
        Ok(m) if m.file_type().is_file() => {}
        Ok(_) => return Ok(None),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(e),
    }
    // what was checked may be swapped for a link or a FIFO before the open: open without following links and
    // without blocking, then check the file that was opened
    let file = match open_no_follow(&path) {
        Ok(f) => f,
        Err(e) if matches!(e.kind(), std::io::ErrorKind::NotFound) => return Ok(None),
        Err(e) if e.raw_os_error() == Some(LINK_ERRNO) => return Ok(None),
        Err(e) => return Err(e),
    };
    let meta = file.metadata()?;
    if !meta.is_file() {
        return Ok(None);
    }
    Ok(Some((file, meta.len())))
}

/// ELOOP: what an open with O_NOFOLLOW says about a link.
#[cfg(target_os = "linux")]
const LINK_ERRNO: i32 = 40;
#[cfg(not(target_os = "linux"))]
const LINK_ERRNO: i32 = -1;

#[cfg(target_os = "linux")]
fn open_no_follow(path: &Path) -> std::io::Result<std::fs::File> {
    use rustix::fs::{Mode, OFlags, open};
    let flags = OFlags::RDONLY | OFlags::NOFOLLOW | OFlags::NONBLOCK | OFlags::CLOEXEC;
    Ok(std::fs::File::from(open(path, flags, Mode::empty())?))
}

#[cfg(not(target_os = "linux"))]
fn open_no_follow(path: &Path) -> std::io::Result<std::fs::File> {
    std::fs::File::open(path)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn links_and_directories_are_not_there() {
        let dir = tempfile::tempdir().expect("tmp");
        std::fs::write(dir.path().join("a.csv"), "t_s\n").expect("write");
        std::os::unix::fs::symlink(dir.path().join("a.csv"), dir.path().join("b.csv")).expect("link");
        std::fs::create_dir(dir.path().join("c.csv")).expect("dir");
        let (mut file, len) = open_regular(dir.path(), "a.csv").expect("opens").expect("there");
        let mut text = String::new();
        std::io::Read::read_to_string(&mut file, &mut text).expect("reads");
        assert_eq!((text.as_str(), len), ("t_s\n", 4));
        for name in ["b.csv", "c.csv", "missing.csv"] {
            assert!(open_regular(dir.path(), name).expect("no error").is_none(), "{name}");
        }
    }
}

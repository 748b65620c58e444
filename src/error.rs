//! The bad-input marker (exit 2: the user can fix it). Which errors are bad input is decided at the crate's top
//! ([`crate::is_bad_input`]), where every room's error type is known; this bottom room knows none of them.

/// Bad input that has no richer error type of its own (a command-line value, say). The message names what and where.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct BadInput(pub String);

/// A value a key does not allow: which key (as the file spells it, e.g. `motor.displacement_cm3`), and what is wrong.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{key} {message}")]
pub struct KeyError {
    pub key: String,
    pub message: String,
}

impl KeyError {
    pub fn new(key: String, message: String) -> KeyError {
        KeyError { key, message }
    }
}

/// Whether a file the user named cannot be read for a reason theirs to fix: it is missing, not readable, a
/// directory, or not UTF-8 text (exit 2, not 1).
pub fn unreadable_is_bad_input(e: &std::io::Error) -> bool {
    use std::io::ErrorKind::{InvalidData, IsADirectory, NotADirectory, NotFound, PermissionDenied};
    matches!(e.kind(), NotFound | PermissionDenied | IsADirectory | NotADirectory | InvalidData)
}

/// The most a model or config file may hold. The largest real one is a few kB; the cap keeps a wrong path
/// (`/dev/zero`, a recording) from taking the machine's memory before the parser can say what is wrong.
pub const TEXT_FILE_CAP: u64 = 1 << 20;

/// Reads a small file whole (a model, a config, a certificate), refusing one larger than [`TEXT_FILE_CAP`] after
/// reading no more than the cap (InvalidData, so bad input: exit 2). Devices and pipes are read the same way, never
/// to their end.
pub fn read_small_file(path: &std::path::Path) -> std::io::Result<Vec<u8>> {
    use std::io::Read;
    let file = open_without_waiting(path)?;
    let mut bytes = Vec::new();
    file.take(TEXT_FILE_CAP + 1).read_to_end(&mut bytes)?;
    if bytes.is_empty() && is_fifo(path) {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            "a named pipe with nothing written to it (no writer): nothing to read",
        ));
    }
    if bytes.len() as u64 > TEXT_FILE_CAP {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!(
                "larger than {} kB, the cap for a model, config or certificate file: is it the right file?",
                TEXT_FILE_CAP >> 10
            ),
        ));
    }
    Ok(bytes)
}

/// Opens `path` for reading without waiting for a writer: a named pipe nobody writes to blocked the open forever
/// (`serve --config` on a FIFO hung). Opened non-blocking, then read blocking as any file is: a pipe with a writer
/// (a shell's process substitution) is read whole, one without ends at once.
pub fn open_without_waiting(path: &std::path::Path) -> std::io::Result<std::fs::File> {
    #[cfg(target_os = "linux")]
    {
        use rustix::fs::OFlags;
        use std::os::unix::fs::OpenOptionsExt;
        let nonblock = i32::try_from(OFlags::NONBLOCK.bits()).unwrap_or(0);
        let file = std::fs::OpenOptions::new().read(true).custom_flags(nonblock).open(path)?;
        rustix::fs::fcntl_setfl(&file, rustix::fs::fcntl_getfl(&file)?.difference(OFlags::NONBLOCK))?;
        Ok(file)
    }
    #[cfg(not(target_os = "linux"))]
    {
        std::fs::File::open(path)
    }
}

/// Whether `path` is a named pipe.
pub fn is_fifo(path: &std::path::Path) -> bool {
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        std::fs::metadata(path).is_ok_and(|m| m.file_type().is_fifo())
    }
    #[cfg(not(unix))]
    {
        let _ = path;
        false
    }
}

/// [`read_small_file`], as UTF-8 text. A byte that is not names its line and column (counted in characters, 1-based)
/// and the byte offset: a Latin-1 `é` in a comment was said as "byte 24" only.
pub fn read_text_file(path: &std::path::Path) -> std::io::Result<String> {
    String::from_utf8(read_small_file(path)?).map_err(|e| {
        let at = e.utf8_error().valid_up_to();
        let before = String::from_utf8_lossy(&e.as_bytes()[..at]);
        let line = before.matches('\n').count() + 1;
        let column = before.rsplit('\n').next().map_or(0, |l| l.chars().count()) + 1;
        std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("not UTF-8 text at line {line}, column {column} (byte {at}; save the file as UTF-8)"),
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_text_file_beyond_the_cap_is_refused_after_reading_no_more_than_the_cap() {
        let err = read_text_file(std::path::Path::new("/dev/zero")).expect_err("refused");
        assert!(unreadable_is_bad_input(&err));
        assert!(err.to_string().contains("1024 kB"), "{err}");
        let dir = tempfile::tempdir().expect("dir");
        let path = dir.path().join("m.toml");
        std::fs::write(&path, b"a = 1\n\xff").expect("write");
        let err = read_text_file(&path).expect_err("not UTF-8");
        assert!(err.to_string().contains("line 2, column 1 (byte 6"), "{err}");
        std::fs::write(&path, "a = 1 # r\u{e9}\nb = \"".bytes().chain(*b"p\xe9\"\n").collect::<Vec<u8>>())
            .expect("write");
        let err = read_text_file(&path).expect_err("Latin-1");
        assert!(err.to_string().contains("line 2, column 7"), "{err}");
        std::fs::write(&path, "a = 1\n").expect("write");
        assert_eq!(read_text_file(&path).expect("read"), "a = 1\n");
    }

    /// A named pipe nobody writes to hung `serve --config`, `simulate --model` and the rest at the open: now it is
    /// bad input at once; one with a writer is read whole.
    #[cfg(target_os = "linux")]
    #[test]
    fn a_named_pipe_without_a_writer_is_refused_at_once_and_one_with_a_writer_is_read() {
        let dir = tempfile::tempdir().expect("dir");
        let fifo = dir.path().join("m.toml");
        rustix::fs::mkfifoat(rustix::fs::CWD, &fifo, rustix::fs::Mode::from_raw_mode(0o600)).expect("mkfifo");
        let err = read_text_file(&fifo).expect_err("no writer");
        assert!(unreadable_is_bad_input(&err) && err.to_string().contains("no writer"), "{err}");
        // written to (a reader holds the pipe open meanwhile, so the writer's open does not wait and what it
        // wrote stays in the pipe): read whole
        let keeper = open_without_waiting(&fifo).expect("a reader");
        std::io::Write::write_all(
            &mut std::fs::OpenOptions::new().write(true).open(&fifo).expect("writer"),
            b"a = 1\n",
        )
        .expect("write");
        assert_eq!(read_text_file(&fifo).expect("read"), "a = 1\n");
        drop(keeper);
    }
}

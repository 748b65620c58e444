//! Writing recordings: a row writer for streams, a whole-table writer, and an hourly/size rotating file writer.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::os::unix::fs::MetadataExt;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use super::Recording;

/// A value as the CSV holds it: the shortest decimal that reads back to the same double, `3` rather than `3.0` and
/// no `+` in exponents (the layout ryu gives, which the files have always had; a test checks it against ryu);
/// nothing for a missing (non-finite) value.
#[inline]
pub fn push_value(out: &mut Vec<u8>, v: f64) {
    if v.is_finite() {
        let mut buf = zmij::Buffer::new();
        let text = buf.format_finite(v);
        let text = text.strip_suffix(".0").unwrap_or(text);
        if v.abs() >= 1e15
            && let Some((mantissa, exponent)) = text.split_once("e+")
        {
            out.extend_from_slice(mantissa.as_bytes());
            out.push(b'e');
            out.extend_from_slice(exponent.as_bytes());
        } else {
            out.extend_from_slice(text.as_bytes());
        }
    }
}

/// Writes rows of a fixed set of columns.
pub struct RowWriter<W: Write> {
    out: W,
    width: usize,
    line: Vec<u8>,
}

impl<W: Write> RowWriter<W> {
    /// Writes the header row.
    pub fn new(mut out: W, names: &[&str]) -> std::io::Result<RowWriter<W>> {
        writeln!(out, "{}", names.join(","))?;
        Ok(RowWriter { out, width: names.len(), line: Vec::with_capacity(256) })
    }

    /// Writes one row; it must have one value per column.
    pub fn write_row(&mut self, values: impl IntoIterator<Item = f64>) -> std::io::Result<()> {
        self.line.clear();
        let mut n = 0;
        for v in values {
            if n > 0 {
                self.line.push(b',');
            }
            push_value(&mut self.line, v);
            n += 1;
        }
        debug_assert_eq!(n, self.width);
        self.line.push(b'\n');
        self.out.write_all(&self.line)
    }

    pub fn flush(&mut self) -> std::io::Result<()> {
        self.out.flush()
    }

    pub fn into_inner(self) -> W {
        self.out
    }
}

/// Writes a whole recording as CSV.
pub fn write_csv<W: Write>(out: W, rec: &Recording) -> std::io::Result<()> {
    let names: Vec<&str> = rec.names().iter().map(String::as_str).collect();
    let mut w = RowWriter::new(BufWriter::with_capacity(1 << 16, out), &names)?;
    for k in 0..rec.len() {
        w.write_row(rec.row(k))?;
    }
    w.flush()
}

/// A recording split into files `<prefix>-<unix seconds>.csv` in a directory, starting a new file every
/// `max_age` or `max_bytes`, flushed at most `flush_every` after a row is written. A new file gets its header at
/// once; a file that holds no complete row when it is closed after a failure (a full disk) is removed, so that
/// failures leave no empty files behind.
pub struct RotatingWriter {
    dir: PathBuf,
    prefix: String,
    names: Vec<String>,
    max_age: Duration,
    max_bytes: u64,
    flush_every: Duration,
    current: Option<Current>,
    /// Files closed (by rotation, [`RotatingWriter::close`] or [`RotatingWriter::abandon`]) since
    /// [`RotatingWriter::take_closed`] was last asked: several, when one call wrote rows enough for several files.
    closed: Vec<PathBuf>,
}

struct Current {
    writer: RowWriter<CountingWriter<BufWriter<File>>>,
    opened: Instant,
    last_flush: Instant,
    path: PathBuf,
    /// The open file's (device, inode): its path names it until the file is deleted or replaced.
    identity: (u64, u64),
    /// Rows written to the file, and of those the rows a flush has proven on disk.
    rows: u64,
    flushed_rows: u64,
}

/// An open file whose path no longer names it (deleted, its directory removed, or another file put in its place):
/// the rows written to it went with it.
#[derive(Debug, Clone, PartialEq)]
pub struct LostFile {
    pub path: PathBuf,
    pub rows: u64,
    /// Another file is at its path (else the path is gone).
    pub replaced: bool,
}

/// Whether `path` names the file `identity`.
fn names(path: &Path, identity: (u64, u64)) -> bool {
    std::fs::metadata(path).is_ok_and(|m| (m.dev(), m.ino()) == identity)
}

impl Current {
    /// Creates the file at `path` and writes its header through to it: a file that cannot take even that is removed
    /// and the error returned.
    fn create(path: PathBuf, names: &[&str], now: Instant) -> std::io::Result<Current> {
        let file = File::create(&path)?;
        let identity = match file.metadata() {
            Ok(m) => (m.dev(), m.ino()),
            Err(e) => {
                let _ = std::fs::remove_file(&path);
                return Err(e);
            }
        };
        let writer =
            RowWriter::new(CountingWriter { inner: BufWriter::with_capacity(1 << 16, file), bytes: 0 }, names)?;
        let mut c = Current { writer, opened: now, last_flush: now, path, identity, rows: 0, flushed_rows: 0 };
        if let Err(e) = c.flush() {
            let _ = c.end();
            return Err(e);
        }
        Ok(c)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.writer.flush()?;
        self.flushed_rows = self.rows;
        Ok(())
    }

    /// Flushes, syncs and closes the file. When that fails with no row proven on disk, or no row was written, a
    /// file that holds no complete row is removed (if its path still names it).
    fn end(self) -> std::io::Result<()> {
        let Current { writer, path, identity, rows, flushed_rows, .. } = self;
        let mut counting = writer.into_inner();
        let flushed = counting.inner.flush();
        // what could not be written is dropped here, not tried again when the buffer is dropped
        let (file, _) = counting.inner.into_parts();
        let result = flushed.and_then(|()| file.sync_all());
        drop(file);
        let may_be_rowless = if result.is_ok() { rows == 0 } else { flushed_rows == 0 };
        // a device in its place (what a test stands in for a full disk) is not read: nothing reached it
        let rowless = |p: &Path| match std::fs::metadata(p) {
            Ok(m) if !m.is_file() => true,
            _ => super::holds_no_rows(p).unwrap_or(false),
        };
        if may_be_rowless && names(&path, identity) && rowless(&path) {
            match std::fs::remove_file(&path) {
                Ok(()) => tracing::info!(file = %path.display(), "removed a recording that holds no rows"),
                Err(e) => tracing::warn!(file = %path.display(), error = %e,
                    "cannot remove a recording that holds no rows"),
            }
        }
        result
    }
}

/// Counts bytes on their way out, for size rotation.
struct CountingWriter<W> {
    inner: W,
    bytes: u64,
}

impl<W: Write> Write for CountingWriter<W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.bytes += n as u64;
        Ok(n)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush()
    }
}

impl RotatingWriter {
    pub fn new(dir: &Path, prefix: &str, names: &[&str], max_age: Duration, max_bytes: u64) -> RotatingWriter {
        RotatingWriter {
            dir: dir.to_path_buf(),
            prefix: prefix.to_string(),
            names: names.iter().map(|s| s.to_string()).collect(),
            max_age,
            max_bytes,
            flush_every: Duration::from_millis(500),
            current: None,
            closed: Vec::new(),
        }
    }

    /// The file being written, if any.
    pub fn current_path(&self) -> Option<&Path> {
        self.current.as_ref().map(|c| c.path.as_path())
    }

    /// The files closed since the last call, oldest first (a file that held no row may have been removed).
    /// A file given up as lost is not among them: its path no longer names it.
    pub fn take_closed(&mut self) -> Vec<PathBuf> {
        std::mem::take(&mut self.closed)
    }

    /// Ends `c`, noting its path as closed.
    fn end(&mut self, c: Current) -> std::io::Result<()> {
        self.closed.push(c.path.clone());
        c.end()
    }

    fn open(&mut self, now: Instant) -> std::io::Result<()> {
        std::fs::create_dir_all(&self.dir)?;
        let stamp = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_millis());
        let mut path = self.dir.join(format!("{}-{stamp}.csv", self.prefix));
        let mut i = 1;
        while path.exists() {
            path = self.dir.join(format!("{}-{stamp}-{i}.csv", self.prefix));
            i += 1;
        }
        let names: Vec<&str> = self.names.iter().map(String::as_str).collect();
        let current = Current::create(path, &names, now)?;
        tracing::info!(file = %current.path.display(), "recording to new file");
        self.current = Some(current);
        Ok(())
    }

    /// Writes a row, rotating and flushing as due.
    pub fn write_row(&mut self, now: Instant, values: impl IntoIterator<Item = f64>) -> std::io::Result<()> {
        let rotate = match &self.current {
            None => true,
            Some(c) => now.duration_since(c.opened) >= self.max_age || c.writer.out.bytes >= self.max_bytes,
        };
        if rotate {
            self.close()?;
            self.open(now)?;
        }
        let Some(c) = self.current.as_mut() else { return Ok(()) };
        c.writer.write_row(values)?;
        c.rows += 1;
        if now.duration_since(c.last_flush) >= self.flush_every {
            c.flush()?;
            c.last_flush = now;
        }
        Ok(())
    }

    /// Flushes what is buffered.
    pub fn flush(&mut self) -> std::io::Result<()> {
        if let Some(c) = self.current.as_mut() {
            c.flush()?;
            c.last_flush = Instant::now();
        }
        Ok(())
    }

    /// Gives up the open file if its path no longer names it (deleted, its directory removed, or replaced): rows
    /// written to it would go nowhere until the next rotation. The next row starts a new file (the directory
    /// recreated). A path that cannot be looked up for another reason (permissions) is taken as still naming it.
    pub fn give_up_if_lost(&mut self) -> Option<LostFile> {
        let c = self.current.as_ref()?;
        let replaced = match std::fs::metadata(&c.path) {
            Ok(m) if (m.dev(), m.ino()) == c.identity => return None,
            Ok(_) => true,
            Err(e) if matches!(e.kind(), std::io::ErrorKind::NotFound | std::io::ErrorKind::NotADirectory) => false,
            Err(_) => return None,
        };
        let c = self.current.take()?;
        let lost = LostFile { path: c.path.clone(), rows: c.rows, replaced };
        // the rows go to the lost file's inode, which is freed when it closes
        let _ = c.end();
        Some(lost)
    }

    /// Gives up the current file after a failed write (it may end in a cut row, which readers drop; one that holds
    /// no row is removed): the next row starts a new file. Errors on the way out are ignored, the failure was
    /// reported already.
    pub fn abandon(&mut self) {
        if let Some(c) = self.current.take() {
            let _ = self.end(c);
        }
    }

    /// Flushes and closes the current file, syncing it to disk.
    pub fn close(&mut self) -> std::io::Result<()> {
        match self.current.take() {
            Some(c) => self.end(c),
            None => Ok(()),
        }
    }
}

impl Drop for RotatingWriter {
    fn drop(&mut self) {
        if let Err(e) = self.close() {
            tracing::error!(error = %e, "closing the recording failed");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::recording::parse;
    use proptest::prelude::*;

    /// What ryu writes for `v` (the files' layout: `3` for 3.0, nothing for a missing value), and what `push_value`
    /// writes.
    fn both(v: f64) -> (String, String) {
        let mut s = String::new();
        if v.is_finite() {
            let mut buf = ryu::Buffer::new();
            let text = buf.format_finite(v);
            s.push_str(text.strip_suffix(".0").unwrap_or(text));
        }
        let mut b = Vec::new();
        push_value(&mut b, v);
        (s, String::from_utf8(b).expect("ASCII"))
    }

    #[test]
    fn push_value_writes_what_ryu_writes_at_the_edges() {
        for e in -330..310 {
            for m in [1.0, 1.5, 9.999_999_999_999_999, 1.234_567_890_123_456_7] {
                let v = m * 10f64.powi(e);
                let (a, b) = both(v);
                assert_eq!(a, b, "{v:e}");
                let (a, b) = both(-v);
                assert_eq!(a, b, "{v:e}");
            }
        }
        for v in [0.0, -0.0, 3.0, 1e15, 1e16, 9_999_999_999_999_998.0, f64::MAX, f64::MIN_POSITIVE, 5e-324, f64::NAN] {
            let (a, b) = both(v);
            assert_eq!(a, b, "{v:e}");
        }
    }

    proptest! {
        #[test]
        fn push_value_writes_what_ryu_writes(bits in any::<u64>(), small in -1e6f64..1e6) {
            for v in [f64::from_bits(bits), small] {
                let (a, b) = both(v);
                prop_assert_eq!(a, b);
            }
        }
    }

    #[test]
    fn round_trip_keeps_values_and_gaps() {
        let rec = Recording::from_columns(
            "mem",
            vec!["t_s".into(), "omega_rad_s".into()],
            vec![vec![0.0, 0.001, 0.002], vec![1.0 / 3.0, f64::NAN, -2.5e-7]],
        );
        let mut buf = Vec::new();
        write_csv(&mut buf, &rec).expect("write");
        let back = parse(buf.as_slice(), "mem").expect("parse");
        let w = back.column("omega_rad_s").expect("col");
        assert_eq!(w[0], 1.0 / 3.0);
        assert!(w[1].is_nan());
        assert_eq!(w[2], -2.5e-7);
    }

    fn rows_in(path: &Path) -> usize {
        crate::recording::load(path).expect("a valid recording").len()
    }

    #[test]
    fn a_deleted_or_replaced_file_or_a_removed_directory_is_given_up_and_the_next_row_starts_a_new_file() {
        let tmp = tempfile::tempdir().expect("tmp");
        let dir = tmp.path().join("rec");
        let mut w = RotatingWriter::new(&dir, "d", &["t_s", "x"], Duration::from_secs(3600), 1 << 20);
        let mut t = 0.0;
        let mut rows = |w: &mut RotatingWriter, n: usize| {
            for _ in 0..n {
                w.write_row(Instant::now(), [t, 1.0]).expect("write");
                t += 1.0;
            }
            w.flush().expect("flush");
            w.current_path().expect("open").to_path_buf()
        };
        let first = rows(&mut w, 5);
        assert_eq!(w.give_up_if_lost(), None, "the file is where it was");
        std::fs::remove_file(&first).expect("rm");
        assert_eq!(w.give_up_if_lost(), Some(LostFile { path: first.clone(), rows: 5, replaced: false }));
        assert_eq!(w.current_path(), None);
        assert_eq!(w.give_up_if_lost(), None, "one event, told once");

        // a new file (its name may be the lost one's, within the same millisecond)
        let second = rows(&mut w, 3);
        assert_eq!(rows_in(&second), 3);
        let other = dir.join("other");
        std::fs::write(&other, "not ours").expect("write");
        std::fs::rename(&other, &second).expect("replace");
        assert_eq!(w.give_up_if_lost(), Some(LostFile { path: second.clone(), rows: 3, replaced: true }));
        assert_eq!(std::fs::read_to_string(&second).expect("read"), "not ours", "the file put there is untouched");

        let third = rows(&mut w, 2);
        std::fs::remove_dir_all(&dir).expect("rm -r");
        assert_eq!(w.give_up_if_lost(), Some(LostFile { path: third, rows: 2, replaced: false }));
        let fourth = rows(&mut w, 4);
        w.close().expect("close");
        assert_eq!(rows_in(&fourth), 4, "the directory is recreated and the rows reach the new file");
    }

    #[test]
    fn a_file_closed_without_rows_is_removed_and_one_with_rows_kept() {
        let dir = tempfile::tempdir().expect("tmp");
        let path = dir.path().join("d-1.csv");
        let c = Current::create(path.clone(), &["t_s", "x"], Instant::now()).expect("created");
        assert_eq!(std::fs::read_to_string(&path).expect("read"), "t_s,x\n", "the header is written at once");
        c.end().expect("closed");
        assert!(!path.exists(), "a header alone is removed");

        let mut w = RotatingWriter::new(dir.path(), "d", &["t_s", "x"], Duration::from_secs(3600), 1 << 20);
        w.write_row(Instant::now(), [0.0, 1.0]).expect("write");
        let kept = w.current_path().expect("open").to_path_buf();
        w.abandon();
        assert_eq!(rows_in(&kept), 1, "a file given up with a row in it is kept");
    }

    /// `/dev/full` refuses every write with ENOSPC, as a full disk does: the file the writer created (here a link
    /// to it) is removed and the error returned.
    #[cfg(target_os = "linux")]
    #[test]
    fn a_file_that_cannot_take_its_header_is_removed() {
        let dir = tempfile::tempdir().expect("tmp");
        let path = dir.path().join("d-1.csv");
        std::os::unix::fs::symlink("/dev/full", &path).expect("symlink");
        let e = Current::create(path.clone(), &["t_s", "x"], Instant::now()).err().expect("a full device");
        assert_eq!(e.raw_os_error(), Some(28), "ENOSPC: {e}");
        assert!(std::fs::symlink_metadata(&path).is_err(), "nothing is left at {}", path.display());
    }

    #[test]
    fn rotates_by_size() {
        let dir = tempfile::tempdir().expect("tmp");
        let mut w = RotatingWriter::new(dir.path(), "d", &["t_s", "x"], Duration::from_secs(3600), 100);
        let now = Instant::now();
        for k in 0..100 {
            w.write_row(now, [k as f64, 1.0]).expect("write");
        }
        w.close().expect("close");
        let files: Vec<_> = std::fs::read_dir(dir.path()).expect("dir").collect();
        assert!(files.len() > 3, "{}", files.len());
        let mut rows = 0;
        for f in files {
            let rec = crate::recording::load(&f.expect("entry").path()).expect("each file is a valid recording");
            rows += rec.len();
        }
        assert_eq!(rows, 100);
    }
}

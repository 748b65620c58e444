//! Writing recordings: a row writer for streams, a whole-table writer, and an hourly/size rotating file writer.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use super::Recording;

/// A value as the CSV holds it: shortest round-trip decimal, empty for a missing (non-finite) value.
pub fn format_value(out: &mut String, v: f64) {
    if v.is_finite() {
        out.push_str(shortest(&mut ryu::Buffer::new(), v));
    }
}

/// [`format_value`] onto bytes, about twice as fast: zmij finds the same shortest digits as ryu and lays them out
/// the same way, but for a `+` in positive exponents (|v| ≥ 1e16), which is dropped here.
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

/// [`push_value`] for a value parsed from the text `cell`: copies the text where it already is what `push_value`
/// writes, and formats `v` otherwise. That is the case for a plain decimal (an optional `-`, digits with no leading
/// zero but a lone one before the point, an optional point with digits that do not end in zero, no exponent) of at
/// most 15 significant digits, 0 or between 0.0001 and 10¹⁵: no two decimals of 15 digits or fewer round to the same
/// double, so no shorter one rounds to `v`, and the shortest round trip is the text itself. (zmij writes plain
/// decimals from 10⁻⁵ to 10¹⁶; the limits here stay a decade inside.) Recorded times (`0.001`, `2999.998`) are
/// mostly such texts, and copying them costs a fraction of formatting them. `cell` must be the text `v` was parsed
/// from.
#[inline]
pub fn push_parsed_value(out: &mut Vec<u8>, v: f64, cell: &[u8]) {
    if is_shortest_plain_decimal(cell) {
        out.extend_from_slice(cell);
    } else {
        push_value(out, v);
    }
}

/// Whether `s` is a decimal as [`push_value`] writes it, and the shortest that rounds to its value (see
/// [`push_parsed_value`]).
fn is_shortest_plain_decimal(s: &[u8]) -> bool {
    let s = s.strip_prefix(b"-").unwrap_or(s);
    let int = s.iter().take_while(|b| b.is_ascii_digit()).count();
    if int == 0 || int > 15 || (int > 1 && s[0] == b'0') {
        return false;
    }
    let frac = match &s[int..] {
        [] => return true,
        [b'.', frac @ ..] => frac,
        _ => return false,
    };
    if frac.is_empty() || !frac.iter().all(u8::is_ascii_digit) || frac.last() == Some(&b'0') {
        return false;
    }
    let significant = if s[0] == b'0' {
        let zeros = frac.iter().take_while(|&&b| b == b'0').count();
        if zeros > 3 {
            return false;
        }
        frac.len() - zeros
    } else {
        int + frac.len()
    };
    significant <= 15
}

#[inline]
fn shortest(buf: &mut ryu::Buffer, v: f64) -> &str {
    let text = buf.format_finite(v);
    // "3.0" → "3": shorter files, and the same numbers as before
    text.strip_suffix(".0").unwrap_or(text)
}

/// Writes rows of a fixed set of columns.
pub struct RowWriter<W: Write> {
    out: W,
    width: usize,
    line: String,
}

impl<W: Write> RowWriter<W> {
    /// Writes the header row.
    pub fn new(mut out: W, names: &[&str]) -> std::io::Result<RowWriter<W>> {
        writeln!(out, "{}", names.join(","))?;
        Ok(RowWriter { out, width: names.len(), line: String::with_capacity(256) })
    }

    /// Writes one row; it must have one value per column.
    pub fn write_row(&mut self, values: impl IntoIterator<Item = f64>) -> std::io::Result<()> {
        self.line.clear();
        let mut n = 0;
        for v in values {
            if n > 0 {
                self.line.push(',');
            }
            format_value(&mut self.line, v);
            n += 1;
        }
        debug_assert_eq!(n, self.width);
        self.line.push('\n');
        self.out.write_all(self.line.as_bytes())
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
/// `max_age` or `max_bytes`, flushed at most `flush_every` after a row is written.
pub struct RotatingWriter {
    dir: PathBuf,
    prefix: String,
    names: Vec<String>,
    max_age: Duration,
    max_bytes: u64,
    flush_every: Duration,
    current: Option<Current>,
}

struct Current {
    writer: RowWriter<CountingWriter<BufWriter<File>>>,
    opened: Instant,
    last_flush: Instant,
    path: PathBuf,
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
        }
    }

    /// The file being written, if any.
    pub fn current_path(&self) -> Option<&Path> {
        self.current.as_ref().map(|c| c.path.as_path())
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
        let file = File::create(&path)?;
        let names: Vec<&str> = self.names.iter().map(String::as_str).collect();
        let writer =
            RowWriter::new(CountingWriter { inner: BufWriter::with_capacity(1 << 16, file), bytes: 0 }, &names)?;
        tracing::info!(file = %path.display(), "recording to new file");
        self.current = Some(Current { writer, opened: now, last_flush: now, path });
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
        if now.duration_since(c.last_flush) >= self.flush_every {
            c.writer.flush()?;
            c.last_flush = now;
        }
        Ok(())
    }

    /// Flushes what is buffered.
    pub fn flush(&mut self) -> std::io::Result<()> {
        if let Some(c) = self.current.as_mut() {
            c.writer.flush()?;
            c.last_flush = Instant::now();
        }
        Ok(())
    }

    /// Gives up the current file after a failed write (it may end in a cut row, which readers drop): the next row
    /// starts a new file. Errors on the way out are ignored, the failure was reported already.
    pub fn abandon(&mut self) {
        if let Some(c) = self.current.take() {
            let mut counting = c.writer.into_inner();
            let _ = counting.flush();
            if let Ok(file) = counting.inner.into_inner() {
                let _ = file.sync_all();
            }
        }
    }

    /// Flushes and closes the current file, syncing it to disk.
    pub fn close(&mut self) -> std::io::Result<()> {
        if let Some(c) = self.current.take() {
            let mut counting = c.writer.into_inner();
            counting.flush()?;
            let file = counting.inner.into_inner().map_err(|e| e.into_error())?;
            file.sync_all()?;
        }
        Ok(())
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

    fn both(v: f64) -> (String, String) {
        let mut s = String::new();
        format_value(&mut s, v);
        let mut b = Vec::new();
        push_value(&mut b, v);
        (s, String::from_utf8(b).expect("ASCII"))
    }

    #[test]
    fn push_value_writes_what_format_value_writes_at_the_edges() {
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

    /// What `push_parsed_value` writes for a cell, and what `push_value` writes for its value.
    fn parsed_both(cell: &str) -> (String, String) {
        let v: f64 = cell.parse().expect("a number");
        let (mut a, mut b) = (Vec::new(), Vec::new());
        push_parsed_value(&mut a, v, cell.as_bytes());
        push_value(&mut b, v);
        (String::from_utf8(a).expect("ASCII"), String::from_utf8(b).expect("ASCII"))
    }

    #[test]
    fn push_parsed_value_writes_what_push_value_writes_for_recorded_times() {
        // every millisecond of the first 1.1 hours and some up to three years, as `simulate` writes them and as
        // `k / 1000` is written by hand
        let mut copied = 0;
        for k in (0..4_000_000u64).chain((4_000_000..100_000_000_000).step_by(99_991)) {
            let mut text = Vec::new();
            push_value(&mut text, k as f64 * 0.001);
            let text = String::from_utf8(text).expect("ASCII");
            let (a, b) = parsed_both(&text);
            assert_eq!(a, b, "{text}");
            copied += usize::from(k < 4_000_000 && is_shortest_plain_decimal(text.as_bytes()));
            // the same times written by hand, trailing zeros and all (these test the check; the lines above mostly
            // test that a formatted time is copied)
            if k % 7 == 0 {
                let text = format!("{}.{:03}", k / 1000, k % 1000);
                let (a, b) = parsed_both(&text);
                assert_eq!(a, b, "{text}");
            }
        }
        // the copy is the common case (a time with 17 digits, such as 0.30000000000000004, is formatted)
        assert!(copied > 3_000_000, "{copied}");
    }

    #[test]
    fn push_parsed_value_writes_what_push_value_writes_at_the_edges() {
        for cell in [
            "0",
            "-0",
            "0.0",
            "00",
            "01",
            "1",
            "10",
            "100",
            "1.5",
            "1.50",
            "-1.5",
            "+1.5",
            "1.",
            ".5",
            "0.1",
            "0.0001",
            "0.00001",
            "0.00012",
            "0.000123456789012345",
            "123456789012345",
            "1234567890123456",
            "999999999999999",
            "999999999999999.9",
            "1e3",
            "1E3",
            "0.30000000000000004",
            "0.3",
            "5e-324",
            "1e15",
            "1e16",
            "0.123456789012345",
            "0.1234567890123456",
            "12345678.1234567",
            "12345678.12345678",
            "9007199254740993",
            "-123.456",
            "0.000001",
            "-0.0000012",
            "0.00000123",
            "1000000000000000",
            "100000000000000",
            "0.0001234567890123",
            "1 ",
            " 1",
        ] {
            if cell.trim() != cell {
                let mut a = Vec::new();
                push_parsed_value(&mut a, 1.0, cell.as_bytes());
                assert_eq!(a, b"1", "{cell:?}");
                continue;
            }
            let (a, b) = parsed_both(cell);
            assert_eq!(a, b, "{cell:?}");
        }
    }

    proptest! {
        #[test]
        fn push_parsed_value_writes_what_push_value_writes(
            int in "-?[0-9]{1,17}", frac in "(\\.[0-9]{0,18})?", exp in "([eE][+-]?[0-9]{1,2})?",
        ) {
            let cell = format!("{int}{frac}{exp}");
            let (a, b) = parsed_both(&cell);
            prop_assert_eq!(a, b, "{}", cell);
        }

        #[test]
        fn push_value_writes_what_format_value_writes(bits in any::<u64>(), small in -1e6f64..1e6) {
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

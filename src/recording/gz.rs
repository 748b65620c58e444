//! Compressed recordings: a closed file `<name>.csv` becomes `<name>.csv.gz` (gzip, which pandas and every shell
//! tool open as it is), and readers take either. Compression goes through a temporary file that is synced and
//! renamed before the original goes, so a process that dies mid-way loses nothing: it leaves the original and at
//! most a temporary `.<name>.csv.gz.tmp`, which the service removes on start.

use std::fs::File;
use std::io::{BufRead, BufWriter, ErrorKind, Read};
use std::path::{Path, PathBuf};

use flate2::Compression;
use flate2::bufread::GzDecoder;
use flate2::write::GzEncoder;

/// The first two bytes of every gzip stream (RFC 1952).
pub const GZIP_MAGIC: [u8; 2] = [0x1f, 0x8b];

/// The suffix a compressed recording has beyond the plain file's name.
pub const GZ_SUFFIX: &str = ".gz";

/// The temporary name `path` is compressed under: hidden, and never taken for a recording.
pub fn temp_path(path: &Path) -> PathBuf {
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    path.with_file_name(format!(".{name}{GZ_SUFFIX}.tmp"))
}

/// Whether `name` is a temporary file left by compressing one of `drive`'s recordings ([`temp_path`] of a name
/// [`super::drive_file_key`] gives `drive`: `.pump-2-….csv.gz.tmp` is drive `pump-2`'s, and `pump`'s recorder removed
/// it).
pub fn is_temp_of(name: &str, drive: &str) -> bool {
    name.strip_prefix('.')
        .and_then(|n| n.strip_suffix(".gz.tmp"))
        .and_then(|plain| super::drive_file_key(plain, drive))
        .is_some_and(|(_, compressed)| !compressed)
}

/// Compresses the closed recording `path` to `path` + `.gz` and removes `path`; returns the new path. On failure
/// `path` is untouched and no temporary file is left. An existing `.gz` of the same name (from a run that died
/// after its rename) is replaced.
pub fn compress(path: &Path) -> std::io::Result<PathBuf> {
    let mut gz = path.as_os_str().to_owned();
    gz.push(GZ_SUFFIX);
    let gz = PathBuf::from(gz);
    let temp = temp_path(path);
    let written = (|| {
        let mut source = File::open(path)?;
        let out = File::create(&temp)?;
        let mut encoder = GzEncoder::new(BufWriter::with_capacity(1 << 16, out), Compression::default());
        std::io::copy(&mut source, &mut encoder)?;
        let out = encoder.finish()?.into_inner().map_err(std::io::IntoInnerError::into_error)?;
        out.sync_all()
    })();
    if let Err(e) = written.and_then(|()| std::fs::rename(&temp, &gz)) {
        let _ = std::fs::remove_file(&temp);
        return Err(e);
    }
    // the rename reaches the disk before the original goes
    if let Some(dir) = gz.parent().filter(|d| !d.as_os_str().is_empty()) {
        File::open(dir)?.sync_all()?;
    }
    match std::fs::remove_file(path) {
        Err(e) if e.kind() != ErrorKind::NotFound => Err(e),
        _ => Ok(gz),
    }
}

/// Whether the file starts as a gzip stream does.
pub fn starts_gzip(head: &[u8]) -> bool {
    head.starts_with(&GZIP_MAGIC)
}

/// The text of a compressed recording, up to its last newline: a last line cut mid-row, or a gzip stream cut
/// short (the process died, or the disk filled, while it was written), is dropped with a warning. Corrupt data is
/// an error of kind `InvalidData` naming the line it follows.
pub fn decoder<R: BufRead>(input: R, origin: &str) -> WholeLines<Members<R>> {
    WholeLines::new(Members { member: Some(GzDecoder::new(input)), origin: origin.to_string() }, origin)
}

/// The members of a gzip file one after the other (as `gzip -d` reads them), and what may follow the last: zero
/// bytes (the block padding of a tape, `dd` or a transfer tool) end the data, as `gzip` takes them; anything else
/// that does not start as a gzip member, before or after them, is corrupt data (a damaged header would hide the
/// rows behind it). A file padded so was refused as "invalid gzip header"; a few bytes of rubbish after the end
/// were taken for a member cut short.
pub struct Members<R: BufRead> {
    /// The member being read; None once the data have ended.
    member: Option<GzDecoder<R>>,
    origin: String,
}

impl<R: BufRead> Read for Members<R> {
    fn read(&mut self, out: &mut [u8]) -> std::io::Result<usize> {
        loop {
            let Some(member) = self.member.as_mut() else { return Ok(0) };
            let n = member.read(out)?;
            if n > 0 || out.is_empty() {
                return Ok(n);
            }
            // the member ended: another one follows, or the end, or padding
            let mut rest = self.member.take().map(GzDecoder::into_inner).expect("a member was read");
            let head = rest.fill_buf()?;
            // a member starts with the magic (of which a buffer's end may show only the first byte)
            if head.starts_with(&GZIP_MAGIC) || *head == GZIP_MAGIC[..1] {
                self.member = Some(GzDecoder::new(rest));
                continue;
            }
            let mut zeros: u64 = 0;
            loop {
                let buf = rest.fill_buf()?;
                if buf.is_empty() {
                    if zeros > 0 {
                        tracing::info!(recording = %self.origin, zero_bytes = zeros,
                            "zero bytes after the compressed data (block padding): ignored, as gzip does");
                    }
                    return Ok(0);
                }
                let k = buf.iter().take_while(|&&b| b == 0).count();
                if k == 0 {
                    let padding = if zeros > 0 { format!(" and {zeros} zero bytes of padding") } else { String::new() };
                    return Err(std::io::Error::new(
                        ErrorKind::InvalidData,
                        format!("data that is not gzip after the compressed stream's end{padding}"),
                    ));
                }
                rest.consume(k);
                zeros += k as u64;
            }
        }
    }
}

/// Hands out the text of `inner` a whole line at a time (see [`decoder`]). A line longer than
/// [`super::MAX_LINE_BYTES`] is handed out as it comes, for the reader to refuse: the buffer stays small whatever
/// the stream holds (a gzip bomb of one endless line).
pub struct WholeLines<R> {
    inner: R,
    origin: String,
    buf: Vec<u8>,
    /// `buf[start..ready]` is whole lines not yet handed out; `buf[ready..end]` a line still being read.
    start: usize,
    ready: usize,
    end: usize,
    done: bool,
    /// Newlines read so far, for messages.
    lines: u64,
    /// The header line's commas, once it is whole: a last line without newline that has as many is a whole row.
    header_commas: Option<usize>,
}

/// Whether `tail`, a last line with no newline after it, is a whole row of a file whose header has `header_commas`
/// commas: as many cells, the last one not empty. A file written without a final newline ends so; a cut row almost
/// never does (only a cut inside its last value, which then reads short: the warning says so).
pub fn whole_row(header_commas: Option<usize>, tail: &[u8]) -> bool {
    header_commas == Some(memchr::memchr_iter(b',', tail).count())
        && tail.last().is_some_and(|&b| !matches!(b, b',' | b'\r'))
}

/// The warning for a last line kept by [`whole_row`].
pub const NO_FINAL_NEWLINE: &str = "the last line has no newline but all its cells: read as a row (had writing \
                                     been cut inside its last value, that value would read short)";

impl<R: Read> WholeLines<R> {
    pub fn new(inner: R, origin: &str) -> WholeLines<R> {
        WholeLines {
            inner,
            origin: origin.to_string(),
            buf: vec![0; 1 << 17],
            start: 0,
            ready: 0,
            end: 0,
            done: false,
            lines: 0,
            header_commas: None,
        }
    }

    /// The end of the text: a partial last line goes, with a warning, unless the text has no newline at all (a
    /// header alone: the parser says what is wrong with it).
    fn finish(&mut self, cut_stream: bool) {
        self.done = true;
        let tail = self.end - self.ready;
        if cut_stream {
            tracing::warn!(recording = %self.origin, line = self.lines + 1, dropped_bytes = tail,
                "the compressed stream was cut short (writing was interrupted): kept the rows before it");
        } else if tail > 0 && self.lines > 0 && whole_row(self.header_commas, &self.buf[self.ready..self.end]) {
            tracing::warn!(recording = %self.origin, line = self.lines + 1, "{NO_FINAL_NEWLINE}");
            self.ready = self.end;
        } else if tail > 0 && self.lines > 0 {
            tracing::warn!(recording = %self.origin, dropped_bytes = tail,
                "the last line was cut mid-row (writing was interrupted): dropped it");
        } else {
            self.ready = self.end;
        }
    }
}

impl<R: Read> Read for WholeLines<R> {
    fn read(&mut self, out: &mut [u8]) -> std::io::Result<usize> {
        loop {
            if self.start < self.ready {
                let n = out.len().min(self.ready - self.start);
                out[..n].copy_from_slice(&self.buf[self.start..self.start + n]);
                self.start += n;
                return Ok(n);
            }
            if self.done || out.is_empty() {
                return Ok(0);
            }
            // the partial line to the front, room behind it
            self.buf.copy_within(self.ready..self.end, 0);
            self.end -= self.ready;
            (self.start, self.ready) = (0, 0);
            if self.end == self.buf.len() {
                self.buf.resize(2 * self.buf.len(), 0);
            }
            match self.inner.read(&mut self.buf[self.end..]) {
                Ok(0) => self.finish(false),
                Ok(n) => {
                    let new = &self.buf[self.end..self.end + n];
                    if self.lines == 0
                        && let Some(first) = memchr::memchr(b'\n', new)
                    {
                        // nothing handed out yet: the buffer starts with the header
                        let header = &self.buf[..self.end + first];
                        self.header_commas = Some(memchr::memchr_iter(b',', header).count());
                    }
                    if let Some(i) = memchr::memrchr(b'\n', new) {
                        self.lines += memchr::memchr_iter(b'\n', new).count() as u64;
                        self.ready = self.end + i + 1;
                    }
                    self.end += n;
                    if self.end - self.ready > super::MAX_LINE_BYTES {
                        self.ready = self.end;
                    }
                }
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                Err(e) if e.kind() == ErrorKind::UnexpectedEof => self.finish(true),
                Err(e) => {
                    return Err(std::io::Error::new(
                        ErrorKind::InvalidData,
                        format!("corrupt gzip data after line {}: {e}", self.lines),
                    ));
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    fn gzip(text: &[u8]) -> Vec<u8> {
        let mut e = GzEncoder::new(Vec::new(), Compression::default());
        e.write_all(text).expect("compress");
        e.finish().expect("finish")
    }

    fn read_all(bytes: Vec<u8>) -> std::io::Result<String> {
        let mut s = String::new();
        decoder(bytes.as_slice(), "t").read_to_string(&mut s)?;
        Ok(s)
    }

    #[test]
    fn whole_lines_pass_and_a_cut_tail_goes() {
        assert_eq!(read_all(gzip(b"t_s,a\n1,2\n")).expect("reads"), "t_s,a\n1,2\n");
        assert_eq!(read_all(gzip(b"t_s,a\n1,2\n3,")).expect("reads"), "t_s,a\n1,2\n");
        assert_eq!(read_all(gzip(b"t_s,a\n1,2\n3")).expect("reads"), "t_s,a\n1,2\n");
        // a whole row without the final newline is a row
        assert_eq!(read_all(gzip(b"t_s,a\n1,2\n3,4")).expect("reads"), "t_s,a\n1,2\n3,4");
        assert_eq!(read_all(gzip(b"t_s,a")).expect("reads"), "t_s,a");
        assert_eq!(read_all(gzip(b"")).expect("reads"), "");
        // lines longer than the buffer
        let long = format!("t_s,a\n{}\n", "1".repeat(300_000));
        assert_eq!(read_all(gzip(long.as_bytes())).expect("reads"), long);
    }

    #[test]
    fn a_stream_cut_short_keeps_the_whole_lines_before_the_cut() {
        let text: String = (0..20_000).map(|k| format!("{k},{}\n", k * 7)).collect();
        let text = format!("t_s,a\n{text}");
        let full = gzip(text.as_bytes());
        for keep in [full.len() - 4, full.len() / 2, 100] {
            let got = read_all(full[..keep].to_vec()).expect("a cut stream reads");
            assert!(
                text.starts_with(&got) && got.ends_with('\n'),
                "{keep}: {:?}",
                &got[got.len().saturating_sub(20)..]
            );
        }
    }

    #[test]
    fn members_follow_each_other_and_zero_padding_ends_the_data() {
        let mut two = gzip(b"t_s,x\n0,1\n");
        two.extend(gzip(b"1,2\n"));
        assert_eq!(read_all(two.clone()).expect("two members"), "t_s,x\n0,1\n1,2\n");
        // a tape's or dd's block padding: gzip takes it (\"trailing zero bytes ignored\"); it was refused here
        let mut padded = two.clone();
        padded.extend([0u8; 512]);
        assert_eq!(read_all(padded).expect("padded"), "t_s,x\n0,1\n1,2\n");
        let mut bad = two;
        bad.extend([0u8; 10]);
        bad.extend(b"rubbish");
        let e = read_all(bad).expect_err("data after the padding");
        assert_eq!(e.kind(), ErrorKind::InvalidData, "{e}");
        assert!(e.to_string().contains("10 zero bytes"), "{e}");
        // a few bytes of rubbish straight after a complete stream: not a member cut short (it was read so, and
        // the warning blamed an interrupted write); a damaged second member's header likewise
        for rubbish in [&b"xyz"[..], b"\n", b"rubbish and more rubbish", b"\x1f\x00abcdefghijkl"] {
            let mut bad = gzip(b"t_s,x\n0,1\n");
            bad.extend(rubbish);
            let e = read_all(bad).expect_err("rubbish after the end");
            assert_eq!(e.kind(), ErrorKind::InvalidData, "{rubbish:?}: {e}");
            assert!(e.to_string().contains("not gzip after the compressed stream's end"), "{e}");
            assert!(e.to_string().contains("after line 2"), "{e}");
        }
        // the magic, then the end: a member cut short in its header
        let mut cut = gzip(b"t_s,x\n0,1\n");
        cut.extend(GZIP_MAGIC);
        assert_eq!(read_all(cut).expect("a cut member"), "t_s,x\n0,1\n");
    }

    #[test]
    fn corrupt_data_is_invalid_data() {
        let text: String = (0..20_000).map(|k| format!("{k},{}\n", k * 7)).collect();
        let mut bytes = gzip(text.as_bytes());
        let n = bytes.len();
        for b in &mut bytes[n / 2..n / 2 + 16] {
            *b ^= 0x55;
        }
        let e = read_all(bytes).expect_err("corrupt");
        assert_eq!(e.kind(), ErrorKind::InvalidData, "{e}");
        assert!(e.to_string().contains("after line"), "{e}");
    }

    #[test]
    fn compress_replaces_the_file_and_leaves_no_temporary() {
        let dir = tempfile::tempdir().expect("tmp");
        let plain = dir.path().join("pump1-1.csv");
        std::fs::write(&plain, "t_s,a\n1,2\n").expect("write");
        let gz = compress(&plain).expect("compresses");
        assert_eq!(gz, dir.path().join("pump1-1.csv.gz"));
        assert!(!plain.exists() && !temp_path(&plain).exists());
        let mut s = String::new();
        flate2::bufread::MultiGzDecoder::new(std::io::BufReader::new(File::open(&gz).expect("open")))
            .read_to_string(&mut s)
            .expect("gunzip");
        assert_eq!(s, "t_s,a\n1,2\n");
        assert!(compress(&dir.path().join("missing.csv")).is_err());
        assert_eq!(std::fs::read_dir(dir.path()).expect("dir").count(), 1);
        assert!(is_temp_of(".pump1-1.csv.gz.tmp", "pump1"));
        assert!(!is_temp_of(".pump12-1.csv.gz.tmp", "pump1") && !is_temp_of("pump1-1.csv.gz", "pump1"));
        assert!(!is_temp_of(".pump1-2-1796702003802.csv.gz.tmp", "pump1"), "drive pump1-2's");
        assert!(is_temp_of(".pump1-2-1796702003802.csv.gz.tmp", "pump1-2"));
    }
}

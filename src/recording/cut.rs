//! Opening a recording whose last line may have been cut mid-row (the service stopped, or the disk filled, while
//! a row was being written): the bytes after the last newline are dropped with a warning, so every reader sees
//! whole lines. A cut anywhere else is still the parser's error. Our writers end every row with a newline.
//! A compressed recording (gzip, told by its first bytes whatever its name) is read through [`super::gz`], which
//! drops a cut last line, or the rest of a stream cut short, the same way. What is not a regular file (a named pipe,
//! `<(…)` in a shell) is read as a stream, never seeked: gzip is told from its first bytes as they are buffered.

use std::fs::File;
use std::io::{BufReader, Chain, Cursor, Read, Seek, SeekFrom, Take};
use std::path::Path;

use super::RecordingError;
use super::gz::{self, WholeLines};

/// A recording file as the readers take it: its text up to its last newline.
pub struct RecordingFile(Text);

enum Text {
    Plain(Take<File>),
    Gzip(Box<WholeLines<gz::Members<BufReader<File>>>>),
    /// From a pipe, plain or compressed: whole lines as they come.
    Stream(Box<WholeLines<Piped>>),
    GzipStream(Box<WholeLines<gz::Members<BufReader<Piped>>>>),
}

/// A pipe's first bytes (read to tell gzip) put back in front of the rest.
type Piped = Chain<Cursor<Vec<u8>>, File>;

impl Read for RecordingFile {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        match &mut self.0 {
            Text::Plain(f) => f.read(buf),
            Text::Gzip(g) => g.read(buf),
            Text::Stream(s) => s.read(buf),
            Text::GzipStream(g) => g.read(buf),
        }
    }
}

/// Opens `path`, leaving out a last line that has no newline; a gzip file is decompressed as it is read.
pub fn open(path: &Path) -> Result<RecordingFile, RecordingError> {
    let name = path.display().to_string();
    let io = |error| RecordingError::Io { path: name.clone(), error };
    // a named pipe with no writer blocked `open` forever (`estimate` on a FIFO hung): opened without waiting, it
    // reads as empty, which the readers say
    let file = crate::error::open_without_waiting(path).map_err(io)?;
    let meta = file.metadata().map_err(io)?;
    if meta.is_dir() {
        let error = std::io::Error::new(std::io::ErrorKind::IsADirectory, "a directory, not a recording file");
        return Err(io(error));
    }
    let mut file = file;
    let mut head = [0u8; 2];
    let mut got = 0;
    // a pipe may hand out one byte at a time
    while got < head.len() {
        match file.read(&mut head[got..]) {
            Ok(0) => break,
            Ok(n) => got += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(io(e)),
        }
    }
    let compressed = gz::starts_gzip(&head[..got]);
    if !meta.is_file() {
        let input = Cursor::new(head[..got].to_vec()).chain(file);
        return Ok(RecordingFile(if compressed {
            Text::GzipStream(Box::new(gz::decoder(BufReader::with_capacity(1 << 16, input), &name)))
        } else {
            Text::Stream(Box::new(WholeLines::new(input, &name)))
        }));
    }
    file.seek(SeekFrom::Start(0)).map_err(io)?;
    if compressed {
        return Ok(RecordingFile(Text::Gzip(Box::new(gz::decoder(BufReader::with_capacity(1 << 16, file), &name)))));
    }
    let len = meta.len();
    let mut keep = whole_lines_len(&mut file, len).map_err(io)?;
    if keep > 0 && keep < len && len - keep <= super::MAX_LINE_BYTES as u64 {
        let mut tail = vec![0; (len - keep) as usize];
        file.seek(SeekFrom::Start(keep)).map_err(io)?;
        file.read_exact(&mut tail).map_err(io)?;
        if gz::whole_row(header_commas(&mut file).map_err(io)?, &tail) {
            tracing::warn!(recording = %name, "{}", gz::NO_FINAL_NEWLINE);
            keep = len;
        }
    }
    if keep < len {
        tracing::warn!(recording = %name, dropped_bytes = len - keep,
            "the last line was cut mid-row (writing was interrupted): dropped it");
    }
    file.seek(SeekFrom::Start(0)).map_err(io)?;
    Ok(RecordingFile(Text::Plain(file.take(keep))))
}

/// The commas of the file's first line, if it ends within [`super::MAX_LINE_BYTES`].
fn header_commas<R: Read + Seek>(file: &mut R) -> std::io::Result<Option<usize>> {
    file.seek(SeekFrom::Start(0))?;
    let mut head = Vec::new();
    file.take(super::MAX_LINE_BYTES as u64).read_to_end(&mut head)?;
    Ok(memchr::memchr(b'\n', &head).map(|i| memchr::memchr_iter(b',', &head[..i]).count()))
}

/// The length up to and including the last newline: `len` when the file ends with one, is empty, or has none at
/// all (a header alone: the parser says what is wrong with it).
fn whole_lines_len<R: Read + Seek>(file: &mut R, len: u64) -> std::io::Result<u64> {
    const BLOCK: u64 = 1 << 16;
    let mut end = len;
    let mut buf = vec![0u8; BLOCK as usize];
    while end > 0 {
        let start = end.saturating_sub(BLOCK);
        let block = &mut buf[..(end - start) as usize];
        file.seek(SeekFrom::Start(start))?;
        file.read_exact(block)?;
        if let Some(i) = memchr::memrchr(b'\n', block) {
            return Ok(start + i as u64 + 1);
        }
        end = start;
    }
    Ok(len)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_a_tail_without_newline_goes() {
        let len = |s: &str| whole_lines_len(&mut std::io::Cursor::new(s.as_bytes()), s.len() as u64).expect("reads");
        assert_eq!(len("t_s,a\n1,2\n"), 10);
        assert_eq!(len("t_s,a\n1,2\n3,"), 10);
        assert_eq!(len("t_s,a"), 5);
        assert_eq!(len(""), 0);
    }
}

//! Streaming a recording CSV in batches of columns (for `estimate`): flat memory, and only the asked-for columns
//! are turned into numbers.
//!
//! The rules are those of [`super::parse`], and a file is accepted or rejected exactly as `parse` would:
//! cells are trimmed of ASCII spaces, an empty cell is NaN, `t_s` must be finite and strictly increasing, a row
//! with more or fewer cells than the header is an error, and so are an empty file, a file without rows and a header
//! without `t_s`. Every cell is checked, also in columns nobody asked for: those are not parsed but scanned
//! against the plain decimal grammar (sign, digits, point, exponent), which costs a fraction of a parse; a cell that
//! does not fit it (`nan`, `inf`, or garbage) goes to `str::parse` as in `parse`, so `nan` is still accepted and
//! `abc` still rejected with file, line and column.
//!
//! How: the file is read in 256 KiB chunks and cut into lines with memchr; asked-for cells are parsed with
//! fast-float2 (bit for bit what `str::parse::<f64>` gives, a proptest below checks it). A line the fast path
//! turns down (spaces other than plain ones, a bad cell, a ragged row) is read again by a careful path that applies
//! `parse`'s checks in `parse`'s order, so the error is the one `parse` reports.
//!
//! Differences from `parse`:
//! - Line numbers in errors are the row's physical line (1-based, counting `\n`). The csv crate under `parse`
//!   names the line before the row in a CRLF file, and the first of any blank lines before it.
//! - The fast path knows no CSV quoting. From the first line that holds a `"`, or a carriage return that does not
//!   end the line, to the end of the file, rows go through the csv crate as in `parse` (with its line numbers,
//!   shifted to the file's). A header with such a byte sends the whole file through the csv crate.

use std::io::{Chain, Cursor, Read};
use std::path::Path;

use super::read::{RecordingError, cell_value, check_time, header_names};

/// Bytes asked of the reader at a time; a longer line grows the buffer. The first read holds the header and what
/// [`StreamReader::into_chunks`] hands on: a quarter of a mebibyte keeps that first piece as long as the chunks
/// `estimate` takes, so neither thread waits on a longer one.
const CHUNK_BYTES: usize = 1 << 18;
const UTF8_BOM: &[u8] = b"\xef\xbb\xbf";

/// Rows of a recording, column by column: `t_s` and the columns [`StreamReader::select`] chose, in its order.
#[derive(Debug, Default, Clone, PartialEq)]
pub struct Batch {
    pub t_s: Vec<f64>,
    pub columns: Vec<Vec<f64>>,
}

impl Batch {
    pub fn len(&self) -> usize {
        self.t_s.len()
    }

    pub fn is_empty(&self) -> bool {
        self.t_s.is_empty()
    }

    fn reset(&mut self, width: usize) {
        self.t_s.clear();
        self.columns.resize_with(width, Vec::new);
        for c in &mut self.columns {
            c.clear();
        }
    }

    /// Drops any values of a row that was begun but not finished.
    fn truncate_to_rows(&mut self) {
        let rows = self.t_s.len();
        for c in &mut self.columns {
            c.truncate(rows);
        }
    }
}

/// What becomes of a column's cells.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Role {
    /// Checked to be a number or empty, then dropped.
    Check,
    Time,
    /// Parsed into `Batch::columns[slot]`.
    Slot(usize),
}

/// A recording read batch by batch. Errors name the file (`origin`), the line and the column, as [`super::parse`].
pub struct StreamReader<R: Read> {
    origin: String,
    names: Vec<String>,
    t_index: usize,
    roles: Vec<Role>,
    selected: usize,
    input: Input<R>,
    last_t: f64,
    rows: u64,
}

enum Input<R: Read> {
    Lines(Lines<R>),
    Csv(Box<CsvInput<R>>),
    /// Only while switching from `Lines` to `Csv`.
    Done,
}

/// The fast path's input: a buffer of whole lines plus the start of the next.
struct Lines<R> {
    reader: R,
    buf: Vec<u8>,
    /// `buf[start..end]` is read and not yet handed out.
    start: usize,
    end: usize,
    eof: bool,
    /// Lines handed out so far (the physical number of the last one).
    line: u64,
}

/// The csv crate's reader over what is left of the file, for files with quotes.
struct CsvInput<R: Read> {
    csv: csv::Reader<Chain<Cursor<Vec<u8>>, R>>,
    record: csv::ByteRecord,
    /// Physical line = csv crate's line + this.
    line_shift: i64,
    /// The first record's line, where the csv crate's count is off.
    first_line: Option<u64>,
}

impl StreamReader<super::RecordingFile> {
    /// Opens a recording file and reads its header. Nothing is selected yet: see [`StreamReader::select`]. A last
    /// line cut mid-row is dropped with a warning (see [`super::cut`]).
    pub fn open(path: &Path) -> Result<StreamReader<super::RecordingFile>, RecordingError> {
        let name = path.display().to_string();
        let file = super::cut::open(path)?;
        StreamReader::new(file, &name)
    }
}

impl<R: Read> StreamReader<R> {
    /// Reads the header of recording CSV text; `origin` names it in errors.
    pub fn new(reader: R, origin: &str) -> Result<StreamReader<R>, RecordingError> {
        let io_err = |source| RecordingError::Io { path: origin.to_string(), source };
        let mut lines = Lines { reader, buf: vec![0; CHUNK_BYTES], start: 0, end: 0, eof: false, line: 0 };
        while lines.end < UTF8_BOM.len() && !lines.eof {
            lines.fill().map_err(io_err)?;
        }
        if lines.buf[..lines.end].starts_with(UTF8_BOM) {
            lines.start = UTF8_BOM.len();
        }
        let header = loop {
            match lines.next_line().map_err(io_err)? {
                None => break None,
                Some((a, b, _)) if is_blank(&lines.buf[a..b]) => continue,
                Some(found) => break Some(found),
            }
        };
        let (names, t_index, input) = match header {
            None => {
                let (names, t_index) = header_names(std::iter::empty(), origin)?;
                (names, t_index, Input::Lines(lines))
            }
            Some((a, b, number)) => {
                let line = &lines.buf[a..b];
                let text = std::str::from_utf8(line).ok().filter(|_| !needs_csv(line));
                match text {
                    Some(text) => {
                        let (names, t_index) = header_names(text.split(',').map(str::trim), origin)?;
                        (names, t_index, Input::Lines(lines))
                    }
                    None => {
                        // quotes or odd line ends in the header: the csv crate reads the whole file, as `parse` does
                        let mut input = CsvInput::new(lines, a, number, true);
                        let headers = input.csv.headers().map_err(|e| RecordingError::File {
                            path: origin.to_string(),
                            message: format!("cannot read the header row: {e}"),
                        })?;
                        let (names, t_index) = header_names(headers.iter(), origin)?;
                        (names, t_index, Input::Csv(Box::new(input)))
                    }
                }
            }
        };
        let roles = (0..names.len()).map(|i| if i == t_index { Role::Time } else { Role::Check }).collect();
        Ok(StreamReader {
            origin: origin.to_string(),
            names,
            t_index,
            roles,
            selected: 0,
            input,
            last_t: f64::NEG_INFINITY,
            rows: 0,
        })
    }

    /// The header's column names, in file order.
    pub fn names(&self) -> &[String] {
        &self.names
    }

    /// Where a column is, by name.
    pub fn index_of(&self, name: &str) -> Option<usize> {
        self.names.iter().position(|n| n == name)
    }

    /// Chooses the columns that [`StreamReader::read_batch`] returns besides `t_s` (indices into
    /// [`StreamReader::names`], not `t_s`'s); the cells of every other column are only checked.
    pub fn select(&mut self, columns: &[usize]) {
        debug_assert!(!columns.contains(&self.t_index), "t_s always comes in Batch::t_s");
        self.roles = (0..self.names.len())
            .map(|i| match columns.iter().position(|&c| c == i) {
                _ if i == self.t_index => Role::Time,
                Some(slot) => Role::Slot(slot),
                None => Role::Check,
            })
            .collect();
        self.selected = columns.len();
    }

    /// Rows read so far.
    pub fn rows(&self) -> u64 {
        self.rows
    }

    /// Replaces `batch`'s content with up to `max_rows` next rows; 0 rows means the end of the file.
    pub fn read_batch(&mut self, batch: &mut Batch, max_rows: usize) -> Result<usize, RecordingError> {
        batch.reset(self.selected);
        while batch.len() < max_rows {
            let (t, line) = match &mut self.input {
                Input::Lines(lines) => {
                    let Some((a, b, number)) = lines.next_line().map_err(|source| io_error(&self.origin, source))?
                    else {
                        break;
                    };
                    let line = &lines.buf[a..b];
                    if is_blank(line) {
                        continue;
                    }
                    if let Some((t, _)) = fast_row(line, &self.roles, batch) {
                        (t, number)
                    } else {
                        batch.truncate_to_rows();
                        if needs_csv(line) {
                            self.switch_to_csv(a, number);
                            continue;
                        }
                        (careful_row(line, number, &self.names, &self.roles, &self.origin, batch)?, number)
                    }
                }
                Input::Csv(input) => match input.next_row(&self.names, &self.roles, &self.origin, batch)? {
                    Some(row) => row,
                    None => break,
                },
                Input::Done => break,
            };
            check_time(t, self.last_t, &self.origin, line)?;
            self.last_t = t;
            batch.t_s.push(t);
            self.rows += 1;
        }
        if batch.is_empty() && self.rows == 0 {
            return Err(RecordingError::File {
                path: self.origin.clone(),
                message: "no data rows after the header".into(),
            });
        }
        Ok(batch.len())
    }

    /// Hands the rest of the file, from the line that starts at `buf[from]`, to the csv crate.
    fn switch_to_csv(&mut self, from: usize, number: u64) {
        if let Input::Lines(lines) = std::mem::replace(&mut self.input, Input::Done) {
            self.input = Input::Csv(Box::new(CsvInput::new(lines, from, number, false)));
        }
    }

    /// The rest of the file as chunks of whole lines that [`ChunkParser::parse`] reads on the fast path, on as many
    /// threads as there are chunks, or `None` when the csv crate reads this file (quotes in the header). Call it
    /// right after [`StreamReader::select`], before any row is read.
    pub fn into_chunks(self) -> Option<(ChunkSource<R>, ChunkParser)> {
        match self.input {
            Input::Lines(lines) if self.rows == 0 => Some((
                ChunkSource {
                    reader: lines.reader,
                    // the buffer itself, its unread part moved to the front: no second buffer to fill
                    pending: {
                        let mut buf = lines.buf;
                        buf.truncate(lines.end);
                        buf.drain(..lines.start);
                        buf
                    },
                    eof: lines.eof,
                },
                ChunkParser { roles: self.roles, selected: self.selected },
            )),
            _ => None,
        }
    }
}

/// The rows of a recording after its header, handed out as chunks of whole lines (see [`StreamReader::into_chunks`]).
pub struct ChunkSource<R> {
    reader: R,
    /// Read and not yet handed out: what was read with the header, then the start of a line the last chunk did not
    /// take whole.
    pending: Vec<u8>,
    eof: bool,
}

/// One chunk of whole lines, its buffer reused from chunk to chunk.
#[derive(Debug, Default)]
pub struct Chunk {
    buf: Vec<u8>,
    len: usize,
}

impl Chunk {
    /// The lines, each ended by `\n` but for the file's last one.
    pub fn bytes(&self) -> &[u8] {
        &self.buf[..self.len]
    }
}

impl<R: Read> ChunkSource<R> {
    /// Replaces `chunk` with the next whole lines, about `bytes` of them: what is left of the last read, then more,
    /// cut at the last line end once `bytes` are in (a longer line comes whole; the rest of the first read comes
    /// whole, which is why that read is no longer than `estimate`'s chunks); `false` at the end of the file.
    pub fn next_chunk(&mut self, chunk: &mut Chunk, bytes: usize) -> std::io::Result<bool> {
        let want = bytes.max(1);
        if chunk.buf.len() < want.max(self.pending.len()) {
            chunk.buf.resize(want.max(self.pending.len()), 0);
        }
        chunk.buf[..self.pending.len()].copy_from_slice(&self.pending);
        chunk.len = self.pending.len();
        self.pending.clear();
        while !self.eof {
            if chunk.len >= want
                && let Some(last) = memchr::memrchr(b'\n', &chunk.buf[..chunk.len])
            {
                self.pending.extend_from_slice(&chunk.buf[last + 1..chunk.len]);
                chunk.len = last + 1;
                break;
            }
            // up to `want` bytes, or twice as many for a line that is longer
            let end = if chunk.len < want { want } else { 2 * chunk.len };
            if chunk.buf.len() < end {
                chunk.buf.resize(end, 0);
            }
            match self.reader.read(&mut chunk.buf[chunk.len..end]) {
                Ok(0) => self.eof = true,
                Ok(n) => chunk.len += n,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(e),
            }
        }
        Ok(chunk.len > 0)
    }
}

/// Reads chunks of a recording's lines into batches on the fast path alone, on any thread.
#[derive(Debug, Clone)]
pub struct ChunkParser {
    roles: Vec<Role>,
    selected: usize,
}

impl ChunkParser {
    /// Replaces `batch`'s content with the rows of `lines` (whole lines, blank ones skipped), and `times` with where
    /// each row's `t_s` text is in `lines`: `false` if a line is not for the fast path (quotes, a bad or unusual
    /// cell such as `nan`, a ragged row) or `t_s` is not finite and increasing within the chunk. The file must then
    /// be read by [`StreamReader::read_batch`], which gives its values or the error with its line and column. Rows
    /// of different chunks are not compared.
    pub fn parse(&self, lines: &[u8], batch: &mut Batch, times: &mut Vec<TimeText>) -> bool {
        batch.reset(self.selected);
        times.clear();
        let mut last_t = f64::NEG_INFINITY;
        let mut start = 0;
        for end in memchr::memchr_iter(b'\n', lines).chain(std::iter::once(lines.len())) {
            let line = &lines[start..end];
            let line_start = start;
            start = end + 1;
            if is_blank(line) {
                continue;
            }
            match fast_row(line, &self.roles, batch) {
                Some((t, text)) if t.is_finite() && t > last_t => {
                    batch.t_s.push(t);
                    times.push(text.shifted(line_start));
                    last_t = t;
                }
                _ => {
                    batch.truncate_to_rows();
                    return false;
                }
            }
        }
        true
    }
}

/// Where a row's `t_s` text is, as a range of bytes, so that it can be copied rather than formatted again (see
/// [`crate::recording::push_parsed_value`]); empty where it is not known.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct TimeText {
    start: u32,
    len: u32,
}

impl TimeText {
    const NONE: TimeText = TimeText { start: 0, len: 0 };

    fn at(start: usize, end: usize) -> TimeText {
        match (u32::try_from(start), u32::try_from(end - start)) {
            (Ok(start), Ok(len)) => TimeText { start, len },
            _ => TimeText::NONE,
        }
    }

    /// The same text in a buffer where the line starts at `line_start`.
    fn shifted(self, line_start: usize) -> TimeText {
        TimeText::at(self.start as usize + line_start, self.start as usize + line_start + self.len as usize)
    }

    /// The text in `lines`, the buffer it was found in (empty if it is not known).
    pub fn in_lines(self, lines: &[u8]) -> &[u8] {
        let start = self.start as usize;
        lines.get(start..start + self.len as usize).unwrap_or_default()
    }
}

fn io_error(origin: &str, source: std::io::Error) -> RecordingError {
    RecordingError::Io { path: origin.to_string(), source }
}

/// An empty line, which the csv crate skips.
fn is_blank(line: &[u8]) -> bool {
    line.is_empty() || line == b"\r"
}

/// A line the fast path cannot read: a quote, or a carriage return that does not end it (the csv crate ends a
/// record there).
fn needs_csv(line: &[u8]) -> bool {
    memchr::memchr(b'"', line).is_some() || memchr::memchr(b'\r', &line[..line.len().saturating_sub(1)]).is_some()
}

/// One line on the fast path into `batch`: `t_s` and where its text is in the line, or `None` for a line that needs
/// [`careful_row`] (the batch may then hold part of the row: see [`Batch::truncate_to_rows`]).
#[inline]
fn fast_row(line: &[u8], roles: &[Role], batch: &mut Batch) -> Option<(f64, TimeText)> {
    let last = roles.len() - 1;
    let mut i = 0;
    let mut t = (f64::NAN, TimeText::NONE);
    for (c, &role) in roles.iter().enumerate() {
        let end = match role {
            Role::Check => checked_cell_end(line, i)?,
            Role::Time => {
                let start = cell_start(line, i);
                let (v, end) = number_cell(line, start)?;
                // the number's text, without the blanks or carriage return that may follow it in the cell
                t = (v, TimeText::at(start, start + line[start..end].trim_ascii_end().len()));
                end
            }
            Role::Slot(slot) => {
                let (v, end) = number_cell(line, i)?;
                batch.columns[slot].push(v);
                end
            }
        };
        if c == last {
            if end != line.len() {
                return None;
            }
        } else {
            if end == line.len() {
                return None;
            }
            i = end + 1;
        }
    }
    Some(t)
}

/// Skips spaces and tabs, and a carriage return that ends the line.
#[inline]
fn skip_blanks(line: &[u8], mut i: usize) -> usize {
    loop {
        match line.get(i) {
            Some(b' ' | b'\t') => i += 1,
            Some(b'\r') if i + 1 == line.len() => i += 1,
            _ => return i,
        }
    }
}

/// Where the content of the cell starting at `i` starts, after blanks.
#[inline]
fn cell_start(line: &[u8], i: usize) -> usize {
    if matches!(line.get(i), Some(b' ' | b'\t' | b'\r')) { skip_blanks(line, i) } else { i }
}

/// Where a cell whose content ends at `i` ends: at a comma or the end of the line, after blanks; `None` if
/// anything else follows.
#[inline]
fn cell_end(line: &[u8], i: usize) -> Option<usize> {
    // the common case first: the comma or the end right there (a branch, not a jump table)
    let b = line.get(i).copied();
    if b == Some(b',') || b.is_none() {
        return Some(i);
    }
    let i = skip_blanks(line, i);
    match line.get(i) {
        None | Some(b',') => Some(i),
        Some(_) => None,
    }
}

/// The number in the cell starting at `i` (NaN when empty) and where the cell ends.
#[inline]
fn number_cell(line: &[u8], i: usize) -> Option<(f64, usize)> {
    let i = cell_start(line, i);
    match line.get(i) {
        None | Some(b',') => Some((f64::NAN, i)),
        Some(_) => {
            let (v, len) = fast_float2::parse_partial::<f64, _>(&line[i..]).ok()?;
            Some((v, cell_end(line, i + len)?))
        }
    }
}

/// Where the cell starting at `i` ends, if it is empty or a plain decimal number.
#[inline]
fn checked_cell_end(line: &[u8], i: usize) -> Option<usize> {
    let i = cell_start(line, i);
    match line.get(i) {
        None | Some(b',') => Some(i),
        Some(_) => cell_end(line, plain_number_end(line, i)?),
    }
}

/// The end of the plain decimal number `[+-]? (digits [. digits?] | . digits) ([eE] [+-]? digits)?` at `s[i..]`;
/// `str::parse::<f64>` accepts every such number (and also `inf`, `nan`, which this leaves to the careful path).
#[inline]
fn plain_number_end(s: &[u8], mut i: usize) -> Option<usize> {
    if matches!(s.get(i), Some(b'+' | b'-')) {
        i += 1;
    }
    let int_start = i;
    i = skip_digits(s, i);
    let mut digits = i - int_start;
    if s.get(i) == Some(&b'.') {
        let frac_start = i + 1;
        i = skip_digits(s, frac_start);
        digits += i - frac_start;
    }
    if digits == 0 {
        return None;
    }
    if matches!(s.get(i), Some(b'e' | b'E')) {
        i += 1;
        if matches!(s.get(i), Some(b'+' | b'-')) {
            i += 1;
        }
        let exp_start = i;
        i = skip_digits(s, i);
        if i == exp_start {
            return None;
        }
    }
    Some(i)
}

/// Skips ASCII digits, eight at a time where it can.
#[inline]
fn skip_digits(s: &[u8], mut i: usize) -> usize {
    while let Some(chunk) = s.get(i..i + 8) {
        let mut word = [0u8; 8];
        word.copy_from_slice(chunk);
        let v = u64::from_le_bytes(word);
        // a byte outside b'0'..=b'9' gets its high bit from adding 0x46 or subtracting 0x30 (fast_float's test);
        // carries and borrows only run towards later bytes, so the first flagged byte is the first non-digit
        let flagged =
            (v.wrapping_add(0x4646_4646_4646_4646) | v.wrapping_sub(0x3030_3030_3030_3030)) & 0x8080_8080_8080_8080;
        if flagged != 0 {
            return i + (flagged.trailing_zeros() / 8) as usize;
        }
        i += 8;
    }
    while s.get(i).is_some_and(u8::is_ascii_digit) {
        i += 1;
    }
    i
}

/// A line the fast path turned down, read with `parse`'s checks in `parse`'s order (field count, then `t_s`,
/// then the other cells in file order): the row's `t_s`, with the selected values pushed, or `parse`'s error.
fn careful_row(
    line: &[u8],
    number: u64,
    names: &[String],
    roles: &[Role],
    origin: &str,
    batch: &mut Batch,
) -> Result<f64, RecordingError> {
    let fields: Vec<&[u8]> = line.split(|&b| b == b',').collect();
    row_from_fields(&fields, number, names, roles, origin, batch)
}

/// The checks of [`super::parse`] on one row's fields; pushes the selected values, returns `t_s`.
fn row_from_fields(
    fields: &[&[u8]],
    number: u64,
    names: &[String],
    roles: &[Role],
    origin: &str,
    batch: &mut Batch,
) -> Result<f64, RecordingError> {
    if fields.len() != names.len() {
        return Err(RecordingError::Line {
            path: origin.into(),
            line: number,
            message: format!("{} fields, expected {} as in the header", fields.len(), names.len()),
        });
    }
    let t_index = roles.iter().position(|r| *r == Role::Time).unwrap_or(0);
    let t = cell_value(fields[t_index], origin, number, &names[t_index])?;
    let mut values = Vec::new();
    for (i, role) in roles.iter().enumerate() {
        if i != t_index {
            let v = cell_value(fields[i], origin, number, &names[i])?;
            if let Role::Slot(slot) = role {
                values.push((*slot, v));
            }
        }
    }
    for (slot, v) in values {
        batch.columns[slot].push(v);
    }
    Ok(t)
}

impl<R: Read> Lines<R> {
    /// The next line as `(start, end, number)` with `buf[start..end]` its bytes without the `\n`.
    fn next_line(&mut self) -> std::io::Result<Option<(usize, usize, u64)>> {
        loop {
            if let Some(k) = memchr::memchr(b'\n', &self.buf[self.start..self.end]) {
                let found = (self.start, self.start + k);
                self.start += k + 1;
                self.line += 1;
                return Ok(Some((found.0, found.1, self.line)));
            }
            if self.eof {
                if self.start == self.end {
                    return Ok(None);
                }
                let found = (self.start, self.end);
                self.start = self.end;
                self.line += 1;
                return Ok(Some((found.0, found.1, self.line)));
            }
            self.fill()?;
        }
    }

    /// Reads more, keeping `buf[start..end]` (moved to the front) and growing the buffer for a long line.
    fn fill(&mut self) -> std::io::Result<()> {
        if self.start > 0 {
            self.buf.copy_within(self.start..self.end, 0);
            self.end -= self.start;
            self.start = 0;
        }
        if self.end == self.buf.len() {
            self.buf.resize((2 * self.buf.len()).max(CHUNK_BYTES), 0);
        }
        loop {
            match self.reader.read(&mut self.buf[self.end..]) {
                Ok(0) => self.eof = true,
                Ok(n) => self.end += n,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                Err(e) => return Err(e),
            }
            return Ok(());
        }
    }
}

impl<R: Read> CsvInput<R> {
    /// The csv crate's reader from `lines.buf[from..]` on, the line there having physical number `number`.
    fn new(lines: Lines<R>, from: usize, number: u64, header: bool) -> CsvInput<R> {
        let rest = &lines.buf[from..lines.end];
        // The csv crate drops a BOM at the start of its input; one that starts a later line is data, so it is put
        // behind a blank line (which the csv crate skips, counting its line for the next record but not this one).
        let shield = rest.starts_with(UTF8_BOM);
        let mut head = Vec::with_capacity(1 + rest.len());
        if shield {
            head.push(b'\n');
        }
        head.extend_from_slice(rest);
        let csv = csv::ReaderBuilder::new()
            .has_headers(header)
            .flexible(true)
            .trim(csv::Trim::All)
            .from_reader(Cursor::new(head).chain(lines.reader));
        let line_shift = number as i64 - 1 - i64::from(shield);
        CsvInput { csv, record: csv::ByteRecord::new(), line_shift, first_line: shield.then_some(number) }
    }

    fn line(&mut self, position: Option<&csv::Position>) -> u64 {
        if let Some(first) = self.first_line.take() {
            return first;
        }
        position.map_or(0, |p| (p.line() as i64 + self.line_shift).max(0) as u64)
    }

    /// The next row: its `t_s` and physical line, with the selected values pushed to `batch`.
    fn next_row(
        &mut self,
        names: &[String],
        roles: &[Role],
        origin: &str,
        batch: &mut Batch,
    ) -> Result<Option<(f64, u64)>, RecordingError> {
        match self.csv.read_byte_record(&mut self.record) {
            Ok(false) => return Ok(None),
            Ok(true) => {}
            Err(e) => {
                let line = self.line(e.position());
                return Err(RecordingError::Line { path: origin.into(), line, message: e.to_string() });
            }
        }
        let position = self.record.position().cloned();
        let line = self.line(position.as_ref());
        let fields: Vec<&[u8]> = self.record.iter().collect();
        let t = row_from_fields(&fields, line, names, roles, origin, batch)?;
        Ok(Some((t, line)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::recording::parse;
    use proptest::prelude::*;

    /// Reads all of `text` with every column but `t_s` selected, `max_rows` at a time, through a reader that hands
    /// out `piece` bytes per read: (names, columns with t_s first as `parse` orders them).
    fn read_all(text: &[u8], max_rows: usize, piece: usize) -> Result<(Vec<String>, Vec<Vec<f64>>), RecordingError> {
        let mut r = StreamReader::new(Trickle { text, at: 0, piece }, "r.csv")?;
        let others: Vec<usize> = (0..r.names().len()).filter(|&i| r.names()[i] != "t_s").collect();
        r.select(&others);
        let mut columns = vec![Vec::new(); others.len() + 1];
        let mut batch = Batch::default();
        while r.read_batch(&mut batch, max_rows)? > 0 {
            assert!(batch.len() <= max_rows);
            columns[0].extend(&batch.t_s);
            for (c, values) in columns[1..].iter_mut().zip(&batch.columns) {
                assert_eq!(values.len(), batch.len());
                c.extend(values);
            }
        }
        let mut names = vec!["t_s".to_string()];
        names.extend(others.iter().map(|&i| r.names()[i].clone()));
        Ok((names, columns))
    }

    /// A reader that returns at most `piece` bytes a call, to cut lines at every place.
    struct Trickle<'a> {
        text: &'a [u8],
        at: usize,
        piece: usize,
    }

    impl Read for Trickle<'_> {
        fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
            let n = self.piece.min(buf.len()).min(self.text.len() - self.at);
            buf[..n].copy_from_slice(&self.text[self.at..self.at + n]);
            self.at += n;
            Ok(n)
        }
    }

    fn same_bits(a: &[f64], b: &[f64]) -> bool {
        a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits() || (x.is_nan() && y.is_nan()))
    }

    /// The streaming reader and `parse` agree on `text`: the same values, or both an error (the same one, but for
    /// line numbers and the ragged-row wording).
    fn assert_agrees(text: &str, max_rows: usize, piece: usize) {
        let whole = parse(text.as_bytes(), "r.csv");
        let streamed = read_all(text.as_bytes(), max_rows, piece);
        match (whole, streamed) {
            (Ok(rec), Ok((names, columns))) => {
                assert_eq!(rec.names(), names.as_slice(), "{text:?}");
                for (name, c) in names.iter().zip(&columns) {
                    assert!(same_bits(rec.column(name).expect("column"), c), "{name} in {text:?}");
                }
            }
            (Err(a), Err(b)) => match (&a, &b) {
                (
                    RecordingError::Cell { column: x, message: m, .. },
                    RecordingError::Cell { column: y, message: n, .. },
                ) => {
                    assert_eq!((x, m), (y, n), "{text:?}")
                }
                (RecordingError::File { message: m, .. }, RecordingError::File { message: n, .. }) => {
                    assert_eq!(m, n, "{text:?}")
                }
                (RecordingError::Line { .. }, RecordingError::Line { .. }) => {}
                _ => panic!("{text:?}: parse says {a}, the stream says {b}"),
            },
            (a, b) => panic!("{text:?}: parse gives {a:?}, the stream {b:?}"),
        }
        // the chunks may turn a file down, but what they take they read as `parse` does
        for want in [1, 7, 64] {
            if let Some(chunked) = read_chunked(text.as_bytes(), want, piece) {
                let rec = parse(text.as_bytes(), "r.csv").expect("the chunks took a file that `parse` rejects");
                for (name, c) in rec.names().iter().zip(&chunked) {
                    assert!(same_bits(rec.column(name).expect("column"), c), "{name} in {text:?}, chunks of {want}");
                }
            }
        }
    }

    /// All of `text` through [`StreamReader::into_chunks`], every column but `t_s` selected, in chunks of `want`
    /// bytes read `piece` bytes at a time: the columns in `parse`'s order (`t_s` first); `None` if a chunk
    /// was turned down or `t_s` does not increase from one chunk to the next. Checks that each chunk is whole lines
    /// and that together they are the file after the header.
    fn read_chunked(text: &[u8], want: usize, piece: usize) -> Option<Vec<Vec<f64>>> {
        let mut r = StreamReader::new(Trickle { text, at: 0, piece }, "r.csv").ok()?;
        let others: Vec<usize> = (0..r.names().len()).filter(|&i| r.names()[i] != "t_s").collect();
        r.select(&others);
        let (mut source, parser) = r.into_chunks()?;
        let mut columns = vec![Vec::new(); others.len() + 1];
        let (mut chunk, mut batch, mut all) = (Chunk::default(), Batch::default(), Vec::new());
        let mut times = Vec::new();
        let mut turned_down = false;
        while source.next_chunk(&mut chunk, want).expect("in memory") {
            assert!(!all.is_empty() || !chunk.bytes().is_empty());
            assert!(all.is_empty() || all.ends_with(b"\n"), "a chunk ends a line, but for the file's last");
            all.extend_from_slice(chunk.bytes());
            if turned_down || !parser.parse(chunk.bytes(), &mut batch, &mut times) {
                turned_down = true;
                continue;
            }
            assert_eq!(times.len(), batch.len());
            for (t, text) in batch.t_s.iter().zip(&times) {
                let text = std::str::from_utf8(text.in_lines(chunk.bytes())).expect("ASCII");
                assert_eq!(text.parse::<f64>().ok(), Some(*t), "{text:?}");
            }
            if batch.t_s.first().is_some_and(|t| columns[0].last().is_some_and(|last| t <= last)) {
                turned_down = true;
            }
            columns[0].extend(&batch.t_s);
            for (c, values) in columns[1..].iter_mut().zip(&batch.columns) {
                assert_eq!(values.len(), batch.len());
                c.extend(values);
            }
        }
        assert!(text.ends_with(&all), "the chunks are the file after the header");
        let header = &text[..text.len() - all.len()];
        assert!(header.ends_with(b"\n") || all.is_empty(), "the header is not in the chunks");
        (!turned_down).then_some(columns)
    }

    #[test]
    fn clean_files_go_through_the_chunks_whole() {
        for text in [
            "t_s,omega_rad_s\r\n0,1\r\n0.001,2\r\n",
            "\u{feff}t_s,omega_rad_s\n0,1\n0.001,2",
            " t_s , omega_rad_s \n 0 , 1 \n\t0.001\t,\t2\t\n",
            "\n\nt_s,omega_rad_s\n\n0,1\n\r\n\n0.001,2\n\n",
            "omega_rad_s,t_s,x\n1.5,0,\n,0.001,3\n2,0.002,-4e-3\n-0.25,0.003,1E+5\n",
        ] {
            for (want, piece) in [(1, 1), (5, 3), (64, 2), (1 << 18, 1 << 20)] {
                let chunked = read_chunked(text.as_bytes(), want, piece).expect("a clean file is taken");
                let rec = parse(text.as_bytes(), "r.csv").expect("valid");
                for (name, c) in rec.names().iter().zip(&chunked) {
                    assert!(same_bits(rec.column(name).expect("column"), c), "{name} in {text:?}");
                }
            }
        }
        // a line longer than the chunk comes whole
        let long = format!("t_s,x\n0,{}\n0.001,2\n", "1".repeat(300));
        assert!(read_chunked(long.as_bytes(), 16, 7).is_some());
    }

    #[test]
    fn the_chunks_turn_down_what_needs_the_careful_path() {
        for text in [
            "t_s,x\n0,1\n0.001,\"2\"\n",
            "t_s,x\n0,1\n0.001,abc\n",
            "t_s,x\n0,1,2\n",
            "t_s,x\n0.001,1\n0.001,2\n",
            "t_s,x\n0.002,1\n0.001,2\n",
            "t_s,x\n,1\n",
            "t_s,x\n0,1\r0.001,2\n",
        ] {
            for want in [1, 64] {
                assert!(read_chunked(text.as_bytes(), want, 3).is_none(), "{text:?} in chunks of {want}");
            }
        }
        // quotes in the header: the csv crate reads the whole file
        let r = StreamReader::new("\"t_s\",x\n0,1\n".as_bytes(), "r.csv").expect("header");
        assert!(r.into_chunks().is_none());
        // `nan` and `inf` are parsed where a column is selected, and left to the careful path where it is only checked
        let taken = |text: &str, selected: &[usize]| {
            let mut r = StreamReader::new(text.as_bytes(), "r.csv").expect("header");
            r.select(selected);
            let (mut source, parser) = r.into_chunks().expect("no quotes");
            let (mut chunk, mut batch) = (Chunk::default(), Batch::default());
            source.next_chunk(&mut chunk, 64).expect("in memory");
            parser.parse(chunk.bytes(), &mut batch, &mut Vec::new())
        };
        for text in ["t_s,x\n0,nan\n", "t_s,x\n0,-inf\n"] {
            assert!(taken(text, &[1]));
            assert!(!taken(text, &[]));
        }
    }

    #[test]
    fn reads_the_selected_columns_in_batches() {
        let text = "omega_rad_s, t_s ,foo\n 1.5 ,0.0,\n,0.001,3\n2,0.002,-4e-3\n";
        let mut r = StreamReader::new(text.as_bytes(), "r.csv").expect("header");
        assert_eq!(r.names(), ["omega_rad_s", "t_s", "foo"]);
        let foo = r.index_of("foo").expect("foo");
        let omega = r.index_of("omega_rad_s").expect("omega");
        r.select(&[foo, omega]);
        let mut b = Batch::default();
        assert_eq!(r.read_batch(&mut b, 2).expect("rows"), 2);
        assert_eq!(b.t_s, [0.0, 0.001]);
        assert!(b.columns[0][0].is_nan() && b.columns[0][1] == 3.0);
        assert!(b.columns[1][0] == 1.5 && b.columns[1][1].is_nan());
        assert_eq!(r.read_batch(&mut b, 2).expect("rows"), 1);
        assert_eq!(b.columns, [vec![-4e-3], vec![2.0]]);
        assert_eq!(r.read_batch(&mut b, 2).expect("end"), 0);
        assert_eq!(r.rows(), 3);
    }

    #[test]
    fn crlf_bom_spaces_quotes_and_blank_lines_read_as_parse_reads_them() {
        for text in [
            "t_s,omega_rad_s\r\n0,1\r\n0.001,2\r\n",
            "\u{feff}t_s,omega_rad_s\n0,1\n0.001,2",
            " t_s , omega_rad_s \n 0 , 1 \n\t0.001\t,\t2\t\n",
            "\"t_s\",omega_rad_s\n0,\"1\"\n0.001,2\n",
            "t_s,omega_rad_s\n0,1\n\"0.001\",\"2.5\"\n",
            "t_s,omega_rad_s\n0,1\n0.001,2\n\"0.002\",3\n0.003,4\n",
            "\n\nt_s,omega_rad_s\n\n0,1\n\r\n\n0.001,2\n\n",
            "t_s,omega_rad_s\r0,1\r0.001,2\r",
            "t_s,omega_rad_s\n0,nan\n0.001,-inf\n0.002,+Infinity\n0.003,1.\n0.004,.5\n0.005,1E5\n",
            "t_s,omega_rad_s\n0,1\x0c\n",
            "t_s,omega_rad_s\n0,\r\n0.001,\r\n",
            "t_s\n0\n1\n",
        ] {
            for (max_rows, piece) in [(1, 1), (2, 3), (4096, 1 << 20)] {
                assert_agrees(text, max_rows, piece);
            }
            read_all(text.as_bytes(), 3, 2).expect("a valid file");
        }
    }

    #[test]
    fn errors_name_the_physical_line_and_the_column() {
        let err = |text: &str| read_all(text.as_bytes(), 4096, 1 << 20).expect_err("bad input").to_string();
        let e = err("t_s,omega_rad_s,f_set_hz\n0,1,2\n0.001,abc,2\n");
        assert!(e.contains("line 3") && e.contains("`omega_rad_s`") && e.contains("\"abc\""), "{e}");
        // a cell of a column nobody selected is still checked
        let mut r = StreamReader::new(&b"t_s,omega_rad_s,f_set_hz\n0,1,2\n0.001,1,2x\n"[..], "r.csv").expect("header");
        r.select(&[1]);
        let e = r.read_batch(&mut Batch::default(), 10).expect_err("bad unused cell").to_string();
        assert!(e.contains("r.csv") && e.contains("line 3") && e.contains("`f_set_hz`") && e.contains("2x"), "{e}");
        // CRLF and blank lines: the row's own line (the csv crate says 2 and 3 here)
        let e = err("t_s,omega_rad_s\r\n0,1\r\n0.001,abc\r\n");
        assert!(e.contains("line 3"), "{e}");
        let e = err("t_s,omega_rad_s\n0,1\n\n\n0.001,abc\n");
        assert!(e.contains("line 5"), "{e}");
        let e = err("t_s,omega_rad_s\n0,1\n0.001,1,2\n");
        assert!(e.contains("line 3") && e.contains("3 fields, expected 2"), "{e}");
        let e = err("t_s,omega_rad_s\n0,1\n0.001\n");
        assert!(e.contains("line 3") && e.contains("1 fields, expected 2"), "{e}");
        let e = err("t_s,omega_rad_s\n0,1\n0.002,1\n0.001,1\n");
        assert!(e.contains("line 4") && e.contains("`t_s`") && e.contains("backwards"), "{e}");
        let e = err("t_s,omega_rad_s\n0,1\n,1\n");
        assert!(e.contains("line 3") && e.contains("`t_s`") && e.contains("missing"), "{e}");
        // in the order `parse` checks: t_s before the other cells of its row
        let e = err("t_s,omega_rad_s\n0,1\nx,y\n");
        assert!(e.contains("`t_s`") && e.contains("\"x\""), "{e}");
        assert!(err("").contains("empty"));
        assert!(err("\n\n").contains("empty"));
        assert!(err("t_s,omega_rad_s\n").contains("no data rows"));
        assert!(err("omega_rad_s\n1\n").contains("no `t_s`"));
        assert!(err("t_s,t_s\n1,2\n").contains("twice"));
        // past a quote the csv crate reads, lines shifted to the file's
        let e = err("t_s,omega_rad_s\n0,1\n\"0.001\",1\n0.002,zz\n");
        assert!(e.contains("line 4") && e.contains("zz"), "{e}");
        let e = err("t_s,omega_rad_s\n0,1\n\"0.001\",\"2,5\"\n");
        assert!(e.contains("line 3") && e.contains("2,5"), "{e}");
        let e = err("t_s,omega_rad_s\n0,1\n\u{feff}\"0.001\",2\n");
        assert!(e.contains("line 3") && e.contains("`t_s`"), "{e}");
    }

    #[test]
    fn a_line_longer_than_the_buffer_grows_it() {
        let long_name = "x".repeat(CHUNK_BYTES + 10);
        let text = format!("t_s,{long_name}\n0,1\n0.001,2\n");
        let (names, columns) = read_all(text.as_bytes(), 10, 1 << 16).expect("valid");
        assert_eq!(names[1], long_name);
        assert_eq!(columns[1], [1.0, 2.0]);
    }

    #[test]
    fn plain_numbers_are_what_std_accepts() {
        for ok in ["0", "-1", "+1.5", "1.", ".5", "1e5", "1E-5", "-.5e+3", "007", "123456789012345678901234567890"] {
            assert_eq!(plain_number_end(ok.as_bytes(), 0), Some(ok.len()), "{ok}");
        }
        for bad in ["", "+", "-", ".", "e5", ".e5", "1e", "1e+", "+-1"] {
            assert_ne!(plain_number_end(bad.as_bytes(), 0), Some(bad.len()), "{bad}");
        }
    }

    proptest! {
        /// An unchecked column's cell is accepted exactly when `str::parse` accepts it.
        #[test]
        fn checked_cells_accept_what_std_accepts(cell in "[ 0-9.eE+\\-a-z]{0,12}") {
            let whole = cell.trim_ascii();
            let std_ok = whole.is_empty() || whole.parse::<f64>().is_ok();
            let line = format!("{cell},1");
            if let Some(end) = checked_cell_end(line.as_bytes(), 0) {
                prop_assert!(std_ok, "{cell:?}");
                prop_assert_eq!(end, cell.len());
            }
            let text = format!("t_s,f_set_hz,omega_rad_s\n0,{cell},1\n");
            let mut r = StreamReader::new(text.as_bytes(), "r.csv").expect("header");
            r.select(&[2]);
            prop_assert_eq!(r.read_batch(&mut Batch::default(), 10).is_ok(), std_ok, "{:?}", cell);
        }

        /// A selected cell's value is `str::parse`'s, to the bit.
        #[test]
        fn parsed_cells_are_std_to_the_bit(
            mantissa in "[+-]?[0-9]{0,20}(\\.[0-9]{0,20})?",
            exponent in proptest::option::of(-330i32..330),
            bits in any::<u64>(),
        ) {
            let mut cells = vec![format!("{}", f64::from_bits(bits)), format!("{:e}", f64::from_bits(bits))];
            cells.push(match exponent {
                Some(e) => format!("{mantissa}e{e}"),
                None => mantissa.clone(),
            });
            for cell in cells {
                let std = cell.parse::<f64>().ok();
                let fast = number_cell(cell.as_bytes(), 0).filter(|(_, end)| *end == cell.len()).map(|(v, _)| v);
                match (std, fast) {
                    (Some(a), Some(b)) => prop_assert!(a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan()), "{cell}"),
                    (None, None) => {}
                    (None, Some(_)) if cell.trim_ascii().is_empty() => {}
                    (a, b) => prop_assert!(false, "{cell:?}: std {a:?}, fast {b:?}"),
                }
            }
        }

        /// Small random recordings, with odd spacing, gaps, line ends and the odd bad cell: the stream reads what
        /// `parse` reads, or fails where it fails, whatever the batch size and however the reads cut the text.
        #[test]
        fn small_recordings_read_as_parse_reads_them(
            rows in proptest::collection::vec(
                (0.0f64..0.01, proptest::collection::vec(
                    prop_oneof![
                        8 => any::<f64>().prop_map(|v| v.to_string()),
                        2 => (-1e3f64..1e3).prop_map(|v| format!("{v:e}")),
                        2 => Just(String::new()),
                        1 => Just(" 2.5 ".to_string()),
                        1 => Just("nan".to_string()),
                        1 => Just("\"4\"".to_string()),
                        1 => Just("x".to_string()),
                        1 => Just("1e".to_string()),
                    ],
                    3,
                ), prop_oneof![8 => Just("\n"), 2 => Just("\r\n"), 1 => Just("\n\n")]),
                1..12,
            ),
            ragged in proptest::option::of(0usize..12),
            max_rows in 1usize..5,
            piece in 1usize..40,
        ) {
            let mut text = String::from("t_s,omega_rad_s,f_set_hz,torque_nm\n");
            let mut t = 0.0;
            for (k, (dt, cells, end)) in rows.iter().enumerate() {
                t += dt;
                text += &format!("{t},{}", cells.join(","));
                if ragged == Some(k) {
                    text += ",9";
                }
                text += end;
            }
            assert_agrees(&text, max_rows, piece);
        }
    }
}

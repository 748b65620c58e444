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
//! How: the file is read in 1 MiB chunks and cut into lines with memchr; asked-for cells are parsed with
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

/// Bytes asked of the reader at a time; a longer line grows the buffer.
const CHUNK_BYTES: usize = 1 << 20;
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
}

impl StreamReader<std::fs::File> {
    /// Opens a recording file and reads its header. Nothing is selected yet: see [`StreamReader::select`].
    pub fn open(path: &Path) -> Result<StreamReader<std::fs::File>, RecordingError> {
        let name = path.display().to_string();
        let file = std::fs::File::open(path).map_err(|source| RecordingError::Io { path: name.clone(), source })?;
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
                    let Some((a, b, number)) = lines.next_line().map_err(|source| io_error(&self.origin, source))? else {
                        break;
                    };
                    let line = &lines.buf[a..b];
                    if is_blank(line) {
                        continue;
                    }
                    if let Some(t) = fast_row(line, &self.roles, batch) {
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

/// One line on the fast path into `batch`: `t_s`, or `None` for a line that needs [`careful_row`] (the batch may
/// then hold part of the row: see [`Batch::truncate_to_rows`]).
#[inline]
fn fast_row(line: &[u8], roles: &[Role], batch: &mut Batch) -> Option<f64> {
    let last = roles.len() - 1;
    let mut i = 0;
    let mut t = f64::NAN;
    for (c, &role) in roles.iter().enumerate() {
        let end = match role {
            Role::Check => checked_cell_end(line, i)?,
            Role::Time => {
                let (v, end) = number_cell(line, i)?;
                t = v;
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

/// Where a cell whose content ends at `i` ends: at a comma or the end of the line, after blanks; `None` if
/// anything else follows.
#[inline]
fn cell_end(line: &[u8], i: usize) -> Option<usize> {
    let i = skip_blanks(line, i);
    match line.get(i) {
        None | Some(b',') => Some(i),
        Some(_) => None,
    }
}

/// The number in the cell starting at `i` (NaN when empty) and where the cell ends.
#[inline]
fn number_cell(line: &[u8], i: usize) -> Option<(f64, usize)> {
    let i = skip_blanks(line, i);
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
    let i = skip_blanks(line, i);
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
        // every byte in b'0'..=b'9' (fast_float's test): no high bit after adding 0x46 or subtracting 0x30
        if (v.wrapping_add(0x4646_4646_4646_4646) | v.wrapping_sub(0x3030_3030_3030_3030)) & 0x8080_8080_8080_8080 != 0
        {
            break;
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
        // A leading blank line (which the csv crate skips) keeps it from taking a BOM-like start for a BOM.
        let mut head = Vec::with_capacity(1 + lines.end - from);
        head.push(b'\n');
        head.extend_from_slice(&lines.buf[from..lines.end]);
        let csv = csv::ReaderBuilder::new()
            .has_headers(header)
            .flexible(true)
            .trim(csv::Trim::All)
            .from_reader(Cursor::new(head).chain(lines.reader));
        CsvInput { csv, record: csv::ByteRecord::new(), line_shift: number as i64 - 2 }
    }

    fn line(&self, position: Option<&csv::Position>) -> u64 {
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
        let line = self.line(self.record.position());
        let fields: Vec<&[u8]> = self.record.iter().collect();
        let t = row_from_fields(&fields, line, names, roles, origin, batch)?;
        Ok(Some((t, line)))
    }
}

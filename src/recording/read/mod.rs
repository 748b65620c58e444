//! Reading a recording CSV: one streaming reader, batch by batch, for [`load`], `estimate` and `analyze`; every bad
//! cell is named by file, line and column.
//!
//! The grammar (CONTRACT.md "Recording CSV"):
//! - Text; a byte-order mark at the start is skipped. A line ends at `\n`, `\r\n` or a lone `\r`; empty lines are
//!   skipped. Line numbers in messages are physical lines, from 1, blank ones counted.
//! - The first line is the header: names between commas, trimmed of ASCII whitespace; `t_s` is required and no name
//!   may appear twice.
//! - Every other line is a row with one cell per name. A cell is trimmed of ASCII whitespace; empty, it is a missing
//!   value (NaN); otherwise it must be a number as `str::parse::<f64>` reads one (`1.5`, `-2e-3`, `nan`, `inf`).
//! - A cell may be quoted, as spreadsheets write them (`"1.5"`): inside the quotes a comma is text and `""` is one
//!   quote. A quote closes on its line (a cell that opens one and does not is an error naming it: a cell of several
//!   lines); text after a closing quote makes the cell its whole text, quotes and all.
//! - `t_s` is finite in every row and strictly increasing.
//!
//! A row is checked in this order: its number of cells, `t_s`, the other cells in file order, then `t_s` against the
//! row before; the first failure is the error.
//!
//! How: the text is read in 256 KiB pieces and cut into lines with memchr. [`row`] reads a line by the grammar
//! above. It is the only reader of a line; [`plain_row`] takes a line of plain cells (no quotes, plain decimals) in
//! one pass first, parsing only the selected cells (fast-float2, the bits `str::parse` gives) and checking the
//! others against the plain decimal grammar, and hands anything else to [`row`]. A proptest checks that the two
//! agree. This keeps `estimate` above 2 M rows/s (docs/performance.md).

use std::io::Read;
use std::path::Path;

use super::{KNOWN_COLUMNS, Recording};

mod cells;

use cells::{check_time, fields, plain_row, row};

/// Bytes asked of the reader at a time.
const READ_BYTES: usize = 1 << 18;
/// The longest line a recording may have (bytes, without its end): a row of the contract's columns is a few
/// hundred bytes, a header with every `true_*` and estimate column under one kB. A longer line is an error naming
/// its number and this cap, so a file of one endless line costs no more memory than a normal one.
pub const MAX_LINE_BYTES: usize = 1 << 14;
/// Blank lines a recording may hold beyond [`BLANK_LINES_PER_ROW`] a row: a file of nothing but line ends (a
/// reviewer's 2 MB gzip of 2 GiB of them took 14 s to refuse, past every cap on rows and line length) is refused at
/// this many.
pub const MAX_EXTRA_BLANK_LINES: u64 = 1000;
/// Blank lines a row may bring (a double-spaced export, CRLF read as two line ends): reading stays within a few
/// times a file of rows alone.
pub const BLANK_LINES_PER_ROW: u64 = 4;
/// Rows per batch when a whole recording is loaded.
const LOAD_BATCH_ROWS: usize = 4096;
const UTF8_BOM: &[u8] = b"\xef\xbb\xbf";

/// What can be wrong with a recording. Everything but `Io` is bad input (exit 2).
#[derive(Debug, thiserror::Error)]
pub enum RecordingError {
    /// (`error` is not a `source`: the message carries it, and a chain printed with `{:#}` would say it twice)
    #[error("cannot read recording {path}: {error}")]
    Io { path: String, error: std::io::Error },
    #[error("recording {path}: {message}")]
    File { path: String, message: String },
    #[error("recording {path}, line {line}: {message}")]
    Line { path: String, line: u64, message: String },
    #[error("recording {path}, line {line}, column `{column}`: {message}")]
    Cell { path: String, line: u64, column: String, message: String },
    /// More rows than the command may hold in memory (with the files before it, for several).
    #[error(
        "recording {path}: more than {max_rows} rows (with the files before it), the most this command holds in \
         memory; give it a part of the recording"
    )]
    TooLong { path: String, max_rows: usize },
}

impl RecordingError {
    /// True when the user can fix it: the file's content (corrupt compressed data too), or a path that does not
    /// exist, may not be read or is a directory (exit code 2).
    pub fn is_bad_input(&self) -> bool {
        use std::io::ErrorKind as K;
        match self {
            RecordingError::Io { error, .. } => {
                matches!(error.kind(), K::NotFound | K::InvalidData | K::PermissionDenied | K::IsADirectory)
            }
            _ => true,
        }
    }
}

/// Reads a recording file whole (a last line cut mid-row is dropped with a warning, see [`super::cut`]).
pub fn load(path: &Path) -> Result<Recording, RecordingError> {
    let name = path.display().to_string();
    parse(super::cut::open(path)?, &name)
}

/// Whether a recording file (plain or gzip) holds no row: empty, or nothing but its header (what a file leaves
/// when the disk was full before its first row reached it). A last line cut mid-row is no row. Reads no further
/// than the start of its second non-empty line.
pub fn holds_no_rows(path: &Path) -> Result<bool, RecordingError> {
    let name = path.display().to_string();
    no_rows_in(super::cut::open(path)?).map_err(|e| io_error(&name, e))
}

/// Whether the text has at most one non-empty line (see [`holds_no_rows`]).
fn no_rows_in<R: Read>(mut text: R) -> std::io::Result<bool> {
    let mut buf = [0u8; 8192];
    let (mut lines, mut in_line) = (0, false);
    let mut read = 0;
    loop {
        // a header is shorter than a line may be: more than that is something (a device that never ends, say)
        if read > MAX_LINE_BYTES {
            return Ok(false);
        }
        let n = match text.read(&mut buf) {
            Ok(0) => return Ok(true),
            Ok(n) => n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(e),
        };
        read += n;
        for &b in &buf[..n] {
            if b == b'\n' || b == b'\r' {
                in_line = false;
            } else if !in_line {
                in_line = true;
                lines += 1;
                if lines == 2 {
                    return Ok(false);
                }
            }
        }
    }
}

/// Reads of a recording file only `t_s` and those of `columns` it has (the other cells are checked, not kept): what
/// `analyze` holds in memory.
pub fn load_columns(path: &Path, columns: &[&str], max_rows: usize) -> Result<Recording, RecordingError> {
    let name = path.display().to_string();
    read_whole(super::cut::open(path)?, &name, |n| columns.contains(&n), max_rows)
}

/// Parses recording CSV text whole, `t_s` first and the other columns in file order; `origin` names it in errors.
pub fn parse<R: Read>(reader: R, origin: &str) -> Result<Recording, RecordingError> {
    read_whole(reader, origin, |_| true, usize::MAX)
}

/// The columns `keep` says yes to, whole.
fn read_whole<R: Read>(
    reader: R,
    origin: &str,
    keep: impl Fn(&str) -> bool,
    max_rows: usize,
) -> Result<Recording, RecordingError> {
    let mut r = StreamReader::new(reader, origin)?;
    let others: Vec<usize> = (0..r.names.len()).filter(|&i| i != r.t_index && keep(&r.names[i])).collect();
    r.select(&others);
    let mut columns = vec![Vec::new(); others.len() + 1];
    let mut batch = Batch::default();
    while r.read_batch(&mut batch, LOAD_BATCH_ROWS)? > 0 {
        columns[0].extend_from_slice(&batch.t_s);
        for (c, values) in columns[1..].iter_mut().zip(&batch.columns) {
            c.extend_from_slice(values);
        }
        if columns[0].len() > max_rows {
            return Err(RecordingError::TooLong { path: origin.to_string(), max_rows });
        }
    }
    // what the doubling growth left spare goes back (a long recording: up to half the columns' memory)
    for c in &mut columns {
        c.shrink_to_fit();
    }
    let names = std::iter::once(r.t_index).chain(others).map(|i| r.names[i].clone()).collect();
    let mut rec = Recording::from_columns(origin, names, columns);
    rec.out_of_range = r.out_of_range();
    Ok(rec)
}

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
    /// A column the contract does not name: not looked at (CONTRACT.md: unknown columns are ignored).
    Ignore,
    Time,
    /// Parsed into `Batch::columns[slot]`.
    Slot(usize),
}

/// A recording read batch by batch, in flat memory. Errors name the file (`origin`), the line and the column.
pub struct StreamReader<R: Read> {
    origin: String,
    names: Vec<String>,
    t_index: usize,
    roles: Vec<Role>,
    selected: usize,
    lines: Lines<R>,
    last_t: f64,
    rows: u64,
    /// Whether [`plain_row`] is tried first (tests turn it off to compare).
    plain_first: bool,
    /// Per column: whether the contract names it (an unknown column's cells are never an error).
    known: Vec<bool>,
    /// Per slot: the sensor's range ([`super::sensor_range`]) and what fell outside it so far.
    screens: Vec<Option<Screen>>,
}

/// A selected column's sensor range, and the cells outside it (taken as missing).
#[derive(Debug, Clone)]
struct Screen {
    column: String,
    low: f64,
    high: f64,
    cells: u64,
    first_line: u64,
}

/// The input: a buffer of whole lines plus the start of the next.
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

impl StreamReader<super::RecordingFile> {
    /// Opens a recording file (plain or gzip) and reads its header. Nothing is selected yet: see
    /// [`StreamReader::select`]. A last line cut mid-row is dropped with a warning (see [`super::cut`]).
    pub fn open(path: &Path) -> Result<StreamReader<super::RecordingFile>, RecordingError> {
        let name = path.display().to_string();
        StreamReader::new(super::cut::open(path)?, &name)
    }
}

impl<R: Read> StreamReader<R> {
    /// Reads the header of recording CSV text; `origin` names it in errors.
    pub fn new(reader: R, origin: &str) -> Result<StreamReader<R>, RecordingError> {
        let io_err = |source| io_error(origin, source);
        let mut lines = Lines { reader, buf: vec![0; READ_BYTES], start: 0, end: 0, eof: false, line: 0 };
        while lines.end < UTF8_BOM.len() && !lines.eof {
            lines.fill().map_err(io_err)?;
        }
        if lines.buf[..lines.end].starts_with(UTF8_BOM) {
            lines.start = UTF8_BOM.len();
        }
        let header = loop {
            match lines.next_line(origin)? {
                Some((a, b, number)) if a == b => {
                    if number > MAX_EXTRA_BLANK_LINES {
                        return Err(too_many_blank_lines(origin, number));
                    }
                    continue;
                }
                found => break found,
            }
        };
        let (names, t_index) = match header {
            None => header_names(Vec::new(), 0, origin)?,
            Some((a, b, number)) => {
                let mut names = Vec::new();
                let cells = fields(&lines.buf[a..b]).map_err(|k| RecordingError::Line {
                    path: origin.into(),
                    line: number,
                    message: format!("the header's name {}: {}", k + 1, cells::UNCLOSED_QUOTE),
                })?;
                for cell in cells {
                    let Ok(name) = std::str::from_utf8(&cell) else {
                        return Err(RecordingError::Line {
                            path: origin.into(),
                            line: number,
                            message: "the header row is not UTF-8 text".into(),
                        });
                    };
                    names.push(name.trim_ascii().to_string());
                }
                header_names(names, number, origin)?
            }
        };
        let known: Vec<bool> = names.iter().map(|n| is_known(n)).collect();
        let mut r = StreamReader {
            origin: origin.to_string(),
            names,
            t_index,
            roles: Vec::new(),
            selected: 0,
            lines,
            last_t: f64::NEG_INFINITY,
            rows: 0,
            plain_first: true,
            known,
            screens: Vec::new(),
        };
        r.select(&[]);
        Ok(r)
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
    /// [`StreamReader::names`], not `t_s`'s); the cells of every other column the contract names are only checked,
    /// those of unknown columns not looked at. A selected value outside its sensor's range
    /// ([`super::sensor_range`]) comes as NaN (missing) and is counted ([`StreamReader::out_of_range`]).
    pub fn select(&mut self, columns: &[usize]) {
        debug_assert!(!columns.contains(&self.t_index), "t_s always comes in Batch::t_s");
        self.roles = (0..self.names.len())
            .map(|i| match columns.iter().position(|&c| c == i) {
                _ if i == self.t_index => Role::Time,
                Some(slot) => Role::Slot(slot),
                None if self.known[i] => Role::Check,
                None => Role::Ignore,
            })
            .collect();
        self.screens = columns
            .iter()
            .map(|&c| {
                let name = self.names.get(c)?;
                let (low, high) = super::sensor_range(name)?;
                Some(Screen { column: name.clone(), low, high, cells: 0, first_line: 0 })
            })
            .collect();
        self.selected = columns.len();
    }

    /// The selected cells read so far that lay outside their sensor's range and were taken as missing, per column.
    pub fn out_of_range(&self) -> Vec<super::OutOfRange> {
        self.screens
            .iter()
            .flatten()
            .filter(|s| s.cells > 0)
            .map(|s| super::OutOfRange {
                file: self.origin.clone(),
                column: s.column.clone(),
                low: s.low,
                high: s.high,
                cells: s.cells,
                first_line: s.first_line,
            })
            .collect()
    }

    /// Rows read so far.
    pub fn rows(&self) -> u64 {
        self.rows
    }

    /// Replaces `batch`'s content with up to `max_rows` next rows; 0 rows means the end of the file.
    pub fn read_batch(&mut self, batch: &mut Batch, max_rows: usize) -> Result<usize, RecordingError> {
        batch.reset(self.selected);
        while batch.len() < max_rows {
            let Some((a, b, number)) = self.lines.next_line(&self.origin)? else {
                break;
            };
            let line = &self.lines.buf[a..b];
            if line.is_empty() {
                // lines so far: the header, the rows and the blank ones
                if number - 1 - self.rows > BLANK_LINES_PER_ROW * self.rows + MAX_EXTRA_BLANK_LINES {
                    return Err(too_many_blank_lines(&self.origin, number));
                }
                continue;
            }
            let plain = if self.plain_first { plain_row(line, &self.roles, batch) } else { None };
            let t = match plain {
                Some(t) => t,
                None => {
                    batch.truncate_to_rows();
                    let names = (&self.names[..], &self.known[..]);
                    row(line, number, names, &self.roles, self.t_index, &self.origin, batch)?
                }
            };
            check_time(t, self.last_t, &self.origin, number)?;
            self.last_t = t;
            batch.t_s.push(t);
            self.rows += 1;
            for (screen, column) in self.screens.iter_mut().zip(&mut batch.columns) {
                if let (Some(s), Some(v)) = (screen, column.last_mut())
                    && !v.is_nan()
                    && !(s.low..=s.high).contains(v)
                {
                    *v = f64::NAN;
                    if s.cells == 0 {
                        s.first_line = number;
                    }
                    s.cells += 1;
                }
            }
        }
        if batch.is_empty() && self.rows == 0 {
            return Err(RecordingError::File {
                path: self.origin.clone(),
                message: "no data rows after the header".into(),
            });
        }
        if batch.is_empty() {
            for s in self.out_of_range() {
                tracing::warn!(recording = %self.origin, "{s}");
            }
        }
        Ok(batch.len())
    }
}

impl<R: Read> Lines<R> {
    /// The next line as `(start, end, number)`, `buf[start..end]` its bytes without the line end; a line longer
    /// than [`MAX_LINE_BYTES`] is an error (`origin` names the file).
    fn next_line(&mut self, origin: &str) -> Result<Option<(usize, usize, u64)>, RecordingError> {
        let line = self.next_line_within(MAX_LINE_BYTES).map_err(|e| io_error(origin, e))?;
        line.map_err(|number| RecordingError::Line {
            path: origin.into(),
            line: number,
            message: format!(
                "longer than {MAX_LINE_BYTES} bytes, the most a recording's line may have (a row of the contract's \
                 columns is a few hundred): not a recording, or a line end is missing"
            ),
        })
    }

    /// The next line, or `Err(number)` for a line longer than `max` bytes.
    #[allow(clippy::type_complexity)]
    fn next_line_within(&mut self, max: usize) -> std::io::Result<Result<Option<(usize, usize, u64)>, u64>> {
        loop {
            let found = memchr::memchr2(b'\n', b'\r', &self.buf[self.start..self.end]);
            if found.unwrap_or(self.end - self.start) > max {
                return Ok(Err(self.line + 1));
            }
            if let Some(k) = found {
                let (a, b) = (self.start, self.start + k);
                let mut next = b + 1;
                if self.buf[b] == b'\r' {
                    if next == self.end && !self.eof {
                        // a `\n` may follow in what is not read yet
                        self.fill()?;
                        continue;
                    }
                    if next < self.end && self.buf[next] == b'\n' {
                        next += 1;
                    }
                }
                self.start = next;
                self.line += 1;
                return Ok(Ok(Some((a, b, self.line))));
            }
            if self.eof {
                if self.start == self.end {
                    return Ok(Ok(None));
                }
                let found = (self.start, self.end);
                self.start = self.end;
                self.line += 1;
                return Ok(Ok(Some((found.0, found.1, self.line))));
            }
            self.fill()?;
        }
    }

    /// Reads more, keeping `buf[start..end]` (moved to the front); the buffer holds a line of the longest allowed.
    fn fill(&mut self) -> std::io::Result<()> {
        if self.start > 0 {
            self.buf.copy_within(self.start..self.end, 0);
            self.end -= self.start;
            self.start = 0;
        }
        if self.end == self.buf.len() {
            self.buf.resize((2 * self.buf.len()).max(READ_BYTES), 0);
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

fn io_error(origin: &str, error: std::io::Error) -> RecordingError {
    RecordingError::Io { path: origin.to_string(), error }
}

/// The error for a recording of more blank lines than [`BLANK_LINES_PER_ROW`] a row and [`MAX_EXTRA_BLANK_LINES`].
fn too_many_blank_lines(origin: &str, line: u64) -> RecordingError {
    RecordingError::Line {
        path: origin.to_string(),
        line,
        message: format!(
            "more blank lines than rows (over {MAX_EXTRA_BLANK_LINES} beyond {BLANK_LINES_PER_ROW} a row): not a \
             recording, refused before reading on"
        ),
    }
}

/// The header's names (trimmed), checked: not empty, `t_s` present, no column of the contract twice (which of the two
/// would be meant?); unknown names are ignored, also twice (a spreadsheet's empty trailing columns, two `note`
/// columns), and logged once.
/// `line` is the header's. Returns the names and where `t_s` is.
fn header_names(names: Vec<String>, line: u64, origin: &str) -> Result<(Vec<String>, usize), RecordingError> {
    if names.is_empty() || (names.len() == 1 && names[0].is_empty()) {
        return Err(RecordingError::File {
            path: origin.to_string(),
            message: if crate::error::is_fifo(std::path::Path::new(origin)) {
                "a named pipe with nothing written to it (no writer): expected a header row starting with `t_s`".into()
            } else {
                "the file is empty: expected a header row starting with `t_s`".into()
            },
        });
    }
    let Some(t_index) = names.iter().position(|n| n == "t_s") else {
        return Err(RecordingError::Line {
            path: origin.into(),
            line,
            message: format!("no `t_s` column (required); the header has {}", names.join(", ")),
        });
    };
    for (i, n) in names.iter().enumerate() {
        if is_known(n) && names[..i].contains(n) {
            return Err(RecordingError::Line {
                path: origin.into(),
                line,
                message: format!("column `{n}` appears twice"),
            });
        }
    }
    let unknown: Vec<&str> = names.iter().map(String::as_str).filter(|n| !is_known(n)).collect();
    if !unknown.is_empty() {
        tracing::info!(recording = origin, columns = ?unknown, "ignoring unknown columns");
    }
    Ok((names, t_index))
}

/// Whether the contract names a column (its own columns and the simulator's `true_*`); the cells of any other are
/// never an error.
fn is_known(name: &str) -> bool {
    KNOWN_COLUMNS.contains(&name) || name.starts_with("true_")
}

#[cfg(test)]
mod tests;

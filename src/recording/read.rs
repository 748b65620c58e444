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
//!   quote. A quote closes on its line; a cell that is not a well-formed quoted cell is taken as its text.
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

use std::borrow::Cow;
use std::io::Read;
use std::path::Path;

use super::{KNOWN_COLUMNS, Recording};

/// Bytes asked of the reader at a time.
const READ_BYTES: usize = 1 << 18;
/// The longest line a recording may have (bytes, without its end): a row of the contract's columns is a few
/// hundred bytes, a header with every `true_*` and estimate column under one kB. A longer line is an error naming
/// its number and this cap, so a file of one endless line costs no more memory than a normal one.
pub const MAX_LINE_BYTES: usize = 1 << 14;
/// Rows per batch when a whole recording is loaded.
const LOAD_BATCH_ROWS: usize = 4096;
const UTF8_BOM: &[u8] = b"\xef\xbb\xbf";

/// What can be wrong with a recording. Everything but `Io` is bad input (exit 2).
#[derive(Debug, thiserror::Error)]
pub enum RecordingError {
    #[error("cannot read recording {path}: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("recording {path}: {message}")]
    File { path: String, message: String },
    #[error("recording {path}, line {line}: {message}")]
    Line { path: String, line: u64, message: String },
    #[error("recording {path}, line {line}, column `{column}`: {message}")]
    Cell { path: String, line: u64, column: String, message: String },
}

impl RecordingError {
    /// True when the user can fix it: the file's content (corrupt compressed data too), or a path that does not
    /// exist, may not be read or is a directory (exit code 2).
    pub fn is_bad_input(&self) -> bool {
        use std::io::ErrorKind as K;
        match self {
            RecordingError::Io { source, .. } => {
                matches!(source.kind(), K::NotFound | K::InvalidData | K::PermissionDenied | K::IsADirectory)
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
pub fn load_columns(path: &Path, columns: &[&str]) -> Result<Recording, RecordingError> {
    let name = path.display().to_string();
    read_whole(super::cut::open(path)?, &name, |n| columns.contains(&n))
}

/// Parses recording CSV text whole, `t_s` first and the other columns in file order; `origin` names it in errors.
pub fn parse<R: Read>(reader: R, origin: &str) -> Result<Recording, RecordingError> {
    read_whole(reader, origin, |_| true)
}

/// The columns `keep` says yes to, whole.
fn read_whole<R: Read>(reader: R, origin: &str, keep: impl Fn(&str) -> bool) -> Result<Recording, RecordingError> {
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
                Some((a, b, _)) if a == b => continue,
                found => break found,
            }
        };
        let (names, t_index) = match header {
            None => header_names(Vec::new(), 0, origin)?,
            Some((a, b, number)) => {
                let mut names = Vec::new();
                for cell in fields(&lines.buf[a..b]) {
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

fn io_error(origin: &str, source: std::io::Error) -> RecordingError {
    RecordingError::Io { path: origin.to_string(), source }
}

/// The header's names (trimmed), checked: not empty, `t_s` present, no name twice; unknown names are logged once.
/// `line` is the header's. Returns the names and where `t_s` is.
fn header_names(names: Vec<String>, line: u64, origin: &str) -> Result<(Vec<String>, usize), RecordingError> {
    if names.is_empty() || (names.len() == 1 && names[0].is_empty()) {
        return Err(RecordingError::File {
            path: origin.to_string(),
            message: "the file is empty: expected a header row starting with `t_s`".into(),
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
        if names[..i].contains(n) {
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

/// The cells of a line, by the grammar's rules on commas and quotes (not yet trimmed).
fn fields(line: &[u8]) -> Vec<Cow<'_, [u8]>> {
    let mut out = Vec::new();
    let mut i = 0;
    loop {
        let (cell, end) = field(line, i);
        out.push(cell);
        if end == line.len() {
            return out;
        }
        i = end + 1;
    }
}

/// The cell that starts at `line[i]`, and where it ends (at a comma or the end of the line).
fn field(line: &[u8], i: usize) -> (Cow<'_, [u8]>, usize) {
    let next_comma = |from: usize| memchr::memchr(b',', &line[from..]).map_or(line.len(), |k| from + k);
    let skip_space = |from: usize| from + line[from..].iter().take_while(|b| b.is_ascii_whitespace()).count();
    let first = skip_space(i);
    if line.get(first) != Some(&b'"') {
        let end = next_comma(i);
        return (Cow::Borrowed(&line[i..end]), end);
    }
    let mut text = Vec::new();
    let mut k = first + 1;
    while k < line.len() {
        if line[k] == b'"' {
            if line.get(k + 1) == Some(&b'"') {
                text.push(b'"');
                k += 2;
                continue;
            }
            let after = skip_space(k + 1);
            if after == line.len() || line[after] == b',' {
                return (Cow::Owned(text), after);
            }
            // text after the closing quote: the cell is its text, up to the next comma
            let end = next_comma(after);
            return (Cow::Borrowed(&line[i..end]), end);
        }
        text.push(line[k]);
        k += 1;
    }
    // not closed on its line: the rest of the line is the cell's text
    (Cow::Borrowed(&line[i..]), line.len())
}

/// A line by the grammar, checked in its order (number of cells, `t_s`, the other cells): the row's `t_s`, with the
/// selected values pushed to `batch`, or the first error.
fn row(
    line: &[u8],
    number: u64,
    (names, known): (&[String], &[bool]),
    roles: &[Role],
    t_index: usize,
    origin: &str,
    batch: &mut Batch,
) -> Result<f64, RecordingError> {
    let cells = fields(line);
    if cells.len() != names.len() {
        return Err(RecordingError::Line {
            path: origin.into(),
            line: number,
            message: format!("{} fields, expected {} as in the header", cells.len(), names.len()),
        });
    }
    let t = cell_value(&cells[t_index], origin, number, &names[t_index])?;
    let mut values = Vec::new();
    for (i, role) in roles.iter().enumerate() {
        match role {
            Role::Time | Role::Ignore => {}
            Role::Check => {
                cell_value(&cells[i], origin, number, &names[i])?;
            }
            // an unknown column read whole: text in it is no value
            Role::Slot(slot) if !known[i] => values.push((*slot, cell_value(&cells[i], "", 0, "").unwrap_or(f64::NAN))),
            Role::Slot(slot) => values.push((*slot, cell_value(&cells[i], origin, number, &names[i])?)),
        }
    }
    for (slot, v) in values {
        batch.columns[slot].push(v);
    }
    Ok(t)
}

/// A cell's value: NaN when empty (after trimming ASCII whitespace), else the number it must hold.
fn cell_value(cell: &[u8], origin: &str, line: u64, column: &str) -> Result<f64, RecordingError> {
    let cell = cell.trim_ascii();
    if cell.is_empty() {
        return Ok(f64::NAN);
    }
    let number = std::str::from_utf8(cell).ok().and_then(|s| s.parse::<f64>().ok());
    number.ok_or_else(|| RecordingError::Cell {
        path: origin.into(),
        line,
        column: column.to_string(),
        message: format!("expected a number, got {:?}", String::from_utf8_lossy(cell)),
    })
}

/// A row's time must be finite and later than the row before's.
fn check_time(t: f64, last_t: f64, origin: &str, line: u64) -> Result<(), RecordingError> {
    if !t.is_finite() {
        return Err(RecordingError::Cell {
            path: origin.into(),
            line,
            column: "t_s".into(),
            message: "time is missing or not finite (required in every row)".into(),
        });
    }
    if t <= last_t {
        return Err(RecordingError::Cell {
            path: origin.into(),
            line,
            column: "t_s".into(),
            message: format!("time goes backwards or repeats: {t} after {last_t} (must strictly increase)"),
        });
    }
    Ok(())
}

/// A line of plain cells in one pass into `batch`: its `t_s`, or `None` for any line that [`row`] must read (the
/// batch may then hold part of the row: see [`Batch::truncate_to_rows`]). Plain: cells separated by commas, padded
/// with spaces or tabs at most, each empty or a decimal number (`nan` and `inf` too where the column is selected).
#[inline]
fn plain_row(line: &[u8], roles: &[Role], batch: &mut Batch) -> Option<f64> {
    let last = roles.len() - 1;
    let mut i = 0;
    let mut t = f64::NAN;
    for (c, &role) in roles.iter().enumerate() {
        let end = match role {
            Role::Check => checked_cell_end(line, i)?,
            // quotes may hide a comma: those lines go to `row`
            Role::Ignore => {
                let end = memchr::memchr(b',', &line[i..]).map_or(line.len(), |k| i + k);
                if memchr::memchr(b'"', &line[i..end]).is_some() {
                    return None;
                }
                end
            }
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

/// Skips spaces and tabs.
#[inline]
fn skip_blanks(line: &[u8], mut i: usize) -> usize {
    while matches!(line.get(i), Some(b' ' | b'\t')) {
        i += 1;
    }
    i
}

/// Where a cell whose content ends at `i` ends: at a comma or the end of the line, after blanks; `None` if
/// anything else follows.
#[inline]
fn cell_end(line: &[u8], i: usize) -> Option<usize> {
    // the common case first: the comma or the end right there
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
/// `str::parse::<f64>` accepts every such number (and also `inf`, `nan`, which this leaves to [`row`]).
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

/// Skips ASCII digits.
#[inline]
fn skip_digits(s: &[u8], i: usize) -> usize {
    i + s[i.min(s.len())..].iter().take_while(|b| b.is_ascii_digit()).count()
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn parse_str(s: &str) -> Result<Recording, RecordingError> {
        parse(s.as_bytes(), "r.csv")
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

    /// All of `text`, every column selected, `max_rows` at a time through reads of `piece` bytes, with or without
    /// [`plain_row`] first: the names and columns, `t_s` first.
    fn read_all(
        text: &[u8],
        max_rows: usize,
        piece: usize,
        plain_first: bool,
    ) -> Result<(Vec<String>, Vec<Vec<f64>>), RecordingError> {
        let mut r = StreamReader::new(Trickle { text, at: 0, piece }, "r.csv")?;
        r.plain_first = plain_first;
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

    fn same_bits(a: &[f64], b: &[f64]) -> bool {
        a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits() || (x.is_nan() && y.is_nan()))
    }

    /// The reader with [`plain_row`] first reads `text` as [`row`] alone does: the same values, or the same error.
    fn assert_plain_path_agrees(text: &str, max_rows: usize, piece: usize) {
        let plain = read_all(text.as_bytes(), max_rows, piece, true);
        let by_rule = read_all(text.as_bytes(), 4096, 1 << 20, false);
        match (plain, by_rule) {
            (Ok((n, a)), Ok((m, b))) => {
                assert_eq!(n, m, "{text:?}");
                for (name, (x, y)) in n.iter().zip(a.iter().zip(&b)) {
                    assert!(same_bits(x, y), "{name} in {text:?}");
                }
            }
            (Err(a), Err(b)) => assert_eq!(a.to_string(), b.to_string(), "{text:?}"),
            (a, b) => panic!("{text:?}: with the plain path {a:?}, by the rule alone {b:?}"),
        }
    }

    #[test]
    fn reads_columns_and_missing_values() {
        let r = parse_str("omega_rad_s, t_s ,foo\n 1.5 ,0.0,\n,0.001,3\n").expect("valid");
        assert_eq!(r.names(), ["t_s", "omega_rad_s", "foo"]);
        assert_eq!(r.t_s(), &[0.0, 0.001]);
        let w = r.column("omega_rad_s").expect("column");
        assert_eq!(w[0], 1.5);
        assert!(w[1].is_nan());
    }

    #[test]
    fn line_ends_bom_spaces_quotes_and_blank_lines_follow_the_grammar() {
        let expected = [vec![0.0, 0.001], vec![1.0, 2.5]];
        for text in [
            "t_s,x\n0,1\n0.001,2.5\n",
            "t_s,x\r\n0,1\r\n0.001,2.5\r\n",
            "t_s,x\r0,1\r0.001,2.5\r",
            "t_s,x\n0,1\r\n0.001,2.5",
            "\u{feff}t_s,x\n0,1\n0.001,2.5\n",
            " t_s , x \n 0 , 1 \n\t0.001\t,\t2.5\x0c\n",
            "\n\nt_s,x\n\n0,1\n\r\n\n0.001,2.5\n\n",
            "\"t_s\",\"x\"\n\"0\",\"1\"\n0.001, \"2.5\" \n",
            "t_s,\"x\"\"\"\n0,1\n0.001,2.5\n",
        ] {
            for (max_rows, piece) in [(1, 1), (2, 3), (4096, 1 << 20)] {
                let (names, columns) = read_all(text.as_bytes(), max_rows, piece, true).expect(text);
                assert_eq!(names[0], "t_s", "{text:?}");
                assert!(names[1] == "x" || names[1] == "x\"", "{text:?}");
                assert_eq!(columns, expected, "{text:?}");
                assert_plain_path_agrees(text, max_rows, piece);
            }
        }
        let r = parse_str("t_s,x\n0,nan\n0.001,-inf\n0.002,+Infinity\n0.003,1.\n0.004,.5\n0.005,1E5\n").expect("valid");
        let x = r.column("x").expect("x");
        assert!(x[0].is_nan() && x[1] == f64::NEG_INFINITY && x[2] == f64::INFINITY);
        assert_eq!(x[3..], [1.0, 0.5, 1e5]);
    }

    #[test]
    fn a_file_holds_no_rows_when_empty_or_a_header_alone_plain_or_gzip() {
        let dir = tempfile::tempdir().expect("tmp");
        let gzip = |text: &[u8]| {
            use std::io::Write;
            let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
            e.write_all(text).expect("gzip");
            e.finish().expect("gzip")
        };
        let cases: [(&[u8], bool); 8] = [
            (b"", true),
            (b"t_s,x", true),
            (b"t_s,x\n", true),
            (b"\r\nt_s,x\r\n\n", true),
            // a row cut mid-way is no row: the readers drop it
            (b"t_s,x\n0,", true),
            (b"t_s,x\n0,1\n", false),
            (b"t_s,x\r0,1\r", false),
            (b"t_s,x\n\n0,1\n0.1,2", false),
        ];
        for (k, (text, none)) in cases.into_iter().enumerate() {
            let plain = dir.path().join(format!("{k}.csv"));
            std::fs::write(&plain, text).expect("write");
            assert_eq!(holds_no_rows(&plain).expect("reads"), none, "{:?}", String::from_utf8_lossy(text));
            let gz = dir.path().join(format!("{k}.csv.gz"));
            std::fs::write(&gz, gzip(text)).expect("write");
            assert_eq!(holds_no_rows(&gz).expect("reads"), none, "gzip {:?}", String::from_utf8_lossy(text));
        }
        let missing = holds_no_rows(&dir.path().join("none.csv")).expect_err("no such file");
        assert!(!missing.to_string().is_empty());
    }

    #[test]
    fn bad_input_names_line_and_column() {
        let err = |text: &str| parse_str(text).expect_err("bad input").to_string();
        let e = err("t_s,omega_rad_s,f_set_hz\n0,1,2\n0.001,abc,2\n");
        assert!(e.contains("r.csv, line 3, column `omega_rad_s`") && e.contains("\"abc\""), "{e}");
        // CRLF and blank lines: the row's own line
        assert!(err("t_s,omega_rad_s\r\n0,1\r\n0.001,abc\r\n").contains("line 3"));
        assert!(err("t_s,omega_rad_s\n0,1\n\n\n0.001,abc\n").contains("line 5"));
        let e = err("t_s,omega_rad_s\n0,1\n0.001,1,2\n");
        assert!(e.contains("line 3") && e.contains("3 fields, expected 2"), "{e}");
        let e = err("t_s,omega_rad_s\n0,1\n0.001\n");
        assert!(e.contains("line 3") && e.contains("1 fields, expected 2"), "{e}");
        let e = err("t_s,omega_rad_s\n0,1\n0.002,1\n0.001,1\n");
        assert!(e.contains("line 4") && e.contains("`t_s`") && e.contains("backwards"), "{e}");
        let e = err("t_s,omega_rad_s\n0,1\n,1\n");
        assert!(e.contains("line 3") && e.contains("`t_s`") && e.contains("missing"), "{e}");
        // in the grammar's order: t_s before the other cells of its row
        let e = err("t_s,omega_rad_s\n0,1\nx,y\n");
        assert!(e.contains("`t_s`") && e.contains("\"x\""), "{e}");
        assert!(err("").contains("empty"));
        assert!(err("\n\n").contains("empty"));
        assert!(err("t_s,omega_rad_s\n").contains("no data rows"));
        let e = err("omega_rad_s\n1\n");
        assert!(e.contains("line 1") && e.contains("no `t_s`"), "{e}");
        assert!(err("\nomega_rad_s\n1\n").contains("line 2"));
        assert!(err("t_s,t_s\n1,2\n").contains("twice"));
        // quotes: a comma inside is text, a quote that does not close takes the rest of its line
        let e = err("t_s,omega_rad_s\n0,1\n\"0.001\",\"2,5\"\n");
        assert!(e.contains("line 3") && e.contains("`omega_rad_s`") && e.contains("2,5"), "{e}");
        let e = err("t_s,omega_rad_s\n0,1\n0.001,\"2\"x\n");
        assert!(e.contains("line 3") && e.contains("`omega_rad_s`"), "{e}");
        let e = err("t_s,omega_rad_s\n0,1\n\"0.001,2\n");
        assert!(e.contains("line 3") && e.contains("1 fields, expected 2"), "{e}");
        // a byte-order mark only starts the file
        let e = err("t_s,omega_rad_s\n0,1\n\u{feff}0.001,2\n");
        assert!(e.contains("line 3") && e.contains("`t_s`"), "{e}");
        let e = parse(&b"t_s,\x80\n0,1\n"[..], "r.csv").expect_err("not UTF-8").to_string();
        assert!(e.contains("line 1") && e.contains("UTF-8"), "{e}");
        // a cell of a column nobody selected is still checked
        let mut r = StreamReader::new(&b"t_s,omega_rad_s,f_set_hz\n0,1,2\n0.001,1,2x\n"[..], "r.csv").expect("header");
        r.select(&[1]);
        let e = r.read_batch(&mut Batch::default(), 10).expect_err("bad unused cell").to_string();
        assert!(e.contains("r.csv") && e.contains("line 3") && e.contains("`f_set_hz`") && e.contains("2x"), "{e}");
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
    fn a_line_longer_than_the_cap_is_named_not_echoed() {
        // a line at the cap reads, through reads that cut it anywhere
        let name = "x".repeat(MAX_LINE_BYTES - 4);
        let text = format!("t_s,{name}\n0,1\n0.001,2\n");
        let (names, columns) = read_all(text.as_bytes(), 10, 1 << 12, true).expect("valid");
        assert_eq!((names[1].len(), &columns[1]), (name.len(), &vec![1.0, 2.0]));
        // one byte more, in a row or with no line end at all: the line's number and the cap, not its text
        for text in [format!("t_s,x\n0,1\n0.001,{}\n", "7".repeat(MAX_LINE_BYTES)), "9".repeat(1 << 20)] {
            let e = parse_str(&text).expect_err("too long").to_string();
            let line = if text.starts_with('t') { "line 3" } else { "line 1" };
            assert!(e.contains(line) && e.contains(&MAX_LINE_BYTES.to_string()) && e.len() < 300, "{e}");
        }
    }

    #[test]
    fn unknown_columns_are_ignored_whatever_they_hold() {
        let text = "t_s,note,omega_rad_s\n0,started,1\n0.001,\"a, b\",2\n0.002,x\"y,3\n";
        let r = parse_str(text).expect("text in an unknown column is no error");
        assert_eq!(r.column("omega_rad_s").expect("omega"), [1.0, 2.0, 3.0]);
        assert!(r.column("note").expect("kept").iter().all(|v| v.is_nan()));
        let mut s = StreamReader::new(text.as_bytes(), "r.csv").expect("header");
        s.select(&[2]);
        assert_eq!(s.read_batch(&mut Batch::default(), 10).expect("rows"), 3);
        // a column the contract names is still checked
        assert!(parse_str("t_s,f_set_hz\n0,fast\n").is_err());
    }

    #[test]
    fn cells_outside_the_sensor_range_are_missing_and_counted() {
        let text =
            "t_s,p_in_bar,omega_rad_s,theta_rad\n0,1e308,5,inf\n0.001,10,1e308,1\n0.002,-3,6,2\n0.003,,7,1e300\n";
        let r = parse_str(text).expect("valid");
        let p = r.column("p_in_bar").expect("p_in");
        assert!(p[0].is_nan() && p[1] == 10.0 && p[2].is_nan() && p[3].is_nan());
        let got: Vec<(&str, u64, u64)> =
            r.out_of_range.iter().map(|o| (o.column.as_str(), o.cells, o.first_line)).collect();
        assert_eq!(got, [("p_in_bar", 2, 2), ("omega_rad_s", 1, 3), ("theta_rad", 1, 2)]);
        let shown = r.out_of_range[0].to_string();
        assert!(shown.contains("r.csv, line 2, column `p_in_bar`") && shown.contains("2 cell(s)"), "{shown}");
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
        /// A cell of a column only checked is accepted exactly when `str::parse` accepts it.
        #[test]
        fn checked_cells_accept_what_std_accepts(cell in "[ 0-9.eE+\\-a-z\"]{0,12}") {
            let text = format!("t_s,f_set_hz,omega_rad_s\n0,{cell},1\n");
            // a quoted cell is read as the text between its quotes
            let trimmed = cell.trim_ascii();
            let inside = trimmed.strip_prefix('"').and_then(|c| c.strip_suffix('"')).filter(|c| !c.contains('"'));
            let value = inside.unwrap_or(trimmed).trim_ascii();
            let std_ok = value.is_empty() || value.parse::<f64>().is_ok();
            let mut r = StreamReader::new(text.as_bytes(), "r.csv").expect("header");
            r.select(&[2]);
            let read = r.read_batch(&mut Batch::default(), 10);
            prop_assert_eq!(read.is_ok(), std_ok, "{:?}: {:?}", cell, read.err());
            assert_plain_path_agrees(&text, 10, 3);
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
                    (Some(a), Some(b)) => {
                        prop_assert!(a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan()), "{cell}")
                    }
                    (None, None) => {}
                    (None, Some(_)) if cell.trim_ascii().is_empty() => {}
                    (a, b) => prop_assert!(false, "{cell:?}: std {a:?}, fast {b:?}"),
                }
            }
        }

        /// Small random recordings, with odd spacing, quotes, gaps, line ends and the odd bad cell: the plain path
        /// reads what the grammar's rule reads, or fails where and as it fails, whatever the batch size and however
        /// the reads cut the text.
        #[test]
        fn the_plain_path_reads_as_the_rule_reads(
            rows in proptest::collection::vec(
                (0.0f64..0.01, proptest::collection::vec(
                    prop_oneof![
                        8 => any::<f64>().prop_map(|v| v.to_string()),
                        2 => (-1e3f64..1e3).prop_map(|v| format!("{v:e}")),
                        2 => Just(String::new()),
                        1 => Just(" 2.5 ".to_string()),
                        1 => Just("\t-1\t".to_string()),
                        1 => Just("nan".to_string()),
                        1 => Just("\"4\"".to_string()),
                        1 => Just("\"4,5\"".to_string()),
                        1 => Just("x".to_string()),
                        1 => Just("1e".to_string()),
                        1 => Just("1\x0c".to_string()),
                    ],
                    3,
                ), prop_oneof![8 => Just("\n"), 2 => Just("\r\n"), 1 => Just("\r"), 1 => Just("\n\n")]),
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
            assert_plain_path_agrees(&text, max_rows, piece);
        }
    }
}

//! Reading a recording CSV: every bad cell is named by file, line and column.

use std::io::Read;
use std::path::Path;

use super::{KNOWN_COLUMNS, Recording};

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
    /// exist (exit code 2).
    pub fn is_bad_input(&self) -> bool {
        match self {
            RecordingError::Io { source, .. } => {
                matches!(source.kind(), std::io::ErrorKind::NotFound | std::io::ErrorKind::InvalidData)
            }
            _ => true,
        }
    }
}

/// Reads a recording file (a last line cut mid-row is dropped with a warning, see [`super::cut`]).
pub fn load(path: &Path) -> Result<Recording, RecordingError> {
    let name = path.display().to_string();
    let file = super::cut::open(path)?;
    parse(std::io::BufReader::with_capacity(1 << 16, file), &name)
}

/// Parses recording CSV text; `origin` names it in errors.
pub fn parse<R: Read>(reader: R, origin: &str) -> Result<Recording, RecordingError> {
    let file_err = |message: String| RecordingError::File { path: origin.to_string(), message };
    let mut csv = csv::ReaderBuilder::new().has_headers(true).trim(csv::Trim::All).from_reader(reader);
    let headers = csv.headers().map_err(|e| file_err(format!("cannot read the header row: {e}")))?.clone();
    let (names, t_index) = header_names(headers.iter(), origin)?;
    // t_s first, the rest in file order
    let order: Vec<usize> = std::iter::once(t_index).chain((0..names.len()).filter(|&i| i != t_index)).collect();
    let mut columns: Vec<Vec<f64>> = vec![Vec::new(); names.len()];
    let mut record = csv::ByteRecord::new();
    let mut last_t = f64::NEG_INFINITY;
    loop {
        match csv.read_byte_record(&mut record) {
            Ok(false) => break,
            Ok(true) => {}
            Err(e) => {
                let line = e.position().map_or(0, csv::Position::line);
                return Err(RecordingError::Line { path: origin.into(), line, message: e.to_string() });
            }
        }
        let line = record.position().map_or(0, csv::Position::line);
        if record.len() != names.len() {
            return Err(RecordingError::Line {
                path: origin.into(),
                line,
                message: format!("{} fields, expected {} as in the header", record.len(), names.len()),
            });
        }
        for (slot, &i) in order.iter().enumerate() {
            columns[slot].push(cell_value(&record[i], origin, line, &names[i])?);
        }
        let t = *columns[0].last().unwrap_or(&f64::NAN);
        check_time(t, last_t, origin, line)?;
        last_t = t;
    }
    if columns[0].is_empty() {
        return Err(file_err("no data rows after the header".into()));
    }
    let ordered_names = order.iter().map(|&i| names[i].clone()).collect();
    Ok(Recording::from_columns(origin, ordered_names, columns))
}

/// The column names of a header row, from its fields as the csv crate gives them (ASCII spaces trimmed), checked:
/// not empty, `t_s` present, no name twice; unknown names are logged once. Returns the names and where `t_s` is.
pub(super) fn header_names<'a>(
    fields: impl IntoIterator<Item = &'a str>,
    origin: &str,
) -> Result<(Vec<String>, usize), RecordingError> {
    let fields: Vec<&str> = fields.into_iter().collect();
    if fields.is_empty() || (fields.len() == 1 && fields[0].is_empty()) {
        return Err(RecordingError::File {
            path: origin.to_string(),
            message: "the file is empty: expected a header row starting with `t_s`".into(),
        });
    }
    let names: Vec<String> = fields.iter().map(|h| h.trim().to_string()).collect();
    let Some(t_index) = names.iter().position(|n| n == "t_s") else {
        return Err(RecordingError::Line {
            path: origin.into(),
            line: 1,
            message: format!("no `t_s` column (required); the header has {}", names.join(", ")),
        });
    };
    for (i, n) in names.iter().enumerate() {
        if names[..i].contains(n) {
            return Err(RecordingError::Line {
                path: origin.into(),
                line: 1,
                message: format!("column `{n}` appears twice"),
            });
        }
    }
    let unknown: Vec<&str> =
        names.iter().map(String::as_str).filter(|n| !KNOWN_COLUMNS.contains(n) && !n.starts_with("true_")).collect();
    if !unknown.is_empty() {
        tracing::info!(recording = origin, columns = ?unknown, "ignoring unknown columns");
    }
    Ok((names, t_index))
}

/// A cell's value: NaN when empty (after trimming ASCII spaces), else the number it must hold.
pub(super) fn cell_value(cell: &[u8], origin: &str, line: u64, column: &str) -> Result<f64, RecordingError> {
    let cell = cell.trim_ascii();
    if cell.is_empty() {
        return Ok(f64::NAN);
    }
    parse_number(cell).ok_or_else(|| RecordingError::Cell {
        path: origin.into(),
        line,
        column: column.to_string(),
        message: format!("expected a number, got {:?}", String::from_utf8_lossy(cell)),
    })
}

/// A row's time must be finite and later than the row before's.
pub(super) fn check_time(t: f64, last_t: f64, origin: &str, line: u64) -> Result<(), RecordingError> {
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

/// A decimal number from a cell's bytes.
pub(super) fn parse_number(cell: &[u8]) -> Option<f64> {
    std::str::from_utf8(cell).ok()?.parse::<f64>().ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse_str(s: &str) -> Result<Recording, RecordingError> {
        parse(s.as_bytes(), "r.csv")
    }

    #[test]
    fn reads_columns_and_missing_values() {
        let r = parse_str("omega_rad_s, t_s ,foo\n 1.5 ,0.0,\n,0.001,3\n").expect("valid");
        assert_eq!(r.names()[0], "t_s");
        assert_eq!(r.t_s(), &[0.0, 0.001]);
        let w = r.column("omega_rad_s").expect("column");
        assert_eq!(w[0], 1.5);
        assert!(w[1].is_nan());
    }

    #[test]
    fn bad_input_names_line_and_column() {
        let e = parse_str("t_s,omega_rad_s\n0,1\n0.001,abc\n").expect_err("bad cell").to_string();
        assert!(e.contains("line 3") && e.contains("omega_rad_s") && e.contains("abc"), "{e}");
        let e = parse_str("t_s,omega_rad_s\n0,1\n0.002,1\n0.001,1\n").expect_err("backwards").to_string();
        assert!(e.contains("line 4") && e.contains("t_s"), "{e}");
        let e = parse_str("omega_rad_s\n1\n").expect_err("no t_s").to_string();
        assert!(e.contains("t_s") && e.contains("line 1"), "{e}");
        let e = parse_str("").expect_err("empty").to_string();
        assert!(e.contains("empty"), "{e}");
        let e = parse_str("t_s,omega_rad_s\n").expect_err("no rows").to_string();
        assert!(e.contains("no data rows"), "{e}");
        let e = parse_str("t_s,omega_rad_s\n0,1,2\n").expect_err("ragged").to_string();
        assert!(e.contains("line 2"), "{e}");
        let e = parse_str("t_s,omega_rad_s\n,1\n").expect_err("missing t").to_string();
        assert!(e.contains("line 2") && e.contains("t_s"), "{e}");
    }
}

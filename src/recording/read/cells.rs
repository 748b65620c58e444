//! The cells of a line: [`row`], the reader of a line by the grammar (quotes included), and [`plain_row`], the one
//! pass over a line of plain cells that parses only the selected ones (the parent module's doc gives the grammar).

use std::borrow::Cow;

use super::*;

/// The cells of a line, by the grammar's rules on commas and quotes (not yet trimmed); `Err(k)` where cell `k`
/// (from 0) opens a quote that does not close on the line.
pub(super) fn fields(line: &[u8]) -> Result<Vec<Cow<'_, [u8]>>, usize> {
    let mut out = Vec::new();
    let mut i = 0;
    loop {
        let (cell, end) = field(line, i).ok_or(out.len())?;
        out.push(cell);
        if end == line.len() {
            return Ok(out);
        }
        i = end + 1;
    }
}

/// What a cell whose quote does not close on its line is told (a spreadsheet's cell of several lines, or a cut one).
pub(super) const UNCLOSED_QUOTE: &str = "a quote opens and does not close on its line (a cell may not span lines)";

/// The cell that starts at `line[i]`, and where it ends (at a comma or the end of the line); None where it opens a
/// quote that does not close on the line.
pub(super) fn field(line: &[u8], i: usize) -> Option<(Cow<'_, [u8]>, usize)> {
    let next_comma = |from: usize| memchr::memchr(b',', &line[from..]).map_or(line.len(), |k| from + k);
    let skip_space = |from: usize| from + line[from..].iter().take_while(|b| b.is_ascii_whitespace()).count();
    let first = skip_space(i);
    if line.get(first) != Some(&b'"') {
        let end = next_comma(i);
        return Some((Cow::Borrowed(&line[i..end]), end));
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
                return Some((Cow::Owned(text), after));
            }
            // text after the closing quote: the cell is its text, up to the next comma
            let end = next_comma(after);
            return Some((Cow::Borrowed(&line[i..end]), end));
        }
        text.push(line[k]);
        k += 1;
    }
    None
}

/// A line by the grammar, checked in its order (number of cells, `t_s`, the other cells): the row's `t_s`, with the
/// selected values pushed to `batch`, or the first error.
pub(super) fn row(
    line: &[u8],
    number: u64,
    (names, known): (&[String], &[bool]),
    roles: &[Role],
    t_index: usize,
    origin: &str,
    batch: &mut Batch,
) -> Result<f64, RecordingError> {
    let cells = fields(line).map_err(|k| match names.get(k) {
        Some(column) => RecordingError::Cell {
            path: origin.into(),
            line: number,
            column: column.clone(),
            message: UNCLOSED_QUOTE.into(),
        },
        None => RecordingError::Line {
            path: origin.into(),
            line: number,
            message: format!("cell {} (the header has {} names): {UNCLOSED_QUOTE}", k + 1, names.len()),
        },
    })?;
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
pub(super) fn cell_value(cell: &[u8], origin: &str, line: u64, column: &str) -> Result<f64, RecordingError> {
    let cell = cell.trim_ascii();
    if cell.is_empty() {
        return Ok(f64::NAN);
    }
    let number = std::str::from_utf8(cell).ok().and_then(|s| s.parse::<f64>().ok());
    number.ok_or_else(|| RecordingError::Cell {
        path: origin.into(),
        line,
        column: column.to_string(),
        message: format!("expected a number, got {}", shown(cell)),
    })
}

/// A cell for a message: quoted, control characters as `\u{…}` (a NUL then a digit read as `"\01"`), at most 40
/// characters.
fn shown(cell: &[u8]) -> String {
    let text = String::from_utf8_lossy(cell);
    let mut out: String = text
        .chars()
        .take(40)
        .map(|c| match c {
            '"' | '\\' => format!("\\{c}"),
            c if c.is_control() => format!("\\u{{{:x}}}", u32::from(c)),
            c => c.to_string(),
        })
        .collect();
    if text.chars().nth(40).is_some() {
        out.push('…');
    }
    format!("\"{out}\"")
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
            message: format!(
                "time goes backwards or repeats: {} after {} (must strictly increase)",
                crate::units::shown(t),
                crate::units::shown(last_t)
            ),
        });
    }
    Ok(())
}

/// A line of plain cells in one pass into `batch`: its `t_s`, or `None` for any line that [`row`] must read (the
/// batch may then hold part of the row: see [`Batch::truncate_to_rows`]). Plain: cells separated by commas, padded
/// with spaces or tabs at most, each empty or a decimal number (`nan` and `inf` too where the column is selected).
#[inline]
pub(super) fn plain_row(line: &[u8], roles: &[Role], batch: &mut Batch) -> Option<f64> {
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
pub(super) fn skip_blanks(line: &[u8], mut i: usize) -> usize {
    while matches!(line.get(i), Some(b' ' | b'\t')) {
        i += 1;
    }
    i
}

/// Where a cell whose content ends at `i` ends: at a comma or the end of the line, after blanks; `None` if
/// anything else follows.
#[inline]
pub(super) fn cell_end(line: &[u8], i: usize) -> Option<usize> {
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
pub(super) fn number_cell(line: &[u8], i: usize) -> Option<(f64, usize)> {
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
pub(super) fn checked_cell_end(line: &[u8], i: usize) -> Option<usize> {
    let i = skip_blanks(line, i);
    match line.get(i) {
        None | Some(b',') => Some(i),
        Some(_) => cell_end(line, plain_number_end(line, i)?),
    }
}

/// The end of the plain decimal number `[+-]? (digits [. digits?] | . digits) ([eE] [+-]? digits)?` at `s[i..]`;
/// `str::parse::<f64>` accepts every such number (and also `inf`, `nan`, which this leaves to [`row`]).
#[inline]
pub(super) fn plain_number_end(s: &[u8], mut i: usize) -> Option<usize> {
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
pub(super) fn skip_digits(s: &[u8], i: usize) -> usize {
    i + s[i.min(s.len())..].iter().take_while(|b| b.is_ascii_digit()).count()
}

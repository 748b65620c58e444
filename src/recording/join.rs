//! One drive's recording from several files: the service's rotated files joined in time order, or the files of one
//! drive found in a recordings directory.

use std::path::{Path, PathBuf};

use super::{Recording, RecordingError};

/// Joins recordings of one drive in the order of their first time stamp. Files named for different drives
/// (`<drive>-<unix ms>.csv[.gz]`) are refused, naming both, and so are files that overlap in time (the service's
/// `t_s` restarts with each run). Columns missing from a file are empty in its rows, with a warning naming the
/// file; `load_nm` is kept only when every file has it (a load recorded in part is no recorded load).
pub fn join(mut parts: Vec<Recording>) -> Result<Recording, RecordingError> {
    if parts.len() == 1 {
        return Ok(parts.remove(0));
    }
    let Some(first) = parts.first() else {
        return Err(RecordingError::File { path: "(none)".into(), message: "no recording given".into() });
    };
    let mut names: Vec<String> = first.names().to_vec();
    let drives: Vec<(usize, &str)> =
        parts.iter().enumerate().filter_map(|(i, p)| drive_of(&p.source).map(|d| (i, d))).collect();
    if let Some(&(i, a)) = drives.first()
        && let Some(&(j, b)) = drives.iter().find(|(_, b)| *b != a)
    {
        return Err(RecordingError::File {
            path: parts[j].source.clone(),
            message: format!(
                "is a recording of drive `{b}`, {} one of drive `{a}`: files of different drives are not joined; \
                 analyse one drive's files",
                parts[i].source
            ),
        });
    }
    parts.sort_by(|a, b| a.t_s()[0].total_cmp(&b.t_s()[0]));
    for w in parts.windows(2) {
        let (a, b) = (&w[0], &w[1]);
        let (end, start) = (a.t_s()[a.len() - 1], b.t_s()[0]);
        if start <= end {
            return Err(RecordingError::File {
                path: b.source.clone(),
                message: format!(
                    "overlaps {} in time (t_s from {start} while that file runs to {end}): the service's t_s \
                     restarts with each run, so analyse the files of one run together",
                    a.source
                ),
            });
        }
    }
    for p in &parts {
        for n in p.names() {
            if !names.contains(n) {
                names.push(n.clone());
            }
        }
    }
    for p in &parts {
        let missing: Vec<&str> = names.iter().filter(|n| p.column(n).is_none()).map(String::as_str).collect();
        if !missing.is_empty() {
            tracing::warn!(recording = %p.source, columns = ?missing, "joined without these columns: empty in its rows");
        }
    }
    if parts.iter().any(|p| p.column("load_nm").is_none()) && names.iter().any(|n| n == "load_nm") {
        tracing::warn!("`load_nm` is not in every file: the joined recording is taken as having no recorded load");
        names.retain(|n| n != "load_nm");
    }
    let total: usize = parts.iter().map(Recording::len).sum();
    let columns: Vec<Vec<f64>> = names
        .iter()
        .map(|n| {
            let mut c = Vec::with_capacity(total);
            for p in &parts {
                match p.column(n) {
                    Some(v) => c.extend_from_slice(v),
                    None => c.extend(std::iter::repeat_n(f64::NAN, p.len())),
                }
            }
            c
        })
        .collect();
    let source = parts.iter().map(|p| p.source.as_str()).collect::<Vec<_>>().join(" + ");
    let mut joined = Recording::from_columns(&source, names, columns);
    joined.out_of_range = parts.iter().flat_map(|p| p.out_of_range.iter().cloned()).collect();
    Ok(joined)
}

/// The drive a recording file is named for (`<drive>-<unix ms>[-<n>].csv[.gz]`), if it is named so.
fn drive_of(path: &str) -> Option<&str> {
    let name = Path::new(path).file_name()?.to_str()?;
    let stem = name.strip_suffix(".csv.gz").or_else(|| name.strip_suffix(".csv"))?;
    let mut drive = stem;
    for _ in 0..2 {
        match drive.rsplit_once('-') {
            Some((head, tail)) if !tail.is_empty() && tail.bytes().all(|b| b.is_ascii_digit()) => drive = head,
            _ => break,
        }
    }
    (drive != stem && !drive.is_empty()).then_some(drive)
}

/// Where `name` sorts among `drive`'s recording files `<drive>-<unix ms>[-<n>].csv[.gz]`: the stamp and the
/// counter, and whether it is compressed; None for any other name (`pump1-…` never picks up `pump1-a-…`, nor
/// `pump1-2-<stamp>…`, drive `pump1-2`'s).
pub fn drive_file_key(name: &str, drive: &str) -> Option<(Vec<u64>, bool)> {
    let rest = name.strip_prefix(drive)?.strip_prefix('-')?;
    let (stem, compressed) = match rest.strip_suffix(".csv.gz") {
        Some(stem) => (stem, true),
        None => (rest.strip_suffix(".csv")?, false),
    };
    // the stamp and an optional counter, all digits
    if stem.split('-').any(|p| p.is_empty() || !p.bytes().all(|b| b.is_ascii_digit())) {
        return None;
    }
    let key: Vec<u64> = stem.split('-').map(|p| p.parse().ok()).collect::<Option<_>>()?;
    // a counter is small beside its stamp: `pump-2-1796702003802.csv` is drive `pump-2`'s, not `pump`'s with stamp 2
    // (taken as `pump`'s, it was deleted by `pump`'s retention and joined into `pump`'s runs)
    let counted_beyond_its_stamp = key.len() == 2 && key[1] >= key[0];
    (key.len() <= 2 && !counted_beyond_its_stamp).then_some((key, compressed))
}

/// The files `<drive>-<unix ms>[-<n>].csv[.gz]` the service wrote for `drive` in `dir`, oldest first. A file
/// found both plain and compressed (compressing was cut short after its rename) is taken once, plain. A file that
/// holds no row (empty, or a header alone: a full disk left it) is skipped with a warning naming it.
pub fn drive_files(dir: &Path, drive: &str) -> Result<Vec<PathBuf>, RecordingError> {
    let io = |error| RecordingError::Io { path: dir.display().to_string(), error };
    let mut found: Vec<((Vec<u64>, bool), PathBuf)> = Vec::new();
    let mut skipped = 0;
    for entry in std::fs::read_dir(dir).map_err(io)? {
        let entry = entry.map_err(io)?;
        let name = entry.file_name().to_string_lossy().into_owned();
        if let Some(key) = drive_file_key(&name, drive) {
            // a named pipe or a device would block or never end: only regular files (a link to one too)
            if !std::fs::metadata(entry.path()).is_ok_and(|m| m.is_file()) {
                tracing::warn!(path = %entry.path().display(), "not a regular file: skipped");
                continue;
            }
            // a file that cannot be read is kept: reading it says what is wrong
            if super::holds_no_rows(&entry.path()).unwrap_or(false) {
                tracing::warn!(file = %entry.path().display(), "skipping a recording that holds no rows");
                skipped += 1;
                continue;
            }
            found.push((key, entry.path()));
        }
    }
    if found.is_empty() {
        let skipped = if skipped > 0 { format!("; {skipped} file(s) with no rows skipped") } else { String::new() };
        return Err(RecordingError::File {
            path: dir.display().to_string(),
            message: format!("no recording of drive `{drive}` (files named {drive}-<unix ms>.csv or .csv.gz){skipped}"),
        });
    }
    found.sort();
    // plain sorts before compressed: a compressed twin follows its plain file
    found.dedup_by(|b, a| a.0.0 == b.0.0);
    Ok(found.into_iter().map(|f| f.1).collect())
}

/// The last run among a drive's recording files given oldest first: the files after the last restart of `t_s`
/// (from each file's first and last `t_s`, streamed, so that older runs are never held in memory).
/// Returns that run and how many files were left out.
pub fn last_run(files: &[PathBuf]) -> (Vec<PathBuf>, usize) {
    let spans: Vec<Option<(f64, f64)>> = files.iter().map(|p| time_span(p)).collect();
    let mut start = 0;
    for i in 1..files.len() {
        if let (Some((_, a_last)), Some((b_first, _))) = (spans[i - 1], spans[i])
            && b_first <= a_last
        {
            start = i;
        }
    }
    (files[start..].to_vec(), start)
}

/// A recording's first and last `t_s`, read as a stream without its other columns (memory stays flat); None when
/// it cannot be read (reading it whole then says why).
fn time_span(path: &Path) -> Option<(f64, f64)> {
    let mut reader = super::StreamReader::open(path).ok()?;
    reader.select(&[]);
    let mut batch = super::Batch::default();
    let mut span: Option<(f64, f64)> = None;
    while reader.read_batch(&mut batch, 1 << 16).ok()? > 0 {
        let (first, last) = (batch.t_s[0], batch.t_s[batch.t_s.len() - 1]);
        span = Some(span.map_or((first, last), |(f, _)| (f, last)));
    }
    span
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rec(name: &str, t: &[f64], cols: &[&str]) -> Recording {
        let mut names = vec!["t_s".to_string()];
        let mut columns = vec![t.to_vec()];
        for c in cols {
            names.push(c.to_string());
            columns.push(t.iter().map(|v| v * 10.0).collect());
        }
        Recording::from_columns(name, names, columns)
    }

    #[test]
    fn joins_in_time_order_and_fills_missing_columns() {
        let a = rec("a.csv", &[0.0, 0.1], &["omega_rad_s"]);
        let b = rec("b.csv", &[0.2, 0.3], &["omega_rad_s", "f_set_hz"]);
        let j = join(vec![b, a]).expect("joins");
        assert_eq!(j.t_s(), &[0.0, 0.1, 0.2, 0.3]);
        assert_eq!(j.column("omega_rad_s").expect("omega"), &[0.0, 1.0, 2.0, 3.0]);
        let f = j.column("f_set_hz").expect("f_set");
        assert!(f[0].is_nan() && f[1].is_nan() && f[2] == 2.0);
        assert_eq!(j.source, "a.csv + b.csv");
    }

    #[test]
    fn overlapping_files_are_refused_naming_both() {
        let a = rec("a.csv", &[0.0, 0.5], &[]);
        let b = rec("b.csv", &[0.2, 0.3], &[]);
        let e = join(vec![a, b]).expect_err("overlap").to_string();
        assert!(e.contains("a.csv") && e.contains("b.csv") && e.contains("overlaps"), "{e}");
    }

    #[test]
    fn files_of_two_drives_are_refused_naming_both() {
        let a = rec("d/pump1-100.csv", &[0.0, 0.1], &[]);
        let b = rec("d/pump2-200.csv.gz", &[0.2, 0.3], &[]);
        let e = join(vec![a, b]).expect_err("two drives").to_string();
        assert!(e.contains("pump1-100.csv") && e.contains("pump2-200.csv.gz") && e.contains("`pump2`"), "{e}");
        let a = rec("d/pump1-a-100.csv", &[0.0, 0.1], &[]);
        let b = rec("d/pump1-a-200-1.csv", &[0.2, 0.3], &[]);
        assert!(join(vec![a, b]).is_ok());
        assert_eq!(drive_of("x/pump1-100-2.csv.gz"), Some("pump1"));
        assert_eq!(drive_of("rec.csv"), None);
        assert_eq!(drive_of("100.csv"), None);
    }

    #[test]
    fn a_load_in_some_files_only_is_no_recorded_load() {
        let a = rec("a.csv", &[0.0, 0.1], &["omega_rad_s", "load_nm"]);
        let b = rec("b.csv", &[0.2, 0.3], &["omega_rad_s"]);
        let j = join(vec![a, b]).expect("joins");
        assert!(j.column("load_nm").is_none() && j.column("omega_rad_s").is_some());
    }

    #[test]
    fn the_last_run_starts_where_time_restarts() {
        let dir = tempfile::tempdir().expect("tmp");
        let files: Vec<PathBuf> = [("1.csv", "0\n1\n"), ("2.csv", "0\n1\n"), ("3.csv", "2\n3\n")]
            .iter()
            .map(|(name, rows)| {
                let p = dir.path().join(name);
                std::fs::write(&p, format!("t_s\n{rows}")).expect("write");
                p
            })
            .collect();
        let (run, left) = last_run(&files);
        assert_eq!(left, 1);
        assert_eq!(run, files[1..]);
    }

    #[test]
    fn finds_a_drives_files_and_nothing_else() {
        let dir = tempfile::tempdir().expect("tmp");
        for n in [
            "pump1-200.csv",
            "pump1-100.csv.gz",
            "pump1-200-1.csv",
            "pump1-200-1.csv.gz",
            "pump1-300.csv.gz",
            ".pump1-400.csv.gz.tmp",
            "pump1-a-5.csv",
            "pump1-5.csv.gz.tmp",
            "pump10-1.csv",
            "pump1-2-1796702003802.csv.gz",
            "pump1-2-1796702003802-1.csv",
            "x.csv",
        ] {
            std::fs::write(dir.path().join(n), "t_s\n0\n").expect("write");
        }
        let files = drive_files(dir.path(), "pump1").expect("found");
        let names: Vec<String> =
            files.iter().map(|p| p.file_name().expect("name").to_string_lossy().into_owned()).collect();
        assert_eq!(names, vec!["pump1-100.csv.gz", "pump1-200.csv", "pump1-200-1.csv", "pump1-300.csv.gz"]);
        let e = drive_files(dir.path(), "pump2").expect_err("none").to_string();
        assert!(e.contains("pump2"), "{e}");
    }

    #[test]
    fn a_drives_files_that_hold_no_rows_are_skipped() {
        let dir = tempfile::tempdir().expect("tmp");
        std::fs::write(dir.path().join("pump1-100.csv"), "t_s\n0\n").expect("write");
        std::fs::write(dir.path().join("pump1-200.csv.gz"), "").expect("write");
        std::fs::write(dir.path().join("pump1-300.csv"), "t_s,x\n").expect("write");
        std::fs::write(dir.path().join("pump1-400.csv"), "t_s\n1\n").expect("write");
        let files = drive_files(dir.path(), "pump1").expect("found");
        let names: Vec<String> =
            files.iter().map(|p| p.file_name().expect("name").to_string_lossy().into_owned()).collect();
        assert_eq!(names, vec!["pump1-100.csv", "pump1-400.csv"]);
        std::fs::remove_file(dir.path().join("pump1-100.csv")).expect("rm");
        std::fs::remove_file(dir.path().join("pump1-400.csv")).expect("rm");
        let e = drive_files(dir.path(), "pump1").expect_err("only empty files").to_string();
        assert!(e.contains("pump1") && e.contains("2 file(s) with no rows skipped"), "{e}");
    }
}

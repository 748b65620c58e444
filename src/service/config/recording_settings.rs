//! `[recording]`: where the recordings go, their rotation, retention and compression, parsed raw and validated (a
//! room of the service config, [`super`]).

use super::*;

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub(super) struct RawRecording {
    dir: String,
    enabled: bool,
    max_file_mb: f64,
    rotate_hours: f64,
    /// All drives' recordings together at most this (each drive keeps its share); absent: unbounded.
    max_total_mb: Option<f64>,
    /// Closed recordings older than this are deleted; absent: kept.
    keep_days: Option<f64>,
    /// Closed files are gzip-compressed to `.csv.gz`.
    compress: bool,
}

impl Default for RawRecording {
    fn default() -> Self {
        RawRecording {
            dir: "recordings".into(),
            enabled: true,
            max_file_mb: 64.0,
            rotate_hours: 1.0,
            max_total_mb: None,
            keep_days: None,
            compress: true,
        }
    }
}

#[derive(Debug, Clone)]
pub struct RecordingSettings {
    /// None: recording off.
    pub dir: Option<PathBuf>,
    pub max_file_bytes: u64,
    pub rotate_after: Duration,
    /// All drives' recordings together at most this many bytes.
    pub max_total_bytes: Option<u64>,
    /// Closed recordings older than this go.
    pub keep: Option<Duration>,
    /// Closed files are compressed to `<name>.csv.gz`, off the poll loop; readers take either.
    pub compress: bool,
    /// Where a writing drive keeps its trip latch across restarts: `recording.dir` whenever it is given, recording on
    /// or off (with recording off, a service killed while its drive was latched sent RUN when started again).
    pub latch_dir: Option<PathBuf>,
}

/// The smallest `recording.max_file_mb`: about 500 rows, half a second at a 1 ms poll.
pub const MIN_FILE_MB: f64 = 0.1;

/// The shortest `recording.rotate_hours`: one minute.
pub const MIN_ROTATE_HOURS: f64 = 1.0 / 60.0;

/// A recordings directory: an existing directory, or a path whose nearest existing ancestor is one.
fn directory_or_creatable(dir: &Path) -> Result<(), String> {
    for p in dir.ancestors().filter(|p| !p.as_os_str().is_empty()) {
        match std::fs::metadata(p) {
            Ok(m) if m.is_dir() => return Ok(()),
            Ok(_) if p == dir => return Err(format!("{} exists and is not a directory", dir.display())),
            Ok(_) => return Err(format!("{}: {} is not a directory", dir.display(), p.display())),
            Err(e) if matches!(e.kind(), std::io::ErrorKind::NotFound | std::io::ErrorKind::NotADirectory) => {}
            // unreadable: leave it to the recorder, whose error then says why
            Err(_) => return Ok(()),
        }
    }
    Ok(())
}

/// `[recording]`, validated.
pub(super) fn validate_recording(r: RawRecording) -> Result<RecordingSettings, Invalid> {
    let max_mb = positive("recording.max_file_mb", r.max_file_mb)?;
    if max_mb < MIN_FILE_MB {
        return Err(KeyError::new(
            "recording.max_file_mb".into(),
            format!("must be ≥ {MIN_FILE_MB} (smaller files rotate every few rows), got {max_mb}"),
        ));
    }
    let hours = positive("recording.rotate_hours", r.rotate_hours)?;
    if hours > 24.0 * 365.0 {
        return Err(KeyError::new("recording.rotate_hours".into(), format!("must be ≤ 8760, got {hours}")));
    }
    if hours < MIN_ROTATE_HOURS {
        return Err(KeyError::new(
            "recording.rotate_hours".into(),
            format!("must be ≥ {MIN_ROTATE_HOURS:.4} (one minute), got {hours}"),
        ));
    }
    if r.dir.is_empty() && r.enabled {
        return Err(KeyError::new("recording.dir".into(), "must not be empty while recording is enabled".into()));
    }
    if r.enabled {
        directory_or_creatable(Path::new(&r.dir)).map_err(|m| KeyError::new("recording.dir".to_string(), m))?;
    }
    let max_total_bytes = match r.max_total_mb {
        None => None,
        Some(t) => {
            let t = positive("recording.max_total_mb", t)?;
            if t < 2.0 * max_mb {
                return Err(KeyError::new(
                    "recording.max_total_mb".into(),
                    format!("must be at least twice recording.max_file_mb ({max_mb}), got {t}"),
                ));
            }
            Some((t * 1024.0 * 1024.0) as u64)
        }
    };
    let keep = match r.keep_days {
        None => None,
        Some(d) => {
            let d = positive("recording.keep_days", d)?;
            if d > 36_500.0 {
                return Err(KeyError::new("recording.keep_days".into(), format!("must be ≤ 36500, got {d}")));
            }
            Some(Duration::from_secs_f64(d * 86_400.0))
        }
    };
    Ok(RecordingSettings {
        latch_dir: (!r.dir.is_empty()).then(|| PathBuf::from(&r.dir)),
        dir: r.enabled.then(|| PathBuf::from(r.dir)),
        max_file_bytes: (max_mb * 1024.0 * 1024.0) as u64,
        rotate_after: Duration::from_secs_f64(hours * 3600.0),
        max_total_bytes,
        keep,
        compress: r.compress,
    })
}

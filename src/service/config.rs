//! The service config (`config/hydrolens.toml`): parsed raw and strictly (unknown keys are errors), then validated
//! into typed settings that cannot be invalid. Every error names its key.
//!
//! In the service's layout (see [`super`]) it uses [`super::freshness`] (the plausible ranges and rates) and
//! [`super::mqtt_config`] (`[mqtt]`), nothing above them: the condition checks and the MQTT publisher take their
//! settings from here.

use crate::error::KeyError;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Duration;

use serde::Deserialize;

use super::freshness::{RateLimits, ValidRanges};
use crate::condition;
use crate::control::{FeedForward, Gains, Limits, Mode};
use crate::estimator::{EstimatorSettings, Method};
use crate::modbus::client::Endpoint;
use crate::modbus::line::{MAX_LINE_LOAD, Parity, SerialLine, line_load, read_frames, write_frames};
use crate::modbus::map::{RegisterMap, RegisterSpec, Table, ValueType, WordOrder};
use crate::plant::dynamics::Coefficients;
use crate::plant::{LoadSpec, PlantModel};

/// The longest `stale_ms`: data older than this are stale whatever the config says.
const MAX_STALE_MS: u64 = 600_000;

/// What can be wrong with a config. Everything is bad input (exit 2) but an `Io` error the user cannot fix.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The reason is in the message and not the error's source, so that a chain prints it once.
    #[error("cannot read config {path}: {error}")]
    Io { path: PathBuf, error: std::io::Error },
    #[error("config {path}: {message}")]
    Syntax { path: String, message: String },
    #[error("config {path}: key `{key}` {message}")]
    Invalid { path: String, key: String, message: String },
}

impl ConfigError {
    pub fn is_bad_input(&self) -> bool {
        match self {
            ConfigError::Io { error, .. } => crate::error::unreadable_is_bad_input(error),
            _ => true,
        }
    }
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawConfig {
    #[serde(default)]
    http: RawHttp,
    #[serde(default)]
    recording: RawRecording,
    #[serde(default)]
    drives: Vec<RawDrive>,
    /// MQTT publishing (src/service/mqtt.rs); absent: off.
    mqtt: Option<super::mqtt_config::RawMqtt>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct RawHttp {
    bind: String,
    token: String,
    max_body_bytes: usize,
    history_seconds: f64,
    /// A request's headers must arrive within this (also how long an idle kept-alive connection lives).
    header_timeout_ms: u64,
    /// A whole request, body included, must be answered within this.
    request_timeout_ms: u64,
    /// Open HTTP connections at most; further clients wait in the kernel's backlog.
    max_connections: usize,
    /// Open connections from one client address at most; beyond, only the reserved routes are served.
    max_connections_per_client: usize,
    /// Open `/api/events` streams at most; beyond, 503 at once.
    max_event_streams: usize,
}

impl Default for RawHttp {
    fn default() -> Self {
        RawHttp {
            bind: "127.0.0.1:8080".into(),
            token: String::new(),
            max_body_bytes: 4096,
            history_seconds: 120.0,
            header_timeout_ms: 10_000,
            request_timeout_ms: 10_000,
            max_connections: 512,
            max_connections_per_client: 128,
            max_event_streams: 64,
        }
    }
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct RawRecording {
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

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawDrive {
    name: String,
    /// `host:port`: the device (tcp) or the serial gateway (rtu-over-tcp); none for rtu.
    address: Option<String>,
    /// "tcp" (default) | "rtu" | "rtu-over-tcp".
    transport: Option<String>,
    /// rtu: the serial device (drives with the same one share the line and take turns).
    serial_port: Option<String>,
    /// The serial line's settings (rtu, and the gateway's line for rtu-over-tcp): they size the inter-frame gap
    /// and the line-capacity check. Signed, so that a negative value gets a message of its own.
    baud_rate: Option<i64>,
    parity: Option<String>,
    stop_bits: Option<i64>,
    #[serde(default = "one_u8")]
    unit_id: u8,
    #[serde(default = "ten")]
    poll_ms: u64,
    #[serde(default = "two_hundred")]
    timeout_ms: u64,
    /// No fresh sample for this long marks the drive stale (default: the larger of 5 polls and 50 ms).
    stale_ms: Option<u64>,
    /// Watchdog refresh period (default 100 ms, well inside the drive's comm timeout / 3).
    #[serde(default = "hundred")]
    watchdog_ms: u64,
    /// The drive's own comm timeout (its watchdog trips after this long without a change); default: the model's
    /// `drive.comm_timeout_ms`. `watchdog_ms` must stay within a third of it (CONTRACT.md, register 2).
    comm_timeout_ms: Option<u64>,
    /// Real-time (SCHED_FIFO) priority of the drive's poll thread, 1..=99; absent: normal scheduling.
    realtime_priority: Option<u8>,
    #[serde(default)]
    control: RawControl,
    #[serde(default)]
    estimator: RawEstimator,
    #[serde(default)]
    limits: RawLimits,
    #[serde(default)]
    registers: BTreeMap<String, RawRegister>,
    /// Condition monitoring (src/service/condition.rs).
    #[serde(default)]
    condition: RawCondition,
}

fn one_u8() -> u8 {
    1
}
fn ten() -> u64 {
    10
}
fn two_hundred() -> u64 {
    200
}
fn hundred() -> u64 {
    100
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct RawControl {
    mode: Mode,
    target_omega_rad_s: f64,
    fixed_hz: f64,
    min_hz: f64,
    max_hz: f64,
    ramp_hz_per_s: f64,
    kp: f64,
    ki: f64,
}

impl Default for RawControl {
    fn default() -> Self {
        RawControl {
            mode: Mode::Monitor,
            target_omega_rad_s: 0.0,
            fixed_hz: 0.0,
            min_hz: 0.0,
            max_hz: 50.0,
            ramp_hz_per_s: 20.0,
            kp: 0.2,
            ki: 0.6,
        }
    }
}

#[derive(Debug, Deserialize, Default)]
#[serde(deny_unknown_fields, default)]
struct RawEstimator {
    method: Option<String>,
    model: Option<String>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct RawLimits {
    min_pressure_bar: f64,
    max_pressure_bar: f64,
    max_speed_rad_s: f64,
    max_frequency_hz: f64,
    /// Rate-of-change plausibility (see [`RateLimits`]); a sample that moved faster is rejected like an
    /// out-of-range one.
    max_pressure_rate_bar_per_s: f64,
    max_speed_rate_rad_per_s2: f64,
    max_frequency_rate_hz_per_s: f64,
}

impl Default for RawLimits {
    fn default() -> Self {
        // the rates: about four times what the reference plant can do (≈ 40 000 bar/s with the pump into a closed
        // volume, ≈ 2 500 rad/s² at 400 bar) and far above sensor noise differenced at a 1 ms poll (≈ 2 500 bar/s,
        // ≈ 9 000 rad/s² at 8 σ); drives ramp at tens of Hz/s
        // the ranges: the sensors' (one definition, which `estimate` and `analyze` apply to recordings too)
        RawLimits {
            min_pressure_bar: crate::recording::PRESSURE_RANGE_BAR.0,
            max_pressure_bar: crate::recording::PRESSURE_RANGE_BAR.1,
            max_speed_rad_s: crate::recording::MAX_SPEED_RAD_S,
            max_frequency_hz: crate::recording::MAX_FREQUENCY_HZ,
            max_pressure_rate_bar_per_s: 200_000.0,
            max_speed_rate_rad_per_s2: 10_000.0,
            max_frequency_rate_hz_per_s: 1_000.0,
        }
    }
}

#[derive(Debug, Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct RawRegister {
    table: Option<Table>,
    address: Option<u16>,
    #[serde(rename = "type")]
    kind: Option<ValueType>,
    scale: Option<f64>,
    offset: Option<f64>,
    word_order: Option<WordOrder>,
}

/// The whole service, validated.
#[derive(Debug, Clone)]
pub struct Settings {
    pub http: HttpSettings,
    pub recording: RecordingSettings,
    pub drives: Vec<DriveSettings>,
    pub mqtt: Option<super::mqtt_config::MqttSettings>,
}

#[derive(Debug, Clone)]
pub struct HttpSettings {
    pub bind: std::net::SocketAddr,
    /// Bearer token of the write routes; None disables them. Never logged.
    pub token: Option<String>,
    pub max_body_bytes: usize,
    pub history: Duration,
    pub header_timeout: Duration,
    pub request_timeout: Duration,
    pub max_connections: usize,
    pub max_connections_per_client: usize,
    pub max_event_streams: usize,
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
}

/// How a drive is reached.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Transport {
    /// Modbus TCP to `address`.
    Tcp,
    /// Modbus RTU on a serial port, shared with the other drives on the same port.
    Rtu { serial_port: String, line: SerialLine },
    /// RTU framing over TCP to a serial gateway at `address` (the gateway's line has the settings given).
    RtuOverTcp { line: SerialLine },
}

/// What identifies the device a drive talks to, whatever its spelling: the socket addresses its `host:port`
/// resolves to (an IPv4-mapped IPv6 address as IPv4, so `localhost`, `127.1` and `[::ffff:127.0.0.1]` are
/// 127.0.0.1's port), or a serial port's canonical path. Where neither resolves, the address as written.
fn device_ids(d: &DriveSettings) -> Vec<String> {
    use std::net::{SocketAddr, ToSocketAddrs};
    match &d.transport {
        Transport::Rtu { serial_port, .. } => {
            vec![std::fs::canonicalize(serial_port).map_or_else(|_| serial_port.clone(), |p| p.display().to_string())]
        }
        Transport::Tcp | Transport::RtuOverTcp { .. } => match d.address.to_socket_addrs() {
            Ok(addrs) => addrs
                .map(|a| match a {
                    SocketAddr::V6(v6) => match v6.ip().to_ipv4_mapped() {
                        Some(v4) => SocketAddr::from((v4, v6.port())).to_string(),
                        None => a.to_string(),
                    },
                    v4 => v4.to_string(),
                })
                .collect(),
            Err(_) => vec![d.address.clone()],
        },
    }
}

#[derive(Debug, Clone)]
pub struct DriveSettings {
    pub name: String,
    /// `host:port` (tcp, rtu-over-tcp) or the serial port (rtu): where the drive is, as the status shows it.
    pub address: String,
    pub transport: Transport,
    pub unit_id: u8,
    pub poll: Duration,
    pub timeout: Duration,
    pub stale_after: Duration,
    pub watchdog_every: Duration,
    /// SCHED_FIFO priority for the poll thread (Linux; needs CAP_SYS_NICE or an rtprio limit, else a warning).
    pub realtime_priority: Option<u8>,
    pub mode: Mode,
    pub target_omega_rad_s: f64,
    pub fixed_hz: f64,
    pub limits: Limits,
    pub gains: Gains,
    pub feed_forward: FeedForward,
    /// The estimator: `method` from `[drives.estimator]`, the rest from the model file's `[estimator]` table.
    pub estimator: EstimatorSettings,
    pub model: PlantModel,
    pub ranges: ValidRanges,
    pub registers: RegisterMap,
    pub condition: ConditionSettings,
}

impl DriveSettings {
    /// The RTU line this drive is on (its serial port, or its gateway's address), with the line's settings;
    /// None over Modbus TCP.
    pub fn line(&self) -> Option<(Endpoint, SerialLine)> {
        match &self.transport {
            Transport::Tcp => None,
            Transport::Rtu { serial_port, line } => {
                Some((Endpoint::Serial { port: serial_port.clone(), line: *line }, *line))
            }
            Transport::RtuOverTcp { line } => Some((Endpoint::RtuOverTcp(self.address.clone()), *line)),
        }
    }

    /// The RTU frames (request bytes, reply bytes) of one poll cycle at most: the reads, and the writes in a
    /// writing mode (the setpoint may change every cycle).
    pub fn cycle_frames(&self) -> Vec<(usize, usize)> {
        let mut frames: Vec<(usize, usize)> =
            crate::modbus::map::read_plan(&self.registers).iter().map(|&(_, _, count)| read_frames(count)).collect();
        if self.mode.writes() {
            frames.extend(crate::modbus::map::write_layout(&self.registers).iter().map(|&(_, n)| write_frames(n)));
        }
        frames
    }

    /// The speed the drive reaches at `max_hz` with no load: the largest target that makes sense.
    pub fn max_target_omega_rad_s(&self) -> f64 {
        self.feed_forward.omega_rad_s(self.limits.max_hz)
    }
}

/// Reads and validates a config file. Relative model paths are tried from the working directory, then from the
/// config file's directory.
pub fn load(path: &Path) -> Result<Settings, ConfigError> {
    let text = crate::error::read_text_file(path).map_err(|error| ConfigError::Io { path: path.into(), error })?;
    parse(&text, &path.display().to_string(), path.parent())
}

/// Parses and validates config text; `origin` names it in errors, `base` resolves relative model paths.
pub fn parse(text: &str, origin: &str, base: Option<&Path>) -> Result<Settings, ConfigError> {
    let raw: RawConfig = toml::from_str(text)
        .map_err(|e| ConfigError::Syntax { path: origin.to_string(), message: e.to_string().trim_end().to_string() })?;
    validate(raw, base).map_err(|KeyError { key, message }| ConfigError::Invalid {
        path: origin.to_string(),
        key,
        message,
    })
}

type Invalid = KeyError;

fn finite(key: &str, v: f64) -> Result<f64, Invalid> {
    if v.is_finite() { Ok(v) } else { Err(KeyError::new(key.into(), format!("must be a finite number, got {v}"))) }
}

fn nonneg(key: &str, v: f64) -> Result<f64, Invalid> {
    if v.is_finite() && v >= 0.0 {
        Ok(v)
    } else {
        Err(KeyError::new(key.into(), format!("must be finite and ≥ 0, got {v}")))
    }
}

fn positive(key: &str, v: f64) -> Result<f64, Invalid> {
    if v.is_finite() && v > 0.0 {
        Ok(v)
    } else {
        Err(KeyError::new(key.into(), format!("must be finite and > 0, got {v}")))
    }
}

/// The smallest `recording.max_file_mb`: about 500 rows, half a second at a 1 ms poll.
pub const MIN_FILE_MB: f64 = 0.1;
/// The shortest `recording.rotate_hours`: one minute.
pub const MIN_ROTATE_HOURS: f64 = 1.0 / 60.0;
/// The largest PI gains accepted: 50 and 170 times the defaults, far beyond any tuning that regulates.
pub const MAX_KP_HZ_PER_RAD_S: f64 = 10.0;
pub const MAX_KI_HZ_PER_RAD: f64 = 100.0;

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

/// The largest value a register can hold, in engineering units (for error messages).
fn register_capacity(spec: &RegisterSpec) -> f64 {
    let raw_max = match spec.kind {
        ValueType::U16 => 65535.0,
        ValueType::I16 => 32767.0,
        ValueType::U32 => 4_294_967_295.0,
        ValueType::I32 => 2_147_483_647.0,
        ValueType::F32 => f64::from(f32::MAX),
    };
    (raw_max * spec.scale.abs() * 1e6).round() / 1e6 + spec.offset
}

fn validate(raw: RawConfig, base: Option<&Path>) -> Result<Settings, Invalid> {
    let http = validate_http(raw.http)?;
    let recording = validate_recording(raw.recording)?;
    let drives = validate_drives(raw.drives, base)?;
    check_lines(&drives)?;
    let mqtt = raw.mqtt.map(|m| super::mqtt_config::validate(m, |p| resolve(p, base))).transpose()?;
    Ok(Settings { http, recording, drives, mqtt })
}

/// `[http]`, validated.
fn validate_http(h: RawHttp) -> Result<HttpSettings, Invalid> {
    let bind = h.bind.parse().map_err(|e| {
        KeyError::new("http.bind".to_string(), format!("{:?} is not an address such as 127.0.0.1:8080 ({e})", h.bind))
    })?;
    if h.max_body_bytes == 0 || h.max_body_bytes > 1 << 20 {
        return Err(KeyError::new(
            "http.max_body_bytes".into(),
            format!("must be 1 ..= 1048576, got {}", h.max_body_bytes),
        ));
    }
    let history_s = positive("http.history_seconds", h.history_seconds)?;
    if history_s > 3600.0 {
        return Err(KeyError::new("http.history_seconds".into(), format!("must be ≤ 3600, got {history_s}")));
    }
    let token = (!h.token.is_empty()).then_some(h.token);
    // an idle or half-sent request must be gone within 30 s (issue 20)
    for (k, ms) in [("http.header_timeout_ms", h.header_timeout_ms), ("http.request_timeout_ms", h.request_timeout_ms)]
    {
        if !(1..=30_000).contains(&ms) {
            return Err(KeyError::new(k.into(), format!("must be 1 ..= 30000, got {ms}")));
        }
    }
    if !(1..=65_536).contains(&h.max_connections) {
        return Err(KeyError::new(
            "http.max_connections".into(),
            format!("must be 1 ..= 65536, got {}", h.max_connections),
        ));
    }
    for (k, n) in [
        ("http.max_connections_per_client", h.max_connections_per_client),
        ("http.max_event_streams", h.max_event_streams),
    ] {
        if !(1..=65_536).contains(&n) {
            return Err(KeyError::new(k.into(), format!("must be 1 ..= 65536, got {n}")));
        }
    }
    Ok(HttpSettings {
        bind,
        token,
        max_body_bytes: h.max_body_bytes,
        history: Duration::from_secs_f64(history_s),
        header_timeout: Duration::from_millis(h.header_timeout_ms),
        request_timeout: Duration::from_millis(h.request_timeout_ms),
        max_connections: h.max_connections,
        max_connections_per_client: h.max_connections_per_client,
        max_event_streams: h.max_event_streams,
    })
}

/// `[recording]`, validated.
fn validate_recording(r: RawRecording) -> Result<RecordingSettings, Invalid> {
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
        dir: r.enabled.then(|| PathBuf::from(r.dir)),
        max_file_bytes: (max_mb * 1024.0 * 1024.0) as u64,
        rotate_after: Duration::from_secs_f64(hours * 3600.0),
        max_total_bytes,
        keep,
        compress: r.compress,
    })
}

/// The `[[drives]]`, each validated, with unique names and no two writing loops on one device.
fn validate_drives(raw: Vec<RawDrive>, base: Option<&Path>) -> Result<Vec<DriveSettings>, Invalid> {
    if raw.is_empty() {
        return Err(KeyError::new("drives".into(), "needs at least one [[drives]] entry".into()));
    }
    let mut drives = Vec::with_capacity(raw.len());
    // each drive's device identity, resolved once
    let mut devices: Vec<Vec<String>> = Vec::with_capacity(raw.len());
    for (i, d) in raw.into_iter().enumerate() {
        let drive = validate_drive(d, i, base)?;
        if drives.iter().any(|o: &DriveSettings| o.name == drive.name) {
            return Err(KeyError::new(
                format!("drives[{i}].name"),
                format!("{:?} is used by another drive", drive.name),
            ));
        }
        let ids = device_ids(&drive);
        if let Some((o, _)) = drives.iter().zip(&devices).find(|(o, o_ids): &(&DriveSettings, &Vec<String>)| {
            drive.mode.writes()
                && o.mode.writes()
                && o.unit_id == drive.unit_id
                && (o.address == drive.address || o_ids.iter().any(|id| ids.contains(id)))
        }) {
            let key = if matches!(drive.transport, Transport::Rtu { .. }) { "serial_port" } else { "address" };
            return Err(KeyError::new(
                format!("drives[{i}].{key}"),
                format!(
                    "{} with unit_id {} is already written by drive {:?}: two writing loops would fight over one \
                     drive (one may watch it in monitor mode)",
                    drive.address, drive.unit_id, o.name
                ),
            ));
        }
        drives.push(drive);
        devices.push(ids);
    }
    Ok(drives)
}

/// The drives on each RTU line: one setting per line, and no more traffic than the line can carry.
fn check_lines(drives: &[DriveSettings]) -> Result<(), Invalid> {
    let mut lines: Vec<(Endpoint, Vec<usize>)> = Vec::new();
    for (i, d) in drives.iter().enumerate() {
        let Some((endpoint, _)) = d.line() else { continue };
        match lines.iter_mut().find(|(e, _)| e.same_line(&endpoint)) {
            Some((_, members)) => members.push(i),
            None => lines.push((endpoint, vec![i])),
        }
    }
    let line_key = |i: usize| match drives[i].transport {
        Transport::Rtu { .. } => format!("drives[{i}].serial_port"),
        _ => format!("drives[{i}].address"),
    };
    let describe =
        |l: &SerialLine| format!("{} baud, parity {}, {} stop bit(s)", l.baud_rate, l.parity.name(), l.stop_bits);
    for (endpoint, members) in &lines {
        let first = &drives[members[0]];
        let Some((_, line)) = first.line() else { continue };
        for &i in &members[1..] {
            if let Some((_, other)) = drives[i].line()
                && other != line
            {
                return Err(KeyError::new(
                    line_key(i),
                    format!(
                        "drive {:?} is on {} with {}, but drive {:?} on the same line has {}: a line has one \
                         setting",
                        drives[i].name,
                        endpoint.name(),
                        describe(&other),
                        first.name,
                        describe(&line)
                    ),
                ));
            }
        }
        let each: Vec<(Vec<(usize, usize)>, Duration)> =
            members.iter().map(|&i| (drives[i].cycle_frames(), drives[i].poll)).collect();
        let load = line_load(&line, &each);
        if load > MAX_LINE_LOAD {
            let names: Vec<String> = members
                .iter()
                .zip(&each)
                .map(|(&i, one)| {
                    format!(
                        "{:?} (poll_ms {}: {:.0} %)",
                        drives[i].name,
                        drives[i].poll.as_millis(),
                        100.0 * line_load(&line, std::slice::from_ref(one))
                    )
                })
                .collect();
            return Err(KeyError::new(
                line_key(members[members.len() - 1]),
                format!(
                    "the line {} ({}) cannot carry drives {}: together they need {:.0} % of its time, at most {:.0} % \
                     is allowed; poll less often (poll_ms), raise baud_rate, or move drives to another line",
                    endpoint.name(),
                    describe(&line),
                    names.join(", "),
                    100.0 * load,
                    100.0 * MAX_LINE_LOAD
                ),
            ));
        }
    }
    Ok(())
}

/// The transport keys of a drive, validated: `(transport, address)`, where the address is the serial port for rtu.
fn validate_transport(d: &RawDrive, key: &dyn Fn(&str) -> String) -> Result<(Transport, String), Invalid> {
    let kind = d.transport.as_deref().unwrap_or("tcp");
    let serial_given = [
        ("serial_port", d.serial_port.is_some()),
        ("baud_rate", d.baud_rate.is_some()),
        ("parity", d.parity.is_some()),
        ("stop_bits", d.stop_bits.is_some()),
    ];
    let host_port = |address: &Option<String>| host_port(address.as_deref(), kind, key);
    let line = || serial_line(d, key);
    let rtu_unit = || rtu_unit(d.unit_id, key);
    match kind {
        "tcp" => {
            if let Some((k, _)) = serial_given.iter().find(|(_, given)| *given) {
                return Err(KeyError::new(
                    key(k),
                    "is for transport = \"rtu\" or \"rtu-over-tcp\"; this drive is on tcp".into(),
                ));
            }
            Ok((Transport::Tcp, host_port(&d.address)?))
        }
        "rtu" => {
            if d.address.is_some() {
                return Err(KeyError::new(
                    key("address"),
                    "is for tcp and rtu-over-tcp; an rtu drive is reached on serial_port".into(),
                ));
            }
            let Some(port) = d.serial_port.clone().filter(|p| !p.is_empty()) else {
                return Err(KeyError::new(
                    key("serial_port"),
                    "is required with transport = \"rtu\" (e.g. /dev/ttyUSB0)".into(),
                ));
            };
            let line = line()?;
            rtu_unit()?;
            Ok((Transport::Rtu { serial_port: port.clone(), line }, port))
        }
        "rtu-over-tcp" => {
            if d.serial_port.is_some() {
                return Err(KeyError::new(
                    key("serial_port"),
                    "is for transport = \"rtu\"; an rtu-over-tcp drive is reached at address (the gateway)".into(),
                ));
            }
            let address = host_port(&d.address)?;
            let line = line()?;
            rtu_unit()?;
            Ok((Transport::RtuOverTcp { line }, address))
        }
        other => {
            Err(KeyError::new(key("transport"), format!("{other:?}: expected \"tcp\", \"rtu\" or \"rtu-over-tcp\"")))
        }
    }
}

/// A drive's `address` as `host:port` (required with `kind`, a transport that reaches it over TCP).
fn host_port(address: Option<&str>, kind: &str, key: &dyn Fn(&str) -> String) -> Result<String, Invalid> {
    match address {
        None => Err(KeyError::new(key("address"), format!("is required with transport = {kind:?} (host:port)"))),
        Some(a) => match a.rsplit_once(':') {
            Some((host, port)) if !host.is_empty() && port.parse::<u16>().is_ok() => Ok(a.to_string()),
            _ => Err(KeyError::new(key("address"), format!("{a:?} is not host:port such as 127.0.0.1:5020"))),
        },
    }
}

/// A drive's serial line settings, defaults where not given.
fn serial_line(d: &RawDrive, key: &dyn Fn(&str) -> String) -> Result<SerialLine, Invalid> {
    let mut line = SerialLine::default();
    if let Some(b) = d.baud_rate {
        if b <= 0 {
            return Err(KeyError::new(key("baud_rate"), format!("must be positive, got {b}")));
        }
        line.baud_rate = u32::try_from(b)
            .map_err(|_| KeyError::new(key("baud_rate"), format!("must be at most {}, got {b}", u32::MAX)))?;
    }
    if let Some(p) = &d.parity {
        line.parity = Parity::parse(p)
            .ok_or_else(|| KeyError::new(key("parity"), format!("{p:?}: expected \"none\", \"even\" or \"odd\"")))?;
    }
    if let Some(s) = d.stop_bits {
        if !(1..=2).contains(&s) {
            return Err(KeyError::new(key("stop_bits"), format!("must be 1 or 2, got {s}")));
        }
        line.stop_bits = s as u8;
    }
    Ok(line)
}

/// A unit id an RTU line can address (0 is broadcast).
fn rtu_unit(unit_id: u8, key: &dyn Fn(&str) -> String) -> Result<(), Invalid> {
    if (1..=247).contains(&unit_id) {
        Ok(())
    } else {
        Err(KeyError::new(key("unit_id"), format!("must be 1 ..= 247 on an RTU line (0 is broadcast), got {unit_id}")))
    }
}

fn validate_drive(d: RawDrive, i: usize, base: Option<&Path>) -> Result<DriveSettings, Invalid> {
    let key = |k: &str| format!("drives[{i}].{k}");
    check_name(&d.name, &key)?;
    let (transport, address) = validate_transport(&d, &key)?;
    let stale_ms = validate_periods(&d, &key)?;
    let c = validate_control(&d.control, &key)?;
    let (estimator, model, feed_forward) = validate_estimator(d.estimator, &key, base)?;
    let ranges = validate_ranges(&d.limits, &key)?;
    let registers = apply_overrides(d.registers, &key("registers"))?;
    let condition = validate_condition(d.condition, &key("condition"), &model, |p| resolve(p, base))?;
    check_setpoint_fits(&registers.frequency_setpoint_hz, &c, &key)?;
    check_watchdog(d.comm_timeout_ms, d.watchdog_ms, &model, &key)?;
    let settings = DriveSettings {
        name: d.name,
        address,
        transport,
        unit_id: d.unit_id,
        poll: Duration::from_millis(d.poll_ms),
        timeout: Duration::from_millis(d.timeout_ms),
        stale_after: Duration::from_millis(stale_ms),
        watchdog_every: Duration::from_millis(d.watchdog_ms),
        realtime_priority: d.realtime_priority,
        mode: c.mode,
        target_omega_rad_s: c.target,
        fixed_hz: c.fixed_hz,
        limits: c.limits,
        gains: c.gains,
        feed_forward,
        estimator,
        model,
        ranges,
        registers,
        condition,
    };
    let target = c.target;
    if target > settings.max_target_omega_rad_s() * 1.5 {
        return Err(KeyError::new(
            key("control.target_omega_rad_s"),
            format!(
                "{target} rad/s is far beyond what max_hz allows (≈ {:.1} rad/s)",
                settings.max_target_omega_rad_s()
            ),
        ));
    }
    Ok(settings)
}

/// A drive's name: it names files and URLs.
fn check_name(name: &str, key: &dyn Fn(&str) -> String) -> Result<(), Invalid> {
    let name_ok =
        !name.is_empty() && name.len() <= 64 && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-');
    if !name_ok {
        return Err(KeyError::new(
            key("name"),
            format!("{name:?}: use 1 to 64 letters, digits, `_` or `-` (it names files and URLs)"),
        ));
    }
    Ok(())
}

/// A drive's periods (poll, timeout, watchdog, stale) and its thread's priority; the stale period in ms.
fn validate_periods(d: &RawDrive, key: &dyn Fn(&str) -> String) -> Result<u64, Invalid> {
    if !(1..=60_000).contains(&d.poll_ms) {
        return Err(KeyError::new(key("poll_ms"), format!("must be 1 ..= 60000, got {}", d.poll_ms)));
    }
    if !(1..=60_000).contains(&d.timeout_ms) {
        return Err(KeyError::new(key("timeout_ms"), format!("must be 1 ..= 60000, got {}", d.timeout_ms)));
    }
    if !(1..=60_000).contains(&d.watchdog_ms) {
        return Err(KeyError::new(key("watchdog_ms"), format!("must be 1 ..= 60000, got {}", d.watchdog_ms)));
    }
    if let Some(p) = d.realtime_priority
        && !(1..=99).contains(&p)
    {
        return Err(KeyError::new(
            key("realtime_priority"),
            format!("must be 1 ..= 99 (SCHED_FIFO priority), got {p}"),
        ));
    }
    let stale_ms = d.stale_ms.unwrap_or((5 * d.poll_ms).max(50));
    if stale_ms < d.poll_ms {
        return Err(KeyError::new(key("stale_ms"), format!("must be ≥ poll_ms ({}), got {stale_ms}", d.poll_ms)));
    }
    if stale_ms > MAX_STALE_MS {
        return Err(KeyError::new(key("stale_ms"), format!("must be ≤ {MAX_STALE_MS} (10 min), got {stale_ms}")));
    }
    Ok(stale_ms)
}

/// `[drives.control]`, validated (its setpoints' fit in the register is checked once the registers are known).
struct Control {
    mode: Mode,
    limits: Limits,
    gains: Gains,
    fixed_hz: f64,
    target: f64,
}

fn validate_control(c: &RawControl, key: &dyn Fn(&str) -> String) -> Result<Control, Invalid> {
    let min_hz = nonneg(&key("control.min_hz"), c.min_hz)?;
    let max_hz = positive(&key("control.max_hz"), c.max_hz)?;
    if min_hz > max_hz {
        return Err(KeyError::new(key("control.min_hz"), format!("{min_hz} is above control.max_hz = {max_hz}")));
    }
    let ramp = positive(&key("control.ramp_hz_per_s"), c.ramp_hz_per_s)?;
    let kp = nonneg(&key("control.kp"), c.kp)?;
    if kp > MAX_KP_HZ_PER_RAD_S {
        return Err(KeyError::new(
            key("control.kp"),
            format!("must be ≤ {MAX_KP_HZ_PER_RAD_S} Hz per rad/s, got {kp}"),
        ));
    }
    let ki = nonneg(&key("control.ki"), c.ki)?;
    if ki > MAX_KI_HZ_PER_RAD {
        return Err(KeyError::new(key("control.ki"), format!("must be ≤ {MAX_KI_HZ_PER_RAD} Hz per rad, got {ki}")));
    }
    let fixed_hz = finite(&key("control.fixed_hz"), c.fixed_hz)?;
    if c.mode == Mode::Manual && !(min_hz..=max_hz).contains(&fixed_hz) {
        return Err(KeyError::new(
            key("control.fixed_hz"),
            format!("{fixed_hz} is outside [min_hz, max_hz] = [{min_hz}, {max_hz}]"),
        ));
    }
    let target = nonneg(&key("control.target_omega_rad_s"), c.target_omega_rad_s)?;
    Ok(Control {
        mode: c.mode,
        limits: Limits { min_hz, max_hz, ramp_hz_per_s: ramp },
        gains: Gains { kp_hz_per_rad_s: kp, ki_hz_per_rad: ki },
        fixed_hz,
        target,
    })
}

/// `[drives.estimator]`: the estimator's settings, the model they come from, and the control's feed-forward.
fn validate_estimator(
    e: RawEstimator,
    key: &dyn Fn(&str) -> String,
    base: Option<&Path>,
) -> Result<(EstimatorSettings, PlantModel, FeedForward), Invalid> {
    let method = match e.method.as_deref() {
        None | Some("rls-sgd") => Method::RlsSgd,
        Some("kalman") => Method::Kalman,
        Some(other) => {
            return Err(KeyError::new(
                key("estimator.method"),
                format!("{other:?}: expected \"rls-sgd\" or \"kalman\""),
            ));
        }
    };
    let model = match e.model {
        None => PlantModel::reference(),
        Some(p) => {
            let path = resolve(&p, base);
            PlantModel::load(&path).map_err(|e| KeyError::new(key("estimator.model"), e.to_string()))?
        }
    };
    if model.motor.displacement_cm3.is_none() {
        return Err(KeyError::new(
            key("estimator.model"),
            "the model needs motor.displacement_cm3 (torque from pressures)".into(),
        ));
    }
    let mut estimator = EstimatorSettings::from_model(&model, "the model file")
        .map_err(|e| KeyError::new(key("estimator.model"), e.to_string()))?;
    estimator.method = method;
    let coefficients =
        Coefficients::from_model(&model).map_err(|e| KeyError::new(key("estimator.model"), e.to_string()))?;
    let feed_forward = FeedForward {
        pole_pairs: coefficients.pole_pairs,
        pump_m3_rad: coefficients.pump_m3_rad,
        motor_m3_rad: coefficients.motor_m3_rad,
        leakage_si: coefficients.leakage_si,
        viscous_nm_s_rad: coefficients.mechanics.viscous_nm_s_rad,
    };
    Ok((estimator, model, feed_forward))
}

/// `[drives.limits]`: the ranges and rates a sample must keep to be used.
fn validate_ranges(l: &RawLimits, key: &dyn Fn(&str) -> String) -> Result<ValidRanges, Invalid> {
    let ranges = ValidRanges {
        min_pressure_bar: finite(&key("limits.min_pressure_bar"), l.min_pressure_bar)?,
        max_pressure_bar: finite(&key("limits.max_pressure_bar"), l.max_pressure_bar)?,
        max_speed_rad_s: positive(&key("limits.max_speed_rad_s"), l.max_speed_rad_s)?,
        max_frequency_hz: positive(&key("limits.max_frequency_hz"), l.max_frequency_hz)?,
        rates: RateLimits {
            pressure_bar_per_s: positive(&key("limits.max_pressure_rate_bar_per_s"), l.max_pressure_rate_bar_per_s)?,
            speed_rad_per_s2: positive(&key("limits.max_speed_rate_rad_per_s2"), l.max_speed_rate_rad_per_s2)?,
            frequency_hz_per_s: positive(&key("limits.max_frequency_rate_hz_per_s"), l.max_frequency_rate_hz_per_s)?,
        },
    };
    if ranges.min_pressure_bar >= ranges.max_pressure_bar {
        return Err(KeyError::new(key("limits.min_pressure_bar"), "must be below limits.max_pressure_bar".into()));
    }
    Ok(ranges)
}

/// The control's frequencies fit the setpoint register.
fn check_setpoint_fits(setpoint: &RegisterSpec, c: &Control, key: &dyn Fn(&str) -> String) -> Result<(), Invalid> {
    let (min_hz, max_hz, fixed_hz) = (c.limits.min_hz, c.limits.max_hz, c.fixed_hz);
    for (k, hz) in [("control.max_hz", max_hz), ("control.fixed_hz", fixed_hz), ("control.min_hz", min_hz)] {
        if setpoint.encode(hz).is_err() {
            return Err(KeyError::new(
                key(k),
                format!(
                    "{hz} Hz does not fit the setpoint register ({:?}, {} Hz per step: at most {} Hz)",
                    setpoint.kind,
                    setpoint.scale,
                    register_capacity(setpoint)
                ),
            ));
        }
    }
    Ok(())
}

/// The watchdog is refreshed well within the drive's comm timeout (`comm_timeout_ms`, else the model's).
fn check_watchdog(
    comm_timeout_ms: Option<u64>,
    watchdog_ms: u64,
    model: &PlantModel,
    key: &dyn Fn(&str) -> String,
) -> Result<(), Invalid> {
    let comm_timeout_ms =
        comm_timeout_ms.unwrap_or_else(|| model.drive.as_ref().map_or(1000, |drive| drive.comm_timeout_ms));
    if !(1..=crate::plant::model::MAX_COMM_TIMEOUT_MS).contains(&comm_timeout_ms) {
        return Err(KeyError::new(
            key("comm_timeout_ms"),
            format!("must be 1 ..= {} (one hour), got {comm_timeout_ms}", crate::plant::model::MAX_COMM_TIMEOUT_MS),
        ));
    }
    if watchdog_ms.saturating_mul(3) > comm_timeout_ms {
        return Err(KeyError::new(
            key("watchdog_ms"),
            format!(
                "{watchdog_ms} ms is more than a third of the drive's comm timeout ({comm_timeout_ms} ms, \
                 comm_timeout_ms or the model's drive.comm_timeout_ms): the drive would trip"
            ),
        ));
    }
    Ok(())
}

/// `[drives.condition]` as written.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct RawCondition {
    enabled: bool,
    window_s: f64,
    every_s: f64,
    model: Option<String>,
    limits: condition::Limits,
    energy_price_per_kwh: Option<f64>,
}

impl Default for RawCondition {
    fn default() -> Self {
        RawCondition {
            enabled: false,
            window_s: 120.0,
            every_s: 300.0,
            model: None,
            limits: condition::Limits::new(),
            energy_price_per_kwh: None,
        }
    }
}

/// A drive's condition monitoring, validated.
#[derive(Debug, Clone)]
pub struct ConditionSettings {
    pub enabled: bool,
    pub window: Duration,
    pub every: Duration,
    /// The nominal model the checks compare against (the estimator's unless `model` says otherwise), its load
    /// set to "recorded": the service's data carry no load, so the load is unknown.
    pub model: PlantModel,
    pub limits: condition::Limits,
    /// The price of a kWh (any currency): the energy report then says what each effect costs a day and a year.
    pub energy_price_per_kwh: Option<f64>,
}

/// Validates `[drives.condition]`; `key` is its prefix (`drives[0].condition`), `estimator_model` the default model,
/// `resolve` finds a relative model path. Errors name the key.
fn validate_condition(
    raw: RawCondition,
    key: &str,
    estimator_model: &PlantModel,
    resolve: impl Fn(&str) -> PathBuf,
) -> Result<ConditionSettings, KeyError> {
    let k = |s: &str| format!("{key}.{s}");
    if !(raw.window_s.is_finite() && (5.0..=3600.0).contains(&raw.window_s)) {
        return Err(KeyError::new(k("window_s"), format!("must be 5 ..= 3600 s, got {}", raw.window_s)));
    }
    if !(raw.every_s.is_finite() && (1.0..=86_400.0).contains(&raw.every_s)) {
        return Err(KeyError::new(k("every_s"), format!("must be 1 ..= 86400 s, got {}", raw.every_s)));
    }
    let mut model = match raw.model {
        None => estimator_model.clone(),
        Some(p) => PlantModel::load(&resolve(&p)).map_err(|e| KeyError::new(k("model"), e.to_string()))?,
    };
    if model.motor.displacement_cm3.is_none() || model.hydraulics.is_none() || model.pump.is_none() {
        return Err(KeyError::new(
            k("model"),
            "the model needs [pump], [motor] displacement_cm3 and [hydraulics]".into(),
        ));
    }
    model.load = LoadSpec::Recorded;
    condition::validate_limits(&raw.limits, &k("limits"))?;
    if let Some(p) = raw.energy_price_per_kwh
        && !(p.is_finite() && p >= 0.0)
    {
        return Err(KeyError::new(k("energy_price_per_kwh"), format!("must be a finite price ≥ 0, got {p}")));
    }
    Ok(ConditionSettings {
        enabled: raw.enabled,
        window: Duration::from_secs_f64(raw.window_s),
        every: Duration::from_secs_f64(raw.every_s),
        model,
        limits: raw.limits,
        energy_price_per_kwh: raw.energy_price_per_kwh,
    })
}

fn resolve(p: &str, base: Option<&Path>) -> PathBuf {
    let path = PathBuf::from(p);
    if path.is_absolute() || path.exists() {
        return path;
    }
    match base.map(|b| b.join(&path)) {
        Some(alt) if alt.exists() => alt,
        _ => path,
    }
}

/// Applies `[drives.registers.<entry>]` overrides to the default map, checking entry names and tables.
fn apply_overrides(overrides: BTreeMap<String, RawRegister>, key: &str) -> Result<RegisterMap, Invalid> {
    let mut map = RegisterMap::default();
    let mut names: Vec<&str> = map.entries().iter().map(|(n, _)| *n).collect();
    names.push("drive_power_w");
    for (name, o) in overrides {
        let slot: &mut RegisterSpec = match name.as_str() {
            "inlet_pressure_bar" => &mut map.inlet_pressure_bar,
            "outlet_pressure_bar" => &mut map.outlet_pressure_bar,
            "shaft_speed_rpm" => &mut map.shaft_speed_rpm,
            "drive_frequency_hz" => &mut map.drive_frequency_hz,
            "status_word" => &mut map.status_word,
            "sample_counter" => &mut map.sample_counter,
            "frequency_setpoint_hz" => &mut map.frequency_setpoint_hz,
            "control_word" => &mut map.control_word,
            "watchdog" => &mut map.watchdog,
            // optional: named, it is read, from `sim`'s register unless the keys say otherwise
            "drive_power_w" => map.drive_power_w.get_or_insert(crate::modbus::map::DRIVE_POWER_W),
            _ => {
                return Err(KeyError::new(
                    format!("{key}.{name}"),
                    format!("is not a register entry; expected one of {}", names.join(", ")),
                ));
            }
        };
        let k = |f: &str| format!("{key}.{name}.{f}");
        if let Some(t) = o.table {
            slot.table = t;
        }
        if let Some(a) = o.address {
            slot.address = a;
        }
        if let Some(t) = o.kind {
            slot.kind = t;
        }
        if let Some(s) = o.scale {
            if !(s.is_finite() && s != 0.0) {
                return Err(KeyError::new(k("scale"), format!("must be finite and not 0, got {s}")));
            }
            slot.scale = s;
        }
        if let Some(off) = o.offset {
            slot.offset = finite(&k("offset"), off)?;
        }
        if let Some(w) = o.word_order {
            slot.word_order = w;
        }
    }
    for (name, spec) in map.entries().into_iter().chain(map.drive_power_w.map(|s| ("drive_power_w", s))) {
        let writable = matches!(name, "frequency_setpoint_hz" | "control_word" | "watchdog");
        if writable && spec.table != Table::Holding {
            return Err(KeyError::new(
                format!("{key}.{name}.table"),
                "must be \"holding\": the service writes it".into(),
            ));
        }
        if u32::from(spec.address) + u32::from(spec.kind.words()) > 65536 {
            return Err(KeyError::new(format!("{key}.{name}.address"), "runs past register 65535".into()));
        }
    }
    for table in [Table::Input, Table::Holding] {
        if let Some((_, count)) = map.span(table)
            && count > 125
        {
            return Err(KeyError::new(
                key.to_string(),
                format!("the {table:?} registers span {count} words: one read takes ≤ 125"),
            ));
        }
    }
    Ok(map)
}

#[cfg(test)]
mod tests {
    use super::*;

    const MINIMAL: &str = r#"
[[drives]]
name = "pump1"
address = "127.0.0.1:5020"
"#;

    fn err(text: &str) -> String {
        match parse(text, "t.toml", None) {
            Ok(_) => panic!("accepted: {text}"),
            Err(e) => e.to_string(),
        }
    }

    #[test]
    fn minimal_config_gets_safe_defaults() {
        let s = parse(MINIMAL, "t.toml", None).expect("valid");
        assert_eq!(s.http.bind.to_string(), "127.0.0.1:8080");
        assert_eq!(s.http.token, None, "no token: write routes off");
        let d = &s.drives[0];
        assert_eq!(d.mode, Mode::Monitor);
        assert_eq!(d.poll, Duration::from_millis(10));
        assert_eq!(d.registers, RegisterMap::default());
    }

    #[test]
    fn errors_name_the_key() {
        assert!(err("[http]\nbnd = \"x\"\n").contains("bnd"));
        let e = err(&format!("{MINIMAL}[drives.control]\nmin_hz = 30.0\nmax_hz = 20.0\n"));
        assert!(e.contains("drives[0].control.min_hz"), "{e}");
        let e = err(&format!("{MINIMAL}realtime_priority = 0\n"));
        assert!(e.contains("drives[0].realtime_priority") && e.contains("1 ..= 99"), "{e}");
        let e = err(&format!("{MINIMAL}stale_ms = 600001\n"));
        assert!(e.contains("drives[0].stale_ms") && e.contains("600000"), "{e}");
        let e = err(&format!("{MINIMAL}comm_timeout_ms = 3600001\n"));
        assert!(e.contains("drives[0].comm_timeout_ms") && e.contains("one hour"), "{e}");
        let e = err(&format!("{MINIMAL}poll_ms = \"fast\"\n"));
        assert!(e.contains("poll_ms"), "{e}");
        let e = err(&format!("{MINIMAL}[drives.registers.inlet_pressure]\naddress = 3\n"));
        assert!(e.contains("drives[0].registers.inlet_pressure"), "{e}");
        let e = err(&format!("{MINIMAL}[drives.registers.watchdog]\ntable = \"input\"\n"));
        assert!(e.contains("watchdog.table"), "{e}");
        let e = err(&format!("{MINIMAL}[drives.control]\nmode = \"turbo\"\n"));
        assert!(e.contains("turbo"), "{e}");
    }

    #[test]
    fn register_overrides_merge_over_the_default() {
        let text = format!(
            "{MINIMAL}[drives.registers.inlet_pressure_bar]\naddress = 10\ntype = \"f32\"\nscale = 1.0\nword_order = \"cdab\"\n"
        );
        let s = parse(&text, "t.toml", None).expect("valid");
        let m = s.drives[0].registers;
        assert_eq!(m.inlet_pressure_bar.address, 10);
        assert_eq!(m.inlet_pressure_bar.kind, ValueType::F32);
        assert_eq!(m.inlet_pressure_bar.word_order, WordOrder::Cdab);
        assert_eq!(m.inlet_pressure_bar.table, Table::Input);
        assert_eq!(m.span(Table::Input), Some((1, 11)));
        assert_eq!(m.drive_power_w, None, "the drive's power is not read unless named");
    }

    #[test]
    fn the_drive_power_register_is_read_once_named() {
        let s = parse(&format!("{MINIMAL}[drives.registers.drive_power_w]\n"), "t.toml", None).expect("valid");
        assert_eq!(s.drives[0].registers.drive_power_w, Some(crate::modbus::map::DRIVE_POWER_W));
        let text = format!("{MINIMAL}[drives.registers.drive_power_w]\naddress = 40\ntype = \"u16\"\nscale = 10.0\n");
        let p = parse(&text, "t.toml", None).expect("valid").drives[0].registers.drive_power_w.expect("read");
        assert_eq!((p.table, p.address, p.kind, p.scale), (Table::Input, 40, ValueType::U16, 10.0));
        let e = err(&format!("{MINIMAL}[drives.registers.drive_power_w]\naddress = 65535\ntype = \"f32\"\n"));
        assert!(e.contains("drive_power_w.address"), "{e}");
        let e = err(&format!("{MINIMAL}[drives.registers.drive_power]\n"));
        assert!(e.contains("drive_power_w"), "the message names the entry: {e}");
    }

    fn rtu(name: &str, unit: u8, extra: &str) -> String {
        format!(
            "[[drives]]\nname = \"{name}\"\ntransport = \"rtu\"\nserial_port = \"/dev/ttyUSB0\"\nunit_id = {unit}\n{extra}\n"
        )
    }

    #[test]
    fn rtu_keys_are_validated() {
        let s = parse(&rtu("vfd3", 3, "baud_rate = 19200\nparity = \"none\"\nstop_bits = 2\npoll_ms = 50"), "t", None)
            .expect("valid");
        let d = &s.drives[0];
        assert_eq!(d.address, "/dev/ttyUSB0");
        let line = SerialLine { baud_rate: 19200, parity: Parity::None, stop_bits: 2 };
        assert_eq!(d.transport, Transport::Rtu { serial_port: "/dev/ttyUSB0".into(), line });
        let e = err("[[drives]]\nname = \"v\"\ntransport = \"rtu\"\n");
        assert!(e.contains("drives[0].serial_port") && e.contains("required"), "{e}");
        let e = err(&rtu("v", 1, "parity = \"mark\""));
        assert!(e.contains("drives[0].parity") && e.contains("mark"), "{e}");
        let e = err(&rtu("v", 1, "baud_rate = -9600"));
        assert!(e.contains("drives[0].baud_rate") && e.contains("positive"), "{e}");
        let e = err(&rtu("v", 1, "baud_rate = 0"));
        assert!(e.contains("drives[0].baud_rate"), "{e}");
        let e = err(&rtu("v", 1, "stop_bits = 3"));
        assert!(e.contains("drives[0].stop_bits") && e.contains("1 or 2"), "{e}");
        let e = err(&rtu("v", 0, "poll_ms = 100"));
        assert!(e.contains("drives[0].unit_id"), "{e}");
        let e = err(&format!("{MINIMAL}parity = \"even\"\n"));
        assert!(e.contains("drives[0].parity") && e.contains("tcp"), "{e}");
        let e = err("[[drives]]\nname = \"v\"\ntransport = \"rtu-over-tcp\"\n");
        assert!(e.contains("drives[0].address") && e.contains("required"), "{e}");
        let e = err(&format!("{MINIMAL}transport = \"udp\"\n"));
        assert!(e.contains("drives[0].transport") && e.contains("udp"), "{e}");
    }

    /// One drive under two spellings is one device: two writing loops at `127.0.0.1:P` and `localhost:P` (or
    /// `127.1:P`, `[::ffff:127.0.0.1]:P`) are refused as they would be at one spelling; a monitoring one may watch.
    #[test]
    fn two_writers_on_one_device_are_refused_whatever_its_spelling() {
        let drive = |name: &str, address: &str, mode: &str| {
            format!(
                "[[drives]]\nname = \"{name}\"\naddress = \"{address}\"\n[drives.control]\nmode = \"{mode}\"\n\
                 fixed_hz = 10.0\n"
            )
        };
        for other in ["localhost:5020", "127.1:5020", "[::ffff:127.0.0.1]:5020", "127.0.0.1:5020"] {
            let text = format!("{}{}", drive("a", "127.0.0.1:5020", "manual"), drive("b", other, "manual"));
            let e = err(&text);
            assert!(e.contains("drives[1].address") && e.contains("already written"), "{other}: {e}");
            let watch = format!("{}{}", drive("a", "127.0.0.1:5020", "manual"), drive("b", other, "monitor"));
            parse(&watch, "t", None).expect("one may watch");
        }
        let text = format!("{}{}", drive("a", "127.0.0.1:5020", "manual"), drive("b", "127.0.0.1:5021", "manual"));
        parse(&text, "t", None).expect("another port is another device");
    }

    #[test]
    fn a_line_has_one_setting_and_a_capacity() {
        // two monitoring drives at 50 ms on 19200 baud, even parity: 37 % each, 73 % together: fits
        let two = format!("{}{}", rtu("a", 1, "poll_ms = 50"), rtu("b", 2, "poll_ms = 50"));
        let s = parse(&two, "t", None).expect("fits the line");
        assert_eq!(s.drives.len(), 2);
        // a third one is too many, and the error names every drive on the line
        let three = format!("{two}{}", rtu("c", 3, "poll_ms = 50"));
        let e = err(&three);
        assert!(e.contains("drives[2].serial_port") && e.contains("cannot carry"), "{e}");
        for name in ["\"a\"", "\"b\"", "\"c\""] {
            assert!(e.contains(name), "{e}");
        }
        assert!(e.contains("110 %"), "{e}");
        // writing adds the write exchange: one speed drive at 50 ms takes 37 % + 34 %
        let speed = rtu("a", 1, "poll_ms = 50\n[drives.control]\nmode = \"speed\"\ntarget_omega_rad_s = 10.0");
        parse(&speed, "t", None).expect("one writing drive fits");
        let e = err(&format!("{speed}{}", rtu("b", 2, "poll_ms = 50")));
        assert!(e.contains("cannot carry"), "{e}");
        // one line, two settings
        let e = err(&format!("{}{}", rtu("a", 1, "poll_ms = 50"), rtu("b", 2, "poll_ms = 50\nbaud_rate = 9600")));
        assert!(e.contains("drives[1].serial_port") && e.contains("one setting") && e.contains("9600"), "{e}");
        // two writing loops on one device of a line
        let speed2 = speed.replace("name = \"a\"", "name = \"b\"").replace("poll_ms = 50", "poll_ms = 500");
        let e = err(&format!("{}{speed2}", speed.replace("poll_ms = 50", "poll_ms = 500")));
        assert!(e.contains("drives[1].serial_port") && e.contains("already written"), "{e}");
        // other ports are other lines
        let other = rtu("c", 3, "poll_ms = 50").replace("ttyUSB0", "ttyUSB1");
        parse(&format!("{two}{other}"), "t", None).expect("a second line");
    }

    #[test]
    fn a_drives_condition_is_carried_and_its_errors_name_the_drives_key() {
        let base = "[[drives]]\nname = \"pump1\"\naddress = \"127.0.0.1:5020\"\n[drives.condition]\n";
        let parse = |extra: &str| parse(&format!("{base}{extra}"), "t.toml", None);
        let s = parse("enabled = true\nevery_s = 60\n").expect("valid");
        assert!(s.drives[0].condition.enabled);
        assert_eq!(s.drives[0].condition.every, Duration::from_secs(60));
        let e = parse("window_s = 0.5\n").expect_err("too short");
        assert!(e.is_bad_input() && e.to_string().contains("drives[0].condition.window_s"), "{e}");
        let e = parse("enable = true\n").expect_err("unknown key");
        assert!(e.is_bad_input() && e.to_string().contains("enable"), "{e}");
        let e = parse("[drives.condition.limits]\ndead_time = { seconds = 1.0 }\n").expect_err("unknown parameter");
        assert!(e.to_string().contains("drives[0].condition.limits.dead_time.seconds"), "{e}");
    }

    /// `[drives.condition]` on its own.
    mod drives_condition {
        use super::*;

        fn raw(text: &str) -> RawCondition {
            toml::from_str(text).expect("parses")
        }

        fn check(text: &str) -> Result<ConditionSettings, KeyError> {
            validate_condition(raw(text), "drives[0].condition", &PlantModel::reference(), |p: &str| PathBuf::from(p))
        }

        #[test]
        fn defaults_are_off_120_s_every_300_s_on_the_estimators_model_with_the_load_unknown() {
            let s = check("").expect("valid");
            assert!(!s.enabled);
            assert_eq!((s.window, s.every), (Duration::from_secs(120), Duration::from_secs(300)));
            assert_eq!(s.model.load, LoadSpec::Recorded);
            assert_eq!(s.model.motor, PlantModel::reference().motor);
            assert!(s.limits.is_empty());
        }

        #[test]
        fn errors_name_the_key() {
            let key = |text: &str| check(text).expect_err(text).key;
            assert_eq!(key("window_s = 1.0"), "drives[0].condition.window_s");
            assert_eq!(key("every_s = -5.0"), "drives[0].condition.every_s");
            assert_eq!(key("model = \"/no/such/plant.toml\""), "drives[0].condition.model");
            assert_eq!(key("[limits]\nleak = { l_min_per_bar = 0.02 }"), "drives[0].condition.limits.leak");
            assert_eq!(
                key("[limits]\ninternal_leakage = { l_per_bar = 0.02 }"),
                "drives[0].condition.limits.internal_leakage.l_per_bar"
            );
            assert_eq!(key("energy_price_per_kwh = -0.1"), "drives[0].condition.energy_price_per_kwh");
            let unknown = toml::from_str::<RawCondition>("enable = true").expect_err("unknown key").to_string();
            assert!(unknown.contains("enable"), "{unknown}");
        }

        #[test]
        fn the_contracts_example_parses() {
            let s = check(
                "enabled = true\nwindow_s = 120\nevery_s = 60\n[limits]\ninternal_leakage = { l_min_per_bar = 0.02 }\n\
                 dead_time = { ms = 50.0 }\nentrained_air = { bulk_modulus_bar = 8000.0 }\n",
            )
            .expect("valid");
            assert!(s.enabled);
            assert_eq!(s.every, Duration::from_secs(60));
            assert_eq!(s.limits["entrained_air"]["bulk_modulus_bar"], 8000.0);
        }
    }
}

//! The service config (`config/hydrolens.toml`): parsed raw and strictly (unknown keys are errors), then validated
//! into typed settings that cannot be invalid. Every error names its key.
//!
//! In the service's layout (see [`super`]) it uses [`super::freshness`] (the plausible ranges and rates), nothing
//! above it: the condition checks, and the outlets above the service (the MQTT publisher, HTTP), take their settings
//! from here. Its rooms: `[http]` (`http_settings`), `[recording]` (`recording_settings`), `[mqtt]`
//! (`mqtt_settings`), one drive's entry (`drive`), RTU lines and gateways (`line`), the condition checks
//! (`condition_monitoring`).

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
use crate::modbus::line::{SerialLine, read_frames, write_frames};
use crate::modbus::map::{RegisterMap, RegisterSpec, Table, ValueType, WordOrder};
use crate::plant::dynamics::Coefficients;
use crate::plant::{LoadSpec, PlantModel};

mod condition_monitoring;
mod drive;
mod http_settings;
mod line;
mod mqtt_settings;
mod recording_settings;

pub use condition_monitoring::ConditionSettings;
use condition_monitoring::RawCondition;
use drive::validate_drive;
pub use http_settings::HttpSettings;
use http_settings::{RawHttp, validate_http};
use line::check_lines;
pub use mqtt_settings::{INTERVAL_MS, MqttSettings, QUEUE_MESSAGES, RawMqtt, validate as validate_mqtt};
pub use recording_settings::{MIN_FILE_MB, MIN_ROTATE_HOURS, RecordingSettings};
use recording_settings::{RawRecording, validate_recording};

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
    /// MQTT publishing (src/mqtt.rs); absent: off.
    mqtt: Option<mqtt_settings::RawMqtt>,
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
    pub mqtt: Option<MqttSettings>,
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
    let raw: RawConfig = toml::from_str(text).map_err(|e| ConfigError::Syntax {
        path: origin.to_string(),
        message: without_secrets(e.to_string().trim_end()),
    })?;
    validate(raw, base).map_err(|KeyError { key, message }| ConfigError::Invalid {
        path: origin.to_string(),
        key,
        message,
    })
}

/// A TOML error's text with the value cut from any quoted source line whose key names a secret (`password`,
/// `token`, `secret`, any case or spelling around them) or is unknown (a misspelt key: `pasword`, `tokn`; its value
/// helps nobody mend the name), and, where a secret's line is quoted, from serde's own words on the value (`invalid
/// type: integer `12345678``): the error quotes the line it is on, and a typo there put the MQTT password or the HTTP
/// token in the journal.
fn without_secrets(rendered: &str) -> String {
    let secret = |key: &str| {
        let key = key.to_ascii_lowercase();
        ["pass", "token", "secret", "pwd"].iter().any(|k| key.contains(k))
    };
    let unknown_key = rendered.contains("unknown field");
    // a quoted source line: `23 | password = "…`, as (gutter, key)
    let quoted = |line: &str| {
        let (gutter, source) = line.split_once(" | ")?;
        let numbered = !gutter.trim().is_empty() && gutter.trim().bytes().all(|b| b.is_ascii_digit());
        let (key, _) = source.split_once('=')?;
        numbered.then(|| (gutter.to_string(), key.to_string()))
    };
    let secret_quoted = rendered.lines().filter_map(quoted).any(|(_, key)| secret(&key));
    let lines = rendered.lines().map(|line| match quoted(line) {
        Some((gutter, key)) if secret(&key) || unknown_key => format!("{gutter} | {key}= … (not repeated)"),
        None if secret_quoted && (line.contains("invalid type") || line.contains("invalid value")) => {
            // every `…` span of serde's message: the value given (and what was expected, which is no secret)
            line.split('`')
                .enumerate()
                .map(|(k, part)| if k % 2 == 1 { "…" } else { part })
                .collect::<Vec<_>>()
                .join("`")
        }
        _ => line.to_string(),
    });
    lines.collect::<Vec<_>>().join("\n")
}

type Invalid = KeyError;

fn finite(key: &str, v: f64) -> Result<f64, Invalid> {
    if v.is_finite() {
        Ok(v)
    } else {
        Err(KeyError::new(key.into(), format!("must be a finite number, got {}", crate::units::shown(v))))
    }
}

fn nonneg(key: &str, v: f64) -> Result<f64, Invalid> {
    if v.is_finite() && v >= 0.0 {
        Ok(v)
    } else {
        Err(KeyError::new(key.into(), format!("must be finite and ≥ 0, got {}", crate::units::shown(v))))
    }
}

fn positive(key: &str, v: f64) -> Result<f64, Invalid> {
    if v.is_finite() && v > 0.0 {
        Ok(v)
    } else {
        Err(KeyError::new(key.into(), format!("must be finite and > 0, got {}", crate::units::shown(v))))
    }
}

/// The steepest setpoint ramp accepted (Hz/s): 1e300 was taken, which is no ramp at all.
pub const MAX_RAMP_HZ_PER_S: f64 = 1000.0;

/// The largest PI gains accepted: 50 and 170 times the defaults, far beyond any tuning that regulates.
pub const MAX_KP_HZ_PER_RAD_S: f64 = 10.0;
pub const MAX_KI_HZ_PER_RAD: f64 = 100.0;

/// The values a register can hold, lowest and highest, in engineering units (for error messages).
fn register_range(spec: &RegisterSpec) -> (f64, f64) {
    let (raw_lo, raw_hi) = spec.kind.raw_range();
    // a negative scale turns the range around
    let ends = [raw_lo * spec.scale, raw_hi * spec.scale].map(|v| (v * 1e6).round() / 1e6 + spec.offset);
    (ends[0].min(ends[1]), ends[0].max(ends[1]))
}

fn validate(raw: RawConfig, base: Option<&Path>) -> Result<Settings, Invalid> {
    let http = validate_http(raw.http)?;
    let recording = validate_recording(raw.recording)?;
    let drives = validate_drives(raw.drives, base)?;
    check_lines(&drives)?;
    let mqtt = raw.mqtt.map(|m| mqtt_settings::validate(m, |p| resolve(p, base))).transpose()?;
    Ok(Settings { http, recording, drives, mqtt })
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

#[cfg(test)]
mod tests;

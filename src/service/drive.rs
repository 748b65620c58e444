//! One drive's poll loop: batched read → decode and validate → estimator → control law → setpoint and watchdog
//! write, every `poll_ms`. Publishes a snapshot each cycle, feeds the history ring and the recording.
//!
//! Data are fresh when the sample counter has moved forward (and has not run backwards lately, see
//! [`super::freshness`]), every value decodes in range and changed no faster than the plausible rates, the reply
//! came within `stale_ms` and the previous new sample no more than `stale_ms` before: the one definition readiness
//! also uses (only fresh samples mark the drive fresh). Only fresh data reach the estimator, and only fresh data
//! lead to a write: on stale data nothing is written, so the drive's own watchdog takes over. A tripped drive is commanded towards 0 Hz and only re-armed by a reset request from the API.
//!
//! Each loop runs on an OS thread of its own with a current-thread runtime, paced by a [`Ticker`]: the HTTP side,
//! other drives and the recorder never share its thread, so they cannot delay its ticks.

use std::sync::Arc;

use tokio::time::Instant;
use tokio_util::sync::CancellationToken;

use super::config::{DriveSettings, ValidRanges};
use super::freshness::{CounterCheck, CounterVerdict, implausible_jump};
use super::metrics::{DriveLabel, ErrorLabels, Metrics, PASCALS_PER_BAR};
use super::recorder::Recorder;
use super::state::{DriveSnapshot, DriveState, DriveStatus, Link, Point};
use super::timing::{LoopTiming, ThreadSetup, Ticker, TimingStats, use_realtime_priority};
use crate::control::{Inputs, SpeedLaw};
use crate::estimator::{Estimate, Estimator, Measurement};
use crate::modbus::bus::Connection;
use crate::modbus::client::ClientError;
use crate::modbus::map::{RegisterMap, RegisterSpec, Table, control, status};
use crate::units::rpm_to_rad_s;

/// A decoded, validated sample.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sample {
    pub p_in_bar: f64,
    pub p_out_bar: f64,
    pub omega_rad_s: f64,
    pub f_drive_hz: f64,
    pub status_word: u16,
    pub counter: u64,
}

/// Why a read's values were refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Rejected {
    #[error("{entry}: {message}")]
    Decode { entry: &'static str, message: String },
    #[error("{entry} = {value} is outside the valid range")]
    Range { entry: &'static str, value: f64 },
    #[error("{entry} jumped from {from} to {to} ({rate:.0}/s, limit {max_rate}/s)")]
    Jump { entry: &'static str, from: f64, to: f64, rate: f64, max_rate: f64 },
}

/// The measured entries of the map, by name.
fn measured(map: &RegisterMap) -> [(&'static str, RegisterSpec); 6] {
    [
        ("inlet_pressure_bar", map.inlet_pressure_bar),
        ("outlet_pressure_bar", map.outlet_pressure_bar),
        ("shaft_speed_rpm", map.shaft_speed_rpm),
        ("drive_frequency_hz", map.drive_frequency_hz),
        ("status_word", map.status_word),
        ("sample_counter", map.sample_counter),
    ]
}

/// The reads of one cycle: per table, the smallest block holding every measured entry of that table.
pub fn read_plan(map: &RegisterMap) -> Vec<(Table, u16, u16)> {
    let mut plan = Vec::new();
    for table in [Table::Input, Table::Holding] {
        let (mut lo, mut hi) = (u32::MAX, 0u32);
        for (_, s) in measured(map).iter().filter(|(_, s)| s.table == table) {
            lo = lo.min(u32::from(s.address));
            hi = hi.max(u32::from(s.address) + u32::from(s.kind.words()));
        }
        if lo < hi {
            plan.push((table, lo as u16, (hi - lo) as u16));
        }
    }
    plan
}

/// Decodes and validates a sample from the blocks of [`read_plan`]. Pure.
pub fn decode_sample(
    map: &RegisterMap,
    blocks: &[(Table, u16, Vec<u16>)],
    ranges: &ValidRanges,
) -> Result<Sample, Rejected> {
    let mut v = [0.0; 6];
    for (i, (entry, spec)) in measured(map).into_iter().enumerate() {
        let Some((_, start, words)) = blocks.iter().find(|(t, _, _)| *t == spec.table) else {
            return Err(Rejected::Decode { entry, message: "its table was not read".into() });
        };
        let x = RegisterMap::decode_from(&spec, *start, words)
            .map_err(|e| Rejected::Decode { entry, message: e.to_string() })?;
        if !x.is_finite() {
            return Err(Rejected::Range { entry, value: x });
        }
        v[i] = x;
    }
    let [p_in, p_out, rpm, f, word, counter] = v;
    let pressure_ok = |p: f64| (ranges.min_pressure_bar..=ranges.max_pressure_bar).contains(&p);
    if !pressure_ok(p_in) {
        return Err(Rejected::Range { entry: "inlet_pressure_bar", value: p_in });
    }
    if !pressure_ok(p_out) {
        return Err(Rejected::Range { entry: "outlet_pressure_bar", value: p_out });
    }
    let omega = rpm_to_rad_s(rpm);
    if omega.abs() > ranges.max_speed_rad_s {
        return Err(Rejected::Range { entry: "shaft_speed_rpm", value: rpm });
    }
    if !(-0.5..=ranges.max_frequency_hz).contains(&f) {
        return Err(Rejected::Range { entry: "drive_frequency_hz", value: f });
    }
    if !(0.0..=65535.0).contains(&word) || word.fract() != 0.0 {
        return Err(Rejected::Range { entry: "status_word", value: word });
    }
    if !(0.0..=u32::MAX as f64).contains(&counter) {
        return Err(Rejected::Range { entry: "sample_counter", value: counter });
    }
    Ok(Sample {
        p_in_bar: p_in,
        p_out_bar: p_out,
        omega_rad_s: omega,
        f_drive_hz: f,
        status_word: word as u16,
        counter: counter as u64,
    })
}

/// The writes for a setpoint, control word and watchdog value: encoded, sorted, adjacent registers merged so that
/// the default map takes one request. Pure.
pub fn plan_writes(
    map: &RegisterMap,
    setpoint_hz: f64,
    control_word: u16,
    watchdog: u16,
) -> Result<Vec<(u16, Vec<u16>)>, String> {
    let mut parts = vec![
        (map.frequency_setpoint_hz.address, map.frequency_setpoint_hz.encode(setpoint_hz).map_err(|e| e.to_string())?),
        (map.control_word.address, map.control_word.encode(f64::from(control_word)).map_err(|e| e.to_string())?),
        (map.watchdog.address, map.watchdog.encode(f64::from(watchdog)).map_err(|e| e.to_string())?),
    ];
    parts.sort_by_key(|(a, _)| *a);
    let mut out: Vec<(u16, Vec<u16>)> = Vec::with_capacity(3);
    for (addr, words) in parts {
        match out.last_mut() {
            Some((start, block)) if usize::from(*start) + block.len() == usize::from(addr) => block.extend(words),
            _ => out.push((addr, words)),
        }
    }
    Ok(out)
}

/// The write requests of a cycle as (start, words): the blocks [`plan_writes`] makes, without the values.
pub fn write_layout(map: &RegisterMap) -> Vec<(u16, usize)> {
    let mut parts = [
        (map.frequency_setpoint_hz.address, usize::from(map.frequency_setpoint_hz.kind.words())),
        (map.control_word.address, usize::from(map.control_word.kind.words())),
        (map.watchdog.address, usize::from(map.watchdog.kind.words())),
    ];
    parts.sort_by_key(|(a, _)| *a);
    let mut out: Vec<(u16, usize)> = Vec::with_capacity(3);
    for (addr, n) in parts {
        match out.last_mut() {
            Some((start, len)) if usize::from(*start) + *len == usize::from(addr) => *len += n,
            _ => out.push((addr, n)),
        }
    }
    out
}

/// The state bits of a status word.
pub fn drive_status(word: u16) -> DriveStatus {
    DriveStatus {
        word,
        ready: word & status::READY != 0,
        running: word & status::RUNNING != 0,
        fault: word & status::FAULT != 0,
        comm_loss_trip: word & status::COMM_LOSS_TRIP != 0,
    }
}

/// Everything one drive's loop owns.
pub struct DriveLoop {
    settings: DriveSettings,
    client: Connection,
    estimator: Box<dyn Estimator>,
    law: SpeedLaw,
    state: Arc<DriveState>,
    metrics: Metrics,
    label: DriveLabel,
    recorder: Option<Recorder>,
    started: Instant,
    timing: LoopTiming,
    plan: Vec<(Table, u16, u16)>,
    counter: CounterCheck,
    /// The last sample that passed every check but timeliness, and when it was read: the reference of the
    /// rate-of-change check and of the gap between new samples.
    last_valid: Option<(Instant, Sample)>,
    last_fresh_at: Option<Instant>,
    /// When the watchdog value last changed: it must change at least every `watchdog_ms`.
    last_watchdog_at: Option<Instant>,
    last_written: Vec<(u16, Vec<u16>)>,
    watchdog: u16,
    /// 0: none; 1: write the fault-reset bit next; 2: written, drop it next.
    reset_phase: u8,
    reconnects_seen: u64,
    link: Link,
    status: DriveStatus,
    sample: Option<Point>,
    estimate: Option<Estimate>,
    /// The window's timing statistics, refreshed every [`STATS_EVERY`].
    stats: TimingStats,
    stats_at: Option<Instant>,
    /// Points not yet in the history ring (it was being read when they came).
    pending_history: Vec<Point>,
    /// Where in its period this loop ticks, see [`DriveLoop::stagger`].
    phase: std::time::Duration,
}

/// The longest span the loops' first ticks are spread over (see [`DriveLoop::stagger`]): a cycle takes well under
/// 100 µs of CPU, so 50 loops 200 µs apart no longer meet.
const STAGGER_SPAN: std::time::Duration = std::time::Duration::from_millis(10);

/// How often the jitter percentiles are recomputed (each is a pass over the 1000-period window).
const STATS_EVERY: std::time::Duration = std::time::Duration::from_millis(50);

impl DriveLoop {
    /// `client` is the drive's connection: its own (Modbus TCP) or its turn on a shared RTU line
    /// ([`crate::modbus::bus::Bus::handle`]).
    pub fn new(
        settings: DriveSettings,
        client: Connection,
        estimator: Box<dyn Estimator>,
        state: Arc<DriveState>,
        metrics: Metrics,
        recorder: Option<Recorder>,
        started: Instant,
    ) -> DriveLoop {
        let label = DriveLabel { drive: settings.name.clone() };
        // every series exists from the start, at 0, so that dashboards and alerts see it before the first event
        for family in [&metrics.polls, &metrics.reconnects, &metrics.rejected_samples, &metrics.stale_samples] {
            let _ = family.get_or_create(&label);
        }
        let _ = metrics.writes.get_or_create(&label);
        let _ = metrics.overruns.get_or_create(&label);
        for kind in ["connect", "timeout", "transport", "protocol", "exception", "encode", "counter"] {
            let _ = metrics.errors.get_or_create(&ErrorLabels { drive: label.drive.clone(), kind: kind.into() });
        }
        let mut law = SpeedLaw::new(settings.mode, settings.limits, settings.gains, settings.feed_forward);
        law.target_omega_rad_s = settings.target_omega_rad_s;
        law.fixed_hz = settings.fixed_hz;
        let counter = CounterCheck::new(16 * u32::from(settings.registers.sample_counter.kind.words()));
        DriveLoop {
            label,
            plan: read_plan(&settings.registers),
            timing: LoopTiming::new(settings.poll),
            client,
            estimator,
            law,
            state,
            metrics,
            recorder,
            started,
            settings,
            counter,
            last_valid: None,
            last_fresh_at: None,
            last_watchdog_at: None,
            last_written: Vec::new(),
            watchdog: 0,
            reset_phase: 0,
            reconnects_seen: 0,
            link: Link::default(),
            status: DriveStatus::default(),
            sample: None,
            estimate: None,
            stats: TimingStats::default(),
            stats_at: None,
            pending_history: Vec::with_capacity(16),
            phase: std::time::Duration::ZERO,
        }
    }

    /// Spreads the loops' ticks: loop `index` of `count` ticks `index/count` of its period (at most of
    /// [`STAGGER_SPAN`]) after the first. Loops started together would otherwise all wake at the same instant, with
    /// their simulators or PLC replies, and queue for the cores: the last of 50 waited milliseconds. The cap keeps
    /// the first poll of slow loops from being put off by up to a period.
    pub fn stagger(&mut self, index: usize, count: usize) {
        self.phase = self.settings.poll.min(STAGGER_SPAN).mul_f64(index as f64 / count.max(1) as f64);
    }

    /// The drive's name.
    pub fn name(&self) -> &str {
        &self.settings.name
    }

    /// Polls until `shutdown` on the calling thread, which it takes over: the ticker sleeps it between cycles and
    /// `rt` (a current-thread runtime of its own) runs each cycle's I/O. Then closes the connection and the
    /// recording.
    pub fn run_blocking(mut self, rt: &tokio::runtime::Runtime, shutdown: &CancellationToken) {
        tracing::info!(drive = %self.settings.name, address = %self.settings.address, mode = ?self.settings.mode,
            poll_ms = self.settings.poll.as_secs_f64() * 1e3, "poll loop started");
        let granted = self.settings.realtime_priority.filter(|&p| use_realtime_priority(p, &self.settings.name));
        let (mut ticker, timer_slack_ns) = Ticker::new(self.settings.poll, self.phase);
        self.timing.thread = ThreadSetup { realtime_priority: granted, timer_slack_ns };
        while ticker.wait(shutdown) {
            let stopped = rt.block_on(async {
                tokio::select! {
                    biased;
                    () = shutdown.cancelled() => true,
                    () = self.cycle() => false,
                }
            });
            if stopped {
                break;
            }
        }
        rt.block_on(self.client.close());
        if let Some(rec) = self.recorder.take() {
            rec.finish();
        }
        tracing::info!(drive = %self.settings.name, "poll loop stopped");
    }

    fn error(&mut self, e: &ClientError) {
        if matches!(e, ClientError::Backoff(_)) {
            return;
        }
        self.link.errors += 1;
        self.link.last_error = Some(e.to_string());
        let labels = ErrorLabels { drive: self.label.drive.clone(), kind: e.kind().to_string() };
        self.metrics.errors.get_or_create(&labels).inc();
        tracing::debug!(drive = %self.settings.name, error = %e, "modbus call failed");
    }

    async fn read(&mut self) -> Result<Vec<(Table, u16, Vec<u16>)>, ClientError> {
        let mut blocks = Vec::with_capacity(self.plan.len());
        for i in 0..self.plan.len() {
            let (table, start, count) = self.plan[i];
            blocks.push((table, start, self.client.read(table, start, count).await?));
        }
        Ok(blocks)
    }

    /// One poll cycle.
    pub async fn cycle(&mut self) {
        let now = Instant::now();
        if let Some(period) = self.timing.start(now) {
            self.metrics.loop_period.get_or_create(&self.label).observe(period.as_secs_f64());
        }
        self.link.polls += 1;
        self.metrics.polls.get_or_create(&self.label).inc();
        if let Some(commands) = self.state.take_commands() {
            self.law.target_omega_rad_s = commands.target_omega_rad_s;
            if commands.reset_requested && self.settings.mode.writes() {
                self.reset_phase = 1;
            }
        }

        match self.read().await {
            Err(e) => self.error(&e),
            Ok(blocks) => match decode_sample(&self.settings.registers, &blocks, &self.settings.ranges) {
                Err(r) => self.reject(&r),
                Ok(sample) => {
                    // a good poll: the link may forget its back-off
                    self.client.good_poll();
                    self.fresh_or_stale(now, sample).await
                }
            },
        }

        let reconnects = self.client.reconnects();
        if reconnects > self.reconnects_seen {
            self.metrics.reconnects.get_or_create(&self.label).inc_by(reconnects - self.reconnects_seen);
            self.reconnects_seen = reconnects;
        }
        self.link.reconnects = reconnects;
        self.link.connected = self.client.is_connected();
        self.timing.end(Instant::now());
        self.publish();
    }

    fn reject(&mut self, r: &Rejected) {
        self.link.rejected_samples += 1;
        self.link.last_error = Some(format!("rejected sample: {r}"));
        self.metrics.rejected_samples.get_or_create(&self.label).inc();
        tracing::debug!(drive = %self.settings.name, reason = %r, "sample rejected");
    }

    fn stale(&mut self) {
        self.metrics.stale_samples.get_or_create(&self.label).inc();
    }

    /// `now` is when the read was sent: the data are at least as old as the reply took.
    async fn fresh_or_stale(&mut self, now: Instant, sample: Sample) {
        self.status = drive_status(sample.status_word);
        match self.counter.observe(sample.counter) {
            CounterVerdict::Moved => {}
            CounterVerdict::Unchanged | CounterVerdict::Settling => return self.stale(),
            CounterVerdict::Backwards => {
                self.link.errors += 1;
                self.link.last_error = Some(format!("sample counter ran backwards (to {})", sample.counter));
                let labels = ErrorLabels { drive: self.label.drive.clone(), kind: "counter".into() };
                self.metrics.errors.get_or_create(&labels).inc();
                tracing::debug!(drive = %self.settings.name, counter = sample.counter, "sample counter ran backwards");
                return self.stale();
            }
        }
        let previous = self.last_valid;
        if let Some((at, prev)) = previous {
            let dt = now.saturating_duration_since(at).max(self.settings.poll);
            if let Some(r) = implausible_jump(&prev, &sample, dt.as_secs_f64(), &self.settings.ranges) {
                return self.reject(&r);
            }
        }
        self.last_valid = Some((now, sample));
        // timely: the reply came within stale_ms, and so did this sample after the one before; else readiness
        // would call the drive stale while the loop wrote from it
        let limit = self.settings.stale_after;
        let reply_took = Instant::now().saturating_duration_since(now);
        let gap_ok = previous.is_some_and(|(at, _)| now.saturating_duration_since(at) <= limit);
        if reply_took > limit || !gap_ok {
            return self.stale();
        }
        let first = self.last_fresh_at.is_none();
        let dt = self.last_fresh_at.map_or(self.settings.poll, |t| now.saturating_duration_since(t));
        self.last_fresh_at = Some(now);
        self.state.mark_fresh(now);
        let d_m = self.settings.feed_forward.motor_m3_rad;
        let torque = d_m * (sample.p_in_bar - sample.p_out_bar) * crate::units::PA_PER_BAR;
        let est = self.estimator.update(&Measurement {
            dt_s: dt.as_secs_f64(),
            omega_rad_s: sample.omega_rad_s,
            drive_torque_nm: torque,
        });
        self.estimate = Some(est);
        let tripped = self.status.fault || self.status.comm_loss_trip;
        if first && self.settings.mode.writes() {
            self.law.start_from(sample.f_drive_hz);
        }
        let setpoint = self.law.step(&Inputs {
            dt_s: dt.as_secs_f64(),
            fresh: true,
            tripped,
            omega_hat_rad_s: est.omega_hat_rad_s,
            load_hat_nm: est.load_hat_nm,
        });
        let mut written = f64::NAN;
        if let Some(hz) = setpoint
            && self.write(now, hz).await
        {
            written = hz;
        }
        let point = Point {
            t_s: now.saturating_duration_since(self.started).as_secs_f64(),
            f_set_hz: written,
            f_drive_hz: sample.f_drive_hz,
            p_in_bar: sample.p_in_bar,
            p_out_bar: sample.p_out_bar,
            omega_rad_s: sample.omega_rad_s,
            omega_hat_rad_s: est.omega_hat_rad_s,
            load_hat_nm: est.load_hat_nm,
            inertia_hat_kg_m2: est.inertia_hat_kg_m2,
            viscous_hat_nm_s_rad: est.viscous_hat_nm_s_rad,
            inertia_sd_kg_m2: est.inertia_sd_kg_m2,
            viscous_sd_nm_s_rad: est.viscous_sd_nm_s_rad,
            status_word: sample.status_word,
        };
        self.sample = Some(point);
        self.pending_history.push(point);
        self.state.push_history(&mut self.pending_history);
        if let Some(r) = &self.recorder {
            r.record(point);
        }
        let l = &self.label;
        self.metrics.inlet_pressure.get_or_create(l).set(sample.p_in_bar * PASCALS_PER_BAR);
        self.metrics.outlet_pressure.get_or_create(l).set(sample.p_out_bar * PASCALS_PER_BAR);
        self.metrics.drive_frequency.get_or_create(l).set(sample.f_drive_hz);
        self.metrics.omega.get_or_create(l).set(sample.omega_rad_s);
        self.metrics.omega_hat.get_or_create(l).set(est.omega_hat_rad_s);
        self.metrics.load_hat.get_or_create(l).set(est.load_hat_nm);
        self.metrics.inertia_hat.get_or_create(l).set(est.inertia_hat_kg_m2);
        self.metrics.inertia_sd.get_or_create(l).set(est.inertia_sd_kg_m2);
        self.metrics.viscous_hat.get_or_create(l).set(est.viscous_hat_nm_s_rad);
        self.metrics.viscous_sd.get_or_create(l).set(est.viscous_sd_nm_s_rad);
    }

    /// Writes the setpoint, control word and watchdog when something changed or the watchdog is due. Returns true
    /// if the setpoint reached the drive (or was already there).
    async fn write(&mut self, now: Instant, hz: f64) -> bool {
        let mut control_word = control::RUN;
        if self.reset_phase == 1 {
            control_word |= control::FAULT_RESET;
        }
        let due =
            self.last_watchdog_at.is_none_or(|t| now.saturating_duration_since(t) >= self.settings.watchdog_every);
        let next_watchdog = if due { self.watchdog.wrapping_add(1) } else { self.watchdog };
        let writes = match plan_writes(&self.settings.registers, hz, control_word, next_watchdog) {
            Ok(w) => w,
            Err(e) => {
                self.link.errors += 1;
                self.link.last_error = Some(format!("cannot encode the setpoint: {e}"));
                let labels = ErrorLabels { drive: self.label.drive.clone(), kind: "encode".into() };
                self.metrics.errors.get_or_create(&labels).inc();
                return false;
            }
        };
        if !due && writes == self.last_written {
            return true;
        }
        for (start, words) in &writes {
            self.link.writes += 1;
            self.metrics.writes.get_or_create(&self.label).inc();
            if let Err(e) = self.client.write(*start, words).await {
                self.error(&e);
                self.last_written.clear();
                return false;
            }
        }
        if due {
            self.last_watchdog_at = Some(now);
        }
        self.watchdog = next_watchdog;
        self.last_written = writes;
        self.reset_phase = match self.reset_phase {
            1 => {
                tracing::info!(drive = %self.settings.name, "fault reset sent");
                2
            }
            _ => 0,
        };
        self.metrics.setpoint.get_or_create(&self.label).set(hz);
        true
    }

    fn publish(&mut self) {
        let now = Instant::now();
        if self.stats_at.is_none_or(|t| now.saturating_duration_since(t) >= STATS_EVERY) {
            self.stats = self.timing.stats();
            self.stats_at = Some(now);
        }
        self.stats.overruns = self.timing.overruns;
        let stats = self.stats;
        let l = &self.label;
        self.metrics.jitter_p50.get_or_create(l).set(stats.jitter_p50_ms * 1e-3);
        self.metrics.jitter_p99.get_or_create(l).set(stats.jitter_p99_ms * 1e-3);
        let new_overruns = stats.overruns.saturating_sub(self.metrics.overruns.get_or_create(l).get());
        self.metrics.overruns.get_or_create(l).inc_by(new_overruns);
        self.metrics.link_up.get_or_create(l).set(i64::from(self.link.connected));
        self.metrics.target.get_or_create(l).set(self.law.target_omega_rad_s);
        let stale = self.last_fresh_at.is_none_or(|t| t.elapsed() > self.settings.stale_after);
        self.metrics.stale.get_or_create(l).set(i64::from(stale));
        let recording_health = self.recorder.as_ref().map(|r| r.health.snapshot());
        if let Some(h) = &recording_health {
            self.metrics.recording_ok.get_or_create(l).set(i64::from(h.ok));
            let errors = self.metrics.recording_errors.get_or_create(l);
            errors.inc_by(h.errors.saturating_sub(errors.get()));
            let lost = self.metrics.recording_rows_lost.get_or_create(l);
            lost.inc_by(h.rows_lost.saturating_sub(lost.get()));
            let deleted = self.metrics.recording_files_deleted.get_or_create(l);
            deleted.inc_by(h.files_deleted.saturating_sub(deleted.get()));
            let compressed = self.metrics.recording_files_compressed.get_or_create(l);
            compressed.inc_by(h.files_compressed.saturating_sub(compressed.get()));
        }
        // skipped when a reader holds it: the next cycle publishes again
        let _ = self.state.publish(DriveSnapshot {
            name: self.settings.name.clone(),
            mode: self.settings.mode,
            address: self.settings.address.clone(),
            unit_id: self.settings.unit_id,
            target_omega_rad_s: self.law.target_omega_rad_s,
            setpoint_hz: self.law.last_hz(),
            tripped: self.status.fault || self.status.comm_loss_trip,
            status: self.status,
            link: self.link.clone(),
            sample: self.sample,
            estimate: self.estimate,
            timing: stats,
            recording: recording_health,
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ranges() -> ValidRanges {
        ValidRanges {
            min_pressure_bar: -1.0,
            max_pressure_bar: 400.0,
            max_speed_rad_s: 1000.0,
            max_frequency_hz: 400.0,
            rates: crate::service::freshness::RateLimits {
                pressure_bar_per_s: 2e5,
                speed_rad_per_s2: 1e4,
                frequency_hz_per_s: 1e3,
            },
        }
    }

    #[test]
    fn default_map_is_one_read_and_one_write() {
        let map = RegisterMap::default();
        assert_eq!(read_plan(&map), vec![(Table::Input, 0, 6)]);
        let w = plan_writes(&map, 25.0, control::RUN, 7).expect("fits");
        assert_eq!(w, vec![(0, vec![2500, control::RUN, 7])]);
        assert_eq!(write_layout(&map), vec![(0, 3)]);
    }

    #[test]
    fn scattered_registers_are_written_apart() {
        let mut map = RegisterMap::default();
        map.watchdog.address = 10;
        map.frequency_setpoint_hz = RegisterSpec::new(Table::Holding, 20, crate::modbus::ValueType::F32, 1.0);
        let w = plan_writes(&map, 25.5, 1, 2).expect("fits");
        assert_eq!(w.len(), 3);
        assert_eq!(w[0], (1, vec![1]));
        assert_eq!(w[2].0, 20);
        assert_eq!(w[2].1.len(), 2);
        let layout: Vec<(u16, usize)> = w.iter().map(|(a, words)| (*a, words.len())).collect();
        assert_eq!(write_layout(&map), layout);
    }

    #[test]
    fn decodes_and_rejects() {
        let map = RegisterMap::default();
        let block = |p_in: u16| vec![(Table::Input, 0u16, vec![p_in, 300, 3820, 2550, 3, 17])];
        let s = decode_sample(&map, &block(3512), &ranges()).expect("valid");
        assert!((s.p_in_bar - 35.12).abs() < 1e-9);
        assert!((s.omega_rad_s - rpm_to_rad_s(382.0)).abs() < 1e-9);
        assert_eq!((s.status_word, s.counter), (3, 17));
        let r = decode_sample(&map, &block(60000), &ranges());
        assert!(matches!(r, Err(Rejected::Range { entry: "inlet_pressure_bar", .. })), "{r:?}");
        let short = vec![(Table::Input, 0u16, vec![1, 2, 3])];
        assert!(matches!(decode_sample(&map, &short, &ranges()), Err(Rejected::Decode { .. })));
    }

    #[test]
    fn nan_floats_are_rejected() {
        let map = RegisterMap {
            inlet_pressure_bar: RegisterSpec::new(Table::Input, 6, crate::modbus::ValueType::F32, 1.0),
            ..RegisterMap::default()
        };
        let blocks = vec![(Table::Input, 0u16, vec![0, 300, 0, 0, 0, 1, 0x7FC0, 0])];
        assert!(decode_sample(&map, &blocks, &ranges()).is_err());
    }
}

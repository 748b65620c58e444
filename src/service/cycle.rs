//! PURE drive cycle: a validated sample and the time it was read → the writes to send and the row to keep. No
//! sockets and no clock: the poll loop ([`super::drive`]) reads, calls [`DriveCycle::step`], sends what it says and
//! reports back with [`DriveCycle::confirm`].
//!
//! Data are fresh when the sample counter has moved forward (and has not run backwards lately, see
//! [`super::freshness`]), every value decodes in range and changed no faster than the plausible rates, the reply
//! came within `stale_ms` and the previous new sample no more than `stale_ms` before: the one definition readiness
//! also uses (only fresh samples mark the drive fresh). Only fresh data reach the estimator, and only fresh data
//! lead to a write: on stale data nothing is written, so the drive's own watchdog takes over. A tripped drive is
//! commanded towards 0 Hz and only re-armed by a reset request from the API.
//!
//! In the service's layout (see [`super`]) it uses [`super::freshness`], [`super::state`] and [`super::config`].

use std::time::Duration;

use tokio::time::Instant;

use super::config::DriveSettings;
use super::freshness::{
    CounterCheck, CounterVerdict, FrozenSpeed, NO_TURN_HZ, Rejected, SpeedMatch, ValidRanges, implausible_jump,
};
use super::owner::{Echo, Finding};
use super::state::{Commands, DriveStatus, Measured, Point};
use crate::control::{Inputs, Mode, SpeedLaw};
use crate::estimator::{Estimate, Estimator, Measurement};
use crate::modbus::map::{MapError, RegisterMap, Sample, control, plan_writes, status};
use std::collections::VecDeque;

/// The state bits of a status word.
pub fn drive_status(word: u16) -> DriveStatus {
    DriveStatus {
        word,
        ready: word & status::READY != 0,
        running: word & status::RUNNING != 0,
        fault: word & status::FAULT != 0,
        comm_loss_trip: word & status::COMM_LOSS_TRIP != 0,
        not_following: false,
        another_master: false,
    }
}

/// What a sample turned out to be.
#[derive(Debug, Clone, PartialEq)]
pub enum Verdict {
    /// Fresh: estimated, controlled, kept as a row.
    Fresh,
    /// Not new or not timely: nothing estimated, nothing written.
    Stale,
    /// The sample counter ran backwards (a device fault): stale.
    CounterBackwards(u64),
    /// Values moved faster than plausible: refused.
    Rejected(Rejected),
}

/// What one step asks of the loop.
#[derive(Debug, Clone, PartialEq)]
pub struct Step {
    pub verdict: Verdict,
    /// The write requests to send now, in order; empty when nothing is due (stale data, monitor mode, or the same
    /// values as last time with the watchdog not yet due).
    pub writes: Vec<(u16, Vec<u16>)>,
    /// The fresh sample's row. Its `f_set_hz` is the setpoint if `writes` reach the drive (NaN when none was
    /// computed or it could not be encoded); the loop blanks it when they fail.
    pub point: Option<Point>,
    /// The setpoint could not be encoded into its register.
    pub encode_error: Option<MapError>,
}

/// Writes handed to the loop and not yet confirmed.
#[derive(Debug, Clone, PartialEq)]
struct Pending {
    writes: Vec<(u16, Vec<u16>)>,
    watchdog: u16,
    /// When the watchdog changed, if it did.
    watchdog_at: Option<Instant>,
    setpoint_hz: f64,
    /// The control word carries RUN.
    run: bool,
    /// The control word carries the fault-reset bit.
    reset: bool,
}

/// A gap between fresh samples longer than this (or than `stale_ms`, if shorter; at least two polls) starts the
/// ramp again from the drive's read-back with one poll's step: with `stale_ms` raised to 5 s, a 3.7 s gap made the
/// first write a whole second's ramp (26 → 46 Hz at 20 Hz/s).
pub const RESUME_AFTER: Duration = Duration::from_millis(250);

/// A reset asked for through the API, until the drive shows no fault after its bit went out, or it lapses.
#[derive(Debug, Clone, Copy, PartialEq)]
struct ResetRequest {
    /// When the cycle first saw a sample after the request: the reset lapses [`RESET_LAPSES_AFTER`] later.
    since: Option<Instant>,
    /// The fault-reset bit reached the drive at least once.
    sent: bool,
}

/// A requested reset that has not cleared the drive's fault this long after the request (or three polls, if
/// longer) lapses: a link that drops meanwhile does not carry it out when it returns (a reviewer's run: the drive
/// tripped on the lost link, and 5.8 s later the old request cleared that trip and sent RUN), and a trip seen after
/// it latches again. Until then the bit stays on, so that a gateway that forwards the latest values every few polls
/// still passes it on.
pub const RESET_LAPSES_AFTER: Duration = Duration::from_secs(1);

/// Our confirmed watchdog values before the last that a read-back may still show and be ours (a gateway's cache, a
/// late write): 1.6 s of values at the default `watchdog_ms` of 100.
const RECENT_WATCHDOGS: usize = 16;

/// What a confirmed write did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Confirmed {
    pub setpoint_hz: f64,
    /// The fault-reset bit went out with it.
    pub reset_sent: bool,
}

/// One drive's control state between cycles: everything but the link, the publishing and the recording.
pub struct DriveCycle {
    mode: Mode,
    registers: RegisterMap,
    ranges: ValidRanges,
    poll: Duration,
    stale_after: Duration,
    watchdog_every: Duration,
    started: Instant,
    estimator: Box<dyn Estimator>,
    law: SpeedLaw,
    counter: CounterCheck,
    /// The last sample that passed every check but timeliness, and when it was read: the reference of the
    /// rate-of-change check and of the gap between new samples.
    last_valid: Option<(Instant, Measured)>,
    last_fresh_at: Option<Instant>,
    /// When the watchdog value last changed: it must change at least every `watchdog_ms`.
    last_watchdog_at: Option<Instant>,
    last_written: Vec<(u16, Vec<u16>)>,
    watchdog: u16,
    /// A reset asked for and not yet done or lapsed: its bit goes out with every write meanwhile.
    reset: Option<ResetRequest>,
    /// A reset lapsed before its bit reached the drive (the loop says so once).
    reset_lapsed: bool,
    /// A trip this service saw (fault or comm-loss bit, a sample counter that restarted: the drive lost power, or a
    /// drive running under RUN that stopped on its own), held until `POST …/reset`: a drive whose trip clears on its
    /// own side, or that comes back from a power cycle, is not sent RUN again by the service itself (no unexpected
    /// restart, EN 60204-1 §7.5). Writing modes only.
    trip_latched: bool,
    /// The last control word the drive confirmed carries RUN: a drive that then stops on its own is latched.
    run_sent: bool,
    /// The control's (min_hz, max_hz): a setpoint register's step never takes a write past them.
    hz_range: (f64, f64),
    /// Some write reached the drive: on a clean stop it is sent control word 0.
    commanded: bool,
    /// The watchdog value of the last write the drive confirmed; None before one, and after a failed write (the
    /// device may or may not hold it).
    confirmed_watchdog: Option<u16>,
    /// The confirmed watchdog values before the last one, newest last (at most [`RECENT_WATCHDOGS`]).
    recent_watchdogs: VecDeque<u16>,
    /// Whether another master writes the drive (see [`super::owner`]); once found, nothing is written until a reset.
    echo: Echo,
    /// The speed frozen while the drive's frequency moves, or showing no turn while the drive runs: rejected.
    frozen: FrozenSpeed,
    /// The speed against the drive's frequency through the model's pump and motor (writing modes).
    speed_match: SpeedMatch,
    pending: Option<Pending>,
    status: DriveStatus,
    /// The drive does not follow its setpoints (the law's verdict), for the alarm.
    not_following: bool,
    estimate: Option<Estimate>,
    measured: Option<Measured>,
}

impl DriveCycle {
    /// `started` is the service's start: rows count their time from it.
    pub fn new(settings: &DriveSettings, estimator: Box<dyn Estimator>, started: Instant) -> DriveCycle {
        let mut law = SpeedLaw::new(settings.mode, settings.limits, settings.gains, settings.feed_forward);
        law.target_omega_rad_s = settings.target_omega_rad_s;
        law.fixed_hz = settings.fixed_hz;
        DriveCycle {
            mode: settings.mode,
            registers: settings.registers,
            ranges: settings.ranges,
            poll: settings.poll,
            stale_after: settings.stale_after,
            watchdog_every: settings.watchdog_every,
            started,
            estimator,
            law,
            counter: CounterCheck::new(16 * u32::from(settings.registers.sample_counter.kind.words())),
            last_valid: None,
            last_fresh_at: None,
            last_watchdog_at: None,
            last_written: Vec::new(),
            watchdog: 0,
            reset: None,
            reset_lapsed: false,
            trip_latched: false,
            run_sent: false,
            hz_range: (settings.limits.min_hz, settings.limits.max_hz),
            commanded: false,
            confirmed_watchdog: None,
            recent_watchdogs: VecDeque::with_capacity(RECENT_WATCHDOGS + 1),
            echo: Echo::default(),
            frozen: FrozenSpeed::default(),
            speed_match: SpeedMatch::default(),
            pending: None,
            status: DriveStatus::default(),
            not_following: false,
            estimate: None,
            measured: None,
        }
    }

    /// Takes the HTTP side's commands: the target, and a reset (re-arms a writing drive at its next write).
    pub fn command(&mut self, c: Commands) {
        self.law.target_omega_rad_s = c.target_omega_rad_s;
        if c.reset_requested && self.mode.writes() {
            self.reset = Some(ResetRequest { since: None, sent: false });
            // what the drive still reports latches again at its next sample
            self.trip_latched = false;
            if self.echo.found() {
                // a service that stood back for another master writes again, ramping from what the drive runs at
                self.last_fresh_at = None;
            }
            // and the check looks afresh (also where a refused read had stood it down)
            self.echo.reset();
        }
    }

    /// One cycle on a validated sample: `sent_at` is when the read was sent (the data are at least as old as the
    /// reply took), `replied_at` when its reply came.
    pub fn step(&mut self, sample: &Sample, sent_at: Instant, replied_at: Instant) -> Step {
        let nothing = |verdict| Step { verdict, writes: Vec::new(), point: None, encode_error: None };
        self.pending = None;
        let before = self.status;
        self.status = drive_status(sample.status_word);
        let writing = self.mode.writes();
        // a drive that ran under this service's RUN and stopped on its own (it lost ready or running: a safe torque
        // off, an enable or an emergency stop, a power cycle) is latched as a fault is: not started again unasked;
        // while a requested reset goes out, the fault it is meant to clear is not latched again
        let stopped = before.ready && before.running && !(self.status.ready && self.status.running);
        let faulted = self.status.fault || self.status.comm_loss_trip;
        let tripped = faulted || (self.run_sent && stopped);
        if let Some(r) = &mut self.reset {
            let since = *r.since.get_or_insert(sent_at);
            if r.sent && !faulted {
                // done: the drive shows no fault after the bit went out
                self.reset = None;
            } else if sent_at.saturating_duration_since(since) > RESET_LAPSES_AFTER.max(3 * self.poll) {
                self.reset_lapsed = !r.sent;
                self.reset = None;
            }
        }
        self.trip_latched |= writing && self.reset.is_none() && tripped;
        match self.counter.observe(sample.counter) {
            CounterVerdict::Moved => {}
            CounterVerdict::Unchanged | CounterVerdict::Settling => return nothing(Verdict::Stale),
            CounterVerdict::Backwards => {
                self.trip_latched |= writing;
                return nothing(Verdict::CounterBackwards(sample.counter));
            }
        }
        let now = sent_at;
        let previous = self.last_valid;
        if let Some((at, prev)) = previous {
            let dt = now.saturating_duration_since(at).max(self.poll);
            if let Some(r) = implausible_jump(&prev, &sample.measured, dt.as_secs_f64(), &self.ranges) {
                return nothing(Verdict::Rejected(r));
            }
        }
        if let Some(r) = self.frozen.observe(sample.measured.omega_rad_s, sample.measured.f_drive_hz, now.into_std()) {
            return nothing(Verdict::Rejected(r));
        }
        if let Some(r) = self.frozen.observe_inlet(sample.measured.p_in_bar, sample.measured.f_drive_hz) {
            return nothing(Verdict::Rejected(r));
        }
        if let Some(r) = self.frozen.observe_image(&sample.measured, now.into_std()) {
            return nothing(Verdict::Rejected(r));
        }
        let m = &sample.measured;
        // the model's pump and motor (the law's): the speed the frequency gives, the torque from Δp
        let plant = self.law.feed_forward;
        let dp_pa = (m.p_in_bar - m.p_out_bar) * crate::units::PA_PER_BAR;
        if writing {
            let speeds = (plant.omega_at_dp(m.f_drive_hz, dp_pa), plant.omega_rad_s(NO_TURN_HZ));
            if let Some(r) = self.speed_match.observe(m.omega_rad_s, speeds, m.f_drive_hz, now.into_std()) {
                return nothing(Verdict::Rejected(r));
            }
        }
        self.last_valid = Some((now, sample.measured));
        if self.frozen.showing_no_turn() || (self.speed_match.mismatched() && !self.speed_match.read_back_only()) {
            // a speed of 0 (or against the drive) while the drive runs, or one the drive's frequency cannot give:
            // held back, not written from, until it fits again or, after a second, the samples are rejected
            return nothing(Verdict::Stale);
        }
        // a read-back below what the turning shaft allows is not what the drive runs at (`read_back_only`): the law
        // goes on without it, from its last setpoint; with no setpoint to go on from (the first cycle, or the first
        // after a gap, when the ramp starts again from the read-back), nothing is written until the read-back fits
        let drive_hz = if self.speed_match.off_now() { f64::NAN } else { m.f_drive_hz };
        // timely: this reply came within stale_ms of the request of the sample before (so within stale_ms of its
        // own request too): the data never aged past stale_ms on the way, as readiness measures the age (from the
        // request of the newest fresh sample). Asking each of the reply's time and the gap alone within stale_ms, a
        // reviewer's replies 45 ms late at a 10 ms poll (stale_ms 50) were written from 54 times in 3.5 s while
        // `/readyz` said stale in 28 of 30 queries
        let limit = self.stale_after;
        if previous.is_none_or(|(at, _)| replied_at.saturating_duration_since(at) > limit) {
            return nothing(Verdict::Stale);
        }
        let first = self.last_fresh_at.is_none();
        let dt = self.last_fresh_at.map_or(self.poll, |t| now.saturating_duration_since(t));
        // the first fresh cycle, or the first after a gap (longer than the data may age: a PLC that refreshes its
        // registers every few polls is no gap): the setpoint ramps from what the drive runs at, one poll's step
        let resumed = first || dt > self.stale_after.min(RESUME_AFTER).max(2 * self.poll);
        if writing && drive_hz.is_nan() && (resumed || self.law.last_hz().is_none()) {
            // (a reviewer's reading: restarted from nothing, the first write was min_hz and a ramp step, with RUN)
            return nothing(Verdict::Stale);
        }
        // a drive this service sent RUN that is not running after a stale stretch (its own watchdog stopped it, or
        // it lost power before it showed running, its counter moving on) is not started again unasked either: a
        // restarted simulator that had not yet shown running got RUN again under load
        let running = self.status.ready && self.status.running;
        if writing && !first && dt > self.stale_after && self.run_sent && !running && self.reset.is_none() {
            self.trip_latched = true;
        }
        self.last_fresh_at = Some(now);
        let torque = plant.motor_m3_rad * dp_pa;
        let est = self.estimator.update(&Measurement {
            dt_s: dt.as_secs_f64(),
            omega_rad_s: m.omega_rad_s,
            drive_torque_nm: torque,
        });
        self.estimate = Some(est);
        // standing back for another master: the regulator rests (nothing is written, not even a stop: that would
        // fight the other master as much as a setpoint), and starts again from the drive's read-back after a reset
        let setpoint = if self.echo.found() {
            None
        } else {
            self.law.step(&Inputs {
                dt_s: if resumed { self.poll } else { dt }.as_secs_f64(),
                fresh: true,
                tripped: self.tripped(),
                omega_hat_rad_s: est.omega_hat_rad_s,
                load_hat_nm: est.load_hat_nm,
                drive_hz,
                drive_running: running,
                resumed,
                dp_pa,
            })
        };
        self.note_following();
        let (mut f_set_hz, mut writes, mut encode_error) = (f64::NAN, Vec::new(), None);
        if let Some(hz) = setpoint {
            match self.plan(now, hz) {
                Ok(w) => (f_set_hz, writes) = (hz, w),
                Err(e) => encode_error = Some(e),
            }
        }
        let measured = Measured { t_s: now.saturating_duration_since(self.started).as_secs_f64(), f_set_hz, ..*m };
        self.measured = Some(measured);
        // the target the law regulated to; none (NaN) outside speed mode, where no target is followed
        let target_omega_rad_s = if self.mode == Mode::Speed { self.law.target_omega_rad_s } else { f64::NAN };
        let point = Point { sample: measured, estimate: est, status_word: sample.status_word, target_omega_rad_s };
        Step { verdict: Verdict::Fresh, writes, point: Some(point), encode_error }
    }

    /// The writes for setpoint `hz`: nothing when they would repeat the last ones and the watchdog is not due.
    fn plan(&mut self, now: Instant, hz: f64) -> Result<Vec<(u16, Vec<u16>)>, MapError> {
        // RUN only to a drive that reports ready and no fault: a drive that is not ready, or tripped, is told to
        // stop (its setpoint still ramps down); a requested reset goes out alone, and RUN follows once the drive
        // reports ready again
        let mut control_word = if self.status.ready && !self.tripped() { control::RUN } else { 0 };
        let reset = self.reset.is_some();
        if reset {
            control_word |= control::FAULT_RESET;
        }
        let due = self.last_watchdog_at.is_none_or(|t| now.saturating_duration_since(t) >= self.watchdog_every);
        let watchdog = if due { self.next_watchdog() } else { self.watchdog };
        let writes = plan_writes(&self.registers, (hz, self.hz_range), control_word, watchdog)?;
        if !due && writes == self.last_written {
            return Ok(Vec::new());
        }
        let watchdog_at = due.then_some(now);
        let run = control_word & control::RUN != 0;
        self.pending = Some(Pending { writes: writes.clone(), watchdog, watchdog_at, setpoint_hz: hz, run, reset });
        Ok(writes)
    }

    /// The loop's report on the last step's writes: all sent (`ok`), or one failed (then the next step writes
    /// everything again). None when there was nothing to confirm or it failed.
    pub fn confirm(&mut self, ok: bool) -> Option<Confirmed> {
        let p = self.pending.take()?;
        if !ok {
            self.last_written.clear();
            self.confirmed_watchdog = None;
            return None;
        }
        if p.watchdog_at.is_some() {
            self.last_watchdog_at = p.watchdog_at;
        }
        if let Some(before) = self.confirmed_watchdog.filter(|&w| w != p.watchdog) {
            self.recent_watchdogs.push_back(before);
            if self.recent_watchdogs.len() > RECENT_WATCHDOGS {
                self.recent_watchdogs.pop_front();
            }
        }
        self.watchdog = p.watchdog;
        self.confirmed_watchdog = Some(p.watchdog);
        self.last_written = p.writes;
        self.run_sent = p.run;
        self.commanded = true;
        let reset_sent = p.reset && self.reset.is_some_and(|r| !r.sent);
        if let Some(r) = self.reset.as_mut().filter(|_| p.reset) {
            r.sent = true;
        }
        Some(Confirmed { setpoint_hz: p.setpoint_hz, reset_sent })
    }

    /// Where the watchdog counts from (the first write carries the next value): the service starts it at a value of
    /// its own, so that two masters started together do not count in step, each taking the other's values for its
    /// own recent ones ([`RECENT_WATCHDOGS`]).
    pub fn start_watchdog_at(&mut self, value: u16) {
        if self.confirmed_watchdog.is_none() {
            self.watchdog = value;
        }
    }

    /// The next watchdog value: counting up, and from 1 again where the register cannot hold the next one (a PLC's
    /// INT, a scale): an `i16` watchdog failed every write from 32768 on, after 54.6 min at 100 ms, and the drive
    /// tripped. 0 is skipped: it is what a drive that lost power shows.
    fn next_watchdog(&self) -> u16 {
        let next = self.watchdog.wrapping_add(1);
        if next != 0 && self.registers.watchdog.encode(f64::from(next)).is_ok() { next } else { 1 }
    }

    /// The watchdog register to read back now, as (address, words): due every [`super::owner::CHECK_EVERY`] in a
    /// writing mode once a write of this service was confirmed. The loop reads it before the sample, so the read
    /// covers the whole time since this service last wrote.
    pub fn echo_due(&self, now: Instant) -> Option<(u16, u16)> {
        let spec = self.registers.watchdog;
        (self.mode.writes() && self.confirmed_watchdog.is_some() && self.echo.due(now))
            .then(|| (spec.address, spec.kind.words()))
    }

    /// The watchdog read-back went unanswered within the call timeout (see [`super::owner::Echo::timed_out`]).
    pub fn echo_timed_out(&mut self, now: Instant) -> Option<Finding> {
        self.echo.timed_out(now)
    }

    /// The watchdog register read back (`None`: the device refused the read): what it showed, where that changed
    /// anything. Once another master is found, this service writes nothing, and on a clean stop sends nothing.
    pub fn echo_read(&mut self, now: Instant, read: Option<&[u16]>) -> Option<Finding> {
        let Some(read) = read else { return self.echo.refused() };
        let encode = |w: u16| self.registers.watchdog.encode(f64::from(w)).ok();
        let ours = encode(self.confirmed_watchdog?)?;
        // our recent values are ours too: a gateway that answers reads from a cache it refreshes every few polls, or
        // passes writes on late, shows them for a while (a reviewer's 20 ms cache was found "another master" within
        // 5 s, and one six values behind too)
        let lagging = self.recent_watchdogs.iter().any(|&p| encode(p).is_some_and(|p| p == read));
        let finding = self.echo.observe(now, read, if lagging { read } else { &ours });
        if self.echo.found() {
            // the drive is the other master's now: its stopping is no trip of ours, and a clean stop leaves it be
            self.commanded = false;
            self.run_sent = false;
            self.confirmed_watchdog = None;
        }
        finding
    }

    /// True once after a requested reset lapsed before its bit reached the drive (for the loop's WARN).
    pub fn take_reset_lapsed(&mut self) -> bool {
        std::mem::take(&mut self.reset_lapsed)
    }

    /// Another master was found writing the drive: this service stands back until a reset.
    pub fn another_master(&self) -> bool {
        self.echo.found()
    }

    /// Logs a drive that stops (or starts again) following its setpoints, once per episode.
    fn note_following(&mut self) {
        let now = self.law.not_following();
        if now != self.not_following {
            self.not_following = now;
            if now {
                tracing::warn!(
                    setpoint_hz = self.law.last_hz(),
                    drive_hz = self.measured.map(|m| m.f_drive_hz),
                    "the drive does not follow its setpoints (local mode, not ready or not running, or held by a \
                     frequency limit of its own below the setpoint): the speed regulator holds its integral and \
                     ramps from the drive's read-back"
                );
            } else {
                tracing::info!("the drive follows its setpoints again");
            }
        }
    }

    /// True while the drive does not follow its setpoints (read-back away from them, or not ready and running).
    pub fn not_following(&self) -> bool {
        self.not_following
    }

    /// The status word's bits, as of the last decoded sample.
    pub fn status(&self) -> DriveStatus {
        self.status
    }

    /// Some write of this service reached the drive.
    pub fn commanded(&self) -> bool {
        self.commanded
    }

    /// A trip this service latched and that was not reset since (writing modes).
    pub fn trip_latched(&self) -> bool {
        self.trip_latched
    }

    /// A sample a range or freshness check refused, as the recording keeps it (what was read is kept, as the
    /// record of the incident): the refused entry's value left out (`rejected`'s), no estimate, nothing written.
    /// None where the whole sample is refused (an image that stopped repeats the last one). A sensor out of range or
    /// a tachometer the frequency contradicts was left out of the recording whole: 2 s of the incident missing, and
    /// `rows_lost` 0 (a reviewer's proxy).
    pub fn refused_point(&self, sample: &Sample, now: Instant, rejected: &Rejected) -> Option<Point> {
        let entry = rejected.entry()?;
        let t_s = now.saturating_duration_since(self.started).as_secs_f64();
        let mut m = Measured { t_s, f_set_hz: f64::NAN, ..sample.measured };
        match entry {
            // the register entries, and the measured column the jump test names
            "inlet_pressure_bar" => m.p_in_bar = f64::NAN,
            "outlet_pressure_bar" => m.p_out_bar = f64::NAN,
            "shaft_speed_rpm" | "omega_rad_s" => m.omega_rad_s = f64::NAN,
            "drive_frequency_hz" => m.f_drive_hz = f64::NAN,
            _ => return None,
        }
        let target_omega_rad_s = if self.mode == Mode::Speed { self.law.target_omega_rad_s } else { f64::NAN };
        Some(Point { sample: m, estimate: Estimate::MISSING, status_word: sample.status_word, target_omega_rad_s })
    }

    /// Latches the trip a previous run of the service left unreset (writing modes).
    pub fn latch_from_before(&mut self) {
        self.trip_latched |= self.mode.writes();
    }

    /// Goes on from the setpoint a previous run left moments ago (writing modes): the first setpoint of this run is
    /// then at most it, as after a gap within a run, whatever the read-back says.
    pub fn resume_below(&mut self, hz: f64) {
        if self.mode.writes() {
            self.law.start_from(hz);
        }
    }

    /// The drive reports a fault or a comm-loss trip, or (writing modes) one was seen and not yet reset.
    pub fn tripped(&self) -> bool {
        self.status.fault || self.status.comm_loss_trip || self.trip_latched
    }

    pub fn estimate(&self) -> Option<Estimate> {
        self.estimate
    }

    /// The last fresh sample's measured columns.
    pub fn measured(&self) -> Option<Measured> {
        self.measured
    }

    pub fn target_omega_rad_s(&self) -> f64 {
        self.law.target_omega_rad_s
    }

    /// The last setpoint the law gave.
    pub fn setpoint_hz(&self) -> Option<f64> {
        self.law.last_hz()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: Duration = Duration::from_millis(1);

    /// Settings from a real config (poll 10 ms, stale 50 ms, watchdog 100 ms, 0–50 Hz at 20 Hz/s unless `control`
    /// says otherwise).
    fn settings(control: &str) -> DriveSettings {
        let text = format!(
            "[[drives]]\nname = \"d\"\naddress = \"127.0.0.1:1\"\npoll_ms = 10\nstale_ms = 50\nwatchdog_ms = 100\n\
             [drives.control]\n{control}\n"
        );
        let mut s = super::super::config::parse(&text, "test", None).expect("valid config");
        s.drives.remove(0)
    }

    fn cycle(control: &str) -> (DriveCycle, Instant) {
        let s = settings(control);
        let t0 = Instant::now();
        (DriveCycle::new(&s, crate::estimator::build(&s.estimator, &s.model), t0), t0)
    }

    fn sample(counter: u64, omega_rad_s: f64, f_drive_hz: f64, status_word: u16) -> Sample {
        let measured = Measured {
            t_s: f64::NAN,
            f_set_hz: f64::NAN,
            // a live sensor: it moves a quantum or two (one value held while the drive ramps 2 Hz is frozen)
            p_in_bar: 40.0 + 0.01 * (counter % 3) as f64,
            p_out_bar: 5.0,
            omega_rad_s,
            f_drive_hz,
            drive_power_w: f64::NAN,
        };
        Sample { measured, status_word, counter }
    }

    /// Steps samples `k0 .. k0 + n` (counter k read at k·10 ms after `t0`, replied 1 ms later), confirming each
    /// write; the steps.
    fn run(c: &mut DriveCycle, t0: Instant, k0: u64, n: u64, omega: f64, word: u16) -> Vec<Step> {
        (0..n)
            .map(|k| {
                let at = t0 + MS * (10 * (k0 + k) as u32);
                let step = c.step(&sample(k0 + k, omega, 20.0, word), at, at + MS);
                c.confirm(true);
                step
            })
            .collect()
    }

    /// The setpoint in a step's writes (default map: one block at 0, setpoint, control word, watchdog).
    fn written(s: &Step) -> Option<(f64, u16, u16)> {
        let (_, w) = s.writes.first()?;
        Some((f64::from(w[0]) * 0.01, w[1], w[2]))
    }

    #[test]
    fn monitor_mode_never_writes_but_keeps_rows() {
        let (mut c, t0) = cycle("mode = \"monitor\"");
        let steps = run(&mut c, t0, 0, 20, 30.0, 3);
        assert!(steps.iter().all(|s| s.writes.is_empty()), "monitor mode writes nothing");
        let fresh: Vec<&Step> = steps.iter().filter(|s| s.verdict == Verdict::Fresh).collect();
        assert_eq!(fresh.len(), 19, "all but the first (no gap to judge yet) are fresh");
        assert!(fresh.iter().all(|s| s.point.is_some_and(|p| p.sample.f_set_hz.is_nan())));
        assert_eq!(c.setpoint_hz(), None);
    }

    #[test]
    fn the_setpoint_is_clamped_and_ramp_limited() {
        // the speed law wants more than 30 Hz for 46 rad/s while the shaft turns at 30
        let (mut c, t0) = cycle("mode = \"speed\"\ntarget_omega_rad_s = 46.0\nmax_hz = 30.0\nramp_hz_per_s = 100.0");
        // a drive that follows: it runs at the setpoint written the cycle before (20 Hz at the start)
        let mut drive_hz = 20.0;
        let mut hz = Vec::new();
        for k in 0..40u64 {
            let at = t0 + MS * (10 * k as u32);
            // the shaft's speed moves a little (one value held while the drive ramps 2 Hz is a frozen sensor)
            let step = c.step(&sample(k, 30.0 + 1e-3 * k as f64, drive_hz, 3), at, at + MS);
            c.confirm(true);
            if let Some(p) = step.point {
                hz.push(p.sample.f_set_hz);
                if p.sample.f_set_hz.is_finite() {
                    drive_hz = p.sample.f_set_hz;
                }
            }
        }
        // starts from the drive's 20 Hz and climbs at most 100 Hz/s · 10 ms = 1 Hz a cycle
        assert!((hz[0] - 21.0).abs() < 1e-9, "{hz:?}");
        for w in hz.windows(2) {
            assert!(w[1] - w[0] <= 1.0 + 1e-9, "ramp limited: {hz:?}");
        }
        assert!(hz.iter().all(|&f| f <= 30.0), "clamped to max_hz: {hz:?}");
        assert_eq!(*hz.last().expect("rows"), 30.0, "held at the clamp: {hz:?}");
    }

    #[test]
    fn stale_data_write_nothing_and_move_nothing() {
        let (mut c, t0) = cycle("mode = \"manual\"\nfixed_hz = 25.0");
        run(&mut c, t0, 0, 5, 30.0, 3);
        let before = c.setpoint_hz();
        // the counter does not move: the same data again
        let at = t0 + MS * 50;
        let same = c.step(&sample(4, 30.0, 20.0, 3), at, at + MS);
        assert_eq!((same.verdict, same.writes.len(), same.point), (Verdict::Stale, 0, None));
        // the reply took longer than stale_ms
        let at = t0 + MS * 60;
        let late = c.step(&sample(5, 30.0, 20.0, 3), at, at + MS * 51);
        assert_eq!((late.verdict, late.writes.len()), (Verdict::Stale, 0));
        // a gap longer than stale_ms since the sample before
        let at = t0 + MS * 200;
        let gap = c.step(&sample(6, 30.0, 20.0, 3), at, at + MS);
        assert_eq!((gap.verdict, gap.writes.len()), (Verdict::Stale, 0));
        assert!(c.confirm(true).is_none(), "nothing to confirm");
        assert_eq!(c.setpoint_hz(), before, "the law held");
        // replies 30 ms late at a 10 ms poll: each within stale_ms (50) of its request, and each request within it
        // of the one before, yet readiness sees the data 70 ms old before each reply: stale, for writing too
        let (mut c, t0) = cycle("mode = \"manual\"\nfixed_hz = 25.0");
        run(&mut c, t0, 0, 5, 30.0, 3);
        for k in 0..5u64 {
            let at = t0 + MS * (80 + 40 * k as u32);
            let late = c.step(&sample(5 + k, 30.0, 20.0, 3), at, at + MS * 30);
            assert_eq!((late.verdict, late.writes.len()), (Verdict::Stale, 0), "reply {k}");
        }
        // prompt again: fresh from the first prompt reply on (its request within stale_ms of the one before)
        let at = t0 + MS * 260;
        assert_eq!(c.step(&sample(10, 30.0, 20.0, 3), at, at + MS).verdict, Verdict::Fresh);
        // a counter that runs backwards
        let back = c.step(&sample(1, 30.0, 20.0, 3), at + MS * 10, at + MS * 11);
        assert_eq!((back.verdict, back.writes.len()), (Verdict::CounterBackwards(1), 0));
        // a jump no plant makes
        let (mut c, t0) = cycle("mode = \"manual\"\nfixed_hz = 25.0");
        run(&mut c, t0, 0, 3, 30.0, 3);
        let at = t0 + MS * 30;
        let jump = c.step(&sample(3, 900.0, 20.0, 3), at, at + MS);
        assert!(matches!(jump.verdict, Verdict::Rejected(Rejected::Jump { .. })), "{jump:?}");
        assert!(jump.writes.is_empty());
    }

    #[test]
    fn the_watchdog_changes_every_watchdog_ms_and_writes_wait_otherwise() {
        let (mut c, t0) = cycle("mode = \"manual\"\nfixed_hz = 20.0");
        let steps = run(&mut c, t0, 0, 51, 30.0, 3);
        // the setpoint equals the drive's 20 Hz from the start: after the first write only the watchdog is due
        let writes: Vec<(usize, (f64, u16, u16))> =
            steps.iter().enumerate().filter_map(|(k, s)| written(s).map(|w| (k, w))).collect();
        let at: Vec<usize> = writes.iter().map(|(k, _)| *k).collect();
        assert_eq!(at, vec![1, 11, 21, 31, 41], "a write every 100 ms (10 cycles), none between");
        let dog: Vec<u16> = writes.iter().map(|(_, w)| w.2).collect();
        assert_eq!(dog, vec![1, 2, 3, 4, 5], "a new watchdog value each time");
        assert!(writes.iter().all(|(_, w)| (w.0 - 20.0).abs() < 1e-9 && w.1 == control::RUN));
        assert!(
            steps[2..].iter().all(|s| s.point.is_some_and(|p| p.sample.f_set_hz == 20.0)),
            "an unchanged setpoint counts as written"
        );
    }

    #[test]
    fn a_failed_write_is_sent_whole_again() {
        let (mut c, t0) = cycle("mode = \"manual\"\nfixed_hz = 20.0");
        let at = |k: u32| t0 + MS * (10 * k);
        c.step(&sample(0, 30.0, 20.0, 3), at(0), at(0) + MS);
        let first = c.step(&sample(1, 30.0, 20.0, 3), at(1), at(1) + MS);
        assert_eq!(written(&first).map(|w| w.2), Some(1));
        assert!(c.confirm(false).is_none(), "a failed write confirms nothing");
        let again = c.step(&sample(2, 30.0, 20.0, 3), at(2), at(2) + MS);
        assert_eq!(written(&again).map(|w| w.2), Some(1), "sent again, the watchdog not counted as changed");
        assert!(c.confirm(true).is_some());
        let quiet = c.step(&sample(3, 30.0, 20.0, 3), at(3), at(3) + MS);
        assert!(quiet.writes.is_empty());
    }

    #[test]
    fn a_tripped_drive_ramps_down_and_a_reset_goes_out_once() {
        let (mut c, t0) = cycle("mode = \"manual\"\nfixed_hz = 20.0\nramp_hz_per_s = 100.0");
        run(&mut c, t0, 0, 3, 30.0, 3);
        let tripped = run(&mut c, t0, 3, 5, 30.0, status::FAULT | status::READY);
        assert!(c.tripped());
        let hz: Vec<f64> = tripped.iter().filter_map(written).map(|w| w.0).collect();
        assert!(hz.windows(2).all(|w| w[1] < w[0]) && hz.len() == 5, "towards 0 Hz, ramp limited: {hz:?}");
        assert!(tripped.iter().filter_map(written).all(|w| w.1 == 0), "no RUN to a tripped drive (issue 29)");
        c.command(Commands { target_omega_rad_s: 0.0, reset_requested: true });
        let at = t0 + MS * 80;
        let reset = c.step(&sample(8, 30.0, 20.0, 3), at, at + MS);
        assert_eq!(written(&reset).map(|w| w.1), Some(control::RUN | control::FAULT_RESET));
        assert_eq!(c.confirm(true).map(|x| x.reset_sent), Some(true));
        let at = t0 + MS * 90;
        let after = c.step(&sample(9, 30.0, 20.0, 3), at, at + MS);
        assert_eq!(written(&after).map(|w| w.1), Some(control::RUN), "the reset bit is dropped the next write");
        // a reset to a drive that still reports its fault goes out without RUN, and RUN follows once it is ready
        run(&mut c, t0, 10, 3, 30.0, status::FAULT);
        c.command(Commands { target_omega_rad_s: 0.0, reset_requested: true });
        let at = t0 + MS * 130;
        let reset = c.step(&sample(13, 30.0, 20.0, status::FAULT), at, at + MS);
        assert_eq!(written(&reset).map(|w| w.1), Some(control::FAULT_RESET));
        assert!(c.confirm(true).is_some());
        let at = t0 + MS * 140;
        let not_ready = c.step(&sample(14, 30.0, 20.0, 0), at, at + MS);
        assert_eq!(written(&not_ready).map(|w| w.1), Some(0), "not ready: still no RUN");
        assert!(c.confirm(true).is_some());
        let at = t0 + MS * 150;
        let ready = c.step(&sample(15, 30.0, 20.0, status::READY), at, at + MS);
        assert_eq!(written(&ready).map(|w| w.1), Some(control::RUN));
        // a trip that clears on the drive's side stays latched: no RUN until a reset
        run(&mut c, t0, 16, 2, 30.0, status::FAULT | status::READY);
        let cleared = run(&mut c, t0, 18, 3, 30.0, status::READY | status::RUNNING);
        assert!(c.tripped(), "latched");
        assert!(cleared.iter().filter_map(written).all(|w| w.1 == 0), "no RUN from the service itself");
        c.command(Commands { target_omega_rad_s: 0.0, reset_requested: true });
        let at = t0 + MS * 210;
        let reset = c.step(&sample(21, 30.0, 20.0, status::READY), at, at + MS);
        assert_eq!(written(&reset).map(|w| w.1), Some(control::RUN | control::FAULT_RESET));
        assert!(!c.tripped());
        // monitor mode ignores a reset
        let (mut m, _) = cycle("mode = \"monitor\"");
        m.command(Commands { target_omega_rad_s: 1.0, reset_requested: true });
        assert_eq!(m.reset, None);
    }

    /// A reset asked for just before the link dropped (a reviewer's run: the drive tripped on the lost link, and
    /// when the link came back 5.8 s later the old request cleared that trip and RUN followed 5 ms later): it lapses,
    /// and the trip seen after it stays latched. A reset's bit stays on while the drive still shows its fault, so a
    /// gateway that forwards the latest values every few polls passes it on.
    #[test]
    fn a_reset_lapses_over_a_link_gap_and_its_bit_stays_on_while_the_fault_shows() {
        let (mut c, t0) = cycle("mode = \"manual\"\nfixed_hz = 20.0\nramp_hz_per_s = 100.0");
        let running = status::READY | status::RUNNING;
        run(&mut c, t0, 0, 5, 30.0, running);
        c.command(Commands { target_omega_rad_s: 0.0, reset_requested: true });
        // one reply comes (stale: the counter did not move), then nothing for 5.8 s
        let at = t0 + MS * 50;
        assert_eq!(c.step(&sample(4, 30.0, 20.0, running), at, at + MS).verdict, Verdict::Stale);
        let back = run(&mut c, t0, 585, 3, 30.0, status::COMM_LOSS_TRIP | status::READY);
        assert!(c.take_reset_lapsed(), "said once");
        assert!(!c.take_reset_lapsed());
        assert!(back.iter().filter_map(written).all(|w| w.1 == 0), "no fault reset and no RUN: {back:?}");
        let cleared = run(&mut c, t0, 588, 5, 30.0, status::READY);
        assert!(c.tripped(), "the trip after the request is latched");
        assert!(cleared.iter().filter_map(written).all(|w| w.1 == 0), "no RUN from the service itself");
        // a reset now: its bit goes out with every write until the drive shows no fault, then RUN
        c.command(Commands { target_omega_rad_s: 0.0, reset_requested: true });
        let fault = status::FAULT | status::READY;
        let held = run(&mut c, t0, 593, 4, 30.0, fault);
        assert!(held.iter().filter_map(written).all(|w| w.1 == control::FAULT_RESET), "{held:?}");
        let ready = run(&mut c, t0, 597, 2, 30.0, status::READY);
        assert_eq!(ready.iter().filter_map(written).map(|w| w.1).collect::<Vec<_>>(), vec![control::RUN; 2]);
        assert!(!c.tripped());
        // a fault that does not clear: the bit lapses after a second, and the fault is latched again
        c.command(Commands { target_omega_rad_s: 0.0, reset_requested: true });
        let stuck = run(&mut c, t0, 600, 150, 30.0, fault);
        // (the writes that go out: every watchdog change, every 100 ms)
        let bits: Vec<(usize, bool)> = (stuck.iter().enumerate())
            .filter_map(|(k, s)| written(s).map(|w| (k, w.1 & control::FAULT_RESET != 0)))
            .collect();
        let (early, late): (Vec<&(usize, bool)>, Vec<_>) = bits.iter().partition(|(k, _)| *k < 95);
        assert!(early.len() >= 9 && early.iter().all(|b| b.1), "on for the first second: {bits:?}");
        assert!(late.len() >= 4 && late.iter().filter(|(k, _)| *k > 110).all(|b| !b.1), "then off: {bits:?}");
        assert!(!c.take_reset_lapsed(), "it went out: not lapsed unsent");
        assert!(c.tripped());
    }

    /// With `stale_ms` raised to 5 s, a gap of 3.7 s is fresh on both sides; the first write after it is one poll's
    /// ramp step from the drive's read-back, not a whole second's (a reviewer's run: 26.3 → 46.3 Hz at 20 Hz/s).
    #[test]
    fn a_gap_within_a_long_stale_ms_starts_the_ramp_again() {
        let text = "[[drives]]\nname = \"d\"\naddress = \"127.0.0.1:1\"\npoll_ms = 10\nstale_ms = 5000\n\
                    comm_timeout_ms = 10000\n[drives.control]\nmode = \"manual\"\nfixed_hz = 50.0\n";
        let s = super::super::config::parse(text, "test", None).expect("valid config").drives.remove(0);
        let t0 = Instant::now();
        let mut c = DriveCycle::new(&s, crate::estimator::build(&s.estimator, &s.model), t0);
        let before = run(&mut c, t0, 0, 3, 30.0, status::READY | status::RUNNING);
        let last = before.iter().filter_map(written).next_back().expect("writes").0;
        let at = t0 + Duration::from_millis(3730);
        let after = c.step(&sample(373, 30.0, last, status::READY | status::RUNNING), at, at + MS);
        let first = written(&after).expect("writes").0;
        assert!(first - last <= 20.0 * 0.01 + 0.011, "{last} → {first}");
    }

    /// A hostile PLC's read-back of 0 Hz under a shaft still turning at 30 rad/s, after a 0.26 s outage (a gateway
    /// that serves zeros until it has polled the drive again): taken as what the drive runs at, the ramp started
    /// again from it and one write took the drive from 19.9 to 0.2 Hz with RUN on. Now the read-back is not believed:
    /// the setpoint goes on from the last one; and a read-back of 0 that lasts is refused after a second (nothing
    /// written: the drive's watchdog takes over).
    #[test]
    fn a_read_back_of_zero_under_a_turning_shaft_is_not_what_the_drive_runs_at() {
        let (mut c, t0) = cycle("mode = \"manual\"\nfixed_hz = 20.0\nramp_hz_per_s = 20.0");
        let running = status::READY | status::RUNNING;
        let before = run(&mut c, t0, 0, 150, 30.0, running);
        let last = before.iter().filter_map(written).next_back().expect("writes").0;
        assert!((last - 20.0).abs() < 1e-9, "{last}");
        // sample k at k·10 ms after `t0`, the drive's frequency `f`, a live tachometer (it moves a quantum or two)
        let live = |c: &mut DriveCycle, t0: Instant, k: u64, f: f64| {
            let at = t0 + MS * (10 * k as u32);
            let s = c.step(&sample(k, 30.0 + 0.01 * (k % 3) as f64, f, running), at, at + MS);
            c.confirm(true);
            s
        };
        let step = |c: &mut DriveCycle, k: u64, f: f64| live(c, t0, k, f);
        // 0.25 s without replies, three read-backs of 0, then the drive's own again: nothing is written while the
        // ramp would start again from a read-back that is not believed, then it starts from the one that fits
        let zeros: Vec<Step> = (175..178).map(|k| step(&mut c, k, 0.0)).collect();
        assert!(
            zeros.iter().all(|s| s.writes.is_empty()),
            "{:?}",
            zeros.iter().map(|s| &s.verdict).collect::<Vec<_>>()
        );
        let after: Vec<Step> = (178..300).map(|k| step(&mut c, k, 20.0)).collect();
        let hz: Vec<f64> = after.iter().filter_map(written).map(|w| w.0).collect();
        assert!(!hz.is_empty() && hz.iter().all(|&f| (f - 20.0).abs() <= 0.2 + 1e-9), "no dive: {hz:?}");
        // a read-back of 0 for a few polls without a gap: the setpoint goes on from the last one
        let mut short: Vec<Step> = (300..310).map(|k| step(&mut c, k, 0.0)).collect();
        short.extend((310..320).map(|k| step(&mut c, k, 20.0)));
        let hz: Vec<f64> = short.iter().filter_map(written).map(|w| w.0).collect();
        assert!(hz.iter().all(|&f| (f - 20.0).abs() <= 0.2 + 1e-9), "no dive: {hz:?}");
        // a read-back of 0 for longer than a second: refused, nothing written
        let lasting: Vec<Step> = (320..470).map(|k| step(&mut c, k, 0.0)).collect();
        assert!(lasting[120..].iter().all(|s| s.writes.is_empty()), "nothing written after a second");
        assert!(lasting.iter().filter_map(written).all(|w| w.0 >= 19.8), "and no dive before");
        assert!(matches!(lasting[149].verdict, Verdict::Rejected(Rejected::Mismatch { .. })));
        // a service that starts while the read-back reads 0 under the turning shaft writes nothing (restarted from
        // nothing, its first write was min_hz and a ramp step, with RUN)
        let (mut fresh, t1) = cycle("mode = \"manual\"\nfixed_hz = 20.0\nramp_hz_per_s = 20.0");
        let first: Vec<Step> = (0..50).map(|k| live(&mut fresh, t1, k, 0.0)).collect();
        assert!(first.iter().all(|s| s.writes.is_empty()), "nothing written from a read-back not believed");
    }

    /// A gateway that answers reads from a cache refreshed every few polls shows our value before the last: that is
    /// ours, not another master's (a reviewer's 20 ms cache was found "another master" within 5 s).
    #[test]
    fn a_read_back_one_value_behind_is_ours() {
        let (mut c, t0) = cycle("mode = \"manual\"\nfixed_hz = 40.0\nramp_hz_per_s = 100.0");
        let mut k = 0;
        for _ in 0..30 {
            let at = t0 + MS * (10 * k as u32);
            if c.echo_due(at).is_some() {
                let behind = c.recent_watchdogs.back().copied().or(c.confirmed_watchdog).expect("written");
                assert_eq!(c.echo_read(at, Some(&[behind])), None);
            }
            run(&mut c, t0, k, 20, 30.0, 3);
            k += 20;
        }
        assert!(!c.another_master());
    }

    /// A gateway that passes writes on late shows our value from several writes back: ours, not another master's.
    #[test]
    fn a_read_back_six_values_behind_is_ours() {
        let (mut c, t0) = cycle("mode = \"manual\"\nfixed_hz = 40.0\nramp_hz_per_s = 100.0");
        let mut ours: Vec<u16> = Vec::new();
        let mut k = 0;
        for _ in 0..60 {
            let at = t0 + MS * (10 * k as u32);
            if let Some(w) = c.confirmed_watchdog.filter(|w| ours.last() != Some(w)) {
                ours.push(w);
            }
            if c.echo_due(at).is_some() {
                let behind = ours[ours.len().saturating_sub(7)];
                assert_eq!(c.echo_read(at, Some(&[behind])), None);
            }
            run(&mut c, t0, k, 20, 30.0, 3);
            k += 20;
        }
        assert!(ours.len() > 20, "{} values", ours.len());
        assert!(!c.another_master());
    }

    /// The watchdog starts where the service says, and counts on from there.
    #[test]
    fn the_watchdog_starts_where_it_is_told() {
        let (mut c, t0) = cycle("mode = \"manual\"\nfixed_hz = 20.0");
        c.start_watchdog_at(20_000);
        let steps = run(&mut c, t0, 0, 12, 30.0, 3);
        let dog: Vec<u16> = steps.iter().filter_map(|s| written(s).map(|w| w.2)).collect();
        assert_eq!(dog, vec![20_001, 20_002]);
    }

    /// An `i16` watchdog (a PLC's INT) counts up to 32767 and then from 1 again: every write failed to encode from
    /// 32768 on before, and the drive tripped.
    #[test]
    fn a_watchdog_counter_wraps_within_what_its_register_holds() {
        let text = "[[drives]]\nname = \"d\"\naddress = \"127.0.0.1:1\"\npoll_ms = 10\nwatchdog_ms = 100\n\
                    [drives.registers.watchdog]\naddress = 2\ntype = \"i16\"\n\
                    [drives.control]\nmode = \"manual\"\nfixed_hz = 20.0\n";
        let s = super::super::config::parse(text, "test", None).expect("valid config").drives.remove(0);
        let t0 = Instant::now();
        let mut c = DriveCycle::new(&s, crate::estimator::build(&s.estimator, &s.model), t0);
        c.watchdog = 32_766;
        let steps = run(&mut c, t0, 0, 40, 30.0, 3);
        assert!(
            steps.iter().all(|s| s.encode_error.is_none()),
            "{:?}",
            steps.iter().find(|s| s.encode_error.is_some())
        );
        let counted: Vec<u16> = steps.iter().filter_map(written).map(|w| w.2).collect();
        assert!(counted.contains(&32_767) && counted.contains(&1), "{counted:?}");
    }

    /// A PLC that refreshes its registers every third poll (30 ms at a 10 ms poll): each fresh sample is a ramp step
    /// of its own 30 ms, not a new start from the read-back with one poll's step (the setpoint crawled at a sixth of
    /// `ramp_hz_per_s`, 3.1 Hz/s against 20, with a 20 ms PLC at a 5 ms poll). A gap past `stale_ms` is a new start.
    #[test]
    fn a_plc_that_refreshes_every_few_polls_gets_the_whole_ramp() {
        let (mut c, t0) = cycle("mode = \"manual\"\nfixed_hz = 40.0\nramp_hz_per_s = 100.0");
        let mut hz = vec![20.0];
        for k in 0..30u64 {
            let at = t0 + MS * (10 * k as u32);
            // the drive runs at the last setpoint it was sent
            let step = c.step(&sample(k / 3, 30.0, hz[hz.len() - 1], 3), at, at + MS);
            c.confirm(true);
            hz.extend(written(&step).map(|w| w.0));
        }
        let hz = &hz[2..];
        let steps: Vec<f64> = hz.windows(2).map(|w| w[1] - w[0]).collect();
        assert!(steps.iter().all(|d| (d - 3.0).abs() < 0.02), "100 Hz/s over 30 ms a step: {steps:?}");
    }

    /// A drive running under RUN that stops on its own, with no fault bit: it drops ready (a safe torque off, an
    /// enable removed, an emergency stop) or comes back from a power cycle ready but not running, its sample counter
    /// moving on (half of all restarts: a counter past 32768 before). Before, RUN went out as soon as it reported
    /// ready and the drive ran again unasked; now the stop is latched until a reset. A drive that never ran under
    /// RUN (starting up, not ready yet) is not latched.
    #[test]
    fn a_drive_that_stops_on_its_own_is_not_started_again_unasked() {
        let ready = status::READY;
        let running = status::READY | status::RUNNING;
        for (what, off) in [("lost ready", 0), ("came back not running", ready)] {
            let (mut c, t0) = cycle("mode = \"manual\"\nfixed_hz = 20.0\nramp_hz_per_s = 100.0");
            let starting = run(&mut c, t0, 40_000, 3, 30.0, ready);
            assert!(starting.iter().filter_map(written).all(|w| w.1 == control::RUN), "{what}: RUN to a ready drive");
            run(&mut c, t0, 40_003, 5, 30.0, running);
            assert!(!c.tripped(), "{what}: running under RUN");
            run(&mut c, t0, 40_008, 3, 30.0, off);
            let back = run(&mut c, t0, 40_011, 5, 30.0, ready);
            assert!(c.tripped(), "{what}: latched");
            assert!(back.iter().filter_map(written).all(|w| w.1 == 0), "{what}: no RUN from the service itself");
            c.command(Commands { target_omega_rad_s: 0.0, reset_requested: true });
            let again = run(&mut c, t0, 40_016, 2, 30.0, ready);
            assert!(!c.tripped(), "{what}: a reset re-arms it");
            assert_eq!(again.iter().filter_map(written).next_back().map(|w| w.1), Some(control::RUN), "{what}");
        }
        // sent RUN, then a power cycle before it showed running: back ready, not running, its counter moving on,
        // after a stale stretch (no sample for 0.5 s)
        let (mut c, t0) = cycle("mode = \"manual\"\nfixed_hz = 20.0\nramp_hz_per_s = 100.0");
        let starting = run(&mut c, t0, 10, 2, 30.0, ready);
        assert!(starting.iter().filter_map(written).all(|w| w.1 == control::RUN), "RUN to a ready drive");
        let back = run(&mut c, t0, 62, 5, 30.0, ready);
        assert!(c.tripped(), "latched after the stale stretch");
        assert!(back.iter().filter_map(written).all(|w| w.1 == 0), "no RUN from the service itself: {back:?}");
        // while a drive that is slow to show running, with fresh data throughout, is still sent RUN
        let (mut c, t0) = cycle("mode = \"manual\"\nfixed_hz = 20.0\nramp_hz_per_s = 100.0");
        let slow = run(&mut c, t0, 10, 50, 30.0, ready);
        assert!(!c.tripped() && slow.iter().filter_map(written).all(|w| w.1 == control::RUN));
    }

    /// Another master's watchdog values in the read-back: once found, the cycle writes nothing (no setpoint, no
    /// stop) and leaves a clean stop's control word 0 unsent; a reset writes again, ramping from the drive's
    /// read-back. Before any confirmed write, and in monitor mode, nothing is read back.
    #[test]
    fn a_cycle_that_finds_another_master_stands_back_until_a_reset() {
        let (mut m, t0) = cycle("mode = \"monitor\"");
        run(&mut m, t0, 0, 5, 30.0, 3);
        assert_eq!(m.echo_due(t0 + MS * 60), None, "monitor mode reads nothing back");
        let (mut c, t0) = cycle("mode = \"manual\"\nfixed_hz = 40.0\nramp_hz_per_s = 100.0");
        assert_eq!(c.echo_due(t0), None, "nothing written yet: nothing to compare");
        run(&mut c, t0, 0, 3, 30.0, 3);
        let mut k = 3;
        let mut found = None;
        let mut checks = 0;
        for check in 0..6 {
            if found.is_some() {
                break;
            }
            checks += 1;
            let at = t0 + MS * (10 * k as u32);
            let (address, words) = c.echo_due(at).expect("due every 200 ms");
            assert_eq!((address, words), (2, 1), "the default map's watchdog");
            // ours once (arming the check), then another master's value each time
            let ours = c.confirmed_watchdog.expect("confirmed");
            let read = if check == 0 { ours } else { ours.wrapping_add(1000) };
            found = found.or(c.echo_read(at, Some(&[read])));
            run(&mut c, t0, k, 20, 30.0, 3);
            k += 20;
        }
        assert!(matches!(found, Some(Finding::AnotherMaster { .. })), "{found:?}");
        assert_eq!(checks, 4, "ours, then found at the third foreign value");
        assert!(c.another_master() && !c.commanded(), "stood back; a clean stop sends nothing");
        let quiet = run(&mut c, t0, k, 30, 30.0, 3);
        assert!(quiet.iter().all(|s| s.writes.is_empty()), "nothing written while another master writes");
        assert!(quiet.iter().all(|s| s.point.as_ref().is_some_and(|p| p.sample.f_set_hz.is_nan())), "no setpoint");
        c.command(Commands { target_omega_rad_s: 0.0, reset_requested: true });
        let again = run(&mut c, t0, k + 30, 2, 30.0, 3);
        let first = again.first().and_then(written).expect("writes again");
        assert!((20.0..=21.0).contains(&first.0), "from the read-back (20 Hz), not 40 at once: {first:?}");
        assert!(!c.another_master() && c.commanded());
    }
}

//! Whether a decoded sample may be used: the plausible ranges and rates of its values ([`ValidRanges`], from
//! `[drives.limits]`), whether a decoded [`Sample`] lies in them or why it was refused ([`Rejected`]), the sample
//! counter's verdict (moved, unchanged, or impossible) and the rate-of-change plausibility of the measured values.
//! Pure: fed counters, samples and Δt.
//!
//! At the bottom of the service's layout (see [`super`]): it uses no other module of the service.

use crate::modbus::map::Sample;
use crate::recording::Measured;

/// The one staleness verdict, taken when the drive's state is read ([`super::state::DriveState::snapshot`]: the
/// status, readiness, the metrics, MQTT), so that a loop that stopped reads as stale: no fresh sample yet (`age`
/// None), or the last one older than `stale_after`. The poll loop decides a write only from a sample that is itself
/// timely against the same `stale_after` ([`super::cycle::DriveCycle::step`]): one this calls fresh.
pub fn is_stale(age: Option<std::time::Duration>, stale_after: std::time::Duration) -> bool {
    age.is_none_or(|a| a > stale_after)
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
    #[error("{entry} stuck at {value} while the drive's frequency moved {moved_hz:.1} Hz: a frozen sensor")]
    Frozen { entry: &'static str, value: f64, moved_hz: f64 },
    #[error(
        "{entry} reads {value} (no turn, or against the drive) while the drive runs at {f_drive_hz:.1} Hz for \
         {held_s:.1} s: a broken tachometer (wire, coupling, sign) or a stalled motor"
    )]
    NoTurn { entry: &'static str, value: f64, f_drive_hz: f64, held_s: f64 },
    #[error(
        "{entry} reads {value:.1} rad/s while the drive runs at {f_drive_hz:.1} Hz, where the model's pump and \
         motor give {expected:.1} rad/s, for {held_s:.1} s: a tachometer or frequency read-back with the wrong \
         scale (a slipping coupling, a changed unit), or a model whose displacements or pole pairs are wrong"
    )]
    Mismatch { entry: &'static str, value: f64, expected: f64, f_drive_hz: f64, held_s: f64 },
    #[error(
        "speed, both pressures and the drive's frequency unchanged bit for bit for {held_s:.1} s while the drive runs \
         at {f_drive_hz:.1} Hz and the sample counter moves: the PLC's copy of the drive's data stopped (a fieldbus \
         link to the drive, an input task)"
    )]
    ImageFrozen { f_drive_hz: f64, held_s: f64 },
}

impl Rejected {
    /// The entry refused, where one is (a register's name, or a measured column's): its value is left out of the
    /// row the recording keeps. None where the whole sample is refused (not decoded, or an image that stopped).
    pub fn entry(&self) -> Option<&'static str> {
        match self {
            Rejected::Range { entry, .. }
            | Rejected::Jump { entry, .. }
            | Rejected::Frozen { entry, .. }
            | Rejected::NoTurn { entry, .. }
            | Rejected::Mismatch { entry, .. } => Some(entry),
            Rejected::Decode { .. } | Rejected::ImageFrozen { .. } => None,
        }
    }
}

/// How far the drive's frequency may move (Hz) while the speed reads the very same non-zero value: 2 Hz is
/// hundreds of the speed register's steps, which no turning shaft holds still.
pub const FROZEN_SPEED_HZ: f64 = 2.0;

/// How long (s) the whole process image (speed, both pressures, the drive's frequency) may repeat bit for bit while
/// the drive runs at [`NO_TURN_HZ`] or more and the sample counter moves: a running pump's sensors move by their noise
/// every sample, so a repeated image is a PLC whose copy of the drive's data stopped updating while its own counter
/// runs on. The service wrote on from it for 10 s (a reviewer's PLC), feeding the drive's watchdog.
pub const FROZEN_IMAGE_S: f64 = 1.0;

/// A drive running at least this fast (Hz) turns its motor: the pump's flow has nowhere else to go.
pub const NO_TURN_HZ: f64 = 5.0;
/// How long (s) a speed of 0, or one against the drive's direction, may last while the drive runs at
/// [`NO_TURN_HZ`] or more: a motor breaking away, a drive starting.
pub const NO_TURN_S: f64 = 1.0;

/// A tachometer frozen at a value while the drive's frequency moves (a stuck sensor or PLC value), or reading no
/// turn (0, or against the drive's direction) while the drive runs at [`NO_TURN_HZ`] or more for [`NO_TURN_S`] (a
/// broken wire, a slipped coupling, a reversed sign, or a stalled motor): a speed regulator on it runs the drive to
/// `max_hz`. Exactly 0 is not a frozen value (a stalled motor reads 0 while its drive ramps), only no turn for long.
#[derive(Debug, Default)]
pub struct FrozenSpeed {
    /// The speed held, and the lowest and highest drive frequency seen while it held.
    held: Frozen,
    /// The inlet pressure likewise: a pressure stuck inside its range (350 bar) read as a load of 175 N·m, and the
    /// speed law's feed-forward kicked the setpoint up 10 Hz (35 % overspeed).
    inlet: Frozen,
    /// Since when the speed has read no turn while the drive runs.
    no_turn_since: Option<std::time::Instant>,
    /// The process image (speed, pressures, frequency, bit for bit) and since when it has repeated.
    image: Option<([u64; 4], std::time::Instant)>,
}

impl FrozenSpeed {
    /// The last sample showed no turn while the drive runs, not yet for [`NO_TURN_S`]: a motor breaking away, or
    /// a tachometer failing. Nothing may be written from it (the setpoint would climb on a speed of 0).
    pub fn showing_no_turn(&self) -> bool {
        self.no_turn_since.is_some()
    }

    /// The verdict on one sample taken at `at` (before its other checks pass, so that the history holds only fresh
    /// ones).
    pub fn observe(&mut self, omega_rad_s: f64, f_drive_hz: f64, at: std::time::Instant) -> Option<Rejected> {
        let no_turn = f_drive_hz.abs() >= NO_TURN_HZ && omega_rad_s * f_drive_hz.signum() <= 0.0;
        if !no_turn {
            self.no_turn_since = None;
        } else {
            let held_s = at.saturating_duration_since(*self.no_turn_since.get_or_insert(at)).as_secs_f64();
            if held_s > NO_TURN_S {
                return Some(Rejected::NoTurn { entry: "shaft_speed_rpm", value: omega_rad_s, f_drive_hz, held_s });
            }
        }
        self.held.observe("shaft_speed_rpm", omega_rad_s, f_drive_hz)
    }

    /// The verdict on one sample's inlet pressure (bar): frozen while the drive's frequency moves.
    pub fn observe_inlet(&mut self, p_in_bar: f64, f_drive_hz: f64) -> Option<Rejected> {
        self.inlet.observe("inlet_pressure_bar", p_in_bar, f_drive_hz)
    }

    /// The verdict on one sample's whole process image, taken at `at`: frozen once it has repeated bit for bit for
    /// [`FROZEN_IMAGE_S`] while the drive runs at [`NO_TURN_HZ`] or more (a resting sensor may hold one value).
    pub fn observe_image(&mut self, m: &Measured, at: std::time::Instant) -> Option<Rejected> {
        let bits = [m.omega_rad_s, m.p_in_bar, m.p_out_bar, m.f_drive_hz].map(f64::to_bits);
        let running = m.f_drive_hz.abs() >= NO_TURN_HZ;
        match self.image {
            Some((held, since)) if held == bits && running => {
                let held_s = at.saturating_duration_since(since).as_secs_f64();
                (held_s > FROZEN_IMAGE_S).then_some(Rejected::ImageFrozen { f_drive_hz: m.f_drive_hz, held_s })
            }
            _ => {
                self.image = Some((bits, at));
                None
            }
        }
    }
}

/// One value held bit for bit, and the lowest and highest drive frequency seen while it held.
#[derive(Debug, Default)]
struct Frozen(Option<(f64, f64, f64)>);

impl Frozen {
    /// Frozen once the drive's frequency moved more than [`FROZEN_SPEED_HZ`] while `value` (not 0) held.
    fn observe(&mut self, entry: &'static str, value: f64, f_drive_hz: f64) -> Option<Rejected> {
        match &mut self.0 {
            Some((w, lo, hi)) if *w == value && value != 0.0 => {
                (*lo, *hi) = (lo.min(f_drive_hz), hi.max(f_drive_hz));
                let moved_hz = *hi - *lo;
                (moved_hz > FROZEN_SPEED_HZ).then_some(Rejected::Frozen { entry, value, moved_hz })
            }
            _ => {
                self.0 = Some((value, f_drive_hz, f_drive_hz));
                None
            }
        }
    }
}

/// How far the measured speed may lie from the one the drive's frequency gives through the model's pump and motor
/// (with its leakage at the measured pressure difference): this share of it plus [`MISMATCH_RAD_S`]. A hidden
/// leak, a motor's slip and the speed's lag behind a 20 Hz/s ramp stay well inside; a tachometer at half or twice
/// the truth (a slipping coupling, a wrong scale) or a frequency read-back at twice it does not.
pub const MISMATCH_SHARE: f64 = 0.35;
pub const MISMATCH_RAD_S: f64 = 3.0;
/// How long (s) the speed may lie outside that band, every sample, before its samples are refused; from the first
/// such sample nothing is written from them (the speed regulator on a tachometer at half ran the drive to max_hz).
pub const MISMATCH_S: f64 = 1.0;

/// The measured speed against the speed the drive's frequency gives (see [`MISMATCH_SHARE`]); for the writing
/// modes, where a regulator acts on them.
#[derive(Debug, Default)]
pub struct SpeedMatch {
    /// Since when the speed has lain outside the band (kept through returns into it shorter than [`MISMATCH_S`]).
    since: Option<std::time::Instant>,
    /// Since when it has been back inside the band, while `since` stands.
    back_since: Option<std::time::Instant>,
    /// Every sample outside the band in this stretch had the drive's frequency below [`NO_TURN_HZ`] and the shaft
    /// turning faster than that frequency allows: a read-back too low (see [`SpeedMatch::read_back_only`]).
    read_back_low: bool,
    /// The last sample lay outside the band.
    off_now: bool,
}

impl SpeedMatch {
    /// The speed lay outside the band and has not been back in it for [`MISMATCH_S`]: the drive's frequency and the
    /// speed disagree, and the read-back is not to be trusted. Unless [`SpeedMatch::read_back_only`], nothing may be
    /// written from them either. A sample back in the band for less proves nothing: a tachometer at half the speed,
    /// its noise crossing the band's edge one sample in thirty, was written from at each crossing, and the setpoint
    /// crept up 3.4 Hz in 2 s.
    pub fn mismatched(&self) -> bool {
        self.since.is_some()
    }

    /// Whether the disagreement is a read-back below [`NO_TURN_HZ`] under a shaft that turns faster than that
    /// frequency allows (a PLC that puts 0 in the register when its link to the drive fails, a gateway that serves
    /// zeros until it has polled the drive again): the speed regulator may go on from its last setpoint, on the
    /// speed, without the read-back, for [`MISMATCH_S`]. Taken as what the drive runs at, that 0 restarted the ramp
    /// from the bottom, and one write took a running drive from 19.9 to 0.2 Hz (a reviewer's hostile PLC). The
    /// regulator still acts on the speed, ramp limited, from its last setpoint; a tachometer too slow (which would
    /// raise it) holds the writes back for the whole stretch.
    pub fn read_back_only(&self) -> bool {
        self.read_back_low
    }

    /// Whether the last sample lay outside the band (its read-back not to be believed now; one back inside may be,
    /// though the stretch has not ended).
    pub fn off_now(&self) -> bool {
        self.off_now
    }

    /// The verdict on one sample: `expected_rad_s` is the speed the drive's frequency `f_drive_hz` gives, and
    /// `turning_rad_s` the speed [`NO_TURN_HZ`] gives. Only while the drive runs at [`NO_TURN_HZ`] or more, or the
    /// shaft turns faster than that (below both, a motor breaking away or a start proves nothing).
    pub fn observe(
        &mut self,
        omega_rad_s: f64,
        (expected_rad_s, turning_rad_s): (f64, f64),
        f_drive_hz: f64,
        at: std::time::Instant,
    ) -> Option<Rejected> {
        let turning = f_drive_hz.abs() >= NO_TURN_HZ || omega_rad_s.abs() > turning_rad_s.abs();
        let off = turning
            && expected_rad_s.is_finite()
            && (omega_rad_s - expected_rad_s).abs() > MISMATCH_SHARE * expected_rad_s.abs() + MISMATCH_RAD_S;
        self.off_now = off;
        if off {
            // for the whole stretch: one sample of a speed the drive's frequency cannot give (a tachometer at half)
            // holds the writes back until the stretch ends, whatever the read-back does after it
            let low = f_drive_hz.abs() < NO_TURN_HZ;
            self.read_back_low = low && (self.since.is_none() || self.read_back_low);
        }
        if !off {
            if self.since.is_some() {
                let back = *self.back_since.get_or_insert(at);
                if at.saturating_duration_since(back).as_secs_f64() > MISMATCH_S {
                    (self.since, self.back_since, self.read_back_low) = (None, None, false);
                }
            }
            return None;
        }
        self.back_since = None;
        let held_s = at.saturating_duration_since(*self.since.get_or_insert(at)).as_secs_f64();
        (held_s > MISMATCH_S).then_some(Rejected::Mismatch {
            entry: "shaft_speed_rpm",
            value: omega_rad_s,
            expected: expected_rad_s,
            f_drive_hz,
            held_s,
        })
    }
}

impl From<crate::modbus::map::DecodeError> for Rejected {
    fn from(e: crate::modbus::map::DecodeError) -> Rejected {
        Rejected::Decode { entry: e.entry, message: e.message }
    }
}

/// Forward steps a counter must make after it ran backwards before its samples count again: a counter alternating
/// between two values never makes two in a row; a device that restarted (counter back to 0) recovers in a few polls.
pub const SETTLE_STEPS: u8 = 3;

/// What the sample counter says about a read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CounterVerdict {
    /// Moved forward: new data.
    Moved,
    /// Unchanged: the same data as before (stale, not a fault).
    Unchanged,
    /// Ran backwards (or jumped more than half its range): impossible, a device fault.
    Backwards,
    /// Moving forward again after running backwards, not yet [`SETTLE_STEPS`] steps in a row.
    Settling,
}

/// Follows a wrapping sample counter of `bits` bits.
#[derive(Debug, Clone)]
pub struct CounterCheck {
    modulus: u64,
    last: Option<u64>,
    /// Forward steps still needed after a backwards one.
    settle: u8,
}

impl CounterCheck {
    /// A counter that wraps after `bits` bits (16 for one register, 32 for two).
    pub fn new(bits: u32) -> CounterCheck {
        CounterCheck { modulus: 1u64 << bits.clamp(1, 63), last: None, settle: 0 }
    }

    pub fn observe(&mut self, counter: u64) -> CounterVerdict {
        let now = counter % self.modulus;
        let Some(last) = self.last.replace(now) else { return CounterVerdict::Moved };
        let delta = (now + self.modulus - last) % self.modulus;
        if delta == 0 {
            CounterVerdict::Unchanged
        } else if delta >= self.modulus / 2 {
            self.settle = SETTLE_STEPS;
            CounterVerdict::Backwards
        } else if self.settle > 0 {
            self.settle -= 1;
            CounterVerdict::Settling
        } else {
            CounterVerdict::Moved
        }
    }
}

/// The largest plausible rates of change of the measured values (`[drives.limits]`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RateLimits {
    pub pressure_bar_per_s: f64,
    pub speed_rad_per_s2: f64,
    pub frequency_hz_per_s: f64,
}

/// Plausible ranges of decoded values; anything outside (or non-finite) is rejected before the estimator.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ValidRanges {
    pub min_pressure_bar: f64,
    pub max_pressure_bar: f64,
    pub max_speed_rad_s: f64,
    pub max_frequency_hz: f64,
    /// The largest plausible rates of change between samples.
    pub rates: RateLimits,
}

/// Refuses a sample with a value outside `ranges`, naming its register entry (the speed in the register's rpm).
pub fn out_of_range(sample: &Sample, ranges: &ValidRanges) -> Option<Rejected> {
    let m = &sample.measured;
    let pressures = ranges.min_pressure_bar..=ranges.max_pressure_bar;
    let checks = [
        ("inlet_pressure_bar", m.p_in_bar, pressures.contains(&m.p_in_bar)),
        ("outlet_pressure_bar", m.p_out_bar, pressures.contains(&m.p_out_bar)),
        ("shaft_speed_rpm", crate::units::rad_s_to_rpm(m.omega_rad_s), m.omega_rad_s.abs() <= ranges.max_speed_rad_s),
        (
            "drive_frequency_hz",
            m.f_drive_hz,
            (crate::recording::MIN_FREQUENCY_HZ..=ranges.max_frequency_hz).contains(&m.f_drive_hz),
        ),
    ];
    checks.into_iter().find(|(_, _, ok)| !ok).map(|(entry, value, _)| Rejected::Range { entry, value })
}

/// Rejects `next` when a measured value moved faster than `ranges` allow since `prev`, `dt_s` earlier (the caller
/// floors Δt at the poll period, so that a late tick followed by an early one does not turn noise into a jump).
pub fn implausible_jump(prev: &Measured, next: &Measured, dt_s: f64, ranges: &ValidRanges) -> Option<Rejected> {
    let r = &ranges.rates;
    let checks = [
        ("inlet_pressure_bar", prev.p_in_bar, next.p_in_bar, r.pressure_bar_per_s),
        ("outlet_pressure_bar", prev.p_out_bar, next.p_out_bar, r.pressure_bar_per_s),
        ("omega_rad_s", prev.omega_rad_s, next.omega_rad_s, r.speed_rad_per_s2),
        ("drive_frequency_hz", prev.f_drive_hz, next.f_drive_hz, r.frequency_hz_per_s),
    ];
    checks.into_iter().find_map(|(entry, a, b, max_rate)| {
        let rate = (b - a).abs() / dt_s.max(1e-6);
        (rate > max_rate).then_some(Rejected::Jump { entry, from: a, to: b, rate, max_rate })
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use CounterVerdict::*;

    #[test]
    fn a_speed_frozen_while_the_drive_moves_is_rejected_and_a_stalled_one_is_not() {
        let t0 = std::time::Instant::now();
        let at = |k: usize| t0 + std::time::Duration::from_millis(10 * k as u64);
        let mut f = FrozenSpeed::default();
        // the drive ramps 0.5 Hz a sample while the speed reads 20.0: rejected once it moved past 2 Hz
        let verdicts: Vec<bool> = (0..8).map(|k| f.observe(20.0, 10.0 + 0.5 * k as f64, at(k)).is_some()).collect();
        assert_eq!(verdicts, [false, false, false, false, false, true, true, true]);
        // the speed moves again: accepted
        assert!(f.observe(20.1, 14.0, at(8)).is_none());
        // a motor breaking away reads exactly 0 while its drive ramps: not a frozen sensor
        let mut g = FrozenSpeed::default();
        assert!((0..20).all(|k| g.observe(0.0, k as f64, at(k)).is_none()));
        // a steady drive with a steady speed: nothing
        let mut h = FrozenSpeed::default();
        assert!((0..200).all(|k| h.observe(30.0, 25.0, at(k)).is_none()));
    }

    /// A speed that reads 0 (a broken wire) or against the drive (a reversed sign) while the drive runs at 20 Hz:
    /// accepted for [`NO_TURN_S`], then rejected until the speed turns with the drive again. A drive below
    /// [`NO_TURN_HZ`] (starting, stopping) with the motor still: accepted for good.
    #[test]
    fn a_speed_that_shows_no_turn_while_the_drive_runs_is_rejected_after_a_second() {
        let t0 = std::time::Instant::now();
        let at = |k: usize| t0 + std::time::Duration::from_millis(10 * k as u64);
        for reading in [0.0, -31.4] {
            let mut f = FrozenSpeed::default();
            let rejected: Vec<usize> = (0..150).filter(|&k| f.observe(reading, 20.0, at(k)).is_some()).collect();
            assert_eq!(rejected.first(), Some(&101), "{reading}: rejected from 1 s on");
            assert_eq!(rejected.len(), 49, "{reading}: and on");
            assert!(f.observe(31.4, 20.0, at(150)).is_none(), "turning with the drive again");
            assert!(f.observe(31.5, 20.0, at(300)).is_none());
        }
        let mut slow = FrozenSpeed::default();
        assert!((0..500).all(|k| slow.observe(0.0, 4.5, at(k)).is_none()));
    }

    /// A speed off the band (half the expected) is held back at once and refused after [`MISMATCH_S`]; a sample
    /// back in the band now and then (the noise crossing its edge) does not clear it, a second back in it does.
    #[test]
    fn a_speed_off_the_band_is_cleared_only_by_a_second_back_in_it() {
        let t0 = std::time::Instant::now();
        let at = |ms: u64| t0 + std::time::Duration::from_millis(ms);
        let mut m = SpeedMatch::default();
        assert_eq!(m.observe(15.0, (30.0, 7.7), 20.0, at(0)), None);
        assert!(m.mismatched(), "held back at once");
        assert!(m.observe(15.0, (30.0, 7.7), 20.0, at(1100)).is_some(), "refused after a second");
        assert_eq!(m.observe(16.6, (30.0, 7.7), 20.0, at(1110)), None, "inside the band");
        assert!(m.mismatched(), "one sample back in the band proves nothing");
        assert!(m.observe(15.0, (30.0, 7.7), 20.0, at(1120)).is_some(), "off again: still refused");
        for k in 0..=110 {
            m.observe(29.0, (30.0, 7.7), 20.0, at(1130 + 10 * k));
        }
        assert!(!m.mismatched(), "a second back in the band clears it");
        assert!(!m.read_back_only());
        // a read-back of 0 under a shaft that turns (a PLC's 0 for a drive it cannot reach): the read-back is not
        // believed, at once, and the samples are refused after a second; below the speed 5 Hz gives, nothing is said
        let mut m = SpeedMatch::default();
        assert_eq!(m.observe(5.0, (-0.1, 7.7), 0.0, at(0)), None, "a shaft that barely turns proves nothing");
        assert!(!m.mismatched());
        assert_eq!(m.observe(30.0, (-0.1, 7.7), 0.0, at(10)), None);
        assert!(m.mismatched() && m.read_back_only(), "the read-back is not believed");
        assert!(m.observe(30.0, (-0.1, 7.7), 0.0, at(1100)).is_some(), "refused after a second");
        // a tachometer too slow for the drive's frequency is still held back from the first sample
        assert_eq!(
            m.observe(15.0, (30.0, 7.7), 20.0, at(1110)),
            Some(Rejected::Mismatch {
                entry: "shaft_speed_rpm",
                value: 15.0,
                expected: 30.0,
                f_drive_hz: 20.0,
                held_s: 1.1
            })
        );
        assert!(!m.read_back_only());
        // a stretch that began with a tachometer too slow stays held back, whatever the read-back does next (a
        // tachometer at half, then a read-back of 0: the regulator would raise the setpoint on the slow tachometer)
        let mut m = SpeedMatch::default();
        assert_eq!(m.observe(15.0, (30.0, 7.7), 20.0, at(0)), None);
        assert_eq!(m.observe(15.0, (-0.1, 7.7), 0.0, at(10)), None);
        assert!(m.mismatched() && !m.read_back_only());
    }

    #[test]
    fn a_counter_that_wraps_moves_on() {
        let mut c = CounterCheck::new(16);
        assert_eq!(c.observe(65534), Moved);
        assert_eq!(c.observe(65535), Moved);
        assert_eq!(c.observe(4), Moved);
        assert_eq!(c.observe(4), Unchanged);
    }

    #[test]
    fn backwards_and_alternating_counters_never_count() {
        let mut c = CounterCheck::new(16);
        c.observe(500);
        let backwards: Vec<_> = (0..10).map(|i| c.observe(400 - i)).collect();
        assert!(backwards.iter().all(|v| *v == Backwards), "{backwards:?}");
        let mut c = CounterCheck::new(16);
        c.observe(500);
        let alternating: Vec<_> = (0..10).map(|i| c.observe(100 + i % 2)).collect();
        assert!(!alternating.contains(&Moved), "{alternating:?}");
        assert!(alternating.contains(&Backwards));
        // a device that restarted from 0 counts again after SETTLE_STEPS forward steps
        let mut c = CounterCheck::new(16);
        c.observe(500);
        assert_eq!(c.observe(0), Backwards);
        let after: Vec<_> = (1..=5).map(|i| c.observe(i)).collect();
        assert_eq!(after, [Settling, Settling, Settling, Moved, Moved]);
    }

    fn ranges() -> ValidRanges {
        ValidRanges {
            min_pressure_bar: -1.0,
            max_pressure_bar: 400.0,
            max_speed_rad_s: 1000.0,
            max_frequency_hz: 400.0,
            rates: RateLimits { pressure_bar_per_s: 1e5, speed_rad_per_s2: 1e4, frequency_hz_per_s: 1e3 },
        }
    }

    /// A decoded sample's measured columns (no time or setpoint stamped yet).
    fn decoded() -> Measured {
        Measured {
            t_s: f64::NAN,
            f_set_hz: f64::NAN,
            p_in_bar: 50.0,
            p_out_bar: 3.0,
            omega_rad_s: 40.0,
            f_drive_hz: 25.0,
            drive_power_w: f64::NAN,
        }
    }

    #[test]
    fn a_value_out_of_range_is_refused_by_its_register_entry() {
        let measured = decoded();
        let sample = |measured| Sample { measured, status_word: 3, counter: 1 };
        assert_eq!(out_of_range(&sample(measured), &ranges()), None);
        let r = out_of_range(&sample(Measured { p_out_bar: 650.0, ..measured }), &ranges());
        assert_eq!(r, Some(Rejected::Range { entry: "outlet_pressure_bar", value: 650.0 }));
        // the speed in the register's unit, rpm
        let r = out_of_range(&sample(Measured { omega_rad_s: -1100.0, ..measured }), &ranges());
        let Some(Rejected::Range { entry: "shaft_speed_rpm", value }) = r else { panic!("{r:?}") };
        assert!((value - crate::units::rad_s_to_rpm(-1100.0)).abs() < 1e-9);
        let r = out_of_range(&sample(Measured { f_drive_hz: -3.0, ..measured }), &ranges());
        assert_eq!(r, Some(Rejected::Range { entry: "drive_frequency_hz", value: -3.0 }));
    }

    #[test]
    fn jumps_beyond_the_rate_are_rejected() {
        let a = decoded();
        let b = Measured { omega_rad_s: 343.0, ..a };
        let r = implausible_jump(&a, &b, 0.01, &ranges());
        assert!(matches!(r, Some(Rejected::Jump { entry: "omega_rad_s", .. })), "{r:?}");
        // the same change over a second is physics
        assert_eq!(implausible_jump(&a, &b, 1.0, &ranges()), None);
        let noisy = Measured { omega_rad_s: 42.0, p_in_bar: 51.0, ..a };
        assert_eq!(implausible_jump(&a, &noisy, 0.001, &ranges()), None);
    }

    /// A process image that repeats bit for bit while the drive runs is frozen after [`FROZEN_IMAGE_S`]; one that
    /// moves by a quantum, or a stopped drive's, is not.
    #[test]
    fn a_process_image_repeated_while_the_drive_runs_is_frozen() {
        let at = std::time::Instant::now();
        let ms = |n: u64| at + std::time::Duration::from_millis(n);
        let running = Measured {
            t_s: 0.0,
            f_set_hz: f64::NAN,
            f_drive_hz: 19.1,
            p_in_bar: 80.3,
            p_out_bar: 2.1,
            omega_rad_s: 30.1,
            drive_power_w: f64::NAN,
        };
        let mut f = FrozenSpeed::default();
        assert_eq!(f.observe_image(&running, ms(0)), None);
        assert_eq!(f.observe_image(&running, ms(1000)), None, "a second is allowed");
        assert!(matches!(f.observe_image(&running, ms(1010)), Some(Rejected::ImageFrozen { .. })));
        // a speed a quantum off starts it again
        let moved = Measured { omega_rad_s: 30.11, ..running };
        assert_eq!(f.observe_image(&moved, ms(1020)), None);
        assert_eq!(f.observe_image(&moved, ms(2000)), None);
        // a stopped drive's sensors may rest on one value
        let stopped = Measured { omega_rad_s: 0.0, f_drive_hz: 0.0, ..running };
        let mut g = FrozenSpeed::default();
        for n in 0..500 {
            assert_eq!(g.observe_image(&stopped, ms(10 * n)), None);
        }
    }
}

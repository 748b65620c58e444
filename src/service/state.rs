//! What each poll loop publishes and the HTTP side, MQTT and the condition checks read: a drive's snapshot, its
//! history ring of rows ([`Point`], also the recording's, columns [`COLUMNS`]), and the commands (target, reset)
//! waiting for the loop. The whole service's state ([`super::ServiceState`]) holds one [`DriveState`] per drive.
//!
//! In the service's layout (see [`super`]) it uses [`super::timing`] alone.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, MutexGuard};
use std::time::Duration;

use serde::Serialize;
use tokio::time::Instant;

use super::timing::TimingStats;
use crate::control::Mode;
use crate::estimator::Estimate;
use crate::recording;
pub use crate::recording::Measured;

/// Locks a mutex whose data are plain values (a poisoned lock is taken over).
pub(crate) fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// As [`lock`], but None instead of waiting when someone holds it.
fn try_lock<T>(m: &Mutex<T>) -> Option<MutexGuard<'_, T>> {
    match m.try_lock() {
        Ok(g) => Some(g),
        Err(std::sync::TryLockError::Poisoned(e)) => Some(e.into_inner()),
        Err(std::sync::TryLockError::WouldBlock) => None,
    }
}

/// One fresh, validated sample with what the service made of it: a row of the recording and of the history.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Point {
    pub sample: Measured,
    pub estimate: Estimate,
    pub status_word: u16,
    /// The speed target the law regulated to in this cycle (speed mode; NaN otherwise): kept with the row so that
    /// the history draws the target as it moved.
    pub target_omega_rad_s: f64,
}

/// The measured and estimated columns together.
const SAMPLE_AND_ESTIMATE: usize = Measured::COLUMNS.len() + Estimate::COLUMNS.len();

/// The recording's columns, in [`Point::values`] order: the measured ones, the estimates, the status word, the
/// target.
pub const COLUMNS: [&str; SAMPLE_AND_ESTIMATE + 2] = recording::concat(
    recording::concat::<{ Measured::COLUMNS.len() }, { Estimate::COLUMNS.len() }, SAMPLE_AND_ESTIMATE>(
        Measured::COLUMNS,
        Estimate::COLUMNS,
    ),
    ["status_word", "target_omega_rad_s"],
);

impl Point {
    pub fn values(&self) -> [f64; COLUMNS.len()] {
        let mut v = [0.0; COLUMNS.len()];
        let m = Measured::COLUMNS.len();
        v[..m].copy_from_slice(&self.sample.values());
        v[m..SAMPLE_AND_ESTIMATE].copy_from_slice(&self.estimate.values());
        v[SAMPLE_AND_ESTIMATE] = f64::from(self.status_word);
        v[SAMPLE_AND_ESTIMATE + 1] = self.target_omega_rad_s;
        v
    }
}

/// Points as columns named [`COLUMNS`], `{"t_s": [...], "f_set_hz": [...], ...}` (a NaN is null): the history's
/// JSON, which the dashboard's charts take as they are.
pub struct PointColumns<'a>(pub &'a [Point]);

impl Serialize for PointColumns<'_> {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeMap;
        let rows: Vec<[f64; COLUMNS.len()]> = self.0.iter().map(Point::values).collect();
        let mut m = s.serialize_map(Some(COLUMNS.len()))?;
        for (i, name) in COLUMNS.iter().enumerate() {
            m.serialize_entry(name, &Column(&rows, i))?;
        }
        m.end()
    }
}

/// Column `.1` of the rows.
struct Column<'a>(&'a [[f64; COLUMNS.len()]], usize);

impl Serialize for Column<'_> {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_seq(self.0.iter().map(|r| r[self.1]))
    }
}

/// The drive's status word, bit by bit.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Default)]
pub struct DriveStatus {
    pub word: u16,
    pub ready: bool,
    pub running: bool,
    pub fault: bool,
    pub comm_loss_trip: bool,
    /// A writing drive that does not follow its setpoints (read-back away from them, or not ready and running, for
    /// longer than its ramp explains): an alarm; the regulator holds its integral meanwhile.
    pub not_following: bool,
    /// Another master writes the drive (its watchdog register read back values this service never wrote): this
    /// service writes nothing until `POST /api/drives/<name>/reset`.
    pub another_master: bool,
}

/// The kinds of failed Modbus call counted apart ([`crate::modbus::client::ClientError::kind`], and the loop's own:
/// `encode`, a setpoint the register cannot hold; `counter`, a sample counter that ran backwards).
pub const ERROR_KINDS: [&str; 7] = {
    // every kind a Modbus call gives but `backoff` (a wait the client chose, not a failed call), then the loop's own
    let k = crate::modbus::client::ClientError::KINDS;
    [k[1], k[2], k[3], k[4], k[5], "encode", "counter"]
};

/// Link health of one drive.
#[derive(Debug, Clone, PartialEq, Serialize, Default)]
pub struct Link {
    pub connected: bool,
    /// No fresh sample (moving sample counter, values in range) for longer than `stale_ms`.
    pub stale: bool,
    pub last_error: Option<String>,
    pub polls: u64,
    pub errors: u64,
    pub reconnects: u64,
    pub rejected_samples: u64,
    pub writes: u64,
    /// Setpoint writes the device refused (an exception) or never answered.
    pub writes_refused: u64,
    /// Reads whose sample counter had not moved; setpoint writes slower than half the poll period; trips seen.
    pub stale_samples: u64,
    pub slow_writes: u64,
    pub trips: u64,
    /// `errors` by kind, in the order of [`ERROR_KINDS`] (`/metrics` only).
    #[serde(skip)]
    pub errors_by_kind: [u64; ERROR_KINDS.len()],
    /// The last writes (3 or more in a row) all failed: the drive is not ready.
    pub writes_failing: bool,
    /// Milliseconds since the last fresh sample; None before the first.
    pub sample_age_ms: Option<f64>,
}

impl Link {
    /// A failed Modbus call (or a loop's own error) of `kind`, one of [`ERROR_KINDS`], with what it said.
    pub fn count_error(&mut self, kind: &str, message: String) {
        self.errors += 1;
        let i = ERROR_KINDS.iter().position(|k| *k == kind);
        debug_assert!(i.is_some(), "error kind {kind} is not in ERROR_KINDS: no errors_total series would count it");
        if let Some(i) = i {
            self.errors_by_kind[i] += 1;
        }
        self.last_error = Some(message);
    }
}

/// Everything known about one drive now: what `/api/status` and the SSE stream show.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DriveSnapshot {
    pub name: String,
    pub mode: Mode,
    pub address: String,
    pub unit_id: u8,
    pub target_omega_rad_s: f64,
    /// The last setpoint written (Hz); None in monitor mode or before the first write.
    pub setpoint_hz: Option<f64>,
    pub tripped: bool,
    pub status: DriveStatus,
    pub link: Link,
    /// The last fresh sample's measured columns; its estimates are `estimate`, its status word `status.word`.
    pub sample: Option<Measured>,
    pub estimate: Option<Estimate>,
    /// The estimate's identification codes in words: J's and B's state with its reason, the load's character.
    pub identification: Option<crate::estimator::Identified>,
    pub timing: TimingStats,
    /// The recorder's health; None while recording is off.
    pub recording: Option<RecordingHealth>,
    /// Where the power goes (src/condition/power.rs), integrated by the condition thread; null while condition
    /// monitoring is off and before its first second. Filled when the snapshot is read, not by the poll loop.
    pub energy: Option<crate::condition::power::EnergyReport>,
    /// Each effect with a limit: its last value, the limit, the alarm and its trend to the limit
    /// (`crate::condition::Tracked`); empty while condition monitoring is off. Filled when read, as `energy`.
    pub condition: Vec<crate::condition::Tracked>,
}

impl DriveSnapshot {
    /// A drive's snapshot before its first poll: who it is, and nothing measured, written or integrated yet.
    pub fn before_first_poll(
        name: String,
        mode: Mode,
        address: String,
        unit_id: u8,
        target_omega_rad_s: f64,
    ) -> DriveSnapshot {
        DriveSnapshot {
            name,
            mode,
            address,
            unit_id,
            target_omega_rad_s,
            setpoint_hz: None,
            tripped: false,
            status: DriveStatus::default(),
            link: Link::default(),
            sample: None,
            estimate: None,
            identification: None,
            timing: TimingStats::default(),
            recording: None,
            energy: None,
            condition: Vec::new(),
        }
    }
}

/// Whether the drive's rows reach the disk (a full disk, say, makes them fail until space returns).
#[derive(Debug, Clone, PartialEq, Serialize, Default)]
pub struct RecordingHealth {
    /// False while rows are failing to be written.
    pub ok: bool,
    /// Write, flush or open failures so far.
    pub errors: u64,
    /// Rows not recorded because of them.
    pub rows_lost: u64,
    pub last_error: Option<String>,
    /// Open recordings lost while written (deleted, their directory removed, or replaced); their rows are in
    /// `rows_lost`.
    pub files_lost: u64,
    /// Old recordings deleted by retention.
    pub files_deleted: u64,
    /// Closed recordings compressed to `.csv.gz` (`recording.compress`).
    pub files_compressed: u64,
}

/// Requests from the HTTP side, taken by the loop at its next cycle.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Commands {
    pub target_omega_rad_s: f64,
    pub reset_requested: bool,
}

/// One drive's shared state.
pub struct DriveState {
    pub name: String,
    pub mode: Mode,
    /// The largest target accepted through the API (rad/s).
    pub max_target_omega_rad_s: f64,
    stale_after: Duration,
    snapshot: Mutex<DriveSnapshot>,
    /// When the last fresh sample arrived, for readiness at query time (a stuck loop still reads as stale): ns
    /// after `epoch`, plus one; 0 = never.
    last_fresh_ns: AtomicU64,
    epoch: Instant,
    history: Mutex<VecDeque<Point>>,
    history_len: usize,
    commands: Mutex<Commands>,
}

impl DriveState {
    pub fn new(
        snapshot: DriveSnapshot,
        max_target_omega_rad_s: f64,
        stale_after: Duration,
        history_len: usize,
    ) -> DriveState {
        DriveState {
            name: snapshot.name.clone(),
            mode: snapshot.mode,
            max_target_omega_rad_s,
            stale_after,
            commands: Mutex::new(Commands { target_omega_rad_s: snapshot.target_omega_rad_s, reset_requested: false }),
            snapshot: Mutex::new(snapshot),
            last_fresh_ns: AtomicU64::new(0),
            // an hour back, so that instants a little before construction still count
            epoch: Instant::now().checked_sub(Duration::from_secs(3600)).unwrap_or_else(Instant::now),
            history: Mutex::new(VecDeque::with_capacity(history_len.min(1 << 16))),
            history_len: history_len.max(1),
        }
    }

    pub fn snapshot(&self) -> DriveSnapshot {
        let mut s = lock(&self.snapshot).clone();
        let (stale, age) = self.freshness();
        s.link.stale = stale;
        s.link.sample_age_ms = age.map(|a| a.as_secs_f64() * 1e3);
        s
    }

    /// Stale or not now, and the age of the last fresh sample.
    fn freshness(&self) -> (bool, Option<Duration>) {
        let ns = self.last_fresh_ns.load(Ordering::Acquire);
        let age = (ns > 0).then(|| (self.epoch + Duration::from_nanos(ns - 1)).elapsed());
        (super::freshness::is_stale(age, self.stale_after), age)
    }

    /// Ready: connected and fresh.
    /// Ready: connected and fresh, and the recording (if on) is being written.
    pub fn ready(&self) -> bool {
        let (connected, recording_ok, writes_ok) = {
            let s = lock(&self.snapshot);
            (s.link.connected, s.recording.as_ref().is_none_or(|r| r.ok), !s.link.writes_failing)
        };
        connected && recording_ok && writes_ok && !self.freshness().0 && !self.not_following() && !self.another_master()
    }

    /// The link is down or the data stale: the part of [`DriveState::ready`] that is the device's.
    pub fn stale_or_down(&self) -> bool {
        !lock(&self.snapshot).link.connected || self.freshness().0
    }

    /// The recording of the drive fails (a full disk, say).
    pub fn recording_failing(&self) -> bool {
        lock(&self.snapshot).recording.as_ref().is_some_and(|r| !r.ok)
    }

    /// Every recent setpoint write failed (the snapshot's `link.writes_failing`).
    pub fn writes_failing(&self) -> bool {
        lock(&self.snapshot).link.writes_failing
    }

    /// The drive does not follow its setpoints (the snapshot's `status.not_following`).
    pub fn not_following(&self) -> bool {
        lock(&self.snapshot).status.not_following
    }

    /// Another master writes the drive (the snapshot's `status.another_master`).
    pub fn another_master(&self) -> bool {
        lock(&self.snapshot).status.another_master
    }

    // The poll thread never waits for a lock the HTTP side may hold: an HTTP worker runs at a lower priority and
    // can be preempted while holding one, which would stall a real-time loop (priority inversion). So the loop's
    // calls below only try the lock, and the loop tries again next cycle.

    /// Replaces the snapshot; false (nothing done) when a reader holds it right now.
    pub fn publish(&self, snapshot: DriveSnapshot) -> bool {
        try_lock(&self.snapshot).map(|mut s| *s = snapshot).is_some()
    }

    /// Lock-free.
    pub fn mark_fresh(&self, at: Instant) {
        let ns = u64::try_from(at.saturating_duration_since(self.epoch).as_nanos()).unwrap_or(u64::MAX - 1);
        self.last_fresh_ns.store(ns + 1, Ordering::Release);
    }

    /// Moves `points` into the history ring, oldest first; leaves them in `points` when a reader holds the ring.
    pub fn push_history(&self, points: &mut Vec<Point>) {
        let Some(mut h) = try_lock(&self.history) else { return };
        for p in points.drain(..) {
            if h.len() >= self.history_len {
                h.pop_front();
            }
            h.push_back(p);
        }
    }

    /// The points of the last `seconds`, at most `max_points` of them (evenly thinned, the newest kept).
    pub fn history(&self, seconds: f64, max_points: usize) -> Vec<Point> {
        let h = lock(&self.history);
        let Some(last) = h.back() else { return Vec::new() };
        let from = last.sample.t_s - seconds;
        let start = h.partition_point(|p| p.sample.t_s < from);
        let n = h.len() - start;
        let stride = n.div_ceil(max_points.max(1)).max(1);
        // walk back from the newest so that it is always included
        let mut out: Vec<Point> = (0..n).rev().step_by(stride).map(|i| h[start + i]).collect();
        out.reverse();
        out
    }

    /// Sets the speed target (already validated).
    pub fn set_target(&self, omega_rad_s: f64) {
        lock(&self.commands).target_omega_rad_s = omega_rad_s;
        lock(&self.snapshot).target_omega_rad_s = omega_rad_s;
    }

    pub fn request_reset(&self) {
        lock(&self.commands).reset_requested = true;
    }

    /// The current commands, a pending reset taken (handed to the loop once); None when the HTTP side holds them
    /// right now.
    pub fn take_commands(&self) -> Option<Commands> {
        let mut c = try_lock(&self.commands)?;
        let out = *c;
        c.reset_requested = false;
        Some(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn point(t: f64) -> Point {
        let estimate = Estimate {
            omega_hat_rad_s: 1.0,
            load_hat_nm: 2.0,
            inertia_hat_kg_m2: 3.0,
            viscous_hat_nm_s_rad: 4.0,
            inertia_sd_kg_m2: 5.0,
            viscous_sd_nm_s_rad: 6.0,
            inertia_identified: 1.0,
            viscous_identified: -2.0,
            load_character: 5.0,
        };
        let sample = Measured {
            t_s: t,
            f_set_hz: f64::NAN,
            f_drive_hz: 7.0,
            p_in_bar: 8.0,
            p_out_bar: 9.0,
            omega_rad_s: 10.0,
            drive_power_w: 12.0,
        };
        Point { sample, estimate, status_word: 11, target_omega_rad_s: 13.0 }
    }

    #[test]
    fn one_shape_for_the_row_the_recording_and_the_history() {
        let m = Measured::COLUMNS.len();
        assert_eq!(COLUMNS[m..m + 9], recording::ESTIMATE_COLUMNS, "the estimator's columns are the recording's");
        assert!(COLUMNS.iter().all(|c| recording::KNOWN_COLUMNS.contains(c)), "every column is the contract's");
        let p = point(0.5);
        let json = serde_json::to_value(PointColumns(&[p, point(0.6)])).expect("serialises");
        let obj = json.as_object().expect("an object");
        assert_eq!(obj.len(), COLUMNS.len());
        for (name, v) in COLUMNS.iter().zip(p.values()) {
            let first = &obj[*name][0];
            if v.is_nan() {
                assert!(first.is_null(), "{name}: NaN is null");
            } else {
                assert_eq!(first.as_f64(), Some(v), "{name}");
            }
        }
        assert_eq!(obj["t_s"][1].as_f64(), Some(0.6));
        let snapshot_sample = serde_json::to_value(p.sample).expect("serialises");
        let mut keys: Vec<&str> = snapshot_sample.as_object().expect("object").keys().map(String::as_str).collect();
        keys.sort_unstable();
        let mut want = Measured::COLUMNS.to_vec();
        want.sort_unstable();
        assert_eq!(keys, want, "the snapshot's sample carries the measured columns only");
    }

    fn state(history_len: usize) -> DriveState {
        let snap = DriveSnapshot::before_first_poll("d".into(), Mode::Monitor, "x:1".into(), 1, 0.0);
        DriveState::new(snap, 100.0, Duration::from_millis(50), history_len)
    }

    #[test]
    fn history_ring_keeps_the_newest_and_thins_evenly() {
        let d = state(100);
        for k in 0..250 {
            let mut pending = vec![point(k as f64 * 0.01)];
            d.push_history(&mut pending);
            assert!(pending.is_empty());
        }
        let all = d.history(1e9, 10_000);
        assert_eq!(all.len(), 100);
        assert!((all[0].sample.t_s - 1.5).abs() < 1e-9);
        let last_half_s = d.history(0.505, 10_000);
        assert_eq!(last_half_s.len(), 51);
        let thin = d.history(1e9, 10);
        assert_eq!(thin.len(), 10);
        assert!((thin[9].sample.t_s - 2.49).abs() < 1e-9, "the newest is kept");
    }

    #[test]
    fn stale_until_fresh_and_again_after_the_limit() {
        let d = state(10);
        let mut s = d.snapshot();
        assert!(s.link.stale);
        s.link.connected = true;
        assert!(d.publish(s));
        assert!(!d.ready());
        d.mark_fresh(Instant::now());
        assert!(d.ready());
        let earlier = Instant::now().checked_sub(Duration::from_millis(60)).expect("the clock runs");
        d.mark_fresh(earlier);
        assert!(!d.ready(), "no fresh sample for 60 ms > 50 ms");
        assert!(d.snapshot().link.stale);
    }

    #[test]
    fn every_kind_of_failed_call_the_loop_counts_has_its_series() {
        use crate::modbus::client::ClientError;
        let counted = ClientError::KINDS.iter().filter(|k| **k != "backoff");
        for kind in counted.chain(&["encode", "counter"]) {
            let mut link = Link::default();
            link.count_error(kind, String::new());
            assert_eq!(link.errors_by_kind.iter().sum::<u64>(), 1, "{kind} is counted in errors_total{{kind}}");
        }
    }

    #[test]
    fn a_reset_is_handed_over_once() {
        let d = state(10);
        d.request_reset();
        d.set_target(12.0);
        let c = d.take_commands().expect("free");
        assert!(c.reset_requested);
        assert_eq!(c.target_omega_rad_s, 12.0);
        assert!(!d.take_commands().expect("free").reset_requested);
    }

    #[test]
    fn the_loop_side_never_waits_for_a_reader() {
        let d = state(10);
        let held = d.snapshot.lock().expect("lock");
        let snap = held.clone();
        assert!(!d.publish(snap.clone()), "a held snapshot is left for next cycle");
        drop(held);
        assert!(d.publish(snap));
        let ring = d.history.lock().expect("lock");
        let mut pending = vec![point(0.0), point(0.01)];
        d.push_history(&mut pending);
        assert_eq!(pending.len(), 2, "kept while the ring is held");
        drop(ring);
        d.push_history(&mut pending);
        assert!(pending.is_empty());
        assert_eq!(d.history(1e9, 100).len(), 2, "in order, nothing lost");
        let commands = d.commands.lock().expect("lock");
        assert!(d.take_commands().is_none());
        drop(commands);
        assert!(d.take_commands().is_some());
    }
}

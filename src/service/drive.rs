//! One drive's poll loop, the I/O around the pure [`DriveCycle`]: batched read → decode ([`crate::modbus::map`]) and
//! validate → [`DriveCycle::step`] → its writes, every `poll_ms`. Publishes a snapshot each cycle, feeds the history
//! ring, the recording and the metrics. What counts as fresh, and that nothing is written from stale data, is the
//! cycle's (see [`super::cycle`]).
//!
//! Each loop runs on an OS thread of its own with a current-thread runtime, paced by a [`Ticker`]: the HTTP side,
//! other drives and the recorder never share its thread, so they cannot delay its ticks.
//!
//! In the service's layout (see [`super`]) it stands on the floors below it: the cycle, the config, a drive's state,
//! the recorder, the metric families, the sample checks and the ticker.

use std::sync::Arc;

use tokio::time::Instant;
use tokio_util::sync::CancellationToken;

use super::config::DriveSettings;
use super::cycle::{DriveCycle, Verdict};
use super::freshness::{Rejected, out_of_range};
use super::owner::Finding;
use super::recorder::Recorder;
use super::state::{DriveSnapshot, DriveState, Link, Point};
use super::timing::{LoopTiming, ThreadSetup, Ticker, TimingStats, use_realtime_priority};
use crate::estimator::Estimator;
use crate::modbus::bus::Connection;
use crate::modbus::client::{ClientError, Loud};
use crate::modbus::map::{Table, decode_sample, read_plan};

/// Everything one drive's loop owns: the link, the pure cycle, and where its results go.
pub struct DriveLoop {
    settings: DriveSettings,
    client: Connection,
    cycle: DriveCycle,
    state: Arc<DriveState>,
    recorder: Option<Recorder>,
    timing: LoopTiming,
    plan: Vec<(Table, u16, u16)>,
    link: Link,
    /// The window's timing statistics, refreshed every [`STATS_EVERY`].
    stats: TimingStats,
    stats_at: Option<Instant>,
    /// Points not yet in the history ring (it was being read when they came).
    pending_history: Vec<Point>,
    /// Where in its period this loop ticks, see [`DriveLoop::stagger`].
    phase: std::time::Duration,
    /// Warnings said lately, per kind (see [`Loud`]).
    loud: Loud,
    /// Setpoint writes that failed one after the other.
    writes_failed_in_row: u32,
    /// The drive reported a trip at the last sample.
    was_tripped: bool,
    /// Where the trip latch outlives the process (`<recordings>/<drive>.tripped`), and whether it holds one now.
    latch_file: Option<(std::path::PathBuf, bool)>,
}

/// How recent a last run's setpoint must be for a new run to go on below it
/// ([`DriveLoop::resume_below_the_last_run`]): a drive's comm-loss watchdog stops it well within this, and a drive
/// that stopped reads back 0, below any setpoint.
const RESUME_WITHIN: std::time::Duration = std::time::Duration::from_secs(60);

/// The last setpoint written in `drive`'s newest recording in `dir`, and how long ago: its file's stamp (the wall
/// clock when it was opened) plus its rows' span. Only a plain file is read, its header, first row and last 64 kB (a
/// run that ended by a crash leaves its file plain; the whole of 64 MB took a second per drive at the start). None
/// without such a file or a written setpoint. Read before the recorder compresses what a run left.
pub(super) fn last_setpoint(dir: &std::path::Path, drive: &str) -> Option<(f64, std::time::Duration)> {
    use std::io::{BufRead, Read, Seek};
    let files = crate::recording::drive_files(dir, drive).ok()?;
    let path = files.last()?;
    let name = path.file_name()?.to_string_lossy().into_owned();
    let (key, compressed) = crate::recording::drive_file_key(&name, drive)?;
    if compressed {
        return None;
    }
    let mut file = std::io::BufReader::new(std::fs::File::open(path).ok()?);
    let (mut header, mut first) = (String::new(), String::new());
    // each line at most what a recording's reader takes (a file without a newline is not read whole)
    let cap = crate::recording::MAX_LINE_BYTES as u64;
    (&mut file).take(cap).read_line(&mut header).ok()?;
    (&mut file).take(cap).read_line(&mut first).ok()?;
    let names: Vec<&str> = header.trim_end().split(',').collect();
    let (t, f) = (names.iter().position(|n| *n == "t_s")?, names.iter().position(|n| *n == "f_set_hz")?);
    let cell = |line: &str, i: usize| line.trim_end().split(',').nth(i).and_then(|c| c.parse::<f64>().ok());
    let first_t = cell(&first, t)?;
    let len = file.get_ref().metadata().ok()?.len();
    file.seek(std::io::SeekFrom::Start(len.saturating_sub(TAIL_BYTES))).ok()?;
    let mut tail = String::new();
    file.take(TAIL_BYTES).read_to_string(&mut tail).ok()?;
    // whole rows only: the tail's first line is the header or cut, and its last may be cut (a kill mid-write)
    let rows: Vec<&str> = tail.lines().skip(1).filter(|l| l.split(',').count() == names.len()).collect();
    let last_t = rows.iter().rev().find_map(|l| cell(l, t))?;
    let last_hz = rows.iter().rev().find_map(|l| cell(l, f).filter(|v| v.is_finite()))?;
    let span = std::time::Duration::try_from_secs_f64(last_t - first_t).ok()?;
    let last_row = std::time::UNIX_EPOCH + std::time::Duration::from_millis(key[0]) + span;
    let ago = std::time::SystemTime::now().duration_since(last_row).unwrap_or_default();
    Some((last_hz, ago))
}

/// How much of a recording's end [`last_setpoint`] reads: some hundreds of rows.
const TAIL_BYTES: u64 = 64 * 1024;

/// Failed setpoint writes in a row after which the drive is not ready: every write is refused.
const WRITES_FAILING_AFTER: u32 = 3;

/// How long a writing drive's loop waits, on a clean stop, for its control word 0 to be confirmed.
pub const STOP_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(1);
/// The pause between two tries of the stop's write.
const STOP_RETRY: std::time::Duration = std::time::Duration::from_millis(20);

/// The longest span the loops' first ticks are spread over (see [`DriveLoop::stagger`]): a cycle takes well under
/// 100 µs of CPU, so 50 loops 200 µs apart no longer meet.
const STAGGER_SPAN: std::time::Duration = std::time::Duration::from_millis(10);

/// How often the jitter percentiles are recomputed (each is a pass over the 1000-period window).
const STATS_EVERY: std::time::Duration = std::time::Duration::from_millis(50);

/// A watchdog start of this process's own (from the clock's nanoseconds and the process id, spread by a
/// multiplicative hash), below 32 000 so that any watchdog register holds it: two masters started together then
/// count far apart, and each sees the other's values as foreign.
fn watchdog_start() -> u16 {
    let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.subsec_nanos());
    let mixed = (nanos ^ std::process::id().rotate_left(16)).wrapping_mul(0x9E37_79B1);
    u16::try_from((mixed >> 16) % 32_000).unwrap_or(0)
}

impl DriveLoop {
    /// `client` is the drive's connection: its own (Modbus TCP) or its turn on a shared RTU line
    /// ([`crate::modbus::bus::Bus::handle`]).
    pub fn new(
        settings: DriveSettings,
        client: Connection,
        estimator: Box<dyn Estimator>,
        state: Arc<DriveState>,
        recorder: Option<Recorder>,
        started: Instant,
    ) -> DriveLoop {
        let mut cycle = DriveCycle::new(&settings, estimator, started);
        cycle.start_watchdog_at(watchdog_start());
        DriveLoop {
            plan: read_plan(&settings.registers),
            timing: LoopTiming::new(settings.poll),
            cycle,
            client,
            state,
            recorder,
            settings,
            link: Link::default(),
            stats: TimingStats::default(),
            stats_at: None,
            pending_history: Vec::with_capacity(16),
            phase: std::time::Duration::ZERO,
            loud: Loud::default(),
            writes_failed_in_row: 0,
            was_tripped: false,
            latch_file: None,
        }
    }

    /// Keeps the trip latch in `<dir>/<drive>.tripped` while it stands, so that it outlives the process: a service
    /// killed while the drive was latched (a crash, an OOM kill) and started again (`restart: unless-stopped`) sent
    /// RUN to the drive as soon as it reported ready. A writing drive whose file is there starts latched.
    pub fn keep_trip_latch_in(&mut self, dir: &std::path::Path) {
        if !self.settings.mode.writes() {
            return;
        }
        // with recording off, nothing else makes the directory
        if let Err(e) = std::fs::create_dir_all(dir) {
            tracing::warn!(drive = %self.settings.name, dir = %dir.display(), error = %e,
                "the trip latch's directory cannot be made: a restart would not know of a trip");
        }
        let path = dir.join(format!("{}.tripped", self.settings.name));
        let latched = path.exists();
        if latched {
            self.cycle.latch_from_before();
            tracing::warn!(drive = %self.settings.name, file = %path.display(),
                "the drive was tripped, and not reset, when this service last ran: no RUN is sent until POST \
                 /api/drives/<name>/reset");
        }
        self.latch_file = Some((path, latched));
    }

    /// Goes on below the setpoint this (writing) drive's last run left in its recording (`last`: [`last_setpoint`]),
    /// where that run ended within [`RESUME_WITHIN`] (a crash, a kill, `restart: unless-stopped`): the first setpoint
    /// of this run is at most it, as after a gap within a run. Started afresh, the first write was the drive's
    /// read-back, and a read-back 1.2–1.4× the truth stepped a drive the last run held at 20.0 Hz to 23.8 and 27.6 Hz
    /// in one write (a reviewer's proxy).
    pub fn resume_below_the_last_run(&mut self, last: Option<(f64, std::time::Duration)>) {
        let Some((hz, ago)) = last else { return };
        if ago <= RESUME_WITHIN {
            self.cycle.resume_below(hz);
            tracing::info!(drive = %self.settings.name, setpoint_hz = hz, ago_s = ago.as_secs_f64(),
                "the last run's setpoint is where this run goes on from, at most");
        }
    }

    /// Writes or removes the latch file where the latch changed (see [`DriveLoop::keep_trip_latch_in`]).
    fn save_trip_latch(&mut self) {
        let Some((path, saved)) = &mut self.latch_file else { return };
        let latched = self.cycle.trip_latched();
        if latched == *saved {
            return;
        }
        let done = if latched {
            std::fs::write(&*path, "tripped: POST /api/drives/<name>/reset re-arms the drive\n")
        } else {
            std::fs::remove_file(&*path)
                .or_else(|e| if e.kind() == std::io::ErrorKind::NotFound { Ok(()) } else { Err(e) })
        };
        match done {
            Ok(()) => *saved = latched,
            Err(e) => {
                let file = path.display().to_string();
                if let Some(held) = self.loud.allow("latch file", Instant::now()) {
                    tracing::warn!(drive = %self.settings.name, file, error = %e, more_since_last = held,
                        "the trip latch could not be kept on disk: a restart would not know of it");
                }
            }
        }
    }

    /// Spreads the loops' ticks: loop `index` of `count` ticks `index/count` of its period (at most of
    /// `STAGGER_SPAN`) after the first. Loops started together would otherwise all wake at the same instant, with
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
        if self.settings.mode.writes() && self.cycle.commanded() {
            rt.block_on(self.stop_drive());
        }
        rt.block_on(self.client.close());
        if let Some(rec) = self.recorder.take() {
            rec.finish();
        }
        tracing::info!(drive = %self.settings.name, "poll loop stopped");
    }

    /// On a clean stop, a drive this service commanded is sent control word 0 (no RUN): it decelerates on its own
    /// ramp now, rather than run unsupervised until its watchdog trips (`comm_timeout_ms`, up to an hour).
    async fn stop_drive(&mut self) {
        let spec = self.settings.registers.control_word;
        let name = &self.settings.name;
        // a cycle cut short by the shutdown may have left a reply in flight on the connection: a fresh one
        let deadline = tokio::time::Instant::now() + STOP_TIMEOUT;
        self.client.close().await;
        let write = async {
            let words = spec.encode(0.0).map_err(|e| e.to_string())?;
            // a link in its reconnect back-off is waited for and tried again within the stop's time, as is one
            // failed try: a SIGTERM during the back-off skipped the stop, and the drive ran on under RUN until its
            // own watchdog (up to an hour)
            let mut last = String::new();
            while tokio::time::Instant::now() < deadline {
                match self.client.write(spec.address, &words).await {
                    Ok(()) => return Ok(()),
                    Err(ClientError::Backoff(wait)) => tokio::time::sleep(wait.max(STOP_RETRY)).await,
                    Err(e) => {
                        last = e.to_string();
                        tokio::time::sleep(STOP_RETRY).await;
                    }
                }
            }
            Err(last)
        };
        match tokio::time::timeout(STOP_TIMEOUT, write).await {
            Ok(Ok(())) => tracing::info!(drive = %name, "stopping: the drive was sent control word 0 (no RUN)"),
            Ok(Err(e)) => tracing::warn!(drive = %name, error = %e,
                "stopping: control word 0 could not be sent; the drive's own watchdog stops it"),
            Err(_) => tracing::warn!(drive = %name, timeout_ms = STOP_TIMEOUT.as_millis() as u64,
                "stopping: control word 0 not confirmed in time; the drive's own watchdog stops it"),
        }
    }

    fn error(&mut self, e: &ClientError) {
        if matches!(e, ClientError::Backoff(_)) {
            return;
        }
        self.link.count_error(e.kind(), e.to_string());
        // what a device says back (an exception, a reply of the wrong form) is loud; a lost link shows as stale
        let kind = e.kind();
        if matches!(kind, "exception" | "protocol")
            && let Some(held) = self.loud.allow(kind, Instant::now())
        {
            tracing::warn!(drive = %self.settings.name, error = %e, more_since_last = held,
                "the device's reply is an error (a Modbus exception, or a reply of the wrong form or length)");
        } else {
            tracing::debug!(drive = %self.settings.name, error = %e, "modbus call failed");
        }
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
        self.timing.start(now);
        self.link.polls += 1;
        if let Some(commands) = self.state.take_commands() {
            self.cycle.command(commands);
        }
        self.check_echo(now).await;

        match self.read().await {
            Err(e) => self.error(&e),
            Ok(blocks) => match decode_sample(&self.settings.registers, &blocks).map_err(Rejected::from) {
                Err(r) => self.reject(&r),
                Ok(sample) => match out_of_range(&sample, &self.settings.ranges) {
                    Some(r) => {
                        self.record_refused(&sample, now, &r);
                        self.reject(&r)
                    }
                    None => {
                        // a good poll: the link may forget its back-off
                        self.client.good_poll();
                        let step = self.cycle.step(&sample, now, Instant::now());
                        if self.cycle.take_reset_lapsed() {
                            tracing::warn!(drive = %self.settings.name,
                                "a requested fault reset lapsed unsent (the drive was not seen fresh within a second \
                                 of the request): POST /api/drives/<name>/reset again once it is");
                        }
                        if let Verdict::Rejected(r) = &step.verdict {
                            self.record_refused(&sample, now, r);
                        }
                        self.act(now, step).await
                    }
                },
            },
        }

        self.link.reconnects = self.client.reconnects();
        self.link.connected = self.client.is_connected();
        self.timing.end(Instant::now());
        self.publish();
    }

    /// Reads the watchdog register back when it is due, before this cycle's sample and writes (see
    /// [`super::owner`]): another master writing the drive is said at WARN, and this service stands back.
    async fn check_echo(&mut self, now: Instant) {
        let Some((address, count)) = self.cycle.echo_due(now) else { return };
        let finding = match self.client.read(Table::Holding, address, count).await {
            Ok(words) => self.cycle.echo_read(now, Some(&words)),
            Err(e) if e.kind() == "exception" => {
                self.error(&e);
                self.cycle.echo_read(now, None)
            }
            Err(e) if e.kind() == "timeout" => {
                self.error(&e);
                self.cycle.echo_timed_out(now)
            }
            // a lost link shows as such; the read-back waits for the next check
            Err(e) => return self.error(&e),
        };
        let name = &self.settings.name;
        match finding {
            Some(Finding::AnotherMaster { read, ours }) => tracing::warn!(drive = %name, register = address,
                read = ?read, ours = ?ours,
                "another master writes this drive, or the drive no longer takes this service's writes (its \
                 watchdog register holds values this service did not write lately): this service stands back and \
                 writes nothing, not even a stop, so the two do not fight; the drive's own watchdog stops it if the \
                 other master does not feed it; POST /api/drives/<name>/reset writes again"),
            Some(Finding::Unavailable(why)) => tracing::warn!(drive = %name, register = address,
                "{why}: another master writing this drive cannot be detected"),
            None => {}
        }
    }

    /// Keeps a refused sample in the recording, its refused entry left out ([`super::cycle::DriveCycle::refused_point`]).
    fn record_refused(&mut self, sample: &crate::modbus::map::Sample, now: Instant, r: &Rejected) {
        if let (Some(rec), Some(point)) = (&self.recorder, self.cycle.refused_point(sample, now, r)) {
            rec.record(point);
        }
    }

    fn reject(&mut self, r: &Rejected) {
        self.link.rejected_samples += 1;
        self.link.last_error = Some(format!("rejected sample: {r}"));
        tracing::debug!(drive = %self.settings.name, reason = %r, "sample rejected");
    }

    fn stale(&mut self) {
        self.link.stale_samples += 1;
    }

    /// Does what a step asks: counts a stale or refused sample; for a fresh one marks the drive fresh, sends the
    /// writes and keeps the row.
    async fn act(&mut self, now: Instant, step: super::cycle::Step) {
        match step.verdict {
            Verdict::Fresh => {}
            Verdict::Stale => return self.stale(),
            Verdict::CounterBackwards(counter) => {
                self.link.count_error("counter", format!("sample counter ran backwards (to {counter})"));
                tracing::debug!(drive = %self.settings.name, counter, "sample counter ran backwards");
                return self.stale();
            }
            Verdict::Rejected(r) => return self.reject(&r),
        }
        self.state.mark_fresh(now);
        if let Some(e) = &step.encode_error {
            self.link.count_error("encode", format!("cannot encode the setpoint: {e}"));
        }
        let Some(mut point) = step.point else { return };
        let mut sent = true;
        let writing = Instant::now();
        for (start, words) in &step.writes {
            self.link.writes += 1;
            if let Err(e) = self.client.write(*start, words).await {
                self.error(&e);
                self.write_failed(&e);
                sent = false;
                break;
            }
        }
        if !step.writes.is_empty() {
            if sent {
                self.writes_failed_in_row = 0;
            }
            self.link.writes_failing = self.writes_failed_in_row >= WRITES_FAILING_AFTER;
            self.note_slow_write(now, writing.elapsed());
        }
        if !sent {
            point.sample.f_set_hz = f64::NAN;
        }
        if let Some(done) = self.cycle.confirm(sent)
            && done.reset_sent
        {
            tracing::info!(drive = %self.settings.name, "fault reset sent");
        }
        self.pending_history.push(point);
        self.state.push_history(&mut self.pending_history);
        if let Some(r) = &self.recorder {
            r.record(point);
        }
    }

    /// A setpoint write refused (or unanswered): counted, said at WARN (rate-limited).
    fn write_failed(&mut self, e: &ClientError) {
        self.writes_failed_in_row = self.writes_failed_in_row.saturating_add(1);
        self.link.writes_refused += 1;
        if let Some(held) = self.loud.allow("write", Instant::now()) {
            tracing::warn!(drive = %self.settings.name, error = %e, more_since_last = held,
                "a setpoint write failed: nothing is taken as written, the next cycle sends it all again");
        }
    }

    /// Writes that take more than half the poll period make the loop overrun: counted, said at WARN with what the
    /// poll rate has become.
    fn note_slow_write(&mut self, cycle_start: Instant, took: std::time::Duration) {
        let poll = self.settings.poll;
        if took <= poll / 2 {
            return;
        }
        self.link.slow_writes += 1;
        if let Some(held) = self.loud.allow("slow write", Instant::now()) {
            let cycle = Instant::now().saturating_duration_since(cycle_start).max(poll);
            tracing::warn!(drive = %self.settings.name, write_ms = took.as_secs_f64() * 1e3,
                poll_ms = poll.as_secs_f64() * 1e3, polls_per_s = 1.0 / cycle.as_secs_f64(), more_since_last = held,
                "the drive answers setpoint writes slowly: the loop overruns its period");
        }
    }

    /// A trip (or its end) is said once, and counted.
    fn note_trip(&mut self) {
        let tripped = self.cycle.tripped();
        if tripped == self.was_tripped {
            return;
        }
        self.was_tripped = tripped;
        let word = self.cycle.status().word;
        if tripped && !self.settings.mode.writes() {
            // a monitor writes nothing: no advice to reset what it may not write (the reset route answers 409)
            self.link.trips += 1;
            tracing::warn!(drive = %self.settings.name, status_word = word,
                "the drive tripped (fault, comm-loss or a restart); monitor mode: its own controls must clear it");
        } else if tripped {
            self.link.trips += 1;
            tracing::warn!(drive = %self.settings.name, status_word = word,
                "the drive tripped (fault, comm-loss or a restart): no RUN is sent and the setpoint ramps to 0 Hz, \
                 also once the drive's own trip clears; POST /api/drives/<name>/reset re-arms it");
        } else {
            tracing::info!(drive = %self.settings.name, status_word = word, "the drive's trip has cleared");
        }
    }

    fn publish(&mut self) {
        self.note_trip();
        self.save_trip_latch();
        let now = Instant::now();
        if self.stats_at.is_none_or(|t| now.saturating_duration_since(t) >= STATS_EVERY) {
            self.stats = self.timing.stats();
            self.stats_at = Some(now);
        }
        self.stats.overruns = self.timing.overruns;
        self.stats.periods = self.timing.periods;
        let recording_health = self.recorder.as_ref().map(|r| r.health.snapshot());
        // skipped when a reader holds it: the next cycle publishes again
        let _ = self.state.publish(DriveSnapshot {
            name: self.settings.name.clone(),
            mode: self.settings.mode,
            address: self.settings.address.clone(),
            unit_id: self.settings.unit_id,
            target_omega_rad_s: self.cycle.target_omega_rad_s(),
            setpoint_hz: self.cycle.setpoint_hz(),
            tripped: self.cycle.tripped(),
            status: super::state::DriveStatus {
                not_following: self.cycle.not_following(),
                another_master: self.cycle.another_master(),
                ..self.cycle.status()
            },
            link: self.link.clone(),
            sample: self.cycle.measured(),
            estimate: self.cycle.estimate(),
            identification: self.cycle.estimate().map(|e| crate::estimator::Identified::of(&e)),
            timing: self.stats,
            recording: recording_health,
            energy: None,
            condition: Vec::new(),
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The last run's setpoint from its plain file's header, first row and tail, a row cut by a kill left out, and
    /// how long ago from the file's stamp and its rows' span; a compressed (closed) file is not read.
    #[test]
    fn the_last_runs_setpoint_comes_from_its_files_tail() {
        let dir = tempfile::tempdir().expect("tmp");
        let now_ms = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).expect("clock").as_millis();
        let stamp = now_ms as u64 - 5_000;
        let mut text = String::from("t_s,f_set_hz,omega_rad_s\n");
        for k in 0..20_000 {
            let hz = if k % 7 == 3 { String::new() } else { format!("{:.3}", 10.0 + k as f64 * 1e-3) };
            text.push_str(&format!("{:.3},{hz},30.0\n", 1.0 + k as f64 * 1e-4));
        }
        text.push_str("3.0001,99.0"); // cut by a kill
        std::fs::write(dir.path().join(format!("pump1-{stamp}.csv")), &text).expect("write");
        let (hz, ago) = last_setpoint(dir.path(), "pump1").expect("found");
        assert!((hz - 29.999).abs() < 1e-9, "the last whole row's setpoint: {hz}");
        // the rows span 2 s after the file was opened 5 s ago: 3 s
        assert!((ago.as_secs_f64() - 3.0).abs() < 0.5, "{ago:?}");
        std::fs::rename(
            dir.path().join(format!("pump1-{stamp}.csv")),
            dir.path().join(format!("pump1-{stamp}.csv.gz")),
        )
        .expect("rename");
        assert_eq!(last_setpoint(dir.path(), "pump1"), None, "a closed, compressed file: the run ended cleanly");
    }
}

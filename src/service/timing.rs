//! Poll-loop timing: the [`Ticker`] that paces a loop on its own thread, and [`LoopTiming`], the period, jitter
//! percentiles and overruns over a sliding window (pure: fed instants).
//!
//! Why not `tokio::time::interval`: tokio's timer wheel has a 1 ms resolution, so a 1 ms loop paced by it wakes
//! anywhere in the millisecond after its deadline (measured: p99 jitter 0.93 ms on an idle machine). The ticker
//! sleeps the thread with `nanosleep` on an absolute schedule, with the thread's timer slack cut from the default
//! 50 µs to 1 µs (Linux), and wakes within tens of microseconds of the deadline.

use std::collections::VecDeque;
use std::time::Duration;

use tokio_util::sync::CancellationToken;

use serde::Serialize;

/// How many periods the percentiles look back over.
pub const WINDOW: usize = 1000;

/// Timing of a periodic loop.
#[derive(Debug, Clone)]
pub struct LoopTiming {
    nominal: Duration,
    periods_s: VecDeque<f64>,
    last_start: Option<tokio::time::Instant>,
    pub overruns: u64,
    /// Every period since the start, in buckets (what `/metrics` exposes as `loop_period_seconds`).
    pub periods: PeriodHistogram,
    /// How the loop's thread is scheduled, once it runs.
    pub thread: ThreadSetup,
}

/// The upper bounds of [`PeriodHistogram`]'s buckets (s): 0.1 ms doubling to ≈ 1.6 s, then +Inf.
pub const PERIOD_BOUNDS_S: [f64; 15] = {
    let mut b = [1e-4; 15];
    let mut i = 1;
    while i < 15 {
        b[i] = b[i - 1] * 2.0;
        i += 1;
    }
    b
};

/// The loop's periods since the start, counted in the buckets of [`PERIOD_BOUNDS_S`] (the last one: beyond them).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct PeriodHistogram {
    pub counts: [u64; PERIOD_BOUNDS_S.len() + 1],
    pub sum_s: f64,
}

impl PeriodHistogram {
    fn observe(&mut self, period_s: f64) {
        let bucket = PERIOD_BOUNDS_S.iter().position(|&b| period_s <= b).unwrap_or(PERIOD_BOUNDS_S.len());
        self.counts[bucket] += 1;
        self.sum_s += period_s;
    }

    pub fn count(&self) -> u64 {
        self.counts.iter().sum()
    }
}

/// How a poll thread is scheduled: what the status reports so that an operator sees what the kernel granted.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Default)]
pub struct ThreadSetup {
    /// The SCHED_FIFO priority in effect; None: normal scheduling.
    pub realtime_priority: Option<u8>,
    /// The thread's timer slack (ns): how late the kernel may wake it to batch wake-ups.
    pub timer_slack_ns: Option<u64>,
}

/// What the status and the metrics report.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Default)]
pub struct TimingStats {
    pub poll_ms: f64,
    pub mean_period_ms: f64,
    pub jitter_p50_ms: f64,
    pub jitter_p99_ms: f64,
    pub overruns: u64,
    #[serde(flatten)]
    pub thread: ThreadSetup,
    /// Every period since the start (`/metrics` only).
    #[serde(skip)]
    pub periods: PeriodHistogram,
}

impl LoopTiming {
    pub fn new(nominal: Duration) -> LoopTiming {
        LoopTiming {
            nominal,
            periods_s: VecDeque::with_capacity(WINDOW),
            last_start: None,
            overruns: 0,
            periods: PeriodHistogram::default(),
            thread: ThreadSetup::default(),
        }
    }

    /// A cycle starts; returns the period since the previous start.
    pub fn start(&mut self, now: tokio::time::Instant) -> Option<Duration> {
        let period = self.last_start.map(|t| now.saturating_duration_since(t));
        self.last_start = Some(now);
        if let Some(p) = period {
            if self.periods_s.len() == WINDOW {
                self.periods_s.pop_front();
            }
            self.periods_s.push_back(p.as_secs_f64());
            self.periods.observe(p.as_secs_f64());
        }
        period
    }

    /// A cycle ends; one that took longer than the period is an overrun.
    pub fn end(&mut self, now: tokio::time::Instant) {
        if let Some(t) = self.last_start
            && now.saturating_duration_since(t) > self.nominal
        {
            self.overruns += 1;
        }
    }

    pub fn stats(&self) -> TimingStats {
        let nominal = self.nominal.as_secs_f64();
        let n = self.periods_s.len();
        let mut jitter: Vec<f64> = self.periods_s.iter().map(|p| (p - nominal).abs()).collect();
        // two selections, O(n): a full sort of the window cost a fifth of a 1 kHz loop's CPU
        let mut pct = |q: f64| {
            if n == 0 {
                return 0.0;
            }
            let k = ((n - 1) as f64 * q).round() as usize;
            *jitter.select_nth_unstable_by(k, f64::total_cmp).1
        };
        let mean = if n == 0 { 0.0 } else { self.periods_s.iter().sum::<f64>() / n as f64 };
        TimingStats {
            poll_ms: nominal * 1e3,
            mean_period_ms: mean * 1e3,
            jitter_p50_ms: pct(0.5) * 1e3,
            jitter_p99_ms: pct(0.99) * 1e3,
            overruns: self.overruns,
            thread: self.thread,
            periods: self.periods,
        }
    }
}

/// The longest single sleep, so that a slow loop still notices a shutdown promptly.
const SLEEP_SLICE: Duration = Duration::from_millis(20);

/// Paces a periodic loop on a thread of its own: ticks on an absolute schedule; a tick missed because a cycle ran
/// long is skipped (the schedule is kept, nothing bunches up).
#[derive(Debug)]
pub struct Ticker {
    period: Duration,
    next: std::time::Instant,
}

impl Ticker {
    /// A ticker whose first tick is `phase` from now. Also sets the calling thread's timer slack (see the module
    /// doc) and returns the slack in effect, where the platform tells.
    pub fn new(period: Duration, phase: Duration) -> (Ticker, Option<u64>) {
        let slack = tighten_timer_slack();
        (Ticker { period: period.max(Duration::from_micros(1)), next: std::time::Instant::now() + phase }, slack)
    }

    /// Blocks until the next tick; false when `shutdown` fired first.
    pub fn wait(&mut self, shutdown: &CancellationToken) -> bool {
        loop {
            if shutdown.is_cancelled() {
                return false;
            }
            let now = std::time::Instant::now();
            if now >= self.next {
                break;
            }
            std::thread::sleep((self.next - now).min(SLEEP_SLICE));
        }
        let now = std::time::Instant::now();
        self.next += self.period;
        if self.next <= now {
            let behind = (now - self.next).as_nanos() / self.period.as_nanos() + 1;
            self.next += self.period * u32::try_from(behind).unwrap_or(u32::MAX);
        }
        true
    }
}

/// How much lower than the poll threads the HTTP side runs (a nice value): enough that a flood of requests
/// cannot take the cores from the loops, which need a few percent of one.
pub const HTTP_NICE: i32 = 10;

/// Lowers the calling thread's scheduling priority to [`HTTP_NICE`] (Linux; elsewhere nothing). For the threads of
/// the HTTP runtime: threads started afterwards from another thread keep their own priority.
pub fn lower_thread_priority() {
    #[cfg(target_os = "linux")]
    {
        let tid = rustix::thread::gettid();
        if let Err(e) = rustix::process::setpriority_process(Some(tid), HTTP_NICE) {
            tracing::debug!(error = %e, "cannot lower an HTTP worker's priority");
        }
    }
}

/// Puts the calling thread under SCHED_FIFO at `priority` (1..=99): it then runs as soon as it wakes, ahead of
/// every normal thread (HTTP, recorders, other programs). The kernel's real-time throttling still keeps 5 % of
/// each second for normal threads. Without the privilege (CAP_SYS_NICE, or an `rtprio` limit) it logs a warning
/// and the thread stays at normal priority. Returns whether the priority was granted.
pub fn use_realtime_priority(priority: u8, what: &str) -> bool {
    #[cfg(target_os = "linux")]
    {
        use thread_priority::{
            RealtimeThreadSchedulePolicy, ThreadPriority, ThreadPriorityValue, ThreadSchedulePolicy,
            set_thread_priority_and_policy, thread_native_id,
        };
        let result = ThreadPriorityValue::try_from(priority).map_err(|e| e.to_string()).and_then(|v| {
            set_thread_priority_and_policy(
                thread_native_id(),
                ThreadPriority::Crossplatform(v),
                ThreadSchedulePolicy::Realtime(RealtimeThreadSchedulePolicy::Fifo),
            )
            .map_err(|e| format!("{e:?}"))
        });
        match result {
            Ok(()) => {
                tracing::info!(thread = what, priority, "real-time priority (SCHED_FIFO)");
                true
            }
            Err(e) => {
                tracing::warn!(thread = what, priority, error = %e,
                    "cannot use a real-time priority (needs CAP_SYS_NICE or an rtprio limit); normal priority");
                false
            }
        }
    }
    #[cfg(not(target_os = "linux"))]
    {
        tracing::warn!(thread = what, priority, "real-time priority is only supported on Linux; normal priority");
        false
    }
}

/// Cuts this thread's timer slack to 1 µs: the kernel may otherwise defer a wake-up by up to 50 µs to batch it.
/// Returns the slack in effect (ns), where the platform tells.
fn tighten_timer_slack() -> Option<u64> {
    #[cfg(target_os = "linux")]
    {
        if let Err(e) = rustix::thread::set_current_timer_slack(std::num::NonZeroU64::new(1_000)) {
            tracing::warn!(error = %e, "cannot set the poll thread's timer slack; wake-ups may be up to 50 µs late");
        }
        rustix::thread::current_timer_slack().ok()
    }
    #[cfg(not(target_os = "linux"))]
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_and_overruns() {
        let mut t = LoopTiming::new(Duration::from_millis(10));
        let mut now = tokio::time::Instant::now();
        for k in 0..101u64 {
            t.start(now);
            // every tenth cycle runs long and starts the next one 5 ms late
            let late = if k % 10 == 9 { 15 } else { 10 };
            t.end(now + Duration::from_millis(if late > 10 { 12 } else { 1 }));
            now += Duration::from_millis(late);
        }
        let s = t.stats();
        assert_eq!(s.overruns, 10);
        assert!(s.jitter_p50_ms.abs() < 1e-9, "{s:?}");
        assert!((s.jitter_p99_ms - 5.0).abs() < 1e-9, "{s:?}");
        assert!((s.mean_period_ms - 10.5).abs() < 1e-9, "{s:?}");
    }

    #[test]
    fn ticker_keeps_its_schedule_and_skips_missed_ticks() {
        let shutdown = CancellationToken::new();
        let period = Duration::from_millis(5);
        let (mut t, _) = Ticker::new(period, Duration::ZERO);
        let origin = t.next;
        let start = std::time::Instant::now();
        assert!(t.wait(&shutdown));
        for _ in 0..10 {
            assert!(t.wait(&shutdown));
        }
        // ten periods after the first tick, never earlier
        assert!(start.elapsed() >= period * 10, "{:?}", start.elapsed());
        // a long cycle: the ticks it spans are skipped, the next one is on the original grid
        std::thread::sleep(period * 3 + Duration::from_micros(500));
        let late = std::time::Instant::now();
        assert!(t.wait(&shutdown));
        assert!(t.next > late, "the overdue tick fired, and the next one is after it");
        let on_grid = (t.next - origin).as_nanos() % period.as_nanos();
        assert_eq!(on_grid, 0, "skipped ticks keep the grid");
        shutdown.cancel();
        assert!(!t.wait(&shutdown), "shutdown ends the wait");
    }

    #[test]
    fn a_phase_delays_the_first_tick_and_keeps_the_period() {
        let shutdown = CancellationToken::new();
        let (period, phase) = (Duration::from_millis(4), Duration::from_millis(3));
        let before = std::time::Instant::now();
        let (mut t, _) = Ticker::new(period, phase);
        let first = t.next;
        assert!(first >= before + phase && first <= std::time::Instant::now() + phase);
        assert!(t.wait(&shutdown));
        assert!(std::time::Instant::now() >= first, "not before its phase");
        // the next tick is on the phase's grid: one period on, or more where this thread woke a period late (a loaded
        // machine; asserting exactly one period failed there, 8 ms against 4)
        let after = t.next - first;
        assert!(after >= period && after.as_nanos() % period.as_nanos() == 0, "{after:?}");
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn http_threads_run_at_a_lower_priority() {
        let nice = std::thread::spawn(|| {
            lower_thread_priority();
            let stat = std::fs::read_to_string("/proc/thread-self/stat").expect("stat");
            // nice is field 19; fields after the ")" that ends the name start at field 3
            stat.rsplit_once(')').and_then(|(_, rest)| rest.split_whitespace().nth(19 - 3)?.parse::<i32>().ok())
        })
        .join()
        .expect("thread");
        assert_eq!(nice, Some(HTTP_NICE));
    }
}

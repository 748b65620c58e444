//! Poll-loop timing: period, jitter percentiles and overruns over a sliding window. Pure: fed instants.

use std::collections::VecDeque;
use std::time::Duration;

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
}

/// What the status and the metrics report.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Default)]
pub struct TimingStats {
    pub poll_ms: f64,
    pub mean_period_ms: f64,
    pub jitter_p50_ms: f64,
    pub jitter_p99_ms: f64,
    pub overruns: u64,
}

impl LoopTiming {
    pub fn new(nominal: Duration) -> LoopTiming {
        LoopTiming { nominal, periods_s: VecDeque::with_capacity(WINDOW), last_start: None, overruns: 0 }
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
        jitter.sort_by(f64::total_cmp);
        let pct = |q: f64| if n == 0 { 0.0 } else { jitter[((n - 1) as f64 * q).round() as usize] };
        let mean = if n == 0 { 0.0 } else { self.periods_s.iter().sum::<f64>() / n as f64 };
        TimingStats {
            poll_ms: nominal * 1e3,
            mean_period_ms: mean * 1e3,
            jitter_p50_ms: pct(0.5) * 1e3,
            jitter_p99_ms: pct(0.99) * 1e3,
            overruns: self.overruns,
        }
    }
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
}

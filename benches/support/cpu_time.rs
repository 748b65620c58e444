//! A criterion measurement of the benchmark thread's own CPU time (`CLOCK_THREAD_CPUTIME_ID`) instead of wall time.
//!
//! On a machine shared with other work, wall time counts the time the thread spends waiting for a core; CPU time
//! does not, so medians stay comparable between a busy and an idle machine (caches and memory bandwidth are still
//! shared). Set `HYDROLENS_BENCH_WALL=1` to measure wall time instead. Only for single-threaded benchmarks.

use std::time::Duration;

use criterion::Throughput;
use criterion::measurement::{Measurement, ValueFormatter, WallTime};
use rustix::time::{ClockId, clock_gettime};

/// The criterion configuration the single-threaded benches use: thread CPU time unless `HYDROLENS_BENCH_WALL=1`.
pub fn criterion() -> criterion::Criterion<Clock> {
    let wall = std::env::var("HYDROLENS_BENCH_WALL").is_ok_and(|v| v == "1");
    criterion::Criterion::default().with_measurement(if wall { Clock::Wall } else { Clock::ThreadCpu })
}

/// Which clock a run reads.
pub enum Clock {
    ThreadCpu,
    Wall,
}

fn thread_cpu_ns() -> u64 {
    let t = clock_gettime(ClockId::ThreadCPUTime);
    t.tv_sec as u64 * 1_000_000_000 + t.tv_nsec as u64
}

/// A start mark: CPU nanoseconds or a wall-clock instant.
pub enum Mark {
    Cpu(u64),
    Wall(std::time::Instant),
}

impl Measurement for Clock {
    type Intermediate = Mark;
    type Value = Duration;

    fn start(&self) -> Mark {
        match self {
            Clock::ThreadCpu => Mark::Cpu(thread_cpu_ns()),
            Clock::Wall => Mark::Wall(WallTime.start()),
        }
    }
    fn end(&self, mark: Mark) -> Duration {
        match mark {
            Mark::Cpu(start) => Duration::from_nanos(thread_cpu_ns().saturating_sub(start)),
            Mark::Wall(start) => WallTime.end(start),
        }
    }
    fn add(&self, a: &Duration, b: &Duration) -> Duration {
        *a + *b
    }
    fn zero(&self) -> Duration {
        Duration::ZERO
    }
    fn to_f64(&self, value: &Duration) -> f64 {
        value.as_nanos() as f64
    }
    fn formatter(&self) -> &dyn ValueFormatter {
        &NanosFormatter
    }
}

/// Formats nanoseconds as criterion's wall-time formatter does, with decimal rates (elem/s, MB/s).
struct NanosFormatter;

fn per_second(amount: f64, typical_ns: f64, values: &mut [f64], units: [&'static str; 4]) -> &'static str {
    let rate = amount * 1e9 / typical_ns;
    let (divisor, unit) = if rate < 1e3 {
        (1.0, units[0])
    } else if rate < 1e6 {
        (1e3, units[1])
    } else if rate < 1e9 {
        (1e6, units[2])
    } else {
        (1e9, units[3])
    };
    for v in values {
        *v = amount * 1e9 / *v / divisor;
    }
    unit
}

impl ValueFormatter for NanosFormatter {
    fn scale_values(&self, typical_ns: f64, values: &mut [f64]) -> &'static str {
        let (factor, unit) = if typical_ns < 1e3 {
            (1.0, "ns")
        } else if typical_ns < 1e6 {
            (1e-3, "µs")
        } else if typical_ns < 1e9 {
            (1e-6, "ms")
        } else {
            (1e-9, "s")
        };
        for v in values {
            *v *= factor;
        }
        unit
    }

    fn scale_throughputs(&self, typical_ns: f64, throughput: &Throughput, values: &mut [f64]) -> &'static str {
        match *throughput {
            Throughput::Bytes(b) | Throughput::BytesDecimal(b) => {
                per_second(b as f64, typical_ns, values, ["B/s", "KB/s", "MB/s", "GB/s"])
            }
            Throughput::Bits(b) => per_second(b as f64, typical_ns, values, ["b/s", "Kb/s", "Mb/s", "Gb/s"]),
            Throughput::Elements(e) | Throughput::ElementsAndBytes { elements: e, .. } => {
                per_second(e as f64, typical_ns, values, ["elem/s", "Kelem/s", "Melem/s", "Gelem/s"])
            }
        }
    }

    fn scale_for_machines(&self, _values: &mut [f64]) -> &'static str {
        "ns"
    }
}

//! The monitoring service: one poll loop per drive (modbus → estimator → control → modbus), publishing snapshots,
//! a history ring, metrics and recordings for the HTTP side.

pub mod config;
pub mod drive;
pub mod estimators;
pub mod freshness;
pub mod metrics;
pub mod program;
pub mod recorder;
pub mod retention;
pub mod state;
pub mod timing;

use std::sync::Arc;

use tokio::time::Instant;
use tokio_util::sync::CancellationToken;

pub use config::{ConfigError, DriveSettings, Settings};
pub use state::{DriveSnapshot, DriveState, Point, ServiceState};

use drive::DriveLoop;
use metrics::Metrics;
use recorder::Recorder;
use state::{DriveStatus, Link};
use timing::TimingStats;

/// The running poll loops.
pub struct Service {
    pub state: Arc<ServiceState>,
    threads: Vec<std::thread::JoinHandle<()>>,
}

/// Starts one poll loop per drive, each on a thread of its own (named `poll-<drive>`); they stop when `shutdown`
/// is cancelled.
pub fn start(settings: &Settings, shutdown: CancellationToken) -> std::io::Result<Service> {
    let (metrics, registry) = Metrics::new();
    let started = Instant::now();
    let mut drives = Vec::with_capacity(settings.drives.len());
    let mut loops = Vec::with_capacity(settings.drives.len());
    for d in &settings.drives {
        let history_len = (settings.http.history.as_secs_f64() / d.poll.as_secs_f64()).ceil() as usize;
        let snapshot = DriveSnapshot {
            name: d.name.clone(),
            mode: d.mode,
            address: d.address.clone(),
            unit_id: d.unit_id,
            target_omega_rad_s: d.target_omega_rad_s,
            setpoint_hz: None,
            tripped: false,
            status: DriveStatus::default(),
            link: Link::default(),
            sample: None,
            estimate: None,
            timing: TimingStats::default(),
            recording: None,
        };
        let state =
            Arc::new(DriveState::new(snapshot, d.max_target_omega_rad_s(), d.stale_after, history_len.min(1 << 20)));
        let recorder = match &settings.recording.dir {
            Some(dir) => {
                let r = &settings.recording;
                let retention = retention::Retention {
                    // each drive keeps its share of the whole
                    max_bytes: r.max_total_bytes.map(|t| t / settings.drives.len().max(1) as u64),
                    keep: r.keep,
                };
                Some(Recorder::start(dir, &d.name, r.rotate_after, r.max_file_bytes, retention)?)
            }
            None => None,
        };
        let estimator = estimators::build(&d.estimator, &d.model);
        loops.push(DriveLoop::new(d.clone(), estimator, state.clone(), metrics.clone(), recorder, started));
        drives.push(state);
    }
    let state =
        Arc::new(ServiceState { drives, metrics, registry, recording_dir: settings.recording.dir.clone(), started });
    let mut threads = Vec::with_capacity(loops.len());
    let count = loops.len();
    for (index, mut l) in loops.into_iter().enumerate() {
        l.stagger(index, count);
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
        let stop = shutdown.clone();
        let spawned =
            std::thread::Builder::new().name(format!("poll-{}", l.name())).spawn(move || l.run_blocking(&rt, &stop));
        match spawned {
            Ok(t) => threads.push(t),
            Err(e) => {
                // the loops already started must not outlive a failed start
                shutdown.cancel();
                join(threads);
                return Err(e);
            }
        }
    }
    Ok(Service { state, threads })
}

/// Joins poll threads, logging any that panicked.
fn join(threads: Vec<std::thread::JoinHandle<()>>) {
    for t in threads {
        if t.join().is_err() {
            tracing::error!("a poll loop ended abnormally");
        }
    }
}

impl Service {
    /// Waits until every loop has stopped and closed its recording.
    pub async fn wait(self) {
        let threads = self.threads;
        if tokio::task::spawn_blocking(move || join(threads)).await.is_err() {
            tracing::error!("waiting for the poll loops failed");
        }
    }
}

//! The monitoring service: one poll loop per drive (modbus → estimator → control → modbus), publishing snapshots,
//! a history ring, metrics and recordings for the HTTP side. [`start`] starts them and builds the whole service's
//! shared state, [`ServiceState`], which the HTTP side reads.
//!
//! # Layout
//! The service's modules, floor by floor (a module uses only those listed before it; this file uses them all):
//! - [`timing`], [`retention`], [`program`], [`freshness`], [`owner`]: a loop's ticker and timing statistics, the
//!   recordings' retention, the demo's target program, whether a decoded sample may be used, whether another master
//!   writes a drive (PURE); none uses another module of the service.
//! - [`config`], [`state`]: the config file, parsed and validated; one drive's shared state (its snapshot, its
//!   history ring of rows, the commands waiting for its loop).
//! - [`cycle`], [`recorder`], [`condition`]: PURE drive cycle (a validated sample and its time → the writes and the
//!   row); a drive's rows to disk; a drive's condition checks and alarms, and their thread.
//! - [`drive`]: one drive's poll loop, the I/O around the cycle.
//!
//! Its outlets stand above it, in rooms of their own ([`crate::metrics`], [`crate::mqtt`], [`crate::http`]): they
//! read [`ServiceState`] (the drives' snapshots, which count what the loops saw), and an outlet registers its own
//! families in the service's registry ([`ServiceState::registry`]). The poll loops never touch a metric.

pub mod condition;
pub mod config;
pub mod cycle;
pub mod drive;
pub mod freshness;
pub mod owner;
pub mod program;
pub mod recorder;
pub mod retention;
pub mod state;
pub mod timing;

use std::path::PathBuf;
use std::sync::{Arc, Mutex, MutexGuard};

use prometheus_client::registry::Registry;

use tokio::time::Instant;
use tokio_util::sync::CancellationToken;

pub use config::{ConfigError, DriveSettings, Settings};
pub use state::{DriveSnapshot, DriveState, Measured, Point};

use crate::modbus::bus::{Bus, Connection};
use crate::modbus::client::DriveClient;
use drive::DriveLoop;
use recorder::Recorder;
use timing::use_realtime_priority;

/// The running poll loops.
pub struct Service {
    pub state: Arc<ServiceState>,
    threads: Vec<std::thread::JoinHandle<()>>,
}

/// The whole service's shared state.
pub struct ServiceState {
    pub drives: Vec<Arc<DriveState>>,
    /// Each drive's condition checks and alarms, in `drives` order.
    pub conditions: Vec<Arc<condition::DriveCondition>>,
    /// Every family, the drives' and the outlets' (who register theirs when they start); locked only to register
    /// and to encode a scrape, never by a poll loop.
    registry: Mutex<Registry>,
    /// Where recordings are written; None when recording is off.
    pub recording_dir: Option<PathBuf>,
    /// The exclusive lock on the recordings directory (`recorder::lock_dir`), held while the service lives.
    pub recording_lock: Option<Arc<recorder::DirLock>>,
    pub started: Instant,
}

impl ServiceState {
    pub fn drive(&self, name: &str) -> Option<&Arc<DriveState>> {
        self.drives.iter().find(|d| d.name == name)
    }

    pub fn condition(&self, name: &str) -> Option<&Arc<condition::DriveCondition>> {
        self.conditions.iter().find(|c| c.drive == name)
    }

    /// Ready when every drive is connected and fresh.
    pub fn ready(&self) -> bool {
        self.drives.iter().all(|d| d.ready())
    }

    pub fn snapshots(&self) -> Vec<DriveSnapshot> {
        self.drives
            .iter()
            .zip(&self.conditions)
            .map(|(d, c)| {
                let mut s = d.snapshot();
                c.fill(&mut s);
                s
            })
            .collect()
    }

    /// The registry, for an outlet to register its families in.
    pub fn registry(&self) -> MutexGuard<'_, Registry> {
        // a panic while registering or encoding leaves the registry as whole as it was: go on with it
        self.registry.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
    }
}

/// Starts one poll loop per drive, each on a thread of its own (named `poll-<drive>`), and one bus task per RTU
/// line (thread `bus-<port>`) that the drives on it take turns on; they stop when `shutdown` is cancelled.
pub fn start(settings: &Settings, shutdown: CancellationToken) -> std::io::Result<Service> {
    let mut registry = Registry::with_prefix("hydrolens");
    let condition_metrics = condition::ConditionMetrics::register(&mut registry);
    let started = Instant::now();
    let mut drives = Vec::with_capacity(settings.drives.len());
    let mut loops = Vec::with_capacity(settings.drives.len());
    let mut conditions = Vec::with_capacity(settings.drives.len());
    let mut condition_jobs = Vec::new();
    // one writer per recordings directory, taken before anything in it is touched (leftovers, retention)
    let recording_lock = settings.recording.dir.as_deref().map(recorder::DirLock::take).transpose()?.map(Arc::new);
    let buses = buses(settings);
    for d in &settings.drives {
        let state = Arc::new(DriveState::new(
            initial_snapshot(d),
            d.max_target_omega_rad_s(),
            d.stale_after,
            history_len(settings, d).min(1 << 20),
        ));
        // a writing drive's, before the recorder compresses what the last run left
        let last_run = (settings.recording.dir.as_deref())
            .filter(|_| d.mode.writes())
            .and_then(|dir| drive::last_setpoint(dir, &d.name));
        let recorder = recorder_for(settings, d, recording_lock.clone())?;
        tracing::info!(drive = %d.name, method = ?d.estimator.method, "estimator");
        let estimator = crate::estimator::build(&d.estimator, &d.model);
        let connection = connection_for(d, &buses);
        let mut drive = DriveLoop::new(d.clone(), connection, estimator, state.clone(), recorder, started);
        drive.resume_below_the_last_run(last_run);
        match &settings.recording.latch_dir {
            Some(dir) => drive.keep_trip_latch_in(dir),
            None if d.mode.writes() => tracing::warn!(drive = %d.name,
                "no recording.dir: a trip latched while this service runs is not kept across a restart (a service \
                 killed while its drive was latched would send RUN when started again); give recording.dir, even \
                 with recording off"),
            None => {}
        }
        loops.push(drive);
        let cond = Arc::new(condition::DriveCondition::new(&d.name, &d.condition));
        if d.condition.enabled {
            condition_jobs.push(condition::Job::new(
                state.clone(),
                cond.clone(),
                d.condition.clone(),
                condition::store_for(settings.recording.dir.as_deref(), &d.name),
            ));
        }
        conditions.push(cond);
        drives.push(state);
    }
    let mut threads = Vec::with_capacity(loops.len() + buses.len() + 2);
    let state = Arc::new(ServiceState {
        drives,
        conditions,
        registry: Mutex::new(registry),
        recording_dir: settings.recording.dir.clone(),
        recording_lock,
        started,
    });
    for bus in buses {
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
        let spawned = spawn_bus(bus, rt, settings, shutdown.clone());
        keep_or_stop(&mut threads, spawned, &shutdown)?;
    }
    let count = loops.len();
    for (index, mut l) in loops.into_iter().enumerate() {
        l.stagger(index, count);
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
        let stop = shutdown.clone();
        let spawned =
            std::thread::Builder::new().name(format!("poll-{}", l.name())).spawn(move || l.run_blocking(&rt, &stop));
        // the loops already started must not outlive a failed start
        keep_or_stop(&mut threads, spawned, &shutdown)?;
    }
    // the checks' thread after the loops: a failed start stops the loops as above
    let checks = condition::start(condition_jobs, condition_metrics, shutdown.clone()).transpose();
    if let Some(spawned) = checks {
        keep_or_stop(&mut threads, spawned, &shutdown)?;
    }
    Ok(Service { state, threads })
}

/// One bus per RTU line (serial port or gateway), shared by the drives on it.
fn buses(settings: &Settings) -> Vec<Bus> {
    let mut buses: Vec<Bus> = Vec::new();
    for d in &settings.drives {
        if let Some((endpoint, _)) = d.line()
            && !buses.iter().any(|b| b.endpoint().same_line(&endpoint))
        {
            let on_line =
                settings.drives.iter().filter(|o| o.line().is_some_and(|(e, _)| e.same_line(&endpoint))).count();
            buses.push(Bus::new(endpoint, on_line));
        }
    }
    buses
}

/// The rows a drive's history ring holds: the HTTP history, or a condition check's window if that is longer.
fn history_len(settings: &Settings, d: &DriveSettings) -> usize {
    let mut ring_s = settings.http.history.as_secs_f64();
    if d.condition.enabled {
        ring_s = ring_s.max(d.condition.window.as_secs_f64());
    }
    (ring_s / d.poll.as_secs_f64()).ceil() as usize
}

/// A drive's snapshot before its first poll.
fn initial_snapshot(d: &DriveSettings) -> DriveSnapshot {
    DriveSnapshot::before_first_poll(d.name.clone(), d.mode, d.address.clone(), d.unit_id, d.target_omega_rad_s)
}

/// A drive's recorder (None when recording is off), keeping its share of the directory's retention.
fn recorder_for(
    settings: &Settings,
    d: &DriveSettings,
    lock: Option<Arc<recorder::DirLock>>,
) -> std::io::Result<Option<Recorder>> {
    let Some(dir) = &settings.recording.dir else { return Ok(None) };
    let r = &settings.recording;
    let retention = retention::Retention {
        // each drive keeps its share of the whole
        max_bytes: r.max_total_bytes.map(|t| t / settings.drives.len().max(1) as u64),
        keep: r.keep,
    };
    Ok(Some(Recorder::start(dir, &d.name, r.rotate_after, r.max_file_bytes, retention, r.compress, lock)?))
}

/// A drive's link: its own client, or its turn on its line's bus.
fn connection_for(d: &DriveSettings, buses: &[Bus]) -> Connection {
    match d.line() {
        None => Connection::Own(DriveClient::new(&d.address, d.unit_id, d.timeout)),
        Some((endpoint, _)) => match buses.iter().find(|b| b.endpoint().same_line(&endpoint)) {
            Some(bus) => bus.handle(d.unit_id, d.timeout),
            None => Connection::Own(DriveClient::on(endpoint, d.unit_id, d.timeout)),
        },
    }
}

/// Runs a line's bus on a thread of its own (`bus-<port>`) on `rt`, until `stop`.
fn spawn_bus(
    bus: Bus,
    rt: tokio::runtime::Runtime,
    settings: &Settings,
    stop: CancellationToken,
) -> std::io::Result<std::thread::JoinHandle<()>> {
    let name = format!("bus-{}", bus.endpoint().name().rsplit('/').next().unwrap_or("line"));
    // the line serves its drives' poll threads: it runs at the highest real-time priority any of them asks for
    let priority = settings
        .drives
        .iter()
        .filter(|d| d.line().is_some_and(|(e, _)| e.same_line(bus.endpoint())))
        .filter_map(|d| d.realtime_priority)
        .max();
    let what = name.clone();
    let run = move || {
        if let Some(p) = priority {
            use_realtime_priority(p, &what);
        }
        rt.block_on(bus.run(stop))
    };
    std::thread::Builder::new().name(name).spawn(run)
}

/// Keeps a thread that started; if it did not, stops and joins those already running and hands back the error.
fn keep_or_stop(
    threads: &mut Vec<std::thread::JoinHandle<()>>,
    spawned: std::io::Result<std::thread::JoinHandle<()>>,
    shutdown: &CancellationToken,
) -> std::io::Result<()> {
    match spawned {
        Ok(t) => {
            threads.push(t);
            Ok(())
        }
        Err(e) => {
            shutdown.cancel();
            join(std::mem::take(threads));
            Err(e)
        }
    }
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
    /// Blocks until every loop has stopped and closed its recording, for a start that failed after this one (the
    /// caller has cancelled the shutdown signal).
    pub fn join(self) {
        join(self.threads);
    }

    /// Waits until every loop has stopped and closed its recording.
    pub async fn wait(self) {
        let threads = self.threads;
        if tokio::task::spawn_blocking(move || join(threads)).await.is_err() {
            tracing::error!("waiting for the poll loops failed");
        }
    }
}

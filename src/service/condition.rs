//! Condition monitoring in the service: each drive's checks and alarms as the HTTP side and MQTT read them, their
//! metrics, and the one low-priority thread that runs the checks. `[drives.condition]` is read and checked at load
//! by [`super::config`] ([`ConditionSettings`]).
//!
//! In the service's layout (see [`super`]) it uses [`super::config`] and [`super::state`]; the outlets read it. Its
//! families (fitted parameters, alarms, power and energy) are its own, set by its thread when a check ends.
//!
//! The checks run on a thread of their own (`condition`), at nice [`CONDITION_NICE`]: below the poll threads and
//! the HTTP workers, never on a poll thread and never on the async runtime. The data are the drive's history ring
//! (kept at least `window_s` long), thinned to at most [`MAX_CHECK_HZ`] samples a second, with the load unknown.

use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::registry::Registry;
use tokio_util::sync::CancellationToken;

pub use super::config::ConditionSettings;
use super::state::{COLUMNS, DriveState, Point, lock};
use crate::condition::power::{EnergyReport, Flows, Ledger, Operating, PowerModel, effects_of_findings};
use crate::condition::{self, Check, Monitor, Store};
use crate::recording::Recording;

/// The checking thread's nice value: below the HTTP workers (10), far below the poll threads.
pub const CONDITION_NICE: i32 = 15;

/// A check sees at most this many samples a second (the ring thinned evenly): the analysis is validated at 5 ms
/// polls, and a check's cost must not grow with the poll rate (a 1 ms poll would make it five times dearer).
pub const MAX_CHECK_HZ: f64 = 200.0;

/// A check waits until the ring holds at least this fraction of `window_s`.
pub const MIN_WINDOW_FRACTION: f64 = 0.5;

/// How often the condition thread integrates each drive's power budget (the ring's new rows since the last time).
pub const ENERGY_EVERY: Duration = Duration::from_secs(1);

/// One drive's checks and alarms, shared by the checking thread and the HTTP side.
pub struct DriveCondition {
    pub drive: String,
    pub enabled: bool,
    monitor: Mutex<Monitor>,
    /// Why the last check failed (cleared by a check that succeeds).
    last_error: Mutex<Option<String>>,
    /// [`Monitor::tracked`] as of the last check (the trends change only with the checks).
    tracked: Mutex<Vec<condition::Tracked>>,
    /// The power budget's report as of the last integration.
    energy: Mutex<Option<EnergyReport>>,
    /// Times a check came due and found no sample newer than the last check's (the link down, say).
    idle_looks: AtomicU64,
}

impl DriveCondition {
    pub fn new(drive: &str, settings: &ConditionSettings) -> DriveCondition {
        DriveCondition {
            drive: drive.to_string(),
            enabled: settings.enabled,
            monitor: Mutex::new(Monitor::with_nominal(settings.limits.clone(), &settings.model)),
            last_error: Mutex::new(None),
            tracked: Mutex::new(Vec::new()),
            energy: Mutex::new(None),
            idle_looks: AtomicU64::new(0),
        }
    }

    /// Puts the drive's `energy` and `condition` (the tracked effects) into its snapshot.
    pub fn fill(&self, snapshot: &mut super::state::DriveSnapshot) {
        if !self.enabled {
            return;
        }
        snapshot.energy = lock(&self.energy).clone();
        snapshot.condition = lock(&self.tracked).clone();
    }

    /// The tracked effects as of the last check.
    pub fn tracked(&self) -> Vec<condition::Tracked> {
        lock(&self.tracked).clone()
    }

    /// The power budget's last report.
    pub fn energy(&self) -> Option<EnergyReport> {
        lock(&self.energy).clone()
    }

    /// Brings [`DriveCondition::tracked`] up to date with the monitor.
    fn refresh(&self) {
        let t = lock(&self.monitor).tracked();
        *lock(&self.tracked) = t;
    }

    /// The body of `GET /api/drives/{name}/condition` (CONTRACT.md "Extensions"), plus `enabled`, `limits`,
    /// `last_error`, `idle_looks` and each check's `alarms`.
    pub fn to_json(&self) -> serde_json::Value {
        let mut v = lock(&self.monitor).to_json(&self.drive);
        if let Some(o) = v.as_object_mut() {
            o.insert("enabled".into(), self.enabled.into());
            o.insert("last_error".into(), lock(&self.last_error).clone().into());
            o.insert("idle_looks".into(), self.idle_looks.load(Ordering::Relaxed).into());
        }
        v
    }

    pub fn push(&self, check: Check) {
        lock(&self.monitor).push(check);
        *lock(&self.last_error) = None;
        self.refresh();
    }

    pub fn monitor(&self) -> std::sync::MutexGuard<'_, Monitor> {
        lock(&self.monitor)
    }
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct ParameterLabels {
    pub drive: String,
    pub effect: String,
    pub parameter: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct EffectLabels {
    pub drive: String,
    pub effect: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct FlowLabels {
    pub drive: String,
    /// A flow of the power budget (`input`, `slip`, `pump_hydraulic`, `leakage`, `internal_leakage`,
    /// `motor_hydraulic`, `viscous`, `dry_friction`, `load`), or `drive`: the drive's output power as read.
    pub flow: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct EfficiencyLabels {
    pub drive: String,
    /// `volumetric`, `mechanical`, or `overall` (where the drive's output power is read).
    pub kind: String,
}

type GaugeF = Gauge<f64, AtomicU64>;

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct DriveLabel {
    pub drive: String,
}

/// The condition families (CONTRACT.md "Extensions"), in the service's registry.
#[derive(Clone)]
pub struct ConditionMetrics {
    /// The last check's fitted effect parameters; an effect the last check did not name has no series.
    pub parameter: Family<ParameterLabels, GaugeF>,
    /// 1 while an alarm of the effect is raised, else 0 (every effect with a limit).
    pub alarm: Family<EffectLabels, Gauge>,
    pub duration: Family<DriveLabel, GaugeF>,
    pub checks: Family<DriveLabel, Counter>,
    pub failures: Family<DriveLabel, Counter>,
    /// Seconds from the last check to the projected crossing of the limit; no series while not rising.
    pub time_to_limit: Family<ParameterLabels, GaugeF>,
    /// The power budget's mean power by flow over the last integration (about a second).
    pub power: Family<FlowLabels, GaugeF>,
    /// The energy of each flow since the service started: a gauge, as an overrunning load runs backwards.
    pub energy: Family<FlowLabels, GaugeF>,
    /// Mean power lost to each effect above the nominal model since the start.
    pub effect_loss: Family<EffectLabels, GaugeF>,
    pub efficiency: Family<EfficiencyLabels, GaugeF>,
}

impl ConditionMetrics {
    pub fn register(r: &mut Registry) -> ConditionMetrics {
        let m = ConditionMetrics {
            parameter: Family::default(),
            alarm: Family::default(),
            duration: Family::default(),
            checks: Family::default(),
            failures: Family::default(),
            time_to_limit: Family::default(),
            power: Family::default(),
            energy: Family::default(),
            effect_loss: Family::default(),
            efficiency: Family::default(),
        };
        r.register(
            "condition_parameter",
            "An effect parameter as the last condition check fitted it (catalogue units)",
            m.parameter.clone(),
        );
        r.register("condition_alarm", "1 while a condition alarm of the effect is raised", m.alarm.clone());
        r.register("condition_check_duration_seconds", "Wall time of the last condition check", m.duration.clone());
        r.register("condition_checks", "Condition checks run", m.checks.clone());
        r.register("condition_check_failures", "Condition checks the analysis refused", m.failures.clone());
        use prometheus_client::registry::Unit;
        let watts = || Unit::Other("watts".into());
        r.register_with_unit(
            "condition_time_to_limit",
            "From the last condition check to the projected crossing of the parameter's limit (absent: not rising)",
            Unit::Seconds,
            m.time_to_limit.clone(),
        );
        r.register_with_unit("power", "Mean power of a flow of the drive's power budget", watts(), m.power.clone());
        r.register_with_unit(
            "energy",
            "Energy of a flow of the power budget since the start",
            Unit::Joules,
            m.energy.clone(),
        );
        r.register_with_unit(
            "effect_power_loss",
            "Mean power lost to an effect above the nominal model",
            watts(),
            m.effect_loss.clone(),
        );
        r.register_with_unit(
            "efficiency",
            "Volumetric, mechanical and overall efficiency (overall: the load's energy over the drive's output)",
            Unit::Other("ratio".into()),
            m.efficiency.clone(),
        );
        m
    }

    /// Sets the power budget's gauges from a drive's energy report.
    fn update_energy(&self, drive: &str, r: &EnergyReport) {
        let flow = |f: &str| FlowLabels { drive: drive.into(), flow: f.trim_end_matches("_w").into() };
        for ((name, p), e) in Flows::COLUMNS.iter().zip(r.power_w.values()).zip(r.energy_j.values()) {
            self.power.get_or_create(&flow(name)).set(p);
            self.energy.get_or_create(&flow(name)).set(e);
        }
        let output = flow("drive_w");
        match (r.drive_power_w, r.drive_energy_j) {
            (Some(p), Some(e)) => {
                self.power.get_or_create(&output).set(p);
                self.energy.get_or_create(&output).set(e);
            }
            _ => {
                self.power.remove(&output);
                self.energy.remove(&output);
            }
        }
        for c in &r.effects {
            self.effect_loss
                .get_or_create(&EffectLabels { drive: drive.into(), effect: c.effect.clone() })
                .set(c.power_w);
        }
        let kinds = [
            ("volumetric", r.volumetric_efficiency),
            ("mechanical", r.mechanical_efficiency),
            ("overall", r.overall_efficiency),
        ];
        for (kind, v) in kinds {
            let l = EfficiencyLabels { drive: drive.into(), kind: kind.into() };
            match v {
                Some(v) => {
                    self.efficiency.get_or_create(&l).set(v);
                }
                None => {
                    self.efficiency.remove(&l);
                }
            }
        }
    }

    /// Sets the gauges from a drive's monitor after its last check.
    fn update(&self, drive: &str, monitor: &Monitor) {
        let alarms = monitor.alarms();
        for effect in monitor.limits().keys() {
            let on = alarms.iter().any(|a| &a.effect == effect);
            self.alarm.get_or_create(&EffectLabels { drive: drive.into(), effect: effect.clone() }).set(i64::from(on));
        }
        let Some(last) = monitor.last() else { return };
        let fitted = last.parameters();
        // drop the series of effects the last check no longer names
        for effect in crate::plant::effects::EFFECT_IDS {
            for &parameter in crate::plant::effects::parameter_names(effect) {
                if !fitted.iter().any(|(e, p, _)| e == effect && p == parameter) {
                    self.parameter.remove(&ParameterLabels {
                        drive: drive.into(),
                        effect: effect.into(),
                        parameter: parameter.into(),
                    });
                }
            }
        }
        for (effect, parameter, value) in fitted {
            self.parameter.get_or_create(&ParameterLabels { drive: drive.into(), effect, parameter }).set(value);
        }
        self.duration.get_or_create(&DriveLabel { drive: drive.into() }).set(last.duration_s);
        for t in monitor.tracked() {
            let l = ParameterLabels { drive: drive.into(), effect: t.effect.clone(), parameter: t.parameter.clone() };
            match t.trend.seconds_to_limit {
                Some(s) => {
                    self.time_to_limit.get_or_create(&l).set(s);
                }
                None => {
                    self.time_to_limit.remove(&l);
                }
            }
        }
    }
}

/// One drive's part of the checking thread.
pub struct Job {
    pub drive: Arc<DriveState>,
    pub condition: Arc<DriveCondition>,
    pub settings: ConditionSettings,
    /// None when recording is off: the history is then kept in memory only.
    pub store: Option<Store>,
    /// Lines in the store's file: past `2 × KEEP_CHECKS` it is rewritten with the checks kept.
    pub stored_lines: usize,
    /// The service time of the last sample this run's last check saw: a drive whose link is down brings no new
    /// data, and the same window is not checked twice.
    pub checked_up_to_s: Option<f64>,
    /// The drive's energies so far, and when they were last brought up to date.
    pub ledger: Ledger,
    pub energy_at: Instant,
}

impl Job {
    pub fn new(
        drive: Arc<DriveState>,
        condition: Arc<DriveCondition>,
        settings: ConditionSettings,
        store: Option<Store>,
    ) -> Job {
        Job {
            drive,
            condition,
            settings,
            store,
            stored_lines: 0,
            checked_up_to_s: None,
            ledger: Ledger::default(),
            energy_at: Instant::now(),
        }
    }

    /// Integrates the power budget over the ring's rows since the last time (the nominal model with the last
    /// check's findings), and publishes the report and its metrics.
    fn integrate_energy(&mut self, metrics: &ConditionMetrics) {
        let lookback = (self.energy_at.elapsed() + ENERGY_EVERY).as_secs_f64().min(self.settings.window.as_secs_f64());
        self.energy_at = Instant::now();
        let points = self.drive.history(lookback, (lookback * MAX_CHECK_HZ).ceil() as usize);
        let fitted = self.condition.monitor().last().map(|c| effects_of_findings(&c.findings)).unwrap_or_default();
        let Some(model) = PowerModel::new(&self.settings.model, &fitted) else { return };
        self.ledger.add_all(&model, points.iter().map(operating));
        let report = self.ledger.report(self.settings.energy_price_per_kwh);
        metrics.update_energy(&self.drive.name, &report);
        *lock(&self.condition.energy) = Some(report);
    }

    /// Loads the drive's history from its store (the alarms replayed) and sets the metrics from it.
    fn restore(&mut self, metrics: &ConditionMetrics) {
        if self.settings.enabled {
            // the counters exist from the start, at 0, so that dashboards and alerts see them before the first check
            let label = DriveLabel { drive: self.drive.name.clone() };
            let _ = metrics.checks.get_or_create(&label);
            let _ = metrics.failures.get_or_create(&label);
        }
        let Some(store) = &self.store else {
            metrics.update(&self.drive.name, &self.condition.monitor());
            return;
        };
        match store.load_counting() {
            Ok((checks, lines)) => {
                self.stored_lines = lines;
                let n = checks.len();
                let mut m = self.condition.monitor();
                checks.into_iter().for_each(|c| m.push(c));
                metrics.update(&self.drive.name, &m);
                if n > 0 {
                    tracing::info!(drive = %self.drive.name, checks = n, alarms = m.alarms().len(),
                        file = %store.path().display(), "condition history loaded");
                }
            }
            Err(e) => tracing::warn!(drive = %self.drive.name, file = %store.path().display(), error = %e,
                "cannot read the condition history; starting without it"),
        }
        self.condition.refresh();
    }

    /// Runs one check on the ring's last window; false when the ring does not hold enough data yet.
    fn run(&mut self, metrics: &ConditionMetrics) -> bool {
        let window_s = self.settings.window.as_secs_f64();
        let points = self.drive.history(window_s, (window_s * MAX_CHECK_HZ).ceil() as usize);
        let (Some(first), Some(last)) = (points.first().copied(), points.last().copied()) else { return false };
        let span = last.sample.t_s - first.sample.t_s;
        if self.checked_up_to_s.is_some_and(|t| last.sample.t_s <= t) {
            tracing::debug!(drive = %self.drive.name, "no new data since the last condition check");
            self.condition.idle_looks.fetch_add(1, Ordering::Relaxed);
            return true;
        }
        if span < MIN_WINDOW_FRACTION * window_s {
            tracing::debug!(drive = %self.drive.name, span_s = span, "condition check waits for more data");
            return false;
        }
        let mut cols: Vec<Vec<f64>> = vec![Vec::with_capacity(points.len()); COLUMNS.len()];
        for p in &points {
            for (c, v) in cols.iter_mut().zip(p.values()) {
                c.push(v);
            }
        }
        let source = format!("{} (last {span:.0} s)", self.drive.name);
        let rec = Recording::from_columns(&source, COLUMNS.iter().map(|s| s.to_string()).collect(), cols);
        drop(points);
        let drive_label = DriveLabel { drive: self.drive.name.clone() };
        self.checked_up_to_s = Some(last.sample.t_s);
        match condition::check(&rec, &self.settings.model, last.sample.t_s, span) {
            Ok(c) => {
                if let Some(store) = &self.store {
                    match store.append(&c) {
                        Ok(()) => self.stored_lines += 1,
                        Err(e) => tracing::warn!(drive = %self.drive.name, file = %store.path().display(),
                            error = %e, "cannot append to the condition history"),
                    }
                }
                let named: Vec<String> = c.parameters().iter().map(|(e, p, v)| format!("{e}.{p}={v:.4}")).collect();
                tracing::info!(drive = %self.drive.name, t_s = c.t_s, window_s = span, duration_s = c.duration_s,
                    findings = ?named, "condition check");
                self.condition.push(c);
                let m = self.condition.monitor();
                for a in m.alarms().iter().filter(|a| a.since_s == last.sample.t_s) {
                    tracing::warn!(drive = %self.drive.name, effect = %a.effect, parameter = %a.parameter,
                        value = a.value, limit = a.limit, "condition alarm raised");
                }
                metrics.update(&self.drive.name, &m);
                metrics.checks.get_or_create(&drive_label).inc();
                if let Some(store) = &self.store
                    && self.stored_lines > 2 * condition::KEEP_CHECKS
                {
                    match store.rewrite(m.checks()) {
                        Ok(()) => self.stored_lines = m.checks().count(),
                        Err(e) => tracing::warn!(drive = %self.drive.name, file = %store.path().display(),
                            error = %e, "cannot rewrite the condition history"),
                    }
                }
            }
            Err(e) => {
                tracing::warn!(drive = %self.drive.name, error = %e, "condition check failed");
                *lock(&self.condition.last_error) = Some(e.to_string());
                metrics.failures.get_or_create(&drive_label).inc();
            }
        }
        true
    }
}

/// A ring row as the power budget takes it: the estimator's speed, and all it sees resist the motor beside inertia.
fn operating(p: &Point) -> Operating {
    let (m, e) = (&p.sample, &p.estimate);
    Operating {
        t_s: m.t_s,
        dp_bar: m.p_in_bar - m.p_out_bar,
        f_drive_hz: m.f_drive_hz,
        omega_rad_s: e.omega_hat_rad_s,
        resisting_torque_nm: e.load_hat_nm + e.viscous_hat_nm_s_rad * e.omega_hat_rad_s,
        drive_power_w: Some(m.drive_power_w).filter(|p| p.is_finite()),
    }
}

/// The store of a drive's history: `<recordings dir>/<drive>.condition.jsonl`.
pub fn store_for(dir: Option<&Path>, drive: &str) -> Option<Store> {
    dir.map(|d| Store::new(d, drive))
}

/// Starts the checking thread for the enabled jobs (None when there are none). Each drive's first check comes
/// `every_s` after the start, then every `every_s`; a check that finds less than half a window of data is tried
/// again a tenth of `every_s` later. The thread ends when `shutdown` is cancelled (after the check running then).
pub fn start(
    mut jobs: Vec<Job>,
    metrics: ConditionMetrics,
    shutdown: CancellationToken,
) -> std::io::Result<Option<std::thread::JoinHandle<()>>> {
    for j in &mut jobs {
        j.restore(&metrics);
    }
    let mut jobs: Vec<(Job, Instant)> = jobs
        .into_iter()
        .filter(|j| j.settings.enabled)
        .map(|j| {
            let due = Instant::now() + j.settings.every;
            (j, due)
        })
        .collect();
    if jobs.is_empty() {
        return Ok(None);
    }
    let thread = std::thread::Builder::new().name("condition".into()).spawn(move || {
        lower_priority();
        // bounded: every pass either sleeps (≤ 100 ms) or runs one check, and the token ends it
        while !shutdown.is_cancelled() {
            let now = Instant::now();
            for (job, _) in jobs.iter_mut() {
                if job.energy_at + ENERGY_EVERY <= now {
                    job.integrate_energy(&metrics);
                }
            }
            let Some(next) = jobs.iter_mut().min_by_key(|(_, due)| *due) else { return };
            if next.1 > now {
                std::thread::sleep((next.1 - now).min(Duration::from_millis(100)));
                continue;
            }
            let (job, due) = next;
            let every = job.settings.every;
            *due = if job.run(&metrics) { (*due + every).max(Instant::now()) } else { Instant::now() + every / 10 };
        }
    })?;
    Ok(Some(thread))
}

/// Puts the calling thread at nice [`CONDITION_NICE`] (Linux; elsewhere nothing). Raising a nice value needs no
/// privilege.
pub fn lower_priority() {
    #[cfg(target_os = "linux")]
    {
        let tid = rustix::thread::gettid();
        if let Err(e) = rustix::process::setpriority_process(Some(tid), CONDITION_NICE) {
            tracing::warn!(error = %e, "cannot lower the condition thread's priority");
        }
    }
}

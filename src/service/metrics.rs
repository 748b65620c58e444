//! The service's Prometheus metrics (prometheus-client): one registry, families labelled by drive.

use std::sync::atomic::AtomicU64;

use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::Registry;

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct DriveLabel {
    pub drive: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct ErrorLabels {
    pub drive: String,
    pub kind: String,
}

type GaugeF = Gauge<f64, AtomicU64>;
type HistogramFamily = Family<DriveLabel, Histogram, fn() -> Histogram>;

fn period_histogram() -> Histogram {
    // 0.1 ms … ≈ 1.6 s
    Histogram::new(exponential_buckets(1e-4, 2.0, 15))
}

/// Every metric family; cheap to clone (the families are shared).
#[derive(Clone)]
pub struct Metrics {
    pub polls: Family<DriveLabel, Counter>,
    pub errors: Family<ErrorLabels, Counter>,
    pub reconnects: Family<DriveLabel, Counter>,
    pub rejected_samples: Family<DriveLabel, Counter>,
    pub stale_samples: Family<DriveLabel, Counter>,
    pub writes: Family<DriveLabel, Counter>,
    pub overruns: Family<DriveLabel, Counter>,
    pub stale: Family<DriveLabel, Gauge>,
    pub link_up: Family<DriveLabel, Gauge>,
    pub loop_period: HistogramFamily,
    pub jitter_p50: Family<DriveLabel, GaugeF>,
    pub jitter_p99: Family<DriveLabel, GaugeF>,
    pub omega: Family<DriveLabel, GaugeF>,
    pub omega_hat: Family<DriveLabel, GaugeF>,
    pub load_hat: Family<DriveLabel, GaugeF>,
    /// J and B as estimated, and how sure the estimator is of them (standard deviations).
    pub inertia_hat: Family<DriveLabel, GaugeF>,
    pub inertia_sd: Family<DriveLabel, GaugeF>,
    pub viscous_hat: Family<DriveLabel, GaugeF>,
    pub viscous_sd: Family<DriveLabel, GaugeF>,
    pub setpoint: Family<DriveLabel, GaugeF>,
    pub target: Family<DriveLabel, GaugeF>,
    /// The recorder's: 1 while rows reach the disk; failures; rows lost to them.
    pub recording_ok: Family<DriveLabel, Gauge>,
    pub recording_errors: Family<DriveLabel, Counter>,
    pub recording_rows_lost: Family<DriveLabel, Counter>,
    pub recording_files_deleted: Family<DriveLabel, Counter>,
    pub recording_files_compressed: Family<DriveLabel, Counter>,
    /// The HTTP side's (no drive label): open connections, wrong tokens, requests refused while throttled.
    pub http_connections: Gauge,
    pub http_auth_failures: Counter,
    pub http_auth_throttled: Counter,
}

impl Metrics {
    /// The families, registered in a new registry.
    pub fn new() -> (Metrics, Registry) {
        let m = Metrics {
            polls: Family::default(),
            errors: Family::default(),
            reconnects: Family::default(),
            rejected_samples: Family::default(),
            stale_samples: Family::default(),
            writes: Family::default(),
            overruns: Family::default(),
            stale: Family::default(),
            link_up: Family::default(),
            loop_period: Family::new_with_constructor(period_histogram as fn() -> Histogram),
            jitter_p50: Family::default(),
            jitter_p99: Family::default(),
            omega: Family::default(),
            omega_hat: Family::default(),
            load_hat: Family::default(),
            inertia_hat: Family::default(),
            inertia_sd: Family::default(),
            viscous_hat: Family::default(),
            viscous_sd: Family::default(),
            setpoint: Family::default(),
            target: Family::default(),
            recording_ok: Family::default(),
            recording_errors: Family::default(),
            recording_rows_lost: Family::default(),
            recording_files_deleted: Family::default(),
            recording_files_compressed: Family::default(),
            http_connections: Gauge::default(),
            http_auth_failures: Counter::default(),
            http_auth_throttled: Counter::default(),
        };
        let mut r = Registry::with_prefix("hydrolens");
        r.register("polls", "Poll cycles run", m.polls.clone());
        r.register("errors", "Failed Modbus calls, by kind", m.errors.clone());
        r.register("reconnects", "Modbus connections re-opened after a failure", m.reconnects.clone());
        r.register(
            "rejected_samples",
            "Samples out of range or not finite, never given to the estimator",
            m.rejected_samples.clone(),
        );
        r.register("stale_samples", "Reads whose sample counter had not moved", m.stale_samples.clone());
        r.register("writes", "Modbus write requests sent", m.writes.clone());
        r.register("loop_overruns", "Poll cycles that took longer than the poll period", m.overruns.clone());
        r.register("stale", "1 while the drive's data are stale", m.stale.clone());
        r.register("link_up", "1 while the Modbus connection is open and answering", m.link_up.clone());
        r.register("loop_period_seconds", "Time between poll cycle starts", m.loop_period.clone());
        r.register(
            "loop_jitter_p50_seconds",
            "Median |period − poll period| over the last 1000 cycles",
            m.jitter_p50.clone(),
        );
        r.register(
            "loop_jitter_p99_seconds",
            "99th percentile |period − poll period| over the last 1000 cycles",
            m.jitter_p99.clone(),
        );
        r.register("omega_rad_s", "Measured shaft speed", m.omega.clone());
        r.register("omega_hat_rad_s", "Estimated shaft speed", m.omega_hat.clone());
        r.register("load_hat_nm", "Estimated load torque", m.load_hat.clone());
        r.register("inertia_hat_kg_m2", "Estimated inertia J", m.inertia_hat.clone());
        r.register(
            "inertia_sd_kg_m2",
            "Standard deviation of the estimated J (0: taken from the model)",
            m.inertia_sd.clone(),
        );
        r.register("viscous_hat_nm_s_rad", "Estimated viscous friction B", m.viscous_hat.clone());
        r.register(
            "viscous_sd_nm_s_rad",
            "Standard deviation of the estimated B (0: taken from the model)",
            m.viscous_sd.clone(),
        );
        r.register("setpoint_hz", "Last frequency setpoint written", m.setpoint.clone());
        r.register("target_omega_rad_s", "Speed target", m.target.clone());
        r.register("recording_ok", "1 while the drive's rows reach the disk", m.recording_ok.clone());
        r.register("recording_errors", "Recording write, flush or open failures", m.recording_errors.clone());
        r.register("recording_rows_lost", "Rows not recorded because writing failed", m.recording_rows_lost.clone());
        r.register(
            "recording_files_deleted",
            "Old recordings deleted by retention (max_total_mb, keep_days)",
            m.recording_files_deleted.clone(),
        );
        r.register(
            "recording_files_compressed",
            "Closed recordings compressed to .csv.gz (recording.compress)",
            m.recording_files_compressed.clone(),
        );
        r.register("http_connections", "Open HTTP connections", m.http_connections.clone());
        r.register("http_auth_failures", "Write requests with a wrong Bearer token", m.http_auth_failures.clone());
        r.register(
            "http_auth_throttled",
            "Write requests refused with 429 after a burst of wrong tokens",
            m.http_auth_throttled.clone(),
        );
        (m, r)
    }
}

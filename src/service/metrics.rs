//! The service's Prometheus metrics (prometheus-client): one registry, families labelled by drive, names in base
//! units; and the exposition in the format the scraper asks for (OpenMetrics or the Prometheus text format 0.0.4).

use std::sync::atomic::AtomicU64;

use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::{Registry, Unit};

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct DriveLabel {
    pub drive: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct ErrorLabels {
    pub drive: String,
    pub kind: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct ReasonLabel {
    pub reason: &'static str,
}

type GaugeF = Gauge<f64, AtomicU64>;

/// Unit suffixes spelt out, as the Prometheus naming conventions ask (docs/metrics.md lists the old names).
const RAD_S: &str = "radians_per_second";
const KG_M2: &str = "kilogram_square_meters";
const NM_S_RAD: &str = "newton_meter_seconds_per_radian";

/// Pascals per bar: the registers carry bar, the metrics the SI unit.
pub const PASCALS_PER_BAR: f64 = 1e5;
/// A unit of the metrics' own (not one of prometheus-client's).
fn unit(u: &str) -> Unit {
    Unit::Other(u.to_string())
}

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
    /// Setpoint writes refused or unanswered; writes slower than half the poll period; trips.
    pub writes_refused: Family<DriveLabel, Counter>,
    pub slow_writes: Family<DriveLabel, Counter>,
    pub trips: Family<DriveLabel, Counter>,
    pub overruns: Family<DriveLabel, Counter>,
    pub stale: Family<DriveLabel, Gauge>,
    pub link_up: Family<DriveLabel, Gauge>,
    pub loop_period: HistogramFamily,
    pub jitter_p50: Family<DriveLabel, GaugeF>,
    pub jitter_p99: Family<DriveLabel, GaugeF>,
    /// The last sample's pressures (pascals: bar × 1e5) and drive output frequency.
    pub inlet_pressure: Family<DriveLabel, GaugeF>,
    pub outlet_pressure: Family<DriveLabel, GaugeF>,
    pub drive_frequency: Family<DriveLabel, GaugeF>,
    pub omega: Family<DriveLabel, GaugeF>,
    pub omega_hat: Family<DriveLabel, GaugeF>,
    pub load_hat: Family<DriveLabel, GaugeF>,
    /// J and B as estimated, and how sure the estimator is of them (standard deviations).
    pub inertia_hat: Family<DriveLabel, GaugeF>,
    pub inertia_sd: Family<DriveLabel, GaugeF>,
    pub viscous_hat: Family<DriveLabel, GaugeF>,
    pub viscous_sd: Family<DriveLabel, GaugeF>,
    /// What the data say of J and B and what the load looks like: the estimate's codes (docs/estimator.md).
    pub inertia_identified: Family<DriveLabel, GaugeF>,
    pub viscous_identified: Family<DriveLabel, GaugeF>,
    pub load_character: Family<DriveLabel, GaugeF>,
    /// 1 while a writing drive does not follow its setpoints (the regulator's alarm).
    pub not_following: Family<DriveLabel, GaugeF>,
    pub setpoint: Family<DriveLabel, GaugeF>,
    pub target: Family<DriveLabel, GaugeF>,
    /// The recorder's: 1 while rows reach the disk; failures; rows lost to them or with a lost file; files lost.
    pub recording_ok: Family<DriveLabel, Gauge>,
    pub recording_errors: Family<DriveLabel, Counter>,
    pub recording_rows_lost: Family<DriveLabel, Counter>,
    pub recording_files_lost: Family<DriveLabel, Counter>,
    pub recording_files_deleted: Family<DriveLabel, Counter>,
    pub recording_files_compressed: Family<DriveLabel, Counter>,
    /// The HTTP side's (no drive label): open connections, wrong tokens, requests refused while throttled.
    pub http_connections: Gauge,
    pub http_auth_failures: Counter,
    pub http_auth_throttled: Counter,
    /// Open `/api/events` streams, and connections or requests turned away, by reason (event_streams: the cap
    /// was reached; per_client: one address held too many connections and the reserve was full; reserved: a
    /// route other than control and health asked on a reserved connection; stalled: a client stopped reading).
    pub http_event_streams: Gauge,
    pub http_refused: Family<ReasonLabel, Counter>,
}

impl Metrics {
    /// The families, registered in a new registry.
    pub fn new() -> (Metrics, Registry) {
        let m = Metrics::families();
        let mut r = Registry::with_prefix("hydrolens");
        m.register_link(&mut r);
        m.register_timing(&mut r);
        m.register_signals(&mut r);
        m.register_status(&mut r);
        m.register_recording(&mut r);
        m.register_http(&mut r);
        (m, r)
    }

    /// Every family, empty.
    fn families() -> Metrics {
        Metrics {
            polls: Family::default(),
            errors: Family::default(),
            reconnects: Family::default(),
            rejected_samples: Family::default(),
            stale_samples: Family::default(),
            writes: Family::default(),
            writes_refused: Family::default(),
            slow_writes: Family::default(),
            trips: Family::default(),
            overruns: Family::default(),
            stale: Family::default(),
            link_up: Family::default(),
            loop_period: Family::new_with_constructor(period_histogram as fn() -> Histogram),
            jitter_p50: Family::default(),
            jitter_p99: Family::default(),
            inlet_pressure: Family::default(),
            outlet_pressure: Family::default(),
            drive_frequency: Family::default(),
            omega: Family::default(),
            omega_hat: Family::default(),
            load_hat: Family::default(),
            inertia_hat: Family::default(),
            inertia_sd: Family::default(),
            viscous_hat: Family::default(),
            viscous_sd: Family::default(),
            inertia_identified: Family::default(),
            viscous_identified: Family::default(),
            load_character: Family::default(),
            not_following: Family::default(),
            setpoint: Family::default(),
            target: Family::default(),
            recording_ok: Family::default(),
            recording_errors: Family::default(),
            recording_rows_lost: Family::default(),
            recording_files_lost: Family::default(),
            recording_files_deleted: Family::default(),
            recording_files_compressed: Family::default(),
            http_connections: Gauge::default(),
            http_auth_failures: Counter::default(),
            http_auth_throttled: Counter::default(),
            http_event_streams: Gauge::default(),
            http_refused: Family::default(),
        }
    }

    /// Registers the poll loop's counts and the link's state.
    fn register_link(&self, r: &mut Registry) {
        r.register("polls", "Poll cycles run", self.polls.clone());
        r.register("errors", "Failed Modbus calls, by kind", self.errors.clone());
        r.register("reconnects", "Modbus connections re-opened after a failure", self.reconnects.clone());
        r.register(
            "rejected_samples",
            "Samples out of range or not finite, never given to the estimator",
            self.rejected_samples.clone(),
        );
        r.register("stale_samples", "Reads whose sample counter had not moved", self.stale_samples.clone());
        r.register("writes", "Modbus write requests sent", self.writes.clone());
        r.register(
            "writes_refused",
            "Setpoint writes the device refused or never answered",
            self.writes_refused.clone(),
        );
        r.register(
            "slow_writes",
            "Setpoint writes that took more than half the poll period (the loop overruns)",
            self.slow_writes.clone(),
        );
        r.register("trips", "Times the drive reported a fault or comm-loss trip", self.trips.clone());
        r.register("loop_overruns", "Poll cycles that took longer than the poll period", self.overruns.clone());
        r.register("stale", "1 while the drive's data are stale", self.stale.clone());
        r.register("link_up", "1 while the Modbus connection is open and answering", self.link_up.clone());
    }

    /// Registers the loop's period and jitter.
    fn register_timing(&self, r: &mut Registry) {
        r.register_with_unit("loop_period", "Time between poll cycle starts", Unit::Seconds, self.loop_period.clone());
        r.register_with_unit(
            "loop_jitter_p50",
            "Median |period − poll period| over the last 1000 cycles",
            Unit::Seconds,
            self.jitter_p50.clone(),
        );
        r.register_with_unit(
            "loop_jitter_p99",
            "99th percentile |period − poll period| over the last 1000 cycles",
            Unit::Seconds,
            self.jitter_p99.clone(),
        );
    }

    /// Registers the last sample's measured signals, the estimates and their standard deviations.
    fn register_signals(&self, r: &mut Registry) {
        r.register_with_unit("inlet_pressure", "Measured inlet pressure", unit("pascals"), self.inlet_pressure.clone());
        r.register_with_unit(
            "outlet_pressure",
            "Measured outlet pressure",
            unit("pascals"),
            self.outlet_pressure.clone(),
        );
        r.register_with_unit(
            "drive_frequency",
            "Output frequency the drive reports",
            unit("hertz"),
            self.drive_frequency.clone(),
        );
        r.register_with_unit("omega", "Measured shaft speed", unit(RAD_S), self.omega.clone());
        r.register_with_unit("omega_hat", "Estimated shaft speed", unit(RAD_S), self.omega_hat.clone());
        r.register_with_unit("load_hat", "Estimated load torque", unit("newton_meters"), self.load_hat.clone());
        r.register_with_unit("inertia_hat", "Estimated inertia J", unit(KG_M2), self.inertia_hat.clone());
        r.register_with_unit(
            "inertia_sd",
            "Standard deviation of the estimated J (0: taken from the model)",
            unit(KG_M2),
            self.inertia_sd.clone(),
        );
        r.register_with_unit("viscous_hat", "Estimated viscous friction B", unit(NM_S_RAD), self.viscous_hat.clone());
        r.register_with_unit(
            "viscous_sd",
            "Standard deviation of the estimated B (0: taken from the model)",
            unit(NM_S_RAD),
            self.viscous_sd.clone(),
        );
    }

    /// Registers what the data say of J, B and the load, whether the drive follows, setpoint and target.
    fn register_status(&self, r: &mut Registry) {
        r.register(
            "inertia_identified",
            "J: 1 identified, 0 too little excitation, -1 nominal predicts as well, -2 not separable from the load, -3 the model's",
            self.inertia_identified.clone(),
        );
        r.register(
            "viscous_identified",
            "B: 1 identified, 0 too little excitation, -1 nominal predicts as well, -2 not separable from the load, -3 the model's",
            self.viscous_identified.clone(),
        );
        r.register(
            "load_character",
            "Load: 0 unknown, 1 steady, 2 stepping, 3 periodic in time, 4 periodic in shaft angle, 5 following the speed, 6 random",
            self.load_character.clone(),
        );
        r.register(
            "drive_not_following",
            "1 while the drive does not follow its setpoints (local mode, not ready or not running)",
            self.not_following.clone(),
        );
        r.register_with_unit("setpoint", "Last frequency setpoint written", unit("hertz"), self.setpoint.clone());
        r.register_with_unit("target_omega", "Speed target", unit(RAD_S), self.target.clone());
    }

    /// Registers the recorder's state and losses.
    fn register_recording(&self, r: &mut Registry) {
        r.register("recording_ok", "1 while the drive's rows reach the disk", self.recording_ok.clone());
        r.register("recording_errors", "Recording write, flush or open failures", self.recording_errors.clone());
        r.register(
            "recording_rows_lost",
            "Rows not recorded: writing failed, or the open file was lost",
            self.recording_rows_lost.clone(),
        );
        r.register(
            "recording_files_lost",
            "Open recordings lost while written (deleted, their directory removed, or replaced)",
            self.recording_files_lost.clone(),
        );
        r.register(
            "recording_files_deleted",
            "Old recordings deleted by retention (max_total_mb, keep_days)",
            self.recording_files_deleted.clone(),
        );
        r.register(
            "recording_files_compressed",
            "Closed recordings compressed to .csv.gz (recording.compress)",
            self.recording_files_compressed.clone(),
        );
    }

    /// Registers the HTTP side's connections, refusals and auth failures.
    fn register_http(&self, r: &mut Registry) {
        r.register("http_connections", "Open HTTP connections", self.http_connections.clone());
        r.register("http_auth_failures", "Write requests with a wrong Bearer token", self.http_auth_failures.clone());
        r.register(
            "http_auth_throttled",
            "Write requests refused with 429 after a burst of wrong tokens",
            self.http_auth_throttled.clone(),
        );
        r.register("http_event_streams", "Open /api/events streams", self.http_event_streams.clone());
        r.register(
            "http_refused",
            "HTTP connections or requests turned away to keep capacity, by reason",
            self.http_refused.clone(),
        );
    }
}

/// The two expositions `/metrics` serves.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    /// OpenMetrics 1.0.0 text, what prometheus-client writes (with `# UNIT` lines and the closing `# EOF`).
    OpenMetrics,
    /// The Prometheus text format 0.0.4: what every scraper reads, and what `promtool check metrics` checks.
    Text,
}

impl Format {
    pub fn content_type(self) -> &'static str {
        match self {
            Format::OpenMetrics => "application/openmetrics-text; version=1.0.0; charset=utf-8",
            Format::Text => "text/plain; version=0.0.4; charset=utf-8",
        }
    }

    /// The format an `Accept` header asks for: OpenMetrics when it names `application/openmetrics-text` (version
    /// 1.0.0 or none) with a quality above 0 and at least that of any range the text format matches (`text/plain`
    /// with version 0.0.4 or none, `text/*`, `*/*`); the text format otherwise, and when there is no header.
    pub fn negotiate(accept: Option<&str>) -> Format {
        let (mut om, mut text) = (0.0_f64, 0.0_f64);
        for range in accept.unwrap_or("").split(',') {
            let mut parts = range.split(';').map(str::trim);
            let media = parts.next().unwrap_or("").to_ascii_lowercase();
            let (mut q, mut version) = (1.0_f64, None);
            for p in parts {
                let Some((k, v)) = p.split_once('=') else { continue };
                let v = v.trim().trim_matches('"');
                match k.trim().to_ascii_lowercase().as_str() {
                    "q" => q = v.parse().ok().filter(|q: &f64| (0.0..=1.0).contains(q)).unwrap_or(0.0),
                    "version" => version = Some(v.to_string()),
                    _ => {}
                }
            }
            match media.as_str() {
                "application/openmetrics-text" if version.as_deref().is_none_or(|v| v == "1.0.0") => om = om.max(q),
                "text/plain" if version.as_deref().is_none_or(|v| v == "0.0.4") => text = text.max(q),
                "text/*" | "*/*" => text = text.max(q),
                _ => {}
            }
        }
        if om > 0.0 && om >= text { Format::OpenMetrics } else { Format::Text }
    }
}

/// The registry's exposition in `format`.
pub fn encode(registry: &Registry, format: Format) -> String {
    let mut out = String::new();
    if let Err(e) = prometheus_client::encoding::text::encode(&mut out, registry) {
        tracing::error!(error = %e, "encoding metrics");
    }
    match format {
        Format::OpenMetrics => out,
        Format::Text => openmetrics_to_text(&out),
    }
}

/// Rewrites prometheus-client's OpenMetrics text as the Prometheus text format 0.0.4 (prometheus-client writes
/// only OpenMetrics). The sample lines are the same in both; the metadata differs: a counter's HELP and TYPE name
/// the `_total` series, `unknown` is `untyped`, an `info` family is a gauge named `_info`, and there is no `# UNIT`
/// and no `# EOF`. The registry holds no exemplars and no `_created` series, so the samples pass through as they are.
pub fn openmetrics_to_text(om: &str) -> String {
    let mut out = String::with_capacity(om.len());
    let mut help: Option<(&str, &str)> = None;
    for line in om.lines() {
        if line == "# EOF" || line.starts_with("# UNIT ") {
            continue;
        }
        if let Some(rest) = line.strip_prefix("# HELP ") {
            help = Some(rest.split_once(' ').unwrap_or((rest, "")));
            continue;
        }
        if let Some(rest) = line.strip_prefix("# TYPE ") {
            let (name, kind) = rest.split_once(' ').unwrap_or((rest, "unknown"));
            let (name, kind) = match kind {
                "counter" => (format!("{name}_total"), "counter"),
                "info" => (format!("{name}_info"), "gauge"),
                "unknown" => (name.to_string(), "untyped"),
                other => (name.to_string(), other),
            };
            if let Some((_, text)) = help.take() {
                // OpenMetrics escapes `"` in HELP; the text format knows only `\\` and `\n` there
                out.push_str(&format!("# HELP {name} {}\n", text.replace("\\\"", "\"")));
            }
            out.push_str(&format!("# TYPE {name} {kind}\n"));
            continue;
        }
        out.push_str(line);
        out.push('\n');
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    const PROMETHEUS_2: &str = "application/openmetrics-text;version=1.0.0,application/openmetrics-text;\
                                version=0.0.1;q=0.75,text/plain;version=0.0.4;q=0.5,*/*;q=0.1";

    #[test]
    fn negotiation_follows_the_accept_header() {
        assert_eq!(Format::negotiate(None), Format::Text);
        assert_eq!(Format::negotiate(Some("*/*")), Format::Text);
        assert_eq!(Format::negotiate(Some("text/plain;version=0.0.4")), Format::Text);
        assert_eq!(Format::negotiate(Some(PROMETHEUS_2)), Format::OpenMetrics);
        assert_eq!(Format::negotiate(Some("application/openmetrics-text")), Format::OpenMetrics);
        assert_eq!(Format::negotiate(Some("Application/OpenMetrics-Text; version=\"1.0.0\"")), Format::OpenMetrics);
        // a version we do not write, a refusal, and a preference for the text format
        assert_eq!(Format::negotiate(Some("application/openmetrics-text;version=2.0.0")), Format::Text);
        assert_eq!(Format::negotiate(Some("application/openmetrics-text;q=0")), Format::Text);
        assert_eq!(Format::negotiate(Some("application/openmetrics-text;q=0.4,text/plain;q=0.9")), Format::Text);
        assert_eq!(Format::negotiate(Some("text/plain;q=0.5,application/openmetrics-text;q=0.5")), Format::OpenMetrics);
    }

    #[test]
    fn the_text_format_renames_counters_and_drops_units_and_eof() {
        let om = "# HELP hydrolens_polls Poll cycles run\n# TYPE hydrolens_polls counter\n\
                  hydrolens_polls_total{drive=\"a\"} 3\n\
                  # HELP hydrolens_omega_radians_per_second Measured \\\"speed\\\"\n\
                  # TYPE hydrolens_omega_radians_per_second gauge\n\
                  # UNIT hydrolens_omega_radians_per_second radians_per_second\n\
                  hydrolens_omega_radians_per_second{drive=\"a\"} 1.5\n# HELP x_build Build\n# TYPE x_build info\n\
                  x_build_info{v=\"1\"} 1\n# EOF\n";
        let text = openmetrics_to_text(om);
        assert_eq!(
            text,
            "# HELP hydrolens_polls_total Poll cycles run\n# TYPE hydrolens_polls_total counter\n\
             hydrolens_polls_total{drive=\"a\"} 3\n\
             # HELP hydrolens_omega_radians_per_second Measured \"speed\"\n\
             # TYPE hydrolens_omega_radians_per_second gauge\nhydrolens_omega_radians_per_second{drive=\"a\"} 1.5\n\
             # HELP x_build_info Build\n# TYPE x_build_info gauge\nx_build_info{v=\"1\"} 1\n"
        );
    }

    #[test]
    fn every_unit_metric_spells_its_unit_out() {
        let (m, r) = Metrics::new();
        let l = DriveLabel { drive: "a".into() };
        m.omega.get_or_create(&l).set(1.0);
        m.inlet_pressure.get_or_create(&l).set(2.0 * PASCALS_PER_BAR);
        let om = encode(&r, Format::OpenMetrics);
        assert!(om.ends_with("# EOF\n"), "{om}");
        assert!(om.contains("# UNIT hydrolens_omega_radians_per_second radians_per_second\n"), "{om}");
        assert!(om.contains("hydrolens_inlet_pressure_pascals{drive=\"a\"} 200000.0\n"), "{om}");
        let text = encode(&r, Format::Text);
        assert!(!text.contains("# UNIT") && !text.contains("# EOF"), "{text}");
        assert!(text.contains("# TYPE hydrolens_http_auth_failures_total counter\n"), "{text}");
    }
}

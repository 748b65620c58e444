//! The Prometheus outlet: the drives' families, read from their snapshots at each scrape (a prometheus-client
//! [`Collector`]), and the exposition in the format the scraper asks for (OpenMetrics or the Prometheus text format
//! 0.0.4). One registry, families labelled by drive, names in base units.
//!
//! An outlet of the service, on the top floor beside [`crate::mqtt`] and [`crate::http`] (see the crate's
//! `# Layout`): it reads [`DriveSnapshot`]s, what the poll loops publish, and the poll loops never touch it. The
//! condition thread's families, the MQTT publisher's and the HTTP side's are registered in the same registry by
//! their owners.

use std::sync::Arc;

use prometheus_client::collector::Collector;
use prometheus_client::encoding::{DescriptorEncoder, EncodeLabelSet, EncodeMetric, MetricEncoder, NoLabelSet};
use prometheus_client::metrics::MetricType;
use prometheus_client::metrics::counter::ConstCounter;
use prometheus_client::metrics::gauge::ConstGauge;
use prometheus_client::registry::{Registry, Unit};

use crate::service::state::ERROR_KINDS;
use crate::service::timing::PERIOD_BOUNDS_S;
use crate::service::{DriveSnapshot, DriveState, ServiceState};

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct DriveLabel {
    drive: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct ErrorLabels {
    drive: String,
    kind: &'static str,
}

/// Unit suffixes spelt out, as the Prometheus naming conventions ask (docs/metrics.md lists the old names).
const RAD_S: &str = "radians_per_second";
const KG_M2: &str = "kilogram_square_meters";
const NM_S_RAD: &str = "newton_meter_seconds_per_radian";

/// Pascals per bar: the registers carry bar, the metrics the SI unit.
pub const PASCALS_PER_BAR: f64 = 1e5;

/// Registers the drives' families in the service's registry.
pub fn register(service: &ServiceState) {
    service.registry().register_collector(Box::new(Drives(service.drives.clone())));
}

/// The exposition of the service's registry in `format`.
pub fn exposition(service: &ServiceState, format: Format) -> String {
    encode(&service.registry(), format)
}

/// The drives' families, each series read from the drive's snapshot at the scrape.
struct Drives(Vec<Arc<DriveState>>);

impl std::fmt::Debug for Drives {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_list().entries(self.0.iter().map(|d| &d.name)).finish()
    }
}

/// One series' value.
enum Value {
    Count(u64),
    Int(i64),
    Float(f64),
}

/// A family's name, help and unit.
struct Desc(&'static str, &'static str, Option<Unit>);

fn desc(name: &'static str, help: &'static str) -> Desc {
    Desc(name, help, None)
}

fn with_unit(name: &'static str, help: &'static str, unit: Unit) -> Desc {
    Desc(name, help, Some(unit))
}

/// A unit prometheus-client has no variant for, by the name the series ends in.
fn other(unit: &str) -> Unit {
    Unit::Other(unit.to_string())
}

/// A drive's series of one family; None: no series (nothing measured yet, say).
type Read = fn(&DriveSnapshot) -> Option<Value>;

/// The link's counts and state, in the order they are exposed.
fn link_families() -> Vec<(Desc, MetricType, Read)> {
    use MetricType::{Counter, Gauge};
    use Value::{Count, Int};
    vec![
        (desc("polls", "Poll cycles run"), Counter, |s| Some(Count(s.link.polls))),
        (desc("reconnects", "Modbus connections re-opened after a failure"), Counter, |s| {
            Some(Count(s.link.reconnects))
        }),
        (desc("rejected_samples", "Samples out of range or not finite, never given to the estimator"), Counter, |s| {
            Some(Count(s.link.rejected_samples))
        }),
        (desc("stale_samples", "Reads whose sample counter had not moved"), Counter, |s| {
            Some(Count(s.link.stale_samples))
        }),
        (desc("writes", "Modbus write requests sent"), Counter, |s| Some(Count(s.link.writes))),
        (desc("writes_refused", "Setpoint writes the device refused or never answered"), Counter, |s| {
            Some(Count(s.link.writes_refused))
        }),
        (
            desc("slow_writes", "Setpoint writes that took more than half the poll period (the loop overruns)"),
            Counter,
            |s| Some(Count(s.link.slow_writes)),
        ),
        (desc("trips", "Times the drive reported a fault or comm-loss trip"), Counter, |s| Some(Count(s.link.trips))),
        (desc("loop_overruns", "Poll cycles that took longer than the poll period"), Counter, |s| {
            Some(Count(s.timing.overruns))
        }),
        (desc("stale", "1 while the drive's data are stale"), Gauge, |s| Some(Int(i64::from(s.link.stale)))),
        (desc("link_up", "1 while the Modbus connection is open and answering"), Gauge, |s| {
            Some(Int(i64::from(s.link.connected)))
        }),
    ]
}

/// The loop's jitter, the last sample's measured signals, the estimates and what the data say of them, the
/// setpoint and the target, in the order they are exposed.
fn signal_families() -> Vec<(Desc, MetricType, Read)> {
    use MetricType::Gauge;
    use Value::Float;
    vec![
        (
            with_unit("loop_jitter_p50", "Median |period − poll period| over the last 1000 cycles", Unit::Seconds),
            Gauge,
            |s| Some(Float(s.timing.jitter_p50_ms * 1e-3)),
        ),
        (
            with_unit(
                "loop_jitter_p99",
                "99th percentile |period − poll period| over the last 1000 cycles",
                Unit::Seconds,
            ),
            Gauge,
            |s| Some(Float(s.timing.jitter_p99_ms * 1e-3)),
        ),
        (with_unit("inlet_pressure", "Measured inlet pressure", other("pascals")), Gauge, |s| {
            measured(s).map(|m| Float(m.p_in_bar * PASCALS_PER_BAR))
        }),
        (with_unit("outlet_pressure", "Measured outlet pressure", other("pascals")), Gauge, |s| {
            measured(s).map(|m| Float(m.p_out_bar * PASCALS_PER_BAR))
        }),
        (with_unit("drive_frequency", "Output frequency the drive reports", other("hertz")), Gauge, |s| {
            measured(s).map(|m| Float(m.f_drive_hz))
        }),
        (with_unit("omega", "Measured shaft speed", other(RAD_S)), Gauge, |s| {
            measured(s).map(|m| Float(m.omega_rad_s))
        }),
        (with_unit("omega_hat", "Estimated shaft speed", other(RAD_S)), Gauge, |s| {
            estimate(s).map(|e| Float(e.omega_hat_rad_s))
        }),
        (with_unit("load_hat", "Estimated load torque", other("newton_meters")), Gauge, |s| {
            estimate(s).map(|e| Float(e.load_hat_nm))
        }),
        (with_unit("inertia_hat", "Estimated inertia J", other(KG_M2)), Gauge, |s| {
            estimate(s).map(|e| Float(e.inertia_hat_kg_m2))
        }),
        (
            with_unit("inertia_sd", "Standard deviation of the estimated J (0: taken from the model)", other(KG_M2)),
            Gauge,
            |s| estimate(s).map(|e| Float(e.inertia_sd_kg_m2)),
        ),
        (with_unit("viscous_hat", "Estimated viscous friction B", other(NM_S_RAD)), Gauge, |s| {
            estimate(s).map(|e| Float(e.viscous_hat_nm_s_rad))
        }),
        (
            with_unit("viscous_sd", "Standard deviation of the estimated B (0: taken from the model)", other(NM_S_RAD)),
            Gauge,
            |s| estimate(s).map(|e| Float(e.viscous_sd_nm_s_rad)),
        ),
        (
            desc(
                "inertia_identified",
                "J: 1 identified, 0 too little excitation, -1 nominal predicts as well, -2 not separable from the load, -3 the model's, -5 a load that moves with the acceleration",
            ),
            Gauge,
            |s| estimate(s).map(|e| Float(e.inertia_identified)),
        ),
        (
            desc(
                "viscous_identified",
                "B: 1 identified, 0 too little excitation, -1 nominal predicts as well, -2 not separable from the load, -3 the model's, -4 friction or a load proportional to the speed, -5 a load that moves with the acceleration",
            ),
            Gauge,
            |s| estimate(s).map(|e| Float(e.viscous_identified)),
        ),
        (
            desc(
                "load_character",
                "Load: 0 unknown, 1 steady, 2 stepping, 3 periodic in time, 4 periodic in shaft angle, 5 following the speed, 6 random",
            ),
            Gauge,
            |s| estimate(s).map(|e| Float(e.load_character)),
        ),
        (
            desc(
                "drive_not_following",
                "1 while the drive does not follow its setpoints (local mode, not ready or not running)",
            ),
            Gauge,
            |s| measured(s).map(|_| Float(if s.status.not_following { 1.0 } else { 0.0 })),
        ),
        (
            desc(
                "drive_tripped",
                "1 while the drive is tripped: it reports a fault or a comm-loss trip, or (writing modes) a trip this service latched has not been reset",
            ),
            Gauge,
            |s| measured(s).map(|_| Float(if s.tripped { 1.0 } else { 0.0 })),
        ),
        (
            desc(
                "drive_another_master",
                "1 while another master writes the drive (its watchdog register read back values this service never wrote): nothing is written until a reset",
            ),
            Gauge,
            |s| measured(s).map(|_| Float(if s.status.another_master { 1.0 } else { 0.0 })),
        ),
        (with_unit("setpoint", "Last frequency setpoint written", other("hertz")), Gauge, |s| s.setpoint_hz.map(Float)),
        (with_unit("target_omega", "Speed target", other(RAD_S)), Gauge, |s| Some(Float(s.target_omega_rad_s))),
    ]
}

fn measured(s: &DriveSnapshot) -> Option<crate::service::Measured> {
    s.sample
}

fn estimate(s: &DriveSnapshot) -> Option<crate::estimator::Estimate> {
    s.estimate
}

/// The recorder's state and losses, where the drive records.
fn recording_families() -> Vec<(Desc, MetricType, Read)> {
    use MetricType::{Counter, Gauge};
    use Value::{Count, Int};
    vec![
        (desc("recording_ok", "1 while the drive's rows reach the disk"), Gauge, |s| {
            s.recording.as_ref().map(|r| Int(i64::from(r.ok)))
        }),
        (desc("recording_errors", "Recording write, flush or open failures"), Counter, |s| {
            s.recording.as_ref().map(|r| Count(r.errors))
        }),
        (desc("recording_rows_lost", "Rows not recorded: writing failed, or the open file was lost"), Counter, |s| {
            s.recording.as_ref().map(|r| Count(r.rows_lost))
        }),
        (
            desc(
                "recording_files_lost",
                "Open recordings lost while written (deleted, their directory removed, or replaced)",
            ),
            Counter,
            |s| s.recording.as_ref().map(|r| Count(r.files_lost)),
        ),
        (
            desc("recording_files_deleted", "Old recordings deleted by retention (max_total_mb, keep_days)"),
            Counter,
            |s| s.recording.as_ref().map(|r| Count(r.files_deleted)),
        ),
        (
            desc("recording_files_compressed", "Closed recordings compressed to .csv.gz (recording.compress)"),
            Counter,
            |s| s.recording.as_ref().map(|r| Count(r.files_compressed)),
        ),
    ]
}

/// A family's descriptor, its help ending with the full stop the registry adds to the help of a family it holds.
fn describe<'s>(
    encoder: &'s mut DescriptorEncoder,
    name: &'s str,
    help: &str,
    unit: Option<&'s Unit>,
    kind: MetricType,
) -> Result<MetricEncoder<'s>, std::fmt::Error> {
    encoder.encode_descriptor(name, &format!("{help}."), unit, kind)
}

/// Writes one family: its descriptor, then each drive's series.
fn family(
    encoder: &mut DescriptorEncoder,
    snapshots: &[DriveSnapshot],
    Desc(name, help, unit): &Desc,
    kind: MetricType,
    read: Read,
) -> std::fmt::Result {
    let mut metric = describe(encoder, name, help, unit.as_ref(), kind)?;
    for s in snapshots {
        let Some(value) = read(s) else { continue };
        let label = DriveLabel { drive: s.name.clone() };
        let series = metric.encode_family(&label)?;
        match value {
            Value::Count(n) => ConstCounter::new(n).encode(series)?,
            Value::Int(i) => ConstGauge::new(i).encode(series)?,
            Value::Float(x) => ConstGauge::new(x).encode(series)?,
        }
    }
    Ok(())
}

impl Collector for Drives {
    fn encode(&self, mut encoder: DescriptorEncoder) -> std::fmt::Result {
        let snapshots: Vec<DriveSnapshot> = self.0.iter().map(|d| d.snapshot()).collect();
        let mut links = link_families().into_iter();
        // polls first, then the errors by kind (every kind from the start, at 0), then the rest of the link's
        if let Some((d, kind, read)) = links.next() {
            family(&mut encoder, &snapshots, &d, kind, read)?;
        }
        let mut errors = describe(&mut encoder, "errors", "Failed Modbus calls, by kind", None, MetricType::Counter)?;
        for s in &snapshots {
            for (kind, n) in ERROR_KINDS.iter().zip(s.link.errors_by_kind) {
                let label = ErrorLabels { drive: s.name.clone(), kind };
                ConstCounter::new(n).encode(errors.encode_family(&label)?)?;
            }
        }
        for (d, kind, read) in links {
            family(&mut encoder, &snapshots, &d, kind, read)?;
        }
        let mut periods = describe(
            &mut encoder,
            "loop_period",
            "Time between poll cycle starts",
            Some(&Unit::Seconds),
            MetricType::Histogram,
        )?;
        for s in &snapshots {
            histogram(periods.encode_family(&DriveLabel { drive: s.name.clone() })?, s)?;
        }
        for (d, kind, read) in signal_families().into_iter().chain(recording_families()) {
            family(&mut encoder, &snapshots, &d, kind, read)?;
        }
        Ok(())
    }
}

/// A drive's loop periods since the start.
fn histogram(mut series: MetricEncoder, s: &DriveSnapshot) -> std::fmt::Result {
    let p = &s.timing.periods;
    let bounds = PERIOD_BOUNDS_S.iter().copied().chain(std::iter::once(f64::INFINITY));
    let buckets: Vec<(f64, u64)> = bounds.zip(p.counts).collect();
    series.encode_histogram::<NoLabelSet>(p.sum_s, p.count(), &buckets, None)
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
        use crate::control::Mode;
        use crate::service::Measured;
        let mut snapshot = DriveSnapshot::before_first_poll("a".into(), Mode::Monitor, "127.0.0.1:502".into(), 1, 0.0);
        let nan = f64::NAN;
        snapshot.sample = Some(Measured {
            t_s: 0.0,
            f_set_hz: nan,
            f_drive_hz: 0.0,
            p_in_bar: 2.0,
            p_out_bar: 0.0,
            omega_rad_s: 1.0,
            drive_power_w: nan,
        });
        snapshot.link.errors_by_kind[1] = 3;
        let drive = Arc::new(DriveState::new(snapshot, 100.0, std::time::Duration::from_secs(1), 4));
        let mut r = Registry::with_prefix("hydrolens");
        r.register_collector(Box::new(Drives(vec![drive])));
        let om = encode(&r, Format::OpenMetrics);
        assert!(om.ends_with("# EOF\n"), "{om}");
        assert!(om.contains("# UNIT hydrolens_omega_radians_per_second radians_per_second\n"), "{om}");
        assert!(om.contains("hydrolens_inlet_pressure_pascals{drive=\"a\"} 200000.0\n"), "{om}");
        assert!(om.contains("hydrolens_errors_total{drive=\"a\",kind=\"timeout\"} 3\n"), "{om}");
        assert!(om.contains("hydrolens_loop_period_seconds_bucket{le=\"0.0001\",drive=\"a\"} 0\n"), "{om}");
        // nothing estimated yet: the family is described, with no series
        assert!(om.contains("# TYPE hydrolens_omega_hat_radians_per_second gauge\n"), "{om}");
        assert!(!om.contains("hydrolens_omega_hat_radians_per_second{"), "{om}");
        let text = encode(&r, Format::Text);
        assert!(!text.contains("# UNIT") && !text.contains("# EOF"), "{text}");
        assert!(text.contains("# TYPE hydrolens_polls_total counter\n"), "{text}");
    }
}

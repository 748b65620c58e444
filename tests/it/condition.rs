//! Condition monitoring on a plant that wears: checks of the last 120 s, every 60 s, with the load unknown, as the
//! service will run them (src/condition.rs). Offline here: the test stand simulated, recorded as the service
//! records at 5 ms.

use hydrolens::condition::{self, Limits, Monitor};
use hydrolens::plant::PlantModel;
use hydrolens::recording::Recording;

use crate::noload::as_the_service_records;

const POLL_MS: usize = 5;
const WINDOW_S: f64 = 120.0;
const EVERY_S: f64 = 60.0;

/// The reference plant; with `growth_per_hour` > 0 its internal leakage grows from zero at that rate.
fn plant(growth_per_hour: f64) -> PlantModel {
    let mut text = hydrolens::plant::model::REFERENCE_TOML.to_string();
    if growth_per_hour > 0.0 {
        text.push_str(&format!(
            "\n[effects.internal_leakage]\nl_min_per_bar = 0.0\n\n[wear.internal_leakage]\ngrowth_per_hour = {growth_per_hour}\n"
        ));
    }
    PlantModel::parse(&text, "wearing.toml").expect("valid")
}

/// The rows of `rec` with `from ≤ t_s < to`.
fn window(rec: &Recording, from: f64, to: f64) -> Recording {
    let t = rec.t_s();
    let (a, b) = (t.partition_point(|v| *v < from), t.partition_point(|v| *v < to));
    let names: Vec<String> = rec.names().to_vec();
    let cols = names.iter().map(|n| rec.column(n).expect("column")[a..b].to_vec()).collect();
    Recording::from_columns("window", names, cols)
}

/// Runs the checks over `seconds` of the plant, returning the monitor and the true leakage at each check's
/// window centre.
fn monitor(truth: &PlantModel, seconds: f64, seed: u64, limits: Limits) -> (Monitor, Vec<f64>) {
    let rec = hydrolens::plant::simulate::test_stand(truth, seconds, seed, &mut |_| {}).expect("simulable");
    let rec = as_the_service_records(&rec, POLL_MS, seed);
    let mut m = Monitor::new(limits);
    let mut centres = Vec::new();
    let mut t = WINDOW_S;
    while t <= seconds + 1e-9 {
        let c = condition::check(&window(&rec, t - WINDOW_S, t), &PlantModel::reference(), t, WINDOW_S).expect("check");
        m.push(c);
        centres.push(truth.at(t - WINDOW_S / 2.0).effects.internal_leakage.map_or(0.0, |l| l.l_min_per_bar));
        t += EVERY_S;
    }
    (m, centres)
}

fn leak_limit(limit: f64) -> Limits {
    [("internal_leakage".to_string(), [("l_min_per_bar".to_string(), limit)].into())].into()
}

#[test]
fn a_growing_leak_shows_rising_in_the_checks_and_raises_its_alarm() {
    // 0.3 l/min/bar an hour: 0.035 after 7 minutes; the limit 0.02 is passed near 4 minutes.
    let (m, truth) = monitor(&plant(0.3), 420.0, 3, leak_limit(0.02));
    let fitted: Vec<Option<f64>> = m.checks().map(|c| c.value("internal_leakage", "l_min_per_bar")).collect();
    eprintln!("fitted {fitted:?}\ntruth {truth:?}\nalarms {:?}", m.alarms());
    let last = fitted.last().copied().flatten().expect("the last check names the leak");
    let first = fitted.first().copied().flatten().unwrap_or(0.0);
    assert!(last > first + 0.01, "the leak rises across checks: {fitted:?}");
    let want = *truth.last().expect("checks");
    assert!((last - want).abs() < 0.3 * want, "last check {last} against the window's mean leak {want}");
    let alarms = m.alarms();
    assert_eq!(alarms.len(), 1, "{alarms:?}");
    assert_eq!(alarms[0].effect, "internal_leakage");
    assert!(alarms[0].value > 0.02);
}

#[test]
fn a_clean_plant_gives_no_finding_and_no_alarm() {
    let (m, _) = monitor(&plant(0.0), 240.0, 3, leak_limit(0.02));
    for c in m.checks() {
        assert_eq!(c.findings, serde_json::json!([]), "check at {} s", c.t_s);
    }
    assert!(m.alarms().is_empty());
}

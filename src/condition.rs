//! Condition monitoring: the analysis run on a drive's own recent data, again and again, and alarms when a fitted
//! parameter passes its limit.
//!
//! - [`check`] analyses one window (the load unknown, as in the service's recordings) against the drive's nominal
//!   model and keeps what the analysis JSON says: findings, baseline, improved.
//! - [`Limits`] says, per effect, which parameter is watched and where its limit is. A bulk modulus alarms *below*
//!   its limit (air softens the oil); every other parameter above it.
//! - [`Monitor`] keeps the checks, oldest first, and the alarms. An alarm is raised when a check's value passes the
//!   limit, and clears only when a later check brings it back inside by [`CLEAR_MARGIN`] of the limit, so a value
//!   that wanders around its limit does not chatter. An effect a check does not name is at its nominal value: inside.
//! - [`Store`] appends each check as one JSON line beside the drive's recordings and reads them back, so that a
//!   restart keeps the history (and the alarms, which are the checks replayed).
//!
//! - [`power`] turns the model, the estimates and the fitted effects into a power budget and its energies;
//!   [`trend`] fits a line through a parameter's history and projects when it reaches its limit.
//!
//! Pure but for [`Store`]; the service decides when and on which thread a check runs.

pub mod power;
pub mod trend;

use crate::error::KeyError;
use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::analysis::{self, Analysis, Options};
use crate::error::BadInput;
use crate::plant::PlantModel;
use crate::recording::Recording;

/// An alarm clears when its value is back inside the limit by this fraction of the limit.
pub const CLEAR_MARGIN: f64 = 0.1;

/// Checks kept in memory (and read back from the store) per drive.
pub const KEEP_CHECKS: usize = 500;

/// One check: when it ran (service time, s), on how much data, and what the analysis said.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Check {
    /// The service time (s since the service started) of the window's last sample. It starts again at 0 when the
    /// service restarts; `unix_s` orders checks across restarts.
    pub t_s: f64,
    /// The span of data the check analysed (s): `window_s` of the config, less while the service has not yet
    /// collected a whole window.
    pub window_s: f64,
    /// The analysis JSON's `findings`, `baseline` and `improved`, as the analysis wrote them.
    pub findings: serde_json::Value,
    pub baseline: serde_json::Value,
    pub improved: serde_json::Value,
    /// Wall time the analysis took (s), for the metrics.
    #[serde(default)]
    pub duration_s: f64,
    /// Wall-clock time of the check (s since the Unix epoch): the dashboard's time axis across restarts.
    #[serde(default)]
    pub unix_s: f64,
}

impl Check {
    /// The value a finding of `effect` gives `parameter`, if the check names the effect.
    pub fn value(&self, effect: &str, parameter: &str) -> Option<f64> {
        self.findings.as_array()?.iter().find(|f| f["effect"] == effect)?["parameters"][parameter].as_f64()
    }

    /// The 95 % interval the analysis gives `parameter` of `effect` (its `confidence_intervals`), if the check names
    /// the effect and the analysis could bound it.
    pub fn interval(&self, effect: &str, parameter: &str) -> Option<(f64, f64)> {
        let f = self.findings.as_array()?.iter().find(|f| f["effect"] == effect)?;
        let i = &f["confidence_intervals"][parameter];
        Some((i["low"].as_f64()?, i["high"].as_f64()?)).filter(|(lo, hi)| lo.is_finite() && hi.is_finite() && lo <= hi)
    }

    /// Every fitted effect parameter of the check: (effect, parameter, value).
    pub fn parameters(&self) -> Vec<(String, String, f64)> {
        let mut out = Vec::new();
        for f in self.findings.as_array().into_iter().flatten() {
            let Some(effect) = f["effect"].as_str() else { continue };
            for (k, v) in f["parameters"].as_object().into_iter().flatten() {
                if let Some(v) = v.as_f64() {
                    out.push((effect.to_string(), k.clone(), v));
                }
            }
        }
        out
    }
}

/// Analyses `window` (the drive's last `window_s` of data, load unknown or recorded) against `nominal`.
pub fn check(window: &Recording, nominal: &PlantModel, t_s: f64, window_s: f64) -> Result<Check, BadInput> {
    let started = std::time::Instant::now();
    let a: Analysis = analysis::analyze(window, nominal, &Options::default(), &mut |_| {})?;
    fn json<T: Serialize>(v: &T) -> serde_json::Value {
        serde_json::to_value(v).unwrap_or(serde_json::Value::Null)
    }
    Ok(Check {
        t_s,
        window_s,
        findings: json(&a.findings),
        baseline: json(&a.baseline),
        improved: json(&a.improved),
        duration_s: started.elapsed().as_secs_f64(),
        unix_s: std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0.0, |d| d.as_secs_f64()),
    })
}

/// Whether a parameter alarms above or below its limit.
pub fn alarms_below(parameter: &str) -> bool {
    parameter == "bulk_modulus_bar"
}

/// `[drives.condition.limits]`: effect → (parameter → limit).
pub type Limits = BTreeMap<String, BTreeMap<String, f64>>;

/// Checks the limits' names against the effects catalogue and the analysis's parameter names: the key at fault.
pub fn validate_limits(limits: &Limits, key_prefix: &str) -> Result<(), KeyError> {
    for (effect, params) in limits {
        if !crate::plant::effects::EFFECT_IDS.contains(&effect.as_str()) {
            return Err(KeyError::new(
                format!("{key_prefix}.{effect}"),
                format!("not an effect of the catalogue ({})", crate::plant::effects::EFFECT_IDS.join(", ")),
            ));
        }
        let known = crate::plant::effects::parameter_names(effect);
        for (p, v) in params {
            if !known.contains(&p.as_str()) {
                return Err(KeyError::new(
                    format!("{key_prefix}.{effect}.{p}"),
                    format!("{effect} has {}", known.join(", ")),
                ));
            }
            if !v.is_finite() {
                return Err(KeyError::new(format!("{key_prefix}.{effect}.{p}"), format!("must be finite, got {v}")));
            }
        }
    }
    Ok(())
}

/// A raised alarm.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Alarm {
    pub effect: String,
    pub parameter: String,
    /// The latest check's value.
    pub value: f64,
    pub limit: f64,
    /// The check time (service time, [`Check::t_s`]) at which it was raised.
    pub since_s: f64,
    /// The same instant as wall-clock time (s since the Unix epoch), which survives a restart.
    #[serde(default)]
    pub since_unix_s: f64,
}

/// The checks of one drive and its alarms.
#[derive(Debug, Clone, Default)]
pub struct Monitor {
    limits: Limits,
    checks: std::collections::VecDeque<Check>,
    /// Beside each check: the effects in alarm once it was counted (derived, so replayed rather than stored).
    alarmed: std::collections::VecDeque<Vec<String>>,
    alarms: BTreeMap<(String, String), Alarm>,
    /// Each limited parameter's value when a check does not name its effect (the nominal model's); a parameter
    /// with none (a Stribeck speed of an effect that is off) takes only the checks that name it.
    nominal: BTreeMap<(String, String), f64>,
}

impl Monitor {
    pub fn new(limits: Limits) -> Monitor {
        Monitor { limits, ..Monitor::default() }
    }

    /// As [`Monitor::new`], with the nominal model that says what an unnamed effect's parameter is.
    pub fn with_nominal(limits: Limits, nominal: &PlantModel) -> Monitor {
        let mut values = BTreeMap::new();
        for (effect, params) in &limits {
            for parameter in params.keys() {
                if let Some(v) = nominal_value(nominal, effect, parameter) {
                    values.insert((effect.clone(), parameter.clone()), v);
                }
            }
        }
        Monitor { limits, nominal: values, ..Monitor::default() }
    }

    /// Adds a check (the newest) and updates the alarms from it.
    pub fn push(&mut self, check: Check) {
        for (effect, params) in &self.limits {
            for (parameter, &limit) in params {
                let key = (effect.clone(), parameter.clone());
                let value = check.value(effect, parameter);
                let below = alarms_below(parameter);
                let past = |v: f64| if below { v < limit } else { v > limit };
                let back = |v: f64| {
                    let margin = CLEAR_MARGIN * limit.abs();
                    if below { v > limit + margin } else { v < limit - margin }
                };
                match (self.alarms.get_mut(&key), value) {
                    (Some(a), Some(v)) if !back(v) => a.value = v,
                    (Some(_), _) => {
                        self.alarms.remove(&key);
                    }
                    (None, Some(v)) if past(v) => {
                        let a = Alarm {
                            effect: key.0.clone(),
                            parameter: key.1.clone(),
                            value: v,
                            limit,
                            since_s: check.t_s,
                            since_unix_s: check.unix_s,
                        };
                        self.alarms.insert(key, a);
                    }
                    (None, _) => {}
                }
            }
        }
        self.checks.push_back(check);
        let mut alarmed: Vec<String> = self.alarms.keys().map(|(effect, _)| effect.clone()).collect();
        alarmed.dedup();
        self.alarmed.push_back(alarmed);
        while self.checks.len() > KEEP_CHECKS {
            self.checks.pop_front();
            self.alarmed.pop_front();
        }
    }

    /// The checks, oldest first.
    pub fn checks(&self) -> impl Iterator<Item = &Check> {
        self.checks.iter()
    }

    pub fn last(&self) -> Option<&Check> {
        self.checks.back()
    }

    pub fn alarms(&self) -> Vec<Alarm> {
        self.alarms.values().cloned().collect()
    }

    pub fn limits(&self) -> &Limits {
        &self.limits
    }

    /// Every effect with a limit: its last value, limit, alarm, and its [`trend`] over the checks kept. Times are
    /// the checks' wall-clock times when every check has one (they survive restarts), else their service times.
    pub fn tracked(&self) -> Vec<Tracked> {
        let wall = self.checks.iter().all(|c| c.unix_s > 0.0);
        let time = |c: &Check| if wall { c.unix_s } else { c.t_s };
        let alarms = self.alarms();
        let mut out = Vec::new();
        for (effect, params) in &self.limits {
            for (parameter, &limit) in params {
                let nominal = self.nominal.get(&(effect.clone(), parameter.clone())).copied();
                let value_of = |c: &Check| c.value(effect, parameter).or(nominal);
                let points: Vec<trend::Point> = self
                    .checks
                    .iter()
                    .filter_map(|c| {
                        // the check's own standard error, from the analysis's 95 % interval of the parameter
                        let sd = c.interval(effect, parameter).map(|(lo, hi)| (hi - lo) / (2.0 * 1.96));
                        value_of(c).map(|v| trend::Point { t_s: time(c) - c.window_s / 2.0, value: v, sd })
                    })
                    .collect();
                let last = self.checks.back();
                let window_s = last.map_or(0.0, |c| c.window_s);
                let now_s = last.map_or(0.0, time);
                let below = alarms_below(parameter);
                let tr = trend::trend(&points, limit, below, window_s, now_s);
                let crossing = |s: Option<f64>| s.zip(last).map(|(s, c)| c.unix_s + s);
                out.push(Tracked {
                    effect: effect.clone(),
                    parameter: parameter.clone(),
                    value: last.and_then(value_of),
                    found: last.is_some_and(|c| c.value(effect, parameter).is_some()),
                    nominal,
                    limit,
                    alarms_below: below,
                    alarm: alarms.iter().any(|a| &a.effect == effect && &a.parameter == parameter),
                    crossing_unix_s: crossing(tr.seconds_to_limit),
                    crossing_unix_s_low: crossing(tr.seconds_to_limit_low),
                    crossing_unix_s_high: crossing(tr.seconds_to_limit_high),
                    trend: tr,
                });
            }
        }
        out
    }

    /// The condition JSON of `GET /api/drives/{name}/condition`: the contract's `drive`, `checks` (oldest first)
    /// and `alarms`; beyond it, each check's `alarms` (the effects in alarm after it, for the dashboard's marks),
    /// the `limits`, and `tracked` ([`Monitor::tracked`]).
    pub fn to_json(&self, drive: &str) -> serde_json::Value {
        let checks: Vec<serde_json::Value> = self
            .checks
            .iter()
            .zip(&self.alarmed)
            .map(|(c, alarmed)| {
                let mut v = serde_json::to_value(c).unwrap_or(serde_json::Value::Null);
                if let Some(o) = v.as_object_mut() {
                    o.insert("alarms".into(), serde_json::json!(alarmed));
                }
                v
            })
            .collect();
        serde_json::json!({
            "drive": drive,
            "checks": checks,
            "alarms": self.alarms(),
            "limits": self.limits,
            "tracked": self.tracked(),
        })
    }
}

/// An effect with a limit, as `/api/status` (`condition[]`), the condition JSON and the dashboard show it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Tracked {
    pub effect: String,
    pub parameter: String,
    /// The last check's value (the nominal one when it did not name the effect); null before the first check.
    pub value: Option<f64>,
    /// True when the last check named the effect; false: checked, nothing found.
    pub found: bool,
    /// The value a check that does not name the effect stands for (the nominal model's; null when there is none).
    pub nominal: Option<f64>,
    pub limit: f64,
    pub alarms_below: bool,
    pub alarm: bool,
    pub trend: trend::Trend,
    /// The projected crossing and its 95 % interval as wall-clock time (s since the Unix epoch).
    pub crossing_unix_s: Option<f64>,
    pub crossing_unix_s_low: Option<f64>,
    pub crossing_unix_s_high: Option<f64>,
}

/// What `parameter` of `effect` is in `model`: its value when the effect is on; when it is off, the value that
/// means "nothing" (0 for a leak, a friction, an offset, a dead time, a slip; the model's bulk modulus for
/// entrained air); None where "off" has no value (a Stribeck speed).
pub fn nominal_value(model: &PlantModel, effect: &str, parameter: &str) -> Option<f64> {
    let on = serde_json::to_value(model.effects).ok()?;
    if let Some(v) = on.get(effect).and_then(|e| e.get(parameter)).and_then(serde_json::Value::as_f64) {
        return Some(v);
    }
    match (effect, parameter) {
        ("entrained_air", "bulk_modulus_bar") => model.hydraulics.as_ref().map(|h| h.bulk_modulus_bar),
        ("stribeck_friction", "speed_rad_s") => None,
        ("stribeck_friction", "breakaway_nm") => Some(model.effects.coulomb_friction.map_or(0.0, |c| c.torque_nm)),
        _ => Some(0.0),
    }
}

/// The longest line of a condition history read: a check is a few kB.
const MAX_CHECK_LINE_BYTES: usize = 1 << 16;

/// A drive's checks as JSON lines beside its recordings: `<dir>/<drive>.condition.jsonl`.
#[derive(Debug, Clone)]
pub struct Store {
    path: PathBuf,
}

impl Store {
    pub fn new(dir: &Path, drive: &str) -> Store {
        Store { path: dir.join(format!("{drive}.condition.jsonl")) }
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Appends one check as a line (created on first use).
    pub fn append(&self, check: &Check) -> std::io::Result<()> {
        let mut line = serde_json::to_vec(check).map_err(std::io::Error::other)?;
        line.push(b'\n');
        let mut f = std::fs::OpenOptions::new().create(true).append(true).open(&self.path)?;
        f.write_all(&line)?;
        f.flush()
    }

    /// The last [`KEEP_CHECKS`] checks, oldest first; none when the file does not exist. A line that does not parse
    /// (a cut last line after a crash, say) is skipped with a warning naming it: the history is advice, not a
    /// contract, and one bad line must not cost the rest.
    pub fn load(&self) -> std::io::Result<Vec<Check>> {
        self.load_counting().map(|(checks, _)| checks)
    }

    /// As [`Store::load`], and how many lines the file holds (to know when to [`Store::rewrite`] it).
    pub fn load_counting(&self) -> std::io::Result<(Vec<Check>, usize)> {
        let file = match std::fs::File::open(&self.path) {
            Ok(f) => f,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok((Vec::new(), 0)),
            Err(e) => return Err(e),
        };
        use std::io::{BufRead, Read};
        let mut checks = std::collections::VecDeque::new();
        let mut lines = 0;
        let mut reader = std::io::BufReader::new(file);
        let mut line = Vec::new();
        // bytes, not text: a line that is not UTF-8 (a disk error, an editor's encoding) is one bad line too; read
        // as text it ended the load, and the whole history was lost. A line is read to at most
        // [`MAX_CHECK_LINE_BYTES`] and the rest of it skipped: 300 MB of NUL bytes were read in whole at start
        loop {
            line.clear();
            let read = (&mut reader).take(MAX_CHECK_LINE_BYTES as u64 + 1).read_until(b'\n', &mut line)?;
            if read == 0 {
                break;
            }
            lines += 1;
            let i = lines - 1;
            if line.len() > MAX_CHECK_LINE_BYTES && line.last() != Some(&b'\n') {
                let rest = reader.skip_until(b'\n')?;
                tracing::warn!(file = %self.path.display(), line = i + 1, bytes = line.len() + rest,
                    "condition history: line skipped, longer than any check");
                continue;
            }
            if line.trim_ascii().is_empty() {
                continue;
            }
            match serde_json::from_slice::<Check>(&line) {
                Ok(c) => {
                    checks.push_back(c);
                    if checks.len() > KEEP_CHECKS {
                        checks.pop_front();
                    }
                }
                Err(e) => {
                    tracing::warn!(file = %self.path.display(), line = i + 1, error = %e, "condition history: line skipped")
                }
            }
        }
        Ok((checks.into(), lines))
    }

    /// Replaces the file with `checks` (written beside it, then renamed over it), so that it stays bounded: the
    /// service rewrites it with the checks it keeps once it holds twice as many lines.
    pub fn rewrite<'a>(&self, checks: impl Iterator<Item = &'a Check>) -> std::io::Result<()> {
        let tmp = self.path.with_extension("jsonl.tmp");
        let mut out = std::io::BufWriter::new(std::fs::File::create(&tmp)?);
        for c in checks {
            serde_json::to_writer(&mut out, c).map_err(std::io::Error::other)?;
            out.write_all(b"\n")?;
        }
        out.into_inner().map_err(|e| e.into_error())?.sync_all()?;
        std::fs::rename(&tmp, &self.path)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn check_with(t_s: f64, leak: Option<f64>) -> Check {
        let findings = match leak {
            Some(v) => serde_json::json!([{"effect": "internal_leakage", "parameters": {"l_min_per_bar": v}}]),
            None => serde_json::json!([]),
        };
        Check {
            t_s,
            window_s: 120.0,
            findings,
            baseline: serde_json::Value::Null,
            improved: serde_json::Value::Null,
            duration_s: 0.0,
            unix_s: 1.7e9 + t_s,
        }
    }

    fn leak_limit(limit: f64) -> Limits {
        [("internal_leakage".to_string(), [("l_min_per_bar".to_string(), limit)].into())].into()
    }

    #[test]
    fn an_alarm_rises_past_its_limit_holds_inside_the_margin_and_clears_beyond_it() {
        let mut m = Monitor::new(leak_limit(0.02));
        let mut alarms_after = |t: f64, leak: Option<f64>| {
            m.push(check_with(t, leak));
            m.alarms()
        };
        assert!(alarms_after(60.0, None).is_empty());
        assert!(alarms_after(120.0, Some(0.015)).is_empty());
        let raised = alarms_after(180.0, Some(0.025));
        assert_eq!(raised.len(), 1);
        assert_eq!((raised[0].since_s, raised[0].value, raised[0].limit), (180.0, 0.025, 0.02));
        // Just inside the limit, within the margin: still raised, value updated, `since` kept.
        let held = alarms_after(240.0, Some(0.019));
        assert_eq!((held[0].since_s, held[0].value), (180.0, 0.019));
        assert!(alarms_after(300.0, Some(0.017)).is_empty(), "0.017 is back inside by more than 10 %");
        assert_eq!(m.checks().count(), 5);
        let json = m.to_json("pump1");
        let marks: Vec<usize> = json["checks"]
            .as_array()
            .expect("checks")
            .iter()
            .map(|c| c["alarms"].as_array().map_or(9, Vec::len))
            .collect();
        assert_eq!(marks, [0, 0, 1, 1, 0], "each check says which effects were in alarm after it");
        assert_eq!(json["checks"][0]["t_s"], 60.0, "oldest first");
    }

    #[test]
    fn tracked_effects_say_nothing_found_as_the_nominal_value_and_project_a_rising_leak() {
        let mut m = Monitor::with_nominal(leak_limit(0.05), &PlantModel::reference());
        m.push(check_with(120.0, None));
        let t = &m.tracked()[0];
        assert_eq!((t.value, t.found, t.alarm), (Some(0.0), false, false), "checked, nothing found: the nominal 0");
        assert_eq!(t.trend.state, trend::TrendState::TooFewChecks);
        // the leak grows 1e-4 per s from t = 0 (each check's value is its window's mean, at t − 60 s)
        for k in 1..5 {
            let t = 120.0 + 60.0 * k as f64;
            m.push(check_with(t, Some(1e-4 * (t - 60.0))));
        }
        let t = &m.tracked()[0];
        assert_eq!(t.trend.state, trend::TrendState::Rising, "{t:?}");
        let last = m.last().expect("checks");
        // true crossing at 500 s; the first check's 0 pulls the line a little
        let at = last.t_s + t.trend.seconds_to_limit.expect("crossing");
        assert!((at - 500.0).abs() < 50.0, "{at}");
        let json = m.to_json("pump1");
        assert_eq!(json["tracked"][0]["trend"]["state"], "rising");
        assert!(json["tracked"][0]["crossing_unix_s"].as_f64().is_some());
    }

    #[test]
    fn a_bulk_modulus_alarms_below_its_limit() {
        let limits: Limits = [("entrained_air".to_string(), [("bulk_modulus_bar".to_string(), 8000.0)].into())].into();
        let mut m = Monitor::new(limits);
        let air = |t: f64, k: f64| Check {
            findings: serde_json::json!([{"effect": "entrained_air", "parameters": {"bulk_modulus_bar": k}}]),
            ..check_with(t, None)
        };
        m.push(air(60.0, 12000.0));
        assert!(m.alarms().is_empty());
        m.push(air(120.0, 6000.0));
        assert_eq!(m.alarms().len(), 1);
        m.push(air(180.0, 8500.0));
        assert_eq!(m.alarms().len(), 1, "8500 is within 10 % of 8000");
        m.push(air(240.0, 9000.0));
        assert!(m.alarms().is_empty());
    }

    #[test]
    fn the_store_keeps_checks_across_a_restart_and_skips_a_cut_line() {
        let dir = tempfile::tempdir().expect("tempdir");
        let store = Store::new(dir.path(), "pump1");
        assert!(store.load().expect("no file yet").is_empty());
        let a = check_with(60.0, None);
        let b = check_with(120.0, Some(0.03));
        store.append(&a).expect("append");
        // a line that is not UTF-8 (it cost the whole history: 0 of 5 checks came back)
        std::fs::OpenOptions::new()
            .append(true)
            .open(store.path())
            .and_then(|mut f| f.write_all(b"{\"t_s\": 90.0, \"note\": \"\xff\xfe\"}\n"))
            .expect("a Latin-1 line");
        store.append(&b).expect("append");
        std::fs::OpenOptions::new()
            .append(true)
            .open(store.path())
            .and_then(|mut f| f.write_all(b"{\"t_s\": 180.0, \"wind"))
            .expect("cut line");
        let (back, lines) = store.load_counting().expect("loads");
        assert_eq!(back, vec![a.clone(), b.clone()]);
        assert_eq!(lines, 4, "the bad and the cut line count");
        store.rewrite(back.iter().skip(1)).expect("rewrite");
        assert_eq!(store.load_counting().expect("loads"), (vec![b], 1), "rewritten with what was given");
        store.rewrite([a.clone(), check_with(120.0, Some(0.03))].iter()).expect("rewrite");
        let back = store.load().expect("loads");
        // Replaying the history gives the alarms back.
        let mut m = Monitor::new(leak_limit(0.02));
        back.into_iter().for_each(|c| m.push(c));
        assert_eq!(m.alarms().len(), 1);
    }

    /// A history of 300 MB of NUL bytes (one line) was read in whole at start: now a line is read to at most
    /// [`MAX_CHECK_LINE_BYTES`], the rest skipped, and the checks around it kept.
    #[test]
    fn a_line_longer_than_any_check_is_skipped_without_holding_it() {
        let dir = tempfile::tempdir().expect("tempdir");
        let store = Store::new(dir.path(), "pump1");
        let a = check_with(60.0, None);
        store.append(&a).expect("append");
        std::fs::OpenOptions::new()
            .append(true)
            .open(store.path())
            .and_then(|mut f| f.write_all(&vec![0u8; 4 * MAX_CHECK_LINE_BYTES + 7]).and_then(|()| f.write_all(b"\n")))
            .expect("a long line");
        let b = check_with(120.0, Some(0.03));
        store.append(&b).expect("append");
        assert_eq!(store.load_counting().expect("loads"), (vec![a, b], 3));
    }

    #[test]
    fn limits_name_the_key_at_fault() {
        assert!(validate_limits(&leak_limit(0.02), "drives.condition.limits").is_ok());
        let bad_effect: Limits = [("leak".to_string(), BTreeMap::new())].into();
        let KeyError { key, .. } = validate_limits(&bad_effect, "drives.condition.limits").expect_err("unknown effect");
        assert_eq!(key, "drives.condition.limits.leak");
        let bad_param: Limits = [("dead_time".to_string(), [("seconds".to_string(), 1.0)].into())].into();
        let KeyError { key, message: msg } =
            validate_limits(&bad_param, "drives.condition.limits").expect_err("unknown parameter");
        assert_eq!(key, "drives.condition.limits.dead_time.seconds");
        assert!(msg.contains("ms"), "{msg}");
    }
}

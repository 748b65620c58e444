//! Load-torque profiles the simulator can apply (`[load]` of the plant model): functions of time and, for the
//! speed- and angle-dependent kinds, of the motor shaft's state.

use crate::error::KeyError;
use serde::{Deserialize, Serialize};

/// `[load]`: what the load torque T_L(t, ω, θ) is (ω the motor's speed, θ its shaft angle). `recorded` means "taken from a recording" (estimate, analyze) or,
/// for the test-stand run of `simulate`, the built-in brake-load steps; `unknown` says that no recording has it.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize, Default)]
#[serde(tag = "kind", rename_all = "snake_case", try_from = "LoadTable")]
pub enum LoadSpec {
    /// No load torque.
    None,
    /// A constant torque.
    Constant { torque_nm: f64 },
    /// Levels applied in turn, each for `period_s`, cycling.
    Steps { levels_nm: Vec<f64>, period_s: f64 },
    /// From `from_nm` to `to_nm` linearly over `duration_s`, starting at `start_s`; held before and after.
    Ramp { from_nm: f64, to_nm: f64, start_s: f64, duration_s: f64 },
    /// A slowly increasing load (the paper's Fig. 3): `start_nm + rate_nm_per_s·t`, at most `max_nm`.
    Trend { start_nm: f64, rate_nm_per_s: f64, max_nm: f64 },
    /// `mean_nm + amplitude_nm·sin(2πt/period_s)`.
    Sine { mean_nm: f64, amplitude_nm: f64, period_s: f64 },
    /// A load that depends on speed: `constant_nm + linear_nm_s_rad·ω + quadratic_nm_s2_rad2·ω·|ω|` (a load ∝ ω is
    /// the linear term, a centrifugal fan or pump the quadratic one).
    Speed { constant_nm: f64, linear_nm_s_rad: f64, quadratic_nm_s2_rad2: f64 },
    /// A fan or centrifugal pump said the plant engineer's way: `torque_nm` at `at_rad_s`, ∝ ω·|ω|.
    Centrifugal { torque_nm: f64, at_rad_s: f64 },
    /// A reciprocating machine behind a gearbox: `mean_nm + amplitude_nm·sin(cycles_per_rev·θ)`, periodic in the
    /// motor's shaft angle θ, so that its period in time follows the speed. `cycles_per_rev` is 1/gear ratio (may be
    /// below 1, and need not be a whole number).
    ShaftAngle { mean_nm: f64, amplitude_nm: f64, cycles_per_rev: f64 },
    /// A smooth random load that never repeats: `mean_nm` plus value noise of standard deviation about `sd_nm`,
    /// smooth over `correlation_s`; a pure function of t and `seed`, so that every run of a seed shows the same load.
    Random { mean_nm: f64, sd_nm: f64, correlation_s: f64, seed: u64 },
    /// `base_nm` plus half-sine pulses of height `peak_nm` and width `width_s`, one in each `mean_interval_s`, at a
    /// pseudo-random place within it drawn from `seed` (deterministic, as `random`).
    Impacts { base_nm: f64, peak_nm: f64, width_s: f64, mean_interval_s: f64, seed: u64 },
    /// `mean_nm + Σ amplitudes_nm[i]·sin(2πt/periods_s[i])`: sines of unrelated periods.
    Sines { mean_nm: f64, amplitudes_nm: Vec<f64>, periods_s: Vec<f64> },
    /// From a recording (the `load_nm` column), or the test stand's brake program.
    #[default]
    Recorded,
    /// Not measured (no torque transducer, as on most plants): `analyze` finds what the flow balance shows and
    /// names nothing that the load could hide. In `simulate`/`sim`/`demo`, the test stand's brake program.
    Unknown,
}

/// The kinds of `[load]`, by name.
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(rename_all = "snake_case")]
enum LoadKind {
    None,
    Constant,
    Steps,
    Ramp,
    Trend,
    Sine,
    Speed,
    Centrifugal,
    ShaftAngle,
    Random,
    Impacts,
    Sines,
    Recorded,
    Unknown,
}

macro_rules! load_table {
    ($($key:ident: $ty:ty),* $(,)?) => {
        /// `[load]` as written: its kind and every key some kind takes, each read where it stands, so that a key of
        /// the wrong type or an unknown one is reported at its line and column (as an internally tagged enum,
        /// `[load]` was read into a buffer first, and its errors pointed at the table; unknown keys beside a kind
        /// without parameters were ignored).
        #[derive(Deserialize)]
        #[serde(deny_unknown_fields)]
        struct LoadTable {
            kind: LoadKind,
            $($key: Option<$ty>,)*
        }

        impl LoadTable {
            /// The keys given, besides `kind`.
            fn given(&self) -> Vec<&'static str> {
                [$((stringify!($key), self.$key.is_some()),)*].into_iter().filter(|k| k.1).map(|k| k.0).collect()
            }
        }
    };
}

load_table! {
    torque_nm: f64, levels_nm: Vec<f64>, period_s: f64, from_nm: f64, to_nm: f64, start_s: f64, duration_s: f64,
    start_nm: f64, rate_nm_per_s: f64, max_nm: f64, mean_nm: f64, amplitude_nm: f64, constant_nm: f64,
    linear_nm_s_rad: f64, quadratic_nm_s2_rad2: f64, at_rad_s: f64, cycles_per_rev: f64, sd_nm: f64,
    correlation_s: f64, seed: u64, base_nm: f64, peak_nm: f64, width_s: f64, mean_interval_s: f64,
    amplitudes_nm: Vec<f64>, periods_s: Vec<f64>,
}

impl TryFrom<LoadTable> for LoadSpec {
    type Error = String;

    fn try_from(t: LoadTable) -> Result<LoadSpec, String> {
        let given = t.given();
        let kind = t.kind;
        // the name as written: ShaftAngle is shaft_angle
        let name: String = format!("{kind:?}")
            .chars()
            .enumerate()
            .flat_map(|(i, c)| (i > 0 && c.is_uppercase()).then_some('_').into_iter().chain(c.to_lowercase()))
            .collect();
        fn need<T>(value: Option<T>, kind: &str, key: &str) -> Result<T, String> {
            value.ok_or_else(|| format!("kind {kind:?} needs the key `{key}`"))
        }
        let spec = match kind {
            LoadKind::None => LoadSpec::None,
            LoadKind::Constant => LoadSpec::Constant { torque_nm: need(t.torque_nm, &name, "torque_nm")? },
            LoadKind::Steps => LoadSpec::Steps {
                levels_nm: need(t.levels_nm, &name, "levels_nm")?,
                period_s: need(t.period_s, &name, "period_s")?,
            },
            LoadKind::Ramp => LoadSpec::Ramp {
                from_nm: need(t.from_nm, &name, "from_nm")?,
                to_nm: need(t.to_nm, &name, "to_nm")?,
                start_s: need(t.start_s, &name, "start_s")?,
                duration_s: need(t.duration_s, &name, "duration_s")?,
            },
            LoadKind::Trend => LoadSpec::Trend {
                start_nm: need(t.start_nm, &name, "start_nm")?,
                rate_nm_per_s: need(t.rate_nm_per_s, &name, "rate_nm_per_s")?,
                max_nm: need(t.max_nm, &name, "max_nm")?,
            },
            LoadKind::Sine => LoadSpec::Sine {
                mean_nm: need(t.mean_nm, &name, "mean_nm")?,
                amplitude_nm: need(t.amplitude_nm, &name, "amplitude_nm")?,
                period_s: need(t.period_s, &name, "period_s")?,
            },
            LoadKind::Speed => LoadSpec::Speed {
                constant_nm: need(t.constant_nm, &name, "constant_nm")?,
                linear_nm_s_rad: need(t.linear_nm_s_rad, &name, "linear_nm_s_rad")?,
                quadratic_nm_s2_rad2: need(t.quadratic_nm_s2_rad2, &name, "quadratic_nm_s2_rad2")?,
            },
            LoadKind::Centrifugal => LoadSpec::Centrifugal {
                torque_nm: need(t.torque_nm, &name, "torque_nm")?,
                at_rad_s: need(t.at_rad_s, &name, "at_rad_s")?,
            },
            LoadKind::ShaftAngle => LoadSpec::ShaftAngle {
                mean_nm: need(t.mean_nm, &name, "mean_nm")?,
                amplitude_nm: need(t.amplitude_nm, &name, "amplitude_nm")?,
                cycles_per_rev: need(t.cycles_per_rev, &name, "cycles_per_rev")?,
            },
            LoadKind::Random => LoadSpec::Random {
                mean_nm: need(t.mean_nm, &name, "mean_nm")?,
                sd_nm: need(t.sd_nm, &name, "sd_nm")?,
                correlation_s: need(t.correlation_s, &name, "correlation_s")?,
                seed: need(t.seed, &name, "seed")?,
            },
            LoadKind::Impacts => LoadSpec::Impacts {
                base_nm: need(t.base_nm, &name, "base_nm")?,
                peak_nm: need(t.peak_nm, &name, "peak_nm")?,
                width_s: need(t.width_s, &name, "width_s")?,
                mean_interval_s: need(t.mean_interval_s, &name, "mean_interval_s")?,
                seed: need(t.seed, &name, "seed")?,
            },
            LoadKind::Sines => LoadSpec::Sines {
                mean_nm: need(t.mean_nm, &name, "mean_nm")?,
                amplitudes_nm: need(t.amplitudes_nm, &name, "amplitudes_nm")?,
                periods_s: need(t.periods_s, &name, "periods_s")?,
            },
            LoadKind::Recorded => LoadSpec::Recorded,
            LoadKind::Unknown => LoadSpec::Unknown,
        };
        // a key of another kind is a mistake (a misspelt kind, a key left from an edit): said, not ignored
        let takes: Vec<String> = match toml::Value::try_from(&spec) {
            Ok(toml::Value::Table(t)) => t.keys().filter(|k| *k != "kind").cloned().collect(),
            _ => Vec::new(),
        };
        match given.iter().find(|k| !takes.iter().any(|t| t == *k)) {
            Some(extra) if takes.is_empty() => Err(format!("kind {name:?} takes no keys, got `{extra}`")),
            Some(extra) => Err(format!("kind {name:?} takes no key `{extra}` (it takes {})", takes.join(", "))),
            None => Ok(spec),
        }
    }
}

/// The test stand's brake: load levels (N·m) applied in turn.
const BRAKE_LEVELS_NM: [f64; 6] = [0.0, 6.0, 12.0, 4.0, 15.0, 9.0];
/// How long each brake level is held; not a multiple of the setpoint program's steps so that the two decorrelate.
const BRAKE_PERIOD_S: f64 = 3.7;

impl LoadSpec {
    /// The load torque (N·m) at time `t_s` with the motor turning at `omega_rad_s`, its shaft at `angle_rad` (the
    /// angle turned since the start). The time-only kinds ignore the state.
    pub fn torque_at(&self, t_s: f64, omega_rad_s: f64, angle_rad: f64) -> f64 {
        match self {
            LoadSpec::None => 0.0,
            LoadSpec::Constant { torque_nm } => *torque_nm,
            LoadSpec::Steps { levels_nm, period_s } => steps(levels_nm, *period_s, t_s),
            LoadSpec::Ramp { from_nm, to_nm, start_s, duration_s } => {
                let x = if *duration_s > 0.0 {
                    ((t_s - start_s) / duration_s).clamp(0.0, 1.0)
                } else if t_s >= *start_s {
                    1.0
                } else {
                    0.0
                };
                from_nm + (to_nm - from_nm) * x
            }
            LoadSpec::Trend { start_nm, rate_nm_per_s, max_nm } => (start_nm + rate_nm_per_s * t_s).min(*max_nm),
            LoadSpec::Sine { mean_nm, amplitude_nm, period_s } => {
                mean_nm + amplitude_nm * (2.0 * std::f64::consts::PI * t_s / period_s).sin()
            }
            LoadSpec::Speed { constant_nm, linear_nm_s_rad, quadratic_nm_s2_rad2 } => {
                constant_nm + linear_nm_s_rad * omega_rad_s + quadratic_nm_s2_rad2 * omega_rad_s * omega_rad_s.abs()
            }
            LoadSpec::Centrifugal { torque_nm, at_rad_s } => {
                let x = omega_rad_s / at_rad_s;
                torque_nm * x * x.abs()
            }
            LoadSpec::ShaftAngle { mean_nm, amplitude_nm, cycles_per_rev } => {
                mean_nm + amplitude_nm * (cycles_per_rev * angle_rad).sin()
            }
            LoadSpec::Random { mean_nm, sd_nm, correlation_s, seed } => {
                mean_nm + sd_nm * value_noise(*seed, t_s / correlation_s)
            }
            LoadSpec::Impacts { base_nm, peak_nm, width_s, mean_interval_s, seed } => {
                base_nm + peak_nm * impacts(*seed, *width_s, *mean_interval_s, t_s)
            }
            LoadSpec::Sines { mean_nm, amplitudes_nm, periods_s } => {
                let tau = std::f64::consts::TAU;
                mean_nm + amplitudes_nm.iter().zip(periods_s).map(|(a, p)| a * (tau * t_s / p).sin()).sum::<f64>()
            }
            LoadSpec::Recorded | LoadSpec::Unknown => steps(&BRAKE_LEVELS_NM, BRAKE_PERIOD_S, t_s),
        }
    }

    /// Checks the parameters, naming the key of the first bad one.
    pub fn validate(&self) -> Result<(), KeyError> {
        let all_within = |vals: &[f64]| vals.iter().all(|v| v.abs() <= MAX_LOAD_MAGNITUDE);
        match self {
            LoadSpec::Steps { levels_nm, period_s } => {
                if levels_nm.is_empty() || !all_within(levels_nm) {
                    return bad("levels_nm", "must be a non-empty list of finite numbers".into());
                }
                positive("period_s", *period_s)?;
            }
            LoadSpec::Sine { mean_nm, amplitude_nm, period_s } => {
                if !all_within(&[*mean_nm, *amplitude_nm]) {
                    return bad("amplitude_nm", "mean_nm and amplitude_nm must be finite".into());
                }
                positive("period_s", *period_s)?;
            }
            LoadSpec::Ramp { from_nm, to_nm, start_s, duration_s } => {
                if !all_within(&[*from_nm, *to_nm]) || !start_s.is_finite() {
                    return bad("from_nm", "from_nm, to_nm and start_s must be finite".into());
                }
                nonneg("duration_s", *duration_s)?;
            }
            LoadSpec::Trend { start_nm, rate_nm_per_s, max_nm }
                if !all_within(&[*start_nm, *rate_nm_per_s]) || max_nm.is_nan() =>
            {
                return bad("rate_nm_per_s", "start_nm, rate_nm_per_s and max_nm must be numbers".into());
            }
            LoadSpec::Constant { torque_nm } => finite("torque_nm", *torque_nm)?,
            LoadSpec::Speed { constant_nm, linear_nm_s_rad, quadratic_nm_s2_rad2 } => {
                finite("constant_nm", *constant_nm)?;
                finite("linear_nm_s_rad", *linear_nm_s_rad)?;
                finite("quadratic_nm_s2_rad2", *quadratic_nm_s2_rad2)?;
            }
            LoadSpec::Centrifugal { torque_nm, at_rad_s } => {
                finite("torque_nm", *torque_nm)?;
                positive("at_rad_s", *at_rad_s)?;
            }
            LoadSpec::ShaftAngle { mean_nm, amplitude_nm, cycles_per_rev } => {
                if !all_within(&[*mean_nm, *amplitude_nm]) {
                    return bad("amplitude_nm", "mean_nm and amplitude_nm must be finite".into());
                }
                positive("cycles_per_rev", *cycles_per_rev)?;
            }
            LoadSpec::Random { mean_nm, sd_nm, correlation_s, .. } => {
                finite("mean_nm", *mean_nm)?;
                nonneg("sd_nm", *sd_nm)?;
                finite("sd_nm", *sd_nm)?;
                positive("correlation_s", *correlation_s)?;
            }
            LoadSpec::Impacts { base_nm, peak_nm, width_s, mean_interval_s, .. } => {
                if !all_within(&[*base_nm, *peak_nm]) {
                    return bad("peak_nm", "base_nm and peak_nm must be finite".into());
                }
                positive("width_s", *width_s)?;
                positive("mean_interval_s", *mean_interval_s)?;
                // each evaluation looks at every interval a pulse may reach into: their number is the cost
                if width_s / mean_interval_s > MAX_TERMS as f64 {
                    return bad(
                        "width_s",
                        format!(
                            "{width_s} s pulses one each {mean_interval_s} s overlap {:.3e} at a time, more than \
                             {MAX_TERMS}: the load would cost that much each sample",
                            width_s / mean_interval_s
                        ),
                    );
                }
            }
            LoadSpec::Sines { mean_nm, amplitudes_nm, periods_s } => {
                finite("mean_nm", *mean_nm)?;
                if amplitudes_nm.is_empty() || !all_within(amplitudes_nm) {
                    return bad("amplitudes_nm", "must be a non-empty list of finite numbers".into());
                }
                if periods_s.len() != amplitudes_nm.len() || !periods_s.iter().all(|p| *p > 0.0 && p.is_finite()) {
                    return bad("periods_s", "must be one period > 0 for each of amplitudes_nm".into());
                }
                if amplitudes_nm.len() > MAX_TERMS {
                    return bad("amplitudes_nm", format!("{} sines, more than {MAX_TERMS}", amplitudes_nm.len()));
                }
            }
            _ => {}
        }
        Ok(())
    }
}

/// The most terms a load program sums each sample (sines, or impacts overlapping): the real-time simulator
/// evaluates it every sample.
pub const MAX_TERMS: usize = 1000;

/// The error of a bad `load.<key>`.
fn bad(key: &str, msg: String) -> Result<(), KeyError> {
    Err(KeyError::new(format!("load.{key}"), msg))
}

/// The largest magnitude of a load's torque or coefficient: beyond any plant (a constant load of 1e300 N·m was taken,
/// and `analyze --model-out` wrote it into a model that `simulate` then refused).
pub const MAX_LOAD_MAGNITUDE: f64 = 1e6;

/// `load.<key>` must be finite, within ±[`MAX_LOAD_MAGNITUDE`].
fn finite(key: &str, v: f64) -> Result<(), KeyError> {
    if v.abs() <= MAX_LOAD_MAGNITUDE {
        Ok(())
    } else {
        bad(key, format!("must be a finite number within ±{MAX_LOAD_MAGNITUDE:e}, got {v:e}"))
    }
}

/// `load.<key>` must be finite and > 0.
fn positive(key: &str, v: f64) -> Result<(), KeyError> {
    if v > 0.0 && v.is_finite() { Ok(()) } else { bad(key, format!("must be > 0, got {}", crate::units::shown(v))) }
}

/// `load.<key>` must be finite and ≥ 0.
fn nonneg(key: &str, v: f64) -> Result<(), KeyError> {
    if v >= 0.0 && v.is_finite() { Ok(()) } else { bad(key, format!("must be ≥ 0, got {}", crate::units::shown(v))) }
}

fn steps(levels: &[f64], period_s: f64, t_s: f64) -> f64 {
    if levels.is_empty() || period_s <= 0.0 {
        return 0.0;
    }
    let i = (t_s.max(0.0) / period_s).floor() as usize % levels.len();
    levels[i]
}

/// splitmix64's finaliser: a well-mixed 64-bit hash of `x`.
pub(crate) fn splitmix64(x: u64) -> u64 {
    let mut z = x.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// A uniform number in [0, 1) that is a pure function of `seed` and `k`.
pub(crate) fn unit_hash(seed: u64, k: u64) -> f64 {
    (splitmix64(seed ^ splitmix64(k)) >> 11) as f64 / (1u64 << 53) as f64
}

/// A standard normal number that is a pure function of `seed` and `k` (Box–Muller on two hashed uniforms).
fn normal_hash(seed: u64, k: u64) -> f64 {
    let u1 = 1.0 - unit_hash(seed, k.wrapping_mul(2)); // in (0, 1]: its log is finite
    let u2 = unit_hash(seed, k.wrapping_mul(2).wrapping_add(1));
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

/// Value noise of unit standard deviation (about): standard normals at the integers, joined by smoothstep. The
/// blend of two independent values has variance (1−s)² + s², 26/35 on average over a cell: hence the scale.
fn value_noise(seed: u64, x: f64) -> f64 {
    if !x.is_finite() {
        return 0.0;
    }
    let k = x.floor();
    let f = x - k;
    let s = f * f * (3.0 - 2.0 * f);
    let k = k as i64 as u64;
    let (a, b) = (normal_hash(seed, k), normal_hash(seed, k.wrapping_add(1)));
    (a + (b - a) * s) * (35.0f64 / 26.0).sqrt()
}

/// The pulse train of `impacts` at `t_s`, in units of the peak: one half-sine of `width_s` in each interval of
/// `interval_s`, starting at a hashed place within it (pulses wider than the interval overlap and add).
fn impacts(seed: u64, width_s: f64, interval_s: f64, t_s: f64) -> f64 {
    if !(t_s.is_finite() && width_s > 0.0 && interval_s > 0.0) {
        return 0.0;
    }
    let j = (t_s / interval_s).floor() as i64;
    let back = (width_s / interval_s).ceil() as i64;
    let room = (interval_s - width_s).max(0.0);
    (j - back..=j)
        .map(|i| {
            let start = i as f64 * interval_s + unit_hash(seed, i as u64) * room;
            let x = (t_s - start) / width_s;
            if (0.0..1.0).contains(&x) { (std::f64::consts::PI * x).sin() } else { 0.0 }
        })
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `[load]` errors name the key and stand at its line and column (they pointed at the table, and said
    /// "invalid type: string, expected f64" of no key); keys of another kind are refused, also beside a kind that
    /// takes none (they were ignored).
    #[test]
    fn load_table_errors_name_the_key_where_it_stands() {
        #[derive(Debug, Deserialize)]
        struct Model {
            #[allow(dead_code)]
            load: LoadSpec,
        }
        let error = |body: &str| {
            let text = format!("[load]\n{body}\n");
            toml::from_str::<Model>(&text).map(|m| format!("{m:?}")).expect_err(body).to_string()
        };
        let e = error("kind = \"sine\"\nmean_nm = 1.0\namplitude_nm = \"a\"\nperiod_s = 2.0");
        assert!(e.contains("line 4, column 16") && e.contains("expected f64"), "{e}");
        let e = error("kind = \"recorded\"\nbogus = 1");
        assert!(e.contains("line 3, column 1") && e.contains("unknown field `bogus`"), "{e}");
        let e = error("kind = \"recorded\"\ntorque_nm = 1.0");
        assert!(e.contains("kind \"recorded\" takes no keys, got `torque_nm`"), "{e}");
        let e = error("kind = \"constant\"\ntorque_nm = 1.0\nperiod_s = 3.0");
        assert!(e.contains("kind \"constant\" takes no key `period_s` (it takes torque_nm)"), "{e}");
        let e = error("kind = \"shaft_angle\"\nmean_nm = 1.0\namplitude_nm = 2.0");
        assert!(e.contains("kind \"shaft_angle\" needs the key `cycles_per_rev`"), "{e}");
        let e = error("kind = \"fan\"");
        assert!(e.contains("line 2, column 8") && e.contains("unknown variant `fan`"), "{e}");
        // every kind written back and read again is itself (the keys each kind takes are its variant's fields)
        for spec in [
            LoadSpec::Random { mean_nm: 1.0, sd_nm: 0.5, correlation_s: 2.0, seed: 7 },
            LoadSpec::Sines { mean_nm: 1.0, amplitudes_nm: vec![1.0, 2.0], periods_s: vec![3.0, 5.0] },
            LoadSpec::ShaftAngle { mean_nm: 1.0, amplitude_nm: 2.0, cycles_per_rev: 0.5 },
            LoadSpec::Unknown,
        ] {
            let text = format!("[load]\n{}", toml::to_string(&spec).expect("writes"));
            let back: LoadSpec = toml::from_str::<toml::Table>(&text)
                .ok()
                .and_then(|t| t.get("load").cloned())
                .and_then(|v| v.try_into().ok())
                .expect("reads");
            assert_eq!(back, spec);
        }
    }

    #[test]
    fn profiles() {
        let s = LoadSpec::Steps { levels_nm: vec![1.0, 2.0], period_s: 1.0 };
        assert_eq!(s.torque_at(0.5, 0.0, 0.0), 1.0);
        assert_eq!(s.torque_at(1.5, 0.0, 0.0), 2.0);
        assert_eq!(s.torque_at(2.5, 0.0, 0.0), 1.0);
        let r = LoadSpec::Ramp { from_nm: 0.0, to_nm: 10.0, start_s: 1.0, duration_s: 2.0 };
        assert_eq!(r.torque_at(0.0, 0.0, 0.0), 0.0);
        assert_eq!(r.torque_at(2.0, 0.0, 0.0), 5.0);
        assert_eq!(r.torque_at(9.0, 0.0, 0.0), 10.0);
        let t = LoadSpec::Trend { start_nm: 1.0, rate_nm_per_s: 0.5, max_nm: 3.0 };
        assert_eq!(t.torque_at(2.0, 0.0, 0.0), 2.0);
        assert_eq!(t.torque_at(100.0, 0.0, 0.0), 3.0);
    }

    fn parse(body: &str) -> LoadSpec {
        toml::from_str(body).unwrap_or_else(|e| panic!("{body}: {e}"))
    }

    #[test]
    fn the_state_dependent_kinds_parse_and_follow_speed_and_angle() {
        let s = parse("kind = \"speed\"\nconstant_nm = 1.0\nlinear_nm_s_rad = 0.1\nquadratic_nm_s2_rad2 = 0.01\n");
        assert_eq!(s.torque_at(3.0, 10.0, 0.0), 1.0 + 1.0 + 1.0);
        assert_eq!(s.torque_at(3.0, -10.0, 0.0), 1.0 - 1.0 - 1.0, "the load opposes the motion both ways");
        let c = parse("kind = \"centrifugal\"\ntorque_nm = 12.0\nat_rad_s = 60.0\n");
        assert_eq!(c.torque_at(0.0, 60.0, 0.0), 12.0);
        assert_eq!(c.torque_at(0.0, 30.0, 0.0), 3.0);
        assert_eq!(c.torque_at(0.0, -60.0, 0.0), -12.0);
        let g = parse("kind = \"shaft_angle\"\nmean_nm = 10.0\namplitude_nm = 4.0\ncycles_per_rev = 0.25\n");
        let quarter_cycle = std::f64::consts::TAU; // a whole turn of the motor is a quarter cycle
        assert!((g.torque_at(99.0, 5.0, quarter_cycle) - 14.0).abs() < 1e-12);
        assert!((g.torque_at(0.0, 0.0, 0.0) - 10.0).abs() < 1e-12);
        for spec in [&s, &c, &g] {
            assert_eq!(spec.validate(), Ok(()));
        }
        let text = "kind = \"centrifugal\"\ntorque_nm = 12.0\nat_rad_s = 60.0\nat_rpm = 3.0\n";
        assert!(toml::from_str::<LoadSpec>(text).is_err(), "unknown keys are refused");
    }

    #[test]
    fn the_time_kinds_parse_and_are_pure_functions_of_time() {
        let r = parse("kind = \"random\"\nmean_nm = 10.0\nsd_nm = 3.0\ncorrelation_s = 0.5\nseed = 7\n");
        let i = parse(
            "kind = \"impacts\"\nbase_nm = 2.0\npeak_nm = 20.0\nwidth_s = 0.1\nmean_interval_s = 1.0\nseed = 3\n",
        );
        let w = parse("kind = \"sines\"\nmean_nm = 5.0\namplitudes_nm = [1.0, 2.0]\nperiods_s = [2.0, 7.3]\n");
        for spec in [&r, &i, &w] {
            assert_eq!(spec.validate(), Ok(()));
            let a: Vec<f64> = (0..5000).map(|k| spec.torque_at(k as f64 * 0.01, 0.0, 0.0)).collect();
            let b: Vec<f64> = (0..5000).map(|k| spec.torque_at(k as f64 * 0.01, 50.0, 9.0)).collect();
            assert_eq!(a, b, "{spec:?} ignores the state and holds no state of its own");
            assert!(a.iter().all(|v| v.is_finite()), "{spec:?}");
        }
        // the random load: about its mean and sd over many correlation times, and another seed another load
        let v: Vec<f64> = (0..200_000).map(|k| r.torque_at(k as f64 * 0.01, 0.0, 0.0)).collect();
        let mean = v.iter().sum::<f64>() / v.len() as f64;
        let sd = (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / v.len() as f64).sqrt();
        assert!((mean - 10.0).abs() < 0.3 && (sd - 3.0).abs() < 0.3, "mean {mean}, sd {sd}");
        let other = LoadSpec::Random { mean_nm: 10.0, sd_nm: 3.0, correlation_s: 0.5, seed: 8 };
        assert_ne!(r.torque_at(1.3, 0.0, 0.0), other.torque_at(1.3, 0.0, 0.0));
        // impacts: one pulse of 20 N·m a second on top of the base, 0.1 s wide
        let p: Vec<f64> = (0..10_000).map(|k| i.torque_at(k as f64 * 1e-3, 0.0, 0.0)).collect();
        let peak = p.iter().cloned().fold(f64::MIN, f64::max);
        assert!(peak > 21.9 && peak <= 22.0 + 1e-9, "{peak}");
        assert!(p.iter().all(|v| *v >= 2.0), "half-sines only add");
        let above = p.iter().filter(|v| **v > 2.0).count();
        assert!((990..=1010).contains(&above), "10 pulses of 100 ms: {above} ms above the base");
        // sines: the sum of both
        let t: f64 = 1.1;
        let tau = std::f64::consts::TAU;
        assert!((w.torque_at(t, 0.0, 0.0) - (5.0 + (tau * t / 2.0).sin() + 2.0 * (tau * t / 7.3).sin())).abs() < 1e-12);
    }

    #[test]
    fn bad_parameters_name_their_key() {
        let key = |spec: LoadSpec| spec.validate().expect_err("invalid").key;
        let at = LoadSpec::Centrifugal { torque_nm: 12.0, at_rad_s: 0.0 };
        assert_eq!(key(at), "load.at_rad_s");
        assert_eq!(
            key(LoadSpec::Speed { constant_nm: 0.0, linear_nm_s_rad: f64::NAN, quadratic_nm_s2_rad2: 0.0 }),
            "load.linear_nm_s_rad"
        );
        assert_eq!(
            key(LoadSpec::ShaftAngle { mean_nm: 1.0, amplitude_nm: 1.0, cycles_per_rev: -0.5 }),
            "load.cycles_per_rev"
        );
        assert_eq!(
            key(LoadSpec::Random { mean_nm: 1.0, sd_nm: 1.0, correlation_s: 0.0, seed: 1 }),
            "load.correlation_s"
        );
        assert_eq!(key(LoadSpec::Random { mean_nm: 1.0, sd_nm: -1.0, correlation_s: 1.0, seed: 1 }), "load.sd_nm");
        // magnitudes beyond any plant (a constant load of 1e300 N·m was taken, and copied by `analyze --model-out`
        // into a model `simulate` refused)
        assert_eq!(key(LoadSpec::Constant { torque_nm: 1e300 }), "load.torque_nm");
        assert_eq!(key(LoadSpec::Random { mean_nm: 1.0, sd_nm: 1e300, correlation_s: 1.0, seed: 1 }), "load.sd_nm");
        assert_eq!(key(LoadSpec::Steps { levels_nm: vec![1.0, -1e7], period_s: 1.0 }), "load.levels_nm");
        LoadSpec::Constant { torque_nm: -MAX_LOAD_MAGNITUDE }.validate().expect("at the bound");
        assert_eq!(
            key(LoadSpec::Impacts { base_nm: 1.0, peak_nm: 9.0, width_s: 0.0, mean_interval_s: 1.0, seed: 1 }),
            "load.width_s"
        );
        assert_eq!(
            key(LoadSpec::Impacts { base_nm: 1.0, peak_nm: 9.0, width_s: 0.1, mean_interval_s: -1.0, seed: 1 }),
            "load.mean_interval_s"
        );
        assert_eq!(
            key(LoadSpec::Sines { mean_nm: 1.0, amplitudes_nm: vec![1.0, 2.0], periods_s: vec![3.0] }),
            "load.periods_s"
        );
        // a cost per sample without bound (a sample took 0.1 s): pulses overlapping 10⁷ at a time, 10⁵ sines
        assert_eq!(
            key(LoadSpec::Impacts { base_nm: 1.0, peak_nm: 1e-9, width_s: 10.0, mean_interval_s: 1e-6, seed: 1 }),
            "load.width_s"
        );
        let many = vec![1.0; 100_000];
        assert_eq!(
            key(LoadSpec::Sines { mean_nm: 1.0, amplitudes_nm: many.clone(), periods_s: many }),
            "load.amplitudes_nm"
        );
        assert_eq!(
            key(LoadSpec::Sines { mean_nm: 1.0, amplitudes_nm: vec![], periods_s: vec![] }),
            "load.amplitudes_nm"
        );
    }
}

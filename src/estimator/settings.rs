//! Estimator settings: the `[estimator]` table of a plant model, parsed strictly, validated, with the paper's defaults.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Serialize};

use crate::plant::{ModelError, PlantModel};
use crate::units::{bar_to_pa, cm3_per_rev_to_m3_per_rad};

/// Which estimator runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
    /// The seed paper's RLS (J, B) + SGD (load), corrected: observer for ω̂, descent sign fixed, guarded RLS.
    #[default]
    RlsSgd,
    /// Kalman filter on [ω, T_L] with a random-walk load and the model's J and B.
    Kalman,
    /// The paper as printed: per-sample RLS on [ΔP, ω], eq. (11) with its "+" sign. For reproduction only.
    PaperLiteral,
}

impl Method {
    pub const NAMES: [&'static str; 3] = ["rls-sgd", "kalman", "paper-literal"];

    pub fn name(self) -> &'static str {
        match self {
            Method::RlsSgd => "rls-sgd",
            Method::Kalman => "kalman",
            Method::PaperLiteral => "paper-literal",
        }
    }
}

impl fmt::Display for Method {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Method {
    type Err = String;
    fn from_str(s: &str) -> Result<Method, String> {
        match s {
            "rls-sgd" => Ok(Method::RlsSgd),
            "kalman" => Ok(Method::Kalman),
            "paper-literal" => Ok(Method::PaperLiteral),
            _ => Err(format!("unknown method {s:?}: expected one of {}", Method::NAMES.join(", "))),
        }
    }
}

/// Everything an estimator can be tuned with. Noise levels left `None` come from the model's `[sensors]`;
/// initial J and B left `None` come from `[motor]`.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct EstimatorSettings {
    pub method: Method,
    /// RLS forgetting factor λ, applied once per RLS update (paper: 0.99).
    pub lambda: f64,
    /// SGD learning rate η of the load torque, normalised by the gradient (paper: 0.05; stable for 0 < η < 2).
    pub eta: f64,
    /// Bandwidth of the ω̂ observer's innovation gain (rad/s): lower suppresses more noise, higher lags less.
    pub speed_bandwidth_rad_s: f64,
    /// Length of the load-cancelling windows the RLS learns from, one update per half window (s): θ is slow, T_L
    /// is fast, so they do not fight.
    pub rls_period_s: f64,
    /// Not used since the windowed RLS (it needs no load bias); accepted so that older model files still load.
    pub load_forgetting: f64,
    /// paper-literal: initial RLS covariance (paper: "large").
    pub initial_covariance: f64,
    /// paper-literal: upper bound on trace(P).
    pub max_covariance_trace: f64,
    /// Not used since the windowed RLS (excitation is judged against each window's noise); accepted for older files.
    pub excitation_torque_nm: f64,
    /// A window residual beyond this many σ (noise and parameter spread) holds a load change: it is not learnt from.
    pub change_threshold: f64,
    /// Not used since the windowed RLS; accepted for older files.
    pub excitation_speed_rad_s: f64,
    /// rls-sgd: prior standard deviation of J₀/J (the model's J is this uncertain before any data).
    pub inertia_prior_sd: f64,
    /// rls-sgd: prior standard deviation of B/J relative to the model's (B is this uncertain before any data).
    pub viscous_prior_sd: f64,
    /// Jump test on the normalised speed innovations (CUSUM): drift per sample and alarm threshold (σ).
    pub jump_drift: f64,
    pub jump_threshold: f64,
    /// A detected jump widens the load's standard deviation by this much (N·m; kalman, and rls-sgd's tracker).
    pub jump_load_sd_nm: f64,
    /// rls-sgd: also estimate B from one fit over the last 20 s with a periodic load (constant, trend and one
    /// sinusoid of a searched period), where the windows alone cannot tell a sine load's curvature from B·ω.
    pub periodic_load: bool,
    /// Physical range of J as factors of the model's J.
    pub inertia_bounds_factor: [f64; 2],
    /// Physical range of B (N·m·s/rad).
    pub viscous_bounds_nm_s_rad: Option<[f64; 2]>,
    /// Largest load torque the estimators will report (N·m).
    pub max_load_nm: f64,
    /// Starting J, overriding `[motor]` (kg·m²).
    pub initial_inertia_kg_m2: Option<f64>,
    /// Starting B, overriding `[motor]` (N·m·s/rad).
    pub initial_viscous_nm_s_rad: Option<f64>,
    /// Starting load torque (N·m).
    pub initial_load_nm: f64,
    /// σ of the speed measurement (rad/s); default `sensors.speed_noise_rad_s`.
    pub speed_noise_rad_s: Option<f64>,
    /// σ of the drive torque measurement (N·m); default from `sensors.pressure_noise_bar` and D_m.
    pub torque_noise_nm: Option<f64>,
    /// Kalman: random-walk intensity of the load (N·m/√s).
    pub load_rate_nm_per_s: f64,
    /// Kalman: σ of the initial load estimate (N·m).
    pub initial_load_sigma_nm: f64,
    /// A gap between samples longer than this (s) restarts ω̂ from the measurement instead of predicting across it.
    pub max_gap_s: f64,
}

impl Default for EstimatorSettings {
    fn default() -> Self {
        EstimatorSettings {
            method: Method::RlsSgd,
            lambda: 0.99,
            eta: 0.05,
            speed_bandwidth_rad_s: 60.0,
            rls_period_s: 1.5,
            load_forgetting: 0.9,
            initial_covariance: 100.0,
            max_covariance_trace: 100.0,
            excitation_torque_nm: 0.5,
            change_threshold: 5.0,
            excitation_speed_rad_s: 2.0,
            inertia_prior_sd: 0.7,
            viscous_prior_sd: 1.5,
            jump_drift: 0.5,
            jump_threshold: 8.0,
            jump_load_sd_nm: 4.0,
            periodic_load: true,
            inertia_bounds_factor: [0.2, 5.0],
            viscous_bounds_nm_s_rad: None,
            max_load_nm: 1e4,
            initial_inertia_kg_m2: None,
            initial_viscous_nm_s_rad: None,
            initial_load_nm: 0.0,
            speed_noise_rad_s: None,
            torque_noise_nm: None,
            load_rate_nm_per_s: 6.0,
            initial_load_sigma_nm: 20.0,
            max_gap_s: 0.1,
        }
    }
}

/// Settings resolved against a model: every number present, finite and in range. Built only by
/// [`EstimatorSettings::resolve`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Resolved {
    pub lambda: f64,
    pub eta: f64,
    pub speed_bandwidth_rad_s: f64,
    pub rls_period_s: f64,
    pub load_forgetting: f64,
    pub initial_covariance: f64,
    pub max_covariance_trace: f64,
    pub excitation_torque_nm: f64,
    pub excitation_speed_rad_s: f64,
    pub change_threshold: f64,
    pub inertia_prior_sd: f64,
    pub viscous_prior_sd: f64,
    pub jump_drift: f64,
    pub jump_threshold: f64,
    pub jump_load_sd_nm: f64,
    pub periodic_load: bool,
    /// The model's nominal J and B: the scale of the normalised RLS parameters and of the bounds.
    pub nominal_inertia_kg_m2: f64,
    pub nominal_viscous_nm_s_rad: f64,
    pub inertia_bounds_kg_m2: [f64; 2],
    pub viscous_bounds_nm_s_rad: [f64; 2],
    pub max_load_nm: f64,
    pub initial_inertia_kg_m2: f64,
    pub initial_viscous_nm_s_rad: f64,
    pub initial_load_nm: f64,
    pub speed_noise_rad_s: f64,
    pub torque_noise_nm: f64,
    pub load_rate_nm_per_s: f64,
    pub initial_load_sigma_nm: f64,
    pub max_gap_s: f64,
    /// Motor displacement D_m (m³/rad) when the model has it: the paper-literal mode regresses on ΔP = τ/D_m.
    pub displacement_m3_rad: Option<f64>,
}

use crate::error::KeyError;

fn check(key: &str, v: f64, ok: bool, expected: &str) -> Result<f64, KeyError> {
    if v.is_finite() && ok {
        Ok(v)
    } else {
        let v = if v != 0.0 && !(1e-4..1e6).contains(&v.abs()) { format!("{v:e}") } else { format!("{v}") };
        Err(KeyError::new(format!("estimator.{key}"), format!("must be {expected}, got {v}")))
    }
}

impl EstimatorSettings {
    /// The `[estimator]` table of a model (defaults when absent), parsed strictly; errors name the key.
    pub fn from_model(model: &PlantModel, origin: &str) -> Result<EstimatorSettings, ModelError> {
        let Some(table) = &model.estimator else { return Ok(EstimatorSettings::default()) };
        let settings: EstimatorSettings =
            toml::Value::Table(table.clone()).try_into().map_err(|e: toml::de::Error| ModelError::Invalid {
                path: origin.to_string(),
                key: "[estimator]".into(),
                message: e.to_string().trim_end().to_string(),
            })?;
        settings.resolve(model).map_err(|KeyError { key, message }| ModelError::Invalid {
            path: origin.to_string(),
            key,
            message,
        })?;
        Ok(settings)
    }

    /// Checks every value against the model and fills in what comes from it; the key and the problem otherwise.
    pub fn resolve(&self, model: &PlantModel) -> Result<Resolved, KeyError> {
        let s = self;
        let unit = |key: &str, v: f64| check(key, v, v > 0.0 && v <= 1.0, "in (0, 1]");
        let pos = |key: &str, v: f64| check(key, v, v > 0.0, "> 0");
        let nonneg = |key: &str, v: f64| check(key, v, v >= 0.0, "≥ 0");
        // paper-literal's P: from 1e308 its first update overflowed and the estimate stood at 0 without a word
        let covariance = |key: &str, v: f64| check(key, v, v > 0.0 && v <= MAX_COVARIANCE, "in (0, 1e12]");
        // a noise or a rate squares into a variance: at 1e154 it overflowed, and ω̂ stood at 0 on a third of the rows
        // without a word (`estimate --speed-noise=1e154`, a reviewer's run)
        let spread = |key: &str, v: f64| check(key, v, v > 0.0 && v <= MAX_SPREAD, "in (0, 1e6]");
        let j0 = model.motor.inertia_kg_m2;
        let b0 = model.motor.viscous_nm_s_rad;
        let [jlo, jhi] = s.inertia_bounds_factor;
        check("inertia_bounds_factor", jlo, jlo > 0.0 && jlo <= 1.0, "[low, high] with 0 < low ≤ 1 ≤ high")?;
        check("inertia_bounds_factor", jhi, jhi >= 1.0, "[low, high] with 0 < low ≤ 1 ≤ high")?;
        let [blo, bhi] = s.viscous_bounds_nm_s_rad.unwrap_or([0.0, (5.0 * b0).max(0.05 * j0).max(1e-6)]);
        check("viscous_bounds_nm_s_rad", blo, blo >= 0.0, "[low, high] with 0 ≤ low < high")?;
        check("viscous_bounds_nm_s_rad", bhi, bhi > blo, "[low, high] with 0 ≤ low < high")?;
        let inertia_bounds = [j0 * jlo, j0 * jhi];
        // a start outside the bounds was clamped into them without a word: refused, naming the bounds
        let within = |key: &str, v: f64, [lo, hi]: [f64; 2], bounds: &str| {
            check(key, v, (lo..=hi).contains(&v), &format!("within {bounds} [{lo}, {hi}]"))
        };
        let initial_inertia = pos("initial_inertia_kg_m2", s.initial_inertia_kg_m2.unwrap_or(j0))?;
        within("initial_inertia_kg_m2", initial_inertia, inertia_bounds, "inertia_bounds_factor × the model's J:")?;
        let initial_viscous = nonneg("initial_viscous_nm_s_rad", s.initial_viscous_nm_s_rad.unwrap_or(b0))?;
        within("initial_viscous_nm_s_rad", initial_viscous, [blo, bhi], "viscous_bounds_nm_s_rad")?;
        let displacement = model.motor.displacement_cm3.map(cm3_per_rev_to_m3_per_rad);
        let speed_noise = s.speed_noise_rad_s.unwrap_or(if model.sensors.speed_noise_rad_s > 0.0 {
            model.sensors.speed_noise_rad_s
        } else {
            DEFAULT_SPEED_NOISE_RAD_S
        });
        // Both pressures carry the sensor noise: σ_τ = D_m·√2·σ_p.
        let torque_noise = s.torque_noise_nm.unwrap_or_else(|| {
            let from_pressure =
                displacement.map_or(0.0, |d| d * bar_to_pa(model.sensors.pressure_noise_bar) * 2f64.sqrt());
            if from_pressure > 0.0 { from_pressure } else { 0.05 }
        });
        let max_load = pos("max_load_nm", s.max_load_nm)?;
        let initial_load =
            check("initial_load_nm", s.initial_load_nm, s.initial_load_nm.abs() <= max_load, "within ±max_load_nm")?;
        Ok(Resolved {
            lambda: unit("lambda", s.lambda)?,
            eta: check("eta", s.eta, s.eta > 0.0 && s.eta < 2.0, "in (0, 2)")?,
            speed_bandwidth_rad_s: pos("speed_bandwidth_rad_s", s.speed_bandwidth_rad_s)?,
            rls_period_s: pos("rls_period_s", s.rls_period_s)?,
            load_forgetting: unit("load_forgetting", s.load_forgetting)?,
            initial_covariance: covariance("initial_covariance", s.initial_covariance)?,
            max_covariance_trace: covariance("max_covariance_trace", s.max_covariance_trace)?,
            excitation_torque_nm: nonneg("excitation_torque_nm", s.excitation_torque_nm)?,
            excitation_speed_rad_s: nonneg("excitation_speed_rad_s", s.excitation_speed_rad_s)?,
            change_threshold: pos("change_threshold", s.change_threshold)?,
            inertia_prior_sd: pos("inertia_prior_sd", s.inertia_prior_sd)?,
            viscous_prior_sd: pos("viscous_prior_sd", s.viscous_prior_sd)?,
            jump_drift: nonneg("jump_drift", s.jump_drift)?,
            jump_threshold: pos("jump_threshold", s.jump_threshold)?,
            jump_load_sd_nm: nonneg("jump_load_sd_nm", s.jump_load_sd_nm)?,
            periodic_load: s.periodic_load,
            nominal_inertia_kg_m2: j0,
            nominal_viscous_nm_s_rad: b0,
            inertia_bounds_kg_m2: inertia_bounds,
            viscous_bounds_nm_s_rad: [blo, bhi],
            max_load_nm: max_load,
            initial_inertia_kg_m2: initial_inertia,
            initial_viscous_nm_s_rad: initial_viscous,
            initial_load_nm: initial_load,
            speed_noise_rad_s: spread("speed_noise_rad_s", speed_noise)?,
            torque_noise_nm: spread("torque_noise_nm", torque_noise)?,
            load_rate_nm_per_s: spread("load_rate_nm_per_s", s.load_rate_nm_per_s)?,
            initial_load_sigma_nm: spread("initial_load_sigma_nm", s.initial_load_sigma_nm)?,
            max_gap_s: pos("max_gap_s", s.max_gap_s)?,
            displacement_m3_rad: displacement,
        })
    }
}

/// σ of the speed (rad/s) where neither the settings nor the model's `[sensors]` give one (`estimate` says so).
pub const DEFAULT_SPEED_NOISE_RAD_S: f64 = 0.1;

/// The largest covariance a setting may start from or be bounded by: beyond it an update's products overflow.
const MAX_COVARIANCE: f64 = 1e12;

/// The largest noise or load rate a setting may give (its unit's standard deviation): squared and summed, larger ones
/// overflow.
const MAX_SPREAD: f64 = 1e6;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn methods_parse_kebab_case() {
        for name in Method::NAMES {
            let m: Method = name.parse().expect("known");
            assert_eq!(m.name(), name);
            let v: Method = toml::Value::String(name.into()).try_into().expect("serde");
            assert_eq!(v, m);
        }
        assert!("rls_sgd".parse::<Method>().expect_err("snake case").contains("rls-sgd"));
    }

    #[test]
    fn defaults_are_the_papers_and_resolve() {
        let s = EstimatorSettings::default();
        assert_eq!((s.lambda, s.eta), (0.99, 0.05));
        let r = s.resolve(&PlantModel::reference()).expect("valid");
        assert_eq!(r.initial_inertia_kg_m2, 0.08);
        assert!((r.torque_noise_nm - 0.216).abs() < 0.01, "{}", r.torque_noise_nm);
        assert_eq!(r.speed_noise_rad_s, 0.8);
    }

    #[test]
    fn estimator_table_is_strict_and_names_the_key() {
        let text =
            format!("{}\n[estimator]\nlambda = 0.98\nmethod = \"kalman\"\n", crate::plant::model::REFERENCE_TOML);
        let m = PlantModel::parse(&text, "p.toml").expect("model");
        let s = EstimatorSettings::from_model(&m, "p.toml").expect("valid");
        assert_eq!((s.lambda, s.method, s.periodic_load), (0.98, Method::Kalman, true));
        let off = text.replace("lambda = 0.98", "periodic_load = false");
        let m = PlantModel::parse(&off, "p.toml").expect("model");
        assert!(!EstimatorSettings::from_model(&m, "p.toml").expect("valid").periodic_load);
        let bad = text.replace("lambda = 0.98", "lamda = 0.98");
        let m = PlantModel::parse(&bad, "p.toml").expect("model");
        let e = EstimatorSettings::from_model(&m, "p.toml").expect_err("unknown key");
        assert!(e.is_bad_input() && e.to_string().contains("lamda"), "{e}");
        let bad = text.replace("lambda = 0.98", "lambda = 1.5");
        let m = PlantModel::parse(&bad, "p.toml").expect("model");
        let e = EstimatorSettings::from_model(&m, "p.toml").expect_err("out of range").to_string();
        assert!(e.contains("estimator.lambda") && e.contains("1.5"), "{e}");
        // a start beyond the bounds was clamped into them in silence
        for (key, v) in [
            ("initial_inertia_kg_m2", "1e300"),
            ("initial_viscous_nm_s_rad", "50.0"),
            ("initial_covariance", "1e308"),
            ("max_covariance_trace", "1e300"),
            ("speed_noise_rad_s", "1e154"),
            ("load_rate_nm_per_s", "1e200"),
        ] {
            let bad = text.replace("lambda = 0.98", &format!("{key} = {v}"));
            let m = PlantModel::parse(&bad, "p.toml").expect("model");
            let e = EstimatorSettings::from_model(&m, "p.toml").expect_err("beyond the bounds").to_string();
            let why = e.contains("within") || e.contains("1e12") || e.contains("1e6");
            assert!(e.contains(&format!("estimator.{key}")) && why && e.len() < 300, "{e}");
        }
    }
}

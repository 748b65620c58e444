//! PURE estimation of shaft speed, load torque, inertia and viscous friction from measured speed and pressures
//! (PHYSICS.md §2). Fed Δt and samples; never reads a clock. Implementations: RLS+SGD (the seed paper, corrected)
//! and a Kalman filter.
//!
//! A service builds one estimator per drive and feeds it every sample:
//! `let settings = EstimatorSettings::from_model(&model, path)?;` (the model's `[estimator]` table, checked, bad
//! input naming the key), then `let mut est = build(&settings, &model);` and `est.update(&Measurement { .. })`
//! per sample. Measurements carry Δt since the previous sample; a non-finite field is a missing value.
//! docs/estimator.md gives the design, the measured accuracy and the settings.

pub mod battery;
mod covariance;
mod guard;
mod kalman;
mod paper;
mod periodic;
mod pool;
mod rls_sgd;
pub mod settings;
mod windows;

pub use guard::{Identification, Identified, LoadCharacter, Verdict};
pub use kalman::Kalman;
pub use paper::PaperLiteral;
pub use rls_sgd::RlsSgd;
pub use settings::{DEFAULT_SPEED_NOISE_RAD_S, EstimatorSettings, Method, Resolved};

use crate::plant::PlantModel;

/// One measured sample as the estimators take it. A non-finite field means "missing": the estimator must skip it
/// and keep its state.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Measurement {
    /// Time since the previous sample (s).
    pub dt_s: f64,
    /// Measured shaft speed (rad/s).
    pub omega_rad_s: f64,
    /// Drive torque on the shaft (N·m): `D_m·(p_in − p_out)`, or a measured torque.
    pub drive_torque_nm: f64,
}

crate::units::columns! {
    /// What the estimators say after a sample. Its columns are [`crate::recording::ESTIMATE_COLUMNS`] (tested).
    #[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
    pub struct Estimate {
        pub omega_hat_rad_s: f64,
        pub load_hat_nm: f64,
        pub inertia_hat_kg_m2: f64,
        pub viscous_hat_nm_s_rad: f64,
        /// Standard deviations of J and B as the estimator knows them (rls-sgd: from its RLS covariance). Zero where
        /// they are not estimated but taken from the model (kalman, paper-literal).
        pub inertia_sd_kg_m2: f64,
        pub viscous_sd_nm_s_rad: f64,
        /// What the data say of J and B ([`Identification::code`]): 1 identified, 0 too little excitation, −1 the
        /// nominal predicts as well (and stands), −2 not separable from the load, −3 the model's value.
        pub inertia_identified: f64,
        pub viscous_identified: f64,
        /// What the load looks like ([`LoadCharacter::code`]).
        pub load_character: f64,
    }
}

/// A running estimator. Every output is finite whatever the input.
pub trait Estimator: Send {
    /// Takes one sample and returns the updated estimate.
    fn update(&mut self, m: &Measurement) -> Estimate;
    /// The latest estimate.
    fn estimate(&self) -> Estimate;
    /// A copy in the present state, for a replay that may have to start over.
    fn boxed_clone(&self) -> Box<dyn Estimator>;
}

/// The estimator `settings.method` names, for a model; the settings key at fault when they do not fit the model.
pub fn try_build(
    settings: &EstimatorSettings,
    model: &PlantModel,
) -> Result<Box<dyn Estimator>, crate::error::KeyError> {
    let r = settings.resolve(model)?;
    Ok(match settings.method {
        Method::RlsSgd => Box::new(RlsSgd::new(r)),
        Method::Kalman => Box::new(Kalman::new(r)),
        Method::PaperLiteral => Box::new(PaperLiteral::new(r)),
    })
}

/// The estimator `settings.method` names, for a model. Settings that do not fit the model (see
/// [`EstimatorSettings::resolve`]) fall back to the defaults, so this never fails; check them first with
/// [`EstimatorSettings::from_model`] or [`try_build`] to report the bad key.
pub fn build(settings: &EstimatorSettings, model: &PlantModel) -> Box<dyn Estimator> {
    try_build(settings, model).unwrap_or_else(|_| {
        let fallback = EstimatorSettings { method: settings.method, ..EstimatorSettings::default() };
        let r = fallback.resolve(model).unwrap_or_else(|_| safe_resolved(model));
        match settings.method {
            Method::RlsSgd => Box::new(RlsSgd::new(r)),
            Method::Kalman => Box::new(Kalman::new(r)),
            Method::PaperLiteral => Box::new(PaperLiteral::new(r)),
        }
    })
}

/// Defaults for a model whose own numbers the defaults cannot resolve (cannot happen for a validated model).
fn safe_resolved(model: &PlantModel) -> Resolved {
    let j = if model.motor.inertia_kg_m2.is_finite() && model.motor.inertia_kg_m2 > 0.0 {
        model.motor.inertia_kg_m2
    } else {
        1.0
    };
    let mut m = model.clone();
    m.motor.inertia_kg_m2 = j;
    m.motor.viscous_nm_s_rad = 0.0;
    m.motor.displacement_cm3 = None;
    match EstimatorSettings::default().resolve(&m) {
        Ok(r) => r,
        Err(e) => unreachable!("defaults resolve for a positive inertia: {e:?}"),
    }
}

/// Speeds and torques beyond these are not measurements but garbage; they are treated as missing.
const MAX_ABS_SPEED_RAD_S: f64 = 1e5;
const MAX_ABS_TORQUE_NM: f64 = 1e7;

/// A time step within this share of `max_gap_s` above it is no gap: a clock written in decimal (t_s = 0.1, 0.2, 0.3,
/// …) gives steps of 0.1 ± an ulp, and a recording polled at exactly `max_gap_s` (100 ms) was refused as "longer than
/// max_gap_s", half its steps gaps.
const GAP_ROUNDING: f64 = 1e-3;

/// Whether a time step `dt_s` is longer than `max_gap_s`, beyond the rounding of a decimal clock ([`GAP_ROUNDING`]).
pub(crate) fn beyond_gap(dt_s: f64, max_gap_s: f64) -> bool {
    dt_s > max_gap_s * (1.0 + GAP_ROUNDING)
}

/// The usable parts of a sample: each `None` is missing, non-finite or absurd.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Checked {
    /// Time step, when it is positive and at most `max_gap_s`.
    pub dt_s: Option<f64>,
    /// True when the step is a gap: longer than `max_gap_s`, or not a number.
    pub gap: bool,
    pub omega_rad_s: Option<f64>,
    pub torque_nm: Option<f64>,
}

impl Checked {
    pub fn new(m: &Measurement, max_gap_s: f64) -> Checked {
        let ok_dt = m.dt_s.is_finite() && m.dt_s > 0.0 && !beyond_gap(m.dt_s, max_gap_s);
        let finite_in = |v: f64, max: f64| (v.is_finite() && v.abs() <= max).then_some(v);
        Checked {
            dt_s: ok_dt.then_some(m.dt_s),
            gap: !ok_dt,
            omega_rad_s: finite_in(m.omega_rad_s, MAX_ABS_SPEED_RAD_S),
            torque_nm: finite_in(m.drive_torque_nm, MAX_ABS_TORQUE_NM),
        }
    }
}

/// Runs one `step` of `est`; when it leaves a non-finite estimate (which a correct estimator never produces, but
/// garbage input might), the estimator starts over as `restart` makes it and the estimate from before is reported.
pub(crate) fn step_guarded<E: Estimator>(
    est: &mut E,
    step: impl FnOnce(&mut E),
    restart: impl FnOnce(&E) -> E,
) -> Estimate {
    let before = est.estimate();
    step(est);
    let after = est.estimate();
    if after != finite_or(after, before) {
        *est = restart(est);
        return before;
    }
    after
}

/// Replaces any non-finite field (which a correct estimator never produces) by a fallback.
pub(crate) fn finite_or(e: Estimate, fallback: Estimate) -> Estimate {
    let pick = |v: f64, f: f64| if v.is_finite() { v } else { f };
    Estimate {
        omega_hat_rad_s: pick(e.omega_hat_rad_s, fallback.omega_hat_rad_s),
        load_hat_nm: pick(e.load_hat_nm, fallback.load_hat_nm),
        inertia_hat_kg_m2: pick(e.inertia_hat_kg_m2, fallback.inertia_hat_kg_m2),
        viscous_hat_nm_s_rad: pick(e.viscous_hat_nm_s_rad, fallback.viscous_hat_nm_s_rad),
        inertia_sd_kg_m2: pick(e.inertia_sd_kg_m2, fallback.inertia_sd_kg_m2),
        viscous_sd_nm_s_rad: pick(e.viscous_sd_nm_s_rad, fallback.viscous_sd_nm_s_rad),
        inertia_identified: pick(e.inertia_identified, fallback.inertia_identified),
        viscous_identified: pick(e.viscous_identified, fallback.viscous_identified),
        load_character: pick(e.load_character, fallback.load_character),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A step of `max_gap_s` written in decimal (0.3 − 0.2 = 0.09999999999999998, 0.1 + an ulp) is no gap; a longer
    /// one is.
    #[test]
    fn a_step_of_max_gap_s_in_decimal_is_no_gap() {
        let m = |dt_s: f64| Measurement { dt_s, omega_rad_s: 1.0, drive_torque_nm: 1.0 };
        for dt in [0.3 - 0.2, 0.1, 0.30000000000000004 - 0.2, 0.1 + 1e-12] {
            assert!(!Checked::new(&m(dt), 0.1).gap, "{dt}");
        }
        assert!(Checked::new(&m(0.101), 0.1).gap);
        assert!(beyond_gap(0.2, 0.1) && !beyond_gap(0.1 * (1.0 + 1e-6), 0.1));
    }
}

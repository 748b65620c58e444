//! The estimator battery (docs/estimator.md): a generated scenario run through the plant at 1 ms, polled at a
//! service's rate with the register map's quantisation, then estimated on the same rows by rls-sgd from the
//! scenario's wrong J and B and by the Kalman filter told the true J and B, both scored against the truth.

use super::{Estimate, EstimatorSettings, Measurement, Method, try_build};
use crate::plant::PlantModel;
use crate::plant::scenario::Scenario;
use crate::plant::simulate::Inputs;
use crate::recording::simulated;
use crate::units::{bar_to_pa, cm3_per_rev_to_m3_per_rad};

/// Scores start this long after the start: both estimators begin from a standstill guess.
pub const SCORE_FROM_S: f64 = 5.0;
/// The gates of one run: rls-sgd within these factors of the Kalman filter told the truth…
pub const SPEED_RMSE_FACTOR: f64 = 1.15;
pub const LOAD_RMSE_FACTOR: f64 = 1.3;
/// …and its final J within this fraction of the truth.
pub const INERTIA_TOLERANCE: f64 = 0.15;

/// Register resolution of the default map (CONTRACT.md): pressures 0.01 bar, speed 0.1 rpm.
const PRESSURE_LSB_BAR: f64 = 0.01;
const SPEED_LSB_RAD_S: f64 = 0.1 * std::f64::consts::TAU / 60.0;

/// How one estimator did on one run.
#[derive(Debug, Clone, Copy)]
pub struct Score {
    pub omega_rmse_rad_s: f64,
    pub load_rmse_nm: f64,
    /// The final estimate, with its confidence.
    pub last: Estimate,
    /// Final J and B relative to the truth (0 = exact).
    pub inertia_error: f64,
    pub viscous_error: f64,
}

/// One scenario at one poll period.
#[derive(Debug, Clone)]
pub struct Run {
    pub describe: String,
    pub poll_ms: u32,
    pub rls: Score,
    pub kalman: Score,
}

impl Run {
    pub fn speed_ratio(&self) -> f64 {
        self.rls.omega_rmse_rad_s / self.kalman.omega_rmse_rad_s
    }

    pub fn load_ratio(&self) -> f64 {
        self.rls.load_rmse_nm / self.kalman.load_rmse_nm
    }

    /// The gates that fail, empty when the run holds.
    pub fn failures(&self) -> Vec<String> {
        let mut f = Vec::new();
        if self.speed_ratio() > SPEED_RMSE_FACTOR {
            f.push(format!("ω̂ RMSE {:.2}× Kalman's", self.speed_ratio()));
        }
        if self.load_ratio() > LOAD_RMSE_FACTOR {
            f.push(format!("T̂_L RMSE {:.2}× Kalman's", self.load_ratio()));
        }
        if self.rls.inertia_error.abs() > INERTIA_TOLERANCE {
            f.push(format!("J {:+.0} %", self.rls.inertia_error * 100.0));
        }
        f
    }

    pub fn holds(&self) -> bool {
        self.failures().is_empty()
    }

    /// B's confidence is honest in this run: the true B lies within two of rls-sgd's final standard deviations.
    pub fn viscous_honest(&self) -> bool {
        let (b, e) = (self.rls.last.viscous_hat_nm_s_rad, self.rls.viscous_error);
        (e * b / (1.0 + e)).abs() <= 2.0 * self.rls.last.viscous_sd_nm_s_rad
    }
}

/// The polled rows of a scenario: measurements as the service would hand them over, and the truth beside them.
pub struct Polled {
    pub t_s: Vec<f64>,
    pub measurements: Vec<Measurement>,
    pub true_omega_rad_s: Vec<f64>,
    pub true_load_nm: Vec<f64>,
}

/// Runs the scenario on `truth` at its 1 ms sample and keeps every `poll_ms`-th row, quantised by the register map.
pub fn poll(scenario: &Scenario, truth: &PlantModel, poll_ms: u32) -> Polled {
    let inputs = Inputs {
        setpoint_hz: &|t| scenario.setpoint_hz(t),
        load_nm: &|t, omega, angle| scenario.load.torque_at(t, omega, angle),
    };
    let mut model = truth.clone();
    model.sensors.sample_ms = 1.0;
    let rec = match simulated::run(&model, scenario.duration_s, scenario.seed, &inputs, &mut |_| {}) {
        Ok(rec) => rec,
        Err(crate::error::KeyError { key, message: msg }) => unreachable!("the battery's plant is valid: {key}: {msg}"),
    };
    let col = |name: &str| rec.column(name).unwrap_or_else(|| unreachable!("simulate writes {name}"));
    let d_m = cm3_per_rev_to_m3_per_rad(truth.motor.displacement_cm3.unwrap_or(0.0));
    let q = |v: f64, lsb: f64| (v / lsb).round() * lsb;
    let (t, p_in, p_out, w) = (rec.t_s(), col("p_in_bar"), col("p_out_bar"), col("omega_rad_s"));
    let rows: Vec<usize> = (0..rec.len()).step_by(poll_ms.max(1) as usize).collect();
    let measurements = rows
        .iter()
        .enumerate()
        .map(|(i, &k)| Measurement {
            dt_s: if i == 0 { f64::NAN } else { t[k] - t[rows[i - 1]] },
            omega_rad_s: q(w[k], SPEED_LSB_RAD_S),
            drive_torque_nm: d_m * bar_to_pa(q(p_in[k], PRESSURE_LSB_BAR) - q(p_out[k], PRESSURE_LSB_BAR)),
        })
        .collect();
    Polled {
        t_s: rows.iter().map(|&k| t[k]).collect(),
        measurements,
        true_omega_rad_s: rows.iter().map(|&k| col("true_omega_rad_s")[k]).collect(),
        true_load_nm: rows.iter().map(|&k| col("true_load_nm")[k]).collect(),
    }
}

/// Replays polled rows through an estimator built for `model` and scores it against the truth.
pub fn score(polled: &Polled, settings: &EstimatorSettings, model: &PlantModel, truth: &PlantModel) -> Score {
    let mut est = match try_build(settings, model) {
        Ok(e) => e,
        Err(crate::error::KeyError { key, message }) => {
            unreachable!("the battery's settings resolve: {key}: {message}")
        }
    };
    let k0 = polled.t_s.iter().take_while(|t| **t < SCORE_FROM_S).count();
    let (mut se_w, mut se_l, mut n) = (0.0, 0.0, 0usize);
    let mut last = est.estimate();
    for (k, m) in polled.measurements.iter().enumerate() {
        last = est.update(m);
        if k >= k0 {
            se_w += (last.omega_hat_rad_s - polled.true_omega_rad_s[k]).powi(2);
            se_l += (last.load_hat_nm - polled.true_load_nm[k]).powi(2);
            n += 1;
        }
    }
    let n = n.max(1) as f64;
    Score {
        omega_rmse_rad_s: (se_w / n).sqrt(),
        load_rmse_nm: (se_l / n).sqrt(),
        last,
        inertia_error: last.inertia_hat_kg_m2 / truth.motor.inertia_kg_m2 - 1.0,
        viscous_error: last.viscous_hat_nm_s_rad / truth.motor.viscous_nm_s_rad - 1.0,
    }
}

/// The first seed of a named seed set (docs/estimator.md): `tuned` 1…, `held-out` 1001…, `fresh` 5001…, `unseen`
/// 7001…, `final` 9001…; `None` for another name.
pub fn first_seed(set: &str) -> Option<u64> {
    match set {
        "tuned" => Some(1),
        "held-out" => Some(1001),
        "fresh" => Some(5001),
        "unseen" => Some(7001),
        "final" => Some(9001),
        "sealed" => Some(11001),
        _ => None,
    }
}

/// The scenario's wrong model: `truth` with J and B off by the scenario's factors.
pub fn wrong_model(scenario: &Scenario, truth: &PlantModel) -> PlantModel {
    let mut wrong = truth.clone();
    wrong.motor.inertia_kg_m2 *= scenario.inertia_factor;
    wrong.motor.viscous_nm_s_rad *= scenario.viscous_factor;
    wrong
}

/// One battery run: the scenario on the reference plant at `poll_ms`, rls-sgd (with `settings`) from the wrong
/// start against the Kalman filter (with `reference`'s settings) told the truth.
pub fn run(scenario: &Scenario, poll_ms: u32, settings: &EstimatorSettings, reference: &EstimatorSettings) -> Run {
    let truth = PlantModel::reference();
    let polled = poll(scenario, &truth, poll_ms);
    let wrong = wrong_model(scenario, &truth);
    // rls-sgd is given the wrong model as its nominal one, as a plant engineer's model would be: its bounds and
    // normalisation come from the wrong J and B too.
    let rls_settings = EstimatorSettings { method: Method::RlsSgd, ..settings.clone() };
    let kalman_settings = EstimatorSettings { method: Method::Kalman, ..reference.clone() };
    Run {
        describe: scenario.describe(),
        poll_ms,
        rls: score(&polled, &rls_settings, &wrong, &truth),
        kalman: score(&polled, &kalman_settings, &truth, &truth),
    }
}

//! The estimator battery (docs/estimator.md): a generated scenario run through the plant at 1 ms, polled at a
//! service's rate with the register map's quantisation (and a seeded few polls lost), then estimated on the same
//! rows by rls-sgd from the scenario's wrong J and B, by the Kalman filter told the true J and B, and by the Kalman
//! filter on the wrong J and B (what a user gets with no adaptation), all scored against the truth.

use super::{Estimate, EstimatorSettings, Measurement, Method, try_build};
use crate::plant::PlantModel;
use crate::plant::load::unit_hash;
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

/// The fraction of polls lost on the link in [`run`] by default (the example's `lost=`): a lost poll's row is not
/// handed over, so the next one comes with twice the Δt.
pub const LOST_POLLS: f64 = 0.02;
/// The times (s) at which a [`Score`] keeps the estimate: the first row at or after each, within the run.
pub const CHECKPOINTS_S: [f64; 4] = [15.0, 30.0, 45.0, 60.0];
/// Mixed into the scenario's seed for the lost polls, so that they do not follow the scenario's other draws.
const LOST_POLL_SALT: u64 = 0x6c6f_7374_706f_6c6c;

/// Register resolution of the default map (CONTRACT.md): pressures 0.01 bar, speed 0.1 rpm.
const PRESSURE_LSB_BAR: f64 = 0.01;
const SPEED_LSB_RAD_S: f64 = 0.1 * std::f64::consts::TAU / 60.0;

/// How one estimator did on one run.
#[derive(Debug, Clone)]
pub struct Score {
    pub omega_rmse_rad_s: f64,
    pub load_rmse_nm: f64,
    /// The final estimate, with its confidence.
    pub last: Estimate,
    /// Final J and B relative to the truth (0 = exact).
    pub inertia_error: f64,
    pub viscous_error: f64,
    /// The estimate at each of [`CHECKPOINTS_S`] the run reaches: how it converges, not only where it ends.
    pub checkpoints: Vec<(f64, Estimate)>,
    /// How often J and B fell back from identified to too little excitation or the nominal predicting as well (over
    /// every row): a state a user can rely on does not flap.
    pub identified_lost: (usize, usize),
}

/// One scenario at one poll period.
#[derive(Debug, Clone)]
pub struct Run {
    pub family: crate::plant::scenario::Family,
    pub describe: String,
    pub poll_ms: u32,
    /// The fraction of polls lost.
    pub lost_fraction: f64,
    pub rls: Score,
    pub kalman: Score,
    /// The Kalman filter on the scenario's wrong J and B: what a user gets with no adaptation.
    pub nominal: Score,
    /// The plant's true J and B, for the checkpoints' coverage.
    pub truth: (f64, f64),
}

/// The guard's gates (docs/estimator.md): rls-sgd's T̂_L RMSE at most this factor of the nominal-model Kalman
/// filter's in every run…
pub const NOMINAL_RMSE_FACTOR: f64 = 1.05;
/// …and the truth within this many of its standard deviations at the checkpoints, unless flagged not identified.
pub const COVERAGE_SIGMAS: f64 = 2.0;

/// A run judged by the guard's gates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GuardVerdict {
    /// T̂_L no worse than the nominal-model Kalman filter's (within [`NOMINAL_RMSE_FACTOR`]).
    pub no_harm: bool,
    /// Where the final J is identified and B known (identified, or known as friction or a load ∝ ω): T̂_L within
    /// [`LOAD_RMSE_FACTOR`] of the Kalman filter told the truth. None where they are not.
    pub near_truth_reference: Option<bool>,
    /// Checkpoint values (J and B at each) whose truth lies within [`COVERAGE_SIGMAS`] or that are flagged not
    /// identified, and all checkpoint values.
    pub covered: (usize, usize),
    /// Checkpoints (and the end) where J is reported identified, and of those, how many have it within
    /// [`INERTIA_TOLERANCE`].
    pub inertia_sound: (usize, usize),
}

impl Run {
    pub fn speed_ratio(&self) -> f64 {
        self.rls.omega_rmse_rad_s / self.kalman.omega_rmse_rad_s
    }

    pub fn load_ratio(&self) -> f64 {
        self.rls.load_rmse_nm / self.kalman.load_rmse_nm
    }

    /// rls-sgd's T̂_L RMSE over that of the Kalman filter on the wrong model: below 1, adapting paid.
    pub fn nominal_ratio(&self) -> f64 {
        self.rls.load_rmse_nm / self.nominal.load_rmse_nm
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

    /// The guard's gates on this run.
    pub fn guard(&self) -> GuardVerdict {
        let identified = |code: f64| code == super::Identification::Identified.code();
        let last = &self.rls.last;
        let (j, b) = self.truth;
        let points: Vec<&Estimate> = self.rls.checkpoints.iter().map(|(_, e)| e).collect();
        let mut covered = (0, 0);
        for e in &points {
            for (x, sd, code, truth) in [
                (e.inertia_hat_kg_m2, e.inertia_sd_kg_m2, e.inertia_identified, j),
                (e.viscous_hat_nm_s_rad, e.viscous_sd_nm_s_rad, e.viscous_identified, b),
            ] {
                covered.1 += 1;
                covered.0 += usize::from(!identified(code) || (x - truth).abs() <= COVERAGE_SIGMAS * sd);
            }
        }
        let mut inertia_sound = (0, 0);
        for e in points.iter().copied().chain(std::iter::once(last)) {
            if identified(e.inertia_identified) {
                inertia_sound.0 += 1;
                inertia_sound.1 += usize::from((e.inertia_hat_kg_m2 / j - 1.0).abs() <= INERTIA_TOLERANCE);
            }
        }
        GuardVerdict {
            no_harm: self.nominal_ratio() <= NOMINAL_RMSE_FACTOR,
            // B known as the speed term counts, whether or not it can be called friction (`FrictionOrLoad`)
            near_truth_reference: (identified(last.inertia_identified)
                && (identified(last.viscous_identified)
                    || last.viscous_identified == super::Identification::FrictionOrLoad.code()))
            .then(|| self.load_ratio() <= LOAD_RMSE_FACTOR),
            covered,
            inertia_sound,
        }
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

/// Runs the scenario on `truth` at its 1 ms sample and keeps every `poll_ms`-th row, quantised by the register map;
/// no poll is lost.
pub fn poll(scenario: &Scenario, truth: &PlantModel, poll_ms: u32) -> Polled {
    poll_losing(scenario, truth, poll_ms, 0.0)
}

/// As [`poll`], with `lost_fraction` of the polls (after the first) lost: drawn per row from the scenario's seed,
/// so the same rows are lost on every run. The row after a lost one carries the longer Δt.
pub fn poll_losing(scenario: &Scenario, truth: &PlantModel, poll_ms: u32, lost_fraction: f64) -> Polled {
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
    let lost = |k: usize| k > 0 && unit_hash(scenario.seed ^ LOST_POLL_SALT, k as u64) < lost_fraction;
    let rows: Vec<usize> = (0..rec.len()).step_by(poll_ms.max(1) as usize).filter(|&k| !lost(k)).collect();
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
    let mut checkpoints = Vec::new();
    let mut identified_lost = (0, 0);
    // identified, then back to too little excitation or the nominal predicting as well: the evidence lost (not a
    // reading refined to friction-or-load or a load following the speed)
    let lost = |before: f64, now: f64| {
        use super::Identification::{Identified, NominalPredictsAsWell, TooLittleExcitation};
        before == Identified.code() && (now == TooLittleExcitation.code() || now == NominalPredictsAsWell.code())
    };
    for (k, m) in polled.measurements.iter().enumerate() {
        let before = last;
        last = est.update(m);
        identified_lost.0 += usize::from(lost(before.inertia_identified, last.inertia_identified));
        identified_lost.1 += usize::from(lost(before.viscous_identified, last.viscous_identified));
        if let Some(&c) = CHECKPOINTS_S.get(checkpoints.len())
            && polled.t_s[k] >= c - 1e-9
        {
            checkpoints.push((c, last));
        }
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
        checkpoints,
        identified_lost,
    }
}

/// The first seed of a named seed set (docs/estimator.md): `tuned` 1…, `held-out` 1001…, `fresh` 5001…, `unseen`
/// 7001…, `final` 9001…, `sealed` 11001…, `novel` 13001…, `last` 15001…, `spare` 17001…, `reserve` 19001…, `blind`
/// 21001…, `untouched` 23001…; `None` for another name.
pub fn first_seed(set: &str) -> Option<u64> {
    match set {
        "tuned" => Some(1),
        "held-out" => Some(1001),
        "fresh" => Some(5001),
        "unseen" => Some(7001),
        "final" => Some(9001),
        "sealed" => Some(11001),
        "novel" => Some(13001),
        "last" => Some(15001),
        "spare" => Some(17001),
        "reserve" => Some(19001),
        "blind" => Some(21001),
        "untouched" => Some(23001),
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

/// One battery run: the scenario on `truth` at `poll_ms` with `lost_fraction` of the polls lost ([`LOST_POLLS`] as a
/// rule), rls-sgd (with `settings`) from the wrong start against the Kalman filter (with `reference`'s settings) told
/// the truth, and against that filter on the wrong model.
pub fn run(
    truth: &PlantModel,
    scenario: &Scenario,
    poll_ms: u32,
    lost_fraction: f64,
    settings: &EstimatorSettings,
    reference: &EstimatorSettings,
) -> Run {
    let polled = poll_losing(scenario, truth, poll_ms, lost_fraction);
    let wrong = wrong_model(scenario, truth);
    // rls-sgd is given the wrong model as its nominal one, as a plant engineer's model would be: its bounds and
    // normalisation come from the wrong J and B too.
    let rls_settings = EstimatorSettings { method: Method::RlsSgd, ..settings.clone() };
    let kalman_settings = EstimatorSettings { method: Method::Kalman, ..reference.clone() };
    Run {
        family: scenario.family,
        describe: scenario.describe(),
        poll_ms,
        lost_fraction,
        rls: score(&polled, &rls_settings, &wrong, truth),
        kalman: score(&polled, &kalman_settings, truth, truth),
        nominal: score(&polled, &kalman_settings, &wrong, truth),
        truth: (truth.motor.inertia_kg_m2, truth.motor.viscous_nm_s_rad),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plant::LoadSpec;
    use crate::plant::scenario::{Family, LoadProgram};

    #[test]
    fn lost_polls_are_seeded_and_lengthen_the_next_step() {
        let truth = PlantModel::reference();
        let s = Scenario::generate(Family::Centrifugal, 3, 20.0);
        let whole = poll(&s, &truth, 10);
        let lossy = poll_losing(&s, &truth, 10, 0.05);
        assert_eq!(whole.t_s.len(), 2001);
        let lost = whole.t_s.len() - lossy.t_s.len();
        assert!((50..=150).contains(&lost), "{lost} of 2000 lost at 5 %");
        assert_eq!(lossy.t_s, poll_losing(&s, &truth, 10, 0.05).t_s, "the same polls are lost every run");
        let doubled = lossy.measurements.iter().filter(|m| (m.dt_s - 0.02).abs() < 1e-9).count();
        assert!(doubled > 0 && doubled <= lost, "{doubled}");
        assert!(lossy.measurements.iter().skip(1).all(|m| m.dt_s > 0.0099));
        // a kept row is the row of the lossless poll at the same time, truth included
        let k = whole.t_s.iter().position(|t| *t == lossy.t_s[500]).expect("same rows");
        assert_eq!(whole.true_load_nm[k], lossy.true_load_nm[500]);
    }

    #[test]
    fn a_run_scores_the_nominal_filter_and_keeps_checkpoints() {
        let s = Scenario::generate(Family::Brake, 1, 32.0);
        let settings = EstimatorSettings::default();
        let r = run(&PlantModel::reference(), &s, 10, LOST_POLLS, &settings, &settings);
        let times: Vec<f64> = r.rls.checkpoints.iter().map(|(t, _)| *t).collect();
        assert_eq!(times, [15.0, 30.0], "only the checkpoints within 32 s");
        assert_eq!(r.nominal.checkpoints.len(), 2);
        assert!(r.nominal.load_rmse_nm.is_finite() && r.nominal_ratio().is_finite(), "{r:?}");
        let j = r.nominal.inertia_error;
        assert!((j - (s.inertia_factor - 1.0)).abs() < 1e-9, "the filter on the wrong model keeps its J: {j}");
    }

    /// No record of ω and drive torque tells viscous friction from a load ∝ ω: a plant with friction B and a load
    /// c + k·ω leaves the same record as one with friction B + k and the load c. So rls-sgd, started from the same
    /// wrong model, gives the same J, B and T̂_L on both (T̂_L is right on one plant and off by k·ω on the other,
    /// whatever an estimator does), and says so: B is not reported as identified friction on either.
    #[test]
    fn friction_and_a_load_proportional_to_speed_leave_one_record_and_the_estimate_says_so() {
        let speed_load = Scenario::generate(Family::Linear, 9, 30.0);
        let LoadProgram::Profile(LoadSpec::Speed { constant_nm, linear_nm_s_rad, .. }) = speed_load.load else {
            unreachable!("the linear family is a speed profile")
        };
        let plant_a = PlantModel::reference();
        let mut plant_b = plant_a.clone();
        plant_b.motor.viscous_nm_s_rad += linear_nm_s_rad;
        let constant_load = Scenario {
            load: LoadProgram::Profile(LoadSpec::Constant { torque_nm: constant_nm }),
            ..speed_load.clone()
        };
        let (a, b) = (poll(&speed_load, &plant_a, 1), poll(&constant_load, &plant_b, 1));
        // the same record to a quantum of the register map (rounding differs where a value sits on a boundary)
        let torque_lsb = 2.0
            * cm3_per_rev_to_m3_per_rad(plant_a.motor.displacement_cm3.unwrap_or(0.0))
            * bar_to_pa(PRESSURE_LSB_BAR);
        for (x, y) in a.measurements.iter().zip(&b.measurements) {
            assert!((x.omega_rad_s - y.omega_rad_s).abs() <= 1.01 * SPEED_LSB_RAD_S, "{x:?} {y:?}");
            assert!((x.drive_torque_nm - y.drive_torque_nm).abs() <= 1.01 * torque_lsb, "{x:?} {y:?}");
        }
        let settings = EstimatorSettings { method: Method::RlsSgd, ..EstimatorSettings::default() };
        let wrong = wrong_model(&speed_load, &plant_a);
        let (ea, eb) = (score(&a, &settings, &wrong, &plant_a), score(&b, &settings, &wrong, &plant_b));
        let (la, lb) = (ea.last, eb.last);
        assert!((la.viscous_hat_nm_s_rad / lb.viscous_hat_nm_s_rad - 1.0).abs() < 1e-3, "{la:?} {lb:?}");
        assert!((la.inertia_hat_kg_m2 / lb.inertia_hat_kg_m2 - 1.0).abs() < 1e-3, "{la:?} {lb:?}");
        assert!((la.load_hat_nm - lb.load_hat_nm).abs() < 0.05, "{la:?} {lb:?}");
        for e in [la, lb] {
            assert_ne!(e.viscous_identified, super::super::Identification::Identified.code(), "{e:?}");
        }
        // the load's RMSE on the two truths differs by about k·ω: what the record cannot show
        eprintln!(
            "B {:.4} ± {:.4} ({}); T̂_L RMSE {:.2} N·m against c + k·ω, {:.2} against c",
            la.viscous_hat_nm_s_rad,
            la.viscous_sd_nm_s_rad,
            super::super::Identification::from_code(la.viscous_identified).name(),
            ea.load_rmse_nm,
            eb.load_rmse_nm
        );
    }
}

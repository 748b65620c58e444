//! How an effect is proven: blocked cross-validation (out-of-fold free runs, the regime where an effect acts) and
//! the delete-one-block jackknife of the confidence intervals.

use std::collections::BTreeMap;

use crate::plant::PlantModel;

use super::predict::{self, Prediction};
use super::search::{self, MechTerms, Rows, Scored};
use super::series::Series;
use super::{Interval, Options, parameters};

/// A candidate fitted on every fold.
pub(super) struct CrossValidated {
    /// Each fold's model (the fold's previous model where the effect could not be fitted on it).
    pub(super) models: Vec<Option<(PlantModel, MechTerms)>>,
    /// Out-of-fold score (mean squared NRMSE of the blocks' free runs) with the effect.
    pub(super) score: f64,
    pub(super) regime: Option<Regime>,
}

/// The out-of-fold error on the rows of the regime where an effect acts.
pub(super) struct Regime {
    pub(super) name: String,
    pub(super) seconds: f64,
    /// 1 − after/before of the root of the regime's share of the out-of-fold score.
    pub(super) drop: f64,
}

/// The out-of-fold prediction: block k predicted by fold k's model, run free from the block's measured state.
pub(super) fn out_of_fold(
    models: &[Option<(PlantModel, MechTerms)>],
    folds: &[Rows],
    s: &Series,
) -> Option<Prediction> {
    let n = s.len();
    let mut out: Option<Prediction> = None;
    let copy = |dst: &mut Vec<f64>, src: &[f64], a: usize, b: usize| dst[a..b].copy_from_slice(&src[a..b]);
    for (m, r) in models.iter().zip(folds) {
        let (a, b) = r.held_out?;
        let (m, _) = m.as_ref()?;
        let p = predict::predict_rows(m, s, a, b, &[]).ok()?;
        let o = out.get_or_insert_with(|| Prediction {
            omega_rad_s: vec![f64::NAN; n],
            dp_bar: p.dp_bar.as_ref().map(|_| vec![f64::NAN; n]),
            torque_nm: p.torque_nm.as_ref().map(|_| vec![f64::NAN; n]),
            f_drive_hz: p.f_drive_hz.as_ref().map(|_| vec![f64::NAN; n]),
            f_drive_nominal_hz: p.f_drive_nominal_hz.as_ref().map(|_| vec![f64::NAN; n]),
            dp_noise_bar2: p.dp_noise_bar2,
        });
        copy(&mut o.omega_rad_s, &p.omega_rad_s, a, b);
        if let (Some(d), Some(v)) = (o.dp_bar.as_mut(), p.dp_bar.as_ref()) {
            copy(d, v, a, b);
        }
        if let (Some(d), Some(v)) = (o.torque_nm.as_mut(), p.torque_nm.as_ref()) {
            copy(d, v, a, b);
        }
        if let (Some(d), Some(v)) = (o.f_drive_hz.as_mut(), p.f_drive_hz.as_ref()) {
            copy(d, v, a, b);
        }
        if let (Some(d), Some(v)) = (o.f_drive_nominal_hz.as_mut(), p.f_drive_nominal_hz.as_ref()) {
            copy(d, v, a, b);
        }
    }
    out
}

pub(super) fn out_of_fold_score(models: &[Option<(PlantModel, MechTerms)>], folds: &[Rows], s: &Series) -> Option<f64> {
    let p = out_of_fold(models, folds, s)?;
    Some(predict::errors(&p, s, 0, s.len()).score(s.family)).filter(|v| v.is_finite())
}

/// Hydraulic score restricted to `rows`: Σ over the rows of the squared error of each judged signal, over that
/// signal's total variance on the whole recording, averaged over the signals (the regime's share of the score).
fn regime_score(p: &Prediction, s: &Series, rows: &[bool]) -> f64 {
    let part = |sim: &[f64], meas: &[f64]| -> f64 {
        let fin: Vec<(f64, f64)> =
            sim.iter().zip(meas).map(|(a, b)| (*a, *b)).filter(|(a, b)| a.is_finite() && b.is_finite()).collect();
        let mean = fin.iter().map(|x| x.1).sum::<f64>() / fin.len().max(1) as f64;
        let den: f64 = fin.iter().map(|x| (x.1 - mean).powi(2)).sum();
        let num: f64 = sim
            .iter()
            .zip(meas)
            .zip(rows)
            .filter(|((a, b), r)| **r && a.is_finite() && b.is_finite())
            .map(|((a, b), _)| (a - b).powi(2))
            .sum();
        if den > 0.0 { num / den } else { f64::NAN }
    };
    let w = part(&p.omega_rad_s, &s.omega_rad_s);
    match (&p.dp_bar, &s.dp_bar) {
        (Some(sim), Some(meas)) => 0.5 * (w + part(sim, meas)),
        _ => w,
    }
}

/// A dead time acts while the drive follows a setpoint move: the rows up to this many dead times after the
/// setpoint changed, and at least `DEAD_TIME_REGIME_MIN_S`.
const DEAD_TIME_REGIME_LAGS: f64 = 8.0;
const DEAD_TIME_REGIME_MIN_S: f64 = 0.25;

/// The rows at most `after_s` after the setpoint last changed (a step, or any sample of a ramp).
fn moving(setpoint: &[f64], after_s: f64, sample_hz: f64) -> Vec<bool> {
    let span = (after_s * sample_hz).round() as usize;
    let mut last_move: Option<usize> = None;
    (0..setpoint.len())
        .map(|k| {
            if k > 0 && (setpoint[k] - setpoint[k - 1]).abs() > 1e-9 {
                last_move = Some(k);
            }
            last_move.is_some_and(|m| k - m <= span)
        })
        .collect()
}

/// Fits candidate `id` on every fold (on top of that fold's current model) and scores the blocks out of fold.
pub(super) fn cross_validate(
    id: &str,
    standard: &Scored,
    fold_current: &[Option<(PlantModel, MechTerms)>],
    folds: &[Rows],
    s: &Series,
    opts: &Options,
) -> Option<CrossValidated> {
    let models: Vec<Option<(PlantModel, MechTerms)>> = fold_current
        .iter()
        .zip(folds)
        .map(|(cur, r)| {
            let (m, t) = cur.as_ref()?;
            search::candidate(id, m, *t, s, r, Some(&standard.model)).or_else(|| Some((m.clone(), *t)))
        })
        .collect();
    let p = out_of_fold(&models, folds, s)?;
    let score = predict::errors(&p, s, 0, s.len()).score(s.family);
    if !score.is_finite() {
        return None;
    }
    // the regime where the effect acts, from the standard fit
    let e = &standard.model.effects;
    let acts: Option<(String, Vec<bool>)> = match (id, e.stribeck_friction, e.dead_time, &s.setpoint_hz) {
        ("stribeck_friction", Some(st), _, _) => Some((
            format!("low speed (|ω| < {:.2} rad/s)", 2.0 * st.speed_rad_s),
            s.omega_f.iter().map(|w| w.abs() < 2.0 * st.speed_rad_s).collect(),
        )),
        ("dead_time", _, Some(d), Some(sp)) => {
            let after_s = (DEAD_TIME_REGIME_LAGS * d.ms / 1e3).max(DEAD_TIME_REGIME_MIN_S);
            Some((
                format!("setpoint moves (up to {after_s:.2} s after the setpoint changed)"),
                moving(sp, after_s, s.sample_hz),
            ))
        }
        _ => None,
    };
    let regime = acts.and_then(|(name, rows)| {
        let seconds = rows.iter().filter(|r| **r).count() as f64 / s.sample_hz;
        if seconds < opts.regime_min_s {
            return None;
        }
        let before = out_of_fold(fold_current, folds, s).map(|q| regime_score(&q, s, &rows));
        let after = regime_score(&p, s, &rows);
        before.filter(|b| *b > 0.0 && after.is_finite()).map(|b| Regime {
            name,
            seconds,
            drop: 1.0 - (after / b).sqrt(),
        })
    });
    Some(CrossValidated { models, score, regime })
}

/// Delete-one-block jackknife: 95 % interval of each `key` around the reported value, from the fold estimates. A
/// dead time's half-width is at least the recording's time resolution, a sample period over √12 (where in its
/// period a row was stamped): the drive read back gives every fold the same lag to a few µs, and what the folds
/// cannot show is how the free run's timing differs from the plant's (on the slow programs, 12.477 ms for 12.5).
pub(super) fn jackknife(
    reported: &PlantModel,
    folds: &[Option<(PlantModel, MechTerms)>],
    keys: &[String],
    sample_hz: f64,
) -> BTreeMap<String, Interval> {
    let reported = parameters(reported);
    let fold_params: Vec<BTreeMap<String, f64>> = folds.iter().flatten().map(|(m, _)| parameters(m)).collect();
    let mut out = BTreeMap::new();
    for key in keys {
        let Some(&theta) = reported.get(key) else { continue };
        let v: Vec<f64> = fold_params.iter().filter_map(|p| p.get(key).copied()).filter(|x| x.is_finite()).collect();
        let m = v.len();
        if m < 3 {
            continue;
        }
        let mean = v.iter().sum::<f64>() / m as f64;
        let se = ((m as f64 - 1.0) / m as f64 * v.iter().map(|x| (x - mean).powi(2)).sum::<f64>()).sqrt();
        // Student t, 97.5 % quantile, m − 1 degrees of freedom
        let t = match m - 1 {
            2 => 4.303,
            3 => 3.182,
            4 => 2.776,
            5 => 2.571,
            6 => 2.447,
            7 => 2.365,
            _ => 2.306,
        };
        let floor = if key == "dead_time.ms" { 1e3 / (sample_hz * 12f64.sqrt()) } else { 0.0 };
        let half = (t * se).max(floor);
        out.insert(key.clone(), Interval { low: theta - half, high: theta + half });
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_dead_time_interval_is_never_narrower_than_the_recordings_time_resolution() {
        let mut m = PlantModel::reference();
        m.effects.dead_time = Some(crate::plant::effects::DeadTime { ms: 12.5 });
        // every fold finds the same lag: the spread alone would give an interval of no width
        let folds: Vec<Option<(PlantModel, MechTerms)>> =
            (0..4).map(|_| Some((m.clone(), MechTerms::default()))).collect();
        let keys = ["dead_time.ms".to_string(), "inertia_kg_m2".to_string()];
        let ci = jackknife(&m, &folds, &keys, 1000.0);
        let half = 1.0 / 12f64.sqrt();
        assert!((ci["dead_time.ms"].high - 12.5 - half).abs() < 1e-12, "{:?}", ci["dead_time.ms"]);
        assert!((12.5 - ci["dead_time.ms"].low - half).abs() < 1e-12);
        // no floor on the other parameters
        assert_eq!(ci["inertia_kg_m2"].high, m.motor.inertia_kg_m2);
    }
}

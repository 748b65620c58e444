//! What a scored model shows against the recording: the residual of each judged signal and its noise floor, the
//! traces the report draws, and a finding's evidence (where the effect shows, how much it removed). Part of the
//! PURE analysis room ([`super`]).

use std::collections::BTreeMap;

use super::explain::explain;
use super::mismatch;
use super::search::Scored;
use super::series::{Family, Series};
use super::signal;
use super::{Evidence, Finding, Traces, effect_parameters};

/// The sensor-noise floor of each judged signal, as the residual sees it: σ of the white part of the measurement
/// (what a zero-phase low-pass removes, robustly, scaled for the pass band); for a filtered comparison (torque)
/// the part of that noise inside the pass band. The flow family's ΔP is predicted from the measured speed, so its
/// floor adds the share of the speed sensor's noise that `sc`'s prediction carries.
pub(super) fn noise_floors(s: &Series, sc: &Scored) -> Vec<(&'static str, f64)> {
    let passed = (2.0 * s.cutoff_hz / s.sample_hz).clamp(0.0, 0.9);
    let sigma = |raw: &[f64]| -> f64 {
        let f = signal::filtfilt_butter4(raw, s.cutoff_hz, s.sample_hz);
        let mut d: Vec<f64> = raw.iter().zip(&f).map(|(a, b)| (a - b).abs()).filter(|v| v.is_finite()).collect();
        d.sort_by(f64::total_cmp);
        let mad = d.get(d.len() / 2).copied().unwrap_or(0.0);
        1.4826 * mad / (1.0 - passed).sqrt()
    };
    let mut out = Vec::new();
    match s.family {
        Family::Hydraulic => {
            out.push(("omega", sigma(&s.omega_rad_s)));
            if let Some(dp) = &s.dp_bar {
                out.push(("dp", sigma(dp)));
            }
        }
        Family::Torque => out.push(("torque", sigma(&s.drive_torque_nm) * passed.sqrt())),
        Family::Flow => {
            if let Some(dp) = &s.dp_bar {
                out.push(("dp", sigma(dp).hypot(sc.prediction.dp_noise_bar2.max(0.0).sqrt())));
            }
            if let Some(f) = &s.f_drive_hz {
                // the register's 0.01 Hz quantisation at least
                out.push(("f_drive", sigma(f).max(0.01 / 12f64.sqrt())));
            }
        }
    }
    out
}

/// Per row, the variance that the time stamps' own uncertainty makes of the drive frequency: a row is placed within
/// one sample period T (a service recording stamps it when the read is sent; the setpoint it carries lands after the
/// reply), uniform over T, so σ_t = T/√12 and the frequency the model ramps moves by ḟ·σ_t. `None` without a drive
/// frequency prediction.
pub(super) fn timing_variance(s: &Series, sc: &Scored) -> Option<Vec<f64>> {
    let f = sc.prediction.f_drive_hz.as_ref()?;
    let sigma_t = 1.0 / (s.sample_hz * 12f64.sqrt());
    let n = f.len().min(s.t_s.len());
    Some(
        (0..n)
            .map(|i| {
                let (a, b) = (i.saturating_sub(1), (i + 1).min(n - 1));
                let dt = s.t_s[b] - s.t_s[a];
                let rate = if dt > 0.0 { (f[b] - f[a]) / dt } else { 0.0 };
                (rate * sigma_t).powi(2)
            })
            .collect(),
    )
}

/// Measured − model for each judged signal of the family, over the whole recording.
/// Residuals (measured − predicted) per judged signal; NaN where nothing was measured, so that no window of
/// filled-in values is called unexplained.
pub(super) fn residual_signals(sc: &Scored, s: &Series) -> Vec<(&'static str, Vec<f64>)> {
    let mut out = residual_signals_filled(sc, s);
    for (name, r) in &mut out {
        let mask = match *name {
            "omega" => &s.measured_omega,
            "dp" => &s.measured_dp,
            "f_drive" => &s.measured_f_drive,
            _ => continue,
        };
        for (v, m) in r.iter_mut().zip(mask) {
            if !m {
                *v = f64::NAN;
            }
        }
    }
    out
}

fn residual_signals_filled(sc: &Scored, s: &Series) -> Vec<(&'static str, Vec<f64>)> {
    let mut out = Vec::new();
    match s.family {
        Family::Hydraulic => {
            out.push(("omega", s.omega_rad_s.iter().zip(&sc.prediction.omega_rad_s).map(|(m, p)| m - p).collect()));
            if let (Some(meas), Some(sim)) = (&s.dp_bar, &sc.prediction.dp_bar) {
                out.push(("dp", meas.iter().zip(sim).map(|(m, p)| m - p).collect()));
            }
        }
        Family::Torque => {
            if let Some(tau) = &sc.prediction.torque_nm {
                out.push(("torque", s.drive_torque_f.iter().zip(tau).map(|(m, p)| m - p).collect()));
            }
        }
        Family::Flow => {
            if let (Some(meas), Some(sim)) = (&s.dp_bar, &sc.prediction.dp_bar) {
                out.push(("dp", meas.iter().zip(sim).map(|(m, p)| m - p).collect()));
            }
            if let (Some(meas), Some(sim)) = (&s.f_drive_hz, &sc.prediction.f_drive_hz) {
                out.push(("f_drive", meas.iter().zip(sim).map(|(m, p)| m - p).collect()));
            }
        }
    }
    out
}

fn effort(sc: &Scored, s: &Series) -> Vec<f64> {
    match s.family {
        Family::Hydraulic | Family::Flow => sc.prediction.dp_bar.clone().unwrap_or_default(),
        Family::Torque => sc.prediction.torque_nm.clone().unwrap_or_default(),
    }
}

pub(super) fn traces(base: &Scored, improved: &Scored, s: &Series) -> Traces {
    let (effort_name, effort_meas) = match &s.dp_bar {
        Some(dp) => ("ΔP (bar)", dp.clone()),
        None => ("torque (N·m)", s.drive_torque_f.clone()),
    };
    Traces {
        t_s: s.t_s.clone(),
        split: s.split,
        omega_meas: s.omega_rad_s.clone(),
        omega_baseline: base.prediction.omega_rad_s.clone(),
        omega_improved: improved.prediction.omega_rad_s.clone(),
        effort_name,
        effort_meas,
        effort_baseline: effort(base, s),
        effort_improved: effort(improved, s),
        omega_f: s.omega_f.clone(),
        drive_meas: s.f_drive_hz.clone().unwrap_or_default(),
        drive_baseline: base.prediction.f_drive_hz.clone().unwrap_or_default(),
        drive_improved: improved.prediction.f_drive_hz.clone().unwrap_or_default(),
    }
}

/// The correlation of `a` and `b` over the rows where both are measured (a masked row is NaN).
fn correlation(a: &[f64], b: &[f64]) -> f64 {
    let pairs: Vec<(f64, f64)> = measured_pairs(a, b).collect();
    let n = pairs.len() as f64;
    if n < 2.0 {
        return 0.0;
    }
    let ma = pairs.iter().map(|p| p.0).sum::<f64>() / n;
    let mb = pairs.iter().map(|p| p.1).sum::<f64>() / n;
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in &pairs {
        sab += (x - ma) * (y - mb);
        saa += (x - ma).powi(2);
        sbb += (y - mb).powi(2);
    }
    if saa > 0.0 && sbb > 0.0 { sab / (saa * sbb).sqrt() } else { 0.0 }
}

pub(super) fn finding(
    id: &str,
    before: &Scored,
    after: &Scored,
    delta_bic: f64,
    s: &Series,
    cond: &mismatch::Conditions,
) -> Finding {
    let family = s.family;
    let (b, a) = (before.validation.score(family), after.validation.score(family));
    // the judged signal where the effect changed the prediction most, on the validation segment
    let rb = residual_signals(before, s);
    let ra = residual_signals(after, s);
    let v = s.split;
    let mut corr = 0.0;
    let mut where_it_shows = String::new();
    if let Some(k) = most_improved(&rb, &ra, v) {
        let ((name, r0), (_, r1)) = (&rb[k], &ra[k]);
        let change: Vec<f64> = r0[v..].iter().zip(&r1[v..]).map(|(x, y)| x - y).collect();
        corr = correlation(&r0[v..], &change);
        // the windows where the effect removed the most residual
        let w = ((mismatch::WINDOW_S * s.sample_hz) as usize).max(10);
        let mut gains: Vec<(f64, usize)> = (0..r0.len() / w)
            .map(|i| {
                let (p, q) = (i * w, (i + 1) * w);
                (gain_of(&r0[p..q], &r1[p..q]), p)
            })
            .collect();
        gains.sort_by(|x, y| y.0.total_cmp(&x.0));
        let top: Vec<usize> = gains.iter().take(5).map(|g| g.1).collect();
        let mut counts: BTreeMap<String, usize> = BTreeMap::new();
        for p in top {
            *counts.entry(cond.describe(s, p, p + w)).or_default() += 1;
        }
        let most = counts.into_iter().max_by_key(|c| c.1).map(|c| c.0).unwrap_or_default();
        where_it_shows = format!("{name}: {most}");
    }
    let parameters = effect_parameters(&after.model, id);
    let explanation = explain(id, &after.model, s, b, a);
    Finding {
        effect: id.to_string(),
        parameters,
        confidence_intervals: BTreeMap::new(),
        explanation,
        evidence: Evidence {
            delta_bic,
            validation_score_before: b,
            validation_score_after: a,
            relative_drop: 1.0 - (a / b).sqrt(),
            residual_correlation: corr,
            where_it_shows,
            cross_validation_score_before: None,
            cross_validation_score_after: None,
            validated_on: String::new(),
        },
    }
}

/// The judged signal whose residual an effect lowered most against its own size, on the rows from `v` (before: `rb`,
/// after: `ra`, the same signals in the same order).
fn most_improved(rb: &[(&'static str, Vec<f64>)], ra: &[(&'static str, Vec<f64>)], v: usize) -> Option<usize> {
    let mut best: Option<(usize, f64)> = None;
    for (k, ((_, r0), (_, r1))) in rb.iter().zip(ra).enumerate() {
        let norm = s_norm(&r0[v..]);
        if norm <= 0.0 {
            continue;
        }
        let relative = gain_of(&r0[v..], &r1[v..]) / norm;
        if best.is_none_or(|(_, b)| relative > b) {
            best = Some((k, relative));
        }
    }
    best.map(|(k, _)| k)
}

/// Σ x² over the measured rows (a masked row is NaN).
fn s_norm(x: &[f64]) -> f64 {
    x.iter().filter(|v| v.is_finite()).map(|v| v * v).sum()
}

/// The pairs of `a` and `b` where both are measured.
fn measured_pairs<'a>(a: &'a [f64], b: &'a [f64]) -> impl Iterator<Item = (f64, f64)> + 'a {
    a.iter().zip(b).map(|(x, y)| (*x, *y)).filter(|(x, y)| x.is_finite() && y.is_finite())
}

/// Σ r0² − Σ r1² over the rows where both residuals are measured: how much residual an effect removed. A row the
/// recording did not measure (NaN) counts in neither, so one such row does not make the whole signal's gain NaN
/// (which no comparison prefers, leaving the choice to another signal whatever its gain).
fn gain_of(r0: &[f64], r1: &[f64]) -> f64 {
    measured_pairs(r0, r1).map(|(x, y)| x * x - y * y).sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_row_not_measured_does_not_hide_where_an_effect_shows() {
        let nan = f64::NAN;
        // ΔP hardly changes; the drive frequency's residual falls by 90 %, one of its rows not measured
        let before = vec![("dp", vec![1.0, -1.0, 1.0, -1.0]), ("f_drive", vec![2.0, nan, -2.0, 2.0])];
        let after = vec![("dp", vec![1.0, -1.0, 1.0, -0.999]), ("f_drive", vec![0.2, nan, -0.2, 0.2])];
        assert_eq!(most_improved(&before, &after, 0), Some(1));
        assert!((gain_of(&before[1].1, &after[1].1) - 3.0 * (4.0 - 0.04)).abs() < 1e-12);
        let change: Vec<f64> = before[1].1.iter().zip(&after[1].1).map(|(x, y)| x - y).collect();
        assert!((correlation(&before[1].1, &change) - 1.0).abs() < 1e-12, "the removed part is the residual");
        // nothing measured: no signal to name
        assert_eq!(most_improved(&[("dp", vec![nan, nan])], &[("dp", vec![nan, nan])], 0), None);
    }
}

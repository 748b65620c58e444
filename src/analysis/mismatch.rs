//! Locating where the free-run residual is large, and the operating conditions those windows share.

use serde::Serialize;

use super::series::{Series, percentile};

/// A stretch of the recording where the model misses, and what was going on there.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Mismatch {
    pub t_start_s: f64,
    pub t_end_s: f64,
    /// `omega`, `dp` or `torque`.
    pub signal: String,
    /// The operating conditions the window shares, e.g. "low speed, after setpoint steps".
    pub condition: String,
    /// RMS of the residual in the window, in the signal's unit (rad/s, bar, N·m).
    pub rms: f64,
}

/// Length of the windows the residual is cut into (s).
pub const WINDOW_S: f64 = 0.5;
/// A window is a mismatch when its residual RMS exceeds this multiple of the median window's.
pub const THRESHOLD_X_MEDIAN: f64 = 2.0;
/// At most this many mismatches are listed (the largest).
pub const MAX_MISMATCHES: usize = 40;

/// Per-row operating conditions, computed once.
pub struct Conditions {
    low_speed: Vec<bool>,
    reversal: Vec<bool>,
    high_dp: Vec<bool>,
    after_step: Vec<bool>,
    accelerating: Vec<bool>,
}

impl Conditions {
    pub fn new(s: &Series) -> Conditions {
        let n = s.len();
        let scale = s.speed_scale();
        let low_speed = s.omega_f.iter().map(|w| w.abs() < 0.1 * scale).collect();
        // rows within 0.2 s of a sign change of the speed (beyond the smooth-sign band)
        let mut reversal = vec![false; n];
        let reach = (0.2 * s.sample_hz) as usize;
        let mut last_sign = 0.0;
        for k in 0..n {
            let w = s.omega_f[k];
            if w.abs() > 0.02 * scale {
                let sign = w.signum();
                if last_sign != 0.0 && sign != last_sign {
                    for r in reversal.iter_mut().take((k + reach).min(n)).skip(k.saturating_sub(reach)) {
                        *r = true;
                    }
                }
                last_sign = sign;
            }
        }
        let load: Vec<f64> = match &s.dp_bar {
            Some(dp) => dp.clone(),
            None => s.drive_torque_f.iter().map(|t| t.abs()).collect(),
        };
        let hi = percentile(&load, 0.8);
        let high_dp = load.iter().map(|v| *v > hi).collect();
        let mut after_step = vec![false; n];
        let driver: Vec<f64> = match &s.setpoint_hz {
            Some(u) => u.clone(),
            None => s.drive_torque_f.clone(),
        };
        let jump = match &s.setpoint_hz {
            Some(_) => 0.5,
            None => 0.2 * (percentile(&driver, 0.95) - percentile(&driver, 0.05)).abs(),
        };
        let hold = s.sample_hz as usize;
        let mut k = 1;
        while k < n {
            let look = (k + (0.02 * s.sample_hz) as usize).min(n - 1);
            if (driver[look] - driver[k - 1]).abs() > jump && jump > 0.0 {
                for r in after_step.iter_mut().take((k + hold).min(n)).skip(k) {
                    *r = true;
                }
                k += hold;
            } else {
                k += 1;
            }
        }
        let acc_hi = percentile(&s.alpha_f.iter().map(|a| a.abs()).collect::<Vec<_>>(), 0.9);
        let accelerating = s.alpha_f.iter().map(|a| a.abs() > acc_hi).collect();
        Conditions { low_speed, reversal, high_dp, after_step, accelerating }
    }

    /// The names of the conditions true for at least 30 % of rows `a..b`.
    pub fn describe(&self, s: &Series, a: usize, b: usize) -> String {
        let frac = |v: &[bool]| v[a..b].iter().filter(|x| **x).count() as f64 / (b - a).max(1) as f64;
        let high_name = if s.dp_bar.is_some() { "high ΔP" } else { "high torque" };
        let step_name = if s.setpoint_hz.is_some() { "after setpoint steps" } else { "after torque steps" };
        let named = [
            (frac(&self.reversal), "speed reversals"),
            (frac(&self.low_speed), "low speed"),
            (frac(&self.after_step), step_name),
            (frac(&self.accelerating), "fast acceleration"),
            (frac(&self.high_dp), high_name),
        ];
        let hits: Vec<&str> = named.iter().filter(|(f, _)| *f >= 0.3).map(|(_, n)| *n).collect();
        if hits.is_empty() { "steady running".to_string() } else { hits.join(", ") }
    }
}

/// The windows where `residual` (measured − model) is unusually large.
pub fn locate(s: &Series, cond: &Conditions, signal: &str, residual: &[f64]) -> Vec<Mismatch> {
    let w = ((WINDOW_S * s.sample_hz) as usize).max(10);
    let n = residual.len();
    let rms: Vec<(usize, usize, f64)> = (0..n / w)
        .map(|i| {
            let (a, b) = (i * w, ((i + 1) * w).min(n));
            let ms = residual[a..b].iter().map(|r| r * r).sum::<f64>() / (b - a) as f64;
            (a, b, ms.sqrt())
        })
        .collect();
    let median = percentile(&rms.iter().map(|r| r.2).collect::<Vec<_>>(), 0.5);
    let mut out = Vec::new();
    let mut i = 0;
    while i < rms.len() {
        if rms[i].2 > THRESHOLD_X_MEDIAN * median {
            let a = rms[i].0;
            let mut j = i;
            while j + 1 < rms.len() && rms[j + 1].2 > THRESHOLD_X_MEDIAN * median {
                j += 1;
            }
            let b = rms[j].1;
            let ms = residual[a..b].iter().map(|r| r * r).sum::<f64>() / (b - a) as f64;
            out.push(Mismatch {
                t_start_s: s.t_s[a],
                t_end_s: s.t_s[b - 1],
                signal: signal.to_string(),
                condition: cond.describe(s, a, b),
                rms: ms.sqrt(),
            });
            i = j + 1;
        } else {
            i += 1;
        }
    }
    out
}

/// Where the improved model still misses: windows of one signal under one operating condition whose residual RMS
/// exceeds [`UNEXPLAINED_X_FLOOR`] × the sensor-noise floor.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Unexplained {
    /// `omega`, `dp`, `torque` or `f_drive`.
    pub signal: String,
    /// The operating conditions the windows share, e.g. "low speed".
    pub condition: String,
    /// The windows, `[t_start_s, t_end_s]`, in time order (the longest [`MAX_UNEXPLAINED_WINDOWS`]).
    pub windows: Vec<[f64; 2]>,
    /// RMS of the residual over those windows, and the noise floor, in the signal's unit.
    pub rms: f64,
    pub noise_floor: f64,
    /// Fraction of the recording's rows in those windows.
    pub share: f64,
}

/// A window is unexplained when its residual RMS exceeds this multiple of the noise floor. White noise alone gives
/// a window RMS within a few % of the floor (0.5 s holds hundreds of samples); 2× means a model error of at least
/// √3 ≈ 1.7× the noise.
pub const UNEXPLAINED_X_FLOOR: f64 = 2.0;
/// An entry (one signal, one condition) is listed when its windows add up to at least this long (s), or when its
/// RMS reaches [`UNEXPLAINED_ALONE_X_FLOOR`]: a lone half-second at 2–4× the floor is what the clean reference plant
/// gives where the model changes regime (the shaft stopping against the anti-cavitation limit: 1.3–1.5 bar against a
/// 0.44 bar floor, test `analysis::clean_runs_name_nothing`), not a pattern of missing physics.
pub const MIN_UNEXPLAINED_S: f64 = 1.0;
/// See [`MIN_UNEXPLAINED_S`].
pub const UNEXPLAINED_ALONE_X_FLOOR: f64 = 5.0;
/// At most this many windows are listed per entry.
pub const MAX_UNEXPLAINED_WINDOWS: usize = 20;

/// Windows of `residual` (measured − improved model) above the floor, merged and grouped by condition. `timing`,
/// when given, is a per-row variance added to the floor's square: what the uncertainty of the rows' time stamps
/// alone makes of the signal (see `noise_floors`).
pub fn unexplained(
    s: &Series,
    cond: &Conditions,
    signal: &str,
    residual: &[f64],
    floor: f64,
    timing: Option<&[f64]>,
) -> Vec<Unexplained> {
    if !(floor > 0.0 && floor.is_finite()) {
        return Vec::new();
    }
    let floor_at = |a: usize, b: usize| -> f64 {
        let extra = timing.map_or(0.0, |v| {
            let w = &v[a.min(v.len())..b.min(v.len())];
            w.iter().filter(|x| x.is_finite()).sum::<f64>() / w.len().max(1) as f64
        });
        (floor * floor + extra).sqrt()
    };
    let w = ((WINDOW_S * s.sample_hz) as usize).max(10);
    let n = residual.len();
    let rms = |a: usize, b: usize| -> (f64, usize) {
        let v: Vec<f64> = residual[a..b].iter().copied().filter(|x| x.is_finite()).collect();
        ((v.iter().map(|x| x * x).sum::<f64>() / v.len().max(1) as f64).sqrt(), v.len())
    };
    // each window above the floor with its own condition; the first window (the free run settling from its
    // measured initial state) is not judged. Adjacent windows of one condition merge into a run.
    let above: Vec<Option<String>> = (0..n / w)
        .map(|i| {
            let (a, b) = (i * w, (i + 1) * w);
            (i > 0 && rms(a, b).0 > UNEXPLAINED_X_FLOOR * floor_at(a, b)).then(|| cond.describe(s, a, b))
        })
        .collect();
    let mut groups: Vec<(String, Vec<(usize, usize)>)> = Vec::new();
    let mut i = 0;
    while i < above.len() {
        let Some(c) = above[i].clone() else {
            i += 1;
            continue;
        };
        let mut j = i;
        while j + 1 < above.len() && above[j + 1].as_deref() == Some(c.as_str()) {
            j += 1;
        }
        let (a, b) = (i * w, (j + 1) * w);
        match groups.iter_mut().find(|g| g.0 == c) {
            Some(g) => g.1.push((a, b)),
            None => groups.push((c, vec![(a, b)])),
        }
        i = j + 1;
    }
    groups
        .into_iter()
        .map(|(condition, runs)| {
            let (mut ss, mut fs, mut count) = (0.0, 0.0, 0usize);
            for &(a, b) in &runs {
                let (r, m) = rms(a, b);
                ss += r * r * m as f64;
                fs += floor_at(a, b).powi(2) * m as f64;
                count += m;
            }
            let mut longest = runs.clone();
            longest.sort_by_key(|y| std::cmp::Reverse(y.1 - y.0));
            longest.truncate(MAX_UNEXPLAINED_WINDOWS);
            longest.sort_by_key(|x| x.0);
            Unexplained {
                signal: signal.to_string(),
                condition,
                windows: longest.iter().map(|&(a, b)| [s.t_s[a], s.t_s[b - 1]]).collect(),
                rms: (ss / count.max(1) as f64).sqrt(),
                noise_floor: (fs / count.max(1) as f64).sqrt(),
                share: runs.iter().map(|(a, b)| b - a).sum::<usize>() as f64 / n.max(1) as f64,
            }
        })
        .filter(|u| {
            let seconds = u.share * n as f64 / s.sample_hz;
            seconds >= MIN_UNEXPLAINED_S - 1e-9 || u.rms >= UNEXPLAINED_ALONE_X_FLOOR * u.noise_floor
        })
        .collect()
}

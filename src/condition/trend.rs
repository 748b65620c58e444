//! Where a tracked effect is heading: a robust line through one parameter's condition history, its uncertainty,
//! and when the line reaches the parameter's limit, with an interval (PURE).
//!
//! Each check's value is the mean over its window, so it stands at the window's centre (`time − window_s/2`). The
//! line is Theil–Sen's: the median of the slopes between every two checks, through the median of the values less
//! that slope (a check that misses an effect, or one fit gone astray, moves it little). Its uncertainty has two
//! parts:
//!
//! - **the scatter** of the checks about the line: the residual variance (n − 2 degrees of freedom), inflated by
//!   the windows' overlap (`window_s / spacing` when checks come more often than their windows are long:
//!   overlapping windows share data and their errors are not independent), and by π/3 (Theil–Sen's efficiency
//!   against least squares on normal errors is 3/π, Sen 1968). It shrinks as checks accrue;
//! - **each check's own error** (the analysis's 95 % interval of the parameter, `sd_level`: the median of the
//!   checks' own standard errors): an error shared by neighbouring checks, such as a bias of the fit, does not
//!   average away over checks, so it is added to the line's level whole, never divided by n. Without it the
//!   interval shrinks toward zero near the crossing while the fit's bias stays, and stops holding the truth.
//!
//! With q the two-sided 95 % Student quantile on n − 2 degrees of freedom:
//!
//! - **rising** when the slope toward the limit is above q standard errors: the crossing is where the line meets
//!   the limit, and its interval the times at which the line's 95 % band (both parts) holds the limit (Fieller's,
//!   with the checks' own error added; the late end open when the band never leaves it);
//! - **not rising** otherwise (flat, falling, or too uncertain to say);
//! - **past limit** when the line is already past it at the last check;
//! - **too few checks** below [`MIN_CHECKS`].
//!
//! A parameter alarmed below its limit (the bulk modulus) is turned over (−value, −limit) so that "rising" always
//! means "heading for the limit".

use serde::Serialize;

/// Fewer checks than this give no trend.
pub const MIN_CHECKS: usize = 4;

/// The state of a trend.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum TrendState {
    Rising,
    NotRising,
    PastLimit,
    TooFewChecks,
}

/// One value of the history: where it stands in time (s, any origin), its value, and its own standard error where
/// the analysis gave one (from its 95 % interval).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Point {
    pub t_s: f64,
    pub value: f64,
    pub sd: Option<f64>,
}

/// The trend of one parameter toward its limit.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Trend {
    pub state: TrendState,
    /// Values the line was fitted on.
    pub checks: usize,
    /// The line at the last check (the parameter's units).
    pub value_now: Option<f64>,
    /// The line's slope (the parameter's units per day) and its standard error (overlap included).
    pub slope_per_day: Option<f64>,
    pub slope_sd_per_day: Option<f64>,
    /// The checks' own standard error (the median of theirs), added whole to the line's level; null when no check
    /// carried one.
    pub level_sd: Option<f64>,
    /// From the last check to the line's crossing (s); 0 when past; null when not rising.
    pub seconds_to_limit: Option<f64>,
    /// The 95 % interval of the crossing (s from the last check); the late end null when the data cannot bound it.
    pub seconds_to_limit_low: Option<f64>,
    pub seconds_to_limit_high: Option<f64>,
}

impl Trend {
    fn empty(state: TrendState, checks: usize) -> Trend {
        Trend {
            state,
            checks,
            value_now: None,
            slope_per_day: None,
            slope_sd_per_day: None,
            level_sd: None,
            seconds_to_limit: None,
            seconds_to_limit_low: None,
            seconds_to_limit_high: None,
        }
    }
}

/// Two-sided 95 % quantile of Student's t with `df` degrees of freedom.
pub fn t_quantile_975(df: usize) -> f64 {
    const T: [f64; 30] = [
        12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160, 2.145, 2.131,
        2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048, 2.045, 2.042,
    ];
    match df {
        0 => f64::INFINITY,
        1..=30 => T[df - 1],
        _ => 1.96 + 2.4 / df as f64,
    }
}

/// Theil–Sen's efficiency against least squares on normal errors (Sen 1968): its variance is π/3 times theirs.
const THEIL_SEN_EFFICIENCY: f64 = 3.0 / std::f64::consts::PI;

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 { v[n / 2] } else { 0.5 * (v[n / 2 - 1] + v[n / 2]) }
}

/// Theil–Sen's line through `p` (t, y): (slope, the line's value at `t_mean`).
fn theil_sen(p: &[(f64, f64)], t_mean: f64) -> (f64, f64) {
    let mut slopes = Vec::with_capacity(p.len() * (p.len() - 1) / 2);
    for (i, a) in p.iter().enumerate() {
        for b in &p[i + 1..] {
            if b.0 > a.0 {
                slopes.push((b.1 - a.1) / (b.0 - a.0));
            }
        }
    }
    let b = median(&mut slopes);
    let mut levels: Vec<f64> = p.iter().map(|x| x.1 - b * (x.0 - t_mean)).collect();
    (b, median(&mut levels))
}

/// The trend of `points` (any order; non-finite ones left out) toward `limit`, `below` when the parameter alarms
/// below it; `window_s` is the span each value was taken over (for the overlap), `now_s` the last check's time.
pub fn trend(points: &[Point], limit: f64, below: bool, window_s: f64, now_s: f64) -> Trend {
    let s = if below { -1.0 } else { 1.0 };
    let mut p: Vec<(f64, f64)> =
        points.iter().filter(|p| p.t_s.is_finite() && p.value.is_finite()).map(|p| (p.t_s, s * p.value)).collect();
    p.sort_by(|a, b| a.0.total_cmp(&b.0));
    let n = p.len();
    if n < MIN_CHECKS {
        return Trend::empty(TrendState::TooFewChecks, n);
    }
    let nf = n as f64;
    let t_mean = p.iter().map(|x| x.0).sum::<f64>() / nf;
    let sxx: f64 = p.iter().map(|x| (x.0 - t_mean).powi(2)).sum();
    if sxx <= 0.0 {
        return Trend::empty(TrendState::TooFewChecks, n);
    }
    let (b, level) = theil_sen(&p, t_mean);
    let rss: f64 = p.iter().map(|x| (x.1 - level - b * (x.0 - t_mean)).powi(2)).sum();
    let spacing = (p[n - 1].0 - p[0].0) / (nf - 1.0);
    let overlap = if spacing > 0.0 { (window_s / spacing).max(1.0) } else { 1.0 };
    let var = rss / (nf - 2.0) * overlap / THEIL_SEN_EFFICIENCY;
    let mut own: Vec<f64> = points.iter().filter_map(|p| p.sd).filter(|sd| sd.is_finite() && *sd >= 0.0).collect();
    let level_sd = (!own.is_empty()).then(|| median(&mut own));
    let sys = level_sd.unwrap_or(0.0).powi(2);
    let se_b = (var / sxx).sqrt();
    let q = t_quantile_975(n - 2);
    let u_now = now_s - t_mean;
    let line_now = level + b * u_now;
    let target = s * limit;
    let mut out = Trend {
        value_now: Some(s * line_now),
        slope_per_day: Some(s * b * 86_400.0),
        slope_sd_per_day: Some(se_b * 86_400.0),
        level_sd,
        ..Trend::empty(TrendState::NotRising, n)
    };
    if line_now >= target {
        out.state = TrendState::PastLimit;
        out.seconds_to_limit = Some(0.0);
        return out;
    }
    if b - q * se_b <= 0.0 {
        return out;
    }
    out.state = TrendState::Rising;
    out.seconds_to_limit = Some((target - line_now) / b);
    // the band holds the limit where (c − b u)² ≤ q² (var (1/n + u²/Sxx) + sd_level²), c = target − level,
    // u = t − t̄: a quadratic in u
    let c = target - level;
    let qq = q * q * var;
    let a2 = b * b - qq / sxx;
    let a1 = -2.0 * b * c;
    let a0 = c * c - qq / nf - q * q * sys;
    let disc = a1 * a1 - 4.0 * a2 * a0;
    if a2 > 0.0 && disc >= 0.0 {
        let r = disc.sqrt();
        let (lo, hi) = ((-a1 - r) / (2.0 * a2), (-a1 + r) / (2.0 * a2));
        out.seconds_to_limit_low = Some((lo - u_now).max(0.0));
        out.seconds_to_limit_high = Some((hi - u_now).max(0.0));
    } else {
        out.seconds_to_limit_low = Some(0.0);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[track_caller]
    fn assert_close(a: f64, b: f64, rel: f64) {
        assert!((a - b).abs() <= rel * a.abs().max(b.abs()), "{a} against {b} (relative {rel})");
    }

    fn line(n: usize, a: f64, b: f64, noise: &[f64]) -> Vec<Point> {
        (0..n)
            .map(|k| Point { t_s: 60.0 * k as f64, value: a + b * 60.0 * k as f64 + noise[k % noise.len()], sd: None })
            .collect()
    }

    const NOISE: [f64; 5] = [0.001, -0.0015, 0.0005, 0.0012, -0.0008];

    #[test]
    fn a_rising_line_crosses_where_it_should_and_its_interval_holds_it() {
        // 0.01 + 1e-5/s: reaches 0.05 at 4000 s; 10 checks to 540 s
        let pts = line(10, 0.01, 1e-5, &NOISE);
        let tr = trend(&pts, 0.05, false, 60.0, 540.0);
        assert_eq!(tr.state, TrendState::Rising);
        let s = tr.seconds_to_limit.expect("crossing");
        assert!((s + 540.0 - 4000.0).abs() < 0.1 * 4000.0, "{s}");
        let (lo, hi) = (tr.seconds_to_limit_low.expect("low"), tr.seconds_to_limit_high.expect("high"));
        assert!(lo < 4000.0 - 540.0 && 4000.0 - 540.0 < hi, "{lo} … {hi}");
        assert!(lo <= s && s <= hi);
        assert_close(tr.slope_per_day.expect("slope"), 0.864, 0.1);
    }

    #[test]
    fn a_flat_or_falling_line_is_not_rising_and_a_bulk_modulus_falls_toward_its_limit() {
        let flat = line(10, 0.01, 0.0, &NOISE);
        assert_eq!(trend(&flat, 0.05, false, 60.0, 540.0).state, TrendState::NotRising);
        let falling = line(10, 0.03, -1e-5, &NOISE);
        assert_eq!(trend(&falling, 0.05, false, 60.0, 540.0).state, TrendState::NotRising);
        // a bulk modulus falling 1 bar/s from 15 000 toward 8 000: rising toward its limit, 7000 s from t = 0
        let air: Vec<Point> = line(10, 15_000.0, -1.0, &[10.0, -20.0, 5.0]);
        let tr = trend(&air, 8000.0, true, 60.0, 540.0);
        assert_eq!(tr.state, TrendState::Rising);
        let s = tr.seconds_to_limit.expect("crossing");
        assert!((s + 540.0 - 7000.0).abs() < 100.0, "{s}");
        assert!(tr.slope_per_day.expect("slope") < 0.0, "the slope in the parameter's own sense");
        assert!(tr.value_now.expect("value") < 15_000.0);
    }

    #[test]
    fn past_the_limit_too_few_checks_and_overlap() {
        let pts = line(10, 0.06, 1e-5, &NOISE);
        let tr = trend(&pts, 0.05, false, 60.0, 540.0);
        assert_eq!((tr.state, tr.seconds_to_limit), (TrendState::PastLimit, Some(0.0)));
        assert_eq!(trend(&pts[..3], 0.05, false, 60.0, 120.0).state, TrendState::TooFewChecks);
        // overlapping windows widen the slope's error by √(window/spacing)
        let pts = line(10, 0.01, 1e-5, &NOISE);
        let one = trend(&pts, 0.05, false, 60.0, 540.0).slope_sd_per_day.expect("sd");
        let four = trend(&pts, 0.05, false, 240.0, 540.0).slope_sd_per_day.expect("sd");
        assert_close(four / one, 2.0, 1e-9);
    }

    #[test]
    fn one_check_gone_astray_moves_the_line_little_and_widens_its_uncertainty() {
        // 0.01 + 1e-5/s (0.864 a day), one check reading 0 (a check that missed the effect)
        let clean = line(12, 0.01, 1e-5, &NOISE);
        let mut pts = clean.clone();
        pts[8].value = 0.0;
        let tr = trend(&pts, 0.05, false, 60.0, 660.0);
        let ts_err = (tr.slope_per_day.expect("slope") - 0.864).abs() / 0.864;
        // least squares through the same points
        let n = pts.len() as f64;
        let (tm, ym) = (pts.iter().map(|p| p.t_s).sum::<f64>() / n, pts.iter().map(|p| p.value).sum::<f64>() / n);
        let sxy: f64 = pts.iter().map(|p| (p.t_s - tm) * (p.value - ym)).sum();
        let sxx: f64 = pts.iter().map(|p| (p.t_s - tm).powi(2)).sum();
        let ls_err = (sxy / sxx * 86_400.0 - 0.864).abs() / 0.864;
        assert!(ts_err < 0.2 && ts_err < 0.5 * ls_err, "Theil–Sen {ts_err:.3} off, least squares {ls_err:.3}");
        // its scatter is not hidden: the slope is less sure than without it
        let sd = |t: &Trend| t.slope_sd_per_day.expect("sd");
        assert!(sd(&tr) > 2.0 * sd(&trend(&clean, 0.05, false, 60.0, 660.0)), "{tr:?}");
    }

    #[test]
    fn each_checks_own_error_widens_the_interval_and_does_not_average_away() {
        // 0.01 + 3e-5/s crosses 0.05 at 1333 s; every check 0.002 low (a bias of the fit, shared by all), each with
        // its own 95 % interval ±0.003. Near the crossing the scatter alone gives an interval that misses the truth;
        // with the checks' own error it holds it
        let biased: Vec<Point> = line(20, 0.008, 3e-5, &NOISE);
        let plain = trend(&biased, 0.05, false, 60.0, 1140.0);
        let with_own: Vec<Point> = biased.iter().map(|p| Point { sd: Some(0.003 / 1.96), ..*p }).collect();
        let own = trend(&with_own, 0.05, false, 60.0, 1140.0);
        let holds = |tr: &Trend| {
            let (lo, hi) = (tr.seconds_to_limit_low.expect("low"), tr.seconds_to_limit_high.expect("high"));
            lo + 1140.0 <= 1333.3 && 1333.3 <= hi + 1140.0
        };
        assert!(!holds(&plain), "the scatter alone claims too much: {plain:?}");
        assert!(holds(&own), "{own:?}");
        assert_eq!(own.seconds_to_limit, plain.seconds_to_limit, "the same line");
        assert_close(own.level_sd.expect("own"), 0.003 / 1.96, 1e-12);
        assert_eq!(plain.level_sd, None);
    }

    #[test]
    fn a_noisy_rise_too_weak_to_tell_is_not_rising() {
        let noise = [0.02, -0.03, 0.025, -0.01, 0.03, -0.02];
        let pts = line(6, 0.01, 1e-6, &noise);
        assert_eq!(trend(&pts, 0.05, false, 60.0, 300.0).state, TrendState::NotRising);
    }
}

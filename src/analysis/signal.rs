//! Signal helpers for the analysis: zero-phase Butterworth filtering, differentiation, least squares, 1-D search.

use nalgebra::{DMatrix, DVector};

/// One second-order section in transposed direct form II.
#[derive(Debug, Clone, Copy)]
struct Biquad {
    b: [f64; 3],
    a: [f64; 2],
}

impl Biquad {
    /// A low-pass section of quality `q` at `cutoff_hz` (bilinear transform with pre-warping).
    fn lowpass(cutoff_hz: f64, sample_hz: f64, q: f64) -> Biquad {
        let w0 = 2.0 * std::f64::consts::PI * cutoff_hz / sample_hz;
        let (sin, cos) = w0.sin_cos();
        let alpha = sin / (2.0 * q);
        let a0 = 1.0 + alpha;
        let b0 = (1.0 - cos) / 2.0 / a0;
        Biquad { b: [b0, 2.0 * b0, b0], a: [-2.0 * cos / a0, (1.0 - alpha) / a0] }
    }

    /// Filters in place, starting from the steady state of the first value.
    fn run(&self, x: &mut [f64]) {
        let Some(&x0) = x.first() else { return };
        let [b0, b1, b2] = self.b;
        let [a1, a2] = self.a;
        let mut z2 = (b2 - a2) * x0;
        let mut z1 = (b1 - a1) * x0 + z2;
        for v in x.iter_mut() {
            let xin = *v;
            let y = b0 * xin + z1;
            z1 = b1 * xin - a1 * y + z2;
            z2 = b2 * xin - a2 * y;
            *v = y;
        }
    }
}

/// 4th-order Butterworth low-pass applied forward and backward (zero phase, as MATLAB's `filtfilt`), with odd
/// reflection at both ends to tame edge transients. A cutoff at or above Nyquist returns the input.
pub fn filtfilt_butter4(x: &[f64], cutoff_hz: f64, sample_hz: f64) -> Vec<f64> {
    if x.len() < 4 || cutoff_hz.is_nan() || cutoff_hz <= 0.0 || cutoff_hz >= 0.49 * sample_hz {
        return x.to_vec();
    }
    let sections = [
        Biquad::lowpass(cutoff_hz, sample_hz, 1.0 / (2.0 * (std::f64::consts::PI / 8.0).cos())),
        Biquad::lowpass(cutoff_hz, sample_hz, 1.0 / (2.0 * (3.0 * std::f64::consts::PI / 8.0).cos())),
    ];
    let n = x.len();
    let pad = ((3.0 * sample_hz / cutoff_hz) as usize).clamp(12, n - 1);
    let mut y = Vec::with_capacity(n + 2 * pad);
    let (first, last) = (x[0], x[n - 1]);
    y.extend((1..=pad).rev().map(|i| 2.0 * first - x[i]));
    y.extend_from_slice(x);
    y.extend((1..=pad).map(|i| 2.0 * last - x[n - 1 - i]));
    for s in &sections {
        s.run(&mut y);
    }
    y.reverse();
    for s in &sections {
        s.run(&mut y);
    }
    y.reverse();
    y[pad..pad + n].to_vec()
}

/// Central differences dx/dt on the time stamps (one-sided at the ends).
pub fn derivative(x: &[f64], t: &[f64]) -> Vec<f64> {
    let n = x.len();
    if n < 2 {
        return vec![0.0; n];
    }
    (0..n)
        .map(|k| {
            let (i, j) = (k.saturating_sub(1), (k + 1).min(n - 1));
            (x[j] - x[i]) / (t[j] - t[i])
        })
        .collect()
}

/// A lone value this many robust σ away from the median of its neighbourhood is a spike, not a measurement.
pub const SPIKE_X_SIGMA: f64 = 30.0;

/// Takes out spikes: values that stand [`SPIKE_X_SIGMA`] robust standard deviations off the median of the five
/// finite values around them (a row or two corrupted). Where a signal is monotone the median is the value itself,
/// so steps and ramps are never touched; σ is 1.4826 × the median of the non-zero deviations (the noise where the
/// signal turns; where fewer than 1 % of the rows turn, as a position does, of its steps between rows). A spike also
/// shifts its neighbours' medians, so each pass takes only the values that stand out most within their five, and the
/// next pass looks again without them (two spikes side by side: two passes).
/// Returns the signal with spikes as NaN (missing) and the rows taken out, in order.
pub fn without_spikes(x: &[f64]) -> (Vec<f64>, Vec<usize>) {
    let mut out = x.to_vec();
    let mut taken = Vec::new();
    let mut first_sigma = None;
    for _ in 0..4 {
        let finite: Vec<usize> = (0..out.len()).filter(|&k| out[k].is_finite()).collect();
        let deviation: Vec<f64> = (0..finite.len())
            .map(|i| {
                let (a, b) = (i.saturating_sub(2), (i + 3).min(finite.len()));
                let mut w: Vec<f64> = finite[a..b].iter().map(|&k| out[k]).collect();
                w.sort_by(f64::total_cmp);
                (out[finite[i]] - w[w.len() / 2]).abs()
            })
            .collect();
        let sigma = *first_sigma.get_or_insert_with(|| {
            // at least 20, and 1 % of the rows: a spike's neighbours alone must not make the set
            let robust = |mut nonzero: Vec<f64>| {
                let mid = nonzero.len() / 2;
                (nonzero.len() >= 20.max(x.len() / 100))
                    .then(|| 1.4826 * *nonzero.select_nth_unstable_by(mid, f64::total_cmp).1)
            };
            // a smooth signal that seldom turns (a position) has too few: the scale of its steps stands in
            let steps = || finite.windows(2).map(|w| (out[w[1]] - out[w[0]]).abs()).filter(|d| *d > 0.0).collect();
            robust(deviation.iter().copied().filter(|d| *d > 0.0).collect()).or_else(|| robust(steps()))
        });
        let Some(sigma) = sigma else { break };
        let before = taken.len();
        for (i, &d) in deviation.iter().enumerate() {
            let (a, b) = (i.saturating_sub(2), (i + 3).min(finite.len()));
            if d > SPIKE_X_SIGMA * sigma && deviation[a..b].iter().all(|&e| e <= d) {
                taken.push(finite[i]);
            }
        }
        if taken.len() == before {
            break;
        }
        for &k in &taken[before..] {
            out[k] = f64::NAN;
        }
    }
    taken.sort_unstable();
    (out, taken)
}

/// Replaces missing (non-finite) values by the last value seen (the first value seen before it).
pub fn fill_gaps(x: &[f64]) -> Vec<f64> {
    let first = x.iter().copied().find(|v| v.is_finite()).unwrap_or(0.0);
    let mut last = first;
    x.iter()
        .map(|&v| {
            if v.is_finite() {
                last = v;
            }
            last
        })
        .collect()
}

/// Least squares `A θ ≈ y` for regressor columns; `None` when the columns do not determine θ.
pub fn least_squares(columns: &[Vec<f64>], y: &[f64]) -> Option<Vec<f64>> {
    let p = columns.len();
    let n = y.len();
    if p == 0 || n < p || columns.iter().any(|c| c.len() != n) {
        return None;
    }
    let norms = unit_norms(columns)?;
    let a = DMatrix::from_fn(n, p, |i, j| columns[j][i] / norms[j]);
    solve_and_unscale(a, DVector::from_column_slice(y), &norms)
}

/// The least-squares fit of [`least_squares`] with each coefficient's standard deviation, the residual's variance
/// (over n − p) taken as white: `None` where [`least_squares`] gives none.
pub fn least_squares_with_sd(columns: &[Vec<f64>], y: &[f64]) -> Option<(Vec<f64>, Vec<f64>)> {
    let theta = least_squares(columns, y)?;
    let (n, p) = (y.len(), columns.len());
    if n <= p {
        return None;
    }
    let rss: f64 =
        (0..n).map(|i| (y[i] - columns.iter().zip(&theta).map(|(c, t)| c[i] * t).sum::<f64>()).powi(2)).sum();
    let norms = unit_norms(columns)?;
    let a = DMatrix::from_fn(n, p, |i, j| columns[j][i] / norms[j]);
    let inverse = (a.transpose() * a).try_inverse()?;
    let var = rss / (n - p) as f64;
    let sd: Vec<f64> = (0..p).map(|j| (var * inverse[(j, j)]).max(0.0).sqrt() / norms[j]).collect();
    sd.iter().all(|v| v.is_finite()).then_some((theta, sd))
}

/// The Euclidean norm of each column, so that a fit can scale its columns to unit norm and its rank test means
/// the same whatever the units; `None` when a column is zero or not finite.
fn unit_norms(columns: &[Vec<f64>]) -> Option<Vec<f64>> {
    let norms: Vec<f64> = columns.iter().map(|c| c.iter().map(|v| v * v).sum::<f64>().sqrt()).collect();
    norms.iter().all(|&s| s > 0.0 && s.is_finite()).then_some(norms)
}

/// Solves `a θ = b` by SVD for columns scaled by `norms`, and undoes the scaling; `None` when `a` is rank
/// deficient or θ not finite.
fn solve_and_unscale(a: DMatrix<f64>, b: DVector<f64>, norms: &[f64]) -> Option<Vec<f64>> {
    let svd = a.svd(true, true);
    let smax = svd.singular_values.max();
    let smin = svd.singular_values.min();
    if smin.is_nan() || smin <= 1e-9 * smax {
        return None;
    }
    let theta = svd.solve(&b, 1e-12).ok()?;
    let out: Vec<f64> = theta.iter().zip(norms).map(|(t, s)| t / s).collect();
    out.iter().all(|v| v.is_finite()).then_some(out)
}

/// Cosine of the angle between two regressors (uncentred): near ±1 means least squares cannot tell them apart.
pub fn cosine(a: &[f64], b: &[f64]) -> f64 {
    let ab: f64 = a.iter().zip(b).map(|(x, y)| x * y).sum();
    let aa: f64 = a.iter().map(|x| x * x).sum();
    let bb: f64 = b.iter().map(|x| x * x).sum();
    if aa > 0.0 && bb > 0.0 { ab / (aa * bb).sqrt() } else { 0.0 }
}

/// ‖sim − meas‖ / ‖meas − mean(meas)‖ over the pairs where both are finite.
pub fn nrmse(sim: &[f64], meas: &[f64]) -> f64 {
    let (mut n, mut sum) = (0usize, 0.0);
    for (&s, &m) in sim.iter().zip(meas) {
        if s.is_finite() && m.is_finite() {
            n += 1;
            sum += m;
        }
    }
    if n == 0 {
        return f64::NAN;
    }
    let mean = sum / n as f64;
    let (mut num, mut den) = (0.0, 0.0);
    for (&s, &m) in sim.iter().zip(meas) {
        if s.is_finite() && m.is_finite() {
            num += (s - m).powi(2);
            den += (m - mean).powi(2);
        }
    }
    if den > 0.0 { (num / den).sqrt() } else { f64::NAN }
}

/// Minimises `f` over an increasing grid, then refines by golden section between the best point's neighbours.
/// Returns the argument and the value.
pub fn minimize_1d(f: &mut dyn FnMut(f64) -> f64, grid: &[f64], refine_iters: usize) -> (f64, f64) {
    let mut best = (f64::NAN, f64::INFINITY);
    let mut values = Vec::with_capacity(grid.len());
    for &x in grid {
        let v = f(x);
        values.push(v);
        if v < best.1 {
            best = (x, v);
        }
    }
    let Some(i) = grid.iter().position(|&x| x == best.0) else { return best };
    let (mut lo, mut hi) = (grid[i.saturating_sub(1)], grid[(i + 1).min(grid.len() - 1)]);
    let g = 0.5 * (5f64.sqrt() - 1.0);
    let mut x1 = hi - g * (hi - lo);
    let mut x2 = lo + g * (hi - lo);
    let (mut f1, mut f2) = (f(x1), f(x2));
    for _ in 0..refine_iters {
        if f1 < f2 {
            hi = x2;
            x2 = x1;
            f2 = f1;
            x1 = hi - g * (hi - lo);
            f1 = f(x1);
        } else {
            lo = x1;
            x1 = x2;
            f1 = f2;
            x2 = lo + g * (hi - lo);
            f2 = f(x2);
        }
    }
    for (x, v) in [(x1, f1), (x2, f2)] {
        if v < best.1 {
            best = (x, v);
        }
    }
    best
}

/// Instrumental-variable least squares: θ from `Zᵀ A θ = Zᵀ y`, with instruments `z` (one column per regressor
/// column of `a`) that move with the regressors but not with their noise. `None` when `Zᵀ A` does not determine θ.
pub fn instrumental_least_squares(a: &[Vec<f64>], z: &[Vec<f64>], y: &[f64]) -> Option<Vec<f64>> {
    let p = a.len();
    let n = y.len();
    if p == 0 || z.len() != p || n < p || a.iter().chain(z).any(|c| c.len() != n) {
        return None;
    }
    let (na, nz) = (unit_norms(a)?, unit_norms(z)?);
    let dot = |u: &[f64], v: &[f64]| u.iter().zip(v).map(|(x, y)| x * y).sum::<f64>();
    let zta = DMatrix::from_fn(p, p, |i, j| dot(&z[i], &a[j]) / (nz[i] * na[j]));
    let zty = DVector::from_fn(p, |i, _| dot(&z[i], y) / nz[i]);
    solve_and_unscale(zta, zty, &na)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn instruments_undo_the_attenuation_that_noise_in_a_regressor_gives_least_squares() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(33);
        let noise = Normal::new(0.0, 1.0).expect("σ > 0");
        // y = 2·x + 1, x seen with noise as large as its own spread; the instrument is x without the noise
        let x: Vec<f64> = (0..20_000).map(|k| (k as f64 * 0.01).sin()).collect();
        let y: Vec<f64> = x.iter().map(|v| 2.0 * v + 1.0 + 0.1 * noise.sample(&mut rng)).collect();
        let seen: Vec<f64> = x.iter().map(|v| v + 0.7 * noise.sample(&mut rng)).collect();
        let ones = vec![1.0; x.len()];
        let ls = least_squares(&[seen.clone(), ones.clone()], &y).expect("determined");
        let iv = instrumental_least_squares(&[seen, ones.clone()], &[x, ones], &y).expect("determined");
        // least squares: 2·var(x)/(var(x) + 0.49) = 2·0.5/0.99 ≈ 1.01; the instruments: 2
        assert!((ls[0] - 1.01).abs() < 0.05, "{ls:?}");
        assert!((iv[0] - 2.0).abs() < 0.05 && (iv[1] - 1.0).abs() < 0.02, "{iv:?}");
    }

    #[test]
    fn spikes_go_and_steps_stay() {
        // noise on a step and a ramp, with two lone spikes
        let mut x: Vec<f64> = (0..2000)
            .map(|k| if k < 1000 { 10.0 } else { 50.0 + 0.01 * k as f64 } + 0.3 * ((k * 7919 % 101) as f64 / 101.0 - 0.5))
            .collect();
        x[500] = 390.0;
        x[1500] = -1.0;
        let (y, taken) = without_spikes(&x);
        assert_eq!(taken, [500, 1500]);
        assert!(y[500].is_nan() && y[999] == x[999] && y[1000] == x[1000]);
        // two spikes side by side: both, in two passes
        x[700] = 300.0;
        x[701] = 280.0;
        assert_eq!(without_spikes(&x).1, [500, 700, 701, 1500]);
    }

    #[test]
    fn a_corrupt_cell_in_a_position_goes_alone() {
        // a position turning back and forth, with a little noise, one cell 1e300: its neighbours' medians shift
        // by a step, and were taken with it
        let noise = |k: usize| 2e-6 * ((k * 7919 % 101) as f64 / 101.0 - 0.5);
        let mut x: Vec<f64> = (0..3000).map(|k| 0.05 * (k as f64 * 0.004).sin() + noise(k)).collect();
        x[1000] = 1e300;
        let (y, taken) = without_spikes(&x);
        assert_eq!(taken, [1000]);
        assert!(y[999] == x[999] && y[1001] == x[1001]);
    }

    #[test]
    fn filter_keeps_slow_signals_and_removes_fast_ones_without_lag() {
        let fs = 1000.0;
        let t: Vec<f64> = (0..4000).map(|k| k as f64 / fs).collect();
        let slow: Vec<f64> = t.iter().map(|&t| (2.0 * std::f64::consts::PI * 1.0 * t).sin()).collect();
        let mixed: Vec<f64> =
            t.iter().zip(&slow).map(|(&t, s)| s + 0.5 * (2.0 * std::f64::consts::PI * 200.0 * t).sin()).collect();
        let y = filtfilt_butter4(&mixed, 20.0, fs);
        let err = y[200..3800].iter().zip(&slow[200..3800]).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
        assert!(err < 2e-3, "{err}");
    }

    #[test]
    fn least_squares_recovers_a_line_and_refuses_collinear_columns() {
        let x: Vec<f64> = (0..100).map(|k| k as f64).collect();
        let y: Vec<f64> = x.iter().map(|x| 2.0 * x + 3.0).collect();
        let ones = vec![1.0; 100];
        let th = least_squares(&[x.clone(), ones.clone()], &y).expect("solvable");
        assert!((th[0] - 2.0).abs() < 1e-9 && (th[1] - 3.0).abs() < 1e-9);
        assert!(least_squares(&[ones.clone(), ones], &y).is_none());
    }

    #[test]
    fn minimize_finds_a_parabola_minimum() {
        let (x, _) = minimize_1d(&mut |x| (x - 0.37).powi(2), &[0.0, 0.25, 0.5, 0.75, 1.0], 30);
        assert!((x - 0.37).abs() < 1e-5, "{x}");
    }
}

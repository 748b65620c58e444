//! Fitting: J, B and the friction/offset terms by least squares on the torque balance; the flow-side effects by
//! 1-D search on the free-run error (each effect's candidate in `candidates`); greedy forward selection judged on the
//! validation segment.

use crate::BadInput;
use crate::plant::PlantModel;
use crate::plant::dynamics::Mechanics;
use crate::plant::effects::{CoulombFriction, EFFECT_IDS, StribeckFriction, TorqueOffset};

use super::predict::{Errors, Prediction, errors, extra_torque_nm, predict, predict_rows};
use super::series::{Family, Series};
use super::signal::{instrumental_least_squares, least_squares, minimize_1d};

mod candidates;
pub use candidates::{candidate, coulomb_beside_stribeck, refit_low_speed};

/// Which torque-balance terms the least-squares fit includes besides J and B.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct MechTerms {
    pub coulomb: bool,
    pub offset: bool,
    pub stribeck: bool,
}

/// A model under consideration, with its predictions over the whole recording and their errors. The prediction is
/// shared (clones of the model in force cost nothing) and may be dropped ([`Scored::without_prediction`]): a
/// candidate needs only its errors, and a long recording's prediction is tens of MB.
#[derive(Debug, Clone)]
pub struct Scored {
    pub model: PlantModel,
    pub terms: MechTerms,
    pub prediction: std::sync::Arc<Prediction>,
    /// Errors on the fitting segment (for BIC) and the validation segment (for selection).
    pub fit: Errors,
    pub validation: Errors,
}

impl Scored {
    pub fn evaluate(model: PlantModel, terms: MechTerms, s: &Series) -> Result<Scored, BadInput> {
        let prediction = predict(&model, s, s.len())?;
        let fit = errors(&prediction, s, 0, s.split);
        let validation = errors(&prediction, s, s.split, s.len());
        Ok(Scored { model, terms, prediction: std::sync::Arc::new(prediction), fit, validation })
    }

    /// The same scores without the prediction (what a candidate keeps); [`Scored::evaluate`] gives it back.
    pub fn without_prediction(self) -> Scored {
        Scored { prediction: Default::default(), ..self }
    }
}

/// Which rows a fit may use: the least-squares rows, and the free-run search over rows `0..search_end` restarted
/// from the measured state at `restarts`, judged only on `search` (ranges). The documented fit uses the fitting
/// segment ([`Rows::standard`]); cross-validation fits each fold on the recording without one block ([`Rows::fold`]).
#[derive(Debug, Clone)]
pub struct Rows {
    pub ls: Vec<(usize, usize)>,
    pub search: Vec<(usize, usize)>,
    pub search_start: usize,
    pub search_end: usize,
    pub restarts: Vec<usize>,
    /// Cross-validation: the held-out block (rows), none for the standard fit.
    pub held_out: Option<(usize, usize)>,
}

impl Rows {
    /// The fitting segment `0..split`; the free-run search on its first `search_end` rows.
    pub fn standard(s: &Series, search_end: usize) -> Rows {
        Rows {
            ls: vec![(0, s.split)],
            search: vec![(0, search_end)],
            search_start: 0,
            search_end,
            restarts: Vec::new(),
            held_out: None,
        }
    }

    /// Fold `k` of `folds`: every row but block `k` (the recording cut into `folds` equal blocks). The free-run
    /// search uses about `search_len` rows of the training data from the start, restarting at the block's edges.
    pub fn fold(s: &Series, k: usize, folds: usize, search_len: usize) -> Rows {
        let n = s.len();
        let (a, b) = (k * n / folds, (k + 1) * n / folds);
        let ranges = |end: usize| -> Vec<(usize, usize)> {
            [(0, a.min(end)), (b.min(end), end)].into_iter().filter(|(p, q)| q > p).collect()
        };
        // the search window: the first `search_len` rows when the block lies beyond them, else as many rows from
        // the block's end; a short recording: its training rows around the block
        let (search_start, search_end) = if a >= search_len {
            (0, search_len)
        } else if b + search_len <= n {
            (b, b + search_len)
        } else {
            (0, (search_len + (b - a)).min(n))
        };
        let search =
            if search_start > 0 || search_end <= a { vec![(search_start, search_end)] } else { ranges(search_end) };
        Rows {
            ls: ranges(n),
            search,
            search_start,
            search_end,
            restarts: [a, b].into_iter().filter(|r| *r > 0 && *r < n).collect(),
            held_out: Some((a, b)),
        }
    }

    /// Sets the rows of `p` outside the search ranges to NaN, so that errors are computed on training rows only.
    fn mask(&self, p: &mut Prediction) {
        if self.search.len() == 1 && self.search[0] == (self.search_start, self.search_end) {
            return;
        }
        let keep = |k: usize| self.search.iter().any(|(a, b)| (*a..*b).contains(&k));
        let blank = |v: &mut Vec<f64>| {
            for (k, x) in v.iter_mut().enumerate() {
                if !keep(k) {
                    *x = f64::NAN;
                }
            }
        };
        blank(&mut p.omega_rad_s);
        if let Some(v) = p.dp_bar.as_mut() {
            blank(v);
        }
        if let Some(v) = p.torque_nm.as_mut() {
            blank(v);
        }
        if let Some(v) = p.f_drive_hz.as_mut() {
            blank(v);
        }
        if let Some(v) = p.f_drive_nominal_hz.as_mut() {
            blank(v);
        }
    }

    /// The free-run error of `m` on the search rows.
    pub fn search_cost(&self, m: &PlantModel, s: &Series) -> f64 {
        let restarts: Vec<usize> = self.restarts.iter().copied().filter(|r| *r > self.search_start).collect();
        match predict_rows(m, s, self.search_start, self.search_end, &restarts) {
            Ok(mut p) => {
                self.mask(&mut p);
                errors(&p, s, self.search_start, self.search_end).score(s.family)
            }
            Err(_) => f64::INFINITY,
        }
    }
}

/// With dry friction fitted, the hydraulic family's torque balance is read through a second low-pass at this
/// fraction of the speed's cutoff (2 Hz at 10 Hz). Every column, the torque and the regressors alike, goes through
/// the same linear filter, so the balance still holds term by term; what it removes is the acceleration's noise (the
/// tachogenerator's noise differentiated), which at the speed's cutoff is most of the balance's residual and carries
/// nothing about B or the dry levels, which show in the steady torque at each speed. On the slow programs of issue 33
/// (a viscous line and a constant told apart over a narrow spread of speeds) least squares at 10 Hz left B at +38 %
/// and +39 % on two runs, within its own noise; through 2 Hz, −3 % and +27 %. A fit without a dry term (the nominal
/// model's J and B) keeps the speed's cutoff: the friction it leaves out moves with every breakaway, and at 2 Hz the
/// acceleration is too small beside it (a tuned run of that sweep: J −38 %, nothing named).
const SLOW_BALANCE_FRACTION: f64 = 0.2;

/// The rows least squares reads the torque balance at, and how a column is read there: each range without its
/// filter edges, decimated; on the hydraulic family with dry friction fitted, through the second low-pass
/// ([`SLOW_BALANCE_FRACTION`]) and not within that filter's reach of a standstill (there dry friction holds whatever
/// torque is below the breakaway, and the tachogenerator's noise smears the sign: those rows carry no friction
/// law; kept, they read as a steep viscous term, B high and the dry level low). A speed from a position encoder
/// (the torque family, EMPS) keeps them, as IDIM-LS does, and is read as it is.
struct BalanceRows {
    rows: Vec<usize>,
    /// The second low-pass (Hz) and the span `lo..hi` it filters.
    smooth: Option<(f64, usize, usize)>,
    sample_hz: f64,
}

impl BalanceRows {
    fn new(s: &Series, ranges: &[(usize, usize)], dry: bool) -> BalanceRows {
        let slow = s.family == Family::Hydraulic && dry;
        let cutoff = if slow { SLOW_BALANCE_FRACTION * s.cutoff_hz } else { s.cutoff_hz };
        let step = ((s.sample_hz / (5.0 * cutoff)).round() as usize).max(1);
        let reach = (s.sample_hz / cutoff) as usize;
        let mut rows = Vec::new();
        for &(lo, hi) in ranges {
            let edge = (reach * 2).min((hi - lo) / 4);
            rows.extend((lo + edge..hi.saturating_sub(edge)).step_by(step));
        }
        if slow {
            let near = near_standstill(&s.omega_f, s.standstill_speed(), reach);
            rows.retain(|&k| !near[k]);
        }
        let lo = ranges.iter().map(|r| r.0).min().unwrap_or(0);
        let hi = ranges.iter().map(|r| r.1).max().unwrap_or(0);
        BalanceRows { rows, smooth: slow.then_some((cutoff, lo, hi)), sample_hz: s.sample_hz }
    }

    /// Column `f` (a function of the row) at the rows.
    fn column(&self, f: impl Fn(usize) -> f64) -> Vec<f64> {
        match self.smooth {
            None => self.rows.iter().map(|&k| f(k)).collect(),
            Some((cutoff, lo, hi)) => {
                let v: Vec<f64> = (lo..hi).map(f).collect();
                let v = super::signal::filtfilt_butter4(&v, cutoff, self.sample_hz);
                self.rows.iter().map(|&k| v[k - lo]).collect()
            }
        }
    }
}

/// Rows within `reach` rows of one whose filtered speed is at most `still`.
fn near_standstill(omega_f: &[f64], still: f64, reach: usize) -> Vec<bool> {
    let n = omega_f.len();
    let mut near = vec![false; n];
    let mut last: Option<usize> = None;
    for k in 0..n {
        if omega_f[k].abs() <= still {
            last = Some(k);
        }
        near[k] = last.is_some_and(|l| k - l <= reach);
    }
    let mut next: Option<usize> = None;
    for k in (0..n).rev() {
        if omega_f[k].abs() <= still {
            next = Some(k);
        }
        near[k] |= next.is_some_and(|l| l - k <= reach);
    }
    near
}

/// Stribeck speeds tried, as fractions of the recording's speed scale (its 95th percentile of |ω|). On a slow
/// program the scale is a few times ω_s (1–8 Hz: 8 rad/s against ω_s of 2–4.5), so the grid reaches 0.6 of it:
/// capped at 0.25, least squares put ω_s at the cap and the rest of the low-speed bump into B (+174 %).
const STRIBECK_FRACTIONS: [f64; 10] = [0.005, 0.01, 0.02, 0.04, 0.07, 0.1, 0.15, 0.25, 0.4, 0.6];

/// Fits J, B and the chosen terms on the fitting segment; `None` when the data do not determine them or the fit is
/// not physical (negative inertia or friction).
pub fn fit_mechanics(base: &PlantModel, s: &Series, terms: MechTerms) -> Option<PlantModel> {
    fit_mechanics_on(base, s, terms, &[(0, s.split)])
}

/// [`fit_mechanics`] on the rows of `ranges`. On the hydraulic family the least-squares fit is refined by IDIM-IV
/// ([`IV_PASSES`] passes): the sensors' noise in the filtered acceleration attenuates J by least squares (errors in
/// the variables), and what J no longer explains goes to B and the dry terms. The instruments are the regressors of
/// the fitted model's own free run, which move with the true ones but not with the noise.
pub fn fit_mechanics_on(
    base: &PlantModel,
    s: &Series,
    terms: MechTerms,
    ranges: &[(usize, usize)],
) -> Option<PlantModel> {
    let fit = |z: Option<&Instruments>| fit_mechanics_holding(base, s, terms, ranges, None, z);
    instrumented(fit, base, s)
}

/// The fitting segment's least-squares J and its standard deviation, on `terms`' torque balance: what the segment
/// says of the inertia. Its rows are taken at five times the balance's low-pass, about 2.5 a correlation time, so
/// the white-residual standard deviation is widened by √2.5. `None` when the balance cannot be solved.
pub fn inertia_with_sd(s: &Series, terms: MechTerms) -> Option<(f64, f64)> {
    let rows = BalanceRows::new(s, &[(0, s.split)], terms.coulomb || terms.stribeck);
    let y = rows.column(|k| s.drive_torque_f[k] - s.load_f[k]);
    let (theta, sd) = super::signal::least_squares_with_sd(&balance_columns(s, &rows, terms), &y)?;
    Some((theta[0], sd[0] * 2.5f64.sqrt()))
}

/// How long the fitting segment's torque-balance rows (the nominal fit's, without a dry term) move: the rows away
/// from a standstill ([`Series::standstill_speed`]) times the rows' spacing, in seconds.
pub fn moving_balance_s(s: &Series) -> f64 {
    let rows = BalanceRows::new(s, &[(0, s.split)], false);
    let spacing = ((s.sample_hz / (5.0 * s.cutoff_hz)).round()).max(1.0) / s.sample_hz;
    let still = s.standstill_speed();
    rows.rows.iter().filter(|&&k| s.omega_f[k].abs() > still).count() as f64 * spacing
}

/// IDIM-IV from the least-squares fit of `fit`, or, where the noise's bias makes least squares unphysical (a
/// negative dry level), from `base`'s free run. `None` when neither gives a fit.
fn instrumented(
    fit: impl Fn(Option<&Instruments>) -> Option<PlantModel>,
    base: &PlantModel,
    s: &Series,
) -> Option<PlantModel> {
    match fit(None) {
        Some(ls) => Some(refine_by_instruments(ls, |z| fit(Some(z)), s)),
        None if s.family == Family::Hydraulic => {
            let first = fit(Some(&Instruments::of(base, s)?))?;
            Some(refine_by_instruments(first, |z| fit(Some(z)), s))
        }
        None => None,
    }
}

/// Passes of IDIM-IV after the least-squares start: each simulates the last fit and fits again on its regressors.
pub const IV_PASSES: usize = 2;

/// The IDIM-IV passes from the least-squares fit `ls`; the last fit that succeeds (`ls` when none does).
fn refine_by_instruments(ls: PlantModel, fit: impl Fn(&Instruments) -> Option<PlantModel>, s: &Series) -> PlantModel {
    if s.family != Family::Hydraulic {
        return ls;
    }
    let mut m = ls;
    for _ in 0..IV_PASSES {
        let Some(next) = Instruments::of(&m, s).and_then(|z| fit(&z)) else { break };
        m = next;
    }
    m
}

/// The instruments of IDIM-IV: the acceleration of a model's free run, through the recording's low-pass.
pub struct Instruments {
    alpha_f: Vec<f64>,
}

impl Instruments {
    /// `model`'s free run over the recording; `None` when it cannot run or does not stay finite.
    pub fn of(model: &PlantModel, s: &Series) -> Option<Instruments> {
        let p = predict(model, s, s.len()).ok()?;
        if p.omega_rad_s.iter().any(|w| !w.is_finite()) {
            return None;
        }
        let omega_f = super::signal::filtfilt_butter4(&p.omega_rad_s, s.cutoff_hz, s.sample_hz);
        let alpha_f = super::signal::derivative(&omega_f, &s.t_s);
        Some(Instruments { alpha_f })
    }

    /// The instrument for the acceleration column at `rows`: the free run's acceleration, which moves with the
    /// true one but not with the noise that attenuates J. Every other column is its own instrument (the speed's
    /// noise is small beside its spread, and the dry terms' columns are taken off standstill, where the noise would
    /// smear the sign). Instrumenting those too from a model not yet right at low speed was worse on the slow
    /// programs (B about twice the truth).
    fn acceleration(&self, rows: &BalanceRows) -> Vec<f64> {
        rows.column(|k| self.alpha_f[k])
    }
}

/// The torque balance's regressors at `rows`, from the filtered speed and acceleration: α, ω, then sign(ω) and 1 as
/// `terms` asks (the Stribeck shape, which depends on ω_s, is [`stribeck_column`]).
fn balance_columns(s: &Series, rows: &BalanceRows, terms: MechTerms) -> Vec<Vec<f64>> {
    let (w, a) = (&s.omega_f, &s.alpha_f);
    let mut cols = vec![rows.column(|k| a[k]), rows.column(|k| w[k])];
    if terms.coulomb {
        cols.push(rows.column(|k| s.sign(w[k])));
    }
    if terms.offset {
        cols.push(vec![1.0; rows.rows.len()]);
    }
    cols
}

/// The Stribeck shape's column at Stribeck speed `ws`.
fn stribeck_column(s: &Series, rows: &BalanceRows, ws: f64) -> Vec<f64> {
    let w = &s.omega_f;
    rows.column(|k| (-(w[k] / ws).powi(2)).exp() * s.sign(w[k]))
}

/// [`fit_mechanics_on`]'s one fit, with the friction and offset terms of `held` taken as a known torque: J, B and
/// the terms of `terms` are fitted beside them, not through them. By least squares, or with `instruments` by
/// IDIM-IV.
fn fit_mechanics_holding(
    base: &PlantModel,
    s: &Series,
    terms: MechTerms,
    ranges: &[(usize, usize)],
    held: Option<&Mechanics>,
    instruments: Option<&Instruments>,
) -> Option<PlantModel> {
    let rows = BalanceRows::new(s, ranges, terms.coulomb || terms.stribeck || held.is_some());
    let y =
        rows.column(|k| s.drive_torque_f[k] - s.load_f[k] - held.map_or(0.0, |h| extra_torque_nm(h, s, s.omega_f[k])));
    // the columns but the Stribeck shape's do not depend on ω_s: read once
    let fixed = balance_columns(s, &rows, terms);
    let instrument = instruments.map(|z| z.acceleration(&rows));
    let solve = |ws: Option<f64>| -> Option<(Vec<f64>, f64)> {
        let mut x = fixed.clone();
        if let Some(ws) = ws {
            x.push(stribeck_column(s, &rows, ws));
        }
        let theta = match &instrument {
            Some(alpha) => {
                let mut z = x.clone();
                z[0].clone_from(alpha);
                instrumental_least_squares(&x, &z, &y)?
            }
            None => least_squares(&x, &y)?,
        };
        let rss = (0..y.len()).map(|i| (y[i] - x.iter().zip(&theta).map(|(c, t)| c[i] * t).sum::<f64>()).powi(2)).sum();
        Some((theta, rss))
    };
    let (theta, stribeck_speed) = if terms.stribeck {
        // ω_s enters nonlinearly: grid, then golden section on the residual, in log ω_s
        let mut rss = |log_ws: f64| solve(Some(log_ws.exp())).map_or(f64::INFINITY, |(_, r)| r);
        let scale = s.speed_scale();
        // a Stribeck speed inside the sign band would only reshape the sign function
        let grid: Vec<f64> =
            STRIBECK_FRACTIONS.iter().map(|f| f * scale).filter(|ws| *ws >= 3.0 * s.sign_speed).map(f64::ln).collect();
        if grid.is_empty() {
            return None;
        }
        let (log_ws, best) = minimize_1d(&mut rss, &grid, 12);
        if !best.is_finite() {
            return None;
        }
        let ws = log_ws.exp();
        (solve(Some(ws))?.0, Some(ws))
    } else {
        (solve(None)?.0, None)
    };
    let mut m = base.clone();
    let mut it = theta.into_iter();
    m.motor.inertia_kg_m2 = it.next()?;
    m.motor.viscous_nm_s_rad = it.next()?.max(0.0);
    if m.motor.inertia_kg_m2.is_nan() || m.motor.inertia_kg_m2 <= 0.0 {
        return None;
    }
    m.effects.coulomb_friction = None;
    m.effects.torque_offset = None;
    m.effects.stribeck_friction = None;
    let mut coulomb = 0.0;
    if terms.coulomb {
        coulomb = it.next()?;
        if coulomb < 0.0 {
            return None;
        }
        m.effects.coulomb_friction = Some(CoulombFriction { torque_nm: coulomb });
    }
    if terms.offset {
        m.effects.torque_offset = Some(TorqueOffset { torque_nm: it.next()? });
    }
    if let Some(ws) = stribeck_speed {
        let extra = it.next()?;
        if extra <= 0.0 {
            return None;
        }
        m.effects.stribeck_friction = Some(StribeckFriction { breakaway_nm: coulomb + extra, speed_rad_s: ws });
    }
    m.validate().ok()?;
    Some(m)
}

/// How many parameters an effect adds (for BIC).
pub fn parameter_count(id: &str) -> usize {
    if id == "stribeck_friction" { 2 } else { 1 }
}

/// Effects of the torque balance: with the load unknown, the load absorbs them.
pub const TORQUE_SIDE: [&str; 3] = ["coulomb_friction", "stribeck_friction", "torque_offset"];

/// The catalogue ids that apply to a recording: every one to the hydraulic plant, the torque-balance ones to a
/// torque-driven recording, the flow-balance ones with the load unknown (dead time only where the setpoint was
/// recorded).
pub fn applicable(s: &Series) -> Vec<&'static str> {
    EFFECT_IDS
        .iter()
        .copied()
        .filter(|id| match s.family {
            Family::Hydraulic => true,
            Family::Torque => TORQUE_SIDE.contains(id),
            Family::Flow => !TORQUE_SIDE.contains(id) && (*id != "dead_time" || s.setpoint_hz.is_some()),
        })
        .collect()
}

/// BIC difference (positive = the richer model is better) from fitting-segment scores, with `n` effective samples.
pub fn delta_bic(score_before: f64, score_after: f64, added_params: usize, n: f64) -> f64 {
    if !(score_before > 0.0 && score_after > 0.0) {
        return 0.0;
    }
    n * (score_before / score_after).ln() - added_params as f64 * n.ln()
}

#[cfg(test)]
mod tests {
    use super::near_standstill;

    #[test]
    fn rows_within_reach_of_a_standstill_are_near_it() {
        let w = [5.0, 5.0, 5.0, 0.1, 5.0, 5.0, 5.0, 5.0, -0.2, 5.0];
        let near = near_standstill(&w, 0.5, 1);
        assert_eq!(near, [false, false, true, true, true, false, false, true, true, true]);
        assert!(near_standstill(&w, 0.5, 0).iter().zip(&w).all(|(n, x)| *n == (x.abs() <= 0.5)));
    }
}

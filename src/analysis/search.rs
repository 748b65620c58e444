//! Fitting: J, B and the friction/offset terms by least squares on the torque balance; the flow-side effects by
//! 1-D search on the free-run error; greedy forward selection judged on the validation segment.

use crate::BadInput;
use crate::plant::PlantModel;
use crate::plant::dynamics::Mechanics;
use crate::plant::effects::{
    CoulombFriction, DeadTime, EFFECT_IDS, EntrainedAir, InternalLeakage, MotorSlip, StribeckFriction, TorqueOffset,
};

use super::predict::{Errors, Prediction, errors, extra_torque_nm, predict, predict_rows};
use super::series::{Family, Series};
use super::signal::{least_squares, minimize_1d};

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

/// Rows of the torque balance used by least squares: each range without its filter edges, decimated.
fn ls_rows(s: &Series, ranges: &[(usize, usize)]) -> Vec<usize> {
    let step = ((s.sample_hz / (5.0 * s.cutoff_hz)).round() as usize).max(1);
    let mut rows = Vec::new();
    for &(lo, hi) in ranges {
        let edge = ((s.sample_hz / s.cutoff_hz) as usize * 2).min((hi - lo) / 4);
        rows.extend((lo + edge..hi.saturating_sub(edge)).step_by(step));
    }
    rows
}

/// Stribeck speeds tried, as fractions of the recording's speed scale.
const STRIBECK_FRACTIONS: [f64; 8] = [0.005, 0.01, 0.02, 0.04, 0.07, 0.1, 0.15, 0.25];

/// Fits J, B and the chosen terms on the fitting segment; `None` when the data do not determine them or the fit is
/// not physical (negative inertia or friction).
pub fn fit_mechanics(base: &PlantModel, s: &Series, terms: MechTerms) -> Option<PlantModel> {
    fit_mechanics_on(base, s, terms, &[(0, s.split)])
}

/// [`fit_mechanics`] on the rows of `ranges`.
pub fn fit_mechanics_on(
    base: &PlantModel,
    s: &Series,
    terms: MechTerms,
    ranges: &[(usize, usize)],
) -> Option<PlantModel> {
    fit_mechanics_holding(base, s, terms, ranges, None)
}

/// [`fit_mechanics_on`], with the friction and offset terms of `held` taken as a known torque: J, B and the terms
/// of `terms` are fitted beside them, not through them.
fn fit_mechanics_holding(
    base: &PlantModel,
    s: &Series,
    terms: MechTerms,
    ranges: &[(usize, usize)],
    held: Option<&Mechanics>,
) -> Option<PlantModel> {
    let rows = ls_rows(s, ranges);
    let y: Vec<f64> = rows
        .iter()
        .map(|&k| s.drive_torque_f[k] - s.load_f[k] - held.map_or(0.0, |h| extra_torque_nm(h, s, s.omega_f[k])))
        .collect();
    let mut cols =
        vec![rows.iter().map(|&k| s.alpha_f[k]).collect::<Vec<f64>>(), rows.iter().map(|&k| s.omega_f[k]).collect()];
    if terms.coulomb {
        cols.push(rows.iter().map(|&k| s.sign(s.omega_f[k])).collect());
    }
    if terms.offset {
        cols.push(vec![1.0; rows.len()]);
    }
    let (theta, stribeck_speed) = if terms.stribeck {
        // ω_s enters nonlinearly: grid, then golden section on the least-squares residual, in log ω_s
        let with = |ws: f64| {
            let mut c = cols.clone();
            c.push(rows.iter().map(|&k| (-(s.omega_f[k] / ws).powi(2)).exp() * s.sign(s.omega_f[k])).collect());
            c
        };
        let mut rss = |log_ws: f64| {
            let c = with(log_ws.exp());
            match least_squares(&c, &y) {
                Some(th) => (0..y.len())
                    .map(|i| (y[i] - c.iter().zip(&th).map(|(col, t)| col[i] * t).sum::<f64>()).powi(2))
                    .sum(),
                None => f64::INFINITY,
            }
        };
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
        (least_squares(&with(ws), &y)?, Some(ws))
    } else {
        (least_squares(&cols, &y)?, None)
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

/// The flow-side effects and how their one parameter is searched: grid (increasing) in a search variable, and the
/// map from that variable to the effect.
/// Sets a flow-side effect's parameter from the search variable.
type SetEffect = Box<dyn Fn(&mut PlantModel, f64)>;

fn flow_grid(id: &str, nominal_bulk_bar: f64) -> Option<(Vec<f64>, SetEffect)> {
    match id {
        "internal_leakage" => Some((
            vec![0.0, 0.0025, 0.005, 0.01, 0.02, 0.04, 0.08, 0.16, 0.32],
            Box::new(|m, x| m.effects.internal_leakage = Some(InternalLeakage { l_min_per_bar: x.max(0.0) })),
        )),
        "motor_slip" => Some((
            vec![0.0, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0],
            Box::new(|m, x| m.effects.motor_slip = Some(MotorSlip { rpm_per_nm: x.max(0.0) })),
        )),
        "dead_time" => Some((
            vec![0.0, 5.0, 10.0, 20.0, 40.0, 80.0, 160.0, 320.0],
            Box::new(|m, x| m.effects.dead_time = Some(DeadTime { ms: x.max(0.0) })),
        )),
        "entrained_air" => Some((
            [0.02f64, 0.05, 0.1, 0.15, 0.25, 0.35, 0.5, 0.7, 1.0].iter().map(|f| f.ln()).collect(),
            Box::new(move |m, x| {
                m.effects.entrained_air = Some(EntrainedAir { bulk_modulus_bar: nominal_bulk_bar * x.min(0.0).exp() })
            }),
        )),
        _ => None,
    }
}

/// The flow-side effect's search variable in `m` (as [`flow_grid`] sets it), when present and positive (log ratio
/// for the bulk modulus).
fn flow_value(id: &str, m: &PlantModel, nominal_bulk_bar: f64) -> Option<f64> {
    let e = &m.effects;
    match id {
        "internal_leakage" => e.internal_leakage.map(|x| x.l_min_per_bar).filter(|v| *v > 0.0),
        "motor_slip" => e.motor_slip.map(|x| x.rpm_per_nm).filter(|v| *v > 0.0),
        "dead_time" => e.dead_time.map(|x| x.ms).filter(|v| *v > 0.0),
        "entrained_air" => e.entrained_air.map(|x| (x.bulk_modulus_bar / nominal_bulk_bar).ln()),
        _ => None,
    }
}

/// Builds the candidate that adds effect `id` to `current` (with its torque-balance `terms`), its parameters fitted
/// on `rows`. `None` when it does not apply or cannot be fitted. `hint`, a model with the effect already fitted on
/// other rows (cross-validation folds start from the documented fit), narrows the free-run searches to ×0.5…2
/// around its value.
pub fn candidate(
    id: &str,
    current: &PlantModel,
    terms: MechTerms,
    s: &Series,
    rows: &Rows,
    hint: Option<&PlantModel>,
) -> Option<(PlantModel, MechTerms)> {
    let mut terms = terms;
    match id {
        "coulomb_friction" => terms.coulomb = true,
        "torque_offset" => terms.offset = true,
        "stribeck_friction" => terms.stribeck = true,
        _ => {
            if s.family == Family::Torque {
                return None;
            }
            let nominal_bulk = current.hydraulics.as_ref()?.bulk_modulus_bar;
            // Slip takes flow exactly as leakage does (C = D_p²·k_s): searched as leakage and converted, the two
            // candidates score the same, and which one is named is the catalogue order's choice, not the search's
            if id == "motor_slip" && current.effects.internal_leakage.is_none() {
                let per_rpm = super::slip_as_leakage(current, 1.0).filter(|v| *v > 0.0)?;
                // the hint's slip as the equivalent leakage
                let leak_hint = hint.and_then(|h| h.effects.motor_slip).map(|k| {
                    let mut h = current.clone();
                    h.effects.internal_leakage = Some(InternalLeakage { l_min_per_bar: k.rpm_per_nm * per_rpm });
                    h
                });
                let (leak, _) = candidate("internal_leakage", current, terms, s, rows, leak_hint.as_ref())?;
                let extra = leak.effects.internal_leakage.map_or(0.0, |l| l.l_min_per_bar);
                let mut m = current.clone();
                m.effects.motor_slip = Some(MotorSlip { rpm_per_nm: extra / per_rpm });
                return Some((m, terms));
            }
            let (mut grid, set) = flow_grid(id, nominal_bulk)?;
            let mut iterations = 10;
            if let Some(x0) = hint.and_then(|h| flow_value(id, h, nominal_bulk)) {
                grid = if id == "entrained_air" {
                    [-0.7f64, -0.35, 0.0, 0.35, 0.7].iter().map(|d| (x0 + d).min(0.0)).collect()
                } else {
                    [0.5, 0.7, 1.0, 1.4, 2.0].iter().map(|f| f * x0).collect()
                };
                grid.dedup();
                iterations = 6;
            }
            let mut cost = |x: f64| {
                let mut m = current.clone();
                set(&mut m, x);
                rows.search_cost(&m, s)
            };
            let (x, _) = minimize_1d(&mut cost, &grid, iterations);
            let mut m = current.clone();
            set(&mut m, x);
            return Some((m, terms));
        }
    }
    if id == "stribeck_friction" && s.family == Family::Hydraulic {
        // With dry friction already in, least squares on the 10 Hz-filtered speed often puts the low-speed excess
        // into the Coulomb term (extra ≤ 0): the free run then starts from a guess (excess = the Coulomb
        // friction, at least 0.1 N·m; ω_s = 4 % of the speed scale) over a wider range
        let hinted = hint.and_then(|h| h.effects.stribeck_friction.map(|st| (st, h.effects.coulomb_friction)));
        if let Some((st, tc_hint)) = hinted {
            // start from the hint's low-speed excess and ω_s, J, B and Coulomb friction fitted on these rows
            let mut m = fit_mechanics_on(current, s, terms, &rows.ls)
                .or_else(|| fit_mechanics_on(current, s, MechTerms { stribeck: false, ..terms }, &rows.ls))?;
            let tc = m.effects.coulomb_friction.map_or(0.0, |c| c.torque_nm);
            let extra = (st.breakaway_nm - tc_hint.map_or(0.0, |c| c.torque_nm)).max(1e-3);
            m.effects.stribeck_friction =
                Some(StribeckFriction { breakaway_nm: tc + extra, speed_rad_s: st.speed_rad_s });
            return Some((refine_stribeck(m, s, rows, false, 1), terms));
        }
        let (fitted, wide) = match fit_mechanics_on(current, s, terms, &rows.ls) {
            Some(m) => (m, false),
            None => {
                let mut m = fit_mechanics_on(current, s, MechTerms { stribeck: false, ..terms }, &rows.ls)?;
                let tc = m.effects.coulomb_friction.map_or(0.0, |c| c.torque_nm);
                let ws = (0.04 * s.speed_scale()).max(3.0 * s.sign_speed);
                m.effects.stribeck_friction =
                    Some(StribeckFriction { breakaway_nm: tc + tc.max(0.1), speed_rad_s: ws });
                (m, true)
            }
        };
        return Some((refine_stribeck(fitted, s, rows, wide, 2), terms));
    }
    if let Some(fitted) = fit_mechanics_on(current, s, terms, &rows.ls) {
        return Some((fitted, terms));
    }
    if id != "coulomb_friction" {
        return None;
    }
    coulomb_beside_stribeck(current, terms, s, rows).map(|m| (m, terms))
}

/// [`coulomb_beside_stribeck`] names no Coulomb level below this share of the breakaway.
const MIN_COULOMB_SHARE: f64 = 0.1;
/// Rounds of [`coulomb_beside_stribeck`]'s coordinate descent.
const COULOMB_PASSES: usize = 3;

/// Coulomb friction beside a Stribeck friction already named. Least squares on the filtered speed may share the two
/// badly (a negative dry level or excess), yet a constant and a bump at low speed are told apart by the free run
/// over a spread of speeds. So the breakaway the Stribeck fit found (the whole friction at standstill) is kept and
/// split: the dry level is searched on the free run, with J and B fitted by least squares for each level and both
/// dry terms held; then the excess and ω_s are refined. Each dry term is evaluated whatever the other's state.
pub fn coulomb_beside_stribeck(current: &PlantModel, terms: MechTerms, s: &Series, rows: &Rows) -> Option<PlantModel> {
    if s.family != Family::Hydraulic {
        return None;
    }
    let free = MechTerms { coulomb: false, stribeck: false, ..terms };
    let mut m = current.clone();
    let mut grid: Vec<f64> = vec![0.05, 0.1, 0.2, 0.35, 0.5, 0.7, 0.9];
    // coordinate descent: the dry level at the breakaway found so far, then the excess and ω_s at that level
    for _ in 0..COULOMB_PASSES {
        let st = m.effects.stribeck_friction?;
        let with_coulomb = |tc: f64| -> Option<PlantModel> {
            let breakaway = tc + (st.breakaway_nm - tc).max(1e-3);
            let held = Mechanics {
                inertia_kg_m2: 0.0,
                viscous_nm_s_rad: 0.0,
                coulomb_nm: tc,
                stribeck: Some((breakaway, st.speed_rad_s)),
                offset_nm: 0.0,
            };
            let mut m = fit_mechanics_holding(current, s, free, &rows.ls, Some(&held))?;
            m.effects.coulomb_friction = Some(CoulombFriction { torque_nm: tc });
            m.effects.stribeck_friction = Some(StribeckFriction { breakaway_nm: breakaway, ..st });
            m.validate().ok().map(|()| m)
        };
        let levels: Vec<f64> = grid.iter().map(|f| f * st.breakaway_nm).collect();
        let mut cost = |tc: f64| with_coulomb(tc).map_or(f64::INFINITY, |m| rows.search_cost(&m, s));
        let (tc, best) = minimize_1d(&mut cost, &levels, 8);
        if !best.is_finite() {
            return None;
        }
        if tc < MIN_COULOMB_SHARE * st.breakaway_nm {
            // a level this small is what refitting the Stribeck term alone moves, not a dry friction of its own
            return None;
        }
        m = refine_stribeck(with_coulomb(tc)?, s, rows, false, 1);
        // the next pass looks around this level
        let f = tc / st.breakaway_nm;
        grid = [0.6, 0.8, 1.0, 1.25, 1.6].iter().map(|x| (x * f).min(0.95)).collect();
        grid.dedup();
    }
    Some(m)
}

/// Low-speed friction shows in brief transients, where the low-passed speed of the torque balance smears it; the
/// free run does not. Coordinate descent on (breakaway, ω_s) around the least-squares values, by golden section on
/// the free-run error of the search window (factors 0.5–2 per pass, or 0.25–4 from a guess).
fn refine_stribeck(mut m: PlantModel, s: &Series, rows: &Rows, wide: bool, passes: usize) -> PlantModel {
    let factors: &[f64] = if wide { &[0.25, 0.5, 0.7, 1.0, 1.4, 2.0, 4.0] } else { &[0.5, 0.7, 1.0, 1.4, 2.0] };
    let grid: Vec<f64> = factors.iter().map(|f| f.ln()).collect();
    for _ in 0..passes {
        let Some(st) = m.effects.stribeck_friction else { return m };
        let tc = m.effects.coulomb_friction.map_or(0.0, |c| c.torque_nm);
        let extra = (st.breakaway_nm - tc).max(1e-6);
        let mut with_extra = |x: f64| {
            let mut t = m.clone();
            t.effects.stribeck_friction = Some(StribeckFriction { breakaway_nm: tc + extra * x.exp(), ..st });
            rows.search_cost(&t, s)
        };
        let (x, _) = minimize_1d(&mut with_extra, &grid, 6);
        let st = StribeckFriction { breakaway_nm: tc + extra * x.exp(), ..st };
        let mut with_speed = |x: f64| {
            let mut t = m.clone();
            t.effects.stribeck_friction = Some(StribeckFriction { speed_rad_s: st.speed_rad_s * x.exp(), ..st });
            rows.search_cost(&t, s)
        };
        let (x, _) = minimize_1d(&mut with_speed, &grid, 6);
        m.effects.stribeck_friction = Some(StribeckFriction { speed_rad_s: st.speed_rad_s * x.exp(), ..st });
    }
    m
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

//! Fitting: J, B and the friction/offset terms by least squares on the torque balance; the flow-side effects by
//! 1-D search on the free-run error; greedy forward selection judged on the validation segment.

use crate::BadInput;
use crate::plant::PlantModel;
use crate::plant::effects::{
    CoulombFriction, DeadTime, EFFECT_IDS, EntrainedAir, InternalLeakage, MotorSlip, StribeckFriction, TorqueOffset,
};

use super::predict::{Errors, Prediction, errors, predict};
use super::series::{Family, Series};
use super::signal::{least_squares, minimize_1d};

/// Which torque-balance terms the least-squares fit includes besides J and B.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct MechTerms {
    pub coulomb: bool,
    pub offset: bool,
    pub stribeck: bool,
}

/// A model under consideration, with its predictions over the whole recording and their errors.
#[derive(Debug, Clone)]
pub struct Scored {
    pub model: PlantModel,
    pub terms: MechTerms,
    pub prediction: Prediction,
    /// Errors on the fitting segment (for BIC) and the validation segment (for selection).
    pub fit: Errors,
    pub validation: Errors,
}

impl Scored {
    pub fn evaluate(model: PlantModel, terms: MechTerms, s: &Series) -> Result<Scored, BadInput> {
        let prediction = predict(&model, s, s.len())?;
        let fit = errors(&prediction, s, 0, s.split);
        let validation = errors(&prediction, s, s.split, s.len());
        Ok(Scored { model, terms, prediction, fit, validation })
    }
}

/// Rows of the torque balance used by least squares: the fitting segment without its filter edges, decimated.
fn ls_rows(s: &Series) -> Vec<usize> {
    let edge = ((s.sample_hz / s.cutoff_hz) as usize * 2).min(s.split / 4);
    let step = ((s.sample_hz / (5.0 * s.cutoff_hz)).round() as usize).max(1);
    (edge..s.split.saturating_sub(edge)).step_by(step).collect()
}

/// Stribeck speeds tried, as fractions of the recording's speed scale.
const STRIBECK_FRACTIONS: [f64; 8] = [0.005, 0.01, 0.02, 0.04, 0.07, 0.1, 0.15, 0.25];

/// Fits J, B and the chosen terms on the fitting segment; `None` when the data do not determine them or the fit is
/// not physical (negative inertia or friction).
pub fn fit_mechanics(base: &PlantModel, s: &Series, terms: MechTerms) -> Option<PlantModel> {
    let rows = ls_rows(s);
    let y: Vec<f64> = rows.iter().map(|&k| s.drive_torque_f[k] - s.load_f[k]).collect();
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

/// Builds the candidate that adds effect `id` to `current`, with its parameters fitted on the fitting segment
/// (`search_end` rows at most for the free-run search). `None` when it does not apply or cannot be fitted.
pub fn candidate(id: &str, current: &Scored, s: &Series, search_end: usize) -> Option<(PlantModel, MechTerms)> {
    let mut terms = current.terms;
    match id {
        "coulomb_friction" => terms.coulomb = true,
        "torque_offset" => terms.offset = true,
        "stribeck_friction" => terms.stribeck = true,
        _ => {
            if s.family == Family::Torque {
                return None;
            }
            let nominal_bulk = current.model.hydraulics.as_ref()?.bulk_modulus_bar;
            // Slip takes flow exactly as leakage does (C = D_p²·k_s): searched as leakage and converted, the two
            // candidates score the same, and which one is named is the catalogue order's choice, not the search's
            if id == "motor_slip" && current.model.effects.internal_leakage.is_none() {
                let per_rpm = super::slip_as_leakage(&current.model, 1.0).filter(|v| *v > 0.0)?;
                let (leak, _) = candidate("internal_leakage", current, s, search_end)?;
                let extra = leak.effects.internal_leakage.map_or(0.0, |l| l.l_min_per_bar);
                let mut m = current.model.clone();
                m.effects.motor_slip = Some(MotorSlip { rpm_per_nm: extra / per_rpm });
                return Some((m, terms));
            }
            let (grid, set) = flow_grid(id, nominal_bulk)?;
            let mut cost = |x: f64| {
                let mut m = current.model.clone();
                set(&mut m, x);
                match predict(&m, s, search_end) {
                    Ok(p) => errors(&p, s, 0, search_end).score(s.family),
                    Err(_) => f64::INFINITY,
                }
            };
            let (x, _) = minimize_1d(&mut cost, &grid, 10);
            let mut m = current.model.clone();
            set(&mut m, x);
            return Some((m, terms));
        }
    }
    let fitted = fit_mechanics(&current.model, s, terms)?;
    if id == "stribeck_friction" && s.family == Family::Hydraulic {
        return Some((refine_stribeck(fitted, s, search_end), terms));
    }
    Some((fitted, terms))
}

/// Low-speed friction shows in brief transients, where the low-passed speed of the torque balance smears it; the
/// free run does not. Coordinate descent on (breakaway, ω_s) around the least-squares values, by golden section on
/// the free-run error of the search window.
fn refine_stribeck(mut m: PlantModel, s: &Series, search_end: usize) -> PlantModel {
    let cost = |m: &PlantModel| match predict(m, s, search_end) {
        Ok(p) => errors(&p, s, 0, search_end).score(s.family),
        Err(_) => f64::INFINITY,
    };
    for _ in 0..2 {
        let Some(st) = m.effects.stribeck_friction else { return m };
        let tc = m.effects.coulomb_friction.map_or(0.0, |c| c.torque_nm);
        let extra = (st.breakaway_nm - tc).max(1e-6);
        let mut with_extra = |x: f64| {
            let mut t = m.clone();
            t.effects.stribeck_friction = Some(StribeckFriction { breakaway_nm: tc + extra * x.exp(), ..st });
            cost(&t)
        };
        let grid: Vec<f64> = [0.5f64, 0.7, 1.0, 1.4, 2.0].iter().map(|f| f.ln()).collect();
        let (x, _) = minimize_1d(&mut with_extra, &grid, 6);
        let st = StribeckFriction { breakaway_nm: tc + extra * x.exp(), ..st };
        let mut with_speed = |x: f64| {
            let mut t = m.clone();
            t.effects.stribeck_friction = Some(StribeckFriction { speed_rad_s: st.speed_rad_s * x.exp(), ..st });
            cost(&t)
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

//! The candidates: one catalogue effect added to the model so far, its parameters fitted. Flow-side effects by 1-D
//! search on the free run's cost; dry friction by least squares, then refined on the free run (Stribeck, Coulomb
//! beside it, and the backward refit of low-speed friction). Part of the PURE analysis room ([`crate::analysis`]).

use crate::plant::PlantModel;
use crate::plant::dynamics::Mechanics;
use crate::plant::effects::{DeadTime, EntrainedAir, InternalLeakage, MotorSlip, StribeckFriction};

use super::{Instruments, MechTerms, Rows, fit_mechanics_holding, fit_mechanics_on, instrumented};
use crate::analysis::series::{Family, Series};
use crate::analysis::signal::minimize_1d;

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
        _ => return flow_candidate(id, current, terms, s, rows, hint),
    }
    if id == "stribeck_friction" && s.family == Family::Hydraulic {
        return stribeck_candidate(current, terms, s, rows, hint);
    }
    if let Some(fitted) = fit_mechanics_on(current, s, terms, &rows.ls) {
        return Some((fitted, terms));
    }
    if id != "coulomb_friction" {
        return None;
    }
    coulomb_beside_stribeck(current, terms, s, rows).map(|m| (m, terms))
}

/// A flow-balance candidate (leakage, slip, dead time, entrained air; none for a torque-driven recording): its
/// one parameter searched on the free run's cost over a grid and refined, around the hint's value when given.
fn flow_candidate(
    id: &str,
    current: &PlantModel,
    terms: MechTerms,
    s: &Series,
    rows: &Rows,
    hint: Option<&PlantModel>,
) -> Option<(PlantModel, MechTerms)> {
    if s.family == Family::Torque {
        return None;
    }
    let nominal_bulk = current.hydraulics.as_ref()?.bulk_modulus_bar;
    // Slip takes flow exactly as leakage does (C = D_p²·k_s): searched as leakage and converted, the two
    // candidates score the same, and which one is named is the catalogue order's choice, not the search's
    if id == "motor_slip" && current.effects.internal_leakage.is_none() {
        let per_rpm = crate::analysis::slip_as_leakage(current, 1.0).filter(|v| *v > 0.0)?;
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
    Some((m, terms))
}

/// Stribeck friction for the hydraulic family: J, B and the dry terms by least squares, then refined on the free
/// run (from the hint's low-speed excess and ω_s when given).
fn stribeck_candidate(
    current: &PlantModel,
    terms: MechTerms,
    s: &Series,
    rows: &Rows,
    hint: Option<&PlantModel>,
) -> Option<(PlantModel, MechTerms)> {
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
        m.effects.stribeck_friction = Some(StribeckFriction { breakaway_nm: tc + extra, speed_rad_s: st.speed_rad_s });
        return Some((refine_stribeck(m, s, rows, false, STRIBECK_PASSES_HINTED, true), terms));
    }
    let (fitted, wide) = match fit_mechanics_on(current, s, terms, &rows.ls) {
        Some(m) => (m, false),
        None => {
            let mut m = fit_mechanics_on(current, s, MechTerms { stribeck: false, ..terms }, &rows.ls)?;
            let tc = m.effects.coulomb_friction.map_or(0.0, |c| c.torque_nm);
            let ws = (0.04 * s.speed_scale()).max(3.0 * s.sign_speed);
            m.effects.stribeck_friction = Some(StribeckFriction { breakaway_nm: tc + tc.max(0.1), speed_rad_s: ws });
            (m, true)
        }
    };
    // B with them: on a slow program the Stribeck shape and a viscous line trade over the speeds visited, and
    // least squares on the filtered speed leaves B far off (held-out run 105 of the issue-33 sweep: +717 %)
    Some((refine_stribeck(fitted, s, rows, wide, STRIBECK_PASSES, true), terms))
}

/// [`coulomb_beside_stribeck`] names no Coulomb level below this share of the breakaway.
const MIN_COULOMB_SHARE: f64 = 0.1;
/// Rounds of [`coulomb_beside_stribeck`]'s coordinate descent.
const COULOMB_PASSES: usize = 3;

/// Coulomb friction beside a Stribeck friction already named. Least squares with both dry terms free shares them
/// badly on the filtered speed (a negative dry level or excess), and the free run barely tells a Coulomb level from
/// viscous friction (a constant and a line through the origin over the same speeds trade along a ridge). So the two
/// are split by coordinate descent: J, B and the Coulomb level by least squares (IDIM-IV) with the Stribeck excess
/// above it held, then the excess and ω_s on the free run at that level. Over a spread of speeds above ω_s, the
/// torque balance tells the constant from the line; the low-speed bump is what the free run sees. Each dry term is
/// evaluated whatever the other's state.
pub fn coulomb_beside_stribeck(current: &PlantModel, terms: MechTerms, s: &Series, rows: &Rows) -> Option<PlantModel> {
    if s.family != Family::Hydraulic {
        return None;
    }
    let dry = MechTerms { coulomb: true, stribeck: false, ..terms };
    let mut m = current.clone();
    let first = current.effects.stribeck_friction?;
    // the excess over the Coulomb level: at first the whole breakaway the Stribeck fit found
    let mut excess = first.breakaway_nm - current.effects.coulomb_friction.map_or(0.0, |c| c.torque_nm);
    let mut best: Option<(f64, PlantModel)> = None;
    for _ in 0..COULOMB_PASSES {
        let st = m.effects.stribeck_friction?;
        let held = Mechanics {
            inertia_kg_m2: 0.0,
            viscous_nm_s_rad: 0.0,
            coulomb_nm: 0.0,
            stribeck: Some((excess.max(1e-3), st.speed_rad_s)),
            offset_nm: 0.0,
        };
        let fit = |z: Option<&Instruments>| fit_mechanics_holding(current, s, dry, &rows.ls, Some(&held), z);
        let fitted = instrumented(fit, &m, s)?;
        let tc = fitted.effects.coulomb_friction.map_or(0.0, |c| c.torque_nm);
        let mut next = fitted;
        next.effects.stribeck_friction = Some(StribeckFriction { breakaway_nm: tc + excess.max(1e-3), ..st });
        next.validate().ok()?;
        m = refine_stribeck(next, s, rows, false, 1, false);
        excess = m.effects.stribeck_friction.map_or(excess, |st| st.breakaway_nm - tc);
        let cost = rows.search_cost(&m, s);
        if best.as_ref().is_none_or(|(c, _)| cost < *c) {
            best = Some((cost, m.clone()));
        }
    }
    // the two steps can walk along the ridge between the dry level and the excess: the pass the free run prefers
    let (_, m) = best?;
    let tc = m.effects.coulomb_friction.map_or(0.0, |c| c.torque_nm);
    let breakaway = m.effects.stribeck_friction.map_or(tc, |st| st.breakaway_nm);
    // a level this small is what refitting the Stribeck term alone moves, not a dry friction of its own
    (tc >= MIN_COULOMB_SHARE * breakaway).then_some(m)
}

/// Passes of [`refine_stribeck`] (with B) for a Stribeck candidate fitted from scratch, and from a hint (a fold).
const STRIBECK_PASSES: usize = 3;
const STRIBECK_PASSES_HINTED: usize = 2;
/// Passes of [`refine_stribeck`] (with B) in each half of [`refit_low_speed`].
const REFIT_PASSES: usize = 2;
/// The factors of B tried by [`refine_stribeck`] before golden section.
const VISCOUS_FACTORS: [f64; 8] = [0.1, 0.2, 0.35, 0.5, 0.7, 1.0, 1.4, 2.0];

/// The backward step for low-speed friction: a named Stribeck friction (its excess, ω_s and B) refined again on the
/// free run of `m` with what was named since, and a named dead time searched again beside it (×0.5…2), then the
/// friction once more. A Stribeck friction fitted before the dead time was in was fitted against a free run the
/// missing lag distorted after every setpoint step, and the dead time then fitted against that friction (tuned runs
/// of the issue-33 sweep: a dead time −30 %, B +61 %). `None` when `m` has no Stribeck friction.
pub fn refit_low_speed(m: &PlantModel, terms: MechTerms, s: &Series, rows: &Rows) -> Option<PlantModel> {
    if s.family != Family::Hydraulic {
        return None;
    }
    m.effects.stribeck_friction?;
    let mut n = refine_stribeck(m.clone(), s, rows, false, REFIT_PASSES, true);
    if n.effects.dead_time.is_some() {
        let mut without = n.clone();
        without.effects.dead_time = None;
        n = candidate("dead_time", &without, terms, s, rows, Some(&n))?.0;
        n = refine_stribeck(n, s, rows, false, REFIT_PASSES, true);
    }
    Some(n)
}

/// Low-speed friction shows in brief transients, where the low-passed speed of the torque balance smears it; the
/// free run does not. Coordinate descent on (breakaway, ω_s) around the least-squares values, by golden section on
/// the free-run error of the search window (factors 0.5–2 per pass, or 0.25–4 from a guess).
///
/// With `viscous`, each pass ends with B by golden section on the same free-run error (×0.1…2): on a slow program
/// the Stribeck shape and a viscous line trade over the speeds visited, and least squares on the filtered speed puts
/// into B what belongs to the low-speed friction; the free run tells them apart where the steady speeds do not.
fn refine_stribeck(mut m: PlantModel, s: &Series, rows: &Rows, wide: bool, passes: usize, viscous: bool) -> PlantModel {
    let factors: &[f64] = if wide { &[0.25, 0.5, 0.7, 1.0, 1.4, 2.0, 4.0] } else { &[0.5, 0.7, 1.0, 1.4, 2.0] };
    let grid: Vec<f64> = factors.iter().map(|f| f.ln()).collect();
    let viscous_grid: Vec<f64> = VISCOUS_FACTORS.iter().map(|f| f.ln()).collect();
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
        if viscous {
            let b0 = m.motor.viscous_nm_s_rad.max(1e-4);
            let mut with_b = |x: f64| {
                let mut t = m.clone();
                t.motor.viscous_nm_s_rad = b0 * x.exp();
                rows.search_cost(&t, s)
            };
            let (x, _) = minimize_1d(&mut with_b, &viscous_grid, 6);
            m.motor.viscous_nm_s_rad = b0 * x.exp();
        }
    }
    m
}

//! What a candidate must be besides better by the numbers: beyond what the recording and the plant's own variation
//! resolve, and, for dry friction, the sign that it was missing (B back within reach of the nominal model's). Part
//! of the PURE analysis room ([`crate::analysis`]), used by the selection ([`super`]).

use crate::analysis::Options;
use crate::analysis::explain::slip_as_leakage;
use crate::analysis::series::Series;
use crate::plant::PlantModel;

/// Whether effect `id`, as fitted in `candidate`, lies beyond what the recording and the plant's own variation
/// resolve against `current` (the model before it):
/// - a dead time shorter than one sample period is below what the recording resolves: a service recording stamps a
///   row when the read is sent and the setpoint lands after the reply, so such a lag is the recorder's own;
/// - an oil's bulk modulus moves by 10–20 % with its temperature and pressure, and a service recording's poll jitter
///   softens the fitted one by as much (a plant with only Coulomb friction, served at 5 ms on a loaded machine, gave
///   8 % below the model's): an effective modulus above `air_max_modulus_ratio` of the model's is not entrained air;
/// - leakage through a clearance goes with the oil's viscosity, which moves by 20 % and more over a few kelvin, and
///   a few hundredths of a bar of ΔP timing error is taken up by a trace of it (the Coulomb-friction plant served at
///   5 ms once gave 0.00034 L/min/bar, 1.7 % of the model's): an added leakage (or slip's equivalent) below
///   `leak_min_ratio` of the model's, or taking less than `leak_min_flow_share` of the motor's flow, is not a
///   leak.
pub(super) fn resolved(id: &str, candidate: &PlantModel, current: &PlantModel, s: &Series, opts: &Options) -> bool {
    let e = &candidate.effects;
    match id {
        "dead_time" => e.dead_time.is_none_or(|d| d.ms >= 1e3 / s.sample_hz),
        "entrained_air" => {
            let nominal_bulk = current.hydraulics.as_ref().map_or(f64::INFINITY, |h| h.bulk_modulus_bar);
            e.entrained_air.is_none_or(|a| a.bulk_modulus_bar <= opts.air_max_modulus_ratio * nominal_bulk)
        }
        "internal_leakage" | "motor_slip" => {
            let nominal_leak = current.hydraulics.as_ref().map_or(0.0, |h| h.leakage_l_min_per_bar);
            let added = match id {
                "internal_leakage" => e.internal_leakage.map(|l| l.l_min_per_bar),
                _ => e.motor_slip.and_then(|k| slip_as_leakage(candidate, k.rpm_per_nm)),
            };
            let floor = (opts.leak_min_ratio * nominal_leak)
                .max(opts.leak_min_flow_share * flow_per_bar(current, s).unwrap_or(0.0));
            added.is_none_or(|c| c >= floor)
        }
        _ => true,
    }
}

/// Whether dry-friction candidate `id` brings the viscous friction back within `viscous_plausible_factor` of the
/// nominal model's, from beyond it in `current`: the sign that the dry term was missing (`Options`). Never with
/// `min_relative_drop` infinite (nothing is to be named).
pub(super) fn restores_viscous(
    id: &str,
    candidate: &PlantModel,
    current: &PlantModel,
    nominal: &PlantModel,
    opts: &Options,
) -> bool {
    ["coulomb_friction", "stribeck_friction"].contains(&id)
        && nominal.motor.viscous_nm_s_rad > 0.0
        && opts.min_relative_drop.is_finite()
        && !viscous_plausible(current, nominal, opts)
        && viscous_plausible(candidate, nominal, opts)
}

/// Whether `m`'s B lies within `viscous_plausible_factor` of the nominal model's.
pub(super) fn viscous_plausible(m: &PlantModel, nominal: &PlantModel, opts: &Options) -> bool {
    let (b0, f) = (nominal.motor.viscous_nm_s_rad, opts.viscous_plausible_factor);
    (b0 / f..=b0 * f).contains(&m.motor.viscous_nm_s_rad)
}

/// The motor's mean flow over the recording's mean |ΔP| (L/min/bar): the leakage coefficient that would take the
/// whole flow.
fn flow_per_bar(m: &PlantModel, s: &Series) -> Option<f64> {
    let d_m = crate::units::cm3_per_rev_to_m3_per_rad(m.motor.displacement_cm3?);
    let mean_abs = |v: &[f64]| {
        let (sum, n) = v.iter().filter(|x| x.is_finite()).fold((0.0, 0usize), |(a, n), x| (a + x.abs(), n + 1));
        (n > 0).then(|| sum / n as f64)
    };
    let flow_m3_s = d_m * mean_abs(&s.omega_f)?;
    let dp_bar = mean_abs(s.dp_bar.as_deref()?)?;
    (dp_bar > 0.0).then(|| flow_m3_s / crate::units::l_min_per_bar_to_si(1.0) / crate::units::bar_to_pa(dp_bar))
}

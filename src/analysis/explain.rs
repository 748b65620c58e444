//! The analysis's words: what a finding means physically, which effects the recording cannot tell apart, and
//! which parameters it leaves undetermined.

use crate::plant::PlantModel;
use crate::plant::effects::Effects;
use crate::units::cm3_per_rev_to_m3_per_rad;

use super::series::{Family, Series};
use super::{Ambiguity, NotIdentified, search, signal};

/// Plain-language physics and evidence for a finding.
pub(super) fn explain(id: &str, m: &PlantModel, s: &Series, before: f64, after: f64) -> String {
    let e = &m.effects;
    let gain = gain_text(s, before, after);
    // with the load unknown the speed is measured, not predicted: the effects show in the pressure it gives
    if s.family == Family::Flow
        && let Some(text) = explain_flow(id, e, &gain)
    {
        return text;
    }
    let effort = if s.family == Family::Torque { "drive torque" } else { "ΔP" };
    explain_plant(id, e, effort, gain)
}

/// The validation error before and after, and the measure it is taken in.
fn gain_text(s: &Series, before: f64, after: f64) -> String {
    let measure = if s.family == Family::Flow {
        "geometric mean of the ΔP and drive-frequency NRMSE, the speed noise's share taken out"
    } else {
        "root mean squared NRMSE"
    };
    format!("validation error {:.3} → {:.3} ({measure}) on data never used for fitting", before.sqrt(), after.sqrt())
}

/// With the load unknown: how a flow-balance effect shows in the pressure and the drive frequency.
fn explain_flow(id: &str, e: &Effects, gain: &str) -> Option<String> {
    match id {
        "internal_leakage" => Some(format!(
            "the pump/motor leak {:.4} L/min per bar more than the model says: for the measured pump and \
                 motor speeds the model builds more pressure than was measured, in proportion to ΔP; {gain}",
            e.internal_leakage.map_or(0.0, |c| c.l_min_per_bar)
        )),
        "motor_slip" => Some(format!(
            "the induction motor slips {:.3} rpm per N·m of pump torque: the pump delivers less than the drive \
                 frequency says, so less pressure builds than the model predicts, in proportion to ΔP; {gain}",
            e.motor_slip.map_or(0.0, |c| c.rpm_per_nm)
        )),
        "dead_time" => Some(format!(
            "the drive answers the setpoint {:.1} ms later than the model: the drive frequency read back lags \
                 the drive model run from the setpoint after every change; {gain}",
            e.dead_time.map_or(0.0, |c| c.ms)
        )),
        _ => None,
    }
}

/// How an effect shows in the free run of the whole plant (or of the mechanics from a measured torque).
fn explain_plant(id: &str, e: &Effects, effort: &str, gain: String) -> String {
    match id {
        "coulomb_friction" => format!(
            "dry friction of {:.3} N·m opposes the motion whatever the speed: the model needed that much more {effort} \
             in the direction of motion, changing sign with the speed; {gain}",
            e.coulomb_friction.map_or(0.0, |c| c.torque_nm)
        ),
        "stribeck_friction" => {
            let (ts, ws) = e.stribeck_friction.map_or((0.0, 0.0), |x| (x.breakaway_nm, x.speed_rad_s));
            format!(
                "extra friction at low speed (breakaway {ts:.3} N·m, fading above about {ws:.2} rad/s): the {effort} \
                 residual is largest when starting and stopping; {gain}"
            )
        }
        "torque_offset" => format!(
            "a constant torque of {:.3} N·m acts on the shaft (an unmodelled constant load, or an offset of the \
             pressure/torque measurement): the {effort} residual is a bias at all speeds; {gain}",
            e.torque_offset.map_or(0.0, |c| c.torque_nm)
        ),
        "internal_leakage" => format!(
            "the pump/motor leak {:.4} L/min per bar more than the model says: the speed falls short in proportion to \
             ΔP at steady flow; {gain}",
            e.internal_leakage.map_or(0.0, |c| c.l_min_per_bar)
        ),
        "dead_time" => format!(
            "the drive answers the setpoint {:.1} ms later than the model: speed and pressure lag after every setpoint \
             change; {gain}",
            e.dead_time.map_or(0.0, |c| c.ms)
        ),
        "entrained_air" => format!(
            "the oil is softer than the model's: effective bulk modulus {:.0} bar (air in the oil), so pressure builds \
             more slowly and rings at a lower frequency after steps; {gain}",
            e.entrained_air.map_or(0.0, |c| c.bulk_modulus_bar)
        ),
        "motor_slip" => format!(
            "the induction motor slips {:.3} rpm per N·m of pump torque: pump speed, hence flow and motor speed, fall \
             with load; {gain}",
            e.motor_slip.map_or(0.0, |c| c.rpm_per_nm)
        ),
        _ => gain,
    }
}

/// The two effects that are one term of the flow balance.
const TWINS: [&str; 2] = ["internal_leakage", "motor_slip"];

/// Leakage that removes the same flow as a motor slip of `rpm_per_nm` (they enter the flow balance identically:
/// C = D_p² k_s), in L/min per bar.
pub fn slip_as_leakage(m: &PlantModel, rpm_per_nm: f64) -> Option<f64> {
    let d_p = cm3_per_rev_to_m3_per_rad(m.pump.as_ref()?.displacement_cm3);
    let k_s = crate::units::rpm_to_rad_s(rpm_per_nm);
    Some(d_p * d_p * k_s / crate::units::l_min_per_bar_to_si(1.0))
}

pub(super) fn ambiguities(named: &[&str], ties: &[(&str, &str)], m: &PlantModel, s: &Series) -> Vec<Ambiguity> {
    let mut out: Vec<Ambiguity> = Vec::new();
    let mut push = |a: &str, b: &str, text: String| {
        let mut effects = vec![a.to_string(), b.to_string()];
        effects.sort();
        if !out.iter().any(|x| x.effects == effects) {
            out.push(Ambiguity { effects, explanation: text });
        }
    };
    let has = |id: &str| named.contains(&id);
    // Leakage and slip remove flow in proportion to ΔP in exactly the same way; no signal here separates them.
    if has("internal_leakage") || has("motor_slip") {
        let per_rpm = slip_as_leakage(m, 1.0).unwrap_or(f64::NAN);
        let text = match (m.effects.internal_leakage, m.effects.motor_slip) {
            (Some(l), None) => format!(
                "leakage and motor slip both take flow in proportion to ΔP (C = D_p²·k_s); without a pump-speed \
                 measurement they are the same: {:.4} L/min/bar of leakage equals a slip of {:.3} rpm/N·m",
                l.l_min_per_bar,
                l.l_min_per_bar / per_rpm
            ),
            (None, Some(k)) => format!(
                "leakage and motor slip both take flow in proportion to ΔP (C = D_p²·k_s); without a pump-speed \
                 measurement they are the same: a slip of {:.3} rpm/N·m equals {:.4} L/min/bar of leakage",
                k.rpm_per_nm,
                k.rpm_per_nm * per_rpm
            ),
            _ => "leakage and motor slip both take flow in proportion to ΔP (C = D_p²·k_s); only their sum is \
                  determined without a pump-speed measurement"
                .to_string(),
        };
        push("internal_leakage", "motor_slip", text);
    }
    // Dry friction and a constant bias differ only where the speed changes sign.
    if has("coulomb_friction") != has("torque_offset") {
        let rows: Vec<usize> = (0..s.split).collect();
        let sgn: Vec<f64> = rows.iter().map(|&k| s.sign(s.omega_f[k])).collect();
        let cos = signal::cosine(&sgn, &vec![1.0; sgn.len()]).abs();
        if cos > 0.95 {
            let back = sgn.iter().filter(|v| **v < -0.5).count() as f64 / sgn.len() as f64;
            let fwd = sgn.iter().filter(|v| **v > 0.5).count() as f64 / sgn.len() as f64;
            push(
                "coulomb_friction",
                "torque_offset",
                format!(
                    "the speed hardly reverses ({:.1} % of the fitting data forward, {:.1} % backward): dry friction \
                     and a constant load bias look the same except near standstill, so the choice rests on few samples",
                    100.0 * fwd,
                    100.0 * back
                ),
            );
        }
    }
    // leakage and slip are one term: when either is named, the pair is already reported above
    let covered = |id: &str| has(id) || (TWINS.contains(&id) && TWINS.iter().any(|t| has(t)));
    for (a, b) in ties {
        if !(covered(a) && covered(b)) {
            push(
                a,
                b,
                format!(
                    "{a} and {b} improve the validation error almost equally on this recording; {a} was kept as the \
                     slightly better one, but the data barely distinguish them"
                ),
            );
        }
    }
    // With the load unknown, whatever the torque balance lacks is absorbed by the load.
    if s.family == Family::Flow {
        out.push(Ambiguity {
            effects: search::TORQUE_SIDE.iter().map(|e| e.to_string()).collect(),
            explanation: "load unknown: the recording has no `load_nm`, and dry friction, low-speed friction and a \
                          constant torque act in the torque balance beside the load, which takes up whatever they \
                          are; they are neither named nor ruled out (a `load_nm` column, or a known load such as a \
                          run with the load uncoupled, would separate them)"
                .to_string(),
        });
    }
    out
}

/// What the recording cannot determine. With the load unknown: J and B (the torque balance is not fitted).
pub(super) fn not_identified(s: &Series) -> Vec<NotIdentified> {
    let mut out = Vec::new();
    if s.family == Family::Flow {
        out.push(NotIdentified {
            parameters: vec!["inertia_kg_m2".into(), "viscous_nm_s_rad".into()],
            reason: "load unknown: the torque balance D_m·ΔP = J·dω/dt + B·ω + friction + T_L has T_L as a free \
                     signal, so B·ω cannot be told from a load that follows the speed, nor J·dω/dt from a load that \
                     changes while the speed does; J and B keep the nominal model's values. The flow balance \
                     (leakage, slip, bulk modulus, dead time) needs neither"
                .into(),
        });
        if s.setpoint_hz.is_none() {
            out.push(NotIdentified {
                parameters: vec!["dead_time.ms".into()],
                reason: "no setpoint was recorded (`f_set_hz` empty, e.g. monitor mode): the delay between command \
                         and drive cannot be measured"
                    .into(),
            });
        }
    }
    out
}

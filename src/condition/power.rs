//! Where a drive's power goes: PHYSICS.md §1's plant read as a power budget, per sample, and its energies
//! integrated over time (PURE).
//!
//! The budget, in PHYSICS.md's notation (ΔP = p_in − p_out, ω_sync = 2π f / pole_pairs, T_p = D_p ΔP):
//!
//! ```text
//! input (air gap)      P_in    = T_p · ω_sync
//! slip                 P_slip  = T_p · (ω_sync − ω_pump) = k_s · (D_p ΔP)²
//! pump, hydraulic      P_pump  = D_p ΔP · ω_pump                   = P_in − P_slip
//! leakage              P_leak  = C_L · ΔP²   (nominal C_L0 and internal_leakage apart)
//! motor, hydraulic     P_motor = D_m ΔP · ω                        = P_pump − P_leak − (V/β) ΔP dp_in/dt
//! viscous friction     P_visc  = B · ω²
//! dry friction         P_dry   = (T_c + (T_s − T_c) e^{−(ω/ω_s)²}) · sgn(ω) · ω
//! load                 P_load  = T_L · ω                            = P_motor − P_visc − P_dry − J ω dω/dt
//! ```
//!
//! Where the register map reads the drive's output power P_drive (`[drives.registers.drive_power_w]`), the
//! overall efficiency is η = ∫ P_load dt / ∫ P_drive dt over the samples that carry it: everything between the
//! drive's terminals and the load (the motor's copper and iron, slip, pump, leakage, friction) in one ratio.
//!
//! The compression term and the kinetic term store energy and give it back: over a run they sum to the change of
//! the stored energy, so the integrated budget closes without them. The load torque is the estimator's resisting
//! torque split by the model: `T̂_L + B̂·ω̂` is what the estimator sees resist the motor beside `J dω/dt` whichever
//! way it splits it between load and viscous friction, so `T_L = T̂_L + B̂ ω̂ − B ω̂ − T_dry(ω̂)` with the model's B and
//! dry friction (a constant torque offset cannot be told from a constant load: it stays in the load).
//!
//! The model is the drive's nominal model with the effects the last condition check fitted put in ([`PowerModel`]);
//! the loss of an effect *above the nominal model* is its loss with the fitted effects less its loss with the
//! nominal model alone (what the wear costs).

use std::collections::BTreeMap;
use std::f64::consts::PI;

use serde::Serialize;

use crate::plant::dynamics::{Coefficients, Mechanics};
use crate::plant::{Effects, PlantModel};
use crate::units::{bar_to_pa, l_min_per_bar_to_si};

/// Joules in a kilowatt-hour.
pub const J_PER_KWH: f64 = 3.6e6;
/// Seconds in a day, and in a (365-day) year.
pub const S_PER_DAY: f64 = 86_400.0;
pub const DAYS_PER_YEAR: f64 = 365.0;
/// A gap between samples longer than this is not integrated across (a link outage: the power then is unknown).
pub const MAX_GAP_S: f64 = 0.1;

/// The coefficients the budget needs, in SI.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Budget {
    pub pole_pairs: f64,
    pub pump_m3_rad: f64,
    pub motor_m3_rad: f64,
    /// `hydraulics.leakage_l_min_per_bar` (m³/(s·Pa)).
    pub nominal_leakage_si: f64,
    /// `internal_leakage` (m³/(s·Pa)).
    pub internal_leakage_si: f64,
    pub slip_rad_s_per_nm: f64,
    pub mechanics: Mechanics,
}

impl Budget {
    /// From a model with its hydraulic sections; None without them (a torque-only model has no budget).
    pub fn of(model: &PlantModel) -> Option<Budget> {
        let c = Coefficients::from_model(model).ok()?;
        let nominal = l_min_per_bar_to_si(model.hydraulic().ok()?.hydraulics.leakage_l_min_per_bar);
        Some(Budget {
            pole_pairs: c.pole_pairs,
            pump_m3_rad: c.pump_m3_rad,
            motor_m3_rad: c.motor_m3_rad,
            nominal_leakage_si: nominal,
            internal_leakage_si: (c.leakage_si - nominal).max(0.0),
            slip_rad_s_per_nm: c.slip_rad_s_per_nm,
            mechanics: c.mechanics,
        })
    }

    /// Dry friction torque at ω (Coulomb and Stribeck, no offset), opposing motion.
    fn dry_nm(&self, omega: f64) -> f64 {
        Mechanics { offset_nm: 0.0, ..self.mechanics }.extra_torque_nm(omega)
    }

    /// The budget of one operating point.
    pub fn flows(&self, x: &Operating) -> Flows {
        let dp = bar_to_pa(x.dp_bar);
        let w = x.omega_rad_s;
        let pump_torque = self.pump_m3_rad * dp;
        let w_sync = 2.0 * PI * x.f_drive_hz / self.pole_pairs;
        let slip_w = self.slip_rad_s_per_nm * pump_torque * pump_torque;
        let viscous_w = self.mechanics.viscous_nm_s_rad * w * w;
        let dry = self.dry_nm(w);
        let resisting = x.resisting_torque_nm - self.mechanics.viscous_nm_s_rad * w - dry;
        Flows {
            input_w: pump_torque * w_sync,
            slip_w,
            pump_hydraulic_w: pump_torque * w_sync - slip_w,
            leakage_w: self.nominal_leakage_si * dp * dp,
            internal_leakage_w: self.internal_leakage_si * dp * dp,
            motor_hydraulic_w: self.motor_m3_rad * dp * w,
            viscous_w,
            dry_friction_w: dry * w,
            load_w: resisting * w,
        }
    }
}

/// One operating point as the service knows it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Operating {
    pub t_s: f64,
    /// p_in − p_out (bar).
    pub dp_bar: f64,
    /// Drive output frequency read back (Hz).
    pub f_drive_hz: f64,
    /// Motor speed: the estimator's ω̂ (rad/s).
    pub omega_rad_s: f64,
    /// `T̂_L + B̂ ω̂`: all the estimator sees resist the motor beside inertia (N·m).
    pub resisting_torque_nm: f64,
    /// The drive's output power (W) as its register reads it; None where the map does not read it.
    pub drive_power_w: Option<f64>,
}

crate::units::columns! {
    /// The power budget of a moment (W), or, summed over time, its energies (J).
    #[derive(Debug, Clone, Copy, PartialEq, Default, Serialize)]
    pub struct Flows {
        /// Into the pump at the motor's synchronous speed (the drive's output, less its own losses).
        pub input_w: f64,
        pub slip_w: f64,
        pub pump_hydraulic_w: f64,
        /// Leakage of the nominal model (`hydraulics.leakage_l_min_per_bar`).
        pub leakage_w: f64,
        /// Leakage beyond it (`internal_leakage`).
        pub internal_leakage_w: f64,
        /// Into the hydraulic motor.
        pub motor_hydraulic_w: f64,
        pub viscous_w: f64,
        pub dry_friction_w: f64,
        /// To the load.
        pub load_w: f64,
    }
}

impl Flows {
    fn add_scaled(&mut self, f: &Flows, k: f64) {
        let mut v = self.values();
        for (a, b) in v.iter_mut().zip(f.values()) {
            *a += k * b;
        }
        *self = Flows::from_values(v);
    }

    fn from_values(v: [f64; 9]) -> Flows {
        let [
            input_w,
            slip_w,
            pump_hydraulic_w,
            leakage_w,
            internal_leakage_w,
            motor_hydraulic_w,
            viscous_w,
            dry,
            load_w,
        ] = v;
        Flows {
            input_w,
            slip_w,
            pump_hydraulic_w,
            leakage_w,
            internal_leakage_w,
            motor_hydraulic_w,
            viscous_w,
            dry_friction_w: dry,
            load_w,
        }
    }

    /// Volumetric efficiency: the share of the pump's hydraulic power not lost to leakage.
    pub fn volumetric_efficiency(&self) -> Option<f64> {
        ratio(self.pump_hydraulic_w - self.leakage_w - self.internal_leakage_w, self.pump_hydraulic_w)
    }

    /// Mechanical efficiency of the motor: the share of its hydraulic power not lost to friction.
    pub fn mechanical_efficiency(&self) -> Option<f64> {
        ratio(self.motor_hydraulic_w - self.viscous_w - self.dry_friction_w, self.motor_hydraulic_w)
    }
}

/// a / b when b is clearly positive, clamped to 0…1 (noise at standstill must not give 140 %).
fn ratio(a: f64, b: f64) -> Option<f64> {
    (b > 1e-9 && a.is_finite()).then(|| (a / b).clamp(0.0, 1.0))
}

/// The drive's nominal model with the fitted effects put in, and the nominal model alone.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PowerModel {
    pub fitted: Budget,
    pub nominal: Budget,
}

impl PowerModel {
    /// `nominal` with `fitted` effects (a condition check's findings) put in, each replacing the nominal's of the
    /// same id; None for a model without the hydraulic sections.
    pub fn new(nominal: &PlantModel, fitted: &Effects) -> Option<PowerModel> {
        let mut with = nominal.clone();
        with.effects = merge(&nominal.effects, fitted);
        Some(PowerModel { fitted: Budget::of(&with)?, nominal: Budget::of(nominal)? })
    }

    /// The loss of each effect above the nominal model at `x` (W): id → watts, for the effects that cost power.
    pub fn above_nominal(&self, x: &Operating) -> BTreeMap<&'static str, f64> {
        let (f, n) = (self.fitted.flows(x), self.nominal.flows(x));
        // the Coulomb part alone, and the Stribeck part as what it adds to it
        let coulomb = |b: &Budget| {
            Mechanics { stribeck: None, offset_nm: 0.0, ..b.mechanics }.extra_torque_nm(x.omega_rad_s) * x.omega_rad_s
        };
        let stribeck = |b: &Budget| b.dry_nm(x.omega_rad_s) * x.omega_rad_s - coulomb(b);
        let mut out = BTreeMap::new();
        out.insert("internal_leakage", f.internal_leakage_w + f.leakage_w - n.internal_leakage_w - n.leakage_w);
        out.insert("coulomb_friction", coulomb(&self.fitted) - coulomb(&self.nominal));
        out.insert("stribeck_friction", stribeck(&self.fitted) - stribeck(&self.nominal));
        out.insert("motor_slip", f.slip_w - n.slip_w);
        out
    }
}

/// `base` with every effect `over` switches on replacing base's.
pub fn merge(base: &Effects, over: &Effects) -> Effects {
    Effects {
        coulomb_friction: over.coulomb_friction.or(base.coulomb_friction),
        stribeck_friction: over.stribeck_friction.or(base.stribeck_friction),
        torque_offset: over.torque_offset.or(base.torque_offset),
        internal_leakage: over.internal_leakage.or(base.internal_leakage),
        dead_time: over.dead_time.or(base.dead_time),
        entrained_air: over.entrained_air.or(base.entrained_air),
        motor_slip: over.motor_slip.or(base.motor_slip),
    }
}

/// The effects a condition check's `findings` name (the analysis JSON's shape), with their fitted parameters; a
/// finding that does not parse (a parameter missing) is left out.
pub fn effects_of_findings(findings: &serde_json::Value) -> Effects {
    let mut e = Effects::default();
    for f in findings.as_array().into_iter().flatten() {
        let Some(id) = f["effect"].as_str() else { continue };
        let one = serde_json::json!({ id: f["parameters"] });
        if let Ok(x) = serde_json::from_value::<Effects>(one) {
            e = merge(&e, &x);
        }
    }
    e
}

/// The energies of a drive, integrated sample by sample (rectangle rule on the later sample: the service's rows
/// are evenly spaced, and a gap over [`MAX_GAP_S`] is skipped).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Ledger {
    /// Seconds integrated.
    pub span_s: f64,
    /// Energy of each flow (J).
    pub energy_j: Flows,
    /// Energy lost to each effect above the nominal model (J).
    pub above_nominal_j: BTreeMap<&'static str, f64>,
    /// The mean power over the last [`Ledger::add_all`] call (W), and its span.
    pub recent: Flows,
    pub recent_s: f64,
    /// Over the samples that carry the drive's output power: its energy, and the load's over the same samples (J).
    pub drive: Option<DriveEnergy>,
    /// The drive's mean output power over the last [`Ledger::add_all`] call (W), where read.
    pub recent_drive_w: Option<f64>,
    last_t_s: Option<f64>,
}

/// The drive's output energy and the load's, both over the samples that carry the drive's output power.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct DriveEnergy {
    pub span_s: f64,
    pub drive_j: f64,
    pub load_j: f64,
}

impl DriveEnergy {
    /// Overall efficiency: the share of the drive's output energy that reached the load.
    pub fn overall_efficiency(&self) -> Option<f64> {
        ratio(self.load_j, self.drive_j)
    }
}

impl Ledger {
    /// The time of the last sample taken.
    pub fn last_t_s(&self) -> Option<f64> {
        self.last_t_s
    }

    /// Takes the operating points after the last one taken (older ones are skipped), in time order.
    pub fn add_all(&mut self, model: &PowerModel, points: impl IntoIterator<Item = Operating>) {
        let mut recent = Flows::default();
        let mut recent_s = 0.0;
        let mut recent_drive = DriveEnergy::default();
        for x in points {
            let Some(prev) = self.last_t_s else {
                self.last_t_s = Some(x.t_s);
                continue;
            };
            // older or the same (or NaN): taken already
            if x.t_s.partial_cmp(&prev) != Some(std::cmp::Ordering::Greater) {
                continue;
            }
            self.last_t_s = Some(x.t_s);
            let dt = x.t_s - prev;
            let finite = [x.dp_bar, x.f_drive_hz, x.omega_rad_s, x.resisting_torque_nm].iter().all(|v| v.is_finite());
            if dt > MAX_GAP_S || !finite {
                continue;
            }
            let f = model.fitted.flows(&x);
            self.energy_j.add_scaled(&f, dt);
            recent.add_scaled(&f, dt);
            for (id, w) in model.above_nominal(&x) {
                *self.above_nominal_j.entry(id).or_insert(0.0) += w * dt;
            }
            if let Some(p) = x.drive_power_w.filter(|p| p.is_finite()) {
                for d in [self.drive.get_or_insert_default(), &mut recent_drive] {
                    d.span_s += dt;
                    d.drive_j += p * dt;
                    d.load_j += f.load_w * dt;
                }
            }
            self.span_s += dt;
            recent_s += dt;
        }
        if recent_s > 0.0 {
            self.recent = Flows::default();
            self.recent.add_scaled(&recent, 1.0 / recent_s);
            self.recent_s = recent_s;
            self.recent_drive_w = (recent_drive.span_s > 0.0).then(|| recent_drive.drive_j / recent_drive.span_s);
        }
    }

    /// The report `/api/status`, `/metrics` and MQTT show; `price_per_kwh` from the config, if any.
    pub fn report(&self, price_per_kwh: Option<f64>) -> EnergyReport {
        let per_day = |j: f64| if self.span_s > 0.0 { j / self.span_s * S_PER_DAY / J_PER_KWH } else { 0.0 };
        let effects = self
            .above_nominal_j
            .iter()
            .filter(|(_, j)| **j != 0.0)
            .map(|(id, &j)| {
                let kwh_per_day = per_day(j);
                EffectCost {
                    effect: id.to_string(),
                    power_w: if self.span_s > 0.0 { j / self.span_s } else { 0.0 },
                    energy_j: j,
                    kwh_per_day,
                    cost_per_day: price_per_kwh.map(|p| p * kwh_per_day),
                    cost_per_year: price_per_kwh.map(|p| p * kwh_per_day * DAYS_PER_YEAR),
                }
            })
            .collect();
        let e = &self.energy_j;
        EnergyReport {
            span_s: self.span_s,
            up_to_t_s: self.last_t_s,
            power_w: self.recent,
            energy_j: self.energy_j,
            kwh_per_day: Flows::from_values(e.values().map(per_day)),
            volumetric_efficiency: e.volumetric_efficiency(),
            mechanical_efficiency: e.mechanical_efficiency(),
            drive_power_w: self.recent_drive_w,
            drive_energy_j: self.drive.map(|d| d.drive_j),
            overall_efficiency: self.drive.and_then(|d| d.overall_efficiency()),
            effects,
            energy_price_per_kwh: price_per_kwh,
        }
    }
}

/// What one effect above the nominal model costs.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EffectCost {
    pub effect: String,
    /// Mean power lost over the span integrated (W).
    pub power_w: f64,
    pub energy_j: f64,
    pub kwh_per_day: f64,
    /// With `energy_price_per_kwh` in the config; null without.
    pub cost_per_day: Option<f64>,
    pub cost_per_year: Option<f64>,
}

/// A drive's `energy` in `/api/status`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EnergyReport {
    /// Seconds of data integrated (since the service started, gaps left out).
    pub span_s: f64,
    /// The service time (`t_s`) of the last sample taken: the report is up to date with the rows up to it.
    pub up_to_t_s: Option<f64>,
    /// Mean power of each flow over the last integration step (about a second).
    pub power_w: Flows,
    /// Energy of each flow since the start.
    pub energy_j: Flows,
    /// Each flow's mean rate over the span, as kWh per day.
    pub kwh_per_day: Flows,
    /// Over the span; null while nothing flowed.
    pub volumetric_efficiency: Option<f64>,
    pub mechanical_efficiency: Option<f64>,
    /// The drive's output power (W), mean over the last integration step, and its energy since the start (J),
    /// where `[drives.registers.drive_power_w]` reads it; null where not read.
    pub drive_power_w: Option<f64>,
    pub drive_energy_j: Option<f64>,
    /// The load's energy over the drive's output energy, over the samples that carry it; null where not read.
    pub overall_efficiency: Option<f64>,
    /// The effects above the nominal model that cost power, and what.
    pub effects: Vec<EffectCost>,
    pub energy_price_per_kwh: Option<f64>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[track_caller]
    fn assert_close(a: f64, b: f64, rel: f64) {
        assert!((a - b).abs() <= rel * a.abs().max(b.abs()), "{a} against {b} (relative {rel})");
    }
    use crate::plant::effects::{CoulombFriction, InternalLeakage, MotorSlip};

    fn at(dp_bar: f64, f_hz: f64, omega: f64, resisting: f64) -> Operating {
        Operating {
            t_s: 0.0,
            dp_bar,
            f_drive_hz: f_hz,
            omega_rad_s: omega,
            resisting_torque_nm: resisting,
            drive_power_w: None,
        }
    }

    #[test]
    fn the_budget_of_the_reference_plant_by_hand() {
        let m = PlantModel::reference();
        let b = Budget::of(&m).expect("hydraulic");
        // 100 bar, 25 Hz on 2 pole pairs: ω_sync = 78.54 rad/s; D_p = 16 cm³/2π, D_m = 32 cm³/2π
        let x = at(100.0, 25.0, 30.0, 40.0);
        let f = b.flows(&x);
        let dp = 1e7;
        let dpump = 16e-6 / (2.0 * PI);
        let dm = 32e-6 / (2.0 * PI);
        assert_close(f.input_w, dpump * dp * 2.0 * PI * 25.0 / 2.0, 1e-12);
        assert_eq!(f.slip_w, 0.0);
        assert_close(f.leakage_w, 0.02e-3 / 60.0 / 1e5 * dp * dp, 1e-12);
        assert_close(f.motor_hydraulic_w, dm * dp * 30.0, 1e-12);
        assert_close(f.viscous_w, 0.04 * 900.0, 1e-12);
        assert_close(f.load_w, (40.0 - 0.04 * 30.0) * 30.0, 1e-12);
        let eta_v = f.volumetric_efficiency().expect("flows");
        assert_close(eta_v, 1.0 - f.leakage_w / f.input_w, 1e-12);
    }

    #[test]
    fn an_effect_costs_its_loss_above_the_nominal_model() {
        let nominal = PlantModel::reference();
        let fitted = Effects {
            internal_leakage: Some(InternalLeakage { l_min_per_bar: 0.03 }),
            coulomb_friction: Some(CoulombFriction { torque_nm: 2.0 }),
            motor_slip: Some(MotorSlip { rpm_per_nm: 1.5 }),
            ..Effects::default()
        };
        let pm = PowerModel::new(&nominal, &fitted).expect("hydraulic");
        let x = at(100.0, 25.0, 30.0, 40.0);
        let above = pm.above_nominal(&x);
        assert_close(above["internal_leakage"], 0.03e-3 / 60.0 / 1e5 * 1e14, 1e-12);
        // tanh(30/0.05) is 1 to double precision
        assert_close(above["coulomb_friction"], 2.0 * 30.0, 1e-9);
        let tp = 16e-6 / (2.0 * PI) * 1e7;
        assert_close(above["motor_slip"], 1.5 * 2.0 * PI / 60.0 * tp * tp, 1e-12);
        assert_eq!(above["stribeck_friction"], 0.0);
        // the dry friction leaves the load: 40 − B ω − T_c
        assert_close(pm.fitted.flows(&x).load_w, (40.0 - 1.2 - 2.0) * 30.0, 1e-9);
    }

    #[test]
    fn the_ledger_integrates_skips_gaps_and_prices_an_effect() {
        let nominal = PlantModel::reference();
        let fitted = Effects { internal_leakage: Some(InternalLeakage { l_min_per_bar: 0.03 }), ..Effects::default() };
        let pm = PowerModel::new(&nominal, &fitted).expect("hydraulic");
        let mut l = Ledger::default();
        let mut pts: Vec<Operating> =
            (0..=1000).map(|k| Operating { t_s: k as f64 * 1e-3, ..at(100.0, 25.0, 30.0, 40.0) }).collect();
        // a 0.5 s outage, then 1 s more
        pts.extend((0..=1000).map(|k| Operating { t_s: 1.5 + k as f64 * 1e-3, ..at(100.0, 25.0, 30.0, 40.0) }));
        l.add_all(&pm, pts.iter().copied());
        assert_close(l.span_s, 2.0, 1e-9);
        l.add_all(&pm, pts.iter().copied()); // the same points again: nothing new
        assert_close(l.span_s, 2.0, 1e-9);
        let leak_w = 0.03e-3 / 60.0 / 1e5 * 1e14;
        assert_close(l.energy_j.internal_leakage_w, 2.0 * leak_w, 1e-9);
        let r = l.report(Some(0.25));
        assert_eq!(r.effects.len(), 1, "{:?}", r.effects);
        let e = &r.effects[0];
        assert_eq!(e.effect, "internal_leakage");
        assert_close(e.kwh_per_day, leak_w * 24.0 / 1e3, 1e-9);
        assert_close(e.cost_per_year.expect("priced"), 0.25 * leak_w * 24.0 / 1e3 * 365.0, 1e-9);
        assert!(l.report(None).effects[0].cost_per_day.is_none());
        assert_eq!((r.drive_power_w, r.drive_energy_j, r.overall_efficiency), (None, None, None), "not read");
    }

    #[test]
    fn the_overall_efficiency_is_the_loads_share_of_the_drives_energy_where_it_was_read() {
        let pm = PowerModel::new(&PlantModel::reference(), &Effects::default()).expect("hydraulic");
        let x = at(100.0, 25.0, 30.0, 40.0);
        let load_w = pm.fitted.flows(&x).load_w;
        let mut l = Ledger::default();
        // 1 s without the drive's power, then 1 s at 1500 W, then 1 s at 1000 W
        let pts = (0..=3000).map(|k| Operating {
            t_s: k as f64 * 1e-3,
            drive_power_w: match k {
                0..=1000 => None,
                1001..=2000 => Some(1500.0),
                _ => Some(1000.0),
            },
            ..x
        });
        l.add_all(&pm, pts.take(2001));
        let r = l.report(None);
        assert_close(r.drive_energy_j.expect("read"), 1500.0, 1e-9);
        assert_close(r.overall_efficiency.expect("read"), load_w / 1500.0, 1e-9);
        let pts = (2001..=3000).map(|k| Operating { t_s: k as f64 * 1e-3, drive_power_w: Some(1000.0), ..x });
        l.add_all(&pm, pts);
        let r = l.report(None);
        assert_close(r.drive_power_w.expect("read"), 1000.0, 1e-9);
        assert_close(r.overall_efficiency.expect("read"), 2.0 * load_w / 2500.0, 1e-9);
        assert_close(l.span_s, 3.0, 1e-9);
    }

    #[test]
    fn findings_become_effects_and_replace_the_nominals() {
        let findings = serde_json::json!([
            {"effect": "internal_leakage", "parameters": {"l_min_per_bar": 0.04}, "explanation": "x"},
            {"effect": "dead_time", "parameters": {"ms": 30.0}},
            {"effect": "stribeck_friction", "parameters": {"breakaway_nm": 3.0}}
        ]);
        let e = effects_of_findings(&findings);
        assert_eq!(e.internal_leakage, Some(InternalLeakage { l_min_per_bar: 0.04 }));
        assert_eq!(e.dead_time.map(|d| d.ms), Some(30.0));
        assert!(e.stribeck_friction.is_none(), "a parameter missing: left out");
        let base = Effects { internal_leakage: Some(InternalLeakage { l_min_per_bar: 0.01 }), ..Effects::default() };
        assert_eq!(merge(&base, &e).internal_leakage, Some(InternalLeakage { l_min_per_bar: 0.04 }));
    }
}

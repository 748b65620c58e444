//! The plant's differential equations (PHYSICS.md §1) in SI, and their RK4 integration with an exact dead time.

use crate::error::KeyError;
use std::collections::VecDeque;
use std::f64::consts::PI;

use super::model::PlantModel;
use crate::units::{bar_to_pa, cm3_per_rev_to_m3_per_rad, l_min_per_bar_to_si, rpm_to_rad_s};

/// Speed scale of the smooth sign function `tanh(ω/0.05)` that keeps friction smooth at standstill.
pub const SIGN_SPEED_RAD_S: f64 = 0.05;
/// The largest internal integration step; well below the hydraulic natural period (≈ 150 ms for the reference plant).
pub const MAX_SUBSTEP_S: f64 = 2e-4;

/// `sgn(ω)` as the model takes it: `tanh(ω/0.05)`.
pub fn smooth_sign(omega_rad_s: f64) -> f64 {
    (omega_rad_s / SIGN_SPEED_RAD_S).tanh()
}

/// The mechanical side: inertia, viscous friction and the friction/offset effects. Enough on its own for a
/// torque-driven recording.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Mechanics {
    pub inertia_kg_m2: f64,
    pub viscous_nm_s_rad: f64,
    pub coulomb_nm: f64,
    /// (breakaway torque T_s, Stribeck speed ω_s), when the effect is on.
    pub stribeck: Option<(f64, f64)>,
    pub offset_nm: f64,
}

impl Mechanics {
    pub fn from_model(model: &PlantModel) -> Mechanics {
        let e = &model.effects;
        Mechanics {
            inertia_kg_m2: model.motor.inertia_kg_m2,
            viscous_nm_s_rad: model.motor.viscous_nm_s_rad,
            coulomb_nm: e.coulomb_friction.map_or(0.0, |c| c.torque_nm),
            stribeck: e.stribeck_friction.map(|s| (s.breakaway_nm, s.speed_rad_s)),
            offset_nm: e.torque_offset.map_or(0.0, |o| o.torque_nm),
        }
    }

    /// Friction and bias torque beyond the viscous term (N·m), opposing motion.
    pub fn extra_torque_nm(&self, omega: f64) -> f64 {
        let sgn = smooth_sign(omega);
        let mut t = self.coulomb_nm * sgn + self.offset_nm;
        if let Some((breakaway, speed)) = self.stribeck {
            t += (breakaway - self.coulomb_nm) * (-(omega / speed).powi(2)).exp() * sgn;
        }
        t
    }

    /// dω/dt for a drive torque and a load torque.
    pub fn acceleration(&self, omega: f64, drive_torque_nm: f64, load_nm: f64) -> f64 {
        (drive_torque_nm - self.viscous_nm_s_rad * omega - load_nm - self.extra_torque_nm(omega)) / self.inertia_kg_m2
    }
}

/// Every coefficient of the hydraulic plant, in SI, with the effects folded in.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Coefficients {
    pub pole_pairs: f64,
    pub ramp_hz_per_s: f64,
    pub time_constant_s: f64,
    pub max_hz: f64,
    /// Pump displacement D_p (m³/rad).
    pub pump_m3_rad: f64,
    /// Motor displacement D_m (m³/rad).
    pub motor_m3_rad: f64,
    pub volume_m3: f64,
    /// Effective bulk modulus β (Pa): the entrained-air value when that effect is on.
    pub bulk_modulus_pa: f64,
    /// Total leakage C_L (m³/(s·Pa)), nominal plus internal_leakage.
    pub leakage_si: f64,
    pub back_pressure_pa: f64,
    /// Slip k_s (rad/s per N·m of pump torque).
    pub slip_rad_s_per_nm: f64,
    pub dead_time_s: f64,
    pub mechanics: Mechanics,
}

impl Coefficients {
    /// From a model that has the hydraulic sections; the missing key otherwise.
    pub fn from_model(model: &PlantModel) -> Result<Coefficients, KeyError> {
        let h = model.hydraulic()?;
        let e = &model.effects;
        let leak = h.hydraulics.leakage_l_min_per_bar + e.internal_leakage.map_or(0.0, |l| l.l_min_per_bar);
        let bulk_bar = e.entrained_air.map_or(h.hydraulics.bulk_modulus_bar, |a| a.bulk_modulus_bar);
        Ok(Coefficients {
            pole_pairs: f64::from(h.drive.pole_pairs),
            ramp_hz_per_s: h.drive.ramp_hz_per_s,
            time_constant_s: h.drive.time_constant_s,
            max_hz: h.drive.max_hz,
            pump_m3_rad: cm3_per_rev_to_m3_per_rad(h.pump.displacement_cm3),
            motor_m3_rad: cm3_per_rev_to_m3_per_rad(h.motor_displacement_cm3),
            volume_m3: h.hydraulics.volume_l * 1e-3,
            bulk_modulus_pa: bar_to_pa(bulk_bar),
            leakage_si: l_min_per_bar_to_si(leak),
            back_pressure_pa: bar_to_pa(h.hydraulics.back_pressure_bar),
            slip_rad_s_per_nm: e.motor_slip.map_or(0.0, |s| rpm_to_rad_s(s.rpm_per_nm)),
            dead_time_s: e.dead_time.map_or(0.0, |d| d.seconds()),
            mechanics: Mechanics::from_model(model),
        })
    }

    /// The time derivative of the state for a drive command (already delayed) and a load.
    pub fn derivative(&self, s: &PlantState, f_cmd_hz: f64, load_nm: f64) -> PlantState {
        let df = ((f_cmd_hz - s.f_hz) / self.time_constant_s).clamp(-self.ramp_hz_per_s, self.ramp_hz_per_s);
        let dp = s.p_in_pa - self.back_pressure_pa;
        let pump_torque = self.pump_m3_rad * dp;
        let omega_pump = 2.0 * PI * s.f_hz / self.pole_pairs - self.slip_rad_s_per_nm * pump_torque;
        let flow = self.pump_m3_rad * omega_pump - self.motor_m3_rad * s.omega_rad_s - self.leakage_si * dp;
        let mut dp_in = self.bulk_modulus_pa / self.volume_m3 * flow;
        if s.p_in_pa <= 0.0 && dp_in < 0.0 {
            dp_in = 0.0;
        }
        let domega = self.mechanics.acceleration(s.omega_rad_s, self.motor_m3_rad * dp, load_nm);
        PlantState { f_hz: df, p_in_pa: dp_in, omega_rad_s: domega }
    }

    /// One classic RK4 step of the drive's frequency alone, of length `h`: the drive's state depends on nothing
    /// but its command, so this is the frequency [`Coefficients::rk4`] gives, to the bit.
    pub fn drive_rk4(&self, f_hz: f64, f_cmd_hz: f64, h: f64) -> f64 {
        let rate = |f: f64| ((f_cmd_hz - f) / self.time_constant_s).clamp(-self.ramp_hz_per_s, self.ramp_hz_per_s);
        let k1 = rate(f_hz);
        let k2 = rate(f_hz + h / 2.0 * k1);
        let k3 = rate(f_hz + h / 2.0 * k2);
        let k4 = rate(f_hz + h * k3);
        f_hz + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    }

    /// One classic RK4 step of length `h`.
    pub fn rk4(&self, s: &PlantState, f_cmd_hz: f64, load_nm: f64, h: f64) -> PlantState {
        let k1 = self.derivative(s, f_cmd_hz, load_nm);
        let k2 = self.derivative(&s.add(&k1, h / 2.0), f_cmd_hz, load_nm);
        let k3 = self.derivative(&s.add(&k2, h / 2.0), f_cmd_hz, load_nm);
        let k4 = self.derivative(&s.add(&k3, h), f_cmd_hz, load_nm);
        let mut next = PlantState {
            f_hz: s.f_hz + h / 6.0 * (k1.f_hz + 2.0 * k2.f_hz + 2.0 * k3.f_hz + k4.f_hz),
            p_in_pa: s.p_in_pa + h / 6.0 * (k1.p_in_pa + 2.0 * k2.p_in_pa + 2.0 * k3.p_in_pa + k4.p_in_pa),
            omega_rad_s: s.omega_rad_s
                + h / 6.0 * (k1.omega_rad_s + 2.0 * k2.omega_rad_s + 2.0 * k3.omega_rad_s + k4.omega_rad_s),
        };
        next.p_in_pa = next.p_in_pa.max(0.0);
        next
    }
}

/// The plant's state: drive frequency, inlet pressure, motor speed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlantState {
    pub f_hz: f64,
    pub p_in_pa: f64,
    pub omega_rad_s: f64,
}

impl PlantState {
    fn add(&self, d: &PlantState, h: f64) -> PlantState {
        PlantState {
            f_hz: self.f_hz + h * d.f_hz,
            p_in_pa: (self.p_in_pa + h * d.p_in_pa).max(0.0),
            omega_rad_s: self.omega_rad_s + h * d.omega_rad_s,
        }
    }
}

/// The plant as a stepping machine: state, time, and the commands still in the dead-time pipeline.
#[derive(Debug, Clone)]
pub struct Plant {
    coefficients: Coefficients,
    state: PlantState,
    t_s: f64,
    /// Commands issued but not yet seen by the drive: (time the drive sees it, frequency).
    pending: VecDeque<(f64, f64)>,
    /// The command the drive currently follows.
    f_cmd_hz: f64,
    /// The last command issued (to skip queueing repeats).
    last_issued_hz: f64,
    max_substep_s: f64,
    /// Plant time from which a wearing model's coefficients are due again.
    next_wear_s: f64,
}

/// How often a wearing plant's coefficients are brought up to date (s of plant time).
pub const WEAR_STEP_S: f64 = 1.0;

impl Plant {
    /// At standstill: no frequency, inlet at back pressure, motor at rest.
    pub fn new(coefficients: Coefficients) -> Plant {
        Plant::with_substep(coefficients, MAX_SUBSTEP_S)
    }

    /// As [`Plant::new`] with a chosen largest internal step (for convergence checks).
    pub fn with_substep(coefficients: Coefficients, max_substep_s: f64) -> Plant {
        Plant {
            state: PlantState { f_hz: 0.0, p_in_pa: coefficients.back_pressure_pa, omega_rad_s: 0.0 },
            coefficients,
            t_s: 0.0,
            pending: VecDeque::new(),
            f_cmd_hz: 0.0,
            last_issued_hz: 0.0,
            max_substep_s,
            next_wear_s: 0.0,
        }
    }

    pub fn state(&self) -> PlantState {
        self.state
    }

    pub fn coefficients(&self) -> &Coefficients {
        &self.coefficients
    }

    pub fn t_s(&self) -> f64 {
        self.t_s
    }

    /// For a model with `[wear]`: once every [`WEAR_STEP_S`] of plant time, the coefficients become those of the
    /// model as worn by now (the state is kept). Nothing for a model that does not wear.
    pub fn wear(&mut self, model: &PlantModel) {
        if !model.wears() || self.t_s < self.next_wear_s {
            return;
        }
        if let Ok(c) = Coefficients::from_model(&model.at(self.t_s)) {
            self.coefficients = c;
        }
        self.next_wear_s = self.t_s + WEAR_STEP_S;
    }

    /// Advances by `dt_s` with the frequency command `f_cmd_hz` issued now (the drive sees it after the dead time,
    /// clamped to 0…max_hz) and the load held at `load_nm`.
    pub fn advance(&mut self, dt_s: f64, f_cmd_hz: f64, load_nm: f64) {
        let cmd = if f_cmd_hz.is_finite() { f_cmd_hz.clamp(0.0, self.coefficients.max_hz) } else { 0.0 };
        if cmd != self.last_issued_hz {
            self.last_issued_hz = cmd;
            if self.coefficients.dead_time_s > 0.0 {
                self.pending.push_back((self.t_s + self.coefficients.dead_time_s, cmd));
            } else {
                self.f_cmd_hz = cmd;
            }
        }
        let t_end = self.t_s + dt_s;
        let eps = 1e-12;
        loop {
            while let Some(&(t_apply, f)) = self.pending.front() {
                if t_apply <= self.t_s + eps {
                    self.f_cmd_hz = f;
                    self.pending.pop_front();
                } else {
                    break;
                }
            }
            let seg_end = self.pending.front().map_or(t_end, |&(t_apply, _)| t_apply.min(t_end));
            let len = seg_end - self.t_s;
            if len > eps {
                let n = (len / self.max_substep_s).ceil().max(1.0);
                let h = len / n;
                for _ in 0..n as usize {
                    self.state = self.coefficients.rk4(&self.state, self.f_cmd_hz, load_nm, h);
                }
            }
            self.t_s = seg_end;
            if seg_end >= t_end - eps {
                self.t_s = t_end;
                break;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn reference() -> Coefficients {
        Coefficients::from_model(&PlantModel::reference()).expect("hydraulic")
    }

    #[test]
    fn dead_time_delays_the_drive_exactly() {
        let mut m = PlantModel::reference();
        m.effects.dead_time = Some(crate::plant::effects::DeadTime { ms: 2.5 });
        let mut p = Plant::new(Coefficients::from_model(&m).expect("hydraulic"));
        p.advance(1e-3, 30.0, 0.0);
        p.advance(1e-3, 30.0, 0.0);
        assert_eq!(p.state().f_hz, 0.0, "nothing before 2.5 ms");
        p.advance(1e-3, 30.0, 0.0);
        let f = p.state().f_hz;
        // ramp-limited at 25 Hz/s for the 0.5 ms after the command arrived
        assert!((f - 25.0 * 0.5e-3).abs() < 1e-9, "{f}");
    }

    #[test]
    fn the_drive_alone_steps_as_the_whole_plant_does_to_the_bit() {
        let c = reference();
        let mut x = PlantState { f_hz: 3.0, p_in_pa: 2e6, omega_rad_s: 10.0 };
        let mut f = x.f_hz;
        // a step up and a step down, at two step lengths: the ramp limit and the lag both act
        for (k, f_cmd) in (0..600).map(|k| (k, if k < 400 { 40.0 } else { 0.0 })) {
            let h = if k % 3 == 0 { 1e-3 } else { 0.7e-3 };
            x = c.rk4(&x, f_cmd, 5.0, h);
            f = c.drive_rk4(f, f_cmd, h);
            assert_eq!(f.to_bits(), x.f_hz.to_bits(), "step {k}");
        }
        assert!(x.f_hz > 3.0, "the drive moved: {}", x.f_hz);
    }

    #[test]
    fn pressure_never_negative() {
        let mut p = Plant::new(reference());
        for _ in 0..2000 {
            p.advance(1e-3, 0.0, -20.0); // the load drives the motor forward: it sucks the line empty
            assert!(p.state().p_in_pa >= 0.0);
        }
    }
}

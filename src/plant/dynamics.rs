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

/// The shortest internal step the simulator takes: a plant whose fastest mode needs shorter steps is refused at load
/// ([`stiffness`]), since at 500 RK4 steps a 1 ms sample it could no longer run in real time.
pub const MIN_SUBSTEP_S: f64 = 2e-6;

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

    /// The largest |∂(dω/dt)/∂ω| (1/s): viscous friction and the steepest slope of the friction effects (at
    /// standstill, where the smooth sign turns), over the inertia.
    pub fn friction_rate(&self) -> f64 {
        let j = self.inertia_kg_m2;
        let coulomb = self.coulomb_nm.abs() / SIGN_SPEED_RAD_S / j;
        let stribeck = self.stribeck.map_or(0.0, |(breakaway, speed)| {
            (breakaway - self.coulomb_nm).abs() * (1.0 / SIGN_SPEED_RAD_S + 1.0 / speed) / j
        });
        self.viscous_nm_s_rad / j + coulomb + stribeck
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

    /// The fastest rate (1/s) of the plant linearised about standstill: the line's pressure (leakage and slip
    /// against its stiffness β/V), the shaft (friction over inertia), and the oscillation between them
    /// (β·D_m²/(V·J)). RK4 is accurate and stable while step × rate ≤ 1. The drive's frequency is left out: its rate
    /// is clamped to the ramp, so a short time constant bounds its error by ramp × step instead of growing.
    pub fn fastest_rate(&self) -> f64 {
        let stiffness = self.bulk_modulus_pa / self.volume_m3;
        let slip = self.pump_m3_rad.powi(2) * self.slip_rad_s_per_nm;
        let pressure = stiffness * (self.leakage_si + slip);
        let shaft = self.mechanics.friction_rate();
        let coupling = stiffness * self.motor_m3_rad.powi(2) / self.mechanics.inertia_kg_m2;
        // the 2×2 system [[-pressure, -β/V·D_m], [D_m/J, -shaft]]: its larger |eigenvalue|
        let half = 0.5 * (pressure + shaft);
        let disc = 0.25 * (pressure - shaft).powi(2) - coupling;
        if disc >= 0.0 { half + disc.sqrt() } else { (pressure * shaft + coupling).sqrt() }
    }

    /// The internal step for this plant: [`MAX_SUBSTEP_S`], shorter where a fast mode needs it (never below
    /// [`MIN_SUBSTEP_S`]; a model needing less is refused at load).
    pub fn stable_step_s(&self) -> f64 {
        (1.0 / self.fastest_rate()).clamp(MIN_SUBSTEP_S, MAX_SUBSTEP_S)
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

/// The fastest rate of a model (1/s): the whole plant's, or the shaft's alone for a torque-driven model.
pub fn model_rate(model: &PlantModel) -> f64 {
    match Coefficients::from_model(model) {
        Ok(c) => c.fastest_rate(),
        Err(_) => Mechanics::from_model(model).friction_rate(),
    }
}

/// Refuses a model whose fastest mode would need steps below [`MIN_SUBSTEP_S`] (1e300 for a bulk modulus or a
/// friction, 1e-300 for an inertia): RK4 at any longer step diverges or rings, and a run's output would be garbage.
/// Names the key whose value makes it so: the one that, put back to the reference plant's (or its effect off),
/// lowers the fastest rate most.
pub fn stiffness(model: &PlantModel) -> Result<(), KeyError> {
    let limit = 1.0 / MIN_SUBSTEP_S;
    let rate = model_rate(model);
    if rate.is_finite() && rate <= limit {
        return Ok(());
    }
    let r = PlantModel::reference();
    type Undo = fn(&mut PlantModel, &PlantModel);
    let undo: [(&str, Undo); 12] = [
        ("motor.inertia_kg_m2", |m, r| m.motor.inertia_kg_m2 = r.motor.inertia_kg_m2),
        ("motor.viscous_nm_s_rad", |m, r| m.motor.viscous_nm_s_rad = r.motor.viscous_nm_s_rad),
        ("motor.displacement_cm3", |m, r| {
            m.motor.displacement_cm3 = m.motor.displacement_cm3.and(r.motor.displacement_cm3)
        }),
        ("pump.displacement_cm3", |m, r| {
            if let (Some(p), Some(rp)) = (m.pump.as_mut(), r.pump.as_ref()) {
                p.displacement_cm3 = rp.displacement_cm3;
            }
        }),
        ("hydraulics.volume_l", |m, r| set_hydraulics(m, r, |h, r| h.volume_l = r.volume_l)),
        ("hydraulics.bulk_modulus_bar", |m, r| set_hydraulics(m, r, |h, r| h.bulk_modulus_bar = r.bulk_modulus_bar)),
        ("hydraulics.leakage_l_min_per_bar", |m, r| {
            set_hydraulics(m, r, |h, r| h.leakage_l_min_per_bar = r.leakage_l_min_per_bar)
        }),
        ("effects.coulomb_friction.torque_nm", |m, _| m.effects.coulomb_friction = None),
        ("effects.stribeck_friction.breakaway_nm", |m, _| m.effects.stribeck_friction = None),
        ("effects.internal_leakage.l_min_per_bar", |m, _| m.effects.internal_leakage = None),
        ("effects.entrained_air.bulk_modulus_bar", |m, _| m.effects.entrained_air = None),
        ("effects.motor_slip.rpm_per_nm", |m, _| m.effects.motor_slip = None),
    ];
    let lowered = |f: Undo| {
        let mut m = model.clone();
        f(&mut m, &r);
        let v = model_rate(&m);
        if v.is_nan() { f64::INFINITY } else { v }
    };
    let key = undo
        .iter()
        .map(|&(key, f)| (lowered(f), key))
        .fold((f64::INFINITY, "motor.inertia_kg_m2"), |best, t| if t.0 < best.0 { t } else { best })
        .1;
    Err(KeyError::new(
        key.into(),
        format!(
            "makes the plant too stiff to simulate: its fastest mode is {}, beyond the {limit:.0e}/s a \
             {MIN_SUBSTEP_S:e} s step resolves; check the value and its unit",
            if rate.is_finite() { format!("{rate:.3e}/s") } else { "not a finite rate".into() }
        ),
    ))
}

/// Sets a field of `[hydraulics]` to the reference plant's, where the model has the section.
fn set_hydraulics(m: &mut PlantModel, r: &PlantModel, f: fn(&mut super::model::Hydraulics, &super::model::Hydraulics)) {
    if let (Some(h), Some(rh)) = (m.hydraulics.as_mut(), r.hydraulics.as_ref()) {
        f(h, rh);
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
    /// The step taken: `max_substep_s`, shorter where the plant's fastest mode needs it.
    substep_s: f64,
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

    /// As [`Plant::new`] with a chosen largest internal step (for convergence checks); shorter where the plant's
    /// fastest mode needs it.
    pub fn with_substep(coefficients: Coefficients, max_substep_s: f64) -> Plant {
        Plant {
            substep_s: max_substep_s.min(coefficients.stable_step_s()),
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
            self.substep_s = self.max_substep_s.min(c.stable_step_s());
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
                let n = (len / self.substep_s).ceil().max(1.0);
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

    #[test]
    fn a_stiff_plant_takes_shorter_steps_and_matches_a_fine_reference() {
        // the reference plant is far from stiff: its steps are the usual ones
        assert!(reference().fastest_rate() < 0.1 / MAX_SUBSTEP_S, "{}", reference().fastest_rate());
        assert_eq!(reference().stable_step_s(), MAX_SUBSTEP_S);
        // a line of 0.1 ml: its fastest mode (5e4/s) rang RK4 at 0.2 ms steps to non-numbers
        let mut m = PlantModel::reference();
        m.hydraulics.as_mut().expect("hydraulics").volume_l = 1e-4;
        let c = Coefficients::from_model(&m).expect("hydraulic");
        assert!(c.fastest_rate() > 2.0 / MAX_SUBSTEP_S, "{}", c.fastest_rate());
        let run = |mut p: Plant| {
            for k in 0..1000 {
                p.advance(1e-3, if k < 500 { 30.0 } else { 10.0 }, 4.0);
            }
            p.state()
        };
        let (adapted, fine) = (run(Plant::new(c)), run(Plant::with_substep(c, 1e-7)));
        assert!((adapted.omega_rad_s - fine.omega_rad_s).abs() < 1e-6 * fine.omega_rad_s.abs(), "{adapted:?} {fine:?}");
        assert!((adapted.p_in_pa - fine.p_in_pa).abs() < 1e-6 * fine.p_in_pa, "{adapted:?} {fine:?}");
        let mut fixed = Plant::new(c);
        fixed.substep_s = MAX_SUBSTEP_S;
        let rung = run(fixed);
        // at 0.2 ms steps it rings, held at 0 bar by the floor: garbage
        assert!(rung.p_in_pa.is_nan() || (rung.p_in_pa - fine.p_in_pa).abs() > 0.1 * fine.p_in_pa, "{rung:?} {fine:?}");
    }

    #[test]
    fn a_model_too_stiff_for_any_step_is_refused_naming_the_key_that_makes_it() {
        let refused = |edit: &dyn Fn(&mut PlantModel)| {
            let mut m = PlantModel::reference();
            edit(&mut m);
            stiffness(&m).expect_err("refused").key
        };
        assert_eq!(refused(&|m| m.motor.inertia_kg_m2 = 1e-300), "motor.inertia_kg_m2");
        assert_eq!(refused(&|m| m.motor.viscous_nm_s_rad = 1e300), "motor.viscous_nm_s_rad");
        assert_eq!(refused(&|m| m.motor.displacement_cm3 = Some(1e300)), "motor.displacement_cm3");
        assert_eq!(
            refused(&|m| m.hydraulics.as_mut().expect("h").bulk_modulus_bar = 1e300),
            "hydraulics.bulk_modulus_bar"
        );
        assert_eq!(refused(&|m| m.hydraulics.as_mut().expect("h").volume_l = 1e-12), "hydraulics.volume_l");
        assert_eq!(
            refused(&|m| m.effects.coulomb_friction = Some(crate::plant::effects::CoulombFriction { torque_nm: 1e9 })),
            "effects.coulomb_friction.torque_nm"
        );
        // the same mechanics alone (a torque-driven model): the shaft's rate
        assert_eq!(
            refused(&|m| {
                m.hydraulics = None;
                m.motor.inertia_kg_m2 = 1e-12;
            }),
            "motor.inertia_kg_m2"
        );
        stiffness(&PlantModel::reference()).expect("the reference plant");
    }
}

//! `service::fallback_observer`: a stand-in estimator, used only until the estimator branch (RLS+SGD, Kalman) lands.

use crate::estimator::{Estimate, Estimator, Measurement};

/// NOT the paper's RLS+SGD and not a Kalman filter. A fixed-gain Luenberger observer
/// on the state [ω, T_L] with J and B taken from the nominal model (it does not identify them):
///
/// ```text
/// ω̂' = (T_drive − B·ω̂ − T̂_L)/J + L1·(ω − ω̂)        T̂_L' = −L2·(ω − ω̂)
/// ```
/// with both observer poles at −[`FallbackObserver::POLE_RAD_S`] (`L1 = 2p − B/J`, `L2 = J·p²`), integrated with
/// explicit Euler at a step capped for stability.
pub struct FallbackObserver {
    inertia_kg_m2: f64,
    viscous_nm_s_rad: f64,
    l1: f64,
    l2: f64,
    omega_hat: f64,
    load_hat: f64,
    started: bool,
}

impl FallbackObserver {
    /// Observer bandwidth (rad/s): fast enough to follow load steps in ≈ 0.3 s, slow enough to filter tacho noise.
    pub const POLE_RAD_S: f64 = 10.0;

    pub fn new(inertia_kg_m2: f64, viscous_nm_s_rad: f64) -> FallbackObserver {
        let p = Self::POLE_RAD_S;
        FallbackObserver {
            inertia_kg_m2,
            viscous_nm_s_rad,
            l1: (2.0 * p - viscous_nm_s_rad / inertia_kg_m2).max(0.0),
            l2: inertia_kg_m2 * p * p,
            omega_hat: 0.0,
            load_hat: 0.0,
            started: false,
        }
    }
}

impl Estimator for FallbackObserver {
    fn update(&mut self, m: &Measurement) -> Estimate {
        let ok = m.dt_s.is_finite() && m.dt_s > 0.0 && m.omega_rad_s.is_finite() && m.drive_torque_nm.is_finite();
        if !ok {
            return self.estimate();
        }
        if !self.started {
            self.omega_hat = m.omega_rad_s;
            self.started = true;
            return self.estimate();
        }
        // explicit Euler is stable for dt·L1 < 1; longer gaps are split
        let max_step = 0.5 / self.l1.max(1.0);
        let steps = (m.dt_s / max_step).ceil().min(1000.0) as usize;
        let h = m.dt_s.min(1.0) / steps as f64;
        for _ in 0..steps {
            let e = m.omega_rad_s - self.omega_hat;
            let accel =
                (m.drive_torque_nm - self.viscous_nm_s_rad * self.omega_hat - self.load_hat) / self.inertia_kg_m2;
            self.omega_hat += h * (accel + self.l1 * e);
            self.load_hat -= h * self.l2 * e;
        }
        if !(self.omega_hat.is_finite() && self.load_hat.is_finite()) {
            self.omega_hat = m.omega_rad_s;
            self.load_hat = 0.0;
        }
        self.estimate()
    }

    fn estimate(&self) -> Estimate {
        Estimate {
            omega_hat_rad_s: self.omega_hat,
            load_hat_nm: self.load_hat,
            inertia_hat_kg_m2: self.inertia_kg_m2,
            viscous_hat_nm_s_rad: self.viscous_nm_s_rad,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn observer_finds_a_constant_load() {
        let (j, b, load) = (0.08, 0.04, 10.0);
        let mut obs = FallbackObserver::new(j, b);
        let (mut omega, torque, dt) = (30.0, 0.0, 0.01);
        let torque = torque + load + b * 30.0; // holds 30 rad/s against the load
        for _ in 0..300 {
            omega += dt * (torque - b * omega - load) / j;
            obs.update(&Measurement { dt_s: dt, omega_rad_s: omega, drive_torque_nm: torque });
        }
        let e = obs.estimate();
        assert!((e.load_hat_nm - load).abs() < 0.1, "{e:?}");
        assert!((e.omega_hat_rad_s - 30.0).abs() < 0.05, "{e:?}");
        let after_nan = obs.update(&Measurement { dt_s: f64::NAN, omega_rad_s: 1.0, drive_torque_nm: 1.0 });
        assert_eq!(after_nan, e, "a missing sample keeps the state");
    }
}

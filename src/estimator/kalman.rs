//! The reference estimator the paper names: a Kalman filter on [ω, T_L] with a random-walk load and known J, B.
//!
//! `ω(k+1) = (1 − Δt·B/J)·ω(k) − Δt/J·T_L(k) + Δt/J·τ(k)`, `T_L(k+1) = T_L(k) + w`, measured `ω + v`.
//! Process noise: the drive torque's measurement noise through Δt/J on ω, `load_rate²·Δt` on T_L; R = σ_ω².
//! Joseph-form update, symmetrised and checked positive definite after every step.
//!
//! Sharper on steps: a random walk tuned for slow drifts follows a brake step slowly. A two-sided CUSUM on the
//! normalised innovations detects an abrupt load change and widens the load's variance by `jump_load_sd_nm²`
//! once, so the filter re-weighs the load at the next samples instead of trusting its old value.

use nalgebra::{Matrix2, RowVector2, Vector2};

use super::covariance::condition;
use super::settings::Resolved;
use super::{Checked, Estimate, Estimator, Measurement, step_guarded};

/// A two-sided CUSUM on normalised innovations: says when the load has jumped.
#[derive(Debug, Clone, Copy, Default)]
struct JumpTest {
    up: f64,
    down: f64,
}

impl JumpTest {
    /// Feeds one innovation in units of its σ over `dt`; true when a jump is detected (and the test restarts).
    pub fn feed(&mut self, z: f64, s: &Resolved) -> bool {
        self.up = (self.up + z - s.jump_drift).max(0.0);
        self.down = (self.down - z - s.jump_drift).max(0.0);
        if self.up > s.jump_threshold || self.down > s.jump_threshold {
            *self = JumpTest::default();
            return true;
        }
        false
    }
}

/// The Kalman filter (method `kalman`).
#[derive(Debug, Clone)]
pub struct Kalman {
    s: Resolved,
    started: bool,
    x: Vector2<f64>,
    p: Matrix2<f64>,
    torque_nm: Option<f64>,
    jump: JumpTest,
    /// Upper bound of trace(P): far above anything the filter reaches, so only garbage input meets it.
    max_trace: f64,
}

impl Kalman {
    pub fn new(s: Resolved) -> Kalman {
        let max_trace = 1e6 * (s.speed_noise_rad_s.powi(2) + s.initial_load_sigma_nm.powi(2));
        Kalman {
            s,
            started: false,
            x: Vector2::new(0.0, s.initial_load_nm),
            p: Self::initial_p(&s),
            torque_nm: None,
            jump: JumpTest::default(),
            max_trace,
        }
    }

    fn initial_p(s: &Resolved) -> Matrix2<f64> {
        Matrix2::new(s.speed_noise_rad_s.powi(2), 0.0, 0.0, s.initial_load_sigma_nm.powi(2))
    }

    /// Moves the load estimate by `delta` (N·m): a tracker taking over another's state on other J and B.
    pub(crate) fn shift_load(&mut self, delta: f64) {
        if delta.is_finite() {
            self.x[1] = (self.x[1] + delta).clamp(-self.s.max_load_nm, self.s.max_load_nm);
        }
    }

    /// The state covariance, for tests and diagnostics.
    pub fn covariance(&self) -> Matrix2<f64> {
        self.p
    }

    fn restart(&mut self, omega: f64) {
        self.x[0] = omega;
        self.p[(0, 0)] = self.s.speed_noise_rad_s.powi(2);
        self.p[(0, 1)] = 0.0;
        self.p[(1, 0)] = 0.0;
        self.started = true;
    }

    /// One sample with the inertia and viscous friction to predict with (the model's, or rls-sgd's estimates);
    /// `load_rate_scale` multiplies the load's random-walk intensity.
    pub(crate) fn step_with(&mut self, m: &Measurement, j: f64, b: f64, load_rate_scale: f64) -> Estimate {
        let c = Checked::new(m, self.s.max_gap_s);
        step_guarded(
            self,
            |k| {
                k.step(c, j, b, load_rate_scale);
                if let Some(t) = c.torque_nm {
                    k.torque_nm = Some(t);
                }
            },
            |k| Kalman::new(k.s),
        )
    }

    fn step(&mut self, c: Checked, j: f64, b: f64, load_rate_scale: f64) {
        let (Some(dt), Some(tau), true) = (c.dt_s, self.torque_nm, self.started) else {
            match c.omega_rad_s {
                Some(w) => self.restart(w),
                None if c.gap => self.started = false,
                None => {}
            }
            return;
        };
        let f = Matrix2::new(1.0 - dt * b / j, -dt / j, 0.0, 1.0);
        let q = Matrix2::new(
            (dt / j * self.s.torque_noise_nm).powi(2),
            0.0,
            0.0,
            (self.s.load_rate_nm_per_s * load_rate_scale).powi(2) * dt,
        );
        self.x = f * self.x + Vector2::new(dt / j * tau, 0.0);
        self.p = f * self.p * f.transpose() + q;
        if let Some(w) = c.omega_rad_s {
            let r = self.s.speed_noise_rad_s.powi(2);
            let h = RowVector2::new(1.0, 0.0);
            let innovation = w - self.x[0];
            let mut s = self.p[(0, 0)] + r;
            if self.s.jump_load_sd_nm > 0.0 && self.jump.feed(innovation / s.sqrt(), &self.s) {
                self.p[(1, 1)] += self.s.jump_load_sd_nm.powi(2);
                s = self.p[(0, 0)] + r;
            }
            let k = self.p.column(0) / s;
            self.x += k * innovation;
            let a = Matrix2::identity() - k * h;
            self.p = a * self.p * a.transpose() + k * r * k.transpose();
        }
        let m = self.s.max_load_nm;
        self.x[1] = self.x[1].clamp(-m, m);
        self.p = condition(self.p, self.max_trace, 1e-12, 1.0);
    }
}

impl Estimator for Kalman {
    fn update(&mut self, m: &Measurement) -> Estimate {
        self.step_with(m, self.s.initial_inertia_kg_m2, self.s.initial_viscous_nm_s_rad, 1.0)
    }

    fn boxed_clone(&self) -> Box<dyn Estimator> {
        Box::new(self.clone())
    }

    fn estimate(&self) -> Estimate {
        Estimate {
            omega_hat_rad_s: self.x[0],
            load_hat_nm: self.x[1],
            inertia_hat_kg_m2: self.s.initial_inertia_kg_m2,
            viscous_hat_nm_s_rad: self.s.initial_viscous_nm_s_rad,
            inertia_sd_kg_m2: 0.0,
            viscous_sd_nm_s_rad: 0.0,
            inertia_identified: super::Identification::FromModel.code(),
            viscous_identified: super::Identification::FromModel.code(),
            load_character: super::LoadCharacter::Unknown.code(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::EstimatorSettings;
    use crate::plant::PlantModel;

    #[test]
    fn finds_a_constant_load_on_a_clean_plant() {
        let r = EstimatorSettings::default().resolve(&PlantModel::reference()).expect("defaults");
        let mut est = Kalman::new(r);
        let (j, b, load, tau, dt) = (0.08, 0.04, 10.9, 14.0, 1e-3);
        let mut w = 30.0;
        for _ in 0..3000 {
            est.update(&Measurement { dt_s: dt, omega_rad_s: w, drive_torque_nm: tau });
            w += dt / j * (tau - b * w - load);
        }
        let e = est.estimate();
        assert!((e.load_hat_nm - load).abs() < 0.2, "{e:?}");
        assert!(est.covariance().cholesky().is_some());
    }
}

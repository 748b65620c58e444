//! The paper as printed (method `paper-literal`): per-sample RLS on [ΔP, ω] and eq. (11) with its "+" sign.
//!
//! For reproducing the paper only: the load estimate runs away (PHYSICS.md §2, erratum) and the covariance winds
//! up without excitation. Outputs are still kept finite: J and B are clamped to the physical bounds when reported,
//! and a non-finite covariance is reset.

use nalgebra::{Matrix2, Vector2};

use super::covariance::condition;
use super::settings::Resolved;
use super::{Checked, Estimate, Estimator, Measurement, step_guarded};

/// The paper's estimator, literally.
#[derive(Debug, Clone)]
pub struct PaperLiteral {
    s: Resolved,
    /// N·m per unit of ΔP in the regressor (ΔP in bar: D_m·1e5; 1 when the model has no displacement).
    torque_per_dp: f64,
    theta: Vector2<f64>,
    p: Matrix2<f64>,
    /// The previous sample's measured speed and ΔP: the regressor.
    previous: Option<(f64, f64)>,
    omega_hat_rad_s: f64,
    load_hat_nm: f64,
    dt_s: f64,
}

impl PaperLiteral {
    pub fn new(s: Resolved) -> PaperLiteral {
        let torque_per_dp = s.displacement_m3_rad.map_or(1.0, |d| d * 1e5);
        let dt = 1e-3;
        let j = s.initial_inertia_kg_m2;
        PaperLiteral {
            s,
            torque_per_dp,
            theta: Vector2::new(dt * torque_per_dp / j, 1.0 - dt * s.initial_viscous_nm_s_rad / j),
            p: Matrix2::identity() * s.initial_covariance,
            previous: None,
            omega_hat_rad_s: 0.0,
            load_hat_nm: s.initial_load_nm,
            dt_s: dt,
        }
    }

    /// The RLS covariance, to show its wind-up.
    pub fn covariance(&self) -> Matrix2<f64> {
        self.p
    }

    fn step(&mut self, c: Checked) {
        let current = c.omega_rad_s.zip(c.torque_nm.map(|t| t / self.torque_per_dp));
        let (Some(dt), Some((w_prev, dp_prev)), Some(w)) = (c.dt_s, self.previous, c.omega_rad_s) else {
            self.previous = current;
            if let Some(w) = c.omega_rad_s {
                self.omega_hat_rad_s = w;
            }
            return;
        };
        self.dt_s = dt;
        let phi = Vector2::new(dp_prev, w_prev);
        // Δt/J = a/D: the load's coefficient in the model ω(k+1) = b·ω + a·ΔP − Δt/J·T_L.
        let dt_over_j = self.theta[0] / self.torque_per_dp;
        let predicted = phi.dot(&self.theta) - dt_over_j * self.load_hat_nm;
        let e = w - predicted;
        let lam = self.s.lambda;
        let p_phi = self.p * phi;
        let k = p_phi / (lam + phi.dot(&p_phi));
        self.theta += k * e;
        self.p = condition((self.p - k * p_phi.transpose()) / lam, 1e200, 1e-30, self.s.initial_covariance);
        // Eq. (11) as printed: "+".
        let m = self.s.max_load_nm;
        self.load_hat_nm = (self.load_hat_nm + self.s.eta * dt_over_j * e).clamp(-m, m);
        self.omega_hat_rad_s = predicted;
        if !self.theta.iter().all(|v| v.is_finite()) {
            *self = PaperLiteral::new(self.s);
        }
        self.previous = current;
    }
}

impl Estimator for PaperLiteral {
    fn update(&mut self, m: &Measurement) -> Estimate {
        step_guarded(self, |e| e.step(Checked::new(m, e.s.max_gap_s)), |e| PaperLiteral::new(e.s))
    }

    fn boxed_clone(&self) -> Box<dyn Estimator> {
        Box::new(self.clone())
    }

    fn estimate(&self) -> Estimate {
        let [jlo, jhi] = self.s.inertia_bounds_kg_m2;
        let [blo, bhi] = self.s.viscous_bounds_nm_s_rad;
        let j = self.dt_s * self.torque_per_dp / self.theta[0];
        let j = if j.is_finite() && j > 0.0 { j.clamp(jlo, jhi) } else { jhi };
        let b = ((1.0 - self.theta[1]) * j / self.dt_s).clamp(blo, bhi);
        Estimate {
            omega_hat_rad_s: self.omega_hat_rad_s,
            load_hat_nm: self.load_hat_nm,
            inertia_hat_kg_m2: j,
            viscous_hat_nm_s_rad: if b.is_finite() { b } else { blo },
            // The paper's P is not a calibrated covariance (no noise weighting): no confidence is claimed.
            inertia_sd_kg_m2: 0.0,
            viscous_sd_nm_s_rad: 0.0,
            inertia_identified: super::Identification::FromModel.code(),
            viscous_identified: super::Identification::FromModel.code(),
            load_character: super::LoadCharacter::Unknown.code(),
        }
    }
}

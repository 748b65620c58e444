//! RLS + SGD done right: an ω̂ observer, the load by normalised descent with the corrected sign, J and B by a guarded RLS.
//!
//! Three time scales, each with its own error, so they do not fight (PHYSICS.md §2, "known traps"):
//! - ω̂ (every sample): model prediction `ω̂⁻ = ω̂ + Δt/J·(τ − Bω̂ − T̂_L)` plus a fraction `l` of the innovation
//!   `e = ω − ω̂⁻`, with `l = 1 − exp(−bandwidth·Δt)`: noise is suppressed without the lag of a low-pass filter.
//! - T̂_L (every sample): stochastic gradient descent on ½e². The gradient is taken through the observer:
//!   `S = ∂ω̂⁻/∂T_L` follows `S⁻ ← (1 − ΔtB/J)·S⁺ − Δt/J`, `S⁺ = (1 − l)·S⁻` (≈ −Δt/(J·l)), so `∂e/∂T_L = −S⁻`
//!   and the normalised step is `T̂_L ← T̂_L + η·e/S⁻`. With `l = 0` this is the corrected eq. (11),
//!   `T̂_L ← T̂_L − η·(J/Δt)·e`. Stable for 0 < η < 2; the paper's η = 0.05 gives a damped second-order observer.
//! - θ (every `rls_period_s`): RLS with forgetting on the speed increment over a block,
//!   `Δω̂ = T·(τ̄/J − (B/J)·ω̄ − T_L/J)`, i.e. the paper's θ = [Δt·D_m/J, 1 − Δt·B/J] plus a load bias of its own,
//!   normalised to the nominal values. The bias forgets fast (load steps), J and B forget only when the block
//!   excites them (no wind-up), trace(P) is bounded, P is kept symmetric positive definite and θ is projected
//!   into the physical bounds.

use nalgebra::{Matrix3, Vector3};

use super::settings::Resolved;
use super::{Checked, Estimate, Estimator, Measurement, finite_or};

/// Smallest diagonal of the RLS covariance (normalised parameters): far below what 40 ms blocks can teach.
const RLS_FLOOR: f64 = 1e-10;

/// The RLS on block increments. Parameters are normalised: `θ = [J₀/J, (B/J)·J₀/B_ref, (T_L/J)·J₀/L_ref]`.
#[derive(Debug, Clone)]
pub(crate) struct BlockRls {
    pub theta: Vector3<f64>,
    pub p: Matrix3<f64>,
    j0: f64,
    b_ref: f64,
    l_ref: f64,
    /// Recent mean drive torque and speed of the blocks: excitation is a block away from these.
    torque_mean_nm: Option<f64>,
    omega_mean_rad_s: f64,
    s: Resolved,
}

impl BlockRls {
    pub fn new(s: Resolved) -> BlockRls {
        let j0 = s.nominal_inertia_kg_m2;
        let b_ref = (s.viscous_bounds_nm_s_rad[1] / 5.0).max(1e-9);
        let l_ref = j0 * 100.0;
        let j = s.initial_inertia_kg_m2;
        let theta =
            Vector3::new(j0 / j, s.initial_viscous_nm_s_rad / j * j0 / b_ref, s.initial_load_nm / j * j0 / l_ref);
        BlockRls {
            theta,
            p: Matrix3::identity() * s.initial_covariance,
            j0,
            b_ref,
            l_ref,
            torque_mean_nm: None,
            omega_mean_rad_s: 0.0,
            s,
        }
    }

    pub fn inertia_kg_m2(&self) -> f64 {
        self.j0 / self.theta[0]
    }

    pub fn viscous_nm_s_rad(&self) -> f64 {
        self.theta[1] * self.b_ref / self.theta[0]
    }

    /// One block: `T` long, speed increment `Δω`, mean drive torque and mean speed, σ of the increment's noise.
    pub fn update(&mut self, t_s: f64, domega: f64, torque_nm: f64, omega_rad_s: f64, noise_sd: f64) {
        let phi = Vector3::new(
            t_s * torque_nm / self.j0,
            -t_s * omega_rad_s * self.b_ref / self.j0,
            -t_s * self.l_ref / self.j0,
        );
        let lam = self.s.lambda;
        let lam_l = self.s.load_forgetting;
        let (excite_j, excite_b) = match self.torque_mean_nm {
            None => (false, false),
            Some(m) => (
                (torque_nm - m).abs() > self.s.excitation_torque_nm,
                (omega_rad_s - self.omega_mean_rad_s).abs() > self.s.excitation_speed_rad_s,
            ),
        };
        let mean_torque = self.torque_mean_nm.unwrap_or(torque_nm);
        self.torque_mean_nm = Some(lam_l * mean_torque + (1.0 - lam_l) * torque_nm);
        self.omega_mean_rad_s = lam_l * self.omega_mean_rad_s + (1.0 - lam_l) * omega_rad_s;
        // Selective forgetting: P ← D·P·D, D = diag(1/√λᵢ); a direction forgets only when it is excited.
        let f = |excited: bool| if excited { 1.0 / lam.sqrt() } else { 1.0 };
        let d = Matrix3::from_diagonal(&Vector3::new(f(excite_j), f(excite_b), 1.0 / lam_l.sqrt()));
        let p = d * self.p * d;
        let p_phi = p * phi;
        let denom = 1.0 + phi.dot(&p_phi);
        let residual = domega - phi.dot(&self.theta);
        // A residual far beyond the noise is a load change (a step of the brake), not news about J or B: it goes
        // to the load bias alone, whose knowledge is reset, and J, B are left as they were.
        let sd = noise_sd * denom.sqrt();
        if residual.abs() > self.s.change_threshold * sd && phi[2] != 0.0 {
            let mut theta = self.theta;
            theta[2] += residual / phi[2];
            let mut p = self.p;
            for i in 0..3 {
                p[(i, 2)] = 0.0;
                p[(2, i)] = 0.0;
            }
            p[(2, 2)] = 1.0;
            self.p = condition(p, self.s.max_covariance_trace, RLS_FLOOR, self.s.initial_covariance);
            self.theta = self.project(theta);
            return;
        }
        let gain = p_phi / denom;
        let theta = self.theta + gain * residual;
        let p = p - gain * p_phi.transpose();
        self.p = condition(p, self.s.max_covariance_trace, RLS_FLOOR, self.s.initial_covariance);
        self.theta = self.project(theta);
    }

    /// θ into the physical bounds of J, B and the load.
    fn project(&self, theta: Vector3<f64>) -> Vector3<f64> {
        if !theta.iter().all(|v| v.is_finite()) {
            return self.theta;
        }
        let [jlo, jhi] = self.s.inertia_bounds_kg_m2;
        let t0 = theta[0].clamp(self.j0 / jhi, self.j0 / jlo);
        let [blo, bhi] = self.s.viscous_bounds_nm_s_rad;
        let t1 = theta[1].clamp(blo * t0 / self.b_ref, bhi * t0 / self.b_ref);
        let lmax = self.s.max_load_nm * t0 / self.l_ref;
        Vector3::new(t0, t1, theta[2].clamp(-lmax, lmax))
    }
}

/// Keeps a covariance usable: symmetric, trace at most `max_trace`, diagonal at least `floor`, positive definite
/// (reset to `reset·I` when it is not, or is not finite).
pub(crate) fn condition<const N: usize>(
    p: nalgebra::SMatrix<f64, N, N>,
    max_trace: f64,
    floor: f64,
    reset: f64,
) -> nalgebra::SMatrix<f64, N, N> {
    let fresh = || nalgebra::SMatrix::<f64, N, N>::identity() * reset.min(max_trace / N as f64);
    if !p.iter().all(|v| v.is_finite()) {
        return fresh();
    }
    let mut p = (p + p.transpose()) * 0.5;
    let tr = p.trace();
    if tr > max_trace {
        p *= max_trace / tr;
    }
    // A floor well below any information the data can give keeps P strictly positive definite.
    for i in 0..N {
        if p[(i, i)] < floor {
            p[(i, i)] = floor;
        }
    }
    if p.cholesky().is_some() { p } else { fresh() }
}

/// Sums over one RLS block. The regression compares the mean measured speed of two consecutive blocks:
/// `ω̄ⱼ₊₁ − ω̄ⱼ = ∫ w(s)·ω̇(s) ds` with a triangular weight `w` rising over block j and falling over block j+1, so
/// torque and speed enter as the same triangular means. Measured speed (not ω̂, which the model itself shaped)
/// keeps the regression independent of the current J and B.
#[derive(Debug, Clone, Copy, Default)]
struct Block {
    t_s: f64,
    /// ∫ω_meas ds and the time with a measured speed.
    omega_meas_dt: f64,
    measured_s: f64,
    /// ∫τ ds and ∫τ·(s − s₀) ds; likewise for ω̂.
    torque_dt: f64,
    torque_ramp: f64,
    omega_dt: f64,
    omega_ramp: f64,
    /// False when a held (not measured) torque went into it: such a block teaches nothing reliable.
    valid: bool,
}

impl Block {
    fn start() -> Block {
        Block { valid: true, ..Block::default() }
    }

    fn add(&mut self, dt: f64, torque: f64, omega_hat: f64, omega_meas: Option<f64>) {
        let mid = self.t_s + 0.5 * dt;
        self.torque_dt += torque * dt;
        self.torque_ramp += torque * mid * dt;
        self.omega_dt += omega_hat * dt;
        self.omega_ramp += omega_hat * mid * dt;
        if let Some(w) = omega_meas {
            self.omega_meas_dt += w * dt;
            self.measured_s += dt;
        }
        self.t_s += dt;
    }

    fn usable(&self) -> bool {
        self.valid && self.t_s > 0.0 && self.measured_s > 0.5 * self.t_s
    }

    fn mean_measured_speed(&self) -> f64 {
        self.omega_meas_dt / self.measured_s
    }
}

/// The regression data of two consecutive blocks: (T, Δω̄, triangular mean torque, triangular mean speed).
fn block_pair(a: &Block, b: &Block) -> (f64, f64, f64, f64) {
    let t = 0.5 * (a.t_s + b.t_s);
    let tri = |ramp_a: f64, sum_b: f64, ramp_b: f64| (ramp_a / a.t_s + sum_b - ramp_b / b.t_s) / t;
    (
        t,
        b.mean_measured_speed() - a.mean_measured_speed(),
        tri(a.torque_ramp, b.torque_dt, b.torque_ramp),
        tri(a.omega_ramp, b.omega_dt, b.omega_ramp),
    )
}

/// The corrected RLS+SGD estimator (method `rls-sgd`).
#[derive(Debug, Clone)]
pub struct RlsSgd {
    s: Resolved,
    started: bool,
    omega_hat_rad_s: f64,
    load_hat_nm: f64,
    /// ∂ω̂/∂T_L after the last correction.
    sensitivity: f64,
    /// The drive torque applied since the last sample (the last measured one).
    torque_nm: Option<f64>,
    torque_measured: bool,
    rls: BlockRls,
    block: Block,
    previous_block: Option<Block>,
}

impl RlsSgd {
    pub fn new(s: Resolved) -> RlsSgd {
        RlsSgd {
            s,
            started: false,
            omega_hat_rad_s: 0.0,
            load_hat_nm: s.initial_load_nm,
            sensitivity: 0.0,
            torque_nm: None,
            torque_measured: false,
            rls: BlockRls::new(s),
            block: Block::start(),
            previous_block: None,
        }
    }

    /// The RLS covariance (normalised parameters), for tests and diagnostics.
    pub fn covariance(&self) -> Matrix3<f64> {
        self.rls.p
    }

    fn restart_speed(&mut self, omega: f64) {
        self.omega_hat_rad_s = omega;
        self.started = true;
        self.sensitivity = 0.0;
        self.block = Block::start();
        self.previous_block = None;
    }

    fn step(&mut self, c: Checked) {
        let (Some(dt), Some(tau), true) = (c.dt_s, self.torque_nm, self.started) else {
            // No step to predict across (first sample, a gap, no torque yet): restart from the measurement.
            match c.omega_rad_s {
                Some(w) => self.restart_speed(w),
                None if c.gap => self.started = false,
                None => {}
            }
            return;
        };
        let j = self.rls.inertia_kg_m2();
        let b = self.rls.viscous_nm_s_rad();
        let w0 = self.omega_hat_rad_s;
        let decay = 1.0 - dt * b / j;
        let predicted = w0 + dt / j * (tau - b * w0 - self.load_hat_nm);
        let s_minus = decay * self.sensitivity - dt / j;
        self.block.add(dt, tau, w0, c.omega_rad_s);
        self.block.valid &= self.torque_measured;
        match c.omega_rad_s {
            Some(w) => {
                let e = w - predicted;
                let l = 1.0 - (-self.s.speed_bandwidth_rad_s * dt).exp();
                self.omega_hat_rad_s = predicted + l * e;
                // Descent on ½e² with ∂e/∂T_L = −S⁻ < 0, normalised by the gradient's size (corrected eq. 11).
                let s_safe = s_minus.min(-dt / j * 0.5);
                let m = self.s.max_load_nm;
                self.load_hat_nm = (self.load_hat_nm + self.s.eta * e / s_safe).clamp(-m, m);
                self.sensitivity = (1.0 - l) * s_minus;
            }
            None => {
                self.omega_hat_rad_s = predicted;
                self.sensitivity = s_minus;
            }
        }
        if self.block.t_s >= self.s.rls_period_s {
            let done = std::mem::replace(&mut self.block, Block::start());
            if let Some(prev) = self.previous_block.filter(|p| p.usable() && done.usable()) {
                let (t, dw, torque, omega) = block_pair(&prev, &done);
                // Mean of n samples of σ_ω noise, twice; n from the sampled time and this step.
                let n = |b: &Block| (b.measured_s / dt).max(1.0);
                let sd = self.s.speed_noise_rad_s * (1.0 / n(&prev) + 1.0 / n(&done)).sqrt();
                self.rls.update(t, dw, torque, omega, sd);
            }
            self.previous_block = Some(done);
        }
    }
}

impl Estimator for RlsSgd {
    fn update(&mut self, m: &Measurement) -> Estimate {
        let before = self.estimate();
        let c = Checked::new(m, self.s.max_gap_s);
        self.step(c);
        if let Some(t) = c.torque_nm {
            self.torque_nm = Some(t);
            self.torque_measured = true;
        } else {
            self.torque_measured = false;
        }
        let after = self.estimate();
        if after != finite_or(after, before) || !self.rls.theta.iter().all(|v| v.is_finite()) {
            // Cannot happen with the guards above; if it does, start over rather than report garbage.
            *self = RlsSgd::new(self.s);
            return before;
        }
        after
    }

    fn boxed_clone(&self) -> Box<dyn Estimator> {
        Box::new(self.clone())
    }

    fn estimate(&self) -> Estimate {
        Estimate {
            omega_hat_rad_s: self.omega_hat_rad_s,
            load_hat_nm: self.load_hat_nm,
            inertia_hat_kg_m2: self.rls.inertia_kg_m2(),
            viscous_hat_nm_s_rad: self.rls.viscous_nm_s_rad(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::EstimatorSettings;
    use crate::plant::PlantModel;

    #[test]
    fn condition_symmetrises_bounds_and_resets() {
        let p = Matrix3::new(2.0, 1.0, 0.0, 0.5, 2.0, 0.0, 0.0, 0.0, 1e9);
        let q = condition(p, 100.0, 1e-10, 10.0);
        assert_eq!(q, q.transpose());
        assert!(q.trace() <= 100.0 + 1e-9);
        assert!(q.cholesky().is_some());
        let bad = Matrix3::new(1.0, 5.0, 0.0, 5.0, 1.0, 0.0, 0.0, 0.0, 1.0);
        assert!(condition(bad, 100.0, 1e-10, 10.0).cholesky().is_some());
        let nan = Matrix3::from_element(f64::NAN);
        assert!(condition(nan, 100.0, 1e-10, 10.0).iter().all(|v| v.is_finite()));
    }

    /// A noise-free plant with a constant load and J, B held (tiny RLS covariance): the corrected, normalised
    /// descent finds the load within a few hundred samples.
    #[test]
    fn corrected_sgd_converges_on_a_constant_load() {
        let s = EstimatorSettings { initial_covariance: 1e-12, ..EstimatorSettings::default() };
        let mut est = RlsSgd::new(s.resolve(&PlantModel::reference()).expect("valid"));
        let (j, b, load, tau, dt) = (0.08, 0.04, 10.9, 14.0, 1e-3);
        let mut w = 30.0;
        for _ in 0..3000 {
            est.update(&Measurement { dt_s: dt, omega_rad_s: w, drive_torque_nm: tau });
            w += dt / j * (tau - b * w - load);
        }
        let e = est.estimate();
        assert!((e.load_hat_nm - load).abs() < 0.2, "{e:?}");
        assert!((e.omega_hat_rad_s - w).abs() < 0.1, "{e:?}");
    }
}

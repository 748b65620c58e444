//! PURE estimation of shaft speed, load torque, inertia and viscous friction from measured speed and pressures
//! (PHYSICS.md §2). Fed Δt and samples; never reads a clock. Implementations: RLS+SGD (the seed paper, corrected)
//! and a Kalman filter.

/// One measured sample as the estimators take it. A non-finite field means "missing": the estimator must skip it
/// and keep its state.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Measurement {
    /// Time since the previous sample (s).
    pub dt_s: f64,
    /// Measured shaft speed (rad/s).
    pub omega_rad_s: f64,
    /// Drive torque on the shaft (N·m): `D_m·(p_in − p_out)`, or a measured torque.
    pub drive_torque_nm: f64,
}

/// What the estimators say after a sample.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Estimate {
    pub omega_hat_rad_s: f64,
    pub load_hat_nm: f64,
    pub inertia_hat_kg_m2: f64,
    pub viscous_hat_nm_s_rad: f64,
}

/// A running estimator. Every output is finite whatever the input.
pub trait Estimator: Send {
    /// Takes one sample and returns the updated estimate.
    fn update(&mut self, m: &Measurement) -> Estimate;
    /// The latest estimate.
    fn estimate(&self) -> Estimate;
}

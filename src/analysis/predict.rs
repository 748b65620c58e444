//! The one place the two model families differ: how a candidate model predicts the recording (free run).

use crate::BadInput;
use crate::plant::PlantModel;
use crate::plant::dynamics::{Coefficients, Mechanics, PlantState};
use crate::units::{bar_to_pa, pa_to_bar};

use super::series::{Family, Series};
use super::signal::nrmse;

/// Largest RK4 step of the analysis's free run. The fastest modes of the reference plant are the drive's 20 ms lag,
/// the hydraulic resonance (≈ 40 rad/s) and the smooth sign of a friction term (≈ 125 /s for 0.5 N·m): h·λ ≤ 0.13,
/// where RK4's error is far below the sensor noise, and 5× fewer steps than the simulator's 0.2 ms.
pub const FREE_RUN_STEP_S: f64 = 1e-3;

/// A candidate model's predictions for rows `0..end`.
#[derive(Debug, Clone, Default)]
pub struct Prediction {
    /// Free-run speed (rad/s).
    pub omega_rad_s: Vec<f64>,
    /// Free-run p_in − p_out (bar), hydraulic family.
    pub dp_bar: Option<Vec<f64>>,
    /// Drive torque the model needs to move as measured (inverse dynamics, N·m), torque family.
    pub torque_nm: Option<Vec<f64>>,
}

/// Errors of a prediction over a range of rows.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Errors {
    pub omega_nrmse: f64,
    pub dp_nrmse: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub torque_nrmse: Option<f64>,
    /// ‖τ − τ̂‖/‖τ‖, the EMPS benchmark's relative force error.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub torque_relative_error: Option<f64>,
}

impl Errors {
    /// The single number the search minimises: mean squared NRMSE of the family's judged signals. Hydraulic: free-run
    /// speed and ΔP. Torque-driven: the inverse-dynamics torque (a closed-loop positioning axis never runs open loop,
    /// so its free-run speed is reported but not judged).
    pub fn score(&self, family: Family) -> f64 {
        match family {
            Family::Hydraulic => match self.dp_nrmse {
                Some(dp) => 0.5 * (self.omega_nrmse.powi(2) + dp.powi(2)),
                None => self.omega_nrmse.powi(2),
            },
            Family::Torque => self.torque_nrmse.map_or(self.omega_nrmse.powi(2), |t| t.powi(2)),
        }
    }
}

/// Predicts rows `0..end` with `model`.
pub fn predict(model: &PlantModel, s: &Series, end: usize) -> Result<Prediction, BadInput> {
    let end = end.min(s.len());
    match s.family {
        Family::Hydraulic => {
            let c = Coefficients::from_model(model).map_err(|(key, msg)| BadInput(format!("model: `{key}` {msg}")))?;
            let (omega, dp) = free_run_hydraulic(&c, s, end);
            Ok(Prediction { omega_rad_s: omega, dp_bar: Some(dp), torque_nm: None })
        }
        Family::Torque => {
            let m = Mechanics::from_model(model);
            Ok(Prediction {
                omega_rad_s: free_run_mechanics(&m, s, end),
                dp_bar: None,
                torque_nm: Some(inverse_dynamics(&m, s, end)),
            })
        }
    }
}

/// Errors of `p` against the recording over rows `from..to`.
pub fn errors(p: &Prediction, s: &Series, from: usize, to: usize) -> Errors {
    let to = to.min(p.omega_rad_s.len());
    let from = from.min(to);
    let omega_nrmse = nrmse(&p.omega_rad_s[from..to], &s.omega_rad_s[from..to]);
    let dp_nrmse = match (&p.dp_bar, &s.dp_bar) {
        (Some(sim), Some(meas)) => Some(nrmse(&sim[from..to], &meas[from..to])),
        _ => None,
    };
    let (torque_nrmse, torque_relative_error) = match &p.torque_nm {
        Some(tau_hat) => {
            let tau = &s.drive_torque_f[from..to];
            let num: f64 = tau_hat[from..to].iter().zip(tau).map(|(a, b)| (a - b).powi(2)).sum();
            let den: f64 = tau.iter().map(|b| b * b).sum();
            (Some(nrmse(&tau_hat[from..to], tau)), Some((num / den).sqrt()))
        }
        None => (None, None),
    };
    Errors { omega_nrmse, dp_nrmse, torque_nrmse, torque_relative_error }
}

/// Free run of the whole plant from the recorded setpoint and load. Row k is the state at t_k; the inputs of row k
/// hold over [t_k, t_k+1), the setpoint delayed by the dead time exactly as the simulator does.
fn free_run_hydraulic(c: &Coefficients, s: &Series, end: usize) -> (Vec<f64>, Vec<f64>) {
    let mut omega = Vec::with_capacity(end);
    let mut dp = Vec::with_capacity(end);
    let empty = Vec::new();
    let u = s.setpoint_hz.as_ref().unwrap_or(&empty);
    let back = c.back_pressure_pa;
    let mut x = PlantState {
        f_hz: s.f0_hz,
        p_in_pa: bar_to_pa(s.p_in0_bar).max(0.0),
        omega_rad_s: s.omega_f.first().copied().unwrap_or(0.0),
    };
    let dt_nominal = 1.0 / s.sample_hz;
    let delay = c.dead_time_s.max(0.0);
    let m = (delay / dt_nominal).floor() as usize;
    let r = delay - m as f64 * dt_nominal;
    let cmd = |j: isize| -> f64 {
        let v = if j < 0 { u.first().copied().unwrap_or(0.0) } else { u.get(j as usize).copied().unwrap_or(0.0) };
        if v.is_finite() { v.clamp(0.0, c.max_hz) } else { 0.0 }
    };
    let integrate = |x: &mut PlantState, len: f64, f_cmd: f64, load: f64| {
        if len <= 0.0 {
            return;
        }
        let steps = (len / FREE_RUN_STEP_S).ceil().max(1.0);
        let h = len / steps;
        for _ in 0..steps as usize {
            *x = c.rk4(x, f_cmd, load, h);
        }
    };
    for k in 0..end {
        omega.push(x.omega_rad_s);
        dp.push(pa_to_bar(x.p_in_pa - back));
        if k + 1 == end {
            break;
        }
        let len = s.t_s[k + 1] - s.t_s[k];
        let load = s.load_nm[k];
        let k = k as isize - m as isize;
        let first = r.min(len);
        integrate(&mut x, first, cmd(k - 1), load);
        integrate(&mut x, len - first, cmd(k), load);
    }
    (omega, dp)
}

/// Free run of the mechanics from the recorded drive and load torques, starting at the measured speed.
fn free_run_mechanics(m: &Mechanics, s: &Series, end: usize) -> Vec<f64> {
    let mut omega = Vec::with_capacity(end);
    let mut w = s.omega_f.first().copied().unwrap_or(0.0);
    for k in 0..end {
        omega.push(w);
        if k + 1 == end {
            break;
        }
        let len = s.t_s[k + 1] - s.t_s[k];
        let steps = (len / FREE_RUN_STEP_S).ceil().max(1.0);
        let h = len / steps;
        let (tau, load) = (s.drive_torque_nm[k], s.load_nm[k]);
        let acc = |w: f64| (tau - load - m.viscous_nm_s_rad * w - extra_torque_nm(m, s, w)) / m.inertia_kg_m2;
        for _ in 0..steps as usize {
            let k1 = acc(w);
            let k2 = acc(w + 0.5 * h * k1);
            let k3 = acc(w + 0.5 * h * k2);
            let k4 = acc(w + h * k3);
            w += h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4);
        }
        if !w.is_finite() {
            w = 0.0;
        }
    }
    omega
}

/// The drive torque the model says the measured (filtered) motion needs: J α + B ω + friction + offset + load.
pub fn inverse_dynamics(m: &Mechanics, s: &Series, end: usize) -> Vec<f64> {
    (0..end)
        .map(|k| {
            let w = s.omega_f[k];
            m.inertia_kg_m2 * s.alpha_f[k] + m.viscous_nm_s_rad * w + extra_torque_nm(m, s, w) + s.load_f[k]
        })
        .collect()
}

/// [`Mechanics::extra_torque_nm`] with the recording's sign band ([`Series::sign`]); identical to the plant's for
/// the reference plant.
pub fn extra_torque_nm(m: &Mechanics, s: &Series, omega: f64) -> f64 {
    let sgn = s.sign(omega);
    let mut t = m.coulomb_nm * sgn + m.offset_nm;
    if let Some((breakaway, speed)) = m.stribeck {
        t += (breakaway - m.coulomb_nm) * (-(omega / speed).powi(2)).exp() * sgn;
    }
    t
}

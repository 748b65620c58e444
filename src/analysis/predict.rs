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
    /// The drive model's frequency run from the setpoint (Hz), where `f_drive_hz` and `f_set_hz` were recorded
    /// (flow and hydraulic families).
    pub f_drive_hz: Option<Vec<f64>>,
    /// Hydraulic family, for a model whose dead time is not the nominal model's: the drive model run with the
    /// nominal dead time on the same rows, which the score's drive factor compares against.
    pub f_drive_nominal_hz: Option<Vec<f64>>,
    /// Flow family: the mean square (bar²) that the speed sensor's noise adds to this model's ΔP prediction.
    pub dp_noise_bar2: f64,
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
    /// The drive model run from `f_set_hz` against `f_drive_hz` (where the dead time shows), where both were
    /// recorded.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub f_drive_nrmse: Option<f64>,
    /// Hydraulic family: the same for the nominal dead time, where the model's differs (see [`Errors::score`]).
    #[serde(skip)]
    pub f_drive_nominal_nrmse: Option<f64>,
    /// Flow family: the part of `dp_nrmse²` expected from the speed noise that drives the pressure equation;
    /// the score takes it out (see [`Series::speed_noise_f`]).
    #[serde(skip)]
    pub dp_noise_nrmse2: f64,
}

impl Errors {
    /// The single number the search minimises: mean squared NRMSE of the family's judged signals. Hydraulic: free-run
    /// speed and ΔP. Torque-driven: the inverse-dynamics torque (a closed-loop positioning axis never runs open loop,
    /// so its free-run speed is reported but not judged).
    pub fn score(&self, family: Family) -> f64 {
        match family {
            // the drive factor: a dead time acts first on the drive, and the frequency read back shows it directly,
            // where the free run of speed and ΔP may be dominated by what it does not explain (a motor crawling and
            // sticking under the brake). A model whose dead time differs from the nominal one is scored times the
            // ratio of the drive's squared errors; any other model's score is the free run's alone, so the ratios
            // between candidates that leave the drive as it is are those of the free run, exactly
            Family::Hydraulic => {
                let free = match self.dp_nrmse {
                    Some(dp) => 0.5 * (self.omega_nrmse.powi(2) + dp.powi(2)),
                    None => self.omega_nrmse.powi(2),
                };
                match (self.f_drive_nrmse, self.f_drive_nominal_nrmse) {
                    (Some(f), Some(f0)) if f.is_finite() && f0.is_finite() && f0 > 0.0 => free * (f / f0).powi(2),
                    _ => free,
                }
            }
            Family::Torque => self.torque_nrmse.map_or(self.omega_nrmse.powi(2), |t| t.powi(2)),
            // the speed is an input here. ΔP and the drive frequency have noise floors two orders of magnitude
            // apart (sensor noise against 0.01 Hz quantisation), so they are combined geometrically: a relative
            // gain on either counts as such
            Family::Flow => {
                let raw = self.dp_nrmse.unwrap_or(f64::NAN).powi(2);
                let dp = (raw - self.dp_noise_nrmse2).max(0.01 * raw);
                match self.f_drive_nrmse {
                    Some(f) if f.is_finite() && f > 0.0 => (dp * f.powi(2)).sqrt(),
                    _ => dp,
                }
            }
        }
    }
}

/// Predicts rows `0..end` with `model`.
pub fn predict(model: &PlantModel, s: &Series, end: usize) -> Result<Prediction, BadInput> {
    predict_rows(model, s, 0, end, &[])
}

/// Predicts rows `start..end` with `model`, the free run starting from the measured state at `start` and
/// restarting from it at each row of `restarts` (sorted): the blocks of cross-validation, each run free from its
/// measured state. Rows before `start` are NaN (no error is computed for them).
pub fn predict_rows(
    model: &PlantModel,
    s: &Series,
    start: usize,
    end: usize,
    restarts: &[usize],
) -> Result<Prediction, BadInput> {
    let end = end.min(s.len());
    let start = start.min(end);
    match s.family {
        Family::Hydraulic => {
            let c = Coefficients::from_model(model)
                .map_err(|crate::error::KeyError { key, message: msg }| BadInput(format!("model: `{key}` {msg}")))?;
            let (omega, dp, f) = free_run_hydraulic(&c, s, start, end, restarts);
            let read_back = s.f_drive_hz.is_some() && s.setpoint_hz.is_some();
            let nominal = (read_back && c.dead_time_s != s.nominal_dead_time_s)
                .then(|| free_run_drive(&c, s.nominal_dead_time_s, s, start, end, restarts));
            Ok(Prediction {
                omega_rad_s: omega,
                dp_bar: Some(dp),
                torque_nm: None,
                f_drive_hz: read_back.then_some(f),
                f_drive_nominal_hz: nominal,
                dp_noise_bar2: 0.0,
            })
        }
        Family::Flow => {
            let c = Coefficients::from_model(model)
                .map_err(|crate::error::KeyError { key, message: msg }| BadInput(format!("model: `{key}` {msg}")))?;
            let (f, dp) = free_run_flow(&c, s, start, end, restarts);
            // the speed drives the flow balance: it is not predicted (NaN: no error is computed for it)
            let compare_f = s.f_drive_hz.is_some() && s.setpoint_hz.is_some();
            Ok(Prediction {
                omega_rad_s: vec![f64::NAN; end],
                dp_bar: Some(dp),
                torque_nm: None,
                f_drive_hz: compare_f.then_some(f),
                f_drive_nominal_hz: None,
                dp_noise_bar2: noise_in_dp_bar2(&c, s),
            })
        }
        Family::Torque => {
            let m = Mechanics::from_model(model);
            Ok(Prediction {
                omega_rad_s: free_run_mechanics(&m, s, start, end, restarts),
                dp_bar: None,
                torque_nm: Some(inverse_dynamics(&m, s, end)),
                f_drive_hz: None,
                f_drive_nominal_hz: None,
                dp_noise_bar2: 0.0,
            })
        }
    }
}

/// Errors of `p` against the recording over rows `from..to`.
pub fn errors(p: &Prediction, s: &Series, from: usize, to: usize) -> Errors {
    let to = to.min(p.omega_rad_s.len());
    let from = from.min(to);
    let omega_nrmse = measured_nrmse(&p.omega_rad_s[from..to], &s.omega_rad_s[from..to], &s.measured_omega[from..to]);
    let dp_nrmse = match (&p.dp_bar, &s.dp_bar) {
        (Some(sim), Some(meas)) => {
            Some(measured_nrmse(&sim[from..to], &meas[from..to], &s.measured_dp[from..to])).filter(|v| v.is_finite())
        }
        _ => None,
    };
    let dp_noise_nrmse2 = match &s.dp_bar {
        Some(meas) if p.dp_noise_bar2 > 0.0 => {
            let m = &meas[from..to];
            let mean = m.iter().sum::<f64>() / m.len().max(1) as f64;
            let den = m.iter().map(|v| (v - mean).powi(2)).sum::<f64>();
            if den > 0.0 { m.len() as f64 * p.dp_noise_bar2 / den } else { 0.0 }
        }
        _ => 0.0,
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
    let drive_nrmse = |sim: &Option<Vec<f64>>| match (sim, &s.f_drive_hz) {
        (Some(sim), Some(meas)) => Some(measured_nrmse(&sim[from..to], &meas[from..to], &s.measured_f_drive[from..to]))
            .filter(|v| v.is_finite()),
        _ => None,
    };
    let f_drive_nrmse = drive_nrmse(&p.f_drive_hz);
    let f_drive_nominal_nrmse = drive_nrmse(&p.f_drive_nominal_hz);
    Errors {
        omega_nrmse,
        dp_nrmse,
        torque_nrmse,
        torque_relative_error,
        f_drive_nrmse,
        f_drive_nominal_nrmse,
        dp_noise_nrmse2,
    }
}

/// A window's NRMSE needs at least this share of its rows measured (and [`MIN_MEASURED_ROWS`]); less gives NaN
/// (null in the JSON): a score of filled-in values would be a score from nothing.
pub const MIN_MEASURED_SHARE: f64 = 0.1;
pub const MIN_MEASURED_ROWS: usize = 20;

/// [`nrmse`] over the rows where `measured` holds; NaN when too few do, or when the measurement does not vary.
fn measured_nrmse(sim: &[f64], meas: &[f64], measured: &[bool]) -> f64 {
    let rows = measured.iter().filter(|m| **m).count();
    if rows < MIN_MEASURED_ROWS || (rows as f64) < MIN_MEASURED_SHARE * measured.len() as f64 {
        return f64::NAN;
    }
    let meas: Vec<f64> = meas.iter().zip(measured).map(|(v, m)| if *m { *v } else { f64::NAN }).collect();
    let e = nrmse(sim, &meas);
    if e.is_finite() { e } else { f64::NAN }
}

/// Free run of the whole plant from the recorded setpoint and load. Row k is the state at t_k; the inputs of row k
/// hold over [t_k, t_k+1), the setpoint delayed by the dead time exactly as the simulator does. Returns the speed,
/// ΔP (bar) and the drive's frequency per row.
fn free_run_hydraulic(
    c: &Coefficients,
    s: &Series,
    start: usize,
    end: usize,
    restarts: &[usize],
) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let mut omega = vec![f64::NAN; start];
    let mut dp = vec![f64::NAN; start];
    let mut f = vec![f64::NAN; start];
    omega.reserve(end - start);
    dp.reserve(end - start);
    f.reserve(end - start);
    let back = c.back_pressure_pa;
    // the measured state at row k (row 0: the recording's first values)
    let measured = |k: usize| PlantState {
        f_hz: if k == 0 { s.f0_hz } else { s.state_f_hz.get(k).copied().unwrap_or(0.0) },
        p_in_pa: bar_to_pa(if k == 0 { s.p_in0_bar } else { s.state_p_in_bar.get(k).copied().unwrap_or(0.0) }).max(0.0),
        omega_rad_s: s.omega_f.get(k).copied().unwrap_or(0.0),
    };
    let mut x = measured(start);
    let restarts = with_gaps(s, restarts);
    let mut next_restart = restarts.iter().copied().filter(|r| *r > start).peekable();
    let setpoint = Delayed::new(s, c.dead_time_s, c.max_hz);
    for k in start..end {
        if next_restart.peek() == Some(&k) {
            next_restart.next();
            x = measured(k);
        }
        omega.push(x.omega_rad_s);
        dp.push(pa_to_bar(x.p_in_pa - back));
        f.push(x.f_hz);
        if k + 1 == end {
            break;
        }
        // across a gap nothing is integrated: the run restarts from the measured state after it
        let len = if next_restart.peek() == Some(&(k + 1)) { 0.0 } else { s.t_s[k + 1] - s.t_s[k] };
        let load = s.load_nm[k];
        for (len, f_cmd) in setpoint.pieces(k, len) {
            substeps(len, |h| x = c.rk4(&x, f_cmd, load, h));
        }
    }
    (omega, dp, f)
}

/// The setpoint as the free run's drive sees it, delayed by a dead time exactly as the simulator delays it: whole
/// samples, then the command switches inside the sample.
struct Delayed<'a> {
    u: &'a [f64],
    max_hz: f64,
    /// Whole samples of the delay, and the rest (s).
    samples: usize,
    rest_s: f64,
}

impl<'a> Delayed<'a> {
    fn new(s: &'a Series, delay_s: f64, max_hz: f64) -> Delayed<'a> {
        let (samples, rest_s) = delay_split(s, delay_s);
        Delayed { u: s.setpoint_hz.as_deref().unwrap_or(&[]), max_hz, samples, rest_s }
    }

    /// The setpoint of row `j` (the first before the recording), clamped to the drive's range.
    fn command(&self, j: isize) -> f64 {
        let u = self.u;
        let v = if j < 0 { u.first().copied().unwrap_or(0.0) } else { u.get(j as usize).copied().unwrap_or(0.0) };
        if v.is_finite() { v.clamp(0.0, self.max_hz) } else { 0.0 }
    }

    /// Row `k`'s interval of `len` s as two pieces, (length, command) each: the delayed setpoint switches inside it.
    fn pieces(&self, k: usize, len: f64) -> [(f64, f64); 2] {
        let k = k as isize - self.samples as isize;
        let first = self.rest_s.min(len);
        [(first, self.command(k - 1)), (len - first, self.command(k))]
    }
}

/// A dead time as the simulator applies it: whole samples of the recording, and the rest (s) after which the
/// command switches inside a sample.
fn delay_split(s: &Series, delay_s: f64) -> (usize, f64) {
    let dt_nominal = 1.0 / s.sample_hz;
    let delay = delay_s.max(0.0);
    let samples = (delay / dt_nominal).floor() as usize;
    (samples, delay - samples as f64 * dt_nominal)
}

/// Calls `step(h)` for RK4 steps of at most [`FREE_RUN_STEP_S`] over `len` s (none when `len` is not positive).
fn substeps(len: f64, mut step: impl FnMut(f64)) {
    if len <= 0.0 {
        return;
    }
    let steps = (len / FREE_RUN_STEP_S).ceil().max(1.0);
    let h = len / steps;
    for _ in 0..steps as usize {
        step(h);
    }
}

/// The drive alone, as [`free_run_hydraulic`] runs it (the same steps, restarts and measured states), with the
/// setpoint delayed by `delay_s`: the frequency per row.
fn free_run_drive(
    c: &Coefficients,
    delay_s: f64,
    s: &Series,
    start: usize,
    end: usize,
    restarts: &[usize],
) -> Vec<f64> {
    let mut out = vec![f64::NAN; start];
    out.reserve(end - start);
    let measured = |k: usize| if k == 0 { s.f0_hz } else { s.state_f_hz.get(k).copied().unwrap_or(0.0) };
    let mut f = measured(start);
    let restarts = with_gaps(s, restarts);
    let mut next_restart = restarts.iter().copied().filter(|r| *r > start).peekable();
    let setpoint = Delayed::new(s, delay_s, c.max_hz);
    for k in start..end {
        if next_restart.peek() == Some(&k) {
            next_restart.next();
            f = measured(k);
        }
        out.push(f);
        if k + 1 == end {
            break;
        }
        let len = if next_restart.peek() == Some(&(k + 1)) { 0.0 } else { s.t_s[k + 1] - s.t_s[k] };
        for (len, f_cmd) in setpoint.pieces(k, len) {
            substeps(len, |h| f = c.drive_rk4(f, f_cmd, h));
        }
    }
    out
}

/// Free run of the flow balance with the load unknown: the drive model from the (delayed) setpoint, and the
/// pressure equation `dp_in/dt = β/V·(D_p ω_pump − D_m ω − C_L Δp)` with ω the measured (low-passed) speed and
/// ω_pump from `f_drive_hz` where recorded, else from the drive model. Inputs are linear between rows. After a gap
/// the state restarts from the measured values. Returns the drive model's frequency and ΔP (bar) per row.
fn free_run_flow(c: &Coefficients, s: &Series, start: usize, end: usize, restarts: &[usize]) -> (Vec<f64>, Vec<f64>) {
    let mut f_out = vec![f64::NAN; start];
    let mut dp_out = vec![f64::NAN; start];
    f_out.reserve(end - start);
    dp_out.reserve(end - start);
    let flow = FlowBalance::new(c);
    let back = c.back_pressure_pa;
    let meas_dp = s.dp_bar.as_deref().unwrap_or(&[]);
    let f_meas = s.f_drive_hz.as_deref();
    let u = s.setpoint_hz.as_deref();
    let (m, r) = delay_split(s, c.dead_time_s);
    let cmd = |j: isize| command(u, f_meas, j, c.max_hz);
    let mut f = s.f0_hz;
    let mut p = bar_to_pa(s.p_in0_bar).max(0.0);
    let mut next_restart = restart_rows(s, start, restarts).into_iter().peekable();
    for k in start..end {
        if next_restart.peek() == Some(&k) {
            next_restart.next();
            p = (bar_to_pa(meas_dp[k]) + back).max(0.0);
            if let Some(fm) = f_meas {
                f = fm[k];
            } else if k == start && start > 0 {
                f = s.state_f_hz.get(k).copied().unwrap_or(f);
            }
        }
        f_out.push(f);
        dp_out.push(pa_to_bar(p - back));
        if k + 1 == end {
            break;
        }
        if next_restart.peek() == Some(&(k + 1)) {
            continue;
        }
        let len = s.t_s[k + 1] - s.t_s[k];
        let row = RowInputs { omega: (s.omega_f[k], s.omega_f[k + 1]), pump: f_meas.map(|fm| (fm[k], fm[k + 1])), len };
        let kk = k as isize - m as isize;
        (f, p) = flow.row((f, p), (cmd(kk - 1), cmd(kk)), r.min(len), &row);
        if !(f.is_finite() && p.is_finite()) {
            f = 0.0;
            p = back;
        }
    }
    (f_out, dp_out)
}

/// The rows from `start` on where the flow family's free run restarts from the measured state: after the
/// recording's gaps, at the given rows, and at `start` itself when it is not the first row.
fn restart_rows(s: &Series, start: usize, restarts: &[usize]) -> Vec<usize> {
    let mut all_restarts: Vec<usize> = s.restarts.iter().chain(restarts).copied().collect();
    if start > 0 {
        all_restarts.push(start);
    }
    all_restarts.sort_unstable();
    all_restarts.dedup();
    all_restarts.into_iter().filter(|r| *r >= start).collect()
}

/// The command at row `j` (rows before the first: the first): the setpoint when written, else the drive's own
/// frequency (monitor-mode recordings), within 0…`max_hz`.
fn command(u: Option<&[f64]>, f_meas: Option<&[f64]>, j: isize, max_hz: f64) -> f64 {
    let j = j.max(0) as usize;
    let v = match (u, f_meas) {
        (Some(u), _) => u.get(j).or(u.last()).copied().unwrap_or(0.0),
        (None, Some(f)) => f.get(j).or(f.last()).copied().unwrap_or(0.0),
        (None, None) => 0.0,
    };
    if v.is_finite() { v.clamp(0.0, max_hz) } else { 0.0 }
}

/// The inputs over one row of the flow family's free run: the low-passed motor speed and, when recorded, the drive
/// frequency at its two ends (linear between), and its length (s).
struct RowInputs {
    omega: (f64, f64),
    pump: Option<(f64, f64)>,
    len: f64,
}

impl RowInputs {
    /// The value at `t` into the row on the line from `a` to `b`.
    fn lerp(&self, a: f64, b: f64, t: f64) -> f64 {
        a + (b - a) * (t / self.len)
    }

    /// The motor speed at `t` into the row.
    fn omega_at(&self, t: f64) -> f64 {
        self.lerp(self.omega.0, self.omega.1, t)
    }

    /// The pump's drive frequency at `t` into the row: as recorded, else the drive model's `f_model`.
    fn pump_at(&self, t: f64, f_model: f64) -> f64 {
        self.pump.map_or(f_model, |(a, b)| self.lerp(a, b, t))
    }
}

/// The flow family's free-run equations on (drive frequency, inlet pressure): the drive's lag and ramp limit, and
/// the pressure equation fed by the pump and drained by the motor, the leak and the slip.
struct FlowBalance<'a> {
    c: &'a Coefficients,
    beta_v: f64,
    two_pi_pp: f64,
}

impl<'a> FlowBalance<'a> {
    /// The equations with `c`'s coefficients, β/V and 2π/pole pairs taken once.
    fn new(c: &'a Coefficients) -> FlowBalance<'a> {
        FlowBalance { c, beta_v: c.bulk_modulus_pa / c.volume_m3, two_pi_pp: 2.0 * std::f64::consts::PI / c.pole_pairs }
    }

    /// dp_in/dt for pump frequency `fp`, motor speed `w`, inlet pressure `p`.
    fn dpdt(&self, p: f64, fp: f64, w: f64) -> f64 {
        let c = self.c;
        let dp = p - c.back_pressure_pa;
        let omega_pump = self.two_pi_pp * fp - c.slip_rad_s_per_nm * c.pump_m3_rad * dp;
        let d = self.beta_v * (c.pump_m3_rad * omega_pump - c.motor_m3_rad * w - c.leakage_si * dp);
        if p <= 0.0 && d < 0.0 { 0.0 } else { d }
    }

    /// df/dt of the drive frequency `f` following `cmd`.
    fn dfdt(&self, f: f64, cmd: f64) -> f64 {
        ((cmd - f) / self.c.time_constant_s).clamp(-self.c.ramp_hz_per_s, self.c.ramp_hz_per_s)
    }

    /// (f, p) over one row: the command switches from `commands.0` to `commands.1` inside the row exactly where the
    /// delayed command does (`first` s in), as in the simulator; RK4 steps of at most `FREE_RUN_STEP_S`.
    fn row(&self, (mut f, mut p): (f64, f64), commands: (f64, f64), first: f64, row: &RowInputs) -> (f64, f64) {
        for (from, to, command) in [(0.0, first, commands.0), (first, row.len, commands.1)] {
            if to <= from {
                continue;
            }
            let steps = ((to - from) / FREE_RUN_STEP_S).ceil().max(1.0) as usize;
            let h = (to - from) / steps as f64;
            for i in 0..steps {
                (f, p) = self.rk4((f, p), command, from + i as f64 * h, h, row);
            }
        }
        (f, p)
    }

    /// One RK4 step of `h` on (f, p) from `ta` into the row, the inputs at the start, middle and end of the step.
    fn rk4(&self, (f, p): (f64, f64), command: f64, ta: f64, h: f64, row: &RowInputs) -> (f64, f64) {
        let (tb, tc) = (ta + 0.5 * h, ta + h);
        let (wa, wb, wc) = (row.omega_at(ta), row.omega_at(tb), row.omega_at(tc));
        let k1f = self.dfdt(f, command);
        let k1p = self.dpdt(p, row.pump_at(ta, f), wa);
        let (f2, p2) = (f + 0.5 * h * k1f, (p + 0.5 * h * k1p).max(0.0));
        let k2f = self.dfdt(f2, command);
        let k2p = self.dpdt(p2, row.pump_at(tb, f2), wb);
        let (f3, p3) = (f + 0.5 * h * k2f, (p + 0.5 * h * k2p).max(0.0));
        let k3f = self.dfdt(f3, command);
        let k3p = self.dpdt(p3, row.pump_at(tb, f3), wb);
        let (f4, p4) = (f + h * k3f, (p + h * k3p).max(0.0));
        let k4f = self.dfdt(f4, command);
        let k4p = self.dpdt(p4, row.pump_at(tc, f4), wc);
        let f = f + h / 6.0 * (k1f + 2.0 * k2f + 2.0 * k3f + k4f);
        let p = (p + h / 6.0 * (k1p + 2.0 * k2p + 2.0 * k3p + k4p)).max(0.0);
        (f, p)
    }
}

/// The mean square (bar²) that the low-passed speed noise adds to the ΔP a model predicts: the pressure equation,
/// linearised (leak and slip together, `a = β/V·(C_L + k_s D_p²)`), driven by the synthetic noise of the series.
fn noise_in_dp_bar2(c: &Coefficients, s: &Series) -> f64 {
    let Some(noise) = s.speed_noise_f.as_deref() else { return 0.0 };
    let beta_v = c.bulk_modulus_pa / c.volume_m3;
    let a = beta_v * (c.leakage_si + c.slip_rad_s_per_nm * c.pump_m3_rad * c.pump_m3_rad);
    let b = beta_v * c.motor_m3_rad;
    if !(a > 0.0 && a.is_finite()) {
        return 0.0;
    }
    let e = (-a / s.sample_hz).exp();
    let g = b * (1.0 - e) / a;
    // the first tenth settles the state
    let settle = noise.len() / 10;
    let (mut x, mut sum) = (0.0, 0.0);
    for (k, n) in noise.iter().enumerate() {
        x = e * x - g * n;
        if k >= settle {
            sum += x * x;
        }
    }
    let count = (noise.len() - settle).max(1) as f64;
    sum / count / (crate::units::PA_PER_BAR * crate::units::PA_PER_BAR)
}

/// `restarts` and the rows after the recording's gaps, sorted: a free run restarts from the measured state there and
/// integrates nothing across the gap, so its work follows the rows, not the seconds.
fn with_gaps(s: &Series, restarts: &[usize]) -> Vec<usize> {
    let mut all: Vec<usize> = s.restarts.iter().chain(restarts).copied().collect();
    all.sort_unstable();
    all.dedup();
    all
}

/// Free run of the mechanics from the recorded drive and load torques, starting at the measured speed.
fn free_run_mechanics(m: &Mechanics, s: &Series, start: usize, end: usize, restarts: &[usize]) -> Vec<f64> {
    let mut omega = vec![f64::NAN; start];
    omega.reserve(end - start);
    let mut w = s.omega_f.get(start).copied().unwrap_or(0.0);
    let restarts = with_gaps(s, restarts);
    let mut next_restart = restarts.iter().copied().filter(|r| *r > start).peekable();
    for k in start..end {
        if next_restart.peek() == Some(&k) {
            next_restart.next();
            w = s.omega_f[k];
        }
        omega.push(w);
        if k + 1 == end || next_restart.peek() == Some(&(k + 1)) {
            continue;
        }
        let len = s.t_s[k + 1] - s.t_s[k];
        let (tau, load) = (s.drive_torque_nm[k], s.load_nm[k]);
        let acc = |w: f64| (tau - load - m.viscous_nm_s_rad * w - extra_torque_nm(m, s, w)) / m.inertia_kg_m2;
        substeps(len, |h| {
            let k1 = acc(w);
            let k2 = acc(w + 0.5 * h * k1);
            let k3 = acc(w + 0.5 * h * k2);
            let k4 = acc(w + h * k3);
            w += h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4);
        });
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

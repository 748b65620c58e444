//! Offline replay, at the recording's edge of the estimators: turns a recording's columns into measurements
//! (CONTRACT.md rules: which columns, in which units) and runs an estimator over them,
//! over a whole [`Recording`] ([`replay`]) or batch by batch as a file streams in ([`Plan`], [`Replayer`]).

use crate::error::BadInput;
use crate::estimator::{Estimate, Estimator, Measurement};
use crate::plant::PlantModel;
use crate::recording::{Recording, position_step};
use crate::units::{bar_to_pa, cm3_per_rev_to_m3_per_rad};

/// Why a recording cannot be replayed: always bad input (the message names the column or key).
pub type ReplayError = BadInput;

/// Drive torque per row: `torque_nm` when present, else `D_m·(p_in − p_out)`. Missing cells give NaN.
pub fn drive_torques(rec: &Recording, model: &PlantModel, model_origin: &str) -> Result<Vec<f64>, ReplayError> {
    if let Some(t) = rec.present("torque_nm") {
        return Ok(t.to_vec());
    }
    let (Some(p_in), Some(p_out)) = (rec.present("p_in_bar"), rec.present("p_out_bar")) else {
        return Err(no_drive_torque(&rec.source));
    };
    let d = displacement_m3_per_rad(model, model_origin)?;
    Ok(p_in.iter().zip(p_out).map(|(a, b)| d * bar_to_pa(a - b)).collect())
}

/// Shaft speed per row: `omega_rad_s` when present, else the backward difference of `theta_rad` (a single-turn
/// encoder's wraps taken out: [`position_step`]).
pub fn speeds(rec: &Recording) -> Result<Vec<f64>, ReplayError> {
    if let Some(w) = rec.present("omega_rad_s") {
        return Ok(w.to_vec());
    }
    let Some(theta) = rec.present("theta_rad") else {
        return Err(no_speed(&rec.source));
    };
    let t = rec.t_s();
    Ok((0..theta.len())
        .map(|k| if k == 0 { f64::NAN } else { position_step(theta[k - 1], theta[k]) / (t[k] - t[k - 1]) })
        .collect())
}

/// The measurements of a recording, one per row; the first row's Δt is NaN (nothing before it).
pub fn measurements(rec: &Recording, model: &PlantModel, model_origin: &str) -> Result<Vec<Measurement>, ReplayError> {
    let torque = drive_torques(rec, model, model_origin)?;
    let omega = speeds(rec)?;
    let t = rec.t_s();
    Ok((0..rec.len())
        .map(|k| Measurement {
            dt_s: if k == 0 { f64::NAN } else { t[k] - t[k - 1] },
            omega_rad_s: omega[k],
            drive_torque_nm: torque[k],
        })
        .collect())
}

/// Runs `estimator` over every row of a recording: one estimate per row. Never reads `load_nm` or `true_*`.
pub fn replay(
    rec: &Recording,
    model: &PlantModel,
    model_origin: &str,
    estimator: &mut dyn Estimator,
) -> Result<Vec<Estimate>, ReplayError> {
    Ok(measurements(rec, model, model_origin)?.iter().map(|m| estimator.update(m)).collect())
}

fn no_drive_torque(recording: &str) -> ReplayError {
    BadInput(format!(
        "recording {recording}: no drive torque: expected a `torque_nm` column, or `p_in_bar` and `p_out_bar`"
    ))
}

fn no_speed(recording: &str) -> ReplayError {
    BadInput(format!("recording {recording}: no speed: expected an `omega_rad_s` or a `theta_rad` column"))
}

/// The motor's displacement per radian, which turns pressures into torque.
fn displacement_m3_per_rad(model: &PlantModel, model_origin: &str) -> Result<f64, ReplayError> {
    match model.motor.displacement_cm3 {
        Some(cm3) => Ok(cm3_per_rev_to_m3_per_rad(cm3)),
        None => Err(BadInput(format!(
            "model file {model_origin}: key `motor.displacement_cm3` is required to turn the recording's pressures into torque"
        ))),
    }
}

/// Where a streamed replay takes the drive torque from ([`drive_torques`]'s choice).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum TorqueFrom {
    TorqueColumn,
    Pressures,
    /// No column can give it: the replay fails (after the whole file has been checked, as [`replay`] does).
    Nothing,
}

/// Where a streamed replay takes the shaft speed from ([`speeds`]' choice).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SpeedFrom {
    OmegaColumn,
    ThetaColumn,
    Nothing,
}

/// The columns a streamed replay reads, chosen from a header as [`replay`] chooses from a whole recording.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Plan {
    pub torque: TorqueFrom,
    pub speed: SpeedFrom,
}

impl Plan {
    /// Chooses from the header's `names`. [`replay`] takes a column only if it holds a value somewhere, so where
    /// both a column and its fallback are in the header (`torque_nm` beside both pressures, `omega_rad_s` beside
    /// `theta_rad`) the choice depends on the content: `holds(columns)` then says, for each column asked about,
    /// whether it holds a finite value anywhere. It is not called otherwise.
    pub fn choose(names: &[String], holds: impl FnOnce(&[&'static str]) -> Vec<bool>) -> Plan {
        let has = |name: &str| names.iter().any(|n| n == name);
        let pressures = has("p_in_bar") && has("p_out_bar");
        let mut ask = Vec::new();
        if has("torque_nm") && pressures {
            ask.push("torque_nm");
        }
        if has("omega_rad_s") && has("theta_rad") {
            ask.push("omega_rad_s");
        }
        let answers = if ask.is_empty() { Vec::new() } else { holds(&ask) };
        // a column nobody asked about is taken when it is there: the end of the replay checks it held a value
        let take = |name: &str| {
            has(name) && ask.iter().position(|a| *a == name).is_none_or(|k| answers.get(k).copied().unwrap_or(false))
        };
        let torque = if take("torque_nm") {
            TorqueFrom::TorqueColumn
        } else if pressures {
            TorqueFrom::Pressures
        } else {
            TorqueFrom::Nothing
        };
        let speed = if take("omega_rad_s") {
            SpeedFrom::OmegaColumn
        } else if has("theta_rad") {
            SpeedFrom::ThetaColumn
        } else {
            SpeedFrom::Nothing
        };
        Plan { torque, speed }
    }

    /// The columns to read besides `t_s`, in the order [`Replayer::push`] takes them: speed, then torque or the
    /// two pressures.
    pub fn columns(&self) -> Vec<&'static str> {
        let mut c = Vec::with_capacity(3);
        match self.speed {
            SpeedFrom::OmegaColumn => c.push("omega_rad_s"),
            SpeedFrom::ThetaColumn => c.push("theta_rad"),
            SpeedFrom::Nothing => {}
        }
        match self.torque {
            TorqueFrom::TorqueColumn => c.push("torque_nm"),
            TorqueFrom::Pressures => c.extend(["p_in_bar", "p_out_bar"]),
            TorqueFrom::Nothing => {}
        }
        c
    }
}

/// [`replay`] batch by batch: the same measurements, estimates and errors, with memory that does not grow with the
/// recording. Feed it [`Plan::columns`] with [`Replayer::push`], then ask [`Replayer::finish`] whether the replay
/// stands: a column that never held a value, or a model without the displacement the pressures need, fails it at
/// the end as [`replay`] would have failed at the start.
pub struct Replayer<'e> {
    plan: Plan,
    /// m³/rad, or why pressures cannot become torque.
    displacement: Result<f64, ReplayError>,
    estimator: &'e mut dyn Estimator,
    /// False when it is already sure the replay fails: rows are then only looked at, for the right message.
    runs: bool,
    prev_t_s: f64,
    prev_theta_rad: f64,
    /// Whether the speed column, the torque column (or `p_in_bar`) and `p_out_bar` held a finite value yet.
    held: [bool; 3],
    rows: u64,
    /// Rows whose speed (or its position) was missing or not finite, and rows whose torque (or a pressure) was.
    without: [u64; 2],
    /// Rows with ω̂ beyond any plant's speed, and the time of the first ([`Replayed::diverged`]).
    diverged: (u64, f64),
    /// The check of the recording's time step, while it waits for its rows.
    time_step: Option<TimeStepCheck>,
    /// Why the replay cannot stand, found on the way (its time step).
    refused: Option<String>,
    recording: String,
}

/// Rows whose time steps decide whether the recording's clock fits the estimator.
const TIME_STEP_ROWS: usize = 2000;

/// The check of a recording's time step against the estimator's bounds, made as the rows pass (once: a pipe or a
/// FIFO cannot be read twice): the median of the first [`TIME_STEP_ROWS`] steps.
struct TimeStepCheck {
    max_gap_s: f64,
    model_origin: String,
    last_t_s: f64,
    steps: Vec<f64>,
}

impl TimeStepCheck {
    fn take(&mut self, t_s: &[f64]) {
        for &t in t_s {
            if self.steps.len() >= TIME_STEP_ROWS {
                break;
            }
            if self.last_t_s.is_finite() {
                self.steps.push(t - self.last_t_s);
            }
            self.last_t_s = t;
        }
    }

    /// Why the estimator cannot run on this clock, if it cannot (too few steps: no verdict).
    fn verdict(mut self, recording: &str) -> Option<String> {
        if self.steps.len() < 2 {
            return None;
        }
        let mid = self.steps.len() / 2;
        let median = *self.steps.select_nth_unstable_by(mid, f64::total_cmp).1;
        let why = if crate::estimator::beyond_gap(median, self.max_gap_s) {
            format!(
                "longer than estimator.max_gap_s = {} s (model file {}): every row would be a gap the estimator \
                 restarts at, and nothing would be estimated; check the unit of t_s, or raise max_gap_s",
                self.max_gap_s, self.model_origin
            )
        } else if median < crate::recording::MIN_TIME_STEP_S {
            format!("{}: check the unit of t_s", crate::recording::TOO_SHORT_A_STEP)
        } else {
            return None;
        };
        Some(format!("recording {recording}: its time step is {median:.3e} s (the median of its first rows), {why}"))
    }
}

/// What a replay went through.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Replayed {
    pub rows: u64,
    /// Rows without a speed: ω̂ there is the model's prediction alone.
    pub without_speed: u64,
    /// Rows without a drive torque: the last one is held there.
    pub without_torque: u64,
    /// Rows whose ω̂ left any physical range ([`crate::plant::simulate::PHYSICAL_LIMITS`]), and the time of the first:
    /// an estimator that diverged (paper-literal with the paper's sign, PHYSICS.md §2), written finite but said.
    pub diverged: (u64, f64),
}

impl Replayed {
    /// The rows it filled in, as `; N without …` clauses (empty when none): what `estimate` says of a recording with
    /// holes, so that a user knows how much of the output stands on the model alone.
    pub fn filled(&self) -> String {
        let mut said = String::new();
        if self.without_speed > 0 {
            said += &format!("; {} without a speed (ω̂ there is the model's prediction alone)", self.without_speed);
        }
        if self.without_torque > 0 {
            said += &format!("; {} without a drive torque (the last one held there)", self.without_torque);
        }
        if let (rows @ 1.., first_t_s) = self.diverged {
            said += &format!(
                "; {rows} with ω̂ beyond any plant's speed, from t = {first_t_s:.3} s: the estimate diverged (paper-literal: \
                 the paper's sign, docs/estimator.md \"The erratum\")"
            );
        }
        said
    }
}

impl<'e> Replayer<'e> {
    /// `recording` names the recording in messages.
    pub fn new(
        plan: Plan,
        model: &PlantModel,
        model_origin: &str,
        recording: &str,
        estimator: &'e mut dyn Estimator,
    ) -> Replayer<'e> {
        let displacement = displacement_m3_per_rad(model, model_origin);
        let runs = plan.speed != SpeedFrom::Nothing
            && match plan.torque {
                TorqueFrom::TorqueColumn => true,
                TorqueFrom::Pressures => displacement.is_ok(),
                TorqueFrom::Nothing => false,
            };
        Replayer {
            plan,
            displacement,
            estimator,
            runs,
            prev_t_s: f64::NAN,
            prev_theta_rad: f64::NAN,
            held: [false; 3],
            rows: 0,
            without: [0; 2],
            diverged: (0, f64::NAN),
            time_step: None,
            refused: None,
            recording: recording.to_string(),
        }
    }

    /// Checks the recording's time step (the median of its first rows) against the estimator's bounds: longer than
    /// `max_gap_s` (every row a gap) or shorter than 10 µs (a clock in the wrong unit) fails the replay, naming it.
    pub fn check_time_step(&mut self, max_gap_s: f64, model_origin: &str) {
        let model_origin = model_origin.to_string();
        self.time_step = Some(TimeStepCheck { max_gap_s, model_origin, last_t_s: f64::NAN, steps: Vec::new() });
    }

    /// Replays rows: `columns` are [`Plan::columns`]' values for the times `t_s`. Calls `out(t_s, estimate)` for each
    /// row, unless the replay is already sure to fail.
    pub fn push(&mut self, t_s: &[f64], columns: &[Vec<f64>], mut out: impl FnMut(f64, &Estimate)) {
        let n = t_s.len();
        if let Some(check) = self.time_step.as_mut() {
            check.take(t_s);
            if check.steps.len() >= TIME_STEP_ROWS {
                self.judge_time_step();
            }
        }
        let has_speed = self.plan.speed != SpeedFrom::Nothing;
        let torque_at = usize::from(has_speed);
        let empty: &[f64] = &[];
        let column = |k: usize| columns.get(k).map_or(empty, |c| &c[..n]);
        let speed = if has_speed { column(0) } else { empty };
        let (torque, p_out) = match self.plan.torque {
            TorqueFrom::TorqueColumn => (column(torque_at), empty),
            TorqueFrom::Pressures => (column(torque_at), column(torque_at + 1)),
            TorqueFrom::Nothing => (empty, empty),
        };
        for (held, values) in self.held.iter_mut().zip([speed, torque, p_out]) {
            *held = *held || values.iter().any(|v| v.is_finite());
        }
        self.rows += n as u64;
        if !self.runs {
            return;
        }
        let d = self.displacement.as_ref().copied().unwrap_or(f64::NAN);
        for k in 0..n {
            let t = t_s[k];
            let omega_rad_s = match self.plan.speed {
                SpeedFrom::ThetaColumn => {
                    let w = position_step(self.prev_theta_rad, speed[k]) / (t - self.prev_t_s);
                    self.prev_theta_rad = speed[k];
                    w
                }
                _ => speed[k],
            };
            let drive_torque_nm = match self.plan.torque {
                TorqueFrom::Pressures => d * bar_to_pa(torque[k] - p_out[k]),
                _ => torque[k],
            };
            self.without[0] += u64::from(!omega_rad_s.is_finite());
            self.without[1] += u64::from(!drive_torque_nm.is_finite());
            let m = Measurement { dt_s: t - self.prev_t_s, omega_rad_s, drive_torque_nm };
            self.prev_t_s = t;
            let e = self.estimator.update(&m);
            if e.omega_hat_rad_s.is_nan() || e.omega_hat_rad_s.abs() > crate::plant::simulate::PHYSICAL_LIMITS.0 {
                if self.diverged.0 == 0 {
                    self.diverged.1 = t;
                }
                self.diverged.0 += 1;
            }
            out(t, &e);
        }
    }

    /// The time step's verdict, once: a refusal stops the estimating (the rows are only looked at).
    fn judge_time_step(&mut self) {
        if let Some(why) = self.time_step.take().and_then(|c| c.verdict(&self.recording)) {
            self.refused = Some(why);
            self.runs = false;
        }
    }

    /// Whether the replay stands, with [`replay`]'s error if not; the rows replayed, and how many it filled in.
    pub fn finish(mut self) -> Result<Replayed, ReplayError> {
        self.judge_time_step();
        if let Some(why) = self.refused {
            return Err(BadInput(why));
        }
        let [speed, torque_or_p_in, p_out] = self.held;
        match self.plan.torque {
            TorqueFrom::TorqueColumn if torque_or_p_in => {}
            TorqueFrom::Pressures if torque_or_p_in && p_out => {
                self.displacement?;
            }
            _ => return Err(no_drive_torque(&self.recording)),
        }
        if self.plan.speed == SpeedFrom::Nothing || !speed {
            return Err(no_speed(&self.recording));
        }
        let [without_speed, without_torque] = self.without;
        Ok(Replayed { rows: self.rows, without_speed, without_torque, diverged: self.diverged })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::{EstimatorSettings, Method, try_build};

    fn rec(names: &[&str], columns: Vec<Vec<f64>>) -> Recording {
        Recording::from_columns("r.csv", names.iter().map(|n| n.to_string()).collect(), columns)
    }

    /// A short recording with wandering signals and a few gaps: `t_s`, ω, θ, p_in, p_out, torque.
    fn signals(n: usize) -> Vec<Vec<f64>> {
        let t: Vec<f64> = (0..n).map(|k| k as f64 * 0.001 + if k > 50 { 0.0005 } else { 0.0 }).collect();
        let w: Vec<f64> = t.iter().map(|t| 20.0 + 5.0 * (7.0 * t).sin()).collect();
        let mut theta = vec![0.0; n];
        for k in 1..n {
            theta[k] = theta[k - 1] + w[k] * (t[k] - t[k - 1]);
        }
        let p_in: Vec<f64> = t.iter().map(|t| 60.0 + 10.0 * (3.0 * t).cos()).collect();
        let p_out = vec![3.0; n];
        let torque: Vec<f64> = p_in.iter().map(|p| 0.5 * p).collect();
        let mut all = vec![t, w, theta, p_in, p_out, torque];
        for c in &mut all[1..] {
            for k in (5..n).step_by(37) {
                c[k] = f64::NAN;
            }
        }
        all
    }

    /// Streams `rec` through a [`Replayer`] in batches of `batch` rows, as the plan for its header chooses.
    fn streamed(rec: &Recording, method: Method, batch: usize) -> Result<Vec<Estimate>, ReplayError> {
        let model = PlantModel::reference();
        let mut est = try_build(&EstimatorSettings { method, ..EstimatorSettings::default() }, &model).expect("ok");
        let plan = Plan::choose(rec.names(), |ask| ask.iter().map(|c| rec.present(c).is_some()).collect());
        let columns: Vec<&[f64]> = plan.columns().iter().map(|c| rec.column(c).expect("chosen from names")).collect();
        let mut replayer = Replayer::new(plan, &model, "m.toml", &rec.source, est.as_mut());
        let mut out = Vec::new();
        for start in (0..rec.len()).step_by(batch) {
            let end = (start + batch).min(rec.len());
            let cols: Vec<Vec<f64>> = columns.iter().map(|c| c[start..end].to_vec()).collect();
            replayer.push(&rec.t_s()[start..end], &cols, |_, e| out.push(*e));
        }
        let done = replayer.finish()?;
        assert_eq!(done.rows as usize, rec.len());
        Ok(out)
    }

    fn whole(rec: &Recording, method: Method) -> Result<Vec<Estimate>, ReplayError> {
        let model = PlantModel::reference();
        let mut est = try_build(&EstimatorSettings { method, ..EstimatorSettings::default() }, &model).expect("ok");
        replay(rec, &model, "m.toml", est.as_mut())
    }

    #[test]
    fn batches_replay_as_the_whole_recording_does() {
        let [t, w, theta, p_in, p_out, torque] = <[Vec<f64>; 6]>::try_from(signals(300)).expect("six");
        let empty = vec![f64::NAN; t.len()];
        let cases = [
            rec(
                &["t_s", "omega_rad_s", "p_in_bar", "p_out_bar"],
                vec![t.clone(), w.clone(), p_in.clone(), p_out.clone()],
            ),
            rec(&["t_s", "omega_rad_s", "torque_nm"], vec![t.clone(), w.clone(), torque.clone()]),
            rec(
                &["t_s", "theta_rad", "p_in_bar", "p_out_bar"],
                vec![t.clone(), theta.clone(), p_in.clone(), p_out.clone()],
            ),
            // both a column and its fallback: the column when it holds values, else the fallback
            rec(
                &["t_s", "omega_rad_s", "theta_rad", "p_in_bar", "p_out_bar", "torque_nm"],
                vec![t.clone(), w.clone(), theta.clone(), p_in.clone(), p_out.clone(), torque.clone()],
            ),
            rec(
                &["t_s", "omega_rad_s", "theta_rad", "p_in_bar", "p_out_bar", "torque_nm"],
                vec![t.clone(), empty.clone(), theta.clone(), p_in.clone(), p_out.clone(), empty.clone()],
            ),
        ];
        for r in &cases {
            for method in [Method::RlsSgd, Method::Kalman] {
                let expected = whole(r, method).expect("replays");
                for batch in [1, 7, 64, 1000] {
                    assert_eq!(streamed(r, method, batch).expect("replays"), expected, "{:?} {batch}", r.names());
                }
            }
        }
    }

    #[test]
    fn batches_fail_as_the_whole_recording_does() {
        let [t, w, _, p_in, _, torque] = <[Vec<f64>; 6]>::try_from(signals(50)).expect("six");
        let empty = vec![f64::NAN; t.len()];
        for r in [
            rec(&["t_s", "omega_rad_s"], vec![t.clone(), w.clone()]),
            rec(&["t_s", "torque_nm"], vec![t.clone(), torque.clone()]),
            rec(&["t_s", "omega_rad_s", "torque_nm"], vec![t.clone(), w.clone(), empty.clone()]),
            rec(&["t_s", "omega_rad_s", "torque_nm"], vec![t.clone(), empty.clone(), torque.clone()]),
            rec(&["t_s", "omega_rad_s", "p_in_bar", "p_out_bar"], vec![t.clone(), w.clone(), p_in.clone(), empty]),
            rec(&["t_s", "omega_rad_s", "p_in_bar"], vec![t.clone(), w.clone(), p_in.clone()]),
        ] {
            let expected = whole(&r, Method::RlsSgd).expect_err("fails").to_string();
            let got = streamed(&r, Method::RlsSgd, 8).expect_err("fails").to_string();
            assert_eq!(got, expected);
        }
        // pressures with a model that has no displacement
        let r = rec(&["t_s", "omega_rad_s", "p_in_bar", "p_out_bar"], vec![t.clone(), w, p_in.clone(), p_in]);
        let mut model = PlantModel::reference();
        model.motor.displacement_cm3 = None;
        let mut est = try_build(&EstimatorSettings::default(), &model).expect("ok");
        let expected = replay(&r, &model, "m.toml", est.as_mut()).expect_err("no displacement").to_string();
        let plan = Plan::choose(r.names(), |_| unreachable!("nothing to ask"));
        let mut replayer = Replayer::new(plan, &model, "m.toml", &r.source, est.as_mut());
        let cols: Vec<Vec<f64>> = plan.columns().iter().map(|c| r.column(c).expect("col").to_vec()).collect();
        replayer.push(r.t_s(), &cols, |_, _| panic!("a replay sure to fail estimates nothing"));
        assert_eq!(replayer.finish().expect_err("no displacement").to_string(), expected);
    }
}

//! The offline test-stand run behind `hydrolens simulate`: the plant, the built-in program, noisy sensors. Rows go
//! to a sink ([`run_into`]); `recording::simulated` keeps them as a recording.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

use super::dynamics::{Coefficients, Plant, PlantState};
use super::model::PlantModel;
use crate::error::KeyError;
use crate::units::pa_to_bar;

crate::units::columns! {
    /// One row `simulate` writes (CONTRACT.md: measured columns, then `true_*`); [`COLUMNS`] names them in order.
    #[derive(Debug, Clone, Copy, PartialEq)]
    pub struct Row {
        pub t_s: f64,
        pub f_set_hz: f64,
        pub f_drive_hz: f64,
        pub p_in_bar: f64,
        pub p_out_bar: f64,
        pub omega_rad_s: f64,
        pub load_nm: f64,
        pub true_omega_rad_s: f64,
        pub true_p_in_bar: f64,
        pub true_load_nm: f64,
        pub true_f_drive_hz: f64,
    }
}

/// The columns `simulate` writes, in order.
pub const COLUMNS: [&str; Row::COLUMNS.len()] = Row::COLUMNS;

/// What drives a run: the setpoint program over time, and the load as a function of (t_s, ω rad/s, shaft angle
/// rad). The load is evaluated once a sample, from the plant's state at the sample's start, and held over it.
pub struct Inputs<'a> {
    pub setpoint_hz: &'a dyn Fn(f64) -> f64,
    pub load_nm: &'a dyn Fn(f64, f64, f64) -> f64,
}

/// Why a streamed run stopped.
#[derive(Debug)]
pub enum RunError {
    /// The model lacks something a simulation needs.
    Model(KeyError),
    /// The row sink failed (a full disk, say).
    Sink(std::io::Error),
    /// The plant's state left any physical range (time in s, what and its value): a model of absurd magnitudes.
    Diverged(f64, &'static str, f64),
}

impl std::fmt::Display for RunError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            RunError::Model(e) => write!(f, "{e}"),
            RunError::Sink(e) => write!(f, "{e}"),
            RunError::Diverged(t, what, v) => write!(
                f,
                "the plant left any physical range at t = {t} s ({what} = {v:e}): the model's magnitudes (torques, \
                 displacements, pressures) are beyond any plant; check their values and units"
            ),
        }
    }
}

/// A test-stand run handing each row (in [`COLUMNS`] order) to `sink` instead of keeping it (`recording::simulated`
/// keeps them as a recording): memory stays flat for runs of any length.
pub fn run_into(
    model: &PlantModel,
    duration_s: f64,
    seed: u64,
    inputs: &Inputs<'_>,
    progress: &mut dyn FnMut(f64),
    sink: &mut dyn FnMut(&[f64; COLUMNS.len()]) -> std::io::Result<()>,
) -> Result<usize, RunError> {
    let coefficients = Coefficients::from_model(model).map_err(RunError::Model)?;
    let dt = model.sample_s();
    let n = (duration_s / dt).floor() as usize + 1;
    let mut plant = Plant::new(coefficients);
    let mut noise = SensorNoise::new(model, seed);
    let back_pressure_bar = pa_to_bar(coefficients.back_pressure_pa);
    let report_every = (n / 100).max(1);
    // the motor's shaft angle since the start: ω integrated by the trapezoid over each sample
    let mut angle_rad = 0.0;
    for k in 0..n {
        let t = k as f64 * dt;
        let f_set = (inputs.setpoint_hz)(t);
        let s = plant.state();
        let load = (inputs.load_nm)(t, s.omega_rad_s, angle_rad);
        let p_in_bar = pa_to_bar(s.p_in_pa);
        let row = Row {
            t_s: t,
            f_set_hz: f_set,
            f_drive_hz: s.f_hz,
            p_in_bar: noise.pressure_reading(p_in_bar),
            p_out_bar: noise.pressure_reading(back_pressure_bar),
            omega_rad_s: s.omega_rad_s + noise.speed(),
            load_nm: load + noise.load(),
            true_omega_rad_s: s.omega_rad_s,
            true_p_in_bar: p_in_bar,
            true_load_nm: load,
            true_f_drive_hz: s.f_hz,
        };
        sink(&row.values()).map_err(RunError::Sink)?;
        plant.wear(model);
        plant.advance(dt, f_set, load);
        if let Some((what, v)) = beyond_physics(&plant.state()) {
            return Err(RunError::Diverged(t + dt, what, v));
        }
        angle_rad += 0.5 * (s.omega_rad_s + plant.state().omega_rad_s) * dt;
        if k % report_every == 0 {
            progress(k as f64 / n as f64);
        }
    }
    progress(1.0);
    Ok(n)
}

/// The largest speed (rad/s, about 10⁷ rpm) and pressure (bar, 100 GPa) a plant's state may reach: far beyond
/// any machine, so only a model of absurd magnitudes (a torque of 1e30 N·m, say) gets there.
pub const PHYSICAL_LIMITS: (f64, f64) = (1e6, 1e6);

/// What of a plant's state is beyond [`PHYSICAL_LIMITS`] or not a number, with its value.
pub fn beyond_physics(s: &PlantState) -> Option<(&'static str, f64)> {
    let p_bar = pa_to_bar(s.p_in_pa);
    if s.omega_rad_s.is_nan() || s.omega_rad_s.abs() > PHYSICAL_LIMITS.0 {
        Some(("speed (rad/s)", s.omega_rad_s))
    } else if p_bar.is_nan() || p_bar.abs() > PHYSICAL_LIMITS.1 {
        Some(("inlet pressure (bar)", p_bar))
    } else if !s.f_hz.is_finite() {
        Some(("drive frequency (Hz)", s.f_hz))
    } else {
        None
    }
}

/// White sensor noise from a seeded, portable generator.
pub struct SensorNoise {
    rng: ChaCha8Rng,
    pressure: Option<Normal<f64>>,
    speed: Option<Normal<f64>>,
    load: Option<Normal<f64>>,
}

impl SensorNoise {
    pub fn new(model: &PlantModel, seed: u64) -> SensorNoise {
        let normal = |sigma: f64| (sigma > 0.0).then(|| Normal::new(0.0, sigma).ok()).flatten();
        SensorNoise {
            rng: ChaCha8Rng::seed_from_u64(seed),
            pressure: normal(model.sensors.pressure_noise_bar),
            speed: normal(model.sensors.speed_noise_rad_s),
            load: normal(model.sensors.load_noise_nm),
        }
    }

    fn draw(rng: &mut ChaCha8Rng, d: Option<Normal<f64>>) -> f64 {
        d.map_or(0.0, |d| d.sample(rng))
    }

    pub fn pressure(&mut self) -> f64 {
        Self::draw(&mut self.rng, self.pressure)
    }

    /// What a pressure sensor reads of `bar`: with its noise, and never beyond its range (it saturates there), so
    /// that a simulated recording holds no cell a reader must take as missing.
    pub fn pressure_reading(&mut self, bar: f64) -> f64 {
        let (lo, hi) = super::PRESSURE_SENSOR_RANGE_BAR;
        (bar + self.pressure()).clamp(lo, hi)
    }

    pub fn speed(&mut self) -> f64 {
        Self::draw(&mut self.rng, self.speed)
    }

    pub fn load(&mut self) -> f64 {
        Self::draw(&mut self.rng, self.load)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pressure_sensor_saturates_at_its_range_and_never_reads_beyond_it() {
        let mut model = PlantModel::reference();
        model.sensors.pressure_noise_bar = 50.0;
        let mut noise = SensorNoise::new(&model, 7);
        let (lo, hi) = crate::plant::PRESSURE_SENSOR_RANGE_BAR;
        let near_zero: Vec<f64> = (0..1000).map(|_| noise.pressure_reading(0.0)).collect();
        assert!(near_zero.iter().all(|p| (lo..=hi).contains(p)));
        assert!(near_zero.contains(&lo), "a vacuum reading saturates at {lo} bar");
        assert!((0..1000).map(|_| noise.pressure_reading(390.0)).any(|p| p == hi));
    }

    #[test]
    fn a_leak_that_grows_slows_the_motor_as_the_worn_model_does() {
        // A constant setpoint and load: the motor's speed is the pump's flow less the leak, over its displacement.
        let text = format!(
            "{}\n[effects.internal_leakage]\nl_min_per_bar = 0.0\n\n[wear.internal_leakage]\ngrowth_per_hour = 3600.0\n",
            crate::plant::model::REFERENCE_TOML
        );
        let mut worn = PlantModel::parse(&text, "worn.toml").expect("parses");
        worn.sensors.sample_ms = 1.0;
        let inputs = Inputs { setpoint_hz: &|_| 40.0, load_nm: &|_, _, _| 10.0 };
        let final_speed = |m: &PlantModel| -> f64 {
            let truth = COLUMNS.iter().position(|c| *c == "true_omega_rad_s").expect("truth column");
            let mut w = Vec::new();
            let mut sink = |row: &[f64; COLUMNS.len()]| {
                w.push(row[truth]);
                Ok(())
            };
            run_into(m, 20.0, 1, &inputs, &mut |_| {}, &mut sink).expect("runs");
            w[w.len() - 500..].iter().sum::<f64>() / 500.0
        };
        // 3600 l/min/bar an hour is 0.001 per second: 0.02 after 20 s, as much again as the nominal leakage.
        let mut at_end = worn.at(20.0);
        at_end.wear = Default::default();
        let mut clean = worn.at(0.0);
        clean.wear = Default::default();
        let (w_worn, w_end, w_clean) = (final_speed(&worn), final_speed(&at_end), final_speed(&clean));
        assert!(w_clean - w_end > 2.0, "the leak must show: clean {w_clean:.2}, worn model {w_end:.2}");
        assert!((w_worn - w_end).abs() < 0.05 * (w_clean - w_end), "worn {w_worn:.2} vs {w_end:.2}");
    }

    #[test]
    fn the_load_sees_the_state_at_the_sample_start_and_true_load_is_what_was_applied() {
        use crate::plant::load::LoadSpec;
        let model = PlantModel::reference();
        let fan = LoadSpec::Centrifugal { torque_nm: 12.0, at_rad_s: 60.0 };
        let gear = LoadSpec::ShaftAngle { mean_nm: 0.0, amplitude_nm: 1.0, cycles_per_rev: 1.0 };
        let col = |name: &str| COLUMNS.iter().position(|c| *c == name).expect("column");
        let (w_col, load_col) = (col("true_omega_rad_s"), col("true_load_nm"));
        for spec in [fan, gear] {
            let load = spec.clone();
            let inputs = Inputs {
                setpoint_hz: &|t| if t > 0.2 { 40.0 } else { 0.0 },
                load_nm: &move |t, w, a| load.torque_at(t, w, a),
            };
            let mut rows = Vec::new();
            let mut sink = |row: &[f64; COLUMNS.len()]| {
                rows.push(*row);
                Ok(())
            };
            run_into(&model, 5.0, 1, &inputs, &mut |_| {}, &mut sink).expect("runs");
            let dt = model.sample_s();
            let mut angle = 0.0;
            for (k, row) in rows.iter().enumerate() {
                if k > 0 {
                    angle += 0.5 * (rows[k - 1][w_col] + row[w_col]) * dt;
                }
                let expected = spec.torque_at(row[0], row[w_col], angle);
                assert!((row[load_col] - expected).abs() < 1e-9, "{spec:?} row {k}: {} vs {expected}", row[load_col]);
            }
            assert!(angle > 20.0 && rows[rows.len() - 1][w_col] > 40.0, "{spec:?}: the shaft turned, {angle} rad");
        }
    }
}

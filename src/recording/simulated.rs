//! A simulated test-stand run kept in memory as a recording (the plant room streams rows; this room holds them):
//! what the tests, the estimator battery and the benches analyse.

use crate::error::KeyError;
use crate::plant::PlantModel;
use crate::plant::excitation;
use crate::plant::simulate::{COLUMNS, Inputs, RunError, run_into};

use super::Recording;

/// Runs the test stand for `duration_s` with the built-in setpoint program and the model's `[load]`
/// (the brake-load steps for `recorded`). Deterministic for a seed.
pub fn test_stand(
    model: &PlantModel,
    duration_s: f64,
    seed: u64,
    progress: &mut dyn FnMut(f64),
) -> Result<Recording, KeyError> {
    let load = model.load.clone();
    let inputs = Inputs { setpoint_hz: &excitation::setpoint_hz, load_nm: &move |t, w, a| load.torque_at(t, w, a) };
    run(model, duration_s, seed, &inputs, progress)
}

/// Runs the plant for `duration_s` with given inputs, sampling every `sensors.sample_ms`. Row k holds the state at
/// t_k and the inputs applied over [t_k, t_k+1).
pub fn run(
    model: &PlantModel,
    duration_s: f64,
    seed: u64,
    inputs: &Inputs<'_>,
    progress: &mut dyn FnMut(f64),
) -> Result<Recording, KeyError> {
    let n = (duration_s / model.sample_s()).floor() as usize + 1;
    let mut columns: Vec<Vec<f64>> = (0..COLUMNS.len()).map(|_| Vec::with_capacity(n)).collect();
    let mut sink = |row: &[f64; COLUMNS.len()]| {
        for (col, v) in columns.iter_mut().zip(row) {
            col.push(*v);
        }
        Ok(())
    };
    run_into(model, duration_s, seed, inputs, progress, &mut sink).map_err(|e| match e {
        RunError::Model(e) => e,
        RunError::Sink(e) => KeyError::new("(memory)".into(), e.to_string()),
        e @ RunError::Diverged(..) => KeyError::new("(model)".into(), e.to_string()),
    })?;
    Ok(Recording::from_columns("simulate", COLUMNS.iter().map(|c| c.to_string()).collect(), columns))
}

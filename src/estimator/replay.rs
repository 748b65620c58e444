//! Offline replay: turns a recording's columns into measurements (CONTRACT.md rules) and runs an estimator over them.

use super::{Estimate, Estimator, Measurement};
use crate::error::BadInput;
use crate::plant::PlantModel;
use crate::recording::Recording;
use crate::units::{bar_to_pa, cm3_per_rev_to_m3_per_rad};

/// Why a recording cannot be replayed: always bad input (the message names the column or key).
pub type ReplayError = BadInput;

/// Drive torque per row: `torque_nm` when present, else `D_m·(p_in − p_out)`. Missing cells give NaN.
pub fn drive_torques(rec: &Recording, model: &PlantModel, model_origin: &str) -> Result<Vec<f64>, ReplayError> {
    if let Some(t) = rec.present("torque_nm") {
        return Ok(t.to_vec());
    }
    let (Some(p_in), Some(p_out)) = (rec.present("p_in_bar"), rec.present("p_out_bar")) else {
        return Err(BadInput(format!(
            "recording {}: no drive torque: expected a `torque_nm` column, or `p_in_bar` and `p_out_bar`",
            rec.source
        )));
    };
    let Some(cm3) = model.motor.displacement_cm3 else {
        return Err(BadInput(format!(
            "model file {model_origin}: key `motor.displacement_cm3` is required to turn the recording's pressures into torque"
        )));
    };
    let d = cm3_per_rev_to_m3_per_rad(cm3);
    Ok(p_in.iter().zip(p_out).map(|(a, b)| d * bar_to_pa(a - b)).collect())
}

/// Shaft speed per row: `omega_rad_s` when present, else the backward difference of `theta_rad`.
pub fn speeds(rec: &Recording) -> Result<Vec<f64>, ReplayError> {
    if let Some(w) = rec.present("omega_rad_s") {
        return Ok(w.to_vec());
    }
    let Some(theta) = rec.present("theta_rad") else {
        return Err(BadInput(format!(
            "recording {}: no speed: expected an `omega_rad_s` or a `theta_rad` column",
            rec.source
        )));
    };
    let t = rec.t_s();
    Ok((0..theta.len())
        .map(|k| if k == 0 { f64::NAN } else { (theta[k] - theta[k - 1]) / (t[k] - t[k - 1]) })
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

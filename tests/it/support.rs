//! Helpers shared by the integration tests.
#![allow(dead_code)]

use std::path::PathBuf;

/// The project's root (where Cargo.toml is).
pub fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The `hydrolens` binary built for these tests.
pub fn bin() -> PathBuf {
    PathBuf::from(env!("CARGO_BIN_EXE_hydrolens"))
}

/// Normalised RMS error ‖a − b‖ / ‖b − mean(b)‖ over finite pairs.
pub fn nrmse(a: &[f64], b: &[f64]) -> f64 {
    let pairs: Vec<(f64, f64)> =
        a.iter().zip(b).filter(|(x, y)| x.is_finite() && y.is_finite()).map(|(x, y)| (*x, *y)).collect();
    let mean = pairs.iter().map(|p| p.1).sum::<f64>() / pairs.len() as f64;
    let num: f64 = pairs.iter().map(|(x, y)| (x - y).powi(2)).sum();
    let den: f64 = pairs.iter().map(|(_, y)| (y - mean).powi(2)).sum();
    (num / den).sqrt()
}

/// RMS of a − b over finite pairs.
pub fn rmse(a: &[f64], b: &[f64]) -> f64 {
    let d: Vec<f64> =
        a.iter().zip(b).filter(|(x, y)| x.is_finite() && y.is_finite()).map(|(x, y)| (x - y).powi(2)).collect();
    (d.iter().sum::<f64>() / d.len() as f64).sqrt()
}

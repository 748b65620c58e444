//! Which estimator a drive runs: the method of `[drives.estimator]` with the model file's `[estimator]` settings.

use crate::estimator::{self, Estimator, EstimatorSettings};
use crate::plant::PlantModel;

/// The estimator for a drive (settings were validated when the config was loaded).
pub fn build(settings: &EstimatorSettings, model: &PlantModel) -> Box<dyn Estimator> {
    tracing::info!(method = ?settings.method, "estimator");
    estimator::build(settings, model)
}

//! Which estimator a drive runs. Until the `est` branch lands, every method maps to the
//! [`fallback_observer`](super::fallback_observer): a minimal observer so that the service works end to end.
//! Switch [`build`] to `estimator::build` when it exists.

use crate::estimator::Estimator;
use crate::plant::PlantModel;

use super::config::EstimatorMethod;
use super::fallback_observer::FallbackObserver;

/// The estimator for a drive. `method` is kept for the real estimators; the fallback ignores it.
pub fn build(method: EstimatorMethod, model: &PlantModel) -> Box<dyn Estimator> {
    tracing::info!(?method, "estimator: using service::fallback_observer (the est branch has not landed yet)");
    Box::new(FallbackObserver::new(model.motor.inertia_kg_m2, model.motor.viscous_nm_s_rad))
}

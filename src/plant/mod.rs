//! The plant: VFD → pump → high-pressure line → hydraulic motor → load (PHYSICS.md §1). Pure: no clock, no I/O.

pub mod dynamics;
pub mod effects;
pub mod excitation;
pub mod load;
pub mod model;
pub mod scenario;
pub mod simulate;

pub use dynamics::{Coefficients, Plant, PlantState};
pub use effects::Effects;
pub use load::LoadSpec;
pub use model::{ModelError, PlantModel};

/// Inlet and outlet pressure a sensor reads (bar, gauge): vacuum to the top of a 400 bar sensor. The simulator's
/// sensors saturate there; a recording's cell outside it is not a measurement (`recording::PRESSURE_RANGE_BAR`).
pub const PRESSURE_SENSOR_RANGE_BAR: (f64, f64) = (-1.0, 400.0);

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

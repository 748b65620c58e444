//! Modbus: the register map (pure encode/decode), the client with timeouts and reconnects, and the plant simulator.

pub mod bus;
pub mod client;
pub mod line;
pub mod map;
pub mod simulator;

pub use map::{RegisterMap, RegisterSpec, Table, ValueType, WordOrder};

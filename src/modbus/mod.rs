//! Modbus: the register map (pure encode/decode), an RTU line's timing (pure), the client with timeouts and
//! reconnects (TCP, RTU, RTU over TCP), the bus task of a shared RTU line, and the plant simulator.

pub mod bus;
pub mod client;
pub mod line;
pub mod map;
pub mod simulator;

pub use map::{RegisterMap, RegisterSpec, Table, ValueType, WordOrder};

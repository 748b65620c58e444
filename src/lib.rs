//! hydrolens watches and drives an electro-hydraulic drive (VFD → pump → hydraulic motor) over Modbus TCP or RTU:
//! it polls, estimates speed and load torque, regulates the speed, records, serves a dashboard, and explains
//! where a plant model and a recording disagree.
//!
//! # Layout
//! The rooms, and which may use which (a room uses only those listed before it):
//! - [`units`], [`error`]: conversions and the bad-input marker shared by everyone (which errors are bad input is
//!   decided here at the top, [`is_bad_input`]).
//! - [`plant`]: PURE physics (model file, effects, loads, RK4 integrator, test-stand run). No clock, no I/O.
//! - [`recording`]: the contract's CSV, read strictly by one streaming reader (whole or batch by batch, plain or
//!   gzip) and written streaming with rotation; a simulated run kept as a recording (`recording::simulated`).
//! - [`output`]: the files a command writes: checked against its inputs and each other before any work, written
//!   beside and renamed into place (a failed run leaves the old file).
//! - [`modbus`]: the register map with a cycle's read plan, sample decoding and write planning, and the RTU line's
//!   timing (pure), the client (TCP, RTU, RTU over TCP), the bus task that shares an RTU line among its drives, and
//!   the plant simulator server.
//! - [`estimator`]: PURE RLS+SGD and Kalman estimators; fed Δt and samples.
//! - [`replay`]: a recording's columns turned into the estimators' measurements (which column, which unit), and an
//!   estimator run over them, whole or batch by batch.
//! - [`replay_file`]: `hydrolens estimate`: a recording file streamed through an estimator into a CSV, on two
//!   threads (one reads and writes, one estimates and formats).
//! - [`analysis`]: PURE mismatch analysis (fit, free-run residuals, effect search) + its HTML report at the edge.
//! - [`condition`]: condition monitoring: the analysis on a drive's recent data, checks kept, alarms with a margin
//!   against chatter (PURE), and the checks' JSON-lines history at the edge.
//! - [`control`]: PURE control law (speed PI with load feed-forward, clamp, ramp limit, nothing on stale data).
//! - [`service`]: the poll loops per drive (modbus → estimator → control → modbus) around a PURE drive cycle
//!   (`service::cycle`: a validated sample and its time → the writes and the row), snapshots, history, recording,
//!   the low-priority thread that runs each drive's [`condition`] checks on its history, and the registry its
//!   outlets register their families in; its modules' floors are its own `# Layout`. The poll loops count what they
//!   see in the drives' snapshots and never touch a metric.
//! - [`metrics`]: the first of the service's outlets, which read its shared state from above: the drives'
//!   families, read from their snapshots at each scrape, and the exposition.
//! - [`mqtt`]: the outlet that publishes each drive's status and condition to a broker, on its own thread.
//! - [`http`]: the outlet an operator uses, the axum router; never uses [`modbus`]; serves [`metrics`]' exposition
//!   and reports [`mqtt`]'s health in `/api/status`.
//! - [`server`]: the service and its HTTP front put together (what `serve`, `demo` and the tests run).
//!
//! The binary (`main.rs`, which parses the command line, and `commands/`, the subcommands' work) stands above them
//! all, and is the only place `anyhow` lives.

pub mod analysis;
pub mod condition;
pub mod control;
pub mod error;
pub mod estimator;
pub mod http;
pub mod metrics;
pub mod modbus;
pub mod mqtt;
pub mod output;
pub mod plant;
pub mod recording;
pub mod replay;
pub mod replay_file;
pub mod server;
pub mod service;
pub mod units;

pub use error::BadInput;

/// True when some error in the chain is bad input: a model file, config, recording or argument the user can fix
/// (exit 2); everything else is exit 1. Each room's error type answers for itself (`is_bad_input`), so an error that
/// wraps another (an [`replay_file::EstimateError`] around a recording's) can travel through `?` and keep its code.
pub fn is_bad_input(err: &(dyn std::error::Error + 'static)) -> bool {
    let mut cur: Option<&(dyn std::error::Error + 'static)> = Some(err);
    while let Some(e) = cur {
        if e.is::<BadInput>() {
            return true;
        }
        // a bad-input error carried by an I/O error (the service's start, say)
        if let Some(io) = e.downcast_ref::<std::io::Error>()
            && io.get_ref().is_some_and(|inner| inner.is::<BadInput>())
        {
            return true;
        }
        if let Some(m) = e.downcast_ref::<plant::ModelError>() {
            return m.is_bad_input();
        }
        if let Some(r) = e.downcast_ref::<recording::RecordingError>() {
            return r.is_bad_input();
        }
        if let Some(c) = e.downcast_ref::<service::ConfigError>() {
            return c.is_bad_input();
        }
        if let Some(x) = e.downcast_ref::<replay_file::EstimateError>() {
            return x.is_bad_input();
        }
        cur = e.source();
    }
    false
}

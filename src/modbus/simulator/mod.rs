//! The plant simulator: the plant model behind the default register map, served in real time over Modbus TCP, RTU
//! on a serial device, or RTU framing over TCP. Input register 6 holds the drive's output power
//! ([`DRIVE_POWER_W`](super::map::DRIVE_POWER_W), the optional `drive_power_w` entry of the map), through the
//! simulated motor's [`MOTOR_EFFICIENCY`].
//!
//! [`DriveSim`] is the drive and plant as a pure state machine stepped one sample at a time; [`Simulator`] adds the
//! clock and the Modbus server (`serve_until`, so it stops cleanly on a signal). It serves one plant at any unit
//! id, or (an RS-485 line with several drives) one plant per listed unit id, each with a noise seed of its own,
//! and then leaves requests to other unit ids unanswered, as a line without that device would.

use crate::error::KeyError;
use std::future::Future;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use tokio::net::TcpListener;
use tokio_modbus::server::tcp::{Server, accept_tcp_connection};
use tokio_modbus::server::{rtu, rtu_over_tcp};
use tokio_modbus::{ExceptionCode, Request, Response, SlaveRequest};
use tokio_util::sync::CancellationToken;

use super::line::SerialLine;
use super::map::Table;
use crate::plant::model::PlantModel;

mod drive;

use drive::RealTime;
pub use drive::{DriveSim, Faults, MOTOR_EFFICIENCY, Truth, drive_power_w};

/// Shared access to a running simulator's drive, for tests and the demo.
#[derive(Clone)]
pub struct SimHandle(Arc<Mutex<DriveSim>>);

impl SimHandle {
    /// Locks the drive (a poisoned lock is taken over: the state is plain data).
    pub fn lock(&self) -> MutexGuard<'_, DriveSim> {
        self.0.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// The Modbus face of the simulator.
#[derive(Clone)]
struct ModbusService {
    drive: SimHandle,
    /// One plant per unit id; empty: `drive` answers every unit id.
    units: Arc<Vec<(u8, SimHandle)>>,
}

type Reply = Result<Option<Response>, ExceptionCode>;

impl tokio_modbus::server::Service for ModbusService {
    type Request = SlaveRequest<'static>;
    type Response = Option<Response>;
    type Exception = ExceptionCode;
    type Future = Pin<Box<dyn Future<Output = Reply> + Send>>;

    fn call(&self, req: Self::Request) -> Self::Future {
        let drive = if self.units.is_empty() {
            &self.drive
        } else {
            match self.units.iter().find(|(unit, _)| *unit == req.slave) {
                Some((_, d)) => d,
                // no such device on the line: nobody answers
                None => return Box::pin(async { Ok(None) }),
            }
        };
        let (reply, faults) = {
            let mut d = drive.lock();
            // the register image is exactly as of now, not as of the clock task's last tick
            d.catch_up();
            let faults = d.faults;
            let reply = match req.request {
                Request::ReadInputRegisters(a, n) => d.read(Table::Input, a, n).map(Response::ReadInputRegisters),
                Request::ReadHoldingRegisters(a, n) => d.read(Table::Holding, a, n).map(Response::ReadHoldingRegisters),
                Request::WriteSingleRegister(a, v) => d.write(a, &[v]).map(|()| Response::WriteSingleRegister(a, v)),
                Request::WriteMultipleRegisters(a, ref vs) => {
                    d.write(a, vs).map(|()| Response::WriteMultipleRegisters(a, vs.len() as u16))
                }
                _ => Err(ExceptionCode::IllegalFunction),
            };
            (reply, faults)
        };
        Box::pin(async move {
            if let Some(delay) = faults.reply_delay {
                tokio::time::sleep(delay).await;
            }
            if faults.no_reply {
                return Ok(None);
            }
            if let Some(code) = faults.exception {
                return Err(code);
            }
            reply.map(Some)
        })
    }
}

/// The simulator: a drive (or one per unit id), its clock and its Modbus server.
pub struct Simulator {
    drive: SimHandle,
    units: Arc<Vec<(u8, SimHandle)>>,
}

/// How long the serial simulator waits before reopening a device that failed or is not there.
const REOPEN_EVERY: Duration = Duration::from_millis(100);

impl Simulator {
    /// One plant, answering every unit id.
    pub fn new(model: PlantModel, seed: u64) -> Result<Simulator, KeyError> {
        Ok(Simulator { drive: SimHandle(Arc::new(Mutex::new(DriveSim::new(model, seed)?))), units: Arc::default() })
    }

    /// One plant per unit id (noise seeds `seed`, `seed + 1`, …); other unit ids get no answer. An empty list is
    /// [`Simulator::new`].
    pub fn with_units(model: PlantModel, seed: u64, units: &[u8]) -> Result<Simulator, KeyError> {
        let mut sim = Simulator::new(model.clone(), seed)?;
        let mut plants = Vec::with_capacity(units.len());
        for (i, &unit) in units.iter().enumerate() {
            let drive = if i == 0 {
                sim.drive.clone()
            } else {
                SimHandle(Arc::new(Mutex::new(DriveSim::new(model.clone(), seed + i as u64)?)))
            };
            plants.push((unit, drive));
        }
        sim.units = Arc::new(plants);
        Ok(sim)
    }

    /// The plant (the first unit's, with several).
    pub fn handle(&self) -> SimHandle {
        self.drive.clone()
    }

    /// The plant at `unit` (with [`Simulator::with_units`]; else the one plant).
    pub fn handle_for(&self, unit: u8) -> Option<SimHandle> {
        if self.units.is_empty() {
            return Some(self.drive.clone());
        }
        self.units.iter().find(|(u, _)| *u == unit).map(|(_, d)| d.clone())
    }

    fn service(&self) -> ModbusService {
        ModbusService { drive: self.drive.clone(), units: self.units.clone() }
    }

    fn start_clocks(&self, shutdown: &CancellationToken) -> Vec<tokio::task::JoinHandle<()>> {
        let mut plants = vec![self.drive.clone()];
        plants.extend(self.units.iter().skip(1).map(|(_, d)| d.clone()));
        plants.into_iter().map(|d| tokio::spawn(run_clock(d, shutdown.clone()))).collect()
    }

    async fn stop_clocks(clocks: Vec<tokio::task::JoinHandle<()>>, shutdown: &CancellationToken) {
        shutdown.cancel();
        for clock in clocks {
            let _ = clock.await;
        }
        tracing::info!("plant simulator stopped");
    }

    /// Runs the plant in real time and serves Modbus TCP on `listener` until `shutdown` fires.
    pub async fn run(self, listener: TcpListener, shutdown: CancellationToken) -> std::io::Result<()> {
        let addr = listener.local_addr()?;
        tracing::info!(%addr, "plant simulator serving Modbus TCP");
        let clocks = self.start_clocks(&shutdown);
        let server = Server::new(listener);
        let service = self.service();
        let on_connected = move |stream, socket_addr: SocketAddr| {
            let service = service.clone();
            async move {
                tracing::debug!(%socket_addr, "simulator: client connected");
                accept_tcp_connection(stream, socket_addr, move |_| Ok(Some(service.clone())))
            }
        };
        let on_process_error = |err| tracing::debug!(%err, "simulator: connection ended");
        let stop = shutdown.clone();
        let result = server.serve_until(&on_connected, on_process_error, async move { stop.cancelled().await }).await;
        Simulator::stop_clocks(clocks, &shutdown).await;
        result.map(|_| ())
    }

    /// As [`Simulator::run`], with RTU framing on each TCP connection (what a serial gateway passes through).
    pub async fn run_rtu_over_tcp(self, listener: TcpListener, shutdown: CancellationToken) -> std::io::Result<()> {
        let addr = listener.local_addr()?;
        tracing::info!(%addr, "plant simulator serving Modbus RTU over TCP");
        let clocks = self.start_clocks(&shutdown);
        let server = rtu_over_tcp::Server::new(listener);
        let service = self.service();
        let on_connected = move |stream, socket_addr: SocketAddr| {
            let service = service.clone();
            async move {
                tracing::debug!(%socket_addr, "simulator: client connected");
                rtu_over_tcp::accept_tcp_connection(stream, socket_addr, move |_| Ok(Some(service.clone())))
            }
        };
        let on_process_error = |err| tracing::debug!(%err, "simulator: connection ended");
        let stop = shutdown.clone();
        let result = server.serve_until(&on_connected, on_process_error, async move { stop.cancelled().await }).await;
        Simulator::stop_clocks(clocks, &shutdown).await;
        result.map(|_| ())
    }

    /// Runs the plant in real time and serves Modbus RTU on the serial device `path` until `shutdown` fires. A
    /// device that is missing, fails or goes away (a line unplugged) is reopened every `REOPEN_EVERY`.
    pub async fn run_serial(self, path: &str, line: SerialLine, shutdown: CancellationToken) -> std::io::Result<()> {
        tracing::info!(
            path,
            baud_rate = line.baud_rate,
            parity = line.parity.name(),
            stop_bits = line.stop_bits,
            "plant simulator serving Modbus RTU"
        );
        let clocks = self.start_clocks(&shutdown);
        let mut logged_missing = false;
        while !shutdown.is_cancelled() {
            match super::client::open_serial(path, &line) {
                Ok(port) => {
                    logged_missing = false;
                    tracing::debug!(path, "simulator: serial device open");
                    let stop = shutdown.clone();
                    let served =
                        rtu::Server::new(port).serve_until(self.service(), async move { stop.cancelled().await }).await;
                    if let Err(e) = served {
                        tracing::warn!(path, error = %e, "simulator: serial line failed, reopening");
                    }
                }
                Err(e) => {
                    if !logged_missing {
                        tracing::warn!(path, error = %e, "simulator: cannot open the serial device, retrying");
                        logged_missing = true;
                    }
                }
            }
            tokio::select! {
                () = shutdown.cancelled() => {}
                () = tokio::time::sleep(REOPEN_EVERY) => {}
            }
        }
        Simulator::stop_clocks(clocks, &shutdown).await;
        Ok(())
    }
}

/// Steps the drive in real time: as many samples as wall time asks for, at each tick of a 1 ms-resolution timer;
/// requests catch up to the exact instant on their own.
async fn run_clock(drive: SimHandle, shutdown: CancellationToken) {
    let period = {
        let mut d = drive.lock();
        d.clock = Some(RealTime { start: tokio::time::Instant::now(), done: 0 });
        Duration::from_secs_f64(d.sample_s())
    };
    let mut tick = tokio::time::interval(period);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            () = shutdown.cancelled() => break,
        }
        drive.lock().catch_up();
    }
}

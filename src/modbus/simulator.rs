//! The plant simulator: the plant model behind the default register map, served in real time over Modbus TCP, RTU
//! on a serial device, or RTU framing over TCP. Input register 6 holds the drive's output power ([`DRIVE_POWER_W`],
//! the optional `drive_power_w` entry of the map), through the simulated motor's [`MOTOR_EFFICIENCY`].
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
use super::map::{DRIVE_POWER_W, RegisterMap, Table, control, status};
use crate::plant::dynamics::{Coefficients, Plant};
use crate::plant::model::PlantModel;
use crate::plant::simulate::SensorNoise;
use crate::units::{pa_to_bar, rad_s_to_rpm};

/// Faults a test can switch on to see how a client copes (the fault-injection harness).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Faults {
    /// Hold every reply this long before sending it.
    pub reply_delay: Option<Duration>,
    /// Answer every request with this Modbus exception.
    pub exception: Option<ExceptionCode>,
    /// Never answer (the request is swallowed).
    pub no_reply: bool,
    /// The sample counter stops moving (the PLC's data are frozen).
    pub freeze_counter: bool,
    /// Report this inlet pressure (bar) instead of the measured one, e.g. out of range.
    pub inlet_pressure_override_bar: Option<f64>,
    /// The drive in local mode: it answers setpoint writes OK but runs at this frequency (Hz), ready and running.
    pub local_hz: Option<f64>,
}

/// Efficiency of the simulated induction motor, copper and iron (its slip is the plant's `motor_slip`): the drive
/// delivers the air-gap power T_p·ω_sync divided by it while motoring, and takes back T_p·ω_sync times it while
/// the pump drives the motor (braking). About that of a 1 kW four-pole IE3 motor at full load.
pub const MOTOR_EFFICIENCY: f64 = 0.85;

/// The drive's output power (W) for an air-gap power `air_gap_w` (T_p·ω_sync), through [`MOTOR_EFFICIENCY`].
pub fn drive_power_w(air_gap_w: f64) -> f64 {
    if air_gap_w >= 0.0 { air_gap_w / MOTOR_EFFICIENCY } else { air_gap_w * MOTOR_EFFICIENCY }
}

/// The ground truth at the current sample, for tests and the demo.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Truth {
    pub t_s: f64,
    pub omega_rad_s: f64,
    pub p_in_bar: f64,
    pub load_nm: f64,
    /// The motor's shaft angle turned since the start (rad): what a `shaft_angle` load follows.
    pub shaft_angle_rad: f64,
    pub f_drive_hz: f64,
    pub f_set_hz: f64,
    pub tripped: bool,
    /// The drive's output power (W): what its register 6 serves, before quantisation.
    pub drive_power_w: f64,
    /// Since the start (J): the drive's output energy, and the energy given to the load (∫ T_L ω dt), each sample
    /// integrated by the trapezoid.
    pub drive_energy_j: f64,
    pub load_energy_j: f64,
}

/// The drive and plant, stepped one sample at a time, with the register image a PLC would show.
pub struct DriveSim {
    model: PlantModel,
    plant: Plant,
    noise: SensorNoise,
    map: RegisterMap,
    sample: u64,
    counter: u16,
    setpoint_hz: f64,
    control_word: u16,
    watchdog_value: u16,
    /// Sample at which the watchdog register last changed; None until the first write arms it.
    watchdog_changed_at: Option<u64>,
    tripped: bool,
    fault: bool,
    input_image: Vec<u16>,
    /// The load applied over the last sample, from the plant's state at its start.
    load_nm: f64,
    /// The motor's shaft angle since the start (rad): ω integrated by the trapezoid over each sample.
    shaft_angle_rad: f64,
    /// The drive's output energy and the load's since the start (J), for [`Truth`].
    drive_energy_j: f64,
    load_energy_j: f64,
    pub faults: Faults,
    /// Writes accepted (all holding-register writes), for tests that check a client wrote nothing.
    pub writes: u64,
    /// Wall-clock pacing once [`Simulator::run`] has started it; None while stepped by hand.
    clock: Option<RealTime>,
}

/// Wall-clock pacing: sample k is due at `start + k·sample`. On tokio's clock, so that a test with a paused clock
/// runs the plant in virtual time (outside a runtime it is the system's monotonic clock).
#[derive(Debug, Clone, Copy)]
struct RealTime {
    start: tokio::time::Instant,
    done: u64,
}

impl DriveSim {
    /// At standstill, drive stopped, watchdog unarmed.
    pub fn new(model: PlantModel, seed: u64) -> Result<DriveSim, KeyError> {
        let coefficients = Coefficients::from_model(&model)?;
        let noise = SensorNoise::new(&model, seed);
        let map = RegisterMap::default();
        let mut sim = DriveSim {
            plant: Plant::new(coefficients),
            noise,
            map,
            sample: 0,
            counter: 0,
            setpoint_hz: 0.0,
            control_word: 0,
            watchdog_value: 0,
            watchdog_changed_at: None,
            tripped: false,
            fault: false,
            input_image: vec![0; 7],
            load_nm: 0.0,
            shaft_angle_rad: 0.0,
            drive_energy_j: 0.0,
            load_energy_j: 0.0,
            faults: Faults::default(),
            writes: 0,
            clock: None,
            model,
        };
        sim.refresh_image();
        Ok(sim)
    }

    pub fn sample_s(&self) -> f64 {
        self.model.sample_s()
    }

    fn comm_timeout_samples(&self) -> u64 {
        let ms = self.model.drive.as_ref().map_or(1000, |d| d.comm_timeout_ms) as f64;
        (ms / self.model.sensors.sample_ms).ceil() as u64
    }

    fn ready(&self) -> bool {
        !self.tripped && !self.fault
    }

    fn status_word(&self) -> u16 {
        let mut s = 0;
        if self.ready() {
            s |= status::READY;
        }
        if self.ready() && self.control_word & control::RUN != 0 {
            s |= status::RUNNING;
        }
        if self.fault {
            s |= status::FAULT;
        }
        if self.tripped {
            s |= status::COMM_LOSS_TRIP;
        }
        s
    }

    /// Steps every sample that wall time has made due since the clock started, catching up at most one second
    /// (a stalled process skips ahead rather than racing). Does nothing while the drive is stepped by hand.
    fn catch_up(&mut self) {
        let Some(mut clock) = self.clock else { return };
        let sample_s = self.sample_s();
        let due = (clock.start.elapsed().as_secs_f64() / sample_s) as u64;
        let max_catch_up = (1.0 / sample_s).ceil() as u64;
        if due.saturating_sub(clock.done) > max_catch_up {
            clock.done = due - max_catch_up;
        }
        while clock.done < due {
            self.step();
            clock.done += 1;
        }
        self.clock = Some(clock);
    }

    /// Advances the plant by one sample and refreshes the register image.
    pub fn step(&mut self) {
        if let Some(changed) = self.watchdog_changed_at
            && !self.tripped
            && self.sample.saturating_sub(changed) >= self.comm_timeout_samples()
        {
            self.tripped = true;
            tracing::warn!(t_s = self.plant.t_s(), "simulator: watchdog unchanged, comm-loss trip");
        }
        let run = self.control_word & control::RUN != 0;
        let f_cmd = match self.faults.local_hz {
            Some(hz) => hz,
            None if run && self.ready() => self.setpoint_hz,
            None => 0.0,
        };
        let t = self.plant.t_s();
        let omega_rad_s = self.plant.state().omega_rad_s;
        let drive_before_w = self.drive_power_w();
        self.load_nm = self.model.load.torque_at(t, omega_rad_s, self.shaft_angle_rad);
        self.plant.wear(&self.model);
        self.plant.advance(self.sample_s(), f_cmd, self.load_nm);
        let omega_mean = 0.5 * (omega_rad_s + self.plant.state().omega_rad_s);
        self.shaft_angle_rad += omega_mean * self.sample_s();
        self.drive_energy_j += 0.5 * (drive_before_w + self.drive_power_w()) * self.sample_s();
        self.load_energy_j += self.load_nm * omega_mean * self.sample_s();
        self.sample += 1;
        if !self.faults.freeze_counter {
            self.counter = self.counter.wrapping_add(1);
        }
        self.refresh_image();
    }

    /// The drive's output power now (W): the pump's torque T_p = D_p ΔP at the synchronous speed 2π f / pole_pairs,
    /// through [`MOTOR_EFFICIENCY`].
    fn drive_power_w(&self) -> f64 {
        let (s, c) = (self.plant.state(), self.plant.coefficients());
        let pump_torque_nm = c.pump_m3_rad * (s.p_in_pa - c.back_pressure_pa);
        drive_power_w(pump_torque_nm * 2.0 * std::f64::consts::PI * s.f_hz / c.pole_pairs)
    }

    fn refresh_image(&mut self) {
        let s = self.plant.state();
        let back_bar = pa_to_bar(self.plant.coefficients().back_pressure_pa);
        let reading = self.noise.pressure_reading(pa_to_bar(s.p_in_pa));
        let p_in = self.faults.inlet_pressure_override_bar.unwrap_or(reading);
        let values = [
            (self.map.inlet_pressure_bar, p_in),
            (self.map.outlet_pressure_bar, self.noise.pressure_reading(back_bar)),
            (self.map.shaft_speed_rpm, rad_s_to_rpm(s.omega_rad_s + self.noise.speed())),
            (self.map.drive_frequency_hz, s.f_hz),
            (self.map.status_word, f64::from(self.status_word())),
            (self.map.sample_counter, f64::from(self.counter)),
            (DRIVE_POWER_W, self.drive_power_w()),
        ];
        for (spec, v) in values {
            let words = spec.encode_saturating(v);
            let at = usize::from(spec.address);
            self.input_image[at..at + words.len()].copy_from_slice(&words);
        }
    }

    /// The ground truth now.
    pub fn truth(&self) -> Truth {
        let s = self.plant.state();
        Truth {
            t_s: self.plant.t_s(),
            omega_rad_s: s.omega_rad_s,
            p_in_bar: pa_to_bar(s.p_in_pa),
            load_nm: self.load_nm,
            shaft_angle_rad: self.shaft_angle_rad,
            f_drive_hz: s.f_hz,
            f_set_hz: self.setpoint_hz,
            tripped: self.tripped,
            drive_power_w: self.drive_power_w(),
            drive_energy_j: self.drive_energy_j,
            load_energy_j: self.load_energy_j,
        }
    }

    /// Sets the drive's fault state (as a PLC would on an overload).
    pub fn set_fault(&mut self, fault: bool) {
        self.fault = fault;
        self.refresh_image();
    }

    fn holding(&self) -> [u16; 3] {
        let sp = self.map.frequency_setpoint_hz.encode_saturating(self.setpoint_hz);
        [sp[0], self.control_word, self.watchdog_value]
    }

    /// Reads `count` registers from `address` of a table.
    pub fn read(&self, table: Table, address: u16, count: u16) -> Result<Vec<u16>, ExceptionCode> {
        let image: Vec<u16> = match table {
            Table::Input => self.input_image.clone(),
            Table::Holding => self.holding().to_vec(),
        };
        let (a, n) = (usize::from(address), usize::from(count));
        if n == 0 || a + n > image.len() {
            return Err(ExceptionCode::IllegalDataAddress);
        }
        Ok(image[a..a + n].to_vec())
    }

    /// Writes holding registers starting at `address`.
    pub fn write(&mut self, address: u16, values: &[u16]) -> Result<(), ExceptionCode> {
        let end = usize::from(address) + values.len();
        if values.is_empty() || end > 3 {
            return Err(ExceptionCode::IllegalDataAddress);
        }
        self.writes += 1;
        for (i, &v) in values.iter().enumerate() {
            match usize::from(address) + i {
                0 => {
                    let hz =
                        self.map.frequency_setpoint_hz.decode(&[v]).map_err(|_| ExceptionCode::IllegalDataValue)?;
                    self.setpoint_hz = hz;
                }
                1 => {
                    let rising_reset = v & control::FAULT_RESET != 0 && self.control_word & control::FAULT_RESET == 0;
                    if rising_reset {
                        self.tripped = false;
                        self.fault = false;
                        if self.watchdog_changed_at.is_some() {
                            self.watchdog_changed_at = Some(self.sample);
                        }
                    }
                    self.control_word = v;
                }
                _ => {
                    if self.watchdog_changed_at.is_none() || v != self.watchdog_value {
                        self.watchdog_changed_at = Some(self.sample);
                    }
                    self.watchdog_value = v;
                }
            }
        }
        self.refresh_image();
        Ok(())
    }
}

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

#[cfg(test)]
mod tests {
    use super::*;

    fn sim() -> DriveSim {
        DriveSim::new(PlantModel::reference(), 1).expect("reference is hydraulic")
    }

    #[test]
    fn runs_only_with_run_bit_and_trips_on_watchdog() {
        let mut d = sim();
        d.write(0, &[2000]).expect("setpoint 20 Hz");
        for _ in 0..500 {
            d.step();
        }
        assert_eq!(d.truth().f_drive_hz, 0.0, "no run bit, no motion");
        d.write(1, &[control::RUN]).expect("run");
        d.write(2, &[1]).expect("arm watchdog");
        for _ in 0..900 {
            d.step();
        }
        assert!(d.truth().f_drive_hz > 10.0);
        assert_eq!(d.read(Table::Input, 4, 1).expect("status")[0] & status::RUNNING, status::RUNNING);
        for _ in 0..200 {
            d.step();
        }
        assert!(d.truth().tripped, "watchdog unchanged for 1.1 s");
        assert_ne!(d.read(Table::Input, 4, 1).expect("status")[0] & status::COMM_LOSS_TRIP, 0);
        for _ in 0..2000 {
            d.step();
        }
        assert!(d.truth().f_drive_hz < 0.01, "ramped to 0 Hz");
        d.write(1, &[control::RUN | control::FAULT_RESET]).expect("reset");
        assert!(!d.truth().tripped);
        d.write(1, &[control::RUN]).expect("run");
        for _ in 0..500 {
            d.step();
            d.write(2, &[(d.sample % 1000) as u16]).expect("kick");
        }
        assert!(d.truth().f_drive_hz > 10.0, "runs again after reset");
    }

    #[test]
    fn counter_moves_once_per_sample_and_bad_addresses_are_refused() {
        let mut d = sim();
        let c0 = d.read(Table::Input, 5, 1).expect("counter")[0];
        d.step();
        d.step();
        assert_eq!(d.read(Table::Input, 5, 1).expect("counter")[0], c0.wrapping_add(2));
        assert_eq!(d.read(Table::Input, 5, 3), Err(ExceptionCode::IllegalDataAddress));
        assert_eq!(d.write(3, &[1]), Err(ExceptionCode::IllegalDataAddress));
    }

    #[test]
    fn register_6_is_the_drives_output_power_and_its_energy_is_integrated() {
        let mut model = PlantModel::reference();
        model.load = crate::plant::load::LoadSpec::Constant { torque_nm: 8.0 };
        let mut d = DriveSim::new(model, 1).expect("reference is hydraulic");
        d.write(0, &[2500]).expect("setpoint 25 Hz");
        d.write(1, &[control::RUN]).expect("run");
        for _ in 0..3000 {
            d.step();
        }
        let t = d.truth();
        let c = Coefficients::from_model(&PlantModel::reference()).expect("hydraulic");
        let air_gap_w =
            c.pump_m3_rad * (t.p_in_bar * 1e5 - c.back_pressure_pa) * 2.0 * std::f64::consts::PI * t.f_drive_hz
                / c.pole_pairs;
        assert!((t.drive_power_w - air_gap_w / MOTOR_EFFICIENCY).abs() < 1e-9 * air_gap_w, "{t:?}");
        let read = DRIVE_POWER_W.decode(&d.read(Table::Input, 6, 1).expect("register 6")).expect("decodes");
        assert!((read - t.drive_power_w).abs() <= 0.5, "{read} W read, {} W true", t.drive_power_w);
        assert!(t.drive_power_w > 100.0 && t.drive_energy_j > 100.0 && t.load_energy_j > 0.0, "{t:?}");
        assert!(t.load_energy_j < t.drive_energy_j, "the load gets less than the drive gives");
        assert_eq!(drive_power_w(-100.0), -100.0 * MOTOR_EFFICIENCY, "braking: the drive takes back less");
    }

    #[test]
    fn a_state_dependent_load_is_the_one_simulate_applies() {
        use crate::plant::load::LoadSpec;
        use crate::plant::simulate::{COLUMNS, Inputs, run_into};
        let mut model = PlantModel::reference();
        let loads = [
            LoadSpec::Centrifugal { torque_nm: 12.0, at_rad_s: 60.0 },
            LoadSpec::ShaftAngle { mean_nm: 8.0, amplitude_nm: 4.0, cycles_per_rev: 0.3 },
            LoadSpec::Random { mean_nm: 8.0, sd_nm: 3.0, correlation_s: 0.5, seed: 4 },
        ];
        for load in loads {
            model.load = load.clone();
            let mut d = DriveSim::new(model.clone(), 1).expect("reference is hydraulic");
            d.write(0, &[3000]).expect("setpoint 30 Hz");
            d.write(1, &[control::RUN]).expect("run");
            let mut sim_rows = Vec::new();
            for _ in 0..3000 {
                let before = d.truth();
                d.step();
                sim_rows.push((before.omega_rad_s, before.shaft_angle_rad, d.truth().load_nm));
            }
            let spec = load.clone();
            let inputs = Inputs { setpoint_hz: &|_| 30.0, load_nm: &move |t, w, a| spec.torque_at(t, w, a) };
            let mut rows = Vec::new();
            let mut sink = |row: &[f64; COLUMNS.len()]| {
                rows.push((row[7], row[9]));
                Ok(())
            };
            run_into(&model, 3.0, 1, &inputs, &mut |_| {}, &mut sink).expect("runs");
            assert!(rows.len() >= sim_rows.len());
            for (k, ((w, l), (w_sim, _, l_sim))) in rows.iter().zip(&sim_rows).enumerate() {
                assert!(
                    (w - w_sim).abs() < 1e-9 && (l - l_sim).abs() < 1e-9,
                    "{load:?} row {k}: {w} {l} vs {w_sim} {l_sim}"
                );
            }
            let (w_end, angle_end, _) = sim_rows[sim_rows.len() - 1];
            assert!(w_end > 30.0 && angle_end > 30.0, "{load:?}: turning, {w_end} rad/s, {angle_end} rad");
        }
    }
}

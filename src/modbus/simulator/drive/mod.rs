//! The simulated drive and plant as a pure state machine, stepped one sample at a time: the register image it
//! serves, the writes it takes (setpoint, control word, watchdog), its trips, the faults a test switches on, and the
//! truth a test compares against.

use crate::error::KeyError;
use std::time::Duration;

use tokio_modbus::ExceptionCode;

use crate::modbus::map::{DRIVE_POWER_W, RegisterMap, Table, control, status};
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
    /// Report this shaft speed (rad/s) instead of the measured one: a frozen tachometer.
    pub speed_override_rad_s: Option<f64>,
    /// Report the shaft speed times this: a tachometer on a slipping coupling, or read with the wrong scale.
    pub speed_scale: Option<f64>,
    /// Report the drive's output frequency times this: a read-back scaled wrong (a 50/60 Hz scale, slip
    /// compensation).
    pub frequency_scale: Option<f64>,
    /// Every value but the sample counter stops updating: the PLC's copy of the drive's data stopped (a fieldbus
    /// link to the drive, an input task) while its own counter runs on.
    pub freeze_values: bool,
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
    /// Wall-clock pacing once [`super::Simulator::run`] has started it; None while stepped by hand.
    pub(super) clock: Option<RealTime>,
}

/// Wall-clock pacing: sample k is due at `start + k·sample`. On tokio's clock, so that a test with a paused clock
/// runs the plant in virtual time (outside a runtime it is the system's monotonic clock).
#[derive(Debug, Clone, Copy)]
pub(super) struct RealTime {
    pub(super) start: tokio::time::Instant,
    pub(super) done: u64,
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
    pub(super) fn catch_up(&mut self) {
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
        if !self.fault
            && let Some((what, v)) = crate::plant::simulate::beyond_physics(&self.plant.state())
        {
            // a model of absurd magnitudes (a torque of 1e30 N·m): the drive faults, as one would on overload
            self.fault = true;
            tracing::error!(
                t_s = self.plant.t_s(),
                what,
                value = v,
                "simulator: the plant left any physical range; drive faulted: check the model's magnitudes"
            );
        }
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
            (
                self.map.shaft_speed_rpm,
                rad_s_to_rpm(
                    self.faults
                        .speed_override_rad_s
                        .unwrap_or(self.faults.speed_scale.unwrap_or(1.0) * s.omega_rad_s + self.noise.speed()),
                ),
            ),
            (self.map.drive_frequency_hz, self.faults.frequency_scale.unwrap_or(1.0) * s.f_hz),
            (self.map.status_word, f64::from(self.status_word())),
            (self.map.sample_counter, f64::from(self.counter)),
            (DRIVE_POWER_W, self.drive_power_w()),
        ];
        for (spec, v) in values {
            if self.faults.freeze_values && spec != self.map.sample_counter {
                continue;
            }
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

#[cfg(test)]
mod tests;

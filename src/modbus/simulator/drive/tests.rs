//! The simulated drive's tests: the register image, writes, the watchdog and the faults.

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
    let air_gap_w = c.pump_m3_rad * (t.p_in_bar * 1e5 - c.back_pressure_pa) * 2.0 * std::f64::consts::PI * t.f_drive_hz
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

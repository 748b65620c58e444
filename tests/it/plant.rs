//! The plant model against its own physics: steady states, each effect's signature, convergence, determinism,
//! and an independent implementation of PHYSICS.md §1.

use hydrolens::recording::simulated;
use std::f64::consts::PI;

use hydrolens::plant::dynamics::{Coefficients, Plant};
use hydrolens::plant::effects::*;
use hydrolens::plant::simulate::Inputs;
use hydrolens::plant::{LoadSpec, PlantModel};
use hydrolens::units::{bar_to_pa, cm3_per_rev_to_m3_per_rad, l_min_per_bar_to_si, pa_to_bar, rpm_to_rad_s};

use crate::support::{nrmse, rmse};

fn reference() -> PlantModel {
    PlantModel::reference()
}

/// Runs the plant at a constant frequency and load until it settles; returns (ω, Δp in Pa).
fn steady(model: &PlantModel, f_hz: f64, load_nm: f64) -> (f64, f64) {
    let c = Coefficients::from_model(model).expect("hydraulic");
    let mut p = Plant::new(c);
    for _ in 0..20_000 {
        p.advance(1e-3, f_hz, load_nm);
    }
    let s = p.state();
    (s.omega_rad_s, s.p_in_pa - c.back_pressure_pa)
}

#[test]
fn steady_state_relations_hold() {
    let m = reference();
    let d_p = cm3_per_rev_to_m3_per_rad(16.0);
    let d_m = cm3_per_rev_to_m3_per_rad(32.0);
    let c_l = l_min_per_bar_to_si(0.02);
    for (f, load) in [(20.0, 0.0), (35.0, 8.0), (50.0, 15.0)] {
        let (omega, dp) = steady(&m, f, load);
        // torque balance: Δp = (Bω + T_L)/D_m  (= (Bω + T_L)·2π/D_m per revolution)
        let dp_expected = (0.04 * omega + load) / d_m;
        assert!((dp - dp_expected).abs() / dp_expected.max(1e4) < 1e-4, "f={f}: Δp {dp} vs {dp_expected}");
        // flow balance: ω = (pump flow − leakage)/D_m
        let omega_expected = (d_p * 2.0 * PI * f / 2.0 - c_l * dp) / d_m;
        assert!((omega - omega_expected).abs() / omega_expected < 1e-4, "f={f}: ω {omega} vs {omega_expected}");
    }
}

/// Steady states of the nominal plant and of a plant with one effect, at a few operating points.
fn compare(effects: Effects, points: &[(f64, f64)]) -> Vec<((f64, f64), (f64, f64))> {
    let nominal = reference();
    let mut with = reference();
    with.effects = effects;
    points.iter().map(|&(f, l)| (steady(&nominal, f, l), steady(&with, f, l))).collect()
}

#[test]
fn coulomb_and_offset_raise_pressure_by_their_torque() {
    let d_m = cm3_per_rev_to_m3_per_rad(32.0);
    for effects in [
        Effects { coulomb_friction: Some(CoulombFriction { torque_nm: 1.5 }), ..Effects::default() },
        Effects { torque_offset: Some(TorqueOffset { torque_nm: 1.5 }), ..Effects::default() },
    ] {
        for ((w0, dp0), (w1, dp1)) in compare(effects, &[(20.0, 5.0), (45.0, 10.0)]) {
            // 1.5 N·m more to overcome: Δp up by 1.5/D_m (= 2.95 bar), speed down only by the extra leakage
            let ddp = dp1 - dp0 - 0.04 * (w1 - w0) / d_m;
            assert!((ddp - 1.5 / d_m).abs() / (1.5 / d_m) < 1e-3, "{effects:?}: Δp rise {ddp}");
            let leak = l_min_per_bar_to_si(0.02) * (dp1 - dp0) / d_m;
            assert!(((w0 - w1) - leak).abs() < 1e-3, "{effects:?}: speed change {} vs leakage {leak}", w0 - w1);
        }
    }
}

#[test]
fn stribeck_shows_only_at_low_speed() {
    let d_m = cm3_per_rev_to_m3_per_rad(32.0);
    let effects = Effects {
        stribeck_friction: Some(StribeckFriction { breakaway_nm: 2.0, speed_rad_s: 3.0 }),
        ..Effects::default()
    };
    let r = compare(effects, &[(2.0, 1.0), (40.0, 1.0)]);
    let low_bar = pa_to_bar(r[0].1.1 - r[0].0.1);
    let high_bar = pa_to_bar(r[1].1.1 - r[1].0.1);
    // at ω ≈ 3 rad/s: 2·e^{-1} N·m ≈ 0.74 N·m ≈ 1.4 bar; at ω ≈ 60 rad/s: nothing
    let expected_low = pa_to_bar(2.0 * (-(r[0].1.0 / 3.0f64).powi(2)).exp() / d_m);
    assert!((low_bar - expected_low).abs() < 0.02 && low_bar > 0.5, "low speed: {low_bar} bar vs {expected_low}");
    assert!(high_bar.abs() < 1e-6, "high speed: {high_bar} bar");
}

#[test]
fn leakage_and_slip_cost_speed_in_proportion_to_pressure() {
    let d_p = cm3_per_rev_to_m3_per_rad(16.0);
    let d_m = cm3_per_rev_to_m3_per_rad(32.0);
    let leak = Effects { internal_leakage: Some(InternalLeakage { l_min_per_bar: 0.05 }), ..Effects::default() };
    let slip = Effects { motor_slip: Some(MotorSlip { rpm_per_nm: 2.0 }), ..Effects::default() };
    for (f, load) in [(30.0, 4.0), (30.0, 14.0)] {
        let r = compare(leak, &[(f, load)]);
        let ((w0, _), (w1, dp1)) = r[0];
        let deficit = l_min_per_bar_to_si(0.05) * dp1 / d_m;
        assert!(((w0 - w1) - deficit).abs() / deficit < 0.01, "leakage: deficit {} vs {deficit}", w0 - w1);
        let r = compare(slip, &[(f, load)]);
        let ((w0, _), (w1, dp1)) = r[0];
        let deficit = rpm_to_rad_s(2.0) * d_p * dp1 * d_p / d_m;
        assert!(((w0 - w1) - deficit).abs() / deficit < 0.01, "slip: deficit {} vs {deficit}", w0 - w1);
    }
}

#[test]
fn dead_time_and_air_change_transients_not_steady_states() {
    let step = |model: &PlantModel, load_nm: f64| -> Vec<(f64, f64, f64)> {
        let mut p = Plant::new(Coefficients::from_model(model).expect("hydraulic"));
        (0..15_000)
            .map(|k| {
                let f = if k >= 100 { 30.0 } else { 0.0 };
                p.advance(1e-3, f, load_nm);
                let s = p.state();
                (s.f_hz, s.p_in_pa, s.omega_rad_s)
            })
            .collect()
    };
    // unloaded, so that the plant rests exactly until the step
    let nominal = step(&reference(), 0.0);
    let mut delayed = reference();
    delayed.effects.dead_time = Some(DeadTime { ms: 40.0 });
    let delayed = step(&delayed, 0.0);
    // the drive responds exactly 40 samples later, and the whole response is the nominal one shifted
    let first_move = |run: &[(f64, f64, f64)]| run.iter().position(|s| s.0 > 0.0).expect("moves");
    assert_eq!(first_move(&delayed) - first_move(&nominal), 40);
    for k in 100..14_900 {
        let (a, b) = (nominal[k], delayed[k + 40]);
        assert!((a.2 - b.2).abs() < 1e-6 && (a.1 - b.1).abs() < 1.0, "k={k}: {a:?} vs {b:?}");
    }
    let mut airy = reference();
    airy.effects.entrained_air = Some(EntrainedAir { bulk_modulus_bar: 3000.0 });
    let airy = step(&airy, 5.0);
    let nominal = step(&reference(), 5.0);
    // softer oil: pressure builds more slowly after the step…
    let rise = |run: &[(f64, f64, f64)]| run.iter().position(|s| s.1 > bar_to_pa(10.0)).expect("builds up");
    assert!(rise(&airy) > rise(&nominal) + 20, "air: {} vs {}", rise(&airy), rise(&nominal));
    // …it overshoots at least as much (a softer spring, the same inertia)…
    let overshoot = |run: &[(f64, f64, f64)]| run.iter().map(|s| s.2).fold(f64::MIN, f64::max);
    assert!(overshoot(&airy) > overshoot(&nominal) * 0.9);
    // …and the steady state is the same.
    let (a, b) = (nominal[14_999], airy[14_999]);
    assert!((a.2 - b.2).abs() < 1e-3 && (a.1 - b.1).abs() < 100.0, "steady: {a:?} vs {b:?}");
}

#[test]
fn integrator_agrees_with_a_much_finer_step() {
    let mut model = reference();
    model.effects.dead_time = Some(DeadTime { ms: 12.3 });
    model.effects.coulomb_friction = Some(CoulombFriction { torque_nm: 0.8 });
    let c = Coefficients::from_model(&model).expect("hydraulic");
    let mut coarse = Plant::new(c);
    let mut fine = Plant::with_substep(c, 1e-5);
    let load = LoadSpec::Recorded;
    let (mut wc, mut wf, mut pc, mut pf) = (vec![], vec![], vec![], vec![]);
    for k in 0..20_000 {
        let t = k as f64 * 1e-3;
        let f = hydrolens::plant::excitation::setpoint_hz(t);
        coarse.advance(1e-3, f, load.torque_at(t, coarse.state().omega_rad_s, 0.0));
        fine.advance(1e-3, f, load.torque_at(t, fine.state().omega_rad_s, 0.0));
        wc.push(coarse.state().omega_rad_s);
        wf.push(fine.state().omega_rad_s);
        pc.push(coarse.state().p_in_pa);
        pf.push(fine.state().p_in_pa);
    }
    let (e_w, e_p) = (nrmse(&wc, &wf), nrmse(&pc, &pf));
    assert!(e_w < 1e-3 && e_p < 1e-3, "speed {e_w:e}, pressure {e_p:e} (NRMSE)");
}

#[test]
fn runs_are_deterministic_by_seed() {
    let m = reference();
    let a = simulated::test_stand(&m, 5.0, 7, &mut |_| {}).expect("run");
    let b = simulated::test_stand(&m, 5.0, 7, &mut |_| {}).expect("run");
    let c = simulated::test_stand(&m, 5.0, 8, &mut |_| {}).expect("run");
    assert_eq!(a, b);
    assert_ne!(a.column("omega_rad_s"), c.column("omega_rad_s"));
    assert_eq!(a.column("true_omega_rad_s"), c.column("true_omega_rad_s"), "noise never feeds back into the plant");
    // the noise has the configured spread
    let e = rmse(a.column("omega_rad_s").expect("ω"), a.column("true_omega_rad_s").expect("true ω"));
    assert!((e - 0.8).abs() < 0.05, "σ_ω {e}");
}

/// A second, independent implementation of PHYSICS.md §1: explicit midpoint at 20 µs, state kept in engineering
/// units (bar, Hz), the command delayed by indexing the recorded setpoint. Shares no code with `plant`.
fn independent(model: &PlantModel, f_set: &[f64], load: &[f64], dt: f64) -> (Vec<f64>, Vec<f64>) {
    let (drive, pump, motor) = (model.drive.as_ref().expect("drive"), model.pump.as_ref().expect("pump"), &model.motor);
    let hyd = model.hydraulics.as_ref().expect("hydraulics");
    let e = &model.effects;
    let dp_m3 = pump.displacement_cm3 * 1e-6 / (2.0 * PI);
    let dm_m3 = motor.displacement_cm3.expect("motor displacement") * 1e-6 / (2.0 * PI);
    let beta = e.entrained_air.map_or(hyd.bulk_modulus_bar, |a| a.bulk_modulus_bar) * 1e5;
    let v = hyd.volume_l * 1e-3;
    let leak = (hyd.leakage_l_min_per_bar + e.internal_leakage.map_or(0.0, |l| l.l_min_per_bar)) * 1e-3 / 60.0 / 1e5;
    let p_back = hyd.back_pressure_bar * 1e5;
    let ks = e.motor_slip.map_or(0.0, |s| s.rpm_per_nm) * 2.0 * PI / 60.0;
    let tc = e.coulomb_friction.map_or(0.0, |c| c.torque_nm);
    let delay = e.dead_time.map_or(0.0, |d| d.ms) * 1e-3;
    let friction = |w: f64| {
        let sg = (w / 0.05).tanh();
        let mut t = tc * sg + e.torque_offset.map_or(0.0, |o| o.torque_nm);
        if let Some(s) = e.stribeck_friction {
            t += (s.breakaway_nm - tc) * (-(w / s.speed_rad_s).powi(2)).exp() * sg;
        }
        t
    };
    let rhs = |x: [f64; 3], cmd: f64, tl: f64| -> [f64; 3] {
        let [f, p, w] = x;
        let df = ((cmd.clamp(0.0, drive.max_hz) - f) / drive.time_constant_s)
            .clamp(-drive.ramp_hz_per_s, drive.ramp_hz_per_s);
        let dpp = p - p_back;
        let wp = 2.0 * PI * f / f64::from(drive.pole_pairs) - ks * dp_m3 * dpp;
        let mut dp = beta / v * (dp_m3 * wp - dm_m3 * w - leak * dpp);
        if p <= 0.0 && dp < 0.0 {
            dp = 0.0;
        }
        let dw = (dm_m3 * dpp - motor.viscous_nm_s_rad * w - tl - friction(w)) / motor.inertia_kg_m2;
        [df, dp, dw]
    };
    let h = 2e-5;
    let per = (dt / h).round() as usize;
    let mut x = [0.0, p_back, 0.0];
    let (mut omega, mut p_in) = (Vec::new(), Vec::new());
    for k in 0..f_set.len() {
        omega.push(x[2]);
        p_in.push(x[1] / 1e5);
        for j in 0..per {
            let t = k as f64 * dt + j as f64 * h;
            let delayed = t - delay;
            let cmd = if delayed < 0.0 { 0.0 } else { f_set[((delayed / dt + 1e-9).floor() as usize).min(k)] };
            let k1 = rhs(x, cmd, load[k]);
            let mid = [x[0] + h / 2.0 * k1[0], (x[1] + h / 2.0 * k1[1]).max(0.0), x[2] + h / 2.0 * k1[2]];
            let k2 = rhs(mid, cmd, load[k]);
            x = [x[0] + h * k2[0], (x[1] + h * k2[1]).max(0.0), x[2] + h * k2[2]];
        }
    }
    (omega, p_in)
}

#[test]
fn an_independent_implementation_agrees_with_simulate() {
    let with_effects = {
        let mut m = reference();
        m.effects = Effects {
            coulomb_friction: Some(CoulombFriction { torque_nm: 0.6 }),
            stribeck_friction: Some(StribeckFriction { breakaway_nm: 1.2, speed_rad_s: 2.0 }),
            torque_offset: Some(TorqueOffset { torque_nm: 0.4 }),
            internal_leakage: Some(InternalLeakage { l_min_per_bar: 0.03 }),
            dead_time: Some(DeadTime { ms: 17.0 }),
            entrained_air: Some(EntrainedAir { bulk_modulus_bar: 6000.0 }),
            motor_slip: Some(MotorSlip { rpm_per_nm: 1.5 }),
        };
        m
    };
    for model in [reference(), with_effects] {
        let rec = simulated::test_stand(&model, 30.0, 3, &mut |_| {}).expect("run");
        let f_set = rec.column("f_set_hz").expect("setpoint");
        let load = rec.column("true_load_nm").expect("load");
        let (omega, p_in) = independent(&model, f_set, load, model.sample_s());
        let e_w = nrmse(&omega, rec.column("true_omega_rad_s").expect("ω"));
        let e_p = nrmse(&p_in, rec.column("true_p_in_bar").expect("p"));
        assert!(e_w < 0.02, "{:?}: speed NRMSE {e_w}", model.effects.active_ids());
        assert!(e_p < 0.03, "{:?}: pressure NRMSE {e_p}", model.effects.active_ids());
        eprintln!(
            "independent implementation, effects {:?}: NRMSE ω {e_w:.2e}, p_in {e_p:.2e}",
            model.effects.active_ids()
        );
    }
}

#[test]
fn simulate_inputs_drive_the_run() {
    let m = reference();
    let inputs = Inputs { setpoint_hz: &|t| if t > 0.5 { 25.0 } else { 0.0 }, load_nm: &|_, _, _| 3.0 };
    let rec = simulated::run(&m, 4.0, 1, &inputs, &mut |_| {}).expect("run");
    let f = rec.column("true_f_drive_hz").expect("f");
    assert_eq!(f[400], 0.0);
    assert!((f[3999] - 25.0).abs() < 1e-6);
    assert!(rec.column("true_load_nm").expect("load").iter().all(|&l| l == 3.0));
}

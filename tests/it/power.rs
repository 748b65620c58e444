//! Where the power goes (src/condition/power.rs) against the simulator's true power flows, on three plants (clean,
//! leak, leak + dry friction): the test stand simulated at 1 kHz, recorded as the service records at 5 ms, the
//! service's estimator run over it, a condition check on its last 120 s (the load unknown, as in the service), and
//! the budget integrated from those, as the service's condition thread does. The truth is the same budget's
//! formulas on the simulator's `true_*` states with the true model (its load `true_load_nm`), and that budget is
//! first shown to close on the integrator's own states (so the formulas are the plant's, not only each other's).
//!
//! `cargo test --test it power:: -- --nocapture` prints the table of docs/energy.md.

use hydrolens::condition::power::{Budget, Flows, Ledger, Operating, PowerModel, effects_of_findings};
use hydrolens::condition::{self};
use hydrolens::estimator::{self, EstimatorSettings};
use hydrolens::plant::PlantModel;
use hydrolens::plant::dynamics::{Coefficients, smooth_sign};
use hydrolens::recording::Recording;

use crate::noload::as_the_service_records;

const SECONDS: f64 = 240.0;
const POLL_MS: usize = 5;
const WINDOW_S: f64 = 120.0;
/// The estimator's first seconds (J and B still settling) are left out on both sides.
const FROM_S: f64 = 10.0;

fn plant(extra: &str) -> PlantModel {
    let text = format!("{}\n{extra}", hydrolens::plant::model::REFERENCE_TOML);
    PlantModel::parse(&text, "plant.toml").expect("valid")
}

const LEAK: &str = "[effects.internal_leakage]\nl_min_per_bar = 0.03\n";
const FRICTION: &str = "[effects.coulomb_friction]\ntorque_nm = 2.0\n";

/// The rows of `rec` with `from ≤ t_s < to`.
fn window(rec: &Recording, from: f64, to: f64) -> Recording {
    let t = rec.t_s();
    let (a, b) = (t.partition_point(|v| *v < from), t.partition_point(|v| *v < to));
    let names: Vec<String> = rec.names().to_vec();
    let cols = names.iter().map(|n| rec.column(n).expect("column")[a..b].to_vec()).collect();
    Recording::from_columns("window", names, cols)
}

/// The mean power of each flow over the run from the true states with the true model.
fn truth(rec: &Recording, model: &PlantModel) -> Flows {
    let budget = Budget::of(model).expect("hydraulic");
    let c = Coefficients::from_model(model).expect("hydraulic");
    let col = |n: &str| rec.column(n).expect("true column");
    let (t, p, w, f, load) =
        (col("t_s"), col("true_p_in_bar"), col("true_omega_rad_s"), col("true_f_drive_hz"), col("true_load_nm"));
    let back_bar = c.back_pressure_pa / 1e5;
    let points = (0..rec.len()).filter(|&k| t[k] >= FROM_S).map(|k| Operating {
        t_s: t[k],
        dp_bar: p[k] - back_bar,
        f_drive_hz: f[k],
        omega_rad_s: w[k],
        // what resists the motor beside inertia: the load, viscous and dry friction
        resisting_torque_nm: load[k] + c.mechanics.viscous_nm_s_rad * w[k] + c.mechanics.coulomb_nm * smooth_sign(w[k]),
        drive_power_w: None,
    });
    let mut l = Ledger::default();
    l.add_all(&PowerModel { fitted: budget, nominal: budget }, points);
    mean(&l)
}

fn mean(l: &Ledger) -> Flows {
    let r = l.report(None);
    let v = r.energy_j;
    let s = l.span_s;
    Flows {
        input_w: v.input_w / s,
        slip_w: v.slip_w / s,
        pump_hydraulic_w: v.pump_hydraulic_w / s,
        leakage_w: v.leakage_w / s,
        internal_leakage_w: v.internal_leakage_w / s,
        motor_hydraulic_w: v.motor_hydraulic_w / s,
        viscous_w: v.viscous_w / s,
        dry_friction_w: v.dry_friction_w / s,
        load_w: v.load_w / s,
    }
}

/// What the service makes of the same run: its rows, its estimator, a condition check, its budget.
fn estimated(rec: &Recording, nominal: &PlantModel) -> (Flows, String) {
    let served = as_the_service_records(rec, POLL_MS, 5);
    let mut est = estimator::try_build(&EstimatorSettings::default(), nominal).expect("estimator");
    let estimates = hydrolens::replay::replay(&served, nominal, "nominal", est.as_mut()).expect("replays");
    let check = condition::check(&window(&served, SECONDS - WINDOW_S, SECONDS + 1.0), nominal, SECONDS, WINDOW_S)
        .expect("check");
    let pm = PowerModel::new(nominal, &effects_of_findings(&check.findings)).expect("hydraulic");
    let col = |n: &str| served.column(n).expect("column");
    let (t, p_in, p_out, f) = (col("t_s"), col("p_in_bar"), col("p_out_bar"), col("f_drive_hz"));
    let points = (0..served.len()).filter(|&k| t[k] >= FROM_S).map(|k| {
        let e = &estimates[k];
        Operating {
            t_s: t[k],
            dp_bar: p_in[k] - p_out[k],
            f_drive_hz: f[k],
            omega_rad_s: e.omega_hat_rad_s,
            resisting_torque_nm: e.load_hat_nm + e.viscous_hat_nm_s_rad * e.omega_hat_rad_s,
            drive_power_w: None,
        }
    });
    let mut l = Ledger::default();
    l.add_all(&pm, points);
    let named: Vec<String> = check.parameters().iter().map(|(e, p, v)| format!("{e}.{p}={v:.4}")).collect();
    (mean(&l), named.join(" "))
}

/// The flows compared, by name, with the share of the input below which a flow is too small to hold to 5 %
/// (the clean plant's internal leakage is 0 on both sides). Every flow is held to 5 %, viscous and dry friction
/// apart too: their split is the commissioning analysis's (IDIM-IV, docs/analysis.md), and their sum besides.
fn compare(name: &str, truth: &Flows, est: &Flows, named: &str) -> Vec<String> {
    let mut failures = Vec::new();
    eprintln!("{name}: check found [{named}]");
    eprintln!("  {:<20} {:>10} {:>10} {:>8}", "flow", "true W", "est. W", "error");
    for (k, col) in Flows::COLUMNS.iter().enumerate() {
        let (a, b) = (truth.values()[k], est.values()[k]);
        let err = if a.abs() > 1e-9 { (b - a) / a } else { 0.0 };
        eprintln!("  {col:<20} {a:>10.1} {b:>10.1} {:>7.1} %", 100.0 * err);
        let material = a.abs() > 0.005 * truth.input_w || b.abs() > 0.005 * truth.input_w;
        if material && (b - a).abs() > 0.05 * a.abs() {
            failures.push(format!("{name}.{col}: {b:.1} W against {a:.1} W"));
        }
    }
    let (a, b) = (truth.viscous_w + truth.dry_friction_w, est.viscous_w + est.dry_friction_w);
    eprintln!("  {:<20} {a:>10.1} {b:>10.1} {:>7.1} %", "friction (both)", 100.0 * (b - a) / a);
    if (b - a).abs() > 0.05 * a {
        failures.push(format!("{name}.friction: {b:.1} W against {a:.1} W"));
    }
    failures
}

#[test]
fn the_budget_closes_on_the_simulators_own_states() {
    // pump = leak + motor + compression; motor = viscous + dry + load + kinetic: over a run the stored energies
    // are their end values less their start values, small beside the flows
    let model = plant(&format!("{LEAK}{FRICTION}"));
    let rec = hydrolens::recording::simulated::test_stand(&model, 60.0, 1, &mut |_| {}).expect("simulable");
    let f = truth(&rec, &model);
    let hydraulic_rest = f.pump_hydraulic_w - f.leakage_w - f.internal_leakage_w - f.motor_hydraulic_w;
    let shaft_rest = f.motor_hydraulic_w - f.viscous_w - f.dry_friction_w - f.load_w;
    eprintln!("{f:?}\nhydraulic rest {hydraulic_rest:.2} W, shaft rest {shaft_rest:.2} W");
    assert!(hydraulic_rest.abs() < 0.01 * f.input_w, "{hydraulic_rest} W of {} W", f.input_w);
    assert!(shaft_rest.abs() < 0.01 * f.input_w, "{shaft_rest} W of {} W", f.input_w);
    assert!(f.internal_leakage_w > 0.05 * f.input_w && f.dry_friction_w > 0.02 * f.input_w, "{f:?}");
}

#[test]
fn the_power_by_effect_matches_the_simulators_truth_within_5_percent_on_three_plants() {
    // The service's nominal model knows what a commissioning analysis on the test stand (load recorded) fitted:
    // the dry friction. With the load unknown, a condition check cannot tell dry friction from load.
    let commissioned = {
        let before = plant(FRICTION);
        let rec = hydrolens::recording::simulated::test_stand(&before, 120.0, 11, &mut |_| {}).expect("simulable");
        let a = hydrolens::analysis::analyze(&rec, &PlantModel::reference(), &Default::default(), &mut |_| {})
            .expect("analysis");
        a.improved_model
    };
    eprintln!("commissioned: B {} N·m·s/rad, {:?}", commissioned.motor.viscous_nm_s_rad, commissioned.effects);
    assert!(commissioned.effects.coulomb_friction.is_some(), "the commissioning finds the friction");
    let cases = [
        ("clean", plant(""), PlantModel::reference()),
        ("leak", plant(LEAK), PlantModel::reference()),
        ("leak+friction", plant(&format!("{LEAK}{FRICTION}")), commissioned),
    ];
    let mut failures = Vec::new();
    for (name, truth_model, nominal) in &cases {
        let rec = hydrolens::recording::simulated::test_stand(truth_model, SECONDS, 3, &mut |_| {}).expect("simulable");
        let t = truth(&rec, truth_model);
        let (e, named) = estimated(&rec, nominal);
        failures.extend(compare(name, &t, &e, &named));
    }
    assert!(failures.is_empty(), "{failures:#?}");
}

// ---- the overall efficiency over real TCP: `sim` serves the drive's output power, the service reads it ----

/// The service polls the simulator over Modbus TCP, with `[drives.registers.drive_power_w]` (`sim`'s register 6:
/// the air-gap power T_p·ω_sync through its motor's efficiency, 0.85), its target moving through the demo program;
/// then the simulator stops, and the service's integrals up to its last sample are held against the simulator's
/// own (its true drive output and load energy, sample by sample at 1 kHz). Without the register, all of it is
/// null ("not read").
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn over_tcp_the_overall_efficiency_is_the_simulators_within_5_percent() {
    use std::time::Duration;

    use crate::support::{self, Stack, wait_for};

    const CONDITION: &str = "[drives.condition]\nenabled = true\nwindow_s = 60.0\nevery_s = 86400.0\n";
    let control = "[drives.control]\nmode = \"speed\"\ntarget_omega_rad_s = 40.0\nmax_hz = 50.0\n";
    let run = async {
        let extra = format!("{control}\n[drives.registers.drive_power_w]\n\n{CONDITION}");
        let stack = Stack::start(8.0, 10, &extra).await;
        let drive = stack.state.drives[0].clone();
        let program = tokio_util::sync::CancellationToken::new();
        let mover = {
            let (drive, stop) = (drive.clone(), program.clone());
            tokio::spawn(async move {
                let start = std::time::Instant::now();
                while !stop.is_cancelled() {
                    let t = 2.0 * start.elapsed().as_secs_f64();
                    let target = hydrolens::service::program::demo_target_rad_s(t, 40.0, drive.max_target_omega_rad_s);
                    drive.set_target(target);
                    tokio::time::sleep(Duration::from_millis(100)).await;
                }
            })
        };
        let span = |s: &serde_json::Value| s["energy"]["span_s"].as_f64().unwrap_or(0.0);
        // 20 s of integrated data: more than a cycle of the program (15 s)
        wait_for(Duration::from_secs(90), || async { span(&stack.status().await) >= 20.0 })
            .await
            .expect("20 s integrated");
        let now = stack.status().await;
        let read = now["sample"]["drive_power_w"].as_f64().expect("the sample carries the drive's power");
        let metrics = stack.metrics().await;
        program.cancel();
        mover.await.expect("joins");
        // the simulator stops: no new rows; the ledger catches up with the last one the ring holds
        stack.sim_stop.cancel();
        wait_for(Duration::from_secs(10), || async { drive.snapshot().link.stale }).await.expect("stale");
        // the newest row once stale, taken once: the ledger's time only grows, so waiting for it to reach a fixed
        // row cannot miss (a moving target could, were any row added after)
        let last_row_t = drive.history(1.0, 1).last().map(|p| p.sample.t_s);
        wait_for(Duration::from_secs(20), || async {
            stack.status().await["energy"]["up_to_t_s"].as_f64() >= last_row_t
        })
        .await
        .expect("the ledger takes the last row");
        let e = stack.status().await["energy"].clone();
        let truth = stack.sim.lock().truth();
        let drive_j = e["drive_energy_j"].as_f64().expect("the drive's energy");
        let overall = e["overall_efficiency"].as_f64().expect("the overall efficiency");
        let true_overall = truth.load_energy_j / truth.drive_energy_j;
        let (drive_err, overall_err) =
            ((drive_j - truth.drive_energy_j) / truth.drive_energy_j, (overall - true_overall) / true_overall);
        let input_share = e["energy_j"]["input_w"].as_f64().expect("input") / drive_j;
        eprintln!(
            "over {:.1} s: drive output {drive_j:.0} J (true {:.0} J, {:+.2} %), load {:.0} J (true {:.0} J), \
             overall efficiency {overall:.4} (true {true_overall:.4}, {:+.2} %); input / drive output {input_share:.4} \
             (the simulated motor's {})",
            e["span_s"].as_f64().unwrap_or(f64::NAN),
            truth.drive_energy_j,
            100.0 * drive_err,
            e["energy_j"]["load_w"].as_f64().unwrap_or(f64::NAN),
            truth.load_energy_j,
            100.0 * overall_err,
            hydrolens::modbus::simulator::MOTOR_EFFICIENCY,
        );
        assert!(read.is_finite() && read > 0.0, "{read} W read while running");
        assert!(drive_err.abs() < 0.02, "the drive's energy {:+.2} % off", 100.0 * drive_err);
        assert!(overall_err.abs() < 0.05, "the overall efficiency {:+.2} % off", 100.0 * overall_err);
        assert!(e["drive_power_w"].as_f64().is_some(), "{e}");
        for (series, what) in [
            ("hydrolens_efficiency_ratio{drive=\"pump1\",kind=\"overall\"}", "overall efficiency"),
            ("hydrolens_power_watts{drive=\"pump1\",flow=\"drive\"}", "drive power"),
            ("hydrolens_energy_joules{drive=\"pump1\",flow=\"drive\"}", "drive energy"),
        ] {
            let v = support::metric(&metrics, series);
            assert!(v.is_some_and(|v| v > 0.0 && v.is_finite()), "{what}: {v:?}");
        }
        stack.stop().await;

        // the register not in the map: not read, null everywhere, no series
        let stack = Stack::start(8.0, 10, &format!("{control}\n{CONDITION}")).await;
        wait_for(Duration::from_secs(30), || async { span(&stack.status().await) > 0.0 })
            .await
            .expect("an energy report");
        let s = stack.status().await;
        assert!(s["sample"]["drive_power_w"].is_null(), "{s}");
        for key in ["drive_power_w", "drive_energy_j", "overall_efficiency"] {
            assert!(s["energy"][key].is_null(), "{key}: {}", s["energy"]);
        }
        let metrics = stack.metrics().await;
        assert!(!metrics.contains("kind=\"overall\"") && !metrics.contains("flow=\"drive\""), "{metrics}");
        stack.stop().await;
    };
    tokio::time::timeout(Duration::from_secs(180), run).await.expect("bounded");
}

//! `analyze` with the load unknown, on recordings as the service writes them: offline test-stand runs turned into
//! service recordings (poll rate, Modbus quantisation, skipped cycles, no `load_nm`), and the sweep behind
//! docs/analysis.md's no-load table.

use hydrolens::analysis::{self, Analysis, Options};
use hydrolens::plant::PlantModel;
use hydrolens::plant::effects::{CoulombFriction, DeadTime, EntrainedAir, InternalLeakage, MotorSlip};
use hydrolens::recording::Recording;

/// Length of the offline runs (s): two test-stand cycles, as the concealed-effect tests.
const RUN_S: f64 = 80.0;

/// A simulated 1 kHz test-stand recording as the service would have written it at `poll_ms`: every `poll_ms`-th
/// row, values through the default register map's quantisation (0.01 bar, 0.1 rpm, 0.01 Hz), about one cycle in
/// 200 skipped as stale plus one 0.4 s outage, no `load_nm` and no ground truth, and the estimate columns
/// riding along (filled with nonsense: they must not be used).
pub fn as_the_service_records(rec: &Recording, poll_ms: usize, seed: u64) -> Recording {
    let q = |v: f64, lsb: f64| (v / lsb).round() * lsb;
    let rpm = 60.0 / (2.0 * std::f64::consts::PI);
    let col = |name: &str| rec.column(name).expect("simulated column");
    let (t, f_set, f_drive) = (col("t_s"), col("f_set_hz"), col("f_drive_hz"));
    let (p_in, p_out, omega) = (col("p_in_bar"), col("p_out_bar"), col("omega_rad_s"));
    let names = [
        "t_s",
        "f_set_hz",
        "f_drive_hz",
        "p_in_bar",
        "p_out_bar",
        "omega_rad_s",
        "omega_hat_rad_s",
        "load_hat_nm",
        "inertia_hat_kg_m2",
        "viscous_hat_nm_s_rad",
        "status_word",
    ];
    let mut cols: Vec<Vec<f64>> = vec![Vec::new(); names.len()];
    // a small deterministic generator for the skipped cycles
    let mut state = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
    let mut next = || {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (state >> 33) as f64 / (1u64 << 31) as f64
    };
    let outage = (0.37 * t[t.len() - 1], 0.37 * t[t.len() - 1] + 0.4);
    for k in (0..rec.len()).step_by(poll_ms) {
        if next() < 0.005 || (outage.0..outage.1).contains(&t[k]) {
            continue;
        }
        let row = [
            t[k],
            q(f_set[k], 0.01),
            q(f_drive[k], 0.01),
            q(p_in[k].max(0.0), 0.01),
            q(p_out[k].max(0.0), 0.01),
            q(omega[k] * rpm, 0.1) / rpm,
            -omega[k],
            1e3,
            -1.0,
            f64::NAN,
            3.0,
        ];
        for (c, v) in cols.iter_mut().zip(row) {
            c.push(v);
        }
    }
    Recording::from_columns("service-like.csv", names.iter().map(|s| s.to_string()).collect(), cols)
}

/// The reference plant with `effect`, simulated offline, recorded as the service would at `poll_ms`, analysed
/// against the nominal model (whose `[load]` is "recorded": the load is then unknown).
pub fn no_load(effect: &dyn Fn(&mut PlantModel), seed: u64, poll_ms: usize) -> Analysis {
    let mut truth = PlantModel::reference();
    effect(&mut truth);
    let rec = hydrolens::plant::simulate::test_stand(&truth, RUN_S, seed, &mut |_| {}).expect("simulable");
    let rec = as_the_service_records(&rec, poll_ms, seed);
    analysis::analyze(&rec, &PlantModel::reference(), &Options::default(), &mut |_| {}).expect("analysable")
}

pub fn named(a: &Analysis) -> Vec<&str> {
    a.findings.iter().map(|f| f.effect.as_str()).collect()
}

/// The flow-balance effects the no-load analysis must find, with their key parameter.
pub const HYDRAULIC: [&str; 4] = ["internal_leakage", "motor_slip", "dead_time", "entrained_air"];

fn summary(a: &Analysis) -> String {
    format!(
        "load {} named {:?} params {:?} dp {:.4}->{:.4} f {:?}->{:?} amb {:?}",
        a.load,
        named(a),
        a.findings.iter().map(|f| &f.parameters).collect::<Vec<_>>(),
        a.baseline.validation.dp_nrmse.unwrap_or(f64::NAN),
        a.improved.validation.dp_nrmse.unwrap_or(f64::NAN),
        a.baseline.validation.f_drive_nrmse,
        a.improved.validation.f_drive_nrmse,
        a.ambiguities.iter().map(|x| &x.effects).collect::<Vec<_>>()
    )
}

/// A probe for development: prints what the no-load analysis makes of a few cases.
#[test]
#[ignore]
fn probe() {
    type Set = Box<dyn Fn(&mut PlantModel) + Sync>;
    let cases: Vec<(&str, Set)> = vec![
        ("clean", Box::new(|_| {})),
        ("leak 0.012", Box::new(|m| m.effects.internal_leakage = Some(InternalLeakage { l_min_per_bar: 0.012 }))),
        ("dead 30", Box::new(|m| m.effects.dead_time = Some(DeadTime { ms: 30.0 }))),
        ("air 7000", Box::new(|m| m.effects.entrained_air = Some(EntrainedAir { bulk_modulus_bar: 7000.0 }))),
        ("slip 2.5", Box::new(|m| m.effects.motor_slip = Some(MotorSlip { rpm_per_nm: 2.5 }))),
        ("coulomb 0.6", Box::new(|m| m.effects.coulomb_friction = Some(CoulombFriction { torque_nm: 0.6 }))),
    ];
    let polls: Vec<usize> =
        std::env::var("PROBE_POLLS").map_or(vec![5], |v| v.split(',').filter_map(|x| x.parse().ok()).collect());
    for poll in polls {
        for (name, set) in &cases {
            let t0 = std::time::Instant::now();
            let a = no_load(set.as_ref(), 3, poll);
            eprintln!("{poll} ms {name}: {} ({:.1} s)", summary(&a), t0.elapsed().as_secs_f64());
        }
    }
}

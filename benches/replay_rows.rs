//! The estimator alone on the rows of a recording, the side-by-side peer of padasip's filter alone in
//! `bench/peers.sh` step b: the recording and the model are loaded first (not timed), then the rows are replayed
//! through the estimator in batches of 4 096 as `hydrolens estimate` does, on one thread, without formatting or
//! writing anything; `REPEATS` times, each from the estimator's initial state. Prints
//! `replay rows=N method=M s=… rows_per_s=… ns_per_row=…` (median wall time of the repeats).
//!
//! usage: `cargo bench --bench replay_rows -- [REC.csv [REPEATS (5)] [METHOD (rls-sgd)] [MODEL (config/plant.toml)]]`;
//! without a recording (as in `cargo bench`), a test-stand run of the model, 100 k rows, simulated in memory.

use hydrolens::recording::simulated;
use std::hint::black_box;
use std::path::Path;
use std::time::Instant;

use hydrolens::estimator::{self, EstimatorSettings, Method};
use hydrolens::plant::PlantModel;
use hydrolens::replay::{Plan, Replayer};

const BATCH_ROWS: usize = 4096;

fn main() {
    // cargo passes `--bench` to a bench without a harness
    let args: Vec<String> = std::env::args().skip(1).filter(|a| !a.starts_with("--")).collect();
    let rec_path = args.first().map_or("(100 k simulated rows)", String::as_str);
    let repeats: usize = args.get(1).map_or(5, |r| r.parse().expect("REPEATS: a whole number"));
    let method = match args.get(2).map_or("rls-sgd", String::as_str) {
        "kalman" => Method::Kalman,
        "rls-sgd" => Method::RlsSgd,
        other => panic!("METHOD: rls-sgd or kalman, not {other}"),
    };
    let model_path = args.get(3).map_or("config/plant.toml", String::as_str);
    let model = PlantModel::load(Path::new(model_path)).expect("model");
    let settings = EstimatorSettings {
        method,
        ..EstimatorSettings::from_model(&model, model_path).expect("estimator settings in the model")
    };
    let rec = match args.first() {
        Some(path) => hydrolens::recording::load(Path::new(path)).expect("recording"),
        None => simulated::test_stand(&model, 99_999.0 * model.sample_s(), 1, &mut |_| {}).expect("a hydraulic model"),
    };
    let plan = Plan::choose(rec.names(), |ask| ask.iter().map(|c| rec.present(c).is_some()).collect());
    let columns: Vec<&[f64]> = plan.columns().iter().map(|c| rec.column(c).expect("a column of the plan")).collect();
    let t_s = rec.t_s();
    let rows = t_s.len();
    // the batches as `estimate` hands them over, made before the clock starts
    let batches: Vec<(usize, usize, Vec<Vec<f64>>)> = (0..rows)
        .step_by(BATCH_ROWS)
        .map(|start| {
            let end = (start + BATCH_ROWS).min(rows);
            (start, end, columns.iter().map(|c| c[start..end].to_vec()).collect())
        })
        .collect();

    let mut times = Vec::with_capacity(repeats);
    for _ in 0..repeats.max(1) {
        let mut est = estimator::try_build(&settings, &model).expect("settings");
        let mut replayer = Replayer::new(plan, &model, model_path, rec_path, est.as_mut());
        let mut sum = 0.0;
        let start = Instant::now();
        for (a, b, cols) in &batches {
            replayer.push(&t_s[*a..*b], black_box(cols), |_, e| sum += e.omega_hat_rad_s);
        }
        let elapsed = start.elapsed().as_secs_f64();
        black_box(sum);
        assert_eq!(replayer.finish().expect("the recording replays").rows as usize, rows);
        times.push(elapsed);
    }
    times.sort_by(f64::total_cmp);
    let s = times[times.len() / 2];
    println!(
        "replay rows={rows} method={method} s={s:.4} rows_per_s={:.0} ns_per_row={:.1}",
        rows as f64 / s,
        s * 1e9 / rows as f64
    );
}

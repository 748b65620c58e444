//! The two halves of `hydrolens estimate` (src/replay_file.rs), each on one thread, on a `simulate` recording of
//! 100 k rows (11 columns) in memory: the recording reader (with the 4 columns the replay needs, and with all 11),
//! and the replay with the formatting of its output. Times are the thread's CPU time (support/cpu_time.rs). Then the
//! whole of `estimate_file` on the same rows from a file to a file, with its two threads, in wall time.

#[path = "support/cpu_time.rs"]
mod cpu_time;

use hydrolens::recording::simulated;
use std::hint::black_box;
use std::time::Duration;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use hydrolens::estimator::{self, EstimatorSettings, Method};
use hydrolens::plant::PlantModel;
use hydrolens::recording::{self, Batch, StreamReader};
use hydrolens::replay::{Plan, Replayer};

const ROWS: usize = 100_000;

fn bench_estimate(c: &mut Criterion<cpu_time::Clock>) {
    let model = PlantModel::reference();
    let duration_s = (ROWS - 1) as f64 * model.sample_s();
    let rec = simulated::test_stand(&model, duration_s, 1, &mut |_| {}).expect("reference plant is hydraulic");
    let mut text = Vec::new();
    recording::write_csv(&mut text, &rec).expect("writing to memory");

    let mut g = c.benchmark_group("estimate/100k_rows");
    g.measurement_time(Duration::from_secs(3)).sample_size(20).warm_up_time(Duration::from_secs(1));
    g.throughput(Throughput::ElementsAndBytes { elements: ROWS as u64, bytes: text.len() as u64 });
    let plan = Plan::choose(rec.names(), |_| unreachable!("no column beside its fallback"));
    let read = |columns: &[&str]| {
        let mut r = StreamReader::new(black_box(text.as_slice()), "bench.csv").expect("header");
        let selected: Vec<usize> = columns.iter().filter_map(|c| r.index_of(c)).collect();
        r.select(&selected);
        let mut batch = Batch::default();
        let mut sum = 0.0;
        while r.read_batch(&mut batch, 4096).expect("valid") > 0 {
            sum += batch.t_s[0];
        }
        sum
    };
    let used = plan.columns();
    g.bench_function("stream_read_4_columns", |b| b.iter(|| read(&used)));
    let all: Vec<&str> = rec.names().iter().map(String::as_str).filter(|n| *n != "t_s").collect();
    g.bench_function("stream_read_11_columns", |b| b.iter(|| read(&all)));

    // the other thread: measurements, estimator, output text
    let columns: Vec<Vec<f64>> = used.iter().map(|c| rec.column(c).expect("column").to_vec()).collect();
    let t_s = rec.t_s().to_vec();
    let mut out = Vec::with_capacity(ROWS * 100);
    for method in [Method::RlsSgd, Method::Kalman] {
        let settings = EstimatorSettings { method, ..EstimatorSettings::default() };
        g.bench_function(format!("replay_and_format_{method}"), |b| {
            b.iter(|| {
                let mut est = estimator::try_build(&settings, &model).expect("settings");
                let mut replayer = Replayer::new(plan, &model, "model", "bench.csv", est.as_mut());
                out.clear();
                for start in (0..ROWS).step_by(4096) {
                    let end = (start + 4096).min(ROWS);
                    let cols: Vec<Vec<f64>> = columns.iter().map(|c| c[start..end].to_vec()).collect();
                    replayer.push(&t_s[start..end], &cols, |t, e| {
                        let (j, b) = (e.inertia_hat_kg_m2, e.viscous_hat_nm_s_rad);
                        for v in [t, e.omega_hat_rad_s, e.load_hat_nm, j, b, e.inertia_sd_kg_m2] {
                            recording::push_value(&mut out, v);
                            out.push(b',');
                        }
                        recording::push_value(&mut out, e.viscous_sd_nm_s_rad);
                        out.push(b'\n');
                    });
                }
                replayer.finish().expect("replays");
                out.len()
            })
        });
    }
    g.finish();
}

/// `estimate_file` end to end, file to file (both threads: wall time). The output is removed after each run, so
/// that each writes a new file as a first run does (replacing a file just written costs the kernel more).
fn bench_estimate_file(c: &mut Criterion) {
    let model = PlantModel::reference();
    let duration_s = (ROWS - 1) as f64 * model.sample_s();
    let rec = simulated::test_stand(&model, duration_s, 1, &mut |_| {}).expect("reference plant is hydraulic");
    let dir = tempfile::tempdir().expect("temporary directory");
    let path = dir.path().join("rec.csv");
    let mut text = Vec::new();
    recording::write_csv(&mut text, &rec).expect("writing to memory");
    std::fs::write(&path, &text).expect("writing the recording");
    let out = dir.path().join("est.csv");

    let mut g = c.benchmark_group("estimate/100k_rows");
    g.measurement_time(Duration::from_secs(4)).sample_size(20).warm_up_time(Duration::from_secs(1));
    g.throughput(Throughput::ElementsAndBytes { elements: ROWS as u64, bytes: text.len() as u64 });
    for method in [Method::RlsSgd, Method::Kalman] {
        let settings = EstimatorSettings { method, ..EstimatorSettings::default() };
        g.bench_function(format!("file_to_file_{method}"), |b| {
            b.iter_batched(
                || {
                    let _ = std::fs::remove_file(&out);
                    estimator::try_build(&settings, &model).expect("settings")
                },
                |est| hydrolens::replay_file::estimate_file(&path, &model, "model", est.as_ref(), &out, None),
                criterion::BatchSize::PerIteration,
            )
        });
    }
    g.finish();
}

criterion_group! {
    name = benches;
    config = cpu_time::criterion();
    targets = bench_estimate
}
criterion_group!(wall, bench_estimate_file);
criterion_main!(benches, wall);

//! One estimator update per method, in ns/sample: `cargo bench --bench estimator`. rls-sgd is also timed on a
//! 10 ms stream, where its window fits (every 0.75 s of data) are spread over ten times fewer samples.

use std::hint::black_box;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use hydrolens::estimator::{self, EstimatorSettings, Measurement, Method};
use hydrolens::plant::PlantModel;

fn updates(c: &mut Criterion) {
    let model = PlantModel::reference();
    // A plausible, varying sample stream (1 kHz, speed around 40 rad/s, torque around 10 N·m).
    let samples: Vec<Measurement> = (0..4096)
        .map(|k| {
            let x = k as f64 * 1e-3;
            Measurement {
                dt_s: 1e-3,
                omega_rad_s: 40.0 + 5.0 * (3.0 * x).sin() + 0.8 * (k as f64 * 12.9898).sin(),
                drive_torque_nm: 10.0 + 3.0 * (2.0 * x).cos(),
            }
        })
        .collect();
    let mut group = c.benchmark_group("estimator_update");
    group.throughput(Throughput::Elements(1));
    for method in [Method::RlsSgd, Method::Kalman, Method::PaperLiteral] {
        let settings = EstimatorSettings { method, ..EstimatorSettings::default() };
        let mut est = estimator::build(&settings, &model);
        let mut k = 0;
        group.bench_function(method.name(), |b| {
            b.iter(|| {
                k = (k + 1) % samples.len();
                black_box(est.update(black_box(&samples[k])))
            })
        });
    }
    let slow: Vec<Measurement> = samples.iter().map(|m| Measurement { dt_s: 1e-2, ..*m }).collect();
    let mut est = estimator::build(&EstimatorSettings::default(), &model);
    let mut k = 0;
    group.bench_function("rls-sgd at 10 ms", |b| {
        b.iter(|| {
            k = (k + 1) % slow.len();
            black_box(est.update(black_box(&slow[k])))
        })
    });
    group.finish();
}

criterion_group!(benches, updates);
criterion_main!(benches);

//! The plant model's cost: one 1 ms sample (`Plant::advance`, RK4 at ≤ 0.2 ms substeps) and `simulate` throughput.
//! Times are the thread's CPU time (see support/cpu_time.rs; `HYDROLENS_BENCH_WALL=1` for wall time).

#[path = "support/cpu_time.rs"]
mod cpu_time;

use hydrolens::recording::simulated;
use std::hint::black_box;
use std::time::Duration;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use hydrolens::plant::{Coefficients, Plant, PlantModel};

fn bench_plant(c: &mut Criterion<cpu_time::Clock>) {
    let model = PlantModel::reference();
    let coefficients = Coefficients::from_model(&model).expect("reference plant is hydraulic");

    let mut g = c.benchmark_group("plant");
    g.measurement_time(Duration::from_secs(3)).sample_size(20).warm_up_time(Duration::from_secs(1));
    g.throughput(Throughput::Elements(1));
    // running at 20 Hz under load, so the state is away from the clamps
    let mut plant = Plant::new(coefficients);
    for _ in 0..2000 {
        plant.advance(1e-3, 20.0, 6.0);
    }
    g.bench_function("advance_1ms", |b| b.iter(|| plant.advance(black_box(1e-3), black_box(20.0), black_box(6.0))));

    let mut with_dead_time = model.clone();
    with_dead_time.effects.dead_time = Some(hydrolens::plant::effects::DeadTime { ms: 2.5 });
    let mut delayed = Plant::new(Coefficients::from_model(&with_dead_time).expect("hydraulic"));
    let mut k = 0u64;
    // a new command every sample: the dead-time queue and the split integration are exercised each time
    g.bench_function("advance_1ms_dead_time_new_command", |b| {
        b.iter(|| {
            k += 1;
            delayed.advance(1e-3, black_box(20.0 + (k % 2) as f64), 6.0)
        })
    });
    g.finish();

    let mut g = c.benchmark_group("simulate");
    g.measurement_time(Duration::from_secs(3)).sample_size(10).warm_up_time(Duration::from_secs(1));
    for seconds in [10.0, 60.0] {
        let samples = (seconds / model.sample_s()) as u64 + 1;
        g.throughput(Throughput::Elements(samples));
        g.bench_function(format!("test_stand_{seconds}s"), |b| {
            b.iter(|| simulated::test_stand(&model, black_box(seconds), 1, &mut |_| {}).expect("hydraulic").len())
        });
    }
    g.finish();
}

criterion_group! {
    name = benches;
    config = cpu_time::criterion();
    targets = bench_plant
}
criterion_main!(benches);

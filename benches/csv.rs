//! Recording CSV read and write throughput (rows/s and MB/s) on `simulate` recordings of 10 k and 100 k rows.
//! Times are the thread's CPU time (see support/cpu_time.rs; `HYDROLENS_BENCH_WALL=1` for wall time).

#[path = "support/cpu_time.rs"]
mod cpu_time;

use hydrolens::recording::simulated;
use std::hint::black_box;
use std::time::Duration;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use hydrolens::plant::PlantModel;
use hydrolens::plant::simulate;
use hydrolens::recording::{self, Recording, RowWriter};

/// A test-stand recording of `rows` samples at 1 kHz (the reference plant, seed 1).
fn recording_of(rows: usize) -> Recording {
    let model = PlantModel::reference();
    let duration_s = (rows - 1) as f64 * model.sample_s();
    let rec = simulated::test_stand(&model, duration_s, 1, &mut |_| {}).expect("reference plant is hydraulic");
    assert_eq!(rec.len(), rows);
    rec
}

fn csv_text(rec: &Recording) -> Vec<u8> {
    let mut out = Vec::new();
    recording::write_csv(&mut out, rec).expect("writing to memory");
    out
}

fn bench_csv(c: &mut Criterion<cpu_time::Clock>) {
    for rows in [10_000usize, 100_000] {
        let rec = recording_of(rows);
        let text = csv_text(&rec);
        let throughput = Throughput::ElementsAndBytes { elements: rows as u64, bytes: text.len() as u64 };

        let mut g = c.benchmark_group(format!("csv/{}k_rows", rows / 1000));
        g.measurement_time(Duration::from_secs(3)).sample_size(20).warm_up_time(Duration::from_secs(1));
        g.throughput(throughput);
        g.bench_function("parse", |b| {
            b.iter(|| recording::parse(black_box(text.as_slice()), "bench.csv").expect("valid recording"))
        });
        let mut buffer = Vec::with_capacity(text.len());
        g.bench_function("write_csv", |b| {
            b.iter(|| {
                buffer.clear();
                recording::write_csv(&mut buffer, black_box(&rec)).expect("writing to memory");
                buffer.len()
            })
        });
        // the streaming path `simulate` and the service use: one fixed-width row at a time
        let rows_as_arrays: Vec<[f64; simulate::COLUMNS.len()]> = (0..rec.len())
            .map(|k| {
                let mut row = [0.0; simulate::COLUMNS.len()];
                for (slot, v) in row.iter_mut().zip(rec.row(k)) {
                    *slot = v;
                }
                row
            })
            .collect();
        g.bench_function("row_writer", |b| {
            b.iter(|| {
                buffer.clear();
                let mut w = RowWriter::new(&mut buffer, &simulate::COLUMNS).expect("header");
                for row in &rows_as_arrays {
                    w.write_row(black_box(row).iter().copied()).expect("writing to memory");
                }
                w.flush().expect("flush");
            })
        });
        g.finish();
    }
}

criterion_group! {
    name = benches;
    config = cpu_time::criterion();
    targets = bench_csv
}
criterion_main!(benches);

//! What condition monitoring costs: `cargo bench --bench condition`.
//!
//! 1. **A check's CPU time**: one check (src/condition.rs `check`, what the service's `condition` thread runs) of
//!    120 s of data at 5 ms (24 000 rows, the most a check sees: the service thins its ring to 200 Hz), on a
//!    simulated plant whose leak grows. The thread's own CPU time (`CLOCK_THREAD_CPUTIME_ID`) and its wall time,
//!    over `HYDROLENS_BENCH_CHECKS` checks (default 3). Target: ≤ 2 s of CPU.
//! 2. **Poll-loop jitter while checks run**: the plant simulator (1 kHz samples) and the service polling it every
//!    1 ms, in this process over 127.0.0.1, in speed mode. First `HYDROLENS_BENCH_SECONDS` (default 10) with no
//!    check, then as long with checks of the 120 s window running back to back on a thread at the `condition`
//!    thread's nice value (src/service/condition.rs). The service's own p99 of |period − 1 ms| over its last 1000
//!    cycles (`/api/status` `timing.jitter_p99_ms`) is read once a second; the table gives the median and the
//!    worst of those readings. Target: ≤ 200 µs while checks run. `HYDROLENS_BENCH_RT=<1..99>` puts the poll
//!    thread under SCHED_FIFO (as `demo` does) and the simulator thread with it.
//! 3. **Ten drives with a check every 60 s**: 10 × the CPU of one check / 60 s, as a share of one core (the checks
//!    of all drives run one after another on the one `condition` thread). Target: < 0.5 core.
//!
//! Linux (thread CPU clock, nice). Run it on an otherwise quiet machine for the jitter figures.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use hydrolens::condition;
use hydrolens::modbus::simulator::Simulator;
use hydrolens::plant::PlantModel;
use hydrolens::recording::Recording;
use hydrolens::service;
use rustix::time::{ClockId, clock_gettime};
use tokio_util::sync::CancellationToken;

fn thread_cpu_s() -> f64 {
    let t = clock_gettime(ClockId::ThreadCPUTime);
    t.tv_sec as f64 + t.tv_nsec as f64 * 1e-9
}

fn env_or(name: &str, default: u64) -> u64 {
    std::env::var(name).ok().and_then(|v| v.parse().ok()).unwrap_or(default)
}

/// The reference plant with an internal leak growing from 0 by 0.3 l/min/bar an hour.
fn wearing_plant() -> PlantModel {
    let text = format!(
        "{}\n[effects.internal_leakage]\nl_min_per_bar = 0.0\n\n[wear.internal_leakage]\ngrowth_per_hour = 0.3\n",
        hydrolens::plant::model::REFERENCE_TOML
    );
    PlantModel::parse(&text, "wearing plant").expect("valid")
}

/// 120 s of the wearing plant on the test stand (after 300 s of wear), kept as the service keeps its ring: the
/// recorder's columns, every 5th plant sample (5 ms), no load column (the load is unknown).
fn window_120_s_at_5_ms() -> Recording {
    let rec = hydrolens::recording::simulated::test_stand(&wearing_plant(), 420.0, 3, &mut |_| {}).expect("simulable");
    let t = rec.t_s();
    let from = t.partition_point(|v| *v < 300.0);
    let names = service::state::COLUMNS;
    let mut cols: Vec<Vec<f64>> = vec![Vec::new(); names.len()];
    for k in (from..rec.len()).step_by(5) {
        for (c, name) in cols.iter_mut().zip(names) {
            c.push(rec.column(name).map_or(f64::NAN, |col| col[k]));
        }
    }
    Recording::from_columns("120 s at 5 ms", names.iter().map(|s| s.to_string()).collect(), cols)
}

fn nominal() -> PlantModel {
    let mut m = PlantModel::reference();
    m.load = hydrolens::plant::LoadSpec::Recorded;
    m
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn check_cost(window: &Recording, runs: u64) -> (f64, f64, f64) {
    let model = nominal();
    let (mut cpu, mut wall) = (Vec::new(), Vec::new());
    for _ in 0..runs {
        let (c0, w0) = (thread_cpu_s(), Instant::now());
        let c = condition::check(window, &model, 420.0, 120.0).expect("a check");
        cpu.push(thread_cpu_s() - c0);
        wall.push(w0.elapsed().as_secs_f64());
        // a check that works: the window's leak (0.015 to 0.021 l/min/bar) is named
        assert!(c.value("internal_leakage", "l_min_per_bar").is_some(), "the leak named: {}", c.findings);
    }
    let worst = cpu.iter().copied().fold(0.0, f64::max);
    (median(&mut cpu), worst, median(&mut wall))
}

/// Reads the drive's p99 jitter (ms) once a second for `seconds`.
fn jitter_readings(state: &service::ServiceState, seconds: u64) -> Vec<f64> {
    (0..seconds)
        .map(|_| {
            std::thread::sleep(Duration::from_secs(1));
            state.drives[0].snapshot().timing.jitter_p99_ms
        })
        .collect()
}

fn main() {
    // `cargo bench` passes --bench; a filter or --list has nothing to select here
    if std::env::args().any(|a| a == "--list") {
        return;
    }
    let runs = env_or("HYDROLENS_BENCH_CHECKS", 3).max(1);
    let seconds = env_or("HYDROLENS_BENCH_SECONDS", 10).max(2);
    let rt_priority = std::env::var("HYDROLENS_BENCH_RT").ok().and_then(|v| v.parse::<u8>().ok());

    eprintln!("simulating 420 s of a wearing plant for the 120 s window …");
    let window = Arc::new(window_120_s_at_5_ms());
    let (cpu, cpu_worst, wall) = check_cost(&window, runs);

    // the plant and the service, 1 ms poll, speed mode
    let stop = CancellationToken::new();
    let sim = Simulator::new(PlantModel::reference(), 7).expect("simulator");
    let listener = std::net::TcpListener::bind("127.0.0.1:0").expect("bind");
    let addr = listener.local_addr().expect("addr");
    listener.set_nonblocking(true).expect("nonblocking");
    let sim_stop = stop.clone();
    let plant = std::thread::spawn(move || {
        if let Some(p) = rt_priority {
            service::timing::use_realtime_priority(p, "plant-sim");
        }
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().expect("runtime");
        rt.block_on(async move {
            let l = tokio::net::TcpListener::from_std(listener).expect("listener");
            let _ = sim.run(l, sim_stop).await;
        });
    });
    let rt_line = rt_priority.map_or(String::new(), |p| format!("realtime_priority = {p}\n"));
    let text = format!(
        "[http]\nbind = \"127.0.0.1:0\"\n\n[recording]\nenabled = false\n\n[[drives]]\nname = \"pump1\"\n\
         address = \"{addr}\"\npoll_ms = 1\ntimeout_ms = 200\n{rt_line}\n[drives.control]\nmode = \"speed\"\n\
         target_omega_rad_s = 40.0\n"
    );
    let settings = service::config::parse(&text, "bench config", None).expect("config");
    let svc = service::start(&settings, stop.clone()).expect("service");
    std::thread::sleep(Duration::from_secs(3)); // connected, settled, a full timing window
    let quiet = jitter_readings(&svc.state, seconds);

    let running = Arc::new(AtomicBool::new(true));
    let (flag, w) = (running.clone(), window.clone());
    let checker = std::thread::Builder::new()
        .name("condition".into())
        .spawn(move || {
            service::condition::lower_priority();
            let model = nominal();
            let mut n = 0u32;
            while flag.load(Ordering::Relaxed) {
                let _ = condition::check(&w, &model, 420.0, 120.0);
                n += 1;
            }
            n
        })
        .expect("checker");
    std::thread::sleep(Duration::from_secs(1)); // the readings' 1000 cycles all under the checks
    let loaded = jitter_readings(&svc.state, seconds);
    running.store(false, Ordering::Relaxed);
    let checks_run = checker.join().expect("checker joins");
    let overruns = svc.state.drives[0].snapshot().timing.overruns;
    stop.cancel();
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().expect("runtime");
    rt.block_on(svc.wait());
    let _ = plant.join();

    let (mut q, mut l) = (quiet.clone(), loaded.clone());
    let worst = |v: &[f64]| v.iter().copied().fold(0.0, f64::max);
    println!("condition monitoring cost ({} CPUs online)", std::thread::available_parallelism().map_or(0, |n| n.get()));
    println!("| measure | value | target |");
    println!("|---|---|---|");
    println!(
        "| one check, 120 s at 5 ms (24 000 rows): CPU, median of {runs} (worst) | {cpu:.2} s ({cpu_worst:.2} s) | ≤ 2 s |"
    );
    println!("| the same check: wall time, median | {wall:.2} s | |");
    println!(
        "| 1 ms poll loop{}, p99 jitter, no check: median (worst) of {seconds} readings | {:.0} µs ({:.0} µs) | |",
        if rt_priority.is_some() { " (SCHED_FIFO)" } else { "" },
        median(&mut q) * 1e3,
        worst(&quiet) * 1e3
    );
    println!(
        "| … while checks run back to back ({checks_run} checks): median (worst) | {:.0} µs ({:.0} µs) | ≤ 200 µs |",
        median(&mut l) * 1e3,
        worst(&loaded) * 1e3
    );
    println!("| poll-loop overruns over the whole run | {overruns} | |");
    println!(
        "| ten drives, a check each every 60 s: 10 × {cpu:.2} s / 60 s | {:.3} core | < 0.5 core |",
        10.0 * cpu / 60.0
    );
}

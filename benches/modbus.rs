//! Round-trip latency of one batched Modbus read (6 input registers, function 04) with tokio-modbus.
//!
//! By default against the plant simulator in this process on 127.0.0.1:0; with `HYDROLENS_BENCH_ADDR=host:port`
//! against an external one (`hydrolens sim`), which is how `bench/peers.sh` puts it side by side with pymodbus.
//! `HYDROLENS_BENCH_REQUESTS` sets the number of timed requests (default 5000, after 500 untimed ones).
//! Prints one line per run: `modbus_read6 rust-tokio-modbus requests=N p50_us=… p90_us=… p99_us=… max_us=… mean_us=…`.

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use hydrolens::modbus::simulator::Simulator;
use hydrolens::plant::PlantModel;
use tokio_modbus::client::{Reader, tcp};
use tokio_modbus::slave::Slave;
use tokio_util::sync::CancellationToken;

const WARM_UP: usize = 500;

fn env_or<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name).ok().and_then(|v| v.parse().ok()).unwrap_or(default)
}

/// The value at quantile `q` (0…1) of sorted samples, nearest rank.
fn quantile(sorted: &[Duration], q: f64) -> Duration {
    let rank = ((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len());
    sorted[rank - 1]
}

fn micros(d: Duration) -> f64 {
    d.as_secs_f64() * 1e6
}

async fn measure(addr: SocketAddr, requests: usize) -> Result<Vec<Duration>, String> {
    let mut ctx = tcp::connect_slave(addr, Slave(1)).await.map_err(|e| format!("connecting to {addr}: {e}"))?;
    let timeout = Duration::from_secs(1);
    let mut samples = Vec::with_capacity(requests);
    for i in 0..WARM_UP + requests {
        let start = Instant::now();
        let reply = tokio::time::timeout(timeout, ctx.read_input_registers(0, 6))
            .await
            .map_err(|_| format!("request {i} timed out"))?
            .map_err(|e| format!("request {i}: {e}"))?
            .map_err(|e| format!("request {i}: exception {e}"))?;
        let elapsed = start.elapsed();
        if reply.len() != 6 {
            return Err(format!("request {i}: {} registers, expected 6", reply.len()));
        }
        if i >= WARM_UP {
            samples.push(elapsed);
        }
    }
    Ok(samples)
}

fn main() {
    // `cargo bench [FILTER]` passes the filter and `--bench`; run only when no filter or a matching one is given
    let filters: Vec<String> = std::env::args().skip(1).filter(|a| !a.starts_with('-')).collect();
    if !filters.is_empty() && !filters.iter().any(|f| "modbus_read6".contains(f.as_str())) {
        return;
    }
    let requests: usize = env_or("HYDROLENS_BENCH_REQUESTS", 5000).max(1);
    let external: Option<SocketAddr> = std::env::var("HYDROLENS_BENCH_ADDR").ok().map(|a| {
        a.parse().unwrap_or_else(|e| {
            eprintln!("HYDROLENS_BENCH_ADDR={a:?}: not an address such as 127.0.0.1:5020 ({e})");
            std::process::exit(2)
        })
    });
    let runtime = match tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build() {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("starting the async runtime: {e}");
            std::process::exit(1)
        }
    };
    let result = runtime.block_on(async move {
        let stop = CancellationToken::new();
        let (addr, server, target) = match external {
            Some(addr) => (addr, None, "external"),
            None => {
                let listener =
                    tokio::net::TcpListener::bind("127.0.0.1:0").await.map_err(|e| format!("binding: {e}"))?;
                let addr = listener.local_addr().map_err(|e| e.to_string())?;
                let sim = Simulator::new(PlantModel::reference(), 1).map_err(|e| e.to_string())?;
                let s = stop.clone();
                (addr, Some(tokio::spawn(async move { sim.run(listener, s).await })), "in-process")
            }
        };
        let samples = measure(addr, requests).await;
        stop.cancel();
        if let Some(server) = server {
            let _ = server.await;
        }
        samples.map(|s| (s, target))
    });
    let (mut samples, target) = match result {
        Ok(r) => r,
        Err(e) => {
            eprintln!("modbus bench: {e}");
            std::process::exit(1)
        }
    };
    samples.sort_unstable();
    let mean = samples.iter().map(|d| d.as_secs_f64()).sum::<f64>() / samples.len() as f64 * 1e6;
    println!(
        "modbus_read6 rust-tokio-modbus simulator={target} requests={} p50_us={:.1} p90_us={:.1} p99_us={:.1} \
         max_us={:.1} mean_us={mean:.1}",
        samples.len(),
        micros(quantile(&samples, 0.5)),
        micros(quantile(&samples, 0.9)),
        micros(quantile(&samples, 0.99)),
        micros(quantile(&samples, 1.0)),
    );
}

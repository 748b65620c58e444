//! The plant simulator over real Modbus TCP on 127.0.0.1 (port 0), and the `sim`/`simulate` command line.

use std::process::Command;
use std::time::Duration;

use hydrolens::modbus::map::{control, status};
use hydrolens::modbus::simulator::{SimHandle, Simulator};
use hydrolens::plant::PlantModel;
use tokio::net::TcpListener;
use tokio_modbus::prelude::*;
use tokio_util::sync::CancellationToken;

use crate::support::{bin, root};

/// A simulator of `model` on an ephemeral loopback port.
async fn start(model: PlantModel) -> (std::net::SocketAddr, SimHandle, CancellationToken, tokio::task::JoinHandle<()>) {
    let listener = TcpListener::bind("127.0.0.1:0").await.expect("bind loopback");
    let addr = listener.local_addr().expect("addr");
    let sim = Simulator::new(model, 11).expect("hydraulic model");
    let handle = sim.handle();
    let stop = CancellationToken::new();
    let s = stop.clone();
    let task = tokio::spawn(async move {
        sim.run(listener, s).await.expect("simulator ran");
    });
    (addr, handle, stop, task)
}

async fn within<T>(what: &str, fut: impl std::future::Future<Output = T>) -> T {
    tokio::time::timeout(Duration::from_secs(5), fut).await.unwrap_or_else(|_| panic!("{what} timed out"))
}

async fn speed_rad_s(ctx: &mut tokio_modbus::client::Context) -> f64 {
    let regs = within("read", ctx.read_input_registers(0, 6)).await.expect("transport").expect("no exception");
    f64::from(regs[2] as i16) * 0.1 * 2.0 * std::f64::consts::PI / 60.0
}

/// On tokio's paused clock: the plant runs in virtual time (2–4 s of it here), the sockets are real.
#[tokio::test(start_paused = true)]
async fn a_setpoint_written_over_modbus_moves_the_shaft() {
    let (addr, handle, stop, task) = start(PlantModel::reference()).await;
    let mut ctx = within("connect", tcp::connect_slave(addr, Slave(1))).await.expect("connect");
    let c0 = within("read", ctx.read_input_registers(5, 1)).await.expect("transport").expect("ok")[0];
    // 20 Hz, run
    within("write", ctx.write_multiple_registers(0, &[2000, control::RUN, 1])).await.expect("transport").expect("ok");
    let holding = within("read", ctx.read_holding_registers(0, 3)).await.expect("transport").expect("ok");
    assert_eq!(holding, vec![2000, control::RUN, 1]);
    // any number of clients share the one drive
    let mut others = Vec::new();
    for _ in 0..3 {
        others.push(within("connect", tcp::connect_slave(addr, Slave(1))).await.expect("connect"));
    }
    for other in &mut others {
        let seen = within("read", other.read_holding_registers(0, 1)).await.expect("transport").expect("ok");
        assert_eq!(seen, vec![2000], "another client sees the setpoint (0.01 Hz/LSB)");
    }
    // ideal: 20 Hz / 2 pole pairs = 62.8 rad/s at the pump, half that at the motor, less leakage
    let mut omega = 0.0;
    for k in 0..40u16 {
        tokio::time::sleep(Duration::from_millis(100)).await;
        within("kick", ctx.write_single_register(2, k + 2)).await.expect("transport").expect("ok");
        omega = speed_rad_s(&mut ctx).await;
        if k > 20 && (omega - 31.0).abs() < 3.0 {
            break;
        }
    }
    assert!((omega - 31.0).abs() < 3.0, "speed {omega} rad/s");
    let truth = handle.lock().truth();
    assert!((truth.omega_rad_s - 31.0).abs() < 1.5, "true speed {}", truth.omega_rad_s);
    let c1 = within("read", ctx.read_input_registers(5, 1)).await.expect("transport").expect("ok")[0];
    let moved = c1.wrapping_sub(c0);
    assert!(moved > 1000, "sample counter moved {moved} in > 2 s");
    // a read past the map is a Modbus exception, not a dropped link
    let e = within("read", ctx.read_input_registers(4, 10)).await.expect("transport");
    assert_eq!(e, Err(ExceptionCode::IllegalDataAddress));
    assert!(within("read", ctx.read_input_registers(0, 6)).await.expect("transport").is_ok());
    stop.cancel();
    within("stop", task).await.expect("clean stop");
}

/// On tokio's paused clock: the simulator's plant runs in virtual time, so the waits below cost nothing and the
/// trip comes after exactly `comm_timeout_ms` of plant time.
#[tokio::test(start_paused = true)]
async fn the_watchdog_trips_the_drive_and_a_reset_rearms_it() {
    let mut model = PlantModel::reference();
    if let Some(d) = model.drive.as_mut() {
        d.comm_timeout_ms = 300;
    }
    let (addr, handle, stop, task) = start(model).await;
    let mut ctx = within("connect", tcp::connect_slave(addr, Slave(1))).await.expect("connect");
    within("write", ctx.write_multiple_registers(0, &[3000, control::RUN, 1])).await.expect("transport").expect("ok");
    tokio::time::sleep(Duration::from_millis(200)).await;
    let st = within("read", ctx.read_input_registers(4, 1)).await.expect("transport").expect("ok")[0];
    assert_eq!(st & (status::READY | status::RUNNING), status::READY | status::RUNNING, "status {st:#06b}");
    // stop kicking the watchdog: the drive trips and ramps down
    tokio::time::sleep(Duration::from_millis(600)).await;
    let st = within("read", ctx.read_input_registers(4, 1)).await.expect("transport").expect("ok")[0];
    assert_ne!(st & status::COMM_LOSS_TRIP, 0, "status {st:#06b}");
    assert_eq!(st & status::READY, 0);
    assert!(handle.lock().truth().tripped);
    tokio::time::sleep(Duration::from_millis(1500)).await;
    assert!(handle.lock().truth().f_drive_hz < 0.5, "ramping to 0 Hz");
    // fault reset (bit 7), then run again while kicking the watchdog
    within("reset", ctx.write_single_register(1, control::RUN | control::FAULT_RESET))
        .await
        .expect("transport")
        .expect("ok");
    within("run", ctx.write_single_register(1, control::RUN)).await.expect("transport").expect("ok");
    for k in 0..10u16 {
        within("kick", ctx.write_single_register(2, 100 + k)).await.expect("transport").expect("ok");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let st = within("read", ctx.read_input_registers(4, 1)).await.expect("transport").expect("ok")[0];
    assert_eq!(st & status::COMM_LOSS_TRIP, 0, "status {st:#06b}");
    assert!(handle.lock().truth().f_drive_hz > 5.0);
    stop.cancel();
    within("stop", task).await.expect("clean stop");
}

#[test]
fn simulate_writes_the_contract_columns_fast_and_deterministically() {
    let dir = tempfile::tempdir().expect("tmp");
    let run = |seed: &str, out: &str| {
        let status = Command::new(bin())
            .args(["simulate", "--model"])
            .arg(root().join("config/plant.toml"))
            .args(["--duration", "10", "--seed", seed, "--out"])
            .arg(dir.path().join(out))
            .status()
            .expect("runs");
        assert!(status.success());
        std::fs::read_to_string(dir.path().join(out)).expect("written")
    };
    let a = run("5", "a.csv");
    assert_eq!(a, run("5", "b.csv"));
    assert_ne!(a, run("6", "c.csv"));
    let header = a.lines().next().expect("header");
    assert_eq!(
        header,
        "t_s,f_set_hz,f_drive_hz,p_in_bar,p_out_bar,omega_rad_s,load_nm,true_omega_rad_s,true_p_in_bar,true_load_nm,true_f_drive_hz"
    );
    assert_eq!(a.lines().count(), 10_002);
}

/// A fan behind the motor (`[load] kind = "centrifugal"`): `simulate` applies it at the shaft's speed, and
/// `true_load_nm` is the torque applied in each row.
#[test]
fn simulate_applies_a_load_that_follows_the_shaft_speed() {
    let dir = tempfile::tempdir().expect("tmp");
    let plant = std::fs::read_to_string(root().join("config/plant.toml")).expect("plant.toml");
    let model = dir.path().join("fan.toml");
    let fan = plant.replace("kind = \"recorded\"", "kind = \"centrifugal\"\ntorque_nm = 12.0\nat_rad_s = 60.0");
    std::fs::write(&model, fan).expect("write");
    let out = dir.path().join("fan.csv");
    let status = Command::new(bin())
        .args(["simulate", "--model"])
        .arg(&model)
        .args(["--duration", "20", "--seed", "1", "--out"])
        .arg(&out)
        .status()
        .expect("runs");
    assert!(status.success());
    let text = std::fs::read_to_string(&out).expect("written");
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().expect("header").split(',').collect();
    let col = |name: &str| header.iter().position(|c| *c == name).expect("column");
    let (w, load) = (col("true_omega_rad_s"), col("true_load_nm"));
    let mut fastest = 0.0f64;
    for line in lines {
        let v: Vec<f64> = line.split(',').map(|x| x.parse().expect("number")).collect();
        let x = v[w] / 60.0;
        assert!((v[load] - 12.0 * x * x.abs()).abs() < 1e-6 * (1.0 + v[load].abs()), "{line}");
        fastest = fastest.max(v[w]);
    }
    assert!(fastest > 30.0, "the program turns the shaft: {fastest} rad/s at most");
}

#[test]
fn bad_input_exits_2_naming_what_and_where() {
    let dir = tempfile::tempdir().expect("tmp");
    let plant = std::fs::read_to_string(root().join("config/plant.toml")).expect("plant.toml");
    let cases = [
        ("unknown.toml", plant.replace("volume_l", "volume_litres"), "volume_litres"),
        ("type.toml", plant.replace("pole_pairs = 2", "pole_pairs = \"two\""), "pole_pairs"),
        ("negative.toml", plant.replace("time_constant_s = 0.02", "time_constant_s = -1.0"), "drive.time_constant_s"),
        ("effect.toml", format!("{plant}\n[effects.dead_time]\nmilliseconds = 3\n"), "milliseconds"),
        (
            "fan.toml",
            plant.replace("kind = \"recorded\"", "kind = \"centrifugal\"\ntorque_nm = 12.0\nat_rad_s = 0.0"),
            "load.at_rad_s",
        ),
    ];
    for (name, text, needle) in cases {
        let path = dir.path().join(name);
        std::fs::write(&path, text).expect("write");
        let out = Command::new(bin())
            .args(["simulate", "--model"])
            .arg(&path)
            .args(["--duration", "1", "--out"])
            .arg(dir.path().join("x.csv"))
            .output()
            .expect("runs");
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{name}: {err}");
        assert!(err.contains(needle) && err.contains(name), "{name}: {err}");
    }
    let out = Command::new(bin()).args(["sim", "--model"]).arg(dir.path().join("missing.toml")).output().expect("runs");
    assert_eq!(out.status.code(), Some(2), "a file that does not exist is bad input");
    assert!(String::from_utf8_lossy(&out.stderr).contains("missing.toml"));
}

#[test]
fn sim_serves_until_sigterm_and_exits_cleanly() {
    for reader_kept in [true, false] {
        sigterm_with_stderr(reader_kept);
    }
}

/// `sim` on SIGTERM, its stderr read to the end or closed after its address (a `| head` or a log shipper that went
/// away): it logs "shutting down" and exits 0 either way. Before, the log line into the closed pipe aborted it (the
/// logger's own error report panicked: exit 134, and a `serve` so killed sends no stop).
fn sigterm_with_stderr(reader_kept: bool) {
    use std::io::{BufRead, BufReader};
    let mut child = Command::new(bin())
        .args(["sim", "--model"])
        .arg(root().join("config/plant.toml"))
        .args(["--listen", "127.0.0.1:0"])
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("starts");
    let stderr = child.stderr.take().expect("stderr");
    let mut lines = BufReader::new(stderr).lines();
    let addr = loop {
        let line = lines.next().expect("sim prints its address").expect("utf-8");
        if let Some(rest) = line.split("modbus tcp://").nth(1) {
            break rest.trim().to_string();
        }
    };
    let addr: std::net::SocketAddr = addr.parse().expect("an address");
    assert!(addr.ip().is_loopback());
    std::net::TcpStream::connect_timeout(&addr, Duration::from_secs(2)).expect("accepts connections");
    if !reader_kept {
        drop(lines);
    }
    let pid = child.id().to_string();
    assert!(Command::new("kill").args(["-TERM", &pid]).status().expect("kill").success());
    let status = crate::support::wait_exit(&mut child, Duration::from_secs(5)).expect("sim stops on SIGTERM");
    assert!(status.success(), "stderr read: {reader_kept}; exit {status:?}");
}

//! Compressed recordings (issue 20, item 10): the service compresses each closed file to `.csv.gz` over real Modbus
//! loopback to the simulator, and `estimate`, `analyze`, the download route and retention take them as they are.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, SystemTime};

use flate2::Compression;
use flate2::read::MultiGzDecoder;
use flate2::write::GzEncoder;
use hydrolens::plant::PlantModel;
use hydrolens::recording::{self, Recording};

use crate::support::{self, metric, start_service, stop_service, wait_for};

fn gzip(bytes: &[u8]) -> Vec<u8> {
    let mut e = GzEncoder::new(Vec::new(), Compression::default());
    e.write_all(bytes).expect("compress");
    e.finish().expect("finish")
}

fn gunzip(bytes: &[u8]) -> String {
    let mut s = String::new();
    MultiGzDecoder::new(bytes).read_to_string(&mut s).expect("a valid gzip stream");
    s
}

fn names_in(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> =
        std::fs::read_dir(dir).expect("dir").map(|e| e.expect("entry").file_name().to_string_lossy().into()).collect();
    v.sort();
    v
}

/// The service with the smallest rotation (`max_file_mb = 0.1`) at a 1 ms poll: each closed file becomes a
/// `.csv.gz` that decompresses to a valid recording, the open one stays plain, the routes list and serve the
/// compressed files as they are, and at the stop the last file is compressed too.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_service_compresses_each_closed_file_and_serves_it() {
    let run = async {
        let (_sim, modbus, sim_stop, _task) = support::start_sim(support::test_plant(5.0), 0).await;
        let dir = tempfile::tempdir().expect("tmp");
        let text = format!(
            "[http]\nbind = \"127.0.0.1:0\"\n[recording]\ndir = {:?}\nmax_file_mb = 0.1\n\
             [[drives]]\nname = \"pump1\"\naddress = \"{modbus}\"\npoll_ms = 1\n",
            dir.path().display().to_string()
        );
        let svc = start_service(&text).await;
        let url = svc.url.clone();
        let gz_files = || names_in(dir.path()).into_iter().filter(|n| n.ends_with(".csv.gz")).collect::<Vec<_>>();
        let two = wait_for(Duration::from_secs(20), || async { gz_files().len() >= 2 }).await;
        assert!(two.is_some(), "closed files compressed: {:?}", names_in(dir.path()));
        // the open file, the newest, is never compressed (the closed ones are, at the keeper's next turn)
        let mut files: Vec<(Vec<u64>, bool)> =
            names_in(dir.path()).iter().filter_map(|n| recording::drive_file_key(n, "pump1")).collect();
        files.sort();
        assert_eq!(files.last().map(|(_, compressed)| *compressed), Some(false), "{:?}", names_in(dir.path()));
        for name in gz_files() {
            let bytes = std::fs::read(dir.path().join(&name)).expect("read");
            let text = gunzip(&bytes);
            let rec = recording::parse(text.as_bytes(), &name).expect("decompresses to a valid recording");
            assert!(rec.len() > 100, "{name}: {} rows", rec.len());
            let again = recording::load(&dir.path().join(&name)).expect("loads as it is");
            assert_eq!(again.t_s(), rec.t_s());
        }
        // the routes: listed, and served as the gzip file it is
        let list = support::get_json(format!("{url}/api/recordings")).await;
        let listed: Vec<&str> =
            list["files"].as_array().expect("files").iter().filter_map(|f| f["name"].as_str()).collect();
        let name = gz_files()[0].clone();
        assert!(listed.contains(&name.as_str()), "{name} in {listed:?}");
        let got = reqwest::get(format!("{url}/api/recordings/{name}")).await.expect("GET file");
        assert_eq!(got.status(), 200);
        assert_eq!(got.headers()["content-type"], "application/gzip");
        assert!(got.headers().get("content-encoding").is_none(), "saved, it stays a .csv.gz");
        let body = got.bytes().await.expect("body");
        assert_eq!(body.as_ref(), std::fs::read(dir.path().join(&name)).expect("read").as_slice());
        assert!(gunzip(&body).starts_with("t_s,f_set_hz,"));
        let m = reqwest::get(format!("{url}/metrics")).await.expect("metrics").text().await.expect("text");
        assert!(metric(&m, "hydrolens_recording_files_compressed_total{drive=\"pump1\"}").unwrap_or(0.0) >= 2.0, "{m}");
        stop_service(svc).await;
        sim_stop.cancel();
        // at the stop the last file was closed and compressed: nothing plain, no temporary file
        let left = names_in(dir.path());
        // (the lock file stays: the lock itself went with the process's handle)
        let left: Vec<&String> = left.iter().filter(|n| *n != hydrolens::service::recorder::LOCK_FILE).collect();
        assert!(left.iter().all(|n| n.starts_with("pump1-") && n.ends_with(".csv.gz")), "{left:?}");
        // and the files join into one recording, time running on across them
        let files = recording::drive_files(dir.path(), "pump1").expect("found");
        let parts: Vec<Recording> = files.iter().map(|p| recording::load(p).expect("loads")).collect();
        let joined = recording::join(parts).expect("one run");
        assert!(joined.len() > 1000, "{} rows", joined.len());
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("bounded");
}

/// A short test-stand recording written as the service writes it, `rec.csv` and its gzip `rec.csv.gz`.
fn recording_pair(dir: &Path) -> (PathBuf, PathBuf, Recording) {
    let rec =
        hydrolens::recording::simulated::test_stand(&PlantModel::reference(), 30.0, 7, &mut |_| {}).expect("runs");
    let plain = dir.join("rec.csv");
    recording::write_csv(std::fs::File::create(&plain).expect("create"), &rec).expect("write");
    let gz = dir.join("rec.csv.gz");
    std::fs::write(&gz, gzip(&std::fs::read(&plain).expect("read"))).expect("write gz");
    (plain, gz, rec)
}

fn estimate(rec: &Path, out: &Path) -> std::process::Output {
    Command::new(support::bin())
        .arg("estimate")
        .arg(rec)
        .arg("--model")
        .arg(support::root().join("config/plant.toml"))
        .arg("--out")
        .arg(out)
        .output()
        .expect("estimate runs")
}

/// `analyze` on `args`, its JSON without the name of what it read.
fn analyze(args: &[&std::ffi::OsStr], json: &Path) -> serde_json::Value {
    let out = Command::new(support::bin())
        .arg("analyze")
        .args(args)
        .arg("--model")
        .arg(support::root().join("config/plant.toml"))
        .arg("--json")
        .arg(json)
        .output()
        .expect("analyze runs");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let mut v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(json).expect("json")).expect("valid json");
    let o = v.as_object_mut().expect("object");
    o.remove("recording");
    // each entry names the file and line it is in, as `recording` names the files
    for entry in o.get_mut("out_of_range").and_then(|e| e.as_array_mut()).into_iter().flatten() {
        let entry = entry.as_object_mut().expect("object");
        entry.remove("file");
        entry.remove("first_line");
    }
    v
}

#[test]
fn estimate_and_analyze_give_the_same_on_a_csv_gz_as_on_the_csv() {
    let tmp = tempfile::tempdir().expect("tmp");
    let (plain, gz, rec) = recording_pair(tmp.path());
    let (a, b) = (tmp.path().join("a.csv"), tmp.path().join("b.csv"));
    for (input, out) in [(&plain, &a), (&gz, &b)] {
        let o = estimate(input, out);
        assert!(o.status.success(), "{}: {}", input.display(), String::from_utf8_lossy(&o.stderr));
    }
    let (a, b) = (std::fs::read(&a).expect("a"), std::fs::read(&b).expect("b"));
    assert!(a.len() > 100_000 && a == b, "the same estimates, byte for byte ({} and {} bytes)", a.len(), b.len());

    let json = tmp.path().join("a.json");
    let on_csv = analyze(&[plain.as_os_str()], &json);
    let on_gz = analyze(&[gz.as_os_str()], &json);
    assert_eq!(on_csv["samples"].as_u64(), Some(rec.len() as u64));
    assert_eq!(on_csv, on_gz);
    // a recordings directory of compressed rotated files, read with --drive
    let drive_dir = tmp.path().join("recordings");
    std::fs::create_dir(&drive_dir).expect("mkdir");
    let n = rec.len();
    for (i, (from, to)) in [(0, n / 2), (n / 2, n)].into_iter().enumerate() {
        let cols: Vec<Vec<f64>> = rec.names().iter().map(|c| rec.column(c).expect("col")[from..to].to_vec()).collect();
        let mut text = Vec::new();
        recording::write_csv(&mut text, &Recording::from_columns("part", rec.names().to_vec(), cols)).expect("write");
        std::fs::write(drive_dir.join(format!("pump1-{}.csv.gz", 1000 + i)), gzip(&text)).expect("write gz");
    }
    let on_dir = analyze(&[drive_dir.as_os_str(), "--drive".as_ref(), "pump1".as_ref()], &json);
    assert_eq!(on_csv, on_dir);
}

/// A gzip stream cut short (the process died while compressing by hand, or the copy was cut) keeps its whole
/// rows with a warning; corrupt data and a bad cell inside a `.csv.gz` exit 2 naming the file (and the line).
#[test]
fn a_truncated_csv_gz_is_read_with_a_warning_and_errors_name_file_and_line() {
    let tmp = tempfile::tempdir().expect("tmp");
    let (plain, gz, rec) = recording_pair(tmp.path());
    let full = std::fs::read(&gz).expect("read");
    let cut = tmp.path().join("cut.csv.gz");
    std::fs::write(&cut, &full[..full.len() * 2 / 3]).expect("write");
    let loaded = recording::load(&cut).expect("a cut stream is read");
    assert!(loaded.len() > rec.len() / 2 && loaded.len() < rec.len(), "{} of {} rows", loaded.len(), rec.len());
    assert_eq!(loaded.t_s(), &rec.t_s()[..loaded.len()], "the rows before the cut, whole");
    let out = tmp.path().join("est.csv");
    let o = estimate(&cut, &out);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    assert!(stderr.contains("cut short"), "warned: {stderr}");
    assert_eq!(recording::load(&out).expect("output").len(), loaded.len());

    // corrupt data: in the middle (the garbage reaches the parser, or the inflater refuses it), and in the
    // checksum at the end (every row reads, then the check fails)
    let n = full.len();
    for (name, at) in [("corrupt.csv.gz", n / 2), ("checksum.csv.gz", n - 8)] {
        let mut bad = full.clone();
        for b in &mut bad[at..(at + 64).min(n)] {
            *b ^= 0x5a;
        }
        let corrupt = tmp.path().join(name);
        std::fs::write(&corrupt, &bad).expect("write");
        let o = estimate(&corrupt, &out);
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{stderr}");
        assert!(stderr.contains(name) && stderr.contains("line "), "{stderr}");
        if name == "checksum.csv.gz" {
            assert!(stderr.contains("corrupt gzip data after line"), "{stderr}");
        }
    }

    // a bad cell on line 1001, inside the compressed text
    let text = std::fs::read_to_string(&plain).expect("read");
    let mut lines: Vec<String> = text.lines().map(String::from).collect();
    lines[1000] = lines[1000].replacen(',', ",abc", 1);
    let cell = tmp.path().join("cell.csv.gz");
    std::fs::write(&cell, gzip(format!("{}\n", lines.join("\n")).as_bytes())).expect("write");
    for command in ["estimate", "analyze"] {
        let o = if command == "estimate" {
            estimate(&cell, &out)
        } else {
            Command::new(support::bin())
                .arg("analyze")
                .arg(&cell)
                .arg("--model")
                .arg(support::root().join("config/plant.toml"))
                .arg("--json")
                .arg(tmp.path().join("a.json"))
                .output()
                .expect("analyze runs")
        };
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{command}: {stderr}");
        assert!(stderr.contains("cell.csv.gz") && stderr.contains("line 1001"), "{command}: {stderr}");
    }
}

/// Retention counts and deletes `.csv.gz` files like plain ones; at start the recorder compresses a plain file an
/// earlier run left behind and removes the temporary file of a compression cut short.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn retention_deletes_old_csv_gz_and_the_start_compresses_what_an_earlier_run_left() {
    let run = async {
        let (_sim, modbus, sim_stop, _task) = support::start_sim(support::test_plant(5.0), 0).await;
        let dir = tempfile::tempdir().expect("tmp");
        let text = "t_s,omega_rad_s\n0,1\n0.001,2\n";
        let ten_days_ago = SystemTime::now() - Duration::from_secs(10 * 86_400);
        for name in ["pump1-1000.csv.gz", "pump1-2000-1.csv.gz"] {
            let f = std::fs::File::create(dir.path().join(name)).expect("create");
            (&f).write_all(&gzip(text.as_bytes())).expect("write");
            f.set_modified(ten_days_ago).expect("mtime");
        }
        // a recent compressed file, a plain file an earlier run left, a compression cut short
        std::fs::write(dir.path().join("pump1-3000.csv.gz"), gzip(text.as_bytes())).expect("write");
        std::fs::write(dir.path().join("pump1-4000.csv"), text).expect("write");
        std::fs::write(dir.path().join(".pump1-4000.csv.gz.tmp"), b"\x1f\x8b half").expect("write");
        let config = format!(
            "[http]\nbind = \"127.0.0.1:0\"\n[recording]\ndir = {:?}\nkeep_days = 1\n\
             [[drives]]\nname = \"pump1\"\naddress = \"{modbus}\"\npoll_ms = 10\n",
            dir.path().display().to_string()
        );
        let svc = start_service(&config).await;
        let url = svc.url.clone();
        let deleted = || async {
            let m = reqwest::get(format!("{url}/metrics")).await.expect("metrics").text().await.expect("text");
            metric(&m, "hydrolens_recording_files_deleted_total{drive=\"pump1\"}").unwrap_or(0.0)
        };
        let went = wait_for(Duration::from_secs(10), || async { deleted().await >= 2.0 }).await;
        assert!(went.is_some(), "old .csv.gz deleted and counted: {:?}", names_in(dir.path()));
        let compressed = wait_for(Duration::from_secs(10), || async {
            dir.path().join("pump1-4000.csv.gz").exists() && !dir.path().join("pump1-4000.csv").exists()
        })
        .await;
        assert!(compressed.is_some(), "the earlier run's file compressed: {:?}", names_in(dir.path()));
        let left = names_in(dir.path());
        assert!(!left.iter().any(|n| n == "pump1-1000.csv.gz" || n == "pump1-2000-1.csv.gz"), "{left:?}");
        assert!(left.iter().any(|n| n == "pump1-3000.csv.gz"), "a recent file stays: {left:?}");
        assert!(!left.iter().any(|n| n.ends_with(".tmp")), "the cut compression removed: {left:?}");
        let back = recording::load(&dir.path().join("pump1-4000.csv.gz")).expect("valid");
        assert_eq!(back.t_s(), &[0.0, 0.001]);
        stop_service(svc).await;
        sim_stop.cancel();
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("bounded");
}

/// The disk one drive needs per day at each poll rate, uncompressed and compressed (docs/reliability.md,
/// "Disk per drive"): the service regulates the reference plant (sensor noise, brake-load steps) over Modbus
/// loopback to the simulator while the target runs the demo program, and records `HYDROLENS_DISK_S` seconds
/// (default 20) at each poll rate; each file is then compressed by the recorder's own `gz::compress`.
/// `cargo test --locked --test it -- compressed::disk_per_drive_per_day --ignored --nocapture`
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "a measurement: about 90 s"]
async fn disk_per_drive_per_day() {
    let seconds: u64 = std::env::var("HYDROLENS_DISK_S").ok().and_then(|s| s.parse().ok()).unwrap_or(20);
    println!(
        "| poll | rows | bytes/row, .csv | bytes/row, .csv.gz | ratio | per day, .csv | per day, .csv.gz | compressing |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    let mut sample = Vec::new();
    for poll_ms in [1u64, 2, 5, 10] {
        let (_sim, modbus, sim_stop, sim_task) = support::start_sim(PlantModel::reference(), 0).await;
        let dir = tempfile::tempdir().expect("tmp");
        let config = format!(
            "[http]\nbind = \"127.0.0.1:0\"\n[recording]\ndir = {:?}\ncompress = false\n[[drives]]\nname = \"pump1\"\n\
             address = \"{modbus}\"\npoll_ms = {poll_ms}\ntimeout_ms = 100\n[drives.control]\nmode = \"speed\"\n\
             target_omega_rad_s = 40.0\nmax_hz = 50.0\nramp_hz_per_s = 20.0\n",
            dir.path().display().to_string()
        );
        let svc = start_service(&config).await;
        support::follow_demo_program(&svc.state.drives[0], seconds).await;
        stop_service(svc).await;
        sim_stop.cancel();
        let _ = tokio::time::timeout(Duration::from_secs(10), sim_task).await;
        let (mut rows, mut plain, mut packed, mut compress_s) = (0u64, 0u64, 0u64, 0.0);
        for path in recording::drive_files(dir.path(), "pump1").expect("recorded") {
            rows += recording::load(&path).expect("valid").len() as u64;
            if sample.is_empty() {
                sample = std::fs::read(&path).expect("read");
            }
            plain += std::fs::metadata(&path).expect("meta").len();
            let t0 = std::time::Instant::now();
            let gz = recording::gz::compress(&path).expect("compresses");
            compress_s += t0.elapsed().as_secs_f64();
            packed += std::fs::metadata(&gz).expect("meta").len();
        }
        assert!(rows > seconds * 1000 / poll_ms / 2, "{rows} rows");
        let (per_row, per_row_gz) = (plain as f64 / rows as f64, packed as f64 / rows as f64);
        let rows_per_day = 86_400_000.0 / poll_ms as f64;
        println!(
            "| {poll_ms} ms | {rows} | {per_row:.1} | {per_row_gz:.1} | {:.2} | {:.2} GB | {:.2} GB | {:.0} MB/s |",
            per_row / per_row_gz,
            per_row * rows_per_day / 1e9,
            per_row_gz * rows_per_day / 1e9,
            plain as f64 / 1e6 / compress_s
        );
    }
    // a whole 64 MB file (the default max_file_mb) as the recorder compresses it: the 1 ms recording's rows, repeated
    let dir = tempfile::tempdir().expect("tmp");
    let big = dir.path().join("pump1-1.csv");
    let header_end = sample.iter().position(|&b| b == b'\n').expect("header") + 1;
    let mut text = sample.clone();
    while text.len() < 64 << 20 {
        text.extend_from_slice(&sample[header_end..]);
    }
    std::fs::write(&big, &text).expect("write");
    let t0 = std::time::Instant::now();
    let gz = recording::gz::compress(&big).expect("compresses");
    let took = t0.elapsed().as_secs_f64();
    let packed = std::fs::metadata(&gz).expect("meta").len();
    println!(
        "a {:.1} MB file: compressed in {took:.2} s ({:.0} MB/s), to {:.1} MB",
        text.len() as f64 / 1e6,
        text.len() as f64 / 1e6 / took,
        packed as f64 / 1e6
    );
}

//! Bad input to the commands, through the real binary (issue 30): bounds that keep `sim` and `simulate` sane, a
//! panic that stops the process, outputs that never replace an input, unreadable files that exit 2 naming the path,
//! a stderr without colour codes, and the warnings `serve` gives of a guessable or readable token.

use std::ffi::OsStr;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crate::support::{bin, root};

/// The binary, running; killed when dropped. Its stderr and stdout are gathered as it writes them.
struct Running {
    child: Child,
    out: Arc<Mutex<String>>,
    readers: Vec<std::thread::JoinHandle<()>>,
}

impl Running {
    fn start<S: AsRef<OsStr>>(args: &[S], env: &[(&str, &str)]) -> Running {
        let mut child = Command::new(bin())
            .args(args)
            .envs(env.iter().copied())
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("starts");
        let out = Arc::new(Mutex::new(String::new()));
        let mut readers = Vec::new();
        for mut pipe in [
            Box::new(child.stderr.take().expect("stderr")) as Box<dyn Read + Send>,
            Box::new(child.stdout.take().expect("stdout")),
        ] {
            let out = out.clone();
            readers.push(std::thread::spawn(move || {
                let mut buf = [0u8; 4096];
                while let Ok(n @ 1..) = pipe.read(&mut buf) {
                    out.lock().expect("lock").push_str(&String::from_utf8_lossy(&buf[..n]));
                }
            }));
        }
        Running { child, out, readers }
    }

    fn output(&self) -> String {
        self.out.lock().expect("lock").clone()
    }

    /// Waits until the output holds `needle`; false at the deadline or when the process ends first.
    fn wait_for(&mut self, needle: &str, timeout: Duration) -> bool {
        let deadline = Instant::now() + timeout;
        while Instant::now() < deadline {
            if self.output().contains(needle) {
                return true;
            }
            if self.child.try_wait().expect("wait").is_some() {
                return self.output().contains(needle);
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        false
    }

    /// Its exit status once it ends, or `None` (and it is killed) at the deadline; with the output.
    fn finish(mut self, timeout: Duration) -> (Option<ExitStatus>, String) {
        let deadline = Instant::now() + timeout;
        let status = loop {
            if let Some(status) = self.child.try_wait().expect("wait") {
                break Some(status);
            }
            if Instant::now() > deadline {
                break None;
            }
            std::thread::sleep(Duration::from_millis(20));
        };
        let _ = self.child.kill();
        let _ = self.child.wait();
        // the readers see the pipes close: all the output is in
        for reader in self.readers.drain(..) {
            reader.join().expect("a reader");
        }
        (status, self.output())
    }

    fn sigterm(&self) {
        self.signal("-TERM");
    }

    /// Sends the signal `kill` names so (`-INT`, `-TERM`).
    fn signal(&self, name: &str) {
        let status = Command::new("kill").args([name, &self.child.id().to_string()]).status().expect("kill");
        assert!(status.success());
    }
}

impl Drop for Running {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Runs the binary to its end (20 s at most) and returns its exit code (`None`: killed or signalled) and output.
fn run<S: AsRef<OsStr>>(args: &[S]) -> (Option<i32>, String) {
    let (status, out) = Running::start(args, &[]).finish(Duration::from_secs(20));
    (status.and_then(|s| s.code()), out)
}

fn exits_2_naming<S: AsRef<OsStr>>(args: &[S], needles: &[&str]) -> String {
    let (code, out) = run(args);
    assert_eq!(code, Some(2), "{needles:?}: {out}");
    for n in needles {
        assert!(out.contains(n), "`{n}` not in: {out}");
    }
    out
}

/// `simulate --model <model> --duration <duration> --out <out>`.
fn simulate_args<'a>(model: &'a Path, duration: &'a str, out: &'a Path) -> [&'a OsStr; 7] {
    let flag = |f: &'static str| OsStr::new(f);
    [
        flag("simulate"),
        flag("--model"),
        model.as_os_str(),
        flag("--duration"),
        OsStr::new(duration),
        flag("--out"),
        out.as_os_str(),
    ]
}

/// `estimate <recording> --model <model> --out <out>`.
fn estimate_args<'a>(recording: &'a Path, model: &'a Path, out: &'a Path) -> [&'a OsStr; 6] {
    [
        "estimate".as_ref(),
        recording.as_os_str(),
        "--model".as_ref(),
        model.as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
    ]
}

/// `analyze <recording> --model <model> --json <json>`.
fn analyze_args<'a>(recording: &'a Path, model: &'a Path, json: &'a Path) -> [&'a OsStr; 6] {
    [
        "analyze".as_ref(),
        recording.as_os_str(),
        "--model".as_ref(),
        model.as_os_str(),
        "--json".as_ref(),
        json.as_os_str(),
    ]
}

fn reference_model() -> String {
    std::fs::read_to_string(root().join("config/plant.toml")).expect("model")
}

/// The reference model with `sample_ms` set, written into `dir`.
fn model_sampling_at(dir: &Path, sample_ms: &str) -> PathBuf {
    let path = dir.join(format!("plant_{sample_ms}.toml"));
    let text = reference_model().replace("sample_ms = 1.0", &format!("sample_ms = {sample_ms}"));
    std::fs::write(&path, text).expect("write");
    path
}

/// A short test-stand recording made by `simulate`.
fn recording(dir: &Path) -> PathBuf {
    let rec = dir.join("rec.csv");
    let (code, out) = run(&simulate_args(&root().join("config/plant.toml"), "3", &rec));
    assert_eq!(code, Some(0), "{out}");
    rec
}

fn files_in(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> =
        std::fs::read_dir(dir).expect("dir").map(|e| e.expect("entry").file_name().to_string_lossy().into()).collect();
    names.sort();
    names
}

// ---- finding 1: rates and sizes within bounds; a panic stops the process; SIGTERM ends `sim`

#[test]
fn sim_refuses_a_sample_period_it_cannot_run() {
    let dir = tempfile::tempdir().expect("tmp");
    let model = model_sampling_at(dir.path(), "1e-7");
    let args = ["sim".as_ref(), "--model".as_ref(), model.as_os_str(), "--listen".as_ref(), "127.0.0.1:0".as_ref()];
    exits_2_naming(&args, &["sensors.sample_ms", "plant_1e-7.toml"]);
}

#[test]
fn simulate_refuses_a_run_of_more_rows_than_it_may_write() {
    let dir = tempfile::tempdir().expect("tmp");
    let out = dir.path().join("rec.csv");
    let simulate = |model: &Path, duration: &str| {
        let (status, out) = Running::start(&simulate_args(model, duration, &out), &[])
            // refused at once; a run that goes on writes gigabytes, so it is stopped early
            .finish(Duration::from_secs(5));
        (status.and_then(|s| s.code()), out)
    };
    let (code, msg) = simulate(&model_sampling_at(dir.path(), "1e-9"), "8");
    assert_eq!(code, Some(2), "{msg}");
    assert!(msg.contains("sensors.sample_ms"), "{msg}");
    // numbers far out of range said in exponent form (1e308 was printed as 309 digits)
    let (code, msg) = simulate(&model_sampling_at(dir.path(), "1e300"), "8");
    assert!(code == Some(2) && msg.contains("got 1e300") && msg.len() < 300, "{msg}");
    let (code, msg) = simulate(&root().join("config/plant.toml"), "1e308");
    assert!(code == Some(2) && msg.contains("--duration 1e308") && msg.len() < 200, "{msg}");
    let (code, msg) = simulate(&root().join("config/plant.toml"), "1000000");
    assert_eq!(code, Some(2), "{msg}");
    assert!(msg.contains("--duration") && msg.contains("rows"), "{msg}");
    assert!(!out.exists(), "nothing written");
    // more than the file may hold (a file-size limit here, as a full disk would be): said before writing a byte
    let script = "ulimit -S -f 200; exec \"$0\" \"$@\"";
    let o = std::process::Command::new("sh")
        .args(["-c", script])
        .arg(bin())
        .args(simulate_args(&root().join("config/plant.toml"), "10", &out))
        .output()
        .expect("runs");
    let msg = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{msg}");
    assert!(msg.contains("--duration 10") && msg.contains("10000 rows") && msg.contains("has room for"), "{msg}");
    assert!(files_in(dir.path()).iter().all(|f| !f.contains("rec.csv")), "nothing written");
}

#[test]
fn a_panic_in_any_thread_stops_the_process() {
    let model = root().join("config/plant.toml");
    let args = ["sim".as_ref(), "--model".as_ref(), model.as_os_str(), "--listen".as_ref(), "127.0.0.1:0".as_ref()];
    let running = Running::start(&args, &[("HYDROLENS_DEBUG_PANIC_AFTER_MS", "300")]);
    let (status, out) = running.finish(Duration::from_secs(15));
    let status = status.unwrap_or_else(|| panic!("still running 15 s after a thread panicked: {out}"));
    assert!(!status.success(), "{status:?}: {out}");
    assert!(out.contains("panicked") && out.contains("the process stops"), "{out}");
}

#[test]
fn sigterm_ends_sim() {
    let model = root().join("config/plant.toml");
    let args = ["sim".as_ref(), "--model".as_ref(), model.as_os_str(), "--listen".as_ref(), "127.0.0.1:0".as_ref()];
    let mut running = Running::start(&args, &[]);
    assert!(running.wait_for("plant simulator on", Duration::from_secs(15)), "{}", running.output());
    running.sigterm();
    let (status, out) = running.finish(Duration::from_secs(10));
    assert_eq!(status.and_then(|s| s.code()), Some(0), "{out}");
}

// ---- finding 2: outputs checked before any work, never an input, written whole or not at all

#[test]
fn an_output_that_is_an_input_or_another_output_is_refused_and_nothing_is_lost() {
    let dir = tempfile::tempdir().expect("tmp");
    let d = dir.path();
    let rec = recording(d);
    let before = std::fs::read(&rec).expect("recording");
    let model = d.join("plant.toml");
    std::fs::write(&model, reference_model()).expect("model");
    let p = |name: &str| d.join(name).into_os_string();
    let (rec_s, model_s) = (rec.clone().into_os_string(), model.clone().into_os_string());
    let estimate = |out: &OsStr| {
        vec!["estimate".into(), rec_s.clone(), "--model".into(), model_s.clone(), "--out".into(), out.into()]
    };
    let analyze = |more: &[&OsStr]| {
        let mut args: Vec<std::ffi::OsString> =
            vec!["analyze".into(), rec_s.clone(), "--model".into(), model_s.clone()];
        args.extend(more.iter().map(|a| a.into()));
        args
    };
    exits_2_naming(&estimate(rec.as_os_str()), &["--out", "rec.csv", "input"]);
    exits_2_naming(&estimate(model.as_os_str()), &["--out", "plant.toml", "input"]);
    exits_2_naming(&analyze(&["--json".as_ref(), rec.as_os_str()]), &["--json", "rec.csv", "input"]);
    exits_2_naming(
        &analyze(&["--json".as_ref(), &p("a.json"), "--report".as_ref(), rec.as_os_str()]),
        &["--report", "rec.csv", "input"],
    );
    exits_2_naming(
        &analyze(&["--json".as_ref(), &p("out"), "--report".as_ref(), &p("out")]),
        &["--report", "--json", "out"],
    );
    exits_2_naming(
        &analyze(&["--json".as_ref(), &p("a.json"), "--model-out".as_ref(), model.as_os_str()]),
        &["--model-out", "plant.toml", "input"],
    );
    // a directory that is not there: refused at once, before the analysis
    let started = Instant::now();
    exits_2_naming(&analyze(&["--json".as_ref(), &p("nodir/x.json")]), &["--json", "nodir", "does not exist"]);
    assert!(started.elapsed() < Duration::from_secs(5), "refused only after {:?}", started.elapsed());
    assert_eq!(std::fs::read(&rec).expect("recording"), before, "the recording is untouched");
    assert_eq!(std::fs::read_to_string(&model).expect("model"), reference_model(), "the model is untouched");
    assert_eq!(files_in(d), ["plant.toml", "rec.csv"], "nothing else written");
}

#[test]
fn simulate_with_a_bad_model_leaves_the_old_output() {
    let dir = tempfile::tempdir().expect("tmp");
    let out = dir.path().join("rec.csv");
    std::fs::write(&out, "the old recording\n").expect("write");
    // a model that loads but cannot run (no hydraulics: it fails once the run starts), and one that does not load
    let no_pump = dir.path().join("no_pump.toml");
    let torque_only = "[motor]\ninertia_kg_m2 = 0.08\nviscous_nm_s_rad = 0.04\n[load]\nkind = \"none\"\n";
    std::fs::write(&no_pump, torque_only).expect("write");
    let negative = dir.path().join("negative.toml");
    std::fs::write(&negative, reference_model().replace("inertia_kg_m2 = 0.08", "inertia_kg_m2 = -1.0"))
        .expect("write");
    // magnitudes no plant has: they exited 0 with a recording of empty speeds. Too stiff for any step (refused at
    // load, naming the key), and a torque that drives the shaft beyond any speed (stopped at the moment it does)
    let stiff = dir.path().join("stiff.toml");
    std::fs::write(&stiff, reference_model().replace("bulk_modulus_bar = 15000.0", "bulk_modulus_bar = 1e300"))
        .expect("write");
    let huge = dir.path().join("huge.toml");
    std::fs::write(&huge, reference_model() + "[effects.torque_offset]\ntorque_nm = 1e30\n").expect("write");
    let cases = [
        (&no_pump, "[drive]"),
        (&negative, "motor.inertia_kg_m2"),
        (&stiff, "hydraulics.bulk_modulus_bar"),
        (&huge, "physical range"),
    ];
    for (model, key) in cases {
        let name = model.file_name().expect("name").to_string_lossy().into_owned();
        exits_2_naming(&simulate_args(model, "1", &out), &[key, &name]);
        assert_eq!(std::fs::read_to_string(&out).expect("out"), "the old recording\n", "{name}");
    }
    assert_eq!(files_in(dir.path()), ["huge.toml", "negative.toml", "no_pump.toml", "rec.csv", "stiff.toml"]);
    // a recording with pressures analysed against the torque-only model: the model's path with what it lacks
    let sub = tempfile::tempdir().expect("tmp");
    let rec = recording(sub.path());
    let json = sub.path().join("a.json");
    exits_2_naming(&analyze_args(&rec, &no_pump, &json), &["model file", "no_pump.toml", "[drive]"]);
}

#[test]
fn a_killed_runs_temporary_file_is_removed_by_the_next_run() {
    let dir = tempfile::tempdir().expect("tmp");
    let rec = recording(dir.path());
    // what `estimate` killed by SIGKILL leaves: its pid is beyond any pid Linux hands out
    let stale = dir.path().join(".est.csv.4294967294.tmp");
    std::fs::write(&stale, "half an estimate").expect("write");
    let out = dir.path().join("est.csv");
    let model = root().join("config/plant.toml");
    let (code, msg) = run(&estimate_args(&rec, &model, &out));
    assert_eq!(code, Some(0), "{msg}");
    assert_eq!(files_in(dir.path()), ["est.csv", "rec.csv"]);
}

/// Ctrl-C or SIGTERM during a run removes its temporary file (the run's size, 20 MB a minute of `simulate`) and
/// keeps the old output; the exit status is the signal's (128 + its number).
#[test]
fn a_signal_removes_the_runs_temporary_file_and_keeps_the_old_output() {
    let dir = tempfile::tempdir().expect("tmp");
    let out = dir.path().join("rec.csv");
    for (name, code) in [("-INT", 130), ("-TERM", 143)] {
        std::fs::write(&out, "the old recording\n").expect("write");
        // long enough (1e6 rows, about 160 MB) that the signal finds it writing
        let running = Running::start(&simulate_args(&root().join("config/plant.toml"), "1000", &out), &[]);
        let writing = crate::support::wait_for_sync(Duration::from_secs(20), || {
            files_in(dir.path()).iter().any(|f| f.ends_with(".tmp"))
        });
        assert!(writing.is_some(), "{name}: no temporary file: {}", running.output());
        running.signal(name);
        let (status, msg) = running.finish(Duration::from_secs(20));
        assert_eq!(status.and_then(|s| s.code()), Some(code), "{name}: {msg}");
        assert!(msg.contains("temporary files removed"), "{name}: {msg}");
        assert_eq!(files_in(dir.path()), ["rec.csv"], "{name}");
        assert_eq!(std::fs::read_to_string(&out).expect("read"), "the old recording\n", "{name}");
    }
}

/// A recording that is a named pipe nobody writes to is refused at once, named so; it hung `estimate` and `analyze`.
#[test]
fn a_recording_pipe_with_no_writer_exits_2_at_once() {
    let dir = tempfile::tempdir().expect("tmp");
    let fifo = dir.path().join("rec.csv");
    assert!(Command::new("mkfifo").arg(&fifo).status().expect("mkfifo").success());
    let model = root().join("config/plant.toml");
    let (est, json) = (dir.path().join("est.csv"), dir.path().join("a.json"));
    exits_2_naming(&estimate_args(&fifo, &model, &est), &["rec.csv", "named pipe with nothing written to it"]);
    exits_2_naming(&analyze_args(&fifo, &model, &json), &["rec.csv"]);
}

/// Every command that reads a model checks its `[estimator]` table as `estimate` does: `simulate` and `analyze` ran
/// on a table `estimate` refused.
#[test]
fn every_command_refuses_a_bad_estimator_table_naming_the_key() {
    let dir = tempfile::tempdir().expect("tmp");
    let rec = recording(dir.path());
    for (table, key) in [("bogus = 1", "bogus"), ("lambda = 1.5", "estimator.lambda"), ("method = \"magic\"", "magic")]
    {
        let model = dir.path().join("m.toml");
        std::fs::write(&model, format!("{}\n[estimator]\n{table}\n", reference_model())).expect("write");
        let (out, json) = (dir.path().join("out.csv"), dir.path().join("a.json"));
        exits_2_naming(&simulate_args(&model, "1", &out), &["m.toml", key]);
        exits_2_naming(&estimate_args(&rec, &model, &out), &["m.toml", key]);
        exits_2_naming(&analyze_args(&rec, &model, &json), &["m.toml", key]);
        let sim = ["sim".as_ref(), "--model".as_ref(), model.as_os_str(), "--listen".as_ref(), "127.0.0.1:0".as_ref()];
        exits_2_naming(&sim, &["m.toml", key]);
        assert_eq!(files_in(dir.path()), ["m.toml", "rec.csv"], "{table}: nothing written");
    }
}

/// `analyze` refuses a nominal model of absurd magnitudes, as `simulate` does: it was analysed to a speed error of
/// 2.5e9 and a finding, and its `--model-out` was a model `simulate` refused.
#[test]
fn analyze_refuses_a_model_beyond_any_plant_as_simulate_does() {
    let dir = tempfile::tempdir().expect("tmp");
    let rec = recording(dir.path());
    for (from, to) in
        [("displacement_cm3 = 16.0", "displacement_cm3 = 1e9"), ("back_pressure_bar = 3.0", "back_pressure_bar = 1e9")]
    {
        let model = dir.path().join("absurd.toml");
        let text = reference_model();
        assert!(text.contains(from), "{from}");
        std::fs::write(&model, text.replace(from, to)).expect("write");
        let (out, json, fitted) = (dir.path().join("out.csv"), dir.path().join("a.json"), dir.path().join("fit.toml"));
        exits_2_naming(&simulate_args(&model, "3", &out), &["absurd.toml", "physical range"]);
        let mut args = analyze_args(&rec, &model, &json).to_vec();
        args.extend(["--model-out".as_ref(), fitted.as_os_str()]);
        exits_2_naming(&args, &["model file", "absurd.toml", "physical range"]);
        assert_eq!(files_in(dir.path()), ["absurd.toml", "rec.csv"], "{to}: nothing written");
    }
}

/// An output path that gets past the checks but cannot be created (under `/proc`) exits 2 naming it, not 1.
#[test]
fn an_output_path_that_cannot_be_created_exits_2_naming_it() {
    let dir = tempfile::tempdir().expect("tmp");
    let rec = recording(dir.path());
    let model = root().join("config/plant.toml");
    let nowhere = Path::new("/proc/hydrolens-test/out.csv");
    exits_2_naming(&estimate_args(&rec, &model, nowhere), &["/proc/hydrolens-test/out.csv"]);
    exits_2_naming(&analyze_args(&rec, &model, nowhere), &["/proc/hydrolens-test/out.csv"]);
    let proc_file = Path::new("/proc/hydrolens-test.csv");
    exits_2_naming(&estimate_args(&rec, &model, proc_file), &["creating /proc/hydrolens-test.csv"]);
}

// ---- finding 3: unreadable files exit 2 naming the path (once); no colour codes in a file

#[test]
fn missing_or_directory_configs_recordings_and_a_non_utf8_model_exit_2_naming_the_path_once() {
    let dir = tempfile::tempdir().expect("tmp");
    let missing = dir.path().join("missing.toml");
    let out = exits_2_naming(&["serve".as_ref(), "--config".as_ref(), missing.as_os_str()], &["missing.toml"]);
    assert_eq!(out.matches("No such file").count(), 1, "the reason once: {out}");
    exits_2_naming(&["serve".as_ref(), "--config".as_ref(), dir.path().as_os_str()], &[&*dir.path().to_string_lossy()]);
    let latin1 = dir.path().join("latin1.toml");
    let mut bytes = reference_model().into_bytes();
    bytes.extend_from_slice(b"# caf\xe9\n");
    std::fs::write(&latin1, bytes).expect("write");
    let out = dir.path().join("rec.csv");
    exits_2_naming(&simulate_args(&latin1, "1", &out), &["latin1.toml", "UTF-8"]);
    // a config whose model cannot be read: the config's key and the model's path
    let config = dir.path().join("svc.toml");
    std::fs::write(&config, service_config(dir.path(), "a-token-long-enough-1234", Some(&missing))).expect("write");
    let out = exits_2_naming(
        &["serve".as_ref(), "--config".as_ref(), config.as_os_str()],
        &["estimator.model", "missing.toml"],
    );
    assert_eq!(out.matches("No such file").count(), 1, "the reason once: {out}");
    // a recording that is not there, or a directory: the path and the reason, each once
    let model = dir.path().join("plant.toml");
    std::fs::write(&model, reference_model()).expect("write");
    let missing_csv = dir.path().join("missing.csv");
    let est_out = dir.path().join("est.csv");
    for (recording, reason) in [(missing_csv.as_path(), "No such file"), (dir.path(), "a directory")] {
        let out = exits_2_naming(&estimate_args(recording, &model, &est_out), &[&*recording.to_string_lossy(), reason]);
        assert_eq!(out.matches(reason).count(), 1, "the reason once: {out}");
    }
}

#[test]
fn demo_with_recordings_under_a_file_exits_2_and_stops_its_simulator() {
    // the config's error returned before the simulator was told to stop, and demo then waited for it for ever
    let dir = tempfile::tempdir().expect("tmp");
    let file = dir.path().join("not-a-dir");
    std::fs::write(&file, "x").expect("write");
    for recordings in [file.clone(), file.join("sub")] {
        let args = [
            "demo".as_ref(),
            "--http".as_ref(),
            "127.0.0.1:0".as_ref(),
            "--recordings".as_ref(),
            recordings.as_os_str(),
        ];
        exits_2_naming(&args, &["not-a-dir"]);
    }
}

#[test]
fn contradictory_or_wrong_command_line_targets_exit_2_naming_the_flag() {
    // one port for the service and the simulator: the second bind failed with exit 1 (checked before any bind)
    let one_port = ["demo", "--http", "127.0.0.1:18093", "--modbus", "0.0.0.0:18093"];
    exits_2_naming(&one_port, &["--http", "--modbus", "one port"]);
    // an output named as a directory: it failed writing with exit 1
    let dir = tempfile::tempdir().expect("tmp");
    let out = format!("{}/", dir.path().join("nodir").display());
    let model = root().join("config/plant.toml");
    let args = simulate_args(&model, "1", Path::new(&out));
    exits_2_naming(&args, &["--out", "nodir/", "ends in '/'"]);
    assert!(files_in(dir.path()).is_empty(), "nothing written");
    // a serial device that is not there, or a file that is not a serial line: it retried for ever
    let plain = dir.path().join("plain.txt");
    std::fs::write(&plain, "x").expect("write");
    for device in [dir.path().join("ttyNONE"), plain] {
        let args = ["sim".as_ref(), "--model".as_ref(), model.as_os_str(), "--serial".as_ref(), device.as_os_str()];
        exits_2_naming(&args, &["--serial", &*device.to_string_lossy()]);
    }
}

#[test]
fn a_model_or_config_beyond_the_size_cap_exits_2_without_reading_it_whole() {
    let dir = tempfile::tempdir().expect("tmp");
    // /dev/zero never ends: before the cap it grew the process by 1 GB/s
    exits_2_naming(&["serve", "--config", "/dev/zero"], &["/dev/zero", "1024 kB"]);
    // a 48 MB model: comments after a valid model, so only its size is wrong (it took 2.4 GB)
    let big = dir.path().join("big.toml");
    let mut text = reference_model();
    let line = format!("# {}\n", "x".repeat(1000));
    while text.len() < 48 << 20 {
        text.push_str(&line);
    }
    std::fs::write(&big, text).expect("write");
    let out = dir.path().join("rec.csv");
    exits_2_naming(&simulate_args(&big, "1", &out), &["big.toml", "1024 kB"]);
    assert!(!out.exists(), "nothing written");
}

#[test]
fn a_setpoint_mapped_onto_the_control_word_exits_2_naming_both_entries() {
    let dir = tempfile::tempdir().expect("tmp");
    let config = dir.path().join("svc.toml");
    let text = service_config(dir.path(), "a-token-long-enough-1234", None)
        + "[drives.control]\nmode = \"speed\"\n[drives.registers.frequency_setpoint_hz]\naddress = 1\n";
    std::fs::write(&config, text).expect("write");
    exits_2_naming(
        &["serve".as_ref(), "--config".as_ref(), config.as_os_str()],
        &["svc.toml", "drives[0].registers.control_word.address", "frequency_setpoint_hz"],
    );
    assert!(!dir.path().join("rec").exists(), "nothing started, nothing recorded");
}

/// A service config with one drive that nobody answers, recording into `dir`.
fn service_config(dir: &Path, token: &str, model: Option<&Path>) -> String {
    let model = model.map_or_else(|| root().join("config/plant.toml"), Path::to_path_buf);
    format!(
        "[http]\nbind = \"127.0.0.1:0\"\ntoken = \"{token}\"\n[recording]\ndir = {:?}\n[[drives]]\nname = \"p\"\n\
         address = \"127.0.0.1:9\"\n[drives.estimator]\nmodel = {:?}\n",
        dir.join("rec"),
        model
    )
}

/// `serve` on `http` with `config` (of `mode`), run until it says where its dashboard is; its output.
fn serve_start(dir: &Path, token: &str, mode: u32, http: &str) -> String {
    use std::os::unix::fs::PermissionsExt;
    let config = dir.join("svc.toml");
    std::fs::write(&config, service_config(dir, token, None)).expect("write");
    std::fs::set_permissions(&config, std::fs::Permissions::from_mode(mode)).expect("chmod");
    let args = ["serve".as_ref(), "--config".as_ref(), config.as_os_str(), "--http".as_ref(), http.as_ref()];
    let mut running = Running::start(&args, &[]);
    assert!(running.wait_for("dashboard on", Duration::from_secs(20)), "{}", running.output());
    running.sigterm();
    let (status, out) = running.finish(Duration::from_secs(20));
    assert_eq!(status.and_then(|s| s.code()), Some(0), "{out}");
    out
}

#[test]
fn no_colour_codes_reach_a_stderr_that_is_not_a_terminal() {
    let dir = tempfile::tempdir().expect("tmp");
    let out = serve_start(dir.path(), "a-token-long-enough-1234", 0o600, "127.0.0.1:0");
    assert!(out.contains("INFO"), "the log is there: {out}");
    assert!(!out.contains('\u{1b}'), "escape codes in: {out:?}");
    // the drive (127.0.0.1:9) is unreachable, and said so; nothing else is to be warned of
    let warned = out.lines().filter(|l| l.contains("WARN") && !l.contains("modbus connection cannot be made"));
    assert_eq!(warned.count(), 0, "nothing to warn of: {out}");
}

// ---- finding 4: warnings of a token that is guessable or readable

#[test]
fn serve_warns_of_a_short_token_beyond_loopback_and_of_a_config_others_read() {
    let dir = tempfile::tempdir().expect("tmp");
    let out = serve_start(dir.path(), "short", 0o644, "0.0.0.0:0");
    assert_eq!(out.matches("http.token is short").count(), 1, "one warning: {out}");
    assert!(out.contains("beyond loopback"), "{out}");
    assert!(out.contains("svc.toml") && out.contains("chmod 600"), "{out}");
}

#[test]
fn serve_beyond_loopback_without_a_token_says_writes_are_disabled() {
    let dir = tempfile::tempdir().expect("tmp");
    let out = serve_start(dir.path(), "", 0o644, "0.0.0.0:0");
    assert!(out.contains("write routes are disabled"), "{out}");
    assert!(!out.contains("chmod 600"), "no token, nothing to hide: {out}");
}

#[test]
fn stuck_sensors_wrong_clocks_and_costly_loads_exit_2_naming_what() {
    let dir = tempfile::tempdir().expect("tmp");
    let rec = recording(dir.path());
    let text = std::fs::read_to_string(&rec).expect("recording");
    let header: Vec<&str> = text.lines().next().expect("header").split(',').collect();
    // the recording with `edit` applied to the cells of every row
    let edited = |name: &str, edit: &dyn Fn(&mut Vec<String>)| {
        let mut out = String::new();
        for (k, line) in text.lines().enumerate() {
            let mut cells: Vec<String> = line.split(',').map(String::from).collect();
            if k > 0 {
                edit(&mut cells);
            }
            out.push_str(&cells.join(","));
            out.push('\n');
        }
        let p = dir.path().join(name);
        std::fs::write(&p, out).expect("write");
        p
    };
    let set = |column: &'static str, value: &'static str| {
        let i = header.iter().position(|h| *h == column).expect("column");
        move |cells: &mut Vec<String>| cells[i] = value.to_string()
    };
    let model = root().join("config/plant.toml");
    let json = dir.path().join("a.json");
    // a stuck tachometer: J came out 10⁸ with "named: nothing"
    let stuck = edited("stuck.csv", &set("omega_rad_s", "30"));
    exits_2_naming(&analyze_args(&stuck, &model, &json), &["stuck.csv", "`omega_rad_s` holds 30 in every row"]);
    // a drive torque column of zeros beside real pressures: it said "the speed hardly changes"
    let zeros: String =
        text.lines().enumerate().map(|(k, l)| format!("{l},{}\n", if k == 0 { "torque_nm" } else { "0" })).collect();
    let zero_torque = dir.path().join("zero_torque.csv");
    std::fs::write(&zero_torque, zeros).expect("write");
    exits_2_naming(
        &analyze_args(&zero_torque, &model, &json),
        &["zero_torque.csv", "`torque_nm` holds 0 in every row"],
    );
    // a clock in ms read as s: every row a gap, the load estimate 0 throughout
    let ms = edited("ms.csv", &|cells| cells[0] = format!("{}", cells[0].parse::<f64>().expect("t") * 1000.0));
    let out = dir.path().join("e.csv");
    exits_2_naming(&estimate_args(&ms, &model, &out), &["ms.csv", "max_gap_s"]);
    assert!(!out.exists(), "nothing written");
    // a start beyond the estimator's bounds (clamped in silence)
    let ij = dir.path().join("ij.toml");
    std::fs::write(&ij, reference_model() + "[estimator]\ninitial_inertia_kg_m2 = 1e300\n").expect("write");
    exits_2_naming(&estimate_args(&rec, &ij, &out), &["ij.toml", "estimator.initial_inertia_kg_m2", "within"]);
    // a load that costs without bound each sample (0.1 s a sample)
    let imp = dir.path().join("imp.toml");
    let impacts = "kind = \"impacts\"\nbase_nm = 1.0\npeak_nm = 1.0\nwidth_s = 10.0\nmean_interval_s = 1e-6\nseed = 1";
    std::fs::write(&imp, reference_model().replace("kind = \"recorded\"", impacts)).expect("write");
    exits_2_naming(&simulate_args(&imp, "1", &dir.path().join("s.csv")), &["imp.toml", "load.width_s"]);
}

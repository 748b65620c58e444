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
        for mut pipe in [
            Box::new(child.stderr.take().expect("stderr")) as Box<dyn Read + Send>,
            Box::new(child.stdout.take().expect("stdout")),
        ] {
            let out = out.clone();
            std::thread::spawn(move || {
                let mut buf = [0u8; 4096];
                while let Ok(n @ 1..) = pipe.read(&mut buf) {
                    out.lock().expect("lock").push_str(&String::from_utf8_lossy(&buf[..n]));
                }
            });
        }
        Running { child, out }
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
        // the readers see the pipes close
        std::thread::sleep(Duration::from_millis(50));
        (status, self.output())
    }

    fn sigterm(&self) {
        let status = Command::new("kill").args(["-TERM", &self.child.id().to_string()]).status().expect("kill");
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
        let (status, out) = Running::start(
            &["simulate".as_ref(), "--model".as_ref(), model.as_os_str(), "--duration".as_ref(), duration.as_ref()]
                .into_iter()
                .chain(["--out".as_ref(), out.as_os_str()])
                .collect::<Vec<&OsStr>>(),
            &[],
        )
        // refused at once; a run that goes on writes gigabytes, so it is stopped early
        .finish(Duration::from_secs(5));
        (status.and_then(|s| s.code()), out)
    };
    let (code, msg) = simulate(&model_sampling_at(dir.path(), "1e-9"), "8");
    assert_eq!(code, Some(2), "{msg}");
    assert!(msg.contains("sensors.sample_ms"), "{msg}");
    let (code, msg) = simulate(&root().join("config/plant.toml"), "1000000");
    assert_eq!(code, Some(2), "{msg}");
    assert!(msg.contains("--duration") && msg.contains("rows"), "{msg}");
    assert!(!out.exists(), "nothing written");
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

//! `hydrolens serve` as a user meets it: a mistyped config exits 2 naming the key, and the token never reaches
//! the log, even at debug level.

use std::io::Read;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use crate::support::{bin, root};

fn serve(config: &std::path::Path, extra_env: &[(&str, &str)], run_for: Duration) -> (Option<i32>, String) {
    let mut child = Command::new(bin())
        .args(["serve", "--config"])
        .arg(config)
        .args(["--http", "127.0.0.1:0"])
        .envs(extra_env.iter().copied())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("starts");
    let start = Instant::now();
    let code = loop {
        if let Some(status) = child.try_wait().expect("wait") {
            break status.code();
        }
        if start.elapsed() > run_for {
            let pid = child.id().to_string();
            let _ = Command::new("kill").args(["-TERM", &pid]).status();
            let deadline = Instant::now() + Duration::from_secs(5);
            while child.try_wait().expect("wait").is_none() {
                assert!(Instant::now() < deadline, "serve did not stop on SIGTERM");
                std::thread::sleep(Duration::from_millis(20));
            }
            break None;
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let mut out = String::new();
    child.stderr.take().expect("stderr").read_to_string(&mut out).expect("utf-8");
    child.stdout.take().expect("stdout").read_to_string(&mut out).expect("utf-8");
    (code, out)
}

#[test]
fn a_mistyped_service_config_exits_2_naming_the_key() {
    let dir = tempfile::tempdir().expect("tmp");
    let good = std::fs::read_to_string(root().join("config/hydrolens.toml")).expect("config");
    let good =
        good.replace("model = \"config/plant.toml\"", &format!("model = {:?}", root().join("config/plant.toml")));
    let cases = [
        ("unknown.toml", good.replace("poll_ms = 5", "poll_ms = 5\npoll_rate = 3"), "poll_rate"),
        ("type.toml", good.replace("unit_id = 1", "unit_id = \"one\""), "unit_id"),
        ("limits.toml", good.replace("min_hz = 0.0", "min_hz = 55.0"), "min_hz"),
        ("mode.toml", good.replace("mode = \"monitor\"", "mode = \"turbo\""), "mode"),
        ("register.toml", format!("{good}\n[drives.registers.inlet_pressure_bar]\ntype = \"f64\"\n"), "f64"),
        ("mqtt_scheme.toml", format!("{good}\n[mqtt]\nurl = \"ssl://broker:8883\"\n"), "mqtt.url"),
        ("mqtt_url.toml", format!("{good}\n[mqtt]\nurl = \"broker:1883\"\n"), "mqtt.url"),
        ("mqtt_interval.toml", format!("{good}\n[mqtt]\nurl = \"mqtt://b\"\ninterval_ms = 5\n"), "mqtt.interval_ms"),
    ];
    let exits_2_naming = |name: &str, text: String, needles: &[&str]| {
        let path = dir.path().join(name);
        std::fs::write(&path, text).expect("write");
        let (code, out) = serve(&path, &[], Duration::from_secs(10));
        assert_eq!(code, Some(2), "{name}: {out}");
        assert!(out.contains(name) && needles.iter().all(|n| out.contains(n)), "{name}: {needles:?}: {out}");
    };
    for (name, text, needle) in cases {
        exits_2_naming(name, text, &[needle]);
    }
    // mqtts://: the TLS files are read at load; the file's path is in the message
    let not_a_ca = dir.path().join("not-a-ca.txt");
    std::fs::write(&not_a_ca, "a CA certificate would be PEM\n").expect("write");
    let missing = dir.path().join("missing-ca.pem");
    let tls = |rest: &str| format!("{good}\n[mqtt]\nurl = \"mqtts://127.0.0.1:8883\"\n{rest}");
    let ca = |p: &std::path::Path| format!("ca_file = {:?}\n", p.display().to_string());
    exits_2_naming("mqtt_ca_missing.toml", tls(&ca(&missing)), &["mqtt.ca_file", "missing-ca.pem"]);
    exits_2_naming("mqtt_ca_not_pem.toml", tls(&ca(&not_a_ca)), &["mqtt.ca_file", "not-a-ca.txt", "no PEM"]);
    let half = tls("client_cert_file = \"client.pem\"\n");
    exits_2_naming("mqtt_client_half.toml", half, &["mqtt.client_key_file"]);
    let plain = format!("{good}\n[mqtt]\nurl = \"mqtt://127.0.0.1\"\n{}", ca(&not_a_ca));
    exits_2_naming("mqtt_tls_plain.toml", plain, &["mqtt.ca_file", "mqtts://"]);
}

#[test]
fn the_token_never_reaches_the_log() {
    let dir = tempfile::tempdir().expect("tmp");
    let secret = "s3cr3t-t0ken-4f9a";
    let text = format!(
        "[http]\nbind = \"127.0.0.1:0\"\ntoken = \"{secret}\"\n[recording]\ndir = {:?}\n[[drives]]\nname = \"p\"\n\
         address = \"127.0.0.1:9\"\n[drives.estimator]\nmodel = {:?}\n",
        dir.path().join("rec"),
        root().join("config/plant.toml")
    );
    let path = dir.path().join("svc.toml");
    std::fs::write(&path, text).expect("write");
    let (code, out) = serve(&path, &[("RUST_LOG", "trace")], Duration::from_secs(2));
    assert_eq!(code, None, "serve keeps running with an unreachable drive: {out}");
    assert!(out.contains("dashboard on"), "{out}");
    assert!(!out.contains(secret), "the token is in the log:\n{out}");
    // a drive unreachable from the start is said (it showed only in /api/status and /readyz)
    assert!(out.contains("modbus connection cannot be made") && out.contains("127.0.0.1:9"), "{out}");
}

/// The configs we ship parse (the compose one with its in-container model path pointed at the repository's).
#[test]
fn the_shipped_service_configs_are_valid() {
    let model = format!("{:?}", root().join("config/plant.toml"));
    for (file, container_model) in [
        ("config/hydrolens.toml", "\"config/plant.toml\""),
        ("docker/hydrolens.compose.toml", "\"/opt/hydrolens/config/plant.toml\""),
    ] {
        let text = std::fs::read_to_string(root().join(file)).expect("config");
        assert!(text.contains(container_model), "{file} names its model as {container_model}");
        let text = text.replace(container_model, &model);
        let settings = hydrolens::service::config::parse(&text, file, None).unwrap_or_else(|e| panic!("{file}: {e}"));
        assert!(!settings.drives.is_empty(), "{file}");
        if file.starts_with("docker/") {
            assert_eq!(settings.drives[0].realtime_priority, Some(20), "compose grants SYS_NICE for it");
        }
    }
}

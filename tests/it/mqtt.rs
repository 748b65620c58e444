//! MQTT against a real broker: Debian's `mosquitto`, started here on a free loopback port, and a rumqttc subscriber.
//! Status messages carry the drive's `/api/status` object; a broker that dies never slows polling (its messages are
//! dropped, oldest first, and counted); publishing resumes when it is back; the last will says `offline`. TLS:
//! certificates made by the `openssl` CLI, a mosquitto TLS listener, and `mosquitto_sub` (OpenSSL) as the subscriber.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use rumqttc::{AsyncClient, Event, MqttOptions, Packet, QoS};
use tokio::sync::mpsc;

use crate::support::{self, Stack, wait_for};

fn mosquitto() -> PathBuf {
    for dir in ["/usr/sbin", "/usr/bin", "/usr/local/sbin", "/usr/local/bin"] {
        let p = Path::new(dir).join("mosquitto");
        if p.exists() {
            return p;
        }
    }
    panic!("no mosquitto found: install Debian's `mosquitto` (apt-get install -y mosquitto); tests/run.sh does this");
}

/// A free loopback port (bound, then released for the broker).
fn free_port() -> u16 {
    let l = std::net::TcpListener::bind("127.0.0.1:0").expect("bind");
    l.local_addr().expect("addr").port()
}

/// A mosquitto on 127.0.0.1:`port`, anonymous, no persistence; killed when dropped.
struct Broker {
    child: Child,
    port: u16,
    _dir: tempfile::TempDir,
}

impl Broker {
    async fn start(port: u16) -> Broker {
        Broker::start_with(port, "").await
    }

    /// A broker whose listener has the `listener_conf` lines (e.g. TLS's cafile, certfile, keyfile).
    async fn start_with(port: u16, listener_conf: &str) -> Broker {
        let dir = tempfile::tempdir().expect("tmp");
        let conf = dir.path().join("mosquitto.conf");
        std::fs::write(
            &conf,
            format!("listener {port} 127.0.0.1\n{listener_conf}allow_anonymous true\npersistence false\n"),
        )
        .expect("write conf");
        let log = std::fs::File::create(dir.path().join("mosquitto.log")).expect("log");
        let child = Command::new(mosquitto())
            .arg("-c")
            .arg(&conf)
            .stdin(Stdio::null())
            .stdout(log.try_clone().expect("log"))
            .stderr(log)
            .spawn()
            .expect("start mosquitto");
        let mut b = Broker { child, port, _dir: dir };
        let up = wait_for(Duration::from_secs(15), || async {
            tokio::net::TcpStream::connect(("127.0.0.1", port)).await.is_ok()
        })
        .await;
        if up.is_none() {
            let log = std::fs::read_to_string(b._dir.path().join("mosquitto.log")).unwrap_or_default();
            b.kill();
            panic!("mosquitto did not listen on {port} within 5 s:\n{log}");
        }
        b
    }

    fn url(&self) -> String {
        format!("mqtt://127.0.0.1:{}", self.port)
    }

    fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Broker {
    fn drop(&mut self) {
        self.kill();
    }
}

/// A subscriber to `filter` that re-subscribes after every reconnect; messages arrive on the channel as
/// (topic, payload). Stops when the returned handle is aborted or the test ends.
fn subscribe(port: u16, filter: &str) -> (mpsc::UnboundedReceiver<(String, String)>, tokio::task::JoinHandle<()>) {
    let mut o = MqttOptions::new(format!("test-sub-{}", free_port()), "127.0.0.1", port);
    o.set_keep_alive(Duration::from_secs(5));
    let (client, mut events) = AsyncClient::new(o, 16);
    let (tx, rx) = mpsc::unbounded_channel();
    let filter = filter.to_string();
    let task = tokio::spawn(async move {
        loop {
            match events.poll().await {
                Ok(Event::Incoming(Packet::ConnAck(_))) => {
                    let (c, f) = (client.clone(), filter.clone());
                    tokio::spawn(async move { c.subscribe(f, QoS::AtLeastOnce).await });
                }
                Ok(Event::Incoming(Packet::Publish(p))) => {
                    let _ = tx.send((p.topic.clone(), String::from_utf8_lossy(&p.payload).into_owned()));
                }
                Ok(_) => {}
                Err(_) => tokio::time::sleep(Duration::from_millis(100)).await,
            }
        }
    });
    (rx, task)
}

/// The next message on `topic` within `limit`.
async fn next_on(rx: &mut mpsc::UnboundedReceiver<(String, String)>, topic: &str, limit: Duration) -> Option<String> {
    let deadline = tokio::time::Instant::now() + limit;
    loop {
        match tokio::time::timeout_at(deadline, rx.recv()).await {
            Ok(Some((t, p))) if t == topic => return Some(p),
            Ok(Some(_)) => {}
            Ok(None) | Err(_) => return None,
        }
    }
}

async fn api_status(stack: &Stack) -> serde_json::Value {
    support::get_json(format!("{}/api/status", stack.url)).await
}

fn keys(v: &serde_json::Value) -> Vec<String> {
    v.as_object().map(|o| o.keys().cloned().collect()).unwrap_or_default()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn status_goes_to_the_broker_and_a_dead_broker_never_slows_polling() {
    let run = async {
        let port = free_port();
        let mut broker = Broker::start(port).await;
        let (mut rx, sub) = subscribe(port, "hl/#");
        let mqtt = format!(
            "\n[mqtt]\nurl = \"{}\"\ntopic_prefix = \"hl\"\ninterval_ms = 100\nqueue_messages = 8\n",
            broker.url()
        );
        let stack = Stack::start(5.0, 10, &format!("[drives.control]\nmode = \"monitor\"\n{mqtt}")).await;

        // the retained `online`, then status messages: the drive's /api/status object, field for field
        let online = next_on(&mut rx, "hl/status", Duration::from_secs(10)).await;
        assert_eq!(online.as_deref(), Some("online"));
        let mut last = serde_json::Value::Null;
        for _ in 0..3 {
            let p = next_on(&mut rx, "hl/pump1/status", Duration::from_secs(5)).await.expect("a status message");
            last = serde_json::from_str(&p).expect("status JSON");
        }
        assert_eq!(last["name"], "pump1");
        for field in ["mode", "link", "sample", "estimate", "timing", "recording"] {
            assert!(last.get(field).is_some(), "status message lacks {field}: {last}");
        }
        let status = api_status(&stack).await;
        assert_eq!(keys(&last), keys(&status["drives"][0]), "the MQTT object is /api/status's drive object");
        assert_eq!(status["mqtt"]["connected"], true, "{status}");
        assert!(status["mqtt"]["published"].as_u64().expect("published") >= 3);
        assert!(support::metric(&stack.metrics().await, "hydrolens_mqtt_connected 1").is_some());

        // the broker dies: polling goes on at its rate, the messages beyond the queue are dropped and counted
        broker.kill();
        let polls_before = stack.status().await["link"]["polls"].as_u64().expect("polls");
        let dropped = wait_for(Duration::from_secs(10), || async {
            api_status(&stack).await["mqtt"]["dropped"].as_u64().unwrap_or(0) >= 10
        })
        .await;
        assert!(dropped.is_some(), "no drops counted with the broker down: {}", api_status(&stack).await);
        // within 1 s more at a 10 ms poll (100 cycles), half of them: far beyond what a blocked loop would manage
        let polls = || async { api_status(&stack).await["drives"][0]["link"]["polls"].as_u64().expect("polls") };
        let on = wait_for(Duration::from_secs(15), || async { polls().await >= polls_before + 50 }).await;
        let status = api_status(&stack).await;
        assert_eq!(status["mqtt"]["connected"], false, "{status}");
        assert!(!status["drives"][0]["link"]["stale"].as_bool().expect("stale"), "{status}");
        assert!(on.is_some(), "polling slowed: {polls_before} → {}", polls().await);
        let m = stack.metrics().await;
        let dropped_metric = support::metric(&m, "hydrolens_mqtt_dropped_messages_total").expect("drop counter");
        assert!(dropped_metric >= 10.0, "{m}");

        // the broker is back on its port: publishing resumes (the subscriber reconnects by itself)
        let _broker = Broker::start(port).await;
        let back = next_on(&mut rx, "hl/pump1/status", Duration::from_secs(10)).await;
        assert!(back.is_some(), "no status message after the broker came back: {}", api_status(&stack).await);
        assert_eq!(api_status(&stack).await["mqtt"]["connected"], true);

        // a clean stop says `offline` itself (after the `online` of the reconnection, which may still be on its way)
        stack.stop().await;
        let mut said = Vec::new();
        while let Some(p) = next_on(&mut rx, "hl/status", Duration::from_secs(5)).await {
            said.push(p);
            if said.last().is_some_and(|p| p == "offline") {
                break;
            }
        }
        assert!(said.last().is_some_and(|p| p == "offline") && said.len() <= 2, "{said:?}");
        sub.abort();
    };
    tokio::time::timeout(Duration::from_secs(60), run).await.expect("bounded");
}

/// `[drives.condition]` every `every_s`, publishing to the broker at `url` under `hc`.
fn condition_extra(every_s: u32, url: &str) -> String {
    format!(
        "[drives.condition]\nenabled = true\nwindow_s = 5\nevery_s = {every_s}\n\n[mqtt]\nurl = \"{url}\"\n\
         topic_prefix = \"hc\"\ninterval_ms = 100\n"
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn condition_checks_go_to_the_condition_topic_and_again_after_a_broker_restart() {
    let run = async {
        let port = free_port();
        let mut broker = Broker::start(port).await;
        let (mut rx, sub) = subscribe(port, "hc/#");
        let stack = Stack::start(5.0, 10, &condition_extra(1, &broker.url())).await;
        // the first message has no check yet; the next comes with the first check
        let mut with_check = None;
        for _ in 0..20 {
            let Some(p) = next_on(&mut rx, "hc/pump1/condition", Duration::from_secs(10)).await else { break };
            let v: serde_json::Value = serde_json::from_str(&p).expect("condition JSON");
            assert_eq!(v["drive"], "pump1");
            if v["checks"].as_array().is_some_and(|c| !c.is_empty()) {
                with_check = Some(v);
                break;
            }
        }
        let v = with_check.expect("a condition message with a check within the bound");
        let from_http = support::get_json(format!("{}/api/drives/pump1/condition", stack.url)).await;
        assert_eq!(keys(&v), keys(&from_http), "the MQTT object is GET /api/drives/pump1/condition's");
        assert_eq!(v["checks"][0]["t_s"], from_http["checks"][0]["t_s"]);
        assert!(v["tracked"].is_array(), "the tracked effects and their trends ride along: {v}");
        let dir = stack.stop().await;

        // a service that restores those checks from the recordings dir and checks again only in a day: its one
        // condition message comes at the start, and again only because the broker came back without it
        let (_sim, modbus, sim_stop, sim_task) = support::start_sim(support::test_plant(5.0), 0).await;
        let text = support::config_text(modbus, dir.path(), 10, &condition_extra(86_400, &broker.url()));
        let svc = support::start_service(&text).await;
        let first = next_on(&mut rx, "hc/pump1/condition", Duration::from_secs(10)).await.expect("restored checks");
        assert!(first.contains("\"checks\":[{"), "{first}");
        broker.kill();
        let _broker = Broker::start(port).await;
        let again = next_on(&mut rx, "hc/pump1/condition", Duration::from_secs(10)).await;
        assert_eq!(again.as_deref(), Some(first.as_str()), "the condition is sent again after the broker's restart");
        support::stop_service(svc).await;
        sim_stop.cancel();
        let _ = tokio::time::timeout(Duration::from_secs(10), sim_task).await.expect("simulator stops");
        sub.abort();
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("bounded");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_last_will_says_offline_when_the_service_dies() {
    let run = async {
        let port = free_port();
        let broker = Broker::start(port).await;
        let (mut rx, sub) = subscribe(port, "hw/status");
        let (_sim, modbus, sim_stop, sim_task) = support::start_sim(support::test_plant(5.0), 0).await;
        let dir = tempfile::tempdir().expect("tmp");
        let config = dir.path().join("hydrolens.toml");
        let mut f = std::fs::File::create(&config).expect("config");
        write!(
            f,
            "[http]\nbind = \"127.0.0.1:0\"\n\n[recording]\nenabled = false\n\n[[drives]]\nname = \"pump1\"\n\
             address = \"{modbus}\"\npoll_ms = 10\n\n[mqtt]\nurl = \"{}\"\ntopic_prefix = \"hw\"\ninterval_ms = 100\n",
            broker.url()
        )
        .expect("write config");
        drop(f);
        let mut service = Command::new(support::bin())
            .args(["serve", "--config"])
            .arg(&config)
            .current_dir(support::root())
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("start hydrolens serve");
        let online = next_on(&mut rx, "hw/status", Duration::from_secs(10)).await;
        // SIGKILL: no goodbye, the broker sees the connection drop and publishes the will
        let _ = service.kill();
        let _ = service.wait();
        assert_eq!(online.as_deref(), Some("online"));
        let offline = next_on(&mut rx, "hw/status", Duration::from_secs(10)).await;
        assert_eq!(offline.as_deref(), Some("offline"), "the last will");
        sim_stop.cancel();
        let _ = tokio::time::timeout(Duration::from_secs(5), sim_task).await;
        sub.abort();
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("bounded");
}

/// `openssl <args>` in `dir`; panics with its output when it fails or is missing (tests/run.sh installs it).
fn openssl(dir: &Path, args: &[&str]) {
    let out = Command::new("openssl")
        .args(args)
        .current_dir(dir)
        .stdin(Stdio::null())
        .output()
        .expect("run openssl: install Debian's `openssl` (tests/run.sh does this)");
    assert!(out.status.success(), "openssl {args:?}: {}", String::from_utf8_lossy(&out.stderr));
}

/// A CA in `dir`: `<name>.pem` and `<name>.key` (P-256, two days).
fn make_ca(dir: &Path, name: &str) {
    let (key, pem, subject) = (format!("{name}.key"), format!("{name}.pem"), format!("/CN=hydrolens test {name}"));
    #[rustfmt::skip]
    openssl(dir, &[
        "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes", "-keyout", &key,
        "-out", &pem, "-days", "2", "-subj", &subject, "-addext", "basicConstraints=critical,CA:TRUE",
        "-addext", "keyUsage=critical,keyCertSign,cRLSign",
    ]);
}

/// A certificate `<name>.pem` with key `<name>.key` for 127.0.0.1, signed by the CA `ca`, for `usage` (serverAuth or
/// clientAuth).
fn make_leaf(dir: &Path, name: &str, ca: &str, usage: &str) {
    let (key, csr, pem) = (format!("{name}.key"), format!("{name}.csr"), format!("{name}.pem"));
    let ext = format!("{name}.ext");
    std::fs::write(
        dir.join(&ext),
        format!("subjectAltName=IP:127.0.0.1\nbasicConstraints=CA:FALSE\nextendedKeyUsage={usage}\n"),
    )
    .expect("write ext");
    #[rustfmt::skip]
    openssl(dir, &[
        "req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes", "-keyout", &key, "-out", &csr,
        "-subj", "/CN=127.0.0.1",
    ]);
    let (ca_pem, ca_key) = (format!("{ca}.pem"), format!("{ca}.key"));
    #[rustfmt::skip]
    openssl(dir, &[
        "x509", "-req", "-in", &csr, "-CA", &ca_pem, "-CAkey", &ca_key, "-CAcreateserial", "-out", &pem,
        "-days", "2", "-extfile", &ext,
    ]);
}

/// `hydrolens serve` (the binary: its log is the user's) on the drive at `modbus`, HTTP on 127.0.0.1:`http_port`,
/// with `mqtt` as its `[mqtt]` table; stderr to `log`. Killed when dropped.
struct Serve(Child);

impl Serve {
    fn start(dir: &Path, name: &str, modbus: std::net::SocketAddr, http_port: u16, mqtt: &str) -> Serve {
        let config = dir.join(format!("{name}.toml"));
        std::fs::write(
            &config,
            format!(
                "[http]\nbind = \"127.0.0.1:{http_port}\"\n\n[recording]\nenabled = false\n\n[[drives]]\n\
                 name = \"pump1\"\naddress = \"{modbus}\"\npoll_ms = 10\n\n[mqtt]\n{mqtt}"
            ),
        )
        .expect("write config");
        let log = std::fs::File::create(dir.join(format!("{name}.log"))).expect("log");
        let child = Command::new(support::bin())
            .args(["serve", "--config"])
            .arg(&config)
            .current_dir(support::root())
            .env("RUST_LOG", "info")
            .stdin(Stdio::null())
            .stdout(log.try_clone().expect("log"))
            .stderr(log)
            .spawn()
            .expect("start hydrolens serve");
        Serve(child)
    }
}

impl Drop for Serve {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// `/api/status` of the service on `http_port` once it answers (bounded).
async fn status_on(http_port: u16) -> serde_json::Value {
    let url = format!("http://127.0.0.1:{http_port}/api/status");
    for _ in 0..250 {
        if let Ok(r) = reqwest::get(&url).await {
            return r.json().await.expect("status JSON");
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    panic!("no answer on {url} within 5 s");
}

/// `mosquitto_sub` over TLS (OpenSSL, not the service's rustls) on `filter`: its exit code and the messages
/// (`topic payload` lines) it got, at most `count` within `wait_s` seconds (exit code 27 when the wait ran out).
async fn tls_sub(dir: &Path, port: u16, filter: &str, count: u32, wait_s: u32) -> (Option<i32>, Vec<String>) {
    let mut cmd = Command::new("mosquitto_sub");
    cmd.current_dir(dir).stdin(Stdio::null()).args(["-h", "127.0.0.1", "-p", &port.to_string(), "-t", filter, "-v"]);
    cmd.args(["--cafile", "ca.pem", "--cert", "client.pem", "--key", "client.key"]);
    cmd.args(["-C", &count.to_string(), "-W", &wait_s.to_string()]);
    let out = tokio::task::spawn_blocking(move || cmd.output())
        .await
        .expect("joins")
        .expect("run mosquitto_sub: install Debian's `mosquitto-clients` (tests/run.sh does this)");
    let lines = String::from_utf8_lossy(&out.stdout).lines().map(str::to_string).collect();
    (out.status.code(), lines)
}

fn polls(status: &serde_json::Value) -> u64 {
    status["drives"][0]["link"]["polls"].as_u64().expect("polls")
}

/// mqtts:// with `mqtt.ca_file`: a broker whose certificate (for IP 127.0.0.1) the CA signed gets the status
/// messages, over a connection with a client certificate (the broker requires one). A CA that did not sign it: no
/// message, the link reported down, the TLS error in the log, and polling untouched.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tls_broker_gets_status_and_an_untrusted_ca_is_refused() {
    let run = async {
        let pki = tempfile::tempdir().expect("tmp");
        let d = pki.path();
        make_ca(d, "ca");
        make_ca(d, "other_ca");
        make_leaf(d, "server", "ca", "serverAuth");
        make_leaf(d, "client", "ca", "clientAuth");
        // mosquitto started as root reads its files as the `mosquitto` user: test keys, readable for it
        use std::os::unix::fs::PermissionsExt;
        for (f, mode) in [(d.to_path_buf(), 0o755), (d.join("server.key"), 0o644)] {
            std::fs::set_permissions(&f, std::fs::Permissions::from_mode(mode)).expect("chmod");
        }
        // a client key that is not the certificate's is refused at load, naming the key
        let text = "url = \"mqtts://127.0.0.1\"\nca_file = \"ca.pem\"\nclient_cert_file = \"client.pem\"\n\
                    client_key_file = \"other_ca.key\"\n";
        let raw: hydrolens::service::config::RawMqtt = toml::from_str(text).expect("toml");
        let hydrolens::error::KeyError { key, message } =
            hydrolens::service::config::validate_mqtt(raw, |p: &str| d.join(p)).expect_err("key mismatch");
        assert_eq!(key, "mqtt.client_key_file", "{message}");
        let port = free_port();
        let tls = format!(
            "cafile {}\ncertfile {}\nkeyfile {}\nrequire_certificate true\n",
            d.join("ca.pem").display(),
            d.join("server.pem").display(),
            d.join("server.key").display()
        );
        let _broker = Broker::start_with(port, &tls).await;
        let (_sim, modbus, sim_stop, sim_task) = support::start_sim(support::test_plant(5.0), 0).await;

        // the CA that signed the broker's certificate, and a client certificate: status messages arrive
        let http = free_port();
        let mqtt = |prefix: &str, ca: &str| {
            format!(
                "url = \"mqtts://127.0.0.1:{port}\"\ntopic_prefix = \"{prefix}\"\ninterval_ms = 100\nca_file = {:?}\n\
                 client_cert_file = {:?}\nclient_key_file = {:?}\n",
                d.join(ca).display().to_string(),
                d.join("client.pem").display().to_string(),
                d.join("client.key").display().to_string()
            )
        };
        let service = Serve::start(d, "trusted", modbus, http, &mqtt("ht1", "ca.pem"));
        let (code, got) = tls_sub(d, port, "ht1/+/status", 3, 15).await;
        let log = std::fs::read_to_string(d.join("trusted.log")).unwrap_or_default();
        assert_eq!((code, got.len()), (Some(0), 3), "{got:?}\n{log}");
        let payload = got[0].strip_prefix("ht1/pump1/status ").expect("the drive's status topic");
        let v: serde_json::Value = serde_json::from_str(payload).expect("status JSON");
        assert_eq!(v["name"], "pump1");
        let status = status_on(http).await;
        assert_eq!(status["mqtt"]["connected"], true, "{status}");
        assert_eq!(status["mqtt"]["url"], format!("mqtts://127.0.0.1:{port}"), "{status}");
        assert!(log.contains("MQTT connected"), "{log}");
        drop(service);

        // a CA that did not sign it: nothing reaches the broker while the subscriber waits 3 s
        let http = free_port();
        let _service = Serve::start(d, "untrusted", modbus, http, &mqtt("ht2", "other_ca.pem"));
        let before = polls(&status_on(http).await);
        let (code, got) = tls_sub(d, port, "ht2/#", 1, 3).await;
        assert_eq!((code, got.len()), (Some(27), 0), "the subscriber waited out its 3 s without a message: {got:?}");
        let status = status_on(http).await;
        assert_eq!(status["mqtt"]["connected"], false, "{status}");
        // ≥ 3 s at a 10 ms poll: 300 cycles; a third of them is far beyond what a blocked loop would manage
        assert!(polls(&status) >= before + 100, "polling slowed: {before} → {}", polls(&status));
        assert!(!status["drives"][0]["link"]["stale"].as_bool().expect("stale"), "{status}");
        let log = std::fs::read_to_string(d.join("untrusted.log")).expect("log");
        assert!(
            log.contains("MQTT connection attempt failed") && log.contains("invalid peer certificate"),
            "the TLS error is in the log:\n{log}"
        );
        assert!(!log.contains("MQTT connected"), "{log}");
        sim_stop.cancel();
        let _ = tokio::time::timeout(Duration::from_secs(5), sim_task).await;
    };
    tokio::time::timeout(Duration::from_secs(60), run).await.expect("bounded");
}

/// A broker that accepts each connection (CONNACK) and closes it at once is reconnected to with a growing back-off:
/// it started again from 0.1 s at every CONNACK, 10 connections a second for as long as it lasted (a hostile
/// tester's broker). The waits between attempts are a lower bound on the time eight connections take, whatever the
/// machine's load: 0.1 + 0.2 + 0.4 + 0.8 + 1.6 + 2 + 2 s.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_broker_that_drops_each_connection_at_once_is_retried_with_a_growing_back_off() {
    use tokio::io::AsyncWriteExt;
    let run = async {
        let broker = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind");
        let port = broker.local_addr().expect("addr").port();
        let (tx, mut accepted) = tokio::sync::mpsc::unbounded_channel();
        let dropper = tokio::spawn(async move {
            while let Ok((mut c, _)) = broker.accept().await {
                let _ = tx.send(std::time::Instant::now());
                // CONNACK, session not present, accepted; then gone
                let _ = c.write_all(&[0x20, 0x02, 0x00, 0x00]).await;
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        });
        let mqtt = format!("\n[mqtt]\nurl = \"mqtt://127.0.0.1:{port}\"\ntopic_prefix = \"hl\"\ninterval_ms = 100\n");
        let stack = Stack::start(5.0, 10, &format!("[drives.control]\nmode = \"monitor\"\n{mqtt}")).await;
        let first = accepted.recv().await.expect("a first connection");
        let mut last = first;
        for _ in 1..8 {
            last = accepted.recv().await.expect("a connection");
        }
        let took = last - first;
        eprintln!("eight connections to a broker that drops each at once: {took:?}");
        assert!(took >= Duration::from_secs(7), "the back-off grows across the connections: {took:?}");
        stack.stop().await;
        dropper.abort();
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("bounded");
}

/// Issue 29, finding 9: a broker that takes the connection but never reads nor answers receives nothing, and nothing
/// is counted published (before, every message handed to the client was).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_broker_that_never_answers_gets_nothing_counted_as_published() {
    let run = async {
        let mute = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind");
        let port = mute.local_addr().expect("addr").port();
        let held = tokio::spawn(async move {
            let mut conns = Vec::new();
            while let Ok((c, _)) = mute.accept().await {
                conns.push(c); // held open, never read
            }
        });
        let mqtt = format!(
            "\n[mqtt]\nurl = \"mqtt://127.0.0.1:{port}\"\ntopic_prefix = \"hl\"\ninterval_ms = 100\nqueue_messages = 8\n"
        );
        let stack = Stack::start(5.0, 10, &format!("[drives.control]\nmode = \"monitor\"\n{mqtt}")).await;
        let dropped = wait_for(Duration::from_secs(10), || async {
            api_status(&stack).await["mqtt"]["dropped"].as_u64().unwrap_or(0) >= 5
        })
        .await;
        let status = api_status(&stack).await;
        assert!(dropped.is_some(), "the queue overflows and says so: {status}");
        assert_eq!(status["mqtt"]["published"], 0, "nothing reached a broker: {status}");
        assert_eq!(status["mqtt"]["connected"], false, "{status}");
        stack.stop().await;
        held.abort();
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("bounded");
}

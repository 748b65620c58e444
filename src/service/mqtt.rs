//! MQTT publishing (`[mqtt]`, CONTRACT.md "Extensions"): each drive's `/api/status` object to
//! `<prefix>/<drive>/status` every `interval_ms`, its condition to `<prefix>/<drive>/condition` when a check changed
//! it, and `<prefix>/status` = `online` / `offline` (retained; `offline` is also the last will). `mqtts://` is TLS
//! (rustls, ring provider): the broker's certificate is checked against `mqtt.ca_file`, or the system's roots.
//!
//! The publisher runs on a thread of its own. The poll loops never wait for it: it reads their shared state, and
//! what it has to send waits in a bounded [`Outbox`] that drops its oldest message when full (counted), so a broker
//! that is down costs the drives nothing.

use crate::error::KeyError;
use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Duration;

use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::registry::Registry;
use rumqttc::{AsyncClient, Event, LastWill, MqttOptions, Packet, QoS, TlsConfiguration, Transport};
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer, ServerName};
use serde::{Deserialize, Serialize};
use tokio::sync::Notify;
use tokio_util::sync::CancellationToken;

use super::condition::DriveCondition;
use super::state::DriveState;

/// `[mqtt]` as written.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawMqtt {
    url: String,
    #[serde(default = "default_prefix")]
    topic_prefix: String,
    #[serde(default = "default_interval")]
    interval_ms: u64,
    username: Option<String>,
    password: Option<String>,
    /// Default `hydrolens-<pid>`; two services on one broker need different ids.
    client_id: Option<String>,
    /// Messages waiting for the broker at most; past it the oldest is dropped (and counted).
    #[serde(default = "default_queue")]
    queue_messages: usize,
    /// mqtts:// only: PEM of the CA(s) that signed the broker's certificate; absent: the system's roots.
    ca_file: Option<String>,
    /// mqtts:// only, both or neither: a client certificate (PEM, chain) and its key, for brokers that ask for one.
    client_cert_file: Option<String>,
    client_key_file: Option<String>,
}

fn default_prefix() -> String {
    "hydrolens".into()
}
fn default_interval() -> u64 {
    1000
}
fn default_queue() -> usize {
    1000
}

/// The bounds of `mqtt.interval_ms`: 10 messages a second per drive at most, one an hour at least.
pub const INTERVAL_MS: std::ops::RangeInclusive<u64> = 100..=3_600_000;
/// The bounds of `mqtt.queue_messages`.
pub const QUEUE_MESSAGES: std::ops::RangeInclusive<usize> = 1..=100_000;

/// Validated `[mqtt]`.
#[derive(Debug, Clone)]
pub struct MqttSettings {
    /// As written, for `/api/status` and the logs (credentials are never in it).
    pub url: String,
    pub host: String,
    pub port: u16,
    pub topic_prefix: String,
    pub interval: Duration,
    /// Username and password, both or neither. Never logged.
    pub credentials: Option<(String, String)>,
    pub client_id: String,
    pub queue_messages: usize,
    /// mqtts://: the TLS client built at load (roots, client certificate); `None` for mqtt://.
    pub tls: Option<Arc<rustls::ClientConfig>>,
}

/// `mqtt://host[:port]` (port 1883 by default) or `mqtts://host[:port]` (TLS, port 8883 by default) into TLS or
/// not, host and port.
fn parse_url(url: &str) -> Result<(bool, String, u16), String> {
    let lower = url.to_ascii_lowercase();
    let (tls, rest) = if lower.starts_with("mqtt://") {
        (false, &url["mqtt://".len()..])
    } else if lower.starts_with("mqtts://") {
        (true, &url["mqtts://".len()..])
    } else {
        return Err(format!("{url:?} is not a URL such as mqtt://127.0.0.1:1883 or mqtts://broker.plant:8883"));
    };
    let rest = rest.strip_suffix('/').unwrap_or(rest);
    if rest.contains('@') {
        return Err(format!("{url:?}: put credentials in mqtt.username and mqtt.password, not in the URL"));
    }
    if rest.contains(['/', '?', '#']) {
        return Err(format!("{url:?}: a broker URL has no path or query (mqtt://host:port)"));
    }
    let (host, port) = if let Some(v6) = rest.strip_prefix('[') {
        let (h, tail) = v6.split_once(']').ok_or_else(|| format!("{url:?}: unclosed [ in the host"))?;
        (h, tail.strip_prefix(':'))
    } else {
        match rest.rsplit_once(':') {
            Some((h, p)) => (h, Some(p)),
            None => (rest, None),
        }
    };
    if host.is_empty() || (host.contains([':', ' ']) && !rest.starts_with('[')) {
        return Err(format!("{url:?}: no host"));
    }
    let port = match port {
        None if tls => 8883,
        None => 1883,
        Some(p) => {
            p.parse().ok().filter(|p| *p > 0).ok_or_else(|| format!("{url:?}: port {p:?} is not 1 ..= 65535"))?
        }
    };
    Ok((tls, host.to_string(), port))
}

/// The PEM certificates in `path` (read for the key `key`); at least one.
fn read_certs(key: &str, path: &Path) -> Result<Vec<CertificateDer<'static>>, KeyError> {
    let pem = crate::error::read_small_file(path)
        .map_err(|e| KeyError::new(key.to_string(), format!("{}: {e}", path.display())))?;
    let certs = CertificateDer::pem_slice_iter(&pem)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| KeyError::new(key.to_string(), format!("{}: not PEM certificates: {e}", path.display())))?;
    if certs.is_empty() {
        return Err(KeyError::new(
            key.to_string(),
            format!("{}: no PEM certificate (-----BEGIN CERTIFICATE-----) in it", path.display()),
        ));
    }
    Ok(certs)
}

/// The TLS client of `mqtts://`: roots from `ca_file` or the system's, a client certificate if given. Every file is
/// read and checked here, at load, so that a mistyped one stops the service with its key's name.
fn tls_config(ca_file: Option<&Path>, client: Option<(&Path, &Path)>) -> Result<rustls::ClientConfig, KeyError> {
    let k = |s: &str| format!("mqtt.{s}");
    let mut roots = rustls::RootCertStore::empty();
    match ca_file {
        Some(path) => {
            for (i, cert) in read_certs(&k("ca_file"), path)?.into_iter().enumerate() {
                roots.add(cert).map_err(|e| {
                    KeyError::new(
                        k("ca_file"),
                        format!("{}: certificate {} is not a CA certificate: {e}", path.display(), i + 1),
                    )
                })?;
            }
        }
        None => {
            let found = rustls_native_certs::load_native_certs();
            let (added, _) = roots.add_parsable_certificates(found.certs);
            if added == 0 {
                let errors: Vec<String> = found.errors.iter().map(|e| e.to_string()).collect();
                return Err(KeyError::new(
                    k("ca_file"),
                    format!(
                        "is not given and the system has no CA certificates ({}); name the broker's CA in mqtt.ca_file, \
                         or install the system's (Debian: ca-certificates)",
                        if errors.is_empty() { "none found".to_string() } else { errors.join("; ") }
                    ),
                ));
            }
        }
    }
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let builder = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| KeyError::new(k("url"), format!("TLS: {e}")))?
        .with_root_certificates(roots);
    match client {
        None => Ok(builder.with_no_client_auth()),
        Some((cert_path, key_path)) => {
            let chain = read_certs(&k("client_cert_file"), cert_path)?;
            let key_pem = crate::error::read_small_file(key_path)
                .map_err(|e| KeyError::new(k("client_key_file"), format!("{}: {e}", key_path.display())))?;
            let key = PrivateKeyDer::from_pem_slice(&key_pem).map_err(|e| {
                KeyError::new(k("client_key_file"), format!("{}: no PEM private key: {e}", key_path.display()))
            })?;
            builder.with_client_auth_cert(chain, key).map_err(|e| {
                KeyError::new(
                    k("client_key_file"),
                    format!("{}: does not go with mqtt.client_cert_file: {e}", key_path.display()),
                )
            })
        }
    }
}

/// Validates `[mqtt]`; errors name the key. `resolve` turns a file name as written into a path (relative ones as the
/// config's model paths are).
pub fn validate(raw: RawMqtt, resolve: impl Fn(&str) -> PathBuf) -> Result<MqttSettings, KeyError> {
    let k = |s: &str| format!("mqtt.{s}");
    let (tls, host, port) = parse_url(raw.url.trim()).map_err(|m| KeyError::new(k("url"), m))?;
    let prefix = raw.topic_prefix;
    if prefix.is_empty() || prefix.starts_with('/') || prefix.ends_with('/') || prefix.contains(['+', '#', '\0']) {
        return Err(KeyError::new(
            k("topic_prefix"),
            format!("{prefix:?} must be a topic without wildcards (+, #) and without a leading or trailing /"),
        ));
    }
    if !INTERVAL_MS.contains(&raw.interval_ms) {
        return Err(KeyError::new(k("interval_ms"), format!("must be 100 ..= 3600000, got {}", raw.interval_ms)));
    }
    if !QUEUE_MESSAGES.contains(&raw.queue_messages) {
        return Err(KeyError::new(k("queue_messages"), format!("must be 1 ..= 100000, got {}", raw.queue_messages)));
    }
    let credentials = match (raw.username, raw.password) {
        (Some(u), Some(p)) => Some((u, p)),
        (None, None) => None,
        (Some(_), None) => return Err(KeyError::new(k("password"), "is needed with mqtt.username".into())),
        (None, Some(_)) => return Err(KeyError::new(k("username"), "is needed with mqtt.password".into())),
    };
    let client_id = raw.client_id.unwrap_or_else(|| format!("hydrolens-{}", std::process::id()));
    if client_id.is_empty() || client_id.len() > 65535 {
        return Err(KeyError::new(k("client_id"), "must not be empty".into()));
    }
    let files = [
        ("ca_file", &raw.ca_file),
        ("client_cert_file", &raw.client_cert_file),
        ("client_key_file", &raw.client_key_file),
    ];
    if !tls && let Some((key, _)) = files.iter().find(|(_, f)| f.is_some()) {
        return Err(KeyError::new(k(key), "is for TLS: the broker's URL (mqtt.url) would be mqtts://".into()));
    }
    let client = match (raw.client_cert_file, raw.client_key_file) {
        (Some(c), Some(key)) => Some((resolve(&c), resolve(&key))),
        (None, None) => None,
        (Some(_), None) => {
            return Err(KeyError::new(k("client_key_file"), "is needed with mqtt.client_cert_file".into()));
        }
        (None, Some(_)) => {
            return Err(KeyError::new(k("client_cert_file"), "is needed with mqtt.client_key_file".into()));
        }
    };
    let tls = if tls {
        ServerName::try_from(host.as_str()).map_err(|_| {
            KeyError::new(
                k("url"),
                format!("{host:?} is neither a DNS name nor an IP address to check the certificate against"),
            )
        })?;
        let ca_file = raw.ca_file.map(|p| resolve(&p));
        let client = client.as_ref().map(|(c, key)| (c.as_path(), key.as_path()));
        Some(Arc::new(tls_config(ca_file.as_deref(), client)?))
    } else {
        None
    };
    Ok(MqttSettings {
        url: raw.url.trim().to_string(),
        host,
        port,
        topic_prefix: prefix,
        interval: Duration::from_millis(raw.interval_ms),
        credentials,
        client_id,
        queue_messages: raw.queue_messages,
        tls,
    })
}

/// One message for the broker.
#[derive(Debug, Clone, PartialEq)]
pub struct Message {
    pub topic: String,
    pub payload: Vec<u8>,
    pub qos: QoS,
    pub retain: bool,
}

/// A bounded queue that drops its oldest message to take a new one when full: pushing never waits.
#[derive(Debug)]
pub struct Outbox {
    queue: Mutex<VecDeque<Message>>,
    capacity: usize,
    ready: Notify,
}

impl Outbox {
    pub fn new(capacity: usize) -> Outbox {
        Outbox { queue: Mutex::new(VecDeque::with_capacity(capacity)), capacity: capacity.max(1), ready: Notify::new() }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, VecDeque<Message>> {
        self.queue.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Queues `m`; true when the oldest message was dropped to make room.
    pub fn push(&self, m: Message) -> bool {
        let dropped = {
            let mut q = self.lock();
            let dropped = q.len() >= self.capacity && q.pop_front().is_some();
            q.push_back(m);
            dropped
        };
        self.ready.notify_one();
        dropped
    }

    pub fn try_pop(&self) -> Option<Message> {
        self.lock().pop_front()
    }

    pub fn len(&self) -> usize {
        self.lock().len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The oldest message, waiting for one (a single consumer: a push while it does not wait leaves a permit).
    pub async fn pop(&self) -> Message {
        loop {
            if let Some(m) = self.try_pop() {
                return m;
            }
            self.ready.notified().await;
        }
    }
}

/// What `/api/status` and `/metrics` say of the publisher.
#[derive(Debug)]
pub struct MqttHealth {
    pub url: String,
    connected: AtomicBool,
    published: AtomicU64,
    dropped: AtomicU64,
    metrics: MqttMetrics,
}

/// `mqtt` in `/api/status`.
#[derive(Debug, Clone, Serialize)]
pub struct MqttStatus {
    pub url: String,
    /// True while the broker has accepted the connection.
    pub connected: bool,
    /// Messages the broker has taken: QoS 1 ones it acknowledged, QoS 0 ones (status) sent on the open
    /// connection; nothing while it is away or does not answer.
    pub published: u64,
    /// Messages dropped, oldest first, because the queue was full (the broker down or too slow).
    pub dropped: u64,
}

impl MqttHealth {
    pub fn status(&self) -> MqttStatus {
        MqttStatus {
            url: self.url.clone(),
            connected: self.connected.load(Ordering::Relaxed),
            published: self.published.load(Ordering::Relaxed),
            dropped: self.dropped.load(Ordering::Relaxed),
        }
    }

    fn set_connected(&self, up: bool) {
        self.connected.store(up, Ordering::Relaxed);
        self.metrics.connected.set(i64::from(up));
    }

    fn count_published(&self) {
        self.published.fetch_add(1, Ordering::Relaxed);
        self.metrics.published.inc();
    }

    fn count_dropped(&self) {
        self.dropped.fetch_add(1, Ordering::Relaxed);
        self.metrics.dropped.inc();
    }
}

/// The publisher's families, registered only when `[mqtt]` is configured.
#[derive(Debug, Clone)]
pub struct MqttMetrics {
    connected: Gauge,
    published: Counter,
    dropped: Counter,
}

impl MqttMetrics {
    pub fn register(r: &mut Registry) -> MqttMetrics {
        let m = MqttMetrics { connected: Gauge::default(), published: Counter::default(), dropped: Counter::default() };
        r.register("mqtt_connected", "1 while the MQTT broker has accepted the connection", m.connected.clone());
        r.register(
            "mqtt_published_messages",
            "MQTT messages the broker has taken (QoS 1 acknowledged; QoS 0 sent on the open connection)",
            m.published.clone(),
        );
        r.register(
            "mqtt_dropped_messages",
            "MQTT messages dropped, oldest first, because the queue was full",
            m.dropped.clone(),
        );
        m
    }
}

/// The topics of one drive.
struct DriveTopics {
    state: Arc<DriveState>,
    condition: Option<Arc<DriveCondition>>,
    status: String,
    condition_topic: String,
    /// The condition JSON last queued: a new one is sent only when it changed (a check, an alarm).
    last_condition: Option<Vec<u8>>,
}

/// Starts the publisher's thread; it stops when `shutdown` is cancelled, after sending `offline` (bounded: 2 s).
pub fn start(
    settings: &MqttSettings,
    drives: &[Arc<DriveState>],
    conditions: &[Arc<DriveCondition>],
    registry: &mut Registry,
    shutdown: CancellationToken,
) -> std::io::Result<(Arc<MqttHealth>, std::thread::JoinHandle<()>)> {
    let health = Arc::new(MqttHealth {
        url: settings.url.clone(),
        connected: AtomicBool::new(false),
        published: AtomicU64::new(0),
        dropped: AtomicU64::new(0),
        metrics: MqttMetrics::register(registry),
    });
    let prefix = &settings.topic_prefix;
    let topics: Vec<DriveTopics> = drives
        .iter()
        .zip(conditions)
        .map(|(d, c)| DriveTopics {
            state: d.clone(),
            condition: c.enabled.then(|| c.clone()),
            status: format!("{prefix}/{}/status", d.name),
            condition_topic: format!("{prefix}/{}/condition", d.name),
            last_condition: None,
        })
        .collect();
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
    let (s, h) = (settings.clone(), health.clone());
    let thread = std::thread::Builder::new().name("mqtt".into()).spawn(move || {
        super::condition::lower_priority();
        rt.block_on(run(s, topics, h, shutdown));
    })?;
    Ok((health, thread))
}

/// The payloads of one interval: every drive's status, and the condition of those whose condition changed.
fn interval_messages(topics: &mut [DriveTopics]) -> Vec<Message> {
    let mut out = Vec::with_capacity(topics.len() * 2);
    for t in topics {
        match serde_json::to_vec(&t.state.snapshot()) {
            Ok(payload) => out.push(Message { topic: t.status.clone(), payload, qos: QoS::AtMostOnce, retain: false }),
            Err(e) => tracing::error!(drive = %t.state.name, error = %e, "serialising the status for MQTT"),
        }
        if let Some(c) = &t.condition {
            match serde_json::to_vec(&c.to_json()) {
                Ok(payload) if t.last_condition.as_ref() != Some(&payload) => {
                    t.last_condition = Some(payload.clone());
                    out.push(Message {
                        topic: t.condition_topic.clone(),
                        payload,
                        qos: QoS::AtLeastOnce,
                        retain: true,
                    });
                }
                Ok(_) => {}
                Err(e) => tracing::error!(drive = %t.state.name, error = %e, "serialising the condition for MQTT"),
            }
        }
    }
    out
}

/// The longest wait between two connection attempts.
const MAX_BACKOFF: Duration = Duration::from_secs(2);

async fn run(
    settings: MqttSettings,
    mut topics: Vec<DriveTopics>,
    health: Arc<MqttHealth>,
    shutdown: CancellationToken,
) {
    let online_topic = format!("{}/status", settings.topic_prefix);
    let mut options = MqttOptions::new(&settings.client_id, &settings.host, settings.port);
    options.set_keep_alive(Duration::from_secs(5));
    options.set_clean_session(true);
    options.set_last_will(LastWill::new(&online_topic, "offline", QoS::AtLeastOnce, true));
    if let Some((u, p)) = &settings.credentials {
        options.set_credentials(u, p);
    }
    if let Some(tls) = &settings.tls {
        options.set_transport(Transport::Tls(TlsConfiguration::Rustls(tls.clone())));
    }
    // a small channel: what waits for the broker waits in the outbox, where it is counted when dropped
    let (client, mut eventloop) = AsyncClient::new(options, 8);
    let outbox = Arc::new(Outbox::new(settings.queue_messages));
    // set on every connection: the retained condition messages go again (a broker without persistence lost them,
    // and the queue may have dropped the last one while the broker was away)
    let resend = AtomicBool::new(false);

    let produce = async {
        let mut tick = tokio::time::interval(settings.interval);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tick.tick().await;
            if resend.swap(false, Ordering::Relaxed) {
                topics.iter_mut().for_each(|t| t.last_condition = None);
            }
            for m in interval_messages(&mut topics) {
                if outbox.push(m) {
                    health.count_dropped();
                }
            }
        }
    };
    let publish = async {
        loop {
            let m = outbox.pop().await;
            // waits while rumqttc's channel is full (the broker down); the outbox keeps taking messages meanwhile
            // counted as published by the connection's events, once the broker has it
            let _ = client.publish(m.topic, m.qos, m.retain, m.payload).await;
        }
    };
    let drive_connection = async {
        let mut backoff = Duration::from_millis(100);
        // the failure last logged as a warning: the same one again (every 2 s while it lasts) goes to debug
        let mut last_failure: Option<String> = None;
        loop {
            match eventloop.poll().await {
                Ok(Event::Incoming(Packet::ConnAck(_))) => {
                    tracing::info!(url = %settings.url, "MQTT connected");
                    last_failure = None;
                    health.set_connected(true);
                    resend.store(true, Ordering::Relaxed);
                    backoff = Duration::from_millis(100);
                    // queued behind at most the channel's few messages; rumqttc's channel never loses it
                    let c = client.clone();
                    let topic = online_topic.clone();
                    tokio::spawn(async move {
                        let _ = c.publish(topic, QoS::AtLeastOnce, true, "online").await;
                    });
                }
                // published: a QoS 1 message once the broker acknowledges it; a QoS 0 one (status) once it has
                // gone into the open connection (nothing acknowledges those)
                Ok(Event::Incoming(Packet::PubAck(_))) | Ok(Event::Outgoing(rumqttc::Outgoing::Publish(0))) => {
                    health.count_published();
                }
                Ok(_) => {}
                Err(e) => {
                    let error = e.to_string();
                    if health.connected.load(Ordering::Relaxed) {
                        tracing::warn!(url = %settings.url, error, "MQTT connection lost");
                    } else if last_failure.as_ref() != Some(&error) {
                        tracing::warn!(url = %settings.url, error, "MQTT connection attempt failed");
                    } else {
                        tracing::debug!(url = %settings.url, error, "MQTT connection attempt failed");
                    }
                    last_failure = Some(error);
                    health.set_connected(false);
                    tokio::time::sleep(backoff).await;
                    backoff = (backoff * 2).min(MAX_BACKOFF);
                }
            }
        }
    };
    tokio::select! {
        _ = shutdown.cancelled() => {}
        _ = produce => {}
        _ = publish => {}
        _ = drive_connection => {}
    }
    // a clean goodbye: `offline` (retained) as the will would say it, then DISCONNECT
    if health.connected.load(Ordering::Relaxed) {
        let _ = client.try_publish(&online_topic, QoS::AtLeastOnce, true, "offline");
        let _ = client.try_disconnect();
        let goodbye = async {
            loop {
                match eventloop.poll().await {
                    Ok(Event::Outgoing(rumqttc::Outgoing::Disconnect)) | Err(_) => return,
                    Ok(_) => {}
                }
            }
        };
        let _ = tokio::time::timeout(Duration::from_secs(2), goodbye).await;
    }
    health.set_connected(false);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn raw(text: &str) -> RawMqtt {
        toml::from_str(text).expect("parses")
    }

    fn settings(text: &str) -> Result<MqttSettings, KeyError> {
        validate(raw(text), |p: &str| PathBuf::from(p))
    }

    fn err(text: &str) -> KeyError {
        settings(text).expect_err("invalid")
    }

    #[test]
    fn urls_and_bounds() {
        let s = settings("url = \"mqtt://127.0.0.1:1884\"\n").expect("valid");
        assert_eq!((s.host.as_str(), s.port, s.topic_prefix.as_str()), ("127.0.0.1", 1884, "hydrolens"));
        assert_eq!(s.interval, Duration::from_secs(1));
        let s = settings("url = \"mqtt://broker.plant/\"\n").expect("valid");
        assert_eq!((s.host.as_str(), s.port), ("broker.plant", 1883));
        let s = settings("url = \"mqtt://[::1]:1883\"\n").expect("valid");
        assert_eq!(s.host, "::1");
        for bad in ["ssl://b:8883", "http://b", "mqtt://", "mqtt://b:0", "mqtt://b:x", "mqtt://u:p@b", "mqtt://b/x"] {
            let KeyError { key, message } = err(&format!("url = \"{bad}\"\n"));
            assert_eq!(key, "mqtt.url", "{bad}: {message}");
        }
        assert_eq!(parse_url("mqtts://broker.plant"), Ok((true, "broker.plant".into(), 8883)));
        assert_eq!(parse_url("MQTTS://10.0.0.5:8884"), Ok((true, "10.0.0.5".into(), 8884)));
        assert_eq!(parse_url("mqtt://10.0.0.5"), Ok((false, "10.0.0.5".into(), 1883)));
        assert_eq!(err("url = \"mqtt://b\"\ninterval_ms = 10\n").key, "mqtt.interval_ms");
        assert_eq!(err("url = \"mqtt://b\"\ninterval_ms = 4000000\n").key, "mqtt.interval_ms");
        assert_eq!(err("url = \"mqtt://b\"\nqueue_messages = 0\n").key, "mqtt.queue_messages");
        assert_eq!(err("url = \"mqtt://b\"\ntopic_prefix = \"a/#\"\n").key, "mqtt.topic_prefix");
        assert_eq!(err("url = \"mqtt://b\"\ntopic_prefix = \"/a\"\n").key, "mqtt.topic_prefix");
        assert_eq!(err("url = \"mqtt://b\"\nusername = \"u\"\n").key, "mqtt.password");
        let s = settings("url = \"mqtt://b\"\nusername = \"u\"\npassword = \"p\"\n").expect("valid");
        assert_eq!(s.credentials, Some(("u".into(), "p".into())));
    }

    /// The TLS keys are refused at load naming the key (and the file); a working mqtts:// is tests/it/mqtt.rs's.
    #[test]
    fn tls_files_are_checked_at_load() {
        let dir = tempfile::tempdir().expect("tmp");
        let not_pem = dir.path().join("ca.txt");
        std::fs::write(&not_pem, "just some text\n").expect("write");
        let bad_pem = dir.path().join("bad.pem");
        std::fs::write(&bad_pem, "-----BEGIN CERTIFICATE-----\n!!!\n-----END CERTIFICATE-----\n").expect("write");
        let missing = dir.path().join("missing.pem");
        for (file, text) in [(&not_pem, "no PEM certificate"), (&bad_pem, ""), (&missing, "")] {
            let KeyError { key, message } =
                err(&format!("url = \"mqtts://127.0.0.1\"\nca_file = {:?}\n", file.display().to_string()));
            assert_eq!(key, "mqtt.ca_file", "{message}");
            assert!(message.contains(&file.display().to_string()) && message.contains(text), "{message}");
        }
        let KeyError { key, message } = err("url = \"mqtts://b\"\nclient_cert_file = \"c.pem\"\n");
        assert_eq!(key, "mqtt.client_key_file", "{message}");
        assert_eq!(err("url = \"mqtts://b\"\nclient_key_file = \"k.pem\"\n").key, "mqtt.client_cert_file");
        let KeyError { key, message } = err("url = \"mqtt://b\"\nca_file = \"ca.pem\"\n");
        assert_eq!(key, "mqtt.ca_file");
        assert!(message.contains("mqtts://"), "{message}");
        let client = "client_cert_file = \"c.pem\"\nclient_key_file = \"k.pem\"\n";
        assert_eq!(err(&format!("url = \"mqtt://b\"\n{client}")).key, "mqtt.client_cert_file");
        assert_eq!(err("url = \"mqtt://b\"\nclient_key_file = \"k.pem\"\n").key, "mqtt.client_key_file");
        assert_eq!(err("url = \"mqtts://a..b\"\n").key, "mqtt.url");
    }

    fn msg(i: u8) -> Message {
        Message { topic: "t".into(), payload: vec![i], qos: QoS::AtMostOnce, retain: false }
    }

    #[test]
    fn a_full_outbox_drops_its_oldest() {
        let o = Outbox::new(3);
        assert!(!o.push(msg(1)) && !o.push(msg(2)) && !o.push(msg(3)));
        assert!(o.push(msg(4)));
        assert_eq!(o.len(), 3);
        let left: Vec<u8> = std::iter::from_fn(|| o.try_pop()).map(|m| m.payload[0]).collect();
        assert_eq!(left, [2, 3, 4]);
        assert!(o.is_empty());
    }

    #[tokio::test]
    async fn pop_waits_for_a_push() {
        let o = Arc::new(Outbox::new(2));
        let o2 = o.clone();
        let waiter = tokio::spawn(async move { o2.pop().await });
        tokio::task::yield_now().await;
        o.push(msg(7));
        let m = tokio::time::timeout(Duration::from_secs(5), waiter).await.expect("bounded").expect("joins");
        assert_eq!(m.payload, [7]);
    }
}

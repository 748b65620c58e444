//! MQTT publishing (`[mqtt]`, CONTRACT.md "Extensions"): each drive's `/api/status` object to
//! `<prefix>/<drive>/status` every `interval_ms`, its condition to `<prefix>/<drive>/condition` when a check changed
//! it, and `<prefix>/status` = `online` / `offline` (retained; `offline` is also the last will). `mqtts://` is TLS
//! (rustls, ring provider): the broker's certificate is checked against `mqtt.ca_file`, or the system's roots. The
//! `[mqtt]` section itself is read and checked at load with the rest of the config
//! ([`crate::service::config::MqttSettings`]).
//!
//! The publisher runs on a thread of its own. The poll loops never wait for it: it reads their shared state, and
//! what it has to send waits in a bounded [`Outbox`] that drops its oldest message when full (counted), so a broker
//! that is down costs the drives nothing.
//!
//! An outlet of the service, on the top floor beside [`crate::http`] (see the crate's `# Layout`): it reads the
//! service's shared state ([`ServiceState`]: the drives' snapshots and conditions) and registers its families in the
//! service's registry; nothing below uses it. [`crate::server`] starts it.

use std::collections::VecDeque;
use std::sync::Arc;
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Duration;

use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::registry::Registry;
use rumqttc::{AsyncClient, Event, LastWill, MqttOptions, Packet, QoS, TlsConfiguration, Transport};
use serde::Serialize;
use tokio::sync::Notify;
use tokio_util::sync::CancellationToken;

use crate::service::condition::{DriveCondition, lower_priority};
use crate::service::config::MqttSettings;
use crate::service::{DriveState, ServiceState};

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

/// Starts the publisher's thread on `service`'s drives, its families registered in the service's registry; it stops
/// when `shutdown` is cancelled, after sending `offline` (bounded: 2 s).
pub fn start(
    settings: &MqttSettings,
    service: &ServiceState,
    shutdown: CancellationToken,
) -> std::io::Result<(Arc<MqttHealth>, std::thread::JoinHandle<()>)> {
    let metrics = MqttMetrics::register(&mut service.registry());
    let health = Arc::new(MqttHealth {
        url: settings.url.clone(),
        connected: AtomicBool::new(false),
        published: AtomicU64::new(0),
        dropped: AtomicU64::new(0),
        metrics,
    });
    let prefix = &settings.topic_prefix;
    let topics: Vec<DriveTopics> = service
        .drives
        .iter()
        .zip(&service.conditions)
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
        lower_priority();
        rt.block_on(run(s, topics, h, shutdown));
    })?;
    Ok((health, thread))
}

/// The payloads of one interval: every drive's status, and the condition of those whose condition changed.
fn interval_messages(topics: &mut [DriveTopics]) -> Vec<Message> {
    let mut out = Vec::with_capacity(topics.len() * 2);
    for t in topics {
        let mut snapshot = t.state.snapshot();
        if let Some(c) = &t.condition {
            c.fill(&mut snapshot);
        }
        match serde_json::to_vec(&snapshot) {
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
/// A connection that lasted this long held: the back-off starts again from its shortest after it.
const CONNECTION_HELD: Duration = Duration::from_secs(10);

async fn run(
    settings: MqttSettings,
    mut topics: Vec<DriveTopics>,
    health: Arc<MqttHealth>,
    shutdown: CancellationToken,
) {
    let online_topic = format!("{}/status", settings.topic_prefix);
    // a small channel: what waits for the broker waits in the outbox, where it is counted when dropped
    let (client, mut eventloop) = AsyncClient::new(options(&settings, &online_topic), 8);
    let outbox = Arc::new(Outbox::new(settings.queue_messages));
    // set on every connection: the retained condition messages go again (a broker without persistence lost them,
    // and the queue may have dropped the last one while the broker was away)
    let resend = AtomicBool::new(false);
    tokio::select! {
        _ = shutdown.cancelled() => {}
        _ = produce(settings.interval, &mut topics, &outbox, &health, &resend) => {}
        _ = publish(&outbox, &client) => {}
        _ = drive_connection(&mut eventloop, &client, &settings, &online_topic, &health, &resend) => {}
    }
    // a clean goodbye: `offline` (retained) as the will would say it, then DISCONNECT
    if health.connected.load(Ordering::Relaxed) {
        say_goodbye(&client, &mut eventloop, &online_topic).await;
    }
    health.set_connected(false);
}

/// The connection's options: keep-alive, clean session, `offline` as the last will, credentials and TLS if given.
fn options(settings: &MqttSettings, online_topic: &str) -> MqttOptions {
    let mut options = MqttOptions::new(&settings.client_id, &settings.host, settings.port);
    options.set_keep_alive(Duration::from_secs(5));
    options.set_clean_session(true);
    options.set_last_will(LastWill::new(online_topic, "offline", QoS::AtLeastOnce, true));
    if let Some((u, p)) = &settings.credentials {
        options.set_credentials(u, p);
    }
    if let Some(tls) = &settings.tls {
        options.set_transport(Transport::Tls(TlsConfiguration::Rustls(tls.clone())));
    }
    options
}

/// Every `interval`: the drives' messages into the outbox (the oldest dropped, and counted, when it is full).
async fn produce(
    interval: Duration,
    topics: &mut [DriveTopics],
    outbox: &Outbox,
    health: &MqttHealth,
    resend: &AtomicBool,
) {
    let mut tick = tokio::time::interval(interval);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tick.tick().await;
        if resend.swap(false, Ordering::Relaxed) {
            topics.iter_mut().for_each(|t| t.last_condition = None);
        }
        for m in interval_messages(topics) {
            if outbox.push(m) {
                health.count_dropped();
            }
        }
    }
}

/// Hands the outbox's messages to the client, one by one.
async fn publish(outbox: &Outbox, client: &AsyncClient) {
    loop {
        let m = outbox.pop().await;
        // waits while rumqttc's channel is full (the broker down); the outbox keeps taking messages meanwhile
        // counted as published by the connection's events, once the broker has it
        let _ = client.publish(m.topic, m.qos, m.retain, m.payload).await;
    }
}

/// Drives the connection: counts what the broker took, says `online` on each connection, and after a failure
/// waits (a back-off doubling to [`MAX_BACKOFF`]) before the event loop connects again.
async fn drive_connection(
    eventloop: &mut rumqttc::EventLoop,
    client: &AsyncClient,
    settings: &MqttSettings,
    online_topic: &str,
    health: &MqttHealth,
    resend: &AtomicBool,
) {
    let mut backoff = Duration::from_millis(100);
    // the failure last logged as a warning: the same one again (every 2 s while it lasts) goes to debug
    let mut last_failure: Option<String> = None;
    // when the broker last accepted the connection, and whether connections are being closed soon after (a
    // broker that takes each one and drops it at once: said once, then at debug, until one holds)
    let mut connected_at: Option<std::time::Instant> = None;
    let mut flapping = false;
    loop {
        match eventloop.poll().await {
            Ok(Event::Incoming(Packet::ConnAck(_))) => {
                if flapping {
                    tracing::debug!(url = %settings.url, "MQTT connected");
                } else {
                    tracing::info!(url = %settings.url, "MQTT connected");
                }
                last_failure = None;
                connected_at = Some(std::time::Instant::now());
                health.set_connected(true);
                resend.store(true, Ordering::Relaxed);
                // queued behind at most the channel's few messages; rumqttc's channel never loses it
                let c = client.clone();
                let topic = online_topic.to_string();
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
                // the back-off starts again only after a connection that held: reset at every CONNACK, a broker
                // that closed each connection at once was reconnected to 10 times a second (a hostile tester's)
                let held = connected_at.take().map(|at| at.elapsed() >= CONNECTION_HELD);
                if held == Some(true) {
                    backoff = Duration::from_millis(100);
                    flapping = false;
                }
                if held == Some(false) && !flapping {
                    flapping = true;
                    tracing::warn!(url = %settings.url, error,
                        "MQTT connection lost soon after the broker accepted it: retrying with back-off, and \
                         said again only once a connection holds");
                } else if held.is_some() && flapping {
                    tracing::debug!(url = %settings.url, error, "MQTT connection lost");
                } else if health.connected.load(Ordering::Relaxed) {
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
}

/// `offline` (retained) and DISCONNECT, given 2 s at most to go out.
async fn say_goodbye(client: &AsyncClient, eventloop: &mut rumqttc::EventLoop, online_topic: &str) {
    let _ = client.try_publish(online_topic, QoS::AtLeastOnce, true, "offline");
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

#[cfg(test)]
mod tests {
    use super::*;

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

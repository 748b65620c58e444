//! The HTTP face of the service (CONTRACT.md "HTTP"): JSON API, server-sent events, Prometheus metrics, recordings
//! and the embedded dashboard. Built by [`router`] from the shared state; never talks Modbus.

use std::convert::Infallible;
use std::sync::Arc;
use std::time::Duration;

use axum::body::Bytes;
use axum::extract::rejection::{BytesRejection, QueryRejection};
use axum::extract::{DefaultBodyLimit, Path, Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use futures::StreamExt;
use serde::{Deserialize, Serialize};
use subtle::ConstantTimeEq;
use tokio_util::sync::CancellationToken;

use crate::control::Mode;
use crate::service::ServiceState;
use crate::service::state::{DriveSnapshot, PointColumns};

pub mod bounded;
mod condition;
pub mod conn;
pub mod files;
pub mod metrics;
pub mod throttle;

use bounded::{Bounded, Refused};
pub use conn::{ConnLimits, serve_with};
pub use metrics::HttpMetrics;
use metrics::ReasonLabel;
use throttle::AuthThrottle;

/// What the handlers share.
#[derive(Clone)]
pub struct AppState {
    pub service: Arc<ServiceState>,
    /// The Bearer token of the write routes; None disables them.
    pub token: Option<Arc<str>>,
    pub max_body_bytes: usize,
    /// Ends the event streams so that a graceful shutdown does not wait on them.
    pub shutdown: CancellationToken,
    /// The last rendered `/api/status` body (see [`STATUS_MAX_AGE`]).
    pub status_cache: Arc<StatusCache>,
    /// Wrong tokens per client (see [`throttle`]).
    pub auth: Arc<AuthThrottle>,
    /// Open `/api/events` streams (`http.max_event_streams`, an address its [`bounded::address_share`]).
    pub event_streams: Bounded,
    /// `/api/history` replies being built or sent ([`MAX_HISTORY_REPLIES`], an address its share).
    pub history_replies: Bounded,
    /// Recordings being downloaded ([`MAX_DOWNLOADS`], an address its share).
    pub downloads: Bounded,
    /// This side's own families, in the service's registry.
    pub metrics: HttpMetrics,
    /// The MQTT publisher's health, when one runs beside this outlet ([`AppState::with_mqtt`]).
    pub mqtt: Option<Arc<crate::mqtt::MqttHealth>>,
    /// Served on a loopback address: only requests naming a loopback host are answered ([`loopback_host`]).
    pub loopback_only: bool,
}

impl AppState {
    /// The state of a router over `service`, with the token and body limit of `http` and this side's `metrics`
    /// ([`HttpMetrics::register`]ed by the caller in the service's registry); the caches start empty.
    pub fn new(
        service: Arc<ServiceState>,
        http: &crate::service::config::HttpSettings,
        metrics: HttpMetrics,
        shutdown: CancellationToken,
    ) -> AppState {
        AppState {
            metrics,
            service,
            token: http.token.as_deref().map(Arc::from),
            max_body_bytes: http.max_body_bytes,
            shutdown,
            status_cache: Default::default(),
            auth: Default::default(),
            event_streams: Bounded::new(http.max_event_streams),
            history_replies: Bounded::new(MAX_HISTORY_REPLIES),
            downloads: Bounded::new(MAX_DOWNLOADS),
            mqtt: None,
            loopback_only: false,
        }
    }

    /// The same, answering only requests whose `Host` names a loopback host where `listening` is a loopback address
    /// (see [`loopback_host`]).
    pub fn listening_on(self, listening: std::net::SocketAddr) -> AppState {
        AppState { loopback_only: listening.ip().is_loopback(), ..self }
    }

    /// The same, reporting the MQTT publisher's health in `/api/status`.
    pub fn with_mqtt(self, mqtt: Option<Arc<crate::mqtt::MqttHealth>>) -> AppState {
        AppState { mqtt, ..self }
    }
}

/// How long a rendered `/api/status` body is served to further requests. Requests within it share one rendering
/// (the first renders while the others wait), so a flood of requests costs at most 1000 renderings a second
/// however many clients there are: with 50 drives one rendering is ≈ 75 kB of JSON. The snapshots themselves are
/// as old as the last poll; this adds at most 1 ms. A write route clears it, so a client reads its own writes.
pub const STATUS_MAX_AGE: Duration = Duration::from_millis(1);

/// See [`STATUS_MAX_AGE`].
#[derive(Debug, Default)]
pub struct StatusCache(std::sync::Mutex<Option<(std::time::Instant, Bytes)>>);

impl StatusCache {
    fn lock(&self) -> std::sync::MutexGuard<'_, Option<(std::time::Instant, Bytes)>> {
        self.0.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn clear(&self) {
        *self.lock() = None;
    }
}

/// An error answer: a status and a JSON body `{"error": "..."}`. 5xx are logged once, here.
#[derive(Debug)]
pub struct ApiError {
    pub status: StatusCode,
    pub message: String,
    /// Seconds for `Retry-After` (429: what is left of the block).
    pub retry_after_s: Option<u64>,
}

impl ApiError {
    pub fn new(status: StatusCode, message: impl Into<String>) -> ApiError {
        ApiError { status, message: message.into(), retry_after_s: None }
    }
    fn not_found(message: impl Into<String>) -> ApiError {
        ApiError::new(StatusCode::NOT_FOUND, message)
    }
    fn bad_request(message: impl Into<String>) -> ApiError {
        ApiError::new(StatusCode::BAD_REQUEST, message)
    }
    fn throttled(wait: Duration) -> ApiError {
        // the header says what is left of the block, as the body does (it said the whole block, 60 s, always)
        let left = wait.as_secs_f64().ceil().max(1.0) as u64;
        ApiError {
            status: StatusCode::TOO_MANY_REQUESTS,
            message: format!("too many wrong tokens: try again in {left} s"),
            retry_after_s: Some(left),
        }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        if self.status.is_server_error() {
            tracing::error!(status = %self.status, error = %self.message, "request failed");
        }
        let mut resp = (self.status, Json(serde_json::json!({ "error": self.message }))).into_response();
        if self.status == StatusCode::UNAUTHORIZED {
            resp.headers_mut().insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
        }
        if let Some(s) = self.retry_after_s {
            resp.headers_mut().insert(header::RETRY_AFTER, HeaderValue::from(s));
        }
        resp
    }
}

impl From<BytesRejection> for ApiError {
    fn from(r: BytesRejection) -> ApiError {
        let status = if r.status() == StatusCode::PAYLOAD_TOO_LARGE { r.status() } else { StatusCode::BAD_REQUEST };
        ApiError::new(status, r.body_text())
    }
}

/// A path segment (`{name}`, `{file}`); one axum cannot take (not UTF-8: `%ff`) is a JSON 400 as every error of the
/// API, not axum's plain-text one.
pub(super) struct Segment(pub String);

impl<S: Send + Sync> axum::extract::FromRequestParts<S> for Segment {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut axum::http::request::Parts, state: &S) -> Result<Segment, ApiError> {
        match Path::<String>::from_request_parts(parts, state).await {
            Ok(Path(segment)) => Ok(Segment(segment)),
            Err(r) => Err(ApiError::bad_request(r.body_text())),
        }
    }
}

impl From<QueryRejection> for ApiError {
    fn from(r: QueryRejection) -> ApiError {
        ApiError::bad_request(r.body_text())
    }
}

/// The embedded dashboard: the binary is self-contained (demo, docker).
const STATIC_FILES: [(&str, &str, &str); 6] = [
    ("index.html", "text/html; charset=utf-8", include_str!("../../static/index.html")),
    ("app.js", "text/javascript; charset=utf-8", include_str!("../../static/app.js")),
    ("condition.js", "text/javascript; charset=utf-8", include_str!("../../static/condition.js")),
    ("style.css", "text/css; charset=utf-8", include_str!("../../static/style.css")),
    (
        "vendor/uPlot.iife.min.js",
        "text/javascript; charset=utf-8",
        include_str!("../../static/vendor/uPlot.iife.min.js"),
    ),
    ("vendor/uPlot.min.css", "text/css; charset=utf-8", include_str!("../../static/vendor/uPlot.min.css")),
];

/// The service's routes.
pub fn router(state: AppState) -> Router {
    let limit = state.max_body_bytes;
    Router::new()
        .route("/", get(|| static_file("index.html")))
        .route("/app.js", get(|| static_file("app.js")))
        .route("/condition.js", get(|| static_file("condition.js")))
        .route("/style.css", get(|| static_file("style.css")))
        .route("/vendor/{file}", get(|Segment(f): Segment| static_file_owned(format!("vendor/{f}"))))
        .route("/api/status", get(status))
        .route("/api/history", get(history))
        .route("/api/events", get(events))
        .route("/api/drives/{name}/target", post(set_target))
        .route("/api/drives/{name}/reset", post(reset))
        .route("/api/drives/{name}/condition", get(condition::condition))
        .route("/api/recordings", get(recordings))
        .route("/api/recordings/{file}", get(recording_file))
        .route("/metrics", get(metrics))
        .route("/healthz", get(|| async { Json(serde_json::json!({ "status": "ok" })) }))
        .route("/readyz", get(readyz))
        .fallback(|| async { ApiError::not_found("no such route") })
        .layer(DefaultBodyLimit::max(limit))
        .layer(axum::middleware::from_fn_with_state(state.clone(), loopback_host))
        .with_state(state)
}

/// On a loopback address, a request whose `Host` is not a loopback name (`localhost`, `127.x.x.x`, `[::1]`, any
/// port) is refused with 421: a web page the operator opens elsewhere can point its own name at 127.0.0.1 (DNS
/// rebinding) and read the status and the recordings through the operator's browser; its requests still name the
/// page's host. A request without `Host` (HTTP/1.0) is answered. Beyond loopback the firewall and the token decide.
async fn loopback_host(
    State(s): State<AppState>,
    request: axum::extract::Request,
    next: axum::middleware::Next,
) -> Response {
    let named = |h: &str| {
        // `127.0.0.1:1@evil.example` names evil.example
        if h.contains('@') {
            return false;
        }
        let name = match h.strip_prefix('[') {
            Some(v6) => v6.split(']').next().unwrap_or(""),
            None => h.rsplit_once(':').map_or(h, |(name, _)| name),
        };
        name.eq_ignore_ascii_case("localhost") || name.parse::<std::net::IpAddr>().is_ok_and(|ip| ip.is_loopback())
    };
    // every `Host` counts, and the host an absolute-form request line names (`GET http://host/…`): only the first
    // header was looked at, and `Host: 127.0.0.1` then `Host: evil.example` was answered
    let hosts = request.headers().get_all(header::HOST).iter().map(|h| h.to_str().unwrap_or("\u{fffd}"));
    let refused = hosts
        .chain(request.uri().authority().map(|a| a.as_str()))
        .filter(|_| s.loopback_only)
        .find(|h| !named(h))
        .map(|h| {
            format!("this service listens on loopback and answers requests for a loopback host only, not {}", echo(h))
        });
    match refused {
        Some(why) => ApiError::new(StatusCode::MISDIRECTED_REQUEST, why).into_response(),
        None => next.run(request).await,
    }
}

/// What a client sent, for an error message: quoted, at most [`ECHOED_CHARS`] characters (a 20 kB drive name came
/// back whole).
pub(crate) fn echo(text: &str) -> String {
    match text.char_indices().nth(ECHOED_CHARS) {
        Some((cut, _)) => format!("{:?}… ({} bytes)", &text[..cut], text.len()),
        None => format!("{text:?}"),
    }
}

/// See [`echo`].
const ECHOED_CHARS: usize = 64;

/// Serves the router on an already-bound listener until `state.shutdown` fires, within the default
/// [`ConnLimits`].
pub async fn serve(listener: tokio::net::TcpListener, state: AppState) -> std::io::Result<()> {
    serve_with(listener, state, ConnLimits::default()).await
}

/// The client's address, when the request came through [`serve_with`] (not in `oneshot` tests).
pub struct ClientAddr(Option<std::net::SocketAddr>);

impl ClientAddr {
    /// The client's IP; requests without an address (in-process tests) share 0.0.0.0.
    fn ip(&self) -> std::net::IpAddr {
        self.0.map_or(std::net::IpAddr::from([0, 0, 0, 0]), |a| a.ip())
    }
}

impl<S: Send + Sync> axum::extract::FromRequestParts<S> for ClientAddr {
    type Rejection = Infallible;

    async fn from_request_parts(parts: &mut axum::http::request::Parts, _: &S) -> Result<Self, Infallible> {
        Ok(ClientAddr(parts.extensions.get::<axum::extract::ConnectInfo<std::net::SocketAddr>>().map(|c| c.0)))
    }
}

async fn static_file(path: &'static str) -> Response {
    static_file_owned(path.to_string()).await
}

async fn static_file_owned(path: String) -> Response {
    match STATIC_FILES.iter().find(|(p, _, _)| *p == path) {
        Some((_, mime, body)) => {
            ([(header::CONTENT_TYPE, *mime), (header::CACHE_CONTROL, "no-cache")], *body).into_response()
        }
        None => ApiError::not_found(format!("no static file {}", echo(&path))).into_response(),
    }
}

/// `/api/status` and each SSE event.
#[derive(Debug, Serialize)]
pub struct StatusBody {
    pub ready: bool,
    pub uptime_s: f64,
    /// True when the write routes accept a token.
    pub writes_enabled: bool,
    pub drives: Vec<DriveSnapshot>,
    /// The MQTT publisher (connected, published, dropped); absent when `[mqtt]` is not configured.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mqtt: Option<crate::mqtt::MqttStatus>,
}

fn status_body(state: &AppState) -> StatusBody {
    StatusBody {
        ready: state.service.ready(),
        uptime_s: state.service.started.elapsed().as_secs_f64(),
        writes_enabled: state.token.is_some(),
        drives: state.service.snapshots(),
        mqtt: state.mqtt.as_ref().map(|m| m.status()),
    }
}

async fn status(State(s): State<AppState>) -> Response {
    let now = std::time::Instant::now();
    let mut cached = s.status_cache.lock();
    if let Some((at, body)) = &*cached
        && now.saturating_duration_since(*at) < STATUS_MAX_AGE
    {
        return json_bytes(body.clone());
    }
    let mut buf = Vec::with_capacity(1536 * s.service.drives.len() + 256);
    if let Err(e) = serde_json::to_writer(&mut buf, &status_body(&s)) {
        tracing::error!(error = %e, "serialising the status");
        return StatusCode::INTERNAL_SERVER_ERROR.into_response();
    }
    let body = Bytes::from(buf);
    *cached = Some((now, body.clone()));
    json_bytes(body)
}

fn json_bytes(body: Bytes) -> Response {
    ([(header::CONTENT_TYPE, HeaderValue::from_static("application/json"))], body).into_response()
}

/// A JSON body serialised into a buffer sized up front. axum's `Json` grows a small `BytesMut` through many tiny
/// writes: with 50 drives (≈ 75 kB) that copying was a fifth of the status route's CPU.
fn json_response<T: Serialize>(body: &T, size_hint: usize) -> Response {
    serialised(body, size_hint).map_or_else(|| StatusCode::INTERNAL_SERVER_ERROR.into_response(), json_bytes)
}

/// [`json_response`]'s body; `None` (logged) when it does not serialise, which is a 500.
fn serialised<T: Serialize>(body: &T, size_hint: usize) -> Option<Bytes> {
    let mut buf = Vec::with_capacity(size_hint.max(256));
    serde_json::to_writer(&mut buf, body)
        .inspect_err(|e| tracing::error!(error = %e, "serialising a response"))
        .ok()
        .map(|()| Bytes::from(buf))
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct HistoryQuery {
    drive: String,
    #[serde(default = "sixty")]
    seconds: f64,
    #[serde(default = "two_thousand")]
    max_points: usize,
}

fn sixty() -> f64 {
    60.0
}
fn two_thousand() -> usize {
    2000
}

/// Recent points as columns named like the recording's ([`PointColumns`]).
#[derive(Serialize)]
struct HistoryBody<'a> {
    drive: &'a str,
    #[serde(flatten)]
    columns: PointColumns<'a>,
}

async fn history(
    State(s): State<AppState>,
    client: ClientAddr,
    q: Result<Query<HistoryQuery>, QueryRejection>,
) -> Result<Response, ApiError> {
    let Query(q) = q?;
    if !(q.seconds.is_finite() && q.seconds > 0.0) {
        return Err(ApiError::bad_request(format!("seconds must be a finite number > 0, got {}", q.seconds)));
    }
    if !(1..=100_000).contains(&q.max_points) {
        return Err(ApiError::bad_request(format!("max_points must be 1 ..= 100000, got {}", q.max_points)));
    }
    let drive = s.service.drive(&q.drive).ok_or_else(|| ApiError::not_found(format!("no drive {}", echo(&q.drive))))?;
    let permit = match s.history_replies.take(client.ip()) {
        Ok(held) => held,
        Err(why) => return Ok(refused(&s, why, &HISTORY_REFUSALS, 1)),
    };
    let points = drive.history(q.seconds, q.max_points);
    let body = HistoryBody { drive: &q.drive, columns: PointColumns(&points) };
    // about 20 bytes a value, 13 columns
    let Some(bytes) = serialised(&body, 260 * points.len()) else {
        return Ok(StatusCode::INTERNAL_SERVER_ERROR.into_response());
    };
    // sent in chunks that hold the permit until the last one is taken: a reply a client does not read stays counted
    let chunks = (0..bytes.len().div_ceil(DOWNLOAD_CHUNK)).map(move |k| {
        let _held = &permit;
        Ok::<_, Infallible>(bytes.slice(k * DOWNLOAD_CHUNK..((k + 1) * DOWNLOAD_CHUNK).min(bytes.len())))
    });
    let body = axum::body::Body::from_stream(futures::stream::iter(chunks));
    Ok(([(header::CONTENT_TYPE, HeaderValue::from_static("application/json"))], body).into_response())
}

/// `/api/history` replies built or being sent at once: at its largest (100 000 points, about 9 MB) eight hold 72 MB.
/// Each was built whole and held until its client read it: 120 clients that did not read took the service from 20 MB
/// to 1.3 GB and disturbed the 1 ms poll loop; the ninth now gets 503 with `Retry-After`.
pub const MAX_HISTORY_REPLIES: usize = 8;

/// The SSE period: about 10 Hz.
const EVENT_PERIOD: Duration = Duration::from_millis(100);

/// What a refused [`Bounded`] place is counted under and said with: where the address holds its share, and where
/// every place is held.
type Refusals = [(&'static str, &'static str); 2];

const EVENT_REFUSALS: Refusals = [
    (
        "event_share",
        "this address holds its share of the event streams (three quarters of http.max_event_streams): try again later",
    ),
    ("event_streams", "too many event streams open (http.max_event_streams): try again later"),
];
const HISTORY_REFUSALS: Refusals = [
    ("history_share", "this address holds its share of the history replies in flight: try again in a moment"),
    ("history_replies", "too many history replies in flight: try again in a moment"),
];
const DOWNLOAD_REFUSALS: Refusals = [
    ("download_share", "this address holds its share of the downloads at once: try again in a moment"),
    ("downloads", "too many recordings being downloaded: try again in a moment"),
];

/// 503 with `Retry-After` for a [`Bounded`] place refused, counted and said as `refusals` give.
fn refused(s: &AppState, why: Refused, refusals: &Refusals, retry_after_s: u64) -> Response {
    let (reason, message) = match why {
        Refused::Share => refusals[0],
        Refused::All => refusals[1],
    };
    s.metrics.refused.get_or_create(&ReasonLabel { reason }).inc();
    conn::busy(message, retry_after_s)
}

/// Holds an event stream's place and counts it open while it lives.
struct StreamSlot {
    _held: bounded::Held,
    open: prometheus_client::metrics::gauge::Gauge,
}

impl Drop for StreamSlot {
    fn drop(&mut self) {
        self.open.dec();
    }
}

/// A snapshot every [`EVENT_PERIOD`], while fewer than `http.max_event_streams` are open, and fewer than
/// [`bounded::address_share`] of them from the client's address; 503 at once beyond, so a crowd of tabs (or a flood) cannot hold
/// every connection, nor one address every stream. A client that stops reading is closed by the accept loop (see
/// [`conn`]).
async fn events(State(s): State<AppState>, client: ClientAddr) -> Response {
    let held = match s.event_streams.take(client.ip()) {
        Ok(held) => held,
        Err(why) => return refused(&s, why, &EVENT_REFUSALS, 5),
    };
    s.metrics.event_streams.inc();
    let slot = StreamSlot { _held: held, open: s.metrics.event_streams.clone() };
    let stop = s.shutdown.clone();
    let mut tick = tokio::time::interval(EVENT_PERIOD);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let stream = futures::stream::unfold((s, tick, slot), |(s, mut tick, slot)| async move {
        tick.tick().await;
        let event = match serde_json::to_string(&status_body(&s)) {
            Ok(json) => Event::default().event("snapshot").data(json),
            Err(e) => Event::default().event("error").data(e.to_string()),
        };
        Some((Ok::<_, Infallible>(event), (s, tick, slot)))
    })
    .take_until(async move { stop.cancelled().await });
    Sse::new(stream).keep_alive(KeepAlive::default()).into_response()
}

/// Checks `Authorization: Bearer <token>` in constant time. The right token is always accepted, whoever else
/// shares the client's address (behind a reverse proxy every user does); only wrong ones are slowed: after a burst
/// of them an address gets 429 for its wrong tokens for a while (see [`throttle`]). Failures are counted and logged
/// with the client's address, never the token.
fn authorize(s: &AppState, headers: &HeaderMap, client: &ClientAddr) -> Result<(), ApiError> {
    let Some(token) = &s.token else {
        return Err(ApiError::new(StatusCode::FORBIDDEN, "write routes are disabled: no http.token in the config"));
    };
    let given = headers
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        // the scheme is case-insensitive (RFC 9110 §11.1): `bearer` and `BEARER` are the same
        .and_then(|v| v.split_once(' ').filter(|(scheme, _)| scheme.eq_ignore_ascii_case("bearer")))
        .map(|(_, t)| t.trim());
    if given.is_some_and(|g| same_token(g.as_bytes(), token.as_bytes())) {
        return Ok(());
    }
    let ip = client.ip();
    let now = std::time::Instant::now();
    if let Some(wait) = s.auth.blocked(ip, now) {
        s.metrics.auth_throttled.inc();
        return Err(ApiError::throttled(wait));
    }
    let Some(_) = given else {
        return Err(ApiError::new(StatusCode::UNAUTHORIZED, "needs Authorization: Bearer <token>"));
    };
    s.metrics.auth_failures.inc();
    let (failures, blocked) = s.auth.failed(ip, now);
    if blocked {
        tracing::warn!(client = %ip, block_s = throttle::BLOCK.as_secs(),
            "wrong token: too many from this client, its wrong tokens answer 429 for a while");
    } else {
        tracing::warn!(client = %ip, failures, "wrong token on a write route");
    }
    Err(ApiError::new(StatusCode::UNAUTHORIZED, "wrong token"))
}

/// `given == token` in a time that depends on the token's length only: `ct_eq` on slices answers at once where the
/// lengths differ, which tells a guesser the token's length. Every byte of the token is compared with the given
/// one at its place (or a zero past the given's end), and the lengths in constant time too.
fn same_token(given: &[u8], token: &[u8]) -> bool {
    let mut equal = (given.len() as u64).ct_eq(&(token.len() as u64));
    for (k, t) in token.iter().enumerate() {
        equal &= given.get(k).copied().unwrap_or(0).ct_eq(t);
    }
    bool::from(equal)
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct TargetBody {
    target_omega_rad_s: f64,
}

async fn set_target(
    State(s): State<AppState>,
    Segment(name): Segment,
    client: ClientAddr,
    headers: HeaderMap,
    body: Result<Bytes, BytesRejection>,
) -> Result<Json<serde_json::Value>, ApiError> {
    authorize(&s, &headers, &client)?;
    let drive = s.service.drive(&name).ok_or_else(|| ApiError::not_found(format!("no drive {}", echo(&name))))?;
    let body = body?;
    let expected =
        |e: &dyn std::fmt::Display| ApiError::bad_request(format!("expected {{\"target_omega_rad_s\": number}}: {e}"));
    // an object only: serde would take `[40]` as the struct's fields in order; parsed once, into the struct, which
    // refuses a key given twice (a JSON value keeps the last)
    if body.trim_ascii_start().first() != Some(&b'{') {
        return Err(expected(&"the body is not a JSON object"));
    }
    let t: TargetBody = serde_json::from_slice(&body).map_err(|e| expected(&e))?;
    match drive.mode {
        Mode::Speed => {}
        m => {
            return Err(ApiError::new(
                StatusCode::CONFLICT,
                format!("drive {name:?} is in {m:?} mode: a speed target applies only in speed mode"),
            ));
        }
    }
    let max = drive.max_target_omega_rad_s;
    if !(t.target_omega_rad_s.is_finite() && (0.0..=max).contains(&t.target_omega_rad_s)) {
        return Err(ApiError::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            format!(
                "target_omega_rad_s must be 0 ..= {max:.1} (max_hz with no load), got {:.6e}",
                t.target_omega_rad_s
            ),
        ));
    }
    drive.set_target(t.target_omega_rad_s);
    s.status_cache.clear();
    tracing::info!(drive = %name, target_omega_rad_s = t.target_omega_rad_s, "new speed target");
    Ok(Json(serde_json::json!({ "drive": name, "target_omega_rad_s": t.target_omega_rad_s })))
}

/// The body, which a reset does not need, is read (within `max_body_bytes`) before the answer: answered first, the
/// connection was dropped under the body still coming, and the client's next request on it failed (a client that
/// retries would reset twice).
async fn reset(
    State(s): State<AppState>,
    Segment(name): Segment,
    client: ClientAddr,
    headers: HeaderMap,
    body: Result<Bytes, BytesRejection>,
) -> Result<(StatusCode, Json<serde_json::Value>), ApiError> {
    body?;
    authorize(&s, &headers, &client)?;
    let drive = s.service.drive(&name).ok_or_else(|| ApiError::not_found(format!("no drive {}", echo(&name))))?;
    if drive.mode == Mode::Monitor {
        return Err(ApiError::new(StatusCode::CONFLICT, format!("drive {name:?} is in monitor mode: it never writes")));
    }
    if drive.stale_or_down() {
        // kept, it would be carried out unseen whenever the link came back
        return Err(ApiError::new(
            StatusCode::CONFLICT,
            format!("drive {name:?} is not seen (link down or data stale): a reset is taken only while it is"),
        ));
    }
    drive.request_reset();
    s.status_cache.clear();
    tracing::info!(drive = %name, "fault reset requested");
    Ok((StatusCode::ACCEPTED, Json(serde_json::json!({ "drive": name, "reset": "requested" }))))
}

#[derive(Debug, Serialize)]
struct RecordingEntry {
    name: String,
    bytes: u64,
    modified_unix_s: Option<u64>,
}

async fn recordings(State(s): State<AppState>) -> Result<Json<serde_json::Value>, ApiError> {
    let Some(dir) = &s.service.recording_dir else {
        return Ok(Json(serde_json::json!({ "enabled": false, "files": [] })));
    };
    let mut files = Vec::new();
    let mut rd = match tokio::fs::read_dir(dir).await {
        Ok(rd) => rd,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Ok(Json(serde_json::json!({ "enabled": true, "files": [] })));
        }
        Err(e) => return Err(ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, format!("listing recordings: {e}"))),
    };
    while let Ok(Some(entry)) = rd.next_entry().await {
        let name = entry.file_name().to_string_lossy().into_owned();
        if !valid_file_name(&name) {
            continue;
        }
        // only regular files: never a link, FIFO or directory (what the download route would refuse)
        if !entry.file_type().await.is_ok_and(|t| t.is_file()) {
            continue;
        }
        let Ok(meta) = entry.metadata().await else { continue };
        let modified_unix_s =
            meta.modified().ok().and_then(|m| m.duration_since(std::time::UNIX_EPOCH).ok()).map(|d| d.as_secs());
        files.push(RecordingEntry { name, bytes: meta.len(), modified_unix_s });
    }
    files.sort_by(|a, b| a.name.cmp(&b.name));
    Ok(Json(serde_json::json!({ "enabled": true, "files": files })))
}

/// A recording's file name: letters, digits, `-`, `_`, `.`, ending in `.csv` or `.csv.gz`, never a path.
fn valid_file_name(name: &str) -> bool {
    name.len() <= 128
        && (name.ends_with(".csv") || name.ends_with(".csv.gz"))
        && !name.starts_with('.')
        && !name.contains("..")
        && name.chars().all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
}

/// The media type of a recording file, by its name.
fn content_type(name: &str) -> &'static str {
    if name.ends_with(".gz") { "application/gzip" } else { "text/csv; charset=utf-8" }
}

/// The read buffer of a download: what a client's download holds in memory, however large the file and however
/// slowly it reads (the rest waits in the file), beside the connection's write buffer (`conn::WRITE_BUFFER_BYTES`
/// in hyper and in the kernel).
const DOWNLOAD_CHUNK: usize = 64 * 1024;

/// Recordings downloaded at once; the next gets 503 with `Retry-After`. 512 slow downloads held every connection (the
/// dashboard's routes answered 503 for 10–20 s at a time) and took the service from 12 to 310 MB.
pub const MAX_DOWNLOADS: usize = 8;

async fn recording_file(
    State(s): State<AppState>,
    client: ClientAddr,
    Segment(file): Segment,
) -> Result<Response, ApiError> {
    if !valid_file_name(&file) {
        return Err(ApiError::bad_request(format!(
            "{} is not a recording name such as pump1-1700000000000.csv",
            echo(&file)
        )));
    }
    let Some(dir) = &s.service.recording_dir else { return Err(ApiError::not_found("recording is off")) };
    let permit = match s.downloads.take(client.ip()) {
        Ok(held) => held,
        Err(why) => return Ok(refused(&s, why, &DOWNLOAD_REFUSALS, 5)),
    };
    let (dir, name) = (dir.clone(), file.clone());
    let opened = tokio::task::spawn_blocking(move || files::open_regular(&dir, &name))
        .await
        .map_err(|e| ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, format!("reading {file}: {e}")))?;
    match opened {
        Ok(Some((f, len))) => {
            // streamed, as long as the file was when opened (the open recording grows meanwhile)
            let reader = tokio::io::AsyncReadExt::take(tokio::fs::File::from_std(f), len);
            // the permit goes with the last chunk (or a client gone)
            let chunks = tokio_util::io::ReaderStream::with_capacity(reader, DOWNLOAD_CHUNK).map(move |chunk| {
                let _held = &permit;
                chunk
            });
            let body = axum::body::Body::from_stream(chunks);
            Ok((
                [
                    // a compressed recording goes as the file it is (no Content-Encoding: saved, it stays .csv.gz)
                    (header::CONTENT_TYPE, content_type(&file).to_string()),
                    (header::CONTENT_DISPOSITION, format!("attachment; filename=\"{file}\"")),
                    (header::CONTENT_LENGTH, len.to_string()),
                ],
                body,
            )
                .into_response())
        }
        Ok(None) => Err(ApiError::not_found(format!("no recording {}", echo(&file)))),
        Err(e) => Err(ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, format!("reading {file}: {e}"))),
    }
}

/// OpenMetrics when the scraper's `Accept` asks for it, the Prometheus text format 0.0.4 otherwise.
async fn metrics(State(s): State<AppState>, headers: HeaderMap) -> Response {
    let accept = headers.get(header::ACCEPT).and_then(|v| v.to_str().ok());
    let format = crate::metrics::Format::negotiate(accept);
    ([(header::CONTENT_TYPE, format.content_type())], crate::metrics::exposition(&s.service, format)).into_response()
}

async fn readyz(State(s): State<AppState>) -> Response {
    let names = |which: &dyn Fn(&crate::service::DriveState) -> bool| {
        s.service.drives.iter().filter(|d| which(d)).map(|d| d.name.clone()).collect::<Vec<_>>()
    };
    let not_ready = names(&|d| !d.ready());
    if not_ready.is_empty() {
        Json(serde_json::json!({ "status": "ready" })).into_response()
    } else {
        (
            StatusCode::SERVICE_UNAVAILABLE,
            Json(serde_json::json!({
                "status": "not ready",
                "not_ready": not_ready,
                "stale_or_down": names(&|d| d.stale_or_down()),
                "not_following": names(&|d| d.not_following()),
                "another_master": names(&|d| d.another_master()),
                "writes_refused": names(&|d| d.writes_failing()),
                "recording_failing": names(&|d| d.recording_failing()),
            })),
        )
            .into_response()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recording_names_are_never_paths() {
        assert!(valid_file_name("pump1-1700000000000.csv"));
        assert!(valid_file_name("pump1-1700000000000-1.csv"));
        assert!(valid_file_name("pump1-1700000000000-1.csv.gz"));
        assert!(!valid_file_name(".pump1-1700000000000.csv.gz.tmp") && !valid_file_name("pump1-1.gz"));
        for bad in ["../etc/passwd", "a/b.csv", ".hidden.csv", "x..csv", "x.txt", "%2e%2e.csv", ""] {
            assert!(!valid_file_name(bad), "{bad}");
        }
    }

    #[test]
    fn a_token_is_the_same_only_whole() {
        let token = b"s3cret-Token-0123456789";
        assert!(same_token(token, token));
        for given in
            [&b""[..], b"s", b"s3cret-Token-012345678", b"s3cret-Token-01234567890", b"S3cret-Token-0123456789"]
        {
            assert!(!same_token(given, token), "{given:?}");
        }
        // a zero past the given one's end is no match for a token that has zeros there
        assert!(!same_token(b"ab", b"ab\0"));
    }

    #[test]
    fn what_a_client_sent_is_echoed_short() {
        assert_eq!(echo("pump1"), "\"pump1\"");
        let long = "x".repeat(20_000);
        let e = echo(&long);
        assert!(e.len() < 100 && e.ends_with("… (20000 bytes)"), "{e}");
        assert!(echo(&"é".repeat(100)).starts_with("\"éé"), "cut on a character's boundary");
    }
}

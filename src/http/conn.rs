//! The HTTP accept loop, with bounds a hostile client cannot stretch:
//! - at most `max_connections` connections at once (the rest wait in the kernel's backlog, holding none of our file
//!   descriptors), and at most `max_connections_per_client` of them from one address;
//! - an address beyond its share has its oldest connection that never carried a request (held open half-sent, as a
//!   flood does) closed for the new one: the operator, who may share the flooder's address (a proxy, a NAT), gets in;
//! - with every connection held, the oldest one of any address that never carried a request is closed for the new
//!   one, else the one kept alive longest between requests (never one answering a request: a stream, a download):
//!   a crowd spread over many addresses, each within its share, cannot keep the operator in the backlog;
//! - [`RESERVED_CONNECTIONS`] more, kept for the operator: taken when the others are all held (or one address holds
//!   its share of connections that all carried requests), and serving only the control routes, `/healthz` and
//!   `/readyz`, one request each;
//! - request headers within `header_timeout` (hyper's timer also runs while a kept-alive connection waits for its
//!   next request, so an idle connection is closed as soon), and a whole request answered within `request_timeout`;
//! - a connection whose writes make no progress for `header_timeout` (a client that stopped reading an event stream
//!   or a download) is closed.

use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr};
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use axum::extract::{ConnectInfo, Request, State};
use axum::http::{HeaderValue, Method, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use hyper_util::rt::{TokioIo, TokioTimer};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tower::ServiceExt;

use super::HttpMetrics;
use super::metrics::ReasonLabel;
use super::{AppState, router};

/// The bounds of [`serve_with`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ConnLimits {
    pub header_timeout: Duration,
    pub request_timeout: Duration,
    pub max_connections: usize,
    pub max_connections_per_client: usize,
}

impl From<&crate::service::config::HttpSettings> for ConnLimits {
    fn from(h: &crate::service::config::HttpSettings) -> ConnLimits {
        ConnLimits {
            header_timeout: h.header_timeout,
            request_timeout: h.request_timeout,
            max_connections: h.max_connections,
            max_connections_per_client: h.max_connections_per_client,
        }
    }
}

impl Default for ConnLimits {
    /// 10 s for headers and for a whole request (well inside the 30 s an idle or half-sent request may live),
    /// 512 connections, 128 from one address.
    fn default() -> ConnLimits {
        ConnLimits {
            header_timeout: Duration::from_secs(10),
            request_timeout: Duration::from_secs(10),
            max_connections: 512,
            max_connections_per_client: 128,
        }
    }
}

/// A connection's buffer of what it sends, in hyper (its `max_buf_size`, also the most a request's head may take)
/// and in the kernel (the socket's send buffer): at hyper's and the kernel's defaults a client that stopped reading
/// a download held about 600 kB of the service's memory and 4 MB of the kernel's.
pub const WRITE_BUFFER_BYTES: usize = 64 * 1024;

/// Connections beyond `max_connections` kept for the control routes, `/healthz` and `/readyz`.
pub const RESERVED_CONNECTIONS: usize = 32;

/// How long a reserved connection may take to send its request: one request, promptly, or it goes.
const RESERVED_HEADER_TIMEOUT: Duration = Duration::from_secs(2);

/// Marks a request that came on a reserved connection.
#[derive(Debug, Clone, Copy)]
struct Reserved;

/// The routes a reserved connection serves: the control routes and the health checks.
fn reserved_route(method: &Method, path: &str) -> bool {
    match *method {
        Method::GET => matches!(path, "/healthz" | "/readyz"),
        Method::POST => {
            path.strip_prefix("/api/drives/").is_some_and(|rest| rest.ends_with("/target") || rest.ends_with("/reset"))
        }
        _ => false,
    }
}

/// A 503 that closes its connection, with a hint when to come back.
pub(super) fn busy(message: &str, retry_after_s: u64) -> Response {
    let mut resp =
        (StatusCode::SERVICE_UNAVAILABLE, axum::Json(serde_json::json!({ "error": message }))).into_response();
    resp.headers_mut().insert(header::RETRY_AFTER, HeaderValue::from(retry_after_s));
    resp.headers_mut().insert(header::CONNECTION, HeaderValue::from_static("close"));
    resp
}

/// On a reserved connection, everything but [`reserved_route`] gets 503 at once.
async fn reserve_gate(State(metrics): State<HttpMetrics>, req: Request, next: Next) -> Response {
    if req.extensions().get::<Reserved>().is_some() && !reserved_route(req.method(), req.uri().path()) {
        metrics.refused.get_or_create(&ReasonLabel { reason: "reserved" }).inc();
        return busy("the service is at its connection limit: only control and health routes answer", 1);
    }
    next.run(req).await
}

/// Open connections per client address (IPv6 by its /64, as the token throttle keys them), oldest first.
#[derive(Debug, Default)]
struct PerClient(Mutex<HashMap<IpAddr, Vec<Arc<Mark>>>>);

/// How long a new connection has to send its request before it is held open half-sent, and is closed for a newer
/// one ahead of a connection kept alive between requests: under a crowd churning thousands of connections a second,
/// the operator's was closed before its request was read.
const NEVER_SERVED_GRACE: Duration = Duration::from_secs(1);

/// One open connection, as its address's list holds it.
#[derive(Debug)]
struct Mark {
    /// When it came (the order the connections came in, any address).
    opened: Instant,
    /// A request came on it: it is a client's, not a connection held open half-sent.
    served: std::sync::atomic::AtomicBool,
    /// A request is being answered on it (from the request until its response body is sent or dropped): an event
    /// stream or a download stays busy for as long as it runs.
    busy: std::sync::atomic::AtomicBool,
    /// When its last response ended (milliseconds since the accept loop's epoch): how long it has waited, kept
    /// alive, for its next request.
    idle_since_ms: AtomicU64,
    /// Cancelled to close it (evicted for a newer connection of its address).
    close: tokio_util::sync::CancellationToken,
}

impl PerClient {
    /// Counts one more connection from `ip`; the count, this one included, its mark, and a guard that takes it
    /// back.
    fn enter(self: &Arc<Self>, ip: IpAddr) -> (usize, ClientGuard) {
        let ip = super::throttle::key(ip);
        let mark = Arc::new(Mark {
            opened: Instant::now(),
            served: Default::default(),
            busy: Default::default(),
            idle_since_ms: Default::default(),
            close: Default::default(),
        });
        let mut m = self.0.lock().unwrap_or_else(|e| e.into_inner());
        let list = m.entry(ip).or_default();
        list.push(mark.clone());
        (list.len(), ClientGuard { clients: self.clone(), ip, mark })
    }

    /// Closes the oldest connection of `ip` that never carried a request (one held open half-sent, as a flood
    /// does), so that a newer one (the operator's, who shares the address) is served instead of refused. False
    /// when every connection of `ip` carried one.
    fn evict_idle(&self, newcomer: &ClientGuard) -> bool {
        let m = self.0.lock().unwrap_or_else(|e| e.into_inner());
        let victim = m.get(&newcomer.ip).and_then(|list| {
            list.iter()
                .find(|c| {
                    !Arc::ptr_eq(c, &newcomer.mark) && !c.served.load(Ordering::Relaxed) && !c.close.is_cancelled()
                })
                .cloned()
        });
        victim.inspect(|c| c.close.cancel()).is_some()
    }

    /// Closes the oldest connection of any address that never carried a request, where every ordinary connection
    /// is held: a crowd held open half-sent from many addresses, each within its share, is never past a share, and
    /// held every connection (reconnecting as each timed out) while the operator's waited in the kernel's backlog.
    ///
    /// One that came less than [`NEVER_SERVED_GRACE`] ago is closed only after those kept alive between requests;
    /// where every connection carried one, the one kept alive longest between requests goes (a reviewer's crowd of
    /// 515 sending a request every 8 s held every connection, and a silent crowd the reserve): a client's next
    /// request opens a new connection. A connection answering a request (an event stream, a download) is never
    /// closed for another.
    fn evict_oldest_idle(&self) -> bool {
        let m = self.0.lock().unwrap_or_else(|e| e.into_inner());
        let open = || m.values().flatten().filter(|c| !c.close.is_cancelled());
        let never = |old: bool| {
            open()
                .filter(|c| !c.served.load(Ordering::Relaxed) && (c.opened.elapsed() >= NEVER_SERVED_GRACE) == old)
                .min_by_key(|c| c.opened)
        };
        let between = || {
            open()
                .filter(|c| c.served.load(Ordering::Relaxed) && !c.busy.load(Ordering::Relaxed))
                .min_by_key(|c| c.idle_since_ms.load(Ordering::Relaxed))
        };
        // held half-sent past its grace, else kept alive between requests, else the oldest still in its grace
        let victim = never(true).or_else(between).or_else(|| never(false)).cloned();
        victim.inspect(|c| c.close.cancel()).is_some()
    }
}

struct ClientGuard {
    clients: Arc<PerClient>,
    ip: IpAddr,
    mark: Arc<Mark>,
}

impl Drop for ClientGuard {
    fn drop(&mut self) {
        let mut m = self.clients.0.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(list) = m.get_mut(&self.ip) {
            list.retain(|c| !Arc::ptr_eq(c, &self.mark));
            if list.is_empty() {
                m.remove(&self.ip);
            }
        }
    }
}

/// A request being answered on a connection: its mark is busy until this is dropped (with the response body).
struct Answering {
    mark: Arc<Mark>,
    epoch: Instant,
}

impl Drop for Answering {
    fn drop(&mut self) {
        self.mark.idle_since_ms.store(millis_since(self.epoch), Ordering::Relaxed);
        self.mark.busy.store(false, Ordering::Relaxed);
    }
}

/// A response body that keeps its connection busy ([`Answering`]) until it is sent or dropped.
struct Tracked {
    inner: axum::body::Body,
    _answering: Option<Answering>,
}

impl hyper::body::Body for Tracked {
    type Data = axum::body::Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<hyper::body::Frame<Self::Data>, Self::Error>>> {
        Pin::new(&mut self.inner).poll_frame(cx)
    }
    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }
    fn size_hint(&self) -> hyper::body::SizeHint {
        self.inner.size_hint()
    }
}

/// A connection's socket, noting since when a write has been waiting on a client that does not read (milliseconds
/// since `epoch`, plus one; 0 while none waits).
struct Watched<T> {
    inner: T,
    epoch: Instant,
    waiting_since: Arc<AtomicU64>,
}

impl<T> Watched<T> {
    fn note<R>(&self, poll: &Poll<std::io::Result<R>>) {
        match poll {
            Poll::Pending => {
                let now = millis_since(self.epoch) + 1;
                let _ = self.waiting_since.compare_exchange(0, now, Ordering::Relaxed, Ordering::Relaxed);
            }
            Poll::Ready(_) => self.waiting_since.store(0, Ordering::Relaxed),
        }
    }
}

impl<T: AsyncRead + Unpin> AsyncRead for Watched<T> {
    fn poll_read(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_read(cx, buf)
    }
}

impl<T: AsyncWrite + Unpin> AsyncWrite for Watched<T> {
    fn poll_write(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<std::io::Result<usize>> {
        let p = Pin::new(&mut self.inner).poll_write(cx, buf);
        self.note(&p);
        p
    }
    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        let p = Pin::new(&mut self.inner).poll_write_vectored(cx, bufs);
        self.note(&p);
        p
    }
    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }
    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }
    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

/// Milliseconds since `epoch` (the accept loop's), at most `u64::MAX - 1` so that one more fits.
fn millis_since(epoch: Instant) -> u64 {
    u64::try_from(epoch.elapsed().as_millis()).unwrap_or(u64::MAX - 1).min(u64::MAX - 1)
}

/// Resolves once a write has waited `limit` on a client that does not read.
async fn stalled(waiting_since: Arc<AtomicU64>, epoch: Instant, limit: Duration) {
    let limit_ms = u64::try_from(limit.as_millis()).unwrap_or(u64::MAX);
    loop {
        tokio::time::sleep((limit / 4).max(Duration::from_millis(50))).await;
        let since = waiting_since.load(Ordering::Relaxed);
        let now = millis_since(epoch) + 1;
        if since != 0 && now.saturating_sub(since) >= limit_ms {
            return;
        }
    }
}

/// A connection slot: one of `max_connections`, or one of the reserve.
struct Slot {
    _permit: OwnedSemaphorePermit,
    reserved: bool,
}

/// File descriptors kept free of HTTP for the poll loops (a Modbus connection each), recordings and the rest.
pub const FD_RESERVE: u64 = 256;

/// Raises the soft open-file limit to the hard one (Linux) and returns the soft limit now in force.
pub fn raise_open_file_limit() -> Option<u64> {
    #[cfg(target_os = "linux")]
    {
        use rustix::process::{Resource, Rlimit, getrlimit, setrlimit};
        let limit = getrlimit(Resource::Nofile);
        if limit.current < limit.maximum {
            let raised = Rlimit { current: limit.maximum, maximum: limit.maximum };
            if let Err(e) = setrlimit(Resource::Nofile, raised) {
                tracing::warn!(error = %e, "cannot raise the open-file limit");
            }
        }
        getrlimit(Resource::Nofile).current
    }
    #[cfg(not(target_os = "linux"))]
    {
        None
    }
}

/// Serves the router on `listener` within `limits` until `state.shutdown` fires; then lets the open connections
/// finish (bounded) and returns.
pub async fn serve_with(listener: tokio::net::TcpListener, state: AppState, limits: ConnLimits) -> std::io::Result<()> {
    let shutdown = state.shutdown.clone();
    let max = connection_budget(limits.max_connections);
    let per_client = limits.max_connections_per_client.clamp(1, max);
    let metrics = state.metrics.clone();
    let app = router(state)
        .layer(axum::middleware::from_fn_with_state(metrics.clone(), reserve_gate))
        .layer(tower_http::timeout::TimeoutLayer::with_status_code(StatusCode::REQUEST_TIMEOUT, limits.request_timeout))
        .layer(axum::middleware::map_response(json_error_body));
    let open_slots = Arc::new(Semaphore::new(max));
    let reserve = Arc::new(Semaphore::new(RESERVED_CONNECTIONS));
    let clients = Arc::new(PerClient::default());
    let epoch = Instant::now();
    let mut last_accept_error: Option<Instant> = None;
    loop {
        // accepted first, then given a slot: with every slot held, a connection held half-sent or kept alive
        // between requests makes room for it ([`PerClient::evict_oldest_idle`]); else it waits for a slot or the
        // reserve (one connection waits here, the rest in the kernel's backlog)
        let (stream, peer) = tokio::select! {
            biased;
            () = shutdown.cancelled() => break,
            r = listener.accept() => match r {
                Ok(x) => x,
                Err(e) => {
                    // out of file descriptors, say: log once a minute, back off, never spin
                    if last_accept_error.is_none_or(|t| t.elapsed() >= Duration::from_secs(60)) {
                        tracing::error!(error = %e, "http accept failed");
                        last_accept_error = Some(Instant::now());
                    }
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    continue;
                }
            },
        };
        let slot = match open_slots.clone().try_acquire_owned() {
            Ok(p) => Slot { _permit: p, reserved: false },
            Err(_) => {
                // (counted `evicted` by the connection closed)
                let evicted = clients.evict_oldest_idle();
                tokio::select! {
                    biased;
                    () = shutdown.cancelled() => break,
                    p = open_slots.clone().acquire_owned() => match p {
                        Ok(p) => Slot { _permit: p, reserved: false },
                        Err(_) => break,
                    },
                    // the evicted connection's slot is the one to wait for, not the reserve
                    p = reserve.clone().acquire_owned(), if !evicted => match p {
                        Ok(p) => Slot { _permit: p, reserved: true },
                        Err(_) => break,
                    },
                }
            }
        };
        let Some((slot, client)) = admit(slot, &clients, peer.ip(), per_client, &reserve) else {
            metrics.refused.get_or_create(&ReasonLabel { reason: "per_client" }).inc();
            continue; // the stream closes here
        };
        let _ = stream.set_nodelay(true);
        // what a client that stops reading can hold of the kernel's memory (it doubles this), and how soon its
        // writes stall: the kernel's own sizing took 4 MB a connection, and a stream nobody read took minutes to
        // fill it and be closed
        #[cfg(target_os = "linux")]
        let _ = rustix::net::sockopt::set_socket_send_buffer_size(&stream, WRITE_BUFFER_BYTES);
        let connection = Connection { peer, epoch, limits, metrics: metrics.clone(), stop: shutdown.clone() };
        tokio::spawn(connection.serve(stream, app.clone(), slot, client));
    }
    drop(listener);
    // the connections finish (event streams end on shutdown); bounded
    let wait = async {
        let _ = open_slots.acquire_many(u32::try_from(max).unwrap_or(u32::MAX)).await;
        let _ = reserve.acquire_many(RESERVED_CONNECTIONS as u32).await;
    };
    let _ = tokio::time::timeout(Duration::from_secs(6), wait).await;
    Ok(())
}

/// An error answered with no body (a method the route does not take: 405; a request past `request_timeout`: 408)
/// gets the JSON every other error has, `{"error": …}`, naming the status: a client reads one shape of error.
async fn json_error_body(response: Response) -> Response {
    use axum::body::HttpBody;
    let status = response.status();
    if !(status.is_client_error() || status.is_server_error()) || response.body().size_hint().exact() != Some(0) {
        return response;
    }
    let message = match status {
        StatusCode::METHOD_NOT_ALLOWED => "this route does not take that method".to_string(),
        StatusCode::REQUEST_TIMEOUT => "the request was not complete within http.request_timeout_ms".to_string(),
        s => s.canonical_reason().unwrap_or("error").to_lowercase(),
    };
    let (mut parts, _) = response.into_parts();
    parts.headers.insert(header::CONTENT_TYPE, HeaderValue::from_static("application/json"));
    parts.headers.remove(header::CONTENT_LENGTH);
    let body = serde_json::json!({ "error": message }).to_string();
    Response::from_parts(parts, axum::body::Body::from(body))
}

/// The connections served at once: `configured`, or fewer where the open-file limit (raised as far as allowed)
/// leaves room for fewer beside the reserve and the service's own files (logged).
fn connection_budget(configured: usize) -> usize {
    let mut max = configured.max(1);
    if let Some(fds) = raise_open_file_limit() {
        let room = usize::try_from(fds.saturating_sub(FD_RESERVE)).unwrap_or(usize::MAX).max(1);
        let room = room.saturating_sub(RESERVED_CONNECTIONS).max(1);
        if room < max {
            tracing::warn!(
                max_connections = max,
                open_file_limit = fds,
                "fewer HTTP connections than configured: \
                the open-file limit leaves room for {room}"
            );
            max = room;
        }
    }
    max
}

/// An address's share counts its ordinary connections; beyond it, its oldest connection that never carried a
/// request is closed for the new one, else the reserve or nothing (None: refused).
fn admit(
    slot: Slot,
    clients: &Arc<PerClient>,
    ip: IpAddr,
    per_client: usize,
    reserve: &Arc<Semaphore>,
) -> Option<(Slot, Option<ClientGuard>)> {
    if slot.reserved {
        return Some((slot, None));
    }
    match clients.enter(ip) {
        (count, client) if count <= per_client || clients.evict_idle(&client) => Some((slot, Some(client))),
        _ => {
            drop(slot);
            reserve.clone().try_acquire_owned().ok().map(|p| (Slot { _permit: p, reserved: true }, None))
        }
    }
}

/// One accepted connection's settings.
struct Connection {
    peer: SocketAddr,
    epoch: Instant,
    limits: ConnLimits,
    metrics: HttpMetrics,
    stop: tokio_util::sync::CancellationToken,
}

impl Connection {
    /// Serves HTTP/1 on `stream` until the client closes, stops reading (stalled), or the service shuts down
    /// (gracefully, 5 s at most); the slot and the client's count are given back at the end. A connection on the
    /// reserve gets a shorter header timeout and no keep-alive.
    async fn serve(self, stream: tokio::net::TcpStream, app: axum::Router, slot: Slot, client: Option<ClientGuard>) {
        let Connection { peer, epoch, limits, metrics, stop } = self;
        let reserved = slot.reserved;
        metrics.connections.inc();
        let waiting_since = Arc::new(AtomicU64::new(0));
        let io = Watched { inner: stream, epoch, waiting_since: waiting_since.clone() };
        let mark = client.as_ref().map(|c| c.mark.clone());
        let served = mark.clone();
        let service = hyper::service::service_fn(move |mut req: hyper::Request<hyper::body::Incoming>| {
            let answering = served.clone().map(|m| {
                m.served.store(true, Ordering::Relaxed);
                m.busy.store(true, Ordering::Relaxed);
                Answering { mark: m, epoch }
            });
            req.extensions_mut().insert(ConnectInfo::<SocketAddr>(peer));
            if reserved {
                req.extensions_mut().insert(Reserved);
            }
            let response = app.clone().oneshot(req);
            async move {
                let response = response.await?;
                Ok::<_, std::convert::Infallible>(response.map(|inner| Tracked { inner, _answering: answering }))
            }
        });
        let mut builder = hyper::server::conn::http1::Builder::new();
        let header_timeout =
            if reserved { limits.header_timeout.min(RESERVED_HEADER_TIMEOUT) } else { limits.header_timeout };
        builder
            .timer(TokioTimer::new())
            .header_read_timeout(header_timeout)
            .keep_alive(!reserved)
            .max_buf_size(WRITE_BUFFER_BYTES);
        let conn = builder.serve_connection(TokioIo::new(io), service).with_upgrades();
        tokio::pin!(conn);
        tokio::select! {
            _ = conn.as_mut() => {}
            () = async {
                match &mark {
                    Some(m) => m.close.cancelled().await,
                    None => std::future::pending().await,
                }
            } => {
                metrics.refused.get_or_create(&ReasonLabel { reason: "evicted" }).inc();
                tracing::debug!(client = %peer, "closed a connection that never sent a request, for a newer one");
            }
            () = stalled(waiting_since, epoch, limits.header_timeout) => {
                metrics.refused.get_or_create(&ReasonLabel { reason: "stalled" }).inc();
                tracing::debug!(client = %peer, "closed a connection whose client stopped reading");
            }
            () = stop.cancelled() => {
                conn.as_mut().graceful_shutdown();
                let _ = tokio::time::timeout(Duration::from_secs(5), conn).await;
            }
        }
        metrics.connections.dec();
        drop(client);
        drop(slot);
    }
}

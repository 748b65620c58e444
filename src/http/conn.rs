//! The HTTP accept loop, with bounds a hostile client cannot stretch: at most `max_connections` connections at
//! once (the rest wait in the kernel's backlog, holding none of our file descriptors), request headers within
//! `header_timeout` (hyper's timer also runs while a kept-alive connection waits for its next request, so an idle
//! connection is closed as soon), and a whole request, body included, answered within `request_timeout`.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use axum::extract::ConnectInfo;
use axum::http::StatusCode;
use hyper_util::rt::{TokioIo, TokioTimer};
use tokio::sync::Semaphore;
use tower::ServiceExt;

use super::{AppState, router};

/// The bounds of [`serve_with`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ConnLimits {
    pub header_timeout: Duration,
    pub request_timeout: Duration,
    pub max_connections: usize,
}

impl From<&crate::service::config::HttpSettings> for ConnLimits {
    fn from(h: &crate::service::config::HttpSettings) -> ConnLimits {
        ConnLimits {
            header_timeout: h.header_timeout,
            request_timeout: h.request_timeout,
            max_connections: h.max_connections,
        }
    }
}

impl Default for ConnLimits {
    /// 10 s for headers and for a whole request (well inside the 30 s an idle or half-sent request may live),
    /// 512 connections (the dashboard's SSE streams each hold one).
    fn default() -> ConnLimits {
        ConnLimits {
            header_timeout: Duration::from_secs(10),
            request_timeout: Duration::from_secs(10),
            max_connections: 512,
        }
    }
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
    let mut max = limits.max_connections.max(1);
    if let Some(fds) = raise_open_file_limit() {
        let room = usize::try_from(fds.saturating_sub(FD_RESERVE)).unwrap_or(usize::MAX).max(1);
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
    let metrics = state.service.metrics.clone();
    let app = router(state).layer(tower_http::timeout::TimeoutLayer::with_status_code(
        StatusCode::REQUEST_TIMEOUT,
        limits.request_timeout,
    ));
    let slots = Arc::new(Semaphore::new(max));
    let mut last_accept_error: Option<std::time::Instant> = None;
    loop {
        let permit = tokio::select! {
            p = slots.clone().acquire_owned() => match p { Ok(p) => p, Err(_) => break },
            () = shutdown.cancelled() => break,
        };
        let (stream, peer) = tokio::select! {
            r = listener.accept() => match r {
                Ok(x) => x,
                Err(e) => {
                    // out of file descriptors, say: log once a minute, back off, never spin
                    if last_accept_error.is_none_or(|t| t.elapsed() >= Duration::from_secs(60)) {
                        tracing::error!(error = %e, "http accept failed");
                        last_accept_error = Some(std::time::Instant::now());
                    }
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    continue;
                }
            },
            () = shutdown.cancelled() => break,
        };
        let _ = stream.set_nodelay(true);
        let app = app.clone();
        let stop = shutdown.clone();
        let open = metrics.http_connections.clone();
        tokio::spawn(async move {
            open.inc();
            let service = hyper::service::service_fn(move |mut req: hyper::Request<hyper::body::Incoming>| {
                req.extensions_mut().insert(ConnectInfo::<SocketAddr>(peer));
                app.clone().oneshot(req)
            });
            let mut builder = hyper::server::conn::http1::Builder::new();
            builder.timer(TokioTimer::new()).header_read_timeout(limits.header_timeout);
            let conn = builder.serve_connection(TokioIo::new(stream), service).with_upgrades();
            tokio::pin!(conn);
            tokio::select! {
                _ = conn.as_mut() => {}
                () = stop.cancelled() => {
                    conn.as_mut().graceful_shutdown();
                    let _ = tokio::time::timeout(Duration::from_secs(5), conn).await;
                }
            }
            open.dec();
            drop(permit);
        });
    }
    drop(listener);
    // the connections finish (event streams end on shutdown); bounded
    let all = u32::try_from(max).unwrap_or(u32::MAX);
    let _ = tokio::time::timeout(Duration::from_secs(6), slots.acquire_many(all)).await;
    Ok(())
}

//! `[http]`: the listener, the write token and the connection limits, parsed raw and validated (a room of the
//! service config, [`super`]).

use super::*;

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub(super) struct RawHttp {
    bind: String,
    token: String,
    max_body_bytes: usize,
    history_seconds: f64,
    /// A request's headers must arrive within this (also how long an idle kept-alive connection lives).
    header_timeout_ms: u64,
    /// A whole request, body included, must be answered within this.
    request_timeout_ms: u64,
    /// Open HTTP connections at most; further clients wait in the kernel's backlog.
    max_connections: usize,
    /// Open connections from one client address at most; beyond, only the reserved routes are served.
    max_connections_per_client: usize,
    /// Open `/api/events` streams at most; beyond, 503 at once.
    max_event_streams: usize,
}

impl Default for RawHttp {
    fn default() -> Self {
        RawHttp {
            bind: "127.0.0.1:8080".into(),
            token: String::new(),
            max_body_bytes: 4096,
            history_seconds: 120.0,
            header_timeout_ms: 10_000,
            request_timeout_ms: 10_000,
            max_connections: 512,
            max_connections_per_client: 128,
            max_event_streams: 64,
        }
    }
}

#[derive(Debug, Clone)]
pub struct HttpSettings {
    pub bind: std::net::SocketAddr,
    /// Bearer token of the write routes; None disables them. Never logged.
    pub token: Option<String>,
    pub max_body_bytes: usize,
    pub history: Duration,
    pub header_timeout: Duration,
    pub request_timeout: Duration,
    pub max_connections: usize,
    pub max_connections_per_client: usize,
    pub max_event_streams: usize,
}

/// `[http]`, validated.
pub(super) fn validate_http(h: RawHttp) -> Result<HttpSettings, Invalid> {
    let bind = h.bind.parse().map_err(|e| {
        KeyError::new("http.bind".to_string(), format!("{:?} is not an address such as 127.0.0.1:8080 ({e})", h.bind))
    })?;
    if h.max_body_bytes == 0 || h.max_body_bytes > 1 << 20 {
        return Err(KeyError::new(
            "http.max_body_bytes".into(),
            format!("must be 1 ..= 1048576, got {}", h.max_body_bytes),
        ));
    }
    let history_s = positive("http.history_seconds", h.history_seconds)?;
    if history_s > 3600.0 {
        return Err(KeyError::new("http.history_seconds".into(), format!("must be ≤ 3600, got {history_s}")));
    }
    // a client sends `Authorization: Bearer <token>` as one visible ASCII word: a token with a space, a line end or
    // a non-ASCII letter never matched, and the write routes could never be used
    if let Some(c) = h.token.chars().find(|c| !c.is_ascii_graphic()) {
        return Err(KeyError::new(
            "http.token".into(),
            format!("must be visible ASCII without spaces (no client can send {c:?} in a Bearer token)"),
        ));
    }
    let token = (!h.token.is_empty()).then_some(h.token);
    // an idle or half-sent request must be gone within 30 s (issue 20)
    for (k, ms) in [("http.header_timeout_ms", h.header_timeout_ms), ("http.request_timeout_ms", h.request_timeout_ms)]
    {
        if !(1..=30_000).contains(&ms) {
            return Err(KeyError::new(k.into(), format!("must be 1 ..= 30000, got {ms}")));
        }
    }
    if !(1..=65_536).contains(&h.max_connections) {
        return Err(KeyError::new(
            "http.max_connections".into(),
            format!("must be 1 ..= 65536, got {}", h.max_connections),
        ));
    }
    for (k, n) in [
        ("http.max_connections_per_client", h.max_connections_per_client),
        ("http.max_event_streams", h.max_event_streams),
    ] {
        if !(1..=65_536).contains(&n) {
            return Err(KeyError::new(k.into(), format!("must be 1 ..= 65536, got {n}")));
        }
    }
    Ok(HttpSettings {
        bind,
        token,
        max_body_bytes: h.max_body_bytes,
        history: Duration::from_secs_f64(history_s),
        header_timeout: Duration::from_millis(h.header_timeout_ms),
        request_timeout: Duration::from_millis(h.request_timeout_ms),
        max_connections: h.max_connections,
        max_connections_per_client: h.max_connections_per_client,
        max_event_streams: h.max_event_streams,
    })
}

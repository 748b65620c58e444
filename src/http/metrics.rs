//! The HTTP side's own families (no drive label): open connections and event streams, wrong tokens, and what was
//! turned away to keep capacity. Registered in the service's registry by whoever makes the router's state
//! ([`HttpMetrics::register`], then [`super::AppState::new`]; `server::start` does), and counted by the connection
//! layer and the routes.

use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::registry::Registry;

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct ReasonLabel {
    pub reason: &'static str,
}

/// The families; cheap to clone (they are shared).
#[derive(Clone, Debug, Default)]
pub struct HttpMetrics {
    pub connections: Gauge,
    pub auth_failures: Counter,
    pub auth_throttled: Counter,
    /// Open `/api/events` streams, and connections or requests turned away, by reason (event_streams: the cap
    /// was reached; per_client: one address held too many connections and the reserve was full; reserved: a
    /// route other than control and health asked on a reserved connection; stalled: a client stopped reading).
    pub event_streams: Gauge,
    pub refused: Family<ReasonLabel, Counter>,
}

impl HttpMetrics {
    /// The families, registered in `r`.
    pub fn register(r: &mut Registry) -> HttpMetrics {
        let m = HttpMetrics::default();
        r.register("http_connections", "Open HTTP connections", m.connections.clone());
        r.register("http_auth_failures", "Write requests with a wrong Bearer token", m.auth_failures.clone());
        r.register(
            "http_auth_throttled",
            "Write requests refused with 429 after a burst of wrong tokens",
            m.auth_throttled.clone(),
        );
        r.register("http_event_streams", "Open /api/events streams", m.event_streams.clone());
        r.register(
            "http_refused",
            "HTTP connections or requests turned away to keep capacity, by reason",
            m.refused.clone(),
        );
        m
    }
}

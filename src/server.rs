//! The service and its HTTP front put together: what `serve`, `demo` and the tests run, after mini-redis's
//! `server::run(listener, shutdown)`. The caller binds the listener (so a test can take port 0 and a command can
//! name the address in its error) and owns the shutdown signal.

use std::sync::Arc;

use tokio::net::TcpListener;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

use crate::http::{self, AppState, ConnLimits};
use crate::service::config::Settings;
use crate::service::{self, Service, ServiceState};
use crate::{metrics, mqtt};

/// A running service: the poll loops on their threads, the HTTP server on the runtime's workers.
pub struct Server {
    /// What the loops publish and the routes read.
    pub state: Arc<ServiceState>,
    /// `http://<the listener's address>`.
    pub url: String,
    shutdown: CancellationToken,
    service: Service,
    http: JoinHandle<std::io::Result<()>>,
    /// The MQTT publisher's thread, when `[mqtt]` is configured.
    mqtt: Option<std::thread::JoinHandle<()>>,
}

/// A token shorter than this is warned of at start (16 random characters of 62 are 95 bits).
pub const MIN_TOKEN_CHARS: usize = 16;

/// Starts the poll loops of `settings` and serves HTTP on `listener` until `shutdown` is cancelled.
pub fn start(listener: TcpListener, settings: &Settings, shutdown: CancellationToken) -> std::io::Result<Server> {
    let addr = listener.local_addr()?;
    let url = format!("http://{addr}");
    warn_of_token(settings.http.token.as_deref(), addr.ip().is_loopback());
    let service = service::start(settings, shutdown.clone())?;
    metrics::register(&service.state);
    let (mqtt_health, mqtt) = match &settings.mqtt {
        Some(m) => match mqtt::start(m, &service.state, shutdown.clone()) {
            Ok((health, thread)) => (Some(health), Some(thread)),
            Err(e) => {
                // the loops already started must not outlive a failed start
                shutdown.cancel();
                service.join();
                return Err(e);
            }
        },
        None => (None, None),
    };
    let http_metrics = http::HttpMetrics::register(&mut service.state.registry());
    let state = AppState::new(service.state.clone(), &settings.http, http_metrics, shutdown.clone())
        .with_mqtt(mqtt_health)
        .listening_on(addr);
    let limits = ConnLimits::from(&settings.http);
    // on the runtime's (lower-priority) workers, not on the thread that started the poll loops
    let http = tokio::spawn(http::serve_with(listener, state, limits));
    Ok(Server { state: service.state.clone(), url, shutdown, service, http, mqtt })
}

/// Says at start what the token leaves open: a short one is warned of (louder beyond loopback, where anyone on
/// the network may guess), and beyond loopback no token is said to disable the write routes.
fn warn_of_token(token: Option<&str>, loopback: bool) {
    let reach = if loopback { "loopback" } else { "beyond loopback" };
    match token {
        Some(t) if t.chars().count() < MIN_TOKEN_CHARS => tracing::warn!(
            chars = t.chars().count(),
            bound = reach,
            "http.token is short: a right token is never refused, so its length is what keeps a guesser out; use \
             {MIN_TOKEN_CHARS} random characters or more"
        ),
        None if !loopback => {
            tracing::info!(bound = reach, "http.token is empty: the write routes are disabled (read-only service)");
        }
        _ => {}
    }
}

impl Server {
    /// Waits until the HTTP server has stopped (a cancelled `shutdown`, or its own failure, which stops the loops
    /// too) and every loop has closed its recording.
    pub async fn wait(self) -> std::io::Result<()> {
        let served = self.http.await;
        self.shutdown.cancel();
        self.service.wait().await;
        if let Some(thread) = self.mqtt
            && tokio::task::spawn_blocking(move || thread.join()).await.is_err()
        {
            tracing::error!("waiting for the MQTT publisher failed");
        }
        served.map_err(std::io::Error::other)?
    }
}

impl Server {
    /// Cancels the shutdown signal the server was started with, then [`Server::wait`]s.
    pub async fn stop(self) -> std::io::Result<()> {
        self.shutdown.cancel();
        self.wait().await
    }
}

/// [`start`], then [`Server::wait`].
pub async fn run(listener: TcpListener, settings: &Settings, shutdown: CancellationToken) -> std::io::Result<()> {
    start(listener, settings, shutdown)?.wait().await
}

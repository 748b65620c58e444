//! An RTU line shared by several drives: one bus task owns the port (or the gateway's TCP connection) and serves
//! the drives' requests one at a time, in the order they come, each with its drive's unit id. RTU has no
//! transaction ids, so only one request may be on the line at once.
//!
//! The bus task runs the same [`DriveClient`] a drive with a connection of its own uses (timeouts, reconnects,
//! the inter-frame gap). What differs is who waits after a failure: a device that does not answer, or answers
//! garbage, is held back on its own (the same capped doubling back-off), and the port is reopened at once for the
//! others; a port that fails (unplugged, gone) backs off for every drive on it.

use std::collections::HashMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Duration;

use tokio::sync::{mpsc, oneshot};
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;

use super::client::{BACKOFF_CAP, BACKOFF_START, ClientError, DriveClient, Endpoint};
use super::map::Table;

/// How long a line still carries its drives' last requests after shutdown (their stop): a drive waits at most
/// `service::drive::STOP_TIMEOUT` (1 s) for its own.
pub const SHUTDOWN_DRAIN: Duration = Duration::from_secs(2);

/// A drive's way to its device: a connection of its own (Modbus TCP), or its turn on a shared RTU line.
pub enum Connection {
    Own(DriveClient),
    Line(LineHandle),
}

impl Connection {
    pub async fn read(&mut self, table: Table, start: u16, count: u16) -> Result<Vec<u16>, ClientError> {
        match self {
            Connection::Own(c) => c.read(table, start, count).await,
            Connection::Line(l) => l.read(table, start, count).await,
        }
    }

    pub async fn write(&mut self, start: u16, words: &[u16]) -> Result<(), ClientError> {
        match self {
            Connection::Own(c) => c.write(start, words).await,
            Connection::Line(l) => l.write(start, words).await,
        }
    }

    /// A poll came back whole and valid: the next failure starts the back-off afresh.
    pub fn good_poll(&mut self) {
        match self {
            Connection::Own(c) => c.good_poll(),
            Connection::Line(l) => l.good_poll(),
        }
    }

    /// True while the connection (or the line's port) is open.
    pub fn is_connected(&self) -> bool {
        match self {
            Connection::Own(c) => c.is_connected(),
            Connection::Line(l) => l.status.connected.load(Ordering::Relaxed),
        }
    }

    /// Connections opened after the first (on a shared line: the line's).
    pub fn reconnects(&self) -> u64 {
        match self {
            Connection::Own(c) => c.reconnects,
            Connection::Line(l) => l.status.reconnects.load(Ordering::Relaxed),
        }
    }

    /// Closes a connection of its own; a shared line is closed by its bus task.
    pub async fn close(&mut self) {
        if let Connection::Own(c) = self {
            c.close().await;
        }
    }
}

/// The line's state as the drives on it see it.
#[derive(Debug, Default)]
struct LineStatus {
    connected: AtomicBool,
    reconnects: AtomicU64,
}

enum Op {
    Read { table: Table, start: u16, count: u16, reply: oneshot::Sender<Result<Vec<u16>, ClientError>> },
    Write { start: u16, words: Vec<u16>, reply: oneshot::Sender<Result<(), ClientError>> },
    GoodPoll,
}

struct Call {
    unit_id: u8,
    timeout: Duration,
    op: Op,
}

/// One drive's side of a shared line.
pub struct LineHandle {
    unit_id: u8,
    timeout: Duration,
    tx: mpsc::Sender<Call>,
    status: Arc<LineStatus>,
}

fn bus_stopped() -> ClientError {
    ClientError::Transport(std::io::Error::new(std::io::ErrorKind::BrokenPipe, "the line's bus task has stopped"))
}

impl LineHandle {
    async fn call<T>(
        &self,
        make: impl FnOnce(oneshot::Sender<Result<T, ClientError>>) -> Op,
    ) -> Result<T, ClientError> {
        let (reply, answer) = oneshot::channel();
        let call = Call { unit_id: self.unit_id, timeout: self.timeout, op: make(reply) };
        self.tx.send(call).await.map_err(|_| bus_stopped())?;
        answer.await.map_err(|_| bus_stopped())?
    }

    async fn read(&self, table: Table, start: u16, count: u16) -> Result<Vec<u16>, ClientError> {
        self.call(|reply| Op::Read { table, start, count, reply }).await
    }

    async fn write(&self, start: u16, words: &[u16]) -> Result<(), ClientError> {
        let words = words.to_vec();
        self.call(|reply| Op::Write { start, words, reply }).await
    }

    fn good_poll(&self) {
        // best effort: a full queue means the bus is busy, and the next good poll says it again
        let _ = self.tx.try_send(Call { unit_id: self.unit_id, timeout: self.timeout, op: Op::GoodPoll });
    }
}

/// A device held back after it failed.
#[derive(Debug, Clone, Copy)]
struct Held {
    until: Instant,
    backoff: Duration,
}

/// The task that owns a shared line.
pub struct Bus {
    client: DriveClient,
    rx: mpsc::Receiver<Call>,
    tx: mpsc::Sender<Call>,
    status: Arc<LineStatus>,
    held: HashMap<u8, Held>,
}

impl Bus {
    /// A bus on `endpoint` (RTU on a serial port, or RTU over TCP); it opens the line on the first request.
    pub fn new(endpoint: Endpoint, drives: usize) -> Bus {
        // each drive has at most one request and one good-poll note waiting
        let (tx, rx) = mpsc::channel(2 * drives.max(1));
        Bus {
            client: DriveClient::on(endpoint, 0, Duration::from_millis(200)),
            rx,
            tx,
            status: Arc::default(),
            held: HashMap::new(),
        }
    }

    /// The line's endpoint.
    pub fn endpoint(&self) -> &Endpoint {
        self.client.endpoint()
    }

    /// A drive's handle: its requests go to `unit_id`, each under `timeout`.
    pub fn handle(&self, unit_id: u8, timeout: Duration) -> Connection {
        Connection::Line(LineHandle { unit_id, timeout, tx: self.tx.clone(), status: self.status.clone() })
    }

    /// Serves requests until `shutdown` (or until every handle is gone), then closes the line.
    pub async fn run(mut self, shutdown: CancellationToken) {
        // only the handles keep the channel open from here
        let (closed, _) = mpsc::channel(1);
        drop(std::mem::replace(&mut self.tx, closed));
        // after shutdown the line still carries what its drives send on their way out (the stop of a writing
        // drive), for a short while or until every handle is gone
        let mut drain_until = None;
        loop {
            let call = match drain_until {
                Some(until) => match tokio::time::timeout_at(until, self.rx.recv()).await {
                    Ok(Some(c)) => c,
                    _ => break,
                },
                None => tokio::select! {
                    biased;
                    () = shutdown.cancelled() => {
                        drain_until = Some(Instant::now() + SHUTDOWN_DRAIN);
                        continue;
                    }
                    call = self.rx.recv() => match call {
                        Some(c) => c,
                        None => break,
                    },
                },
            };
            self.serve(call).await;
            self.status.connected.store(self.client.is_connected(), Ordering::Relaxed);
            self.status.reconnects.store(self.client.reconnects, Ordering::Relaxed);
        }
        self.client.close().await;
        self.status.connected.store(false, Ordering::Relaxed);
    }

    async fn serve(&mut self, call: Call) {
        let unit = call.unit_id;
        if let Op::GoodPoll = call.op {
            self.held.remove(&unit);
            self.client.good_poll();
            return;
        }
        let waiting = self.held.get(&unit).map(|h| h.until).filter(|&t| Instant::now() < t);
        self.client.set_unit_id(unit);
        self.client.set_call_timeout(call.timeout);
        match call.op {
            Op::Read { table, start, count, reply } => {
                let result = match waiting {
                    Some(t) => Err(ClientError::Backoff(t - Instant::now())),
                    None => self.client.read(table, start, count).await,
                };
                if let Err(e) = &result {
                    self.failed(unit, e);
                }
                let _ = reply.send(result);
            }
            Op::Write { start, words, reply } => {
                let result = match waiting {
                    Some(t) => Err(ClientError::Backoff(t - Instant::now())),
                    None => self.client.write(start, &words).await,
                };
                if let Err(e) = &result {
                    self.failed(unit, e);
                }
                let _ = reply.send(result);
            }
            Op::GoodPoll => {}
        }
    }

    /// Whose fault a failure is: a device's (no answer, garbage) holds that device back and reopens the port for
    /// the others at once; the port's (cannot open, I/O error) keeps the client's back-off for the whole line.
    fn failed(&mut self, unit: u8, e: &ClientError) {
        match e {
            ClientError::Timeout(_) | ClientError::Protocol(_) | ClientError::WrongLength { .. } => {
                let backoff = self.held.get(&unit).map_or(BACKOFF_START, |h| (h.backoff * 2).min(BACKOFF_CAP));
                self.held.insert(unit, Held { until: Instant::now() + backoff, backoff });
                self.client.forgive();
            }
            ClientError::Backoff(_)
            | ClientError::Connect { .. }
            | ClientError::Transport(_)
            | ClientError::Exception(_) => {}
        }
    }
}

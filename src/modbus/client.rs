//! The Modbus client of one drive or one RTU line: every call under a timeout, the connection dropped after any
//! failure and re-opened with capped exponential back-off. The same code speaks Modbus TCP, RTU on a serial port
//! (with the inter-frame gap kept between requests) and RTU framing over TCP (serial gateways).
//!
//! tokio-modbus has no timeout of its own (upstream issue 113), and a reply that arrives after a timeout is taken
//! as the answer to the next request (issue 324). So after a timeout, a transport error or a protocol error the
//! connection is dropped, never reused. A Modbus exception is a proper answer and keeps the connection.

use std::time::Duration;

use tokio::time::{Instant, timeout};
use tokio_modbus::client::{Client, Context};
use tokio_modbus::{ExceptionCode, Slave};
use tokio_modbus::{Request, Response};

use super::line::{Parity, SerialLine};
use super::map::Table;

/// Where and how a client talks to its device(s).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Endpoint {
    /// Modbus TCP to `host:port`.
    Tcp(String),
    /// RTU framing over a TCP connection to `host:port` (a serial gateway in transparent mode).
    RtuOverTcp(String),
    /// RTU on a serial port.
    Serial { port: String, line: SerialLine },
}

impl Endpoint {
    /// The address or serial port, for logs and errors.
    pub fn name(&self) -> &str {
        match self {
            Endpoint::Tcp(a) | Endpoint::RtuOverTcp(a) => a,
            Endpoint::Serial { port, .. } => port,
        }
    }

    /// Whether two endpoints are one RTU line: the same serial port (whatever the settings), or the same gateway.
    pub fn same_line(&self, other: &Endpoint) -> bool {
        match (self, other) {
            (Endpoint::Serial { port: a, .. }, Endpoint::Serial { port: b, .. }) => a == b,
            (Endpoint::RtuOverTcp(a), Endpoint::RtuOverTcp(b)) => a == b,
            _ => false,
        }
    }
}

/// The first back-off after a failure; it doubles up to [`BACKOFF_CAP`].
pub const BACKOFF_START: Duration = Duration::from_millis(50);
/// The longest wait between reconnect attempts: the client is back within this long of the server's return.
pub const BACKOFF_CAP: Duration = Duration::from_millis(500);

/// Why a call failed. [`ClientError::kind`] names it for metrics.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    #[error("waiting {0:?} before reconnecting")]
    Backoff(Duration),
    #[error("cannot connect to {address}: {message}")]
    Connect { address: String, message: String },
    #[error("no reply within {0:?}")]
    Timeout(Duration),
    #[error("transport: {0}")]
    Transport(std::io::Error),
    #[error("protocol: {0}")]
    Protocol(String),
    #[error("modbus exception: {0}")]
    Exception(ExceptionCode),
    /// A reply with another number of registers than the request asked for (fewer or more).
    #[error("reply has {got} registers, expected {expected}")]
    WrongLength { expected: usize, got: usize },
}

impl ClientError {
    /// Every label [`ClientError::kind`] gives, written once: the poll loop counts each but `backoff` (a wait it
    /// chose, not a failed call) in `errors_total{kind}`.
    pub const KINDS: [&'static str; 6] = ["backoff", "connect", "timeout", "transport", "protocol", "exception"];

    /// A short label for the `errors_total{kind}` metric, one of [`ClientError::KINDS`].
    pub fn kind(&self) -> &'static str {
        Self::KINDS[match self {
            ClientError::Backoff(_) => 0,
            ClientError::Connect { .. } => 1,
            ClientError::Timeout(_) => 2,
            ClientError::Transport(_) => 3,
            ClientError::Protocol(_) | ClientError::WrongLength { .. } => 4,
            ClientError::Exception(_) => 5,
        }]
    }
}

/// One drive's connection, or one RTU line's (then [`DriveClient::set_unit_id`] picks the device of each call).
pub struct DriveClient {
    endpoint: Endpoint,
    /// The shortest silence between two frames on a serial line (none on TCP).
    gap: Option<Duration>,
    /// When the last exchange on the line ended: the next request waits out the gap from here.
    line_quiet_since: Option<Instant>,
    unit_id: u8,
    call_timeout: Duration,
    ctx: Option<Context>,
    backoff: Duration,
    next_attempt: Option<Instant>,
    /// Connections opened after the first, for the `reconnects_total` metric.
    pub reconnects: u64,
    ever_connected: bool,
    /// Dropped connections said at WARN, rate-limited: a link that connects and drops every back-off said it twice
    /// a second (7 000 lines an hour).
    loud: Loud,
}

/// How often one kind of failure is logged at WARN at most; the ones between are counted and said with the next.
const WARN_EVERY: Duration = Duration::from_secs(10);

/// Rate-limited warnings (the client's, and the poll loops' of what a device says back): per kind, when it was last
/// said and how many were held back since.
#[derive(Debug, Default)]
pub struct Loud(Vec<(&'static str, Instant, u64)>);

impl Loud {
    /// Some(the number held back since the last) when `kind` may be said now; None (and counted) otherwise.
    pub fn allow(&mut self, kind: &'static str, now: Instant) -> Option<u64> {
        match self.0.iter_mut().find(|e| e.0 == kind) {
            Some(e) if now.saturating_duration_since(e.1) < WARN_EVERY => {
                e.2 += 1;
                None
            }
            Some(e) => {
                let held = e.2;
                (e.1, e.2) = (now, 0);
                Some(held)
            }
            None => {
                self.0.push((kind, now, 0));
                Some(0)
            }
        }
    }
}

impl DriveClient {
    /// A Modbus TCP client that connects on first use. `address` is `host:port`; the host is resolved at each
    /// connect.
    pub fn new(address: &str, unit_id: u8, call_timeout: Duration) -> DriveClient {
        DriveClient::on(Endpoint::Tcp(address.to_string()), unit_id, call_timeout)
    }

    /// A client of any endpoint, connecting on first use.
    pub fn on(endpoint: Endpoint, unit_id: u8, call_timeout: Duration) -> DriveClient {
        let gap = match &endpoint {
            Endpoint::Serial { line, .. } => Some(line.inter_frame_gap()),
            _ => None,
        };
        DriveClient {
            endpoint,
            gap,
            line_quiet_since: None,
            unit_id,
            call_timeout,
            ctx: None,
            backoff: BACKOFF_START,
            next_attempt: None,
            reconnects: 0,
            ever_connected: false,
            loud: Loud::default(),
        }
    }

    /// True while a connection is open.
    pub fn is_connected(&self) -> bool {
        self.ctx.is_some()
    }

    /// The device the next calls go to (on a shared RTU line, set before each call).
    pub fn set_unit_id(&mut self, unit_id: u8) {
        self.unit_id = unit_id;
        if let Some(ctx) = self.ctx.as_mut() {
            tokio_modbus::slave::SlaveContext::set_slave(ctx, Slave(unit_id));
        }
    }

    /// The timeout of the next calls (drives on a shared line may each have their own).
    pub fn set_call_timeout(&mut self, call_timeout: Duration) {
        self.call_timeout = call_timeout;
    }

    /// Forgets the back-off of the last failure: the next call reconnects at once. For a shared RTU line, where
    /// the device that failed is kept back on its own and the others must not wait for it.
    pub fn forgive(&mut self) {
        self.next_attempt = None;
        self.backoff = BACKOFF_START;
    }

    async fn connect(&mut self) -> Result<(), ClientError> {
        if let Some(at) = self.next_attempt
            && Instant::now() < at
        {
            return Err(ClientError::Backoff(at - Instant::now()));
        }
        let endpoint = self.endpoint.clone();
        let slave = Slave(self.unit_id);
        let attempt = async move {
            match endpoint {
                Endpoint::Tcp(address) => {
                    let mut last = None;
                    for addr in tokio::net::lookup_host(address.as_str()).await? {
                        match tokio_modbus::client::tcp::connect_slave(addr, slave).await {
                            Ok(ctx) => return Ok(ctx),
                            Err(e) => last = Some(e),
                        }
                    }
                    Err(last.unwrap_or_else(|| std::io::Error::other("the name resolves to no address")))
                }
                Endpoint::RtuOverTcp(address) => {
                    let stream = tokio::net::TcpStream::connect(address.as_str()).await?;
                    stream.set_nodelay(true)?;
                    Ok(tokio_modbus::client::rtu::attach_slave(stream, slave))
                }
                Endpoint::Serial { port, line } => {
                    let port = open_serial(&port, &line)?;
                    // bytes already waiting (a late reply to the request that timed out, which dropped the last
                    // connection) are not the answer to the next request
                    tokio_serial::SerialPort::clear(&port, tokio_serial::ClearBuffer::Input)?;
                    Ok(tokio_modbus::client::rtu::attach_slave(port, slave))
                }
            }
        };
        match timeout(self.call_timeout, attempt).await {
            Ok(Ok(ctx)) => {
                if self.ever_connected {
                    self.reconnects += 1;
                }
                self.ever_connected = true;
                self.ctx = Some(ctx);
                // the back-off stays: a device that accepts and then answers garbage must not be reconnected
                // to at full rate; [`DriveClient::good_poll`] resets it
                self.next_attempt = None;
                // at most every WARN_EVERY at INFO (the rest at debug): a line of noise, or a neighbour answering
                // late, reopened the port 10 times a second
                match self.loud.allow("connected", Instant::now()) {
                    Some(more_since_last) => tracing::info!(address = %self.endpoint.name(), unit_id = self.unit_id,
                        more_since_last, "modbus connected"),
                    None => tracing::debug!(address = %self.endpoint.name(), unit_id = self.unit_id,
                        "modbus connected"),
                }
                Ok(())
            }
            Ok(Err(e)) => {
                Err(self
                    .failed(ClientError::Connect { address: self.endpoint.name().to_string(), message: e.to_string() }))
            }
            Err(_) => Err(self.failed(ClientError::Connect {
                address: self.endpoint.name().to_string(),
                message: format!("no answer within {:?}", self.call_timeout),
            })),
        }
    }

    /// Drops the connection and schedules the next attempt. A connection that cannot be made is said too (at most
    /// every [`WARN_EVERY`]): a device unreachable from the start showed only in `/api/status` and `/readyz`.
    fn failed(&mut self, err: ClientError) -> ClientError {
        if self.ctx.take().is_some() {
            if let Some(more_since_last) = self.loud.allow("dropped", Instant::now()) {
                tracing::warn!(address = %self.endpoint.name(), error = %err, more_since_last,
                    "modbus connection dropped");
            }
        } else if matches!(err, ClientError::Connect { .. })
            && let Some(more_since_last) = self.loud.allow("connect", Instant::now())
        {
            tracing::warn!(address = %self.endpoint.name(), error = %err, more_since_last,
                "modbus connection cannot be made; retrying");
        }
        self.next_attempt = Some(Instant::now() + self.backoff);
        self.backoff = (self.backoff * 2).min(BACKOFF_CAP);
        err
    }

    /// Runs one request on the open connection (connecting first if needed), under the timeout.
    ///
    /// On an RTU line a late reply must not answer the next request: after anything but a whole reply (a timeout,
    /// a garbled or stray frame), the line is left alone for [`DriveClient::late_reply_grace`] and the port opened
    /// again with its input cleared (the silence before a request is waited out before the port is opened). A reply
    /// from another device that still comes first is not this device's fault either: after the same wait and
    /// clearing, the request goes once more.
    /// Charged to this device, a neighbour answering 15 ms past its timeout gave a healthy drive one protocol error
    /// for each of its own, and a write gap of 0.72 s (a hostile tester's line).
    async fn call<T, F>(&mut self, f: F) -> Result<T, ClientError>
    where
        F: for<'a> Fn(&'a mut Context) -> futures::future::BoxFuture<'a, tokio_modbus::Result<T>>,
    {
        let mut stray_cleared = false;
        let result = loop {
            if let (Some(gap), Some(quiet)) = (self.gap, self.line_quiet_since) {
                // RTU: a frame ends with 3.5 characters of silence; a request sent sooner would run into the last
                // reply
                tokio::time::sleep_until(quiet + gap).await;
            }
            if self.ctx.is_none() {
                self.connect().await?;
            }
            let Some(ctx) = self.ctx.as_mut() else { return Err(ClientError::Backoff(self.backoff)) };
            let result = timeout(self.call_timeout, f(ctx)).await;
            if self.gap.is_some() {
                // anything but a whole reply (a timeout, a garbled or stray frame) may have one still coming
                let grace = if matches!(result, Ok(Ok(_))) { Duration::ZERO } else { self.late_reply_grace() };
                self.line_quiet_since = Some(Instant::now() + grace);
            }
            match &result {
                Ok(Err(tokio_modbus::Error::Protocol(tokio_modbus::ProtocolError::HeaderMismatch {
                    message, ..
                }))) if self.gap.is_some() && !stray_cleared => {
                    tracing::debug!(address = %self.endpoint.name(), unit_id = self.unit_id, message,
                        "a reply from another device on the line: cleared, the request sent again");
                    stray_cleared = true;
                    self.ctx = None;
                    self.next_attempt = None;
                }
                _ => break result,
            }
        };
        match result {
            Ok(Ok(Ok(v))) => Ok(v),
            Ok(Ok(Err(code))) => Err(ClientError::Exception(code)),
            Ok(Err(tokio_modbus::Error::Transport(e))) => Err(self.failed(ClientError::Transport(e))),
            Ok(Err(tokio_modbus::Error::Protocol(e))) => Err(self.failed(ClientError::Protocol(e.to_string()))),
            Err(_) => Err(self.failed(ClientError::Timeout(self.call_timeout))),
        }
    }

    /// How long an RTU line is left alone after a request timed out, or a stray reply came, before the port is
    /// cleared for the next request: half the call timeout, so that a reply that late is dropped rather than taken
    /// for the next one's.
    fn late_reply_grace(&self) -> Duration {
        self.call_timeout / 2
    }

    /// Reads `count` registers of a table from `start` in one request.
    pub async fn read(&mut self, table: Table, start: u16, count: u16) -> Result<Vec<u16>, ClientError> {
        let request = match table {
            Table::Input => Request::ReadInputRegisters(start, count),
            Table::Holding => Request::ReadHoldingRegisters(start, count),
        };
        let response = self.call(move |ctx| Box::pin(ctx.call(request.clone()))).await?;
        let words = match response {
            Response::ReadInputRegisters(w) | Response::ReadHoldingRegisters(w) => w,
            other => return Err(self.failed(ClientError::Protocol(format!("unexpected reply {other:?}")))),
        };
        // a reply with fewer or more registers than asked is a protocol error, not data
        if words.len() != usize::from(count) {
            let err = ClientError::WrongLength { expected: usize::from(count), got: words.len() };
            return Err(self.failed(err));
        }
        Ok(words)
    }

    /// Writes holding registers from `start` (function 16, or 06 for one word). The device's echo is checked here,
    /// not by tokio-modbus, whose debug assertions would panic the poll thread on a garbled echo.
    pub async fn write(&mut self, start: u16, words: &[u16]) -> Result<(), ClientError> {
        let request = match words {
            [w] => Request::WriteSingleRegister(start, *w),
            _ => Request::WriteMultipleRegisters(start, std::borrow::Cow::Owned(words.to_vec())),
        };
        let response = self.call(move |ctx| Box::pin(ctx.call(request.clone()))).await?;
        let echoed = match response {
            Response::WriteSingleRegister(a, w) => a == start && words == [w],
            Response::WriteMultipleRegisters(a, n) => a == start && usize::from(n) == words.len(),
            _ => false,
        };
        if echoed {
            Ok(())
        } else {
            Err(self.failed(ClientError::Protocol(format!("the write's echo does not match: {response:?}"))))
        }
    }

    /// A poll came back whole and valid: the next failure starts the back-off afresh.
    pub fn good_poll(&mut self) {
        self.backoff = BACKOFF_START;
    }

    /// The endpoint this client talks to.
    pub fn endpoint(&self) -> &Endpoint {
        &self.endpoint
    }

    /// Closes the connection (on shutdown).
    pub async fn close(&mut self) {
        if let Some(mut ctx) = self.ctx.take() {
            let _ = timeout(self.call_timeout, tokio_modbus::client::Client::disconnect(&mut ctx)).await;
        }
    }
}

/// Opens a serial port for RTU: 8 data bits, the line's parity and stop bits, no flow control.
pub fn open_serial(port: &str, line: &SerialLine) -> std::io::Result<tokio_serial::SerialStream> {
    use tokio_serial::SerialPortBuilderExt;
    let parity = match line.parity {
        Parity::None => tokio_serial::Parity::None,
        Parity::Even => tokio_serial::Parity::Even,
        Parity::Odd => tokio_serial::Parity::Odd,
    };
    let stop_bits = if line.stop_bits == 2 { tokio_serial::StopBits::Two } else { tokio_serial::StopBits::One };
    tokio_serial::new(port, line.baud_rate)
        .data_bits(tokio_serial::DataBits::Eight)
        .parity(parity)
        .stop_bits(stop_bits)
        .flow_control(tokio_serial::FlowControl::None)
        .open_native_async()
        .map_err(std::io::Error::from)
}

//! The Modbus TCP client of one drive: every call under a timeout, the connection dropped after any failure and
//! re-opened with capped exponential back-off.
//!
//! tokio-modbus has no timeout of its own (upstream issue 113), and a reply that arrives after a timeout is taken
//! as the answer to the next request (issue 324). So after a timeout, a transport error or a protocol error the
//! connection is dropped, never reused. A Modbus exception is a proper answer and keeps the connection.

use std::time::Duration;

use tokio::time::{Instant, timeout};
use tokio_modbus::client::{Client, Context};
use tokio_modbus::{ExceptionCode, Slave};
use tokio_modbus::{Request, Response};

use super::map::Table;

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
    #[error("reply has {got} registers, expected {expected}")]
    ShortReply { expected: usize, got: usize },
}

impl ClientError {
    /// A short label for the `errors_total{kind}` metric.
    pub fn kind(&self) -> &'static str {
        match self {
            ClientError::Backoff(_) => "backoff",
            ClientError::Connect { .. } => "connect",
            ClientError::Timeout(_) => "timeout",
            ClientError::Transport(_) => "transport",
            ClientError::Protocol(_) => "protocol",
            ClientError::Exception(_) => "exception",
            ClientError::ShortReply { .. } => "protocol",
        }
    }
}

/// One drive's connection.
pub struct DriveClient {
    address: String,
    unit_id: u8,
    call_timeout: Duration,
    ctx: Option<Context>,
    backoff: Duration,
    next_attempt: Option<Instant>,
    /// Connections opened after the first, for the `reconnects_total` metric.
    pub reconnects: u64,
    ever_connected: bool,
}

impl DriveClient {
    /// A client that connects on first use. `address` is `host:port`; the host is resolved at each connect.
    pub fn new(address: &str, unit_id: u8, call_timeout: Duration) -> DriveClient {
        DriveClient {
            address: address.to_string(),
            unit_id,
            call_timeout,
            ctx: None,
            backoff: BACKOFF_START,
            next_attempt: None,
            reconnects: 0,
            ever_connected: false,
        }
    }

    /// True while a connection is open.
    pub fn is_connected(&self) -> bool {
        self.ctx.is_some()
    }

    async fn connect(&mut self) -> Result<(), ClientError> {
        if let Some(at) = self.next_attempt
            && Instant::now() < at
        {
            return Err(ClientError::Backoff(at - Instant::now()));
        }
        let address = self.address.clone();
        let slave = Slave(self.unit_id);
        let attempt = async move {
            let mut last = None;
            for addr in tokio::net::lookup_host(address.as_str()).await? {
                match tokio_modbus::client::tcp::connect_slave(addr, slave).await {
                    Ok(ctx) => return Ok(ctx),
                    Err(e) => last = Some(e),
                }
            }
            Err(last.unwrap_or_else(|| std::io::Error::other("the name resolves to no address")))
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
                tracing::info!(address = %self.address, unit_id = self.unit_id, "modbus connected");
                Ok(())
            }
            Ok(Err(e)) => {
                Err(self.failed(ClientError::Connect { address: self.address.clone(), message: e.to_string() }))
            }
            Err(_) => Err(self.failed(ClientError::Connect {
                address: self.address.clone(),
                message: format!("no answer within {:?}", self.call_timeout),
            })),
        }
    }

    /// Drops the connection and schedules the next attempt.
    fn failed(&mut self, err: ClientError) -> ClientError {
        if self.ctx.take().is_some() {
            tracing::warn!(address = %self.address, error = %err, "modbus connection dropped");
        }
        self.next_attempt = Some(Instant::now() + self.backoff);
        self.backoff = (self.backoff * 2).min(BACKOFF_CAP);
        err
    }

    /// Runs one request on the open connection (connecting first if needed), under the timeout.
    async fn call<T, F>(&mut self, f: F) -> Result<T, ClientError>
    where
        F: for<'a> FnOnce(&'a mut Context) -> futures::future::BoxFuture<'a, tokio_modbus::Result<T>>,
    {
        if self.ctx.is_none() {
            self.connect().await?;
        }
        let Some(ctx) = self.ctx.as_mut() else { return Err(ClientError::Backoff(self.backoff)) };
        match timeout(self.call_timeout, f(ctx)).await {
            Ok(Ok(Ok(v))) => Ok(v),
            Ok(Ok(Err(code))) => Err(ClientError::Exception(code)),
            Ok(Err(tokio_modbus::Error::Transport(e))) => Err(self.failed(ClientError::Transport(e))),
            Ok(Err(tokio_modbus::Error::Protocol(e))) => Err(self.failed(ClientError::Protocol(e.to_string()))),
            Err(_) => Err(self.failed(ClientError::Timeout(self.call_timeout))),
        }
    }

    /// Reads `count` registers of a table from `start` in one request.
    pub async fn read(&mut self, table: Table, start: u16, count: u16) -> Result<Vec<u16>, ClientError> {
        let request = match table {
            Table::Input => Request::ReadInputRegisters(start, count),
            Table::Holding => Request::ReadHoldingRegisters(start, count),
        };
        let response = self.call(move |ctx| Box::pin(ctx.call(request))).await?;
        let words = match response {
            Response::ReadInputRegisters(w) | Response::ReadHoldingRegisters(w) => w,
            other => return Err(self.failed(ClientError::Protocol(format!("unexpected reply {other:?}")))),
        };
        if words.len() < usize::from(count) {
            let err = ClientError::ShortReply { expected: usize::from(count), got: words.len() };
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
        let response = self.call(move |ctx| Box::pin(ctx.call(request))).await?;
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

    /// Closes the connection (on shutdown).
    pub async fn close(&mut self) {
        if let Some(mut ctx) = self.ctx.take() {
            let _ = timeout(self.call_timeout, tokio_modbus::client::Client::disconnect(&mut ctx)).await;
        }
    }
}

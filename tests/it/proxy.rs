//! The fault-injection harness's byte-level half: a Modbus TCP proxy on 127.0.0.1 that passes frames through or
//! damages them on command (stall, drop, refuse, garbage, wrong transaction id, wrong byte count, slow replies).
#![allow(dead_code)]

use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio_util::sync::CancellationToken;

/// What the proxy does to traffic.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Fault {
    /// Pass every frame through.
    Pass,
    /// Take requests but never answer.
    Stall,
    /// Close every connection, current and new, at once.
    Drop,
    /// Stop listening: connections are refused until the mode changes.
    Refuse,
    /// Answer with random bytes.
    Garbage,
    /// Answer with a transaction id that does not match the request.
    WrongTransactionId,
    /// Answer with a byte count that does not match the data.
    WrongByteCount,
    /// Answer a register read with one register more than asked (a well-formed frame).
    ExtraRegister,
    /// Pass frames through after a delay.
    Slow(Duration),
    /// Answer every write (functions 6 and 16) with a Modbus exception (4, server device failure), without passing
    /// it on; reads pass.
    RefuseWrites,
    /// Hold the reply to every write this long; reads pass at once.
    SlowWrites(Duration),
    /// Hold the reply to every holding-register read (function 3) this long; the rest pass at once (a gateway slow
    /// only on holding registers).
    SlowHoldingReads(Duration),
}

/// A proxy in front of an upstream Modbus TCP server.
pub struct FaultProxy {
    pub addr: SocketAddr,
    fault: Arc<Mutex<Fault>>,
    /// Cancelled (and replaced) to cut every open connection.
    cut: Arc<Mutex<CancellationToken>>,
    stop: CancellationToken,
}

impl FaultProxy {
    /// Listens on an ephemeral loopback port and forwards to `upstream`.
    pub async fn start(upstream: SocketAddr) -> FaultProxy {
        let listener = TcpListener::bind("127.0.0.1:0").await.expect("bind loopback");
        let addr = listener.local_addr().expect("addr");
        let proxy = FaultProxy {
            addr,
            fault: Arc::new(Mutex::new(Fault::Pass)),
            cut: Arc::new(Mutex::new(CancellationToken::new())),
            stop: CancellationToken::new(),
        };
        let (fault, cut, stop) = (proxy.fault.clone(), proxy.cut.clone(), proxy.stop.clone());
        tokio::spawn(accept_loop(Some(listener), addr, upstream, fault, cut, stop));
        proxy
    }

    /// Switches the fault; `Drop` and `Refuse` also cut the connections that are open.
    pub fn set(&self, fault: Fault) {
        *self.fault.lock().unwrap_or_else(|e| e.into_inner()) = fault;
        if matches!(fault, Fault::Drop | Fault::Refuse) {
            let mut cut = self.cut.lock().unwrap_or_else(|e| e.into_inner());
            cut.cancel();
            *cut = CancellationToken::new();
        }
    }

    pub fn fault(&self) -> Fault {
        *self.fault.lock().unwrap_or_else(|e| e.into_inner())
    }
}

impl Drop for FaultProxy {
    fn drop(&mut self) {
        self.stop.cancel();
        self.cut.lock().unwrap_or_else(|e| e.into_inner()).cancel();
    }
}

async fn accept_loop(
    mut listener: Option<TcpListener>,
    addr: SocketAddr,
    upstream: SocketAddr,
    fault: Arc<Mutex<Fault>>,
    cut: Arc<Mutex<CancellationToken>>,
    stop: CancellationToken,
) {
    loop {
        let current = *fault.lock().unwrap_or_else(|e| e.into_inner());
        if current == Fault::Refuse {
            listener = None; // closing the socket: connects are refused
            tokio::select! {
                () = tokio::time::sleep(Duration::from_millis(10)) => continue,
                () = stop.cancelled() => return,
            }
        }
        let Some(l) = listener.as_ref() else {
            match TcpListener::bind(addr).await {
                Ok(l) => listener = Some(l),
                Err(_) => tokio::time::sleep(Duration::from_millis(10)).await,
            }
            continue;
        };
        let accepted = tokio::select! {
            r = l.accept() => r,
            () = tokio::time::sleep(Duration::from_millis(20)) => continue,
            () = stop.cancelled() => return,
        };
        let Ok((client, _)) = accepted else { continue };
        if current == Fault::Drop {
            drop(client);
            continue;
        }
        let token = cut.lock().unwrap_or_else(|e| e.into_inner()).clone();
        let fault = fault.clone();
        tokio::spawn(async move {
            tokio::select! {
                _ = relay(client, upstream, fault) => {}
                () = token.cancelled() => {}
            }
        });
    }
}

/// Reads one MBAP frame: 7-byte header (transaction, protocol, length, unit) then length − 1 bytes.
async fn read_frame(s: &mut TcpStream) -> std::io::Result<Vec<u8>> {
    let mut head = [0u8; 7];
    s.read_exact(&mut head).await?;
    let len = usize::from(u16::from_be_bytes([head[4], head[5]]));
    let mut frame = head.to_vec();
    frame.resize(7 + len.saturating_sub(1), 0);
    s.read_exact(&mut frame[7..]).await?;
    Ok(frame)
}

async fn relay(mut client: TcpStream, upstream: SocketAddr, fault: Arc<Mutex<Fault>>) -> std::io::Result<()> {
    let mut server = TcpStream::connect(upstream).await?;
    let mut noise: u64 = 0x9E37_79B9_7F4A_7C15;
    loop {
        let request = read_frame(&mut client).await?;
        let current = *fault.lock().unwrap_or_else(|e| e.into_inner());
        let write = request.len() > 7 && matches!(request[7], 6 | 16);
        match current {
            Fault::Stall => continue,
            Fault::Drop | Fault::Refuse => return Ok(()),
            Fault::Slow(d) => tokio::time::sleep(d).await,
            Fault::SlowWrites(d) if write => tokio::time::sleep(d).await,
            Fault::SlowHoldingReads(d) if request.len() > 7 && request[7] == 3 => tokio::time::sleep(d).await,
            Fault::RefuseWrites if write => {
                // MBAP with length 3 (unit, function | 0x80, exception code)
                let mut reply = request[..7].to_vec();
                reply[4..6].copy_from_slice(&3u16.to_be_bytes());
                reply.extend_from_slice(&[request[7] | 0x80, 4]);
                client.write_all(&reply).await?;
                continue;
            }
            _ => {}
        }
        server.write_all(&request).await?;
        let mut reply = read_frame(&mut server).await?;
        match current {
            Fault::Garbage => {
                for b in reply.iter_mut() {
                    noise ^= noise << 13;
                    noise ^= noise >> 7;
                    noise ^= noise << 17;
                    *b = noise as u8;
                }
            }
            Fault::WrongTransactionId => {
                reply[0] ^= 0x5A;
                reply[1] ^= 0xA5;
            }
            Fault::WrongByteCount if reply.len() > 8 => {
                reply[8] = reply[8].wrapping_add(2);
            }
            // function 3 or 4: MBAP length and byte count grow by one register, its value appended
            Fault::ExtraRegister if reply.len() > 8 && matches!(reply[7], 3 | 4) => {
                let length = u16::from_be_bytes([reply[4], reply[5]]) + 2;
                reply[4..6].copy_from_slice(&length.to_be_bytes());
                reply[8] = reply[8].wrapping_add(2);
                reply.extend_from_slice(&[0x12, 0x34]);
            }
            _ => {}
        }
        client.write_all(&reply).await?;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use hydrolens::modbus::simulator::Simulator;
    use hydrolens::plant::PlantModel;
    use tokio_modbus::prelude::*;

    async fn read(addr: SocketAddr) -> Result<Vec<u16>, String> {
        let fut = async {
            let mut ctx = tcp::connect_slave(addr, Slave(1)).await.map_err(|e| format!("connect: {e}"))?;
            ctx.read_input_registers(0, 6).await.map_err(|e| format!("transport: {e}"))?.map_err(|e| format!("{e:?}"))
        };
        tokio::time::timeout(Duration::from_millis(500), fut).await.map_err(|_| "timeout".to_string())?
    }

    /// Reads through `addr` until a result satisfies `done` (the proxy's accept loop takes up to 20 ms to see a
    /// fault that acts on the listener), 3 s at most: the last result.
    async fn read_until(
        addr: SocketAddr,
        done: impl Fn(&Result<Vec<u16>, String>) -> bool,
    ) -> Result<Vec<u16>, String> {
        let start = tokio::time::Instant::now();
        loop {
            let r = read(addr).await;
            if done(&r) || start.elapsed() > Duration::from_secs(3) {
                return r;
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    }

    /// A reply with one register more than asked is a well-formed frame; hydrolens's client refuses it as a protocol
    /// error (the wrong length) instead of decoding whatever the device sent.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_reply_with_more_registers_than_asked_is_a_protocol_error() {
        let listener = TcpListener::bind("127.0.0.1:0").await.expect("bind");
        let addr = listener.local_addr().expect("addr");
        let sim = Simulator::new(PlantModel::reference(), 1).expect("model");
        let stop = CancellationToken::new();
        let s = stop.clone();
        let task = tokio::spawn(async move {
            let _ = sim.run(listener, s).await;
        });
        let proxy = FaultProxy::start(addr).await;
        proxy.set(Fault::ExtraRegister);
        let mut client =
            hydrolens::modbus::client::DriveClient::new(&proxy.addr.to_string(), 1, Duration::from_millis(300));
        let e = client.read(hydrolens::modbus::Table::Input, 0, 6).await.expect_err("refused");
        assert!(matches!(e, hydrolens::modbus::client::ClientError::WrongLength { expected: 6, got: 7 }), "{e:?}");
        assert_eq!(e.kind(), "protocol");
        proxy.set(Fault::Pass);
        // the client backs off after the error, then reads again
        let mut words = Vec::new();
        for _ in 0..100 {
            if let Ok(w) = client.read(hydrolens::modbus::Table::Input, 0, 6).await {
                words = w;
                break;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        assert_eq!(words.len(), 6, "reads again");
        stop.cancel();
        let _ = task.await;
    }

    /// Each fault is seen by a plain client as the failure it stands for, and passing through works again after.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn every_fault_shows_as_a_client_error_and_clears() {
        let listener = TcpListener::bind("127.0.0.1:0").await.expect("bind");
        let upstream = listener.local_addr().expect("addr");
        let sim = Simulator::new(PlantModel::reference(), 3).expect("sim");
        let stop = CancellationToken::new();
        let task = tokio::spawn(sim.run(listener, stop.clone()));
        let proxy = FaultProxy::start(upstream).await;
        assert_eq!(read(proxy.addr).await.map(|r| r.len()), Ok(6));
        for fault in [
            Fault::Stall,
            Fault::Drop,
            Fault::Refuse,
            Fault::Garbage,
            Fault::WrongTransactionId,
            Fault::WrongByteCount,
            Fault::Slow(Duration::from_millis(800)),
        ] {
            proxy.set(fault);
            let refuse = fault == Fault::Refuse;
            let r = read_until(proxy.addr, |r| r.as_ref().is_err_and(|e| !refuse || e.starts_with("connect"))).await;
            assert!(r.is_err(), "{fault:?} gave {r:?}");
            if fault == Fault::Refuse {
                let e = r.expect_err("refused");
                assert!(e.starts_with("connect"), "refused at connect: {e}");
            }
            proxy.set(Fault::Pass);
            let r = read_until(proxy.addr, Result::is_ok).await;
            assert_eq!(r.map(|r| r.len()), Ok(6), "after {fault:?}");
        }
        stop.cancel();
        let _ = task.await;
    }
}

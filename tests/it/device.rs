//! A misbehaving Modbus TCP device written for the hardening tests: it serves the default register map from a
//! script (input image per read), and can answer late or with garbage. It counts connections and writes.
#![allow(dead_code)]

use std::net::SocketAddr;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio_util::sync::CancellationToken;

/// The input image (registers 0..6 of the default map) for the `n`-th read answered.
pub type Script = Box<dyn FnMut(u64) -> [u16; 6] + Send>;

/// A healthy drive at about 40 rad/s: pressures 50 and 3 bar, 382 rpm, 25.5 Hz, ready and running, a counter
/// that moves by 10 each read and a little noise on the inlet pressure.
pub fn healthy() -> Script {
    Box::new(|n| [5000 + (n % 7) as u16, 300, 3820, 2550, 3, (n * 10) as u16])
}

/// What the device does now; tests change it through [`Device::lock`].
pub struct Behaviour {
    pub script: Script,
    /// Hold every reply this long.
    pub delay: Duration,
    /// Answer every request with bytes that are not a Modbus frame.
    pub garbage: bool,
    /// Echo each write with another address than the one written (a well-formed frame that does not match).
    pub bad_echo: bool,
    /// Reads answered so far (the script's `n`).
    pub reads: u64,
    /// Write requests answered.
    pub writes: u64,
    /// Connections accepted.
    pub connections: u64,
}

pub struct Device {
    pub addr: SocketAddr,
    behaviour: Arc<Mutex<Behaviour>>,
    stop: CancellationToken,
}

impl Device {
    pub async fn start(script: Script) -> Device {
        let listener = TcpListener::bind("127.0.0.1:0").await.expect("bind loopback");
        let addr = listener.local_addr().expect("addr");
        let behaviour = Arc::new(Mutex::new(Behaviour {
            script,
            delay: Duration::ZERO,
            garbage: false,
            bad_echo: false,
            reads: 0,
            writes: 0,
            connections: 0,
        }));
        let stop = CancellationToken::new();
        let (b, s) = (behaviour.clone(), stop.clone());
        tokio::spawn(async move {
            loop {
                let accepted = tokio::select! {
                    r = listener.accept() => r,
                    () = s.cancelled() => return,
                };
                let Ok((stream, _)) = accepted else { continue };
                lock(&b).connections += 1;
                let (b, s) = (b.clone(), s.clone());
                tokio::spawn(async move {
                    tokio::select! {
                        _ = serve(stream, b) => {}
                        () = s.cancelled() => {}
                    }
                });
            }
        });
        Device { addr, behaviour, stop }
    }

    pub fn lock(&self) -> MutexGuard<'_, Behaviour> {
        lock(&self.behaviour)
    }
}

impl Drop for Device {
    fn drop(&mut self) {
        self.stop.cancel();
    }
}

fn lock(b: &Mutex<Behaviour>) -> MutexGuard<'_, Behaviour> {
    b.lock().unwrap_or_else(|e| e.into_inner())
}

async fn serve(mut s: TcpStream, b: Arc<Mutex<Behaviour>>) -> std::io::Result<()> {
    loop {
        let mut head = [0u8; 7];
        s.read_exact(&mut head).await?;
        let len = usize::from(u16::from_be_bytes([head[4], head[5]]));
        let mut pdu = vec![0u8; len.saturating_sub(1)];
        s.read_exact(&mut pdu).await?;
        let (delay, garbage, reply_pdu) = {
            let mut g = lock(&b);
            let reply = match pdu.first().copied() {
                Some(0x04) | Some(0x03) if pdu.len() >= 5 => {
                    let start = usize::from(u16::from_be_bytes([pdu[1], pdu[2]]));
                    let count = usize::from(u16::from_be_bytes([pdu[3], pdu[4]]));
                    let image = if pdu[0] == 0x04 {
                        let n = g.reads;
                        g.reads += 1;
                        (g.script)(n).to_vec()
                    } else {
                        vec![0; 8]
                    };
                    let mut r = vec![pdu[0], (2 * count) as u8];
                    for i in start..start + count {
                        r.extend_from_slice(&image.get(i).copied().unwrap_or(0).to_be_bytes());
                    }
                    r
                }
                Some(0x06) | Some(0x10) if pdu.len() >= 5 => {
                    g.writes += 1;
                    let mut echo = pdu[..5].to_vec();
                    if g.bad_echo {
                        echo[1] ^= 0x02;
                    }
                    echo
                }
                Some(f) => vec![f | 0x80, 0x01],
                None => vec![0x80, 0x01],
            };
            (g.delay, g.garbage, reply)
        };
        if !delay.is_zero() {
            tokio::time::sleep(delay).await;
        }
        if garbage {
            s.write_all(&[0xFF; 12]).await?;
            continue;
        }
        let mut frame = head[..4].to_vec();
        frame.extend_from_slice(&((reply_pdu.len() + 1) as u16).to_be_bytes());
        frame.push(head[6]);
        frame.extend_from_slice(&reply_pdu);
        s.write_all(&frame).await?;
    }
}

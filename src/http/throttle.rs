//! Throttling of wrong Bearer tokens, per client address: after [`MAX_FAILURES`] wrong tokens within [`WINDOW`] a
//! client's wrong tokens get 429 for [`BLOCK`]. The right token is never refused (the caller checks it first): behind
//! a reverse proxy every user shares one address, and one stranger must not lock the operator out. What keeps a
//! guesser out is then the token's length (the config warns of a short one). Pure bookkeeping, fed the time.

use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// Wrong tokens a client may send within [`WINDOW`] before it is blocked.
pub const MAX_FAILURES: u32 = 10;
/// The window the failures are counted over.
pub const WINDOW: Duration = Duration::from_secs(60);
/// How long a client's wrong tokens are answered 429 without being counted.
pub const BLOCK: Duration = Duration::from_secs(60);
/// Clients remembered at most; beyond it the stalest entry is forgotten.
const MAX_CLIENTS: usize = 4096;

#[derive(Debug, Clone, Copy)]
struct Entry {
    window_start: Instant,
    failures: u32,
    blocked_until: Option<Instant>,
}

/// See the module doc. Clients are keyed by IP address (IPv6 by its /64, which one host usually holds whole).
#[derive(Debug, Default)]
pub struct AuthThrottle {
    clients: Mutex<HashMap<IpAddr, Entry>>,
}

/// The key of a client address: IPv4-mapped IPv6 as IPv4, other IPv6 by its /64.
pub(super) fn key(ip: IpAddr) -> IpAddr {
    match ip {
        IpAddr::V6(v6) => match v6.to_ipv4_mapped() {
            Some(v4) => IpAddr::V4(v4),
            None => {
                let s = v6.segments();
                IpAddr::V6(std::net::Ipv6Addr::new(s[0], s[1], s[2], s[3], 0, 0, 0, 0))
            }
        },
        v4 => v4,
    }
}

impl AuthThrottle {
    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<IpAddr, Entry>> {
        self.clients.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// How much longer `ip` is blocked, if it is.
    pub fn blocked(&self, ip: IpAddr, now: Instant) -> Option<Duration> {
        let clients = self.lock();
        let until = clients.get(&key(ip))?.blocked_until?;
        (until > now).then(|| until - now)
    }

    /// Counts a wrong token from `ip`; returns the failures in its window and true if this one blocks it.
    pub fn failed(&self, ip: IpAddr, now: Instant) -> (u32, bool) {
        let mut clients = self.lock();
        if clients.len() >= MAX_CLIENTS && !clients.contains_key(&key(ip)) {
            clients.retain(|_, e| {
                now.saturating_duration_since(e.window_start) < WINDOW || e.blocked_until.is_some_and(|u| u > now)
            });
            if clients.len() >= MAX_CLIENTS
                && let Some(stalest) = clients.iter().min_by_key(|(_, e)| e.window_start).map(|(k, _)| *k)
            {
                clients.remove(&stalest);
            }
        }
        let e = clients.entry(key(ip)).or_insert(Entry { window_start: now, failures: 0, blocked_until: None });
        if now.saturating_duration_since(e.window_start) >= WINDOW {
            *e = Entry { window_start: now, failures: 0, blocked_until: None };
        }
        e.failures += 1;
        let blocks = e.failures >= MAX_FAILURES && e.blocked_until.is_none_or(|u| u <= now);
        if blocks {
            e.blocked_until = Some(now + BLOCK);
            // a fresh window once the block ends
            e.window_start = now + BLOCK;
            e.failures = 0;
        }
        (e.failures, blocks)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_burst_blocks_for_a_while_and_others_are_untouched() {
        let t = AuthThrottle::default();
        let (a, b): (IpAddr, IpAddr) = ("10.0.0.1".parse().expect("ip"), "10.0.0.2".parse().expect("ip"));
        let t0 = Instant::now();
        for i in 1..MAX_FAILURES {
            assert_eq!(t.failed(a, t0), (i, false));
            assert_eq!(t.blocked(a, t0), None);
        }
        assert!(t.failed(a, t0).1, "the tenth blocks");
        assert_eq!(t.blocked(a, t0), Some(BLOCK));
        assert_eq!(t.blocked(b, t0), None);
        assert_eq!(t.blocked(a, t0 + BLOCK), None, "and the block ends");
        // failures spread thinner than the window never block
        let t = AuthThrottle::default();
        for i in 0..100 {
            assert!(!t.failed(a, t0 + WINDOW * i / 5).1);
        }
    }

    #[test]
    fn ipv6_clients_are_keyed_by_their_64() {
        let t = AuthThrottle::default();
        let now = Instant::now();
        for i in 0..MAX_FAILURES {
            t.failed(format!("2001:db8::{i:x}").parse().expect("ip"), now);
        }
        assert!(t.blocked("2001:db8::ffff".parse().expect("ip"), now).is_some());
    }
}

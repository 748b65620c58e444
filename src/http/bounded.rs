//! A resource the HTTP side holds for a bounded number of requests at once (event streams, history replies,
//! downloads), of which one client address holds at most its share ([`address_share`]): a flood, a crowd of one
//! host's tabs or a client that reads nothing leaves room for every other address.

use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::{Arc, Mutex};

use tokio::sync::{OwnedSemaphorePermit, Semaphore};

/// What one client address may hold of `max` at once: three quarters, at least one. One address held all 64 event
/// streams with streams it did not read, and every other client got 503 for minutes; all 8 downloads likewise.
pub fn address_share(max: usize) -> usize {
    (max * 3 / 4).max(1)
}

/// At most `max` held at once, at most [`address_share`] of them by one address.
#[derive(Clone)]
pub struct Bounded {
    permits: Arc<Semaphore>,
    by_address: Arc<Mutex<HashMap<IpAddr, usize>>>,
    share: usize,
}

/// Why [`Bounded::take`] refused.
#[derive(Debug, PartialEq, Eq)]
pub enum Refused {
    /// The address holds its share.
    Share,
    /// Every one is held.
    All,
}

/// One held, counted against its address until dropped.
pub struct Held {
    _permit: OwnedSemaphorePermit,
    by_address: Arc<Mutex<HashMap<IpAddr, usize>>>,
    ip: IpAddr,
}

impl Drop for Held {
    fn drop(&mut self) {
        let mut m = self.by_address.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(n) = m.get_mut(&self.ip) {
            *n = n.saturating_sub(1);
            if *n == 0 {
                m.remove(&self.ip);
            }
        }
    }
}

impl Bounded {
    pub fn new(max: usize) -> Bounded {
        Bounded { permits: Arc::new(Semaphore::new(max)), by_address: Default::default(), share: address_share(max) }
    }

    /// How many are free.
    pub fn available(&self) -> usize {
        self.permits.available_permits()
    }

    /// One more for the client at `ip` (an IPv6 client by its /64, [`super::throttle::key`]), unless its address
    /// holds its share or every one is held.
    pub fn take(&self, ip: IpAddr) -> Result<Held, Refused> {
        let ip = super::throttle::key(ip);
        let mut m = self.by_address.lock().unwrap_or_else(|e| e.into_inner());
        let held = m.get(&ip).copied().unwrap_or(0);
        if held >= self.share {
            return Err(Refused::Share);
        }
        let permit = self.permits.clone().try_acquire_owned().map_err(|_| Refused::All)?;
        m.insert(ip, held + 1);
        Ok(Held { _permit: permit, by_address: self.by_address.clone(), ip })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_address_holds_its_share_and_the_others_the_rest() {
        let bounded = Bounded::new(8);
        let (a, b) = (IpAddr::from([10, 0, 0, 1]), IpAddr::from([10, 0, 0, 2]));
        let mut held: Vec<Held> = (0..6).map(|_| bounded.take(a).expect("within its share")).collect();
        assert_eq!(bounded.take(a).err(), Some(Refused::Share));
        held.extend((0..2).map(|_| bounded.take(b).expect("the rest")));
        assert_eq!(bounded.take(b).err(), Some(Refused::All));
        assert_eq!(bounded.available(), 0);
        held.truncate(5);
        assert_eq!(bounded.available(), 3);
        assert!(bounded.take(a).is_ok(), "one of a's given back frees a place in its share");
        drop(held);
        assert_eq!(bounded.available(), 8);
        assert!(bounded.by_address.lock().expect("lock").is_empty(), "nothing left counted");
    }
}

//! PURE: whether this service is the only master writing a drive. A drive obeys one master; two (a second `serve`
//! pointed at the same drive, an HMI or an engineering tool left writing) fight over its setpoint and RUN, each
//! undoing the other's writes, and each regulator winds up against a drive it does not command.
//!
//! The watchdog register tells them apart: every write of this service carries its own watchdog value, which no
//! other master has reason to write, so read back between two writes it is the last value this service wrote
//! unless another master wrote since. [`Echo`] reads it back every [`CHECK_EVERY`] and finds another master once
//! [`MISMATCHES`] of the last [`WINDOW`] read-backs held a value neither ours nor 0 (a register cleared is a drive
//! that lost power and came back, or a PLC that clears the watchdog it has read; one stray value is a write of ours
//! the drive took in a way we did not see: the next write puts ours back). A device that never echoes our value (a
//! write-only register, a gateway answering reads from elsewhere) or refuses the read cannot show another master:
//! the check stands down and says so once.

use std::time::Duration;

use tokio::time::Instant;

/// How often the watchdog register is read back: an extra read (function 03) every this long.
pub const CHECK_EVERY: Duration = Duration::from_millis(200);

/// How long a read-back that timed out puts the next one off: each costs the link (the client reconnects after a
/// timeout) and a cycle's sample, so three of them close together took the drive past its comm-loss watchdog.
pub const TIMED_OUT_WAIT: Duration = Duration::from_secs(2);

/// Read-backs remembered.
const WINDOW: u32 = 8;

/// Read-backs of the last [`WINDOW`] not ours that find another master.
const MISMATCHES: u32 = 3;

/// Read-backs allowed to show our value for the first time before the check stands down (5 s at [`CHECK_EVERY`]).
const LEARN_CHECKS: u32 = 25;

/// Refused read-backs in a row (Modbus exceptions) that stand the check down: one exception 11 (a gateway's target
/// that did not answer once) stood it down for good, and a second master then went unseen.
const REFUSALS: u32 = 3;

/// What a read-back found, where it changed the check's state.
#[derive(Debug, Clone, PartialEq)]
pub enum Finding {
    /// Another master writes the drive.
    AnotherMaster { read: Vec<u16>, ours: Vec<u16> },
    /// The check cannot work on this device, and why.
    Unavailable(&'static str),
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum State {
    /// Not yet seen our value echoed: `checks` read-backs so far.
    Learning {
        checks: u32,
    },
    /// The device echoes our writes; `recent` holds the last read-backs, one bit each (1: not ours), newest lowest.
    Armed {
        recent: u32,
    },
    /// Another master was found: this service writes nothing until a reset.
    Found,
    Unavailable,
}

/// The read-back check of one drive.
#[derive(Debug, Clone)]
pub struct Echo {
    state: State,
    last_check: Option<Instant>,
    /// Refused read-backs in a row.
    refusals: u32,
}

impl Default for Echo {
    fn default() -> Echo {
        Echo { state: State::Learning { checks: 0 }, last_check: None, refusals: 0 }
    }
}

impl Echo {
    /// A read-back is due now (the caller also needs a confirmed write of its own to compare with).
    pub fn due(&self, now: Instant) -> bool {
        matches!(self.state, State::Learning { .. } | State::Armed { .. })
            && self.last_check.is_none_or(|t| now.saturating_duration_since(t) >= CHECK_EVERY)
    }

    /// Another master was found, and this service has stood back.
    pub fn found(&self) -> bool {
        self.state == State::Found
    }

    /// The register read back as `read`; `ours` is what this service last wrote there (and the drive confirmed).
    pub fn observe(&mut self, now: Instant, read: &[u16], ours: &[u16]) -> Option<Finding> {
        self.last_check = Some(now);
        self.refusals = 0;
        let foreign = read != ours && read.iter().any(|&w| w != 0);
        match self.state {
            State::Learning { .. } if read == ours => self.state = State::Armed { recent: 0 },
            State::Learning { checks } if checks + 1 >= LEARN_CHECKS => {
                self.state = State::Unavailable;
                return Some(Finding::Unavailable("the drive never read back the watchdog value this service wrote"));
            }
            State::Learning { checks } => self.state = State::Learning { checks: checks + 1 },
            State::Armed { recent } => {
                let recent = ((recent << 1) | u32::from(foreign)) & ((1 << WINDOW) - 1);
                if recent.count_ones() >= MISMATCHES {
                    self.state = State::Found;
                    return Some(Finding::AnotherMaster { read: read.to_vec(), ours: ours.to_vec() });
                }
                self.state = State::Armed { recent };
            }
            State::Found | State::Unavailable => {}
        }
        None
    }

    /// The device refused the read (a Modbus exception): [`REFUSALS`] in a row, the check cannot work on it.
    pub fn refused(&mut self) -> Option<Finding> {
        self.failed("the drive refuses to read back its watchdog register (a Modbus exception)")
    }

    /// The read went unanswered within the call timeout, at `now`: not due again for [`TIMED_OUT_WAIT`], and
    /// [`REFUSALS`] in a row stand the check down as refusals do. A gateway slow only on holding registers timed out
    /// the read-back first thing after every reconnect, before the cycle's own reads: 13 reconnects and no sample
    /// for 7.5 s, and the drive tripped on its lost link (a reviewer's proxy, 260 ms against a 200 ms timeout).
    pub fn timed_out(&mut self, now: Instant) -> Option<Finding> {
        // `due` counts the check's period from here
        self.last_check = Some(now + TIMED_OUT_WAIT.saturating_sub(CHECK_EVERY));
        self.failed("the drive does not answer the read-back of its watchdog register within the call timeout")
    }

    fn failed(&mut self, why: &'static str) -> Option<Finding> {
        if matches!(self.state, State::Unavailable | State::Found) {
            return None;
        }
        self.refusals += 1;
        if self.refusals < REFUSALS {
            return None;
        }
        self.state = State::Unavailable;
        Some(Finding::Unavailable(why))
    }

    /// An operator's reset: a master that stood back writes again and looks afresh, and a check that stood down
    /// tries again.
    pub fn reset(&mut self) {
        self.refusals = 0;
        match self.state {
            State::Found => self.state = State::Armed { recent: 0 },
            State::Unavailable => self.state = State::Learning { checks: 0 },
            State::Learning { .. } | State::Armed { .. } => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(ms: u64) -> Instant {
        // one base for every call of a test: Instant::now() once, then offsets
        static BASE: std::sync::OnceLock<Instant> = std::sync::OnceLock::new();
        *BASE.get_or_init(Instant::now) + Duration::from_millis(ms)
    }

    #[test]
    fn another_master_is_found_on_the_third_foreign_value_in_eight_and_not_on_a_power_cycle() {
        let mut e = Echo::default();
        assert!(e.due(at(0)));
        assert_eq!(e.observe(at(0), &[5], &[5]), None, "ours: armed");
        assert!(!e.due(at(100)) && e.due(at(200)), "every 200 ms");
        // a power cycle, or a PLC that clears the watchdog it has read: 0 is no other master's
        for i in 0..5 {
            assert_eq!(e.observe(at(200), &[0], &[6]), None, "cleared {i}");
        }
        for i in 0..10 {
            assert_eq!(e.observe(at(400 + 200 * i), &[7 + i as u16], &[7 + i as u16]), None);
        }
        // two foreign values, four of ours, a third foreign one: 3 of the last 8
        assert_eq!(e.observe(at(3000), &[900], &[20]), None);
        assert_eq!(e.observe(at(3200), &[901], &[20]), None);
        for i in 0..4 {
            assert_eq!(e.observe(at(3400 + 200 * i), &[21], &[21]), None);
        }
        let found = e.observe(at(4200), &[902], &[22]);
        assert_eq!(found, Some(Finding::AnotherMaster { read: vec![902], ours: vec![22] }));
        assert!(e.found() && !e.due(at(9000)), "stood back: no more reads");
        e.reset();
        assert!(!e.found() && e.due(at(9000)), "a reset looks afresh");
        assert_eq!(e.observe(at(9000), &[903], &[23]), None, "the old mismatches are forgotten");
    }

    #[test]
    fn foreign_values_spread_wider_than_the_window_are_not_another_master() {
        let mut e = Echo::default();
        e.observe(at(0), &[1], &[1]);
        for i in 0..40u16 {
            let read = if i % 4 == 0 { 500 + i } else { i };
            assert_eq!(e.observe(at(200 * u64::from(i + 1)), &[read], &[i]), None, "check {i}");
        }
    }

    #[test]
    fn a_device_that_never_echoes_or_refuses_the_read_stands_the_check_down() {
        let mut e = Echo::default();
        for i in 0..LEARN_CHECKS - 1 {
            assert_eq!(e.observe(at(200 * u64::from(i)), &[0], &[u16::try_from(i).unwrap_or(0) + 1]), None);
        }
        assert!(matches!(e.observe(at(10_000), &[0], &[99]), Some(Finding::Unavailable(_))));
        assert!(!e.due(at(20_000)) && !e.found());
        // one refusal is a transient (exception 11, a gateway's target that did not answer once): the check goes
        // on; three in a row stand it down, said once; a reset tries again
        let mut r = Echo::default();
        assert_eq!(r.refused(), None, "one refusal");
        assert_eq!(r.observe(at(0), &[4], &[4]), None, "armed");
        assert_eq!((r.refused(), r.refused()), (None, None));
        assert_eq!(r.observe(at(200), &[5], &[5]), None, "a good read starts the count again");
        assert_eq!((r.refused(), r.refused()), (None, None));
        assert!(matches!(r.refused(), Some(Finding::Unavailable(_))), "the third in a row");
        assert_eq!(r.refused(), None, "said once");
        assert!(!r.due(at(10_000)));
        r.reset();
        assert!(r.due(at(10_000)), "a reset tries again");
        assert_eq!(r.observe(at(10_000), &[6], &[6]), None);
        for i in 0..3u16 {
            r.observe(at(10_200 + 200 * u64::from(i)), &[900 + i], &[7]);
        }
        assert!(r.found(), "and finds a second master again");
        // timeouts likewise, and each puts the next read-back off by TIMED_OUT_WAIT
        let mut t = Echo::default();
        assert_eq!(t.timed_out(at(0)), None);
        assert!(!t.due(at(1900)) && t.due(at(2000)), "not again for a while");
        assert_eq!(t.timed_out(at(2000)), None);
        assert!(matches!(t.timed_out(at(4000)), Some(Finding::Unavailable(why)) if why.contains("timeout")));
        assert!(!t.due(at(10_000)));
    }
}

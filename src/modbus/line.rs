//! A Modbus RTU serial line, pure: its settings, the time a frame takes on it, the inter-frame gap, and the load
//! that drives polled over it put on it (the line-capacity rule of the config).

use std::time::Duration;

/// Parity of a serial line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Parity {
    None,
    Even,
    Odd,
}

impl Parity {
    /// `none`, `even` or `odd` (the config's and the simulator's spelling).
    pub fn parse(s: &str) -> Option<Parity> {
        match s {
            "none" => Some(Parity::None),
            "even" => Some(Parity::Even),
            "odd" => Some(Parity::Odd),
            _ => None,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Parity::None => "none",
            Parity::Even => "even",
            Parity::Odd => "odd",
        }
    }
}

/// A serial line's settings: 8 data bits always (Modbus RTU), the rest configurable.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SerialLine {
    pub baud_rate: u32,
    pub parity: Parity,
    /// 1 or 2.
    pub stop_bits: u8,
}

impl Default for SerialLine {
    /// The Modbus serial-line default: 19200 baud, even parity, one stop bit.
    fn default() -> Self {
        SerialLine { baud_rate: 19200, parity: Parity::Even, stop_bits: 1 }
    }
}

/// The largest bytes per second of RTU traffic the config lets a line carry, as a share of what it can carry:
/// the rest is left for the devices' turnaround and the master's own scheduling.
pub const MAX_LINE_LOAD: f64 = 0.8;

impl SerialLine {
    /// Bits on the wire per byte: start, 8 data, parity if any, stop bits.
    pub fn bits_per_char(&self) -> u32 {
        1 + 8 + u32::from(self.parity != Parity::None) + u32::from(self.stop_bits)
    }

    /// The silence that ends a frame (t3.5): 3.5 character times, fixed at 1.75 ms above 19200 baud (Modbus over
    /// Serial Line V1.02, 2.5.1.1).
    pub fn inter_frame_gap(&self) -> Duration {
        if self.baud_rate > 19200 {
            Duration::from_micros(1750)
        } else {
            Duration::from_secs_f64(3.5 * f64::from(self.bits_per_char()) / f64::from(self.baud_rate.max(1)))
        }
    }

    /// The time a frame of `bytes` takes on the line, with the gap that must follow it.
    pub fn frame_time(&self, bytes: usize) -> Duration {
        let bits = bytes as f64 * f64::from(self.bits_per_char());
        Duration::from_secs_f64(bits / f64::from(self.baud_rate.max(1))) + self.inter_frame_gap()
    }

    /// The line time of one exchange per frame pair (request bytes, reply bytes).
    pub fn cycle_time(&self, frames: &[(usize, usize)]) -> Duration {
        frames.iter().map(|&(req, rep)| self.frame_time(req) + self.frame_time(rep)).sum()
    }
}

/// The RTU frames (request bytes, reply bytes) of reading `count` registers (function 03 or 04).
pub fn read_frames(count: u16) -> (usize, usize) {
    // request: unit, function, start, count, CRC; reply: unit, function, byte count, 2n data, CRC
    (8, 5 + 2 * usize::from(count))
}

/// The RTU frames of writing `count` registers (06 for one, 16 for more).
pub fn write_frames(count: usize) -> (usize, usize) {
    if count == 1 {
        (8, 8)
    } else {
        // unit, function, start, quantity, byte count, 2n data, CRC; the reply echoes start and quantity
        (9 + 2 * count, 8)
    }
}

/// The share of a line's time that drives polled over it take: Σ line time of a poll cycle / poll period.
/// Each entry is (frames of one cycle, poll period).
pub fn line_load(line: &SerialLine, drives: &[(Vec<(usize, usize)>, Duration)]) -> f64 {
    drives.iter().map(|(frames, poll)| line.cycle_time(frames).as_secs_f64() / poll.as_secs_f64().max(1e-9)).sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bits_and_gaps() {
        let even = SerialLine::default();
        assert_eq!(even.bits_per_char(), 11);
        assert_eq!(SerialLine { parity: Parity::None, ..even }.bits_per_char(), 10);
        assert_eq!(SerialLine { parity: Parity::None, stop_bits: 2, ..even }.bits_per_char(), 11);
        // 3.5 × 11 bits at 9600 baud
        let slow = SerialLine { baud_rate: 9600, ..even };
        assert!((slow.inter_frame_gap().as_secs_f64() - 3.5 * 11.0 / 9600.0).abs() < 1e-9);
        assert_eq!(SerialLine { baud_rate: 115_200, ..even }.inter_frame_gap(), Duration::from_micros(1750));
    }

    #[test]
    fn one_default_drive_at_19200_baud() {
        // the default map: one read of 6 input registers (8 + 17 bytes), one write of 3 holding registers (15 + 8)
        let line = SerialLine::default();
        assert_eq!(read_frames(6), (8, 17));
        assert_eq!(write_frames(3), (15, 8));
        assert_eq!(write_frames(1), (8, 8));
        let monitor = line.cycle_time(&[read_frames(6)]).as_secs_f64();
        // 25 bytes × 11 bits / 19200 + 2 gaps of 3.5 × 11 / 19200
        let expected = (25.0 * 11.0 + 7.0 * 11.0) / 19200.0;
        assert!((monitor - expected).abs() < 1e-8, "{monitor} vs {expected}");
        // at 50 ms: 36.7 % of the line
        let load = line_load(&line, &[(vec![read_frames(6)], Duration::from_millis(50))]);
        assert!((load - expected / 0.05).abs() < 1e-6);
    }
}

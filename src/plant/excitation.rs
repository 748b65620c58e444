//! The test stand's built-in setpoint program: steps and ramps from standstill, repeated.

/// One piece of the program: from `t_s` on, the setpoint goes from `from_hz` to `to_hz` over `ramp_s`
/// (0 = a step) and holds.
#[derive(Debug, Clone, Copy)]
struct Segment {
    t_s: f64,
    from_hz: f64,
    to_hz: f64,
    ramp_s: f64,
}

const fn seg(t_s: f64, from_hz: f64, to_hz: f64, ramp_s: f64) -> Segment {
    Segment { t_s, from_hz, to_hz, ramp_s }
}

/// One 40 s cycle: standstill, steps up and down, ramps, a stop and a restart, low and high speeds.
const PROGRAM: [Segment; 12] = [
    seg(0.0, 0.0, 0.0, 0.0),
    seg(1.0, 20.0, 20.0, 0.0),
    seg(5.0, 35.0, 35.0, 0.0),
    seg(9.0, 35.0, 50.0, 4.0),
    seg(13.0, 15.0, 15.0, 0.0),
    seg(17.0, 15.0, 45.0, 3.0),
    seg(20.0, 30.0, 30.0, 0.0),
    seg(24.0, 0.0, 0.0, 0.0),
    seg(26.0, 0.0, 40.0, 4.0),
    seg(30.0, 25.0, 25.0, 0.0),
    seg(34.0, 45.0, 45.0, 0.0),
    seg(38.0, 10.0, 10.0, 0.0),
];
const CYCLE_S: f64 = 40.0;

/// The frequency setpoint (Hz) of the test-stand program at time `t_s`.
pub fn setpoint_hz(t_s: f64) -> f64 {
    let t = t_s.max(0.0) % CYCLE_S;
    let mut current = PROGRAM[0];
    for s in PROGRAM {
        if s.t_s <= t {
            current = s;
        }
    }
    let x = if current.ramp_s > 0.0 { ((t - current.t_s) / current.ramp_s).clamp(0.0, 1.0) } else { 1.0 };
    current.from_hz + (current.to_hz - current.from_hz) * x
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn starts_from_standstill_and_repeats() {
        assert_eq!(setpoint_hz(0.5), 0.0);
        assert_eq!(setpoint_hz(2.0), 20.0);
        assert_eq!(setpoint_hz(11.0), 42.5);
        assert_eq!(setpoint_hz(42.0), 20.0);
        assert_eq!(setpoint_hz(25.0), 0.0);
    }
}

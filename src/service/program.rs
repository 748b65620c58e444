//! PURE: the demo's target-speed program, so that its recordings hold enough excitation to analyse (steps up and
//! down, a ramp, a slow stretch), repeating every [`CYCLE_S`].

/// One cycle of the program (s).
pub const CYCLE_S: f64 = 30.0;

/// The program as (start s, end s, factor at start, factor at end) of the base target, within a cycle.
pub const SEGMENTS: [(f64, f64, f64, f64); 7] = [
    (0.0, 5.0, 1.0, 1.0),
    (5.0, 9.0, 1.3, 1.3),
    (9.0, 13.0, 0.6, 0.6),
    (13.0, 18.0, 0.6, 1.3),
    (18.0, 22.0, 0.9, 0.9),
    (22.0, 25.0, 0.3, 0.3),
    (25.0, 30.0, 1.1, 1.1),
];

/// The target (rad/s) at `t_s` seconds into the program, for a base target `base_rad_s`, at most `max_rad_s`.
pub fn demo_target_rad_s(t_s: f64, base_rad_s: f64, max_rad_s: f64) -> f64 {
    let t = t_s.max(0.0) % CYCLE_S;
    let factor =
        SEGMENTS.iter().find(|s| t >= s.0 && t < s.1).map_or(1.0, |&(a, b, fa, fb)| fa + (fb - fa) * (t - a) / (b - a));
    (factor * base_rad_s).clamp(0.0, max_rad_s.max(0.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_program_steps_ramps_repeats_and_stays_within_the_limit() {
        assert_eq!(demo_target_rad_s(1.0, 40.0, 75.0), 40.0);
        assert_eq!(demo_target_rad_s(6.0, 40.0, 75.0), 52.0);
        assert!((demo_target_rad_s(15.5, 40.0, 75.0) - 38.0).abs() < 1e-9, "mid-ramp");
        assert_eq!(demo_target_rad_s(23.0, 40.0, 75.0), 12.0);
        assert_eq!(demo_target_rad_s(36.0, 40.0, 75.0), demo_target_rad_s(6.0, 40.0, 75.0));
        assert_eq!(demo_target_rad_s(6.0, 40.0, 50.0), 50.0);
        // the segments tile the cycle
        assert!(SEGMENTS.windows(2).all(|w| w[0].1 == w[1].0) && SEGMENTS[6].1 == CYCLE_S);
    }
}

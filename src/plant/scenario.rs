//! Seeded test-stand scenarios for batteries: setpoint programs, load programs the estimator is not told, and the
//! wrong starting J and B it must recover from. Pure: a seed gives the same scenario on every machine.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Uniform};

use super::load::LoadSpec;

/// What kind of program a scenario runs: the families of the estimator battery (docs/estimator.md).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Family {
    /// Setpoint steps and ramps over 0–55 Hz, brake steps of 0–30 N·m every 1–4 s.
    Brake,
    /// As `Brake`, with a large load landing 0.3–1 s after the first setpoint step, while the shaft accelerates.
    StartUp,
    /// Setpoint steps and ramps at 1.5–30 Hz, brake steps of 0–15 N·m every 1–4 s.
    Slow,
    /// Setpoint program over 0–55 Hz, a load ramp between two levels.
    Ramp,
    /// Setpoint program over 0–55 Hz, a slowly increasing load (the paper's Fig. 3).
    Trend,
    /// Setpoint program over 0–55 Hz, a sinusoidal load.
    Sine,
}

impl Family {
    pub const ALL: [Family; 6] =
        [Family::Brake, Family::StartUp, Family::Slow, Family::Ramp, Family::Trend, Family::Sine];

    pub fn name(self) -> &'static str {
        match self {
            Family::Brake => "brake",
            Family::StartUp => "start-up",
            Family::Slow => "slow",
            Family::Ramp => "ramp",
            Family::Trend => "trend",
            Family::Sine => "sine",
        }
    }
}

/// A piecewise setpoint program: from `t_s` on, the setpoint goes from the previous level to `to_hz` over
/// `ramp_s` (0 = a step) and holds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SetpointMove {
    pub t_s: f64,
    pub to_hz: f64,
    pub ramp_s: f64,
}

/// The load: brake steps (levels held from their times on) or one of the model's profiles.
#[derive(Debug, Clone, PartialEq)]
pub enum LoadProgram {
    /// `levels_nm[i]` from `times_s[i]` on; zero before the first.
    Steps {
        times_s: Vec<f64>,
        levels_nm: Vec<f64>,
    },
    Profile(LoadSpec),
}

impl LoadProgram {
    /// The load torque (N·m) at `t_s` with the motor at `omega_rad_s` and its shaft at `angle_rad`.
    pub fn torque_at(&self, t_s: f64, omega_rad_s: f64, angle_rad: f64) -> f64 {
        match self {
            LoadProgram::Steps { times_s, levels_nm } => {
                let i = times_s.partition_point(|t| *t <= t_s);
                if i == 0 { 0.0 } else { levels_nm[i - 1] }
            }
            LoadProgram::Profile(spec) => spec.torque_at(t_s, omega_rad_s, angle_rad),
        }
    }
}

/// One generated scenario.
#[derive(Debug, Clone, PartialEq)]
pub struct Scenario {
    pub seed: u64,
    pub family: Family,
    pub duration_s: f64,
    /// Setpoint moves in time order, from 0 Hz at t = 0.
    pub setpoint: Vec<SetpointMove>,
    pub load: LoadProgram,
    /// The estimator under test starts from the model's J and B times these.
    pub inertia_factor: f64,
    pub viscous_factor: f64,
}

impl Scenario {
    /// The scenario of `seed` in a family, `duration_s` long. Starting J within ×0.5…×2, B within ×0.3…×3 (log-uniform).
    pub fn generate(family: Family, seed: u64, duration_s: f64) -> Scenario {
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ (family as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15));
        let mut draw = |lo: f64, hi: f64| match Uniform::new(lo, hi) {
            Ok(u) => u.sample(&mut rng),
            Err(_) => lo,
        };
        let (lo_hz, hi_hz) = if family == Family::Slow { (1.5, 30.0) } else { (0.0, 55.0) };
        let first_move_s = draw(0.3, 1.0);
        let mut setpoint = Vec::new();
        let mut t = first_move_s;
        let mut first = true;
        while t < duration_s {
            let stop = !first && family != Family::Slow && draw(0.0, 1.0) < 0.12;
            let to_hz = if stop {
                0.0
            } else if first {
                draw((lo_hz + hi_hz) * 0.4, hi_hz)
            } else {
                draw(lo_hz.max(if family == Family::Slow { 1.5 } else { 8.0 }), hi_hz)
            };
            let ramp_s = if !first && draw(0.0, 1.0) < 0.35 { draw(0.5, 4.0) } else { 0.0 };
            setpoint.push(SetpointMove { t_s: t, to_hz, ramp_s });
            t += ramp_s + draw(1.5, 5.0);
            first = false;
        }
        let max_step_nm = if family == Family::Slow { 15.0 } else { 30.0 };
        let load = match family {
            Family::Brake | Family::StartUp | Family::Slow => {
                let mut times_s = Vec::new();
                let mut levels_nm = Vec::new();
                let mut t = if family == Family::StartUp { first_move_s + draw(0.3, 1.0) } else { draw(0.5, 4.0) };
                if family == Family::StartUp {
                    times_s.push(t);
                    levels_nm.push(draw(15.0, 30.0));
                    t += draw(1.0, 4.0);
                }
                while t < duration_s {
                    times_s.push(t);
                    levels_nm.push(draw(0.0, max_step_nm));
                    t += draw(1.0, 4.0);
                }
                LoadProgram::Steps { times_s, levels_nm }
            }
            Family::Ramp => {
                let start_s = draw(2.0, duration_s * 0.3);
                LoadProgram::Profile(LoadSpec::Ramp {
                    from_nm: draw(0.0, 10.0),
                    to_nm: draw(5.0, 25.0),
                    start_s,
                    duration_s: draw(5.0, duration_s - start_s),
                })
            }
            Family::Trend => LoadProgram::Profile(LoadSpec::Trend {
                start_nm: draw(0.0, 5.0),
                rate_nm_per_s: draw(0.1, 0.5),
                max_nm: 25.0,
            }),
            Family::Sine => LoadProgram::Profile(LoadSpec::Sine {
                mean_nm: draw(6.0, 14.0),
                amplitude_nm: draw(2.0, 6.0),
                period_s: draw(1.5, 10.0),
            }),
        };
        let inertia_factor = 2f64.powf(draw(-1.0, 1.0));
        let viscous_factor = 10f64.powf(draw(0.3f64.log10(), 3f64.log10()));
        Scenario { seed, family, duration_s, setpoint, load, inertia_factor, viscous_factor }
    }

    /// The frequency setpoint at `t_s` (Hz).
    pub fn setpoint_hz(&self, t_s: f64) -> f64 {
        let mut level = 0.0;
        for m in &self.setpoint {
            if m.t_s > t_s {
                break;
            }
            let x = if m.ramp_s > 0.0 { ((t_s - m.t_s) / m.ramp_s).clamp(0.0, 1.0) } else { 1.0 };
            level += (m.to_hz - level) * x;
        }
        level
    }

    /// A line naming the scenario, for tables and failures.
    pub fn describe(&self) -> String {
        format!(
            "{} seed {}: start J ×{:.2}, B ×{:.2}, {}",
            self.family.name(),
            self.seed,
            self.inertia_factor,
            self.viscous_factor,
            match &self.load {
                LoadProgram::Steps { times_s, .. } => format!("{} brake steps", times_s.len()),
                LoadProgram::Profile(spec) => format!("{spec:?}"),
            }
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_seed_gives_one_scenario_and_seeds_differ() {
        for family in Family::ALL {
            let a = Scenario::generate(family, 11, 60.0);
            assert_eq!(a, Scenario::generate(family, 11, 60.0));
            assert_ne!(a, Scenario::generate(family, 12, 60.0));
            assert!((0.5..=2.0).contains(&a.inertia_factor) && (0.3..=3.0).contains(&a.viscous_factor), "{a:?}");
            assert_eq!(a.setpoint_hz(0.0), 0.0);
            assert!(a.setpoint.windows(2).all(|w| w[0].t_s < w[1].t_s));
            let hi = if family == Family::Slow { 30.0 } else { 55.0 };
            assert!((0..600).all(|k| (0.0..=hi).contains(&a.setpoint_hz(k as f64 * 0.1))), "{a:?}");
        }
    }

    #[test]
    fn start_up_lands_a_large_load_while_the_shaft_accelerates() {
        let s = Scenario::generate(Family::StartUp, 3, 60.0);
        let LoadProgram::Steps { times_s, levels_nm } = &s.load else { panic!("{s:?}") };
        assert!(times_s[0] - s.setpoint[0].t_s <= 1.0 && levels_nm[0] >= 15.0, "{s:?}");
        assert_eq!(s.load.torque_at(times_s[0] - 1e-9, 0.0, 0.0), 0.0);
        assert_eq!(s.load.torque_at(times_s[0], 0.0, 0.0), levels_nm[0]);
    }

    #[test]
    fn ramps_interpolate_from_the_previous_level() {
        let s = Scenario {
            seed: 0,
            family: Family::Brake,
            duration_s: 10.0,
            setpoint: vec![
                SetpointMove { t_s: 1.0, to_hz: 20.0, ramp_s: 0.0 },
                SetpointMove { t_s: 2.0, to_hz: 40.0, ramp_s: 2.0 },
            ],
            load: LoadProgram::Profile(LoadSpec::None),
            inertia_factor: 1.0,
            viscous_factor: 1.0,
        };
        assert_eq!(s.setpoint_hz(0.5), 0.0);
        assert_eq!(s.setpoint_hz(1.5), 20.0);
        assert!((s.setpoint_hz(3.0) - 30.0).abs() < 1e-12);
        assert_eq!(s.setpoint_hz(5.0), 40.0);
    }
}

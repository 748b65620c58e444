//! Seeded test-stand scenarios for batteries: setpoint programs, load programs the estimator is not told (of time,
//! speed or shaft angle), and the wrong starting J and B it must recover from. Pure: a seed gives the same scenario
//! on every machine.

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
    // The families below are [`Family::NEW`]: added after the six above so that those keep their discriminants,
    // which seed their generators (their scenarios stay byte-identical).
    /// Setpoint program over 0–55 Hz, a fan or centrifugal pump: ∝ ω·|ω|, 5–25 N·m at top speed, plus 0–5 N·m.
    Centrifugal,
    /// Setpoint program over 0–55 Hz, a load ∝ ω (0.05–0.3 N·m·s/rad) plus 2–10 N·m.
    Linear,
    /// Setpoint program over 0–55 Hz, a reciprocating machine behind a gearbox: periodic in the shaft angle (0.1–0.6
    /// cycles a motor turn), amplitude 2–8 N·m around 5–15 N·m; its period in time follows the speed.
    Gearbox,
    /// Setpoint program over 0–55 Hz, a smooth random load that never repeats: sd 2–6 N·m, correlation 0.3–3 s,
    /// around 5–15 N·m.
    Random,
    /// Setpoint program over 0–55 Hz, impacts: 1–4 N·m with half-sine pulses of 10–30 N·m, 20–150 ms wide, one
    /// every 0.5–3 s on average.
    Impacts,
    /// Setpoint program over 0–55 Hz, two sines of unrelated periods (1.5–12 s).
    TwoSines,
    /// As `Brake`, plus one of the centrifugal, random or gearbox loads (drawn by the seed).
    Mixed,
}

/// The reference plant's motor speed at the setpoint programs' top, 55 Hz (2 pole pairs, 16 over 32 cm³): where a
/// centrifugal family's torque is said.
pub const TOP_SPEED_RAD_S: f64 = 86.4;

impl Family {
    /// The battery's families of time-only loads (the gates of docs/estimator.md are measured on these).
    pub const ALL: [Family; 6] =
        [Family::Brake, Family::StartUp, Family::Slow, Family::Ramp, Family::Trend, Family::Sine];
    /// The families of loads that depend on the plant's state (speed, shaft angle) or never repeat.
    pub const NEW: [Family; 7] = [
        Family::Centrifugal,
        Family::Linear,
        Family::Gearbox,
        Family::Random,
        Family::Impacts,
        Family::TwoSines,
        Family::Mixed,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Family::Brake => "brake",
            Family::StartUp => "start-up",
            Family::Slow => "slow",
            Family::Ramp => "ramp",
            Family::Trend => "trend",
            Family::Sine => "sine",
            Family::Centrifugal => "centrifugal",
            Family::Linear => "linear",
            Family::Gearbox => "gearbox",
            Family::Random => "random",
            Family::Impacts => "impacts",
            Family::TwoSines => "two-sines",
            Family::Mixed => "mixed",
        }
    }

    /// The family of a [`Family::name`], from [`Family::ALL`] or [`Family::NEW`].
    pub fn from_name(name: &str) -> Option<Family> {
        Family::ALL.into_iter().chain(Family::NEW).find(|f| f.name() == name)
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

/// The load: brake steps (levels held from their times on), one of the model's profiles, or a sum of loads.
#[derive(Debug, Clone, PartialEq)]
pub enum LoadProgram {
    /// `levels_nm[i]` from `times_s[i]` on; zero before the first.
    Steps {
        times_s: Vec<f64>,
        levels_nm: Vec<f64>,
    },
    Profile(LoadSpec),
    /// Loads acting together (a brake on a shaft that also drives a fan, say).
    Sum(Vec<LoadProgram>),
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
            LoadProgram::Sum(parts) => parts.iter().map(|p| p.torque_at(t_s, omega_rad_s, angle_rad)).sum(),
        }
    }

    /// Names the load for tables: the brake steps counted, a time-only profile as its fields (as always), a new
    /// kind briefly.
    pub fn describe(&self) -> String {
        match self {
            LoadProgram::Steps { times_s, .. } => format!("{} brake steps", times_s.len()),
            LoadProgram::Profile(spec) => match spec {
                LoadSpec::Constant { torque_nm } => format!("{torque_nm:.1} N·m"),
                LoadSpec::Speed { constant_nm, linear_nm_s_rad, quadratic_nm_s2_rad2 } => {
                    let mut d = format!("speed {constant_nm:.1} N·m");
                    if *linear_nm_s_rad != 0.0 {
                        d += &format!(" + {linear_nm_s_rad:.3}·ω");
                    }
                    if *quadratic_nm_s2_rad2 != 0.0 {
                        d += &format!(" + {quadratic_nm_s2_rad2:.5}·ω|ω|");
                    }
                    d
                }
                LoadSpec::Centrifugal { torque_nm, at_rad_s } => {
                    format!("centrifugal {torque_nm:.1} N·m at {at_rad_s:.1} rad/s")
                }
                LoadSpec::ShaftAngle { mean_nm, amplitude_nm, cycles_per_rev } => {
                    format!("shaft angle {mean_nm:.1} ± {amplitude_nm:.1} N·m, {cycles_per_rev:.3} cycles/rev")
                }
                LoadSpec::Random { mean_nm, sd_nm, correlation_s, .. } => {
                    format!("random {mean_nm:.1} N·m sd {sd_nm:.1}, {correlation_s:.2} s")
                }
                LoadSpec::Impacts { base_nm, peak_nm, width_s, mean_interval_s, .. } => format!(
                    "impacts {base_nm:.1} N·m + {peak_nm:.1} N·m × {:.0} ms every {mean_interval_s:.2} s",
                    width_s * 1e3
                ),
                LoadSpec::Sines { mean_nm, amplitudes_nm, periods_s } => {
                    let parts: Vec<String> =
                        amplitudes_nm.iter().zip(periods_s).map(|(a, p)| format!("{a:.1} N·m/{p:.2} s")).collect();
                    format!("sines {mean_nm:.1} N·m + {}", parts.join(" + "))
                }
                _ => format!("{spec:?}"),
            },
            LoadProgram::Sum(parts) => parts.iter().map(LoadProgram::describe).collect::<Vec<_>>().join(" + "),
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
        let first_move_s = draw(0.3, 1.0);
        let setpoint = setpoint_moves(family, duration_s, first_move_s, &mut draw);
        let load = load_program(family, duration_s, first_move_s, &mut draw);
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
            self.load.describe()
        )
    }
}

/// The setpoint moves from `first_move_s` to `duration_s`: steps, some ramped, some to a stop (not in the slow family).
fn setpoint_moves(
    family: Family,
    duration_s: f64,
    first_move_s: f64,
    draw: &mut dyn FnMut(f64, f64) -> f64,
) -> Vec<SetpointMove> {
    let (lo_hz, hi_hz) = if family == Family::Slow { (1.5, 30.0) } else { (0.0, 55.0) };
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
    setpoint
}

/// The family's load program (`first_move_s`: when the drive first starts).
fn load_program(
    family: Family,
    duration_s: f64,
    first_move_s: f64,
    draw: &mut dyn FnMut(f64, f64) -> f64,
) -> LoadProgram {
    let max_step_nm = if family == Family::Slow { 15.0 } else { 30.0 };
    match family {
        Family::Brake | Family::StartUp | Family::Slow => {
            let mut times_s = Vec::new();
            let mut levels_nm = Vec::new();
            let mut t = if family == Family::StartUp { first_move_s + draw(0.3, 1.0) } else { draw(0.5, 4.0) };
            if family == Family::StartUp {
                times_s.push(t);
                levels_nm.push(draw(15.0, 30.0));
                t += draw(1.0, 4.0);
            }
            steps(times_s, levels_nm, t, duration_s, max_step_nm, draw)
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
        Family::Centrifugal => LoadProgram::Sum(vec![
            LoadProgram::Profile(LoadSpec::Constant { torque_nm: draw(0.0, 5.0) }),
            centrifugal(draw),
        ]),
        Family::Linear => LoadProgram::Profile(LoadSpec::Speed {
            constant_nm: draw(2.0, 10.0),
            linear_nm_s_rad: draw(0.05, 0.3),
            quadratic_nm_s2_rad2: 0.0,
        }),
        Family::Gearbox => gearbox(draw),
        Family::Random => {
            let seed = hash_seed(draw);
            random(draw, seed)
        }
        Family::Impacts => {
            let seed = hash_seed(draw);
            LoadProgram::Profile(LoadSpec::Impacts {
                base_nm: draw(1.0, 4.0),
                peak_nm: draw(10.0, 30.0),
                width_s: draw(0.02, 0.15),
                mean_interval_s: draw(0.5, 3.0),
                seed,
            })
        }
        Family::TwoSines => two_sines(draw),
        Family::Mixed => {
            let t = draw(0.5, 4.0);
            let brake = steps(Vec::new(), Vec::new(), t, duration_s, max_step_nm, draw);
            let other = match (draw(0.0, 3.0) as u32).min(2) {
                0 => centrifugal(draw),
                1 => {
                    let seed = hash_seed(draw);
                    random(draw, seed)
                }
                _ => gearbox(draw),
            };
            LoadProgram::Sum(vec![brake, other])
        }
    }
}

/// Load steps after `times_s` and `levels_nm`, from `t` to `duration_s`: a level up to `max_step_nm` every 1 to 4 s.
fn steps(
    mut times_s: Vec<f64>,
    mut levels_nm: Vec<f64>,
    mut t: f64,
    duration_s: f64,
    max_step_nm: f64,
    draw: &mut dyn FnMut(f64, f64) -> f64,
) -> LoadProgram {
    while t < duration_s {
        times_s.push(t);
        levels_nm.push(draw(0.0, max_step_nm));
        t += draw(1.0, 4.0);
    }
    LoadProgram::Steps { times_s, levels_nm }
}

/// Two sines of unrelated periods: the second is redrawn while the two are near a ratio of small whole numbers.
fn two_sines(draw: &mut dyn FnMut(f64, f64) -> f64) -> LoadProgram {
    let p1 = draw(1.5, 12.0);
    let related = |p2: f64| {
        let r = p1.max(p2) / p1.min(p2);
        [1.0, 2.0, 3.0, 4.0, 1.5, 2.5, 4.0 / 3.0, 5.0 / 3.0, 5.0 / 4.0].iter().any(|q| (r / q - 1.0).abs() < 0.06)
    };
    let mut p2 = draw(1.5, 12.0);
    for _ in 0..20 {
        if !related(p2) {
            break;
        }
        p2 = draw(1.5, 12.0);
    }
    LoadProgram::Profile(LoadSpec::Sines {
        mean_nm: draw(6.0, 14.0),
        amplitudes_nm: vec![draw(2.0, 5.0), draw(1.5, 4.0)],
        periods_s: vec![p1, p2],
    })
}

/// The seed of a hashed load (random, impacts): a whole number below 2⁵³.
fn hash_seed(draw: &mut dyn FnMut(f64, f64) -> f64) -> u64 {
    (draw(0.0, 1.0) * 9_007_199_254_740_992.0) as u64
}

/// A fan: 5–25 N·m at [`TOP_SPEED_RAD_S`].
fn centrifugal(draw: &mut dyn FnMut(f64, f64) -> f64) -> LoadProgram {
    LoadProgram::Profile(LoadSpec::Centrifugal { torque_nm: draw(5.0, 25.0), at_rad_s: TOP_SPEED_RAD_S })
}

/// A reciprocating machine behind a gearbox of ratio 1.7–10.
fn gearbox(draw: &mut dyn FnMut(f64, f64) -> f64) -> LoadProgram {
    LoadProgram::Profile(LoadSpec::ShaftAngle {
        mean_nm: draw(5.0, 15.0),
        amplitude_nm: draw(2.0, 8.0),
        cycles_per_rev: draw(0.1, 0.6),
    })
}

/// A smooth random load around 5–15 N·m.
fn random(draw: &mut dyn FnMut(f64, f64) -> f64, seed: u64) -> LoadProgram {
    LoadProgram::Profile(LoadSpec::Random {
        mean_nm: draw(5.0, 15.0),
        sd_nm: draw(2.0, 6.0),
        correlation_s: draw(0.3, 3.0),
        seed,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_seed_gives_one_scenario_and_seeds_differ() {
        for family in Family::ALL.into_iter().chain(Family::NEW) {
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

    #[test]
    fn every_family_is_found_by_its_name_and_the_old_ones_keep_their_seeds() {
        let all: Vec<Family> = Family::ALL.into_iter().chain(Family::NEW).collect();
        for f in &all {
            assert_eq!(Family::from_name(f.name()), Some(*f));
        }
        assert_eq!(Family::from_name("fan"), None);
        // the discriminant seeds a family's generator: the six of ALL are 0…5 as they always were
        assert_eq!(Family::ALL.map(|f| f as u64), [0, 1, 2, 3, 4, 5]);
    }

    /// The load of a scenario at a steady speed ω (θ = ω·t) over `seconds`, every 10 ms.
    fn at_steady_speed(s: &Scenario, omega: f64, seconds: f64) -> Vec<f64> {
        (0..(seconds * 100.0) as usize)
            .map(|k| {
                let t = k as f64 * 0.01;
                s.load.torque_at(t, omega, omega * t)
            })
            .collect()
    }

    #[test]
    fn the_new_loads_are_finite_and_named() {
        for family in Family::NEW {
            for seed in 1..20 {
                let s = Scenario::generate(family, seed, 60.0);
                for omega in [-20.0, 0.0, 40.0, 90.0] {
                    assert!(at_steady_speed(&s, omega, 60.0).iter().all(|v| v.is_finite()), "{s:?}");
                }
                let d = s.describe();
                assert!(d.starts_with(family.name()) && !d.contains("Profile"), "{d}");
            }
        }
        let mixed = Scenario::generate(Family::Mixed, 4, 60.0);
        let LoadProgram::Sum(parts) = &mixed.load else { panic!("{mixed:?}") };
        assert!(matches!(parts[..], [LoadProgram::Steps { .. }, LoadProgram::Profile(_)]), "{mixed:?}");
        assert!(mixed.describe().contains("brake steps + "), "{}", mixed.describe());
    }

    #[test]
    fn a_centrifugal_load_grows_with_speed() {
        for seed in 1..10 {
            let s = Scenario::generate(Family::Centrifugal, seed, 60.0);
            let at = |w: f64| s.load.torque_at(10.0, w, 0.0);
            assert!(at(20.0) < at(40.0) && at(40.0) < at(80.0), "{s:?}");
            // ∝ ω² above its constant part
            assert!(((at(80.0) - at(0.0)) / (at(40.0) - at(0.0)) - 4.0).abs() < 1e-9, "{s:?}");
            assert!((5.0..=25.0).contains(&(at(TOP_SPEED_RAD_S) - at(0.0))), "{s:?}");
        }
        let l = Scenario::generate(Family::Linear, 2, 60.0);
        let at = |w: f64| l.load.torque_at(10.0, w, 0.0);
        assert!(((at(80.0) - at(0.0)) / (at(40.0) - at(0.0)) - 2.0).abs() < 1e-9, "{l:?}");
    }

    /// The mean time between upward crossings of the mean.
    fn period_s(v: &[f64]) -> f64 {
        let mean = v.iter().sum::<f64>() / v.len() as f64;
        let ups: Vec<usize> = (1..v.len()).filter(|&k| v[k - 1] < mean && v[k] >= mean).collect();
        (ups[ups.len() - 1] - ups[0]) as f64 * 0.01 / (ups.len() - 1) as f64
    }

    #[test]
    fn a_gearbox_load_turns_with_the_shaft_so_its_period_halves_when_the_speed_doubles() {
        for seed in 1..6 {
            let s = Scenario::generate(Family::Gearbox, seed, 60.0);
            let LoadProgram::Profile(LoadSpec::ShaftAngle { cycles_per_rev, .. }) = s.load else { panic!("{s:?}") };
            let (slow, fast) =
                (period_s(&at_steady_speed(&s, 20.0, 120.0)), period_s(&at_steady_speed(&s, 40.0, 120.0)));
            assert!((slow / fast - 2.0).abs() < 0.05, "{s:?}: {slow} s at 20 rad/s, {fast} s at 40");
            let expected = std::f64::consts::TAU / (cycles_per_rev * 20.0);
            assert!((slow / expected - 1.0).abs() < 0.02, "{s:?}: {slow} s, expected {expected}");
        }
    }

    #[test]
    fn a_random_load_never_repeats_and_has_about_its_sd() {
        for seed in 1..6 {
            let s = Scenario::generate(Family::Random, seed, 60.0);
            let LoadProgram::Profile(LoadSpec::Random { sd_nm, correlation_s, .. }) = s.load else { panic!("{s:?}") };
            let v = at_steady_speed(&s, 30.0, 1200.0);
            let mean = v.iter().sum::<f64>() / v.len() as f64;
            let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / v.len() as f64;
            assert!((var.sqrt() / sd_nm - 1.0).abs() < 0.15, "{s:?}: sd {}", var.sqrt());
            // no lag of 1–20 s brings it back, once past the correlation time's own smoothing (half of it: value
            // noise is still 0.66-correlated there)
            let from = (100.0f64).max(50.0 * correlation_s) as usize;
            for lag in (from..=2000).step_by(25) {
                let c = (0..v.len() - lag).map(|k| (v[k] - mean) * (v[k + lag] - mean)).sum::<f64>()
                    / ((v.len() - lag) as f64 * var);
                assert!(c < 0.8, "{s:?}: autocorrelation {c:.2} at {} s", lag as f64 * 0.01);
            }
        }
    }
}

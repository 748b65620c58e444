//! `analyze` on slow programs it was not built on (issue 33): dry friction, low-speed friction and a dead time, alone
//! and together, on setpoint programs of other speed ranges and dwell times than the project's own
//! ([`analysis::slow_program_sweep`](super::analysis)), with brake steps and the load recorded.

use hydrolens::analysis::{self, Analysis, Options};
use hydrolens::plant::PlantModel;
use hydrolens::plant::effects::{CoulombFriction, DeadTime, StribeckFriction};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Uniform};

/// A uniform draw in [lo, hi).
fn draw(rng: &mut ChaCha8Rng, lo: f64, hi: f64) -> f64 {
    Uniform::new(lo, hi).map_or(lo, |u| u.sample(rng))
}

/// A setpoint program: steps and ramps between `lo_hz` and `hi_hz`, each level held `dwell_s`; and a brake
/// program of 3–30 N·m steps every 1–4 s. Pure functions of t, drawn from `seed`.
struct Program {
    /// (time, from Hz, to Hz, ramp s): the moves.
    moves: Vec<(f64, f64, f64, f64)>,
    /// (time, N·m): the brake's steps.
    brake: Vec<(f64, f64)>,
}

impl Program {
    fn generate(seed: u64, (lo_hz, hi_hz): (f64, f64), (dwell_lo, dwell_hi): (f64, f64), run_s: f64) -> Program {
        let mut rng = ChaCha8Rng::seed_from_u64(seed.wrapping_mul(0x2545_f491_4f6c_dd1d) ^ 0x33);
        let mut moves = Vec::new();
        let (mut t, mut at) = (draw(&mut rng, 0.3, 1.0), 0.0);
        while t < run_s {
            // half the levels in the lowest fifth of the range: the motor spends a good share of its time slow
            let to = if draw(&mut rng, 0.0, 1.0) < 0.3 {
                draw(&mut rng, lo_hz, lo_hz + 0.2 * (hi_hz - lo_hz))
            } else {
                draw(&mut rng, lo_hz, hi_hz)
            };
            let ramp = if draw(&mut rng, 0.0, 1.0) < 0.4 { draw(&mut rng, 0.5, 3.0) } else { 0.0 };
            moves.push((t, at, to, ramp));
            at = to;
            t += ramp + draw(&mut rng, dwell_lo, dwell_hi);
        }
        let mut brake = Vec::new();
        let mut t = 0.0;
        while t < run_s {
            brake.push((t, draw(&mut rng, 3.0, 30.0)));
            t += draw(&mut rng, 1.0, 4.0);
        }
        Program { moves, brake }
    }

    fn setpoint_hz(&self, t: f64) -> f64 {
        let Some(&(t0, from, to, ramp)) = self.moves.iter().rev().find(|m| m.0 <= t) else { return 0.0 };
        if ramp > 0.0 && t < t0 + ramp { from + (to - from) * (t - t0) / ramp } else { to }
    }

    fn load_nm(&self, t: f64) -> f64 {
        self.brake.iter().rev().find(|b| b.0 <= t).map_or(0.0, |b| b.1)
    }
}

/// Simulates `truth` on the program for `run_s` at 1 kHz (load recorded) and analyses it with the nominal model.
fn analysed(truth: &PlantModel, program: &Program, seed: u64, run_s: f64) -> Analysis {
    let inputs = hydrolens::plant::simulate::Inputs {
        setpoint_hz: &|t| program.setpoint_hz(t),
        load_nm: &|t, _, _| program.load_nm(t),
    };
    let rec = hydrolens::recording::simulated::run(truth, run_s, seed, &inputs, &mut |_| {}).expect("simulable");
    analysis::analyze(&rec, &PlantModel::reference(), &Options::default(), &mut |_| {}).expect("analysable")
}

/// The concealed effects of a case: Coulomb N·m, Stribeck (breakaway N·m above nothing, ω_s), dead time ms.
#[derive(Debug, Clone, Copy)]
struct Hidden {
    coulomb: Option<f64>,
    stribeck: Option<(f64, f64)>,
    dead_time: Option<f64>,
}

impl Hidden {
    fn truth(&self) -> PlantModel {
        let mut m = PlantModel::reference();
        m.effects.coulomb_friction = self.coulomb.map(|c| CoulombFriction { torque_nm: c });
        m.effects.stribeck_friction = self.stribeck.map(|(b, w)| StribeckFriction { breakaway_nm: b, speed_rad_s: w });
        m.effects.dead_time = self.dead_time.map(|ms| DeadTime { ms });
        m
    }

    fn ids(&self) -> Vec<&'static str> {
        let mut v = Vec::new();
        if self.coulomb.is_some() {
            v.push("coulomb_friction");
        }
        if self.dead_time.is_some() {
            v.push("dead_time");
        }
        if self.stribeck.is_some() {
            v.push("stribeck_friction");
        }
        v
    }
}

/// One case's outcome: named (sorted), per effect the relative error of its key parameter, B's relative error.
struct Outcome {
    named: Vec<String>,
    errors: Vec<(&'static str, Option<f64>)>,
    viscous_error: f64,
    /// B's 95 % interval, relative to the truth.
    viscous_interval: Option<(f64, f64)>,
}

fn judge(a: &Analysis, hidden: &Hidden) -> Outcome {
    let mut named: Vec<String> = a.findings.iter().map(|f| f.effect.clone()).collect();
    named.sort();
    let value = |effect: &str, name: &str| a.findings.iter().find(|f| f.effect == effect).map(|f| f.parameters[name]);
    let mut errors = Vec::new();
    if let Some(c) = hidden.coulomb {
        errors.push(("coulomb_friction", value("coulomb_friction", "torque_nm").map(|v| v / c - 1.0)));
    }
    if let Some((b, _)) = hidden.stribeck {
        errors.push(("stribeck_friction", value("stribeck_friction", "breakaway_nm").map(|v| v / b - 1.0)));
    }
    if let Some(ms) = hidden.dead_time {
        errors.push(("dead_time", value("dead_time", "ms").map(|v| v / ms - 1.0)));
    }
    let b_true = PlantModel::reference().motor.viscous_nm_s_rad;
    let viscous_interval = a
        .improved
        .confidence_intervals
        .get("viscous_nm_s_rad")
        .map(|ci| (ci.low / b_true - 1.0, ci.high / b_true - 1.0));
    Outcome { named, errors, viscous_error: a.improved_model.motor.viscous_nm_s_rad / b_true - 1.0, viscous_interval }
}

impl Outcome {
    /// All hidden effects named within ±30 %, nothing else named, B within ±25 %.
    fn holds(&self, hidden: &Hidden) -> bool {
        self.named == hidden.ids()
            && self.errors.iter().all(|(_, e)| e.is_some_and(|e| e.abs() <= 0.3))
            && self.viscous_error.abs() <= 0.25
    }
}

/// Issue 33's recording: 60 s at 1 kHz, steps and ramps at 1.5–12 Hz, brake steps of 3–30 N·m, Coulomb 2 N·m,
/// Stribeck breakaway 6 N·m at 3 rad/s and a 25 ms dead time: all three are named within ±30 % and B ends within
/// ±25 % of the truth (before, only the Stribeck friction was named, and B came out +421 %).
#[test]
fn coulomb_stribeck_and_dead_time_on_a_slow_program_are_all_named() {
    let hidden = Hidden { coulomb: Some(2.0), stribeck: Some((6.0, 3.0)), dead_time: Some(25.0) };
    let program = Program::generate(7, (1.5, 12.0), (1.5, 4.0), 60.0);
    let a = analysed(&hidden.truth(), &program, 7, 60.0);
    let o = judge(&a, &hidden);
    let tried: Vec<String> = a
        .candidates
        .iter()
        .map(|c| {
            format!(
                "{} {} {:?} {:?} {:?} {}",
                c.round, c.effect, c.validation_score, c.delta_bic, c.cross_validation_score, c.kept
            )
        })
        .collect();
    println!("B {:+.0} % of the truth", 100.0 * o.viscous_error);
    assert_eq!(o.named, hidden.ids(), "{tried:#?}");
    assert!(o.errors.iter().all(|(_, e)| e.is_some_and(|e| e.abs() <= 0.3)), "{:?}", o.errors);
    assert!(o.viscous_error.abs() <= 0.25, "B {:+.0} % of the truth", 100.0 * o.viscous_error);
}

/// The sweep of issue 33: programs of other speed ranges and dwell times, one, two and three effects of drawn
/// sizes, clean runs; tuned and held-out seeds, named / missed / false per effect and B against the truth. It asks
/// what the issue asks: at least 90 % of the runs on seeds not tuned on hold (the tuned ones are printed).
#[test]
#[ignore = "sweep: cargo test --release --test it -- --ignored slow_programs::sweep --nocapture"]
fn sweep() {
    let programs =
        [((1.5, 12.0), (1.5, 4.0)), ((1.0, 8.0), (3.0, 8.0)), ((2.0, 20.0), (0.8, 2.5)), ((1.5, 30.0), (2.0, 5.0))];
    let mut failures = Vec::new();
    let mut untuned = None;
    // SLOW_CASES="seed:program,…" runs only those cases (diagnosis), printing each candidate and the improved model
    let only: Option<Vec<(u64, usize)>> = std::env::var("SLOW_CASES").ok().map(|v| {
        v.split(',')
            .filter_map(|c| c.split_once(':'))
            .filter_map(|(a, b)| Some((a.trim().parse().ok()?, b.trim().parse().ok()?)))
            .collect()
    });
    // SLOW_SET=name runs one seed set
    let only_set = std::env::var("SLOW_SET").ok();
    // 201–206 were added after the method met the issue on 101–106, and run once
    for (set, seeds) in [("tuned", 1u64..=3), ("held-out", 101u64..=106), ("fresh", 201u64..=206)] {
        if only_set.as_ref().is_some_and(|o| o != set) {
            continue;
        }
        println!(
            "\n**{set}**\n\n| seed | program Hz, dwell s | hidden | named | errors | B (95 %) |\n|---|---|---|---|---|---|"
        );
        let (mut held, mut runs, mut b_ok, mut b_covered) = (0, 0, 0, 0);
        // per effect: named (hidden and named within ±30 %), off (named, outside ±30 %), missed, false
        let mut tally: std::collections::BTreeMap<&str, [usize; 4]> = Default::default();
        for seed in seeds {
            let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5eed);
            for (k, &(range, dwell)) in programs.iter().enumerate() {
                let scale = draw(&mut rng, 0.6, 1.6);
                let kind = draw(&mut rng, 0.0, 8.0) as u32;
                let hidden = Hidden {
                    coulomb: (kind & 1 != 0).then_some(2.0 * scale),
                    stribeck: (kind & 2 != 0).then_some((6.0 * scale, draw(&mut rng, 2.0, 4.5))),
                    dead_time: (kind & 4 != 0).then_some(draw(&mut rng, 12.0, 40.0)),
                };
                if only.as_ref().is_some_and(|o| !o.contains(&(seed, k))) {
                    continue;
                }
                let program = Program::generate(seed * 10 + k as u64, range, dwell, 60.0);
                let a = analysed(&hidden.truth(), &program, seed * 10 + k as u64, 60.0);
                if only.is_some() {
                    println!("hidden {hidden:?}");
                    for c in &a.candidates {
                        println!(
                            "  round {} {} val {:?} ΔBIC {:?} cv {:?} regime {:?} kept {}",
                            c.round,
                            c.effect,
                            c.validation_score,
                            c.delta_bic,
                            c.cross_validation_score,
                            c.regime_drop,
                            c.kept
                        );
                    }
                    println!(
                        "  baseline cv {:?} improved cv {:?}",
                        a.baseline.cross_validation_score, a.improved.cross_validation_score
                    );
                    for u in &a.unexplained {
                        println!("  unexplained {u:?}");
                    }
                    println!("  improved errors {:?}", a.improved.validation);
                    let m = &a.improved_model;
                    println!(
                        "  improved J {} B {} effects {:?}",
                        m.motor.inertia_kg_m2, m.motor.viscous_nm_s_rad, m.effects
                    );
                }
                let o = judge(&a, &hidden);
                let ok = o.holds(&hidden);
                b_ok += usize::from(o.viscous_error.abs() <= 0.25);
                b_covered += usize::from(o.viscous_interval.is_some_and(|(lo, hi)| lo <= 0.0 && 0.0 <= hi));
                for id in ["coulomb_friction", "dead_time", "stribeck_friction"] {
                    let t = tally.entry(id).or_default();
                    match (o.errors.iter().find(|e| e.0 == id), o.named.iter().any(|n| n == id)) {
                        (Some((_, Some(e))), _) => t[if e.abs() <= 0.3 { 0 } else { 1 }] += 1,
                        (Some((_, None)), _) => t[2] += 1,
                        (None, true) => t[3] += 1,
                        (None, false) => {}
                    }
                }
                runs += 1;
                held += usize::from(ok);
                let errors: Vec<String> = o
                    .errors
                    .iter()
                    .map(|(id, e)| format!("{id} {}", e.map_or("missed".into(), |e| format!("{:+.0} %", 100.0 * e))))
                    .collect();
                let interval = o
                    .viscous_interval
                    .map_or(String::new(), |(lo, hi)| format!(" ({:+.0}…{:+.0} %)", 100.0 * lo, 100.0 * hi));
                println!(
                    "| {seed} | {range:?}, {dwell:?} | {:?} | {} | {} | {:+.0} %{interval}{} |",
                    hidden.ids(),
                    o.named.join(", "),
                    errors.join("; "),
                    100.0 * o.viscous_error,
                    if ok { "" } else { " ✗" }
                );
                if !ok {
                    failures.push(format!("{set} seed {seed} program {k}"));
                }
                for f in a.findings.iter().filter(|f| !hidden.ids().contains(&f.effect.as_str())) {
                    println!(
                        "  (not hidden: {} {:?}, validated on {})",
                        f.effect, f.parameters, f.evidence.validated_on
                    );
                }
            }
        }
        println!(
            "\n{set}: {held}/{runs} hold (all hidden named within ±30 %, nothing else, B within ±25 %); B within ±25 %: {b_ok}/{runs}; B's 95 % interval holds the truth: {b_covered}/{runs}"
        );
        if set != "tuned" && only.is_none() {
            let (h, r) = untuned.unwrap_or((0, 0));
            untuned = Some((h + held, r + runs));
        }
        println!(
            "\n| effect | named within ±30 % | named, outside | missed | named, not hidden |\n|---|---|---|---|---|"
        );
        for (id, t) in &tally {
            println!("| {id} | {} | {} | {} | {} |", t[0], t[1], t[2], t[3]);
        }
    }
    println!("failures: {failures:?}");
    if let Some((held, runs)) = untuned {
        assert!(
            10 * held >= 9 * runs,
            "{held} of {runs} runs on seeds not tuned on hold, fewer than 90 %: {failures:?}"
        );
    }
}

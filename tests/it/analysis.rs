//! `analyze` end to end: effects concealed in test-stand runs are named, fitted and proven; clean runs name nothing;
//! the real EMPS recording gives the published friction model through the same code path.

use std::process::Command;
use std::sync::LazyLock;

use hydrolens::analysis::{self, Analysis, Options};
use hydrolens::plant::PlantModel;
use hydrolens::plant::effects::{
    CoulombFriction, DeadTime, EntrainedAir, InternalLeakage, MotorSlip, StribeckFriction, TorqueOffset,
};

use crate::support;

/// Length of the concealed-effect runs: two test-stand cycles, so the validation segment (last 30 %) holds steps,
/// ramps and a standstill.
const RUN_S: f64 = 80.0;

/// Simulates the reference plant with `effect` switched on and analyses it with the nominal reference model.
fn concealed(effect: impl Fn(&mut PlantModel), seed: u64) -> Analysis {
    let mut truth = PlantModel::reference();
    effect(&mut truth);
    let rec = hydrolens::recording::simulated::test_stand(&truth, RUN_S, seed, &mut |_| {}).expect("simulable");
    analysis::analyze(&rec, &PlantModel::reference(), &Options::default(), &mut |_| {}).expect("analysable")
}

fn named(a: &Analysis) -> Vec<&str> {
    a.findings.iter().map(|f| f.effect.as_str()).collect()
}

fn parameter(a: &Analysis, effect: &str, name: &str) -> f64 {
    let f = a.findings.iter().find(|f| f.effect == effect).unwrap_or_else(|| panic!("{effect} not named: {a:#?}"));
    f.parameters[name]
}

fn score(e: &analysis::Errors) -> f64 {
    e.omega_nrmse.powi(2) + e.dp_nrmse.unwrap_or(0.0).powi(2)
}

/// The effect is named (first), its key parameter is within 30 % of the truth, the validation error drops.
fn assert_found(a: &Analysis, effect: &str, name: &str, truth: f64) {
    assert_eq!(named(a).first().copied(), Some(effect), "{:#?}", a.findings);
    assert!(a.model_misfit.is_none(), "{:#?}", a.model_misfit);
    let fitted = parameter(a, effect, name);
    assert!((fitted - truth).abs() <= 0.3 * truth.abs(), "{effect}.{name}: fitted {fitted}, truth {truth}");
    assert!(
        score(&a.improved.validation) < 0.9 * score(&a.baseline.validation),
        "validation {:?} → {:?}",
        a.baseline.validation,
        a.improved.validation
    );
}

#[test]
fn concealed_coulomb_friction() {
    for (seed, tc) in [(11, 0.5), (12, 0.7)] {
        let a = concealed(|m| m.effects.coulomb_friction = Some(CoulombFriction { torque_nm: tc }), seed);
        assert_found(&a, "coulomb_friction", "torque_nm", tc);
    }
}

#[test]
fn concealed_stribeck_friction() {
    for (seed, ts, ws) in [(13, 1.5, 3.0), (14, 2.0, 2.0)] {
        let a = concealed(
            |m| m.effects.stribeck_friction = Some(StribeckFriction { breakaway_nm: ts, speed_rad_s: ws }),
            seed,
        );
        assert_found(&a, "stribeck_friction", "breakaway_nm", ts);
        assert!(a.findings[0].evidence.where_it_shows.contains("low speed"), "{:#?}", a.findings[0].evidence);
    }
}

#[test]
fn concealed_torque_offset() {
    for (seed, off) in [(15, 0.5), (16, -0.6)] {
        let a = concealed(|m| m.effects.torque_offset = Some(TorqueOffset { torque_nm: off }), seed);
        assert_found(&a, "torque_offset", "torque_nm", off);
    }
}

#[test]
fn concealed_internal_leakage() {
    for (seed, l) in [(17, 0.01), (18, 0.015)] {
        let a = concealed(|m| m.effects.internal_leakage = Some(InternalLeakage { l_min_per_bar: l }), seed);
        assert_found(&a, "internal_leakage", "l_min_per_bar", l);
        assert!(a.ambiguities.iter().any(|x| x.effects.iter().any(|e| e == "motor_slip")), "{:#?}", a.ambiguities);
    }
}

#[test]
fn concealed_dead_time() {
    for (seed, ms) in [(19, 25.0), (20, 40.0)] {
        let a = concealed(|m| m.effects.dead_time = Some(DeadTime { ms }), seed);
        assert_found(&a, "dead_time", "ms", ms);
        // located: most mismatch windows follow setpoint steps
        let after = a.mismatches.iter().filter(|m| m.condition.contains("after setpoint steps")).count();
        assert!(2 * after > a.mismatches.len(), "{:#?}", a.mismatches);
        assert!(a.findings[0].evidence.where_it_shows.contains("after setpoint steps"));
    }
}

#[test]
fn concealed_entrained_air() {
    for (seed, beta) in [(21, 5000.0), (22, 8000.0)] {
        let a = concealed(|m| m.effects.entrained_air = Some(EntrainedAir { bulk_modulus_bar: beta }), seed);
        assert_found(&a, "entrained_air", "bulk_modulus_bar", beta);
    }
}

/// Slip and extra leakage enter the flow balance identically (C = D_p²·k_s) and no recorded signal sees the pump
/// speed, so the tool names the pair's first catalogue id, reports the ambiguity, and the equivalent slip is right.
#[test]
fn concealed_motor_slip_is_named_as_its_equivalent_and_reported_ambiguous() {
    for (seed, ks) in [(23, 2.0), (24, 3.0)] {
        let a = concealed(|m| m.effects.motor_slip = Some(MotorSlip { rpm_per_nm: ks }), seed);
        assert_eq!(named(&a), vec!["internal_leakage"], "{:#?}", a.findings);
        let per_rpm = analysis::slip_as_leakage(&PlantModel::reference(), 1.0).expect("pump");
        let slip = parameter(&a, "internal_leakage", "l_min_per_bar") / per_rpm;
        assert!((slip - ks).abs() <= 0.3 * ks, "equivalent slip {slip} rpm/N·m, truth {ks}");
        let amb = a.ambiguities.iter().find(|x| x.effects.iter().any(|e| e == "motor_slip")).expect("ambiguity");
        assert!(amb.explanation.contains("rpm/N·m"), "{}", amb.explanation);
        assert!(score(&a.improved.validation) < 0.9 * score(&a.baseline.validation));
    }
}

#[test]
fn concealed_pairs_are_both_named() {
    let a = concealed(
        |m| {
            m.effects.coulomb_friction = Some(CoulombFriction { torque_nm: 0.6 });
            m.effects.dead_time = Some(DeadTime { ms: 30.0 });
        },
        25,
    );
    let mut n = named(&a);
    n.sort();
    assert_eq!(n, vec!["coulomb_friction", "dead_time"], "{:#?}", a.findings);
    assert!((parameter(&a, "coulomb_friction", "torque_nm") - 0.6).abs() < 0.18);
    assert!((parameter(&a, "dead_time", "ms") - 30.0).abs() < 9.0);
    let a = concealed(
        |m| {
            m.effects.internal_leakage = Some(InternalLeakage { l_min_per_bar: 0.012 });
            m.effects.torque_offset = Some(TorqueOffset { torque_nm: 0.5 });
        },
        26,
    );
    let mut n = named(&a);
    n.sort();
    assert_eq!(n, vec!["internal_leakage", "torque_offset"], "{:#?}", a.findings);
    assert!((parameter(&a, "internal_leakage", "l_min_per_bar") - 0.012).abs() < 0.0036);
    assert!((parameter(&a, "torque_offset", "torque_nm") - 0.5).abs() < 0.15);
}

#[test]
fn clean_runs_name_nothing() {
    for seed in [27, 28] {
        let a = concealed(|_| {}, seed);
        assert!(a.findings.is_empty(), "seed {seed}: {:#?}", a.findings);
        assert!(a.model_misfit.is_none(), "seed {seed}: {:#?}", a.model_misfit);
        assert!(a.ambiguities.is_empty(), "seed {seed}: {:#?}", a.ambiguities);
        // nothing is missing, so nothing stays unexplained
        assert!(a.unexplained.is_empty(), "seed {seed}: {:#?}", a.unexplained);
        let j = a.improved.parameters["inertia_kg_m2"];
        assert!((j - 0.08).abs() < 0.1 * 0.08, "J {j}");
    }
}

/// A nominal model that declares a Coulomb friction the plant does not have (`torque_nm = 0`): least squares puts
/// the dry friction a little below zero on some runs (seeds 1, 6, 7, 8 of 20 s), and the baseline fit was refused as a
/// speed that hardly changes (exit 2). The fit within the bound keeps the term at 0 N·m, and nothing is missing.
#[test]
fn a_dry_friction_the_recording_does_not_have_is_fitted_at_zero() {
    let mut nominal = PlantModel::reference();
    nominal.effects.coulomb_friction = Some(CoulombFriction { torque_nm: 0.0 });
    for seed in [1, 6] {
        let rec = hydrolens::recording::simulated::test_stand(&PlantModel::reference(), 20.0, seed, &mut |_| {})
            .expect("run");
        let a = analysis::analyze(&rec, &nominal, &Options::default(), &mut |_| {})
            .unwrap_or_else(|e| panic!("seed {seed}: {e}"));
        assert!(a.findings.is_empty(), "seed {seed}: {:#?}", a.findings);
        let j = a.improved.parameters["inertia_kg_m2"];
        assert!((j - 0.08).abs() < 0.1 * 0.08, "seed {seed}: J {j}");
    }
}

/// A model that does not describe the recording at all names nothing and says so (a black-box tester's runs, 20 s,
/// seed 3): the speed column in rpm named a Stribeck friction at 433 rad/s with a zero-width interval (speed NRMSE
/// 2.21 before, 2.22 after, J a tenth of the model's, no warning); a model with a bulk modulus of 2 bar (1e-300 is
/// now refused at load) named one at 723 rad/s (2.40 after).
#[test]
fn a_model_that_does_not_describe_the_recording_names_nothing_and_says_so() {
    let reference = PlantModel::reference();
    let rec = hydrolens::recording::simulated::test_stand(&reference, 20.0, 3, &mut |_| {}).expect("run");
    let mut rpm = rec.clone();
    let omega = rec.column("omega_rad_s").expect("speed");
    rpm.set_column("omega_rad_s", omega.iter().map(|w| w * 60.0 / std::f64::consts::TAU).collect());
    let mut soft = reference.clone();
    soft.hydraulics.as_mut().expect("hydraulic").bulk_modulus_bar = 2.0;
    for (what, rec, model, says) in [("rpm", &rpm, &reference, "rpm"), ("2 bar", &rec, &soft, "model's values")] {
        let a = analysis::analyze(rec, model, &Options::default(), &mut |_| {}).expect("analysable");
        assert!(a.findings.is_empty(), "{what}: {:#?}", a.findings);
        let m = a.model_misfit.as_ref().unwrap_or_else(|| panic!("{what}: no misfit: {:?}", a.improved.validation));
        assert!(m.explanation.contains(says) && m.validation_nrmse > 1.5, "{what}: {m:#?}");
        assert_eq!(a.improved.parameters, a.baseline.parameters, "{what}");
    }
    let a = analysis::analyze(&rec, &reference, &Options::default(), &mut |_| {}).expect("analysable");
    assert!(a.model_misfit.is_none() && a.findings.is_empty(), "{:#?} {:#?}", a.model_misfit, a.findings);
}

/// Setpoint of "a program that runs slowly at times" (issue 18): the seeded slow program (steps and ramps at
/// 1.5–30 Hz) for the first `slow_until_s`, then the test stand's program (mostly 10–50 Hz, one stop per cycle).
fn slow_at_times(seed: u64, slow_until_s: f64) -> impl Fn(f64) -> f64 {
    let slow =
        hydrolens::plant::scenario::Scenario::generate(hydrolens::plant::scenario::Family::Slow, seed, slow_until_s);
    move |t| if t < slow_until_s { slow.setpoint_hz(t) } else { hydrolens::plant::excitation::setpoint_hz(t) }
}

/// Simulates `truth` on [`slow_at_times`] (brake-load steps) and analyses it with the nominal reference model.
fn concealed_on_slow_program(truth: &PlantModel, seed: u64, run_s: f64, slow_until_s: f64) -> Analysis {
    let setpoint = slow_at_times(seed, slow_until_s);
    let load = truth.load.clone();
    let inputs =
        hydrolens::plant::simulate::Inputs { setpoint_hz: &setpoint, load_nm: &move |t, w, a| load.torque_at(t, w, a) };
    let rec = hydrolens::recording::simulated::run(truth, run_s, seed, &inputs, &mut |_| {}).expect("simulable");
    analysis::analyze(&rec, &PlantModel::reference(), &Options::default(), &mut |_| {}).expect("analysable")
}

/// Issue 18's recording: Coulomb friction 2 N·m, Stribeck breakaway 6 N·m (ω_s 3 rad/s) and a 25 ms dead time, on
/// a program that runs slowly at times (down to 1.5 Hz) but hardly in its last 30 %. All three are named.
#[test]
fn stribeck_with_coulomb_and_dead_time_on_a_slow_program_names_all_three() {
    let a = &*ISSUE_18;
    let mut n = named(a);
    n.sort();
    let tried: Vec<String> = a
        .candidates
        .iter()
        .map(|c| format!("{} {} {:?} {:?} {}", c.round, c.effect, c.validation_score, c.delta_bic, c.kept))
        .collect();
    assert_eq!(n, vec!["coulomb_friction", "dead_time", "stribeck_friction"], "{tried:#?}");
    assert!((parameter(a, "coulomb_friction", "torque_nm") - 2.0).abs() <= 0.3 * 2.0, "{:#?}", a.findings);
    assert!((parameter(a, "stribeck_friction", "breakaway_nm") - 6.0).abs() <= 0.3 * 6.0, "{:#?}", a.findings);
    assert!((parameter(a, "dead_time", "ms") - 25.0).abs() <= 0.3 * 25.0, "{:#?}", a.findings);
}

/// Issue 18's recording (seed 41, 80 s, slow at times until 50 s) analysed once: two tests judge it, and it is the
/// suite's costliest analysis (about 45 s of CPU at the test profile).
static ISSUE_18: LazyLock<Analysis> = LazyLock::new(|| concealed_on_slow_program(&issue_18_truth(1.0), 41, 80.0, 50.0));

/// The truth of issue 18's recording at `scale` × (Coulomb 2 N·m, breakaway 6 N·m, dead time 25 ms; ω_s 3 rad/s).
fn issue_18_truth(scale: f64) -> PlantModel {
    let mut truth = PlantModel::reference();
    truth.effects.coulomb_friction = Some(CoulombFriction { torque_nm: 2.0 * scale });
    truth.effects.stribeck_friction = Some(StribeckFriction { breakaway_nm: 6.0 * scale, speed_rad_s: 3.0 });
    truth.effects.dead_time = Some(DeadTime { ms: 25.0 * scale });
    truth
}

/// With nothing allowed to be named, the improved model is the nominal one and what it misses is listed: on issue
/// 18's recording, ΔP at low speed, where the Stribeck friction acts, above the noise floor.
#[test]
fn unexplained_locates_what_the_model_still_misses() {
    let truth = issue_18_truth(1.0);
    let setpoint = slow_at_times(41, 50.0);
    let load = truth.load.clone();
    let inputs =
        hydrolens::plant::simulate::Inputs { setpoint_hz: &setpoint, load_nm: &move |t, w, a| load.torque_at(t, w, a) };
    let rec = hydrolens::recording::simulated::run(&truth, 80.0, 41, &inputs, &mut |_| {}).expect("simulable");
    let opts = Options { min_relative_drop: f64::INFINITY, ..Options::default() };
    let a = analysis::analyze(&rec, &PlantModel::reference(), &opts, &mut |_| {}).expect("analysable");
    assert!(a.findings.is_empty());
    let low = a
        .unexplained
        .iter()
        .find(|u| u.signal == "dp" && u.condition.contains("low speed"))
        .unwrap_or_else(|| panic!("{:#?}", a.unexplained));
    assert!(low.rms > 2.0 * low.noise_floor && low.share > 0.0 && !low.windows.is_empty(), "{low:#?}");
    assert!(low.windows.iter().all(|w| w[0] <= w[1]), "{low:#?}");
    // the noise floor of ΔP is the sensors' (σ 0.3 bar on each pressure: 0.42 bar)
    assert!((0.3..0.6).contains(&low.noise_floor), "{low:#?}");
}

/// Every fitted parameter has a finite, ordered interval that holds its reported value; over the issue's recording
/// the truth lies inside for the three effects.
#[test]
fn confidence_intervals_are_finite_ordered_and_hold_the_truth() {
    let a = &*ISSUE_18;
    for (k, v) in &a.improved.parameters {
        let ci = a.improved.confidence_intervals.get(k).unwrap_or_else(|| panic!("no interval for {k}"));
        assert!(ci.low.is_finite() && ci.high.is_finite() && ci.low <= *v && *v <= ci.high, "{k}: {v} {ci:?}");
    }
    for (effect, name, value) in
        [("coulomb_friction", "torque_nm", 2.0), ("stribeck_friction", "breakaway_nm", 6.0), ("dead_time", "ms", 25.0)]
    {
        let f = a.findings.iter().find(|f| f.effect == effect).unwrap_or_else(|| panic!("{effect} not named"));
        let ci = f.confidence_intervals[name];
        assert!(ci.low <= value && value <= ci.high, "{effect}.{name}: truth {value} outside {ci:?}");
    }
}

/// Coverage of the intervals and the slow-program cases over seeds and magnitudes (minutes, release):
/// `cargo test --release --locked --test it -- --ignored slow_program_sweep --nocapture`. Seeds 41, 42 were looked
/// at while the method was built (tuned); 301–304 were not (held out).
#[test]
#[ignore]
fn slow_program_sweep() {
    let mut failures = Vec::new();
    for (set, seeds) in [("tuned", vec![41u64, 42]), ("held-out", vec![301, 302, 303, 304])] {
        println!("\n**{set} seeds — {seeds:?}**\n");
        println!(
            "| scale | seed | named | Coulomb N·m (95 %) | breakaway N·m (95 %) | ω_s rad/s | dead time ms (95 %) | CV score nominal → improved | unexplained |"
        );
        println!("|---|---|---|---|---|---|---|---|---|");
        let (mut inside, mut total) = (0, 0);
        for scale in [0.5, 1.0] {
            for &seed in &seeds {
                let a = concealed_on_slow_program(&issue_18_truth(scale), seed, 80.0, 50.0);
                let mut n = named(&a);
                n.sort();
                let cell = |effect: &str, name: &str, truth: f64, inside: &mut usize, total: &mut usize| -> String {
                    match a.findings.iter().find(|f| f.effect == effect) {
                        Some(f) => {
                            let v = f.parameters[name];
                            match f.confidence_intervals.get(name) {
                                Some(ci) => {
                                    *total += 1;
                                    let ok = ci.low <= truth && truth <= ci.high;
                                    *inside += usize::from(ok);
                                    format!("{v:.3} ({:.3}…{:.3}){}", ci.low, ci.high, if ok { "" } else { " ✗" })
                                }
                                None => format!("{v:.3} (—)"),
                            }
                        }
                        None => "—".into(),
                    }
                };
                let c = cell("coulomb_friction", "torque_nm", 2.0 * scale, &mut inside, &mut total);
                let st = cell("stribeck_friction", "breakaway_nm", 6.0 * scale, &mut inside, &mut total);
                let dt = cell("dead_time", "ms", 25.0 * scale, &mut inside, &mut total);
                let ws = a
                    .findings
                    .iter()
                    .find(|f| f.effect == "stribeck_friction")
                    .map_or("—".into(), |f| format!("{:.2}", f.parameters["speed_rad_s"]));
                let un: Vec<String> = a
                    .unexplained
                    .iter()
                    .map(|u| format!("{} {} {:.1} %", u.signal, u.condition, 100.0 * u.share))
                    .collect();
                println!(
                    "| ×{scale} | {seed} | {} | {c} | {st} | {ws} | {dt} | {:.2e} → {:.2e} | {} |",
                    n.join(", "),
                    a.baseline.cross_validation_score.unwrap_or(f64::NAN),
                    a.improved.cross_validation_score.unwrap_or(f64::NAN),
                    if un.is_empty() { "none".into() } else { un.join("; ") }
                );
                if n != vec!["coulomb_friction", "dead_time", "stribeck_friction"] {
                    failures.push(format!("{set} seed {seed} ×{scale}: {n:?}"));
                }
                for (effect, name, truth) in [
                    ("coulomb_friction", "torque_nm", 2.0),
                    ("stribeck_friction", "breakaway_nm", 6.0),
                    ("dead_time", "ms", 25.0),
                ] {
                    if let Some(f) = a.findings.iter().find(|f| f.effect == effect)
                        && (f.parameters[name] - truth * scale).abs() > 0.3 * truth * scale
                    {
                        failures.push(format!("{set} seed {seed} ×{scale}: {effect}.{name} {}", f.parameters[name]));
                    }
                }
            }
        }
        // clean slow programs: nothing named
        let mut clean = Vec::new();
        for &seed in &seeds {
            let a = concealed_on_slow_program(&PlantModel::reference(), seed, 80.0, 50.0);
            clean.push(format!(
                "{seed}: {}",
                if a.findings.is_empty() { "nothing".into() } else { named(&a).join(", ") }
            ));
            if !a.findings.is_empty() {
                failures.push(format!("{set} clean seed {seed}: {:?}", named(&a)));
            }
        }
        println!("\nclean slow programs: {}; interval coverage of the truth: {inside}/{total}", clean.join("; "));
    }
    assert!(failures.is_empty(), "{failures:#?}");
}

/// Effect id, key parameter, its true value, and how to switch the effect on.
type Case = (&'static str, &'static str, f64, Box<dyn Fn(&mut PlantModel)>);

/// A wider sweep of seeds and magnitudes (minutes in the dev profile): `cargo test --test it -- --ignored sweep`.
#[test]
#[ignore]
fn sweep_of_seeds_and_magnitudes() {
    let mut failures = Vec::new();
    for seed in 100..104u64 {
        for scale in [0.8, 1.0, 1.5] {
            let cases: Vec<Case> = vec![
                (
                    "coulomb_friction",
                    "torque_nm",
                    0.6 * scale,
                    Box::new(move |m| m.effects.coulomb_friction = Some(CoulombFriction { torque_nm: 0.6 * scale })),
                ),
                (
                    "torque_offset",
                    "torque_nm",
                    0.6 * scale,
                    Box::new(move |m| m.effects.torque_offset = Some(TorqueOffset { torque_nm: 0.6 * scale })),
                ),
                (
                    "stribeck_friction",
                    "breakaway_nm",
                    1.8 * scale,
                    Box::new(move |m| {
                        m.effects.stribeck_friction =
                            Some(StribeckFriction { breakaway_nm: 1.8 * scale, speed_rad_s: 2.5 })
                    }),
                ),
                (
                    "internal_leakage",
                    "l_min_per_bar",
                    0.012 * scale,
                    Box::new(move |m| {
                        m.effects.internal_leakage = Some(InternalLeakage { l_min_per_bar: 0.012 * scale })
                    }),
                ),
                (
                    "dead_time",
                    "ms",
                    30.0 * scale,
                    Box::new(move |m| m.effects.dead_time = Some(DeadTime { ms: 30.0 * scale })),
                ),
                (
                    "entrained_air",
                    "bulk_modulus_bar",
                    7000.0 / scale,
                    Box::new(move |m| {
                        m.effects.entrained_air = Some(EntrainedAir { bulk_modulus_bar: 7000.0 / scale })
                    }),
                ),
            ];
            for (effect, name, truth, set) in cases {
                let a = concealed(|m| set(m), seed);
                let ok = named(&a).first() == Some(&effect)
                    && a.findings
                        .iter()
                        .find(|f| f.effect == effect)
                        .is_some_and(|f| (f.parameters[name] - truth).abs() <= 0.3 * truth.abs());
                if !ok {
                    failures.push(format!(
                        "seed {seed} {effect} {truth}: {:?}",
                        a.findings.iter().map(|f| (&f.effect, &f.parameters)).collect::<Vec<_>>()
                    ));
                }
            }
        }
        let a = concealed(|_| {}, seed);
        if !a.findings.is_empty() {
            failures.push(format!("clean seed {seed}: {:?}", named(&a)));
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}

/// The real EMPS recording, through the binary: from the viscous-only model the tool names Coulomb friction and a
/// torque offset and recovers the benchmark's IDIM-LS table.
#[test]
fn emps_real_data_gives_the_published_friction_model() {
    let dir = support::root().join("tests/data/emps");
    let tmp = tempfile::tempdir().expect("tmp");
    let (json, fitted, report) = (tmp.path().join("a.json"), tmp.path().join("m.toml"), tmp.path().join("r.html"));
    let out = Command::new(support::bin())
        .arg("analyze")
        .arg(dir.join("recording.csv"))
        .arg("--model")
        .arg(dir.join("model.toml"))
        .arg("--json")
        .arg(&json)
        .arg("--model-out")
        .arg(&fitted)
        .arg("--report")
        .arg(&report)
        .output()
        .expect("runs");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&json).expect("json")).expect("valid");
    let effects: Vec<&str> =
        v["findings"].as_array().expect("findings").iter().filter_map(|f| f["effect"].as_str()).collect();
    assert!(effects.contains(&"coulomb_friction") && effects.contains(&"torque_offset"), "{effects:?}");
    assert_eq!(v["baseline"]["validation"]["dp_nrmse"], serde_json::Value::Null);
    for key in
        ["recording", "samples", "validation_from_s", "baseline", "mismatches", "findings", "ambiguities", "improved"]
    {
        assert!(!v[key].is_null(), "contract key {key} missing");
    }
    assert_eq!(v["samples"], 24841);
    let p = &v["improved"]["parameters"];
    let get = |k: &str| p[k].as_f64().unwrap_or(f64::NAN);
    for (key, published) in
        [("inertia_kg_m2", 95.1089), ("viscous_nm_s_rad", 203.5034), ("coulomb_friction.torque_nm", 20.3935)]
    {
        let fitted = get(key);
        assert!((fitted - published).abs() <= 0.05 * published, "{key}: {fitted} vs published {published}");
    }
    let offset = get("torque_offset.torque_nm");
    assert!((offset - -3.1648).abs() <= 0.5, "offset {offset}");
    let rel = v["improved"]["whole_recording"]["torque_relative_error"].as_f64().unwrap_or(f64::NAN);
    assert!((0.035..0.055).contains(&rel), "relative force error {rel} (published 4.08 %)");
    let val = v["improved"]["validation"]["torque_relative_error"].as_f64().unwrap_or(f64::NAN);
    let base = v["baseline"]["validation"]["torque_relative_error"].as_f64().unwrap_or(f64::NAN);
    assert!(val < 0.5 * base, "validation {base} → {val}");
    // the fitted model is a plant TOML the other commands accept
    let m = PlantModel::load(&fitted).expect("fitted model parses");
    assert!(m.effects.coulomb_friction.is_some() && m.effects.torque_offset.is_some());
    // every fitted parameter carries an interval, in the JSON and in the report, and so does what stays unexplained
    let intervals = &v["improved"]["confidence_intervals"];
    for (k, value) in p.as_object().expect("parameters") {
        let (lo, hi) = (intervals[k]["low"].as_f64(), intervals[k]["high"].as_f64());
        let value = value.as_f64().unwrap_or(f64::NAN);
        assert!(lo.zip(hi).is_some_and(|(lo, hi)| lo <= value && value <= hi), "{k}: {value} in {lo:?}..{hi:?}");
    }
    assert!(v["unexplained"].is_array(), "unexplained is part of the JSON");
    let html = std::fs::read_to_string(&report).expect("report");
    assert!(html.contains("<svg") && html.contains("coulomb_friction") && !html.contains("<script"));
    assert!(html.contains("confidence intervals") && html.contains("95 % low"), "the report shows the intervals");
    let ci = &intervals["coulomb_friction.torque_nm"];
    let shown = format!("{:.5}", ci["low"].as_f64().unwrap_or(f64::NAN));
    assert!(html.contains(&shown), "the report shows the interval {shown}");
    assert!(html.contains("still leaves unexplained"), "the report has the unexplained section");
}

#[test]
fn bad_input_exits_2_naming_the_column() {
    let tmp = tempfile::tempdir().expect("tmp");
    let rec = tmp.path().join("r.csv");
    let mut text = String::from("t_s,torque_nm\n");
    for k in 0..300 {
        text.push_str(&format!("{},{}\n", k as f64 * 1e-3, 1.0));
    }
    std::fs::write(&rec, text).expect("write");
    let out = Command::new(support::bin())
        .args(["analyze"])
        .arg(&rec)
        .arg("--model")
        .arg(support::root().join("config/plant.toml"))
        .arg("--json")
        .arg(tmp.path().join("a.json"))
        .output()
        .expect("runs");
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("omega_rad_s") && err.contains("theta_rad"), "{err}");
}

/// `analyze` on a copy of the EMPS recording with `edit` applied to its rows (t_s, θ, τ): exit code, stderr, JSON.
fn emps_edited(edit: impl Fn(usize, &mut [f64; 3])) -> (Option<i32>, String, Option<serde_json::Value>) {
    let dir = support::root().join("tests/data/emps");
    let tmp = tempfile::tempdir().expect("tmp");
    let text = std::fs::read_to_string(dir.join("recording.csv")).expect("emps");
    let mut lines = text.lines();
    let mut out = format!("{}\n", lines.next().expect("header"));
    assert_eq!(out, "t_s,theta_rad,torque_nm\n", "the columns this helper edits");
    for (k, line) in lines.enumerate() {
        let mut row = [0.0; 3];
        for (v, cell) in row.iter_mut().zip(line.split(',')) {
            *v = cell.parse().expect("a number");
        }
        edit(k, &mut row);
        out.push_str(&format!("{:e},{:e},{:e}\n", row[0], row[1], row[2]));
    }
    let (rec, json) = (tmp.path().join("r.csv"), tmp.path().join("a.json"));
    std::fs::write(&rec, out).expect("write");
    let o = Command::new(support::bin())
        .arg("analyze")
        .arg(&rec)
        .arg("--model")
        .arg(dir.join("model.toml"))
        .arg("--json")
        .arg(&json)
        .output()
        .expect("runs");
    let v = std::fs::read_to_string(&json).ok().map(|t| serde_json::from_str(&t).expect("valid"));
    (o.status.code(), String::from_utf8_lossy(&o.stderr).into_owned(), v)
}

#[test]
fn a_corrupt_position_a_long_pause_and_a_stretched_clock_are_handled_or_refused() {
    let effects = |v: &serde_json::Value| -> Vec<String> {
        v["findings"]
            .as_array()
            .expect("findings")
            .iter()
            .filter_map(|f| f["effect"].as_str().map(String::from))
            .collect()
    };
    // one θ cell of 1e300: taken out as a spike, alone, and the same physics named (it was "the speed hardly
    // changes" with no location)
    let (code, err, v) = emps_edited(|k, r| {
        if k == 998 {
            r[1] = 1e300;
        }
    });
    assert_eq!(code, Some(0), "{err}");
    assert!(err.contains("theta_rad") && err.contains("rows=1 "), "one spike named: {err}");
    let named = effects(&v.expect("json"));
    assert!(named.contains(&"coulomb_friction".into()) && named.contains(&"torque_offset".into()), "{named:?}");
    // a pause of 10⁹ s near the end: the validation segment is still the last 30 % of the recorded time (it was
    // the 840 rows after the pause), and the message gives the gap in few digits
    let (code, err, v) = emps_edited(|k, r| {
        if k >= 24_000 {
            r[0] += 1e9;
        }
    });
    assert_eq!(code, Some(0), "{err}");
    let from = v.expect("json")["validation_from_s"].as_f64().expect("validation_from_s");
    assert!((from - 17.39).abs() < 0.05, "validation from {from} s");
    assert!(err.contains("1.000e9 s after row 24000"), "{err}");
    // t_s ×10⁶ (1000 s a sample): 2.5·10¹⁰ integration steps a pass, refused at once naming the unit
    let (code, err, _) = emps_edited(|_, r| r[0] *= 1e6);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("r.csv") && err.contains("t_s") && err.contains("unit"), "{err}");
    // θ jumping by 10⁶ rad from row 10 000 on (an encoder reset): refused naming the recording, the column and when
    // (a helper's black-box run: the model's free run left any physical range, blaming the model file)
    let (code, err, _) = emps_edited(|k, r| {
        if k >= 10_000 {
            r[1] += 1e6;
        }
    });
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("r.csv") && err.contains("theta_rad") && err.contains("jumps near t = "), "{err}");
    assert!(!err.contains("model file"), "{err}");
}

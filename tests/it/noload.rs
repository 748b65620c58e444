//! `analyze` with the load unknown, on recordings as the service writes them: offline test-stand runs turned into
//! service recordings (poll rate, Modbus quantisation, skipped cycles, no `load_nm`), and the sweep behind
//! docs/analysis.md's no-load table.

use hydrolens::analysis::{self, Analysis, Options};
use hydrolens::plant::PlantModel;
use hydrolens::plant::effects::{
    CoulombFriction, DeadTime, EntrainedAir, InternalLeakage, MotorSlip, StribeckFriction, TorqueOffset,
};
use hydrolens::recording::Recording;

/// Length of the offline runs (s): two test-stand cycles, as the concealed-effect tests.
const RUN_S: f64 = 80.0;

/// A simulated 1 kHz test-stand recording as the service would have written it at `poll_ms`: every `poll_ms`-th
/// row, values through the default register map's quantisation (0.01 bar, 0.1 rpm, 0.01 Hz), about one cycle in
/// 200 skipped as stale plus one 0.4 s outage, no `load_nm` and no ground truth, and the estimate columns
/// riding along (filled with nonsense: they must not be used).
pub fn as_the_service_records(rec: &Recording, poll_ms: usize, seed: u64) -> Recording {
    let q = |v: f64, lsb: f64| (v / lsb).round() * lsb;
    let rpm = 60.0 / (2.0 * std::f64::consts::PI);
    let col = |name: &str| rec.column(name).expect("simulated column");
    let (t, f_set, f_drive) = (col("t_s"), col("f_set_hz"), col("f_drive_hz"));
    let (p_in, p_out, omega) = (col("p_in_bar"), col("p_out_bar"), col("omega_rad_s"));
    // the service recorder's own columns (one shape: src/service/state.rs)
    let names = hydrolens::service::state::COLUMNS;
    let mut cols: Vec<Vec<f64>> = vec![Vec::new(); names.len()];
    // a small deterministic generator for the skipped cycles
    let mut state = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
    let mut next = || {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (state >> 33) as f64 / (1u64 << 31) as f64
    };
    let outage = (0.37 * t[t.len() - 1], 0.37 * t[t.len() - 1] + 0.4);
    for k in (0..rec.len()).step_by(poll_ms) {
        if next() < 0.005 || (outage.0..outage.1).contains(&t[k]) {
            continue;
        }
        // in COLUMNS order (the compiler holds the length to it): the measured columns (the drive's power not read),
        // estimates that are nonsense (never used), the status word, no target
        let row: [f64; hydrolens::service::state::COLUMNS.len()] = [
            t[k],
            q(f_set[k], 0.01),
            q(f_drive[k], 0.01),
            q(p_in[k].max(0.0), 0.01),
            q(p_out[k].max(0.0), 0.01),
            q(omega[k] * rpm, 0.1) / rpm,
            f64::NAN,
            -omega[k],
            1e3,
            -1.0,
            f64::NAN,
            -2.0,
            f64::NAN,
            1.0,
            -2.0,
            5.0,
            3.0,
            f64::NAN,
        ];
        for (c, v) in cols.iter_mut().zip(row) {
            c.push(v);
        }
    }
    Recording::from_columns("service-like.csv", names.iter().map(|s| s.to_string()).collect(), cols)
}

/// The reference plant with `effect`, simulated offline, recorded as the service would at `poll_ms`, analysed
/// against the nominal model (whose `[load]` is "recorded": the load is then unknown).
pub fn no_load(effect: &dyn Fn(&mut PlantModel), seed: u64, poll_ms: usize) -> Analysis {
    let mut truth = PlantModel::reference();
    effect(&mut truth);
    let rec = hydrolens::recording::simulated::test_stand(&truth, RUN_S, seed, &mut |_| {}).expect("simulable");
    let rec = as_the_service_records(&rec, poll_ms, seed);
    analysis::analyze(&rec, &PlantModel::reference(), &Options::default(), &mut |_| {}).expect("analysable")
}

pub fn named(a: &Analysis) -> Vec<&str> {
    a.findings.iter().map(|f| f.effect.as_str()).collect()
}

/// The flow-balance effects the no-load analysis must find, with their key parameter.
pub const HYDRAULIC: [&str; 4] = ["internal_leakage", "motor_slip", "dead_time", "entrained_air"];

// ---- over real TCP: `sim` with a concealed effect, `serve` recording in speed mode, `analyze` the files ----

use std::path::Path;
use std::time::Duration;

use crate::support;

/// How long each TCP case records (s): long enough for a validation segment with several target changes.
const TCP_RECORD_S: u64 = 40;

/// The service's config for one drive `pump1` in speed mode at `poll_ms`, files rotated every 0.3 MB (several
/// files per run, as a long recording has).
fn speed_mode_config(modbus: std::net::SocketAddr, dir: &Path, poll_ms: u64) -> String {
    format!(
        "[http]\nbind = \"127.0.0.1:0\"\n\n[recording]\ndir = {dir:?}\nmax_file_mb = 0.3\n\n[[drives]]\n\
         name = \"pump1\"\naddress = \"{modbus}\"\npoll_ms = {poll_ms}\ntimeout_ms = 100\n\n[drives.control]\n\
         mode = \"speed\"\ntarget_omega_rad_s = 40.0\nmax_hz = 50.0\nramp_hz_per_s = 20.0\n",
        dir = dir.display().to_string()
    )
}

/// `sim` runs `truth` (the reference plant and its brake-load steps, plus a concealed effect) on 127.0.0.1:0; the
/// service polls it every `poll_ms`, regulating the speed while the target moves through the demo program, and
/// records for `seconds`. Everything is stopped before this returns; the recordings stay in the returned dir.
async fn serve_a_recording(truth: PlantModel, poll_ms: u64, seconds: u64) -> tempfile::TempDir {
    let (_sim, addr, sim_stop, sim_task) = support::start_sim(truth, 0).await;
    let dir = tempfile::tempdir().expect("tmp");
    let svc = support::start_service(&speed_mode_config(addr, dir.path(), poll_ms)).await;
    support::follow_demo_program(&svc.state.drives[0], seconds).await;
    support::stop_service(svc).await;
    sim_stop.cancel();
    let _ = tokio::time::timeout(Duration::from_secs(10), sim_task).await.expect("simulator stops");
    dir
}

/// `hydrolens analyze DIR --drive pump1 --model config/plant.toml` through the binary: the JSON, stderr.
fn analyze_dir(dir: &Path) -> (serde_json::Value, String) {
    let json = dir.join("a.json");
    let report = dir.join("a.html");
    let out = std::process::Command::new(support::bin())
        .arg("analyze")
        .arg(dir)
        .args(["--drive", "pump1", "--model"])
        .arg(support::root().join("config/plant.toml"))
        .arg("--json")
        .arg(&json)
        .arg("--report")
        .arg(&report)
        .output()
        .expect("analyze runs");
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "{stderr}");
    let html = std::fs::read_to_string(&report).expect("report");
    assert!(html.contains("<svg") && html.contains("load unknown"), "the report draws the no-load analysis");
    let v = serde_json::from_str(&std::fs::read_to_string(&json).expect("json")).expect("valid json");
    (v, stderr)
}

fn effects(v: &serde_json::Value) -> Vec<String> {
    v["findings"].as_array().expect("findings").iter().filter_map(|f| f["effect"].as_str().map(String::from)).collect()
}

/// The five TCP cases run side by side (each its own simulator, service and recording), so the test takes one
/// recording's time.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn served_recordings_with_the_load_unknown_name_the_hidden_flow_effect() {
    served_cases(5).await;
}

/// The same at the other poll rates the service is run at (`cargo test --test it -- --ignored served_at`).
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
#[ignore]
async fn served_at_1_and_10_ms() {
    for poll_ms in [1, 10] {
        served_cases(poll_ms).await;
    }
}

/// Leak, dead time, air, clean and Coulomb friction served at `poll_ms`, analysed with the nominal model; every
/// check of the issue asserted.
async fn served_cases(poll_ms: u64) {
    type Case = (&'static str, Box<dyn Fn(&mut PlantModel) + Send>);
    let cases: Vec<Case> = vec![
        ("clean", Box::new(|_| {})),
        ("leak", Box::new(|m| m.effects.internal_leakage = Some(InternalLeakage { l_min_per_bar: 0.012 }))),
        ("dead_time", Box::new(|m| m.effects.dead_time = Some(DeadTime { ms: 30.0 }))),
        ("air", Box::new(|m| m.effects.entrained_air = Some(EntrainedAir { bulk_modulus_bar: 6000.0 }))),
        ("coulomb", Box::new(|m| m.effects.coulomb_friction = Some(CoulombFriction { torque_nm: 0.8 }))),
    ];
    let run = async {
        let started = std::time::Instant::now();
        let tasks: Vec<_> = cases
            .into_iter()
            .map(|(name, set)| {
                let mut truth = PlantModel::reference();
                set(&mut truth);
                tokio::spawn(async move {
                    let dir = serve_a_recording(truth, poll_ms, TCP_RECORD_S).await;
                    let (v, stderr) = tokio::task::spawn_blocking({
                        let path = dir.path().to_path_buf();
                        move || analyze_dir(&path)
                    })
                    .await
                    .expect("analysis thread");
                    (name, dir, v, stderr)
                })
            })
            .collect();
        let mut results = Vec::new();
        for t in tasks {
            results.push(t.await.expect("case task"));
        }
        for (name, _dir, v, stderr) in &results {
            let named = effects(v);
            let param = |effect: &str, key: &str| {
                v["findings"]
                    .as_array()
                    .expect("findings")
                    .iter()
                    .find(|f| f["effect"] == effect)
                    .map_or(f64::NAN, |f| f["parameters"][key].as_f64().unwrap_or(f64::NAN))
            };
            let windows: Vec<String> = v["mismatches"]
                .as_array()
                .expect("mismatches")
                .iter()
                .map(|m| format!("{} {}", m["signal"], m["condition"]))
                .collect();
            let shows: Vec<&serde_json::Value> =
                v["findings"].as_array().expect("findings").iter().map(|f| &f["evidence"]["where_it_shows"]).collect();
            eprintln!("TCP {poll_ms} ms {name}: shows {shows:?}; mismatch windows {windows:?}");
            let unexplained: Vec<String> = v["unexplained"]
                .as_array()
                .expect("unexplained")
                .iter()
                .map(|u| {
                    format!(
                        "{} {} rms {} floor {} share {}",
                        u["signal"], u["condition"], u["rms"], u["noise_floor"], u["share"]
                    )
                })
                .collect();
            eprintln!("TCP {poll_ms} ms {name}: unexplained {unexplained:#?}");
            eprintln!(
                "TCP {poll_ms} ms {name}: named {named:?}, leak {:.5}, dead {:.2} ms, β {:.0} bar; dp {} → {}, f {} → {}",
                param("internal_leakage", "l_min_per_bar"),
                param("dead_time", "ms"),
                param("entrained_air", "bulk_modulus_bar"),
                v["baseline"]["validation"]["dp_nrmse"],
                v["improved"]["validation"]["dp_nrmse"],
                v["baseline"]["validation"]["f_drive_nrmse"],
                v["improved"]["validation"]["f_drive_nrmse"],
            );
            assert_eq!(v["load"], "unknown", "{name}");
            assert!(stderr.contains("files joined"), "{name}: several rotated files: {stderr}");
            assert!(stderr.contains("load_nm"), "{name}: the note says the load is unknown: {stderr}");
            // three quarters of the polls at least: rows from every rotated file
            let polls = TCP_RECORD_S * 1000 / poll_ms;
            assert!(4 * v["samples"].as_u64().expect("samples") > 3 * polls, "{name}: {}", v["samples"]);
            let within = |effect: &str, key: &str, truth: f64| {
                let got = param(effect, key);
                assert!((got - truth).abs() <= 0.3 * truth, "{name}: {effect}.{key} {got}, truth {truth}");
            };
            match *name {
                "clean" => {
                    assert!(named.is_empty(), "clean: {named:?}");
                    // the flow family's ΔP floor carries the speed noise its prediction carries; the drive
                    // frequency's, the rows' timing
                    assert_eq!(v["unexplained"], serde_json::json!([]), "clean: nothing stays unexplained");
                }
                "leak" => {
                    assert_eq!(named.first().map(String::as_str), Some("internal_leakage"), "{named:?}");
                    within("internal_leakage", "l_min_per_bar", 0.012);
                }
                "dead_time" => {
                    assert_eq!(named, vec!["dead_time".to_string()]);
                    within("dead_time", "ms", 30.0);
                    // located: the drive frequency misses where the target moved
                    let windows = v["mismatches"].as_array().expect("mismatches");
                    assert!(windows.iter().any(|m| m["signal"] == "f_drive"), "{}", v["mismatches"]);
                    // and its gain is on the drive frequency. Which operating condition labels those windows is
                    // not asserted: the regulator ramps the setpoint (20 Hz/s), so where the lag shows is wherever
                    // the regulator moved it, and a served run's targets and poll times follow the wall clock ("after
                    // setpoint steps", "fast acceleration" and "steady running" were all seen in full-suite runs)
                    let shows = v["findings"][0]["evidence"]["where_it_shows"].as_str().unwrap_or_default();
                    assert!(shows.starts_with("f_drive: "), "{shows}");
                }
                "air" => {
                    assert_eq!(named, vec!["entrained_air".to_string()]);
                    within("entrained_air", "bulk_modulus_bar", 6000.0);
                }
                _ => {
                    assert!(named.iter().all(|e| !HYDRAULIC.contains(&e.as_str())), "coulomb: {named:?}");
                    let listed = v["ambiguities"].as_array().expect("ambiguities").iter().any(|a| {
                        a["explanation"].as_str().is_some_and(|x| x.contains("load unknown"))
                            && a["effects"].as_array().is_some_and(|e| e.iter().any(|x| x == "coulomb_friction"))
                    });
                    assert!(named.iter().any(|e| e == "coulomb_friction") || listed, "{}", v["ambiguities"]);
                }
            }
        }
        eprintln!("TCP cases: {:.1} s", started.elapsed().as_secs_f64());
    };
    tokio::time::timeout(Duration::from_secs(TCP_RECORD_S + 100), run).await.expect("bounded");
}

// ---- the no-load sweep behind docs/analysis.md's table ----

/// One no-load case: the effect hidden, the parameter judged, its true value; `None` effect for clean and friction
/// runs (which must name no flow-balance effect).
struct Sweep {
    label: &'static str,
    effect: Option<&'static str>,
    key: &'static str,
    truth: f64,
    set: Box<dyn Fn(&mut PlantModel) + Sync>,
}

fn sweep_cases(scale: f64) -> Vec<Sweep> {
    let leak = 0.012 * scale;
    let slip = 2.5 * scale;
    let dead = 30.0 * scale;
    let air = 7000.0 / scale;
    let coulomb = 0.6 * scale;
    vec![
        Sweep {
            label: "internal_leakage",
            effect: Some("internal_leakage"),
            key: "l_min_per_bar",
            truth: leak,
            set: Box::new(move |m| m.effects.internal_leakage = Some(InternalLeakage { l_min_per_bar: leak })),
        },
        Sweep {
            label: "motor_slip",
            effect: Some("motor_slip"),
            key: "rpm_per_nm",
            truth: slip,
            set: Box::new(move |m| m.effects.motor_slip = Some(MotorSlip { rpm_per_nm: slip })),
        },
        Sweep {
            label: "dead_time",
            effect: Some("dead_time"),
            key: "ms",
            truth: dead,
            set: Box::new(move |m| m.effects.dead_time = Some(DeadTime { ms: dead })),
        },
        Sweep {
            label: "entrained_air",
            effect: Some("entrained_air"),
            key: "bulk_modulus_bar",
            truth: air,
            set: Box::new(move |m| m.effects.entrained_air = Some(EntrainedAir { bulk_modulus_bar: air })),
        },
        Sweep {
            label: "coulomb_friction (no flow effect may be named)",
            effect: None,
            key: "",
            truth: coulomb,
            set: Box::new(move |m| m.effects.coulomb_friction = Some(CoulombFriction { torque_nm: coulomb })),
        },
        Sweep {
            label: "stribeck_friction (no flow effect may be named)",
            effect: None,
            key: "",
            truth: 3.0 * coulomb,
            set: Box::new(move |m| {
                m.effects.stribeck_friction = Some(StribeckFriction { breakaway_nm: 3.0 * coulomb, speed_rad_s: 2.5 })
            }),
        },
        Sweep {
            label: "torque_offset (no flow effect may be named)",
            effect: None,
            key: "",
            truth: coulomb,
            set: Box::new(move |m| m.effects.torque_offset = Some(TorqueOffset { torque_nm: coulomb })),
        },
    ]
}

/// The fitted value of `effect.key`; slip may come back as its equivalent leakage (the two are one term).
fn fitted(a: &Analysis, effect: &str, key: &str) -> Option<f64> {
    let direct = a.findings.iter().find(|f| f.effect == effect).map(|f| f.parameters[key]);
    if effect == "motor_slip" && direct.is_none() {
        let per_rpm = analysis::slip_as_leakage(&PlantModel::reference(), 1.0)?;
        return a
            .findings
            .iter()
            .find(|f| f.effect == "internal_leakage")
            .map(|f| f.parameters["l_min_per_bar"] / per_rpm);
    }
    direct
}

/// Runs every case for `seeds` × magnitudes × poll rates on two threads; prints the table rows (markdown) and
/// returns the failures.
fn no_load_sweep(seeds: &[u64], set_name: &str) -> Vec<String> {
    let scales = [0.7, 1.0, 1.5];
    let polls = [1usize, 5, 10];
    let mut jobs = Vec::new();
    for &poll in &polls {
        for &scale in &scales {
            for (i, _) in sweep_cases(scale).iter().enumerate() {
                for &seed in seeds {
                    jobs.push((poll, scale, i, seed));
                }
            }
        }
        for &seed in seeds {
            jobs.push((poll, 0.0, usize::MAX, seed)); // clean
        }
    }
    let next = std::sync::atomic::AtomicUsize::new(0);
    // (poll, label, relative error or None when not named, wrongly named flow effects)
    let results = std::sync::Mutex::new(Vec::<(usize, String, Option<f64>, Vec<String>)>::new());
    std::thread::scope(|scope| {
        for _ in 0..2 {
            scope.spawn(|| {
                loop {
                    let j = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    let Some(&(poll, scale, i, seed)) = jobs.get(j) else { break };
                    let (label, effect, key, truth, a) = if i == usize::MAX {
                        ("clean".to_string(), None, "", 0.0, no_load(&|_| {}, seed, poll))
                    } else {
                        let c = sweep_cases(scale).swap_remove(i);
                        let a = no_load(c.set.as_ref(), seed, poll);
                        (c.label.to_string(), c.effect, c.key, c.truth, a)
                    };
                    let named = named(&a);
                    let wrong: Vec<String> = named
                        .iter()
                        .filter(|e| {
                            effect.is_none_or(|x| **e != x && !(x == "motor_slip" && **e == "internal_leakage"))
                        })
                        .map(|e| format!("{e} (seed {seed}, ×{scale})"))
                        .collect();
                    let err = effect.and_then(|e| fitted(&a, e, key)).map(|v| (v - truth) / truth);
                    if effect.is_some() && err.is_none() {
                        eprintln!("not named: {label} {truth} at {poll} ms, seed {seed}: {:?}", named);
                    }
                    results.lock().expect("results").push((poll, label, err, wrong));
                }
            });
        }
    });
    let results = results.into_inner().expect("results");
    let mut failures = Vec::new();
    eprintln!("\n{set_name} (seeds {seeds:?}, magnitudes ×0.7, ×1, ×1.5)");
    eprintln!("| effect | poll | runs | named | median error | worst error | wrongly named |");
    eprintln!("|---|---|---|---|---|---|---|");
    let mut labels: Vec<String> = sweep_cases(1.0).iter().map(|c| c.label.to_string()).collect();
    labels.push("clean".into());
    for label in &labels {
        for &poll in &polls {
            let rows: Vec<_> = results.iter().filter(|r| r.0 == poll && &r.1 == label).collect();
            let judged = !(label == "clean" || label.contains("no flow effect"));
            let mut errs: Vec<f64> = rows.iter().filter_map(|r| r.2).collect();
            errs.sort_by(|a, b| a.abs().total_cmp(&b.abs()));
            let named = errs.len();
            let wrong: Vec<&String> = rows.iter().flat_map(|r| r.3.iter()).collect();
            let (median, worst) = if errs.is_empty() {
                ("—".to_string(), "—".to_string())
            } else {
                (format!("{:+.1} %", 100.0 * errs[errs.len() / 2]), format!("{:+.1} %", 100.0 * errs[errs.len() - 1]))
            };
            eprintln!(
                "| {label} | {poll} ms | {} | {} | {median} | {worst} | {} |",
                rows.len(),
                if judged { format!("{named}/{}", rows.len()) } else { "—".into() },
                wrong.len()
            );
            // every effect named in at least 4 runs of 5 (the smallest magnitudes sit near the noise at 10 ms;
            // docs/analysis.md lists the misses), never outside ±30 %, nothing named that was not hidden
            if judged && (5 * named < 4 * rows.len() || errs.iter().any(|e| e.abs() > 0.3)) {
                failures.push(format!("{label} at {poll} ms: named {named}/{}, errors {errs:?}", rows.len()));
            }
            if !wrong.is_empty() {
                failures.push(format!("{label} at {poll} ms: wrongly named {wrong:?}"));
            }
        }
    }
    failures
}

/// The seeds the no-load method was developed on (`cargo test --release --test it -- --ignored no_load_sweep`).
#[test]
#[ignore]
fn no_load_sweep_tuned_seeds() {
    let failures = no_load_sweep(&[3, 4, 5], "tuned seeds");
    assert!(failures.is_empty(), "{failures:#?}");
}

/// Seeds never looked at while developing: the held-out figures of docs/analysis.md.
#[test]
#[ignore]
fn no_load_sweep_held_out_seeds() {
    let failures = no_load_sweep(&[201, 202, 203, 204, 205], "held-out seeds");
    assert!(failures.is_empty(), "{failures:#?}");
}

/// A served recording (5 ms, `seed`) of `nominal` with `set` applied, analysed against `nominal`: `effect` is named
/// with its `key` within 15 % of `truth` under the default options, and nothing is named under `stricter`.
fn named_only_beyond_the_plants_own_variation(
    nominal: &PlantModel,
    set: impl Fn(&mut PlantModel),
    seed: u64,
    (effect, key, truth): (&str, &str, f64),
    stricter: Options,
) {
    let mut plant = nominal.clone();
    set(&mut plant);
    let rec = hydrolens::recording::simulated::test_stand(&plant, RUN_S, seed, &mut |_| {}).expect("simulable");
    let rec = as_the_service_records(&rec, 5, seed);
    let run = |opts: &Options| analysis::analyze(&rec, nominal, opts, &mut |_| {}).expect("analysable");
    let default = run(&Options::default());
    assert_eq!(named(&default), vec![effect]);
    let got = fitted(&default, effect, key).expect("fitted");
    assert!((got - truth).abs() < 0.15 * truth, "{effect}.{key} {got}, truth {truth}");
    let strict = run(&stricter);
    assert!(named(&strict).is_empty(), "{:?}", named(&strict));
}

/// Entrained air is named only when the fitted modulus lies below `air_max_modulus_ratio` of the model's: 7000 bar
/// (47 % of the model's 15 000) is named at the default 0.8 and not when the band is widened to 0.4.
#[test]
fn entrained_air_is_named_only_below_the_oils_own_band() {
    named_only_beyond_the_plants_own_variation(
        &PlantModel::reference(),
        |m| m.effects.entrained_air = Some(EntrainedAir { bulk_modulus_bar: 7000.0 }),
        3,
        ("entrained_air", "bulk_modulus_bar", 7000.0),
        Options { air_max_modulus_ratio: 0.4, ..Options::default() },
    );
}

/// An added leakage is named only when it is at least `leak_min_ratio` of the model's own (0.02 L/min/bar): 0.006
/// (30 %) is named at the default 0.2 and not when the floor is raised to 0.5.
#[test]
fn a_leak_is_named_only_above_the_oils_own_variation() {
    named_only_beyond_the_plants_own_variation(
        &PlantModel::reference(),
        |m| m.effects.internal_leakage = Some(InternalLeakage { l_min_per_bar: 0.006 }),
        4,
        ("internal_leakage", "l_min_per_bar", 0.006),
        Options { leak_min_ratio: 0.5, ..Options::default() },
    );
}

/// With a model whose own leakage is zero, the floor is a share of the motor's flow (`leak_min_flow_share`, 0.3 %:
/// about 0.002 L/min/bar on this program): 0.005 L/min/bar is named at the default and not with the share at 3 %.
#[test]
fn with_a_leak_free_model_a_leak_is_named_only_above_a_share_of_the_flow() {
    let mut nominal = PlantModel::reference();
    nominal.hydraulics.as_mut().expect("hydraulics").leakage_l_min_per_bar = 0.0;
    named_only_beyond_the_plants_own_variation(
        &nominal,
        |m| m.effects.internal_leakage = Some(InternalLeakage { l_min_per_bar: 0.005 }),
        5,
        ("internal_leakage", "l_min_per_bar", 0.005),
        Options { leak_min_flow_share: 0.03, ..Options::default() },
    );
}

/// A monitor-mode recording (no setpoint written): the pressure equation runs from `f_drive_hz`, leakage is
/// still found, and the dead time is said to be undeterminable rather than searched.
#[test]
fn without_a_setpoint_the_leak_is_found_and_the_dead_time_is_not_identified() {
    let mut truth = PlantModel::reference();
    truth.effects.internal_leakage = Some(InternalLeakage { l_min_per_bar: 0.012 });
    let rec = hydrolens::recording::simulated::test_stand(&truth, RUN_S, 31, &mut |_| {}).expect("simulable");
    let mut rec = as_the_service_records(&rec, 5, 31);
    rec.set_column("f_set_hz", vec![f64::NAN; rec.len()]);
    let a = analysis::analyze(&rec, &PlantModel::reference(), &Options::default(), &mut |_| {}).expect("analysable");
    assert_eq!(named(&a), vec!["internal_leakage"], "{:#?}", a.findings);
    let l = a.findings[0].parameters["l_min_per_bar"];
    assert!((l - 0.012).abs() <= 0.3 * 0.012, "leak {l}");
    assert!(a.candidates.iter().all(|c| c.effect != "dead_time"), "dead time is not searched without a setpoint");
    assert!(a.not_identified.iter().any(|x| x.parameters.contains(&"dead_time.ms".to_string())));
    assert!(a.not_identified.iter().any(|x| x.parameters.contains(&"inertia_kg_m2".to_string())));
    assert!(a.baseline.validation.omega_nrmse.is_nan(), "the speed is an input here, not predicted");
}

/// `[load] kind = "unknown"` analyses with the load unknown even when a `load_nm` column is there; a torque-driven
/// recording cannot be analysed without its load and says so naming the column.
#[test]
fn kind_unknown_is_the_load_unknown_and_a_torque_recording_needs_its_load() {
    let mut truth = PlantModel::reference();
    truth.effects.dead_time = Some(DeadTime { ms: 25.0 });
    let rec = hydrolens::recording::simulated::test_stand(&truth, RUN_S, 32, &mut |_| {}).expect("simulable");
    let mut nominal = PlantModel::reference();
    nominal.load = hydrolens::plant::LoadSpec::Unknown;
    let a = analysis::analyze(&rec, &nominal, &Options::default(), &mut |_| {}).expect("analysable");
    assert_eq!((a.load, a.family), ("unknown", "flow"));
    assert_eq!(named(&a), vec!["dead_time"], "{:#?}", a.findings);
    let with_load =
        analysis::analyze(&rec, &PlantModel::reference(), &Options::default(), &mut |_| {}).expect("analysable");
    assert_eq!((with_load.load, with_load.family), ("recorded", "hydraulic"));
    let torque = Recording::from_columns(
        "t.csv",
        vec!["t_s".into(), "torque_nm".into(), "omega_rad_s".into()],
        vec![(0..400).map(|k| k as f64 * 1e-3).collect(), vec![1.0; 400], vec![2.0; 400]],
    );
    let err = analysis::analyze(&torque, &nominal, &Options::default(), &mut |_| {}).expect_err("no load");
    assert!(err.0.contains("load_nm") && err.0.contains("unknown"), "{}", err.0);
    // and the plant file says it in its own words
    let m = PlantModel::parse(
        &std::fs::read_to_string(support::root().join("config/plant.toml"))
            .expect("plant")
            .replace("kind = \"recorded\"", "kind = \"unknown\""),
        "plant.toml",
    )
    .expect("kind = \"unknown\" is accepted");
    assert_eq!(m.load, hydrolens::plant::LoadSpec::Unknown);
}

/// The worked example of docs/commands.md on the service's own recordings, shortened: `demo --plant` on a plant
/// with a hidden leak, stopped by SIGTERM, then `analyze DIR --drive pump1` against config/plant.toml names the
/// leak with its size. A plant file that does not
/// exist is bad input (exit 2, naming it).
#[test]
fn demo_on_a_leaking_plant_then_analyze_names_the_leak() {
    use std::process::{Command, Stdio};
    let tmp = tempfile::tempdir().expect("tmp");
    let plant = tmp.path().join("plant_leak.toml");
    let text = std::fs::read_to_string(support::root().join("config/plant.toml")).expect("plant");
    std::fs::write(&plant, format!("{text}\n[effects.internal_leakage]\nl_min_per_bar = 0.012\n")).expect("write");
    let recordings = tmp.path().join("rec");
    let demo = |plant: &Path| {
        Command::new(support::bin())
            .args(["demo", "--http", "127.0.0.1:0", "--plant"])
            .arg(plant)
            .arg("--recordings")
            .arg(&recordings)
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("demo starts")
    };
    let missing = demo(&tmp.path().join("nope.toml")).wait_with_output().expect("exits");
    assert_eq!(missing.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&missing.stderr).contains("nope.toml"));

    let mut child = demo(&plant);
    // 35 s of the service's own time in the recording, however fast this machine runs the demo
    let recorded = support::wait_for_sync(Duration::from_secs(120), || {
        std::thread::sleep(Duration::from_millis(200));
        recorded_up_to_s(&recordings) >= 35.0
    });
    assert!(recorded.is_some(), "the demo recorded 35 s within 120 s: {} s", recorded_up_to_s(&recordings));
    let _ = Command::new("kill").args(["-TERM", &child.id().to_string()]).status();
    assert!(support::wait_exit(&mut child, Duration::from_secs(10)).is_some(), "demo did not stop on SIGTERM");
    // the service told the drive to stop before the plant simulator went (the simulator stopped first, the write
    // then failed with a WARN)
    let mut log = String::new();
    std::io::Read::read_to_string(&mut child.stderr.take().expect("stderr"), &mut log).expect("utf-8");
    assert!(log.contains("the drive was sent control word 0"), "{log}");
    let out = Command::new(support::bin())
        .arg("analyze")
        .arg(&recordings)
        .args(["--drive", "pump1", "--model"])
        .arg(support::root().join("config/plant.toml"))
        .arg("--json")
        .arg(tmp.path().join("a.json"))
        .output()
        .expect("analyze runs");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(tmp.path().join("a.json")).expect("json")).expect("valid");
    assert_eq!(effects(&v), vec!["internal_leakage".to_string()], "{}", v["findings"]);
    let l = v["findings"][0]["parameters"]["l_min_per_bar"].as_f64().expect("size");
    eprintln!("demo --plant (35 s at 1 ms) → analyze: internal_leakage {l:.5} L/min/bar (truth 0.012)");
    assert!((l - 0.012).abs() <= 0.3 * 0.012, "leak {l}");
}

/// The newest `t_s` in the CSV files of `dir` (their last complete line), 0 while there is none.
fn recorded_up_to_s(dir: &Path) -> f64 {
    use std::io::{Read, Seek, SeekFrom};
    let last_t = |path: &Path| -> Option<f64> {
        let mut f = std::fs::File::open(path).ok()?;
        let mut head = String::new();
        std::io::BufRead::read_line(&mut std::io::BufReader::new(&f), &mut head).ok()?;
        let col = head.trim_end().split(',').position(|c| c == "t_s")?;
        let len = f.metadata().ok()?.len();
        f.seek(SeekFrom::Start(len.saturating_sub(4096))).ok()?;
        let mut tail = String::new();
        f.read_to_string(&mut tail).ok()?;
        let complete = &tail[..tail.rfind('\n')?];
        complete.rsplit('\n').next()?.split(',').nth(col)?.parse().ok()
    };
    std::fs::read_dir(dir)
        .map(|d| {
            d.filter_map(Result::ok)
                .map(|e| e.path())
                .filter(|p| p.extension().is_some_and(|x| x == "csv"))
                .filter_map(|p| last_t(&p))
                .fold(0.0, f64::max)
        })
        .unwrap_or(0.0)
}

/// Several files: joined in time order; files of two service runs (overlapping `t_s`) and a directory without
/// `--drive` are bad input, exit 2, naming what is wrong.
#[test]
fn analyze_joins_files_and_refuses_what_cannot_be_joined() {
    let tmp = tempfile::tempdir().expect("tmp");
    let mut truth = PlantModel::reference();
    truth.effects.internal_leakage = Some(InternalLeakage { l_min_per_bar: 0.012 });
    let rec = hydrolens::recording::simulated::test_stand(&truth, RUN_S, 33, &mut |_| {}).expect("simulable");
    let rec = as_the_service_records(&rec, 5, 33);
    // split in three as rotation would, written out of order
    let n = rec.len();
    let part = |a: usize, b: usize| {
        let cols: Vec<Vec<f64>> = rec.names().iter().map(|c| rec.column(c).expect("col")[a..b].to_vec()).collect();
        Recording::from_columns("part", rec.names().to_vec(), cols)
    };
    let files: Vec<std::path::PathBuf> = [(0, n / 3), (n / 3, 2 * n / 3), (2 * n / 3, n)]
        .iter()
        .enumerate()
        .map(|(i, &(a, b))| {
            let p = tmp.path().join(format!("pump1-{}.csv", 1000 + i));
            let f = std::fs::File::create(&p).expect("create");
            hydrolens::recording::write_csv(f, &part(a, b)).expect("write");
            p
        })
        .collect();
    let analyze = |args: &[&std::ffi::OsStr]| {
        std::process::Command::new(support::bin())
            .arg("analyze")
            .args(args)
            .arg("--model")
            .arg(support::root().join("config/plant.toml"))
            .arg("--json")
            .arg(tmp.path().join("a.json"))
            .output()
            .expect("runs")
    };
    let out = analyze(&[files[2].as_os_str(), files[0].as_os_str(), files[1].as_os_str()]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(tmp.path().join("a.json")).expect("json")).expect("valid");
    assert_eq!(v["samples"].as_u64(), Some(n as u64));
    assert_eq!(effects(&v), vec!["internal_leakage".to_string()]);
    // the same file twice: overlapping time
    let out = analyze(&[files[0].as_os_str(), files[0].as_os_str()]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("overlaps"), "{}", String::from_utf8_lossy(&out.stderr));
    let out = analyze(&[tmp.path().as_os_str()]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("--drive"));
    let out = analyze(&[tmp.path().as_os_str(), "--drive".as_ref(), "pump2".as_ref()]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("pump2"));
}

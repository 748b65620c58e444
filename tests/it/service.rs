//! Simulator + service + HTTP in one process over loopback: regulation, retargeting, monitor mode, estimates,
//! recordings, loop timing.

use std::time::{Duration, Instant};

use crate::support::{self, Stack, TOKEN, wait_for};

const SPEED: &str =
    "[drives.control]\nmode = \"speed\"\ntarget_omega_rad_s = 40.0\nmax_hz = 50.0\nramp_hz_per_s = 20.0\n";

/// Seconds until the true speed stays within 5 % of `target` for a whole second (None: not within `limit`).
async fn settle(stack: &Stack, target: f64, limit: Duration) -> Option<f64> {
    let start = Instant::now();
    let mut inside_since: Option<Instant> = None;
    while start.elapsed() < limit {
        let omega = stack.sim.lock().truth().omega_rad_s;
        if (omega - target).abs() <= 0.05 * target {
            let since = *inside_since.get_or_insert_with(Instant::now);
            if since.elapsed() >= Duration::from_secs(1) {
                return Some((since - start).as_secs_f64());
            }
        } else {
            inside_since = None;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    None
}

async fn post_target(stack: &Stack, target: f64, token: Option<&str>) -> reqwest::StatusCode {
    let mut req = reqwest::Client::new()
        .post(format!("{}/api/drives/pump1/target", stack.url))
        .json(&serde_json::json!({ "target_omega_rad_s": target }));
    if let Some(t) = token {
        req = req.bearer_auth(t);
    }
    req.send().await.expect("POST target").status()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn speed_mode_regulates_retargets_and_estimates_near_truth() {
    let run = async {
        // 1 kHz: every plant sample (the simulator samples at 1 ms)
        let stack = Stack::start(8.0, 1, SPEED).await;
        let t1 = settle(&stack, 40.0, Duration::from_secs(10)).await.expect("within 5 % of 40 rad/s in 10 s");
        // steady-state error and estimates over a second
        let (mut err2, mut est_omega2, mut load_err, n) = (0.0, 0.0, 0.0, 50);
        for _ in 0..n {
            let truth = stack.sim.lock().truth();
            let s = stack.state.drives[0].snapshot();
            let e = s.estimate.expect("estimates");
            err2 += (truth.omega_rad_s - 40.0).powi(2);
            est_omega2 += (e.omega_hat_rad_s - truth.omega_rad_s).powi(2);
            load_err += (e.load_hat_nm - truth.load_nm).abs();
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        let (rms, est_rms, load_mae) = ((err2 / n as f64).sqrt(), (est_omega2 / n as f64).sqrt(), load_err / n as f64);
        assert!(rms < 1.0, "speed error RMS {rms} rad/s");
        assert!(est_rms < 1.0, "ω̂ RMS error {est_rms} rad/s");
        assert!(load_mae < 1.5, "T̂_L mean abs error {load_mae} N·m against 8 N·m");

        assert_eq!(post_target(&stack, 25.0, None).await, reqwest::StatusCode::UNAUTHORIZED);
        assert_eq!(post_target(&stack, 25.0, Some("wrong")).await, reqwest::StatusCode::UNAUTHORIZED);
        assert_eq!(post_target(&stack, 1e6, Some(TOKEN)).await, reqwest::StatusCode::UNPROCESSABLE_ENTITY);
        assert_eq!(post_target(&stack, 25.0, Some(TOKEN)).await, reqwest::StatusCode::OK);
        let t2 = settle(&stack, 25.0, Duration::from_secs(10)).await.expect("within 5 % of 25 rad/s in 10 s");
        assert_eq!(stack.status().await["target_omega_rad_s"], 25.0);
        eprintln!(
            "regulation: settled to 40 rad/s (±5 %) in {t1:.2} s, RMS error {rms:.3} rad/s; ω̂ RMS {est_rms:.3} rad/s, \
             |T̂_L − T_L| {load_mae:.3} N·m; retarget to 25 rad/s settled in {t2:.2} s"
        );
        assert!(!stack.sim.lock().truth().tripped);
        stack.stop().await;
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("bounded");
}

/// At the default 10 ms poll the service sees every tenth plant sample. The Kalman filter (true J and B) keeps its
/// load estimate there (rls-sgd at 10 ms: `at_a_10_ms_poll_rls_sgd_identifies_inertia_under_a_random_brake_program`).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn at_the_default_10_ms_poll_kalman_regulates_and_estimates_near_truth() {
    let run = async {
        let config = format!("{SPEED}\n[drives.estimator]\nmethod = \"kalman\"\n");
        let stack = Stack::start(8.0, 10, &config).await;
        let t1 = settle(&stack, 40.0, Duration::from_secs(10)).await.expect("within 5 % of 40 rad/s in 10 s");
        // the load estimate converges (2 s at most, as long as this test ever gave it), then is measured for a second
        wait_for(Duration::from_secs(15), || async {
            let truth = stack.sim.lock().truth();
            stack.state.drives[0].snapshot().estimate.is_some_and(|e| (e.load_hat_nm - truth.load_nm).abs() < 1.5)
        })
        .await
        .expect("T̂_L within 1.5 N·m of the truth within 2 s of settling");
        let (mut load_err, mut est_omega2, n) = (0.0, 0.0, 50);
        for _ in 0..n {
            let truth = stack.sim.lock().truth();
            let e = stack.state.drives[0].snapshot().estimate.expect("estimates");
            load_err += (e.load_hat_nm - truth.load_nm).abs();
            est_omega2 += (e.omega_hat_rad_s - truth.omega_rad_s).powi(2);
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        let (load_mae, est_rms) = (load_err / n as f64, (est_omega2 / n as f64).sqrt());
        eprintln!("10 ms poll, kalman: settled in {t1:.2} s; ω̂ RMS {est_rms:.3} rad/s, |T̂_L − T_L| {load_mae:.3} N·m");
        assert!(est_rms < 1.0, "ω̂ RMS error {est_rms} rad/s");
        assert!(load_mae < 1.5, "T̂_L mean abs error {load_mae} N·m against 8 N·m");
        stack.stop().await;
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("bounded");
}

/// Writes the reference plant (config/plant.toml) with J and B replaced into `dir`; the `model = …` line of a drive's
/// `[drives.estimator]` that points at it.
fn wrong_model(dir: &std::path::Path, inertia_kg_m2: &str, viscous_nm_s_rad: &str) -> String {
    let reference = std::fs::read_to_string(support::root().join("config/plant.toml")).expect("plant.toml");
    let text = reference
        .replace("inertia_kg_m2 = 0.08", &format!("inertia_kg_m2 = {inertia_kg_m2}"))
        .replace("viscous_nm_s_rad = 0.04", &format!("viscous_nm_s_rad = {viscous_nm_s_rad}"));
    assert_ne!(text, reference);
    let model = dir.join("wrong.toml");
    std::fs::write(&model, text).expect("write model");
    format!("model = {:?}\n", model.display().to_string())
}

/// `sim` and `serve` over TCP at the contract's 10 ms poll, rls-sgd started from a nominal J and B 50 % wrong (the
/// simulator's truth is 0.08 and 0.04; a nominal equal to the truth cannot be beaten, so the estimator rightly keeps
/// it with the prior's spread), a random brake program (seeded) the service is not told, and target changes for
/// excitation: `/api/status` carries J identified near the truth with a standard deviation that contains it, B with
/// its own, and T̂_L following the brake. Each dwell is counted in the loop's polls; the targets keep stepping until
/// J is identified, 20 of them at most.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn at_a_10_ms_poll_rls_sgd_identifies_inertia_under_a_random_brake_program() {
    let run = async {
        let mut plant = support::test_plant(0.0);
        let brake = hydrolens::plant::scenario::Scenario::generate(hydrolens::plant::scenario::Family::Brake, 77, 30.0);
        let levels: Vec<f64> = (0..8).map(|k| brake.load.torque_at(1.0 + 2.5 * k as f64, 0.0, 0.0)).collect();
        plant.load = hydrolens::plant::LoadSpec::Steps { levels_nm: levels.clone(), period_s: 2.5 };
        let dir = tempfile::tempdir().expect("tmp");
        let extra =
            format!("{SPEED}[drives.estimator]\nmethod = \"rls-sgd\"\n{}", wrong_model(dir.path(), "0.12", "0.06"));
        let stack = Stack::start_on(plant, 10, &extra).await;
        let identified = |s: &serde_json::Value| s["identification"]["inertia"]["state"] == "identified";
        let targets = [30.0, 45.0, 20.0, 40.0, 25.0, 50.0, 35.0];
        // a dwell is 170 fresh samples (the estimator learns only from those), not 170 polls
        let fresh = |l: &hydrolens::service::state::Link| {
            l.polls.saturating_sub(l.stale_samples + l.rejected_samples + l.errors)
        };
        // the status as J is first identified: what it claims then is what is judged. A J first identified within
        // 8 s can fall back to "too little excitation" a second later (seen in the repeated suite runs: 619 polls,
        // the loop left early, the later status no longer identified); the message gives J's state after the load
        // samples
        let mut at_identification = None;
        for target in targets.iter().cycle().take(20) {
            assert_eq!(post_target(&stack, *target, Some(TOKEN)).await, reqwest::StatusCode::OK);
            let from = fresh(&stack.state.drives[0].snapshot().link);
            let dwell = support::wait_for(Duration::from_secs(30), || async {
                fresh(&stack.state.drives[0].snapshot().link) >= from + 170
            });
            dwell.await.expect("170 fresh samples within 30 s");
            let status = stack.status().await;
            if identified(&status) {
                at_identification = Some(status);
                break;
            }
        }
        let (mut load_err, n) = (0.0, 50);
        for _ in 0..n {
            let truth = stack.sim.lock().truth();
            let e = stack.state.drives[0].snapshot().estimate.expect("estimates");
            load_err += (e.load_hat_nm - truth.load_nm).abs();
            stack.wait_polls(2, "between load samples").await;
        }
        let later = stack.status().await["identification"]["inertia"]["state"].clone();
        let Some(status) = at_identification else {
            let s = stack.status().await;
            panic!(
                "J not identified in 20 targets: {}; link {}; timing {}",
                s["identification"], s["link"], s["timing"]
            );
        };
        let e = &status["estimate"];
        let (j, j_sd) = (e["inertia_hat_kg_m2"].as_f64().expect("J"), e["inertia_sd_kg_m2"].as_f64().expect("σ_J"));
        let (b, b_sd) =
            (e["viscous_hat_nm_s_rad"].as_f64().expect("B"), e["viscous_sd_nm_s_rad"].as_f64().expect("σ_B"));
        let load_mae = load_err / n as f64;
        eprintln!(
            "10 ms, rls-sgd from J 0.12, B 0.06, brake levels {levels:.1?}: J {j:.4} ± {j_sd:.4} (true 0.08), \
             B {b:.4} ± {b_sd:.4} (true 0.04) when J was identified, at {:.1} s; |T̂_L − T_L| {load_mae:.2} N·m over \
             the next 100 polls, J's state then {later}",
            status["sample"]["t_s"].as_f64().unwrap_or(f64::NAN)
        );
        assert!((j / 0.08 - 1.0).abs() <= 0.15, "J {j} ± {j_sd}");
        assert!(j_sd > 0.0 && j_sd < 0.1 * j, "σ_J {j_sd}");
        // (4 sd: one run, not a coverage figure; the battery judges coverage)
        assert!((j - 0.08).abs() <= 4.0 * j_sd, "J {j} ± {j_sd} excludes the truth 0.08");
        assert!(b_sd > 0.0, "σ_B {b_sd}");
        assert!(load_mae < 2.0, "T̂_L mean abs error {load_mae} N·m");
        stack.stop().await;
    };
    tokio::time::timeout(Duration::from_secs(240), run).await.expect("bounded");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn monitor_mode_writes_nothing_and_refuses_write_routes() {
    let run = async {
        let stack = Stack::start(5.0, 10, "").await;
        wait_for(Duration::from_secs(15), || async { stack.state.ready() }).await.expect("fresh data");
        stack.wait_polls(30, "monitoring").await;
        assert_eq!(post_target(&stack, 30.0, Some(TOKEN)).await, reqwest::StatusCode::CONFLICT);
        assert_eq!(support::post_reset(&stack.url).await, 409);
        stack.wait_polls(5, "a write, had the refused routes asked for one, would land").await;
        assert_eq!(stack.sim.lock().writes, 0, "monitor mode never writes");
        let s = stack.status().await;
        assert_eq!(s["mode"], "monitor");
        assert!(s["link"]["polls"].as_u64().expect("polls") > 30);
        assert_eq!(s["setpoint_hz"], serde_json::Value::Null);
        stack.stop().await;
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("bounded");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn recordings_hold_every_fresh_sample_and_are_readable() {
    let run = async {
        // the drive's output power read too, so that every column of the row holds values
        let stack = Stack::start(6.0, 10, &format!("{SPEED}\n[drives.registers.drive_power_w]\n")).await;
        wait_for(Duration::from_secs(15), || async { stack.state.ready() }).await.expect("fresh data");
        stack.wait_polls(150, "recording").await; // more than the 100 rows asserted below, if every sample is kept
        let list = support::get_json(format!("{}/api/recordings", stack.url)).await;
        let name = list["files"][0]["name"].as_str().expect("a recording").to_string();
        assert!(name.starts_with("pump1-") && name.ends_with(".csv"), "{name}");
        let live = reqwest::get(format!("{}/api/recordings/{name}", stack.url)).await.expect("GET file");
        assert_eq!(live.status(), 200);
        let text = live.text().await.expect("text");
        assert!(
            text.starts_with("t_s,f_set_hz,f_drive_hz,p_in_bar,p_out_bar,omega_rad_s,drive_power_w,omega_hat_rad_s"),
            "{text:.80}"
        );
        let bad = reqwest::get(format!("{}/api/recordings/..%2Fsecret.csv", stack.url)).await.expect("GET");
        assert!(bad.status().is_client_error());
        let dir = stack.stop().await; // closes the file: every row written, then compressed (recording.compress)
        assert!(!dir.path().join(&name).exists(), "the closed file was compressed");
        let name = format!("{name}.gz");
        let rec = hydrolens::recording::load(&dir.path().join(&name)).expect("a valid recording");
        assert!(rec.len() > 100, "{} rows", rec.len());
        for col in hydrolens::service::state::COLUMNS {
            assert!(rec.present(col).is_some(), "column {col}");
        }
        let omega = rec.column("omega_rad_s").expect("omega");
        let hat = rec.column("omega_hat_rad_s").expect("omega_hat");
        assert!(support::rmse(hat, omega) < 3.0);
        // and `hydrolens estimate` replays it
        let out = dir.path().join("est.csv");
        let status = std::process::Command::new(support::bin())
            .arg("estimate")
            .arg(dir.path().join(&name))
            .arg("--model")
            .arg(support::root().join("config/plant.toml"))
            .arg("--out")
            .arg(&out)
            .status()
            .expect("estimate runs");
        assert!(status.success());
        let est = hydrolens::recording::load(&out).expect("estimate output");
        assert_eq!(est.len(), rec.len(), "one output row per recorded row");
        assert!(est.column("load_hat_nm").expect("load").iter().all(|v| v.is_finite()));
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("bounded");
}

/// Loop timing on loopback at 1 ms and 10 ms (the figures go to the test log).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn poll_loop_holds_1_ms_and_10_ms_on_loopback() {
    let run = async {
        for poll_ms in [1u64, 10] {
            let started = Instant::now();
            let stack = Stack::start(5.0, poll_ms, SPEED).await;
            // a window of 2100 ms of polls at the nominal rate, counted in the loop's own cycles; the rate is then
            // the polls over the time they took since the service started (70 % of nominal at least)
            let polls = 2100 / poll_ms;
            stack.wait_polls(polls, "the timing window").await;
            let took = started.elapsed();
            let s = stack.state.drives[0].snapshot();
            let t = s.timing;
            eprintln!(
                "poll {poll_ms} ms: mean period {:.3} ms, jitter p50 {:.3} ms, p99 {:.3} ms, overruns {} of {} polls \
                 in {:.0} ms, errors {}",
                t.mean_period_ms,
                t.jitter_p50_ms,
                t.jitter_p99_ms,
                t.overruns,
                s.link.polls,
                took.as_secs_f64() * 1e3,
                s.link.errors
            );
            let nominal = poll_ms as f64;
            assert!((t.mean_period_ms - nominal).abs() < 0.25 * nominal, "mean period {} ms", t.mean_period_ms);
            assert_eq!(s.link.errors, 0);
            let rate_per_ms = s.link.polls as f64 / (took.as_secs_f64() * 1e3);
            assert!(rate_per_ms > 0.7 / nominal, "{} polls in {took:?}", s.link.polls);
            stack.stop().await;
        }
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("bounded");
}

/// The poll thread of a drive, by its name in /proc (Linux): (thread id, scheduling policy).
fn poll_thread(drive: &str) -> Option<(String, u32)> {
    let want = format!("poll-{drive}");
    let read = |dir: &std::path::Path| -> Option<(String, u32)> {
        if std::fs::read_to_string(dir.join("comm")).ok()?.trim() != want {
            return None;
        }
        let stat = std::fs::read_to_string(dir.join("stat")).ok()?;
        // the fields after the ")" that ends the name start at field 3; the policy is field 41
        let policy = stat.rsplit_once(')')?.1.split_whitespace().nth(41 - 3)?.parse().ok()?;
        Some((dir.file_name()?.to_string_lossy().into_owned(), policy))
    };
    // threads come and go while this reads: skip any that cannot be read
    std::fs::read_dir("/proc/self/task").ok()?.filter_map(|t| read(&t.ok()?.path())).next()
}

/// Each drive polls on a thread of its own with a 1 µs timer slack; `realtime_priority` puts it under SCHED_FIFO
/// where the kernel allows it (probed first on a scratch thread), and it stays at normal priority where not.
#[cfg(target_os = "linux")]
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn each_drive_polls_on_its_own_thread_with_the_priority_asked_for() {
    use thread_priority::{RealtimeThreadSchedulePolicy, ThreadPriority, ThreadSchedulePolicy};
    let allowed = std::thread::spawn(|| {
        thread_priority::set_thread_priority_and_policy(
            thread_priority::thread_native_id(),
            ThreadPriority::Crossplatform(5u8.try_into().expect("1..=99")),
            ThreadSchedulePolicy::Realtime(RealtimeThreadSchedulePolicy::Fifo),
        )
        .is_ok()
    })
    .join()
    .expect("probe");
    let run = async {
        let (_sim, addr, sim_stop, sim_task) = support::start_sim(support::test_plant(5.0), 0).await;
        let dir = tempfile::tempdir().expect("tmp");
        let drive = |name: &str, extra: &str| {
            format!(
                "[[drives]]\nname = \"{name}\"\naddress = \"{addr}\"\npoll_ms = 5\n{extra}[drives.estimator]\n\
                 model = {:?}\n",
                support::root().join("config/plant.toml")
            )
        };
        let text = format!(
            "[http]\nbind = \"127.0.0.1:0\"\n[recording]\ndir = {:?}\n{}{}",
            dir.path().display().to_string(),
            drive("rt-probe", "realtime_priority = 5\n"),
            drive("plain", "")
        );
        let svc = support::start_service(&text).await;
        let url = svc.url.clone();
        wait_for(Duration::from_secs(15), || async { svc.state.drives.iter().all(|d| d.snapshot().link.polls > 10) })
            .await
            .expect("both drives poll");
        let rt = poll_thread("rt-probe").expect("a thread named poll-rt-probe");
        let plain = poll_thread("plain").expect("a thread named poll-plain");
        assert_ne!(rt.0, plain.0, "a thread per drive");
        assert_eq!(plain.1, 0, "no realtime_priority: SCHED_OTHER");
        assert_eq!(rt.1, if allowed { 1 } else { 0 }, "SCHED_FIFO exactly when the kernel allows it");
        // and the status says what the kernel granted
        let status = support::get_json(format!("{url}/api/status")).await;
        let timing = |i: usize| status["drives"][i]["timing"].clone();
        assert_eq!(
            timing(0)["realtime_priority"],
            if allowed { serde_json::json!(5) } else { serde_json::Value::Null }
        );
        assert_eq!(timing(1)["realtime_priority"], serde_json::Value::Null);
        // the kernel gives real-time threads no slack at all
        assert_eq!(timing(0)["timer_slack_ns"], if allowed { 0 } else { 1_000 }, "{status}");
        assert_eq!(timing(1)["timer_slack_ns"], 1_000, "{status}");
        tokio::time::timeout(Duration::from_secs(5), svc.stop()).await.expect("service stops").expect("http server");
        assert!(poll_thread("rt-probe").is_none(), "the poll thread ended with the service");
        sim_stop.cancel();
        let _ = sim_task.await;
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("bounded");
}

/// The regulator's tracking error (RMS of the true speed against the target, rad/s) while the demo's target
/// program runs for `seconds`, sampled every 20 ms to the program's end once the drive has run 200 poll cycles (2 s
/// at 10 ms: the start-up transient left out).
async fn tracking_rms(stack: &Stack, seconds: u64) -> f64 {
    let drive = stack.state.drives[0].clone();
    let done = std::sync::atomic::AtomicBool::new(false);
    let program = async {
        support::follow_demo_program(&drive, seconds).await;
        done.store(true, std::sync::atomic::Ordering::Relaxed);
    };
    let sample = async {
        stack.wait_polls(200, "the regulator's start").await;
        let (mut se, mut n) = (0.0, 0usize);
        while !done.load(std::sync::atomic::Ordering::Relaxed) {
            let omega = stack.sim.lock().truth().omega_rad_s;
            let target = drive.snapshot().target_omega_rad_s;
            se += (omega - target).powi(2);
            n += 1;
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        (se / n.max(1) as f64).sqrt()
    };
    let (_, rms) = tokio::join!(program, sample);
    rms
}

/// Speed mode on loads the estimator is not told and cannot tell from friction (a centrifugal fan) or that never
/// repeat (a smooth random load), both estimators started from the same wrong J and B: with rls-sgd adapting, the
/// speed follows the target at least as well as with adaptation off (the Kalman filter on the wrong values).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn speed_mode_with_adaptation_follows_a_fan_and_a_random_load_as_well_as_without() {
    let run = async {
        // the service's nominal model: the reference plant with J and B wrong (×1.6, ×2.2)
        let dir = tempfile::tempdir().expect("tmp");
        let wrong = wrong_model(dir.path(), "0.13", "0.09");
        for load in [
            hydrolens::plant::LoadSpec::Centrifugal { torque_nm: 12.0, at_rad_s: 60.0 },
            hydrolens::plant::LoadSpec::Random { mean_nm: 8.0, sd_nm: 4.0, correlation_s: 1.0, seed: 5 },
        ] {
            let mut plant = support::test_plant(0.0);
            plant.load = load.clone();
            let adapt = format!("{SPEED}[drives.estimator]\nmethod = \"rls-sgd\"\n{wrong}");
            let fixed = format!("{SPEED}[drives.estimator]\nmethod = \"kalman\"\n{wrong}");
            let (a, k) = tokio::join!(Stack::start_on(plant.clone(), 10, &adapt), Stack::start_on(plant, 10, &fixed));
            let (rms_adapt, rms_fixed) = tokio::join!(tracking_rms(&a, 12), tracking_rms(&k, 12));
            let id = a.status().await["identification"].clone();
            eprintln!("{load:?}: speed error RMS {rms_adapt:.2} rad/s adapting, {rms_fixed:.2} without; {id}");
            assert!(rms_adapt <= 1.1 * rms_fixed + 0.2, "{load:?}: {rms_adapt} against {rms_fixed}");
            a.stop().await;
            k.stop().await;
        }
    };
    tokio::time::timeout(Duration::from_secs(60), run).await.expect("bounded");
}

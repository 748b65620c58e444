//! How honest rls-sgd's B confidence is over a whole run, not only at its end (docs/estimator.md): the battery's
//! scenarios from their wrong starts, and for every row from 5 s on whether the true B lies within two of the
//! reported standard deviations, and whether a B more than 25 % off is shown as identified (the estimator's verdict,
//! `viscous_identified`, as the dashboard shows it), and a B within 25 % shown as not identified.
//!
//! `cargo run --release --example estimator_confidence -- [set=tuned|held-out|fresh|unseen|final|sealed] [runs=N]`
//! `[polls=1,5,10] [periodic=0]` (`periodic=0`: without the periodic-load fit); `[seed=K trace]`: only scenario K,
//! printing B̂ ± σ_B every 2.5 s.

use hydrolens::estimator::battery::{self, SCORE_FROM_S};
use hydrolens::estimator::{EstimatorSettings, Identification, Method, try_build};
use hydrolens::plant::PlantModel;
use hydrolens::plant::scenario::{Family, Scenario};

fn main() {
    let (mut set, mut runs, mut polls) = ("tuned".to_string(), 24u64, vec![1u32, 5, 10]);
    let (mut only_seed, mut trace, mut periodic) = (None::<u64>, false, true);
    for arg in std::env::args().skip(1) {
        match arg.split_once('=') {
            Some(("set", v)) => set = v.to_string(),
            Some(("runs", v)) => runs = v.parse().unwrap_or(runs),
            Some(("polls", v)) => polls = v.split(',').filter_map(|p| p.parse().ok()).collect(),
            Some(("seed", v)) => only_seed = v.parse().ok(),
            Some(("periodic", v)) => periodic = v != "0",
            None if arg == "trace" => trace = true,
            _ => eprintln!("ignoring {arg}"),
        }
    }
    let Some(first) = battery::first_seed(&set) else {
        eprintln!("unknown set {set:?}: tuned, held-out, fresh, unseen, final or sealed");
        std::process::exit(2);
    };
    let truth = PlantModel::reference();
    let b_true = truth.motor.viscous_nm_s_rad;
    let settings =
        EstimatorSettings { method: Method::RlsSgd, periodic_load: periodic, ..EstimatorSettings::default() };
    println!("set {set}, {runs} scenarios, B confidence from {SCORE_FROM_S} s on");
    println!(
        "| poll | final B within 2 sd | rows: B within 2 sd | rows: B > 25 % off | of those, shown as identified | rows: B within 25 %, not identified |"
    );
    println!("|---|---|---|---|---|---|");
    for &poll in &polls {
        let mut good_unidentified = 0usize;
        let identified = Identification::Identified.code();
        let (mut final_ok, mut n, mut rows, mut covered, mut off, mut off_identified) =
            (0, 0, 0usize, 0usize, 0usize, 0usize);
        for i in (0..runs).filter(|i| only_seed.is_none_or(|k| k == first + i)) {
            let scenario = Scenario::generate(Family::ALL[i as usize % Family::ALL.len()], first + i, 60.0);
            let polled = battery::poll(&scenario, &truth, poll);
            let wrong = battery::wrong_model(&scenario, &truth);
            let Ok(mut est) = try_build(&settings, &wrong) else { unreachable!("the battery's model is valid") };
            let mut last = est.estimate();
            for (k, m) in polled.measurements.iter().enumerate() {
                last = est.update(m);
                let t = polled.t_s[k];
                if trace && ((t * 1e3).round() as i64) % 2500 == 0 {
                    let (b, sd) = (last.viscous_hat_nm_s_rad, last.viscous_sd_nm_s_rad);
                    println!("{poll} ms {}: t {t:5.1} s  B {b:.4} ± {sd:.4} (true {b_true})", scenario.describe());
                }
                if t < SCORE_FROM_S {
                    continue;
                }
                let err = (last.viscous_hat_nm_s_rad - b_true).abs();
                rows += 1;
                covered += usize::from(err <= 2.0 * last.viscous_sd_nm_s_rad);
                if err > 0.25 * b_true {
                    off += 1;
                    off_identified += usize::from(last.viscous_identified == identified);
                } else {
                    good_unidentified += usize::from(last.viscous_identified != identified);
                }
            }
            n += 1;
            final_ok += usize::from((last.viscous_hat_nm_s_rad - b_true).abs() <= 2.0 * last.viscous_sd_nm_s_rad);
        }
        let pct = |a: usize, b: usize| 100.0 * a as f64 / b.max(1) as f64;
        println!(
            "| {poll} ms | {final_ok}/{n} | {:.1} % | {:.1} % | {:.1} % | {:.1} % |",
            pct(covered, rows),
            pct(off, rows),
            pct(off_identified, off),
            pct(good_unidentified, rows - off)
        );
    }
}

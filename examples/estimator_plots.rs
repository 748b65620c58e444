//! Measures both estimators on the 60 s test-stand run and draws docs/estimator_speed.svg and docs/estimator_load.svg.
//!
//! `cargo run --example estimator_plots [-- --no-plots] [load=steps|ramp|trend] [seed=N] [j=1.3 b=0.7] [key=value …]`: key=value pairs go into the
//! `[estimator]` table (e.g. `eta=0.05`), for trying settings.

use hydrolens::estimator::{self, Estimate, EstimatorSettings, Method};
use hydrolens::plant::PlantModel;
use hydrolens::recording::Recording;
use hydrolens::recording::simulated;
use plotters::prelude::*;

const SCORE_FROM_S: f64 = 5.0;

fn rmse(a: &[f64], b: &[f64], t: &[f64]) -> f64 {
    let d: Vec<f64> =
        a.iter().zip(b).zip(t).filter(|(_, t)| **t >= SCORE_FROM_S).map(|((x, y), _)| (x - y).powi(2)).collect();
    (d.iter().sum::<f64>() / d.len() as f64).sqrt()
}

fn run(rec: &Recording, model: &PlantModel, settings: &EstimatorSettings) -> Vec<Estimate> {
    let mut est = match estimator::try_build(settings, model) {
        Ok(e) => e,
        Err(e) => panic!("settings: {e}"),
    };
    hydrolens::replay::replay(rec, model, "model", est.as_mut()).expect("replay")
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let plots = !args.iter().any(|a| a == "--no-plots");
    let load = args.iter().find_map(|a| a.strip_prefix("load=")).unwrap_or("recorded").to_string();
    let table: String = args
        .iter()
        .filter(|a| {
            a.contains('=')
                && !a.starts_with("load=")
                && !a.starts_with("seed=")
                && !a.starts_with("j=")
                && !a.starts_with("b=")
        })
        .map(|a| format!("{a}\n"))
        .collect();
    let mut truth = PlantModel::reference();
    truth.load = match load.as_str() {
        "recorded" => hydrolens::plant::LoadSpec::Recorded,
        "ramp" => hydrolens::plant::LoadSpec::Ramp { from_nm: 2.0, to_nm: 14.0, start_s: 10.0, duration_s: 40.0 },
        "trend" => hydrolens::plant::LoadSpec::Trend { start_nm: 1.0, rate_nm_per_s: 0.2, max_nm: 20.0 },
        _ => hydrolens::plant::LoadSpec::Steps { levels_nm: vec![3.0, 12.0, 6.0], period_s: 5.0 },
    };
    let factor = |key: &str, default: f64| {
        args.iter().find_map(|a| a.strip_prefix(key)).and_then(|s| s.parse().ok()).unwrap_or(default)
    };
    let (j_factor, b_factor) = (factor("j=", 1.3), factor("b=", 0.7));
    let seed = args.iter().find_map(|a| a.strip_prefix("seed=")).and_then(|s| s.parse().ok()).unwrap_or(7);
    let rec = simulated::test_stand(&truth, 60.0, seed, &mut |_| {}).map_err(|e| format!("{e:?}"))?;
    let t = rec.t_s().to_vec();
    let true_w = rec.column("true_omega_rad_s").ok_or("true_omega")?.to_vec();
    let true_l = rec.column("true_load_nm").ok_or("true_load")?.to_vec();
    let meas_w = rec.column("omega_rad_s").ok_or("omega")?.to_vec();
    let extra: toml::Table = toml::from_str(&table)?;
    let mut results = Vec::new();
    // rls-sgd and kalman as the targets have them, then kalman with the same wrong J and B as rls-sgd starts from.
    for (method, wrong) in [(Method::RlsSgd, true), (Method::Kalman, false), (Method::Kalman, true)] {
        let mut model = PlantModel::reference();
        if wrong {
            model.motor.inertia_kg_m2 *= j_factor;
            model.motor.viscous_nm_s_rad *= b_factor;
        }
        let mut tbl = extra.clone();
        tbl.insert("method".into(), toml::Value::String(method.name().into()));
        model.estimator = Some(tbl);
        let settings = EstimatorSettings::from_model(&model, "model")?;
        let e = run(&rec, &model, &settings);
        let w: Vec<f64> = e.iter().map(|e| e.omega_hat_rad_s).collect();
        let l: Vec<f64> = e.iter().map(|e| e.load_hat_nm).collect();
        let last = e.last().copied().ok_or("empty")?;
        println!(
            "{:24} omega_rmse={:.3} rad/s ({:.3} sigma)  load_rmse={:.3} N·m  J_end={:.4} ({:+.1} %)  B_end={:.4} ({:+.1} %)",
            format!("{method}{}", if wrong { format!(" (J ×{j_factor}, B ×{b_factor})") } else { String::new() }),
            rmse(&w, &true_w, &t),
            rmse(&w, &true_w, &t) / 0.8,
            rmse(&l, &true_l, &t),
            last.inertia_hat_kg_m2,
            (last.inertia_hat_kg_m2 / 0.08 - 1.0) * 100.0,
            last.viscous_hat_nm_s_rad,
            (last.viscous_hat_nm_s_rad / 0.04 - 1.0) * 100.0,
        );
        if std::env::var("HL_TRACE").is_ok() {
            for k in (0..e.len()).step_by(2000) {
                println!(
                    "  t={:5.1} J={:.4} B={:.4} L={:.2}/{:.2}",
                    t[k], e[k].inertia_hat_kg_m2, e[k].viscous_hat_nm_s_rad, e[k].load_hat_nm, true_l[k]
                );
            }
        }
        results.push((method, w, l));
    }
    if plots {
        plot(
            "docs/estimator_speed.svg",
            "Speed: measured, true and estimated (rad/s)",
            &t,
            &[
                ("measured", &meas_w, RGBColor(200, 200, 200)),
                ("true", &true_w, BLACK),
                ("rls-sgd", &results[0].1, BLUE),
                ("kalman", &results[1].1, RED),
            ],
        )?;
        plot(
            "docs/estimator_load.svg",
            "Load torque: true and estimated (N·m)",
            &t,
            &[("true", &true_l, BLACK), ("rls-sgd", &results[0].2, BLUE), ("kalman", &results[1].2, RED)],
        )?;
    }
    Ok(())
}

fn plot(
    path: &str,
    title: &str,
    t: &[f64],
    series: &[(&str, &Vec<f64>, RGBColor)],
) -> Result<(), Box<dyn std::error::Error>> {
    // 0–20 s: the first half of the program, readable at this size; every 5th sample.
    let n = t.iter().take_while(|t| **t <= 20.0).count();
    let (lo, hi) =
        series.iter().flat_map(|s| s.1[..n].iter()).fold((f64::MAX, f64::MIN), |(lo, hi), v| (lo.min(*v), hi.max(*v)));
    let root = SVGBackend::new(path, (1000, 420)).into_drawing_area();
    root.fill(&WHITE)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 18))
        .margin(10)
        .x_label_area_size(35)
        .y_label_area_size(50)
        .build_cartesian_2d(0.0..20.0, (lo - 1.0)..(hi + 1.0))?;
    chart.configure_mesh().x_desc("t (s)").draw()?;
    for (name, v, color) in series {
        let c = *color;
        chart
            .draw_series(LineSeries::new((0..n).step_by(5).map(|k| (t[k], v[k])), c.stroke_width(1)))?
            .label(*name)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 15, y)], c));
    }
    chart.configure_series_labels().background_style(WHITE.mix(0.8)).border_style(BLACK).draw()?;
    root.present()?;
    Ok(())
}

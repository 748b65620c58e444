//! B from one long penalised fit: a diagnostic of how far B can be told from a smooth load, not an
//! estimator. For each battery scenario, the measured speed over `from`…`to` seconds is fitted in integrated form,
//! `ω = ω₀ + ∫τ/J − (B/J)·∫ω − ∫T_L/J`, with J held at the truth and the load T_L piecewise linear (knots every
//! `knot` s) under a penalty `lambda` on its second differences; it prints B's error and standard deviation.
//!
//! `cargo run --release --example estimator_spline_b -- seeds=12,18,24 lambda=0.01 [from=5] [to=25] [knot=0.25]`
//! `[poll=1] [family=random]` (a seed's family is the battery's: seed k is family (k − 1) mod 6 of brake, start-up,
//! slow, ramp, trend, sine; `family=` names one of those or of the new loads, `Family::NEW`, for every seed).

use hydrolens::estimator::battery;
use hydrolens::plant::PlantModel;
use hydrolens::plant::scenario::{Family, Scenario};
use nalgebra::{DMatrix, DVector};

/// Rows of the fit, one every this many seconds (the integrals run at the poll rate in between).
const ROW_S: f64 = 0.01;

fn main() {
    let mut seeds: Vec<u64> = vec![12, 18, 24];
    let (mut lambda, mut from, mut to, mut knot, mut poll) = (0.01, 5.0, 25.0, 0.25, 1u32);
    let mut named: Option<Family> = None;
    for arg in std::env::args().skip(1) {
        let (k, v) = arg.split_once('=').unwrap_or((arg.as_str(), ""));
        let number = |v: &str| -> f64 {
            v.parse().unwrap_or_else(|_| {
                eprintln!("{k}: not a number: {v}");
                std::process::exit(2)
            })
        };
        match k {
            "seeds" => seeds = v.split(',').map(|s| number(s) as u64).collect(),
            "lambda" => lambda = number(v),
            "from" => from = number(v),
            "to" => to = number(v),
            "knot" => knot = number(v),
            "poll" => poll = number(v) as u32,
            "family" => {
                named = Some(Family::from_name(v).unwrap_or_else(|| {
                    eprintln!("family: no such family: {v}");
                    std::process::exit(2)
                }))
            }
            _ => {
                eprintln!("unknown argument {arg}");
                std::process::exit(2)
            }
        }
    }
    if !(to > from + 1.0 && knot > 0.0 && lambda >= 0.0) {
        eprintln!("need to > from + 1, knot > 0, lambda ≥ 0");
        std::process::exit(2)
    }
    let truth = PlantModel::reference();
    let (j, b_true) = (truth.motor.inertia_kg_m2, truth.motor.viscous_nm_s_rad);
    let sigma = truth.sensors.speed_noise_rad_s;
    for seed in seeds {
        let family = named.unwrap_or(Family::ALL[(seed.max(1) - 1) as usize % Family::ALL.len()]);
        // the battery's 60 s scenarios (the draws depend on the length)
        let scenario = Scenario::generate(family, seed, 60f64.max(to + 1.0));
        let p = battery::poll(&scenario, &truth, poll);
        // Rows (t, ω, ∫τ, ∫ω) from the first sample at or after `from`, integrals by the trapezoid.
        let mut rows: Vec<(f64, f64, f64, f64)> = Vec::new();
        let (mut i_torque, mut i_speed, mut next) = (0.0, 0.0, from);
        for k in 1..p.t_s.len() {
            let (t, m, m0) = (p.t_s[k], &p.measurements[k], &p.measurements[k - 1]);
            if t < from {
                continue;
            }
            if t > to {
                break;
            }
            if !rows.is_empty() {
                i_torque += m.dt_s * 0.5 * (m.drive_torque_nm + m0.drive_torque_nm);
                i_speed += m.dt_s * 0.5 * (m.omega_rad_s + m0.omega_rad_s);
            }
            if t >= next - 1e-9 {
                rows.push((t, m.omega_rad_s, i_torque, i_speed));
                next = t + ROW_S;
            }
        }
        let Some(&(start, ..)) = rows.first() else { continue };
        let knots = ((to - start) / knot).ceil() as usize + 1;
        // ∫ from `start` to t of the hat function of knot k (width ±knot around start + k·knot).
        let integral_of_hat = |k: usize, t: f64| -> f64 {
            let centre = start + k as f64 * knot;
            let cumulative = |x: f64| -> f64 {
                let u = (x / knot).clamp(-1.0, 1.0);
                if u <= 0.0 { 0.5 * knot * (1.0 + u).powi(2) } else { knot * (1.0 - 0.5 * (1.0 - u).powi(2)) }
            };
            cumulative(t - centre) - cumulative(start - centre)
        };
        // Unknowns: ω₀, B/J, then the load at each knot over J. Rows weighed by the speed noise, then the penalty.
        let (n, penalties) = (rows.len(), knots.saturating_sub(2));
        let mut a = DMatrix::<f64>::zeros(n + penalties, 2 + knots);
        let mut y = DVector::<f64>::zeros(n + penalties);
        for (i, &(t, w, it, iw)) in rows.iter().enumerate() {
            a[(i, 0)] = 1.0 / sigma;
            a[(i, 1)] = -iw / sigma;
            for k in 0..knots {
                a[(i, 2 + k)] = -integral_of_hat(k, t) / sigma;
            }
            y[i] = (w - it / j) / sigma;
        }
        // λ·∫(T_L'')² ≈ λ·Σ (second difference / knot²)²·knot
        let weight = lambda.sqrt() * knot.powf(-1.5);
        for k in 1..knots - 1 {
            let row = n + k - 1;
            a[(row, 1 + k)] = weight;
            a[(row, 2 + k)] = -2.0 * weight;
            a[(row, 3 + k)] = weight;
        }
        let normal = a.transpose() * &a;
        let Some(factor) = normal.cholesky() else {
            println!("{} seed {seed}: singular", family.name());
            continue;
        };
        let x = factor.solve(&(a.transpose() * &y));
        let sd_b = factor.inverse()[(1, 1)].sqrt() * j;
        let residual = (a.rows(0, n) * &x - y.rows(0, n)).norm_squared() / n as f64;
        println!(
            "{:<8} seed {seed}: {}  B {:+.1} % ± {:.1} %  (residual {residual:.2} σ²)",
            family.name(),
            scenario.describe().split(": ").nth(1).unwrap_or(""),
            (x[1] * j / b_true - 1.0) * 100.0,
            sd_b / b_true * 100.0,
        );
    }
}

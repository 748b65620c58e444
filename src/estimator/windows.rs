//! The windows rls-sgd learns J and B from (module doc of `rls_sgd.rs`): each window's least-squares fit of the
//! measured speed with the load a nuisance (a polynomial and at most one step, chosen by GLR), the robust RLS on
//! θ = [J₀/J, (B/J)·J₀/B₀] that adds each window's information ([`WindowRls`]), which also pools the windows' own
//! B and J (`pool.rs`). Pure: fed rows of Δt, speed and torque integrals.

use nalgebra::{Matrix2, SMatrix, SVector, Vector2};

use super::covariance::condition;
use super::pool::{CHANGE_WINDOWS, HUBER_Z, OVERLAP, WindowPool};
use super::settings::Resolved;

/// Informative windows remembered for the consistency check, and how many of them rejected mean "wrong".
const RECENT_WINDOWS: u32 = 8;
const REJECTED_MEANS_WRONG: u32 = 5;
/// Step-time candidates per window before refinement.
const STEP_GRID: usize = 16;
/// A step is in the window when it lowers the residual sum of squares by this many σ² (GLR over the candidates).
const STEP_GLR: f64 = 25.0;
/// How fast the window scatter is learnt (per informative window).
const OVERDISPERSION_RATE: f64 = 0.15;
/// The speed moved in a window when the drive's torque explains this many σ² more of it than the load alone.
const SPEED_MOVED_GLR: f64 = 100.0;
/// What a higher power of the load polynomial must explain (σ²) to be chosen.
const DEGREE_PENALTY: f64 = 10.0;

/// One row of a window: time since its start, measured speed, and the running integrals of τ and ω.
#[derive(Debug, Clone, Copy)]
pub(super) struct Row {
    pub s: f64,
    pub omega: f64,
    pub i_torque: f64,
    pub i_speed: f64,
}

/// The rows of the window being collected, and what the fit of the last one needs (kept to avoid allocations).
#[derive(Debug, Clone, Default)]
pub(super) struct Window {
    pub rows: Vec<Row>,
    /// Suffix sums for the step candidates: per row, Σ from that row on of q and of u·q, q = [columns…, ω].
    suffix: Vec<[f64; 2 * (POLY + 1)]>,
}

/// Columns of a window's fit without the step: θ₁, θ₂, then the nuisance polynomial 1, u, u², u³, u⁴.
const POLY: usize = 7;
/// All columns: the step last.
const ALL: usize = POLY + 1;
const STEP: usize = POLY;
type Normal = SMatrix<f64, ALL, ALL>;
type Column = SVector<f64, ALL>;

/// The least-squares columns of a row: θ₁, θ₂, then the nuisance 1, u, u², u³, u⁴ (u = s/length): the speed of
/// a load that is constant, linear, quadratic or cubic over the window.
fn columns(r: &Row, u: f64, j0: f64, b0: f64) -> [f64; POLY] {
    let u2 = u * u;
    [r.i_torque / j0, -r.i_speed * b0 / j0, 1.0, u, u2, u2 * u, u2 * u2]
}

/// A sub-model: which columns take part (the others are held at zero).
#[derive(Debug, Clone, Copy)]
struct Model {
    /// Highest power of u in the nuisance (2, 3 or 4).
    degree: usize,
    step: bool,
    /// False for the load alone, without the drive's torque and friction (the test of whether the speed moved).
    dynamics: bool,
}

impl Model {
    fn active(&self, i: usize) -> bool {
        match i {
            STEP => self.step,
            0 | 1 => self.dynamics,
            _ => i < 3 + self.degree,
        }
    }

    fn parameters(&self) -> usize {
        3 + self.degree + usize::from(self.step)
    }

    /// The normal equations restricted to the model: inactive rows and columns become identity rows.
    fn restrict(&self, a: &Normal, b: &Column) -> (Normal, Column) {
        let mut a = *a;
        let mut b = *b;
        for i in 0..ALL {
            if !self.active(i) {
                a.row_mut(i).fill(0.0);
                a.column_mut(i).fill(0.0);
                a[(i, i)] = 1.0;
                b[i] = 0.0;
            } else {
                a[(i, i)] += 1e-12 * a[(i, i)].abs() + 1e-300;
            }
        }
        (a, b)
    }

    /// Solves the model: parameters and the residual sum of squares.
    fn solve(&self, a: &Normal, b: &Column, yy: f64) -> Option<(Column, f64)> {
        let (a, b) = self.restrict(a, b);
        let x = a.cholesky()?.solve(&b);
        Some((x, yy - b.dot(&x)))
    }

    /// The θ block of a fit: the estimate, and its information (σ² times the inverse covariance).
    fn theta(&self, a: &Normal, x: &Column) -> Option<(Vector2<f64>, Matrix2<f64>)> {
        let (a, _) = self.restrict(a, &Column::zeros());
        let inv = a.cholesky()?.inverse();
        let c = Matrix2::new(inv[(0, 0)], inv[(0, 1)], inv[(1, 0)], inv[(1, 1)]);
        let info = c.try_inverse()?;
        Some((Vector2::new(x[0], x[1]), (info + info.transpose()) * 0.5))
    }
}

/// What the RLS did with a window, for the consistency check and tests.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Verdict {
    Uninformative,
    Accepted,
    /// The load did not fit the nuisance (more than one step, a fast change).
    Misfit,
    /// The window disagrees with θ beyond both uncertainties.
    Rejected,
}

/// Each suffix sum's stride in [`Window::suffix`]: the columns without the step, then ω.
const Q: usize = POLY + 1;

/// The normal equations (`a`, `b`, without the step) with the step column at row k: (u − u_{k−1})₊, non-zero from
/// row k on, from the window's suffix sums.
fn with_step(w: &Window, length: f64, (a, b): (&Normal, &Column), k: usize) -> (Normal, Column) {
    let us = w.rows[k - 1].s / length;
    let sf = &w.suffix[k];
    let (mut a, mut b) = (*a, *b);
    for j in 0..POLY {
        let v = sf[Q + j] - us * sf[j];
        a[(STEP, j)] = v;
        a[(j, STEP)] = v;
    }
    // Σ (u − us)² = Σu² − 2·us·Σu + us²·Σ1 over the suffix (columns 2, 3, 4 are 1, u, u²).
    a[(STEP, STEP)] = sf[4] - 2.0 * us * sf[3] + us * us * sf[2];
    b[STEP] = sf[Q + POLY] - us * sf[POLY];
    (a, b)
}

/// Each nuisance order, with and without its best step: the model with the least RSS after a penalty per extra
/// term, with its normal equations, solution and RSS.
fn choose_model(
    w: &Window,
    length: f64,
    (a, b, yy): (&Normal, &Column, f64),
    sigma2: f64,
) -> Option<(Model, Normal, Column, Column, f64)> {
    let mut chosen: Option<(Model, Normal, Column, Column, f64, f64)> = None; // (model, A, b, x, rss, penalised)
    for degree in 2..=4 {
        let plain = Model { degree, step: false, dynamics: true };
        if let Some((x, rss)) = plain.solve(a, b, yy) {
            let pen = rss / sigma2 + DEGREE_PENALTY * (degree - 2) as f64;
            if chosen.as_ref().is_none_or(|c| pen < c.5) {
                chosen = Some((plain, *a, *b, x, rss, pen));
            }
        }
        let Some(k) = best_step(w, length, plain, (a, b, yy)) else { continue };
        let stepped = Model { degree, step: true, dynamics: true };
        let (ak, bk) = with_step(w, length, (a, b), k);
        if let Some((x, rss)) = stepped.solve(&ak, &bk, yy) {
            let pen = rss / sigma2 + DEGREE_PENALTY * (degree - 2) as f64 + STEP_GLR;
            if chosen.as_ref().is_none_or(|c| pen < c.5) {
                chosen = Some((stepped, ak, bk, x, rss, pen));
            }
        }
    }
    chosen.map(|(model, a, b, x, rss, _)| (model, a, b, x, rss))
}

/// The row at which a step added to the `plain` model removes the most RSS: each candidate scored by what its
/// column adds to the plain fit (one factorisation and its inverted factor for all; RSS falls by
/// (c·r)² / (c·c − cᵀA⁻¹c), r the plain residual), on a coarse grid of [`STEP_GRID`], then finer around the best.
fn best_step(w: &Window, length: f64, plain: Model, (a, b, yy): (&Normal, &Column, f64)) -> Option<usize> {
    let n = w.rows.len();
    let (a_plain, b_plain) = plain.restrict(a, b);
    let factor = a_plain.cholesky()?;
    let x_plain = factor.solve(&b_plain);
    // cᵀA⁻¹c = |L⁻¹c|²: L inverted once, one product per candidate rather than two triangular solves.
    let l_inv = factor.l().solve_lower_triangular(&Normal::identity())?;
    let rss_plain = yy - b_plain.dot(&x_plain);
    let try_step = |k: usize| -> Option<(f64, usize)> {
        if !(2..n - 2).contains(&k) {
            return None;
        }
        let us = w.rows[k - 1].s / length;
        let sf = &w.suffix[k];
        let mut cross = Column::zeros();
        for j in (0..POLY).filter(|&j| plain.active(j)) {
            cross[j] = sf[Q + j] - us * sf[j];
        }
        let cc = sf[4] - 2.0 * us * sf[3] + us * us * sf[2];
        let cy = sf[Q + POLY] - us * sf[POLY];
        let left = cc - (l_inv * cross).norm_squared();
        (left > 1e-12 * cc.abs()).then(|| (rss_plain - (cy - cross.dot(&x_plain)).powi(2) / left, k))
    };
    let better = |cand: Option<(f64, usize)>, best: &mut Option<(f64, usize)>| {
        if let Some(c) = cand
            && best.is_none_or(|b| c.0 < b.0)
        {
            *best = Some(c);
        }
    };
    let mut best = None;
    let spacing = (n / STEP_GRID).max(1);
    for g in 1..STEP_GRID {
        better(try_step(g * spacing), &mut best);
    }
    if let Some((_, coarse)) = best {
        let stride = (spacing / 8).max(1);
        for k in (coarse.saturating_sub(spacing)..=coarse + spacing).step_by(stride) {
            better(try_step(k), &mut best);
        }
        if let Some((_, mid)) = best {
            for k in mid.saturating_sub(stride)..=mid + stride {
                better(try_step(k), &mut best);
            }
        }
    }
    best.map(|(_, k)| k)
}

/// The robust RLS on windows. θ = [J₀/J, (B/J)·J₀/B₀]; P its covariance.
#[derive(Debug, Clone)]
pub(crate) struct WindowRls {
    pub theta: Vector2<f64>,
    pub p: Matrix2<f64>,
    prior: Matrix2<f64>,
    j0: f64,
    pub b0: f64,
    /// Outcomes of the last informative windows, newest in bit 0 (1 = rejected), and how many are recorded.
    recent: u32,
    recorded: u32,
    /// The last informative window's estimate and variances, and how much the windows scatter beyond what their
    /// own fits claim (per component, ≥ 1): a load the nuisance only roughly follows biases each window a little
    /// differently, and the scatter between consecutive windows shows it whatever θ is.
    last_window: [Option<(Vector2<f64>, Vector2<f64>)>; 2],
    overdispersion: Vector2<f64>,
    /// Windows learnt from, rejected, and with a step found: for diagnostics.
    pub counts: [u64; 4],
    pub viscous: WindowPool,
    /// J from the same windows, pooled as B is, rejected windows included: the RLS leaves out the windows that
    /// contradict it, so its own covariance is surer than the windows are (guard: `RlsSgd::credible`).
    pub inertia: WindowPool,
    /// Whether the plant changed at the last window ([`WindowRls::restart_at`]), until `rls_sgd.rs` takes it.
    changed: bool,
    s: Resolved,
}

impl WindowRls {
    pub(super) fn new(s: Resolved) -> WindowRls {
        let j0 = s.nominal_inertia_kg_m2;
        let b0 = s.nominal_viscous_nm_s_rad.max(s.viscous_bounds_nm_s_rad[1] / 5.0).max(1e-9);
        let j = s.initial_inertia_kg_m2;
        let theta = Vector2::new(j0 / j, s.initial_viscous_nm_s_rad / j * j0 / b0);
        let prior = Matrix2::from_diagonal(&Vector2::new(
            s.inertia_prior_sd.powi(2),
            (s.viscous_prior_sd * theta[1].max(1.0)).powi(2),
        ));
        WindowRls {
            theta,
            p: prior,
            prior,
            j0,
            b0,
            recent: 0,
            recorded: 0,
            last_window: [None, None],
            overdispersion: Vector2::new(1.0, 1.0),
            counts: [0; 4],
            viscous: WindowPool::new(
                s.initial_viscous_nm_s_rad,
                (s.viscous_prior_sd * s.initial_viscous_nm_s_rad.max(b0)).powi(2),
                s.viscous_bounds_nm_s_rad,
                1.0,
            ),
            inertia: WindowPool::new(j, (s.inertia_prior_sd * j).powi(2), s.inertia_bounds_kg_m2, OVERLAP),
            changed: false,
            s,
        }
    }

    pub(super) fn inertia_kg_m2(&self) -> f64 {
        self.j0 / self.theta[0]
    }

    /// θ of a J and B.
    pub(super) fn theta_of(&self, j: f64, b: f64) -> Vector2<f64> {
        Vector2::new(self.j0 / j, b / j * self.j0 / self.b0)
    }

    /// Standard deviation of J (from P, first-order propagation).
    pub(super) fn inertia_sd(&self) -> f64 {
        let t0 = self.theta[0];
        let gj = Vector2::new(-self.j0 / (t0 * t0), 0.0);
        gj.dot(&(self.p * gj)).max(0.0).sqrt()
    }

    /// Fits one window (rows in `w`) and learns from it; first scores it under the [nominal, adapted] `hypotheses`
    /// (θ held, the load nuisance fitted): their residual sums of squares and what noise alone leaves, where the
    /// window fitted and the speed moved (the guard's held-out test).
    pub(super) fn learn(
        &mut self,
        w: &mut Window,
        sequence: usize,
        speed_sd: f64,
        hypotheses: [Vector2<f64>; 2],
    ) -> (Verdict, Option<(f64, f64, f64)>) {
        let n = w.rows.len();
        let Some(last) = w.rows.last() else { return (Verdict::Uninformative, None) };
        let length = last.s;
        if n < 16 || length <= 0.0 {
            return (Verdict::Uninformative, None);
        }
        let (a, b, yy) = self.normal_equations(w, length);
        let sigma2 = speed_sd * speed_sd;
        let Some((model, a_m, b_m, x_m, rss)) = choose_model(w, length, (&a, &b, yy), sigma2) else {
            return (Verdict::Uninformative, None);
        };
        let Some((x_theta, info)) = model.theta(&a_m, &x_m) else { return (Verdict::Uninformative, None) };
        if model.step {
            self.counts[3] += 1;
        }
        // Did the speed move beyond what the load alone could make it do? If the load explains the window as well
        // without the drive's torque (the speed held by the pump while the torque follows the load), the window
        // cannot tell J apart from the load, whatever its fit says.
        let load_alone = Model { dynamics: false, ..model };
        let moved = load_alone.solve(&a_m, &b_m, yy).map_or(0.0, |(_, r)| (r - rss) / sigma2);
        // The window under each hypothesis, θ held, its load nuisance fitted: the guard's held-out test.
        let rss_at = |theta: Vector2<f64>| {
            let mut b_h = b_m;
            for i in 0..ALL {
                b_h[i] -= a_m[(i, 0)] * theta[0] + a_m[(i, 1)] * theta[1];
            }
            let a_tt = Matrix2::new(a_m[(0, 0)], a_m[(0, 1)], a_m[(1, 0)], a_m[(1, 1)]);
            let yy_h = yy - 2.0 * (theta[0] * b_m[0] + theta[1] * b_m[1]) + theta.dot(&(a_tt * theta));
            load_alone.solve(&a_m, &b_h, yy_h).map(|(_, r)| r)
        };
        // A load the nuisance cannot follow leaves far more than noise behind.
        let dof = (n - model.parameters()) as f64;
        let misfit = rss / sigma2 > dof + 6.0 * (2.0 * dof).sqrt() + 10.0;
        let informative = info[(0, 0)] / sigma2 * self.prior[(0, 0)] > 9.0 && moved > SPEED_MOVED_GLR;
        // A window whose best J is outside anything physical has a load the nuisance could not follow either.
        let [jlo, jhi] = self.s.inertia_bounds_kg_m2;
        let impossible = !(self.j0 / jhi..=self.j0 / jlo).contains(&x_theta[0]);
        // The window's own residual variance, where it is above the sensor's: what the nuisance left unexplained
        // counts as noise, so such a window teaches (and contradicts) less.
        let variance = sigma2.max(rss / dof);
        let score = (!misfit && moved > SPEED_MOVED_GLR)
            .then(|| rss_at(hypotheses[0]).zip(rss_at(hypotheses[1])))
            .flatten()
            .map(|(n, a)| (n, a, sigma2 * dof));
        let verdict = if misfit || (informative && impossible) {
            Verdict::Misfit
        } else if moved <= SPEED_MOVED_GLR {
            Verdict::Uninformative
        } else {
            // Each sample lies in two windows (the staggered sequences): each counts half.
            self.absorb(x_theta, info / variance * 0.5, sequence, informative)
        };
        if !misfit && !impossible && moved > SPEED_MOVED_GLR {
            self.pool_window(w, x_theta, info / variance * 0.5);
        }
        match verdict {
            Verdict::Accepted => self.counts[0] += 1,
            Verdict::Misfit => self.counts[1] += 1,
            Verdict::Rejected => self.counts[2] += 1,
            Verdict::Uninformative => {}
        }
        if informative && verdict != Verdict::Misfit {
            self.remember(verdict == Verdict::Rejected);
        }
        (verdict, score)
    }

    /// The window's normal equations for every column but the step (A, b of the fit of ω on them, and Σω²), and the
    /// suffix sums in `w` from which each candidate step's column is added ([`with_step`]).
    fn normal_equations(&self, w: &mut Window, length: f64) -> (Normal, Column, f64) {
        let n = w.rows.len();
        let (j0, b0) = (self.j0, self.b0);
        let mut a = Normal::zeros();
        let mut b = Column::zeros();
        let mut yy = 0.0;
        w.suffix.resize(n + 1, [0.0; 2 * Q]);
        w.suffix[n] = [0.0; 2 * Q];
        for i in (0..n).rev() {
            let r = &w.rows[i];
            let u = r.s / length;
            let c = columns(r, u, j0, b0);
            for j in 0..POLY {
                for k in 0..=j {
                    a[(j, k)] += c[j] * c[k];
                }
                b[j] += c[j] * r.omega;
            }
            yy += r.omega * r.omega;
            let mut acc = w.suffix[i + 1];
            for k in 0..POLY {
                acc[k] += c[k];
                acc[Q + k] += u * c[k];
            }
            acc[POLY] += r.omega;
            acc[Q + POLY] += u * r.omega;
            w.suffix[i] = acc;
        }
        for j in 0..POLY {
            for k in 0..j {
                a[(k, j)] = a[(j, k)];
            }
        }
        (a, b, yy)
    }

    /// Pools the window's own B and J (from the fit already made, its information `info`) into
    /// [`WindowRls::viscous`] and [`WindowRls::inertia`], unless its B lies far outside anything physical (a load its
    /// nuisance could not follow).
    fn pool_window(&mut self, w: &Window, x_theta: Vector2<f64>, info: Matrix2<f64>) {
        let Some(c) = info.try_inverse() else { return };
        let (t0, t1) = (x_theta[0], x_theta[1]);
        let g = Vector2::new(-t1 * self.b0 / (t0 * t0), self.b0 / t0);
        let (b_w, var_w) = (t1 * self.b0 / t0, g.dot(&(c * g)));
        let [blo, bhi] = self.s.viscous_bounds_nm_s_rad;
        let sd_w = var_w.max(0.0).sqrt();
        if (blo - 3.0 * sd_w..=bhi + 3.0 * sd_w).contains(&b_w) {
            // against the speed's magnitude: a fan's local B is 2·k·|ω| whichever way the shaft turns
            let speed = w.rows.iter().map(|r| r.omega.abs()).sum::<f64>() / w.rows.len() as f64;
            self.viscous.add(b_w, var_w, speed);
            let gj = Vector2::new(-self.j0 / (t0 * t0), 0.0);
            let direction = match (w.rows.first(), w.rows.last()) {
                (Some(first), Some(last)) => (last.omega - first.omega).signum(),
                _ => 0.0,
            };
            self.inertia.add(self.j0 / t0, gj.dot(&(c * gj)), direction);
            if let Some((j, var)) = self.inertia.changed() {
                self.restart_at(j, var);
            }
        }
    }

    /// The plant changed ([`WindowPool::changed`]): the older windows are another plant's. The J pool keeps the
    /// newest windows only, and the RLS starts again from their J, as sure of it as they are (B where it was, with
    /// its prior's uncertainty). Without it, after J tripled (a reviewer's coupled mass) the old J stayed identified
    /// 12.8 s, until five of eight windows were rejected, and the new one was never identified: the pool's 40 windows
    /// of the old plant kept the old J the credible one (`estimator::a_plant_whose_inertia_changes_is_followed`).
    fn restart_at(&mut self, j: f64, var: f64) {
        self.inertia.keep_newest(CHANGE_WINDOWS);
        let b = self.theta[1] * self.b0 / self.theta[0];
        self.theta = self.project(self.theta_of(j, b));
        let g = self.j0 / (j * j);
        self.start_again();
        self.p[(0, 0)] = (g * g * var).min(self.prior[(0, 0)]);
        self.changed = true;
    }

    /// P back to the prior and the consistency record forgotten: learning starts again from θ.
    fn start_again(&mut self) {
        self.p = self.prior;
        self.recent = 0;
        self.recorded = 0;
    }

    /// Whether the plant changed since the last call: what the older windows backed (the sign test, the drift) is
    /// then forgotten too.
    pub(super) fn take_change(&mut self) -> bool {
        std::mem::take(&mut self.changed)
    }

    /// Adds a window's estimate `x` of θ with information `info` (inverse covariance), robustly.
    fn absorb(&mut self, x: Vector2<f64>, info: Matrix2<f64>, sequence: usize, informative: bool) -> Verdict {
        let info = self.deflate(x, info, sequence, informative);
        let excited = |i: usize| info[(i, i)] * self.prior[(i, i)] > 9.0;
        let f = |e: bool| if e { 1.0 / self.s.lambda.sqrt() } else { 1.0 };
        let d = Matrix2::from_diagonal(&Vector2::new(f(excited(0)), f(excited(1))));
        let p = bounded(d * self.p * d, &self.prior);
        let Some(p_inv) = p.try_inverse() else { return Verdict::Uninformative };
        // Disagreement in the directions the window informs: (x − θ) weighed by the window's information, against
        // what noise and the present uncertainty allow.
        let delta = x - self.theta;
        let spread = info * p * info + info;
        let nu = info * delta;
        let z2 = spread.try_inverse().map_or(0.0, |m| nu.dot(&(m * nu)));
        let z = z2.max(0.0).sqrt();
        if z > self.s.change_threshold {
            self.p = p;
            return Verdict::Rejected;
        }
        let weight = if z > HUBER_Z { HUBER_Z / z } else { 1.0 };
        let Some(p_new) = (p_inv + info * weight).try_inverse() else { return Verdict::Uninformative };
        let theta = p_new * (p_inv * self.theta + info * weight * x);
        self.p = bounded(p_new, &self.prior);
        self.theta = self.project(theta);
        if informative { Verdict::Accepted } else { Verdict::Uninformative }
    }

    /// The window's information divided by how much windows scatter beyond their claims (component by component,
    /// learnt from consecutive informative windows), so that P stays honest when the load is only roughly followed.
    fn deflate(&mut self, x: Vector2<f64>, info: Matrix2<f64>, sequence: usize, informative: bool) -> Matrix2<f64> {
        let var = info.try_inverse().map_or(Vector2::new(f64::INFINITY, f64::INFINITY), |c| c.diagonal());
        if informative {
            if let Some((x0, v0)) = self.last_window[sequence] {
                for i in 0..2 {
                    let v = var[i] + v0[i];
                    // only where both windows say something about the component
                    if v.is_finite() && v > 0.0 && v < 0.25 * self.prior[(i, i)] {
                        let z2 = ((x[i] - x0[i]).powi(2) / v).min(1e4);
                        self.overdispersion[i] =
                            (1.0 - OVERDISPERSION_RATE) * self.overdispersion[i] + OVERDISPERSION_RATE * z2;
                    }
                }
            }
            self.last_window[sequence] = Some((x, var));
        }
        let d = Matrix2::from_diagonal(&self.overdispersion.map(|b| 1.0 / b.max(1.0).sqrt()));
        d * info * d
    }

    /// Counts an informative window's outcome; most of the recent ones rejected means θ is wrong.
    fn remember(&mut self, rejected: bool) {
        self.recent = (self.recent << 1) | u32::from(rejected);
        self.recorded = (self.recorded + 1).min(RECENT_WINDOWS);
        let mask = (1u32 << RECENT_WINDOWS) - 1;
        if self.recorded == RECENT_WINDOWS && (self.recent & mask).count_ones() >= REJECTED_MEANS_WRONG {
            // The data keep contradicting the estimate beyond its uncertainty: start learning again from here, as
            // uncertain as the prior.
            self.start_again();
        }
    }

    /// θ into the physical bounds; a clamped component gets its prior variance back.
    fn project(&mut self, theta: Vector2<f64>) -> Vector2<f64> {
        if !theta.iter().all(|v| v.is_finite()) {
            self.p = self.prior;
            return self.theta;
        }
        let [jlo, jhi] = self.s.inertia_bounds_kg_m2;
        let t0 = theta[0].clamp(self.j0 / jhi, self.j0 / jlo);
        let [blo, bhi] = self.s.viscous_bounds_nm_s_rad;
        let t1 = theta[1].clamp(blo * t0 / self.b0, bhi * t0 / self.b0);
        for (i, clamped) in [t0 != theta[0], t1 != theta[1]].into_iter().enumerate() {
            if clamped {
                for k in 0..2 {
                    self.p[(i, k)] = 0.0;
                    self.p[(k, i)] = 0.0;
                }
                self.p[(i, i)] = self.prior[(i, i)];
            }
        }
        Vector2::new(t0, t1)
    }
}

/// P kept symmetric positive definite and never wider than the prior on its diagonal.
fn bounded(p: Matrix2<f64>, prior: &Matrix2<f64>) -> Matrix2<f64> {
    let mut p = condition(p, prior.trace(), 1e-14, 1.0);
    for i in 0..2 {
        let limit = prior[(i, i)];
        if p[(i, i)] > limit {
            let s = (limit / p[(i, i)]).sqrt();
            for k in 0..2 {
                p[(i, k)] *= s;
                p[(k, i)] *= s;
            }
        }
    }
    if p.cholesky().is_some() { p } else { *prior }
}

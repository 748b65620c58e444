//! B under a periodic load (rls-sgd): one fit over a long horizon where the windows see only curvature.
//!
//! Within a 1.5 s window a sine load's curvature over a setpoint change and `B·ω` are the same data, so the windows'
//! B scatter far beyond their own claims and only many of them average it out (docs/estimator.md). Over a horizon
//! of several periods they are not: if the load is a constant, a trend and one sinusoid, the measured speed is
//!
//! ```text
//! ω(u) = ω₀ + (1/J)·∫τ − (B/J)·∫ω − (m/J)·u − (k/J)·u²/2 − (a/J)·sin(wu)/w − (b/J)·(1 − cos(wu))/w
//! ```
//!
//! linear in everything but w. The speed is kept as block means (`BLOCK_S`), the period searched on a grid and
//! refined, and the fit accepted only where its residual is as rough as noise (Durbin–Watson): a brake step or a
//! load that is not periodic leaves a smooth residual and no answer. The variances of B and J are the larger of the
//! fit's own, a delete-a-segment jackknife's (a fit whose parts disagree is not believed) and 1 % of the value
//! (the plant equation is no truer than that), and an answer ages by 10 % of the value per minute. The answer is
//! one more estimate of B beside the windows' pool and of J beside their RLS, combined by precision; where the load
//! is not periodic it says nothing.
//!
//! Where the windows have shown a load that grows with the speed ([`PeriodicLoad::fit_fan`]), the fit gains a fan's
//! term, `− (q/J)·∫ω|ω|`: a fan is then explained by it, not by the sinusoid or B, and the fit's B is friction's,
//! which rls-sgd takes alone (the windows' B carries the fan's local slope).

use std::collections::VecDeque;
use std::f64::consts::TAU;

use nalgebra::{SMatrix, SVector};

/// Length of one block of the horizon (s): its speed is the mean of its samples.
const BLOCK_S: f64 = 0.1;
/// Blocks kept: the horizon (s) the load must be periodic over.
const HORIZON_S: f64 = 20.0;
/// No fit before the blocks span this long (s).
const MIN_SPAN_S: f64 = 8.0;
/// A fit every this much data (s). Once the horizon is full, each refused fit doubles the interval to the next, up
/// to `FIT_AT_MOST_EVERY_S`, so that a load that is not periodic costs little; while it grows, each fit searches
/// longer periods than the last (up to half the span), so a refusal says nothing of the next, and the interval
/// stays (doubling from the first refusal on, a load of a long period was answered up to 10 s after its second
/// cycle: `a_long_period_is_answered_once_two_cycles_are_in_the_horizon`).
const FIT_EVERY_S: f64 = 2.5;
const FIT_AT_MOST_EVERY_S: f64 = 10.0;
/// Periods searched (s): from this, up to the span over `CONFIRMED_CYCLES`.
const MIN_PERIOD_S: f64 = 1.2;
/// Cycles of its period the horizon must hold for an answer to be confirmed: then the sinusoid is told from a trend
/// and the speed's own program, and the answer stands after later fits are refused.
const CONFIRMED_CYCLES: f64 = 2.0;
/// Before any answer is confirmed, while the horizon fills, and where no period up to the span over `CONFIRMED_CYCLES`
/// is accepted, longer periods up to the span over this are searched: an answer there is provisional. It is one more
/// estimate of B and J as a confirmed one is, a cycle earlier than two allow, while the windows' B, which a sine's
/// curvature biases, would stand in its place (sealed sine 11018 at 5 ms, period 4.2 s: T̂_L 1.81× the truth
/// reference's, 1.22× with it); but it stands only until the next fit is refused, and does not turn the speed test off
/// (`RlsSgd::speed_test_applies`). Held after a refusal, a smooth random load's one cycle left B +60 % for a minute
/// (last random 15018 at 5 ms: T̂_L 0.64 → 0.97× the nominal model's).
const PROVISIONAL_CYCLES: f64 = 1.0;
/// Ratio between neighbouring periods of the search grid; the best is then refined within one step.
const SCAN_RATIO: f64 = 1.05;
/// The fit is accepted when the residual's Durbin–Watson statistic is at least this (2 for white noise; a load
/// the model does not follow leaves a smooth residual and a small one).
const MIN_DURBIN_WATSON: f64 = 1.0;
/// B's standard deviation from a fit is never below this fraction of B: the plant equation itself is no truer.
const MODEL_SD: f64 = 0.01;
/// An accepted answer ages: its standard deviation grows by this fraction of B per minute (the oil's temperature
/// moves B), so the windows' pool takes over again when no later fit is accepted.
const AGING_PER_MIN: f64 = 0.1;
/// A fit that knows B or J no better than this fraction of its value has identified nothing (one steady speed:
/// ∫τ, ∫ω and time are then nearly the same column) and is refused, so the estimates hold instead of drifting.
const MAX_RELATIVE_SD: f64 = 0.25;
/// Contiguous segments of the jackknife.
const SEGMENTS: usize = 6;

const N: usize = 8;
type Normal = SMatrix<f64, N, N>;
type Column = SVector<f64, N>;

/// One block: mean time, speed and running integrals of τ and ω over its samples.
#[derive(Debug, Clone, Copy, Default)]
struct Block {
    t: f64,
    omega: f64,
    i_torque: f64,
    i_speed: f64,
    i_fan: f64,
}

/// The periodic-load fit of rls-sgd (module doc).
#[derive(Debug, Clone)]
pub(crate) struct PeriodicLoad {
    blocks: VecDeque<Block>,
    /// The block being filled: sums and sample count, and the time it covers.
    sum: Block,
    count: u32,
    span: f64,
    /// Time and running integrals since the start.
    t: f64,
    i_torque: f64,
    i_speed: f64,
    i_fan: f64,
    /// Whether the fits have a fan's term (a running integral of ω|ω| beside those of τ and ω).
    fan: bool,
    since_fit: f64,
    fit_every: f64,
    /// The period of the last accepted fit, where the next search starts.
    period: Option<f64>,
    /// The last accepted fit's answer, and its time.
    accepted: Option<(Answer, f64)>,
    /// Fits accepted and refused, for diagnostics.
    pub fits: [u64; 2],
    /// Whether a fit has been accepted with two cycles of its period in the horizon (`CONFIRMED_CYCLES`). Until one
    /// is, an accepted answer is provisional: it stands only until the next fit is refused.
    confirmed: bool,
}

impl Default for PeriodicLoad {
    fn default() -> Self {
        PeriodicLoad {
            blocks: VecDeque::with_capacity(blocks_kept() + 1),
            sum: Block::default(),
            count: 0,
            span: 0.0,
            t: 0.0,
            i_torque: 0.0,
            i_speed: 0.0,
            i_fan: 0.0,
            fan: false,
            since_fit: 0.0,
            fit_every: FIT_EVERY_S,
            period: None,
            accepted: None,
            fits: [0; 2],
            confirmed: false,
        }
    }
}

fn blocks_kept() -> usize {
    (HORIZON_S / BLOCK_S).round() as usize
}

/// What an accepted fit says: B and J, each with its variance.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Answer {
    pub viscous: (f64, f64),
    pub inertia: (f64, f64),
}

/// The fit at one period: the solution (unscaled), the residual sum of squares, and the Cholesky factor of the
/// normal matrix with its columns scaled by `scale`.
struct Fit {
    x: Column,
    ssr: f64,
    factor: nalgebra::Cholesky<f64, nalgebra::Const<N>>,
    scale: Column,
}

impl PeriodicLoad {
    /// B and J with their variances from the last accepted fit, aged since (nothing before the first).
    pub fn estimate(&self) -> Option<Answer> {
        self.accepted.map(|(a, t)| {
            let aged = |(x, var): (f64, f64)| (x, var + (AGING_PER_MIN * x).powi(2) * (self.t - t) / 60.0);
            Answer { viscous: aged(a.viscous), inertia: aged(a.inertia) }
        })
    }

    /// From now on, fits with a fan's term (`−∫ω|ω|`, module doc): the windows have shown a load that grows with the
    /// speed. A provisional answer fitted without it goes.
    pub fn fit_fan(&mut self) {
        if !self.fan && !self.confirmed {
            self.accepted = None;
        }
        self.fan = true;
    }

    /// Whether the fits have a fan's term ([`Self::fit_fan`]).
    pub fn fits_fan(&self) -> bool {
        self.fan
    }

    /// Whether a fit has been accepted with two cycles of its period in the horizon: its answer then stands, aging,
    /// until a later one is. A provisional answer (`PROVISIONAL_CYCLES`) is in [`Self::estimate`] but not confirmed.
    pub fn confirmed(&self) -> bool {
        self.confirmed
    }

    /// Forgets the horizon (after a gap or a missing value); the last answer stands until the next fit, which comes as
    /// often as for a horizon that grows.
    pub fn restart(&mut self) {
        self.blocks.clear();
        self.sum = Block::default();
        self.count = 0;
        self.span = 0.0;
        self.since_fit = 0.0;
        self.fit_every = FIT_EVERY_S;
    }

    /// One complete sample pair (speeds and torques at both ends of `dt`). `bounds` is B's physical range. True when
    /// it closed a block (the estimate may have changed, and it has aged).
    pub fn push(&mut self, dt: f64, (w0, t0): (f64, f64), (w1, t1): (f64, f64), bounds: [f64; 2]) -> bool {
        self.t += dt;
        self.i_torque += dt * 0.5 * (t0 + t1);
        self.i_speed += dt * 0.5 * (w0 + w1);
        self.i_fan += dt * 0.5 * (w0 * w0.abs() + w1 * w1.abs());
        self.sum.t += self.t;
        self.sum.omega += w1;
        self.sum.i_torque += self.i_torque;
        self.sum.i_speed += self.i_speed;
        self.sum.i_fan += self.i_fan;
        self.count += 1;
        self.span += dt;
        if self.span < BLOCK_S - 1e-9 {
            return false;
        }
        let n = f64::from(self.count);
        let s = self.sum;
        self.blocks.push_back(Block {
            t: s.t / n,
            omega: s.omega / n,
            i_torque: s.i_torque / n,
            i_speed: s.i_speed / n,
            i_fan: s.i_fan / n,
        });
        if self.blocks.len() > blocks_kept() {
            self.blocks.pop_front();
        }
        self.since_fit += self.span;
        (self.sum, self.count, self.span) = (Block::default(), 0, 0.0);
        let covered = match (self.blocks.front(), self.blocks.back()) {
            (Some(a), Some(b)) => b.t - a.t,
            _ => 0.0,
        };
        if self.since_fit >= self.fit_every && covered >= MIN_SPAN_S {
            self.since_fit = 0.0;
            let answer = self.fit(covered, bounds);
            self.fits[usize::from(answer.is_none())] += 1;
            self.period = answer.and_then(|(_, p, confirmed)| confirmed.then_some(p));
            let full = self.blocks.len() >= blocks_kept();
            match answer {
                Some((a, _, confirmed)) => {
                    (self.accepted, self.fit_every) = (Some((a, self.t)), FIT_EVERY_S);
                    self.confirmed |= confirmed;
                }
                None => {
                    if !self.confirmed {
                        // a provisional answer does not outlive a refusal
                        self.accepted = None;
                    }
                    if full {
                        self.fit_every = (2.0 * self.fit_every).min(FIT_AT_MOST_EVERY_S);
                    }
                }
            }
        }
        true
    }

    /// Searches the period, fits, and judges the fit: B and J with their variances, the period, and whether it is
    /// confirmed (two of its cycles in the horizon); or nothing. Periods up to half the span first, around the last
    /// confirmed one if there is one; where none answers, none has been confirmed yet and the horizon is not yet full,
    /// longer ones up to the span
    /// (`PROVISIONAL_CYCLES`).
    fn fit(&self, covered: f64, bounds: [f64; 2]) -> Option<(Answer, f64, bool)> {
        let prepared = prepare(self.rows());
        let confirmable = covered / CONFIRMED_CYCLES;
        let range = match self.period {
            Some(p) if p <= confirmable => (p / SCAN_RATIO.powi(2), (p * SCAN_RATIO.powi(2)).min(confirmable)),
            _ => (MIN_PERIOD_S, confirmable),
        };
        let answer = |range| best_period(&prepared, range).and_then(|p| accepted(&prepared, p, bounds));
        if let Some((a, p)) = answer(range) {
            return Some((a, p, true));
        }
        if self.confirmed || self.blocks.len() >= blocks_kept() {
            return None;
        }
        answer((confirmable, covered / PROVISIONAL_CYCLES)).map(|(a, p)| (a, p, false))
    }

    /// The horizon's rows, relative to its first block.
    fn rows(&self) -> Vec<Row> {
        let Some(first) = self.blocks.front().copied() else { return Vec::new() };
        self.blocks
            .iter()
            .map(|b| Row {
                u: b.t - first.t,
                y: b.omega,
                i_torque: b.i_torque - first.i_torque,
                i_speed: b.i_speed - first.i_speed,
                i_fan: if self.fan { b.i_fan - first.i_fan } else { 0.0 },
            })
            .collect()
    }
}

/// The fit at period `p` if it is accepted: B known to `MAX_RELATIVE_SD` and within its bounds (allowing two of its
/// standard deviations, then clamped to them), J known likewise; with the period.
fn accepted(prepared: &Prepared, p: f64, [lo, hi]: [f64; 2]) -> Option<(Answer, f64)> {
    let answer = fit_at(prepared, p)?;
    let ((b_hat, var), (_, var_j)) = (answer.viscous, answer.inertia);
    let sd = var.sqrt();
    let identified = sd <= MAX_RELATIVE_SD * b_hat.abs() && var_j.sqrt() <= MAX_RELATIVE_SD * answer.inertia.0;
    if !(var.is_finite() && var_j.is_finite() && identified && b_hat > lo - 2.0 * sd && b_hat < hi + 2.0 * sd) {
        return None;
    }
    Some((Answer { viscous: (b_hat.clamp(lo, hi), var), ..answer }, p))
}

/// The period of least residual within `(from, to)`: a geometric grid (every other row), then a golden section
/// within one grid step on all rows.
fn best_period(prepared: &Prepared, (from, to): (f64, f64)) -> Option<f64> {
    let mut best: Option<(f64, f64)> = None;
    // The grid on every other row (the period's valley is as wide), then the refinement on all.
    let coarse = prepare(prepared.rows.iter().step_by(2).copied().collect());
    let mut p = from;
    while p <= to {
        if let Some(ssr) = solve(&coarse, p)
            && best.is_none_or(|(s, _)| ssr < s)
        {
            best = Some((ssr, p));
        }
        p *= SCAN_RATIO;
    }
    let (_, p) = best?;
    // Refine within one grid step (golden section).
    let (mut a, mut b) = (p / SCAN_RATIO, (p * SCAN_RATIO).min(to));
    let g = 0.5 * (5f64.sqrt() - 1.0);
    let ssr = |p: f64| solve(prepared, p).unwrap_or(f64::INFINITY);
    let (mut c, mut d) = (b - g * (b - a), a + g * (b - a));
    let (mut fc, mut fd) = (ssr(c), ssr(d));
    for _ in 0..10 {
        if fc < fd {
            (b, d, fd) = (d, c, fc);
            c = b - g * (b - a);
            fc = ssr(c);
        } else {
            (a, c, fc) = (c, d, fd);
            d = a + g * (b - a);
            fd = ssr(d);
        }
    }
    Some(if fc < fd { c } else { d })
}

/// The fit at period `p` from exact regressors, with one normal system per jackknife segment: B and J with their
/// variances (the fit's own, residual-scaled, at least the delete-a-segment jackknife's and the model floor); None
/// where the residual is too smooth (Durbin–Watson) or the fit unphysical.
fn fit_at(prepared: &Prepared, p: f64) -> Option<Answer> {
    let rows = &prepared.rows;

    let n = rows.len();
    let len = n.div_ceil(SEGMENTS);
    let mut parts = [(Normal::zeros(), Column::zeros(), 0.0); SEGMENTS];
    let w = TAU / p;
    let xs: Vec<Column> = rows.iter().map(|r| regressors(r, w)).collect();
    for (i, (x, r)) in xs.iter().zip(rows).enumerate() {
        let part = &mut parts[i / len];
        part.0.ger(1.0, x, x, 1.0);
        part.1 += x * r.y;
        part.2 += r.y * r.y;
    }
    let (mut a, mut b, mut yy) = (Normal::zeros(), Column::zeros(), 0.0);
    for part in &parts {
        a += part.0;
        b += part.1;
        yy += part.2;
    }
    let fit = factorise(&a, &b, yy)?;
    // Durbin–Watson on the residual.
    let residual: Vec<f64> = xs.iter().zip(rows).map(|(x, r)| r.y - x.dot(&fit.x)).collect();
    let rough: f64 = residual.windows(2).map(|w| (w[1] - w[0]).powi(2)).sum();
    let level: f64 = residual.iter().map(|r| r * r).sum();
    let viscous = |x: &Column| x[2] / x[1];
    let b_hat = viscous(&fit.x);
    let j_hat = 1.0 / fit.x[1];
    if !(level > 0.0 && rough / level >= MIN_DURBIN_WATSON && fit.x[1] > 0.0 && b_hat.is_finite()) {
        return None;
    }
    // The fit's own variance of B = x₂/x₁ (first order), residual-scaled.
    let active = N - usize::from(prepared.ff[(FAN, FAN)] == 0.0);
    let sigma2 = fit.ssr / (n - active) as f64;
    let grad = [-fit.x[2] / (fit.x[1] * fit.x[1]), 1.0 / fit.x[1]];
    let (s1, s2) = (fit.scale[1], fit.scale[2]);
    let inverse = fit.factor.inverse();
    let cov = |i: usize, j: usize, si: f64, sj: f64| inverse[(i, j)] / (si * sj) * sigma2;
    let own = grad[0] * grad[0] * cov(1, 1, s1, s1)
        + 2.0 * grad[0] * grad[1] * cov(1, 2, s1, s2)
        + grad[1] * grad[1] * cov(2, 2, s2, s2);
    let own_j = cov(1, 1, s1, s1) * j_hat.powi(4);
    // Delete-a-segment jackknife.
    let mut leave_out = [(0.0, 0.0); SEGMENTS];
    for (k, out) in leave_out.iter_mut().enumerate() {
        let (pa, pb, py) = &parts[k];
        let x = factorise(&(a - pa), &(b - pb), yy - py)?.x;
        *out = (viscous(&x), 1.0 / x[1]);
    }
    let k = SEGMENTS as f64;
    let jackknife = |f: fn(&(f64, f64)) -> f64| {
        let mean = leave_out.iter().map(f).sum::<f64>() / k;
        (k - 1.0) / k * leave_out.iter().map(|o| (f(o) - mean).powi(2)).sum::<f64>()
    };
    let var = own.max(jackknife(|o| o.0)).max((MODEL_SD * b_hat).powi(2));
    let var_j = own_j.max(jackknife(|o| o.1)).max((MODEL_SD * j_hat).powi(2));
    Some(Answer { viscous: (b_hat, var), inertia: (j_hat, var_j) })
}

#[derive(Debug, Clone, Copy)]
struct Row {
    u: f64,
    y: f64,
    i_torque: f64,
    i_speed: f64,
    i_fan: f64,
}

/// The regressors of one row that do not depend on the period: [1, ∫τ, −∫ω, −u, −u²/2, −∫ω|ω|] (the last zero
/// where the fit has no fan's term).
fn fixed_regressors(r: &Row) -> SVector<f64, FIXED> {
    SVector::from([1.0, r.i_torque, -r.i_speed, -r.u, -0.5 * r.u * r.u, -r.i_fan])
}

/// All regressors of one row at angular frequency `w`: the fixed ones, then −sin(wu)/w and −(1 − cos(wu))/w.
fn regressors(r: &Row, w: f64) -> Column {
    let (s, c) = (w * r.u).sin_cos();
    let mut x = Column::zeros();
    x.fixed_rows_mut::<FIXED>(0).copy_from(&fixed_regressors(r));
    x[FIXED] = -s / w;
    x[FIXED + 1] = -(1.0 - c) / w;
    x
}

/// The horizon's fixed part, gathered once per fit: the normal equations of the fixed regressors.
struct Prepared {
    rows: Vec<Row>,
    fixed: Vec<SVector<f64, FIXED>>,
    ff: SMatrix<f64, FIXED, FIXED>,
    fy: SVector<f64, FIXED>,
    yy: f64,
    /// The rows' spacing when it is the same throughout (one rotation serves every row).
    spacing: Option<f64>,
}

const FIXED: usize = N - 2;
/// The fan's column among the fixed regressors (all zero where the fit has no fan's term).
const FAN: usize = FIXED - 1;

fn prepare(rows: Vec<Row>) -> Prepared {
    let fixed: Vec<SVector<f64, FIXED>> = rows.iter().map(fixed_regressors).collect();
    let mut ff = SMatrix::<f64, FIXED, FIXED>::zeros();
    let mut fy = SVector::<f64, FIXED>::zeros();
    let mut yy = 0.0;
    for (f, r) in fixed.iter().zip(&rows) {
        ff.ger(1.0, f, f, 1.0);
        fy += f * r.y;
        yy += r.y * r.y;
    }
    let h = rows.get(1).map_or(0.0, |r| r.u);
    let spacing = rows.windows(2).all(|w| ((w[1].u - w[0].u) - h).abs() <= 1e-9 * h.max(1.0)).then_some(h);
    Prepared { rows, fixed, ff, fy, yy, spacing }
}

/// cos φ and sin φ for |φ| ≲ 1.1 (Taylor to φ⁹; error below 10⁻⁶ there): the rotation between neighbouring rows.
fn rotation(phi: f64) -> (f64, f64) {
    let p2 = phi * phi;
    let c = 1.0 - p2 / 2.0 * (1.0 - p2 / 12.0 * (1.0 - p2 / 30.0 * (1.0 - p2 / 56.0)));
    let s = phi * (1.0 - p2 / 6.0 * (1.0 - p2 / 20.0 * (1.0 - p2 / 42.0 * (1.0 - p2 / 72.0))));
    (c, s)
}

/// Least squares at one period: only the two sinusoid columns are new (their angle by rotation from row to row),
/// and the 8×8 system is factorised with its columns scaled to unit mean square.
fn solve(p: &Prepared, period: f64) -> Option<f64> {
    if p.rows.len() <= N + 1 {
        return None;
    }
    let w = TAU / period;
    let (mut fs, mut fc) = (SVector::<f64, FIXED>::zeros(), SVector::<f64, FIXED>::zeros());
    let (mut ss, mut sc, mut cc, mut sy, mut cy) = (0.0, 0.0, 0.0, 0.0, 0.0);
    let (mut cos, mut sin, mut u) = (1.0, 0.0, 0.0);
    let uniform = p.spacing.map(|h| rotation(w * h));
    for (f, r) in p.fixed.iter().zip(&p.rows) {
        let (cr, sr) = uniform.unwrap_or_else(|| rotation(w * (r.u - u)));
        (cos, sin, u) = (cos * cr - sin * sr, sin * cr + cos * sr, r.u);
        let (gs, gc) = (-sin / w, -(1.0 - cos) / w);
        fs.axpy(gs, f, 1.0);
        fc.axpy(gc, f, 1.0);
        ss += gs * gs;
        sc += gs * gc;
        cc += gc * gc;
        sy += gs * r.y;
        cy += gc * r.y;
    }
    let mut a = Normal::zeros();
    a.fixed_view_mut::<FIXED, FIXED>(0, 0).copy_from(&p.ff);
    a.fixed_view_mut::<FIXED, 1>(0, FIXED).copy_from(&fs);
    a.fixed_view_mut::<FIXED, 1>(0, FIXED + 1).copy_from(&fc);
    a.fixed_view_mut::<1, FIXED>(FIXED, 0).copy_from(&fs.transpose());
    a.fixed_view_mut::<1, FIXED>(FIXED + 1, 0).copy_from(&fc.transpose());
    a[(FIXED, FIXED)] = ss;
    a[(FIXED, FIXED + 1)] = sc;
    a[(FIXED + 1, FIXED)] = sc;
    a[(FIXED + 1, FIXED + 1)] = cc;
    let mut b = Column::zeros();
    b.fixed_rows_mut::<FIXED>(0).copy_from(&p.fy);
    b[FIXED] = sy;
    b[FIXED + 1] = cy;
    if a[(FAN, FAN)] == 0.0 {
        // no fan's term: the system without its column, a size smaller (the search's cost is in these solves)
        let keep = |i: usize| if i < FAN { i } else { i + 1 };
        let a = SMatrix::<f64, { N - 1 }, { N - 1 }>::from_fn(|i, j| a[(keep(i), keep(j))]);
        let b = SVector::<f64, { N - 1 }>::from_fn(|i, _| b[keep(i)]);
        return residual(&a, &b, p.yy);
    }
    residual(&a, &b, p.yy)
}

/// The residual sum of squares of the least-squares fit with normal equations `a`, `b` (scaled as [`factorise`]
/// scales them).
fn residual<const M: usize>(a: &SMatrix<f64, M, M>, b: &SVector<f64, M>, yy: f64) -> Option<f64> {
    let (scaled, _, rhs) = scaled(a, b);
    let z = scaled.cholesky()?.solve(&rhs);
    Some((yy - z.dot(&rhs)).max(0.0))
}

/// Solves scaled normal equations; the residual sum of squares from `yy`. A column that is all zero (the fan's term
/// where there is none) has its coefficient zero and leaves the others as they would be without it.
fn factorise(a: &Normal, b: &Column, yy: f64) -> Option<Fit> {
    let (scaled, scale, rhs) = scaled(a, b);
    let chol = scaled.cholesky()?;
    let z = chol.solve(&rhs);
    let ssr = (yy - z.dot(&rhs)).max(0.0);
    Some(Fit { x: z.component_div(&scale), ssr, factor: chol, scale })
}

/// Normal equations with their columns scaled to unit mean square: the matrix, the scales and the right-hand side. A
/// column that is all zero keeps a unit diagonal, so that its coefficient is zero.
fn scaled<const M: usize>(
    a: &SMatrix<f64, M, M>,
    b: &SVector<f64, M>,
) -> (SMatrix<f64, M, M>, SVector<f64, M>, SVector<f64, M>) {
    let scale = SVector::<f64, M>::from_fn(|i, _| a[(i, i)].sqrt().max(1e-300));
    let m =
        SMatrix::<f64, M, M>::from_fn(
            |i, j| if i == j && a[(i, i)] == 0.0 { 1.0 } else { a[(i, j)] / (scale[i] * scale[j]) },
        );
    (m, scale, b.component_div(&scale))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::battery;
    use crate::plant::PlantModel;
    use crate::plant::scenario::{Family, Scenario};

    /// Feeds a battery scenario's polled rows to a fresh periodic fit; with `drop_every` = k,
    /// every k-th row is lost (as a late poll would be), so the steps and blocks are uneven.
    fn fed(family: Family, seed: u64, poll_ms: u32, drop_every: Option<usize>) -> PeriodicLoad {
        fed_watching(family, seed, poll_ms, drop_every, |_, _| {})
    }

    /// As [`fed`], calling `watch` with each row's time and the fit after it.
    fn fed_watching(
        family: Family,
        seed: u64,
        poll_ms: u32,
        drop_every: Option<usize>,
        watch: impl FnMut(f64, &PeriodicLoad),
    ) -> PeriodicLoad {
        feed(PeriodicLoad::default(), family, seed, poll_ms, drop_every, watch)
    }

    /// As [`fed_watching`], into a given fit.
    fn feed(
        mut fit: PeriodicLoad,
        family: Family,
        seed: u64,
        poll_ms: u32,
        drop_every: Option<usize>,
        mut watch: impl FnMut(f64, &PeriodicLoad),
    ) -> PeriodicLoad {
        let truth = PlantModel::reference();
        let p = battery::poll(&Scenario::generate(family, seed, 60.0), &truth, poll_ms);
        let kept: Vec<usize> = (0..p.t_s.len()).filter(|&k| drop_every.is_none_or(|d| k % d != d - 1)).collect();
        for pair in kept.windows(2) {
            let (a, b) = (&p.measurements[pair[0]], &p.measurements[pair[1]]);
            let dt = p.t_s[pair[1]] - p.t_s[pair[0]];
            fit.push(dt, (a.omega_rad_s, a.drive_torque_nm), (b.omega_rad_s, b.drive_torque_nm), [0.0, 0.2]);
            watch(p.t_s[pair[1]], &fit);
        }
        fit
    }

    #[test]
    fn the_rotation_between_rows_is_the_sine_and_cosine() {
        for i in -110..=110 {
            let phi = f64::from(i) / 100.0;
            let (c, s) = rotation(phi);
            assert!((c - phi.cos()).abs() < 1e-6 && (s - phi.sin()).abs() < 1e-6, "{phi}");
        }
    }

    /// Tuned sine seed 6 (period 6.6 s, amplitude 5 N·m): the windows' B scatter from −0.09 to +0.22 there; one fit
    /// over the horizon finds B = 0.04 and J = 0.08 within a few per cent, and says how sure it is.
    #[test]
    fn under_a_sine_load_the_fit_finds_b_and_j_and_says_how_sure() {
        // evenly polled, and with every 7th poll lost (uneven rows: the rotation is then computed row by row)
        for drop_every in [None, Some(7)] {
            let fit = fed(Family::Sine, 6, 10, drop_every);
            let answer = fit.estimate().expect("accepted");
            assert!(fit.fits[0] >= 10, "{drop_every:?}: {:?}", fit.fits);
            for ((x, var), truth) in [(answer.viscous, 0.04), (answer.inertia, 0.08)] {
                let sd = var.sqrt();
                assert!((x - truth).abs() < 0.05 * truth, "{drop_every:?}: {x} ± {sd}, true {truth}");
                assert!((x - truth).abs() <= 2.0 * sd && sd < 0.05 * truth, "{drop_every:?}: {x} ± {sd}, true {truth}");
            }
        }
    }

    /// Brake steps are not periodic: the residual is smooth, every fit is refused (every 2.5 s of data from 8 s on,
    /// doubling the interval to the next, up to 10 s, once the horizon is full), and there is no answer.
    #[test]
    fn under_brake_steps_there_is_no_answer() {
        for seed in [1, 7] {
            let fit = fed(Family::Brake, seed, 10, None);
            assert!(fit.estimate().is_none() && fit.fits[0] == 0 && fit.fits[1] >= 8, "{:?}", fit.fits);
        }
    }

    /// A load of a long period is confirmed within a fit's interval of the horizon holding two of its cycles, however
    /// many fits were refused (or provisional) before: held-out sine seed 1018 (period 7.3 s), whose windows' B stands
    /// +60 % on an exact model until the fit comes, is answered at 15.6 s (at 23 s where a refused fit doubled the
    /// interval to the next).
    #[test]
    fn a_long_period_is_answered_once_two_cycles_are_in_the_horizon() {
        let scenario = Scenario::generate(Family::Sine, 1018, 60.0);
        let crate::plant::scenario::LoadProgram::Profile(crate::plant::load::LoadSpec::Sine { period_s, .. }) =
            scenario.load
        else {
            unreachable!("the sine family is a sine profile")
        };
        let mut answered = None;
        fed_watching(Family::Sine, 1018, 10, None, |t, fit| {
            if answered.is_none() && fit.confirmed() {
                answered = Some(t);
            }
        });
        let t = answered.expect("answered");
        assert!(t <= 2.0 * period_s + FIT_EVERY_S + BLOCK_S, "period {period_s} s, answered at {t} s");
    }

    /// An answer stands when later fits are refused, but grows less sure with its age; a restart keeps it.
    #[test]
    fn an_answer_ages_and_outlives_a_restart() {
        let mut fit = fed(Family::Sine, 6, 10, None);
        let (b, var) = fit.estimate().expect("accepted").viscous;
        fit.restart();
        for _ in 0..6000 {
            fit.push(0.01, (40.0, 10.0), (40.0, 10.0), [0.0, 0.2]);
        }
        let (b_later, var_later) = fit.estimate().expect("still there").viscous;
        assert_eq!(b_later, b);
        // one minute later: the standard deviation has grown by about a tenth of B
        assert!((var_later - var - (0.1 * b).powi(2)).abs() < 1e-9, "{var} → {var_later}");
    }

    /// One cycle in the horizon gives a provisional answer, two confirm it: tuned sine seed 6 (period 6.6 s) is
    /// answered at the first fit, at 8 s, with B and J within 2 sd of the truth, and confirmed at 15.6 s. A provisional
    /// answer goes at the next refusal: under tuned ramp seed 9 one cycle fits at 8 and 10.6 s, the fit at 13.1 s is
    /// refused, and the answer goes with it (at 25.6 s a fit over two cycles is confirmed).
    #[test]
    fn one_cycle_gives_a_provisional_answer_and_two_confirm_it() {
        // when the answer comes, goes or is confirmed, and the first answer
        let changes = |family, seed| {
            let (mut seen, mut first) = (vec![(0.0, (false, false))], None);
            fed_watching(family, seed, 10, None, |t, fit| {
                let now = (fit.estimate().is_some(), fit.confirmed());
                first = first.or(fit.estimate());
                if seen.last().is_some_and(|(_, was)| *was != now) {
                    seen.push((t, now));
                }
            });
            (seen, first)
        };
        let (seen, first) = changes(Family::Sine, 6);
        let [_, (provisional_at, (true, false)), (confirmed_at, (true, true))] = seen[..] else { panic!("{seen:?}") };
        assert!(provisional_at < 8.5 && (15.0..16.0).contains(&confirmed_at), "{seen:?}");
        let provisional = first.expect("answered");
        for ((x, var), truth) in [(provisional.viscous, 0.04), (provisional.inertia, 0.08)] {
            assert!((x - truth).abs() <= 2.0 * var.sqrt(), "provisional {x} ± {}, true {truth}", var.sqrt());
        }
        let (seen, _) = changes(Family::Ramp, 9);
        let [_, (answered_at, (true, false)), (gone_at, (false, false)), ..] = seen[..] else { panic!("{seen:?}") };
        assert!(answered_at < 8.5 && gone_at < 13.5, "{seen:?}");
    }

    /// Under a fan (torque ∝ ω|ω|, tuned centrifugal seeds 1–4, 10 ms) the fit without a fan's term is refused at
    /// every try (the load is not periodic); with it, B is friction's and J the inertia, each within 2 sd.
    #[test]
    fn with_a_fans_term_the_fit_finds_friction_under_a_fan() {
        for seed in 1..=4 {
            let plain = fed(Family::Centrifugal, seed, 10, None);
            assert!(plain.estimate().is_none() && plain.fits[0] == 0, "seed {seed}: {:?}", plain.fits);
            let mut fan = PeriodicLoad::default();
            fan.fit_fan();
            let fit = feed(fan, Family::Centrifugal, seed, 10, None, |_, _| {});
            let answer = fit.estimate().expect("answered");
            for ((x, var), truth) in [(answer.viscous, 0.04), (answer.inertia, 0.08)] {
                assert!((x - truth).abs() <= 2.0 * var.sqrt(), "seed {seed}: {x} ± {}, true {truth}", var.sqrt());
            }
        }
    }
}

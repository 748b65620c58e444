//! The windows' own B and J pooled as random-effects means (DerSimonian–Laird, Huber-robust), and the tests of
//! whether the windows' B depends on the speed they saw (a load that follows the speed) and whether their J
//! differs between speed-ups and slow-downs (a load that moves with the acceleration). Pure: fed each window's
//! estimate, variance and covariate (B: its mean speed; J: the sign of its speed change) by `windows.rs`.

/// Huber threshold (σ) of a window's disagreement (with θ in the RLS, with the pooled value here): beyond it the
/// window counts for less.
pub(super) const HUBER_Z: f64 = 2.5;
/// Informative windows pooled for B.
const POOL: usize = 40;
/// How many times the between-window variance τ² counts in J's pool variance: each sample lies in two windows
/// (the staggered sequences), so n windows hold about n/2 independent looks at the scatter. B's pool keeps 1: its
/// variance also weighs B against the periodic fit and decides where B stands, and 2 there traded four runs that
/// hold on the six families for five runs of no harm on the new loads (tuned, held-out, fresh and sealed seeds).
pub(super) const OVERLAP: f64 = 2.0;

/// B (and, for its credible standard deviation, J) from the windows as a random-effects mean (DerSimonian–Laird),
/// robust (Huber). A window's B is biased by whatever part of the load its nuisance did not follow (a sine's curvature
/// over a setpoint change), differently in each window; so the windows are pooled as studies of one B, each with its
/// own variance plus a between-window variance τ² learnt from their scatter. Consistent windows (brake steps) give a
/// tight B; scattered ones (sine loads) give their plain average with a standard deviation as wide as the scatter says,
/// never the confident answer of whichever windows came first. The prior (the model's B) is one more, fixed, study; old
/// windows leave the pool, so a wrong B recovers.
#[derive(Debug, Clone)]
pub(super) struct WindowPool {
    prior: (f64, f64),
    windows: [(f64, f64); POOL],
    /// Each window's covariate. B: its mean speed (a B that grows with the speed it was measured at is a load that
    /// follows the speed). J: the sign of its speed change (a J that differs between speed-ups and slow-downs is a
    /// load that moves with the acceleration; an inertia is the same both ways).
    speeds: [f64; POOL],
    len: usize,
    next: usize,
    bounds: [f64; 2],
    /// How many times the between-window variance τ² counts in the pooled variance (not in the weights).
    overlap: f64,
    /// The pooled value and its variance.
    pub estimate: (f64, f64),
    /// Whether the pooled value lay outside the physical bounds (`estimate` is then the bound, with the prior's
    /// variance): the windows' fits are no fits of the plant.
    pub outside: bool,
    /// The windows' line on their covariate ([`WindowPool::speed_slope`]), fitted as each window comes: the tests
    /// read it at every judgement (every 0.1 s of data), and fitting it there cost an update at 1 ms 7 ns.
    slope: Option<SpeedSlope>,
}

impl WindowPool {
    pub(super) fn new(b: f64, var: f64, bounds: [f64; 2], overlap: f64) -> WindowPool {
        WindowPool {
            prior: (b, var),
            windows: [(0.0, 0.0); POOL],
            speeds: [0.0; POOL],
            len: 0,
            next: 0,
            bounds,
            overlap,
            estimate: (b, var),
            outside: false,
            slope: None,
        }
    }

    pub(super) fn add(&mut self, b: f64, var: f64, speed: f64) {
        if !(b.is_finite() && var.is_finite() && var > 0.0) {
            return;
        }
        self.windows[self.next] = (b, var);
        self.speeds[self.next] = speed;
        self.next = (self.next + 1) % POOL;
        self.len = (self.len + 1).min(POOL);
        (self.estimate, self.outside) = self.pool();
        self.slope = self.speed_slope();
    }

    /// Whether the windows' B grows (or falls) with the speed they were measured at: the slope of B on the window's
    /// mean speed (weighted by each window's variance plus the between-window scatter) is `SPEED_SLOPE_Z` standard
    /// errors from zero and moves B by more than half its mean over the speeds seen. Viscous friction is one number
    /// at every speed; a fan's torque has a slope that doubles with the speed. Once `shown`, `SPEED_SLOPE_HOLD_Z`
    /// standard errors keep it: the verdict flapped as windows left the pool.
    pub(super) fn depends_on_speed(&self, shown: bool) -> bool {
        self.depends_on_covariate(shown, 0.5)
    }

    /// Whether the windows' J differs between speed-ups and slow-downs (the J pool's covariate is the sign of each
    /// window's speed change): by `SPEED_SLOPE_Z` standard errors (`SPEED_SLOPE_HOLD_Z` once shown) and by more than
    /// [`ACCELERATION_J_SHARE`] of J. An inertia is one number whichever way the speed goes; a load that rises on
    /// every speed-up (a conveyor loading as it starts, a load timed with the setpoint program) adds to the J of the
    /// speed-ups only. A load exactly proportional to the acceleration either way is inertia to any data of speed
    /// and torque, and is not seen.
    pub(super) fn depends_on_direction(&self, shown: bool) -> bool {
        self.depends_on_covariate(shown, ACCELERATION_J_SHARE)
    }

    /// Whether the pool holds `count` windows of each sign of its covariate that each know their value to `share` of
    /// the pooled one (J: speed-ups and slow-downs). Until then a load that moves with the acceleration cannot be told
    /// from inertia, since J has been seen one way only.
    pub(super) fn seen_both_ways(&self, share: f64, count: usize) -> bool {
        let m = self.estimate.0;
        let informative = |sign: f64| {
            let windows = self.windows[..self.len].iter().zip(&self.speeds[..self.len]);
            windows.filter(|&(&(_, v), &c)| c * sign > 0.0 && v.sqrt() <= share * m.abs()).count()
        };
        informative(1.0) >= count && informative(-1.0) >= count
    }

    /// The slope of the windows' values on their covariate is `SPEED_SLOPE_Z` standard errors from zero
    /// (`SPEED_SLOPE_HOLD_Z` once `shown`) and moves the value by more than `share` of its mean over the range seen.
    fn depends_on_covariate(&self, shown: bool, share: f64) -> bool {
        let z = if shown { SPEED_SLOPE_HOLD_Z } else { SPEED_SLOPE_Z };
        self.slope
            .is_some_and(|s| (s.slope / s.se).abs() > z && (s.slope * s.speed_range).abs() > share * s.mean_b.abs())
    }

    /// Whether the windows' B hints at a speed dependence, its slope more than `SPEED_SLOPE_HOLD_Z` standard errors
    /// from zero; `None` before there are windows enough to look (`SPEED_SLOPE_WINDOWS`).
    pub(super) fn speed_hint(&self) -> Option<bool> {
        self.slope.map(|s| (s.slope / s.se).abs() > SPEED_SLOPE_HOLD_Z)
    }

    /// How much likelier the windows' B against their speed is under a load that made up `distance` of B at their
    /// mean speed than under friction (one B at every speed): the likelihood ratio of the fitted slope, a fan's
    /// slope (its local B is twice its torque over the speed, so the slope is that B over the speed) against none,
    /// with the slope's standard error. Near 1 where the two slopes lie within a standard error of each other (too
    /// few windows, too narrow a range of speeds, a small distance): the windows cannot tell them apart. `None`
    /// before there are windows enough to look (`SPEED_SLOPE_WINDOWS`).
    pub(super) fn load_odds(&self, distance: f64) -> Option<f64> {
        self.slope.map(|s| {
            let load = distance / s.mean_abs_speed.max(f64::MIN_POSITIVE);
            ((s.slope * load - load * load / 2.0) / (s.se * s.se)).exp()
        })
    }

    /// The weighted line of the windows' B on their mean speed (a meta-regression: each window weighted by its
    /// variance plus the between-window scatter about the line); `None` before `SPEED_SLOPE_WINDOWS` windows.
    fn speed_slope(&self) -> Option<SpeedSlope> {
        let n = self.len;
        if n < SPEED_SLOPE_WINDOWS {
            return None;
        }
        let (b, speeds) = (&self.windows[..n], &self.speeds[..n]);
        let line = |tau2: f64| {
            let (mut sw, mut sx, mut sy, mut sxx, mut sxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
            for (&(y, v), &x) in b.iter().zip(speeds) {
                let w = 1.0 / (v + tau2).max(1e-300);
                (sw, sx, sy, sxx, sxy) = (sw + w, sx + w * x, sy + w * y, sxx + w * x * x, sxy + w * x * y);
            }
            let var_x = sxx / sw - (sx / sw).powi(2);
            let slope = (sxy / sw - sx / sw * sy / sw) / var_x;
            (slope, sy / sw, sx / sw, sw * var_x)
        };
        // each window's squared distance from a line (slope, mean B, mean speed), with the window's variance
        let about = |(slope, mean_b, mean_x): (f64, f64, f64)| {
            b.iter().zip(speeds).map(move |(&(y, v), &x)| ((y - mean_b - slope * (x - mean_x)).powi(2), v))
        };
        // the scatter is measured about the line, not about the mean: a speed dependence is not scatter
        let (slope, mean_b, mean_x, _) = line(0.0);
        let excess: f64 = about((slope, mean_b, mean_x)).map(|(d2, v)| d2 - v).sum();
        let tau2 = (SCATTER_SHARE * excess / (n - 2) as f64).max(0.0);
        let (slope, mean_b, mean_speed, information) = line(tau2);
        if !(information.is_finite() && information > 0.0) {
            return None;
        }
        // residual scatter about the line, for the slope's standard error
        let resid: f64 =
            about((slope, mean_b, mean_speed)).map(|(d2, v)| d2 / (v + tau2).max(1e-300)).sum::<f64>() / (n - 2) as f64;
        let se = (resid.max(1.0) / information).sqrt();
        let (lo, hi) = speeds.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| (a.min(x), b.max(x)));
        let mean_abs_speed = speeds.iter().map(|x| x.abs()).sum::<f64>() / n as f64;
        Some(SpeedSlope { slope, se, mean_b, mean_abs_speed, speed_range: hi - lo })
    }

    /// Whether the plant changed (a mass coupled, a load with an inertia of its own): the newest [`CHANGE_WINDOWS`]
    /// windows, pooled, differ from the older ones, pooled, by [`CHANGE_Z`] standard errors of the difference and by
    /// [`CHANGE_SHARE`] of the older value, and they hold both signs of the covariate (J: a speed-up and a slow-down,
    /// since an inertia is the same both ways). Each group is pooled with its own scatter, so windows that scatter (a
    /// load their nuisance follows badly) show no change however far a few of them lie. The newest windows' pooled
    /// value and variance where they differ.
    pub(super) fn changed(&self) -> Option<(f64, f64)> {
        if self.len < CHANGE_WINDOWS + CHANGE_OLDER_WINDOWS {
            return None;
        }
        // newest first
        let (mut newest, mut older) = ([(0.0, 0.0); POOL], [(0.0, 0.0); POOL]);
        let mut ways = (false, false);
        for i in 0..self.len {
            let k = (self.next + POOL - 1 - i) % POOL;
            if i < CHANGE_WINDOWS {
                newest[i] = self.windows[k];
                ways = (ways.0 || self.speeds[k] > 0.0, ways.1 || self.speeds[k] < 0.0);
            } else {
                older[i - CHANGE_WINDOWS] = self.windows[k];
            }
        }
        if ways != (true, true) {
            return None;
        }
        let ((new, new_var), _) = self.pool_of(&newest[..CHANGE_WINDOWS]);
        let ((old, old_var), _) = self.pool_of(&older[..self.len - CHANGE_WINDOWS]);
        let d = (new - old).abs();
        (d > CHANGE_Z * (new_var + old_var).sqrt() && d > CHANGE_SHARE * old.abs()).then_some((new, new_var))
    }

    /// Forgets all but the newest `n` windows (those of a plant that changed, [`WindowPool::changed`]).
    pub(super) fn keep_newest(&mut self, n: usize) {
        let n = n.min(self.len);
        let (mut windows, mut speeds) = ([(0.0, 0.0); POOL], [0.0; POOL]);
        for i in 0..n {
            let k = (self.next + POOL - n + i) % POOL;
            (windows[i], speeds[i]) = (self.windows[k], self.speeds[k]);
        }
        (self.windows, self.speeds, self.len, self.next) = (windows, speeds, n, n % POOL);
        (self.estimate, self.outside) = self.pool();
        self.slope = self.speed_slope();
    }

    fn pool(&self) -> ((f64, f64), bool) {
        self.pool_of(&self.windows[..self.len])
    }

    /// The random-effects mean of windows `w` with the prior as one more study, and whether it lay outside the bounds.
    fn pool_of(&self, w: &[(f64, f64)]) -> ((f64, f64), bool) {
        let (pb, pv) = self.prior;
        // Start from the windows' median (weighed by their claims), so a wild window cannot pull the start.
        let mut order: [(f64, f64); POOL] = [(0.0, 0.0); POOL];
        order[..w.len()].copy_from_slice(w);
        let order = &mut order[..w.len()];
        order.sort_by(|a, b| a.0.total_cmp(&b.0));
        let total: f64 = order.iter().map(|&(_, v)| 1.0 / v).sum();
        let mut acc = 0.0;
        let mut m = order
            .iter()
            .find(|&&(_, v)| {
                acc += 1.0 / v;
                acc >= 0.5 * total
            })
            .map_or(pb, |&(x, _)| x);
        // Then a random-effects mean, iteratively reweighted: Huber weights h from each window's distance to the
        // mean in units of its variance plus the between-window variance τ² (DerSimonian–Laird over the weighted
        // windows), and the prior as one more study.
        let mut tau2 = 0.0;
        let mut honest = 1.0 / pv;
        for _ in 0..6 {
            let h = |x: f64, v: f64, t2: f64| {
                let z = (x - m).abs() / (v + t2).sqrt();
                if z > HUBER_Z { HUBER_Z / z } else { 1.0 }
            };
            let (mut sw, mut swx, mut sw2, mut sh) = (0.0, 0.0, 0.0, 0.0);
            for &(x, v) in w {
                let hw = h(x, v, tau2) / v;
                sw += hw;
                swx += hw * x;
                sw2 += hw * hw;
                sh += h(x, v, tau2);
            }
            if sw > 0.0 && sh > 1.0 {
                let fixed = swx / sw;
                let q: f64 = w.iter().map(|&(x, v)| h(x, v, tau2) * (x - fixed).powi(2) / v).sum();
                tau2 = ((q - (sh - 1.0)) / (sw - sw2 / sw)).max(0.0);
            }
            let mut b = pb / pv;
            let mut info = 1.0 / pv;
            honest = 1.0 / pv;
            for &(x, v) in w {
                let hw = h(x, v, tau2) / (v + tau2);
                info += hw;
                honest += h(x, v, tau2) / (v + self.overlap * tau2);
                b += hw * x;
            }
            m = b / info;
        }
        let [lo, hi] = self.bounds;
        if m < lo || m > hi { ((m.clamp(lo, hi), pv), true) } else { ((m, 1.0 / honest), false) }
    }
}

/// The plant changed ([`WindowPool::changed`]) where the newest this many windows (about 4 s of informative windows
/// at the default 1.5 s, staggered) differ from at least `CHANGE_OLDER_WINDOWS` older ones…
pub(super) const CHANGE_WINDOWS: usize = 5;
const CHANGE_OLDER_WINDOWS: usize = 5;
/// …by this many standard errors of their difference…
const CHANGE_Z: f64 = 4.0;
/// …and by this share of the older value: a change a user would call one (a coupled mass), not a J that wanders. At
/// 3 newest windows, 3 standard errors and no share, the test fired 11–15 times in each six-family set of 96 runs,
/// and the six families lost 34 runs that hold (docs/estimator.md, "Tried and not used").
const CHANGE_SHARE: f64 = 0.25;

/// The windows' B depends on their speed when its slope is this many standard errors from zero.
const SPEED_SLOPE_Z: f64 = 3.0;
/// …and, once it was shown, while it stays this many.
const SPEED_SLOPE_HOLD_Z: f64 = 1.0;
/// …among at least this many windows.
const SPEED_SLOPE_WINDOWS: usize = 5;
/// The windows' J of speed-ups and slow-downs differ by more than this share of J: a load that moves with the
/// acceleration (twice the 5 % to which J must be known to be identified).
const ACCELERATION_J_SHARE: f64 = 0.1;

/// The share of the between-window scatter (measured about the line) added to each window's variance in the
/// slope's weights: a quarter, as the test has weighed it since it came in.
const SCATTER_SHARE: f64 = 0.25;

/// The windows' B against their mean speed, as [`WindowPool::speed_slope`] fits it.
#[derive(Debug, Clone, Copy)]
struct SpeedSlope {
    slope: f64,
    se: f64,
    mean_b: f64,
    mean_abs_speed: f64,
    speed_range: f64,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The windows' B of a fan run (held-out seed 1001 at 5 ms, after 21 windows): speed, B, sd.
    #[allow(clippy::approx_constant)] // measured values (0.318 is a window's B, not 1/π)
    const FAN_WINDOWS: [(f64, f64, f64); 21] = [
        (6.0, 0.098, 0.008),
        (11.0, 0.056, 0.018),
        (0.0, -0.017, 0.114),
        (8.0, 0.090, 0.008),
        (56.0, 0.318, 0.107),
        (27.0, 0.142, 0.033),
        (21.0, 0.042, 0.167),
        (20.0, 0.097, 0.087),
        (11.0, 0.101, 0.018),
        (1.0, 0.087, 0.053),
        (1.0, 0.063, 0.041),
        (16.0, 0.005, 0.032),
        (35.0, 0.131, 0.008),
        (17.0, 0.113, 0.039),
        (31.0, 0.094, 0.040),
        (66.0, 0.261, 0.116),
        (43.0, 0.256, 0.259),
        (68.0, -0.024, 0.358),
        (63.0, 0.228, 0.052),
        (20.0, 0.150, 0.094),
        (14.0, 0.146, 0.125),
    ];

    /// Windows that agree give a B as tight as their own claims; windows that each claim ±0.002 but scatter by
    /// ±0.05 (a load their nuisance did not follow) give their average with a standard deviation as wide as the
    /// scatter says; the prior alone is the prior; a pool full of new windows forgets a wrong start.
    #[test]
    fn the_viscous_pool_is_as_sure_as_the_windows_agree() {
        let mut agree = WindowPool::new(0.12, 0.01, [0.0, 0.5], 1.0);
        assert_eq!(agree.estimate, (0.12, 0.01));
        for i in 0..20 {
            agree.add(0.04 + 0.002 * if i % 2 == 0 { 1.0 } else { -1.0 }, 0.002f64.powi(2), 10.0 + i as f64);
        }
        let (b, var) = agree.estimate;
        assert!((b - 0.04).abs() < 1e-3 && var.sqrt() < 1e-3, "{b} ± {}", var.sqrt());
        let mut scatter = WindowPool::new(0.12, 0.01, [0.0, 0.5], 1.0);
        // the same windows, counted as overlapping by half (J's pool): the same value, √2 less sure
        let mut overlapping = WindowPool::new(0.12, 0.01, [0.0, 0.5], OVERLAP);
        let biases = [0.05, -0.04, 0.03, -0.06, 0.02, -0.03, 0.06, -0.05, 0.04, -0.02];
        for bias in biases.iter().chain(biases.iter()) {
            scatter.add(0.04 + bias, 0.002f64.powi(2), 30.0);
            overlapping.add(0.04 + bias, 0.002f64.powi(2), 30.0);
        }
        let (b, var) = scatter.estimate;
        let sd = var.sqrt();
        assert!((b - 0.04).abs() < 2.0 * sd, "{b} ± {sd}");
        assert!(sd > 0.005, "the scatter (±0.05 over 20 windows) says about ±0.01, got ±{sd}");
        let (b2, var2) = overlapping.estimate;
        assert_eq!(b2, b);
        assert!((var2 / var - 2.0).abs() < 0.05, "{var2} against {var}");
    }

    /// Twenty windows of J 0.08 (±1 %) and then five of 0.24 are a new plant, and the pool keeps the five; five that
    /// lie as far but scatter as far among themselves (0.14–0.34) are not, nor are five only 10 % off, nor five
    /// speed-ups.
    #[test]
    fn a_pool_sees_a_plant_that_changed_and_not_windows_that_scatter() {
        let pool = |newest: &[f64]| {
            let mut p = WindowPool::new(0.09, 0.05f64.powi(2), [0.01, 1.0], OVERLAP);
            for i in 0..20 {
                p.add(0.08 * (1.0 + 0.01 * if i % 2 == 0 { 1.0 } else { -1.0 }), 0.0008f64.powi(2), 1.0);
            }
            for (i, &j) in newest.iter().enumerate() {
                p.add(j, 0.0024f64.powi(2), if i % 2 == 0 { 1.0 } else { -1.0 });
            }
            p
        };
        let mut changed = pool(&[0.24, 0.243, 0.238, 0.241, 0.239]);
        let (j, var) = changed.changed().expect("a new plant");
        assert!((j - 0.24).abs() < 0.005 && var.sqrt() < 0.005, "{j} ± {}", var.sqrt());
        changed.keep_newest(CHANGE_WINDOWS);
        assert!((changed.estimate.0 - 0.24).abs() < 0.005, "{:?}", changed.estimate);
        assert_eq!(pool(&[0.14, 0.34, 0.16, 0.32, 0.24]).changed(), None);
        assert_eq!(pool(&[0.088, 0.087, 0.089, 0.088, 0.088]).changed(), None);
        // seen one way only (five speed-ups): a load that rises with them, not yet an inertia
        let mut one_way = WindowPool::new(0.09, 0.05f64.powi(2), [0.01, 1.0], OVERLAP);
        for i in 0..25 {
            let j = if i < 20 { 0.08 } else { 0.24 };
            one_way.add(j, 0.001f64.powi(2), if i < 20 && i % 2 == 1 { -1.0 } else { 1.0 });
        }
        assert_eq!(one_way.changed(), None);
    }

    /// The windows' B of the fan run ([`FAN_WINDOWS`]): their scatter is
    /// mostly the fan's speed dependence, so measured about the mean it hid the slope (z 2.96, under 3); measured
    /// about the line it shows. Windows of one friction with the same claims and speeds, scattered by their own
    /// noise, show none.
    #[test]
    fn a_speed_dependence_is_not_taken_for_scatter() {
        let pool = |b: &dyn Fn(usize, f64, f64) -> f64| {
            let mut p = WindowPool::new(0.03, 0.01, [0.0, 0.5], 1.0);
            for (i, &(speed, b_w, sd)) in FAN_WINDOWS.iter().enumerate() {
                p.add(b(i, b_w, sd), sd * sd, speed);
            }
            p
        };
        assert!(pool(&|_, b_w, _| b_w).depends_on_speed(false));
        // one friction, 0.04, each window off by up to its own sd (a fixed pattern, no seed)
        let friction = pool(&|i, _, sd| 0.04 + sd * [0.9, -0.6, 0.3, -1.0, 0.5, -0.2, 0.8, -0.7][i % 8]);
        assert!(!friction.depends_on_speed(false));
        assert!(!friction.depends_on_speed(true), "once shown or not, friction shows no speed dependence");
        assert_eq!(friction.speed_hint(), Some(false));
        assert_eq!(pool(&|_, b_w, _| b_w).speed_hint(), Some(true));
    }

    /// No hint favours friction only where a fan would have shown one: windows of one friction (each off by up to its
    /// own sd) at 30–32 rad/s show no hint, yet a fan that made up 0.05 N·m·s/rad there would not have shown one
    /// either, and the odds stay near 1; the same windows spread over 5–60 rad/s favour friction. The fan run's
    /// windows ([`FAN_WINDOWS`]) favour a fan that made up their distance from a nominal of 0.03.
    #[test]
    fn the_windows_favour_friction_only_where_a_fan_would_show() {
        let pattern = [0.9, -0.6, 0.3, -1.0, 0.5, -0.2, 0.8, -0.7];
        let pool = |speed: &dyn Fn(usize) -> f64| {
            let mut p = WindowPool::new(0.04, 0.01, [0.0, 0.5], 1.0);
            for i in 0..16 {
                p.add(0.04 + 0.01 * pattern[i % 8], 0.01f64.powi(2), speed(i));
            }
            p
        };
        let odds = |p: &WindowPool, distance: f64| p.load_odds(distance).expect("windows enough");
        let narrow = pool(&|i| 30.0 + (i % 3) as f64);
        assert_eq!(narrow.speed_hint(), Some(false));
        assert!(odds(&narrow, 0.05) > 0.5, "{}", odds(&narrow, 0.05));
        let wide = pool(&|i| 5.0 + 55.0 * ((i * 5) % 16) as f64 / 15.0);
        assert_eq!(wide.speed_hint(), Some(false));
        assert!(odds(&wide, 0.05) < 1.0 / 3.0, "{}", odds(&wide, 0.05));
        assert_eq!(odds(&wide, 0.0), 1.0, "no distance, nothing to tell");
        let mut fan = WindowPool::new(0.03, 0.01, [0.0, 0.5], 1.0);
        for &(speed, b, sd) in &FAN_WINDOWS {
            fan.add(b, sd * sd, speed);
        }
        let distance = fan.estimate.0 - 0.03;
        eprintln!(
            "odds of a fan: narrow {:.2}, wide {:.3}, the fan run's {:.1}",
            odds(&narrow, 0.05),
            odds(&wide, 0.05),
            odds(&fan, distance)
        );
        assert!(odds(&fan, distance) > 3.0, "{distance}: {}", odds(&fan, distance));
        assert!(WindowPool::new(0.03, 0.01, [0.0, 0.5], 1.0).load_odds(0.05).is_none(), "no windows, no look");
    }

    /// The windows' J against the way the speed went (+1 a speed-up, −1 a slow-down). One inertia, every window off
    /// by up to its own sd: no difference. A load that rises on every speed-up adds 20 % to the speed-ups' J: they
    /// differ. Speed-ups alone, or a single slow-down among them: not seen both ways.
    #[test]
    fn speed_ups_and_slow_downs_must_agree_on_j() {
        let pattern = [0.9, -0.6, 0.3, -1.0, 0.5, -0.2, 0.8, -0.7];
        let pool = |windows: &[(f64, f64, f64)]| {
            let mut p = WindowPool::new(0.08, 1e-3, [0.001, 1.0], OVERLAP);
            for &(j, sd, way) in windows {
                p.add(j, sd * sd, way);
            }
            p
        };
        let inertia: Vec<(f64, f64, f64)> =
            (0..16).map(|i| (0.16 + 0.003 * pattern[i % 8], 0.003, if i % 2 == 0 { 1.0 } else { -1.0 })).collect();
        let one = pool(&inertia);
        assert!(!one.depends_on_direction(false) && !one.depends_on_direction(true));
        assert!(one.seen_both_ways(0.1, 2));
        let timed: Vec<(f64, f64, f64)> =
            inertia.iter().map(|&(j, sd, way)| (if way > 0.0 { 1.2 * j } else { j }, sd, way)).collect();
        assert!(pool(&timed).depends_on_direction(false));
        let ups: Vec<(f64, f64, f64)> = timed.iter().copied().filter(|w| w.2 > 0.0).collect();
        assert!(!pool(&ups).seen_both_ways(0.1, 2));
        let mut downs = ups.clone();
        downs.push((0.16, 0.003, -1.0));
        assert!(!pool(&downs).seen_both_ways(0.1, 2), "one slow-down");
        downs.push((0.161, 0.003, -1.0));
        assert!(pool(&downs).seen_both_ways(0.1, 2), "two slow-downs");
    }

    /// A speed dependence once shown is kept on weaker evidence (`SPEED_SLOPE_HOLD_Z`): the first ten windows of
    /// the fan run above give a slope 1.6 standard errors from zero, not enough to show it, enough to keep it. Without
    /// the hold the verdict flapped as windows left the pool (spare seed 17001, a fan at 1 ms: the load's at 5–25 s,
    /// friction's at 25–40 s with B ×2.9 off and T̂_L 4.4 N·m off, the load's again after).
    #[test]
    fn a_speed_dependence_once_shown_is_kept_on_weaker_evidence() {
        let mut p = WindowPool::new(0.03, 0.01, [0.0, 0.5], 1.0);
        for &(speed, b, sd) in &FAN_WINDOWS[..10] {
            p.add(b, sd * sd, speed);
        }
        assert!(!p.depends_on_speed(false));
        assert!(p.depends_on_speed(true));
        // and it is a hint of one: B does not stand before it is earned (docs/estimator.md, "What stands")
        assert_eq!(p.speed_hint(), Some(true));
        let mut few = WindowPool::new(0.03, 0.01, [0.0, 0.5], 1.0);
        for &(speed, b, sd) in &FAN_WINDOWS[..4] {
            few.add(b, sd * sd, speed);
        }
        assert_eq!(few.speed_hint(), None, "four windows are too few to look");
    }
}

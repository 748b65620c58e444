//! The guard of rls-sgd: adapted J and B stand only as far as the data earn them, judged on data they were not
//! fitted to; what the data say of each (identified, or why not); and what the load looks like.
//!
//! **Validation (prequential), [`Validation`].** Before the RLS learns from a window, `rls_sgd.rs` scores the window
//! under two hypotheses fixed before it (the nominal J and B, and the adapted ones), each with its own best load
//! nuisance, and hands the two residual sums of squares here. A sign test over about [`REMEMBERED_WINDOWS`]
//! windows (a log ratio within [`TIE`] of 0 is a tie) gives a z: the adapted parameters stand from the start, leave
//! force below [`LEAVE_Z`] (the nominal predicts better) and come back above [`ENTER_Z`]. A sign test, because a
//! window whose load the nuisance did not follow can be far off either way, and favours the larger J.
//!
//! **Identification, [`Identification`].** Each of J and B is identified, or not with its reason; `rls_sgd.rs`
//! decides which (from the validation, the parameter's standard deviation, and whether the load follows the speed)
//! and which adapted values stand.
//!
//! **The load's character, [`Character`].** 0.1 s block means of the adapted tracker's T̂_L, the reported T̂_L,
//! ω and the shaft angle (integrated from ω) over the last [`HORIZON_S`]. An adapted T̂_L that a function of the
//! speed explains (R² of `1, ω, ω·|ω|` at least [`FOLLOWS_SPEED_R2`]) is a load following the speed (what the
//! adapted B did not take). Otherwise the reported T̂_L is steady, periodic in time or in shaft angle (an
//! autocorrelation peak after the first zero crossing that recurs at twice its lag, on a time or on an angle grid),
//! stepping (a few increments carry most of its movement), or random. It describes, and decides one thing: where
//! the windows cannot tell a fan from friction, a load that follows the speed in its levels and in its block-to-block
//! changes ([`Character::follows_speed`]) is a fan's (`RlsSgd::fan_favoured`).

use serde::Serialize;

/// A window whose log ratio of residuals is within this of 0 is a tie.
const TIE: f64 = 0.02;
/// Forgetting of the window scores: about this many windows remembered (each 0.75 s at the default window).
const REMEMBERED_WINDOWS: f64 = 30.0;
/// The adapted parameters stand from the start; they leave force when the sign test says the nominal predicts better
/// (z below `LEAVE_Z`, after at least `MIN_WINDOWS` decisive windows), and come back above `ENTER_Z`.
const ENTER_Z: f64 = 1.0;
const LEAVE_Z: f64 = -2.0;
const MIN_WINDOWS: f64 = 4.0;
/// Character: block length (s), horizon (s), classification interval (blocks), least span to classify (blocks).
const CHAR_BLOCK_S: f64 = 0.1;
const HORIZON_S: f64 = 20.0;
const CLASSIFY_EVERY: usize = 25;
const MIN_CHAR_BLOCKS: usize = 80;
/// The adapted tracker's T̂_L follows the speed when a function of ω explains this share of its variance, and moves by
/// at least `FOLLOWS_SPEED_NM` (sd) with it.
const FOLLOWS_SPEED_R2: f64 = 0.6;
const FOLLOWS_SPEED_NM: f64 = 1.0;
/// …and its block-to-block changes follow the speed's when those of ω and ω·|ω| explain this share of theirs: two
/// slow drifts (a brake program, a speed program) line up by chance over a horizon of 20 s, their changes do not. On
/// plants of three times the reference's B the levels alone read a correct B's load as following the speed for
/// 7.5 s at a time (R² 0.6–0.7 on the levels, at most 0.28 on the changes); a fan with Coulomb friction gave 0.6–0.9.
const CHANGES_FOLLOW_SPEED_R2: f64 = 0.5;
/// Below this sd (N·m) the load is steady.
const STEADY_NM: f64 = 0.5;
/// An autocorrelation peak at least this high (after the first zero crossing) is a period.
const PERIODIC_PEAK: f64 = 0.5;
/// The largest tenth of the increments carries at least this share of the movement: stepping.
const STEPPING_SHARE: f64 = 0.6;

/// What the data say of one parameter (J or B).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Identification {
    /// Adapted, predicting better than the nominal on held-out data, and known to its stated standard deviation.
    Identified,
    /// Not yet: the data have not excited it enough (its standard deviation is wide).
    TooLittleExcitation,
    /// The adapted value does not predict the speed better than the nominal one: the nominal stands.
    NominalPredictsAsWell,
    /// The load follows the speed, so its speed-dependent part cannot be told from friction: the nominal stands.
    LoadFollowsSpeed,
    /// B (the torque proportional to the speed) differs from the model's beyond its uncertainty: friction that
    /// changed, or a load proportional to the speed, which no data of speed and drive torque tell apart. The
    /// adapted value (their sum) may stand; it is not called friction.
    FrictionOrLoad,
    /// Not estimated: the model's value (kalman, paper-literal).
    FromModel,
    /// J's windows differ between speed-ups and slow-downs: a load that moves with the acceleration, which cannot be
    /// told from inertia; B comes from the same windows. The adapted value may stand; it is not called the inertia.
    LoadMovesWithAcceleration,
}

impl Identification {
    /// The code in recordings and metrics: 1 identified, 0 too little excitation, −1 the nominal predicts as well,
    /// −2 not separable from the load, −3 the model's value, −4 friction or a load proportional to the speed, −5 a
    /// load that moves with the acceleration.
    pub fn code(self) -> f64 {
        match self {
            Identification::Identified => 1.0,
            Identification::TooLittleExcitation => 0.0,
            Identification::NominalPredictsAsWell => -1.0,
            Identification::LoadFollowsSpeed => -2.0,
            Identification::FromModel => -3.0,
            Identification::FrictionOrLoad => -4.0,
            Identification::LoadMovesWithAcceleration => -5.0,
        }
    }

    /// Known to its stated standard deviation: identified, or (B) identified as the sum of friction and a load
    /// proportional to the speed.
    pub fn known(self) -> bool {
        matches!(self, Identification::Identified | Identification::FrictionOrLoad)
    }

    pub const ALL: [Identification; 7] = [
        Identification::Identified,
        Identification::TooLittleExcitation,
        Identification::NominalPredictsAsWell,
        Identification::LoadFollowsSpeed,
        Identification::FromModel,
        Identification::FrictionOrLoad,
        Identification::LoadMovesWithAcceleration,
    ];

    /// The identification of a code (recordings); `FromModel` for anything else.
    pub fn from_code(code: f64) -> Identification {
        Identification::ALL.into_iter().find(|c| c.code() == code).unwrap_or(Identification::FromModel)
    }

    /// The name in JSON and metric labels.
    pub fn name(self) -> &'static str {
        match self {
            Identification::Identified => "identified",
            Identification::TooLittleExcitation => "too_little_excitation",
            Identification::NominalPredictsAsWell => "nominal_predicts_as_well",
            Identification::LoadFollowsSpeed => "load_follows_speed",
            Identification::FromModel => "from_model",
            Identification::FrictionOrLoad => "friction_or_load",
            Identification::LoadMovesWithAcceleration => "load_moves_with_acceleration",
        }
    }

    /// A plant engineer's sentence.
    pub fn reason(self) -> &'static str {
        match self {
            Identification::Identified => "identified",
            Identification::TooLittleExcitation => "not identified yet: too little excitation (setpoint changes)",
            Identification::NominalPredictsAsWell => {
                "not identified: the adapted value predicts no better than the nominal, which stands"
            }
            Identification::LoadFollowsSpeed => {
                "not identified: the load follows the speed, and its speed-dependent part cannot be told from friction"
            }
            Identification::FromModel => "not estimated: the model's value",
            Identification::FrictionOrLoad => {
                "not identified: differs from the model's, and friction cannot be told from a load proportional to \
                 the speed; the value is their sum"
            }
            Identification::LoadMovesWithAcceleration => {
                "not identified: the load changes with the acceleration (speed-ups and slow-downs give different \
                 inertias), which cannot be told from inertia"
            }
        }
    }
}

/// One parameter's identification as `/api/status` shows it: the state's name and a plant engineer's reason.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Verdict {
    pub state: &'static str,
    pub reason: &'static str,
}

/// What an estimate's codes say, in words: J's and B's identification and the load's character.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Identified {
    pub inertia: Verdict,
    pub viscous: Verdict,
    pub load_character: &'static str,
}

impl Identified {
    pub fn of(e: &super::Estimate) -> Identified {
        let verdict = |code: f64| {
            let i = Identification::from_code(code);
            Verdict { state: i.name(), reason: i.reason() }
        };
        Identified {
            inertia: verdict(e.inertia_identified),
            viscous: verdict(e.viscous_identified),
            load_character: LoadCharacter::from_code(e.load_character).name(),
        }
    }
}

/// What the load looks like over the last 20 s.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum LoadCharacter {
    /// Too little data yet (or not estimated).
    Unknown,
    Steady,
    Stepping,
    PeriodicInTime,
    PeriodicInShaftAngle,
    FollowingTheSpeed,
    Random,
}

impl LoadCharacter {
    /// The code in recordings and metrics: 0 unknown, 1 steady, 2 stepping, 3 periodic in time, 4 periodic in shaft
    /// angle, 5 following the speed, 6 random.
    pub fn code(self) -> f64 {
        match self {
            LoadCharacter::Unknown => 0.0,
            LoadCharacter::Steady => 1.0,
            LoadCharacter::Stepping => 2.0,
            LoadCharacter::PeriodicInTime => 3.0,
            LoadCharacter::PeriodicInShaftAngle => 4.0,
            LoadCharacter::FollowingTheSpeed => 5.0,
            LoadCharacter::Random => 6.0,
        }
    }

    pub const ALL: [LoadCharacter; 7] = [
        LoadCharacter::Unknown,
        LoadCharacter::Steady,
        LoadCharacter::Stepping,
        LoadCharacter::PeriodicInTime,
        LoadCharacter::PeriodicInShaftAngle,
        LoadCharacter::FollowingTheSpeed,
        LoadCharacter::Random,
    ];

    /// The name in JSON and metric labels.
    pub fn name(self) -> &'static str {
        match self {
            LoadCharacter::Unknown => "unknown",
            LoadCharacter::Steady => "steady",
            LoadCharacter::Stepping => "stepping",
            LoadCharacter::PeriodicInTime => "periodic_in_time",
            LoadCharacter::PeriodicInShaftAngle => "periodic_in_shaft_angle",
            LoadCharacter::FollowingTheSpeed => "following_the_speed",
            LoadCharacter::Random => "random",
        }
    }

    /// The character of a code (recordings), `Unknown` for anything else.
    pub fn from_code(code: f64) -> LoadCharacter {
        LoadCharacter::ALL.into_iter().find(|c| c.code() == code).unwrap_or(LoadCharacter::Unknown)
    }
}

/// The prequential comparison of the adapted against the nominal parameters (module doc): scores of the windows,
/// each computed before the window was learnt from.
#[derive(Debug, Clone)]
pub(crate) struct Validation {
    /// Forgotten sums: decisive windows, and wins minus losses of the adapted parameters.
    sums: [f64; 2],
    pub in_force: bool,
}

impl Default for Validation {
    fn default() -> Self {
        Validation { sums: [0.0; 2], in_force: true }
    }
}

impl Validation {
    /// A window's residual sums of squares under the nominal and the adapted parameters (each with its own best
    /// load nuisance), and what noise alone would leave.
    pub fn score(&mut self, nominal_rss: f64, adapted_rss: f64, noise_rss: f64) {
        if !(nominal_rss.is_finite() && adapted_rss.is_finite() && noise_rss > 0.0) {
            return;
        }
        let d = (nominal_rss.max(noise_rss) / adapted_rss.max(noise_rss)).ln();
        // a sign test: a window the nuisance followed badly can be far off either way, so only who won counts
        let won: f64 = if d > TIE {
            1.0
        } else if d < -TIE {
            -1.0
        } else {
            0.0
        };
        let keep = 1.0 - 1.0 / REMEMBERED_WINDOWS;
        self.sums = [keep * self.sums[0] + won.abs(), keep * self.sums[1] + won];
        let z = self.z();
        self.in_force = if self.in_force {
            self.sums[0] < MIN_WINDOWS || z > LEAVE_Z
        } else {
            self.sums[0] >= MIN_WINDOWS && z > ENTER_Z
        };
    }

    /// Wins minus losses of the adapted parameters over the standard error of a fair coin's (0 before any).
    pub fn z(&self) -> f64 {
        let [decisive, net] = self.sums;
        if decisive < 1.0 { 0.0 } else { net / decisive.sqrt() }
    }
}

/// How many learnt windows [`Drift`] remembers (two staggered sequences of 1.5 s windows: about 15 s).
const DRIFT_WINDOWS: usize = 20;

/// The adapted J and B after each of the last [`DRIFT_WINDOWS`] learnt windows. An estimate that moved by Δ over
/// that horizon is not known better than Δ/2 (one sd: its 2-sd interval holds the values it had), whatever the
/// RLS's covariance says: a load its nuisance follows only roughly (random, impacts) moves J and B from window to
/// window by more than the windows' own fits claim. The standard deviations that decide *identified* and that are
/// reported are at least this; the values that stand are not changed by it.
#[derive(Debug, Clone, Default)]
pub(crate) struct Drift {
    values: [(f64, f64); DRIFT_WINDOWS],
    len: usize,
    next: usize,
}

impl Drift {
    pub fn push(&mut self, j: f64, b: f64) {
        self.values[self.next] = (j, b);
        self.next = (self.next + 1) % DRIFT_WINDOWS;
        self.len = (self.len + 1).min(DRIFT_WINDOWS);
    }

    /// Half the largest distance of a remembered (J, B) from `(j, b)`, per parameter.
    pub fn sd_floor(&self, j: f64, b: f64) -> (f64, f64) {
        self.values[..self.len]
            .iter()
            .fold((0.0, 0.0), |(dj, db), &(x, y)| (dj.max(0.5 * (x - j).abs()), db.max(0.5 * (y - b).abs())))
    }
}

/// One 0.1 s block of the character's horizon.
#[derive(Debug, Clone, Copy, Default)]
struct CharBlock {
    /// The adapted tracker's T̂_L: what of the load follows the speed beyond the adapted B.
    tracked_load: f64,
    load: f64,
    omega: f64,
    angle: f64,
}

/// The load's character over the horizon (module doc).
#[derive(Debug, Clone)]
pub(crate) struct Character {
    blocks: std::collections::VecDeque<CharBlock>,
    sum: CharBlock,
    count: u32,
    span: f64,
    angle: f64,
    since: usize,
    follows_speed: bool,
    /// The block-to-block changes of the adapted tracker's T̂_L follow those of the speed (`CHANGES_FOLLOW_SPEED_R2`).
    changes_follow_speed: bool,
    pub character: LoadCharacter,
}

impl Default for Character {
    fn default() -> Self {
        Character {
            blocks: std::collections::VecDeque::with_capacity(blocks_kept() + 1),
            sum: CharBlock::default(),
            count: 0,
            span: 0.0,
            angle: 0.0,
            since: 0,
            follows_speed: false,
            changes_follow_speed: false,
            character: LoadCharacter::Unknown,
        }
    }
}

fn blocks_kept() -> usize {
    (HORIZON_S / CHAR_BLOCK_S).round() as usize
}

impl Character {
    /// One sample: Δt, the adapted tracker's and the reported T̂_L, and ω̂; re-classifies every
    /// [`CLASSIFY_EVERY`] blocks.
    pub fn push(&mut self, dt: f64, tracked_load: f64, load: f64, omega: f64) {
        self.angle += omega * dt;
        self.sum.tracked_load += tracked_load;
        self.sum.load += load;
        self.sum.omega += omega;
        self.count += 1;
        self.span += dt;
        if self.span < CHAR_BLOCK_S - 1e-9 {
            return;
        }
        let n = f64::from(self.count);
        let s = self.sum;
        self.blocks.push_back(CharBlock {
            tracked_load: s.tracked_load / n,
            load: s.load / n,
            omega: s.omega / n,
            angle: self.angle,
        });
        if self.blocks.len() > blocks_kept() {
            self.blocks.pop_front();
        }
        (self.sum, self.count, self.span) = (CharBlock::default(), 0, 0.0);
        self.since += 1;
        if self.since < CLASSIFY_EVERY || self.blocks.len() < MIN_CHAR_BLOCKS {
            return;
        }
        self.since = 0;
        self.classify();
    }

    /// Whether the adapted tracker's T̂_L follows the speed both in its levels (the character) and in its changes: a
    /// speed dependence left beside the adapted B, not two drifts that line up by chance.
    pub fn follows_speed(&self) -> bool {
        self.character == LoadCharacter::FollowingTheSpeed && self.changes_follow_speed
    }

    fn classify(&mut self) {
        let b: Vec<CharBlock> = self.blocks.iter().copied().collect();
        let tracked: Vec<f64> = b.iter().map(|x| x.tracked_load).collect();
        let speed: Vec<[f64; 3]> = b.iter().map(|x| [1.0, x.omega, x.omega * x.omega.abs()]).collect();
        let (r2, explained_sd) = explained(&tracked, &speed);
        self.follows_speed = r2 >= FOLLOWS_SPEED_R2 && explained_sd >= FOLLOWS_SPEED_NM;
        // only where the levels follow the speed: the changes are asked nothing else
        self.changes_follow_speed = self.follows_speed && {
            let changes: Vec<f64> = tracked.windows(2).map(|p| p[1] - p[0]).collect();
            let speed_changes: Vec<[f64; 3]> =
                speed.windows(2).map(|p| [1.0, p[1][1] - p[0][1], p[1][2] - p[0][2]]).collect();
            explained(&changes, &speed_changes).0 >= CHANGES_FOLLOW_SPEED_R2
        };
        let load: Vec<f64> = b.iter().map(|x| x.load).collect();
        let mean = load.iter().sum::<f64>() / load.len() as f64;
        let sd = (load.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / load.len() as f64).sqrt();
        self.character = if self.follows_speed {
            LoadCharacter::FollowingTheSpeed
        } else if sd < STEADY_NM {
            LoadCharacter::Steady
        } else {
            let in_time = periodic_peak(&load);
            let monotone =
                b.windows(2).all(|w| w[1].angle >= w[0].angle) || b.windows(2).all(|w| w[1].angle <= w[0].angle);
            let in_angle = if monotone { periodic_peak(&on_angle_grid(&b)) } else { 0.0 };
            if in_time.max(in_angle) >= PERIODIC_PEAK {
                if in_angle > in_time { LoadCharacter::PeriodicInShaftAngle } else { LoadCharacter::PeriodicInTime }
            } else if stepping_share(&load) >= STEPPING_SHARE {
                LoadCharacter::Stepping
            } else {
                LoadCharacter::Random
            }
        };
    }
}

/// R² of a least-squares fit of `y` on three regressors, and the standard deviation of the fitted part.
fn explained(y: &[f64], x: &[[f64; 3]]) -> (f64, f64) {
    let mut a = nalgebra::Matrix3::<f64>::zeros();
    let mut r = nalgebra::Vector3::<f64>::zeros();
    for (row, &v) in x.iter().zip(y) {
        let c = nalgebra::Vector3::from(*row);
        a += c * c.transpose();
        r += c * v;
    }
    let n = y.len().max(1) as f64;
    let mean = y.iter().sum::<f64>() / n;
    let total: f64 = y.iter().map(|v| (v - mean).powi(2)).sum();
    // scaled for conditioning: ω·|ω| is thousands
    let scale = nalgebra::Vector3::from_fn(|i, _| a[(i, i)].sqrt().max(1e-12));
    let d = nalgebra::Matrix3::from_diagonal(&scale.map(|s| 1.0 / s));
    let Some(coef) = (d * a * d + nalgebra::Matrix3::identity() * 1e-9).cholesky().map(|c| d * c.solve(&(d * r)))
    else {
        return (0.0, 0.0);
    };
    let fitted: Vec<f64> = x.iter().map(|row| nalgebra::Vector3::from(*row).dot(&coef)).collect();
    let residual: f64 = fitted.iter().zip(y).map(|(f, v)| (v - f).powi(2)).sum();
    let fmean = fitted.iter().sum::<f64>() / n;
    let fsd = (fitted.iter().map(|f| (f - fmean).powi(2)).sum::<f64>() / n).sqrt();
    if total <= 0.0 { (0.0, 0.0) } else { (1.0 - residual / total, fsd) }
}

/// How periodic `x` is: the autocorrelation (mean removed) at its highest peak after the first zero crossing, where
/// the peak recurs at twice its lag (at least `PERIODIC_PEAK / 2` there); 0 where there is no such peak. A random
/// step signal has chance peaks, but they do not recur.
fn periodic_peak(x: &[f64]) -> f64 {
    let n = x.len();
    let mean = x.iter().sum::<f64>() / n.max(1) as f64;
    let c: Vec<f64> = x.iter().map(|v| v - mean).collect();
    // sums of squares of every prefix: each lag's two energies without a pass of their own
    let mut energy = vec![0.0; n + 1];
    for (i, v) in c.iter().enumerate() {
        energy[i + 1] = energy[i] + v * v;
    }
    let r: Vec<f64> = (0..n * 2 / 3)
        .map(|lag| {
            let xy: f64 = c[..n - lag].iter().zip(&c[lag..]).map(|(a, b)| a * b).sum();
            let (xx, yy) = (energy[n - lag], energy[n] - energy[lag]);
            if xx > 0.0 && yy > 0.0 { xy / (xx * yy).sqrt() } else { 0.0 }
        })
        .collect();
    let Some(first_negative) = r.iter().position(|&v| v < 0.0) else { return 0.0 };
    (first_negative..r.len() / 2)
        .filter(|&lag| r[lag] >= r[lag - 1] && r[lag] >= r[lag + 1] && r[2 * lag] >= 0.5 * PERIODIC_PEAK)
        .map(|lag| r[lag])
        .fold(0.0, f64::max)
}

/// The blocks' load resampled on a uniform grid of shaft angle (as many points as blocks), by linear interpolation.
fn on_angle_grid(b: &[CharBlock]) -> Vec<f64> {
    let (Some(first), Some(last)) = (b.first(), b.last()) else { return Vec::new() };
    let (a0, a1) = (first.angle, last.angle);
    let n = b.len();
    let mut out = Vec::with_capacity(n);
    let mut k = 0;
    let up = a1 >= a0;
    for i in 0..n {
        let a = a0 + (a1 - a0) * i as f64 / (n - 1).max(1) as f64;
        while k + 2 < n && if up { b[k + 1].angle < a } else { b[k + 1].angle > a } {
            k += 1;
        }
        let (p, q) = (b[k], b[(k + 1).min(n - 1)]);
        let span = q.angle - p.angle;
        let x = if span.abs() > 1e-12 { ((a - p.angle) / span).clamp(0.0, 1.0) } else { 0.0 };
        out.push(p.load + (q.load - p.load) * x);
    }
    out
}

/// The share of the total movement Σ|Δx| that the largest tenth of the increments carry.
fn stepping_share(x: &[f64]) -> f64 {
    let mut d: Vec<f64> = x.windows(2).map(|w| (w[1] - w[0]).abs()).collect();
    let total: f64 = d.iter().sum();
    if total <= 0.0 {
        return 0.0;
    }
    // the largest tenth in front, in no order (no sort: this runs every 2.5 s on every drive)
    let top = d.len().div_ceil(10);
    d.select_nth_unstable_by(top - 1, |a, b| b.total_cmp(a));
    d[..top].iter().sum::<f64>() / total
}

#[cfg(test)]
mod tests {
    use super::*;

    fn classify(load: impl Fn(f64, f64, f64) -> f64, omega: impl Fn(f64) -> f64) -> Character {
        let mut c = Character::default();
        let dt = 0.01;
        let mut angle = 0.0;
        for k in 0..3000 {
            let t = k as f64 * dt;
            let w = omega(t);
            angle += w * dt;
            let l = load(t, w, angle);
            c.push(dt, l, l, w);
        }
        c
    }

    /// Speed program: steps between levels every 2.7 s.
    fn program(t: f64) -> f64 {
        [20.0, 45.0, 30.0, 60.0, 10.0, 50.0][(t / 2.7) as usize % 6]
    }

    #[test]
    fn the_character_of_typical_loads() {
        let fan = classify(|_, w, _| 12.0 * (w / 60.0).powi(2), program);
        assert_eq!(fan.character, LoadCharacter::FollowingTheSpeed);
        assert!(fan.follows_speed && fan.follows_speed(), "in its levels and in its changes");
        let steady = classify(|_, _, _| 8.0, program);
        assert_eq!(steady.character, LoadCharacter::Steady);
        // levels that never repeat in a pattern (a repeating brake program would be periodic, and is reported so)
        let level = |k: u64| (k.wrapping_mul(0x9e37_79b9_7f4a_7c15) >> 40) as f64 / (1u64 << 24) as f64 * 25.0;
        let brake = classify(|t, _, _| level((t / 1.9) as u64), program);
        assert_eq!(brake.character, LoadCharacter::Stepping);
        assert!(!brake.follows_speed());
        // a load that drifts while the speed ramps: its levels line up with the speed, its changes say nothing
        let drift = classify(|t, _, _| 5.0 + 0.2 * t, |t| 10.0 + 1.5 * t);
        assert_eq!(drift.character, LoadCharacter::FollowingTheSpeed);
        assert!(!drift.follows_speed());
        let sine = classify(|t, _, _| 10.0 + 4.0 * (t * std::f64::consts::TAU / 3.3).sin(), program);
        assert_eq!(sine.character, LoadCharacter::PeriodicInTime);
        let gear = classify(|_, _, a| 10.0 + 4.0 * (0.3 * a).sin(), program);
        assert_eq!(gear.character, LoadCharacter::PeriodicInShaftAngle);
    }

    /// An estimate that moved from 0.10 to 0.08 over the remembered windows is not known better than ±0.01; one
    /// that held still is not floored at all; the oldest window leaves.
    #[test]
    fn an_estimate_is_not_surer_than_it_moved_lately() {
        let mut d = Drift::default();
        assert_eq!(d.sd_floor(0.08, 0.04), (0.0, 0.0));
        for k in 0..=DRIFT_WINDOWS {
            d.push(0.10 - 0.02 * k as f64 / DRIFT_WINDOWS as f64, 0.04);
        }
        let (dj, db) = d.sd_floor(0.08, 0.04);
        assert!((dj - 0.5 * 0.02 * (DRIFT_WINDOWS - 1) as f64 / DRIFT_WINDOWS as f64).abs() < 1e-12, "{dj}");
        assert_eq!(db, 0.0);
        for _ in 0..DRIFT_WINDOWS {
            d.push(0.08, 0.04);
        }
        assert_eq!(d.sd_floor(0.08, 0.04), (0.0, 0.0));
    }

    #[test]
    fn adapted_parameters_come_into_force_only_when_they_predict_better() {
        let run = |scores: &[(f64, f64)]| {
            let mut v = Validation::default();
            for &(n, a) in scores.iter().cycle().take(60) {
                v.score(n, a, 100.0);
            }
            v.in_force
        };
        assert!(run(&[(300.0, 120.0), (150.0, 110.0), (105.0, 101.0), (2000.0, 2100.0)]));
        // (nominal, adapted): the adapted loses four windows of five
        assert!(!run(&[(300.0, 120.0), (110.0, 150.0), (101.0, 105.0), (2000.0, 2100.0), (500.0, 900.0)]));
        assert!(run(&[(100.0, 100.0)]), "no evidence: the adapted parameters stand");
    }
}

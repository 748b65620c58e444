//! PURE analysis: where a nominal model and a recording disagree, which catalogue effect was left out, its fit, and
//! the proof (validation error on data never used for fitting). `report` renders the result at the edge.
//!
//! Pipeline (PHYSICS.md §3): extract the signals ([`series`]) → fit J, B ([`search::fit_mechanics`]) → free-run the
//! baseline ([`predict`]) → locate mismatch windows ([`mismatch`]) → greedy forward selection over the catalogue
//! (`select`), each candidate fitted on the fitting segment and kept only when it lowers the validation error by a
//! clear margin and BIC agrees (`validate`: the out-of-fold free runs and the intervals) → ambiguities and
//! explanations (`explain`) → the improved model, with each finding's evidence and the residuals (`evidence`). The
//! result's types are in `result`, re-exported here.

mod evidence;
mod explain;
pub mod mismatch;
pub mod predict;
pub mod report;
mod result;
pub mod search;
mod select;
pub mod series;
pub mod signal;
mod validate;

use std::collections::BTreeMap;

use crate::BadInput;
use crate::plant::PlantModel;
use crate::recording::Recording;

pub use explain::slip_as_leakage;
pub use mismatch::Mismatch;
pub use predict::Errors;
pub use result::{
    Ambiguity, Analysis, CandidateScore, Evidence, Finding, Gaps, Interval, Misfit, NotIdentified, Summary, Traces,
};
pub use series::{Family, Series};

use evidence::{finding, noise_floors, residual_signals, timing_variance, traces};
use explain::{ambiguities, explain, not_identified};
use search::Scored;
use select::{Kept, Selection, fit_baseline, interval_keys, search_start};
use validate::jackknife;

/// The recording columns the analysis reads (besides `t_s`); `analyze` holds only these in memory.
pub const RECORDING_COLUMNS: [&str; 8] =
    ["f_set_hz", "f_drive_hz", "p_in_bar", "p_out_bar", "omega_rad_s", "theta_rad", "load_nm", "torque_nm"];

/// The most rows `analyze` reads (all files together). It holds about 320 bytes a row at its peak (300 001 rows of
/// `simulate` with two effects to name: 96 MB resident), so 10 million rows (2.8 hours at a 1 ms poll) take about
/// 3.2 GB. More is refused as it is read, before it fills the memory.
pub const MAX_ROWS: usize = 10_000_000;

/// Settings of an analysis; the defaults are the documented method.
#[derive(Debug, Clone, Copy)]
pub struct Options {
    /// Fraction of the recording, at its end, kept for validation (never used for fitting).
    pub validation_fraction: f64,
    /// The free-run parameter search uses at most this much of the fitting segment (s); the final fit is confirmed
    /// on the whole recording.
    pub search_window_s: f64,
    /// An effect is kept only if the validation error (root of the mean squared NRMSE) drops by at least this
    /// fraction…
    pub min_relative_drop: f64,
    /// …and BIC on the fitting segment improves by at least this much.
    pub min_delta_bic: f64,
    /// Two candidates whose validation gains are within this fraction of each other are reported as ambiguous.
    pub tie_fraction: f64,
    /// Blocks of the cross-validation (hydraulic family; also the jackknife of the confidence intervals). 0 or 1:
    /// the fixed validation tail decides, as for the other families.
    pub folds: usize,
    /// An effect that acts in one operating regime (Stribeck friction: |ω| < 2 ω_s) may be validated on the
    /// out-of-fold rows of that regime when the recording holds at least this much of it (s).
    pub regime_min_s: f64,
    /// Per round, at most this many candidates (those passing the BIC margin, largest ΔBIC first) are
    /// cross-validated.
    pub max_cross_validated: usize,
    /// Entrained air is named only when the fitted effective bulk modulus is at most this fraction of the model's:
    /// closer, it is the oil's own variation with temperature and pressure, or the recording's timing.
    pub air_max_modulus_ratio: f64,
    /// Internal leakage (or motor slip, as the leakage it equals) is named only when the added leakage is at least
    /// this fraction of the model's own: less is the oil's viscosity moving with its temperature.
    pub leak_min_ratio: f64,
    /// …and never below this share of the motor's mean flow at the recording's mean ΔP: a displacement off by as
    /// much, well inside a unit's tolerance (and taken as given here), moves the flow balance as far. It decides
    /// when the model's own leakage is small or zero.
    pub leak_min_flow_share: f64,
    /// A fitted B more than this factor from the model's is implausible as friction: with a dry-friction term left
    /// out, the viscous term takes its torque (2 N·m over 2–19 rad/s looks like 0.2·ω). A dry-friction candidate
    /// that brings B back within the factor is kept when it improves BIC and the out-of-fold error at all.
    pub viscous_plausible_factor: f64,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            validation_fraction: 0.3,
            search_window_s: 60.0,
            min_relative_drop: 0.10,
            min_delta_bic: 10.0,
            tie_fraction: 0.9,
            folds: 4,
            regime_min_s: 5.0,
            max_cross_validated: 3,
            air_max_modulus_ratio: 0.8,
            leak_min_ratio: 0.2,
            leak_min_flow_share: 0.003,
            viscous_plausible_factor: 2.0,
        }
    }
}

/// The parameters of a model the analysis fits, under their contract names.
pub fn parameters(m: &PlantModel) -> BTreeMap<String, f64> {
    let mut p = BTreeMap::new();
    p.insert("inertia_kg_m2".to_string(), m.motor.inertia_kg_m2);
    p.insert("viscous_nm_s_rad".to_string(), m.motor.viscous_nm_s_rad);
    for id in m.effects.active_ids() {
        for (k, v) in effect_parameters(m, id) {
            p.insert(format!("{id}.{k}"), v);
        }
    }
    p
}

/// One effect's parameters under the catalogue's names.
pub fn effect_parameters(m: &PlantModel, id: &str) -> BTreeMap<String, f64> {
    let e = &m.effects;
    let pairs: Vec<(&str, f64)> = match id {
        "coulomb_friction" => e.coulomb_friction.map(|x| vec![("torque_nm", x.torque_nm)]),
        "stribeck_friction" => {
            e.stribeck_friction.map(|x| vec![("breakaway_nm", x.breakaway_nm), ("speed_rad_s", x.speed_rad_s)])
        }
        "torque_offset" => e.torque_offset.map(|x| vec![("torque_nm", x.torque_nm)]),
        "internal_leakage" => e.internal_leakage.map(|x| vec![("l_min_per_bar", x.l_min_per_bar)]),
        "dead_time" => e.dead_time.map(|x| vec![("ms", x.ms)]),
        "entrained_air" => e.entrained_air.map(|x| vec![("bulk_modulus_bar", x.bulk_modulus_bar)]),
        "motor_slip" => e.motor_slip.map(|x| vec![("rpm_per_nm", x.rpm_per_nm)]),
        _ => None,
    }
    .unwrap_or_default();
    pairs.into_iter().map(|(k, v)| (k.to_string(), v)).collect()
}

/// Analyses a recording against a nominal model. `progress` gets the fraction done (0…1).
pub fn analyze(
    rec: &Recording,
    nominal: &PlantModel,
    opts: &Options,
    progress: &mut dyn FnMut(f64),
) -> Result<Analysis, BadInput> {
    progress(0.0);
    let s = Series::extract(rec, nominal, opts.validation_fraction)?;
    analyze_series(s, Origin::of(rec), nominal, opts, progress)
}

/// As [`analyze`], the recording given up once the analysis has its series: its columns are not held beside them
/// (a long recording's are a quarter of the memory).
pub fn analyze_owned(
    rec: Recording,
    nominal: &PlantModel,
    opts: &Options,
    progress: &mut dyn FnMut(f64),
) -> Result<Analysis, BadInput> {
    progress(0.0);
    let s = Series::extract(&rec, nominal, opts.validation_fraction)?;
    let origin = Origin::of(&rec);
    drop(rec);
    analyze_series(s, origin, nominal, opts, progress)
}

/// What the analysis reports of the recording itself, beside its series.
struct Origin {
    source: String,
    out_of_range: Vec<crate::recording::OutOfRange>,
}

impl Origin {
    fn of(rec: &Recording) -> Origin {
        Origin { source: rec.source.clone(), out_of_range: rec.out_of_range.clone() }
    }
}

/// The pipeline on the extracted signals: baseline, forward selection, intervals, and what the report shows.
fn analyze_series(
    s: Series,
    rec: Origin,
    nominal: &PlantModel,
    opts: &Options,
    progress: &mut dyn FnMut(f64),
) -> Result<Analysis, BadInput> {
    let family = s.family;
    within_any_plant(nominal, &s)?;
    let (start, nominal_terms) = search_start(nominal);
    inertia_told_from_zero(&s, nominal_terms, &rec.source)?;
    long_enough_to_fit(&s, &rec.source)?;
    let baseline = fit_baseline(&start, nominal_terms, &s, &rec.source)?;
    progress(0.05);

    let mut sel = Selection::new(&s, nominal, opts, (&start, nominal_terms), &baseline);
    let total_rounds = sel.remaining.len().max(1);
    for round in 1..=total_rounds {
        if !sel.round(round, progress)? {
            break;
        }
    }
    let model_misfit = misfit(&sel.current, &s, nominal);
    if model_misfit.is_some() {
        sel.name_nothing(&baseline);
    }
    sel.final_fold_models();
    let baseline_intervals =
        jackknife(&baseline.model, &sel.fold_baseline, &interval_keys(&baseline.model, family, &sel.kept), s.sample_hz);
    let improved_intervals = jackknife(
        &sel.current.model,
        &sel.fold_current,
        &interval_keys(&sel.current.model, family, &sel.kept),
        s.sample_hz,
    );
    progress(0.95);

    let conditions = mismatch::Conditions::new(&s);
    let mismatches = mismatches(&s, &conditions, &baseline);
    let unexplained = unexplained(&s, &conditions, &sel.current);
    let findings = findings(&sel.kept, &sel.current, &improved_intervals, &s, &conditions);
    let named: Vec<&str> = sel.kept.iter().map(|k| k.id).collect();
    let ambiguities = ambiguities(&named, &sel.ties, &sel.current.model, &s);
    let not_identified = not_identified(&s);

    let traces = traces(&baseline, &sel.current, &s);
    progress(1.0);
    let validation_rule = validation_rule(opts, sel.cv, sel.n_folds);
    let interval_method = interval_method(sel.n_folds);
    let mut base_summary = summary(&baseline, &s);
    base_summary.cross_validation_score = sel.cv_baseline;
    base_summary.confidence_intervals = baseline_intervals;
    let mut improved_summary = summary(&sel.current, &s);
    improved_summary.cross_validation_score = if sel.cv { sel.cv_before } else { None };
    improved_summary.confidence_intervals = improved_intervals;
    let Selection { current, candidates, .. } = sel;
    Ok(Analysis {
        recording: rec.source.clone(),
        samples: s.len(),
        validation_from_s: s.t_s[s.split],
        family: family.name(),
        speed_source: s.speed_source,
        load: s.load,
        baseline: base_summary,
        mismatches,
        findings,
        model_misfit,
        ambiguities,
        not_identified,
        improved: improved_summary,
        unexplained,
        out_of_range: rec.out_of_range.clone(),
        outliers: s.outliers.clone(),
        gaps: gaps(&s),
        validation_rule,
        interval_method,
        candidates,
        improved_model: with_nominal_load(current.model, nominal),
        traces,
    })
}

/// Refuses a recording whose fitting segment does not tell the inertia from zero (the least-squares J within
/// [`INERTIA_FROM_ZERO_SD`] of its standard deviations of 0, [`search::inertia_with_sd`]): it does not excite the
/// plant (a run at rest, a steady speed). Fitted to anyway, J came out a tenth of the truth or less and a finding was
/// named from noise, or the fit failed (J ≤ 0) and the command refused: which of the two depended on the noise's
/// seed. With the load unknown J is not fitted (the nominal's stands), and nothing is checked.
///
/// The refusal says which of three things it saw, for they need different repairs: a J significantly below zero is
/// a speed that falls where the drive torque accelerates it, a sign or a wiring (a negated speed gave J = −0.0762 ±
/// 0.0010, swapped `p_in_bar`/`p_out_bar` −0.079 ± 0.001, on runs whose J is 0.08: both were said to be "a speed
/// that hardly changes"); a speed whose noise is as large as its movement (σ 50 rad/s added to a 4 s run) hides the
/// acceleration; only otherwise does the speed hardly change.
fn inertia_told_from_zero(s: &Series, terms: search::MechTerms, source: &str) -> Result<(), BadInput> {
    if s.family == Family::Flow {
        return Ok(());
    }
    let Some((j, sd)) = search::inertia_with_sd(s, terms) else { return Ok(()) };
    if j > INERTIA_FROM_ZERO_SD * sd {
        return Ok(());
    }
    let head = format!("recording {source}: inertia and viscous friction cannot be fitted");
    if j < -INERTIA_FROM_ZERO_SD * sd {
        let torque =
            if s.family == Family::Torque { "`torque_nm`" } else { "the pressures (`p_in_bar` − `p_out_bar`)" };
        return Err(BadInput(format!(
            "{head}: the fitting segment gives a significantly negative inertia (J = {j:.3e} ± {sd:.1e} kg·m²): the \
             speed falls where the drive torque accelerates it. A sign or wiring error: is the speed (`{}`) negated, \
             or {torque} swapped or negated?",
            s.speed_source
        )));
    }
    let (noise, spread) = speed_noise_and_spread(s);
    if noise >= NOISE_AS_LARGE_AS_MOVEMENT * spread {
        return Err(BadInput(format!(
            "{head}: the fitting segment does not tell the inertia from zero (J = {j:.3e} ± {sd:.1e} kg·m²): the \
             speed's noise (σ ≈ {noise:.3} rad/s) is as large as its movement (a spread of {spread:.3} rad/s), so \
             its acceleration cannot be read; check the speed sensor and its column (`{}`)",
            s.speed_source
        )));
    }
    Err(BadInput(format!(
        "{head}: the fitting segment does not tell the inertia from zero (J = {j:.3e} ± {sd:.1e} kg·m²): the speed \
         hardly changes (it needs accelerations and several speeds)"
    )))
}

/// The speed sensor's noise is called as large as the movement from this fraction of the filtered speed's spread:
/// the reference plant's tachogenerator (σ 0.8 rad/s) against its test-stand run (a spread of about 17 rad/s) is 0.05.
const NOISE_AS_LARGE_AS_MOVEMENT: f64 = 0.5;

/// The speed's white noise σ (robust, from what the low-pass removed, scaled for the pass band) and the standard
/// deviation of the filtered speed over the fitting segment (rad/s).
fn speed_noise_and_spread(s: &Series) -> (f64, f64) {
    let fit = 0..s.split;
    let d: Vec<f64> = s.omega_rad_s[fit.clone()]
        .iter()
        .zip(&s.omega_f[fit.clone()])
        .map(|(w, f)| (w - f).abs())
        .filter(|d| d.is_finite())
        .collect();
    let passed = (2.0 * s.cutoff_hz / s.sample_hz).clamp(0.0, 0.9);
    let noise = 1.4826 * series::percentile(&d, 0.5) / (1.0 - passed).sqrt();
    let w: Vec<f64> = s.omega_f[fit].iter().copied().filter(|w| w.is_finite()).collect();
    let mean = w.iter().sum::<f64>() / w.len().max(1) as f64;
    let spread = (w.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / w.len().max(1) as f64).sqrt();
    (noise, spread)
}

/// Refuses a recording whose fitting segment moves for less than [`MIN_MOVING_PERIODS`] periods of the speed's
/// low-pass on the rows the torque balance reads: within a shorter stretch the speed and its acceleration move
/// together (one ramp from rest), J and B trade, and the blocks of the jackknife all see the same stretch, so the
/// interval is as narrow as it is wrong. A 2 s run of the reference plant (at rest for its first second; 0.2 s of
/// usable rows) gave B = 0.104 with a 95 % interval of 0.092…0.116 (truth 0.04) on seed 5, B = 0.000 on seeds 2
/// and 4. With the load unknown J and B are not fitted, and nothing is checked.
fn long_enough_to_fit(s: &Series, source: &str) -> Result<(), BadInput> {
    if s.family == Family::Flow {
        return Ok(());
    }
    let moving_s = search::moving_balance_s(s);
    let needed_s = MIN_MOVING_PERIODS / s.cutoff_hz;
    if moving_s >= needed_s {
        return Ok(());
    }
    Err(BadInput(format!(
        "recording {source}: inertia and viscous friction cannot be fitted: too short: its fitting segment (up to \
         t = {:.2} s) moves for {moving_s:.2} s of rows the torque balance can use, and it needs at least \
         {needed_s:.2} s ({MIN_MOVING_PERIODS} periods of the speed's {} Hz low-pass); record longer, with \
         accelerations and several speeds",
        s.t_s[s.split.min(s.len() - 1)],
        s.cutoff_hz
    )))
}

/// Periods of the speed's low-pass the fitting segment must move for (1 s at the tachogenerator's 10 Hz).
const MIN_MOVING_PERIODS: f64 = 10.0;

/// How many standard deviations from zero the fitting segment must put J.
const INERTIA_FROM_ZERO_SD: f64 = 3.0;

/// Refuses a nominal model whose free run on the recording's inputs leaves any physical range
/// ([`crate::plant::simulate::PHYSICAL_LIMITS`]), as `simulate` refuses it: a model of absurd magnitudes (a pump of
/// 1e9 cm³, a back pressure of 1e9 bar) was analysed to a speed error of 2.5e9 and a finding at the edge of its
/// search, and its `--model-out` was a model `simulate` refused.
fn within_any_plant(nominal: &PlantModel, s: &Series) -> Result<(), BadInput> {
    let p = predict::predict(nominal, s, s.len())?;
    let (max_speed, max_bar) = crate::plant::simulate::PHYSICAL_LIMITS;
    // the flow family does not predict the speed (NaN throughout)
    let speed = (s.family != Family::Flow).then_some(("speed (rad/s)", &p.omega_rad_s, max_speed));
    let signals = speed.into_iter().chain(p.dp_bar.as_ref().map(|dp| ("p_in − p_out (bar)", dp, max_bar)));
    for (what, values, max) in signals {
        if let Some(k) = values.iter().position(|v| v.is_nan() || v.abs() > max) {
            return Err(BadInput(format!(
                "model: its free run on the recording's inputs left any physical range at t = {} s ({what} = \
                 {:e}): the model's magnitudes (torques, displacements, pressures) are beyond any plant; check their \
                 values and units",
                crate::units::shown(s.t_s[k]),
                values[k]
            )));
        }
    }
    Ok(())
}

/// A judged signal's free run is taken as not describing the recording at all beyond this NRMSE on the validation
/// segment, where a model that fits leaves about 1 at most (its error is the sensor's noise, and so is the spread of
/// a segment at one steady speed: 0.88 on the last 1.2 s of a 4 s run of the reference plant)…
const MISFIT_VALIDATION_NRMSE: f64 = 1.5;
/// …and, over the whole recording, where the signal moves well beyond its noise, beyond this: no better than the
/// recording's own mean.
const MISFIT_WHOLE_NRMSE: f64 = 1.0;

/// Whether the model, as the search leaves it, describes the recording at all: a judged signal (speed and ΔP; the
/// torque for a torque-driven recording; ΔP and the drive frequency with the load unknown) whose free run is worse
/// than the recording's own mean on the validation segment ([`MISFIT_VALIDATION_NRMSE`]) and over the whole
/// recording ([`MISFIT_WHOLE_NRMSE`]) is a model of another plant, or a column in another unit. An effect fitted to
/// such a model is whatever bends it nearest the recording: a speed column in rpm got a Stribeck friction at
/// 433 rad/s (a zero-width interval; speed NRMSE 2.21 before, 2.22 after), a bulk modulus of 1e-300 bar one at
/// 723 rad/s (3.03 after). Such an effect says nothing of the plant, so nothing is named.
fn misfit(m: &Scored, s: &Series, nominal: &PlantModel) -> Option<Misfit> {
    let whole = predict::errors(&m.prediction, s, 0, s.len());
    let (v, w) = (&m.validation, &whole);
    let judged: Vec<(&'static str, Option<f64>, Option<f64>)> = match s.family {
        Family::Hydraulic => vec![("omega", Some(v.omega_nrmse), Some(w.omega_nrmse)), ("dp", v.dp_nrmse, w.dp_nrmse)],
        Family::Torque => vec![("torque", v.torque_nrmse, w.torque_nrmse)],
        Family::Flow => vec![("dp", v.dp_nrmse, w.dp_nrmse), ("f_drive", v.f_drive_nrmse, w.f_drive_nrmse)],
    };
    let (signal, held, all) = judged
        .into_iter()
        .filter_map(|(name, h, a)| Some((name, h?, a?)))
        .filter(|(_, h, a)| *h > MISFIT_VALIDATION_NRMSE && *a > MISFIT_WHOLE_NRMSE)
        .max_by(|a, b| a.1.total_cmp(&b.1))?;
    let mut explanation = format!(
        "the model does not describe this recording: even fitted, its free run misses {signal} by an NRMSE of \
         {held:.2} on the validation segment and {all:.2} over the whole recording, worse than the recording's own \
         mean; no effect is named, for any would only bend a model of another plant towards it. Check the columns' \
         units and scales (speed in rad/s, not rpm; pressures in bar; torque in N·m) and the model's values"
    );
    if s.family != Family::Flow {
        let off = |fitted: f64, model: f64| model > 0.0 && !(1.0 / 3.0..=3.0).contains(&(fitted / model));
        let (j, b) = (m.model.motor.inertia_kg_m2, m.model.motor.viscous_nm_s_rad);
        let (j0, b0) = (nominal.motor.inertia_kg_m2, nominal.motor.viscous_nm_s_rad);
        if off(j, j0) || off(b, b0) {
            explanation += &format!(
                "; the fit puts J at {j:.3e} kg·m² and B at {b:.3e} N·m·s/rad against the model's {j0} and {b0} \
                 (×{:.2} and ×{:.2}), what a speed or a torque in another unit does",
                j / j0,
                if b0 > 0.0 { b / b0 } else { f64::NAN }
            );
        }
    }
    Some(Misfit { signal, validation_nrmse: held, whole_recording_nrmse: all, explanation })
}

/// The baseline's mismatch windows: the largest `MAX_MISMATCHES` by RMS, in time order.
fn mismatches(s: &Series, conditions: &mismatch::Conditions, baseline: &Scored) -> Vec<Mismatch> {
    let residuals = residual_signals(baseline, s);
    let mut mismatches: Vec<Mismatch> =
        residuals.iter().flat_map(|(name, r)| mismatch::locate(s, conditions, name, r)).collect();
    mismatches.sort_by(|a, b| b.rms.total_cmp(&a.rms));
    mismatches.truncate(mismatch::MAX_MISMATCHES);
    mismatches.sort_by(|a, b| a.t_start_s.total_cmp(&b.t_start_s));
    mismatches
}

/// Where the improved model's residual still exceeds the noise floor, the largest share first.
fn unexplained(s: &Series, conditions: &mismatch::Conditions, improved: &Scored) -> Vec<mismatch::Unexplained> {
    let floors = noise_floors(s, improved);
    let timing = timing_variance(s, improved);
    let mut unexplained: Vec<mismatch::Unexplained> = residual_signals(improved, s)
        .iter()
        .filter_map(|(name, r)| floors.iter().find(|f| f.0 == *name).map(|f| (name, r, f.1)))
        .flat_map(|(name, r, floor)| {
            let timing = (*name == "f_drive").then_some(timing.as_deref()).flatten();
            mismatch::unexplained(s, conditions, name, r, floor, timing)
        })
        .collect();
    unexplained.sort_by(|a, b| b.share.total_cmp(&a.share));
    unexplained
}

/// A finding per kept effect, its values and intervals those of the improved model.
fn findings(
    kept: &[Kept],
    improved: &Scored,
    intervals: &BTreeMap<String, Interval>,
    s: &Series,
    conditions: &mismatch::Conditions,
) -> Vec<Finding> {
    let family = s.family;
    kept.iter()
        .map(|k| {
            let mut f = finding(k.id, &k.before, &k.after, k.delta_bic, s, conditions);
            // the torque-balance terms are refitted with every effect named after them: a finding reports its
            // values in the improved model (as `improved.parameters` and the fitted TOML), with their intervals
            f.parameters = effect_parameters(&improved.model, k.id);
            let (b, a) = (k.before.validation.score(family), k.after.validation.score(family));
            f.explanation = explain(k.id, &improved.model, s, b, a);
            f.evidence.cross_validation_score_before = k.cv_before;
            f.evidence.cross_validation_score_after = k.cv_after;
            f.evidence.validated_on = k.validated_on.clone();
            let prefix = format!("{}.", k.id);
            f.confidence_intervals = intervals
                .iter()
                .filter_map(|(key, v)| key.strip_prefix(&prefix).map(|p| (p.to_string(), *v)))
                .collect();
            f
        })
        .collect()
}

/// How effects were validated, in words, with the figures of `opts`.
fn validation_rule(opts: &Options, cv: bool, n_folds: usize) -> String {
    if cv {
        format!(
            "blocked cross-validation: {n_folds} blocks, each run free from its measured state with the model fitted \
             on the other blocks; an effect is kept when BIC on the fitting segment improves by ≥ {} and the \
             out-of-fold error drops by ≥ {:.0} % overall, or on the rows of the regime where it acts (Stribeck \
             friction: |ω| < 2 ω_s, at least {} s of them) while the overall out-of-fold error also drops",
            opts.min_delta_bic,
            100.0 * opts.min_relative_drop,
            opts.regime_min_s
        )
    } else {
        format!(
            "validation segment: an effect is kept when BIC on the fitting segment improves by ≥ {} and the error \
             on the last {:.0} % drops by ≥ {:.0} %",
            opts.min_delta_bic,
            100.0 * opts.validation_fraction,
            100.0 * opts.min_relative_drop
        )
    }
}

/// How the confidence intervals were computed, in words.
fn interval_method(n_folds: usize) -> String {
    if n_folds == 0 {
        "none (recording too short for the blocks)".to_string()
    } else {
        format!(
            "delete-one-block jackknife over the {n_folds} cross-validation blocks (each fold refits every named \
             effect), 95 %, Student t with folds − 1 degrees of freedom, centred on the reported value"
        )
    }
}

/// The recording's gaps in time: how many, and the longest with the `t_s` it follows.
fn gaps(s: &Series) -> Gaps {
    let longest =
        s.restarts.iter().map(|&k| (s.t_s[k] - s.t_s[k - 1], s.t_s[k - 1])).max_by(|a, b| a.0.total_cmp(&b.0));
    Gaps { count: s.restarts.len(), longest_s: longest.map(|l| l.0), after_t_s: longest.map(|l| l.1) }
}

fn summary(sc: &Scored, s: &Series) -> Summary {
    Summary {
        parameters: parameters(&sc.model),
        validation: sc.validation,
        whole_recording: predict::errors(&sc.prediction, s, 0, s.len()),
        cross_validation_score: None,
        confidence_intervals: BTreeMap::new(),
    }
}

/// The fitted model keeps the nominal model's `[load]` so that `sim`/`simulate` run it as the user set it up.
fn with_nominal_load(mut m: PlantModel, nominal: &PlantModel) -> PlantModel {
    m.load = nominal.load.clone();
    m
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plant::effects::{DeadTime, StribeckFriction};

    fn noiseless(mut m: PlantModel) -> PlantModel {
        m.sensors.pressure_noise_bar = 0.0;
        m.sensors.speed_noise_rad_s = 0.0;
        m.sensors.load_noise_nm = 0.0;
        m
    }

    /// The analysis's free run (1 ms RK4, dead time split inside the sample) reproduces the simulator (0.2 ms).
    #[test]
    fn free_run_matches_the_simulator_on_noiseless_data() {
        let mut m = noiseless(PlantModel::reference());
        m.effects.dead_time = Some(DeadTime { ms: 12.4 });
        m.effects.stribeck_friction = Some(StribeckFriction { breakaway_nm: 1.0, speed_rad_s: 2.0 });
        let rec = crate::recording::simulated::test_stand(&m, 30.0, 1, &mut |_| {}).expect("simulable");
        let s = Series::extract(&rec, &m, 0.3).expect("signals");
        let p = predict::predict(&m, &s, s.len()).expect("prediction");
        let e = predict::errors(&p, &s, 0, s.len());
        assert!(e.omega_nrmse < 2e-3, "{e:?}");
        assert!(e.dp_nrmse.is_some_and(|v| v < 2e-3), "{e:?}");
    }

    #[test]
    fn missing_speed_and_missing_model_sections_are_named() {
        let rec = Recording::from_columns(
            "r.csv",
            vec!["t_s".into(), "torque_nm".into()],
            vec![(0..300).map(|k| k as f64 * 1e-3).collect(), vec![1.0; 300]],
        );
        let m = PlantModel::reference();
        let err = analyze(&rec, &m, &Options::default(), &mut |_| {}).expect_err("no speed");
        assert!(err.0.contains("omega_rad_s") && err.0.contains("theta_rad"), "{}", err.0);
        let rec = Recording::from_columns(
            "r.csv",
            vec!["t_s".into(), "p_in_bar".into(), "p_out_bar".into(), "f_set_hz".into(), "omega_rad_s".into()],
            vec![
                (0..300).map(|k| k as f64 * 1e-3).collect(),
                vec![1.0; 300],
                vec![1.0; 300],
                vec![1.0; 300],
                vec![1.0; 300],
            ],
        );
        let torque_only = PlantModel::parse(
            "[motor]\ninertia_kg_m2 = 1.0\nviscous_nm_s_rad = 1.0\n[load]\nkind = \"none\"\n",
            "m.toml",
        )
        .expect("valid");
        let err = analyze(&rec, &torque_only, &Options::default(), &mut |_| {}).expect_err("no hydraulics");
        assert!(err.0.contains("[drive]"), "{}", err.0);
    }
}

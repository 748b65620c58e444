//! PURE analysis: where a nominal model and a recording disagree, which catalogue effect was left out, its fit, and
//! the proof (validation error on data never used for fitting). `report` renders the result at the edge.
//!
//! Pipeline (PHYSICS.md §3): extract the signals ([`series`]) → fit J, B ([`search::fit_mechanics`]) → free-run the
//! baseline ([`predict`]) → locate mismatch windows ([`mismatch`]) → greedy forward selection over the catalogue,
//! each candidate fitted on the fitting segment and kept only when it lowers the validation error by a clear margin
//! and BIC agrees → ambiguities → the improved model.

mod explain;
pub mod mismatch;
pub mod predict;
pub mod report;
mod result;
pub mod search;
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
    Ambiguity, Analysis, CandidateScore, Evidence, Finding, Gaps, Interval, NotIdentified, Summary, Traces,
};
pub use series::{Family, Series};

use explain::{ambiguities, explain, not_identified};
use search::{MechTerms, Rows, Scored};
use validate::{CrossValidated, cross_validate, jackknife, out_of_fold_score};

/// The recording columns the analysis reads (besides `t_s`); `analyze` holds only these in memory.
pub const RECORDING_COLUMNS: [&str; 8] =
    ["f_set_hz", "f_drive_hz", "p_in_bar", "p_out_bar", "omega_rad_s", "theta_rad", "load_nm", "torque_nm"];

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
    let (start, nominal_terms) = search_start(nominal);
    let baseline = fit_baseline(&start, nominal_terms, &s, &rec.source)?;
    progress(0.05);

    let mut sel = Selection::new(&s, nominal, opts, (&start, nominal_terms), &baseline);
    let total_rounds = sel.remaining.len().max(1);
    for round in 1..=total_rounds {
        if !sel.round(round, progress)? {
            break;
        }
    }
    sel.final_fold_models();
    let baseline_intervals =
        jackknife(&baseline.model, &sel.fold_baseline, &interval_keys(&baseline.model, family, &sel.kept));
    let improved_intervals =
        jackknife(&sel.current.model, &sel.fold_current, &interval_keys(&sel.current.model, family, &sel.kept));
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

/// Where the search starts: the nominal model (its effects are part of it: the search adds to them) with the load
/// taken from the recording, and the torque-balance terms it already has.
fn search_start(nominal: &PlantModel) -> (PlantModel, MechTerms) {
    let mut start = nominal.clone();
    let nominal_terms = MechTerms {
        coulomb: start.effects.coulomb_friction.is_some(),
        offset: start.effects.torque_offset.is_some(),
        stribeck: start.effects.stribeck_friction.is_some(),
    };
    start.load = crate::plant::LoadSpec::Recorded;
    (start, nominal_terms)
}

/// The baseline: the start model with J and B fitted on the fitting segment (with the load unknown the torque
/// balance is not fitted: J and B keep the nominal values), scored on the whole recording.
fn fit_baseline(start: &PlantModel, nominal_terms: MechTerms, s: &Series, source: &str) -> Result<Scored, BadInput> {
    let base_model = if s.family == Family::Flow {
        start.clone()
    } else {
        search::fit_mechanics(start, s, nominal_terms).ok_or_else(|| {
            BadInput(format!(
                "recording {}: inertia and viscous friction cannot be fitted: the speed hardly changes on the \
                 fitting segment (it needs accelerations and several speeds)",
                source
            ))
        })?
    };
    Scored::evaluate(base_model, nominal_terms, s)
}

/// The greedy forward selection over the catalogue: the model so far and its fold models, what was kept and why,
/// and what is left to try.
struct Selection<'a> {
    s: &'a Series,
    nominal: &'a PlantModel,
    opts: &'a Options,
    /// The rows of the fitting segment the free-run parameter search uses.
    std_rows: Rows,
    /// The sample count BIC is taken over.
    n_bic: f64,
    /// Blocked cross-validation: the recording cut into `n_folds` blocks; fold k fits on the others and runs block
    /// k free from its measured state. The fold models are chained like the selection (each fold keeps the
    /// effects kept so far, fitted on its own rows), and give the jackknife intervals.
    n_folds: usize,
    folds: Vec<Rows>,
    /// Whether the out-of-fold score decides (hydraulic family with folds), rather than the validation tail.
    cv: bool,
    fold_baseline: Vec<Option<(PlantModel, MechTerms)>>,
    fold_current: Vec<Option<(PlantModel, MechTerms)>>,
    /// The out-of-fold score of the baseline, and of the model so far.
    cv_baseline: Option<f64>,
    cv_before: Option<f64>,
    current: Scored,
    remaining: Vec<&'static str>,
    kept: Vec<Kept>,
    candidates: Vec<CandidateScore>,
    /// Candidates whose gain came within `tie_fraction` of a kept one's: (kept, other).
    ties: Vec<(&'static str, &'static str)>,
}

impl<'a> Selection<'a> {
    /// The search's rows and blocks, the baseline fitted on every fold, and the catalogue effects the nominal model
    /// lacks.
    fn new(
        s: &'a Series,
        nominal: &'a PlantModel,
        opts: &'a Options,
        (start, nominal_terms): (&PlantModel, MechTerms),
        baseline: &Scored,
    ) -> Selection<'a> {
        let family = s.family;
        let search_end = s.split.min((opts.search_window_s * s.sample_hz) as usize).max(100);
        let std_rows = Rows::standard(s, search_end);
        let n_bic = s.split as f64 / 10.0;
        let n_folds = if opts.folds >= 2 && s.len() >= 200 * opts.folds { opts.folds } else { 0 };
        let folds: Vec<Rows> = (0..n_folds).map(|k| Rows::fold(s, k, n_folds, search_end)).collect();
        let cv = family == Family::Hydraulic && !folds.is_empty();
        let fold_baseline: Vec<Option<(PlantModel, MechTerms)>> = folds
            .iter()
            .map(|r| {
                if family == Family::Flow {
                    Some((start.clone(), nominal_terms))
                } else {
                    search::fit_mechanics_on(start, s, nominal_terms, &r.ls).map(|m| (m, nominal_terms))
                }
            })
            .collect();
        let fold_current = fold_baseline.clone();
        let cv_before = if cv { out_of_fold_score(&fold_current, &folds, s) } else { None };
        let remaining: Vec<&'static str> =
            search::applicable(s).into_iter().filter(|id| !nominal.effects.active_ids().contains(id)).collect();
        Selection {
            s,
            nominal,
            opts,
            std_rows,
            n_bic,
            n_folds,
            folds,
            cv,
            fold_baseline,
            fold_current,
            cv_baseline: cv_before,
            cv_before,
            current: baseline.clone(),
            remaining,
            kept: Vec::new(),
            candidates: Vec::new(),
            ties: Vec::new(),
        }
    }

    /// One round: every remaining candidate tried, the best that passes the rule kept, else a pair that passes
    /// together. False when the search is over.
    fn round(&mut self, round: usize, progress: &mut dyn FnMut(f64)) -> Result<bool, BadInput> {
        let mut tried = self.try_remaining(round, progress);
        if self.cv {
            self.cross_validate_best(&mut tried);
        }
        let accept = self.accepted(&tried);
        self.record(round, &tried, accept);
        match accept {
            Some(i) => self.keep_winner(&tried, i),
            None => self.keep_pair(&tried),
        }
    }

    /// Each remaining candidate fitted on the standard rows on top of the current model, with its ΔBIC.
    fn try_remaining(&self, round: usize, progress: &mut dyn FnMut(f64)) -> Vec<Tried> {
        let (s, current, family) = (self.s, &self.current, self.s.family);
        let mut tried: Vec<Tried> = Vec::new();
        for (i, &id) in self.remaining.iter().enumerate() {
            let scored = search::candidate(id, &current.model, current.terms, s, &self.std_rows, None)
                .and_then(|(m, terms)| Scored::evaluate(m, terms, s).ok())
                .map(Scored::without_prediction)
                .map(|sc| {
                    let db = search::delta_bic(
                        current.fit.score(family),
                        sc.fit.score(family),
                        search::parameter_count(id),
                        self.n_bic,
                    );
                    (sc, db)
                });
            tried.push(Tried { id, scored, cv: None });
            // round r fills the r-th half of what is left: monotonic without knowing how many rounds there will be
            let (start, end) = (1.0 - 0.5f64.powi(round as i32 - 1), 1.0 - 0.5f64.powi(round as i32));
            let within = (i + 1) as f64 / self.remaining.len() as f64;
            progress(0.05 + 0.9 * (start + (end - start) * within));
        }
        tried
    }

    /// Cross-validates the candidates that pass the BIC margin, the largest ΔBIC first (at most
    /// `max_cross_validated` a round: the cost of the folds stays bounded).
    fn cross_validate_best(&self, tried: &mut [Tried]) {
        let opts = self.opts;
        let mut order: Vec<usize> =
            (0..tried.len()).filter(|&i| tried[i].scored.as_ref().is_some_and(|x| x.1 >= opts.min_delta_bic)).collect();
        order.sort_by(|&a, &b| {
            let db = |i: usize| tried[i].scored.as_ref().map_or(f64::NEG_INFINITY, |x| x.1);
            db(b).total_cmp(&db(a))
        });
        for &i in order.iter().take(opts.max_cross_validated) {
            if let Some((sc, _)) = &tried[i].scored {
                tried[i].cv = cross_validate(tried[i].id, sc, &self.fold_current, &self.folds, self.s, opts);
            }
        }
    }

    /// The score a candidate is ranked by: out of fold under cross-validation, else on the validation segment.
    fn rank(&self, t: &Tried) -> Option<f64> {
        if self.cv {
            t.cv.as_ref().map(|c| c.score)
        } else {
            t.scored.as_ref().map(|x| x.0.validation.score(self.s.family))
        }
    }

    /// Whether a candidate passes the rule: the BIC margin, resolved by the recording, and the error down by
    /// `min_relative_drop` (overall, on its regime, or at all when it brings B back within reason).
    fn passes(&self, t: &Tried) -> bool {
        let (s, opts, family) = (self.s, self.opts, self.s.family);
        let current = &self.current;
        let Some((sc, db)) = &t.scored else { return false };
        if *db < opts.min_delta_bic {
            return false;
        }
        if !resolved(t.id, &sc.model, &current.model, s, opts) {
            return false;
        }
        let restores_b = restores_viscous(t.id, &sc.model, &current.model, self.nominal, opts);
        if self.cv {
            let (Some(c), Some(b)) = (&t.cv, self.cv_before) else { return false };
            let drop = 1.0 - (c.score / b).sqrt();
            drop >= opts.min_relative_drop
                || (c.score < b && c.regime.as_ref().is_some_and(|r| r.drop >= opts.min_relative_drop))
                || (c.score < b && restores_b)
        } else {
            let before = current.validation.score(family);
            let after = t.scored.as_ref().map_or(f64::INFINITY, |x| x.0.validation.score(family));
            1.0 - (after / before).sqrt() >= opts.min_relative_drop || (after < before && restores_b)
        }
    }

    /// The candidate this round keeps, if one passes the rule alone.
    fn accepted(&self, tried: &[Tried]) -> Option<usize> {
        let lowest = tried.iter().filter_map(|t| self.rank(t)).fold(f64::INFINITY, f64::min);
        if self.cv {
            // among the candidates that pass, the lowest out-of-fold score (within 0.5 %: the first in catalogue
            // order)
            let low =
                tried.iter().filter(|t| self.passes(t)).filter_map(|t| self.rank(t)).fold(f64::INFINITY, f64::min);
            tried.iter().position(|t| self.passes(t) && self.rank(t).is_some_and(|r| r <= low * 1.005))
        } else {
            // Among candidates indistinguishable in score (within 0.5 %), the first in catalogue order, so that
            // exactly equivalent effects (leakage and slip) are named the same way every time.
            tried
                .iter()
                .position(|t| self.rank(t).is_some_and(|r| r <= lowest * 1.005))
                .filter(|&i| self.passes(&tried[i]))
        }
    }

    /// The round's candidates into the report's list, `accept` marked kept.
    fn record(&mut self, round: usize, tried: &[Tried], accept: Option<usize>) {
        let family = self.s.family;
        for (i, t) in tried.iter().enumerate() {
            self.candidates.push(CandidateScore {
                round,
                effect: t.id.to_string(),
                validation_score: t.scored.as_ref().map(|x| x.0.validation.score(family)),
                delta_bic: t.scored.as_ref().map(|x| x.1),
                cross_validation_score: t.cv.as_ref().map(|c| c.score),
                regime_drop: t.cv.as_ref().and_then(|c| c.regime.as_ref().map(|r| r.drop)),
                kept: accept == Some(i),
            });
        }
    }

    /// No effect earns its place alone: two that do together, each adding to the other (an effect that shows once
    /// another is modelled: a dead time behind a dry friction the viscous term had taken). False when there is no
    /// such pair, or nothing is left to try.
    fn keep_pair(&mut self, tried: &[Tried]) -> Result<bool, BadInput> {
        let (s, family, n_folds) = (self.s, self.s.family, self.n_folds);
        let pair = if self.cv {
            joint_pair(tried, &self.current, self.cv_before, &self.folds, s, &self.std_rows, self.opts, self.n_bic)
        } else {
            None
        };
        let Some(p) = pair else { return Ok(false) };
        let (a, b) = (&tried[p.first], &tried[p.second]);
        let (Some((first, first_db)), Some(first_cv)) = (a.scored.clone(), a.cv.as_ref()) else { return Ok(false) };
        let first = Scored::evaluate(first.model, first.terms, s)?;
        let pair_sc = Scored::evaluate(p.scored.model, p.scored.terms, s)?;
        for c in self.candidates.iter_mut().rev().take(tried.len()) {
            c.kept |= c.effect == a.id || c.effect == b.id;
        }
        let jointly = |other: &str| format!("jointly with {other}: out-of-fold free runs of all {n_folds} blocks");
        self.kept.push(Kept {
            id: a.id,
            before: self.current.clone(),
            after: first.clone(),
            delta_bic: first_db,
            cv_before: self.cv_before,
            cv_after: Some(first_cv.score),
            validated_on: jointly(b.id),
        });
        self.kept.push(Kept {
            id: b.id,
            before: first.clone(),
            after: pair_sc.clone(),
            delta_bic: search::delta_bic(
                first.fit.score(family),
                pair_sc.fit.score(family),
                search::parameter_count(b.id),
                self.n_bic,
            ),
            cv_before: Some(first_cv.score),
            cv_after: Some(p.cv.score),
            validated_on: jointly(a.id),
        });
        self.fold_current = p.cv.models;
        self.cv_before = Some(p.cv.score);
        self.current = pair_sc;
        if self.refit_named()? {
            self.cv_before = out_of_fold_score(&self.fold_current, &self.folds, s);
        }
        let (ia, ib) = (a.id, b.id);
        self.remaining.retain(|r| *r != ia && *r != ib);
        Ok(!self.remaining.is_empty())
    }

    /// Keeps candidate `i` of the round: the evidence for it, its model and fold models, and the candidates that
    /// tie with it. False when nothing is left to try.
    fn keep_winner(&mut self, tried: &[Tried], i: usize) -> Result<bool, BadInput> {
        let s = self.s;
        let winner = &tried[i];
        let Some((sc, db)) = winner.scored.clone() else { return Ok(false) };
        // the winner's prediction again (candidates keep only their errors): the findings need it
        let sc = Scored::evaluate(sc.model, sc.terms, s)?;
        let id = winner.id;
        self.note_ties(tried, winner);
        let cv_after = winner.cv.as_ref().map(|c| c.score);
        let validated_on = self.validated_on(winner);
        self.kept.push(Kept {
            id,
            before: self.current.clone(),
            after: sc.clone(),
            delta_bic: db,
            cv_before: self.cv_before,
            cv_after,
            validated_on,
        });
        if let Some(c) = &winner.cv {
            self.fold_current = c.models.clone();
            self.cv_before = Some(c.score);
        }
        self.current = sc;
        if self.refit_named()? && self.cv {
            self.cv_before = out_of_fold_score(&self.fold_current, &self.folds, s);
        }
        self.remaining.retain(|r| *r != id);
        Ok(!self.remaining.is_empty())
    }

    /// The candidates whose gain over the current model comes within `tie_fraction` of the winner's.
    fn note_ties(&mut self, tried: &[Tried], winner: &Tried) {
        let family = self.s.family;
        let before = self.current.validation.score(family);
        let (cv, cv_before) = (self.cv, self.cv_before);
        let gain_of = |t: &Tried| -> Option<f64> {
            if cv {
                cv_before.zip(t.cv.as_ref()).map(|(b, c)| b - c.score)
            } else {
                t.scored.as_ref().map(|x| before - x.0.validation.score(family))
            }
        };
        if let Some(gain) = gain_of(winner) {
            for t in tried {
                if t.id != winner.id && gain_of(t).is_some_and(|g| g >= self.opts.tie_fraction * gain) {
                    self.ties.push((winner.id, t.id));
                }
            }
        }
    }

    /// What the winner was judged on: the out-of-fold rows of its regime (when it passed there only), all blocks,
    /// or the validation segment.
    fn validated_on(&self, winner: &Tried) -> String {
        let n_folds = self.n_folds;
        match &winner.cv {
            Some(c) if 1.0 - (c.score / self.cv_before.unwrap_or(f64::NAN)).sqrt() < self.opts.min_relative_drop => {
                c.regime.as_ref().map_or_else(String::new, |r| {
                    format!("out-of-fold rows at {} ({:.1} s of the recording)", r.name, r.seconds)
                })
            }
            Some(_) => format!("out-of-fold free runs of all {n_folds} blocks"),
            None => "the validation segment (last part of the recording)".to_string(),
        }
    }

    /// The backward half of the search after an addition ([`refit_named`]); true when a fold model changed.
    fn refit_named(&mut self) -> Result<bool, BadInput> {
        let (nominal, opts) = (self.nominal, self.opts);
        refit_named(&mut self.current, &mut self.fold_current, &self.folds, self.s, &self.std_rows, (nominal, opts))
    }

    /// The fold models of the final set, for the intervals: under cross-validation those chained through the
    /// selection; otherwise the named effects fitted on each fold in the order they were named.
    fn final_fold_models(&mut self) {
        if self.cv {
            return;
        }
        let s = self.s;
        self.fold_current = self
            .fold_baseline
            .iter()
            .zip(&self.folds)
            .map(|(fb, r)| {
                let (mut m, mut t) = fb.clone()?;
                for k in &self.kept {
                    (m, t) = search::candidate(k.id, &m, t, s, r, Some(&k.after.model))?;
                }
                Some((m, t))
            })
            .collect();
    }
}

/// The parameters the jackknife gives intervals for: J and B (unless the load is unknown), the named effects', and
/// the torque-balance terms refitted with them.
fn interval_keys(m: &PlantModel, family: Family, kept: &[Kept]) -> Vec<String> {
    parameters(m)
        .into_keys()
        .filter(|k| family != Family::Flow || !(k == "inertia_kg_m2" || k == "viscous_nm_s_rad"))
        .filter(|k| {
            !k.contains('.')
                || kept.iter().any(|x| k.starts_with(&format!("{}.", x.id)))
                || (["coulomb_friction.", "torque_offset.", "stribeck_friction."].iter().any(|p| k.starts_with(p))
                    && family != Family::Flow)
        })
        .collect()
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

/// A candidate of one round: its fit on the fitting segment (with ΔBIC) and, when cross-validated, the folds.
struct Tried {
    id: &'static str,
    scored: Option<(Scored, f64)>,
    cv: Option<CrossValidated>,
}

/// A kept effect and the evidence for it.
struct Kept {
    id: &'static str,
    before: Scored,
    after: Scored,
    delta_bic: f64,
    cv_before: Option<f64>,
    cv_after: Option<f64>,
    validated_on: String,
}

/// A re-fit of a named effect on given rows (None: nothing to re-fit).
type Refit<'a> = dyn Fn(&PlantModel, MechTerms, &Rows) -> Option<PlantModel> + 'a;

/// The backward half of the search: after an addition, where B is still beyond `viscous_plausible_factor` of the
/// nominal model's with both dry terms named, the Coulomb level is split out of the breakaway again beside what
/// came since, on the standard rows and on every fold's, and kept where the free run fits better. A Coulomb level
/// found before a dead time was in was fitted against a free run the dead time distorted. Likewise a named Stribeck
/// friction (with B) and a named dead time beside it ([`search::refit_low_speed`]). True when a fold model changed
/// (the out-of-fold score must then be taken again).
fn refit_named(
    current: &mut Scored,
    fold_current: &mut [Option<(PlantModel, MechTerms)>],
    folds: &[Rows],
    s: &Series,
    rows: &Rows,
    (nominal, opts): (&PlantModel, &Options),
) -> Result<bool, BadInput> {
    let coulomb_again = |m: &PlantModel, t: MechTerms, r: &Rows| -> Option<PlantModel> {
        m.effects.coulomb_friction.and(m.effects.stribeck_friction)?;
        if viscous_plausible(m, nominal, opts) {
            return None;
        }
        let mut stripped = m.clone();
        stripped.effects.coulomb_friction = None;
        search::coulomb_beside_stribeck(&stripped, t, s, r)
    };
    // the backward step for low-speed friction: refined again beside what was named since (a dead time)
    let low_speed_again = |m: &PlantModel, t: MechTerms, r: &Rows| search::refit_low_speed(m, t, s, r);
    let refits: [&Refit; 2] = [&coulomb_again, &low_speed_again];
    let mut folds_changed = false;
    for refit in refits {
        if let Some(m) = refit(&current.model, current.terms, rows) {
            let refitted = Scored::evaluate(m, current.terms, s)?;
            if rows.search_cost(&refitted.model, s) < rows.search_cost(&current.model, s) {
                *current = refitted;
            }
        }
        for (fold, r) in fold_current.iter_mut().zip(folds) {
            if let Some((m, t)) = fold.as_ref()
                && let Some(n) = refit(m, *t, r)
                && r.search_cost(&n, s) < r.search_cost(m, s)
            {
                *fold = Some((n, *t));
                folds_changed = true;
            }
        }
    }
    Ok(folds_changed)
}

/// Two candidates of a round kept together: the first as tried alone, the second fitted on top of it.
struct Pair {
    first: usize,
    second: usize,
    scored: Scored,
    cv: CrossValidated,
}

/// The pair of this round's cross-validated candidates that passes the rule together where neither did alone: ΔBIC
/// of the two over the current model at least the margin, the out-of-fold error down by `min_relative_drop`, and
/// each of the two lowering it below what the other alone reaches. The lowest out-of-fold score wins.
#[allow(clippy::too_many_arguments)]
fn joint_pair(
    tried: &[Tried],
    current: &Scored,
    cv_before: Option<f64>,
    folds: &[Rows],
    s: &Series,
    rows: &Rows,
    opts: &Options,
    n_bic: f64,
) -> Option<Pair> {
    let before = cv_before?;
    let family = s.family;
    let open: Vec<usize> = (0..tried.len())
        .filter(|&i| {
            let (Some((sc, db)), Some(c)) = (&tried[i].scored, &tried[i].cv) else { return false };
            *db >= opts.min_delta_bic && c.score < before && resolved(tried[i].id, &sc.model, &current.model, s, opts)
        })
        .collect();
    let mut best: Option<Pair> = None;
    for &i in &open {
        for &k in &open {
            if i == k {
                continue;
            }
            let (a, b) = (&tried[i], &tried[k]);
            let (Some((first, _)), Some(a_cv), Some(b_cv)) = (&a.scored, &a.cv, &b.cv) else { continue };
            let Some((m, t)) = search::candidate(b.id, &first.model, first.terms, s, rows, None) else { continue };
            let Ok(pair) = Scored::evaluate(m, t, s).map(Scored::without_prediction) else { continue };
            let params = search::parameter_count(a.id) + search::parameter_count(b.id);
            let db = search::delta_bic(current.fit.score(family), pair.fit.score(family), params, n_bic);
            if db < opts.min_delta_bic || !resolved(b.id, &pair.model, &first.model, s, opts) {
                continue;
            }
            let Some(c) = cross_validate(b.id, &pair, &a_cv.models, folds, s, opts) else { continue };
            let each = c.score < a_cv.score && c.score < b_cv.score;
            if each
                && 1.0 - (c.score / before).sqrt() >= opts.min_relative_drop
                && best.as_ref().is_none_or(|p| c.score < p.cv.score)
            {
                best = Some(Pair { first: i, second: k, scored: pair, cv: c });
            }
        }
    }
    best
}

/// Whether effect `id`, as fitted in `candidate`, lies beyond what the recording and the plant's own variation
/// resolve against `current` (the model before it):
/// - a dead time shorter than one sample period is below what the recording resolves: a service recording stamps a
///   row when the read is sent and the setpoint lands after the reply, so such a lag is the recorder's own;
/// - an oil's bulk modulus moves by 10–20 % with its temperature and pressure, and a service recording's poll jitter
///   softens the fitted one by as much (a plant with only Coulomb friction, served at 5 ms on a loaded machine, gave
///   8 % below the model's): an effective modulus above `air_max_modulus_ratio` of the model's is not entrained air;
/// - leakage through a clearance goes with the oil's viscosity, which moves by 20 % and more over a few kelvin, and
///   a few hundredths of a bar of ΔP timing error is taken up by a trace of it (the Coulomb-friction plant served at
///   5 ms once gave 0.00034 L/min/bar, 1.7 % of the model's): an added leakage (or slip's equivalent) below
///   `leak_min_ratio` of the model's, or taking less than `leak_min_flow_share` of the motor's flow, is not a
///   leak.
fn resolved(id: &str, candidate: &PlantModel, current: &PlantModel, s: &Series, opts: &Options) -> bool {
    let e = &candidate.effects;
    match id {
        "dead_time" => e.dead_time.is_none_or(|d| d.ms >= 1e3 / s.sample_hz),
        "entrained_air" => {
            let nominal_bulk = current.hydraulics.as_ref().map_or(f64::INFINITY, |h| h.bulk_modulus_bar);
            e.entrained_air.is_none_or(|a| a.bulk_modulus_bar <= opts.air_max_modulus_ratio * nominal_bulk)
        }
        "internal_leakage" | "motor_slip" => {
            let nominal_leak = current.hydraulics.as_ref().map_or(0.0, |h| h.leakage_l_min_per_bar);
            let added = match id {
                "internal_leakage" => e.internal_leakage.map(|l| l.l_min_per_bar),
                _ => e.motor_slip.and_then(|k| slip_as_leakage(candidate, k.rpm_per_nm)),
            };
            let floor = (opts.leak_min_ratio * nominal_leak)
                .max(opts.leak_min_flow_share * flow_per_bar(current, s).unwrap_or(0.0));
            added.is_none_or(|c| c >= floor)
        }
        _ => true,
    }
}

/// Whether dry-friction candidate `id` brings the viscous friction back within `viscous_plausible_factor` of the
/// nominal model's, from beyond it in `current`: the sign that the dry term was missing (`Options`). Never with
/// `min_relative_drop` infinite (nothing is to be named).
fn restores_viscous(
    id: &str,
    candidate: &PlantModel,
    current: &PlantModel,
    nominal: &PlantModel,
    opts: &Options,
) -> bool {
    ["coulomb_friction", "stribeck_friction"].contains(&id)
        && nominal.motor.viscous_nm_s_rad > 0.0
        && opts.min_relative_drop.is_finite()
        && !viscous_plausible(current, nominal, opts)
        && viscous_plausible(candidate, nominal, opts)
}

/// Whether `m`'s B lies within `viscous_plausible_factor` of the nominal model's.
fn viscous_plausible(m: &PlantModel, nominal: &PlantModel, opts: &Options) -> bool {
    let (b0, f) = (nominal.motor.viscous_nm_s_rad, opts.viscous_plausible_factor);
    (b0 / f..=b0 * f).contains(&m.motor.viscous_nm_s_rad)
}

/// The motor's mean flow over the recording's mean |ΔP| (L/min/bar): the leakage coefficient that would take the
/// whole flow.
fn flow_per_bar(m: &PlantModel, s: &Series) -> Option<f64> {
    let d_m = crate::units::cm3_per_rev_to_m3_per_rad(m.motor.displacement_cm3?);
    let mean_abs = |v: &[f64]| {
        let (sum, n) = v.iter().filter(|x| x.is_finite()).fold((0.0, 0usize), |(a, n), x| (a + x.abs(), n + 1));
        (n > 0).then(|| sum / n as f64)
    };
    let flow_m3_s = d_m * mean_abs(&s.omega_f)?;
    let dp_bar = mean_abs(s.dp_bar.as_deref()?)?;
    (dp_bar > 0.0).then(|| flow_m3_s / crate::units::l_min_per_bar_to_si(1.0) / crate::units::bar_to_pa(dp_bar))
}

/// The sensor-noise floor of each judged signal, as the residual sees it: σ of the white part of the measurement
/// (what a zero-phase low-pass removes, robustly, scaled for the pass band); for a filtered comparison (torque)
/// the part of that noise inside the pass band. The flow family's ΔP is predicted from the measured speed, so its
/// floor adds the share of the speed sensor's noise that `sc`'s prediction carries.
fn noise_floors(s: &Series, sc: &Scored) -> Vec<(&'static str, f64)> {
    let passed = (2.0 * s.cutoff_hz / s.sample_hz).clamp(0.0, 0.9);
    let sigma = |raw: &[f64]| -> f64 {
        let f = signal::filtfilt_butter4(raw, s.cutoff_hz, s.sample_hz);
        let mut d: Vec<f64> = raw.iter().zip(&f).map(|(a, b)| (a - b).abs()).filter(|v| v.is_finite()).collect();
        d.sort_by(f64::total_cmp);
        let mad = d.get(d.len() / 2).copied().unwrap_or(0.0);
        1.4826 * mad / (1.0 - passed).sqrt()
    };
    let mut out = Vec::new();
    match s.family {
        Family::Hydraulic => {
            out.push(("omega", sigma(&s.omega_rad_s)));
            if let Some(dp) = &s.dp_bar {
                out.push(("dp", sigma(dp)));
            }
        }
        Family::Torque => out.push(("torque", sigma(&s.drive_torque_nm) * passed.sqrt())),
        Family::Flow => {
            if let Some(dp) = &s.dp_bar {
                out.push(("dp", sigma(dp).hypot(sc.prediction.dp_noise_bar2.max(0.0).sqrt())));
            }
            if let Some(f) = &s.f_drive_hz {
                // the register's 0.01 Hz quantisation at least
                out.push(("f_drive", sigma(f).max(0.01 / 12f64.sqrt())));
            }
        }
    }
    out
}

/// Per row, the variance that the time stamps' own uncertainty makes of the drive frequency: a row is placed within
/// one sample period T (a service recording stamps it when the read is sent; the setpoint it carries lands after the
/// reply), uniform over T, so σ_t = T/√12 and the frequency the model ramps moves by ḟ·σ_t. `None` without a drive
/// frequency prediction.
fn timing_variance(s: &Series, sc: &Scored) -> Option<Vec<f64>> {
    let f = sc.prediction.f_drive_hz.as_ref()?;
    let sigma_t = 1.0 / (s.sample_hz * 12f64.sqrt());
    let n = f.len().min(s.t_s.len());
    Some(
        (0..n)
            .map(|i| {
                let (a, b) = (i.saturating_sub(1), (i + 1).min(n - 1));
                let dt = s.t_s[b] - s.t_s[a];
                let rate = if dt > 0.0 { (f[b] - f[a]) / dt } else { 0.0 };
                (rate * sigma_t).powi(2)
            })
            .collect(),
    )
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

/// Measured − model for each judged signal of the family, over the whole recording.
/// Residuals (measured − predicted) per judged signal; NaN where nothing was measured, so that no window of
/// filled-in values is called unexplained.
fn residual_signals(sc: &Scored, s: &Series) -> Vec<(&'static str, Vec<f64>)> {
    let mut out = residual_signals_filled(sc, s);
    for (name, r) in &mut out {
        let mask = match *name {
            "omega" => &s.measured_omega,
            "dp" => &s.measured_dp,
            "f_drive" => &s.measured_f_drive,
            _ => continue,
        };
        for (v, m) in r.iter_mut().zip(mask) {
            if !m {
                *v = f64::NAN;
            }
        }
    }
    out
}

fn residual_signals_filled(sc: &Scored, s: &Series) -> Vec<(&'static str, Vec<f64>)> {
    let mut out = Vec::new();
    match s.family {
        Family::Hydraulic => {
            out.push(("omega", s.omega_rad_s.iter().zip(&sc.prediction.omega_rad_s).map(|(m, p)| m - p).collect()));
            if let (Some(meas), Some(sim)) = (&s.dp_bar, &sc.prediction.dp_bar) {
                out.push(("dp", meas.iter().zip(sim).map(|(m, p)| m - p).collect()));
            }
        }
        Family::Torque => {
            if let Some(tau) = &sc.prediction.torque_nm {
                out.push(("torque", s.drive_torque_f.iter().zip(tau).map(|(m, p)| m - p).collect()));
            }
        }
        Family::Flow => {
            if let (Some(meas), Some(sim)) = (&s.dp_bar, &sc.prediction.dp_bar) {
                out.push(("dp", meas.iter().zip(sim).map(|(m, p)| m - p).collect()));
            }
            if let (Some(meas), Some(sim)) = (&s.f_drive_hz, &sc.prediction.f_drive_hz) {
                out.push(("f_drive", meas.iter().zip(sim).map(|(m, p)| m - p).collect()));
            }
        }
    }
    out
}

fn effort(sc: &Scored, s: &Series) -> Vec<f64> {
    match s.family {
        Family::Hydraulic | Family::Flow => sc.prediction.dp_bar.clone().unwrap_or_default(),
        Family::Torque => sc.prediction.torque_nm.clone().unwrap_or_default(),
    }
}

fn traces(base: &Scored, improved: &Scored, s: &Series) -> Traces {
    let (effort_name, effort_meas) = match &s.dp_bar {
        Some(dp) => ("ΔP (bar)", dp.clone()),
        None => ("torque (N·m)", s.drive_torque_f.clone()),
    };
    Traces {
        t_s: s.t_s.clone(),
        split: s.split,
        omega_meas: s.omega_rad_s.clone(),
        omega_baseline: base.prediction.omega_rad_s.clone(),
        omega_improved: improved.prediction.omega_rad_s.clone(),
        effort_name,
        effort_meas,
        effort_baseline: effort(base, s),
        effort_improved: effort(improved, s),
        omega_f: s.omega_f.clone(),
        drive_meas: s.f_drive_hz.clone().unwrap_or_default(),
        drive_baseline: base.prediction.f_drive_hz.clone().unwrap_or_default(),
        drive_improved: improved.prediction.f_drive_hz.clone().unwrap_or_default(),
    }
}

fn correlation(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len().min(b.len()) as f64;
    if n < 2.0 {
        return 0.0;
    }
    let ma = a.iter().sum::<f64>() / n;
    let mb = b.iter().sum::<f64>() / n;
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        sab += (x - ma) * (y - mb);
        saa += (x - ma).powi(2);
        sbb += (y - mb).powi(2);
    }
    if saa > 0.0 && sbb > 0.0 { sab / (saa * sbb).sqrt() } else { 0.0 }
}

fn finding(
    id: &str,
    before: &Scored,
    after: &Scored,
    delta_bic: f64,
    s: &Series,
    cond: &mismatch::Conditions,
) -> Finding {
    let family = s.family;
    let (b, a) = (before.validation.score(family), after.validation.score(family));
    // the judged signal where the effect changed the prediction most, on the validation segment
    let rb = residual_signals(before, s);
    let ra = residual_signals(after, s);
    let v = s.split;
    let mut corr = 0.0;
    let mut where_it_shows = String::new();
    let mut best_gain = f64::NEG_INFINITY;
    for ((name, r0), (_, r1)) in rb.iter().zip(&ra) {
        let change: Vec<f64> = r0[v..].iter().zip(&r1[v..]).map(|(x, y)| x - y).collect();
        let gain = r0[v..].iter().map(|x| x * x).sum::<f64>() - r1[v..].iter().map(|x| x * x).sum::<f64>();
        let norm = s_norm(&r0[v..]);
        if norm > 0.0 && gain / norm > best_gain {
            best_gain = gain / norm;
            corr = correlation(&r0[v..], &change);
            // the windows where the effect removed the most residual
            let w = ((mismatch::WINDOW_S * s.sample_hz) as usize).max(10);
            let mut gains: Vec<(f64, usize)> = (0..r0.len() / w)
                .map(|i| {
                    let (p, q) = (i * w, (i + 1) * w);
                    let g = r0[p..q].iter().map(|x| x * x).sum::<f64>() - r1[p..q].iter().map(|x| x * x).sum::<f64>();
                    (g, p)
                })
                .collect();
            gains.sort_by(|x, y| y.0.total_cmp(&x.0));
            let top: Vec<usize> = gains.iter().take(5).map(|g| g.1).collect();
            let mut counts: BTreeMap<String, usize> = BTreeMap::new();
            for p in top {
                *counts.entry(cond.describe(s, p, p + w)).or_default() += 1;
            }
            let most = counts.into_iter().max_by_key(|c| c.1).map(|c| c.0).unwrap_or_default();
            where_it_shows = format!("{name}: {most}");
        }
    }
    let parameters = effect_parameters(&after.model, id);
    let explanation = explain(id, &after.model, s, b, a);
    Finding {
        effect: id.to_string(),
        parameters,
        confidence_intervals: BTreeMap::new(),
        explanation,
        evidence: Evidence {
            delta_bic,
            validation_score_before: b,
            validation_score_after: a,
            relative_drop: 1.0 - (a / b).sqrt(),
            residual_correlation: corr,
            where_it_shows,
            cross_validation_score_before: None,
            cross_validation_score_after: None,
            validated_on: String::new(),
        },
    }
}

fn s_norm(x: &[f64]) -> f64 {
    x.iter().map(|v| v * v).sum()
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

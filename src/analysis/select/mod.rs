//! The greedy forward selection over the catalogue: each round fits every remaining effect on top of the model so
//! far and keeps the one that passes the rule (BIC, then the validation or out-of-fold error), or a pair that passes
//! only together; then the backward refits of what was named before. What a candidate must be besides better by the
//! numbers is in `plausible`.

use crate::BadInput;
use crate::plant::PlantModel;

use super::search::{self, MechTerms, Rows, Scored};
use super::series::{Family, Series};
use super::validate::{CrossValidated, cross_validate, out_of_fold_score};
use super::{CandidateScore, Options, parameters};

mod plausible;
use plausible::{resolved, restores_viscous, viscous_plausible};

/// Where the search starts: the nominal model (its effects are part of it: the search adds to them) with the load
/// taken from the recording, and the torque-balance terms it already has.
pub(super) fn search_start(nominal: &PlantModel) -> (PlantModel, MechTerms) {
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
pub(super) fn fit_baseline(
    start: &PlantModel,
    nominal_terms: MechTerms,
    s: &Series,
    source: &str,
) -> Result<Scored, BadInput> {
    let base_model = if s.family == Family::Flow {
        start.clone()
    } else {
        fit_nominal_mechanics(start, s, nominal_terms, &[(0, s.split)]).ok_or_else(|| {
            BadInput(format!(
                "recording {}: inertia and viscous friction cannot be fitted on the fitting segment: the data do not \
                 determine them or give them unphysical (it needs accelerations and several speeds)",
                source
            ))
        })?
    };
    Scored::evaluate(base_model, nominal_terms, s)
}

/// J, B and the nominal model's own dry friction fitted on `ranges`. A Coulomb friction the nominal model has but
/// the recording does not comes out of least squares a little below zero, which is no friction: its optimum within
/// the bound is on it, the fit without the term, and the model keeps the term at 0 N·m (a reviewer's model with
/// `[effects.coulomb_friction] torque_nm = 0` on a recording without it was refused as a speed that hardly changes).
fn fit_nominal_mechanics(
    start: &PlantModel,
    s: &Series,
    terms: MechTerms,
    ranges: &[(usize, usize)],
) -> Option<PlantModel> {
    search::fit_mechanics_on(start, s, terms, ranges).or_else(|| {
        if !terms.coulomb || terms.stribeck {
            return None;
        }
        let mut m = search::fit_mechanics_on(start, s, MechTerms { coulomb: false, ..terms }, ranges)?;
        m.effects.coulomb_friction = Some(crate::plant::effects::CoulombFriction { torque_nm: 0.0 });
        Some(m)
    })
}

/// The greedy forward selection over the catalogue: the model so far and its fold models, what was kept and why,
/// and what is left to try.
pub(super) struct Selection<'a> {
    pub(super) s: &'a Series,
    pub(super) nominal: &'a PlantModel,
    pub(super) opts: &'a Options,
    /// The rows of the fitting segment the free-run parameter search uses.
    pub(super) std_rows: Rows,
    /// The sample count BIC is taken over.
    pub(super) n_bic: f64,
    /// Blocked cross-validation: the recording cut into `n_folds` blocks; fold k fits on the others and runs block
    /// k free from its measured state. The fold models are chained like the selection (each fold keeps the
    /// effects kept so far, fitted on its own rows), and give the jackknife intervals.
    pub(super) n_folds: usize,
    pub(super) folds: Vec<Rows>,
    /// Whether the out-of-fold score decides (hydraulic family with folds), rather than the validation tail.
    pub(super) cv: bool,
    pub(super) fold_baseline: Vec<Option<(PlantModel, MechTerms)>>,
    pub(super) fold_current: Vec<Option<(PlantModel, MechTerms)>>,
    /// The out-of-fold score of the baseline, and of the model so far.
    pub(super) cv_baseline: Option<f64>,
    pub(super) cv_before: Option<f64>,
    pub(super) current: Scored,
    pub(super) remaining: Vec<&'static str>,
    pub(super) kept: Vec<Kept>,
    pub(super) candidates: Vec<CandidateScore>,
    /// Candidates whose gain came within `tie_fraction` of a kept one's: (kept, other).
    pub(super) ties: Vec<(&'static str, &'static str)>,
}

impl<'a> Selection<'a> {
    /// The search's rows and blocks, the baseline fitted on every fold, and the catalogue effects the nominal model
    /// lacks.
    pub(super) fn new(
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
                    fit_nominal_mechanics(start, s, nominal_terms, &r.ls).map(|m| (m, nominal_terms))
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
    pub(super) fn round(&mut self, round: usize, progress: &mut dyn FnMut(f64)) -> Result<bool, BadInput> {
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

    /// Drops what was named (a model that does not describe the recording, [`super::misfit`]): the model and its
    /// fold models back to the baseline, no candidate kept.
    pub(super) fn name_nothing(&mut self, baseline: &Scored) {
        self.kept.clear();
        self.ties.clear();
        self.current = baseline.clone();
        self.fold_current = self.fold_baseline.clone();
        self.cv_before = self.cv_baseline;
        for c in &mut self.candidates {
            c.kept = false;
        }
    }

    /// The fold models of the final set, for the intervals: under cross-validation those chained through the
    /// selection; otherwise the named effects fitted on each fold in the order they were named.
    pub(super) fn final_fold_models(&mut self) {
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
pub(super) fn interval_keys(m: &PlantModel, family: Family, kept: &[Kept]) -> Vec<String> {
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

/// A candidate of one round: its fit on the fitting segment (with ΔBIC) and, when cross-validated, the folds.
struct Tried {
    id: &'static str,
    scored: Option<(Scored, f64)>,
    cv: Option<CrossValidated>,
}

/// A kept effect and the evidence for it.
pub(super) struct Kept {
    pub(super) id: &'static str,
    pub(super) before: Scored,
    pub(super) after: Scored,
    pub(super) delta_bic: f64,
    pub(super) cv_before: Option<f64>,
    pub(super) cv_after: Option<f64>,
    pub(super) validated_on: String,
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

//! The analysis's result: the JSON of CONTRACT.md (findings and their evidence, summaries, candidates) and the
//! signals the report draws.

use std::collections::BTreeMap;

use serde::Serialize;

use crate::plant::PlantModel;

use super::mismatch::{self, Mismatch};
use super::predict::Errors;
use super::series;

/// The analysis JSON of CONTRACT.md, plus what the report draws.
#[derive(Debug, Clone, Serialize)]
pub struct Analysis {
    pub recording: String,
    pub samples: usize,
    pub validation_from_s: f64,
    /// `hydraulic` (free run from setpoint and load) or `torque` (driven by a measured torque).
    pub family: &'static str,
    /// Where the speed came from: `omega_rad_s`, or `theta_rad` differentiated after a zero-phase low-pass.
    pub speed_source: &'static str,
    /// Where the load torque came from: `recorded` (`load_nm`), `model` (the model's `[load]` profile) or
    /// `unknown` (the flow balance only).
    pub load: &'static str,
    pub baseline: Summary,
    pub mismatches: Vec<Mismatch>,
    pub findings: Vec<Finding>,
    /// Set when the model does not describe the recording at all (a judged signal's free run worse than the
    /// recording's own mean, on the validation segment and over the whole recording, even after the search): then
    /// nothing is named and `improved` is the baseline. `null` otherwise.
    pub model_misfit: Option<Misfit>,
    pub ambiguities: Vec<Ambiguity>,
    /// Parameters this recording does not determine, and why (with the load unknown: J and B).
    pub not_identified: Vec<NotIdentified>,
    pub improved: Summary,
    /// Where the improved model's residual still exceeds the noise floor, grouped by signal and operating
    /// condition; empty when the model explains the recording down to the sensor noise.
    pub unexplained: Vec<mismatch::Unexplained>,
    /// Cells outside their sensor's range, read as missing (per file and column, with the first line).
    pub out_of_range: Vec<crate::recording::OutOfRange>,
    /// Lone values far off their neighbours (spikes), taken as missing (per column, with the first `t_s`).
    pub outliers: Vec<series::Outlier>,
    /// Steps in `t_s` the free run restarts after (see `series::gaps`): how many, and the longest.
    pub gaps: Gaps,
    /// How effects were validated and how the confidence intervals were computed.
    pub validation_rule: String,
    pub interval_method: String,
    /// Every candidate tried, round by round: what the selection saw.
    pub candidates: Vec<CandidateScore>,
    #[serde(skip)]
    pub improved_model: PlantModel,
    #[serde(skip)]
    pub traces: Traces,
}

/// A model that does not describe the recording: the signal it misses most, by how much, and what to check.
#[derive(Debug, Clone, Serialize)]
pub struct Misfit {
    /// `omega`, `dp`, `torque` or `f_drive`.
    pub signal: &'static str,
    pub validation_nrmse: f64,
    pub whole_recording_nrmse: f64,
    pub explanation: String,
}

/// The recording's gaps in time.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Gaps {
    pub count: usize,
    /// The longest gap (s) and the `t_s` it follows; absent without gaps.
    pub longest_s: Option<f64>,
    pub after_t_s: Option<f64>,
}

/// A model's parameters and its validation errors.
#[derive(Debug, Clone, Serialize)]
pub struct Summary {
    pub parameters: BTreeMap<String, f64>,
    pub validation: Errors,
    /// The same errors over the whole recording (fitting and validation segments), to compare with published
    /// figures computed that way.
    pub whole_recording: Errors,
    /// Hydraulic family: the blocked cross-validation score (mean squared NRMSE of the out-of-fold free runs).
    pub cross_validation_score: Option<f64>,
    /// 95 % interval of every fitted parameter (`interval_method`); absent when fewer than 3 folds fitted it.
    pub confidence_intervals: BTreeMap<String, Interval>,
}

/// A confidence interval.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Interval {
    pub low: f64,
    pub high: f64,
}

/// One named effect.
#[derive(Debug, Clone, Serialize)]
pub struct Finding {
    pub effect: String,
    pub parameters: BTreeMap<String, f64>,
    /// 95 % interval of each parameter (catalogue names), as in `improved.confidence_intervals`.
    pub confidence_intervals: BTreeMap<String, Interval>,
    pub explanation: String,
    pub evidence: Evidence,
}

/// Why a finding was kept.
#[derive(Debug, Clone, Serialize)]
pub struct Evidence {
    /// BIC(without) − BIC(with) on the fitting segment; positive favours the effect.
    pub delta_bic: f64,
    /// Validation score (mean squared NRMSE) before and after adding the effect.
    pub validation_score_before: f64,
    pub validation_score_after: f64,
    /// 1 − after/before of the validation error (root of the score).
    pub relative_drop: f64,
    /// Correlation, on the validation segment, between the residual before the effect and what the effect changes
    /// in the prediction: near 1 means the effect has the shape of what was missing.
    pub residual_correlation: f64,
    /// The conditions of the mismatch windows the effect removes most of.
    pub where_it_shows: String,
    /// Hydraulic family: blocked cross-validation score before and after, and what it was judged on.
    pub cross_validation_score_before: Option<f64>,
    pub cross_validation_score_after: Option<f64>,
    pub validated_on: String,
}

/// Effects this recording cannot tell apart.
#[derive(Debug, Clone, Serialize)]
pub struct Ambiguity {
    pub effects: Vec<String>,
    pub explanation: String,
}

/// Parameters the recording leaves undetermined; the model keeps the nominal values.
#[derive(Debug, Clone, Serialize)]
pub struct NotIdentified {
    pub parameters: Vec<String>,
    pub reason: String,
}

/// A candidate's score in a selection round.
#[derive(Debug, Clone, Serialize)]
pub struct CandidateScore {
    pub round: usize,
    pub effect: String,
    pub validation_score: Option<f64>,
    pub delta_bic: Option<f64>,
    /// Hydraulic family, candidates that pass the BIC margin: the out-of-fold score, and on the regime where the
    /// effect acts (when it has one and the recording holds enough of it).
    pub cross_validation_score: Option<f64>,
    pub regime_drop: Option<f64>,
    pub kept: bool,
}

/// Signals for the report: the recording, the baseline and the improved model.
#[derive(Debug, Clone, Default)]
pub struct Traces {
    pub t_s: Vec<f64>,
    pub split: usize,
    pub omega_meas: Vec<f64>,
    pub omega_baseline: Vec<f64>,
    pub omega_improved: Vec<f64>,
    /// ΔP (bar) or, for a torque-driven recording, torque (N·m): measured, baseline, improved.
    pub effort_name: &'static str,
    pub effort_meas: Vec<f64>,
    pub effort_baseline: Vec<f64>,
    pub effort_improved: Vec<f64>,
    /// Low-passed speed, the x axis of the residual maps.
    pub omega_f: Vec<f64>,
    /// Flow family: the drive frequency read back and the drive model's (baseline, improved), Hz; empty otherwise.
    pub drive_meas: Vec<f64>,
    pub drive_baseline: Vec<f64>,
    pub drive_improved: Vec<f64>,
}

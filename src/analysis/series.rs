//! What the analysis reads from a recording: the model family, inputs, measured outputs, filtered regressors.

use crate::BadInput;
use crate::plant::dynamics::SIGN_SPEED_RAD_S;
use crate::plant::{LoadSpec, PlantModel};
use crate::recording::Recording;
use crate::units::cm3_per_rev_to_m3_per_rad;

use super::predict::FREE_RUN_STEP_S;
use super::signal::{derivative, fill_gaps, filtfilt_butter4, without_spikes};

/// Which simulation explains the recording: the pressure-driven hydraulic plant, or mechanics driven by a
/// measured torque.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Family {
    /// `f_set_hz`, `p_in_bar`, `p_out_bar`, speed and load: free-run of the whole plant from setpoint and load.
    Hydraulic,
    /// `torque_nm` and speed (or position): free-run of the mechanics from the drive torque.
    Torque,
    /// Pressures and speed with the load unknown (no `load_nm`, as the service records): the flow balance only.
    /// The measured speed and `f_drive_hz` (else the drive model run from `f_set_hz`) drive a free run of the
    /// pressure equation; the drive model run from `f_set_hz` is compared with `f_drive_hz`. No torque balance.
    Flow,
}

impl Family {
    pub fn name(self) -> &'static str {
        match self {
            Family::Hydraulic => "hydraulic",
            Family::Torque => "torque",
            Family::Flow => "flow",
        }
    }
}

/// Cut-off of the zero-phase low-pass for a measured (tachogenerator) speed: keeps the hydraulic ringing (≈ 6 Hz for
/// the reference plant), removes most of the sensor noise before differentiation.
pub const MEASURED_SPEED_CUTOFF_HZ: f64 = 10.0;
/// Cut-off for a speed differentiated from position, as in the EMPS benchmark's IDIM-LS script.
pub const POSITION_CUTOFF_HZ: f64 = 100.0;
/// The IDIM-LS script then decimates every signal of the torque balance by 10 (MATLAB `decimate`: a low-pass at
/// 0.8 of the new Nyquist frequency, 40 Hz at 1 kHz). The same parallel low-pass is applied here.
pub const DECIMATION: f64 = 10.0;

/// A recording turned into the signals the analysis needs; every vector has one value per row.
#[derive(Debug, Clone)]
pub struct Series {
    pub family: Family,
    pub t_s: Vec<f64>,
    pub sample_hz: f64,
    /// First row of the validation segment (never used for fitting).
    pub split: usize,
    /// Speed as measured, or differentiated from position: what free-run speed is compared to (rad/s).
    pub omega_rad_s: Vec<f64>,
    /// Low-passed speed and its derivative: the regressors of the torque balance.
    pub omega_f: Vec<f64>,
    pub alpha_f: Vec<f64>,
    /// Drive torque (N·m): `torque_nm`, or D_m·(p_in − p_out).
    pub drive_torque_nm: Vec<f64>,
    pub drive_torque_f: Vec<f64>,
    /// Load torque (N·m): `load_nm`, or the model's `[load]` profile.
    pub load_nm: Vec<f64>,
    pub load_f: Vec<f64>,
    /// Measured p_in − p_out (bar), for the hydraulic and flow families.
    pub dp_bar: Option<Vec<f64>>,
    /// The frequency setpoint (Hz), for the hydraulic family (and the flow family when it was written).
    pub setpoint_hz: Option<Vec<f64>>,
    /// The drive frequency read back (Hz), when recorded: the flow family's pump speed and, with the hydraulic
    /// family's, what the drive model is judged against.
    pub f_drive_hz: Option<Vec<f64>>,
    /// The nominal model's dead time (s): the hydraulic score's drive factor compares a model's drive with it.
    pub nominal_dead_time_s: f64,
    /// Where the load came from: `recorded` (`load_nm`), `model` (the model's `[load]` profile) or `unknown`.
    pub load: &'static str,
    /// Rows that follow a gap in the recording (stale cycles skipped, a link outage): the flow family's free run
    /// restarts from the measured state there.
    pub restarts: Vec<usize>,
    /// Flow family: a synthetic stretch of the speed sensor's noise as the analysis sees it (white, of the σ
    /// estimated from the recording, through the same low-pass). The measured speed drives the pressure equation,
    /// so its noise reaches the predicted ΔP, less so the softer the oil or the larger the leak: without
    /// accounting for it, the fit would prefer a softer oil for smoothing the noise (errors in variables).
    pub speed_noise_f: Option<Vec<f64>>,
    /// Initial drive frequency and inlet pressure for the free run.
    pub f0_hz: f64,
    pub p_in0_bar: f64,
    /// The measured state a free run restarts from at a block boundary (cross-validation): drive frequency (Hz,
    /// `f_drive_hz`, else the setpoint) and inlet pressure (bar) per row; empty for the torque family.
    pub state_f_hz: Vec<f64>,
    pub state_p_in_bar: Vec<f64>,
    pub cutoff_hz: f64,
    /// Where the speed came from (`omega_rad_s` or `theta_rad`), for the report.
    pub speed_source: &'static str,
    /// Speed band of the smooth sign in friction terms (see [`Series::sign_speed`]).
    pub sign_speed: f64,
    /// Per row, whether the speed, ΔP and drive frequency compared with a model's were measured there (gaps are
    /// filled for the filters; errors and unexplained windows count only measured rows).
    pub measured_omega: Vec<bool>,
    pub measured_dp: Vec<bool>,
    pub measured_f_drive: Vec<bool>,
    /// Values taken out as spikes ([`without_spikes`]), per column.
    pub outliers: Vec<Outlier>,
}

/// Lone values of one column that stood far off their neighbours and were taken as missing.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Outlier {
    pub column: &'static str,
    pub rows: usize,
    /// The first such row's `t_s`.
    pub first_t_s: f64,
}

/// The measured columns screened for spikes (a setpoint is a command: not screened). A position is monotone between
/// turns, where the median of five is the value itself, so only a lone corrupt value (1e300 in one cell) stands out.
const SCREENED: [&str; 7] = ["p_in_bar", "p_out_bar", "omega_rad_s", "theta_rad", "f_drive_hz", "torque_nm", "load_nm"];

/// The analysed columns of a recording as read: spikes taken out of the screened ones, gaps not yet filled.
struct Columns<'a> {
    src: &'a str,
    raw: Vec<(&'static str, Vec<f64>)>,
    /// Columns the recording has without a single value (every row empty, not a number or out of range).
    valueless: Vec<&'static str>,
}

impl<'a> Columns<'a> {
    /// Reads the columns the analysis uses, screening the measured ones for spikes (taken as missing, reported).
    fn read(rec: &'a Recording, t_s: &[f64]) -> (Columns<'a>, Vec<Outlier>) {
        let src = &rec.source;
        let mut outliers = Vec::new();
        let mut raw: Vec<(&'static str, Vec<f64>)> = Vec::new();
        let mut valueless = Vec::new();
        for name in super::RECORDING_COLUMNS {
            let Some(c) = rec.present(name) else {
                if rec.column(name).is_some() {
                    valueless.push(name);
                }
                continue;
            };
            // a single-turn encoder's position, its wraps taken out first (else each wrap is a spike, and a jump of
            // a turn in the speed)
            let unwrapped = (name == "theta_rad").then(|| crate::recording::unwrapped_positions(c));
            let c = unwrapped.as_deref().unwrap_or(c);
            if SCREENED.contains(&name) {
                let (c, taken) = without_spikes(c);
                if let Some(&first) = taken.first() {
                    outliers.push(Outlier { column: name, rows: taken.len(), first_t_s: t_s[first] });
                    tracing::warn!(recording = %src, column = name, rows = taken.len(), first_t_s = t_s[first],
                        "lone values far off their neighbours (spikes) taken as missing");
                }
                raw.push((name, c));
            } else {
                raw.push((name, c.to_vec()));
            }
        }
        (Columns { src, raw, valueless }, outliers)
    }

    /// A speed (or position), or an inlet pressure, that holds one value in every row is a stuck sensor or a
    /// constant written in its place: fitted to, it gave an inertia of 10⁸ with "nothing named". Refused, naming
    /// the column. So is a drive torque that holds one value while the inlet pressure, which makes it, moves (a
    /// column of zeros beside real pressures was fitted to, "named: nothing"). (An outlet pressure may be a steady
    /// back pressure, and a torque alone a steady command: not checked.) A position beside a speed is not read (the
    /// speed comes from `omega_rad_s`), so it is not judged either: a `theta_rad` of zeros beside a measured speed
    /// was refused, where `estimate` took the same file.
    fn refuse_stuck(&self) -> Result<(), BadInput> {
        let stuck = |name: &str| {
            let c = self.raw_of(name)?;
            let mut finite = c.iter().filter(|v| v.is_finite());
            let &first = finite.next()?;
            (c.len() >= 200 && finite.all(|&v| v == first)).then_some(first)
        };
        // in this order: a torque is judged only beside an inlet pressure already found moving
        for name in ["omega_rad_s", "theta_rad", "p_in_bar", "torque_nm"] {
            if name == "torque_nm" && self.raw_of("p_in_bar").is_none() {
                continue;
            }
            if name == "theta_rad" && self.raw_of("omega_rad_s").is_some_and(|c| c.iter().any(|v| v.is_finite())) {
                continue;
            }
            if let Some(first) = stuck(name) {
                return Err(BadInput(format!(
                    "recording {}: column `{name}` holds {first} in every row: a stuck sensor, or a constant \
                     written in its place; the analysis needs it measured",
                    self.src
                )));
            }
        }
        Ok(())
    }

    /// A column as read, if the recording has it.
    fn raw_of(&self, name: &str) -> Option<&[f64]> {
        self.raw.iter().find(|r| r.0 == name).map(|r| r.1.as_slice())
    }

    /// A column with at least one value, its gaps filled.
    fn col(&self, name: &str) -> Option<Vec<f64>> {
        self.raw_of(name).filter(|c| c.iter().any(|v| v.is_finite())).map(fill_gaps)
    }

    /// Per row, whether the column has a value there.
    fn finite_rows(&self, name: &str) -> Option<Vec<bool>> {
        self.raw_of(name).map(|c| c.iter().map(|v| v.is_finite()).collect::<Vec<bool>>())
    }

    /// The error naming a required column and why it is required.
    fn need(&self, name: &str, why: &str) -> BadInput {
        if self.valueless.contains(&name) {
            return self.unusable(name);
        }
        BadInput(format!("recording {}: column `{name}` is required {why}", self.src))
    }

    /// The error for a column that is there with no value the analysis can use.
    fn unusable(&self, name: &str) -> BadInput {
        BadInput(format!(
            "recording {}: column `{name}` has no usable value (every row empty, not a number or out of range)",
            self.src
        ))
    }

    /// Per row, whether the speed, ΔP and drive frequency were measured there (all rows when not recorded).
    fn measured(&self, speed_source: &str, n: usize) -> (Vec<bool>, Vec<bool>, Vec<bool>) {
        let measured_omega = match speed_source {
            "omega_rad_s" => self.finite_rows("omega_rad_s"),
            _ => self.finite_rows("theta_rad"),
        }
        .unwrap_or_else(|| vec![true; n]);
        let measured_dp = match (self.finite_rows("p_in_bar"), self.finite_rows("p_out_bar")) {
            (Some(a), Some(b)) => a.iter().zip(&b).map(|(a, b)| *a && *b).collect(),
            _ => vec![true; n],
        };
        let measured_f_drive = self.finite_rows("f_drive_hz").unwrap_or_else(|| vec![true; n]);
        (measured_omega, measured_dp, measured_f_drive)
    }
}

/// What drives the free run: the family and its drive torque, and for the pressure-driven families ΔP, the
/// setpoint and the measured state the free run starts and restarts from.
struct Drive {
    family: Family,
    torque_nm: Vec<f64>,
    dp_bar: Option<Vec<f64>>,
    setpoint_hz: Option<Vec<f64>>,
    p_in0_bar: f64,
    f0_hz: f64,
    state_f_hz: Vec<f64>,
    state_p_in_bar: Vec<f64>,
}

impl Drive {
    /// A measured torque makes the torque family; else the pressures drive, with the setpoint (with the load
    /// unknown, the drive frequency read back may stand in for it) and the model's hydraulic parts.
    fn read(
        cols: &Columns,
        model: &PlantModel,
        load_unknown: bool,
        f_drive: Option<&Vec<f64>>,
        n: usize,
    ) -> Result<Drive, BadInput> {
        // a `torque_nm` with no usable value is said so, not taken for a recording of pressures that lacks them
        if cols.valueless.contains(&"torque_nm") {
            return Err(cols.unusable("torque_nm"));
        }
        if let Some(tq) = cols.col("torque_nm") {
            return Ok(Drive {
                family: Family::Torque,
                torque_nm: tq,
                dp_bar: None,
                setpoint_hz: None,
                p_in0_bar: 0.0,
                f0_hz: 0.0,
                state_f_hz: Vec::new(),
                state_p_in_bar: Vec::new(),
            });
        }
        let why = "(a recording without `torque_nm` is analysed as the hydraulic plant)";
        let p_in = cols.col("p_in_bar").ok_or_else(|| cols.need("p_in_bar", why))?;
        let p_out = cols.col("p_out_bar").ok_or_else(|| cols.need("p_out_bar", why))?;
        let f_set = cols.col("f_set_hz");
        let f_set = if load_unknown && f_drive.is_some() {
            f_set
        } else {
            let why = if load_unknown {
                "(with the load unknown, the pump's speed comes from `f_drive_hz` or, without it, from the \
                 drive model run from `f_set_hz`)"
            } else {
                why
            };
            Some(f_set.ok_or_else(|| cols.need("f_set_hz", why))?)
        };
        let parts = model.hydraulic().map_err(|crate::error::KeyError { key, message: msg }| {
            BadInput(format!("model: `{key}` {msg} (the recording has pressures but no `torque_nm`)"))
        })?;
        let d_m = cm3_per_rev_to_m3_per_rad(parts.motor_displacement_cm3);
        let dp: Vec<f64> = p_in.iter().zip(&p_out).map(|(a, b)| a - b).collect();
        let torque = dp.iter().map(|d| d_m * d * 1e5).collect();
        let f0 = f_drive.or(f_set.as_ref()).map_or(0.0, |f| f[0]);
        let state_f_hz = f_drive.or(f_set.as_ref()).cloned().unwrap_or_else(|| vec![0.0; n]);
        Ok(Drive {
            family: if load_unknown { Family::Flow } else { Family::Hydraulic },
            torque_nm: torque,
            dp_bar: Some(dp),
            setpoint_hz: f_set,
            p_in0_bar: p_in[0],
            f0_hz: f0,
            state_f_hz,
            state_p_in_bar: p_in,
        })
    }
}

/// The speed compared with a model's, and the torque balance's regressors.
struct Speed {
    /// As measured, or differentiated from position.
    omega_rad_s: Vec<f64>,
    /// Low-passed speed and its derivative.
    omega_f: Vec<f64>,
    alpha_f: Vec<f64>,
    cutoff_hz: f64,
    source: &'static str,
}

impl Speed {
    /// The measured speed low-passed, or the position differentiated after a low-pass (then every regressor
    /// through the parallel decimation filter of IDIM-LS).
    fn read(cols: &Columns, t_s: &[f64], sample_hz: f64) -> Result<Speed, BadInput> {
        let (omega_rad_s, omega_f, cutoff_hz, speed_source) = if let Some(w) = cols.col("omega_rad_s") {
            let cutoff = MEASURED_SPEED_CUTOFF_HZ.min(0.2 * sample_hz);
            let wf = filtfilt_butter4(&w, cutoff, sample_hz);
            (w, wf, cutoff, "omega_rad_s")
        } else if let Some(theta) = cols.col("theta_rad") {
            let cutoff = POSITION_CUTOFF_HZ.min(0.2 * sample_hz);
            let w = derivative(&filtfilt_butter4(&theta, cutoff, sample_hz), t_s);
            // a position that jumps (an encoder reset, a corrupt run of cells) is a speed no plant has: refused here,
            // naming the column, rather than by the model's free run, which blamed the model file
            let (max_speed, _) = crate::plant::simulate::PHYSICAL_LIMITS;
            if let Some(k) = w.iter().position(|v| !v.is_finite() || v.abs() > max_speed) {
                return Err(BadInput(format!(
                    "recording {}: column `theta_rad` jumps near t = {:.3} s: the speed it gives there, {:.2e} rad/s, is \
                     beyond any plant; take the jump out (an encoder reset?) or cut the recording there",
                    cols.src, t_s[k], w[k]
                )));
            }
            (w.clone(), w, cutoff, "theta_rad")
        } else {
            return Err(BadInput(format!(
                "recording {}: no speed: expected a column `omega_rad_s` or `theta_rad` with values",
                cols.src
            )));
        };
        let mut alpha_f = derivative(&omega_f, t_s);
        let mut omega_f = omega_f;
        // the parallel decimation filter of IDIM-LS, for position-derived speed: every regressor and the torque
        let cutoff_hz = if speed_source == "theta_rad" {
            let parallel = 0.8 * sample_hz / (2.0 * DECIMATION);
            omega_f = filtfilt_butter4(&omega_f, parallel, sample_hz);
            alpha_f = filtfilt_butter4(&alpha_f, parallel, sample_hz);
            parallel
        } else {
            cutoff_hz
        };
        Ok(Speed { omega_rad_s, omega_f, alpha_f, cutoff_hz, source: speed_source })
    }
}

/// The load torque and where it came from: none with the load unknown, `load_nm`, or the model's `[load]` profile
/// run at the recording's speed (an error when a torque-driven recording has no load to take).
fn load_torque(
    cols: &Columns,
    model: &PlantModel,
    family: Family,
    recorded_load: Option<Vec<f64>>,
    omega_f: &[f64],
    t_s: &[f64],
) -> Result<(Vec<f64>, &'static str), BadInput> {
    let n = t_s.len();
    if family == Family::Flow {
        // the flow balance needs no load; zeros keep the vectors one per row
        Ok((vec![0.0; n], "unknown"))
    } else if let Some(l) = recorded_load.filter(|_| model.load != LoadSpec::Unknown) {
        Ok((l, "recorded"))
    } else if matches!(model.load, LoadSpec::Recorded | LoadSpec::Unknown) {
        // only a torque-driven recording gets here: its torque balance cannot be run without the load
        let why = if model.load == LoadSpec::Unknown {
            "because a torque-driven recording (`torque_nm`) is explained by its torque balance, which needs \
             the load; the model's [load] kind is \"unknown\""
        } else {
            "because the model's [load] kind is \"recorded\" and the recording is torque-driven (`torque_nm`)"
        };
        Err(cols.need("load_nm", why))
    } else {
        // the model's load at the recording's (filtered) speed and the shaft angle turned since its first row
        let mut angle_rad = 0.0;
        let load = (0..n)
            .map(|k| {
                if k > 0 {
                    angle_rad += 0.5 * (omega_f[k - 1] + omega_f[k]) * (t_s[k] - t_s[k - 1]);
                }
                model.load.torque_at(t_s[k] - t_s[0], omega_f[k], angle_rad)
            })
            .collect();
        Ok((load, "model"))
    }
}

/// Warns of the recording's gaps in time, naming the longest.
fn warn_of_gaps(src: &str, t_s: &[f64], restarts: &[usize]) {
    if let Some(&longest) = restarts.iter().max_by(|&&a, &&b| (t_s[a] - t_s[a - 1]).total_cmp(&(t_s[b] - t_s[b - 1]))) {
        tracing::warn!(
            recording = %src,
            "{} gap(s) in t_s, the longest {} s after row {longest} (t_s = {}): the free run restarts from the \
             measured state after each",
            restarts.len(),
            short(t_s[longest] - t_s[longest - 1]),
            short(t_s[longest - 1])
        );
    }
}

impl Series {
    /// Reads the signals, naming the missing column or model key when the recording or model cannot be analysed.
    pub fn extract(rec: &Recording, model: &PlantModel, validation_fraction: f64) -> Result<Series, BadInput> {
        let src = &rec.source;
        let n = rec.len();
        if n < 200 {
            return Err(BadInput(format!("recording {src}: {n} rows; the analysis needs at least 200")));
        }
        let t_s = rec.t_s().to_vec();
        // the median step, not the mean: a recording with gaps (skipped stale cycles) keeps its poll rate
        let steps: Vec<f64> = t_s.windows(2).map(|w| w[1] - w[0]).collect();
        let sample_hz = 1.0 / percentile(&steps, 0.5);
        let (cols, outliers) = Columns::read(rec, &t_s);
        let recorded_load = cols.col("load_nm");
        // the load is unknown when the model says so, or when it should come from the recording and does not
        let load_unknown = match model.load {
            LoadSpec::Unknown => true,
            LoadSpec::Recorded => recorded_load.is_none(),
            _ => false,
        };
        let f_drive = cols.col("f_drive_hz");
        let drive = Drive::read(&cols, model, load_unknown, f_drive.as_ref(), n)?;
        let family = drive.family;
        let speed = Speed::read(&cols, &t_s, sample_hz)?;
        let (load_nm, load) = load_torque(&cols, model, family, recorded_load, &speed.omega_f, &t_s)?;
        // what the recording and the model lack is said first; then a signal that does not move
        cols.refuse_stuck()?;
        let cutoff_hz = speed.cutoff_hz;
        let drive_torque_f = filtfilt_butter4(&drive.torque_nm, cutoff_hz, sample_hz);
        let load_f = filtfilt_butter4(&load_nm, cutoff_hz, sample_hz);
        let restarts = gaps(&t_s);
        warn_of_gaps(src, &t_s, &restarts);
        // a recording far slower than the model's fastest mode (a 1 s clock on a hydraulic drive, or ms read as s);
        // the nominal plant's, without the effects (dry friction's smoothed sign is not a mode of the plant)
        let rate = crate::plant::dynamics::model_rate(&PlantModel { effects: Default::default(), ..model.clone() });
        // beyond 100× nothing of the dynamics the fit looks for can show, and the free runs between samples made a
        // 5000-row recording at 10 s steps run for hours; below 10 µs no drive is polled: a clock in the wrong unit
        // either way, refused as `estimate` refuses it
        let too_short = 1.0 / sample_hz < crate::recording::MIN_TIME_STEP_S;
        if rate / sample_hz > MAX_SAMPLE_OVER_MODE || too_short {
            let why = if too_short {
                crate::recording::TOO_SHORT_A_STEP.to_string()
            } else {
                format!(
                    "more than {MAX_SAMPLE_OVER_MODE}× the model's fastest dynamics ({} s): nothing of the inertia, \
                     the dead time or the line shows in it",
                    short(1.0 / rate)
                )
            };
            return Err(BadInput(format!(
                "recording {src}: it samples every {} s (its typical time step), {why}; check the unit of t_s",
                short(1.0 / sample_hz)
            )));
        }
        if rate / sample_hz > 10.0 {
            tracing::warn!(recording = %src, sample_s = 1.0 / sample_hz, fastest_mode_s = 1.0 / rate,
                "the recording samples far slower than the model's fastest dynamics: inertia, dead time and the \
                 line's dynamics cannot show in it, and what is fitted rests on slow changes (check the unit of t_s)");
        }
        // time the free run integrates: the span without its gaps (nothing is integrated across one)
        let active = active_time(&t_s, &restarts);
        let integrated = active[n - 1];
        if integrated / FREE_RUN_STEP_S > MAX_FREE_RUN_STEPS {
            return Err(BadInput(format!(
                "recording {src}: t_s spans {} s without its gaps, a sample every {} s: the free run steps at \
                 {FREE_RUN_STEP_S} s, {} steps a pass, beyond the {MAX_FREE_RUN_STEPS:e} analyze takes (about \
                 28 hours of recording); check the unit of t_s (ms recorded as s?), or analyze a part",
                short(integrated),
                short(1.0 / sample_hz),
                short(integrated / FREE_RUN_STEP_S)
            )));
        }
        let (measured_omega, measured_dp, measured_f_drive) = cols.measured(speed.source, n);
        let speed_noise_f = (family == Family::Flow && speed.source == "omega_rad_s")
            .then(|| synthetic_speed_noise(&speed.omega_rad_s, &speed.omega_f, cutoff_hz, sample_hz));
        // the validation segment is the last share of the recorded time, gaps left out: a long pause would
        // otherwise swallow it
        let t_val = (1.0 - validation_fraction) * integrated;
        let split = active.iter().position(|&t| t >= t_val).unwrap_or(n - 1).clamp(100, n - 50);
        Ok(Series {
            family,
            t_s,
            sample_hz,
            split,
            omega_rad_s: speed.omega_rad_s,
            omega_f: speed.omega_f,
            alpha_f: speed.alpha_f,
            drive_torque_nm: drive.torque_nm,
            drive_torque_f,
            load_nm,
            load_f,
            dp_bar: drive.dp_bar,
            setpoint_hz: drive.setpoint_hz,
            f0_hz: drive.f0_hz,
            p_in0_bar: drive.p_in0_bar,
            state_f_hz: drive.state_f_hz,
            state_p_in_bar: drive.state_p_in_bar,
            cutoff_hz,
            speed_source: speed.source,
            sign_speed: SIGN_SPEED_RAD_S,
            f_drive_hz: f_drive.filter(|_| family != Family::Torque),
            nominal_dead_time_s: model.effects.dead_time.map_or(0.0, |d| d.seconds()),
            load,
            restarts,
            speed_noise_f,
            measured_omega,
            measured_dp,
            measured_f_drive,
            outliers,
        }
        .with_sign_speed())
    }

    /// The plant's smooth sign `tanh(ω/0.05)` is meant for a shaft turning at tens of rad/s. When the recording's
    /// speeds are not large against that band (the EMPS axis moves at a few cm/s), dry friction would be smeared
    /// over the whole operating range, so the band shrinks to 1 % of the speed scale: in effect `sgn(ω)`, as IDIM-LS
    /// takes it. For the reference plant the band stays the plant's own.
    fn with_sign_speed(mut self) -> Series {
        self.sign_speed = SIGN_SPEED_RAD_S.min(0.01 * self.speed_scale());
        self
    }

    /// `sgn(ω)` as the analysis takes it: `tanh(ω/sign_speed)`.
    pub fn sign(&self, omega: f64) -> f64 {
        (omega / self.sign_speed).tanh()
    }

    /// Below this filtered speed (rad/s) the motor is taken as standing still: ten sign bands, or four standard
    /// deviations of the speed sensor's noise through the regressors' low-pass (estimated from the measured speed
    /// against its filtered self), whichever is larger.
    pub fn standstill_speed(&self) -> f64 {
        let d: Vec<f64> =
            self.omega_rad_s.iter().zip(&self.omega_f).map(|(w, f)| (w - f).abs()).filter(|d| d.is_finite()).collect();
        let raw = 1.4826 * percentile(&d, 0.5);
        let through_filter = raw * (2.0 * self.cutoff_hz / self.sample_hz).sqrt();
        (10.0 * self.sign_speed).max(4.0 * through_filter)
    }

    pub fn len(&self) -> usize {
        self.t_s.len()
    }

    pub fn is_empty(&self) -> bool {
        self.t_s.is_empty()
    }

    /// A speed scale of the recording: the 95th percentile of |ω| (rad/s).
    pub fn speed_scale(&self) -> f64 {
        percentile(&self.omega_f.iter().map(|w| w.abs()).collect::<Vec<_>>(), 0.95).max(1e-6)
    }
}

/// Rows of synthetic noise used to estimate how much speed noise reaches the predicted ΔP.
const NOISE_ROWS: usize = 20_000;

/// White noise of the speed sensor's σ, low-passed as the measured speed is. σ comes from what the low-pass
/// removed, `ω − ω_f`, scaled up for the part of white noise inside the pass band.
fn synthetic_speed_noise(omega: &[f64], omega_f: &[f64], cutoff_hz: f64, sample_hz: f64) -> Vec<f64> {
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};
    let d: Vec<f64> = omega.iter().zip(omega_f).map(|(a, b)| a - b).filter(|v| v.is_finite()).collect();
    let mean = d.iter().sum::<f64>() / d.len().max(1) as f64;
    let var = d.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / d.len().max(1) as f64;
    let passed = (2.0 * cutoff_hz / sample_hz).clamp(0.0, 0.9);
    let sigma = (var / (1.0 - passed)).sqrt();
    let Ok(normal) = Normal::new(0.0, sigma.max(0.0)) else { return Vec::new() };
    // a fixed seed: the same recording gives the same analysis
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0x5eed_0fa1);
    let n = NOISE_ROWS.min(omega.len());
    let white: Vec<f64> = (0..n).map(|_| normal.sample(&mut rng)).collect();
    filtfilt_butter4(&white, cutoff_hz, sample_hz)
}

/// The most RK4 steps one free run may take: 10⁸ steps of [`FREE_RUN_STEP_S`] is about 28 hours of recording.
pub const MAX_FREE_RUN_STEPS: f64 = 1e8;

/// A recording sampled more slowly than this many times the model's fastest mode is refused (a clock in the wrong
/// unit): the reference plant's fastest mode is 25 ms, so 1 s samples (40×) are taken, with a warning above 10×.
pub const MAX_SAMPLE_OVER_MODE: f64 = 100.0;

/// Per row, the time recorded up to it with the gaps before `restarts` left out (each counts as nothing).
fn active_time(t_s: &[f64], restarts: &[usize]) -> Vec<f64> {
    let mut gap = restarts.iter().peekable();
    let mut total = 0.0;
    let mut out = Vec::with_capacity(t_s.len());
    for (k, &t) in t_s.iter().enumerate() {
        if k > 0 {
            if gap.peek() == Some(&&k) {
                gap.next();
            } else {
                total += t - t_s[k - 1];
            }
        }
        out.push(total);
    }
    out
}

/// A time for messages: plain when it reads well, else in scientific notation (1e300 has 301 digits).
fn short(v: f64) -> String {
    if v != 0.0 && !(1e-3..1e6).contains(&v.abs()) {
        format!("{v:.3e}")
    } else {
        format!("{}", (v * 1e6).round() / 1e6)
    }
}

/// A step between rows longer than this many median steps (and than [`GAP_MIN_S`]) is a gap in the recording.
pub const GAP_X_MEDIAN_STEP: f64 = 5.0;
/// The shortest gap (s): a few late polls are not a gap.
pub const GAP_MIN_S: f64 = 0.05;

/// The rows that follow a gap in the time stamps.
pub fn gaps(t_s: &[f64]) -> Vec<usize> {
    let steps: Vec<f64> = t_s.windows(2).map(|w| w[1] - w[0]).collect();
    let median = percentile(&steps, 0.5);
    let limit = (GAP_X_MEDIAN_STEP * median).max(GAP_MIN_S);
    steps.iter().enumerate().filter(|(_, d)| **d > limit).map(|(k, _)| k + 1).collect()
}

/// The `q` quantile (0…1) of the finite values; 0 for none.
pub fn percentile(x: &[f64], q: f64) -> f64 {
    let mut v: Vec<f64> = x.iter().copied().filter(|v| v.is_finite()).collect();
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q.clamp(0.0, 1.0)).round() as usize]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_model_load_is_taken_at_the_recordings_speed_and_shaft_angle() {
        // a torque-driven recording at a steady 50 rad/s (a ripple of 10⁻⁹: one value in every row is a stuck sensor)
        let n = 2000;
        let t: Vec<f64> = (0..n).map(|k| k as f64 * 1e-3).collect();
        let names = ["t_s", "omega_rad_s", "torque_nm"].map(String::from).to_vec();
        let omega = (0..n).map(|k| 50.0 + 1e-9 * (k % 2) as f64).collect();
        let rec = Recording::from_columns("steady", names, vec![t.clone(), omega, vec![10.0; n]]);
        let mut model = PlantModel::reference();
        model.load = LoadSpec::Centrifugal { torque_nm: 12.0, at_rad_s: 60.0 };
        let s = Series::extract(&rec, &model, 0.3).expect("extracts");
        assert!(s.load_nm.iter().all(|l| (l - 12.0 * (50.0f64 / 60.0).powi(2)).abs() < 1e-6), "{:?}", &s.load_nm[..3]);
        model.load = LoadSpec::ShaftAngle { mean_nm: 0.0, amplitude_nm: 1.0, cycles_per_rev: 1.0 };
        let s = Series::extract(&rec, &model, 0.3).expect("extracts");
        for (k, l) in s.load_nm.iter().enumerate() {
            assert!((l - (50.0 * t[k]).sin()).abs() < 1e-6, "row {k}: {l}");
        }
    }
}

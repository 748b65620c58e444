//! Load-torque profiles the simulator can apply (`[load]` of the plant model).

use crate::error::KeyError;
use serde::{Deserialize, Serialize};

/// `[load]`: what the load torque T_L(t) is. `recorded` means "taken from a recording" (estimate, analyze) or,
/// for the test-stand run of `simulate`, the built-in brake-load steps; `unknown` says that no recording has it.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize, Default)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum LoadSpec {
    /// No load torque.
    None,
    /// A constant torque.
    Constant { torque_nm: f64 },
    /// Levels applied in turn, each for `period_s`, cycling.
    Steps { levels_nm: Vec<f64>, period_s: f64 },
    /// From `from_nm` to `to_nm` linearly over `duration_s`, starting at `start_s`; held before and after.
    Ramp { from_nm: f64, to_nm: f64, start_s: f64, duration_s: f64 },
    /// A slowly increasing load (the paper's Fig. 3): `start_nm + rate_nm_per_s·t`, at most `max_nm`.
    Trend { start_nm: f64, rate_nm_per_s: f64, max_nm: f64 },
    /// `mean_nm + amplitude_nm·sin(2πt/period_s)`.
    Sine { mean_nm: f64, amplitude_nm: f64, period_s: f64 },
    /// From a recording (the `load_nm` column), or the test stand's brake program.
    #[default]
    Recorded,
    /// Not measured (no torque transducer, as on most plants): `analyze` finds what the flow balance shows and
    /// names nothing that the load could hide. In `simulate`/`sim`/`demo`, the test stand's brake program.
    Unknown,
}

/// The test stand's brake: load levels (N·m) applied in turn.
const BRAKE_LEVELS_NM: [f64; 6] = [0.0, 6.0, 12.0, 4.0, 15.0, 9.0];
/// How long each brake level is held; not a multiple of the setpoint program's steps so that the two decorrelate.
const BRAKE_PERIOD_S: f64 = 3.7;

impl LoadSpec {
    /// The load torque at time `t_s` (N·m).
    pub fn torque_nm(&self, t_s: f64) -> f64 {
        match self {
            LoadSpec::None => 0.0,
            LoadSpec::Constant { torque_nm } => *torque_nm,
            LoadSpec::Steps { levels_nm, period_s } => steps(levels_nm, *period_s, t_s),
            LoadSpec::Ramp { from_nm, to_nm, start_s, duration_s } => {
                let x = if *duration_s > 0.0 {
                    ((t_s - start_s) / duration_s).clamp(0.0, 1.0)
                } else if t_s >= *start_s {
                    1.0
                } else {
                    0.0
                };
                from_nm + (to_nm - from_nm) * x
            }
            LoadSpec::Trend { start_nm, rate_nm_per_s, max_nm } => (start_nm + rate_nm_per_s * t_s).min(*max_nm),
            LoadSpec::Sine { mean_nm, amplitude_nm, period_s } => {
                mean_nm + amplitude_nm * (2.0 * std::f64::consts::PI * t_s / period_s).sin()
            }
            LoadSpec::Recorded | LoadSpec::Unknown => steps(&BRAKE_LEVELS_NM, BRAKE_PERIOD_S, t_s),
        }
    }

    /// Checks the parameters, naming the key of the first bad one.
    pub fn validate(&self) -> Result<(), KeyError> {
        let bad = |key: &str, msg: String| Err(KeyError::new(format!("load.{key}"), msg));
        let all_finite = |vals: &[f64]| vals.iter().all(|v| v.is_finite());
        match self {
            LoadSpec::Steps { levels_nm, period_s } => {
                if levels_nm.is_empty() || !all_finite(levels_nm) {
                    return bad("levels_nm", "must be a non-empty list of finite numbers".into());
                }
                if !(*period_s > 0.0 && period_s.is_finite()) {
                    return bad("period_s", format!("must be > 0, got {period_s}"));
                }
            }
            LoadSpec::Sine { mean_nm, amplitude_nm, period_s } => {
                if !all_finite(&[*mean_nm, *amplitude_nm]) {
                    return bad("amplitude_nm", "mean_nm and amplitude_nm must be finite".into());
                }
                if !(*period_s > 0.0 && period_s.is_finite()) {
                    return bad("period_s", format!("must be > 0, got {period_s}"));
                }
            }
            LoadSpec::Ramp { from_nm, to_nm, start_s, duration_s } => {
                if !all_finite(&[*from_nm, *to_nm, *start_s]) {
                    return bad("from_nm", "from_nm, to_nm and start_s must be finite".into());
                }
                if !(*duration_s >= 0.0 && duration_s.is_finite()) {
                    return bad("duration_s", format!("must be ≥ 0, got {duration_s}"));
                }
            }
            LoadSpec::Trend { start_nm, rate_nm_per_s, max_nm }
                if !all_finite(&[*start_nm, *rate_nm_per_s]) || max_nm.is_nan() =>
            {
                return bad("rate_nm_per_s", "start_nm, rate_nm_per_s and max_nm must be numbers".into());
            }
            LoadSpec::Constant { torque_nm } if !torque_nm.is_finite() => {
                return bad("torque_nm", format!("must be finite, got {torque_nm}"));
            }
            _ => {}
        }
        Ok(())
    }
}

fn steps(levels: &[f64], period_s: f64, t_s: f64) -> f64 {
    if levels.is_empty() || period_s <= 0.0 {
        return 0.0;
    }
    let i = (t_s.max(0.0) / period_s).floor() as usize % levels.len();
    levels[i]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn profiles() {
        let s = LoadSpec::Steps { levels_nm: vec![1.0, 2.0], period_s: 1.0 };
        assert_eq!(s.torque_nm(0.5), 1.0);
        assert_eq!(s.torque_nm(1.5), 2.0);
        assert_eq!(s.torque_nm(2.5), 1.0);
        let r = LoadSpec::Ramp { from_nm: 0.0, to_nm: 10.0, start_s: 1.0, duration_s: 2.0 };
        assert_eq!(r.torque_nm(0.0), 0.0);
        assert_eq!(r.torque_nm(2.0), 5.0);
        assert_eq!(r.torque_nm(9.0), 10.0);
        let t = LoadSpec::Trend { start_nm: 1.0, rate_nm_per_s: 0.5, max_nm: 3.0 };
        assert_eq!(t.torque_nm(2.0), 2.0);
        assert_eq!(t.torque_nm(100.0), 3.0);
    }
}

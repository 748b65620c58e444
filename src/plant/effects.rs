//! The catalogue of physics beyond the nominal model (CONTRACT.md "Effects catalogue"); ids and names are fixed.

use crate::error::KeyError;
use serde::{Deserialize, Serialize};

/// Dry friction `T_c·sgn(ω)`.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct CoulombFriction {
    pub torque_nm: f64,
}

/// Extra friction at low speed on top of Coulomb: `(T_s − T_c)·exp(−(ω/ω_s)²)·sgn(ω)`.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct StribeckFriction {
    pub breakaway_nm: f64,
    pub speed_rad_s: f64,
}

/// Constant torque bias: an unmodelled constant load, or a pressure-sensor offset.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct TorqueOffset {
    pub torque_nm: f64,
}

/// Leakage beyond `hydraulics.leakage_l_min_per_bar` (a worn pump or motor).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct InternalLeakage {
    pub l_min_per_bar: f64,
}

/// Delay between the setpoint and the drive's response.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct DeadTime {
    pub ms: f64,
}

impl DeadTime {
    /// The delay in seconds, as the plant and the analysis both take it.
    pub fn seconds(&self) -> f64 {
        self.ms * 1e-3
    }
}

/// Air in the oil: the effective bulk modulus replaces the model's.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct EntrainedAir {
    pub bulk_modulus_bar: f64,
}

/// Induction-motor slip: pump speed falls with pump torque.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct MotorSlip {
    pub rpm_per_nm: f64,
}

/// Every effect of the catalogue; `None` = off.
#[derive(Debug, Clone, Copy, Default, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Effects {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub coulomb_friction: Option<CoulombFriction>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stribeck_friction: Option<StribeckFriction>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub torque_offset: Option<TorqueOffset>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub internal_leakage: Option<InternalLeakage>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub dead_time: Option<DeadTime>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub entrained_air: Option<EntrainedAir>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub motor_slip: Option<MotorSlip>,
}

/// The catalogue ids, in the contract's order.
pub const EFFECT_IDS: [&str; 7] = [
    "coulomb_friction",
    "stribeck_friction",
    "torque_offset",
    "internal_leakage",
    "dead_time",
    "entrained_air",
    "motor_slip",
];

impl Effects {
    /// Ids of the effects that are switched on.
    pub fn active_ids(&self) -> Vec<&'static str> {
        let on = [
            self.coulomb_friction.is_some(),
            self.stribeck_friction.is_some(),
            self.torque_offset.is_some(),
            self.internal_leakage.is_some(),
            self.dead_time.is_some(),
            self.entrained_air.is_some(),
            self.motor_slip.is_some(),
        ];
        EFFECT_IDS.iter().zip(on).filter_map(|(id, on)| on.then_some(*id)).collect()
    }

    /// Checks every parameter, naming the key of the first bad one.
    pub fn validate(&self) -> Result<(), KeyError> {
        let nonneg = |key: &str, v: f64| -> Result<(), KeyError> {
            if v.is_finite() && v >= 0.0 {
                Ok(())
            } else {
                Err(KeyError::new(
                    format!("effects.{key}"),
                    format!("must be finite and ≥ 0, got {}", crate::units::shown(v)),
                ))
            }
        };
        let positive = |key: &str, v: f64| -> Result<(), KeyError> {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(KeyError::new(
                    format!("effects.{key}"),
                    format!("must be finite and > 0, got {}", crate::units::shown(v)),
                ))
            }
        };
        if let Some(e) = self.coulomb_friction {
            nonneg("coulomb_friction.torque_nm", e.torque_nm)?;
        }
        if let Some(e) = self.stribeck_friction {
            nonneg("stribeck_friction.breakaway_nm", e.breakaway_nm)?;
            positive("stribeck_friction.speed_rad_s", e.speed_rad_s)?;
        }
        if let Some(e) = self.torque_offset
            && !e.torque_nm.is_finite()
        {
            return Err(KeyError::new(
                "effects.torque_offset.torque_nm".into(),
                format!("must be finite, got {}", e.torque_nm),
            ));
        }
        if let Some(e) = self.internal_leakage {
            nonneg("internal_leakage.l_min_per_bar", e.l_min_per_bar)?;
        }
        if let Some(e) = self.dead_time {
            nonneg("dead_time.ms", e.ms)?;
            if e.ms > 10_000.0 {
                return Err(KeyError::new("effects.dead_time.ms".into(), format!("must be ≤ 10000, got {}", e.ms)));
            }
        }
        if let Some(e) = self.entrained_air {
            positive("entrained_air.bulk_modulus_bar", e.bulk_modulus_bar)?;
            super::model::bulk_modulus_in_range("effects.entrained_air.bulk_modulus_bar", e.bulk_modulus_bar)?;
        }
        if let Some(e) = self.motor_slip {
            nonneg("motor_slip.rpm_per_nm", e.rpm_per_nm)?;
        }
        Ok(())
    }
}

/// How fast an effect's main parameter grows, per hour of plant time (negative: falls).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Growth {
    pub growth_per_hour: f64,
}

/// `[wear]`: a plant that wears while it runs. Each entry names an effect of `[effects]` and moves its main
/// parameter (the first of its table: `torque_nm`, `breakaway_nm`, `l_min_per_bar`, `ms`, `bulk_modulus_bar`,
/// `rpm_per_nm`) by `growth_per_hour` for every hour of plant time, so that a leak can grow while a test runs.
#[derive(Debug, Clone, Copy, Default, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Wear {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub coulomb_friction: Option<Growth>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stribeck_friction: Option<Growth>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub torque_offset: Option<Growth>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub internal_leakage: Option<Growth>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub dead_time: Option<Growth>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub entrained_air: Option<Growth>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub motor_slip: Option<Growth>,
}

/// The least bulk modulus wear can bring the oil to (bar): a frothy oil, but still a fluid.
const MIN_WORN_BULK_MODULUS_BAR: f64 = 100.0;

impl Wear {
    /// True when nothing wears.
    pub fn is_none(&self) -> bool {
        *self == Wear::default()
    }

    fn entries(&self) -> [(&'static str, Option<Growth>); 7] {
        [
            ("coulomb_friction", self.coulomb_friction),
            ("stribeck_friction", self.stribeck_friction),
            ("torque_offset", self.torque_offset),
            ("internal_leakage", self.internal_leakage),
            ("dead_time", self.dead_time),
            ("entrained_air", self.entrained_air),
            ("motor_slip", self.motor_slip),
        ]
    }

    /// Each rate finite, and each worn effect switched on in `effects` (wear moves a parameter; it does not invent
    /// the effect's other parameters).
    pub fn validate(&self, effects: &Effects) -> Result<(), KeyError> {
        let on = effects.active_ids();
        for (id, growth) in self.entries() {
            let Some(g) = growth else { continue };
            if !g.growth_per_hour.is_finite() {
                return Err(KeyError::new(
                    format!("wear.{id}.growth_per_hour"),
                    format!("must be finite, got {}", g.growth_per_hour),
                ));
            }
            if !on.contains(&id) {
                return Err(KeyError::new(
                    format!("wear.{id}"),
                    format!("wears an effect that is off: add [effects.{id}]"),
                ));
            }
        }
        Ok(())
    }

    /// `effects` after `hours` of plant time, each worn parameter kept in its valid range.
    pub fn apply(&self, effects: &Effects, hours: f64) -> Effects {
        let mut e = *effects;
        let grown = |g: Option<Growth>, v: f64| g.map_or(v, |g| v + g.growth_per_hour * hours);
        if let Some(x) = e.coulomb_friction.as_mut() {
            x.torque_nm = grown(self.coulomb_friction, x.torque_nm).max(0.0);
        }
        if let Some(x) = e.stribeck_friction.as_mut() {
            x.breakaway_nm = grown(self.stribeck_friction, x.breakaway_nm).max(0.0);
        }
        if let Some(x) = e.torque_offset.as_mut() {
            x.torque_nm = grown(self.torque_offset, x.torque_nm);
        }
        if let Some(x) = e.internal_leakage.as_mut() {
            x.l_min_per_bar = grown(self.internal_leakage, x.l_min_per_bar).max(0.0);
        }
        if let Some(x) = e.dead_time.as_mut() {
            x.ms = grown(self.dead_time, x.ms).clamp(0.0, 10_000.0);
        }
        if let Some(x) = e.entrained_air.as_mut() {
            x.bulk_modulus_bar = grown(self.entrained_air, x.bulk_modulus_bar).max(MIN_WORN_BULK_MODULUS_BAR);
        }
        if let Some(x) = e.motor_slip.as_mut() {
            x.rpm_per_nm = grown(self.motor_slip, x.rpm_per_nm).max(0.0);
        }
        e
    }
}

/// Each effect's parameters under the catalogue's names, its main parameter (the one `[wear]` moves) first.
pub fn parameter_names(id: &str) -> &'static [&'static str] {
    match id {
        "coulomb_friction" | "torque_offset" => &["torque_nm"],
        "stribeck_friction" => &["breakaway_nm", "speed_rad_s"],
        "internal_leakage" => &["l_min_per_bar"],
        "dead_time" => &["ms"],
        "entrained_air" => &["bulk_modulus_bar"],
        "motor_slip" => &["rpm_per_nm"],
        _ => &[],
    }
}

//! The plant model file (`config/plant.toml`): parsed strictly, then validated so that every number is usable.

use crate::error::KeyError;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::effects::{Effects, Wear};
use super::load::LoadSpec;

/// `[drive]`: the frequency drive (VFD) and its induction motor.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Drive {
    pub pole_pairs: u32,
    pub ramp_hz_per_s: f64,
    pub time_constant_s: f64,
    #[serde(default = "default_max_hz")]
    pub max_hz: f64,
    /// Watchdog timeout of the simulated drive's comm-loss monitoring.
    #[serde(default = "default_comm_timeout_ms")]
    pub comm_timeout_ms: u64,
}

fn default_max_hz() -> f64 {
    60.0
}
fn default_comm_timeout_ms() -> u64 {
    1000
}

/// `[pump]`: fixed-displacement pump.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Pump {
    pub displacement_cm3: f64,
}

/// `[motor]`: the hydraulic motor and what it drives (for a torque-driven recording: the whole mechanism).
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Motor {
    /// Needed only when the drive torque comes from pressures.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub displacement_cm3: Option<f64>,
    pub inertia_kg_m2: f64,
    pub viscous_nm_s_rad: f64,
}

/// `[hydraulics]`: the high-pressure line between pump and motor.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Hydraulics {
    pub volume_l: f64,
    pub bulk_modulus_bar: f64,
    pub back_pressure_bar: f64,
    pub leakage_l_min_per_bar: f64,
}

/// `[sensors]`: white-noise σ of each measurement and the sample period.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Sensors {
    #[serde(default)]
    pub pressure_noise_bar: f64,
    #[serde(default)]
    pub speed_noise_rad_s: f64,
    #[serde(default)]
    pub load_noise_nm: f64,
    #[serde(default = "default_sample_ms")]
    pub sample_ms: f64,
}

fn default_sample_ms() -> f64 {
    1.0
}

impl Default for Sensors {
    fn default() -> Self {
        Sensors { pressure_noise_bar: 0.0, speed_noise_rad_s: 0.0, load_noise_nm: 0.0, sample_ms: 1.0 }
    }
}

/// A whole plant model file. Sections other than `[motor]` are optional in the file, because a torque-driven
/// recording needs only the mechanics; [`PlantModel::hydraulic`] checks that a simulation has what it needs.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct PlantModel {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub drive: Option<Drive>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pump: Option<Pump>,
    pub motor: Motor,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hydraulics: Option<Hydraulics>,
    #[serde(default)]
    pub sensors: Sensors,
    #[serde(default)]
    pub load: LoadSpec,
    #[serde(default)]
    pub effects: Effects,
    /// How the effects change while the plant runs (the simulator's plant only; a nominal model does not wear).
    #[serde(default, skip_serializing_if = "Wear::is_none")]
    pub wear: Wear,
    /// Estimator settings (λ, η, covariance, noise, bounds); free-form here, validated by the estimator.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub estimator: Option<toml::Table>,
}

/// The shortest sample period: the real-time simulator steps every sample that is due at each tick of a
/// 1 ms-resolution timer, so 0.1 ms is ten RK4 steps a tick; far shorter, it cannot keep up (and a period that
/// rounds to 0 ns is no timer at all).
pub const MIN_SAMPLE_MS: f64 = 0.1;
/// The longest sample period (1 Hz).
pub const MAX_SAMPLE_MS: f64 = 1000.0;
/// The longest watchdog timeout of the simulated drive.
pub const MAX_COMM_TIMEOUT_MS: u64 = 3_600_000;
/// Upper bounds beyond any plant (a helper's black-box run took `inertia_kg_m2 = 1e308` and
/// `speed_noise_rad_s = 1e308`: `estimate` wrote J 1e308 on every row, `simulate` speeds of ±1e308 that its own
/// `estimate` then refused): the inertia of a ship's shaft line is about 1e5 kg·m², a tachometer's noise a few rad/s.
pub const MAX_INERTIA_KG_M2: f64 = 1e6;
pub const MAX_SPEED_NOISE_RAD_S: f64 = 1e3;
pub const MAX_PRESSURE_NOISE_BAR: f64 = 1e3;
pub const MAX_LOAD_NOISE_NM: f64 = 1e6;
/// The oil's bulk modulus within what a liquid with air in it can be (a black-box run took `bulk_modulus_bar =
/// 1e-300`: its free run left the recording by a speed NRMSE of 20 and `analyze` named a Stribeck friction at
/// 723 rad/s): no mixture is softer than the air itself at atmospheric pressure (1.4 bar adiabatic), and no liquid
/// is stiffer than mercury (2.9e5 bar). The same bounds hold for `effects.entrained_air.bulk_modulus_bar`.
pub const MIN_BULK_MODULUS_BAR: f64 = 1.0;
pub const MAX_BULK_MODULUS_BAR: f64 = 1e6;
/// The oil volume under pressure: a line of a hydrostatic drive holds litres, a ship's whole hydraulic system tens of
/// cubic metres; 1000 m³ is beyond any (`volume_l = 1e300` was taken).
pub const MAX_VOLUME_L: f64 = 1e6;

/// A bulk modulus (bar) under `key` within [`MIN_BULK_MODULUS_BAR`] ..= [`MAX_BULK_MODULUS_BAR`].
pub fn bulk_modulus_in_range(key: &str, bar: f64) -> Result<(), KeyError> {
    if (MIN_BULK_MODULUS_BAR..=MAX_BULK_MODULUS_BAR).contains(&bar) {
        Ok(())
    } else {
        Err(KeyError::new(
            key.into(),
            format!(
                "must be {MIN_BULK_MODULUS_BAR} ..= {MAX_BULK_MODULUS_BAR:e} bar (air at atmospheric pressure to \
                 beyond any liquid), got {bar:e}; check the value and its unit"
            ),
        ))
    }
}

/// The parts a pressure-driven simulation needs, borrowed from a model that has them all.
#[derive(Debug, Clone, Copy)]
pub struct HydraulicParts<'a> {
    pub drive: &'a Drive,
    pub pump: &'a Pump,
    pub motor_displacement_cm3: f64,
    pub hydraulics: &'a Hydraulics,
}

/// What can be wrong with a model file. Every variant is bad input (exit 2) except `Io`.
#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    /// The reason is in the message and not the error's source, so that a chain prints it once.
    #[error("cannot read model file {path}: {error}")]
    Io { path: PathBuf, error: std::io::Error },
    #[error("model file {path}: {message}")]
    Syntax { path: String, message: String },
    #[error("model file {path}: key `{key}` {message}")]
    Invalid { path: String, key: String, message: String },
}

impl ModelError {
    /// True when the user can fix it: by editing the file, or naming one that exists (exit code 2).
    pub fn is_bad_input(&self) -> bool {
        match self {
            ModelError::Io { error, .. } => crate::error::unreadable_is_bad_input(error),
            _ => true,
        }
    }
}

impl PlantModel {
    /// Reads and validates a model file.
    pub fn load(path: &Path) -> Result<PlantModel, ModelError> {
        let text = crate::error::read_text_file(path).map_err(|error| ModelError::Io { path: path.into(), error })?;
        PlantModel::parse(&text, &path.display().to_string())
    }

    /// Parses and validates model text; `origin` names the file in errors.
    pub fn parse(text: &str, origin: &str) -> Result<PlantModel, ModelError> {
        let model: PlantModel = toml::from_str(text).map_err(|e| ModelError::Syntax {
            path: origin.to_string(),
            message: e.to_string().trim_end().to_string(),
        })?;
        model.validate().map_err(|KeyError { key, message }| ModelError::Invalid {
            path: origin.to_string(),
            key,
            message,
        })?;
        Ok(model)
    }

    /// The reference plant of CONTRACT.md (the content of `config/plant.toml`).
    pub fn reference() -> PlantModel {
        // The file is the one source of truth; it is embedded so the binary runs anywhere.
        match PlantModel::parse(REFERENCE_TOML, "config/plant.toml") {
            Ok(m) => m,
            Err(e) => unreachable!("the embedded reference plant is valid: {e}"),
        }
    }

    /// Writes the model as TOML that [`PlantModel::parse`] accepts.
    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).unwrap_or_else(|e| format!("# cannot serialise model: {e}\n"))
    }

    /// The sample period in seconds.
    pub fn sample_s(&self) -> f64 {
        self.sensors.sample_ms * 1e-3
    }

    /// The sections a pressure-driven simulation needs, or the key that is missing.
    pub fn hydraulic(&self) -> Result<HydraulicParts<'_>, KeyError> {
        let need =
            |what: &str| KeyError::new(what.to_string(), "is required to simulate the hydraulic plant".to_string());
        Ok(HydraulicParts {
            drive: self.drive.as_ref().ok_or_else(|| need("[drive]"))?,
            pump: self.pump.as_ref().ok_or_else(|| need("[pump]"))?,
            motor_displacement_cm3: self.motor.displacement_cm3.ok_or_else(|| need("motor.displacement_cm3"))?,
            hydraulics: self.hydraulics.as_ref().ok_or_else(|| need("[hydraulics]"))?,
        })
    }

    /// Checks every number, returning the key and what is wrong with it.
    pub fn validate(&self) -> Result<(), KeyError> {
        fn positive(key: &str, v: f64) -> Result<(), KeyError> {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(KeyError::new(key.into(), format!("must be finite and > 0, got {}", crate::units::shown(v))))
            }
        }
        fn nonneg(key: &str, v: f64) -> Result<(), KeyError> {
            if v.is_finite() && v >= 0.0 {
                Ok(())
            } else {
                Err(KeyError::new(key.into(), format!("must be finite and ≥ 0, got {}", crate::units::shown(v))))
            }
        }
        fn at_most(key: &str, v: f64, max: f64) -> Result<(), KeyError> {
            if v <= max { Ok(()) } else { Err(KeyError::new(key.into(), format!("must be ≤ {max:e}, got {v:e}"))) }
        }
        if let Some(d) = &self.drive {
            if d.pole_pairs == 0 {
                return Err(KeyError::new("drive.pole_pairs".into(), "must be ≥ 1, got 0".into()));
            }
            positive("drive.ramp_hz_per_s", d.ramp_hz_per_s)?;
            positive("drive.time_constant_s", d.time_constant_s)?;
            positive("drive.max_hz", d.max_hz)?;
            if !(1..=MAX_COMM_TIMEOUT_MS).contains(&d.comm_timeout_ms) {
                return Err(KeyError::new(
                    "drive.comm_timeout_ms".into(),
                    format!("must be 1 ..= {MAX_COMM_TIMEOUT_MS} (one hour), got {}", d.comm_timeout_ms),
                ));
            }
        }
        if let Some(p) = &self.pump {
            positive("pump.displacement_cm3", p.displacement_cm3)?;
        }
        if let Some(d) = self.motor.displacement_cm3 {
            positive("motor.displacement_cm3", d)?;
        }
        positive("motor.inertia_kg_m2", self.motor.inertia_kg_m2)?;
        at_most("motor.inertia_kg_m2", self.motor.inertia_kg_m2, MAX_INERTIA_KG_M2)?;
        nonneg("motor.viscous_nm_s_rad", self.motor.viscous_nm_s_rad)?;
        if let Some(h) = &self.hydraulics {
            positive("hydraulics.volume_l", h.volume_l)?;
            at_most("hydraulics.volume_l", h.volume_l, MAX_VOLUME_L)?;
            positive("hydraulics.bulk_modulus_bar", h.bulk_modulus_bar)?;
            bulk_modulus_in_range("hydraulics.bulk_modulus_bar", h.bulk_modulus_bar)?;
            nonneg("hydraulics.back_pressure_bar", h.back_pressure_bar)?;
            nonneg("hydraulics.leakage_l_min_per_bar", h.leakage_l_min_per_bar)?;
        }
        nonneg("sensors.pressure_noise_bar", self.sensors.pressure_noise_bar)?;
        nonneg("sensors.speed_noise_rad_s", self.sensors.speed_noise_rad_s)?;
        nonneg("sensors.load_noise_nm", self.sensors.load_noise_nm)?;
        at_most("sensors.pressure_noise_bar", self.sensors.pressure_noise_bar, MAX_PRESSURE_NOISE_BAR)?;
        at_most("sensors.speed_noise_rad_s", self.sensors.speed_noise_rad_s, MAX_SPEED_NOISE_RAD_S)?;
        at_most("sensors.load_noise_nm", self.sensors.load_noise_nm, MAX_LOAD_NOISE_NM)?;
        let ms = self.sensors.sample_ms;
        if !(ms.is_finite() && (MIN_SAMPLE_MS..=MAX_SAMPLE_MS).contains(&ms)) {
            return Err(KeyError::new(
                "sensors.sample_ms".into(),
                format!(
                    "must be {MIN_SAMPLE_MS} ..= {MAX_SAMPLE_MS} (10 kHz to 1 Hz), got {}",
                    crate::units::shown(ms)
                ),
            ));
        }
        self.load.validate()?;
        self.effects.validate()?;
        self.wear.validate(&self.effects)?;
        super::dynamics::stiffness(self)
    }

    /// True when some effect wears (`[wear]`).
    pub fn wears(&self) -> bool {
        !self.wear.is_none()
    }

    /// The model as it is after `t_s` seconds of plant time: each worn effect moved by its growth.
    pub fn at(&self, t_s: f64) -> PlantModel {
        if !self.wears() {
            return self.clone();
        }
        PlantModel { effects: self.wear.apply(&self.effects, t_s / 3600.0), ..self.clone() }
    }
}

/// `config/plant.toml`, embedded.
pub const REFERENCE_TOML: &str = include_str!("../../config/plant.toml");

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reference_parses_and_round_trips() {
        let m = PlantModel::reference();
        assert_eq!(m.motor.inertia_kg_m2, 0.08);
        assert!(m.hydraulic().is_ok());
        let again = PlantModel::parse(&m.to_toml(), "round trip").expect("own output parses");
        assert_eq!(again, m);
    }

    #[test]
    fn a_model_beyond_any_plant_is_refused_naming_the_key() {
        let refused = |edit: &dyn Fn(&mut PlantModel)| {
            let mut m = PlantModel::reference();
            edit(&mut m);
            m.validate().expect_err("refused").key
        };
        assert_eq!(refused(&|m| m.motor.inertia_kg_m2 = 1e308), "motor.inertia_kg_m2");
        assert_eq!(refused(&|m| m.sensors.speed_noise_rad_s = 1e308), "sensors.speed_noise_rad_s");
        assert_eq!(refused(&|m| m.sensors.pressure_noise_bar = 1e308), "sensors.pressure_noise_bar");
        assert_eq!(refused(&|m| m.sensors.load_noise_nm = 1e308), "sensors.load_noise_nm");
        let hydraulics = |edit: fn(&mut Hydraulics)| {
            move |m: &mut PlantModel| {
                if let Some(h) = m.hydraulics.as_mut() {
                    edit(h)
                }
            }
        };
        assert_eq!(refused(&hydraulics(|h| h.bulk_modulus_bar = 1e-300)), "hydraulics.bulk_modulus_bar");
        assert_eq!(refused(&hydraulics(|h| h.bulk_modulus_bar = 1e300)), "hydraulics.bulk_modulus_bar");
        assert_eq!(refused(&hydraulics(|h| h.volume_l = 1e300)), "hydraulics.volume_l");
        let air = |b: f64| {
            move |m: &mut PlantModel| {
                m.effects.entrained_air = Some(crate::plant::effects::EntrainedAir { bulk_modulus_bar: b })
            }
        };
        assert_eq!(refused(&air(1e-300)), "effects.entrained_air.bulk_modulus_bar");
        let mut edge = PlantModel::reference();
        if let Some(h) = edge.hydraulics.as_mut() {
            (h.bulk_modulus_bar, h.volume_l) = (MIN_BULK_MODULUS_BAR, MAX_VOLUME_L);
        }
        edge.validate().expect("at the bounds");
        let mut big = PlantModel::reference();
        (big.motor.inertia_kg_m2, big.sensors.speed_noise_rad_s) = (MAX_INERTIA_KG_M2, MAX_SPEED_NOISE_RAD_S);
        big.validate().expect("at the bounds");
    }

    const WORN: &str =
        "\n[effects.internal_leakage]\nl_min_per_bar = 0.01\n\n[wear.internal_leakage]\ngrowth_per_hour = 0.36\n";

    #[test]
    fn a_wearing_effect_grows_with_plant_time_and_round_trips() {
        let m = PlantModel::parse(&format!("{REFERENCE_TOML}{WORN}"), "worn.toml").expect("parses");
        assert!(m.wears());
        let leak = |t: f64| m.at(t).effects.internal_leakage.map(|l| l.l_min_per_bar);
        assert_eq!(leak(0.0), Some(0.01));
        assert!((leak(600.0).unwrap_or(0.0) - 0.07).abs() < 1e-12, "{:?}", leak(600.0));
        assert_eq!(m.at(600.0).wear, m.wear, "the worn model still knows how it wears");
        let again = PlantModel::parse(&m.to_toml(), "round trip").expect("own output parses");
        assert_eq!(again, m);
        // Falling parameters stop at their range.
        let shrinking = format!("{REFERENCE_TOML}{}", WORN.replace("0.36", "-3.6"));
        let m = PlantModel::parse(&shrinking, "worn.toml").expect("parses");
        assert_eq!(m.at(3600.0).effects.internal_leakage.map(|l| l.l_min_per_bar), Some(0.0));
        assert!(!PlantModel::reference().wears());
    }

    #[test]
    fn wear_of_an_effect_that_is_off_or_not_finite_is_refused_by_key() {
        let text = format!("{REFERENCE_TOML}\n[wear.dead_time]\ngrowth_per_hour = 10.0\n");
        let err = PlantModel::parse(&text, "p.toml").expect_err("dead time is off").to_string();
        assert!(err.contains("wear.dead_time") && err.contains("effects.dead_time"), "{err}");
        let text = format!("{REFERENCE_TOML}{}", WORN.replace("0.36", "inf"));
        let err = PlantModel::parse(&text, "p.toml").expect_err("not finite").to_string();
        assert!(err.contains("wear.internal_leakage.growth_per_hour"), "{err}");
        let text = format!("{REFERENCE_TOML}{}", WORN.replace("growth_per_hour", "growth_per_day"));
        let err = PlantModel::parse(&text, "p.toml").expect_err("unknown key").to_string();
        assert!(err.contains("growth_per_day"), "{err}");
    }

    #[test]
    fn rates_and_durations_beyond_what_the_simulator_can_run_are_refused_by_key() {
        for (from, to, key) in [
            ("sample_ms = 1.0", "sample_ms = 1e-7", "sensors.sample_ms"),
            ("sample_ms = 1.0", "sample_ms = 0.09", "sensors.sample_ms"),
            ("sample_ms = 1.0", "sample_ms = 1001.0", "sensors.sample_ms"),
            ("sample_ms = 1.0", "sample_ms = nan", "sensors.sample_ms"),
            ("comm_timeout_ms = 1000", "comm_timeout_ms = 3600001", "drive.comm_timeout_ms"),
        ] {
            assert!(REFERENCE_TOML.contains(from), "{from}");
            let msg = PlantModel::parse(&REFERENCE_TOML.replace(from, to), "p.toml").expect_err(to).to_string();
            assert!(msg.contains(key) && msg.contains("p.toml"), "{to}: {msg}");
        }
        let fast = REFERENCE_TOML.replace("sample_ms = 1.0", "sample_ms = 0.1");
        assert_eq!(PlantModel::parse(&fast, "p.toml").expect("10 kHz").sample_s(), 1e-4);
    }

    #[test]
    fn unknown_key_is_named() {
        let text = REFERENCE_TOML.replace("inertia_kg_m2", "inertia_kgm2");
        let err = PlantModel::parse(&text, "p.toml").expect_err("unknown key");
        let msg = err.to_string();
        assert!(msg.contains("inertia_kgm2"), "{msg}");
        assert!(msg.contains("p.toml"), "{msg}");
        assert!(err.is_bad_input());
    }

    #[test]
    fn wrong_type_and_impossible_values_are_named() {
        let text = REFERENCE_TOML.replace("volume_l = 0.3", "volume_l = \"big\"");
        let msg = PlantModel::parse(&text, "p.toml").expect_err("type").to_string();
        assert!(msg.contains("volume_l"), "{msg}");
        let text = REFERENCE_TOML.replace("inertia_kg_m2 = 0.08", "inertia_kg_m2 = -0.08");
        let msg = PlantModel::parse(&text, "p.toml").expect_err("negative").to_string();
        assert!(msg.contains("motor.inertia_kg_m2"), "{msg}");
    }

    #[test]
    fn effects_and_loads_parse() {
        let text =
            format!("{REFERENCE_TOML}\n[effects.dead_time]\nms = 30.0\n[effects.coulomb_friction]\ntorque_nm = 1.5\n")
                .replace("kind = \"recorded\"", "kind = \"steps\"\nlevels_nm = [0.0, 5.0]\nperiod_s = 2.0");
        let m = PlantModel::parse(&text, "p.toml").expect("valid");
        assert_eq!(m.effects.active_ids(), vec!["coulomb_friction", "dead_time"]);
        assert!(matches!(m.load, LoadSpec::Steps { .. }));
        let bad = text.replace("ms = 30.0", "ms = 30.0\nseconds = 1.0");
        let msg = PlantModel::parse(&bad, "p.toml").expect_err("unknown effect key").to_string();
        assert!(msg.contains("seconds"), "{msg}");
    }

    #[test]
    fn torque_only_model_is_valid_but_not_simulable_hydraulically() {
        let m = PlantModel::parse(
            "[motor]\ninertia_kg_m2 = 95.0\nviscous_nm_s_rad = 200.0\n[load]\nkind = \"none\"\n",
            "emps",
        )
        .expect("valid");
        assert_eq!(m.hydraulic().expect_err("no pump").key, "[drive]");
    }
}

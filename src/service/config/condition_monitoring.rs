//! `[drives.condition]`: the condition checks' window, period, limits and energy price.

use super::*;

/// `[drives.condition]` as written.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub(super) struct RawCondition {
    enabled: bool,
    window_s: f64,
    every_s: f64,
    model: Option<String>,
    limits: condition::Limits,
    energy_price_per_kwh: Option<f64>,
}

impl Default for RawCondition {
    fn default() -> Self {
        RawCondition {
            enabled: false,
            window_s: 120.0,
            every_s: 300.0,
            model: None,
            limits: condition::Limits::new(),
            energy_price_per_kwh: None,
        }
    }
}

/// A drive's condition monitoring, validated.
#[derive(Debug, Clone)]
pub struct ConditionSettings {
    pub enabled: bool,
    pub window: Duration,
    pub every: Duration,
    /// The nominal model the checks compare against (the estimator's unless `model` says otherwise), its load
    /// set to "recorded": the service's data carry no load, so the load is unknown.
    pub model: PlantModel,
    pub limits: condition::Limits,
    /// The price of a kWh (any currency): the energy report then says what each effect costs a day and a year.
    pub energy_price_per_kwh: Option<f64>,
}

/// Validates `[drives.condition]`; `key` is its prefix (`drives[0].condition`), `estimator_model` the default model,
/// `resolve` finds a relative model path. Errors name the key.
pub(super) fn validate_condition(
    raw: RawCondition,
    key: &str,
    estimator_model: &PlantModel,
    resolve: impl Fn(&str) -> PathBuf,
) -> Result<ConditionSettings, KeyError> {
    let k = |s: &str| format!("{key}.{s}");
    if !(raw.window_s.is_finite() && (5.0..=3600.0).contains(&raw.window_s)) {
        return Err(KeyError::new(k("window_s"), format!("must be 5 ..= 3600 s, got {}", raw.window_s)));
    }
    if !(raw.every_s.is_finite() && (1.0..=86_400.0).contains(&raw.every_s)) {
        return Err(KeyError::new(k("every_s"), format!("must be 1 ..= 86400 s, got {}", raw.every_s)));
    }
    let mut model = match raw.model {
        None => estimator_model.clone(),
        Some(p) => {
            let path = resolve(&p);
            let model = PlantModel::load(&path).map_err(|e| KeyError::new(k("model"), e.to_string()))?;
            // its `[estimator]` table checked as every model file's is (`hydrolens analyze` on it would refuse it)
            crate::estimator::EstimatorSettings::from_model(&model, &path.display().to_string())
                .map_err(|e| KeyError::new(k("model"), e.to_string()))?;
            model
        }
    };
    if model.motor.displacement_cm3.is_none() || model.hydraulics.is_none() || model.pump.is_none() {
        return Err(KeyError::new(
            k("model"),
            "the model needs [pump], [motor] displacement_cm3 and [hydraulics]".into(),
        ));
    }
    model.load = LoadSpec::Recorded;
    condition::validate_limits(&raw.limits, &k("limits"))?;
    if let Some(p) = raw.energy_price_per_kwh
        && !(p.is_finite() && p >= 0.0)
    {
        return Err(KeyError::new(k("energy_price_per_kwh"), format!("must be a finite price ≥ 0, got {p}")));
    }
    Ok(ConditionSettings {
        enabled: raw.enabled,
        window: Duration::from_secs_f64(raw.window_s),
        every: Duration::from_secs_f64(raw.every_s),
        model,
        limits: raw.limits,
        energy_price_per_kwh: raw.energy_price_per_kwh,
    })
}

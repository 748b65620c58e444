//! One `[[drives]]` entry: its name, periods, control, estimator, plausible ranges, watchdog and register map.

use super::condition_monitoring::validate_condition;
use super::line::validate_transport;
use super::*;

pub(super) fn validate_drive(d: RawDrive, i: usize, base: Option<&Path>) -> Result<DriveSettings, Invalid> {
    let key = |k: &str| format!("drives[{i}].{k}");
    check_name(&d.name, &key)?;
    let (transport, address) = validate_transport(&d, &key)?;
    let stale_ms = validate_periods(&d, &key)?;
    let c = validate_control(&d.control, &key)?;
    let (estimator, model, feed_forward) = validate_estimator(d.estimator, &key, base)?;
    let ranges = validate_ranges(&d.limits, &key)?;
    let registers = apply_overrides(d.registers, &key("registers"))?;
    let condition = validate_condition(d.condition, &key("condition"), &model, |p| resolve(p, base))?;
    check_setpoint_fits(&registers.frequency_setpoint_hz, &c, &key)?;
    check_within_the_drive(&c, &model, &key)?;
    check_watchdog(d.comm_timeout_ms, (d.watchdog_ms, d.poll_ms, c.mode), &model, &key)?;
    if c.mode.writes() && d.unit_id == 0 {
        // on TCP too: a gateway passes a write to unit 0 to every device on its serial line, none of which answers
        return Err(KeyError::new(
            key("unit_id"),
            "0 is the broadcast address: in a writing mode a gateway would pass every setpoint to each device on its \
             line; use the drive's own unit id (1 ..= 247)"
                .to_string(),
        ));
    }
    let settings = DriveSettings {
        name: d.name,
        address,
        transport,
        unit_id: d.unit_id,
        poll: Duration::from_millis(d.poll_ms),
        timeout: Duration::from_millis(d.timeout_ms),
        stale_after: Duration::from_millis(stale_ms),
        watchdog_every: Duration::from_millis(d.watchdog_ms),
        realtime_priority: d.realtime_priority,
        mode: c.mode,
        target_omega_rad_s: c.target,
        fixed_hz: c.fixed_hz,
        limits: c.limits,
        gains: c.gains,
        feed_forward,
        estimator,
        model,
        ranges,
        registers,
        condition,
    };
    // the rule `POST …/target` applies (a target it refused with 422 was accepted here up to 1.5× of it)
    let (target, max) = (c.target, settings.max_target_omega_rad_s());
    if target > max {
        return Err(KeyError::new(
            key("control.target_omega_rad_s"),
            format!("must be 0 ..= {max:.1} (max_hz with no load), got {target:.6e}"),
        ));
    }
    Ok(settings)
}

/// A drive's name: it names files and URLs.
pub(super) fn check_name(name: &str, key: &dyn Fn(&str) -> String) -> Result<(), Invalid> {
    let name_ok =
        !name.is_empty() && name.len() <= 64 && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-');
    if !name_ok {
        return Err(KeyError::new(
            key("name"),
            format!("{name:?}: use 1 to 64 letters, digits, `_` or `-` (it names files and URLs)"),
        ));
    }
    Ok(())
}

/// A drive's periods (poll, timeout, watchdog, stale) and its thread's priority; the stale period in ms.
pub(super) fn validate_periods(d: &RawDrive, key: &dyn Fn(&str) -> String) -> Result<u64, Invalid> {
    if !(1..=60_000).contains(&d.poll_ms) {
        return Err(KeyError::new(key("poll_ms"), format!("must be 1 ..= 60000, got {}", d.poll_ms)));
    }
    if !(1..=60_000).contains(&d.timeout_ms) {
        return Err(KeyError::new(key("timeout_ms"), format!("must be 1 ..= 60000, got {}", d.timeout_ms)));
    }
    if !(1..=60_000).contains(&d.watchdog_ms) {
        return Err(KeyError::new(key("watchdog_ms"), format!("must be 1 ..= 60000, got {}", d.watchdog_ms)));
    }
    if let Some(p) = d.realtime_priority
        && !(1..=99).contains(&p)
    {
        return Err(KeyError::new(
            key("realtime_priority"),
            format!("must be 1 ..= 99 (SCHED_FIFO priority), got {p}"),
        ));
    }
    let stale_ms = d.stale_ms.unwrap_or((5 * d.poll_ms).max(50));
    // a sample is fresh only if its reply came within stale_ms of the request before it, a poll earlier at best: at
    // stale_ms = poll_ms a healthy link was stale 3 120 samples of 3 329 (a reviewer's, against `sim`)
    if stale_ms < 2 * d.poll_ms {
        return Err(KeyError::new(
            key("stale_ms"),
            format!(
                "must be ≥ 2 · poll_ms ({}), got {stale_ms}: a sample is fresh only if its reply comes within \
                 stale_ms of the request of the sample before, a poll earlier",
                2 * d.poll_ms
            ),
        ));
    }
    if stale_ms > MAX_STALE_MS {
        return Err(KeyError::new(key("stale_ms"), format!("must be ≤ {MAX_STALE_MS} (10 min), got {stale_ms}")));
    }
    Ok(stale_ms)
}

/// `[drives.control]`, validated (its setpoints' fit in the register is checked once the registers are known).
pub(super) struct Control {
    mode: Mode,
    limits: Limits,
    gains: Gains,
    fixed_hz: f64,
    target: f64,
}

pub(super) fn validate_control(c: &RawControl, key: &dyn Fn(&str) -> String) -> Result<Control, Invalid> {
    let min_hz = nonneg(&key("control.min_hz"), c.min_hz)?;
    let max_hz = positive(&key("control.max_hz"), c.max_hz)?;
    if min_hz > max_hz {
        return Err(KeyError::new(key("control.min_hz"), format!("{min_hz} is above control.max_hz = {max_hz}")));
    }
    let ramp = positive(&key("control.ramp_hz_per_s"), c.ramp_hz_per_s)?;
    if ramp > super::MAX_RAMP_HZ_PER_S {
        return Err(KeyError::new(
            key("control.ramp_hz_per_s"),
            format!("must be ≤ {} Hz/s (0 to 50 Hz in 50 ms), got {ramp}: that is no ramp", super::MAX_RAMP_HZ_PER_S),
        ));
    }
    let kp = nonneg(&key("control.kp"), c.kp)?;
    if kp > MAX_KP_HZ_PER_RAD_S {
        return Err(KeyError::new(
            key("control.kp"),
            format!("must be ≤ {MAX_KP_HZ_PER_RAD_S} Hz per rad/s, got {kp}"),
        ));
    }
    let ki = nonneg(&key("control.ki"), c.ki)?;
    if ki > MAX_KI_HZ_PER_RAD {
        return Err(KeyError::new(key("control.ki"), format!("must be ≤ {MAX_KI_HZ_PER_RAD} Hz per rad, got {ki}")));
    }
    let fixed_hz = finite(&key("control.fixed_hz"), c.fixed_hz)?;
    if c.mode == Mode::Manual && !(min_hz..=max_hz).contains(&fixed_hz) {
        return Err(KeyError::new(
            key("control.fixed_hz"),
            format!("{fixed_hz} is outside [min_hz, max_hz] = [{min_hz}, {max_hz}]"),
        ));
    }
    let target = nonneg(&key("control.target_omega_rad_s"), c.target_omega_rad_s)?;
    Ok(Control {
        mode: c.mode,
        limits: Limits { min_hz, max_hz, ramp_hz_per_s: ramp },
        gains: Gains { kp_hz_per_rad_s: kp, ki_hz_per_rad: ki },
        fixed_hz,
        target,
    })
}

/// `[drives.estimator]`: the estimator's settings, the model they come from, and the control's feed-forward.
pub(super) fn validate_estimator(
    e: RawEstimator,
    key: &dyn Fn(&str) -> String,
    base: Option<&Path>,
) -> Result<(EstimatorSettings, PlantModel, FeedForward), Invalid> {
    let method = match e.method.as_deref() {
        None | Some("rls-sgd") => Method::RlsSgd,
        Some("kalman") => Method::Kalman,
        Some(other) => {
            return Err(KeyError::new(
                key("estimator.method"),
                format!("{other:?}: expected \"rls-sgd\" or \"kalman\""),
            ));
        }
    };
    let (model, origin) = match e.model {
        None => (PlantModel::reference(), "(the built-in reference)".to_string()),
        Some(p) => {
            let path = resolve(&p, base);
            let model = PlantModel::load(&path).map_err(|e| KeyError::new(key("estimator.model"), e.to_string()))?;
            (model, path.display().to_string())
        }
    };
    if model.motor.displacement_cm3.is_none() {
        return Err(KeyError::new(
            key("estimator.model"),
            "the model needs motor.displacement_cm3 (torque from pressures)".into(),
        ));
    }
    let mut estimator = EstimatorSettings::from_model(&model, &origin)
        .map_err(|e| KeyError::new(key("estimator.model"), e.to_string()))?;
    estimator.method = method;
    let coefficients =
        Coefficients::from_model(&model).map_err(|e| KeyError::new(key("estimator.model"), e.to_string()))?;
    let feed_forward = FeedForward {
        pole_pairs: coefficients.pole_pairs,
        pump_m3_rad: coefficients.pump_m3_rad,
        motor_m3_rad: coefficients.motor_m3_rad,
        leakage_si: coefficients.leakage_si,
        viscous_nm_s_rad: coefficients.mechanics.viscous_nm_s_rad,
    };
    Ok((estimator, model, feed_forward))
}

/// `[drives.limits]`: the ranges and rates a sample must keep to be used.
pub(super) fn validate_ranges(l: &RawLimits, key: &dyn Fn(&str) -> String) -> Result<ValidRanges, Invalid> {
    let ranges = ValidRanges {
        min_pressure_bar: finite(&key("limits.min_pressure_bar"), l.min_pressure_bar)?,
        max_pressure_bar: finite(&key("limits.max_pressure_bar"), l.max_pressure_bar)?,
        max_speed_rad_s: positive(&key("limits.max_speed_rad_s"), l.max_speed_rad_s)?,
        max_frequency_hz: positive(&key("limits.max_frequency_hz"), l.max_frequency_hz)?,
        rates: RateLimits {
            pressure_bar_per_s: positive(&key("limits.max_pressure_rate_bar_per_s"), l.max_pressure_rate_bar_per_s)?,
            speed_rad_per_s2: positive(&key("limits.max_speed_rate_rad_per_s2"), l.max_speed_rate_rad_per_s2)?,
            frequency_hz_per_s: positive(&key("limits.max_frequency_rate_hz_per_s"), l.max_frequency_rate_hz_per_s)?,
        },
    };
    if ranges.min_pressure_bar >= ranges.max_pressure_bar {
        return Err(KeyError::new(key("limits.min_pressure_bar"), "must be below limits.max_pressure_bar".into()));
    }
    Ok(ranges)
}

/// The control's frequencies fit the setpoint register.
pub(super) fn check_setpoint_fits(
    setpoint: &RegisterSpec,
    c: &Control,
    key: &dyn Fn(&str) -> String,
) -> Result<(), Invalid> {
    let (min_hz, max_hz, fixed_hz) = (c.limits.min_hz, c.limits.max_hz, c.fixed_hz);
    for (k, hz) in [("control.max_hz", max_hz), ("control.fixed_hz", fixed_hz), ("control.min_hz", min_hz)] {
        if setpoint.encode(hz).is_err() {
            return Err(KeyError::new(key(k), {
                let (lo, hi) = register_range(setpoint);
                format!(
                    "{hz} Hz does not fit the setpoint register ({:?}, {} Hz per step: it holds {lo} ..= {hi} Hz)",
                    setpoint.kind, setpoint.scale
                )
            }));
        }
    }
    Ok(())
}

/// In a writing mode, no setpoint above the drive's own top frequency as the plant model gives it (`[drive] max_hz`):
/// `control.max_hz = 400` against a model's 60 was taken in silence, and a speed target to match (a reviewer's config).
fn check_within_the_drive(c: &Control, model: &PlantModel, key: &dyn Fn(&str) -> String) -> Result<(), Invalid> {
    let Some(drive) = model.drive.as_ref().filter(|_| c.mode.writes()) else { return Ok(()) };
    if c.limits.max_hz <= drive.max_hz {
        return Ok(());
    }
    Err(KeyError::new(
        key("control.max_hz"),
        format!(
            "{} Hz is above the drive's own max_hz ({} Hz) in the plant model (drives.estimator.model, else the \
             reference plant): raise it there if the drive runs faster",
            crate::units::shown(c.limits.max_hz),
            drive.max_hz
        ),
    ))
}

/// The watchdog is refreshed well within the drive's comm timeout (`comm_timeout_ms`, else the model's): every
/// `watchdog_ms`, and, in a writing mode, at most once a poll, so the poll too is at most a third of it (`poll_ms =
/// 2000` against 1000 ms tripped the drive a second after the start).
pub(super) fn check_watchdog(
    comm_timeout_ms: Option<u64>,
    (watchdog_ms, poll_ms, mode): (u64, u64, Mode),
    model: &PlantModel,
    key: &dyn Fn(&str) -> String,
) -> Result<(), Invalid> {
    let comm_timeout_ms =
        comm_timeout_ms.unwrap_or_else(|| model.drive.as_ref().map_or(1000, |drive| drive.comm_timeout_ms));
    if !(1..=crate::plant::model::MAX_COMM_TIMEOUT_MS).contains(&comm_timeout_ms) {
        return Err(KeyError::new(
            key("comm_timeout_ms"),
            format!("must be 1 ..= {} (one hour), got {comm_timeout_ms}", crate::plant::model::MAX_COMM_TIMEOUT_MS),
        ));
    }
    if watchdog_ms.saturating_mul(3) > comm_timeout_ms {
        return Err(KeyError::new(
            key("watchdog_ms"),
            format!(
                "{watchdog_ms} ms is more than a third of the drive's comm timeout ({comm_timeout_ms} ms, \
                 comm_timeout_ms or the model's drive.comm_timeout_ms): the drive would trip"
            ),
        ));
    }
    if mode.writes() && poll_ms.saturating_mul(3) > comm_timeout_ms {
        return Err(KeyError::new(
            key("poll_ms"),
            format!(
                "{poll_ms} ms is more than a third of the drive's comm timeout ({comm_timeout_ms} ms) in a writing \
                 mode: the watchdog is written once a poll, and the drive would trip between two polls"
            ),
        ));
    }
    Ok(())
}

/// The entries that are bits or a count: read and written as the drive gives them, never scaled.
const BIT_FIELDS: [&str; 4] = ["status_word", "sample_counter", "control_word", "watchdog"];

/// Applies `[drives.registers.<entry>]` overrides to the default map, checking entry names and tables.
pub(super) fn apply_overrides(overrides: BTreeMap<String, RawRegister>, key: &str) -> Result<RegisterMap, Invalid> {
    let mut map = RegisterMap::default();
    let mut names: Vec<&str> = map.entries().iter().map(|(n, _)| *n).collect();
    names.push("drive_power_w");
    for (name, o) in overrides {
        let slot: &mut RegisterSpec = match name.as_str() {
            "inlet_pressure_bar" => &mut map.inlet_pressure_bar,
            "outlet_pressure_bar" => &mut map.outlet_pressure_bar,
            "shaft_speed_rpm" => &mut map.shaft_speed_rpm,
            "drive_frequency_hz" => &mut map.drive_frequency_hz,
            "status_word" => &mut map.status_word,
            "sample_counter" => &mut map.sample_counter,
            "frequency_setpoint_hz" => &mut map.frequency_setpoint_hz,
            "control_word" => &mut map.control_word,
            "watchdog" => &mut map.watchdog,
            // optional: named, it is read, from `sim`'s register unless the keys say otherwise
            "drive_power_w" => map.drive_power_w.get_or_insert(crate::modbus::map::DRIVE_POWER_W),
            _ => {
                return Err(KeyError::new(
                    format!("{key}.{name}"),
                    format!("is not a register entry; expected one of {}", names.join(", ")),
                ));
            }
        };
        let k = |f: &str| format!("{key}.{name}.{f}");
        if let Some(t) = o.table {
            slot.table = t;
        }
        if let Some(a) = o.address {
            slot.address = a;
        }
        if let Some(t) = o.kind {
            slot.kind = t;
        }
        if let Some(s) = o.scale {
            if !(s.is_finite() && s != 0.0) {
                return Err(KeyError::new(k("scale"), format!("must be finite and not 0, got {s}")));
            }
            slot.scale = s;
        }
        if let Some(off) = o.offset {
            slot.offset = finite(&k("offset"), off)?;
        }
        if let Some(w) = o.word_order {
            slot.word_order = w;
        }
    }
    for (name, spec) in map.entries().into_iter().chain(map.drive_power_w.map(|s| ("drive_power_w", s))) {
        let writable = matches!(name, "frequency_setpoint_hz" | "control_word" | "watchdog");
        if writable && spec.table != Table::Holding {
            return Err(KeyError::new(
                format!("{key}.{name}.table"),
                "must be \"holding\": the service writes it".into(),
            ));
        }
        // bit fields and counters are whole words as the drive gives them: a scale or offset moves their bits (RUN
        // written as bit 1, a fault read as running), and a float is no word at all
        if BIT_FIELDS.contains(&name) {
            if spec.scale != 1.0 || spec.offset != 0.0 {
                let (field, want, got) =
                    if spec.scale != 1.0 { ("scale", 1, spec.scale) } else { ("offset", 0, spec.offset) };
                return Err(KeyError::new(
                    format!("{key}.{name}.{field}"),
                    format!("must be {want}, got {got}: {name} is bits or a count, not a measurement"),
                ));
            }
            if spec.kind == crate::modbus::map::ValueType::F32 {
                return Err(KeyError::new(
                    format!("{key}.{name}.type"),
                    format!("must be a whole-number type (u16, i16, u32, i32): {name} is bits or a count"),
                ));
            }
        }
        if u32::from(spec.address) + u32::from(spec.kind.words()) > 65536 {
            return Err(KeyError::new(format!("{key}.{name}.address"), "runs past register 65535".into()));
        }
    }
    // two entries on one word: a setpoint written onto the control word (run, fault reset), or a value read from
    // another's register, is a wiring error the drive would act on
    let all: Vec<(&str, RegisterSpec)> =
        map.entries().into_iter().chain(map.drive_power_w.map(|s| ("drive_power_w", s))).collect();
    for (i, (a, sa)) in all.iter().enumerate() {
        for (b, sb) in &all[i + 1..] {
            let words = |s: &RegisterSpec| u32::from(s.address)..u32::from(s.address) + u32::from(s.kind.words());
            let (wa, wb) = (words(sa), words(sb));
            if sa.table == sb.table && wa.start < wb.end && wb.start < wa.end {
                return Err(KeyError::new(
                    format!("{key}.{b}.address"),
                    format!(
                        "{:?} register {} overlaps {a} ({:?} register {}, {} word(s)): each entry needs its own words",
                        sb.table,
                        sb.address,
                        sa.table,
                        sa.address,
                        sa.kind.words()
                    ),
                ));
            }
        }
    }
    for table in [Table::Input, Table::Holding] {
        if let Some((_, count)) = map.span(table)
            && count > 125
        {
            return Err(KeyError::new(
                key.to_string(),
                format!("the {table:?} registers span {count} words: one read takes ≤ 125"),
            ));
        }
    }
    Ok(map)
}

//! Unit conversions between the engineering units of configs and registers and the SI used inside.

use std::f64::consts::PI;

/// Declares a struct of `f64` columns with its column names and values in field order, so that a row's shape is
/// written down once: `COLUMNS` (the field names as the recording and the JSON spell them) and `values()`.
macro_rules! columns {
    ($(#[$meta:meta])* pub struct $name:ident { $($(#[$field_meta:meta])* pub $field:ident: f64,)* }) => {
        $(#[$meta])*
        pub struct $name {
            $($(#[$field_meta])* pub $field: f64,)*
        }

        impl $name {
            /// The column names, in field order.
            pub const COLUMNS: [&'static str; [$(stringify!($field)),*].len()] = [$(stringify!($field)),*];

            /// The values, in [`Self::COLUMNS`] order.
            pub fn values(&self) -> [f64; [$(stringify!($field)),*].len()] {
                [$(self.$field),*]
            }

            /// Every value missing (NaN: an empty cell in a recording).
            #[allow(dead_code)]
            pub const MISSING: Self = Self { $($field: f64::NAN),* };
        }
    };
}
pub(crate) use columns;

/// A number for a message, every digit kept: as `{}` prints it where that is short, in exponent form beyond 1e9 and
/// below 1e-3 (`{}` printed a `t_s` of 1e308 as 309 digits).
pub fn shown(v: f64) -> String {
    if v == 0.0 || !v.is_finite() || (1e-3..1e9).contains(&v.abs()) { format!("{v}") } else { format!("{v:e}") }
}

/// Pascal per bar.
pub const PA_PER_BAR: f64 = 1e5;

/// bar → Pa.
pub fn bar_to_pa(bar: f64) -> f64 {
    bar * PA_PER_BAR
}

/// Pa → bar.
pub fn pa_to_bar(pa: f64) -> f64 {
    pa / PA_PER_BAR
}

/// Displacement per revolution (cm³/rev) → per radian (m³/rad).
pub fn cm3_per_rev_to_m3_per_rad(cm3: f64) -> f64 {
    cm3 * 1e-6 / (2.0 * PI)
}

/// Leakage coefficient L/min per bar → m³/(s·Pa).
pub fn l_min_per_bar_to_si(l_min_per_bar: f64) -> f64 {
    l_min_per_bar * 1e-3 / 60.0 / PA_PER_BAR
}

/// Flow m³/s → L/min.
pub fn m3_s_to_l_min(q: f64) -> f64 {
    q * 1e3 * 60.0
}

/// rpm → rad/s.
pub fn rpm_to_rad_s(rpm: f64) -> f64 {
    rpm * 2.0 * PI / 60.0
}

/// rad/s → rpm.
pub fn rad_s_to_rpm(rad_s: f64) -> f64 {
    rad_s * 60.0 / (2.0 * PI)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips() {
        assert!((pa_to_bar(bar_to_pa(3.25)) - 3.25).abs() < 1e-12);
        assert!((rad_s_to_rpm(rpm_to_rad_s(1450.0)) - 1450.0).abs() < 1e-9);
        // 16 cm³/rev at 1500 rpm is 24 L/min
        let q = cm3_per_rev_to_m3_per_rad(16.0) * rpm_to_rad_s(1500.0);
        assert!((m3_s_to_l_min(q) - 24.0).abs() < 1e-9);
    }
}

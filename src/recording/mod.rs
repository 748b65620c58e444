//! Recordings: the contract's CSV (CONTRACT.md "Recording CSV"), read strictly by one streaming reader and written
//! streaming, with rotation; closed files may be gzip-compressed, and the reader takes them as they are.

pub mod cut;
pub mod gz;
mod join;
mod read;
pub mod simulated;
mod write;

pub use cut::RecordingFile;
pub use join::{drive_file_key, drive_files, join, last_run};
pub use read::{Batch, MAX_LINE_BYTES, RecordingError, StreamReader, holds_no_rows, load, load_columns, parse};
pub use write::{LostFile, RotatingWriter, RowWriter, push_value, write_csv};

/// The estimate columns, in the order every file that carries them writes them (`estimate`'s output after `t_s`, the
/// service's recordings after the measured columns).
pub const ESTIMATE_COLUMNS: [&str; 9] = [
    "omega_hat_rad_s",
    "load_hat_nm",
    "inertia_hat_kg_m2",
    "viscous_hat_nm_s_rad",
    "inertia_sd_kg_m2",
    "viscous_sd_nm_s_rad",
    "inertia_identified",
    "viscous_identified",
    "load_character",
];

crate::units::columns! {
    /// The measured columns of a sample, named as the recording names them: decoded from the registers
    /// ([`crate::modbus::map::decode_sample`], which leaves `t_s` and `f_set_hz` NaN), stamped by the drive cycle
    /// with its time and setpoint, and read as they are by the recording, the history, the status JSON, the metrics
    /// and MQTT.
    #[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
    pub struct Measured {
        /// Seconds since the service started.
        pub t_s: f64,
        /// Setpoint written in this cycle; NaN (null) when nothing was written.
        pub f_set_hz: f64,
        pub f_drive_hz: f64,
        pub p_in_bar: f64,
        pub p_out_bar: f64,
        pub omega_rad_s: f64,
        /// The drive's output power (W) where `[drives.registers.drive_power_w]` reads it; NaN (null) otherwise.
        pub drive_power_w: f64,
    }
}

/// The columns the contract names; anything else in a file is kept but reported once as unknown.
pub const KNOWN_COLUMNS: [&str; 21] = concat(
    concat::<10, 9, 19>(
        // the measured columns, and what a test stand measures beside them
        concat::<7, 3, 10>(Measured::COLUMNS, ["theta_rad", "load_nm", "torque_nm"]),
        ESTIMATE_COLUMNS,
    ),
    // service recordings: the status word and the speed target
    ["status_word", "target_omega_rad_s"],
);

/// Inlet and outlet pressure a sensor reads (bar, gauge): the service's `[drives.limits]` defaults too.
pub const PRESSURE_RANGE_BAR: (f64, f64) = crate::plant::PRESSURE_SENSOR_RANGE_BAR;
/// The largest shaft speed a tachogenerator reads (rad/s, either way).
pub const MAX_SPEED_RAD_S: f64 = 1000.0;
/// The highest drive frequency (Hz); a drive reads back down to −0.5 Hz at standstill.
pub const MAX_FREQUENCY_HZ: f64 = 400.0;
pub const MIN_FREQUENCY_HZ: f64 = -0.5;
/// Torque beyond this (N·m, either way) is no measurement of a drive of this kind.
pub const MAX_TORQUE_NM: f64 = 1e5;
/// A recording's typical time step below this (s) is a clock in the wrong unit: `estimate` and `analyze` refuse it,
/// saying [`TOO_SHORT_A_STEP`].
pub const MIN_TIME_STEP_S: f64 = 1e-5;
pub const TOO_SHORT_A_STEP: &str = "shorter than 10 µs, faster than any drive is polled";

/// The range a column's sensor can read; a cell outside it is not a measurement and is read as missing (the same
/// rule for `estimate` and `analyze`, and the service's defaults for what it accepts from a drive). Columns without
/// a sensor range (time, position, estimates) have none.
pub fn sensor_range(column: &str) -> Option<(f64, f64)> {
    match column {
        "p_in_bar" | "p_out_bar" => Some(PRESSURE_RANGE_BAR),
        "omega_rad_s" => Some((-MAX_SPEED_RAD_S, MAX_SPEED_RAD_S)),
        "f_set_hz" | "f_drive_hz" => Some((MIN_FREQUENCY_HZ, MAX_FREQUENCY_HZ)),
        "torque_nm" | "load_nm" => Some((-MAX_TORQUE_NM, MAX_TORQUE_NM)),
        "theta_rad" => Some((f64::MIN, f64::MAX)),
        _ => None,
    }
}

/// The shaft's motion between two `theta_rad` readings. A single-turn encoder gives the position within one turn
/// (0 ..< 2π, or −π ..< π) and wraps: where both readings lie in −π ..= 2π and they differ by more than half a turn,
/// the position wrapped and the motion is the shorter way round (a reviewer's wrapped position was read as speeds of
/// 1 073 rad/s, and `analyze` named nothing on an NRMSE of 10⁴). A multi-turn position leaves that range after its
/// first turn and is taken as it is; half a turn per sample is 314 rad/s at a 10 ms step, beyond what the speed
/// column may read at 1 ms.
pub fn position_step(from: f64, to: f64) -> f64 {
    (to - from) - std::f64::consts::TAU * turns_wrapped(from, to, 0.0)
}

/// The whole turns a single-turn position wrapped by between two readings that moved about `moved` between them (0
/// for neighbouring readings, [`position_step`]): 0 where it did not.
fn turns_wrapped(from: f64, to: f64, moved: f64) -> f64 {
    use std::f64::consts::{PI, TAU};
    let off = to - from - moved;
    let one_turn = |x: f64| (-PI..=TAU).contains(&x);
    if off.abs() > PI && one_turn(from) && one_turn(to) { (off / TAU).round() } else { 0.0 }
}

/// `theta_rad` with a single-turn encoder's wraps taken out ([`position_step`]): each reading plus the whole turns
/// wrapped before it (so a position that never wraps is returned as it is, a lone corrupt value included); a missing
/// reading stays missing, and the next one is compared with the last read. Across missing readings the position
/// may have moved by more than half a turn: there the wrap is the one that brings the step nearest the movement at the
/// pace of the last two readings in a row (a multi-turn position still in its first turn moved 4 rad over a gap, and
/// was read as a wrap back).
pub fn unwrapped_positions(theta: &[f64]) -> Vec<f64> {
    use std::f64::consts::TAU;
    // the turns so far, the last reading and its row, and the step a row between the last two readings in a row
    let (mut turns, mut last, mut pace) = (0.0, None::<(usize, f64)>, None::<f64>);
    theta
        .iter()
        .enumerate()
        .map(|(k, &x)| {
            if x.is_finite() {
                if let Some((i, from)) = last {
                    let moved = match pace {
                        Some(p) if k > i + 1 => p * (k - i) as f64,
                        _ => 0.0,
                    };
                    let wrapped = turns_wrapped(from, x, moved);
                    turns += wrapped;
                    if k == i + 1 {
                        pace = Some(x - from - TAU * wrapped);
                    }
                }
                last = Some((k, x));
            }
            x - TAU * turns
        })
        .collect()
}

/// Cells of one column of one file outside the column's [`sensor_range`], taken as missing.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct OutOfRange {
    pub file: String,
    pub column: String,
    pub low: f64,
    pub high: f64,
    pub cells: u64,
    /// The line (of the file, from 1) of the first such cell.
    pub first_line: u64,
}

impl std::fmt::Display for OutOfRange {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "recording {}, line {}, column `{}`: {} cell(s) outside the sensor's range {}…{}, the first on this line; \
             taken as missing",
            self.file, self.first_line, self.column, self.cells, self.low, self.high
        )
    }
}

/// `a` then `b`, for column lists built from [`ESTIMATE_COLUMNS`] (N = A + B, checked when the constant is built).
pub const fn concat<const A: usize, const B: usize, const N: usize>(
    a: [&'static str; A],
    b: [&'static str; B],
) -> [&'static str; N] {
    assert!(A + B == N, "concat: N must be A + B");
    let mut out = [""; N];
    let mut i = 0;
    while i < A {
        out[i] = a[i];
        i += 1;
    }
    while i < N {
        out[i] = b[i - A];
        i += 1;
    }
    out
}

/// A recording held column by column; a missing value is NaN. `t_s` is always the first column.
#[derive(Debug, Clone, PartialEq)]
pub struct Recording {
    /// Where it came from (a file name), for messages.
    pub source: String,
    names: Vec<String>,
    columns: Vec<Vec<f64>>,
    /// Cells read as missing because they lay outside their sensor's range.
    pub out_of_range: Vec<OutOfRange>,
}

impl Recording {
    /// Builds a recording from named columns of equal length.
    pub fn from_columns(source: &str, names: Vec<String>, columns: Vec<Vec<f64>>) -> Recording {
        debug_assert_eq!(names.len(), columns.len());
        debug_assert!(columns.windows(2).all(|w| w[0].len() == w[1].len()));
        Recording { source: source.to_string(), names, columns, out_of_range: Vec::new() }
    }

    pub fn names(&self) -> &[String] {
        &self.names
    }

    /// A column by name.
    pub fn column(&self, name: &str) -> Option<&[f64]> {
        self.names.iter().position(|n| n == name).map(|i| self.columns[i].as_slice())
    }

    /// A column by name, only if it holds at least one value.
    pub fn present(&self, name: &str) -> Option<&[f64]> {
        self.column(name).filter(|c| c.iter().any(|v| v.is_finite()))
    }

    /// Time stamps (s); empty only for a recording built empty.
    pub fn t_s(&self) -> &[f64] {
        self.column("t_s").unwrap_or(&[])
    }

    pub fn len(&self) -> usize {
        self.columns.first().map_or(0, Vec::len)
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Adds (or replaces) a column.
    pub fn set_column(&mut self, name: &str, values: Vec<f64>) {
        match self.names.iter().position(|n| n == name) {
            Some(i) => self.columns[i] = values,
            None => {
                self.names.push(name.to_string());
                self.columns.push(values);
            }
        }
    }

    /// Row `k` as values in column order.
    pub fn row(&self, k: usize) -> impl Iterator<Item = f64> + '_ {
        self.columns.iter().map(move |c| c[k])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_single_turn_position_is_unwrapped_and_a_multi_turn_one_left_as_it_is() {
        use std::f64::consts::{PI, TAU};
        // 0.1 rad a sample forwards through the wrap at 2π, and backwards through −π on a ±π encoder
        assert!((position_step(TAU - 0.05, 0.05) - 0.1).abs() < 1e-12);
        assert!((position_step(-PI + 0.05, PI - 0.05) + 0.1).abs() < 1e-12);
        // a multi-turn position: the steps as they are, also a large one beyond the first turn
        assert_eq!(position_step(10.0, 10.1), 10.1 - 10.0);
        assert_eq!(position_step(10.0, 14.0), 4.0);
        let turns: Vec<f64> = (0..200).map(|k| 0.1 * k as f64).collect();
        let wrapped: Vec<f64> = turns.iter().map(|x| x.rem_euclid(TAU)).collect();
        let back = unwrapped_positions(&wrapped);
        assert!(back.iter().zip(&turns).all(|(a, b)| (a - b).abs() < 1e-9), "{back:?}");
        assert_eq!(unwrapped_positions(&turns), turns, "a multi-turn position is left as it is");
        let spike = [1.0, 1e300, 1.2];
        assert_eq!(unwrapped_positions(&spike), spike, "a lone corrupt value too, for the spike screen");
        // a missing reading stays missing; the next one continues from the last read
        let gap = unwrapped_positions(&[6.2, f64::NAN, 0.1]);
        assert!(gap[1].is_nan() && (gap[2] - (6.2 + position_step(6.2, 0.1))).abs() < 1e-12, "{gap:?}");
        // across 100 missing readings a multi-turn position in its first turn moved 4 rad: no wrap; a single-turn one
        // 0.4 rad over 9 through its wrap, and 4 rad over 100 through its wrap (a step back of 2.2 rad as read): one
        let missing = |x: &[f64], from: usize, n: usize| {
            let mut x = x.to_vec();
            x[from..from + n].fill(f64::NAN);
            x
        };
        let first_turn: Vec<f64> = (0..150).map(|k| 0.04 * k as f64).collect();
        let kept = missing(&first_turn, 20, 100);
        let back = unwrapped_positions(&kept);
        assert!(back.iter().zip(&kept).all(|(a, b)| a.to_bits() == b.to_bits()), "{back:?}");
        for (start, from, n) in [(5.8, 10, 9), (4.0, 20, 100)] {
            let through: Vec<f64> = (0..150).map(|k| start + 0.04 * k as f64).collect();
            let wrapped = missing(&through.iter().map(|x| x.rem_euclid(TAU)).collect::<Vec<_>>(), from, n);
            let back = unwrapped_positions(&wrapped);
            let truth = missing(&through, from, n);
            let same = |(a, b): (&f64, &f64)| (a.is_nan() && b.is_nan()) || (a - b).abs() < 1e-9;
            assert!(back.iter().zip(&truth).all(same), "{start}: {back:?}");
        }
    }
}

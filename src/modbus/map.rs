//! The register map of CONTRACT.md: which register holds what, in which type, word order, scale and offset.

use serde::{Deserialize, Serialize};

use crate::recording::Measured;

/// Which Modbus table an entry lives in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Table {
    /// Input registers (function 04).
    Input,
    /// Holding registers (functions 03, 06, 16).
    Holding,
}

/// The register's raw type.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ValueType {
    U16,
    I16,
    U32,
    I32,
    F32,
}

impl ValueType {
    /// How many 16-bit registers the value spans.
    pub fn words(self) -> u16 {
        match self {
            ValueType::U16 | ValueType::I16 => 1,
            _ => 2,
        }
    }

    /// The raw values the type holds, lowest and highest.
    pub fn raw_range(self) -> (f64, f64) {
        match self {
            ValueType::U16 => (0.0, 65535.0),
            ValueType::I16 => (-32768.0, 32767.0),
            ValueType::U32 => (0.0, 4_294_967_295.0),
            ValueType::I32 => (-2_147_483_648.0, 2_147_483_647.0),
            ValueType::F32 => (-f64::from(f32::MAX), f64::from(f32::MAX)),
        }
    }
}

/// Byte order of a 32-bit value across two registers: `abcd` is big-endian with the high word first.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum WordOrder {
    #[default]
    Abcd,
    Cdab,
    Badc,
    Dcba,
}

/// One entry of the map: engineering value = raw·scale + offset.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct RegisterSpec {
    pub table: Table,
    pub address: u16,
    #[serde(rename = "type")]
    pub kind: ValueType,
    #[serde(default = "one")]
    pub scale: f64,
    #[serde(default)]
    pub offset: f64,
    #[serde(default)]
    pub word_order: WordOrder,
}

fn one() -> f64 {
    1.0
}

/// Why a value cannot be decoded or encoded.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MapError {
    #[error("register {address}: expected {expected} words, got {got}")]
    Length { address: u16, expected: usize, got: usize },
    #[error("register {address}: value {value} is outside what a {kind:?} can hold at scale {scale}")]
    Range { address: u16, value: f64, kind: ValueType, scale: f64 },
    #[error("register {address}: decoded value is not finite")]
    NotFinite { address: u16 },
}

impl RegisterSpec {
    pub const fn new(table: Table, address: u16, kind: ValueType, scale: f64) -> RegisterSpec {
        RegisterSpec { table, address, kind, scale, offset: 0.0, word_order: WordOrder::Abcd }
    }

    fn join(self, w: &[u16]) -> u32 {
        let [a, b] = w[0].to_be_bytes();
        let [c, d] = w[1].to_be_bytes();
        let bytes = match self.word_order {
            WordOrder::Abcd => [a, b, c, d],
            WordOrder::Cdab => [c, d, a, b],
            WordOrder::Badc => [b, a, d, c],
            WordOrder::Dcba => [d, c, b, a],
        };
        u32::from_be_bytes(bytes)
    }

    fn split(self, v: u32) -> [u16; 2] {
        let [a, b, c, d] = v.to_be_bytes();
        let [w0, w1] = match self.word_order {
            WordOrder::Abcd => [[a, b], [c, d]],
            WordOrder::Cdab => [[c, d], [a, b]],
            WordOrder::Badc => [[b, a], [d, c]],
            WordOrder::Dcba => [[d, c], [b, a]],
        };
        [u16::from_be_bytes(w0), u16::from_be_bytes(w1)]
    }

    /// The raw register value, before scale and offset.
    pub fn decode_raw(&self, words: &[u16]) -> Result<f64, MapError> {
        let need = usize::from(self.kind.words());
        if words.len() < need {
            return Err(MapError::Length { address: self.address, expected: need, got: words.len() });
        }
        let raw = match self.kind {
            ValueType::U16 => f64::from(words[0]),
            ValueType::I16 => f64::from(words[0] as i16),
            ValueType::U32 => f64::from(self.join(words)),
            ValueType::I32 => f64::from(self.join(words) as i32),
            ValueType::F32 => f64::from(f32::from_bits(self.join(words))),
        };
        if raw.is_finite() { Ok(raw) } else { Err(MapError::NotFinite { address: self.address }) }
    }

    /// The engineering value from the entry's words (the slice starts at this entry's address).
    pub fn decode(&self, words: &[u16]) -> Result<f64, MapError> {
        Ok(self.decode_raw(words)? * self.scale + self.offset)
    }

    /// The words for an engineering value, rounded to the nearest step; a value out of the type's range is an error.
    pub fn encode(&self, value: f64) -> Result<Vec<u16>, MapError> {
        let raw = (value - self.offset) / self.scale;
        let range = MapError::Range { address: self.address, value, kind: self.kind, scale: self.scale };
        if !raw.is_finite() {
            return Err(range);
        }
        // integers to the nearest step; an f32 as it is
        let r = if self.kind == ValueType::F32 { raw } else { raw.round() };
        let (lo, hi) = self.kind.raw_range();
        if !(lo..=hi).contains(&r) {
            return Err(range);
        }
        Ok(match self.kind {
            ValueType::U16 => vec![r as u16],
            ValueType::I16 => vec![(r as i16) as u16],
            ValueType::U32 => self.split(r as u32).to_vec(),
            ValueType::I32 => self.split((r as i32) as u32).to_vec(),
            ValueType::F32 => self.split((r as f32).to_bits()).to_vec(),
        })
    }

    /// As [`RegisterSpec::encode`], but where the nearest step lies outside `lo ..= hi` (a limit that is not a whole
    /// number of steps: 50 Hz at 0.3 Hz a step rounds to 50.1), the next step inside it.
    pub fn encode_within(&self, value: f64, lo: f64, hi: f64) -> Result<Vec<u16>, MapError> {
        let words = self.encode(value)?;
        let got = self.decode(&words)?;
        if self.kind == ValueType::F32 || (lo..=hi).contains(&got) {
            return Ok(words);
        }
        // one step back towards the value; kept only if it is inside and still the same request
        let back = if got > hi { value - self.scale.abs() * 0.5 } else { value + self.scale.abs() * 0.5 };
        let inner = self.encode(back)?;
        Ok(if (lo..=hi).contains(&self.decode(&inner)?) { inner } else { words })
    }

    /// As [`RegisterSpec::encode`] but saturating at the type's range (for a simulator's sensors).
    pub fn encode_saturating(&self, value: f64) -> Vec<u16> {
        let (lo, hi) = self.kind.raw_range();
        let raw = ((value - self.offset) / self.scale).clamp(lo, hi);
        let raw = if raw.is_nan() { 0.0 } else { raw };
        self.encode(raw * self.scale + self.offset).unwrap_or_else(|_| vec![0; usize::from(self.kind.words())])
    }
}

/// The drive's registers, by what they mean. Names carry the engineering unit.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct RegisterMap {
    pub inlet_pressure_bar: RegisterSpec,
    pub outlet_pressure_bar: RegisterSpec,
    pub shaft_speed_rpm: RegisterSpec,
    pub drive_frequency_hz: RegisterSpec,
    pub status_word: RegisterSpec,
    pub sample_counter: RegisterSpec,
    pub frequency_setpoint_hz: RegisterSpec,
    pub control_word: RegisterSpec,
    pub watchdog: RegisterSpec,
    /// The drive's output power (W; a drive that counts in kW has `scale` 1000 × its step), where the drive exposes
    /// it: optional, absent by default (then not read, and the overall efficiency is unknown). `sim` serves it at
    /// [`DRIVE_POWER_W`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub drive_power_w: Option<RegisterSpec>,
}

/// Where `sim` serves the drive's output power, and the entry `[drives.registers.drive_power_w]` starts from:
/// input register 6, i16, 1 W per step (negative while the drive brakes the motor).
pub const DRIVE_POWER_W: RegisterSpec = RegisterSpec::new(Table::Input, 6, ValueType::I16, 1.0);

/// Status word bits.
pub mod status {
    pub const READY: u16 = 1 << 0;
    pub const RUNNING: u16 = 1 << 1;
    pub const FAULT: u16 = 1 << 2;
    pub const COMM_LOSS_TRIP: u16 = 1 << 3;
}

/// Control word bits.
pub mod control {
    pub const RUN: u16 = 1 << 0;
    pub const FAULT_RESET: u16 = 1 << 7;
}

impl Default for RegisterMap {
    fn default() -> Self {
        use Table::{Holding, Input};
        use ValueType::{I16, U16};
        RegisterMap {
            inlet_pressure_bar: RegisterSpec::new(Input, 0, U16, 0.01),
            outlet_pressure_bar: RegisterSpec::new(Input, 1, U16, 0.01),
            shaft_speed_rpm: RegisterSpec::new(Input, 2, I16, 0.1),
            drive_frequency_hz: RegisterSpec::new(Input, 3, U16, 0.01),
            status_word: RegisterSpec::new(Input, 4, U16, 1.0),
            sample_counter: RegisterSpec::new(Input, 5, U16, 1.0),
            frequency_setpoint_hz: RegisterSpec::new(Holding, 0, U16, 0.01),
            control_word: RegisterSpec::new(Holding, 1, U16, 1.0),
            watchdog: RegisterSpec::new(Holding, 2, U16, 1.0),
            drive_power_w: None,
        }
    }
}

impl RegisterMap {
    /// The entries by name, for configs and messages.
    pub fn entries(&self) -> [(&'static str, RegisterSpec); 9] {
        [
            ("inlet_pressure_bar", self.inlet_pressure_bar),
            ("outlet_pressure_bar", self.outlet_pressure_bar),
            ("shaft_speed_rpm", self.shaft_speed_rpm),
            ("drive_frequency_hz", self.drive_frequency_hz),
            ("status_word", self.status_word),
            ("sample_counter", self.sample_counter),
            ("frequency_setpoint_hz", self.frequency_setpoint_hz),
            ("control_word", self.control_word),
            ("watchdog", self.watchdog),
        ]
    }

    /// The entries the service reads each cycle, by name (the first six of [`RegisterMap::entries`]).
    pub fn measured(&self) -> [(&'static str, RegisterSpec); 6] {
        let e = self.entries();
        [e[0], e[1], e[2], e[3], e[4], e[5]]
    }

    /// The entries the service reads each cycle: [`RegisterMap::measured`], then the optional ones configured.
    pub fn read_entries(&self) -> Vec<(&'static str, RegisterSpec)> {
        let mut out = self.measured().to_vec();
        out.extend(self.drive_power_w.map(|s| ("drive_power_w", s)));
        out
    }

    /// The smallest block (first address, count) covering every entry of a table, the optional ones configured
    /// included, for one batched read.
    pub fn span(&self, table: Table) -> Option<(u16, u16)> {
        let optional = self.drive_power_w.into_iter();
        span_of(self.entries().into_iter().map(|(_, s)| s).chain(optional), table)
    }

    /// Decodes an entry from a block read at `block_start`.
    pub fn decode_from(spec: &RegisterSpec, block_start: u16, block: &[u16]) -> Result<f64, MapError> {
        let at = usize::from(spec.address.wrapping_sub(block_start));
        spec.decode(block.get(at..).unwrap_or(&[]))
    }
}

/// The smallest block (first address, count) of `table` covering `specs`; None when none is in that table.
fn span_of(specs: impl Iterator<Item = RegisterSpec>, table: Table) -> Option<(u16, u16)> {
    let (mut lo, mut hi) = (u32::MAX, 0u32);
    for s in specs.filter(|s| s.table == table) {
        lo = lo.min(u32::from(s.address));
        hi = hi.max(u32::from(s.address) + u32::from(s.kind.words()));
    }
    (lo < hi).then(|| (lo as u16, (hi - lo) as u16))
}

/// The reads of one cycle: per table, the smallest block holding every measured entry of that table.
pub fn read_plan(map: &RegisterMap) -> Vec<(Table, u16, u16)> {
    [Table::Input, Table::Holding]
        .into_iter()
        .filter_map(|t| span_of(map.read_entries().into_iter().map(|(_, s)| s), t).map(|(start, n)| (t, start, n)))
        .collect()
}

/// One read's sample: the measured columns as the recording names them (SI speed; `t_s` and `f_set_hz` NaN until
/// the drive cycle stamps them), and the status word and sample counter that say what the data are worth. Every
/// value is finite and the word and counter whole; whether the values are plausible is the service's policy, not
/// the map's.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sample {
    pub measured: Measured,
    pub status_word: u16,
    pub counter: u64,
}

/// A measured entry that could not be decoded from a cycle's blocks.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{entry}: {message}")]
pub struct DecodeError {
    pub entry: &'static str,
    pub message: String,
}

/// Decodes the measured entries from the blocks of [`read_plan`] (table, first address, words) into a
/// [`Sample`]; an error names the register entry. Pure.
pub fn decode_sample(map: &RegisterMap, blocks: &[(Table, u16, Vec<u16>)]) -> Result<Sample, DecodeError> {
    let decode = |entry: &'static str, spec: RegisterSpec| {
        let Some((_, start, words)) = blocks.iter().find(|(t, _, _)| *t == spec.table) else {
            return Err(DecodeError { entry, message: "its table was not read".into() });
        };
        let value = RegisterMap::decode_from(&spec, *start, words)
            .map_err(|e| DecodeError { entry, message: e.to_string() })?;
        if value.is_finite() {
            Ok(value)
        } else {
            Err(DecodeError { entry, message: format!("{value} is not a number") })
        }
    };
    let whole = |entry: &'static str, value: f64, max: f64| {
        if (0.0..=max).contains(&value) && value.fract() == 0.0 {
            Ok(value)
        } else {
            Err(DecodeError { entry, message: format!("{value} is not a whole number from 0 to {max}") })
        }
    };
    let mut v = [0.0; 6];
    for (x, (entry, spec)) in v.iter_mut().zip(map.measured()) {
        *x = decode(entry, spec)?;
    }
    let drive_power_w = map.drive_power_w.map(|spec| decode("drive_power_w", spec)).transpose()?;
    let [p_in_bar, p_out_bar, shaft_speed_rpm, f_drive_hz, status_word, counter] = v;
    let measured = Measured {
        t_s: f64::NAN,
        f_set_hz: f64::NAN,
        f_drive_hz,
        p_in_bar,
        p_out_bar,
        omega_rad_s: crate::units::rpm_to_rad_s(shaft_speed_rpm),
        drive_power_w: drive_power_w.unwrap_or(f64::NAN),
    };
    Ok(Sample {
        measured,
        status_word: whole("status_word", status_word, f64::from(u16::MAX))? as u16,
        counter: whole("sample_counter", counter, f64::from(u32::MAX))? as u64,
    })
}

/// `parts` (address, what goes there) sorted by address, adjacent ones merged by `join` into one request.
fn merge_adjacent<T>(mut parts: Vec<(u16, T)>, len: impl Fn(&T) -> usize, join: impl Fn(&mut T, T)) -> Vec<(u16, T)> {
    parts.sort_by_key(|(a, _)| *a);
    let mut out: Vec<(u16, T)> = Vec::with_capacity(parts.len());
    for (addr, part) in parts {
        match out.last_mut() {
            Some((start, block)) if usize::from(*start) + len(block) == usize::from(addr) => join(block, part),
            _ => out.push((addr, part)),
        }
    }
    out
}

/// The writes for a setpoint (with its limits: the register step nearest to it inside them), control word and
/// watchdog value: encoded, sorted, adjacent registers merged so that the default map takes one request. Pure.
pub fn plan_writes(
    map: &RegisterMap,
    (setpoint_hz, (min_hz, max_hz)): (f64, (f64, f64)),
    control_word: u16,
    watchdog: u16,
) -> Result<Vec<(u16, Vec<u16>)>, MapError> {
    let setpoint = map.frequency_setpoint_hz.encode_within(setpoint_hz, min_hz, max_hz)?;
    let parts = vec![
        (map.frequency_setpoint_hz.address, setpoint),
        (map.control_word.address, map.control_word.encode(f64::from(control_word))?),
        (map.watchdog.address, map.watchdog.encode(f64::from(watchdog))?),
    ];
    Ok(merge_adjacent(parts, Vec::len, |block, words| block.extend(words)))
}

/// The write requests of a cycle as (start, words): the blocks [`plan_writes`] makes, without the values.
pub fn write_layout(map: &RegisterMap) -> Vec<(u16, usize)> {
    let parts = [map.frequency_setpoint_hz, map.control_word, map.watchdog]
        .map(|s| (s.address, usize::from(s.kind.words())))
        .to_vec();
    merge_adjacent(parts, |n| *n, |n, more| *n += more)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn word_orders_round_trip() {
        for order in [WordOrder::Abcd, WordOrder::Cdab, WordOrder::Badc, WordOrder::Dcba] {
            for kind in [ValueType::U32, ValueType::I32, ValueType::F32] {
                let spec = RegisterSpec { word_order: order, ..RegisterSpec::new(Table::Input, 7, kind, 0.5) };
                let words = spec.encode(1234.5).expect("fits");
                assert_eq!(spec.decode(&words).expect("decodes"), 1234.5, "{order:?} {kind:?}");
            }
        }
        // a known pattern: 0x4148_F5C3 is 12.56f32
        let abcd = RegisterSpec::new(Table::Input, 0, ValueType::F32, 1.0);
        assert!((abcd.decode(&[0x4148, 0xF5C3]).expect("f32") - 12.56).abs() < 1e-5);
        let cdab = RegisterSpec { word_order: WordOrder::Cdab, ..abcd };
        assert!((cdab.decode(&[0xF5C3, 0x4148]).expect("f32") - 12.56).abs() < 1e-5);
    }

    #[test]
    fn scales_signs_and_ranges() {
        let m = RegisterMap::default();
        assert_eq!(m.shaft_speed_rpm.encode(-100.0).expect("fits"), vec![(-1000i16) as u16]);
        assert_eq!(m.shaft_speed_rpm.decode(&[(-1000i16) as u16]).expect("i16"), -100.0);
        assert!(m.frequency_setpoint_hz.encode(-1.0).is_err());
        assert!(m.frequency_setpoint_hz.encode(700.0).is_err());
        assert_eq!(m.frequency_setpoint_hz.encode_saturating(700.0), vec![65535]);
        assert_eq!(m.span(Table::Input), Some((0, 6)));
        assert_eq!(m.span(Table::Holding), Some((0, 3)));
        let nan = RegisterSpec::new(Table::Input, 0, ValueType::F32, 1.0);
        assert!(nan.decode(&[0x7FC0, 0]).is_err());
    }

    #[test]
    fn a_setpoint_never_rounds_past_its_limits() {
        // 0.3 Hz a step: 50 Hz rounds to 50.1 and 10 Hz to 9.9; the next steps inside are written
        let coarse = RegisterSpec::new(Table::Holding, 0, ValueType::U16, 0.3);
        assert_eq!(coarse.encode(50.0).expect("fits"), vec![167]);
        assert_eq!(coarse.encode_within(50.0, 10.0, 50.0).expect("fits"), vec![166]);
        assert_eq!(coarse.encode_within(10.0, 10.0, 50.0).expect("fits"), vec![34]);
        assert_eq!(coarse.encode_within(30.0, 10.0, 50.0).expect("fits"), vec![100]);
        // limits closer than a step: the nearest
        assert_eq!(coarse.encode_within(20.0, 20.0, 20.1).expect("fits"), vec![67]);
    }

    #[test]
    fn default_map_is_one_read_and_one_write() {
        let map = RegisterMap::default();
        assert_eq!(read_plan(&map), vec![(Table::Input, 0, 6)]);
        let w = plan_writes(&map, (25.0, (0.0, 50.0)), control::RUN, 7).expect("fits");
        assert_eq!(w, vec![(0, vec![2500, control::RUN, 7])]);
        assert_eq!(write_layout(&map), vec![(0, 3)]);
    }

    #[test]
    fn scattered_registers_are_written_apart() {
        let mut map = RegisterMap::default();
        map.watchdog.address = 10;
        map.frequency_setpoint_hz = RegisterSpec::new(Table::Holding, 20, ValueType::F32, 1.0);
        let w = plan_writes(&map, (25.5, (0.0, 50.0)), 1, 2).expect("fits");
        assert_eq!(w.len(), 3);
        assert_eq!(w[0], (1, vec![1]));
        assert_eq!(w[2].0, 20);
        assert_eq!(w[2].1.len(), 2);
        let layout: Vec<(u16, usize)> = w.iter().map(|(a, words)| (*a, words.len())).collect();
        assert_eq!(write_layout(&map), layout);
    }

    #[test]
    fn measured_entries_of_both_tables_are_read_apart() {
        let map = RegisterMap {
            sample_counter: RegisterSpec::new(Table::Holding, 40, ValueType::U32, 1.0),
            ..RegisterMap::default()
        };
        assert_eq!(read_plan(&map), vec![(Table::Input, 0, 5), (Table::Holding, 40, 2)]);
        let blocks = vec![(Table::Input, 0u16, vec![3512, 300, 3820, 2550, 3]), (Table::Holding, 40, vec![1, 2])];
        let r = decode_sample(&map, &blocks).expect("decodes");
        assert!((r.measured.p_in_bar - 35.12).abs() < 1e-9);
        assert!((r.measured.omega_rad_s - crate::units::rpm_to_rad_s(382.0)).abs() < 1e-9);
        assert!(r.measured.t_s.is_nan() && r.measured.f_set_hz.is_nan(), "the cycle's to stamp");
        assert_eq!((r.status_word, r.counter), (3, 65538));
        let e = decode_sample(&map, &blocks[..1]).expect_err("the holding block is missing");
        assert_eq!(e.entry, "sample_counter");
        let short = vec![(Table::Input, 0u16, vec![1, 2, 3]), blocks[1].clone()];
        assert_eq!(decode_sample(&map, &short).expect_err("too short").entry, "drive_frequency_hz");
        assert!(r.measured.drive_power_w.is_nan(), "not in the map: not read");
    }

    #[test]
    fn a_value_that_is_not_a_number_or_not_whole_is_named_by_its_entry() {
        let f32_words = |x: f32| [(x.to_bits() >> 16) as u16, x.to_bits() as u16];
        let map = RegisterMap {
            inlet_pressure_bar: RegisterSpec::new(Table::Holding, 10, ValueType::F32, 1.0),
            ..RegisterMap::default()
        };
        let blocks = |p: f32, status: u16| {
            vec![(Table::Input, 0u16, vec![0, 0, 0, 0, status, 9]), (Table::Holding, 10, f32_words(p).to_vec())]
        };
        assert_eq!(decode_sample(&map, &blocks(35.5, 3)).expect("decodes").measured.p_in_bar, 35.5);
        let e = decode_sample(&map, &blocks(f32::NAN, 3)).expect_err("NaN");
        assert_eq!(e.entry, "inlet_pressure_bar", "{e}");
        // a status word scaled into fractions is no status word
        let map = RegisterMap { status_word: RegisterSpec::new(Table::Input, 4, ValueType::U16, 0.1), ..map };
        let e = decode_sample(&map, &blocks(35.5, 3)).expect_err("0.3 is not a word");
        assert_eq!(e.entry, "status_word", "{e}");
    }

    #[test]
    fn the_drive_power_is_read_only_where_the_map_has_it() {
        let map = RegisterMap { drive_power_w: Some(DRIVE_POWER_W), ..RegisterMap::default() };
        assert_eq!(read_plan(&map), vec![(Table::Input, 0, 7)], "still one read");
        let blocks = vec![(Table::Input, 0u16, vec![3512, 300, 3820, 2550, 3, 9, (-250i16) as u16])];
        assert_eq!(decode_sample(&map, &blocks).expect("decodes").measured.drive_power_w, -250.0);
        let short = vec![(Table::Input, 0u16, vec![3512, 300, 3820, 2550, 3, 9])];
        assert_eq!(decode_sample(&map, &short).expect_err("too short").entry, "drive_power_w");
        // a drive counting in 0.01 kW, far from the other registers: a read of its own
        let kw = RegisterSpec::new(Table::Holding, 300, ValueType::U16, 10.0);
        let map = RegisterMap { drive_power_w: Some(kw), ..RegisterMap::default() };
        assert_eq!(read_plan(&map), vec![(Table::Input, 0, 6), (Table::Holding, 300, 1)]);
        let blocks = vec![(Table::Input, 0u16, vec![0; 6]), (Table::Holding, 300, vec![55])];
        assert_eq!(decode_sample(&map, &blocks).expect("decodes").measured.drive_power_w, 550.0);
        assert_eq!(map.span(Table::Holding), Some((0, 301)));
        // absent from the map's TOML by default, and back when written
        let text = toml::to_string(&RegisterMap::default()).expect("serialises");
        assert!(!text.contains("drive_power_w"), "{text}");
        let text = toml::to_string(&map).expect("serialises");
        assert_eq!(toml::from_str::<RegisterMap>(&text).expect("parses"), map);
    }
}

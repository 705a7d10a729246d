//! What a plant behind a Modbus TCP server is to the project: the `[plant.modbus]` table of
//! a plant file (where each channel's output, input and applied value sit in the server's
//! registers, and how their bits become numbers), checked, and the pure arithmetic the
//! bridge needs (decoding, encoding, which registers to read in one request). No I/O here:
//! the client that talks to the server is the `fieldbus` crate's, and this module is what
//! both it and the plant file's loader agree on, tested without a server.
//!
//! Modbus has no types: a register is 16 bits, a coil one bit. A map says per value the
//! register kind, the address (0-based, as on the wire: the "40001" of a manual is
//! holding register 0), the type, the word order of 32-bit values, and a scale and offset
//! (a register in 0.1 °C is `scale = 0.1`).

use serde::{Deserialize, Serialize};

/// The largest number of registers one read may ask for (Modbus: 125).
pub const MAX_REGISTERS_PER_READ: u16 = 125;
/// The largest number of coils or discrete inputs one read may ask for (Modbus: 2000).
pub const MAX_BITS_PER_READ: u16 = 2000;
/// The largest number of registers one write may carry (Modbus: 123).
pub const MAX_REGISTERS_PER_WRITE: u16 = 123;

/// The `[plant.modbus]` table of a plant file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModbusConfig {
    /// The server, `host:port` (a name is resolved when the bridge connects).
    pub address: String,
    /// Unit id (the "slave" a gateway forwards to). Default: 1. A TCP device addressed
    /// directly usually takes 255 or 0 (the Modbus TCP guide's choice, the device's manual
    /// says which).
    #[serde(default = "default_unit")]
    pub unit: u8,
    /// Longest wait for one answer (ms). Default: half the period, at least 20 ms: a read
    /// and a write must fit in a period.
    #[serde(default)]
    pub timeout_ms: Option<u64>,
    /// Longest wait for a connection (ms). Default: 1000.
    #[serde(default = "default_connect_timeout_ms")]
    pub connect_timeout_ms: u64,
    /// How long (ms) a lost connection is tried again, request after request, before the
    /// run ends with the safe stop. Default 0: the first failure ends the run (after the
    /// safe values are written, on a new connection if need be). While it is tried the
    /// loop waits: the periods it misses are counted as overruns, and the controller
    /// sees a gap.
    #[serde(default)]
    pub reconnect_ms: u64,
    /// Registers a read may skip to join two values into one request. Default: 8.
    #[serde(default = "default_max_gap")]
    pub max_gap: u16,
    /// One per channel, in the scenario's order.
    pub channels: Vec<ModbusChannel>,
}

fn default_unit() -> u8 {
    1
}
fn default_connect_timeout_ms() -> u64 {
    1000
}
fn default_max_gap() -> u16 {
    8
}

/// Where one channel lives in the server.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModbusChannel {
    /// The measured output.
    pub output: Point,
    /// The input to write: a holding register or a coil.
    pub input: Point,
    /// What the plant really applies, where the server has it (an actuator's feedback);
    /// absent: what was written, after the register's rounding and range.
    #[serde(default)]
    pub applied: Option<Point>,
    /// The input written on every way out: the end of a run, SIGTERM, an error, a lost
    /// connection. Default 0. Must lie inside the channel's actuator range.
    #[serde(default)]
    pub safe: f64,
}

/// One value in the server.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Point {
    /// Register kind.
    pub kind: RegisterKind,
    /// 0-based address of the (first) register or bit.
    pub address: u16,
    /// How the register's bits are a number. Default: `uint16` for registers, `bool` for
    /// coils and discrete inputs.
    #[serde(default, rename = "type")]
    pub value_type: Option<ValueType>,
    /// Which word of a 32-bit value comes first. Default: big (the high word).
    #[serde(default)]
    pub word_order: WordOrder,
    /// Engineering value = raw × scale + offset. Default 1.
    #[serde(default = "one")]
    pub scale: f64,
    /// Default 0.
    #[serde(default)]
    pub offset: f64,
}

fn one() -> f64 {
    1.0
}

/// Modbus's four tables.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RegisterKind {
    /// Read-write bits (function codes 1, 5, 15).
    Coil,
    /// Read-only bits (function code 2).
    DiscreteInput,
    /// Read-only registers (function code 4).
    Input,
    /// Read-write registers (function codes 3, 6, 16).
    Holding,
}

impl RegisterKind {
    /// A bit table (coils, discrete inputs), not registers.
    pub fn is_bit(self) -> bool {
        matches!(self, RegisterKind::Coil | RegisterKind::DiscreteInput)
    }
    /// The bridge may write it.
    pub fn is_writable(self) -> bool {
        matches!(self, RegisterKind::Coil | RegisterKind::Holding)
    }
    fn max_read(self) -> u16 {
        if self.is_bit() {
            MAX_BITS_PER_READ
        } else {
            MAX_REGISTERS_PER_READ
        }
    }
}

/// How a register's bits are a number.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ValueType {
    /// A coil or discrete input: 0 or 1.
    Bool,
    /// One register, two's complement.
    Int16,
    /// One register.
    Uint16,
    /// Two registers, two's complement.
    Int32,
    /// Two registers.
    Uint32,
    /// Two registers, IEEE 754 single precision.
    Float32,
}

impl ValueType {
    /// Registers (or bits) it takes.
    pub fn width(self) -> u16 {
        match self {
            ValueType::Bool | ValueType::Int16 | ValueType::Uint16 => 1,
            ValueType::Int32 | ValueType::Uint32 | ValueType::Float32 => 2,
        }
    }
    /// The raw range an integer type can hold (`None` for floats).
    fn raw_range(self) -> Option<(f64, f64)> {
        match self {
            ValueType::Bool => Some((0.0, 1.0)),
            ValueType::Int16 => Some((i16::MIN.into(), i16::MAX.into())),
            ValueType::Uint16 => Some((0.0, u16::MAX.into())),
            ValueType::Int32 => Some((i32::MIN.into(), i32::MAX.into())),
            ValueType::Uint32 => Some((0.0, u32::MAX.into())),
            ValueType::Float32 => None,
        }
    }
}

/// Which word of a 32-bit value comes first.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum WordOrder {
    /// The high word first (Modbus's own byte order, carried to words).
    #[default]
    Big,
    /// The low word first ("word-swapped", frequent in PLCs).
    Little,
}

/// A map that cannot be used, with the field at fault.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{field}: {reason}")]
pub struct MapError {
    /// The field, as in the file (`channels[0].input.kind`).
    pub field: String,
    /// Why.
    pub reason: String,
}

fn map_error(field: impl Into<String>, reason: impl Into<String>) -> MapError {
    MapError {
        field: field.into(),
        reason: reason.into(),
    }
}

impl Point {
    /// The type in force (the default of its kind if none is written).
    pub fn value_type(&self) -> ValueType {
        self.value_type.unwrap_or(if self.kind.is_bit() {
            ValueType::Bool
        } else {
            ValueType::Uint16
        })
    }

    /// Registers or bits it spans.
    pub fn width(&self) -> u16 {
        self.value_type().width()
    }

    /// The first address past it (as `u32`: a value may end at 65536).
    pub fn end(&self) -> u32 {
        u32::from(self.address) + u32::from(self.width())
    }

    fn check(&self, field: &str) -> Result<(), MapError> {
        let t = self.value_type();
        if self.kind.is_bit() != (t == ValueType::Bool) {
            return Err(map_error(
                format!("{field}.type"),
                format!(
                    "{t:?} does not fit a {:?} (bits are bool, registers numbers)",
                    self.kind
                ),
            ));
        }
        if self.end() > 65536 {
            return Err(map_error(
                format!("{field}.address"),
                format!(
                    "{} registers from {} pass the last address, 65535",
                    self.width(),
                    self.address
                ),
            ));
        }
        if !self.scale.is_finite() || self.scale == 0.0 {
            return Err(map_error(
                format!("{field}.scale"),
                "must be finite and non-zero",
            ));
        }
        if !self.offset.is_finite() {
            return Err(map_error(format!("{field}.offset"), "must be finite"));
        }
        Ok(())
    }

    /// The engineering value of the words (or bits, as 0/1) read for it. `None` for a
    /// float that is not finite: a sensor's NaN must never reach a controller.
    pub fn decode(&self, words: &[u16]) -> Option<f64> {
        let (a, b) = (words.first().copied()?, words.get(1).copied().unwrap_or(0));
        let (hi, lo) = match self.word_order {
            WordOrder::Big => (a, b),
            WordOrder::Little => (b, a),
        };
        let pair = (u32::from(hi) << 16) | u32::from(lo);
        let raw = match self.value_type() {
            ValueType::Bool => f64::from(u8::from(a != 0)),
            ValueType::Int16 => f64::from(a as i16),
            ValueType::Uint16 => f64::from(a),
            ValueType::Int32 => f64::from(pair as i32),
            ValueType::Uint32 => f64::from(pair),
            ValueType::Float32 => f64::from(f32::from_bits(pair)),
        };
        let v = raw * self.scale + self.offset;
        v.is_finite().then_some(v)
    }

    /// The words to write for the engineering value `v`, and the value they stand for
    /// (after the register's rounding and range: what the plant is really given). A bit is
    /// set for `v >= 0.5`.
    pub fn encode(&self, v: f64) -> (Vec<u16>, f64) {
        let raw = (v - self.offset) / self.scale;
        let t = self.value_type();
        let raw = match t.raw_range() {
            Some((lo, hi)) if t == ValueType::Bool => f64::from(u8::from(raw >= 0.5)).clamp(lo, hi),
            Some((lo, hi)) => raw.round().clamp(lo, hi),
            // Beyond f32's range a cast gives infinity: the largest finite value instead.
            None => f64::from(raw.clamp(-f64::from(f32::MAX), f64::from(f32::MAX)) as f32),
        };
        let pair = match t {
            ValueType::Bool | ValueType::Int16 | ValueType::Uint16 => {
                let w = if t == ValueType::Int16 {
                    raw as i16 as u16
                } else {
                    raw as u16
                };
                return (vec![w], raw * self.scale + self.offset);
            }
            ValueType::Int32 => raw as i32 as u32,
            ValueType::Uint32 => raw as u32,
            ValueType::Float32 => (raw as f32).to_bits(),
        };
        let (hi, lo) = ((pair >> 16) as u16, pair as u16);
        let words = match self.word_order {
            WordOrder::Big => vec![hi, lo],
            WordOrder::Little => vec![lo, hi],
        };
        (words, raw * self.scale + self.offset)
    }
}

impl ModbusConfig {
    /// Check the map for `channels` channels whose actuator ranges are `ranges`
    /// (`(min, max)`, infinite where unlimited). `period` gives the default timeout.
    pub fn check(&self, ranges: &[(f64, f64)]) -> Result<(), MapError> {
        if self.address.trim().is_empty() {
            return Err(map_error("address", "needs host:port"));
        }
        let link = LinkLimits {
            timeout_ms: self.timeout_ms,
            connect_timeout_ms: self.connect_timeout_ms,
            connect_max_ms: 60_000,
            reconnect_ms: self.reconnect_ms,
        };
        link.check(self.channels.len(), ranges.len())?;
        for (i, (c, &(min, max))) in self.channels.iter().zip(ranges).enumerate() {
            let f = format!("channels[{i}]");
            c.output.check(&format!("{f}.output"))?;
            c.input.check(&format!("{f}.input"))?;
            if let Some(a) = &c.applied {
                a.check(&format!("{f}.applied"))?;
            }
            if !c.input.kind.is_writable() {
                return Err(map_error(
                    format!("{f}.input.kind"),
                    format!(
                        "a {:?} cannot be written: use holding or coil",
                        c.input.kind
                    ),
                ));
            }
            check_safe(&f, c.safe, min, max)?;
            // What the register really holds for it (its type's range, its rounding).
            let (_, written) = c.input.encode(c.safe);
            if written < min || written > max || (written - c.safe).abs() > c.input.scale.abs() {
                return Err(map_error(
                    format!("{f}.safe"),
                    format!(
                        "{} would be written as {written} by the input's register ({:?}, scale {}, offset {})",
                        c.safe,
                        c.input.value_type(),
                        c.input.scale,
                        c.input.offset
                    ),
                ));
            }
        }
        self.check_inputs_apart()
    }

    /// Two inputs sharing a register would overwrite each other.
    fn check_inputs_apart(&self) -> Result<(), MapError> {
        for (i, a) in self.channels.iter().enumerate() {
            for (j, b) in self.channels.iter().enumerate().skip(i + 1) {
                let (a, b) = (&a.input, &b.input);
                let overlap = a.kind == b.kind
                    && u32::from(a.address) < b.end()
                    && u32::from(b.address) < a.end();
                if overlap {
                    return Err(map_error(
                        format!("channels[{j}].input"),
                        format!("shares {:?} {} with channels[{i}].input", b.kind, b.address),
                    ));
                }
            }
        }
        Ok(())
    }

    /// The timeout per request for a loop of period `period` (s).
    pub fn timeout(&self, period: f64) -> std::time::Duration {
        request_timeout(self.timeout_ms, period)
    }
}

/// The link settings every server map has (Modbus here, OPC UA in [`crate::opcua`]), and
/// their checks, written once.
pub(crate) struct LinkLimits {
    pub(crate) timeout_ms: Option<u64>,
    pub(crate) connect_timeout_ms: u64,
    /// The longest `connect_timeout_ms` this protocol accepts.
    pub(crate) connect_max_ms: u64,
    pub(crate) reconnect_ms: u64,
}

impl LinkLimits {
    /// The timeouts in range, and a map of `mapped` channels for a file of `channels`.
    pub(crate) fn check(&self, mapped: usize, channels: usize) -> Result<(), MapError> {
        if self.timeout_ms == Some(0) || self.timeout_ms.is_some_and(|t| t > 60_000) {
            return Err(map_error("timeout_ms", "must be 1 to 60000"));
        }
        let max = self.connect_max_ms;
        if self.connect_timeout_ms == 0 || self.connect_timeout_ms > max {
            return Err(map_error(
                "connect_timeout_ms",
                format!("must be 1 to {max}"),
            ));
        }
        if self.reconnect_ms > 3_600_000 {
            return Err(map_error("reconnect_ms", "at most 3600000 (an hour)"));
        }
        if mapped != channels {
            return Err(map_error(
                "channels",
                format!("{mapped} channel(s) mapped, the plant file has {channels}"),
            ));
        }
        Ok(())
    }
}

/// A channel's (`field`, e.g. `channels[0]`) safe value inside its actuator range.
pub(crate) fn check_safe(field: &str, safe: f64, min: f64, max: f64) -> Result<(), MapError> {
    if safe.is_finite() && safe >= min && safe <= max {
        return Ok(());
    }
    Err(map_error(
        format!("{field}.safe"),
        format!("{safe} is outside the channel's actuator range [{min}, {max}]"),
    ))
}

/// The timeout per request: `timeout_ms`, or half the period, at least 20 ms (a read and
/// a write must fit in a period).
pub(crate) fn request_timeout(timeout_ms: Option<u64>, period: f64) -> std::time::Duration {
    let ms = timeout_ms.unwrap_or_else(|| ((period * 500.0).ceil() as u64).max(20));
    std::time::Duration::from_millis(ms)
}

/// One read request: a run of one kind's addresses, and the values it carries.
#[derive(Debug, Clone, PartialEq)]
pub struct Block {
    /// Register kind.
    pub kind: RegisterKind,
    /// First address.
    pub start: u16,
    /// Registers or bits.
    pub count: u16,
    /// The values it carries: `(index in the list planned, offset in the block)`.
    pub values: Vec<(usize, u16)>,
}

/// The fewest read requests that cover `points`: per kind, addresses in order, a value
/// joins the block before it if at most `max_gap` unread addresses lie between them and the
/// block stays within Modbus's limit per request.
pub fn plan_reads(points: &[Point], max_gap: u16) -> Vec<Block> {
    let mut order: Vec<usize> = (0..points.len()).collect();
    order.sort_by_key(|&i| (points[i].kind, points[i].address));
    let mut blocks: Vec<Block> = Vec::new();
    for i in order {
        let p = &points[i];
        let joined = blocks.last_mut().filter(|b| {
            let end = u32::from(b.start) + u32::from(b.count);
            b.kind == p.kind
                && u32::from(p.address) <= end + u32::from(max_gap)
                && p.end().max(end) - u32::from(b.start) <= u32::from(p.kind.max_read())
        });
        match joined {
            Some(b) => {
                let end = (u32::from(b.start) + u32::from(b.count)).max(p.end());
                b.count = (end - u32::from(b.start)) as u16;
                b.values.push((i, p.address - b.start));
            }
            None => blocks.push(Block {
                kind: p.kind,
                start: p.address,
                count: p.width(),
                values: vec![(i, 0)],
            }),
        }
    }
    blocks
}

/// One write request: contiguous registers (or coils) of one kind, the words in order.
#[derive(Debug, Clone, PartialEq)]
pub struct WriteBlock {
    /// Holding or coil.
    pub kind: RegisterKind,
    /// First address.
    pub start: u16,
    /// Words (for coils, 0 or 1 each).
    pub words: Vec<u16>,
}

/// The fewest write requests for `writes` (`(point, its words)`): contiguous addresses of
/// one kind go in one request, up to Modbus's limit.
pub fn plan_writes(writes: &[(Point, Vec<u16>)]) -> Vec<WriteBlock> {
    let mut order: Vec<&(Point, Vec<u16>)> = writes.iter().collect();
    order.sort_by_key(|(p, _)| (p.kind, p.address));
    let mut blocks: Vec<WriteBlock> = Vec::new();
    for (p, words) in order {
        let joined = blocks.last_mut().filter(|b| {
            b.kind == p.kind
                && u32::from(b.start) + b.words.len() as u32 == u32::from(p.address)
                && b.words.len() + words.len() <= usize::from(MAX_REGISTERS_PER_WRITE)
        });
        match joined {
            Some(b) => b.words.extend_from_slice(words),
            None => blocks.push(WriteBlock {
                kind: p.kind,
                start: p.address,
                words: words.clone(),
            }),
        }
    }
    blocks
}

#[cfg(test)]
mod tests {
    use super::*;

    fn point(kind: RegisterKind, address: u16, t: ValueType) -> Point {
        Point {
            kind,
            address,
            value_type: Some(t),
            word_order: WordOrder::Big,
            scale: 1.0,
            offset: 0.0,
        }
    }

    #[test]
    fn values_round_trip_through_their_words_in_both_word_orders() {
        for order in [WordOrder::Big, WordOrder::Little] {
            for (t, v) in [
                (ValueType::Int16, -1234.0),
                (ValueType::Uint16, 65535.0),
                (ValueType::Int32, -7_000_000.0),
                (ValueType::Uint32, 4_000_000_000.0),
                (ValueType::Float32, 21.5),
            ] {
                let p = Point {
                    word_order: order,
                    ..point(RegisterKind::Holding, 0, t)
                };
                let (words, given) = p.encode(v);
                assert_eq!(words.len(), usize::from(t.width()));
                assert_eq!(given, v, "{t:?}");
                assert_eq!(p.decode(&words), Some(v), "{t:?} {order:?}");
            }
        }
    }

    #[test]
    fn word_order_decides_which_word_is_high() {
        let big = point(RegisterKind::Input, 0, ValueType::Uint32);
        let little = Point {
            word_order: WordOrder::Little,
            ..big
        };
        assert_eq!(big.decode(&[1, 2]), Some(65538.0));
        assert_eq!(little.decode(&[1, 2]), Some(131_073.0));
        // 1.0f32 is 0x3F80_0000.
        let f = point(RegisterKind::Input, 0, ValueType::Float32);
        assert_eq!(f.decode(&[0x3F80, 0]), Some(1.0));
        assert_eq!(
            Point {
                word_order: WordOrder::Little,
                ..f
            }
            .decode(&[0, 0x3F80]),
            Some(1.0)
        );
    }

    #[test]
    fn scale_and_offset_make_engineering_units_and_rounding_is_reported() {
        // A register in 0.1 degC above -50: raw 735 is 23.5 degC.
        let p = Point {
            scale: 0.1,
            offset: -50.0,
            ..point(RegisterKind::Holding, 0, ValueType::Int16)
        };
        assert!((p.decode(&[735]).unwrap() - 23.5).abs() < 1e-9);
        let (w, given) = p.encode(23.54);
        assert_eq!(w, vec![735]);
        assert!(
            (given - 23.5).abs() < 1e-9,
            "the applied value is what the register holds"
        );
        // Out of the type's range: clamped, and the clamp is what is reported.
        let u = point(RegisterKind::Holding, 0, ValueType::Uint16);
        assert_eq!(u.encode(-3.0), (vec![0], 0.0));
        assert_eq!(u.encode(1e9), (vec![65535], 65535.0));
        let c = point(RegisterKind::Coil, 0, ValueType::Bool);
        assert_eq!(c.encode(0.7), (vec![1], 1.0));
        assert_eq!(c.encode(0.2), (vec![0], 0.0));
    }

    #[test]
    fn a_nan_or_infinite_float_is_refused() {
        let f = point(RegisterKind::Input, 0, ValueType::Float32);
        let nan = f32::NAN.to_bits();
        assert_eq!(f.decode(&[(nan >> 16) as u16, nan as u16]), None);
        let inf = f32::INFINITY.to_bits();
        assert_eq!(f.decode(&[(inf >> 16) as u16, inf as u16]), None);
        assert_eq!(f.decode(&[]), None, "no words: nothing to decode");
    }

    #[test]
    fn reads_are_joined_per_kind_within_the_gap_and_the_limit() {
        let pts = [
            point(RegisterKind::Input, 10, ValueType::Float32),
            point(RegisterKind::Holding, 0, ValueType::Int16),
            point(RegisterKind::Input, 0, ValueType::Float32),
            point(RegisterKind::Input, 4, ValueType::Uint16),
            point(RegisterKind::Input, 300, ValueType::Uint16),
            point(RegisterKind::Coil, 3, ValueType::Bool),
        ];
        let blocks = plan_reads(&pts, 8);
        let shape: Vec<_> = blocks.iter().map(|b| (b.kind, b.start, b.count)).collect();
        assert_eq!(
            shape,
            vec![
                (RegisterKind::Coil, 3, 1),
                (RegisterKind::Input, 0, 12),
                (RegisterKind::Input, 300, 1),
                (RegisterKind::Holding, 0, 1),
            ]
        );
        assert_eq!(blocks[1].values, vec![(2, 0), (3, 4), (0, 10)]);
        // No gap allowed: input 0-1 and 4 are two requests.
        assert_eq!(plan_reads(&pts[2..4], 0).len(), 2);
        // A block never exceeds 125 registers.
        let far = [
            point(RegisterKind::Input, 0, ValueType::Uint16),
            point(RegisterKind::Input, 124, ValueType::Float32),
        ];
        assert_eq!(plan_reads(&far, 200).len(), 2);
    }

    #[test]
    fn contiguous_writes_go_in_one_request() {
        let a = point(RegisterKind::Holding, 2, ValueType::Float32);
        let b = point(RegisterKind::Holding, 0, ValueType::Float32);
        let c = point(RegisterKind::Holding, 10, ValueType::Int16);
        let blocks = plan_writes(&[(a, vec![3, 4]), (b, vec![1, 2]), (c, vec![9])]);
        assert_eq!(
            blocks,
            vec![
                WriteBlock {
                    kind: RegisterKind::Holding,
                    start: 0,
                    words: vec![1, 2, 3, 4]
                },
                WriteBlock {
                    kind: RegisterKind::Holding,
                    start: 10,
                    words: vec![9]
                },
            ]
        );
    }

    fn config(channels: Vec<ModbusChannel>) -> ModbusConfig {
        ModbusConfig {
            address: "127.0.0.1:502".into(),
            unit: 1,
            timeout_ms: None,
            connect_timeout_ms: 1000,
            reconnect_ms: 0,
            max_gap: 8,
            channels,
        }
    }

    fn channel(input: Point, safe: f64) -> ModbusChannel {
        ModbusChannel {
            output: point(RegisterKind::Input, 0, ValueType::Float32),
            input,
            applied: None,
            safe,
        }
    }

    #[test]
    fn a_map_that_cannot_work_is_refused_with_its_field() {
        let holding = point(RegisterKind::Holding, 0, ValueType::Float32);
        let ok = config(vec![channel(holding, 0.0)]);
        assert_eq!(ok.check(&[(0.0, 24.0)]), Ok(()));
        let field = |c: &ModbusConfig, r: &[(f64, f64)]| c.check(r).unwrap_err().field;
        assert_eq!(field(&ok, &[(1.0, 24.0)]), "channels[0].safe");
        assert_eq!(field(&ok, &[(0.0, 24.0), (0.0, 1.0)]), "channels");
        let read_only = config(vec![channel(
            point(RegisterKind::Input, 0, ValueType::Uint16),
            0.0,
        )]);
        assert_eq!(field(&read_only, &[(0.0, 24.0)]), "channels[0].input.kind");
        let coil_as_float = config(vec![channel(
            point(RegisterKind::Coil, 0, ValueType::Float32),
            0.0,
        )]);
        assert_eq!(
            field(&coil_as_float, &[(0.0, 24.0)]),
            "channels[0].input.type"
        );
        let past_end = config(vec![channel(
            point(RegisterKind::Holding, 65535, ValueType::Float32),
            0.0,
        )]);
        assert_eq!(
            field(&past_end, &[(0.0, 24.0)]),
            "channels[0].input.address"
        );
        let overlapping = config(vec![
            channel(holding, 0.0),
            channel(point(RegisterKind::Holding, 1, ValueType::Uint16), 0.0),
        ]);
        assert_eq!(
            field(&overlapping, &[(0.0, 24.0), (0.0, 24.0)]),
            "channels[1].input"
        );
        // A safe value the register cannot hold: uint16 above an offset of 10 writes 10.
        let offset = config(vec![channel(
            Point {
                offset: 10.0,
                ..point(RegisterKind::Holding, 0, ValueType::Uint16)
            },
            0.0,
        )]);
        assert_eq!(field(&offset, &[(0.0, 24.0)]), "channels[0].safe");
        let direct = ModbusConfig {
            unit: 0,
            ..ok.clone()
        };
        assert_eq!(
            direct.check(&[(0.0, 24.0)]),
            Ok(()),
            "unit 0: a TCP device directly"
        );
        let mut zero_scale = ok.clone();
        zero_scale.channels[0].output.scale = 0.0;
        assert_eq!(
            field(&zero_scale, &[(0.0, 24.0)]),
            "channels[0].output.scale"
        );
    }

    #[test]
    fn the_default_timeout_is_half_a_period_at_least_20_ms() {
        let c = config(vec![]);
        assert_eq!(c.timeout(0.1).as_millis(), 50);
        assert_eq!(c.timeout(0.01).as_millis(), 20);
        let set = ModbusConfig {
            timeout_ms: Some(7),
            ..c
        };
        assert_eq!(set.timeout(0.1).as_millis(), 7);
    }
}

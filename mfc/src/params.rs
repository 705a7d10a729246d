//! The tunable parameters of a channel, in one table: [`PARAMS`].
//!
//! An operator changes a running channel one parameter at a time, by name (`kp=450`,
//! `dead_zone=8`). The names, which laws have each one, its unit, its meaning and its sanity
//! bounds live here and nowhere else: the wire's partial change (`ChannelUpdate` in the
//! protocol), the operator tools and their documentation (`docs/parameters.md`) are all
//! derived from this table, so a new gain is one entry here (and its field on the wire).
//!
//! Each entry reads and writes its value in a [`ChannelConfig`] ([`Param::get`],
//! [`Param::set`]); a law that has no such parameter (`alpha` on a PID) is an error
//! ([`MfcError::NoSuchParameter`]), never a silent no-op, so a caller never believes a
//! gain changed when it did not.
//!
//! The bounds are absolute sanity limits (no plant needs `|kp| > 1e6`), chosen from what
//! the laws mean and what the shipped controllers use. They are data here: the controller
//! service refuses a change outside them (and narrows them from the device's period and
//! envelope, `controller-service/src/bounds.rs`); the laws' own checks (`validate`) also
//! decide what a channel accepts.
//!
//! Units: `y` is the unit of the channel's measured output, `u` of the law's command, `v`
//! of what the actuator gets (the output map's side, e.g. volts), and `n` the order of the
//! ultra-local model `y^(n) = F + α u`.

use core::fmt;

use crate::channel::{ChannelConfig, LawConfig};
use crate::error::{MfcError, Result};

/// The three control laws, without their parameters.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum LawKind {
    /// iP, iPI, iPD or iPID ([`crate::IntelligentController`]).
    Intelligent,
    /// The PID baseline ([`crate::Pid`]).
    Pid,
    /// The linear ADRC baseline ([`crate::Adrc`]).
    Adrc,
}

impl LawKind {
    /// Every law, in the order the table lists them.
    pub const ALL: [LawKind; 3] = [LawKind::Intelligent, LawKind::Pid, LawKind::Adrc];

    /// The name written in files and on the wire (`intelligent`, `pid`, `adrc`).
    pub fn name(self) -> &'static str {
        match self {
            LawKind::Intelligent => "intelligent",
            LawKind::Pid => "pid",
            LawKind::Adrc => "adrc",
        }
    }
}

impl fmt::Display for LawKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl LawConfig {
    /// Which law this is.
    pub fn kind(&self) -> LawKind {
        match self {
            LawConfig::Intelligent { .. } => LawKind::Intelligent,
            LawConfig::Pid { .. } => LawKind::Pid,
            LawConfig::Adrc { .. } => LawKind::Adrc,
        }
    }
}

/// Which laws have a parameter.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Scope {
    /// A parameter of these laws only.
    Laws(&'static [LawKind]),
    /// A parameter of the output map, which every law has.
    OutputMap,
}

impl Scope {
    /// Whether `law` has the parameter.
    pub fn has(self, law: LawKind) -> bool {
        match self {
            Scope::Laws(laws) => laws.contains(&law),
            Scope::OutputMap => true,
        }
    }
}

/// Sanity limits of a parameter's value (the controller service refuses a change outside
/// them). An infinite limit is no limit; NaN is never inside.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Bounds {
    /// `lo <= x <= hi`.
    Range {
        /// Lowest sane value.
        lo: f64,
        /// Highest sane value.
        hi: f64,
    },
    /// `lo <= |x| <= hi`, either sign: a gain whose sign is the plant's, never 0.
    Magnitude {
        /// Smallest sane magnitude (> 0).
        lo: f64,
        /// Largest sane magnitude.
        hi: f64,
    },
}

impl Bounds {
    /// Whether `x` lies within the bounds.
    pub fn contains(self, x: f64) -> bool {
        match self {
            Bounds::Range { lo, hi } => lo <= x && x <= hi,
            Bounds::Magnitude { lo, hi } => lo <= x.abs() && x.abs() <= hi,
        }
    }
}

/// A number as operators write it: `inf`, `-inf`, `0`, `0.001` to `9999.5` plain, and
/// beyond in scientific notation (`1e6`, `1e-6`, `1e308` rather than 309 digits), in the
/// shortest form that reads back to the same value.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Readable(pub f64);

impl fmt::Display for Readable {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let x = self.0;
        if x == 0.0 || !x.is_finite() || (1e-3..1e4).contains(&x.abs()) {
            write!(f, "{x}")
        } else {
            write!(f, "{x:e}")
        }
    }
}

impl fmt::Display for Bounds {
    /// `[lo, hi]`, or `|x| in [lo, hi]` (`[-1e6, 1e6]`, `[-inf, 0]`).
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let (lo, hi) = match *self {
            Bounds::Range { lo, hi } => (lo, hi),
            Bounds::Magnitude { lo, hi } => {
                f.write_str("|x| in ")?;
                (lo, hi)
            }
        };
        f.write_str("[")?;
        write!(f, "{}", Readable(lo))?;
        f.write_str(", ")?;
        write!(f, "{}", Readable(hi))?;
        f.write_str("]")
    }
}

/// Where a parameter's value lives in a configuration: `None` when its law does not have it.
/// An output map without a rate limit gets `+inf` written in first, so reading it (on a
/// copy) says `inf` and writing it replaces the `inf`.
type Slot = fn(&mut ChannelConfig) -> Option<&mut f64>;

/// One tunable parameter.
#[derive(Clone, Copy)]
pub struct Param {
    /// The name operators write (`kp`), the same as the protocol's `ChannelUpdate` field.
    pub name: &'static str,
    /// The laws that have it.
    pub scope: Scope,
    /// Its unit (`y`, `u`, `v` and `n` as in the module documentation).
    pub unit: &'static str,
    /// What it does, in one line.
    pub meaning: &'static str,
    /// Sanity limits (see [`Bounds`]).
    pub bounds: Bounds,
    slot: Slot,
}

impl fmt::Debug for Param {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Param")
            .field("name", &self.name)
            .field("scope", &self.scope)
            .field("unit", &self.unit)
            .field("bounds", &self.bounds)
            .finish_non_exhaustive()
    }
}

impl Param {
    fn missing(&self, c: &ChannelConfig) -> MfcError {
        MfcError::NoSuchParameter {
            name: self.name,
            law: c.law.kind(),
        }
    }

    /// Its value in `c`; an error if `c`'s law has no such parameter. An absent output
    /// limit reads as infinite (`min` as `-inf`, `max` and `rate_limit` as `inf`).
    pub fn get(&self, c: &ChannelConfig) -> Result<f64> {
        let mut copy = *c;
        (self.slot)(&mut copy)
            .map(|v| *v)
            .ok_or_else(|| self.missing(c))
    }

    /// Write `value` into `c`, unchecked (the laws check a configuration when a channel is
    /// built from it); an error, with `c` untouched, if `c`'s law has no such parameter.
    pub fn set(&self, c: &mut ChannelConfig, value: f64) -> Result<()> {
        let err = self.missing(c);
        let slot = (self.slot)(c).ok_or(err)?;
        *slot = value;
        Ok(())
    }

    /// Whether `law` has this parameter.
    pub fn applies_to(&self, law: LawKind) -> bool {
        self.scope.has(law)
    }
}

/// The parameter called `name`, if any.
pub fn param(name: &str) -> Option<&'static Param> {
    PARAMS.iter().find(|p| p.name == name)
}

/// The names of [`PARAMS`], in its order.
pub fn names() -> impl Iterator<Item = &'static str> {
    PARAMS.iter().map(|p| p.name)
}

const I: &[LawKind] = &[LawKind::Intelligent];
const I_PID: &[LawKind] = &[LawKind::Intelligent, LawKind::Pid];
const PID: &[LawKind] = &[LawKind::Pid];
const ADRC: &[LawKind] = &[LawKind::Adrc];

const GAIN: Bounds = Bounds::Range { lo: -1e6, hi: 1e6 };
const INPUT_GAIN: Bounds = Bounds::Magnitude { lo: 1e-6, hi: 1e6 };
const TIME: Bounds = Bounds::Range { lo: 0.0, hi: 1e4 };
const BANDWIDTH: Bounds = Bounds::Range { lo: 0.0, hi: 1e6 };
const POSITIVE_BANDWIDTH: Bounds = Bounds::Range { lo: 1e-6, hi: 1e6 };
const OFFSET: Bounds = Bounds::Range { lo: 0.0, hi: 1e6 };

fn intelligent(c: &mut ChannelConfig) -> Option<&mut crate::IntelligentParams> {
    match &mut c.law {
        LawConfig::Intelligent { params, .. } => Some(params),
        _ => None,
    }
}

fn pid(c: &mut ChannelConfig) -> Option<&mut crate::PidParams> {
    match &mut c.law {
        LawConfig::Pid { params } => Some(params),
        _ => None,
    }
}

fn adrc(c: &mut ChannelConfig) -> Option<&mut crate::AdrcParams> {
    match &mut c.law {
        LawConfig::Adrc { params } => Some(params),
        _ => None,
    }
}

/// The gains the intelligent laws and the PID share (`kp`, `ki`, `kd`, `derivative_filter`).
macro_rules! shared {
    ($field:ident) => {
        |c| match &mut c.law {
            LawConfig::Intelligent { params, .. } => Some(&mut params.$field),
            LawConfig::Pid { params } => Some(&mut params.$field),
            LawConfig::Adrc { .. } => None,
        }
    };
}

/// Every tunable parameter: the laws' (intelligent, then PID, then ADRC), then the output
/// map's. The protocol's `ChannelUpdate` has one optional field per entry, of the same name.
pub static PARAMS: [Param; 19] = [
    Param {
        name: "kp",
        scope: Scope::Laws(I_PID),
        unit: "1/s^n (intelligent); u/y (PID)",
        meaning: "proportional gain on the tracking error",
        bounds: GAIN,
        slot: shared!(kp),
    },
    Param {
        name: "ki",
        scope: Scope::Laws(I_PID),
        unit: "1/s^(n+1) (intelligent); u/(y s) (PID)",
        meaning: "integral gain (iPI, iPID, PID)",
        bounds: GAIN,
        slot: shared!(ki),
    },
    Param {
        name: "kd",
        scope: Scope::Laws(I_PID),
        unit: "1/s^(n-1) (intelligent); u s/y (PID)",
        meaning: "derivative gain (iPD, iPID, PID)",
        bounds: GAIN,
        slot: shared!(kd),
    },
    Param {
        name: "alpha",
        scope: Scope::Laws(I),
        unit: "y/(u s^n)",
        meaning: "alpha of y^(n) = F + alpha u: the scale of u, its sign the plant's",
        bounds: INPUT_GAIN,
        slot: |c| intelligent(c).map(|p| &mut p.alpha),
    },
    Param {
        name: "derivative_filter",
        scope: Scope::Laws(I_PID),
        unit: "s",
        meaning: "time constant of the low-pass on the derivative of y",
        bounds: TIME,
        slot: shared!(derivative_filter),
    },
    Param {
        name: "derivative_observer",
        scope: Scope::Laws(I),
        unit: "rad/s",
        meaning: "bandwidth of the model-based observer of y' (n = 2; 0: the filter instead)",
        bounds: BANDWIDTH,
        slot: |c| intelligent(c).map(|p| &mut p.derivative_observer),
    },
    Param {
        name: "estimate_filter",
        scope: Scope::Laws(I),
        unit: "s",
        meaning: "time constant of a low-pass on F_est (0: off)",
        bounds: TIME,
        slot: |c| intelligent(c).map(|p| &mut p.estimate_filter),
    },
    Param {
        name: "hold_estimate_filter",
        scope: Scope::Laws(I),
        unit: "s",
        meaning: "time constant of the low-pass on F_est once the reference rests (0: off)",
        bounds: TIME,
        slot: |c| intelligent(c).map(|p| &mut p.hold_estimate_filter),
    },
    Param {
        name: "hold_after",
        scope: Scope::Laws(I),
        unit: "s",
        meaning: "how long the reference rests before hold_estimate_filter applies",
        bounds: TIME,
        slot: |c| intelligent(c).map(|p| &mut p.hold_after),
    },
    Param {
        name: "hold_band",
        scope: Scope::Laws(I),
        unit: "u",
        meaning: "while holding, the command changes sign only beyond +-hold_band (0: off)",
        bounds: OFFSET,
        slot: |c| intelligent(c).map(|p| &mut p.hold_band),
    },
    Param {
        name: "b0",
        scope: Scope::Laws(ADRC),
        unit: "y/(u s^n)",
        meaning: "input gain b0 of y^(n) = f + b0 u, its sign the plant's",
        bounds: INPUT_GAIN,
        slot: |c| adrc(c).map(|p| &mut p.b0),
    },
    Param {
        name: "wc",
        scope: Scope::Laws(ADRC),
        unit: "rad/s",
        meaning: "controller bandwidth: every closed-loop pole at -wc",
        bounds: POSITIVE_BANDWIDTH,
        slot: |c| adrc(c).map(|p| &mut p.wc),
    },
    Param {
        name: "wo",
        scope: Scope::Laws(ADRC),
        unit: "rad/s",
        meaning: "observer bandwidth, typically 3 to 10 times wc",
        bounds: POSITIVE_BANDWIDTH,
        slot: |c| adrc(c).map(|p| &mut p.wo),
    },
    Param {
        name: "setpoint_weight",
        scope: Scope::Laws(PID),
        unit: "1",
        meaning: "weight b of the reference in the proportional term kp (b y* - y)",
        bounds: Bounds::Range { lo: 0.0, hi: 10.0 },
        slot: |c| pid(c).map(|p| &mut p.setpoint_weight),
    },
    Param {
        name: "dead_zone",
        scope: Scope::OutputMap,
        unit: "v",
        meaning: "dead-zone compensation: the offset added in the direction of u",
        bounds: OFFSET,
        slot: |c| Some(&mut c.output.dead_zone),
    },
    Param {
        name: "smoothing",
        scope: Scope::OutputMap,
        unit: "u",
        meaning: "softness of the compensation (0: a step; s: dead_zone tanh(u/s))",
        bounds: OFFSET,
        slot: |c| Some(&mut c.output.smoothing),
    },
    Param {
        name: "min",
        scope: Scope::OutputMap,
        unit: "v",
        meaning: "lowest output (-inf: none), inside the envelope",
        bounds: Bounds::Range {
            lo: f64::NEG_INFINITY,
            hi: 0.0,
        },
        slot: |c| Some(&mut c.output.min),
    },
    Param {
        name: "max",
        scope: Scope::OutputMap,
        unit: "v",
        meaning: "highest output (inf: none), inside the envelope",
        bounds: Bounds::Range {
            lo: 0.0,
            hi: f64::INFINITY,
        },
        slot: |c| Some(&mut c.output.max),
    },
    Param {
        name: "rate_limit",
        scope: Scope::OutputMap,
        unit: "v/s",
        meaning: "largest change of the output per second (inf: none)",
        bounds: Bounds::Range {
            lo: 1e-6,
            hi: f64::INFINITY,
        },
        slot: |c| Some(c.output.rate_limit.get_or_insert(f64::INFINITY)),
    },
];

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{AdrcParams, OutputMapConfig, PidParams};

    fn configs() -> [ChannelConfig; 3] {
        [
            ChannelConfig::default(),
            ChannelConfig {
                law: LawConfig::Pid {
                    params: PidParams::default(),
                },
                output: OutputMapConfig::AERO,
            },
            ChannelConfig {
                law: LawConfig::Adrc {
                    params: AdrcParams::default(),
                },
                output: OutputMapConfig::default(),
            },
        ]
    }

    #[test]
    fn names_are_unique_and_each_reaches_exactly_the_laws_of_its_scope() {
        for (i, p) in PARAMS.iter().enumerate() {
            assert!(PARAMS[..i].iter().all(|q| q.name != p.name), "{p:?}");
            assert_eq!(param(p.name).map(|q| q.name), Some(p.name));
            for c in configs() {
                let law = c.law.kind();
                assert_eq!(p.get(&c).is_ok(), p.applies_to(law), "{} on {law}", p.name);
            }
        }
        assert!(param("gain").is_none());
        assert_eq!(names().count(), PARAMS.len());
    }

    #[test]
    fn a_set_value_is_read_back_and_touches_nothing_else() {
        for c in configs() {
            for p in PARAMS.iter().filter(|p| p.applies_to(c.law.kind())) {
                let mut changed = c;
                // A value no default has, in the bounds of every parameter except min.
                let v = if p.name == "min" { -0.375 } else { 0.375 };
                p.set(&mut changed, v).unwrap();
                assert_eq!(p.get(&changed), Ok(v), "{}", p.name);
                for q in PARAMS.iter().filter(|q| q.name != p.name) {
                    assert_eq!(q.get(&changed), q.get(&c), "{} moved {}", p.name, q.name);
                }
            }
        }
    }

    #[test]
    fn a_law_without_the_parameter_says_so_and_keeps_the_config() {
        let mut pid = configs()[1];
        let before = pid;
        let alpha = param("alpha").unwrap();
        let e = alpha.set(&mut pid, 2.0).unwrap_err();
        assert_eq!(pid, before);
        assert_eq!(
            e,
            MfcError::NoSuchParameter {
                name: "alpha",
                law: LawKind::Pid
            }
        );
        assert_eq!(alpha.get(&pid), Err(e));
    }

    #[test]
    fn an_absent_limit_reads_as_infinite_and_writing_it_sets_it() {
        let mut c = ChannelConfig::default();
        let rate = param("rate_limit").unwrap();
        assert_eq!(rate.get(&c), Ok(f64::INFINITY));
        assert_eq!(c.output.rate_limit, None, "reading changes nothing");
        rate.set(&mut c, 50.0).unwrap();
        assert_eq!(c.output.rate_limit, Some(50.0));
        assert_eq!(param("min").unwrap().get(&c), Ok(f64::NEG_INFINITY));
    }

    #[test]
    fn bounds_contain_what_they_say() {
        let alpha = param("alpha").unwrap().bounds;
        assert!(alpha.contains(-2.0) && alpha.contains(1e6) && alpha.contains(1e-6));
        assert!(!alpha.contains(0.0) && !alpha.contains(2e6) && !alpha.contains(f64::NAN));
        let min = param("min").unwrap().bounds;
        assert!(min.contains(f64::NEG_INFINITY) && min.contains(0.0) && !min.contains(0.1));
    }

    #[test]
    fn every_default_lies_within_bounds() {
        let [a, b, c] = configs();
        let aero = ChannelConfig {
            law: LawConfig::default(),
            output: OutputMapConfig::AERO,
        };
        for c in [a, b, c, aero] {
            for p in PARAMS.iter().filter(|p| p.applies_to(c.law.kind())) {
                let v = p.get(&c).unwrap();
                assert!(
                    p.bounds.contains(v),
                    "{} = {v} outside {}",
                    p.name,
                    p.bounds
                );
            }
        }
    }
}

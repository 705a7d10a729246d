//! What a change may set: every parameter of the table (`mfc::params::PARAMS`) and every
//! reference piece within bounds, so that an absurd value is refused with its reason,
//! whichever client sends it.
//!
//! A value can be finite, inside the envelope and still absurd: `kp = 1e308` drives every
//! command to a limit (bang-bang inside the envelope), a sine of period `1e-300` makes the
//! reference non-finite at the next sample. The bound of a parameter is, in this order:
//!
//! 1. the service's file, per channel (`bounds = { kp = [0, 500] }`): wider or narrower,
//!    the person who wrote the file decides;
//! 2. else derived from the device: from its period `h` where the law's discrete loop
//!    says what cannot work (an intelligent law's error dynamics `e^(n) = -kp e - ...`
//!    diverge, under the ideal ultra-local model and an exact estimate, once
//!    `|kp| > (2/h)^n`; a bandwidth above the Nyquist frequency `π/h` means nothing), and
//!    from its envelope (a dead-zone offset larger than the largest command);
//!    intersected with
//! 3. the table's absolute sanity bounds, which also hold before the device's period is
//!    known (its first samples).
//!
//! Only the values a change moves are checked: a bound narrowed in the file below a value
//! in force does not block an unrelated change. References: every piece's size at most
//! [`REFERENCE_LIMIT`] (or inside the channel's `range` from the file, all pieces summed
//! at their extremes), times at most [`TIME_LIMIT`], a sine's period at least two of the
//! device's periods (at least [`MIN_SINE_PERIOD`] before the period is known).
//!
//! Pure: values in, a reason out.

use std::collections::BTreeMap;
use std::f64::consts::PI;

use mfc::params::{Bounds, Param, Readable, PARAMS};
use mfc::trajectory::Piece;
use mfc::{ChannelConfig, LawConfig};

use crate::envelope::Limits;

/// The largest size of a reference piece (its value, height, amplitude, or a ramp's
/// rise) without a `range` in the file: beyond any physical unit this service steers,
/// and small enough that a sine's second derivative stays finite.
pub const REFERENCE_LIMIT: f64 = 1e9;

/// The latest time a reference piece may name (s): about 31 years.
pub const TIME_LIMIT: f64 = 1e9;

/// The shortest sine period before the device's period is known (s): no plant of this
/// service runs faster than 1 kHz, and a period must span two samples to be seen.
pub const MIN_SINE_PERIOD: f64 = 2e-3;

/// A channel's bounds as the service's file sets them.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ChannelBounds {
    /// Per parameter (its name in `PARAMS`), `[lo, hi]` replacing the derived bound.
    set: Vec<(&'static str, Bounds)>,
    /// The range of the channel's measured output: every reference stays inside.
    range: Option<(f64, f64)>,
}

impl ChannelBounds {
    /// The range of the channel's measured output from the file, if it sets one.
    pub fn range(&self) -> Option<(f64, f64)> {
        self.range
    }

    /// From the file's `bounds` and `range`; `Err` names the field and the reason.
    pub fn from_file(
        bounds: &BTreeMap<String, [f64; 2]>,
        range: Option<[f64; 2]>,
    ) -> Result<Self, (String, String)> {
        let mut set = Vec::with_capacity(bounds.len());
        for (name, &[lo, hi]) in bounds {
            let Some(p) = mfc::params::param(name) else {
                let names: Vec<_> = mfc::params::names().collect();
                return Err((
                    format!("bounds.{name}"),
                    format!("no such parameter (one of {})", names.join(", ")),
                ));
            };
            if lo.is_nan() || hi.is_nan() || lo > hi {
                return Err((
                    format!("bounds.{name}"),
                    format!("[{lo}, {hi}]: lo must not be above hi, neither NaN"),
                ));
            }
            set.push((p.name, Bounds::Range { lo, hi }));
        }
        let range = match range {
            None => None,
            Some([lo, hi]) if lo.is_finite() && hi.is_finite() && lo < hi => Some((lo, hi)),
            Some([lo, hi]) => {
                return Err((
                    "range".into(),
                    format!("[{lo}, {hi}]: two finite values, lo below hi"),
                ))
            }
        };
        Ok(Self { set, range })
    }

    /// The bound of `p` on a channel configured as `c` inside `envelope`, at period `h`
    /// (`None`: not known yet), and where it comes from (for the refusal's reason).
    pub fn of(
        &self,
        p: &Param,
        c: &ChannelConfig,
        envelope: &Limits,
        h: Option<f64>,
    ) -> (Bounds, String) {
        let h = tidy(h);
        if let Some((_, b)) = self.set.iter().find(|(name, _)| *name == p.name) {
            return (*b, "set in the service's file".into());
        }
        match derived(p, c, envelope, h) {
            Some((b, why)) => (intersect(b, p.bounds), why),
            None => (p.bounds, "the parameter's sanity bounds".into()),
        }
    }

    /// Whether every parameter `new` sets to another value than `old` (all of them when
    /// the law changes) lies within its bound.
    pub fn check_change(
        &self,
        old: &ChannelConfig,
        new: &ChannelConfig,
        envelope: &Limits,
        h: Option<f64>,
    ) -> Result<(), String> {
        let same_law = old.law.kind() == new.law.kind();
        for p in PARAMS.iter().filter(|p| p.applies_to(new.law.kind())) {
            let Ok(v) = p.get(new) else { continue };
            let moved = !same_law || p.get(old).map_or(true, |o| o.to_bits() != v.to_bits());
            if moved {
                self.check_value(p, new, envelope, h, v)?;
            }
        }
        Ok(())
    }

    /// Whether every parameter of `c` lies within its bound (a file's own values).
    pub fn check_all(
        &self,
        c: &ChannelConfig,
        envelope: &Limits,
        h: Option<f64>,
    ) -> Result<(), String> {
        for p in PARAMS.iter().filter(|p| p.applies_to(c.law.kind())) {
            if let Ok(v) = p.get(c) {
                self.check_value(p, c, envelope, h, v)?;
            }
        }
        Ok(())
    }

    fn check_value(
        &self,
        p: &Param,
        c: &ChannelConfig,
        env: &Limits,
        h: Option<f64>,
        v: f64,
    ) -> Result<(), String> {
        let (b, why) = self.of(p, c, env, h);
        // An output limit left out reads as infinite: "none" is never absurd.
        let unset = matches!(p.name, "min" | "max" | "rate_limit") && v.is_infinite();
        if b.contains(v) || unset {
            return Ok(());
        }
        Err(format!(
            "{} = {} is outside {b} ({why}; the file's `bounds` may change it)",
            p.name,
            readable(v)
        ))
    }

    /// Whether a channel's reference pieces are sane at period `h`; `Err` names the
    /// piece and the reason.
    pub fn check_reference(&self, pieces: &[Piece], h: Option<f64>) -> Result<(), String> {
        let h = tidy(h);
        let min_period = h.map_or(MIN_SINE_PERIOD, |h| 2.0 * h);
        let (mut lo, mut hi) = (0.0, 0.0);
        for (j, piece) in pieces.iter().enumerate() {
            let at = |what: &str| format!("pieces[{j}].{what}");
            let (times, (a, b)) = extent(piece);
            if let Some((name, t)) = times
                .iter()
                .find(|(_, t)| t.abs() > TIME_LIMIT && t.is_finite())
            {
                return Err(format!(
                    "{}: {} s is beyond {TIME_LIMIT:e} s",
                    at(name),
                    readable(*t)
                ));
            }
            if let Piece::Sine { period, .. } = *piece {
                if period < min_period {
                    return Err(format!(
                        "{}: {} s is shorter than {} s ({})",
                        at("period"),
                        readable(period),
                        readable(min_period),
                        if h.is_some() {
                            "two of the device's periods"
                        } else {
                            "the shortest before the device's period is known"
                        }
                    ));
                }
            }
            if self.range.is_none() && a.abs().max(b.abs()) > REFERENCE_LIMIT {
                return Err(format!(
                    "{}: reaches {}, beyond {REFERENCE_LIMIT:e} (set the channel's `range` in the service's file for larger units)",
                    at("size"),
                    readable(if a.abs() > b.abs() { a } else { b })
                ));
            }
            lo += a;
            hi += b;
        }
        match self.range {
            Some((rl, rh)) if lo < rl || hi > rh => Err(format!(
                "the pieces summed at their extremes span [{}, {}], outside the channel's range [{}, {}]",
                readable(lo),
                readable(hi),
                readable(rl),
                readable(rh)
            )),
            _ => Ok(()),
        }
    }
}

/// The period to the microsecond: an estimate from the plant's clock is `0.00999…`, and
/// a bound of `199.99999999999997` reads worse than `200` and means the same.
fn tidy(h: Option<f64>) -> Option<f64> {
    h.map(|h| (h * 1e6).round() / 1e6)
        .filter(|h| *h > 0.0 && h.is_finite())
}

/// A piece's times (named, for the reason) and the interval its value stays in.
fn extent(p: &Piece) -> (Vec<(&'static str, f64)>, (f64, f64)) {
    let span = |x: f64| (x.min(0.0), x.max(0.0));
    match *p {
        Piece::Constant { value } => (vec![], (value, value)),
        Piece::Ramp { start, end, slope } => {
            let rise = slope * (end - start);
            (vec![("start", start), ("end", end)], span(rise))
        }
        Piece::SmoothStep {
            start,
            duration,
            height,
        } => (vec![("start", start), ("duration", duration)], span(height)),
        Piece::Sine {
            amplitude,
            period,
            start,
            end,
            fade,
            ..
        } => (
            vec![
                ("start", start),
                ("end", end),
                ("fade", fade),
                ("period", period),
            ],
            (-amplitude.abs(), amplitude.abs()),
        ),
    }
}

/// The bound the device's period or envelope gives `p`, if any, with the reason.
fn derived(p: &Param, c: &ChannelConfig, env: &Limits, h: Option<f64>) -> Option<(Bounds, String)> {
    let sym = |r: f64| Bounds::Range { lo: -r, hi: r };
    let nyquist = |h: f64| Bounds::Range {
        lo: 0.0,
        hi: PI / h,
    };
    match (p.name, &c.law, h) {
        ("kp" | "ki" | "kd", LawConfig::Intelligent { params, .. }, Some(h)) => {
            let n = i32::from(params.order.n());
            let power = match p.name {
                "kp" => n,
                "ki" => n + 1,
                _ => n - 1,
            };
            // kd on a first-order model is a pure number (e' (1 + kd) = -kp e): no period in it.
            (power > 0).then(|| {
                (
                    sym((2.0 / h).powi(power)),
                    format!("(2/h)^{power} for a model of order {n} at the device's period h = {} s: beyond it the loop diverges", readable(h)),
                )
            })
        }
        ("derivative_observer", LawConfig::Intelligent { .. }, Some(h))
        | ("wc" | "wo", LawConfig::Adrc { .. }, Some(h)) => Some((
            nyquist(h),
            format!(
                "the Nyquist frequency π/h at the device's period h = {} s",
                readable(h)
            ),
        )),
        ("dead_zone", _, _) if env.min.is_finite() || env.max.is_finite() => {
            let largest = [env.min, env.max]
                .into_iter()
                .filter(|x| x.is_finite())
                .fold(0.0_f64, |m, x| m.max(x.abs()));
            Some((
                Bounds::Range {
                    lo: 0.0,
                    hi: largest,
                },
                "the envelope's largest command: a larger offset saturates every command".into(),
            ))
        }
        _ => None,
    }
}

/// `a` within `b`'s limits where both are ranges (a magnitude bound stays the table's).
fn intersect(a: Bounds, b: Bounds) -> Bounds {
    match (a, b) {
        (Bounds::Range { lo: l1, hi: h1 }, Bounds::Range { lo: l2, hi: h2 }) => Bounds::Range {
            lo: l1.max(l2),
            hi: h1.min(h2),
        },
        (_, b) => b,
    }
}

/// A number as people read it (`mfc::params::Readable`).
fn readable(x: f64) -> String {
    Readable(x).to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn file(
        bounds: &[(&str, [f64; 2])],
        range: Option<[f64; 2]>,
    ) -> Result<ChannelBounds, (String, String)> {
        let b = bounds.iter().map(|(n, v)| (n.to_string(), *v)).collect();
        ChannelBounds::from_file(&b, range)
    }

    #[test]
    fn the_file_names_real_parameters_and_sane_intervals() {
        assert!(file(&[("kp", [0.0, 1.0])], Some([-1.0, 1.0])).is_ok());
        for (b, r, field) in [
            (vec![("gain", [0.0, 1.0])], None, "bounds.gain"),
            (vec![("kp", [1.0, 0.0])], None, "bounds.kp"),
            (vec![("kp", [f64::NAN, 0.0])], None, "bounds.kp"),
            (vec![], Some([1.0, 1.0]), "range"),
            (vec![], Some([f64::NEG_INFINITY, 1.0]), "range"),
        ] {
            assert_eq!(file(&b, r).unwrap_err().0, field);
        }
    }

    #[test]
    fn a_reference_stays_inside_the_range_with_its_pieces_summed_at_their_extremes() {
        let b = file(&[], Some([-1.0, 1.0])).unwrap();
        let sine = |amplitude: f64| Piece::Sine {
            amplitude,
            period: 1.0,
            phase: 0.0,
            start: 0.0,
            end: f64::INFINITY,
            fade: 0.0,
        };
        let c = |value: f64| Piece::Constant { value };
        assert!(b.check_reference(&[c(0.5), sine(0.4)], None).is_ok());
        let e = b.check_reference(&[c(0.5), sine(0.6)], None).unwrap_err();
        assert!(
            e.contains(", 1.1], outside the channel's range [-1, 1]"),
            "{e}"
        );
        // A ramp down rises by slope * (end - start) < 0.
        let ramp = Piece::Ramp {
            start: 0.0,
            end: 10.0,
            slope: -0.2,
        };
        assert!(b
            .check_reference(&[ramp], None)
            .unwrap_err()
            .contains("[-2, 0]"));
        // Without a range, sizes up to the limit are accepted, in any unit.
        let open = file(&[], None).unwrap();
        assert!(open.check_reference(&[c(1e8)], None).is_ok());
        assert!(open.check_reference(&[c(2e9)], None).is_err());
        // Before the period is known, a sine is at least MIN_SINE_PERIOD long.
        let short = Piece::Sine {
            amplitude: 1.0,
            period: 1e-3,
            phase: 0.0,
            start: 0.0,
            end: f64::INFINITY,
            fade: 0.0,
        };
        let e = open.check_reference(&[short], None).unwrap_err();
        assert!(e.contains("before the device's period is known"), "{e}");
        assert!(open.check_reference(&[short], Some(1e-4)).is_ok());
    }

    #[test]
    fn derived_bounds_follow_the_order_and_the_period() {
        let b = ChannelBounds::default();
        let env = Limits {
            min: -24.0,
            max: 12.0,
            rate_limit: None,
        };
        let mut c = ChannelConfig::default();
        let kp = mfc::params::param("kp").unwrap();
        let (bound, why) = b.of(kp, &c, &env, Some(0.01));
        assert_eq!(
            (bound, why.contains("(2/h)^1")),
            (
                Bounds::Range {
                    lo: -200.0,
                    hi: 200.0
                },
                true
            )
        );
        // Unknown period: the table's.
        assert_eq!(b.of(kp, &c, &env, None).0, kp.bounds);
        if let LawConfig::Intelligent { params, .. } = &mut c.law {
            params.order = mfc::Order::Two;
        }
        assert_eq!(
            b.of(kp, &c, &env, Some(0.01)).0,
            Bounds::Range { lo: -4e4, hi: 4e4 }
        );
        // At 1 ms the derived 4e6 is wider than the table's 1e6: the table's holds.
        assert_eq!(
            b.of(kp, &c, &env, Some(0.001)).0,
            Bounds::Range { lo: -1e6, hi: 1e6 }
        );
        let dz = mfc::params::param("dead_zone").unwrap();
        assert_eq!(
            b.of(dz, &c, &env, None).0,
            Bounds::Range { lo: 0.0, hi: 24.0 }
        );
        // Without limits, the table's.
        assert_eq!(b.of(dz, &c, &Limits::default(), None).0, dz.bounds);
    }
}

//! A device's safety envelope: the limits no command to it may ever exceed.
//!
//! It belongs to the device, not to a law. The service's file sets it (by default from the
//! channel's output map there); configuration changes from the network can move a law's
//! output map only inside it, and the last step before a command leaves checks it again.
//! Widening it is a separate request the file must allow. Pure values, no I/O.

use mfc::OutputMapConfig;
use serde::{Deserialize, Serialize};

/// Limits of one channel: `min <= v <= max`, and `|dv/dt| <= rate_limit`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Limits {
    /// Lowest command. Default: -infinity (unbounded).
    #[serde(default = "neg_inf")]
    pub min: f64,
    /// Highest command. Default: +infinity (unbounded).
    #[serde(default = "pos_inf")]
    pub max: f64,
    /// Largest change of the command per second of plant time. Default: none.
    #[serde(default)]
    pub rate_limit: Option<f64>,
}

fn neg_inf() -> f64 {
    f64::NEG_INFINITY
}
fn pos_inf() -> f64 {
    f64::INFINITY
}

impl Default for Limits {
    /// Unbounded: what a channel whose output map sets no limits gets.
    fn default() -> Self {
        Self {
            min: f64::NEG_INFINITY,
            max: f64::INFINITY,
            rate_limit: None,
        }
    }
}

impl Limits {
    /// The limits an output map already enforces: the default envelope of a channel whose
    /// file names none, so a file written before envelopes existed keeps its meaning.
    pub fn of_map(o: &OutputMapConfig) -> Self {
        Self {
            min: o.min,
            max: o.max,
            rate_limit: o.rate_limit,
        }
    }

    /// Well formed: no NaN, `min < max`, a positive finite rate limit.
    pub fn check(&self) -> Result<(), String> {
        if self.min.is_nan() || self.max.is_nan() || self.min >= self.max {
            return Err(format!(
                "min {:?} must be below max {:?} (and neither NaN)",
                self.min, self.max
            ));
        }
        if let Some(r) = self.rate_limit {
            if !(r.is_finite() && r > 0.0) {
                return Err(format!("rate_limit {r:?} must be finite and > 0"));
            }
        }
        Ok(())
    }

    /// Whether `other` allows anything these limits do not: a lower min, a higher max, or a
    /// faster (or no) rate limit.
    pub fn is_widened_by(&self, other: &Limits) -> bool {
        other.min < self.min
            || other.max > self.max
            || match (self.rate_limit, other.rate_limit) {
                (Some(_), None) => true,
                (Some(a), Some(b)) => b > a,
                (None, _) => false,
            }
    }

    /// Fit an output map a client asked for into these limits. A limit the client left
    /// out (infinite) becomes the envelope's; one it set outside the envelope is refused,
    /// naming `field`, so a request never widens the envelope silently either way.
    pub fn fit_request(&self, o: OutputMapConfig, field: &str) -> Result<OutputMapConfig, String> {
        let mut out = o;
        if o.min.is_finite() {
            if o.min < self.min {
                return Err(format!(
                    "{field}.min {:?} is below the envelope's {:?} (change the envelope first)",
                    o.min, self.min
                ));
            }
        } else {
            out.min = self.min;
        }
        if o.max.is_finite() {
            if o.max > self.max {
                return Err(format!(
                    "{field}.max {:?} is above the envelope's {:?} (change the envelope first)",
                    o.max, self.max
                ));
            }
        } else {
            out.max = self.max;
        }
        out.rate_limit = match (o.rate_limit, self.rate_limit) {
            (Some(r), Some(e)) if r > e => {
                return Err(format!(
                    "{field}.rate_limit {r:?} is above the envelope's {e:?} (change the envelope first)"
                ))
            }
            (Some(r), _) => Some(r),
            (None, e) => e,
        };
        Ok(out)
    }

    /// The limits both allow: the higher min, the lower max, the slower rate limit. Used
    /// when a fleet member takes a device's envelope from another: the result never
    /// allows more than this member's own file does. Disjoint limits give an empty
    /// interval, which [`Limits::check`] refuses.
    pub fn intersect(&self, other: &Limits) -> Limits {
        Limits {
            min: self.min.max(other.min),
            max: self.max.min(other.max),
            rate_limit: match (self.rate_limit, other.rate_limit) {
                (Some(a), Some(b)) => Some(a.min(b)),
                (a, b) => a.or(b),
            },
        }
    }

    /// Narrow a map in force into these limits (after the envelope itself changed): the
    /// map keeps what lies inside and takes the envelope's bound where it lay outside.
    pub fn narrow(&self, o: OutputMapConfig) -> OutputMapConfig {
        let min = o.min.max(self.min).min(self.max);
        let max = o.max.min(self.max).max(self.min);
        OutputMapConfig {
            dead_zone: o.dead_zone,
            smoothing: o.smoothing,
            min,
            max,
            rate_limit: match (o.rate_limit, self.rate_limit) {
                (Some(r), Some(e)) => Some(r.min(e)),
                (r, e) => r.or(e),
            },
        }
    }

    /// The last check before a command leaves: `v` clipped into `[min, max]` and, given
    /// `prev = (p, dt)`, moved at most `rate_limit * dt` from `p`, the value the actuator
    /// holds (`dt = 0`: not at all). Returns the value and whether it had to clip. `v` must
    /// be finite (the caller refuses a non-finite command outright).
    pub fn clamp(&self, v: f64, prev: Option<(f64, f64)>) -> (f64, bool) {
        let mut out = v.clamp(self.min, self.max);
        if let (Some(r), Some((p, dt))) = (self.rate_limit, prev) {
            if dt.is_finite() && dt >= 0.0 {
                // A tolerance of one part in 10^9 of the step: the output map's own rate
                // limit, computed the same way, must not count as a clip.
                let step = r * dt * (1.0 + 1e-9);
                out = out.clamp(p - step, p + step).clamp(self.min, self.max);
            }
        }
        (out, out != v)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const AERO: Limits = Limits {
        min: -24.0,
        max: 24.0,
        rate_limit: None,
    };

    #[test]
    fn a_request_cannot_widen_and_absent_limits_take_the_envelopes() {
        let asked = OutputMapConfig {
            dead_zone: 10.0,
            ..Default::default()
        };
        let fitted = AERO.fit_request(asked, "channels[0].output").unwrap();
        assert_eq!(
            (fitted.min, fitted.max, fitted.dead_zone),
            (-24.0, 24.0, 10.0)
        );
        let wide = OutputMapConfig {
            max: 100.0,
            ..Default::default()
        };
        let e = AERO.fit_request(wide, "channels[1].output").unwrap_err();
        assert!(e.contains("channels[1].output.max 100"), "{e}");
        let narrower = OutputMapConfig {
            min: -5.0,
            max: 5.0,
            rate_limit: Some(100.0),
            ..Default::default()
        };
        assert_eq!(AERO.fit_request(narrower, "x").unwrap(), narrower);
        let rated = Limits {
            rate_limit: Some(50.0),
            ..AERO
        };
        assert!(rated.fit_request(narrower, "x").is_err());
        assert_eq!(
            rated
                .fit_request(OutputMapConfig::default(), "x")
                .unwrap()
                .rate_limit,
            Some(50.0)
        );
    }

    #[test]
    fn widening_is_told_apart_from_narrowing() {
        let narrow = Limits {
            min: -12.0,
            max: 12.0,
            rate_limit: Some(10.0),
        };
        assert!(!AERO.is_widened_by(&narrow));
        assert!(
            narrow.is_widened_by(&AERO),
            "dropping the rate limit widens"
        );
        assert!(AERO.is_widened_by(&Limits { max: 24.5, ..AERO }));
        assert!(AERO.is_widened_by(&Limits::default()));
    }

    #[test]
    fn narrowing_a_map_keeps_it_inside() {
        let map = OutputMapConfig::AERO;
        let env = Limits {
            min: 0.0,
            max: 12.0,
            rate_limit: Some(5.0),
        };
        let m = env.narrow(map);
        assert_eq!((m.min, m.max, m.rate_limit), (0.0, 12.0, Some(5.0)));
        assert_eq!(m.dead_zone, 10.0);
        // A map entirely outside collapses onto the nearest bound, still inside.
        let high = OutputMapConfig {
            min: 20.0,
            max: 30.0,
            ..Default::default()
        };
        let m = env.narrow(high);
        assert!(m.min >= 0.0 && m.max <= 12.0 && m.min <= m.max);
    }

    #[test]
    fn clamp_enforces_range_and_rate() {
        assert_eq!(AERO.clamp(30.0, None), (24.0, true));
        assert_eq!(AERO.clamp(-3.0, None), (-3.0, false));
        let rated = Limits {
            rate_limit: Some(100.0),
            ..AERO
        };
        // 100 V/s over 10 ms: at most 1 V from the previous command.
        let (v, clipped) = rated.clamp(5.0, Some((0.0, 0.01)));
        assert!(clipped && (v - 1.0).abs() < 1e-6, "{v}");
        assert_eq!(rated.clamp(0.5, Some((0.0, 0.01))), (0.5, false));
        assert_eq!(rated.clamp(0.5, Some((0.0, f64::INFINITY))), (0.5, false));
    }

    #[test]
    fn checks_reject_malformed_limits() {
        assert!(Limits {
            min: 1.0,
            max: 1.0,
            rate_limit: None
        }
        .check()
        .is_err());
        assert!(Limits {
            min: f64::NAN,
            ..AERO
        }
        .check()
        .is_err());
        assert!(Limits {
            rate_limit: Some(0.0),
            ..AERO
        }
        .check()
        .is_err());
        assert!(AERO.check().is_ok() && Limits::default().check().is_ok());
    }
}

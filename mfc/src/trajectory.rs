//! Reference trajectories as sums of smooth pieces with analytic derivatives.
//!
//! Part of the core because the controller (in the service) and the plant side (offline
//! simulation, local fallback) must evaluate the same reference at the same time.
//!
//! The intelligent controllers use `y*'` (and `y*''` for n = 2) as a feed-forward, so the
//! reference generator gives them exactly rather than by differencing.
//!
//! ```toml
//! reference = [
//!   { kind = "constant", value = 0.1 },
//!   { kind = "smooth_step", start = 2.0, duration = 1.5, height = 0.3 },
//!   { kind = "ramp", start = 10.0, end = 14.0, slope = -0.05 },
//!   { kind = "sine", amplitude = 0.1, period = 4.0, start = 20.0, end = 36.0, fade = 1.0 },
//! ]
//! ```

use crate::Reference;

/// One piece of a reference; the reference is the sum of its pieces.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "snapshot", derive(bincode::Encode, bincode::Decode))]
#[cfg_attr(
    feature = "serde",
    serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)
)]
pub enum Piece {
    /// `value` at all times.
    Constant {
        /// The value.
        value: f64,
    },
    /// 0 before `start`, rising at `slope` per second until `end`, then held.
    Ramp {
        /// Start time (s).
        start: f64,
        /// End time (s).
        end: f64,
        /// Slope (units per second).
        slope: f64,
    },
    /// 0 before `start`, `height` after `start + duration`, joined by the quintic
    /// `10s³ - 15s⁴ + 6s⁵` (continuous up to the second derivative).
    SmoothStep {
        /// Start time (s).
        start: f64,
        /// Rise time (s), > 0.
        duration: f64,
        /// Final value.
        height: f64,
    },
    /// `amplitude · sin(2π (t - start)/period + phase)` between `start` and `end`, faded in
    /// and out over `fade` seconds with the same quintic (0 outside).
    Sine {
        /// Amplitude.
        amplitude: f64,
        /// Period (s), > 0.
        period: f64,
        /// Phase (rad). Default 0.
        #[cfg_attr(feature = "serde", serde(default))]
        phase: f64,
        /// Start time (s). Default 0.
        #[cfg_attr(feature = "serde", serde(default))]
        start: f64,
        /// End time (s). Default: never.
        #[cfg_attr(feature = "serde", serde(default = "infinity"))]
        end: f64,
        /// Fade-in and fade-out time (s). Default 0 (abrupt).
        #[cfg_attr(feature = "serde", serde(default))]
        fade: f64,
    },
}

#[cfg(feature = "serde")]
fn infinity() -> f64 {
    f64::INFINITY
}

/// A value with its first two time derivatives.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
struct Jet {
    v: f64,
    d: f64,
    dd: f64,
}

impl Jet {
    fn mul(self, o: Jet) -> Jet {
        Jet {
            v: self.v * o.v,
            d: self.d * o.v + self.v * o.d,
            dd: self.dd * o.v + 2.0 * self.d * o.d + self.v * o.dd,
        }
    }
}

/// Quintic smooth step of `(t - start)/duration`, clamped to [0, 1].
fn smoothstep(t: f64, start: f64, duration: f64) -> Jet {
    let s = (t - start) / duration;
    if s <= 0.0 {
        return Jet::default();
    }
    if s >= 1.0 {
        return Jet {
            v: 1.0,
            ..Jet::default()
        };
    }
    let (s2, s3) = (s * s, s * s * s);
    Jet {
        v: 10.0 * s3 - 15.0 * s2 * s2 + 6.0 * s3 * s2,
        d: (30.0 * s2 - 60.0 * s3 + 30.0 * s2 * s2) / duration,
        dd: (60.0 * s - 180.0 * s2 + 120.0 * s3) / (duration * duration),
    }
}

impl Piece {
    fn jet(&self, t: f64) -> Jet {
        match *self {
            Piece::Constant { value } => Jet {
                v: value,
                ..Jet::default()
            },
            Piece::Ramp { start, end, slope } => {
                let active = t > start && t < end;
                Jet {
                    v: slope * (t.clamp(start, end) - start),
                    d: if active { slope } else { 0.0 },
                    dd: 0.0,
                }
            }
            Piece::SmoothStep {
                start,
                duration,
                height,
            } => {
                let s = smoothstep(t, start, duration);
                Jet {
                    v: height * s.v,
                    d: height * s.d,
                    dd: height * s.dd,
                }
            }
            Piece::Sine {
                amplitude,
                period,
                phase,
                start,
                end,
                fade,
            } => {
                if t < start || t > end {
                    return Jet::default();
                }
                let w = core::f64::consts::TAU / period;
                let arg = w * (t - start) + phase;
                let (sin, cos) = (libm::sin(arg), libm::cos(arg));
                let wave = Jet {
                    v: amplitude * sin,
                    d: amplitude * w * cos,
                    dd: -amplitude * w * w * sin,
                };
                if fade <= 0.0 {
                    return wave;
                }
                let fade_in = smoothstep(t, start, fade);
                let fade_out = if end.is_finite() {
                    let s = smoothstep(-t, -end, fade);
                    // d/dt of f(-t) flips the sign of the first derivative.
                    Jet {
                        v: s.v,
                        d: -s.d,
                        dd: s.dd,
                    }
                } else {
                    Jet {
                        v: 1.0,
                        ..Jet::default()
                    }
                };
                wave.mul(fade_in).mul(fade_out)
            }
        }
    }

    /// Check the piece; `Err` names the field and the reason.
    pub fn validate(&self) -> Result<(), (&'static str, &'static str)> {
        let finite = |name, v: f64| {
            if v.is_finite() {
                Ok(())
            } else {
                Err((name, "must be finite"))
            }
        };
        match *self {
            Piece::Constant { value } => finite("value", value),
            Piece::Ramp { start, end, slope } => {
                finite("start", start)?;
                finite("end", end)?;
                finite("slope", slope)?;
                if end < start {
                    return Err(("end", "must not be before start"));
                }
                Ok(())
            }
            Piece::SmoothStep {
                start,
                duration,
                height,
            } => {
                finite("start", start)?;
                finite("height", height)?;
                if !(duration.is_finite() && duration > 0.0) {
                    return Err(("duration", "must be finite and > 0"));
                }
                Ok(())
            }
            Piece::Sine {
                amplitude,
                period,
                phase,
                start,
                end,
                fade,
            } => {
                finite("amplitude", amplitude)?;
                finite("phase", phase)?;
                finite("start", start)?;
                if !(period.is_finite() && period > 0.0) {
                    return Err(("period", "must be finite and > 0"));
                }
                if end.is_nan() || end < start {
                    return Err(("end", "must not be before start"));
                }
                if !(fade.is_finite() && fade >= 0.0) {
                    return Err(("fade", "must be finite and >= 0"));
                }
                if end.is_finite() && 2.0 * fade > end - start {
                    return Err((
                        "fade",
                        "fade-in and fade-out must fit between start and end",
                    ));
                }
                Ok(())
            }
        }
    }
}

/// Evaluate the sum of `pieces` at `t`.
pub fn evaluate(pieces: &[Piece], t: f64) -> Reference {
    let mut sum = Jet::default();
    for p in pieces {
        let j = p.jet(t);
        sum.v += j.v;
        sum.d += j.d;
        sum.dd += j.dd;
    }
    Reference {
        y: sum.v,
        dy: sum.d,
        ddy: sum.dd,
    }
}

#[cfg(all(test, feature = "std"))]
mod tests {
    use super::*;

    /// The analytic derivatives match finite differences of the value.
    #[test]
    fn derivatives_match_finite_differences() {
        let pieces = [
            Piece::Constant { value: 0.3 },
            Piece::SmoothStep {
                start: 1.0,
                duration: 2.0,
                height: -0.4,
            },
            Piece::Sine {
                amplitude: 0.2,
                period: 3.0,
                phase: 0.4,
                start: 0.5,
                end: 9.0,
                fade: 1.5,
            },
        ];
        let h = 1e-5;
        for k in 1..1000 {
            let t = k as f64 * 0.01;
            let r = evaluate(&pieces, t);
            let (a, b) = (evaluate(&pieces, t - h), evaluate(&pieces, t + h));
            assert!((r.dy - (b.y - a.y) / (2.0 * h)).abs() < 1e-5, "dy at {t}");
            assert!(
                (r.ddy - (b.dy - a.dy) / (2.0 * h)).abs() < 1e-4,
                "ddy at {t}"
            );
        }
    }
}

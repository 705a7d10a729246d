//! The actuator map of one channel: dead-zone compensation, saturation, rate limit, and
//! its inverse.
//!
//! The controller computes a *virtual* input `u`; the plant gets a voltage `v`. On the AERO
//! the propellers hardly move below about 10 V, so the paper maps `v = 10 + u` for `u > 0`
//! and `v = -10 + u` for `u < 0`, then the amplifier saturates at ±24 V.
//!
//! That *step* compensation makes every `v` with `0 < |v| < dead_zone` unreachable. A real
//! actuator's dead zone is soft (the AERO's measured torque is already a ninth of full
//! torque at 7.3 V), so holding a small angle needs a voltage inside the gap, and the loop
//! can only reach it on average, by switching across it: a limit cycle (`docs/results-aero.md`).
//! With `smoothing = s > 0` the compensation is `v = u + dead_zone · tanh(u / s)`: odd,
//! continuous, strictly increasing with slope between 1 and `1 + dead_zone / s`, equal to
//! the step's within `dead_zone · (1 - tanh(|u| / s))` away from 0, and onto the whole
//! `[min, max]`: no output is out of reach. `s` is how soft the dead zone is, in units of
//! `u`; `s → 0` gives the paper's map back, and `smoothing = 0` is exactly that map.
//!
//! The estimator must see what the plant *really* got, in the controller's units: the
//! inverse map turns an applied voltage (saturated, rate-limited, or held after a lost
//! command) back into the `u` of the ultra-local model. For the step it is
//! `u_applied = sign(v) · max(|v| - dead_zone, 0)`; for the smooth map it is the unique
//! solution of `v = u + dead_zone · tanh(u / s)`, found to machine precision.

use crate::error::{finite, non_negative, positive, MfcError, Result};

/// Configuration of an [`OutputMap`].
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "serde", serde(default, deny_unknown_fields))]
#[cfg_attr(feature = "snapshot", derive(bincode::Encode, bincode::Decode))]
pub struct OutputMapConfig {
    /// Dead-zone compensation offset added in the direction of `u` (AERO: 10 V). Default 0.
    pub dead_zone: f64,
    /// How soft the compensation is, in units of `u`: 0 (the default) is the paper's step
    /// `v = u ± dead_zone`, which leaves `(0, dead_zone)` unreachable; `s > 0` is the smooth
    /// `v = u + dead_zone · tanh(u / s)`, which reaches every output (module documentation).
    pub smoothing: f64,
    /// Lower output limit (AERO: -24 V). Default: -infinity.
    pub min: f64,
    /// Upper output limit (AERO: +24 V). Default: +infinity.
    pub max: f64,
    /// Largest change of the output per second, if any. Default: none.
    pub rate_limit: Option<f64>,
}

impl Default for OutputMapConfig {
    fn default() -> Self {
        Self {
            dead_zone: 0.0,
            smoothing: 0.0,
            min: f64::NEG_INFINITY,
            max: f64::INFINITY,
            rate_limit: None,
        }
    }
}

impl OutputMapConfig {
    /// The AERO's map from the paper: ±10 V dead-zone compensation as a step, ±24 V
    /// saturation.
    pub const AERO: Self = Self {
        dead_zone: 10.0,
        smoothing: 0.0,
        min: -24.0,
        max: 24.0,
        rate_limit: None,
    };

    /// Check the configuration.
    pub fn validate(&self) -> Result<()> {
        non_negative("dead_zone", self.dead_zone)?;
        non_negative("smoothing", self.smoothing)?;
        if self.min.is_nan() || self.max.is_nan() || self.min > 0.0 || self.max < 0.0 {
            return Err(MfcError::InvalidParameter {
                name: "min/max",
                value: if self.min > 0.0 { self.min } else { self.max },
                reason: "limits must satisfy min <= 0 <= max",
            });
        }
        if let Some(r) = self.rate_limit {
            positive("rate_limit", r)?;
        }
        Ok(())
    }
}

impl OutputMapConfig {
    /// The dead-zone compensation alone (no limits): odd and nondecreasing.
    #[inline]
    pub fn compensate(&self, u: f64) -> f64 {
        let d = self.dead_zone;
        if self.smoothing > 0.0 {
            u + d * libm::tanh(u / self.smoothing)
        } else if u > 0.0 {
            u + d
        } else if u < 0.0 {
            u - d
        } else {
            0.0
        }
    }

    /// The inverse of [`compensate`](Self::compensate): the `u` whose compensation is
    /// `v` (for the step, 0 inside the dead zone). NaN gives NaN.
    #[inline]
    pub fn uncompensate(&self, v: f64) -> f64 {
        let d = self.dead_zone;
        let mag = v.abs();
        let u = if self.smoothing > 0.0 && d > 0.0 {
            self.smooth_root(mag)
        } else {
            (mag - d).max(0.0)
        };
        if v.is_nan() {
            f64::NAN
        } else if v >= 0.0 {
            u
        } else {
            -u
        }
    }

    /// The `u >= 0` whose smooth compensation is `mag >= 0` (out of line: the step's
    /// inverse, inlined where a channel steps, stays short).
    #[inline(never)]
    fn smooth_root(&self, mag: f64) -> f64 {
        let d = self.dead_zone;
        // g(u) = u + d tanh(u/s) is increasing with g' in [1, 1 + d/s], so the root of
        // g(u) = |v| lies in [max(|v| - d, 0), |v|]: Newton's steps, kept inside that
        // bracket by bisection when they leave it, converge in a handful of steps.
        let s = self.smoothing;
        let (mut lo, mut hi) = ((mag - d).max(0.0), mag);
        let mut u = lo;
        for _ in 0..100 {
            let th = libm::tanh(u / s);
            let g = u + d * th - mag;
            if g == 0.0 {
                break;
            }
            if g > 0.0 {
                hi = u;
            } else {
                lo = u;
            }
            let slope = 1.0 + d / s * (1.0 - th * th);
            let mut next = u - g / slope;
            if !(next > lo && next < hi) {
                next = 0.5 * (lo + hi);
            }
            if next == u || hi - lo <= f64::EPSILON * hi {
                break;
            }
            u = next;
        }
        u
    }
}

/// Dead-zone compensation, saturation and rate limit of one channel (stateful only through
/// the rate limit).
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "snapshot", derive(bincode::Encode, bincode::Decode))]
pub struct OutputMap {
    config: OutputMapConfig,
    last: Option<(f64, f64)>,
}

impl OutputMap {
    /// A map with a checked configuration.
    pub fn new(config: OutputMapConfig) -> Result<Self> {
        config.validate()?;
        Ok(Self { config, last: None })
    }

    /// The configuration.
    pub fn config(&self) -> &OutputMapConfig {
        &self.config
    }

    /// Replace the configuration (the rate-limit memory is kept).
    pub fn set_config(&mut self, config: OutputMapConfig) -> Result<()> {
        config.validate()?;
        self.config = config;
        Ok(())
    }

    /// Map `u` to the output `v` applied from time `t` on.
    #[inline]
    pub fn apply(&mut self, t: f64, u: f64) -> Result<f64> {
        finite("time", t)?;
        finite("control", u)?;
        let c = &self.config;
        let mut v = c.compensate(u).clamp(c.min, c.max);
        if let (Some(rate), Some((t0, v0))) = (c.rate_limit, self.last) {
            let dt = (t - t0).max(0.0);
            // The range wins over the rate: where the last output lies outside it (what
            // the plant reported applying, or a restored state), the map returns into it
            // at once rather than leave it at the rate's pace.
            v = v.clamp(v0 - rate * dt, v0 + rate * dt).clamp(c.min, c.max);
        }
        self.last = Some((t, v));
        Ok(v)
    }

    /// The virtual input `u` that an applied output `v` amounts to, under the dead-zone
    /// model the compensation assumes: for the step, `v` inside the dead zone does nothing;
    /// for the smooth map, the `u` it would have compensated to `v`.
    #[inline]
    pub fn inverse(&self, v: f64) -> f64 {
        self.config
            .uncompensate(v.clamp(self.config.min, self.config.max))
    }

    /// Tell the map what was actually applied (for the rate limit's memory).
    pub fn record_applied(&mut self, t: f64, v: f64) {
        if t.is_finite() && v.is_finite() {
            self.last = Some((t, v));
        }
    }
}

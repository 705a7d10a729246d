//! The actuator map of one channel: dead-zone compensation, saturation, rate limit, and
//! its inverse.
//!
//! The controller computes a *virtual* input `u`; the plant gets a voltage `v`. On the AERO
//! the propellers hardly move below about 10 V, so the paper maps `v = 10 + u` for `u > 0`
//! and `v = -10 + u` for `u < 0`, then the amplifier saturates at ±24 V.
//!
//! The estimator must see what the plant *really* got, in the controller's units: the
//! inverse map `u_applied = sign(v) · max(|v| - dead_zone, 0)` turns an applied voltage
//! (saturated, rate-limited, or held after a lost command) back into the `u` of the
//! ultra-local model.

use crate::error::{finite, non_negative, positive, MfcError, Result};

/// Configuration of an [`OutputMap`].
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "serde", serde(default, deny_unknown_fields))]
#[cfg_attr(feature = "snapshot", derive(bincode::Encode, bincode::Decode))]
pub struct OutputMapConfig {
    /// Dead-zone compensation offset added in the direction of `u` (AERO: 10 V). Default 0.
    pub dead_zone: f64,
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
            min: f64::NEG_INFINITY,
            max: f64::INFINITY,
            rate_limit: None,
        }
    }
}

impl OutputMapConfig {
    /// The AERO's map from the paper: ±10 V dead-zone compensation, ±24 V saturation.
    pub const AERO: Self = Self {
        dead_zone: 10.0,
        min: -24.0,
        max: 24.0,
        rate_limit: None,
    };

    /// Check the configuration.
    pub fn validate(&self) -> Result<()> {
        non_negative("dead_zone", self.dead_zone)?;
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
    pub fn apply(&mut self, t: f64, u: f64) -> Result<f64> {
        finite("time", t)?;
        finite("control", u)?;
        let c = &self.config;
        let mut v = if u > 0.0 {
            u + c.dead_zone
        } else if u < 0.0 {
            u - c.dead_zone
        } else {
            0.0
        };
        v = v.clamp(c.min, c.max);
        if let (Some(rate), Some((t0, v0))) = (c.rate_limit, self.last) {
            let dt = (t - t0).max(0.0);
            v = v.clamp(v0 - rate * dt, v0 + rate * dt);
        }
        self.last = Some((t, v));
        Ok(v)
    }

    /// The virtual input `u` that an applied output `v` amounts to, under the dead-zone
    /// model the compensation assumes (`v` inside the dead zone does nothing).
    pub fn inverse(&self, v: f64) -> f64 {
        let v = v.clamp(self.config.min, self.config.max);
        let mag = (v.abs() - self.config.dead_zone).max(0.0);
        if v >= 0.0 {
            mag
        } else {
            -mag
        }
    }

    /// Tell the map what was actually applied (for the rate limit's memory).
    pub fn record_applied(&mut self, t: f64, v: f64) {
        if t.is_finite() && v.is_finite() {
            self.last = Some((t, v));
        }
    }
}

//! The PID baseline, written the way a careful practitioner would, so that comparisons with
//! the intelligent controllers are fair.
//!
//! ```text
//! u = Kp (b y* - y) + I - Kd · D[y],     I' = Ki (y* - y) + Kt (u_applied - u)
//! ```
//!
//! * derivative on the measurement only (no kick on reference steps), filtered by
//!   `s / (τ s + 1)`;
//! * set-point weight `b` on the proportional term;
//! * anti-windup by back-calculation from the input the plant actually received (`Kt`,
//!   default `Ki / Kp`), plus clamping of the integral to the output limits;
//! * output limits;
//! * bumpless start (the integral is initialised so the first output equals the actuator's
//!   current value) and bumpless gain changes (the integral absorbs the change).

use crate::error::{finite, non_negative, MfcError, Result};
use crate::filter::DerivativeFilter;
use crate::Reference;

/// PID parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "serde", serde(default, deny_unknown_fields))]
#[cfg_attr(feature = "snapshot", derive(bincode::Encode, bincode::Decode))]
pub struct PidParams {
    /// Proportional gain. Default: 1.
    pub kp: f64,
    /// Integral gain. Default: 0.
    pub ki: f64,
    /// Derivative gain. Default: 0.
    pub kd: f64,
    /// Derivative filter time constant (s). Default: 0.02.
    pub derivative_filter: f64,
    /// Set-point weight `b` of the proportional term. Default: 1.
    pub setpoint_weight: f64,
    /// Back-calculation gain `Kt` (1/s); `None` for `Ki / Kp` (or 0 without `Kp`).
    pub tracking_gain: Option<f64>,
    /// Lower output limit. Default: -infinity.
    pub out_min: f64,
    /// Upper output limit. Default: +infinity.
    pub out_max: f64,
}

impl Default for PidParams {
    fn default() -> Self {
        Self {
            kp: 1.0,
            ki: 0.0,
            kd: 0.0,
            derivative_filter: 0.02,
            setpoint_weight: 1.0,
            tracking_gain: None,
            out_min: f64::NEG_INFINITY,
            out_max: f64::INFINITY,
        }
    }
}

impl PidParams {
    /// Check the parameters. Gains may be negative (a plant with negative gain) but must
    /// all have the same sign.
    pub fn validate(&self) -> Result<()> {
        finite("kp", self.kp)?;
        finite("ki", self.ki)?;
        finite("kd", self.kd)?;
        let signs = [self.kp, self.ki, self.kd];
        if signs.iter().any(|g| *g > 0.0) && signs.iter().any(|g| *g < 0.0) {
            return Err(MfcError::InvalidParameter {
                name: "kp/ki/kd",
                value: self.kp,
                reason: "gains must not have opposite signs",
            });
        }
        non_negative("derivative_filter", self.derivative_filter)?;
        finite("setpoint_weight", self.setpoint_weight)?;
        if let Some(kt) = self.tracking_gain {
            non_negative("tracking_gain", kt)?;
        }
        if self.out_min.is_nan() || self.out_max.is_nan() || self.out_min >= self.out_max {
            return Err(MfcError::InvalidParameter {
                name: "out_min/out_max",
                value: self.out_min,
                reason: "need out_min < out_max",
            });
        }
        Ok(())
    }

    fn kt(&self) -> f64 {
        match self.tracking_gain {
            Some(kt) => kt,
            None if self.kp != 0.0 => (self.ki / self.kp).abs(),
            None => 0.0,
        }
    }
}

/// A PID controller.
#[derive(Debug, Clone)]
#[cfg_attr(feature = "snapshot", derive(bincode::Encode, bincode::Decode))]
pub struct Pid {
    params: PidParams,
    pending: Option<PidParams>,
    integral: f64,
    derivative: DerivativeFilter,
    last_t: Option<f64>,
    last_u: f64,
    applied: f64,
    start_from: Option<f64>,
}

impl Pid {
    /// A PID with checked parameters.
    pub fn new(params: PidParams) -> Result<Self> {
        params.validate()?;
        Ok(Self {
            params,
            pending: None,
            integral: 0.0,
            derivative: DerivativeFilter::default(),
            last_t: None,
            last_u: 0.0,
            applied: 0.0,
            start_from: None,
        })
    }

    /// Parameters in force (a pending change shows from the next step).
    pub fn params(&self) -> &PidParams {
        self.pending.as_ref().unwrap_or(&self.params)
    }

    /// Change the parameters at the next step, bumplessly.
    pub fn set_params(&mut self, params: PidParams) -> Result<()> {
        params.validate()?;
        self.pending = Some(params);
        Ok(())
    }

    /// The first output will be `u0` (the actuator's current value).
    pub fn bumpless_start(&mut self, u0: f64) -> Result<()> {
        finite("control", u0)?;
        self.start_from = Some(u0);
        self.last_u = u0;
        self.applied = u0;
        Ok(())
    }

    /// Forget the derivative and the time base after a gap in the data, and restart
    /// bumplessly from the input being applied (the integral is re-initialised to it).
    pub fn forget_window(&mut self) {
        self.derivative = DerivativeFilter::default();
        self.last_t = None;
        self.start_from = Some(self.applied);
    }

    /// The input the plant actually received since the last step.
    pub fn set_applied(&mut self, u: f64) -> Result<()> {
        self.applied = finite("applied input", u)?;
        Ok(())
    }

    /// Check a step's inputs without changing anything.
    pub fn check(&self, t: f64, y: f64, r: &Reference) -> Result<()> {
        finite("time", t)?;
        finite("measurement", y)?;
        r.check()?;
        if let Some(previous) = self.last_t {
            if t <= previous {
                return Err(MfcError::TimeNotAdvancing {
                    previous,
                    current: t,
                });
            }
        }
        Ok(())
    }

    /// One step; returns `u`.
    pub fn step(&mut self, t: f64, y: f64, r: &Reference) -> Result<f64> {
        self.check(t, y, r)?;
        let p = self.params;
        let dy = self.derivative.update(t, y, p.derivative_filter);
        let e = r.y - y;
        if let Some(t0) = self.last_t {
            let dt = t - t0;
            self.integral += dt * (p.ki * e + p.kt() * (self.applied - self.last_u));
        }
        self.last_t = Some(t);
        let mut target = self.start_from.take();
        if let Some(new) = self.pending.take() {
            // Keep the output continuous across a gain change.
            target.get_or_insert(self.unclamped(&p, r, y, dy));
            self.params = new;
        }
        let p = self.params;
        if let Some(u0) = target {
            self.integral = u0 - (p.kp * (p.setpoint_weight * r.y - y) - p.kd * dy);
        }
        self.integral = self.integral.clamp(p.out_min, p.out_max);
        let u = self.unclamped(&p, r, y, dy).clamp(p.out_min, p.out_max);
        self.last_u = u;
        self.applied = u;
        Ok(u)
    }

    fn unclamped(&self, p: &PidParams, r: &Reference, y: f64, dy: f64) -> f64 {
        p.kp * (p.setpoint_weight * r.y - y) + self.integral - p.kd * dy
    }
}

//! Intelligent controllers: iP, iPI, iPD and iPID.
//!
//! With `e = y - y*` and `F_est` from the [`Estimator`](crate::Estimator):
//!
//! ```text
//! u = -(F_est - y*^(n) + Kp e + Ki ∫e + Kd e') / α
//! ```
//!
//! keeping only the terms of the [`ControllerKind`]. Because `F_est` cancels what the model
//! does not know, the error follows `e^(n) + Kd e' + Kp e + Ki ∫e ≈ 0`: the gains are chosen
//! for that simple linear equation, not for the plant.
//!
//! # Bumpless changes
//! New parameters take effect at the next sample. The controller evaluates the law with the
//! old and the new parameters on the same data (the estimate is kept linear in `α`, so `F`
//! is re-evaluated for the new `α` exactly), then either re-initialises the integral so the
//! output is continuous (kinds with an integral) or adds the difference as an offset that
//! fades with `bumpless_time_constant`. The applied input therefore never jumps on a change.

use crate::error::{finite, non_negative, nonzero, MfcError, Result};
use crate::estimator::{Estimator, EstimatorConfig, LinearEstimate, DEFAULT_CAPACITY};
use crate::filter::{decay, DerivativeFilter};
use crate::{ControllerKind, Order, Reference};

/// Parameters of an intelligent controller.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "serde", serde(default, deny_unknown_fields))]
#[cfg_attr(feature = "snapshot", derive(bincode::Encode, bincode::Decode))]
pub struct IntelligentParams {
    /// iP, iPI, iPD or iPID. Default: iP.
    pub kind: ControllerKind,
    /// Order of the ultra-local model. Default: 1.
    pub order: Order,
    /// `α`, non-zero; its sign is the sign of the plant's gain. Default: 1.
    pub alpha: f64,
    /// Proportional gain (>= 0). Default: 1.
    pub kp: f64,
    /// Integral gain (>= 0), used by iPI and iPID. Default: 0.
    pub ki: f64,
    /// Derivative gain (>= 0), used by iPD and iPID. Default: 0.
    pub kd: f64,
    /// Time constant (s) of the filter on the derivative of `y`. Default: 0.02.
    pub derivative_filter: f64,
    /// Time constant (s) with which the offset left by a parameter change fades.
    /// Default: 0.2.
    pub bumpless_time_constant: f64,
}

impl Default for IntelligentParams {
    fn default() -> Self {
        Self {
            kind: ControllerKind::P,
            order: Order::One,
            alpha: 1.0,
            kp: 1.0,
            ki: 0.0,
            kd: 0.0,
            derivative_filter: 0.02,
            bumpless_time_constant: 0.2,
        }
    }
}

impl IntelligentParams {
    /// Check the parameters (and that the kind suits the order).
    pub fn validate(&self) -> Result<()> {
        nonzero("alpha", self.alpha)?;
        non_negative("kp", self.kp)?;
        non_negative("ki", self.ki)?;
        non_negative("kd", self.kd)?;
        non_negative("derivative_filter", self.derivative_filter)?;
        non_negative("bumpless_time_constant", self.bumpless_time_constant)?;
        if !self.kind.supports(self.order) {
            return Err(MfcError::IncompatibleOrder {
                kind: self.kind,
                order: self.order,
            });
        }
        Ok(())
    }

    /// The control law for an estimate `f`, error `e`, error derivative `de` and integral `i`.
    fn law(&self, f: f64, r: &Reference, e: f64, de: f64, i: f64) -> f64 {
        let feedforward = match self.order {
            Order::One => r.dy,
            Order::Two => r.ddy,
        };
        let mut acc = f - feedforward + self.kp * e;
        if self.kind.has_integral() {
            acc += self.ki * i;
        }
        if self.kind.has_derivative() {
            acc += self.kd * de;
        }
        -acc / self.alpha
    }
}

/// What one step of an intelligent controller produced.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IntelligentOutput {
    /// The control `u` (before the output map).
    pub u: f64,
    /// `F_est`, or `None` while the window fills (the output is then the hold value).
    pub f_est: Option<f64>,
    /// Tracking error `e = y - y*`.
    pub error: f64,
}

/// One intelligent controller (one output of the plant).
///
/// In declaration order, the estimator (and its ring) last: the fields a step reads sit
/// together, before the ring (see [`Estimator`]).
#[derive(Debug, Clone)]
#[repr(C)]
pub struct IntelligentController<const CAP: usize = DEFAULT_CAPACITY> {
    pub(crate) params: IntelligentParams,
    pub(crate) pending: Option<IntelligentParams>,
    pub(crate) integral: f64,
    pub(crate) derivative: DerivativeFilter,
    pub(crate) last_t: Option<f64>,
    /// Input applied over the interval that started at `last_t`.
    pub(crate) applied: f64,
    /// Last computed output.
    pub(crate) last_u: f64,
    /// Output while the window fills.
    pub(crate) hold: f64,
    /// Fade-out offset left by a change (or a bumpless start).
    pub(crate) bump: f64,
    pub(crate) bumpless_start: bool,
    pub(crate) estimator: Estimator<CAP>,
}

impl<const CAP: usize> IntelligentController<CAP> {
    /// A controller with checked parameters and estimator configuration.
    pub fn new(params: IntelligentParams, estimator: EstimatorConfig) -> Result<Self> {
        params.validate()?;
        let estimator = Estimator::new(estimator, params.order)?;
        Ok(Self {
            params,
            pending: None,
            estimator,
            integral: 0.0,
            derivative: DerivativeFilter::default(),
            last_t: None,
            applied: 0.0,
            last_u: 0.0,
            hold: 0.0,
            bump: 0.0,
            bumpless_start: false,
        })
    }

    /// Parameters in force (a pending change shows from the next step).
    pub fn params(&self) -> &IntelligentParams {
        self.pending.as_ref().unwrap_or(&self.params)
    }

    /// The estimator (window state, configuration).
    pub fn estimator(&self) -> &Estimator<CAP> {
        &self.estimator
    }

    /// Current value of `∫e`.
    pub fn integral(&self) -> f64 {
        self.integral
    }

    /// Change gains, `α`, kind or order while running; bumpless (see the module docs).
    /// Refused with the state untouched if the parameters are invalid.
    pub fn set_params(&mut self, params: IntelligentParams) -> Result<()> {
        params.validate()?;
        self.estimator.config().validate(params.order, CAP)?;
        if self.last_t.is_none() {
            self.params = params;
        } else {
            self.pending = Some(params);
        }
        Ok(())
    }

    /// Start from an actuator already at `u0` (taking over from another controller): the
    /// output holds `u0` while the window fills, then the difference fades out.
    pub fn bumpless_start(&mut self, u0: f64) -> Result<()> {
        finite("control", u0)?;
        self.hold = u0;
        self.last_u = u0;
        self.applied = u0;
        self.bumpless_start = true;
        Ok(())
    }

    /// Tell the controller the input the plant actually received since the last step (after
    /// saturation, dead-zone mapping, or a held command). Defaults to the computed output.
    pub fn set_applied(&mut self, u: f64) -> Result<()> {
        self.applied = finite("applied input", u)?;
        Ok(())
    }

    /// Forget the past (window, integral, derivative), for example after a long outage; the
    /// parameters stay.
    pub fn reset(&mut self) {
        self.estimator.reset();
        self.integral = 0.0;
        self.derivative = DerivativeFilter::default();
        self.last_t = None;
        self.bump = 0.0;
    }

    /// Forget the estimation window and the derivative (after a gap in the data, such as a
    /// controller restart), keeping the parameters and the integral: the output holds the
    /// input being applied until the window has refilled, then the difference fades.
    pub fn forget_window(&mut self) {
        self.estimator.reset();
        self.derivative = DerivativeFilter::default();
        self.last_t = None;
        self.hold = self.applied;
        self.last_u = self.applied;
        self.bump = 0.0;
        self.bumpless_start = true;
    }

    /// Check a step's inputs without changing anything.
    pub fn check(&self, t: f64, y: f64, r: &Reference) -> Result<()> {
        self.estimator.check(t, y, self.applied)?;
        r.check()
    }

    /// One control step at time `t` with measurement `y` and reference `r`.
    pub fn step(&mut self, t: f64, y: f64, r: &Reference) -> Result<IntelligentOutput> {
        self.check(t, y, r)?;
        let dt = self.last_t.map(|t0| t - t0);
        self.estimator.push(t, y, self.applied)?;
        self.last_t = Some(t);
        let p = self.params;
        let dy = self.derivative.update(t, y, p.derivative_filter);
        let e = y - r.y;
        let de = dy - r.dy;
        if let Some(dt) = dt {
            self.bump *= decay(dt, p.bumpless_time_constant);
            self.integrate(e, dt);
        }
        let (u, f_est) = match self.estimator.estimate(p.order) {
            Err(_) => {
                // Window still filling: hold, and switch parameters directly.
                if let Some(new) = self.pending.take() {
                    self.params = new;
                }
                (self.hold, None)
            }
            Ok(lin) => {
                let old = p.law(lin.at(p.alpha), r, e, de, self.integral) + self.bump;
                let old = if self.bumpless_start {
                    // Start from what the plant is applying now: after a long warm-up (a
                    // restart), the plant may have moved on from the value held at first.
                    self.hold = self.applied;
                    self.bumpless_start = false;
                    self.bump = self.hold - (old - self.bump);
                    self.hold
                } else {
                    old
                };
                if let Some(new) = self.pending.take() {
                    self.switch(new, lin, old, r, e, de);
                }
                let p = self.params;
                let f = lin.at(p.alpha);
                (p.law(f, r, e, de, self.integral) + self.bump, Some(f))
            }
        };
        self.last_u = u;
        self.applied = u;
        Ok(IntelligentOutput { u, f_est, error: e })
    }

    /// Rectangle-rule integral of `e`, frozen while the actuator is saturated in the
    /// direction integrating would push it (conditional integration anti-windup).
    fn integrate(&mut self, e: f64, dt: f64) {
        let p = &self.params;
        if !p.kind.has_integral() {
            return;
        }
        let push = -p.ki * e * dt / p.alpha;
        let tol = 1e-9 * (1.0 + self.last_u.abs());
        let high = self.last_u > self.applied + tol;
        let low = self.last_u < self.applied - tol;
        if (high && push > 0.0) || (low && push < 0.0) {
            return;
        }
        self.integral += e * dt;
    }

    fn switch(
        &mut self,
        new: IntelligentParams,
        lin: LinearEstimate,
        u_old: f64,
        r: &Reference,
        e: f64,
        de: f64,
    ) {
        if !self.params.kind.has_integral() {
            self.integral = 0.0;
        }
        self.params = new;
        let f = lin.at(new.alpha);
        if new.kind.has_integral() && new.ki > 0.0 {
            // Choose ∫e so that the new law alone gives the old output.
            let feedforward = match new.order {
                Order::One => r.dy,
                Order::Two => r.ddy,
            };
            let d = if new.kind.has_derivative() {
                new.kd * de
            } else {
                0.0
            };
            self.integral = (-new.alpha * u_old - f + feedforward - new.kp * e - d) / new.ki;
            self.bump = 0.0;
        } else {
            self.bump = u_old - new.law(f, r, e, de, self.integral);
        }
    }
}

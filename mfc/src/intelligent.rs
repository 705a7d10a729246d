//! Intelligent controllers: iP, iPI, iPD and iPID.
//!
//! With `e = y - y*` and `F_est` from the [`Estimator`]:
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
//! fades with `bumpless_time_constant`. The applied input therefore never jumps on a change,
//! but where `feedforward_within_range` cuts the feedforward (below): a start from another
//! law on such a step matches the law with all of the feedforward, and may jump by what
//! was cut; a change of `α` there, by the difference of the two cuts.
//!
//! # Quantised measurements
//! An encoder's output is a staircase. Differentiating it (even filtered) turns every count
//! into a spike of `e'`, and the estimate of `F` jumps at every count too; through `1/α`
//! both reach the actuator as chatter, and while holding an angle between two counts the
//! loop hunts from one to the other (`docs/results-aero.md`). Two options, off by default:
//!
//! * `derivative_observer = ω` (n = 2): `e'` comes from an observer of `y` and `y'` driven by
//!   the ultra-local model itself (`y'' = F_est + α u_applied`), corrected by the
//!   measurement with both poles at `-ω`. Between counts the model carries the derivative,
//!   so it needs far less smoothing, and far less lag, than a filter on the staircase.
//! * `estimate_filter = τ`: a first-order low-pass of time constant `τ` on `F_est` (on both
//!   parts of its linear form, so that a change of `α` stays exact and bumpless).
//! * `hold_estimate_filter = τ_h`: the low-pass's time constant once the plant holds, that
//!   is once every reference of the plant has rested (`y*` unchanged, `y*'` and `y*''`
//!   zero) for `hold_after` seconds; `estimate_filter` again as soon as any moves. Holding
//!   is where the count-to-count hunting is worst (the plant sits between two counts, and
//!   near the voltage a hold needs the output map's gain is highest); a slower `F` there
//!   stops most of it. The price is a slower answer to a disturbance while holding, which
//!   is why the rule waits for *every* reference: another channel's motion is the
//!   disturbance a coupled plant's `F` most needs to follow. [`crate::MimoController`]
//!   applies that rule; a channel stepped on its own sees only its own reference.
//!
//! * `hold_band = b` (in units of `u`): once the plant holds (the rule above), the command
//!   may change sign only beyond `±b`; a reversal inside the band gives 0 instead. Where a
//!   hold needs about 0 V the law's output dithers around zero at every encoder count, and
//!   through the dead-zone compensation each sign change is a swing of several volts and a
//!   motor reversing; inside the band the actuator rests instead. The price is a
//!   tolerance: an error whose correction needs less than `b` in the reversing direction
//!   waits until it needs more (`docs/results-aero.md`, "A hold band").
//!
//! # A reference the actuator cannot follow
//! The law feeds the reference's own derivative forward (`y*'` for n = 1, `y*''` for
//! n = 2): exact while the plant follows, since the error dynamics then need nothing else.
//! A reference faster than the actuator can make the plant go (a step shaped over 0.3 s on
//! the AERO's pitch) asks for an acceleration, then a braking, that the plant cannot
//! deliver: the command saturates on the feedforward, and in the braking half it
//! saturates *against* the error, braking a plant that is still far behind, which then
//! arrives late and overshoots. With `feedforward_within_range`, a step whose feedforward
//! opposes the rest of the law (the estimate of `F` and the error terms) and would take
//! the command past the actuator's range (the output map's `min` or `max`, through its
//! dead-zone compensation) keeps the feedforward only in the proportion of the range the
//! rest leaves unused on its own side: all of it while the rest asks for nothing (the
//! plant on the reference, where braking with the reference is right), none once the rest
//! alone asks for the whole side (the plant far behind, where it must push on). Where the
//! two push the same way (the reference accelerating away from the plant) the command
//! keeps both and saturates, which is the most the actuator can do to follow (dropping it
//! there too, tried, left the AERO's pitch further behind on slower steps than keeping it
//! always; dropping all of an opposing feedforward, the rule's first form, left the pitch
//! further behind than this cut on every step sequence where either acts). The proportion
//! is measured in the actuator's units, after the map: through the paper's step map
//! (`smoothing = 0`) any rest commands at least the dead zone, so at most `1 - dead_zone /
//! max` of the feedforward is kept there (58 % on the AERO). A reference the plant can follow
//! never saturates the command, so nothing changes there; nor with a map without limits
//! (the default). The cut is not continuous at the limit: the command goes from the limit
//! to the rest plus what is kept of the feedforward, a jump a nearly feasible reference
//! may make it take more than once. Only a [`crate::Channel`] knows the range: a
//! controller stepped on its own keeps the feedforward (`docs/results-aero.md`, "Fast
//! steps").
//!
//! # Predictions (packetized horizons, delay compensation)
//! [`crate::Channel::plan`] runs the ultra-local model forward from the controller's state.
//! With `trend = 0`, `F` is held at the filtered `F_est`: an estimate that already lags
//! the plant by the filter's `τ` (and the window), held for the whole round trip. That
//! staleness is most of what a delay costs (`docs/results-faults.md`). With `trend = g > 0`, the
//! prediction uses the estimate's trend `Ḟ`, the low-passed (time constant
//! [`TREND_FILTER`]` × τ`) difference between the raw and the filtered estimate divided by
//! `τ` (exact for an `F` that ramps): `F(s) = F_est + Ḟ (τ + g s)` at `s` after the sample,
//! that is the filter's lag taken back, then `F` extrapolated at the fraction `g` of its
//! trend. Without `estimate_filter` there is no trend to read, and `F` is held.
//!
//! [`Trend`] gives `g` twice: while any reference of the plant moves, and once every one
//! has rested for `hold_after` (the rule of `hold_estimate_filter`). At rest most of what
//! the trend reads is the encoder: the plant sits between two counts, every count jumps the
//! raw estimate, and extrapolating those jumps over a round trip turns them into the
//! command. So the shipped default is to hold `F` at rest (`at_rest = 0`); a plant whose
//! load drifts while it holds (a ramping disturbance) wants `at_rest = moving`.

use crate::error::{finite, non_negative, nonzero, MfcError, Result};
use crate::estimator::{Estimator, EstimatorConfig, LinearEstimate, DEFAULT_CAPACITY};
use crate::filter::{decay, DerivativeFilter};
use crate::output_map::OutputMapConfig;
use crate::{ControllerKind, Order, Reference};

/// Time constant of the low-pass that gives the estimate's trend for predictions, in units
/// of `estimate_filter` (module documentation): 1.5 keeps the estimate's jumps at encoder
/// counts out of the trend without letting it lag much more than the estimate itself.
pub const TREND_FILTER: f64 = 1.5;

/// How a prediction follows `F` (module documentation): the fraction `g` of the estimate's
/// trend it extrapolates while any reference of the plant moves, and once every reference
/// has rested for `hold_after`. 0 holds `F`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Trend {
    /// While any reference moves, or has rested for less than `hold_after`.
    pub moving: f64,
    /// Once every reference has rested for `hold_after`.
    pub at_rest: f64,
}

impl Trend {
    /// The same fraction whether the references move or rest.
    pub const fn always(g: f64) -> Self {
        Self {
            moving: g,
            at_rest: g,
        }
    }
}

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
    /// Bandwidth (rad/s) of the model-based observer that gives `y'` instead of the
    /// derivative filter (n = 2 only; module documentation). Default 0: off.
    pub derivative_observer: f64,
    /// Time constant (s) of a low-pass on `F_est` (module documentation). Default 0: off.
    pub estimate_filter: f64,
    /// Time constant (s) of the low-pass on `F_est` while holding: once the reference has
    /// been at rest for `hold_after` (module documentation). Default 0: off.
    pub hold_estimate_filter: f64,
    /// How long (s) the reference must have been at rest before `hold_estimate_filter`
    /// takes over from `estimate_filter`. Default: 1.
    pub hold_after: f64,
    /// While holding (as for `hold_estimate_filter`), the command may change sign only
    /// beyond this magnitude, in units of `u` (module documentation). Default 0: off.
    pub hold_band: f64,
    /// Time constant (s) with which the offset left by a parameter change fades.
    /// Default: 0.2.
    pub bumpless_time_constant: f64,
    /// Cut the reference's feedforward on a step where it opposes the rest of the law and
    /// would take the command past the actuator's range, keeping it in the proportion of
    /// the range the rest leaves unused (module documentation, "A reference the actuator
    /// cannot follow"). Default: false.
    pub feedforward_within_range: bool,
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
            derivative_observer: 0.0,
            estimate_filter: 0.0,
            hold_estimate_filter: 0.0,
            hold_after: 1.0,
            hold_band: 0.0,
            bumpless_time_constant: 0.2,
            feedforward_within_range: false,
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
        non_negative("derivative_observer", self.derivative_observer)?;
        non_negative("estimate_filter", self.estimate_filter)?;
        non_negative("hold_estimate_filter", self.hold_estimate_filter)?;
        non_negative("hold_after", self.hold_after)?;
        non_negative("hold_band", self.hold_band)?;
        if self.derivative_observer > 0.0 && self.order == Order::One {
            return Err(MfcError::InvalidParameter {
                name: "derivative_observer",
                value: self.derivative_observer,
                reason: "needs an ultra-local model of order 2 (order one gives y' itself)",
            });
        }
        non_negative("bumpless_time_constant", self.bumpless_time_constant)?;
        if !self.kind.supports(self.order) {
            return Err(MfcError::IncompatibleOrder {
                kind: self.kind,
                order: self.order,
            });
        }
        Ok(())
    }

    /// The reference's derivative of the model's order, which the law feeds forward.
    #[inline(always)]
    fn feedforward(&self, r: &Reference) -> f64 {
        match self.order {
            Order::One => r.dy,
            Order::Two => r.ddy,
        }
    }

    /// The law's output `u` with the reference's feedforward cut where the rule is on, the
    /// feedforward opposes the rest of the law, and with it `u` lies beyond the range of
    /// `map` in the feedforward's direction (module documentation, "A reference the
    /// actuator cannot follow"); else `u`.
    #[inline]
    fn within_range(&self, u: f64, r: &Reference, map: Option<&OutputMapConfig>) -> f64 {
        let Some(map) = map.filter(|_| self.feedforward_within_range) else {
            return u;
        };
        // The feedforward's share of `u`: the law is `-(f - feedforward + ...) / alpha`.
        let share = self.feedforward(r) / self.alpha;
        if share == 0.0 || !share.is_finite() || !u.is_finite() {
            // Nothing to cut, or nothing finite to judge it by: the law as it is (a
            // non-finite command is never sent, `crate::Channel`).
            return u;
        }
        // The rest of the law: the estimate of `F` and the error terms.
        let rest = u - share;
        if rest * share >= 0.0 {
            // The two push the same way (a reference accelerating away from the plant):
            // all of it, saturated, is what the actuator can do to follow.
            return u;
        }
        let v = map.compensate(u);
        let beyond = (share > 0.0 && v > map.max) || (share < 0.0 && v < map.min);
        if !beyond {
            return u;
        }
        // The feedforward in the proportion of its side of the range the rest leaves
        // unused: all of it while the rest asks for nothing (the plant on the reference),
        // none once the rest alone asks for the whole side (the plant far behind).
        // Measured in the actuator's units (after the map): a side of width 0 (a range
        // such as [0, 100]) is all used by any rest, an unlimited side none (`rest` is not
        // 0 here, so neither ratio is 0 / 0). The magnitude, not `-min`: a `min` of 0
        // would give -0, and a ratio of -infinity.
        let side = (if rest > 0.0 { map.max } else { map.min }).abs();
        let used = (map.compensate(rest).abs() / side).min(1.0);
        rest + share * (1.0 - used)
    }

    /// The control law for an estimate `f`, error `e`, error derivative `de` and integral `i`.
    fn law(&self, f: f64, r: &Reference, e: f64, de: f64, i: f64) -> f64 {
        let feedforward = self.feedforward(r);
        let mut acc = f - feedforward + self.kp * e;
        if self.kind.has_integral() {
            acc += self.ki * i;
        }
        if self.kind.has_derivative() {
            acc += self.kd * de;
        }
        // A product with a reciprocal that depends on the parameters alone: the division
        // starts with the step, instead of waiting for the rest of the law at its end.
        acc * (-1.0 / self.alpha)
    }

    /// The law for the estimate `lin` (`f = lin.at(alpha)`), plus `bump`. Equal to
    /// `law(f) + bump` but for rounding, since `-(f + ...)/alpha = -(base + ...)/alpha -
    /// per_alpha`: of the estimate, only `per_alpha` depends on the input the plant was
    /// given, and that input is the last step's output, so a stream of steps is a chain
    /// through it. Subtracted last, it leaves the division and the rest of the law off
    /// that chain (they wait only for the sample).
    #[inline]
    fn law_linear(
        &self,
        lin: LinearEstimate,
        r: &Reference,
        e: f64,
        de: f64,
        i: f64,
        bump: f64,
    ) -> f64 {
        (self.law(lin.base, r, e, de, i) + bump) - lin.per_alpha
    }
}

/// A change of parameters waiting for the next step. With an allocator it is boxed: a
/// change is rare, and inline it was 96 bytes of every plant a service holds
/// (`docs/scale.md`, "Memory per plant"); without one (a microcontroller) it is inline.
#[derive(Debug, Clone, Default, PartialEq)]
pub(crate) struct Pending(
    #[cfg(feature = "alloc")] Option<alloc::boxed::Box<IntelligentParams>>,
    #[cfg(not(feature = "alloc"))] Option<IntelligentParams>,
);

impl Pending {
    pub(crate) fn get(&self) -> Option<&IntelligentParams> {
        self.0.as_ref().map(core::borrow::Borrow::borrow)
    }

    pub(crate) fn is_some(&self) -> bool {
        self.0.is_some()
    }

    pub(crate) fn take(&mut self) -> Option<IntelligentParams> {
        #[cfg(feature = "alloc")]
        {
            self.0.take().map(|p| *p)
        }
        #[cfg(not(feature = "alloc"))]
        {
            self.0.take()
        }
    }

    pub(crate) fn put(&mut self, p: IntelligentParams) {
        // Boxed with an allocator, as it is without one.
        #[allow(clippy::useless_conversion)]
        let p = p.into();
        self.0 = Some(p);
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
/// In declaration order, the estimator last: the fields a step reads sit together, before
/// the ring when it is inline (see [`Estimator`]).
#[derive(Debug, Clone)]
#[repr(C)]
pub struct IntelligentController<const CAP: usize = DEFAULT_CAPACITY> {
    pub(crate) params: IntelligentParams,
    pub(crate) pending: Pending,
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
    /// The model-based observer's `(y, y')`, while `derivative_observer` is on.
    pub(crate) observer: Option<(f64, f64)>,
    /// The estimate in force (filtered if `estimate_filter` is on), from the last step
    /// that had one: the observer's model runs on it.
    pub(crate) estimate: Option<LinearEstimate>,
    /// While the reference is at rest (`y*` unchanged, its derivatives zero): for how long
    /// (s), and the `y*` it rests at. `hold_estimate_filter` applies from `hold_after` on.
    pub(crate) rest: Option<(f64, f64)>,
    /// While `estimate_filter` is on: the low-passed difference between the raw estimate
    /// and the filtered one (both parts of the linear form), the filter's lag, for
    /// predictions (module documentation).
    pub(crate) trend: Option<LinearEstimate>,
    /// The sign of the last nonzero output, for `hold_band`.
    pub(crate) sign: f64,
    pub(crate) estimator: Estimator<CAP>,
}

impl<const CAP: usize> IntelligentController<CAP> {
    /// A controller with checked parameters and estimator configuration.
    pub fn new(params: IntelligentParams, estimator: EstimatorConfig) -> Result<Self> {
        params.validate()?;
        let estimator = Estimator::new(estimator, params.order)?;
        Ok(Self {
            params,
            pending: Pending::default(),
            estimator,
            integral: 0.0,
            derivative: DerivativeFilter::default(),
            last_t: None,
            applied: 0.0,
            last_u: 0.0,
            hold: 0.0,
            bump: 0.0,
            bumpless_start: false,
            observer: None,
            estimate: None,
            rest: None,
            trend: None,
            sign: 0.0,
        })
    }

    /// Parameters in force (a pending change shows from the next step).
    pub fn params(&self) -> &IntelligentParams {
        self.pending.get().unwrap_or(&self.params)
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
            self.adopt(params);
        } else {
            self.pending.put(params);
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
        self.observer = None;
        self.estimate = None;
        self.trend = None;
        self.last_t = None;
        self.bump = 0.0;
    }

    /// Forget the estimation window and the derivative (after a gap in the data, such as a
    /// controller restart), keeping the parameters and the integral: the output holds the
    /// input being applied until the window has refilled, then the difference fades.
    pub fn forget_window(&mut self) {
        self.estimator.reset();
        self.derivative = DerivativeFilter::default();
        self.observer = None;
        self.estimate = None;
        self.trend = None;
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
        self.step_mapped(t, y, r, None)
    }

    /// [`Self::step`] for a law whose output goes through `map` (the actuator's range,
    /// for `feedforward_within_range`).
    ///
    /// Always inlined (into [`crate::Channel`]'s step): its output then reaches the
    /// output map in registers. Returned through memory, it was stored and loaded again
    /// on the chain that runs from one sample's command to the next step's estimate.
    #[inline(always)]
    pub(crate) fn step_mapped(
        &mut self,
        t: f64,
        y: f64,
        r: &Reference,
        map: Option<&OutputMapConfig>,
    ) -> Result<IntelligentOutput> {
        self.check(t, y, r)?;
        let dt = self.last_t.map(|t0| t - t0);
        self.estimator.record(t, y, self.applied);
        self.last_t = Some(t);
        let p = self.params;
        let filtered = self.derivative.update(t, y, p.derivative_filter);
        let dy = self.observe(dt, y, filtered);
        let e = y - r.y;
        let de = dy - r.dy;
        if let Some(dt) = dt {
            // A bump is rare (a change of gains or a start from another law), and its
            // decay costs an exp: none once it is gone.
            if self.bump != 0.0 {
                self.bump *= decay(dt, p.bumpless_time_constant);
            }
            self.integrate(e, dt);
        }
        self.rest = match (self.rest, dt) {
            _ if r.dy != 0.0 || r.ddy != 0.0 => None,
            (Some((held, y0)), Some(dt)) if r.y == y0 => Some((held + dt, y0)),
            _ => Some((0.0, r.y)),
        };
        let (u, f_est) = match self.estimator.estimate(p.order) {
            Err(_) => {
                // Window still filling: hold, and switch parameters directly.
                if let Some(new) = self.pending.take() {
                    self.adopt(new);
                }
                self.estimate = None;
                (self.hold, None)
            }
            Ok(lin) => {
                let lin = self.smooth(dt, lin);
                if self.bumpless_start || self.pending.is_some() {
                    self.start_or_switch(lin, r, e, de);
                }
                let p = self.params;
                let u = p.law_linear(lin, r, e, de, self.integral, self.bump);
                (p.within_range(u, r, map), Some(lin.at(p.alpha)))
            }
        };
        let u = self.hold_hysteresis(u);
        self.last_u = u;
        self.applied = u;
        Ok(IntelligentOutput { u, f_est, error: e })
    }

    /// The first estimate after a bumpless start, or a pending change of parameters:
    /// the output the law in force gives now is the one the next law starts from (the
    /// difference fades out as `bump`, or goes into the integral, see [`Self::switch`]).
    fn start_or_switch(&mut self, lin: LinearEstimate, r: &Reference, e: f64, de: f64) {
        let p = self.params;
        let old = p.law_linear(lin, r, e, de, self.integral, self.bump);
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
    }

    /// The state a prediction starts from, after a step that estimated `f`: the last
    /// measurement, its filtered derivative, the integral and the fading bump; with a
    /// `trend` above 0 (`at_rest` once the references have rested for `hold_after`) and the
    /// estimate filter on, `F` follows the estimate's trend (module documentation). `None`
    /// before the first step.
    pub(crate) fn predictor(&self, f: f64, trend: Trend) -> Option<IntelligentPredictor> {
        let (y, dy) = match self.observer {
            Some(o) => o,
            None => (self.derivative.last()?, self.derivative.value()),
        };
        let tau = self.params.estimate_filter;
        let trend = if self.resting() {
            trend.at_rest
        } else {
            trend.moving
        };
        let (f, rate) = match self.trend {
            Some(lag) if trend > 0.0 && tau > 0.0 => {
                let lag = lag.at(self.params.alpha);
                let (g, r) = (f + lag, trend * lag / tau);
                if g.is_finite() && r.is_finite() {
                    (g, r)
                } else {
                    (f, 0.0)
                }
            }
            _ => (f, 0.0),
        };
        Some(IntelligentPredictor {
            params: self.params,
            rate,
            f,
            y,
            dy,
            integral: self.integral,
            bump: self.bump,
        })
    }

    /// `y'` for the law: the model-based observer's when it is on and an estimate of `F`
    /// exists to drive it, else `filtered` (the derivative filter's), from which the
    /// observer also starts.
    #[inline(always)]
    fn observe(&mut self, dt: Option<f64>, y: f64, filtered: f64) -> f64 {
        let p = &self.params;
        if !(p.derivative_observer > 0.0 && p.order == Order::Two) {
            self.observer = None;
            return filtered;
        }
        self.observe_model(dt, y, filtered)
    }

    /// [`Self::observe`] with the observer on (out of line: most laws have it off).
    #[inline(never)]
    fn observe_model(&mut self, dt: Option<f64>, y: f64, filtered: f64) -> f64 {
        let p = &self.params;
        let next = match (self.observer, dt, self.estimate) {
            (Some((oy, ody)), Some(h), Some(lin)) if h > 0.0 => {
                // Predict over h with the ultra-local model and the input really applied,
                // then correct with the measurement: both poles at exp(-ω h).
                let acc = lin.at(p.alpha) + p.alpha * self.applied;
                let py = oy + h * ody + 0.5 * h * h * acc;
                let pdy = ody + h * acc;
                let beta = libm::exp(-p.derivative_observer * h);
                let e = y - py;
                let l1 = 1.0 - beta * beta;
                let l2 = (1.0 - beta) * (1.0 - beta) / h;
                (py + l1 * e, pdy + l2 * e)
            }
            _ => (y, filtered),
        };
        // Non-finite only from absurd (finite) data: start again from the measurement.
        let next = if next.0.is_finite() && next.1.is_finite() {
            next
        } else {
            (y, filtered)
        };
        self.observer = Some(next);
        next.1
    }

    /// The estimate through `estimate_filter`, remembered as the one in force.
    #[inline(always)]
    fn smooth(&mut self, dt: Option<f64>, lin: LinearEstimate) -> LinearEstimate {
        let p = &self.params;
        if p.estimate_filter <= 0.0 && p.hold_estimate_filter <= 0.0 {
            // No filter (the default): what the general case gives for a `tau` of 0.
            self.estimate = Some(lin);
            self.trend = None;
            return lin;
        }
        self.smooth_filtered(dt, lin)
    }

    /// [`Self::smooth`] with a filter on (out of line: the default has none).
    #[inline(never)]
    fn smooth_filtered(&mut self, dt: Option<f64>, lin: LinearEstimate) -> LinearEstimate {
        let p = &self.params;
        let tau = if p.hold_estimate_filter > 0.0 && self.resting() {
            p.hold_estimate_filter
        } else {
            p.estimate_filter
        };
        let out = match (self.estimate, dt) {
            (Some(old), Some(h)) if tau > 0.0 && h > 0.0 => {
                old.toward(lin, 1.0 - libm::exp(-h / tau))
            }
            _ => lin,
        };
        let out = if out.is_finite() { out } else { lin };
        self.estimate = Some(out);
        // The filter's lag, low-passed: what a prediction adds back (module documentation).
        let lag = lin.minus(out);
        self.trend = match (self.trend, dt) {
            _ if tau <= 0.0 => None,
            (Some(old), Some(h)) if h > 0.0 => {
                Some(old.toward(lag, 1.0 - libm::exp(-h / (TREND_FILTER * tau))))
            }
            (Some(old), _) => Some(old),
            (None, _) => Some(lag),
        }
        .filter(LinearEstimate::is_finite);
        out
    }

    /// Every reference of the plant has rested for `hold_after` (the rule of
    /// `hold_estimate_filter` and of [`Trend::at_rest`]).
    /// `hold_band`: at rest, a reversal of the command's sign inside the band gives 0.
    fn hold_hysteresis(&mut self, u: f64) -> f64 {
        let band = self.params.hold_band;
        if band > 0.0 && u.abs() < band && self.sign != 0.0 && u != 0.0 {
            let reversal = u.signum() != self.sign;
            if reversal && self.resting() {
                return 0.0;
            }
        }
        if u != 0.0 {
            self.sign = u.signum();
        }
        u
    }

    fn resting(&self) -> bool {
        matches!(self.rest, Some((held, _)) if held >= self.params.hold_after)
    }

    /// Rectangle-rule integral of `e`, frozen while the actuator is saturated in the
    /// direction integrating would push it (conditional integration anti-windup).
    fn integrate(&mut self, e: f64, dt: f64) {
        let p = &self.params;
        if !p.kind.has_integral() {
            return;
        }
        // Only its sign counts: that of `-ki e dt / alpha`, without the division.
        let push = -(p.ki * e * dt) * p.alpha;
        let tol = 1e-9 * (1.0 + self.last_u.abs());
        let high = self.last_u > self.applied + tol;
        let low = self.last_u < self.applied - tol;
        if (high && push > 0.0) || (low && push < 0.0) {
            return;
        }
        self.integral += e * dt;
    }

    /// `new` in force from now on, the estimator's running sums serving its order.
    fn adopt(&mut self, new: IntelligentParams) {
        self.estimator.serve(new.order);
        self.params = new;
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
        self.adopt(new);
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
            self.bump = u_old - new.law_linear(lin, r, e, de, self.integral, 0.0);
        }
    }
}

/// The ultra-local model run forward from an intelligent controller's state, for a
/// packetized horizon ([`crate::Channel::plan`]): `F` is held at its last estimate, or
/// follows its trend (module documentation), and the law is evaluated on the predicted
/// output exactly as the controller would on a measured one.
#[derive(Debug, Clone, Copy)]
pub(crate) struct IntelligentPredictor {
    params: IntelligentParams,
    /// `F` at the start of the next period to predict.
    f: f64,
    /// `F'` over the prediction (0: held).
    rate: f64,
    y: f64,
    dy: f64,
    integral: f64,
    bump: f64,
}

impl IntelligentPredictor {
    /// Let `h` pass with `u` applied: `y' = F + alpha u` (n = 1) or `y'' = F + alpha u`
    /// (n = 2), exact for a constant `u` over the period and `F` held or ramping at `rate`.
    pub(crate) fn advance(&mut self, h: f64, u: f64) {
        let p = &self.params;
        let acc = self.f + p.alpha * u;
        let r = self.rate;
        match p.order {
            Order::One => {
                self.y += h * acc + 0.5 * h * h * r;
                self.dy = acc + h * r;
            }
            Order::Two => {
                self.y += h * self.dy + 0.5 * h * h * acc + h * h * h * r / 6.0;
                self.dy += h * acc + 0.5 * h * h * r;
            }
        }
        self.f += h * r;
        self.bump *= decay(h, p.bumpless_time_constant);
    }

    /// The law at the predicted state for reference `r`, its output going through `map`;
    /// the integral then takes this period's error, as [`IntelligentController::step`]
    /// does on the next sample.
    pub(crate) fn law(&mut self, h: f64, r: &Reference, map: &OutputMapConfig) -> f64 {
        let e = self.y - r.y;
        let de = self.dy - r.dy;
        if self.params.kind.has_integral() {
            self.integral += e * h;
        }
        let u = self.params.law(self.f, r, e, de, self.integral) + self.bump;
        self.params.within_range(u, r, Some(map))
    }
}

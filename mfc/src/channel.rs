//! One control channel: a control law (intelligent, PID or ADRC) and its output map.
//!
//! The channel closes the "what did the plant really get" loop: after mapping `u` to the
//! output `v` it tells the law the *applied* `u` (the inverse map of `v`), and
//! [`Channel::report_applied`] corrects it when the plant reports something else (a lost
//! command, a held value, a safety stop).

use crate::adrc::{Adrc, AdrcParams};
use crate::error::{finite, Result};
use crate::estimator::{EstimatorConfig, DEFAULT_CAPACITY};
use crate::intelligent::{IntelligentController, IntelligentParams};
use crate::output_map::{OutputMap, OutputMapConfig};
use crate::pid::{Pid, PidParams};
use crate::{ControllerKind, Order, Reference};

/// Which control law a channel runs, with its parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(
    feature = "serde",
    serde(tag = "law", rename_all = "snake_case", deny_unknown_fields)
)]
#[cfg_attr(feature = "snapshot", derive(bincode::Encode, bincode::Decode))]
pub enum LawConfig {
    /// iP, iPI, iPD or iPID on an ultra-local model.
    Intelligent {
        /// Gains, `α`, kind, order.
        #[cfg_attr(feature = "serde", serde(default))]
        params: IntelligentParams,
        /// Estimator of `F`.
        #[cfg_attr(feature = "serde", serde(default))]
        estimator: EstimatorConfig,
    },
    /// PID baseline.
    Pid {
        /// Gains and limits.
        #[cfg_attr(feature = "serde", serde(default))]
        params: PidParams,
    },
    /// Linear ADRC baseline.
    Adrc {
        /// Bandwidths and `b0`.
        #[cfg_attr(feature = "serde", serde(default))]
        params: AdrcParams,
    },
}

impl LawConfig {
    /// An intelligent controller of `kind` on a model of `order`, with `α` and the gains
    /// `[kp, ki, kd]`, the other parameters at their defaults, over an algebraic window of
    /// `window` samples: the usual way to write one down in code.
    pub fn intelligent(
        kind: ControllerKind,
        order: Order,
        alpha: f64,
        [kp, ki, kd]: [f64; 3],
        window: usize,
    ) -> Self {
        LawConfig::Intelligent {
            params: IntelligentParams {
                kind,
                order,
                alpha,
                kp,
                ki,
                kd,
                ..IntelligentParams::default()
            },
            estimator: EstimatorConfig {
                window,
                ..EstimatorConfig::default()
            },
        }
    }
}

impl Default for LawConfig {
    fn default() -> Self {
        LawConfig::Intelligent {
            params: IntelligentParams::default(),
            estimator: EstimatorConfig::default(),
        }
    }
}

/// Configuration of a [`Channel`].
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "serde", serde(default, deny_unknown_fields))]
#[cfg_attr(feature = "snapshot", derive(bincode::Encode, bincode::Decode))]
pub struct ChannelConfig {
    /// The control law. Default: iP with `α = 1`, `Kp = 1`, a 10-interval algebraic window.
    pub law: LawConfig,
    /// The output map. Default: identity (no dead zone, no limits).
    pub output: OutputMapConfig,
}

/// The control law of a channel.
///
/// The intelligent variant is much larger (its window lives inline so that the core needs
/// no allocator); boxing it would cost an allocation and `alloc` for the common case.
#[derive(Debug, Clone)]
#[allow(clippy::large_enum_variant)]
pub(crate) enum Law<const CAP: usize> {
    Intelligent(IntelligentController<CAP>),
    Pid(Pid),
    Adrc(Adrc),
}

impl<const CAP: usize> Law<CAP> {
    fn new(config: &LawConfig) -> Result<Self> {
        Ok(match *config {
            LawConfig::Intelligent { params, estimator } => {
                Law::Intelligent(IntelligentController::new(params, estimator)?)
            }
            LawConfig::Pid { params } => Law::Pid(Pid::new(params)?),
            LawConfig::Adrc { params } => Law::Adrc(Adrc::new(params)?),
        })
    }

    /// The configuration this law runs: the inverse of [`Law::new`] (a pending change of
    /// parameters included).
    fn config(&self) -> LawConfig {
        match self {
            Law::Intelligent(c) => LawConfig::Intelligent {
                params: *c.params(),
                estimator: *c.estimator().config(),
            },
            Law::Pid(c) => LawConfig::Pid {
                params: *c.params(),
            },
            Law::Adrc(c) => LawConfig::Adrc {
                params: *c.params(),
            },
        }
    }

    fn check(&self, t: f64, y: f64, r: &Reference) -> Result<()> {
        match self {
            Law::Intelligent(c) => c.check(t, y, r),
            Law::Pid(c) => c.check(t, y, r),
            Law::Adrc(c) => c.check(t, y, r),
        }
    }

    fn set_applied(&mut self, u: f64) -> Result<()> {
        match self {
            Law::Intelligent(c) => c.set_applied(u),
            Law::Pid(c) => c.set_applied(u),
            Law::Adrc(c) => c.set_applied(u),
        }
    }

    fn bumpless_start(&mut self, u: f64) -> Result<()> {
        match self {
            Law::Intelligent(c) => c.bumpless_start(u),
            Law::Pid(c) => c.bumpless_start(u),
            Law::Adrc(c) => c.bumpless_start(u),
        }
    }
}

/// What one step of a channel produced.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ChannelOutput {
    /// The law's control `u`.
    pub u: f64,
    /// The output sent to the plant, `v = map(u)`.
    pub v: f64,
    /// The law's estimate of the lumped term (`F_est` for MFC, the ESO's `f` for ADRC).
    pub f_est: Option<f64>,
    /// Tracking error `y - y*`.
    pub error: f64,
    /// The law is still filling its estimation window (its output is a hold value).
    pub warming_up: bool,
}

/// A control law and its output map: one output of the plant.
///
/// In declaration order, the law (with its estimator, whose ring is last without an
/// allocator) last, so that what a step reads sits together (see [`crate::Estimator`]).
///
/// The configuration in force is not kept beside the state: the law holds its parameters
/// and the map its own, and [`Channel::config`] reads them (a copy would be 184 bytes of
/// each plant a service holds, and a second place for the truth).
#[derive(Debug, Clone)]
#[repr(C)]
pub struct Channel<const CAP: usize = DEFAULT_CAPACITY> {
    pub(crate) map: OutputMap,
    pub(crate) last_t: Option<f64>,
    pub(crate) last_v: f64,
    pub(crate) law: Law<CAP>,
}

impl<const CAP: usize> Channel<CAP> {
    /// [`crate::MimoController::prefetch`] for one channel.
    #[cfg(feature = "alloc")]
    #[inline]
    pub(crate) fn prefetch(&self) {
        if let Law::Intelligent(c) = &self.law {
            c.estimator.prefetch();
        }
    }

    /// A channel with a checked configuration.
    pub fn new(config: &ChannelConfig) -> Result<Self> {
        let map = OutputMap::new(config.output)?;
        let law = Law::new(&config.law)?;
        Ok(Self {
            law,
            map,
            last_t: None,
            last_v: 0.0,
        })
    }

    /// The configuration in force: the law's parameters (a change not yet applied
    /// included, as the law's own `params` shows it) and the output map's.
    pub fn config(&self) -> ChannelConfig {
        ChannelConfig {
            law: self.law.config(),
            output: *self.map.config(),
        }
    }

    /// The output map.
    pub fn output_map(&self) -> &OutputMap {
        &self.map
    }

    /// The intelligent controller, if that is the law.
    pub fn intelligent(&self) -> Option<&IntelligentController<CAP>> {
        match &self.law {
            Law::Intelligent(c) => Some(c),
            _ => None,
        }
    }

    /// Check a step's inputs without changing anything.
    pub fn check(&self, t: f64, y: f64, r: &Reference) -> Result<()> {
        self.law.check(t, y, r)
    }

    /// One step: compute `u`, map it to `v`, and remember that `v` is being applied.
    pub fn step(&mut self, t: f64, y: f64, r: &Reference) -> Result<ChannelOutput> {
        self.step_with(t, y, r, None)
    }

    /// One step whose input is `u` instead of the law's (commissioning's excitation):
    /// the law still steps on the sample, so that its estimator and its memory follow
    /// the plant, then `u` goes through the output map (compensation, range, rate limit)
    /// in place of the law's value and is remembered as what is applied. A law stepped
    /// this way and then left to itself starts from what the plant got, with a warm
    /// window: the return is bumpless. A non-finite `u` is refused before anything moves.
    pub fn step_input(&mut self, t: f64, y: f64, r: &Reference, u: f64) -> Result<ChannelOutput> {
        finite("input", u)?;
        self.step_with(t, y, r, Some(u))
    }

    fn step_with(
        &mut self,
        t: f64,
        y: f64,
        r: &Reference,
        input: Option<f64>,
    ) -> Result<ChannelOutput> {
        // Each law checks its inputs before it changes anything.
        let (u, f_est, error, warming_up) = match &mut self.law {
            Law::Intelligent(c) => {
                let o = c.step_mapped(t, y, r, Some(self.map.config()))?;
                (o.u, o.f_est, o.error, o.f_est.is_none())
            }
            Law::Pid(c) => (c.step(t, y, r)?, None, y - r.y, false),
            Law::Adrc(c) => {
                let u = c.step(t, y, r)?;
                (u, Some(c.disturbance()), y - r.y, false)
            }
        };
        // A non-finite u can only come from extreme (finite) data; never send it.
        let u = input.unwrap_or(if u.is_nan() { 0.0 } else { u });
        let v = self.map.apply(t, u.clamp(-f64::MAX, f64::MAX))?;
        self.law.set_applied(self.map.inverse(v))?;
        self.last_t = Some(t);
        self.last_v = v;
        Ok(ChannelOutput {
            u,
            v,
            f_est,
            error,
            warming_up,
        })
    }

    /// A packetized horizon: the outputs this channel would send for the next
    /// `out.len()` periods if no sample came, predicted with the ultra-local model (`F`
    /// from `last.f_est`, the last step's output: held, or following the estimate's trend
    /// as `trend` says, see [`crate::intelligent`]) and the reference known ahead.
    ///
    /// Period 0 is the one the last step's sample opened; `out[j]` is for period `j + 1`,
    /// `refs[j]` is the reference at its start, and `h` the period. `applied[j]`, if
    /// given, is what the plant will apply over period `j` whatever this channel says
    /// (the outputs of commands already on their way, for delay compensation): the model
    /// is driven by those instead of `last.v` and the plan's own elements, and each
    /// element is the law's value on the state the model predicts from them.
    ///
    /// Each element goes through the output map (compensation, limits, and the rate limit
    /// from the element before), so it is a value this channel could have sent. A law with
    /// no model (PID), a law still filling its window, and a step that produced no
    /// estimate give the last output held: the same as a horizon-less plant's hold.
    pub fn plan(
        &self,
        last: &ChannelOutput,
        h: f64,
        refs: &[Reference],
        applied: &[f64],
        trend: crate::Trend,
        out: &mut [f64],
    ) {
        enum P {
            I(crate::intelligent::IntelligentPredictor),
            A(crate::adrc::AdrcPredictor),
        }
        let n = out.len().min(refs.len());
        let predictor = match (&self.law, last.f_est) {
            _ if last.warming_up || h.is_nan() || h <= 0.0 || !h.is_finite() => None,
            (Law::Intelligent(c), Some(f)) => c.predictor(f, trend).map(P::I),
            (Law::Adrc(c), _) => c.predictor().map(P::A),
            _ => None,
        };
        let Some(mut predictor) = predictor else {
            out.iter_mut().for_each(|o| *o = last.v);
            return;
        };
        let c = self.map.config();
        let given = |j: usize| applied.get(j).copied().filter(|a| a.is_finite());
        // What the plant gets over period j (the one before element j's).
        let mut v_cur = given(0).unwrap_or(last.v);
        let mut v_prev = last.v;
        for j in 0..n {
            let u_cur = self.map.inverse(v_cur);
            match &mut predictor {
                P::I(p) => p.advance(h, u_cur),
                P::A(p) => p.advance(h, u_cur),
            }
            let u = match &mut predictor {
                P::I(p) => p.law(h, &refs[j], c),
                P::A(p) => p.law(&refs[j]),
            };
            let mut v = if u.is_finite() {
                c.compensate(u).clamp(c.min, c.max)
            } else {
                v_prev
            };
            if let Some(rate) = c.rate_limit {
                v = v.clamp(v_prev - rate * h, v_prev + rate * h);
            }
            out[j] = v;
            v_prev = v;
            v_cur = given(j + 1).unwrap_or(v);
        }
        out[n..].iter_mut().for_each(|o| *o = v_prev);
    }

    /// The plant reports that it applied `v` since the last step (not the commanded value):
    /// the estimator and anti-windup will use it.
    pub fn report_applied(&mut self, v: f64) -> Result<()> {
        finite("applied output", v)?;
        self.law.set_applied(self.map.inverse(v))?;
        if let Some(t) = self.last_t {
            self.map.record_applied(t, v);
        }
        self.last_v = v;
        Ok(())
    }

    /// How long (s) this channel's reference has rested, for the laws that keep count
    /// (the intelligent ones; see `hold_estimate_filter`). For [`crate::MimoController`].
    #[cfg(feature = "alloc")]
    pub(crate) fn rested(&self) -> Option<f64> {
        match &self.law {
            Law::Intelligent(c) => Some(c.rest.map_or(0.0, |(held, _)| held)),
            _ => None,
        }
    }

    /// Another channel's reference moves (`None`) or has rested for less (`Some`): this
    /// one's time at rest is no longer than that.
    #[cfg(feature = "alloc")]
    pub(crate) fn cap_rest(&mut self, rested: Option<f64>) {
        if let Law::Intelligent(c) = &mut self.law {
            c.rest = match (c.rest, rested) {
                (Some((held, y)), Some(cap)) => Some((held.min(cap), y)),
                _ => None,
            };
        }
    }

    /// Forget the data history after a gap (see the laws' `forget_window`), keeping
    /// parameters, integrals and the output being applied.
    pub fn forget_window(&mut self) {
        match &mut self.law {
            Law::Intelligent(c) => c.forget_window(),
            Law::Pid(c) => c.forget_window(),
            Law::Adrc(c) => c.forget_window(),
        }
        self.last_t = None;
    }

    /// Change the law while running, bumplessly. Same law with new parameters: the state is
    /// kept (the estimator window too). Another law, or another estimator: the new law starts
    /// from the output being applied now, and any difference fades out.
    ///
    /// Refused with nothing changed if the configuration is invalid.
    pub fn reconfigure(&mut self, config: &ChannelConfig) -> Result<()> {
        let map_changed = config.output != *self.map.config();
        if map_changed {
            config.output.validate()?;
        }
        match (&mut self.law, &config.law) {
            (Law::Intelligent(c), LawConfig::Intelligent { params, estimator })
                if estimator == c.estimator().config() =>
            {
                c.set_params(*params)?
            }
            (Law::Pid(c), LawConfig::Pid { params }) => c.set_params(*params)?,
            (Law::Adrc(c), LawConfig::Adrc { params }) => c.set_params(*params)?,
            (_, new) => {
                let mut law = Law::new(new)?;
                if self.last_t.is_some() {
                    law.bumpless_start(self.map.inverse(self.last_v))?;
                }
                self.law = law;
            }
        }
        if map_changed {
            self.map.set_config(config.output)?;
        }
        Ok(())
    }
}

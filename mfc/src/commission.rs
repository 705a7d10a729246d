//! Commissioning: `α` (and the model's order) found from the plant's own data.
//!
//! The paper's rule for `α` (|α u| about |y^(n)|) needs the plant's magnitudes; on a new
//! plant a user has only trial and error. Commissioning asks the plant instead: hold the
//! input it is getting (`u0`), add a square wave of `±amplitude` for a few periods, and
//! watch the estimate of `F`.
//!
//! # Why the smoothest `F` gives `α`
//! The estimator's answer is linear in `α` ([`LinearEstimate`]): `F_est(α) = base + α
//! per_alpha`, `base` from the outputs, `per_alpha` from the inputs. With the plant's true
//! `α*`, `F_est(α*)` is the plant's `F`, which lumps what changes slowly (structure,
//! load, the other outputs); the square wave's jumps are all in `α* u`. With a wrong `α`,
//! part of each jump stays in `F_est`. So `α` is the value for which `F_est` changes least
//! across the switches: with `Δ` the change of each part over `m` samples (one window and
//! one sample: an estimate wholly before a switch against one wholly after),
//!
//! ```text
//! α = -Σ Δbase Δper_alpha / Σ Δper_alpha²       (least squares on ΔF_est(α) = 0)
//! ```
//!
//! and the fraction of `Δbase`'s variance that the input explains, `r² = (Σ Δb Δp)² / (Σ
//! Δp² Σ Δb²)`, says how well the ultra-local model of that order fits: for a plant whose
//! input acts on `y'` (a heater, a motor's speed) the order-1 fit explains the jumps and the
//! order-2 fit sees none (`y'` does not jump, so `y''` barely changes across a switch); for
//! one whose input acts on `y''` (a pendulum, a position) the reverse. Both orders are fitted
//! on the same data and the better `r²` wins, unless the caller fixes the order.
//!
//! # Safety
//! The excitation is bounded by the operator's `amplitude` around the input already
//! applied, its mean is that input (a symmetric square wave), and every sample is checked
//! against `max_deviation` from the output at the start: beyond it the run aborts at once
//! and says so; the caller puts the previous law back (bumplessly, from the applied input).
//! The plant's envelope (limits, rate) stays the caller's: it applies the output map to
//! what [`Commissioning::step`] asks and reports what was really applied.
//!
//! No clock, no I/O: the time is in the samples, as everywhere in this crate.

use crate::channel::LawConfig;
use crate::error::{finite, positive, MfcError, Result};
use crate::estimator::{Estimator, EstimatorConfig, LinearEstimate, DEFAULT_CAPACITY};
use crate::intelligent::IntelligentParams;
use crate::{ControllerKind, Order};

/// What the operator sets for a commissioning run.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "serde", serde(default, deny_unknown_fields))]
pub struct CommissionSpec {
    /// The square wave's half height around the held input, in the law's units (`u`,
    /// before the output map). Default 1.
    pub amplitude: f64,
    /// The square wave's period (s): each half must hold at least `window + 1` samples.
    /// Default 2.
    pub period: f64,
    /// How many periods (at least 2). Default 4.
    pub cycles: u32,
    /// The largest `|y - y0|` allowed, `y0` the output at the start; beyond it the run
    /// aborts. Default 1.
    pub max_deviation: f64,
    /// The estimator's window, in intervals (at least 2, at most the capacity less one).
    /// Default 20.
    pub window: usize,
    /// Fit only this order; `None` (the default) fits both and keeps the better.
    pub order: Option<Order>,
}

impl Default for CommissionSpec {
    fn default() -> Self {
        Self {
            amplitude: 1.0,
            period: 2.0,
            cycles: 4,
            max_deviation: 1.0,
            window: 20,
            order: None,
        }
    }
}

impl CommissionSpec {
    /// Check the specification against an estimator capacity.
    pub fn validate(&self, capacity: usize) -> Result<()> {
        positive("amplitude", self.amplitude)?;
        positive("period", self.period)?;
        positive("max_deviation", self.max_deviation)?;
        if self.cycles < 2 {
            return Err(MfcError::InvalidParameter {
                name: "cycles",
                value: f64::from(self.cycles),
                reason: "at least 2 periods, so that every switch is seen both ways",
            });
        }
        if self.window < 2 || self.window + 1 > capacity {
            return Err(MfcError::InvalidParameter {
                name: "window",
                value: self.window as f64,
                reason: "at least 2 intervals, and one less than the capacity",
            });
        }
        Ok(())
    }

    /// How long the excitation lasts (s).
    pub fn duration(&self) -> f64 {
        self.period * f64::from(self.cycles)
    }
}

/// The fit of one order: `α`, and the fraction `r²` of the output part's changes across
/// the switches that the input explains (0 to 1).
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct CommissionFit {
    /// The model's order.
    pub order: Order,
    /// `α` for that order.
    pub alpha: f64,
    /// How much of `F`'s jumps the input explains with that `α` (1: all).
    pub explained: f64,
}

/// What a finished run found.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct CommissionFinding {
    /// The fit kept (the better `explained`, or the order asked for).
    pub best: CommissionFit,
    /// Every order fitted, order 1 first.
    pub fits: [Option<CommissionFit>; 2],
    /// Samples used.
    pub samples: u64,
}

/// Why a run stopped without a finding.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CommissionAbort {
    /// The output left `max_deviation` around its start value.
    Deviation {
        /// When (s).
        t: f64,
        /// The output then.
        y: f64,
        /// The output at the start.
        y0: f64,
    },
    /// The data cannot give `α`: the input's changes left no trace in the estimates (too
    /// small an amplitude against the noise, or a plant that does not respond within a
    /// window), or the excitation switched faster than a window.
    NoFit(&'static str),
}

impl core::fmt::Display for CommissionAbort {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            CommissionAbort::Deviation { t, y, y0 } => write!(
                f,
                "the output went from {y0} to {y} at t = {t} s, beyond max_deviation: the previous law is back"
            ),
            CommissionAbort::NoFit(why) => write!(f, "no alpha from these data: {why}"),
        }
    }
}

/// What to do after a sample.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CommissionStep {
    /// Apply this input until the next sample.
    Apply(f64),
    /// The excitation is over: here is what it found. Put a law back.
    Done(CommissionFinding),
    /// Stopped early (see [`CommissionAbort`]). Put the previous law back.
    Aborted(CommissionAbort),
}

/// Running sums of one order's fit: `Σ Δb Δp`, `Σ Δp²`, `Σ Δb²`.
#[derive(Debug, Clone, Copy, Default)]
struct Sums {
    bp: f64,
    pp: f64,
    bb: f64,
}

impl Sums {
    fn add(&mut self, now: LinearEstimate, before: LinearEstimate) {
        let (db, dp) = (now.base - before.base, now.per_alpha - before.per_alpha);
        if db.is_finite() && dp.is_finite() {
            self.bp += db * dp;
            self.pp += dp * dp;
            self.bb += db * db;
        }
    }

    fn fit(&self, order: Order) -> Option<CommissionFit> {
        if !(self.pp > 0.0 && self.bb > 0.0) {
            return None;
        }
        let alpha = -self.bp / self.pp;
        let explained = (self.bp * self.bp / (self.pp * self.bb)).clamp(0.0, 1.0);
        (alpha.is_finite() && alpha != 0.0).then_some(CommissionFit {
            order,
            alpha,
            explained,
        })
    }
}

/// A commissioning run on one channel, sample by sample.
#[derive(Debug, Clone)]
pub struct Commissioning<const CAP: usize = DEFAULT_CAPACITY> {
    spec: CommissionSpec,
    u0: f64,
    start: Option<(f64, f64)>,
    last_t: f64,
    samples: u64,
    estimators: [Estimator<CAP>; 2],
    /// The last `window + 1` estimates of both orders, oldest at `head`.
    ring: [[LinearEstimate; 2]; CAP],
    filled: usize,
    head: usize,
    sums: [Sums; 2],
}

impl<const CAP: usize> Commissioning<CAP> {
    /// A run that excites around `u0`, the input the plant is getting now.
    pub fn new(spec: CommissionSpec, u0: f64) -> Result<Self> {
        spec.validate(CAP)?;
        finite("held input", u0)?;
        let config = EstimatorConfig {
            window: spec.window,
            ..EstimatorConfig::default()
        };
        Ok(Self {
            spec,
            u0,
            start: None,
            last_t: f64::NEG_INFINITY,
            samples: 0,
            estimators: [
                Estimator::new(config, Order::One)?,
                Estimator::new(config, Order::Two)?,
            ],
            ring: [[LinearEstimate::default(); 2]; CAP],
            filled: 0,
            head: 0,
            sums: [Sums::default(); 2],
        })
    }

    /// The specification.
    pub fn spec(&self) -> &CommissionSpec {
        &self.spec
    }

    /// One sample: the output `y` at `t`, and the input the plant really received since
    /// the previous sample (`u_applied`, in the law's units). Inputs that are not finite or
    /// a time that does not advance are refused with the run untouched.
    pub fn step(&mut self, t: f64, y: f64, u_applied: f64) -> Result<CommissionStep> {
        self.estimators[0].check(t, y, u_applied)?;
        let (t0, y0) = *self.start.get_or_insert((t, y));
        if (y - y0).abs() > self.spec.max_deviation {
            return Ok(CommissionStep::Aborted(CommissionAbort::Deviation {
                t,
                y,
                y0,
            }));
        }
        for e in &mut self.estimators {
            e.push(t, y, u_applied)?;
        }
        self.last_t = t;
        self.samples += 1;
        self.record();
        let elapsed = t - t0;
        if elapsed >= self.spec.duration() {
            return Ok(self.finish(t0));
        }
        let cycles = elapsed / self.spec.period;
        let phase = cycles - libm::floor(cycles);
        let sign = if phase < 0.5 { 1.0 } else { -1.0 };
        Ok(CommissionStep::Apply(self.u0 + sign * self.spec.amplitude))
    }

    /// Push both orders' estimates into the ring, adding each one's change over `window +
    /// 1` samples to the sums.
    fn record(&mut self) {
        let (Ok(a), Ok(b)) = (
            self.estimators[0].estimate(Order::One),
            self.estimators[1].estimate(Order::Two),
        ) else {
            return;
        };
        let lag = self.spec.window + 1;
        let now = [a, b];
        if self.filled == lag {
            let before = self.ring[self.head];
            for (s, (n, o)) in self.sums.iter_mut().zip(now.iter().zip(before)) {
                s.add(*n, o);
            }
            self.ring[self.head] = now;
            self.head = (self.head + 1) % lag;
        } else {
            self.ring[(self.head + self.filled) % lag] = now;
            self.filled += 1;
        }
    }

    fn finish(&self, t0: f64) -> CommissionStep {
        let h = (self.last_t - t0) / (self.samples.max(2) - 1) as f64;
        if self.spec.period / 2.0 < (self.spec.window + 1) as f64 * h {
            return CommissionStep::Aborted(CommissionAbort::NoFit(
                "each half period must hold at least window + 1 samples",
            ));
        }
        let fits = [self.sums[0].fit(Order::One), self.sums[1].fit(Order::Two)];
        let candidates = fits
            .iter()
            .flatten()
            .filter(|f| self.spec.order.is_none_or(|o| o == f.order));
        let best = candidates.fold(None::<CommissionFit>, |acc, f| match acc {
            Some(a) if a.explained >= f.explained => Some(a),
            _ => Some(*f),
        });
        match best {
            Some(best) if best.explained >= MIN_EXPLAINED => CommissionStep::Done(CommissionFinding {
                best,
                fits,
                samples: self.samples,
            }),
            _ => CommissionStep::Aborted(CommissionAbort::NoFit(
                "the input explains less than 30 % of the output's changes (raise the amplitude; for a plant with a dead time, a window longer than it)",
            )),
        }
    }
}

/// The least `r²` a fit needs to be proposed: below it the input's effect is lost in the
/// rest of `F` and `α` would be noise.
pub const MIN_EXPLAINED: f64 = 0.3;

/// Gains `[kp, ki, kd]` that give an intelligent law of `order` the error dynamics asked
/// for: `e' + ω e = 0` (order 1, an iP) or `e'' + 2ζω e' + ω² e = 0` (order 2, an iPD).
pub fn gains_for(order: Order, bandwidth: f64, damping: f64) -> Result<[f64; 3]> {
    positive("bandwidth", bandwidth)?;
    positive("damping", damping)?;
    Ok(match order {
        Order::One => [bandwidth, 0.0, 0.0],
        Order::Two => [bandwidth * bandwidth, 0.0, 2.0 * damping * bandwidth],
    })
}

/// The law a finding gives a channel whose law is `before` (an intelligent one; `None`
/// for any other): `α` and the order found; the gains from `dynamics` (`(ω, ζ)`, see
/// [`gains_for`]) if asked, otherwise the ones `before` has when the order is the same and
/// the ones that keep its error dynamics when it changes (order 1: `ω = kp`; order 2: `ω
/// = √kp`, `ζ = kd / 2ω`, at least 0.1). New gains make the law an iP or an iPD: no
/// integral (`ki` 0), since the error dynamics asked for have none. Every other parameter
/// as it was. `None` if the gains come out not positive.
pub fn commissioned_law(
    before: &LawConfig,
    f: &CommissionFinding,
    dynamics: Option<(f64, f64)>,
) -> Option<LawConfig> {
    let LawConfig::Intelligent { params, estimator } = *before else {
        return None;
    };
    let best = f.best;
    if best.order == params.order && dynamics.is_none() {
        return Some(LawConfig::Intelligent {
            params: IntelligentParams {
                alpha: best.alpha,
                ..params
            },
            estimator,
        });
    }
    let (omega, zeta) = dynamics.unwrap_or(match params.order {
        Order::One => (params.kp, 0.7),
        Order::Two => {
            let w = libm::sqrt(params.kp);
            (
                w,
                if w > 0.0 {
                    (params.kd / (2.0 * w)).max(0.1)
                } else {
                    0.7
                },
            )
        }
    });
    let [kp, ki, kd] = gains_for(best.order, omega, zeta).ok()?;
    let kind = match best.order {
        Order::One => ControllerKind::P,
        Order::Two => ControllerKind::PD,
    };
    Some(LawConfig::Intelligent {
        params: IntelligentParams {
            kind,
            order: best.order,
            alpha: best.alpha,
            kp,
            ki,
            kd,
            derivative_observer: if best.order == Order::One {
                0.0
            } else {
                params.derivative_observer
            },
            ..params
        },
        estimator,
    })
}

//! Linear active disturbance rejection control (LADRC), the closest rival of model-free
//! control: it too lumps everything unknown into one "total disturbance" `f`, but estimates it
//! with an extended state observer (ESO) instead of an algebraic integral.
//!
//! Model `y^(n) = f + b0 u`. The ESO tracks `z ≈ (y, .., y^(n-1), f)`; the law is
//!
//! ```text
//! n = 1:  u = (ωc (y* - z1) + y*' - z2) / b0
//! n = 2:  u = (ωc² (y* - z1) + 2ωc (y*' - z2) + y*'' - z3) / b0
//! ```
//!
//! Bandwidth parameterisation (Gao, 2003): the controller poles are all at `-ωc`; the
//! observer is the discrete "current" ESO (Miklosovic, Radke and Gao, 2006) whose poles are
//! all at `z = exp(-ωo h)`, with the gains recomputed from each real interval `h`, so
//! irregular sampling keeps the designed observer dynamics. The ESO is fed the input the
//! plant actually received.

use crate::error::{finite, nonzero, positive, MfcError, Result};
use crate::{Order, Reference};

/// LADRC parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "serde", serde(default, deny_unknown_fields))]
#[cfg_attr(feature = "snapshot", derive(bincode::Encode, bincode::Decode))]
pub struct AdrcParams {
    /// Order of the model. Default: 1.
    pub order: Order,
    /// Input gain estimate `b0` (non-zero). Default: 1.
    pub b0: f64,
    /// Controller bandwidth `ωc` (rad/s, > 0). Default: 5.
    pub wc: f64,
    /// Observer bandwidth `ωo` (rad/s, > 0), typically 3 to 10 times `ωc`. Default: 25.
    pub wo: f64,
}

impl Default for AdrcParams {
    fn default() -> Self {
        Self {
            order: Order::One,
            b0: 1.0,
            wc: 5.0,
            wo: 25.0,
        }
    }
}

impl AdrcParams {
    /// Check the parameters.
    pub fn validate(&self) -> Result<()> {
        nonzero("b0", self.b0)?;
        positive("wc", self.wc)?;
        positive("wo", self.wo)?;
        Ok(())
    }
}

/// A linear ADRC controller.
#[derive(Debug, Clone)]
#[cfg_attr(feature = "snapshot", derive(bincode::Encode, bincode::Decode))]
pub struct Adrc {
    params: AdrcParams,
    pending: Option<AdrcParams>,
    /// Observer state: y, (y'), f.
    z: [f64; 3],
    last_t: Option<f64>,
    applied: f64,
    start_from: Option<f64>,
}

impl Adrc {
    /// An ADRC with checked parameters.
    pub fn new(params: AdrcParams) -> Result<Self> {
        params.validate()?;
        Ok(Self {
            params,
            pending: None,
            z: [0.0; 3],
            last_t: None,
            applied: 0.0,
            start_from: None,
        })
    }

    /// Parameters in force.
    pub fn params(&self) -> &AdrcParams {
        self.pending.as_ref().unwrap_or(&self.params)
    }

    /// The observer's estimate of the total disturbance `f`.
    pub fn disturbance(&self) -> f64 {
        match self.params.order {
            Order::One => self.z[1],
            Order::Two => self.z[2],
        }
    }

    /// Change the parameters at the next step. The observer state carries over; `f` is
    /// re-based so that the output does not jump.
    pub fn set_params(&mut self, params: AdrcParams) -> Result<()> {
        params.validate()?;
        if self.last_t.is_none() {
            self.params = params;
        } else {
            self.pending = Some(params);
        }
        Ok(())
    }

    /// The first output will be `u0`: the observer starts with the disturbance that makes
    /// `u0` the control.
    pub fn bumpless_start(&mut self, u0: f64) -> Result<()> {
        finite("control", u0)?;
        self.start_from = Some(u0);
        self.applied = u0;
        Ok(())
    }

    /// After a gap in the data: restart the observer from the next measurement, with the
    /// disturbance estimate that keeps the input being applied (bumpless).
    pub fn forget_window(&mut self) {
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
        match self.last_t {
            None => {
                self.z = [y, 0.0, 0.0];
                if p.order == Order::Two {
                    self.z[1] = r.dy;
                }
            }
            Some(t0) => self.observe(t - t0, y),
        }
        self.last_t = Some(t);
        let mut target = self.start_from.take();
        if let Some(new) = self.pending.take() {
            target.get_or_insert(self.law(&p, r));
            self.params = new;
        }
        if let Some(u0) = target {
            // Re-base f so that the law gives u0: law is linear in f with slope -1/b0.
            let p = self.params;
            let idx = self.f_index();
            self.z[idx] += p.b0 * (self.law(&p, r) - u0);
        }
        let p = self.params;
        let u = self.law(&p, r);
        self.applied = u;
        Ok(u)
    }

    /// A copy of the observer to run forward for a packetized horizon
    /// ([`crate::Channel::plan`]): `None` before the first step.
    pub(crate) fn predictor(&self) -> Option<AdrcPredictor> {
        self.last_t?;
        Some(AdrcPredictor {
            params: self.params,
            z: self.z,
        })
    }

    fn f_index(&self) -> usize {
        match self.params.order {
            Order::One => 1,
            Order::Two => 2,
        }
    }

    fn law(&self, p: &AdrcParams, r: &Reference) -> f64 {
        law(p, &self.z, r)
    }

    /// Predict over `h` with the applied input, then correct with the measurement.
    fn observe(&mut self, h: f64, y: f64) {
        let p = self.params;
        let beta = libm::exp(-p.wo * h);
        let bu = p.b0 * self.applied;
        match p.order {
            Order::One => {
                let z1 = self.z[0] + h * (self.z[1] + bu);
                let e = y - z1;
                let l1 = 1.0 - beta * beta;
                let l2 = (1.0 - beta) * (1.0 - beta) / h;
                self.z[0] = z1 + l1 * e;
                self.z[1] += l2 * e;
            }
            Order::Two => {
                let acc = self.z[2] + bu;
                let z1 = self.z[0] + h * self.z[1] + 0.5 * h * h * acc;
                let z2 = self.z[1] + h * acc;
                let e = y - z1;
                let one_b = 1.0 - beta;
                let l1 = 1.0 - beta * beta * beta;
                let l2 = 1.5 / h * one_b * one_b * (1.0 + beta);
                let l3 = one_b * one_b * one_b / (h * h);
                self.z[0] = z1 + l1 * e;
                self.z[1] = z2 + l2 * e;
                self.z[2] += l3 * e;
            }
        }
    }
}

/// The observer's model run forward with `f` held (no measurement to correct it): the
/// same ultra-local model the intelligent controllers predict with, in the ESO's states.
#[derive(Debug, Clone, Copy)]
pub(crate) struct AdrcPredictor {
    params: AdrcParams,
    z: [f64; 3],
}

impl AdrcPredictor {
    /// Let `h` pass with `u` applied.
    pub(crate) fn advance(&mut self, h: f64, u: f64) {
        let bu = self.params.b0 * u;
        match self.params.order {
            Order::One => self.z[0] += h * (self.z[1] + bu),
            Order::Two => {
                let acc = self.z[2] + bu;
                self.z[0] += h * self.z[1] + 0.5 * h * h * acc;
                self.z[1] += h * acc;
            }
        }
    }

    /// The law at the predicted state.
    pub(crate) fn law(&self, r: &Reference) -> f64 {
        law(&self.params, &self.z, r)
    }
}

/// The control law on an observer state `z` (measured or predicted).
fn law(p: &AdrcParams, z: &[f64; 3], r: &Reference) -> f64 {
    match p.order {
        Order::One => (p.wc * (r.y - z[0]) + r.dy - z[1]) / p.b0,
        Order::Two => {
            let (kp, kd) = (p.wc * p.wc, 2.0 * p.wc);
            (kp * (r.y - z[0]) + kd * (r.dy - z[1]) + r.ddy - z[2]) / p.b0
        }
    }
}

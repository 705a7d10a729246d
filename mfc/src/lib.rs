//! # Model-free control
//!
//! Model-free control (M. Fliess and C. Join) replaces a model of the plant by an
//! *ultra-local model*, valid over a few samples,
//!
//! ```text
//! y^(n) = F + α u        (n = 1, or 2 for weakly damped mechanics)
//! ```
//!
//! where `F` lumps together everything unknown (the plant's structure, disturbances, an added
//! mass) and is re-estimated at every sample from a short integral of the recent inputs and
//! outputs ([`estimator`]). An *intelligent proportional* controller then cancels it and
//! tracks the reference `y*`:
//!
//! ```text
//! u = -(F_est - y*^(n) + Kp e) / α,    e = y - y*          (iP)
//! ```
//!
//! so that the error obeys `e^(n) + Kp e = F - F_est ≈ 0`. The constant `α` is chosen so
//! that `α u` has the magnitude of `y^(n)`; it need not be precise. A MIMO plant runs one
//! such loop per output ([`mimo`]), the other outputs' influence being part of each `F`.
//!
//! This crate holds the control core and nothing else: no I/O, no async, no allocation on the
//! step path, `#![no_std]` without default features. It provides
//!
//! * [`Estimator`]: algebraic kernels for n = 1 and 2 with weights that follow the real
//!   timestamps (exact for constant `F`, unbiased by lost samples, O(1) per step), the
//!   non-circular closed-loop form and a low-pass form;
//! * [`IntelligentController`]: iP, iPI, iPD (n = 2) and iPID, with bumpless changes of
//!   gains, `α` and kind while running;
//! * [`OutputMap`]: dead-zone compensation, saturation, rate limit, and the inverse that
//!   tells the estimator what the plant really got;
//! * baselines for honest comparisons: [`Pid`] and linear [`Adrc`];
//! * [`trajectory`]: references as sums of smooth pieces with analytic derivatives;
//! * [`Channel`] (a law plus its output map) and, with `alloc`, [`mimo::MimoController`];
//! * [`params`]: the table of the parameters an operator tunes by name (`kp`, `alpha`,
//!   `dead_zone`, ...), with their laws, units, meanings and sanity bounds.
//!
//! Every fallible call checks its input first and returns a [`MfcError`] with the state
//! untouched; nothing here panics on data.
//!
//! ## Example
//!
//! Track a ramp on an unknown first-order plant with a constant disturbance:
//!
//! ```
//! use mfc::{Channel, ChannelConfig, ControllerKind, EstimatorConfig, IntelligentParams,
//!           LawConfig, OutputMapConfig, Order, Reference};
//!
//! let params = IntelligentParams {
//!     kind: ControllerKind::P,
//!     order: Order::One,
//!     alpha: 2.0,
//!     kp: 5.0,
//!     ..IntelligentParams::default()
//! };
//! let config = ChannelConfig {
//!     law: LawConfig::Intelligent { params, estimator: EstimatorConfig::default() },
//!     output: OutputMapConfig::default(),
//! };
//! let mut channel: Channel = Channel::new(&config)?;
//!
//! // Plant unknown to the controller: y' = -0.5 y + 3 u + 0.7.
//! let (h, mut y) = (0.01, 0.0);
//! for k in 0..1000 {
//!     let t = k as f64 * h;
//!     let r = Reference { y: 0.2 * t, dy: 0.2, ddy: 0.0 };
//!     let out = channel.step(t, y, &r)?;
//!     for _ in 0..10 {
//!         y += h / 10.0 * (-0.5 * y + 3.0 * out.v + 0.7);
//!     }
//! }
//! let t_end = 1000.0 * h;
//! assert!((y - 0.2 * t_end).abs() < 0.01);
//! # Ok::<(), mfc::MfcError>(())
//! ```
#![cfg_attr(not(feature = "std"), no_std)]
#![warn(missing_docs)]

#[cfg(feature = "alloc")]
extern crate alloc;

pub mod adrc;
pub mod channel;
pub mod commission;
pub mod error;
pub mod estimator;
pub mod filter;
pub mod intelligent;
#[cfg(feature = "alloc")]
pub mod mimo;
pub mod output_map;
pub mod params;
pub mod pid;
#[cfg(feature = "snapshot")]
pub mod snapshot;
pub mod trajectory;

pub use adrc::{Adrc, AdrcParams};
pub use channel::{Channel, ChannelConfig, ChannelOutput, LawConfig};
pub use commission::{
    commissioned_law, gains_for, CommissionAbort, CommissionFinding, CommissionFit, CommissionSpec,
    CommissionStep, Commissioning,
};
pub use error::{MfcError, Result};
pub use estimator::{Estimator, EstimatorConfig, EstimatorKind, LinearEstimate, DEFAULT_CAPACITY};
pub use intelligent::{IntelligentController, IntelligentOutput, IntelligentParams, Trend};
#[cfg(feature = "alloc")]
pub use mimo::MimoController;
pub use output_map::{OutputMap, OutputMapConfig};
pub use pid::{Pid, PidParams};

/// Order `n` of the ultra-local model `y^(n) = F + α u`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "serde", serde(rename_all = "snake_case"))]
#[cfg_attr(feature = "snapshot", derive(bincode::Encode, bincode::Decode))]
pub enum Order {
    /// `y' = F + α u`: the usual choice, even for mechanical systems.
    #[default]
    One,
    /// `y'' = F + α u`: for weak friction, with iPD.
    Two,
}

impl Order {
    /// The integer `n`.
    pub fn n(self) -> u8 {
        match self {
            Order::One => 1,
            Order::Two => 2,
        }
    }

    /// Fewest sample intervals the algebraic kernel of this order needs (n = 2 cannot tell
    /// the curvature from one interval).
    pub fn min_intervals(self) -> usize {
        match self {
            Order::One => 1,
            Order::Two => 2,
        }
    }
}

/// Which intelligent controller: the terms added to the cancellation of `F`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "snapshot", derive(bincode::Encode, bincode::Decode))]
pub enum ControllerKind {
    /// iP (n = 1): `u = -(F - y*' + Kp e)/α`. Written `"ip"` in files.
    #[default]
    #[cfg_attr(feature = "serde", serde(rename = "ip"))]
    P,
    /// iPI (n = 1): iP plus `Ki ∫e`. Written `"ipi"`.
    #[cfg_attr(feature = "serde", serde(rename = "ipi"))]
    PI,
    /// iPD (n = 2): `u = -(F - y*'' + Kp e + Kd e')/α`. Written `"ipd"`.
    #[cfg_attr(feature = "serde", serde(rename = "ipd"))]
    PD,
    /// iPID (n = 1 or 2): all three terms. Written `"ipid"`.
    #[cfg_attr(feature = "serde", serde(rename = "ipid"))]
    PID,
}

impl ControllerKind {
    /// Whether the kind stabilises the error equation of a model of `order`.
    pub fn supports(self, order: Order) -> bool {
        matches!(
            (self, order),
            (ControllerKind::P | ControllerKind::PI, Order::One)
                | (ControllerKind::PD, Order::Two)
                | (ControllerKind::PID, _)
        )
    }

    /// Whether the kind has an integral term.
    pub fn has_integral(self) -> bool {
        matches!(self, ControllerKind::PI | ControllerKind::PID)
    }

    /// Whether the kind has a derivative term.
    pub fn has_derivative(self) -> bool {
        matches!(self, ControllerKind::PD | ControllerKind::PID)
    }
}

/// The reference trajectory at one instant, with its analytic derivatives.
///
/// iP needs `dy` (n = 1) or `ddy` (n = 2) as a feed-forward; a reference generator knows
/// them exactly, so the controller never differentiates the reference numerically.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "snapshot", derive(bincode::Encode, bincode::Decode))]
pub struct Reference {
    /// `y*`.
    pub y: f64,
    /// `dy*/dt`.
    pub dy: f64,
    /// `d²y*/dt²`.
    pub ddy: f64,
}

impl Reference {
    /// A constant set-point.
    pub fn constant(y: f64) -> Self {
        Self {
            y,
            dy: 0.0,
            ddy: 0.0,
        }
    }

    pub(crate) fn check(&self) -> Result<()> {
        error::finite("reference", self.y)?;
        error::finite("reference", self.dy)?;
        error::finite("reference", self.ddy)?;
        Ok(())
    }
}

//! The one error type of the control core.
//!
//! Every fallible call validates its whole input *before* it touches any state, so an
//! `Err` always means "nothing changed": a caller fed bad network data can log the error and
//! carry on with the same controller.

use crate::params::LawKind;
use crate::{ControllerKind, Order};

/// Why a call into the control core was refused.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum MfcError {
    /// A measurement (or an applied input) was NaN or infinite.
    #[error("non-finite {what}: {value}")]
    NonFinite {
        /// Which quantity was bad (`"measurement"`, `"reference"`, `"applied input"`, `"time"`).
        what: &'static str,
        /// The offending value.
        value: f64,
    },
    /// A timestamp did not advance past the previous one. Stale or duplicated data must never
    /// move a controller's time backwards: the caller should drop the sample.
    #[error("time does not advance: previous {previous} s, got {current} s")]
    TimeNotAdvancing {
        /// Timestamp of the last accepted sample.
        previous: f64,
        /// Timestamp that was refused.
        current: f64,
    },
    /// The estimation window is too short for the model order: n = 1 needs at least one
    /// interval (two samples), n = 2 at least two intervals (three samples).
    #[error(
        "estimation window of {len} intervals is too short for order {order:?} (minimum {min})"
    )]
    WindowTooShort {
        /// Requested window length in sample intervals.
        len: usize,
        /// Minimum for the order.
        min: usize,
        /// Model order.
        order: Order,
    },
    /// The window does not fit the estimator's fixed storage (the `CAP` const parameter).
    #[error("estimation window of {len} intervals exceeds the storage capacity {capacity}")]
    WindowTooLong {
        /// Requested window length in sample intervals.
        len: usize,
        /// Storage capacity.
        capacity: usize,
    },
    /// Not enough samples yet to estimate F (warm-up after start or after a reset).
    #[error("not enough samples yet: have {have}, need {need}")]
    NotReady {
        /// Samples in the window.
        have: usize,
        /// Samples required.
        need: usize,
    },
    /// `alpha` (or ADRC's `b0`) is zero or not finite: the control law divides by it.
    #[error("invalid {name} = {value}: must be finite and non-zero")]
    InvalidAlpha {
        /// Parameter name.
        name: &'static str,
        /// The value.
        value: f64,
    },
    /// A gain or time constant is negative, zero where it must be positive, or not finite.
    #[error("invalid parameter {name} = {value}: {reason}")]
    InvalidParameter {
        /// Parameter name.
        name: &'static str,
        /// The value.
        value: f64,
        /// What was expected.
        reason: &'static str,
    },
    /// The controller kind does not stabilise an ultra-local model of that order
    /// (iP and iPI need n = 1, iPD needs n = 2).
    #[error("controller {kind:?} is not defined for order {order:?}")]
    IncompatibleOrder {
        /// Requested kind.
        kind: ControllerKind,
        /// Requested order.
        order: Order,
    },
    /// A parameter asked of a law that has no such parameter (`alpha` of a PID): see
    /// [`crate::params`].
    #[error("the {law} law in force has no {name}")]
    NoSuchParameter {
        /// The parameter's name.
        name: &'static str,
        /// The law in force.
        law: LawKind,
    },
    /// The closed-loop (integral) estimator only exists for n = 1.
    #[error("the closed-loop estimator is only defined for order One")]
    UnsupportedEstimatorOrder,
    /// A MIMO call got slices whose length does not match the number of channels.
    #[error("expected {expected} channels, got {got}")]
    DimensionMismatch {
        /// Number of channels of the controller.
        expected: usize,
        /// Length that was passed.
        got: usize,
    },
}

/// Result alias of the control core.
pub type Result<T> = core::result::Result<T, MfcError>;

pub(crate) fn finite(what: &'static str, value: f64) -> Result<f64> {
    if value.is_finite() {
        Ok(value)
    } else {
        Err(MfcError::NonFinite { what, value })
    }
}

/// `value` must be finite and `>= 0`.
pub(crate) fn non_negative(name: &'static str, value: f64) -> Result<f64> {
    if value.is_finite() && value >= 0.0 {
        Ok(value)
    } else {
        Err(MfcError::InvalidParameter {
            name,
            value,
            reason: "must be finite and >= 0",
        })
    }
}

/// `value` must be finite and `> 0`.
pub(crate) fn positive(name: &'static str, value: f64) -> Result<f64> {
    if value.is_finite() && value > 0.0 {
        Ok(value)
    } else {
        Err(MfcError::InvalidParameter {
            name,
            value,
            reason: "must be finite and > 0",
        })
    }
}

pub(crate) fn nonzero(name: &'static str, value: f64) -> Result<f64> {
    if value.is_finite() && value != 0.0 {
        Ok(value)
    } else {
        Err(MfcError::InvalidAlpha { name, value })
    }
}

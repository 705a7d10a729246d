//! Small discrete filters shared by the controllers.

/// Filtered derivative `s / (τ s + 1)`, discretised by backward Euler so that it follows
/// the real (possibly irregular) sample times and stays stable for any `τ >= 0`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "snapshot", derive(bincode::Encode, bincode::Decode))]
pub struct DerivativeFilter {
    last: Option<(f64, f64)>,
    value: f64,
}

impl DerivativeFilter {
    /// Feed the sample `x` at time `t` (must be after the previous one); returns the
    /// filtered derivative, 0 on the first sample.
    pub fn update(&mut self, t: f64, x: f64, time_constant: f64) -> f64 {
        if let Some((t0, x0)) = self.last {
            let h = t - t0;
            self.value = (time_constant * self.value + (x - x0)) / (time_constant + h);
        }
        self.last = Some((t, x));
        self.value
    }

    /// The current filtered derivative.
    pub fn value(&self) -> f64 {
        self.value
    }

    /// The last sample fed, if any.
    pub fn last(&self) -> Option<f64> {
        self.last.map(|(_, x)| x)
    }
}

/// `exp(-dt / tau)`, the per-step decay of a first-order lag; 0 when `tau` is 0.
pub(crate) fn decay(dt: f64, tau: f64) -> f64 {
    if tau > 0.0 {
        libm::exp(-dt / tau)
    } else {
        0.0
    }
}

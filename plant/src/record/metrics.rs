//! Tracking metrics of a run.

use serde::{Deserialize, Serialize};

/// Tracking figures of one channel.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChannelMetrics {
    /// Channel name.
    pub name: String,
    /// Root mean square of `y - y*`.
    pub rms: f64,
    /// Largest `|y - y*|`.
    pub max_abs: f64,
    /// Integral of `|y - y*|` over time.
    pub iae: f64,
    /// Fraction of samples with the output at a saturation limit.
    pub saturated_fraction: f64,
    /// Mean |v(k) - v(k-1)| per sample (V): how much the actuator chatters.
    pub control_variation: f64,
}

/// Accumulates the metrics of one channel sample by sample.
#[derive(Debug, Clone, Default)]
pub struct Accumulator {
    n: usize,
    sum_sq: f64,
    max_abs: f64,
    iae: f64,
    saturated: usize,
    last_v: Option<f64>,
    variation: f64,
}

impl Accumulator {
    /// Add one sample: error `e` over a period `h`, the applied output `v`, and whether it
    /// was saturated.
    pub fn add(&mut self, e: f64, h: f64, v: f64, saturated: bool) {
        if let Some(last) = self.last_v {
            self.variation += (v - last).abs();
        }
        self.last_v = Some(v);
        self.n += 1;
        self.sum_sq += e * e;
        self.max_abs = self.max_abs.max(e.abs());
        self.iae += e.abs() * h;
        self.saturated += usize::from(saturated);
    }

    /// The metrics so far.
    pub fn finish(&self, name: &str) -> ChannelMetrics {
        let n = self.n.max(1) as f64;
        ChannelMetrics {
            name: name.to_string(),
            rms: (self.sum_sq / n).sqrt(),
            max_abs: self.max_abs,
            iae: self.iae,
            saturated_fraction: self.saturated as f64 / n,
            control_variation: self.variation / (n - 1.0).max(1.0),
        }
    }
}

/// The `q` quantile (0..=1) of sorted values, nearest rank; 0 for no values. The one
/// percentile of the project: round trips, benchmarks and reports all use it.
pub fn percentile<T: Copy + Into<f64>>(sorted: &[T], q: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let i = ((sorted.len() - 1) as f64 * q.clamp(0.0, 1.0)).round() as usize;
    sorted[i.min(sorted.len() - 1)].into()
}

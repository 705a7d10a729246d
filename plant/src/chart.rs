//! What every plot of the project shares, so that a person can read them: the embedded
//! font, ticks at round values with plain labels, and axis titles that carry their unit.
//!
//! plotters chooses its own tick positions by adding a step to the axis' start, so a
//! tick meant for 0 lands on `-1.388e-17`, and a fixed format then prints `2.500e-1` for
//! 0.25. Here the ticks are integer multiples of a round step (1, 2, 2.5 or 5 × 10^k),
//! each value the nearest float to its decimal, and a label prints exactly the decimal
//! the step allows: `0`, `0.05`, `-0.1`, `0.25`; scientific notation (`2.5e-4`) only
//! when the step is below 0.001 or the values reach a million. [`Ticks::axis`] gives the
//! plotters axis whose grid sits on the ticks; [`Ticks::label`] formats them.

use std::ops::Range;
use std::sync::Once;

use plotters::coord::ranged1d::{AsRangedCoord, DefaultFormatting, KeyPointHint, Ranged};
use plotters::style::FontStyle;

static FONT: Once = Once::new();

/// The bitmap backend draws text with an embedded font (no system fonts needed, so plots
/// work on a bare server); call before drawing any PNG.
pub fn ensure_font() {
    FONT.call_once(|| {
        let _ = plotters::style::register_font(
            "sans-serif",
            FontStyle::Normal,
            dejavu::sans::regular(),
        );
    });
}

/// An axis title with its unit: `pitch (rad)`. A quantity without a unit (an empty one,
/// or `1` for a dimensionless one) is titled alone.
pub fn axis_title(quantity: &str, unit: &str) -> String {
    match unit.trim() {
        "" | "1" => quantity.to_string(),
        u => format!("{quantity} ({u})"),
    }
}

/// The round steps of a decade, in tenths: 1, 2, 2.5 and 5.
const STEPS_TENTHS: [i64; 4] = [10, 20, 25, 50];

/// Tick values of an axis and how to label them.
#[derive(Debug, Clone, PartialEq)]
pub struct Ticks {
    values: Vec<f64>,
    /// Every value is an integer multiple of `10^quantum` (0.05: -2; 0.25: -2; 20: 1).
    quantum: i32,
    /// Label in scientific notation (a step below 0.001, or values from a million up).
    scientific: bool,
}

/// `n × 10^exp` as the nearest float (a power of ten up to 10^22 is exact, so dividing
/// by it rounds once).
fn decimal(n: i64, exp: i32) -> f64 {
    if exp >= 0 {
        n as f64 * 10f64.powi(exp)
    } else {
        n as f64 / 10f64.powi(-exp)
    }
}

impl Ticks {
    /// At most `max` (at least 2) ticks covering `lo..=hi` on a linear axis: the smallest
    /// step of 1, 2, 2.5 or 5 × 10^k that gives no more than `max`, at every multiple of
    /// the step inside the range. No ticks for a range that is not finite.
    pub fn linear(lo: f64, hi: f64, max: usize) -> Self {
        let (lo, hi) = if lo <= hi { (lo, hi) } else { (hi, lo) };
        let none = Self {
            values: Vec::new(),
            quantum: 0,
            scientific: false,
        };
        let max = max.max(2);
        let span = hi - lo;
        if !(lo.is_finite() && hi.is_finite() && span.is_finite()) {
            return none;
        }
        if span <= 0.0 || (span / max as f64).log10() < -290.0 {
            // One value: label it with three significant digits.
            let quantum = if lo == 0.0 {
                0
            } else {
                lo.abs().log10().floor() as i32 - 2
            };
            return Self::from_values(vec![lo], quantum);
        }
        let k = (span / max as f64).log10().floor() as i32;
        for exp in k - 1..=k + 2 {
            for tenths in STEPS_TENTHS {
                // The step is `units × 10^quantum`, with `units` an integer.
                let (units, quantum) = if tenths % 10 == 0 {
                    (tenths / 10, exp)
                } else {
                    (tenths, exp - 1)
                };
                let step = decimal(units, quantum);
                // A hair of tolerance: 0.25 / 0.05 must count 5, not 4.999...
                let first = (lo / step - 1e-9).ceil();
                let last = (hi / step + 1e-9).floor();
                if last - first + 1.0 > max as f64 {
                    continue;
                }
                let values = (first as i64..=last as i64)
                    .map(|i| decimal(i * units, quantum))
                    .collect();
                return Self::from_values(values, quantum);
            }
        }
        none
    }

    /// Ticks at 1, 2 and 5 × 10^k covering `lo..=hi` on a logarithmic axis (only the
    /// decades when those are more than `max`); a range too narrow for three of them gets
    /// at most five [`Ticks::linear`] ones, which sit as well on a log axis. No ticks unless
    /// `0 < lo < hi`, both finite.
    pub fn log(lo: f64, hi: f64, max: usize) -> Self {
        if !(lo > 0.0 && hi > lo && hi.is_finite()) {
            return Self::linear(f64::NAN, f64::NAN, max);
        }
        let mut picked: Vec<(i64, i32)> = Vec::new();
        for exp in lo.log10().floor() as i32..=hi.log10().ceil() as i32 {
            for m in [1, 2, 5] {
                let v = decimal(m, exp);
                if v >= lo * (1.0 - 1e-9) && v <= hi * (1.0 + 1e-9) {
                    picked.push((m, exp));
                }
            }
        }
        if picked.len() < 3 {
            return Self::linear(lo, hi, max.min(5));
        }
        if picked.len() > max.max(2) {
            picked.retain(|(m, _)| *m == 1);
        }
        let quantum = picked.iter().map(|(_, e)| *e).min().unwrap_or(0);
        Self::from_values(
            picked.iter().map(|(m, e)| decimal(*m, *e)).collect(),
            quantum,
        )
    }

    /// The light grid lines of a logarithmic axis: every integer multiple of each decade
    /// (2, 3, ... 9 × 10^k) inside `lo..=hi`.
    pub fn log_minor(lo: f64, hi: f64) -> Vec<f64> {
        if !(lo > 0.0 && hi > lo && hi.is_finite()) {
            return Vec::new();
        }
        (lo.log10().floor() as i32..=hi.log10().ceil() as i32)
            .flat_map(|exp| (1..10).map(move |m| decimal(m, exp)))
            .filter(|v| *v >= lo && *v <= hi)
            .collect()
    }

    fn from_values(values: Vec<f64>, quantum: i32) -> Self {
        let largest = values.iter().fold(0.0f64, |a, v| a.max(v.abs()));
        // The step is at least 10^quantum, and below 0.001 exactly when the quantum is.
        let scientific = quantum < -3 || largest >= 1e6;
        Self {
            values,
            quantum,
            scientific,
        }
    }

    /// The tick values, in increasing order.
    pub fn values(&self) -> &[f64] {
        &self.values
    }

    /// A plotters axis over `range` (`lo..hi`, or `(lo..hi).log_scale()`) with its grid
    /// lines and labels at these ticks.
    pub fn axis<A: AsRangedCoord<Value = f64>>(&self, range: A) -> TickedAxis<A::CoordDescType> {
        TickedAxis {
            inner: range.into(),
            major: self.values.clone(),
            minor: Vec::new(),
        }
    }

    /// The label of a tick value: the shortest decimal the axis' step allows (`0`,
    /// `0.05`, `-0.1`, `12.5`, `400`), or `2.5e-4` for a step below 0.001 or values from a
    /// million up. A value off the ticks is rounded to the axis' precision.
    pub fn label(&self, v: f64) -> String {
        if !v.is_finite() {
            return v.to_string();
        }
        let units = (decimal(1, -self.quantum) * v).round();
        if units == 0.0 {
            return "0".into();
        }
        let text = if self.scientific {
            let digits = (units.abs().log10().floor() as usize) + 1;
            let s = format!("{:.*e}", digits.saturating_sub(1), v);
            match s.split_once('e') {
                Some((mantissa, exp)) => format!("{}e{exp}", trim_zeros(mantissa)),
                None => s,
            }
        } else {
            trim_zeros(&format!(
                "{:.*}",
                self.quantum.min(0).unsigned_abs() as usize,
                v
            ))
            .to_string()
        };
        if text == "-0" {
            "0".into()
        } else {
            text
        }
    }
}

/// A plotters axis (linear or logarithmic) whose bold grid lines and labels sit on
/// [`Ticks`] and whose light ones, if any, on the values given to
/// [`TickedAxis::with_minor`]. (plotters' own `WithKeyPoints` does the same but loses the
/// label formatter of an `f64` axis.)
#[derive(Debug, Clone)]
pub struct TickedAxis<R> {
    inner: R,
    major: Vec<f64>,
    minor: Vec<f64>,
}

impl<R> TickedAxis<R> {
    /// Light grid lines at `minor` (e.g. [`Ticks::log_minor`]).
    pub fn with_minor(mut self, minor: Vec<f64>) -> Self {
        self.minor = minor;
        self
    }
}

impl<R: Ranged<ValueType = f64>> Ranged for TickedAxis<R> {
    type FormatOption = DefaultFormatting;
    type ValueType = f64;

    fn map(&self, value: &f64, limit: (i32, i32)) -> i32 {
        self.inner.map(value, limit)
    }

    fn key_points<H: KeyPointHint>(&self, hint: H) -> Vec<f64> {
        if hint.weight().allow_light_points() {
            self.minor.clone()
        } else {
            self.major.clone()
        }
    }

    fn range(&self) -> Range<f64> {
        self.inner.range()
    }

    fn axis_pixel_range(&self, limit: (i32, i32)) -> Range<i32> {
        self.inner.axis_pixel_range(limit)
    }
}

/// `2.50` -> `2.5`, `3.0` -> `3`; whole numbers (`10`) stay as they are.
fn trim_zeros(s: &str) -> &str {
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.')
    } else {
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn labels(t: &Ticks) -> Vec<String> {
        t.values().iter().map(|v| t.label(*v)).collect()
    }

    /// The demo's pitch axis: a zero computed as -1.4e-17 and a top of 0.25.
    #[test]
    fn a_float_zero_and_a_quarter_get_round_ticks_and_plain_labels() {
        let t = Ticks::linear(-1.388e-17, 0.25, 8);
        assert_eq!(labels(&t), ["0", "0.05", "0.1", "0.15", "0.2", "0.25"]);
        assert_eq!(t.values()[0], 0.0);
        assert_eq!(
            t.values()[3],
            0.15,
            "the nearest float to 0.15, not 3 × 0.05"
        );
        let t = Ticks::linear(-0.13, 0.29, 10);
        assert_eq!(
            labels(&t),
            ["-0.1", "-0.05", "0", "0.05", "0.1", "0.15", "0.2", "0.25"]
        );
    }

    #[test]
    fn steps_are_1_2_2_5_or_5_times_a_power_of_ten() {
        assert_eq!(
            labels(&Ticks::linear(0.0, 40.0, 10)),
            ["0", "5", "10", "15", "20", "25", "30", "35", "40"]
        );
        assert_eq!(
            labels(&Ticks::linear(0.0, 400.0, 10)),
            ["0", "50", "100", "150", "200", "250", "300", "350", "400"]
        );
        assert_eq!(
            labels(&Ticks::linear(0.0, 10.0, 5)),
            ["0", "2.5", "5", "7.5", "10"]
        );
        assert_eq!(
            labels(&Ticks::linear(-17.0, 21.0, 10)),
            ["-15", "-10", "-5", "0", "5", "10", "15", "20"]
        );
        assert_eq!(
            labels(&Ticks::linear(18.0, 46.0, 8)),
            ["20", "25", "30", "35", "40", "45"]
        );
        assert_eq!(
            labels(&Ticks::linear(0.0, 1.0, 6)),
            ["0", "0.2", "0.4", "0.6", "0.8", "1"]
        );
        // Never more than asked for, whatever the range.
        for (lo, hi) in [
            (0.0, 1.0),
            (-3.3, 7.7),
            (1e-9, 3e-9),
            (-5e7, 1e8),
            (0.1, 0.1001),
        ] {
            for max in 2..12 {
                let t = Ticks::linear(lo, hi, max);
                assert!(
                    !t.values().is_empty() && t.values().len() <= max,
                    "{lo}..{hi} max {max}: {t:?}"
                );
                assert!(t
                    .values()
                    .iter()
                    .all(|v| *v >= lo - 1e-9 * (hi - lo) && *v <= hi + 1e-9 * (hi - lo)));
            }
        }
    }

    #[test]
    fn only_really_small_or_large_values_are_scientific() {
        // The azimuth velocity, in rad/ms.
        assert_eq!(
            labels(&Ticks::linear(-4.5e-4, 1.05e-3, 8)),
            ["-4e-4", "-2e-4", "0", "2e-4", "4e-4", "6e-4", "8e-4", "1e-3"]
        );
        assert_eq!(
            labels(&Ticks::linear(0.0, 1e-3, 5)),
            ["0", "2.5e-4", "5e-4", "7.5e-4", "1e-3"]
        );
        assert_eq!(
            labels(&Ticks::linear(0.0, 0.003, 4)),
            ["0", "0.001", "0.002", "0.003"]
        );
        assert_eq!(
            labels(&Ticks::linear(0.0, 3e6, 4)),
            ["0", "1e6", "2e6", "3e6"]
        );
        assert_eq!(
            labels(&Ticks::linear(0.0, 300_000.0, 4)),
            ["0", "100000", "200000", "300000"]
        );
    }

    #[test]
    fn log_axes_tick_at_1_2_5_and_narrow_ones_fall_back_to_linear() {
        assert_eq!(
            labels(&Ticks::log(0.8, 24.0, 10)),
            ["1", "2", "5", "10", "20"]
        );
        assert_eq!(
            labels(&Ticks::log(0.05, 3.0, 10)),
            ["0.05", "0.1", "0.2", "0.5", "1", "2"]
        );
        assert_eq!(labels(&Ticks::log(0.8, 2.4, 10)), ["1", "1.5", "2"]);
        assert_eq!(
            labels(&Ticks::log(1.0, 1e4, 5)),
            ["1", "10", "100", "1000", "10000"]
        );
        assert!(Ticks::log(0.0, 1.0, 5).values().is_empty());
        assert_eq!(Ticks::log_minor(0.8, 3.0), [0.8, 0.9, 1.0, 2.0, 3.0]);
    }

    #[test]
    fn labels_off_the_grid_and_degenerate_ranges_stay_readable() {
        let t = Ticks::linear(0.0, 1.0, 6);
        assert_eq!(t.label(-1e-17), "0", "never -0");
        assert_eq!(t.label(0.6000000000000001), "0.6");
        assert_eq!(labels(&Ticks::linear(2.5, 2.5, 5)), ["2.5"]);
        assert!(Ticks::linear(f64::NAN, 1.0, 5).values().is_empty());
        assert!(Ticks::linear(0.0, f64::INFINITY, 5).values().is_empty());
    }

    #[test]
    fn titles_carry_the_unit() {
        assert_eq!(axis_title("pitch", "rad"), "pitch (rad)");
        assert_eq!(axis_title("time", "s"), "time (s)");
        assert_eq!(axis_title("y0", "1"), "y0");
        assert_eq!(axis_title("ratio", ""), "ratio");
    }
}

//! Estimators of the lumped term `F` of the ultra-local model `y^(n) = F + alpha u`.
//!
//! # The algebraic kernels
//! Multiply the model by a weight `w(σ)` that vanishes (with its first `n-1` derivatives) at
//! both ends of a window `[0, T]` and integrate by parts: the unknown initial conditions drop
//! out and, for a constant `F`,
//!
//! * n = 1, `w = σ(T-σ)`:
//!   `F = -(6/T³) ∫₀ᵀ [ (T-2σ) y(σ) + α σ(T-σ) u(σ) ] dσ`
//! * n = 2, `w = σ²(T-σ)²`:
//!   `F = (60/T⁵) ∫₀ᵀ [ (T²-6Tσ+6σ²) y(σ) - (α/2) σ²(T-σ)² u(σ) ] dσ`
//!
//! with σ measured from the oldest sample of the window. Both are weighted averages of `F`
//! over the window with a symmetric non-negative weight, so they lag by about `T/2`, and the
//! integral filters noise.
//!
//! # Discretisation that follows the real timestamps
//! A digital loop holds `u` constant between samples (zero-order hold). Under the ultra-local
//! model `y` is then exactly piecewise linear between samples for n = 1, and piecewise
//! quadratic with curvature `F + α u_k` for n = 2. The estimator integrates the weights
//! against exactly that signal, interval by interval, whatever the interval lengths are:
//! linear interpolation of `y`, plus, for n = 2, the curvature correction
//! `-(F + α u_k)/2 · (t-a)(b-t)`, whose `F` part moves to the left-hand side. The result is
//! exact to rounding for constant `F` and *any* spacing, so a lost sample (a longer interval)
//! does not bias the estimate. On ten samples of a constant `F` (with `u = 0`) the trapezoid rule is
//! off by 2.5 % (n = 1) and 25 % (n = 2); these weights are not.
//!
//! # Cost independent of the window
//! The kernels are polynomials in σ, so each interval contributes fixed "moments"
//! `∫ s^j y`, `∫ s^j u`, ... about an anchor time. The estimator keeps running sums of these
//! (add the newest interval, subtract the evicted one) and re-expands the kernel about the
//! window start with a handful of binomial terms. Floating-point drift from subtracting is
//! bounded by rebuilding: a *shadow* sum starts fresh every window (about the running sum's
//! anchor, so that each interval's moments are computed once) and replaces the running one,
//! moved to the window's start, once it covers exactly the window. No sum is ever older than
//! two windows, no anchor further than two windows from the data, and each step costs the
//! same, with no periodic O(window) spike.
//!
//! # Other forms
//! * [`EstimatorKind::ClosedLoop`]: `F = [y(t) - y(t-T) - α ∫ u_applied] / T` (n = 1). This is
//!   the non-circular reading of the paper's closed-loop formula: it uses the *measured*
//!   output and the *applied* input. Read literally with the computed iP output, that formula
//!   is an identity and `F_est` never moves (see the tests).
//! * [`EstimatorKind::LowPass`]: the minimal exact kernel (one interval for n = 1, two for
//!   n = 2) followed by a first-order low-pass filter, as the paper allows ("this integral ...
//!   may be replaced in practice by a classic digital linear filter").

use crate::error::{finite, positive, MfcError, Result};
use crate::Order;

/// Default storage capacity of an estimator window, in sample intervals.
///
/// 256 intervals is 2.56 s at the AERO's 10 ms period, longer than any useful MFC window.
/// It bounds the window; with an allocator the ring holds only the window's intervals, and a
/// microcontroller build (no allocator, the ring inline) picks a smaller `CAP`.
pub const DEFAULT_CAPACITY: usize = 256;

/// Which estimator of `F` to run.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(
    feature = "serde",
    serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)
)]
#[cfg_attr(feature = "snapshot", derive(bincode::Encode, bincode::Decode))]
pub enum EstimatorKind {
    /// The algebraic kernel over a sliding window (the default).
    Algebraic,
    /// `[y(t) - y(t-T) - α ∫ u_applied] / T`, n = 1 only.
    ClosedLoop,
    /// Minimal exact kernel then a first-order low-pass filter.
    LowPass {
        /// Filter time constant in seconds (> 0).
        time_constant: f64,
    },
}

/// Configuration of an [`Estimator`].
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "serde", serde(default, deny_unknown_fields))]
#[cfg_attr(feature = "snapshot", derive(bincode::Encode, bincode::Decode))]
pub struct EstimatorConfig {
    /// Estimator form. Default: algebraic.
    pub kind: EstimatorKind,
    /// Window length in sample intervals (a window of `N` intervals holds `N + 1` samples).
    /// Default: 10 (100 ms at 10 ms): noise gain about 11 per unit of output noise for n = 1.
    pub window: usize,
    /// An interval longer than this (seconds) restarts the window: after an outage the
    /// zero-order-hold assumption across the gap is no longer credible. Default: infinite
    /// (never restart), which keeps the estimator exact for the ultra-local model.
    pub max_interval: f64,
    /// While the estimator's first window fills, answer from this many intervals on, over
    /// the samples there are, instead of not at all. Default 0: no answer before `window`
    /// intervals, so the controller holds its start value for a whole window; a plant that
    /// moves meanwhile (an arm sagging under a load) goes uncorrected. A shorter window's
    /// estimate is noisier (for n = 2 the noise gain grows as the window's inverse square),
    /// which the `estimate_filter` of an intelligent controller smooths. At least the
    /// order's minimal kernel (1 interval for n = 1, 2 for n = 2), at most `window`; the
    /// algebraic and closed-loop forms only.
    ///
    /// The first window only: after a gap, a [`Estimator::reset`] or a restart from a
    /// snapshot, the whole window again. At a start the input over the short window is the
    /// controller's own held value; after a gap it is another law's (the plant's fallback,
    /// whose input moves every sample), and five intervals of it gave the AERO's pitch an
    /// estimate of F of 4.4 where it was -0.3, and a pitch error of 0.15 rad once control
    /// resumed (`mfc-lab`'s `restart_from_a_snapshot_resumes_without_a_swing`).
    pub first_window: usize,
}

impl Default for EstimatorConfig {
    fn default() -> Self {
        Self {
            kind: EstimatorKind::Algebraic,
            window: 10,
            max_interval: f64::INFINITY,
            first_window: 0,
        }
    }
}

impl EstimatorConfig {
    /// Check the configuration against a storage capacity and a model order.
    pub fn validate(&self, order: Order, capacity: usize) -> Result<()> {
        let min = order.min_intervals();
        if self.max_interval.is_nan() || self.max_interval <= 0.0 {
            return Err(MfcError::InvalidParameter {
                name: "max_interval",
                value: self.max_interval,
                reason: "must be > 0 (or infinite)",
            });
        }
        match self.kind {
            EstimatorKind::LowPass { time_constant } => {
                positive("time_constant", time_constant)?;
                if self.first_window != 0 {
                    return Err(MfcError::InvalidParameter {
                        name: "first_window",
                        value: self.first_window as f64,
                        reason: "the low-pass form answers after its minimal kernel already",
                    });
                }
                if capacity < min {
                    return Err(MfcError::WindowTooLong { len: min, capacity });
                }
                Ok(())
            }
            EstimatorKind::ClosedLoop if order == Order::Two => {
                Err(MfcError::UnsupportedEstimatorOrder)
            }
            EstimatorKind::ClosedLoop | EstimatorKind::Algebraic => {
                if self.window < min {
                    return Err(MfcError::WindowTooShort {
                        len: self.window,
                        min,
                        order,
                    });
                }
                if self.window > capacity {
                    return Err(MfcError::WindowTooLong {
                        len: self.window,
                        capacity,
                    });
                }
                self.validate_first_window(min)
            }
        }
    }

    fn validate_first_window(&self, min: usize) -> Result<()> {
        let w = self.first_window;
        if w == 0 || (min..=self.window).contains(&w) {
            return Ok(());
        }
        Err(MfcError::InvalidParameter {
            name: "first_window",
            value: w as f64,
            reason: if w < min {
                "must be 0 (off) or at least the order's minimal kernel (1 interval for n = 1, 2 for n = 2)"
            } else {
                "must be at most `window`"
            },
        })
    }

    /// Intervals the window holds for this configuration.
    pub(crate) fn intervals(&self) -> usize {
        match self.kind {
            // Two intervals serve both orders' minimal kernels.
            EstimatorKind::LowPass { .. } => 2,
            _ => self.window,
        }
    }
}

/// An estimate of `F` kept linear in `alpha`: `F = base + alpha * per_alpha`.
///
/// Keeping the two parts apart lets a controller evaluate `F` for a new `alpha` on the same
/// data, which is what makes a change of `alpha` bumpless.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "snapshot", derive(bincode::Encode, bincode::Decode))]
pub struct LinearEstimate {
    /// Part of `F_est` that comes from the output `y`.
    pub base: f64,
    /// Coefficient of `alpha`, from the applied input `u`.
    pub per_alpha: f64,
}

impl LinearEstimate {
    /// `F_est` for a given `alpha`.
    #[inline]
    pub fn at(&self, alpha: f64) -> f64 {
        self.base + alpha * self.per_alpha
    }

    /// One step of a first-order low-pass: the fraction `k` of the way to `target`, on
    /// both parts (so that a change of `alpha` stays exact).
    #[inline]
    pub(crate) fn toward(self, target: Self, k: f64) -> Self {
        Self {
            base: self.base + k * (target.base - self.base),
            per_alpha: self.per_alpha + k * (target.per_alpha - self.per_alpha),
        }
    }

    /// `self - other`, part by part.
    #[inline]
    pub(crate) fn minus(self, other: Self) -> Self {
        Self {
            base: self.base - other.base,
            per_alpha: self.per_alpha - other.per_alpha,
        }
    }

    /// Both parts finite.
    #[inline]
    pub(crate) fn is_finite(&self) -> bool {
        self.base.is_finite() && self.per_alpha.is_finite()
    }
}

/// Constants multiplied by, not divided by: a division by a constant stays a division (the
/// product with its reciprocal rounds otherwise), and a step computes the moments of two
/// intervals and a kernel.
const THIRD: f64 = 1.0 / 3.0;
const SIXTH: f64 = 1.0 / 6.0;
const THIRTIETH: f64 = 1.0 / 30.0;

/// One zero-order-hold interval `[a, b]`: output samples at both ends and the input the
/// plant actually received in between.
#[derive(Debug, Clone, Copy, Default)]
#[cfg_attr(feature = "snapshot", derive(bincode::Encode, bincode::Decode))]
pub(crate) struct Interval {
    pub(crate) a: f64,
    pub(crate) b: f64,
    pub(crate) ya: f64,
    pub(crate) yb: f64,
    pub(crate) u: f64,
}

/// A sample of the window, and the input the plant received from it until the next: the
/// start of one interval, whose end is the next slot's sample (or, for the newest, the
/// estimator's last). Consecutive intervals share their ends, so the ring keeps each
/// number once: 24 bytes an interval where the intervals themselves took 40 (a service
/// holds ten thousand rings, `docs/scale.md`, "Memory per plant").
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Slot {
    pub(crate) t: f64,
    pub(crate) y: f64,
    pub(crate) u: f64,
}

impl Slot {
    /// The interval from this slot's sample to `(b, yb)`.
    #[inline(always)]
    pub(crate) fn to(self, (b, yb): (f64, f64)) -> Interval {
        Interval {
            a: self.t,
            b,
            ya: self.y,
            yb,
            u: self.u,
        }
    }
}

impl From<Interval> for Slot {
    fn from(iv: Interval) -> Self {
        Slot {
            t: iv.a,
            y: iv.ya,
            u: iv.u,
        }
    }
}

/// Moments of one or more intervals about an anchor time `c` (`s = t - c`).
#[derive(Debug, Clone, Copy, Default)]
#[cfg_attr(feature = "snapshot", derive(bincode::Encode, bincode::Decode))]
pub(crate) struct Moments {
    /// `∫ s^j y(t) dt`, y linearly interpolated, j = 0..2.
    y: [f64; 3],
    /// `∫ s^j u(t) dt`, j = 0..4.
    u: [f64; 5],
    /// `∫ s^j (t-a)(b-t) dt` per interval (curvature bubble), j = 0..2.
    k: [f64; 3],
    /// `∫ s^j u_k (t-a)(b-t) dt`, j = 0..2.
    ku: [f64; 3],
}

impl Moments {
    /// The moments of one interval in closed form. With `s = m + r x` (`m` the interval's
    /// middle about the anchor, `r` its half-width, `x` in `[-1, 1]`), `y = ȳ + (Δy/2) x`
    /// and the bubble `r²(1 - x²)`, every integral is a short polynomial in `m` and `r`:
    /// exact, as the three-point Gauss-Legendre rule this replaces was, in fewer operations
    /// (a step evaluates it twice: the interval that leaves the window and the one that
    /// joins it). For `order` one, only the five its kernel reads (`y` to j = 1, `u` to
    /// j = 2), the others left at 0; each computed as for order two, to the bit.
    #[inline(always)]
    fn of(iv: &Interval, anchor: f64, order: Order) -> Self {
        let h = iv.b - iv.a;
        let r = 0.5 * h;
        let m = iv.a - anchor + r;
        let (m2, r2) = (m * m, r * r);
        let mean = 0.5 * (iv.ya + iv.yb);
        let dy = iv.yb - iv.ya;
        // ∫ s^j ds, j = 0..4.
        let p2 = m2 + r2 * THIRD;
        if order == Order::One {
            return Moments {
                y: [h * mean, h * (m * mean + r * dy * SIXTH), 0.0],
                u: [h * iv.u, h * m * iv.u, h * p2 * iv.u, 0.0, 0.0],
                k: [0.0; 3],
                ku: [0.0; 3],
            };
        }
        let ps = [
            h,
            h * m,
            h * p2,
            h * m * (m2 + r2),
            h * (m2 * m2 + 2.0 * m2 * r2 + r2 * r2 / 5.0),
        ];
        let y = [
            h * mean,
            h * (m * mean + r * dy * SIXTH),
            h * (mean * p2 + m * r * dy * THIRD),
        ];
        let hr2 = h * r2;
        let k = [
            hr2 * (2.0 / 3.0),
            hr2 * m * (2.0 / 3.0),
            hr2 * (2.0 * m2 / 3.0 + 2.0 * r2 / 15.0),
        ];
        Moments {
            y,
            u: ps.map(|p| p * iv.u),
            k,
            ku: k.map(|k| k * iv.u),
        }
    }

    /// The same moments about an anchor `delta` later: with `s' = s - delta`,
    /// `∫ s'^j = Σ_i C(j, i) (-delta)^(j-i) ∫ s^i` (once per window, on a sum over one window,
    /// so its rounding does not accumulate).
    fn shifted(&self, delta: f64) -> Self {
        const BINOMIAL: [[f64; 5]; 5] = [
            [1.0, 0.0, 0.0, 0.0, 0.0],
            [1.0, 1.0, 0.0, 0.0, 0.0],
            [1.0, 2.0, 1.0, 0.0, 0.0],
            [1.0, 3.0, 3.0, 1.0, 0.0],
            [1.0, 4.0, 6.0, 4.0, 1.0],
        ];
        let d = -delta;
        let powers = [1.0, d, d * d, d * d * d, d * d * d * d];
        fn shift<const N: usize>(m: &[f64; N], powers: &[f64; 5]) -> [f64; N] {
            core::array::from_fn(|j| (0..=j).map(|i| BINOMIAL[j][i] * powers[j - i] * m[i]).sum())
        }
        Moments {
            y: shift(&self.y, &powers),
            u: shift(&self.u, &powers),
            k: shift(&self.k, &powers),
            ku: shift(&self.ku, &powers),
        }
    }

    /// Add `sign` times `o`: for `order` one, only the sums its kernel reads.
    #[inline(always)]
    fn add(&mut self, o: &Moments, sign: f64, order: Order) {
        if order == Order::One {
            for j in 0..2 {
                self.y[j] += sign * o.y[j];
            }
            for j in 0..3 {
                self.u[j] += sign * o.u[j];
            }
            return;
        }
        for j in 0..3 {
            self.y[j] += sign * o.y[j];
            self.k[j] += sign * o.k[j];
            self.ku[j] += sign * o.ku[j];
        }
        for j in 0..5 {
            self.u[j] += sign * o.u[j];
        }
    }

    /// Evaluate the kernel of `order` for a window `[t0, t0 + big_t]` whose moments about
    /// `anchor` are `self`.
    #[inline]
    fn kernel(&self, order: Order, t0: f64, big_t: f64, anchor: f64) -> LinearEstimate {
        let d = t0 - anchor;
        let t = big_t;
        match order {
            Order::One => {
                // ∫(T-2σ) y dσ and ∫σ(T-σ) u dσ with σ = s - d.
                let g = t + 2.0 * d;
                let yint = g * self.y[0] - 2.0 * self.y[1];
                let uint = -self.u[2] + g * self.u[1] - d * (t + d) * self.u[0];
                let c = -6.0 / (t * t * t);
                LinearEstimate {
                    base: c * yint,
                    per_alpha: c * uint,
                }
            }
            Order::Two => {
                // p(σ) = T² - 6Tσ + 6σ² re-expanded in s.
                let p0 = t * t + 6.0 * t * d + 6.0 * d * d;
                let p1 = -(6.0 * t + 12.0 * d);
                let a = 6.0 * self.y[2] + p1 * self.y[1] + p0 * self.y[0];
                let pk = 6.0 * self.k[2] + p1 * self.k[1] + p0 * self.k[0];
                let pku = 6.0 * self.ku[2] + p1 * self.ku[1] + p0 * self.ku[0];
                // q(σ) = σ²(T-σ)² = (-s² + g s - m)², g = T + 2d, m = d (T + d).
                let g = t + 2.0 * d;
                let m = d * (t + d);
                let q = self.u[4] - 2.0 * g * self.u[3] + (g * g + 2.0 * m) * self.u[2]
                    - 2.0 * g * m * self.u[1]
                    + m * m * self.u[0];
                let t5 = t * t * t * t * t;
                // One division, of times alone (the bubble's moments are the samples'
                // times'), where two would wait for the data.
                let inv = 1.0 / (t5 * THIRTIETH + pk);
                LinearEstimate {
                    base: 2.0 * a * inv,
                    per_alpha: -(pku + q) * inv,
                }
            }
        }
    }
}

/// A running sum of moments about a fixed anchor, covering intervals from index `first` on.
#[derive(Debug, Clone, Copy, Default)]
#[cfg_attr(feature = "snapshot", derive(bincode::Encode, bincode::Decode))]
pub(crate) struct Accumulator {
    anchor: f64,
    pub(crate) first: u64,
    pub(crate) active: bool,
    sums: Moments,
}

impl Accumulator {
    fn start(index: u64, anchor: f64) -> Self {
        Self {
            anchor,
            first: index,
            active: true,
            sums: Moments::default(),
        }
    }
}

/// Estimator of `F` over a sliding window of at most `CAP` sample intervals.
///
/// Feed it every sample with [`push`](Self::push), giving the input the plant *actually*
/// received since the previous sample (after dead-zone mapping and saturation, or the held
/// command when a new one was lost), then ask for [`estimate`](Self::estimate). `push`
/// and `estimate` allocate nothing and cost the same whatever the window length (an
/// estimate for the order the running sums do not serve excepted: see [`Estimator::new`]).
///
/// The ring holds the window's intervals, each as the sample that starts it and the input
/// that followed (a `Slot`: the next slot's sample, or the last, ends it). With an
/// allocator (the `alloc` feature) it is exactly the window's length on the heap,
/// allocated once at creation: a service holding ten thousand estimators of a 10-interval
/// window keeps 240 bytes for each, not the capacity's 6 KiB (`docs/scale.md`, "Memory per
/// plant"). Without one it is `CAP` slots inline, laid out last (`repr(C)`), of which a
/// step touches only the window's. `CAP` bounds the window either way.
#[derive(Debug, Clone)]
#[repr(C)]
pub struct Estimator<const CAP: usize = DEFAULT_CAPACITY> {
    pub(crate) config: EstimatorConfig,
    pub(crate) head: usize,
    pub(crate) len: usize,
    pub(crate) next_index: u64,
    pub(crate) last: Option<(f64, f64)>,
    pub(crate) primary: Accumulator,
    pub(crate) shadow: Accumulator,
    /// Low-pass states for n = 1 and n = 2 (both kept so the order can change live).
    pub(crate) lowpass: [Option<LinearEstimate>; 2],
    /// The order whose kernel the running sums serve: order one reads 5 of the 14, and a
    /// step updates only those (an estimate for the other order is still exact, from the
    /// ring, at a window's cost; [`Estimator::serve`] changes it).
    pub(crate) order: Order,
    pub(crate) ring: Ring<CAP>,
}

/// The ring's storage: the window's length on the heap with an allocator, `CAP` inline
/// without (see [`Estimator`]).
#[cfg(feature = "alloc")]
pub(crate) type Ring<const CAP: usize> = alloc::boxed::Box<[Slot]>;
#[cfg(not(feature = "alloc"))]
pub(crate) type Ring<const CAP: usize> = [Slot; CAP];

/// A ring of `slots` empty slots (at most `CAP`, checked by the caller).
pub(crate) fn empty_ring<const CAP: usize>(slots: usize) -> Ring<CAP> {
    #[cfg(feature = "alloc")]
    {
        alloc::vec![Slot::default(); slots].into_boxed_slice()
    }
    #[cfg(not(feature = "alloc"))]
    {
        let _ = slots;
        [Slot::default(); CAP]
    }
}

impl<const CAP: usize> Estimator<CAP> {
    /// A new, empty estimator. The configuration is checked for `order`, whose kernel the
    /// running sums serve; an estimate for the other order is exact too, computed from the
    /// window's intervals (see [`Estimator::serve`]).
    pub fn new(config: EstimatorConfig, order: Order) -> Result<Self> {
        config.validate(order, CAP)?;
        Ok(Self {
            config,
            ring: empty_ring::<CAP>(slots(&config, CAP)),
            head: 0,
            len: 0,
            next_index: 0,
            last: None,
            primary: Accumulator::default(),
            shadow: Accumulator::default(),
            lowpass: [None, None],
            order,
        })
    }

    /// Keep the running sums for `order`'s kernel from now on (a controller changing its
    /// model's order): they are summed again from the window's intervals, at a window's
    /// cost, once.
    pub fn serve(&mut self, order: Order) {
        if order == self.order {
            return;
        }
        self.order = order;
        self.primary.sums = self.moments(0, self.primary.anchor, order);
        self.shadow.sums = if self.shadow.active {
            // The shadow started inside the window (a decoded state is checked for it).
            let oldest = self.next_index - self.len as u64;
            let from = (self.shadow.first - oldest) as usize;
            self.moments(from, self.shadow.anchor, order)
        } else {
            Moments::default()
        };
    }

    /// The moments of `order`'s kernel over the window's intervals from the `from`-th on,
    /// about `anchor`: summed afresh, at a window's cost.
    fn moments(&self, from: usize, anchor: f64, order: Order) -> Moments {
        let mut m = Moments::default();
        for k in from..self.len {
            m.add(&Moments::of(&self.interval(k), anchor, order), 1.0, order);
        }
        m
    }

    /// The configuration.
    pub fn config(&self) -> &EstimatorConfig {
        &self.config
    }

    /// Samples currently in the window.
    pub fn samples(&self) -> usize {
        if self.last.is_some() {
            self.len + 1
        } else {
            0
        }
    }

    /// Timestamp of the newest sample, if any.
    pub fn last_time(&self) -> Option<f64> {
        self.last.map(|(t, _)| t)
    }

    /// Forget all samples (for example after a long outage).
    pub fn reset(&mut self) {
        self.last = None;
        self.clear_window();
    }

    fn clear_window(&mut self) {
        self.head = 0;
        self.len = 0;
        self.primary = Accumulator::default();
        self.shadow = Accumulator::default();
        self.lowpass = [None, None];
    }

    /// Check a sample without changing anything.
    pub fn check(&self, t: f64, y: f64, u_applied: f64) -> Result<()> {
        finite("time", t)?;
        finite("measurement", y)?;
        finite("applied input", u_applied)?;
        if let Some((previous, _)) = self.last {
            if t <= previous {
                return Err(MfcError::TimeNotAdvancing {
                    previous,
                    current: t,
                });
            }
        }
        Ok(())
    }

    /// Add the sample `y` taken at time `t`. `u_applied` is the input the plant received
    /// over the interval from the previous sample to `t` (ignored for the first sample).
    ///
    /// On error nothing changes.
    pub fn push(&mut self, t: f64, y: f64, u_applied: f64) -> Result<()> {
        self.check(t, y, u_applied)?;
        self.record(t, y, u_applied);
        Ok(())
    }

    /// [`push`](Self::push) of a sample already checked (by [`check`](Self::check)).
    #[inline]
    pub(crate) fn record(&mut self, t: f64, y: f64, u_applied: f64) {
        let Some((a, ya)) = self.last.replace((t, y)) else {
            return;
        };
        if t - a > self.config.max_interval {
            // Too long a gap: start a fresh window at this sample.
            self.clear_window();
            return;
        }
        // One copy of the window's update per order, each with its moments' order fixed.
        // The interval goes as its five numbers, in registers: built here and read there
        // through memory, its halves were loaded wider than they had just been stored,
        // which stalls the load (no store forwarding) on every step.
        match self.order {
            Order::One => self.slide::<true>(a, t, ya, y, u_applied),
            Order::Two => self.slide::<false>(a, t, ya, y, u_applied),
        }
        if let EstimatorKind::LowPass { time_constant } = self.config.kind {
            self.update_lowpass(time_constant);
        }
    }

    /// Ring slots in use: the window's intervals, not the whole capacity, so that a
    /// service holding thousands of estimators touches (and keeps resident) only a
    /// window's worth of memory for each, and a step stays in a few cache lines.
    fn slots(&self) -> usize {
        // With an allocator the ring is exactly the window's slots: its length says so
        // without a look at the configuration, and bounds the indices it is read with.
        #[cfg(feature = "alloc")]
        {
            self.ring.len()
        }
        #[cfg(not(feature = "alloc"))]
        {
            slots(&self.config, CAP)
        }
    }

    fn wrap(&self, i: usize) -> usize {
        wrap(i, self.slots())
    }

    /// Ask the processor for the ring's slots the next [`Self::record`] reads and writes
    /// once the window is full (the oldest, which the newest interval then takes, and
    /// the one after it, the window's new start), without reading them. The ring is on the heap, so a caller that holds many estimators
    /// (a service's ten thousand devices) can start the fetch early, and overlap it with
    /// other work, where a step's own read would wait for it. On x86_64; elsewhere nothing.
    #[cfg(feature = "alloc")]
    #[inline]
    pub(crate) fn prefetch(&self) {
        #[cfg(target_arch = "x86_64")]
        {
            use core::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
            let n = self.slots();
            if n == 0 || self.head >= n {
                return;
            }
            for i in [self.head, self.wrap(self.head + 1)] {
                let at = core::ptr::from_ref(&self.ring[i]).cast::<i8>();
                // SAFETY: a prefetch is a hint that reads nothing and never faults, and
                // SSE (its target feature) is part of every x86_64.
                unsafe { _mm_prefetch::<_MM_HINT_T0>(at) };
            }
        }
    }

    /// `iv` joins the window, and the oldest interval leaves it if it is full; the running
    /// sums are order one's (`ONE`) or order two's.
    fn slide<const ONE: bool>(&mut self, a: f64, b: f64, ya: f64, yb: f64, u: f64) {
        let iv = Interval { a, b, ya, yb, u };
        let order = if ONE { Order::One } else { Order::Two };
        if self.len == self.config.intervals() {
            self.evict((a, ya), order);
        }
        self.insert(iv, order);
    }

    /// The oldest interval leaves the window; `newest_end` is the sample that ends the
    /// newest interval (the last one before the sample being taken in).
    #[inline(always)]
    fn evict(&mut self, newest_end: (f64, f64), order: Order) {
        let old = self.interval_ending(0, newest_end);
        let m = Moments::of(&old, self.primary.anchor, order);
        self.primary.sums.add(&m, -1.0, order);
        let next = self.head + 1;
        self.head = if next == self.slots() { 0 } else { next };
        self.len -= 1;
    }

    #[inline(always)]
    fn insert(&mut self, iv: Interval, order: Order) {
        let index = self.next_index;
        self.next_index += 1;
        let slot = self.wrap(self.head + self.len);
        self.ring[slot] = iv.into();
        self.len += 1;
        if self.len == 1 {
            self.primary = Accumulator::start(index, iv.a);
        }
        if !self.shadow.active {
            self.shadow = Accumulator::start(index, self.primary.anchor);
        }
        // The shadow sums about the primary's anchor, so one interval's moments serve both
        // (a decoded state is brought to that: `align_shadow`).
        let m = Moments::of(&iv, self.primary.anchor, order);
        self.primary.sums.add(&m, 1.0, order);
        self.shadow.sums.add(&m, 1.0, order);
        // Once the shadow covers exactly the window, it replaces the running sum: this
        // bounds the floating-point drift of add-and-subtract to one window's worth. It
        // moves to the window's start as it does, so that the anchor follows the data.
        let oldest = self.next_index - self.len as u64;
        if oldest == self.shadow.first {
            let start = self.ring[self.head].t;
            self.primary = Accumulator {
                anchor: start,
                sums: self.shadow.sums.shifted(start - self.shadow.anchor),
                ..self.shadow
            };
            self.shadow.active = false;
        }
    }

    /// The window's start and end times (`len > 0`): the oldest interval's start, at the
    /// head (below the slots, so no wrap), and the newest sample's time, which ends the
    /// newest interval (a decoded state is checked for it).
    #[inline]
    fn span(&self) -> (f64, f64) {
        let t1 = self.last.map_or(f64::NAN, |(t, _)| t);
        (self.ring[self.head].t, t1)
    }

    /// Move a decoded shadow's sums to the primary's anchor, which a step assumes it
    /// shares: nothing here writes another, but a state decoded from elsewhere may hold
    /// one, and its sums are then moved, never mixed.
    #[cfg(feature = "snapshot")]
    pub(crate) fn align_shadow(&mut self) {
        if self.shadow.active && self.shadow.anchor != self.primary.anchor {
            self.shadow.sums = self
                .shadow
                .sums
                .shifted(self.primary.anchor - self.shadow.anchor);
            self.shadow.anchor = self.primary.anchor;
        }
    }

    /// The window's `k`-th interval, oldest first (`k < len`), the newest ending at the
    /// last sample.
    pub(crate) fn interval(&self, k: usize) -> Interval {
        self.interval_ending(k, self.last.unwrap_or_default())
    }

    /// The window's `k`-th interval, the newest ending at `newest_end`: it starts at its
    /// slot and ends at the next one's sample.
    #[inline(always)]
    fn interval_ending(&self, k: usize, newest_end: (f64, f64)) -> Interval {
        let start = self.ring[self.wrap(self.head + k)];
        let end = if k + 1 < self.len {
            let next = self.ring[self.wrap(self.head + k + 1)];
            (next.t, next.y)
        } else {
            newest_end
        };
        start.to(end)
    }

    fn update_lowpass(&mut self, time_constant: f64) {
        let newest = self.interval(self.len - 1);
        let h = newest.b - newest.a;
        let gain = 1.0 - libm::exp(-h / time_constant);
        for (slot, order) in [(0, Order::One), (1, Order::Two)] {
            let Some(raw) = self.minimal(order) else {
                continue;
            };
            self.lowpass[slot] = Some(match self.lowpass[slot] {
                None => raw,
                Some(prev) => prev.toward(raw, gain),
            });
        }
    }

    /// The exact kernel over the last `order.min_intervals()` intervals.
    fn minimal(&self, order: Order) -> Option<LinearEstimate> {
        let n = order.min_intervals();
        if self.len < n {
            return None;
        }
        let first = self.len - n;
        let anchor = self.interval(first).a;
        let m = self.moments(first, anchor, order);
        let t1 = self.interval(self.len - 1).b;
        Some(m.kernel(order, anchor, t1 - anchor, anchor))
    }

    /// The current estimate for a model of `order`, linear in `alpha`.
    ///
    /// `Err(NotReady)` until the window is full (`window` intervals; the minimal
    /// `order.min_intervals()` for the low-pass form), so the noise gain is always the
    /// configured one; with `first_window`, from that many intervals on, over the window
    /// there is, while the first window fills (no interval has left the window yet).
    #[inline]
    pub fn estimate(&self, order: Order) -> Result<LinearEstimate> {
        let need = match self.config.kind {
            EstimatorKind::LowPass { .. } => order.min_intervals(),
            _ if self.config.first_window > 0 && self.next_index == self.len as u64 => {
                self.config.first_window.max(order.min_intervals())
            }
            _ => self.config.window,
        };
        if self.len < need {
            return Err(MfcError::NotReady {
                have: self.samples(),
                need: need + 1,
            });
        }
        let (t0, t1) = self.span();
        match self.config.kind {
            EstimatorKind::Algebraic if order == Order::Two && self.order == Order::One => {
                // The running sums serve order one: order two's from the window itself.
                Ok(self.moments(0, t0, order).kernel(order, t0, t1 - t0, t0))
            }
            EstimatorKind::Algebraic => {
                Ok(self
                    .primary
                    .sums
                    .kernel(order, t0, t1 - t0, self.primary.anchor))
            }
            EstimatorKind::ClosedLoop => {
                if order == Order::Two {
                    return Err(MfcError::UnsupportedEstimatorOrder);
                }
                let big_t = t1 - t0;
                let dy = self.interval(self.len - 1).yb - self.interval(0).ya;
                Ok(LinearEstimate {
                    base: dy / big_t,
                    per_alpha: -self.primary.sums.u[0] / big_t,
                })
            }
            EstimatorKind::LowPass { .. } => {
                let slot = match order {
                    Order::One => 0,
                    Order::Two => 1,
                };
                self.lowpass[slot].ok_or(MfcError::NotReady {
                    have: self.samples(),
                    need: need + 1,
                })
            }
        }
    }
}

/// Ring slots for `config`'s window, with `cap` the most the ring may hold.
pub(crate) fn slots(config: &EstimatorConfig, cap: usize) -> usize {
    config.intervals().clamp(1, cap)
}

/// `i % n`, without the division in the usual case: every index the ring takes is below
/// twice its slots (a head inside them plus at most a window), and a 64-bit division was
/// a tenth of a control step.
fn wrap(i: usize, n: usize) -> usize {
    if i < n {
        i
    } else if i < 2 * n {
        i - n
    } else {
        i % n
    }
}

#[cfg(test)]
mod ring_tests {
    #[test]
    fn wrapping_is_the_remainder() {
        for n in 1..=12 {
            for i in 0..5 * n {
                assert_eq!(super::wrap(i, n), i % n, "{i} % {n}");
            }
        }
    }
}

#[cfg(all(test, feature = "snapshot"))]
mod decoded_tests {
    use super::{Estimator, EstimatorConfig, Order};
    use crate::snapshot::{from_bytes, to_bytes};

    fn pushed(e: &mut Estimator, k: u32) {
        let t = f64::from(k) * 0.01;
        e.push(t, (3.0 * t).sin(), 0.5 + 0.1 * t).unwrap();
    }

    /// A decoded shadow that sums about an anchor of its own (nothing here writes one) is
    /// moved to the running sum's anchor once, when decoded, since a step assumes they
    /// share it: the estimates then go on as the original's, through the shadow's
    /// replacing the running sum. Mixed instead of moved, they would not.
    #[test]
    fn a_decoded_shadow_about_its_own_anchor_is_moved_once() {
        let config = EstimatorConfig {
            window: 10,
            ..Default::default()
        };
        let mut e: Estimator = Estimator::new(config, Order::One).unwrap();
        for k in 0..26 {
            pushed(&mut e, k);
        }
        assert!(e.shadow.active, "the shadow is summing");
        let mut moved = e.clone();
        let delta = 0.037;
        moved.shadow.sums = moved.shadow.sums.shifted(delta);
        moved.shadow.anchor += delta;
        let mut decoded: Estimator = from_bytes(&to_bytes(&moved).unwrap()).unwrap();
        assert_eq!(decoded.shadow.anchor, decoded.primary.anchor);
        for k in 26..60 {
            pushed(&mut e, k);
            pushed(&mut decoded, k);
            let (a, b) = (
                e.estimate(Order::One).unwrap(),
                decoded.estimate(Order::One).unwrap(),
            );
            for (x, y) in [(a.base, b.base), (a.per_alpha, b.per_alpha)] {
                assert!(
                    (x - y).abs() <= 1e-9 * (1.0 + x.abs()),
                    "step {k}: {x} vs {y}"
                );
            }
        }
    }
}

//! Properties of the F estimators.

mod common;

use common::ultra_local;
use mfc::{Estimator, EstimatorConfig, EstimatorKind, MfcError, Order};
use proptest::prelude::*;

/// Irregular sample times: nominal period `h`, jitter of ±`jitter`·h, and lost samples
/// (a gap of 2 or 3 periods) wherever `gaps` says so.
fn times(h: f64, jitter: &[f64], gaps: &[u8]) -> Vec<f64> {
    let mut t = vec![0.0];
    for (j, g) in jitter.iter().zip(gaps) {
        let periods = match g % 8 {
            0 => 2.0,
            1 => 3.0,
            _ => 1.0,
        };
        let last = *t.last().unwrap();
        t.push(last + h * (periods + j));
    }
    t
}

fn order_of(n: u8) -> Order {
    if n == 1 {
        Order::One
    } else {
        Order::Two
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    /// Both kernels recover a constant F to rounding, for any alpha, window, period, jitter,
    /// lost samples and inputs, at every step once the window is full.
    #[test]
    fn algebraic_kernels_are_exact_for_constant_f(
        n in 1u8..=2,
        f in -50.0f64..50.0,
        alpha in prop_oneof![-20.0f64..-0.01, 0.01f64..20.0],
        window in 2usize..80,
        h in 0.001f64..0.05,
        seq in proptest::collection::vec((-0.3f64..0.3, any::<u8>(), -10.0f64..10.0), 120..300),
        y0 in -1.0f64..1.0,
        dy0 in -1.0f64..1.0,
    ) {
        let jitter: Vec<f64> = seq.iter().map(|s| s.0).collect();
        let gaps: Vec<u8> = seq.iter().map(|s| s.1).collect();
        let inputs: Vec<f64> = seq.iter().map(|s| s.2).collect();
        let t = times(h, &jitter, &gaps);
        let data = ultra_local(n, f, alpha, &t, &inputs, y0, dy0);
        let order = order_of(n);
        let cfg = EstimatorConfig { window, ..EstimatorConfig::default() };
        let mut est: Estimator = Estimator::new(cfg, order).unwrap();
        let scale = 1.0 + f.abs() + alpha.abs() * 10.0;
        for (k, &(t, y, u)) in data.iter().enumerate() {
            est.push(t, y, u).unwrap();
            match est.estimate(order) {
                Ok(e) => {
                    prop_assert!(k >= window);
                    let got = e.at(alpha);
                    prop_assert!((got - f).abs() <= 1e-6 * scale,
                        "step {k}: F_est = {got}, F = {f}");
                }
                Err(MfcError::NotReady { .. }) => prop_assert!(k < window),
                Err(other) => prop_assert!(false, "unexpected {other}"),
            }
        }
    }

    /// The closed-loop form is exact for constant F (n = 1) too, holes included.
    #[test]
    fn closed_loop_form_is_exact_for_constant_f(
        f in -50.0f64..50.0,
        alpha in prop_oneof![-20.0f64..-0.01, 0.01f64..20.0],
        window in 1usize..60,
        h in 0.001f64..0.05,
        seq in proptest::collection::vec((-0.3f64..0.3, any::<u8>(), -10.0f64..10.0), 100..200),
    ) {
        let jitter: Vec<f64> = seq.iter().map(|s| s.0).collect();
        let gaps: Vec<u8> = seq.iter().map(|s| s.1).collect();
        let inputs: Vec<f64> = seq.iter().map(|s| s.2).collect();
        let t = times(h, &jitter, &gaps);
        let data = ultra_local(1, f, alpha, &t, &inputs, 0.3, 0.0);
        let cfg = EstimatorConfig { kind: EstimatorKind::ClosedLoop, window, ..Default::default() };
        let mut est: Estimator = Estimator::new(cfg, Order::One).unwrap();
        for &(t, y, u) in &data {
            est.push(t, y, u).unwrap();
        }
        let got = est.estimate(Order::One).unwrap().at(alpha);
        prop_assert!((got - f).abs() <= 1e-6 * (1.0 + f.abs() + 10.0 * alpha.abs()));
    }

    /// A slowly varying F = B + A sin(w t) is followed within the kernel's lag: the
    /// estimate is a symmetric weighted mean of F over the window, so
    /// |F_est(t) - F(t)| <= sup|F'| (T/2 + h) = A w (T/2 + h), for n = 1 and n = 2.
    #[test]
    fn slowly_varying_f_within_lag_bound(
        n in 1u8..=2,
        a in 0.1f64..20.0,
        b in -10.0f64..10.0,
        w in 0.1f64..5.0,
        alpha in 0.1f64..5.0,
        window in 4usize..40,
        h in 0.002f64..0.02,
        inputs in proptest::collection::vec(-3.0f64..3.0, 300),
    ) {
        let order = order_of(n);
        let cfg = EstimatorConfig { window, ..Default::default() };
        let mut est: Estimator = Estimator::new(cfg, order).unwrap();
        let (mut y, mut dy) = (0.0, 0.0);
        let mut worst: f64 = 0.0;
        let mut t = 0.0;
        let mut u_prev = 0.0;
        let big_t = window as f64 * h;
        for &u in &inputs {
            est.push(t, y, u_prev).unwrap();
            if let Ok(e) = est.estimate(order) {
                let truth = b + a * (w * t).sin();
                worst = worst.max((e.at(alpha) - truth).abs());
            }
            // Exact propagation of y^(n) = B + A sin(w t) + alpha u over [t, t + h].
            let (c0, c1) = ((w * t).cos(), (w * (t + h)).cos());
            let (s0, s1) = ((w * t).sin(), (w * (t + h)).sin());
            let int1 = (b + alpha * u) * h + a / w * (c0 - c1);
            if n == 1 {
                y += int1;
            } else {
                y += dy * h + 0.5 * (b + alpha * u) * h * h + a / w * (h * c0) - a / (w * w) * (s1 - s0);
                dy += int1;
            }
            t += h;
            u_prev = u;
        }
        let bound = a * w * (big_t / 2.0 + h);
        prop_assert!(worst <= bound, "worst {worst} > bound {bound}");
    }
}

/// The estimator's cost does not grow with the window, and its running sums must not drift
/// either: after 200 000 steps (many shadow rebuilds) it is still exact.
#[test]
fn running_sums_do_not_drift() {
    for order in [Order::One, Order::Two] {
        let n = order.n();
        let cfg = EstimatorConfig {
            window: 37,
            ..Default::default()
        };
        let mut est: Estimator = Estimator::new(cfg, order).unwrap();
        let (f, alpha, h) = (2.5, 0.7, 0.01);
        let (mut y, mut dy) = (0.0, 0.0);
        let mut u_prev = 0.0;
        for k in 0..200_000u32 {
            let t = f64::from(k) * h;
            est.push(t, y, u_prev).unwrap();
            // Bounded pseudo-random input keeps y bounded (a crude P loop on y).
            let u = -(f + 3.0 * y + 2.0 * dy) / alpha + ((k * 7919) % 13) as f64 * 0.1;
            let acc = f + alpha * u;
            if n == 1 {
                y += h * acc;
            } else {
                y += h * dy + 0.5 * h * h * acc;
                dy += h * acc;
            }
            u_prev = u;
        }
        let got = est.estimate(order).unwrap().at(alpha);
        assert!((got - f).abs() < 1e-7, "{order:?}: {got}");
    }
}

/// The running sums serve one order (order one keeps 5 of the 14); the other order's
/// estimate is still exact, from the window's intervals, and `serve` hands the sums over to
/// it at any point of a window (the shadow sum half built or not): after as many steps
/// again, every estimator agrees with one built for that order from the start.
#[test]
fn the_sums_serve_one_order_and_change_with_it() {
    let cfg = EstimatorConfig {
        window: 12,
        ..Default::default()
    };
    let (h, alpha) = (0.01, 0.7);
    let sample = |k: u32| {
        let t = f64::from(k) * h;
        (t, (3.0 * t).sin() + 0.2 * t * t, (5.0 * t).cos())
    };
    let close = |a: mfc::LinearEstimate, b: mfc::LinearEstimate| {
        let (x, y) = (a.at(alpha), b.at(alpha));
        (x - y).abs() <= 1e-9 * (1.0 + y.abs())
    };
    for switch_at in [0u32, 5, 12, 17, 30] {
        let mut one: Estimator = Estimator::new(cfg, Order::One).unwrap();
        let mut two: Estimator = Estimator::new(cfg, Order::Two).unwrap();
        let mut moved: Estimator = Estimator::new(cfg, Order::One).unwrap();
        let mut back: Estimator = Estimator::new(cfg, Order::Two).unwrap();
        for k in 0..60u32 {
            if k == switch_at {
                moved.serve(Order::Two);
                back.serve(Order::One);
            }
            let (t, y, u) = sample(k);
            for e in [&mut one, &mut two, &mut moved, &mut back] {
                e.push(t, y, u).unwrap();
            }
            let (Ok(e1), Ok(e2)) = (one.estimate(Order::One), two.estimate(Order::Two)) else {
                continue;
            };
            let what = format!("switch at {switch_at}, step {k}");
            // Across orders, from the ring: as exact as the running sums.
            assert!(close(one.estimate(Order::Two).unwrap(), e2), "{what}");
            assert!(close(two.estimate(Order::One).unwrap(), e1), "{what}");
            for e in [&moved, &back] {
                assert!(close(e.estimate(Order::One).unwrap(), e1), "{what}");
                assert!(close(e.estimate(Order::Two).unwrap(), e2), "{what}");
            }
        }
    }
}

/// A gap longer than `max_interval` restarts the window instead of bridging it.
#[test]
fn long_gap_restarts_the_window() {
    let cfg = EstimatorConfig {
        window: 5,
        max_interval: 0.1,
        ..Default::default()
    };
    let mut est: Estimator = Estimator::new(cfg, Order::One).unwrap();
    for k in 0..10 {
        est.push(k as f64 * 0.01, 0.0, 0.0).unwrap();
    }
    assert!(est.estimate(Order::One).is_ok());
    est.push(1.0, 0.0, 0.0).unwrap();
    assert_eq!(est.samples(), 1);
    assert!(matches!(
        est.estimate(Order::One),
        Err(MfcError::NotReady { have: 1, need: 6 })
    ));
}

/// The low-pass form converges to a constant F and filters a noisy one.
#[test]
fn low_pass_form_converges() {
    for order in [Order::One, Order::Two] {
        let cfg = EstimatorConfig {
            kind: EstimatorKind::LowPass {
                time_constant: 0.05,
            },
            ..Default::default()
        };
        let mut est: Estimator = Estimator::new(cfg, order).unwrap();
        let times: Vec<f64> = (0..100).map(|k| k as f64 * 0.01).collect();
        let inputs: Vec<f64> = (0..100).map(|k| (k as f64 * 0.37).sin()).collect();
        let data = ultra_local(order.n(), -4.0, 1.5, &times, &inputs, 0.0, 0.0);
        for &(t, y, u) in &data {
            est.push(t, y, u).unwrap();
        }
        let got = est.estimate(order).unwrap().at(1.5);
        assert!((got + 4.0).abs() < 1e-9, "{order:?}: {got}");
    }
}

/// The trapezoid rule (as in the MATLAB reference implementation) is biased; the exact
/// weights are not. For n = 1 and y = F t the trapezoid's relative bias is 2/N² (2.5 % over
/// nine intervals); for n = 2 it is far worse.
#[test]
fn trapezoid_rule_is_biased_exact_weights_are_not() {
    let (f, alpha, h) = (1.3, 0.0, 0.01);
    let times: Vec<f64> = (0..10).map(|k| k as f64 * h).collect();
    let inputs = vec![0.0; 10];
    for (n, order) in [(1u8, Order::One), (2, Order::Two)] {
        let data = ultra_local(n, f, alpha, &times, &inputs, 0.0, 0.0);
        let big_t = 9.0 * h;
        // Trapezoid rule on the same kernel.
        let mut acc = 0.0;
        for (k, &(t, y, _)) in data.iter().enumerate() {
            let w = if k == 0 || k == 9 { 0.5 * h } else { h };
            let s = t;
            acc += w * if n == 1 {
                (big_t - 2.0 * s) * y
            } else {
                (big_t * big_t - 6.0 * big_t * s + 6.0 * s * s) * y
            };
        }
        let trap = if n == 1 {
            -6.0 / big_t.powi(3) * acc
        } else {
            60.0 / big_t.powi(5) * acc
        };
        let mut est: Estimator = Estimator::new(
            EstimatorConfig {
                window: 9,
                ..Default::default()
            },
            order,
        )
        .unwrap();
        for &(t, y, u) in &data {
            est.push(t, y, u).unwrap();
        }
        let exact = est.estimate(order).unwrap().at(alpha);
        assert!((exact - f).abs() < 1e-9, "n={n}: {exact}");
        assert!((trap - f).abs() > 0.01 * f, "n={n}: trapezoid {trap}");
        eprintln!("n={n}: exact weights {exact:.6}, trapezoid {trap:.6}, truth {f}");
    }
}

/// With `first_window`, the estimator answers from that many intervals on while its first
/// window fills, over the samples it has, and the answer is exact for a constant F there
/// too. Without it, nothing before the window is full.
#[test]
fn first_window_answers_early_and_exactly() {
    for (n, order) in [(1u8, Order::One), (2, Order::Two)] {
        let (f, alpha, h) = (-3.5, 0.4, 0.01);
        let t: Vec<f64> = (0..40).map(|k| f64::from(k) * h).collect();
        let inputs: Vec<f64> = (0..40).map(|k| f64::from(k % 7) - 3.0).collect();
        let data = ultra_local(n, f, alpha, &t, &inputs, 0.2, -0.5);
        let cfg = EstimatorConfig {
            window: 20,
            first_window: 4,
            ..EstimatorConfig::default()
        };
        let mut early: Estimator = Estimator::new(cfg, order).unwrap();
        let mut late: Estimator = Estimator::new(
            EstimatorConfig {
                first_window: 0,
                ..cfg
            },
            order,
        )
        .unwrap();
        for (k, &(t, y, u)) in data.iter().enumerate() {
            early.push(t, y, u).unwrap();
            late.push(t, y, u).unwrap();
            // k intervals after sample k.
            match early.estimate(order) {
                Ok(e) => {
                    assert!(k >= 4, "{order:?}: an answer after {k} intervals");
                    let got = e.at(alpha);
                    assert!(
                        (got - f).abs() < 1e-6 * (1.0 + f.abs()),
                        "{order:?} k={k}: {got}"
                    );
                }
                Err(MfcError::NotReady { .. }) => assert!(k < 4, "{order:?}: none after {k}"),
                Err(e) => panic!("{e}"),
            }
            assert_eq!(late.estimate(order).is_ok(), k >= 20, "{order:?} k={k}");
        }
    }
}

/// After a gap that restarts the window, or a reset, `first_window` no longer applies: the
/// plant was under another law meanwhile, so the estimator waits for the whole window.
#[test]
fn first_window_is_for_the_first_window_only() {
    let cfg = EstimatorConfig {
        window: 10,
        first_window: 3,
        max_interval: 0.1,
        ..Default::default()
    };
    let ready_after = |est: &mut Estimator, t0: f64| {
        (1..=10)
            .find(|k| {
                est.push(t0 + f64::from(*k) * 0.01, 0.0, 0.0).unwrap();
                est.estimate(Order::Two).is_ok()
            })
            .unwrap()
    };
    let mut est: Estimator = Estimator::new(cfg, Order::Two).unwrap();
    est.push(0.0, 0.0, 0.0).unwrap();
    assert_eq!(ready_after(&mut est, 0.0), 3, "the first window");
    // A gap longer than max_interval restarts the window at its sample.
    est.push(1.0, 0.0, 0.0).unwrap();
    assert_eq!(ready_after(&mut est, 1.0), 10, "after a gap");
    est.reset();
    est.push(2.0, 0.0, 0.0).unwrap();
    assert_eq!(ready_after(&mut est, 2.0), 10, "after a reset");
}

/// `first_window` is checked: at least the order's minimal kernel, at most the window, and
/// not with the low-pass form (which answers after its minimal kernel anyway).
#[test]
fn first_window_is_checked() {
    let cfg = |first_window, kind| EstimatorConfig {
        kind,
        window: 10,
        first_window,
        ..EstimatorConfig::default()
    };
    let alg = EstimatorKind::Algebraic;
    let lp = EstimatorKind::LowPass {
        time_constant: 0.05,
    };
    for (c, order, ok) in [
        (cfg(0, alg), Order::Two, true),
        (cfg(2, alg), Order::Two, true),
        (cfg(1, alg), Order::One, true),
        (cfg(10, alg), Order::Two, true),
        (cfg(1, alg), Order::Two, false),
        (cfg(11, alg), Order::One, false),
        (cfg(3, lp), Order::One, false),
    ] {
        let got = Estimator::<64>::new(c, order);
        assert_eq!(got.is_ok(), ok, "{c:?} {order:?}");
        if let Err(e) = got {
            assert!(e.to_string().contains("first_window"), "{e}");
        }
    }
}

/// Why a quantised sensor makes an order-two loop hunt (`docs/results-aero.md`, "The hold
/// at -0.1 rad"): one encoder count `q`, a step of the measurement while the plant is
/// still, is read as `F` rising then falling as the step crosses the window, with peaks of
/// `±(10/√3) q/T²` (the kernel's weight `T² - 6Tσ + 6σ²` integrated from the step's place
/// `σ` to the window's end is `-σ(T-σ)(T-2σ)`, largest in size at `σ = T(3 ∓ √3)/6`), and
/// nothing once it has left. For the AERO's pitch (q = 2π/2048, a 20-interval window of
/// 10 ms) that is ±0.44 rad/s², up to 2.2 of the command at alpha 0.2: a count moves the
/// command more than a hold near 0 V needs. Order one reads the same step as a velocity,
/// `1.5 q/T` at most, and never as a deceleration.
#[test]
fn one_count_is_read_as_a_burst_of_acceleration() {
    let q = 2.0 * std::f64::consts::PI / 2048.0;
    let (h, window) = (0.01, 20);
    let big_t = window as f64 * h;
    for (order, bound) in [
        (Order::Two, 10.0 / 3f64.sqrt() * q / (big_t * big_t)),
        (Order::One, 1.5 * q / big_t),
    ] {
        let mut est: Estimator = Estimator::new(
            EstimatorConfig {
                window,
                ..Default::default()
            },
            order,
        )
        .unwrap();
        let (mut high, mut low, mut last) = ((f64::MIN, 0), (f64::MAX, 0), f64::NAN);
        for k in 0..3 * window {
            let y = if k < window + 3 { 0.0 } else { q };
            est.push(k as f64 * h, y, 0.0).unwrap();
            if let Ok(f) = est.estimate(order) {
                let f = f.at(1.0);
                if f > high.0 {
                    high = (f, k);
                }
                if f < low.0 {
                    low = (f, k);
                }
                last = f;
            }
        }
        let ((high, rose), (low, fell)) = (high, low);
        // The step lasts one interval (the samples are joined by straight lines), which
        // rounds the peaks off a little: within 5 % of the continuous step's.
        assert!(
            (0.95 * bound..=bound).contains(&high),
            "{order:?}: peak {high}, bound {bound}"
        );
        if order == Order::Two {
            assert!(
                (-bound..=-0.95 * bound).contains(&low),
                "{order:?}: trough {low}, bound {bound}"
            );
            assert!(
                rose < fell,
                "{order:?}: the step read as a rise (sample {rose}) before a fall ({fell})"
            );
        } else {
            assert!(
                low.abs() < 1e-12,
                "{order:?}: order one never reads a deceleration"
            );
        }
        assert!(
            last.abs() < 1e-9,
            "{order:?}: the step has left the window: {last}"
        );
    }
}

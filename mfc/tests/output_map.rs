//! The output map's dead-zone compensation: the smooth map reaches every output, is
//! monotone and bounded, and its inverse undoes it; the paper's step leaves a band out.

use mfc::{OutputMap, OutputMapConfig};
use proptest::prelude::*;

fn smooth(dead_zone: f64, smoothing: f64) -> OutputMapConfig {
    OutputMapConfig {
        dead_zone,
        smoothing,
        min: -24.0,
        max: 24.0,
        rate_limit: None,
    }
}

/// Map `u` once, with a fresh map (no rate-limit memory).
fn apply(c: OutputMapConfig, u: f64) -> f64 {
    OutputMap::new(c).unwrap().apply(0.0, u).unwrap()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    /// Monotone (strictly, before the limits), odd, and never outside `[min, max]`.
    #[test]
    fn smooth_compensation_is_monotone_odd_and_bounded(
        d in 0.0f64..20.0,
        s in 0.01f64..20.0,
        u in -100.0f64..100.0,
        du in 1e-6f64..10.0,
    ) {
        let c = smooth(d, s);
        prop_assert!(c.compensate(u + du) > c.compensate(u));
        prop_assert_eq!(c.compensate(-u), -c.compensate(u));
        let (a, b) = (apply(c, u), apply(c, u + du));
        prop_assert!(a <= b);
        prop_assert!((-24.0..=24.0).contains(&a));
        // Lipschitz with slope at most 1 + d/s: a small change of u is a small change of v.
        prop_assert!(c.compensate(u + du) - c.compensate(u) <= (1.0 + d / s) * du * (1.0 + 1e-12) + 1e-12);
    }

    /// No unreachable band: every output in `[min, max]` is the image of some `u`, the one
    /// the inverse gives, and the inverse is monotone and bounded.
    #[test]
    fn every_output_is_reachable_through_the_inverse(
        d in 0.0f64..20.0,
        s in 0.01f64..20.0,
        v in -24.0f64..24.0,
        dv in 1e-6f64..5.0,
    ) {
        let c = smooth(d, s);
        let map = OutputMap::new(c).unwrap();
        let u = map.inverse(v);
        prop_assert!(u.is_finite());
        prop_assert!(u.abs() <= v.abs() + 1e-12, "|u| {} above |v| {}", u, v);
        let back = apply(c, u);
        prop_assert!((back - v).abs() <= 1e-9 * (1.0 + v.abs()), "v {} -> u {} -> v {}", v, u, back);
        prop_assert!(map.inverse(v + dv) >= u);
    }

    /// The inverse undoes the map for every `u` the limits let through.
    #[test]
    fn the_inverse_recovers_u_inside_the_limits(
        d in 0.0f64..15.0,
        s in 0.01f64..20.0,
        u in -9.0f64..9.0,
    ) {
        let c = smooth(d, s);
        let map = OutputMap::new(c).unwrap();
        let v = apply(c, u);
        prop_assume!(v.abs() < 24.0);
        prop_assert!((map.inverse(v) - u).abs() <= 1e-9 * (1.0 + u.abs()));
    }
}

#[test]
fn the_papers_step_leaves_a_band_unreachable_and_the_smooth_map_does_not() {
    let step = OutputMapConfig::AERO;
    // Whatever u the controller asks, the step never gives 5 V: it jumps from 0 to 10.
    let mut hit = false;
    for i in -2000..=2000 {
        let v = apply(step, i as f64 * 1e-3);
        hit |= v > 0.0 && v < 10.0;
    }
    assert!(!hit, "the step reached inside its dead zone");
    let smooth = OutputMapConfig {
        smoothing: 2.0,
        ..OutputMapConfig::AERO
    };
    let u = OutputMap::new(smooth).unwrap().inverse(5.0);
    assert!((apply(smooth, u) - 5.0).abs() < 1e-12);
    // Away from zero the smooth map is the step to within d (1 - tanh(|u|/s)).
    let far = 12.0;
    let gap = apply(step, far) - apply(smooth, far);
    assert!(gap > 0.0 && gap <= 10.0 * (1.0 - (far / 2.0f64).tanh()) + 1e-12);
}

#[test]
fn smoothing_must_not_be_negative_or_nan() {
    for s in [-1.0, f64::NAN] {
        let c = OutputMapConfig {
            smoothing: s,
            ..OutputMapConfig::AERO
        };
        assert!(OutputMap::new(c).is_err(), "smoothing {s} accepted");
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    /// Whatever the plant reported applying last (inside the range or far outside it, as
    /// a fallback with other limits or a restored state may leave it), the next output
    /// stays inside `[min, max]`, and inside the rate limit's reach wherever that reach
    /// meets the range.
    #[test]
    fn the_range_holds_after_any_reported_output(
        applied in -100.0f64..100.0,
        u in -100.0f64..100.0,
        dt in 0.0f64..1.0,
    ) {
        let c = OutputMapConfig { rate_limit: Some(10.0), ..smooth(0.0, 1.0) };
        let mut m = OutputMap::new(c).unwrap();
        m.record_applied(0.0, applied);
        let v = m.apply(dt, u).unwrap();
        prop_assert!((-24.0..=24.0).contains(&v), "v {v}");
        let (lo, hi) = (applied - 10.0 * dt, applied + 10.0 * dt);
        if hi >= -24.0 && lo <= 24.0 {
            prop_assert!(v >= lo - 1e-9 && v <= hi + 1e-9, "v {v} outside [{lo}, {hi}]");
        }
    }
}

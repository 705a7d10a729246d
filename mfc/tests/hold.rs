//! The hold filter (`hold_estimate_filter`, `hold_after`): a slower `F_est` only once every
//! reference has rested for `hold_after`, and the usual one as soon as any moves.
//!
//! Each test feeds the same measurements to a controller with the hold filter and to one
//! without, open loop, so the only difference between their estimates is the filter.

use mfc::{
    ChannelConfig, ChannelOutput, ControllerKind, EstimatorConfig, IntelligentController,
    IntelligentParams, LawConfig, MfcError, MimoController, Order, OutputMapConfig, Reference,
};

const H: f64 = 0.01;

fn params(hold: f64) -> IntelligentParams {
    IntelligentParams {
        kind: ControllerKind::PD,
        order: Order::Two,
        alpha: 0.5,
        kp: 4.0,
        kd: 2.0,
        estimate_filter: 0.0,
        hold_estimate_filter: hold,
        hold_after: 0.5,
        ..IntelligentParams::default()
    }
}

fn controller(hold: f64) -> IntelligentController {
    IntelligentController::new(
        params(hold),
        EstimatorConfig {
            window: 10,
            ..EstimatorConfig::default()
        },
    )
    .unwrap()
}

/// `y'' = F(t)` sampled exactly every `H` (no input applied): `F` is 0 before `t_jump`
/// and `f1` after, so the raw estimate moves from 0 to `f1` within a window.
fn measurements(n: usize, t_jump: f64, f1: f64) -> Vec<(f64, f64)> {
    measure(n, |t| if t >= t_jump { f1 } else { 0.0 })
}

/// `y'' = f(t)`, sampled exactly every `H`.
fn measure(n: usize, f: impl Fn(f64) -> f64) -> Vec<(f64, f64)> {
    let (mut y, mut dy) = (0.0, 0.0);
    (0..n)
        .map(|k| {
            let t = k as f64 * H;
            let sample = (t, y);
            let f = f(t);
            y += H * dy + 0.5 * H * H * f;
            dy += H * f;
            sample
        })
        .collect()
}

/// Both controllers' `F_est` (NaN while the window fills), step by step.
fn estimates(data: &[(f64, f64)], reference: impl Fn(f64) -> Reference) -> Vec<(f64, f64, f64)> {
    let (mut plain, mut hold) = (controller(0.0), controller(1.0));
    data.iter()
        .map(|&(t, y)| {
            let r = reference(t);
            let a = plain.step(t, y, &r).unwrap();
            let b = hold.step(t, y, &r).unwrap();
            plain.set_applied(0.0).unwrap();
            hold.set_applied(0.0).unwrap();
            (t, a.f_est.unwrap_or(f64::NAN), b.f_est.unwrap_or(f64::NAN))
        })
        .collect()
}

fn at(est: &[(f64, f64, f64)], t: f64) -> (f64, f64) {
    let k = (t / H).round() as usize;
    (est[k].1, est[k].2)
}

#[test]
fn at_rest_the_estimate_slows_down_only_after_hold_after() {
    // F jumps at 0.3 s, inside the first 0.5 s at rest: both follow it alike.
    let est = estimates(&measurements(150, 0.3, 2.0), |_| Reference::constant(0.0));
    for &(t, a, b) in est.iter().filter(|e| e.0 < 0.5 && !e.1.is_nan()) {
        assert_eq!(a.to_bits(), b.to_bits(), "t = {t}: {a} vs {b}");
    }
    let (a, _) = at(&est, 0.45);
    assert!((a - 2.0).abs() < 1e-6, "the raw estimate has the jump: {a}");

    // F jumps at 1 s, after 0.5 s at rest: the hold filter (1 s) lags it.
    let est = estimates(&measurements(200, 1.0, 2.0), |_| Reference::constant(0.0));
    let (a, b) = at(&est, 1.2);
    assert!((a - 2.0).abs() < 1e-6, "plain: {a}");
    assert!(
        b > 0.1 && b < 0.5,
        "hold: {b} (a first-order lag of 1 s after 0.1-0.2 s)"
    );
    // ...and converges to it.
    let est = estimates(&measurements(800, 1.0, 2.0), |_| Reference::constant(0.0));
    let (_, b) = at(&est, 7.9);
    assert!((b - 2.0).abs() < 0.01, "hold after 6.9 s: {b}");
}

#[test]
fn a_moving_or_stepped_reference_keeps_the_usual_filter() {
    let data = measurements(300, 1.0, 2.0);
    // A ramp never rests.
    let ramp = estimates(&data, |t| Reference {
        y: 0.1 * t,
        dy: 0.1,
        ddy: 0.0,
    });
    for &(t, a, b) in ramp.iter().filter(|e| !e.1.is_nan()) {
        assert_eq!(a.to_bits(), b.to_bits(), "ramp, t = {t}");
    }
    // A step at 0.8 s (y* changes, its derivatives stay zero) starts the rest again: the
    // jump of F at 1 s, 0.2 s later, is followed at the usual speed until 1.3 s.
    let step = estimates(&data, |t| {
        Reference::constant(if t < 0.8 { 0.0 } else { 0.1 })
    });
    for &(t, a, b) in step.iter().filter(|e| (0.8..1.29).contains(&e.0)) {
        assert_eq!(a.to_bits(), b.to_bits(), "step, t = {t}");
    }
    // Before the step it had rested long enough: the filters differed there.
    let (a, b) = at(&step, 0.7);
    assert_eq!(a, 0.0);
    assert_eq!(b, 0.0);
    // Without the step the hold would have lagged the jump (the test above); with it,
    // the jump was taken at the usual speed.
    let (a, b) = at(&step, 1.25);
    assert!((a - 2.0).abs() < 1e-6 && (b - 2.0).abs() < 1e-6, "{a} {b}");
}

#[test]
fn another_channels_moving_reference_keeps_the_usual_filter() {
    // Channel 0 rests; channel 1 follows a ramp until 1.5 s, then steps at 3 s. The
    // coupling a moving channel brings is what F must follow quickly, so channel 0 holds
    // only from 2 s to 3 s and from 3.5 s on. F jumps at 1.2, 2.6, 3.2 and 4.0 s.
    let config = |hold: f64| -> MimoController {
        let law = LawConfig::Intelligent {
            params: params(hold),
            estimator: EstimatorConfig {
                window: 10,
                ..EstimatorConfig::default()
            },
        };
        let c = ChannelConfig {
            law,
            output: OutputMapConfig::default(),
        };
        MimoController::new(&[c, c]).unwrap()
    };
    let (mut plain, mut hold) = (config(0.0), config(1.0));
    let data = measure(500, |t| match t {
        t if t < 1.2 => 0.0,
        t if t < 2.6 => 2.0,
        t if t < 3.2 => -1.0,
        t if t < 4.0 => 1.0,
        _ => 3.0,
    });
    let mut out_a = [ChannelOutput::default(); 2];
    let mut out_b = [ChannelOutput::default(); 2];
    let mut differed = Vec::new();
    for &(t, y) in &data {
        let r1 = match t {
            t if t < 1.5 => Reference {
                y: 0.1 * t,
                dy: 0.1,
                ddy: 0.0,
            },
            t if t < 3.0 => Reference::constant(0.15),
            _ => Reference::constant(0.2),
        };
        let r = [Reference::constant(0.0), r1];
        plain.step(t, &[y, y], &r, &mut out_a).unwrap();
        hold.step(t, &[y, y], &r, &mut out_b).unwrap();
        plain.report_applied(&[0.0, 0.0]).unwrap();
        hold.report_applied(&[0.0, 0.0]).unwrap();
        if out_a[0].f_est != out_b[0].f_est {
            differed.push(t);
        }
    }
    // The jump at 1.2 s, during the ramp, is followed alike; the one at 2.6 s, held, is
    // not; after the step at 3 s the two agree again (the estimate that lagged catches
    // up at the usual speed, within the 0.1 s window), so the jump at 3.2 s is followed
    // alike; the one at 4 s, held again, is not.
    let in_range = |a: f64, b: f64| differed.iter().any(|t| (a..b).contains(t));
    assert!(
        !in_range(0.0, 2.0),
        "held before every reference rested: {differed:?}"
    );
    assert!(in_range(2.6, 3.0), "no hold from 2 s to 3 s: {differed:?}");
    assert!(
        !in_range(3.15, 3.5),
        "held right after channel 1 stepped: {differed:?}"
    );
    assert!(in_range(4.0, 5.0), "no hold after 3.5 s: {differed:?}");
}

#[test]
fn bad_hold_parameters_are_refused() {
    for (hold, after, name) in [
        (-0.1, 1.0, "hold_estimate_filter"),
        (f64::NAN, 1.0, "hold_estimate_filter"),
        (0.2, -1.0, "hold_after"),
        (0.2, f64::INFINITY, "hold_after"),
    ] {
        let p = IntelligentParams {
            hold_estimate_filter: hold,
            hold_after: after,
            ..params(0.0)
        };
        match p.validate() {
            Err(MfcError::InvalidParameter { name: n, .. }) => assert_eq!(n, name),
            other => panic!("{hold} {after}: {other:?}"),
        }
    }
}

/// `hold_band`: once the reference has rested for `hold_after`, a command that would
/// reverse the sign of the last nonzero one inside `±hold_band` gives 0; beyond the band,
/// or while the reference moves, the law's own output passes. The same measurements go to
/// a controller with the band and one without, so the difference is the band alone.
#[test]
fn a_hold_band_stops_reversals_inside_it_only_at_rest() {
    let make = |band: f64| {
        IntelligentController::<64>::new(
            IntelligentParams {
                kind: ControllerKind::P,
                order: Order::One,
                alpha: 1.0,
                kp: 1.0,
                hold_after: 0.5,
                hold_band: band,
                ..IntelligentParams::default()
            },
            EstimatorConfig {
                window: 2,
                ..EstimatorConfig::default()
            },
        )
        .unwrap()
    };
    let (mut with, mut without) = (make(0.3), make(0.0));
    let rest = Reference {
        y: 0.0,
        dy: 0.0,
        ddy: 0.0,
    };
    let moving = Reference {
        y: 0.0,
        dy: 1e-3,
        ddy: 0.0,
    };
    // y dithers by +-0.1 around the reference: u = -(F + e) reverses at every sample, with
    // |u| small. Both are told the same applied input (the one without the band's), so
    // their estimates stay equal and only the band tells them apart.
    let mut zeros_at_rest = 0;
    let mut applied = 0.0;
    for k in 0..200 {
        let t = f64::from(k) * H;
        let y = if k % 2 == 0 { 0.1 } else { -0.1 };
        let r = if t < 1.0 { moving } else { rest };
        with.set_applied(applied).unwrap();
        without.set_applied(applied).unwrap();
        let a = with.step(t, y, &r).unwrap().u;
        let b = without.step(t, y, &r).unwrap().u;
        applied = b;
        if t < 1.45 {
            assert_eq!(a, b, "t = {t}: the band acts only at rest");
        } else if t < 1.55 {
            // Where the rest reaches hold_after, to rounding.
        } else if b.abs() < 0.3 {
            // A reversal inside the band is 0; the same sign as the last nonzero passes.
            assert!(a == 0.0 || a == b, "t = {t}: {a} against {b}");
            zeros_at_rest += usize::from(a == 0.0 && b != 0.0);
        } else {
            assert_eq!(a, b, "t = {t}: beyond the band the law's output passes");
        }
    }
    assert!(zeros_at_rest > 10, "the band never acted ({zeros_at_rest})");
    let bad = IntelligentParams {
        hold_band: -1.0,
        ..IntelligentParams::default()
    };
    assert!(bad.validate().is_err());
}

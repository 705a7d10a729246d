//! Commissioning finds `α` and the order from a plant's own response to a square wave.

use mfc::{
    commissioned_law, gains_for, CommissionAbort, CommissionFinding, CommissionFit, CommissionSpec,
    CommissionStep, Commissioning, ControllerKind, LawConfig, MfcError, Order, PidParams,
};

/// A plant `y'' = -k y - c y' + b u + d` (second order) or `y' = -a y + b u + d` (first),
/// integrated in 20 sub-steps per period, sampled every `h`.
struct Plant {
    second: bool,
    p: [f64; 2],
    b: f64,
    d: f64,
    y: f64,
    dy: f64,
}

impl Plant {
    /// `y' = -a y + b u + d`, at rest at 0.
    fn first(a: f64, b: f64, d: f64) -> Self {
        Self {
            second: false,
            p: [a, 0.0],
            b,
            d,
            y: 0.0,
            dy: 0.0,
        }
    }

    /// `y'' = -k y - c y' + b u + d`, at rest at 0.
    fn second(k: f64, c: f64, b: f64, d: f64) -> Self {
        Self {
            second: true,
            p: [k, c],
            b,
            d,
            y: 0.0,
            dy: 0.0,
        }
    }

    fn advance(&mut self, u: f64, h: f64) {
        let dt = h / 20.0;
        for _ in 0..20 {
            if self.second {
                let acc = -self.p[0] * self.y - self.p[1] * self.dy + self.b * u + self.d;
                self.y += dt * self.dy;
                self.dy += dt * acc;
            } else {
                self.y += dt * (-self.p[0] * self.y + self.b * u + self.d);
            }
        }
    }
}

/// Run a spec on a plant from rest; the finding or the abort, and the largest |u - u0|.
fn commission(plant: &mut Plant, spec: CommissionSpec, u0: f64, h: f64) -> (CommissionStep, f64) {
    let mut c: Commissioning = Commissioning::new(spec, u0).unwrap();
    let (mut u, mut widest) = (u0, 0.0f64);
    for k in 0..100_000 {
        let t = f64::from(k) * h;
        match c.step(t, plant.y, u).unwrap() {
            CommissionStep::Apply(next) => {
                widest = widest.max((next - u0).abs());
                u = next;
            }
            other => return (other, widest),
        }
        plant.advance(u, h);
    }
    panic!("never finished");
}

#[test]
fn a_first_order_plant_gives_order_one_and_its_gain() {
    for b in [0.05, 2.0, -3.0] {
        let mut p = Plant::first(0.5, b, 0.3);
        let spec = CommissionSpec {
            amplitude: 0.2 / b.abs(),
            period: 2.0,
            cycles: 4,
            max_deviation: 10.0,
            window: 10,
            order: None,
        };
        let (step, widest) = commission(&mut p, spec, 0.1, 0.01);
        let CommissionStep::Done(f) = step else {
            panic!("{step:?}")
        };
        assert_eq!(f.best.order, Order::One, "{f:?}");
        assert!((f.best.alpha / b - 1.0).abs() < 0.1, "b = {b}: {f:?}");
        assert!(f.best.explained > 0.9, "{f:?}");
        let two = f.fits[1].map_or(0.0, |x| x.explained);
        assert!(two < f.best.explained, "{f:?}");
        assert!(
            (widest - spec.amplitude).abs() < 1e-12,
            "the excitation stays within its amplitude"
        );
    }
}

#[test]
fn a_lightly_damped_second_order_plant_gives_order_two_and_its_gain() {
    let b = 0.4;
    let mut p = Plant::second(1.7, 0.3, b, -0.2);
    let spec = CommissionSpec {
        amplitude: 0.5,
        period: 1.0,
        cycles: 6,
        max_deviation: 10.0,
        window: 20,
        order: None,
    };
    let (step, _) = commission(&mut p, spec, 0.0, 0.01);
    let CommissionStep::Done(f) = step else {
        panic!("{step:?}")
    };
    assert_eq!(f.best.order, Order::Two, "{f:?}");
    assert!((f.best.alpha / b - 1.0).abs() < 0.1, "{f:?}");
    // Asked for order one, it answers for order one (worse, but what was asked).
    let mut p = Plant::second(1.7, 0.3, b, -0.2);
    let (step, _) = commission(
        &mut p,
        CommissionSpec {
            order: Some(Order::One),
            ..spec
        },
        0.0,
        0.01,
    );
    match step {
        CommissionStep::Done(f) => assert_eq!(f.best.order, Order::One),
        CommissionStep::Aborted(CommissionAbort::NoFit(_)) => {}
        other => panic!("{other:?}"),
    }
}

#[test]
fn leaving_the_allowed_deviation_aborts_at_once() {
    // An integrator with a large gain: the square wave walks it off.
    let mut p = Plant::first(0.0, 50.0, 1.0);
    let spec = CommissionSpec {
        amplitude: 1.0,
        period: 4.0,
        cycles: 4,
        max_deviation: 0.5,
        window: 10,
        order: None,
    };
    let (step, _) = commission(&mut p, spec, 0.0, 0.01);
    let CommissionStep::Aborted(CommissionAbort::Deviation { t, y, y0 }) = step else {
        panic!("{step:?}")
    };
    assert!(
        (y - y0).abs() > 0.5 && (y - y0).abs() < 0.6,
        "stopped at the first sample beyond: {y}"
    );
    assert!(t < 1.0, "{t}");
    assert!(CommissionAbort::Deviation { t, y, y0 }
        .to_string()
        .contains("previous law is back"));
}

#[test]
fn data_that_cannot_give_alpha_are_refused() {
    // Switching faster than a window.
    let mut p = Plant::first(0.5, 1.0, 0.0);
    let fast = CommissionSpec {
        period: 0.1,
        window: 10,
        max_deviation: 10.0,
        ..CommissionSpec::default()
    };
    let (step, _) = commission(&mut p, fast, 0.0, 0.01);
    assert!(
        matches!(step, CommissionStep::Aborted(CommissionAbort::NoFit(_))),
        "{step:?}"
    );
    // A plant that ignores its input.
    let mut p = Plant::first(0.5, 0.0, 0.4);
    let spec = CommissionSpec {
        max_deviation: 10.0,
        window: 10,
        ..CommissionSpec::default()
    };
    let (step, _) = commission(&mut p, spec, 0.0, 0.01);
    assert!(
        matches!(step, CommissionStep::Aborted(CommissionAbort::NoFit(_))),
        "{step:?}"
    );
}

#[test]
fn specs_and_samples_are_checked() {
    let bad = [
        CommissionSpec {
            amplitude: 0.0,
            ..CommissionSpec::default()
        },
        CommissionSpec {
            period: f64::NAN,
            ..CommissionSpec::default()
        },
        CommissionSpec {
            cycles: 1,
            ..CommissionSpec::default()
        },
        CommissionSpec {
            max_deviation: -1.0,
            ..CommissionSpec::default()
        },
        CommissionSpec {
            window: 1,
            ..CommissionSpec::default()
        },
        CommissionSpec {
            window: 256,
            ..CommissionSpec::default()
        },
    ];
    for spec in bad {
        assert!(Commissioning::<256>::new(spec, 0.0).is_err(), "{spec:?}");
    }
    assert!(Commissioning::<256>::new(CommissionSpec::default(), f64::INFINITY).is_err());
    let mut c: Commissioning = Commissioning::new(CommissionSpec::default(), 0.0).unwrap();
    c.step(0.0, 0.0, 0.0).unwrap();
    assert!(matches!(
        c.step(0.0, 0.0, 0.0),
        Err(MfcError::TimeNotAdvancing { .. })
    ));
    assert!(c.step(0.01, f64::NAN, 0.0).is_err());
    assert!(matches!(
        c.step(0.01, 0.0, 0.0),
        Ok(CommissionStep::Apply(_))
    ));
}

#[test]
fn gains_give_the_error_dynamics_asked_for() {
    assert_eq!(gains_for(Order::One, 2.0, 0.7).unwrap(), [2.0, 0.0, 0.0]);
    assert_eq!(gains_for(Order::Two, 3.0, 0.5).unwrap(), [9.0, 0.0, 3.0]);
    assert!(gains_for(Order::Two, 0.0, 0.5).is_err());
    assert!(gains_for(Order::Two, 1.0, f64::NAN).is_err());
}

fn finding(order: Order, alpha: f64) -> CommissionFinding {
    let best = CommissionFit {
        order,
        alpha,
        explained: 0.9,
    };
    CommissionFinding {
        best,
        fits: [Some(best), None],
        samples: 100,
    }
}

#[test]
fn the_law_keeps_its_error_dynamics() {
    let ipd = LawConfig::intelligent(ControllerKind::PD, Order::Two, 0.2, [9.0, 0.0, 3.0], 20);
    let same = commissioned_law(&ipd, &finding(Order::Two, 0.35), None).unwrap();
    let LawConfig::Intelligent { params, .. } = same else {
        unreachable!()
    };
    assert_eq!((params.alpha, params.kp, params.kd), (0.35, 9.0, 3.0));
    // Order 2 -> 1: e' + 3 e = 0, an iP.
    let one = commissioned_law(&ipd, &finding(Order::One, 1.5), None).unwrap();
    let LawConfig::Intelligent { params, .. } = one else {
        unreachable!()
    };
    assert_eq!(
        (params.kind, params.order, params.kp, params.kd),
        (ControllerKind::P, Order::One, 3.0, 0.0)
    );
    // Order 1 -> 2: damping 0.7 around the same bandwidth.
    let ip = LawConfig::intelligent(ControllerKind::P, Order::One, 1.0, [2.0, 0.0, 0.0], 10);
    let two = commissioned_law(&ip, &finding(Order::Two, 0.5), None).unwrap();
    let LawConfig::Intelligent { params, .. } = two else {
        unreachable!()
    };
    assert_eq!(params.kp, 4.0);
    assert!((params.kd - 2.8).abs() < 1e-12);
    assert!(params.validate().is_ok());
    let pid = LawConfig::Pid {
        params: PidParams::default(),
    };
    // Requested error dynamics win over the law's: e'' + 2 0.5 5 e' + 25 e = 0.
    let asked = commissioned_law(&ipd, &finding(Order::Two, 0.35), Some((5.0, 0.5))).unwrap();
    let LawConfig::Intelligent { params, .. } = asked else {
        unreachable!()
    };
    assert_eq!((params.alpha, params.kp, params.kd), (0.35, 25.0, 5.0));
    assert!(commissioned_law(&ipd, &finding(Order::Two, 0.35), Some((-1.0, 0.5))).is_none());
    assert!(commissioned_law(&pid, &finding(Order::One, 1.0), None).is_none());
}

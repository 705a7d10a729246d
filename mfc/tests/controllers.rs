//! Closed-loop behaviour of every controller on test plants the controllers do not know.

mod common;

use common::{rms, Rk4Plant};
use mfc::{
    AdrcParams, Channel, ChannelConfig, ControllerKind, EstimatorConfig, EstimatorKind,
    IntelligentController, IntelligentParams, LawConfig, Order, OutputMapConfig, PidParams,
    Reference, Trend,
};

const H: f64 = 0.01;

fn intelligent(
    kind: ControllerKind,
    order: Order,
    alpha: f64,
    kp: f64,
    ki: f64,
    kd: f64,
) -> LawConfig {
    LawConfig::intelligent(kind, order, alpha, [kp, ki, kd], 10)
}

fn limits(limit: f64) -> OutputMapConfig {
    OutputMapConfig {
        min: -limit,
        max: limit,
        ..Default::default()
    }
}

/// Closed loop of `channel` on `plant` (output = state 0) for `duration` seconds; returns the
/// RMS error after `settle` seconds and the largest |error| over the whole run.
fn run<const N: usize>(
    channel: &mut Channel,
    plant: &mut Rk4Plant<N>,
    reference: impl Fn(f64) -> Reference,
    duration: f64,
    settle: f64,
) -> (f64, f64) {
    let steps = (duration / H).round() as usize;
    let mut errors = Vec::new();
    let mut worst: f64 = 0.0;
    for k in 0..steps {
        let t = k as f64 * H;
        let r = reference(t);
        let out = channel.step(t, plant.x[0], &r).expect("step");
        worst = worst.max(out.error.abs());
        if t >= settle {
            errors.push(out.error);
        }
        plant.advance(H, out.v, 10);
    }
    (rms(&errors), worst)
}

/// y' = -0.8 y + 2.5 u + 1.5: stable first-order plant with an unknown constant disturbance.
fn first_order() -> Rk4Plant<1> {
    Rk4Plant {
        x: [0.0],
        deriv: |x, u| [-0.8 * x[0] + 2.5 * u + 1.5],
    }
}

/// y'' = -0.3 y' - 4 y + 3 u + 2: lightly damped second-order plant with a disturbance.
fn second_order() -> Rk4Plant<2> {
    Rk4Plant {
        x: [0.0, 0.0],
        deriv: |x, u| [x[1], -0.3 * x[1] - 4.0 * x[0] + 3.0 * u + 2.0],
    }
}

fn sine(amplitude: f64, w: f64, offset: f64) -> impl Fn(f64) -> Reference {
    move |t| Reference {
        y: offset + amplitude * (w * t).sin(),
        dy: amplitude * w * (w * t).cos(),
        ddy: -amplitude * w * w * (w * t).sin(),
    }
}

#[test]
fn every_controller_tracks_a_first_order_plant() {
    let laws = [
        (
            "iP",
            intelligent(ControllerKind::P, Order::One, 2.0, 10.0, 0.0, 0.0),
        ),
        (
            "iPI",
            intelligent(ControllerKind::PI, Order::One, 2.0, 10.0, 20.0, 0.0),
        ),
        (
            "iPID",
            intelligent(ControllerKind::PID, Order::One, 2.0, 10.0, 10.0, 0.05),
        ),
        (
            "PID",
            LawConfig::Pid {
                params: PidParams {
                    kp: 8.0,
                    ki: 20.0,
                    kd: 0.05,
                    ..Default::default()
                },
            },
        ),
        (
            "ADRC",
            LawConfig::Adrc {
                params: AdrcParams {
                    order: Order::One,
                    b0: 2.0,
                    wc: 10.0,
                    wo: 50.0,
                },
            },
        ),
    ];
    for (name, law) in laws {
        let mut channel: Channel = Channel::new(&ChannelConfig {
            law,
            output: limits(20.0),
        })
        .unwrap();
        let (rms, worst) = run(
            &mut channel,
            &mut first_order(),
            sine(0.5, 1.0, 0.3),
            10.0,
            3.0,
        );
        eprintln!("first order, {name}: rms {rms:.2e}, worst {worst:.3}");
        // 2 % of the reference amplitude after the transient, and no excursion beyond the
        // initial offset (|e(0)| = 0.3).
        assert!(rms < 0.01, "{name}: rms {rms}");
        assert!(worst <= 0.31, "{name}: worst {worst}");
    }
}

#[test]
fn every_controller_tracks_a_second_order_plant() {
    let laws = [
        (
            "iPD",
            intelligent(ControllerKind::PD, Order::Two, 3.0, 25.0, 0.0, 10.0),
        ),
        (
            "iPID",
            intelligent(ControllerKind::PID, Order::Two, 3.0, 25.0, 10.0, 10.0),
        ),
        (
            "PID",
            LawConfig::Pid {
                params: PidParams {
                    kp: 80.0,
                    ki: 150.0,
                    kd: 8.0,
                    ..Default::default()
                },
            },
        ),
        (
            "ADRC",
            LawConfig::Adrc {
                params: AdrcParams {
                    order: Order::Two,
                    b0: 3.0,
                    wc: 5.0,
                    wo: 30.0,
                },
            },
        ),
    ];
    for (name, law) in laws {
        let mut channel: Channel = Channel::new(&ChannelConfig {
            law,
            output: limits(50.0),
        })
        .unwrap();
        let (rms, worst) = run(
            &mut channel,
            &mut second_order(),
            sine(0.4, 0.8, 0.0),
            12.0,
            4.0,
        );
        eprintln!("second order, {name}: rms {rms:.2e}, worst {worst:.3}");
        assert!(rms < 0.01, "{name}: rms {rms}");
        assert!(worst < 0.2, "{name}: worst {worst}");
    }
}

/// The literal reading of the paper's closed-loop formula,
/// F_est = (1/τ) ∫ (y*' - α u - Kp e), fed with the iP's own output, is an identity: each
/// integrand equals the previous F_est, so F_est never moves. The non-circular form (measured
/// y, applied u) follows a step in F.
#[test]
fn closed_loop_form_is_not_the_identity_trap() {
    let (alpha, kp, window) = (1.0, 5.0, 10usize);
    let f_true = |t: f64| if t < 1.0 { 1.0 } else { 3.0 };
    let reference = |t: f64| Reference {
        y: 0.5 * t,
        dy: 0.5,
        ddy: 0.0,
    };

    // Ours.
    let cfg = EstimatorConfig {
        kind: EstimatorKind::ClosedLoop,
        window,
        ..Default::default()
    };
    let params = IntelligentParams {
        alpha,
        kp,
        ..Default::default()
    };
    let mut ctrl: IntelligentController = IntelligentController::new(params, cfg).unwrap();
    let mut y = 0.0;
    let mut last_f = None;
    for k in 0..300 {
        let t = k as f64 * H;
        let out = ctrl.step(t, y, &reference(t)).unwrap();
        last_f = out.f_est;
        y += H * (f_true(t) + alpha * out.u);
    }
    let ours = last_f.unwrap();
    assert!((ours - 3.0).abs() < 1e-6, "non-circular form: {ours}");

    // The trap: a window of past integrands (y*' - α u - Kp e).
    let mut integrands = std::collections::VecDeque::from(vec![1.0; window]);
    let mut f_trap: f64 = 1.0;
    let mut y = 0.0;
    for k in 0..300 {
        let t = k as f64 * H;
        let r = reference(t);
        let e = y - r.y;
        let u = -(f_trap - r.dy + kp * e) / alpha;
        integrands.pop_front();
        integrands.push_back(r.dy - alpha * u - kp * e);
        f_trap = integrands.iter().sum::<f64>() / window as f64;
        y += H * (f_true(t) + alpha * u);
    }
    assert!(
        (f_trap - 1.0).abs() < 1e-9,
        "the trap never moves: {f_trap}"
    );
}

/// The estimator is fed what the plant got. With the output saturated, feeding the computed
/// output (the mistake) biases F_est; feeding the applied one (what `Channel` does) keeps it
/// exact.
#[test]
fn saturation_aware_estimation() {
    let (f, alpha) = (-2.0, 1.0);
    let params = IntelligentParams {
        alpha,
        kp: 5.0,
        ..Default::default()
    };
    let law = LawConfig::Intelligent {
        params,
        estimator: EstimatorConfig::default(),
    };
    let mut channel: Channel = Channel::new(&ChannelConfig {
        law,
        output: limits(1.0),
    })
    .unwrap();
    let mut naive: IntelligentController =
        IntelligentController::new(params, EstimatorConfig::default()).unwrap();
    // An unreachable ramp keeps the output saturated at +1 (the plant: y' = F + α v).
    let reference = |t: f64| Reference {
        y: 5.0 * t,
        dy: 5.0,
        ddy: 0.0,
    };
    let (mut y1, mut y2) = (0.0, 0.0);
    let (mut est1, mut est2) = (0.0, 0.0);
    for k in 0..200 {
        let t = k as f64 * H;
        let o1 = channel.step(t, y1, &reference(t)).unwrap();
        assert!(k < 15 || o1.v == 1.0, "saturated");
        est1 = o1.f_est.unwrap_or(0.0);
        y1 += H * (f + alpha * o1.v);
        let o2 = naive.step(t, y2, &reference(t)).unwrap();
        est2 = o2.f_est.unwrap_or(0.0);
        y2 += H * (f + alpha * o2.u.clamp(-1.0, 1.0));
    }
    assert!((est1 - f).abs() < 1e-9, "applied input: {est1}");
    assert!((est2 - f).abs() > 1.0, "computed input: {est2}");
}

/// Dead-zone compensation: v = ±10 + u, saturation at ±24, and the inverse.
#[test]
fn aero_output_map() {
    let mut map = mfc::OutputMap::new(OutputMapConfig::AERO).unwrap();
    assert_eq!(map.apply(0.0, 2.0).unwrap(), 12.0);
    assert_eq!(map.apply(0.01, -3.0).unwrap(), -13.0);
    assert_eq!(map.apply(0.02, 0.0).unwrap(), 0.0);
    assert_eq!(map.apply(0.03, 100.0).unwrap(), 24.0);
    assert_eq!(map.inverse(24.0), 14.0);
    assert_eq!(map.inverse(-12.5), -2.5);
    assert_eq!(map.inverse(5.0), 0.0);
    let mut limited = mfc::OutputMap::new(OutputMapConfig {
        rate_limit: Some(100.0),
        ..Default::default()
    })
    .unwrap();
    assert_eq!(limited.apply(0.0, 0.0).unwrap(), 0.0);
    assert!((limited.apply(0.01, 50.0).unwrap() - 1.0).abs() < 1e-12);
}

/// MIMO: two coupled outputs, one loop each, the coupling left to each F.
#[test]
fn mimo_tracks_a_coupled_plant() {
    let cfg = |alpha| ChannelConfig {
        law: intelligent(ControllerKind::P, Order::One, alpha, 8.0, 0.0, 0.0),
        output: limits(30.0),
    };
    let mut mimo: mfc::MimoController = mfc::MimoController::new(&[cfg(2.0), cfg(1.0)]).unwrap();
    // y1' = -y1 + 2 u1 + 0.8 u2 + 0.5 y2,  y2' = -0.5 y2 + 1.2 u2 - 0.6 u1 - 1.
    let mut x = [0.0f64; 2];
    let mut out = [mfc::ChannelOutput::default(); 2];
    let mut errs = Vec::new();
    for k in 0..1000 {
        let t = k as f64 * H;
        let refs = [sine(0.5, 1.5, 0.0)(t), sine(0.3, 0.7, 0.2)(t)];
        mimo.step(t, &x, &refs, &mut out).unwrap();
        if t > 2.0 {
            errs.push(out[0].error);
            errs.push(out[1].error);
        }
        let (v1, v2) = (out[0].v, out[1].v);
        for _ in 0..10 {
            let d1 = -x[0] + 2.0 * v1 + 0.8 * v2 + 0.5 * x[1];
            let d2 = -0.5 * x[1] + 1.2 * v2 - 0.6 * v1 - 1.0;
            x[0] += H / 10.0 * d1;
            x[1] += H / 10.0 * d2;
        }
    }
    assert!(rms(&errs) < 0.01, "mimo rms {}", rms(&errs));
}

/// The packetized horizon of an iPD (n = 2, `estimate_filter` 0.05 s) after 3 s holding 0
/// (or, with `moving`, tracking `y* = 0.1 t`) against `y'' = d + u`, `d` ramping at 3 per
/// second: the plan and the plant's state at the start of the first planned period.
fn ramp_plan(estimate_filter: f64, trend: Trend, moving: bool) -> (Vec<f64>, Rk4Plant<3>) {
    let config = ChannelConfig {
        law: LawConfig::Intelligent {
            params: IntelligentParams {
                kind: ControllerKind::PD,
                order: Order::Two,
                alpha: 1.0,
                kp: 9.0,
                kd: 6.0,
                estimate_filter,
                ..IntelligentParams::default()
            },
            estimator: EstimatorConfig {
                window: 20,
                ..EstimatorConfig::default()
            },
        },
        output: OutputMapConfig::default(),
    };
    let mut channel: Channel = Channel::new(&config).expect("channel");
    let mut plant = Rk4Plant {
        x: [0.0; 3],
        deriv: |x, u| [x[1], x[2] + u, 3.0],
    };
    let reference = |k: usize| {
        if moving {
            Reference {
                y: 0.1 * k as f64 * H,
                dy: 0.1,
                ddy: 0.0,
            }
        } else {
            Reference::default()
        }
    };
    let mut last = None;
    for k in 0..300 {
        let out = channel
            .step(k as f64 * H, plant.x[0], &reference(k))
            .expect("step");
        plant.advance(H, out.v, 10);
        last = Some(out);
    }
    let refs: Vec<Reference> = (300..320).map(reference).collect();
    let mut out = vec![0.0; 20];
    channel.plan(&last.expect("stepped"), H, &refs, &[], trend, &mut out);
    (out, plant)
}

/// A plan that follows the estimate's trend keeps up with a disturbance that ramps while
/// the plant holds (`at_rest` as `moving`, for a load that drifts): played open loop
/// (every command of 200 ms lost), the plant drifts from where it was a third as far as
/// under a plan that holds `F` at its (filtered, late) estimate with half the trend
/// (7.5e-3 -> 2.7e-3), and a tenth as far with the whole (exact for a ramp).
#[test]
fn a_plan_following_the_trend_of_f_keeps_up_with_a_ramping_disturbance() {
    let worst = |g| {
        let (plan, mut plant) = ramp_plan(0.05, Trend::always(g), false);
        let y0 = plant.x[0];
        plan.iter().fold(0.0_f64, |w, &v| {
            plant.advance(H, v, 10);
            w.max((plant.x[0] - y0).abs())
        })
    };
    let (held, half, whole) = (worst(0.0), worst(0.5), worst(1.0));
    assert!(
        half < 0.5 * held,
        "held {held:.3e}, half the trend {half:.3e}"
    );
    assert!(
        whole < half,
        "half the trend {half:.3e}, the whole {whole:.3e}"
    );
}

/// Without an estimate filter there is no trend to read: the plan holds `F` whatever
/// `trend` says, exactly as with `trend = 0`.
#[test]
fn without_an_estimate_filter_the_trend_changes_nothing() {
    let (held, _) = ramp_plan(0.0, Trend::always(0.0), false);
    let (trend, _) = ramp_plan(0.0, Trend::always(1.0), false);
    assert_eq!(held, trend);
}

/// Which fraction of the trend a plan follows depends on the references: `at_rest` once
/// they have rested for `hold_after` (1 s here, after 3 s at 0), `moving` while one moves
/// (a ramp); the other is then ignored, exactly.
#[test]
fn the_trend_at_rest_applies_once_the_references_rest_and_only_then() {
    let resting = |moving, at_rest| ramp_plan(0.05, Trend { moving, at_rest }, false).0;
    assert_eq!(resting(1.0, 0.0), resting(0.0, 0.0));
    assert_eq!(resting(0.0, 0.5), resting(0.5, 0.5));
    assert_ne!(resting(0.5, 0.5), resting(0.0, 0.0));
    let moving = |moving, at_rest| ramp_plan(0.05, Trend { moving, at_rest }, true).0;
    assert_eq!(moving(0.5, 0.0), moving(0.5, 1.0));
    assert_ne!(moving(0.5, 0.0), moving(0.0, 0.0));
}

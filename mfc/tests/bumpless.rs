//! Changes of gains, alpha, kind and law while running do not bump the output.

mod common;

use common::Rk4Plant;
use mfc::{
    AdrcParams, Channel, ChannelConfig, ControllerKind, LawConfig, Order, OutputMapConfig,
    PidParams, Reference,
};

const H: f64 = 0.01;

fn reference(t: f64) -> Reference {
    Reference {
        y: 0.5 * (1.3 * t).sin(),
        dy: 0.65 * (1.3 * t).cos(),
        ddy: -0.845 * (1.3 * t).sin(),
    }
}

fn plant() -> Rk4Plant<2> {
    // y'' = -2 y' - 3 y + 4 u + 1, measured y = x0.
    Rk4Plant {
        x: [0.1, 0.0],
        deriv: |x, u| [x[1], -2.0 * x[1] - 3.0 * x[0] + 4.0 * u + 1.0],
    }
}

fn ip(kind: ControllerKind, order: Order, alpha: f64, kp: f64, ki: f64, kd: f64) -> ChannelConfig {
    ChannelConfig {
        law: LawConfig::intelligent(kind, order, alpha, [kp, ki, kd], 10),
        output: OutputMapConfig::default(),
    }
}

/// Run 3 s, switch to `to` at t = 1.5 s, and return the largest output step of the settled
/// loop before the switch, the step at the switch, and the largest in the 9 steps after it
/// (which the new law's own dynamics may legitimately enlarge).
fn switch(from: ChannelConfig, to: ChannelConfig) -> (f64, f64, f64) {
    let mut ch: Channel = Channel::new(&from).unwrap();
    let mut p = plant();
    let mut last: Option<f64> = None;
    let (mut largest, mut at_switch, mut after) = (0.0f64, 0.0, 0.0f64);
    for k in 0..300 {
        let t = k as f64 * H;
        if k == 150 {
            ch.reconfigure(&to).unwrap();
        }
        let o = ch.step(t, p.x[0], &reference(t)).unwrap();
        if let Some(prev) = last {
            let jump = (o.v - prev).abs();
            if (50..150).contains(&k) {
                largest = largest.max(jump);
            }
            if k == 150 {
                at_switch = jump;
            }
            if (151..160).contains(&k) {
                after = after.max(jump);
            }
        }
        last = Some(o.v);
        p.advance(H, o.v, 10);
    }
    (largest, at_switch, after)
}

#[test]
fn changes_are_bumpless() {
    use ControllerKind::*;
    let cases = [
        (
            "Kp x4",
            ip(P, Order::One, 4.0, 5.0, 0.0, 0.0),
            ip(P, Order::One, 4.0, 20.0, 0.0, 0.0),
        ),
        (
            "alpha x3",
            ip(P, Order::One, 4.0, 5.0, 0.0, 0.0),
            ip(P, Order::One, 12.0, 5.0, 0.0, 0.0),
        ),
        (
            "iP -> iPI",
            ip(P, Order::One, 4.0, 5.0, 0.0, 0.0),
            ip(PI, Order::One, 4.0, 5.0, 10.0, 0.0),
        ),
        (
            "iPI -> iP",
            ip(PI, Order::One, 4.0, 5.0, 10.0, 0.0),
            ip(P, Order::One, 4.0, 5.0, 0.0, 0.0),
        ),
        (
            "iP -> iPD (n=2)",
            ip(P, Order::One, 4.0, 5.0, 0.0, 0.0),
            ip(PD, Order::Two, 4.0, 25.0, 0.0, 10.0),
        ),
        (
            "iP -> PID",
            ip(P, Order::One, 4.0, 5.0, 0.0, 0.0),
            ChannelConfig {
                law: LawConfig::Pid {
                    params: PidParams {
                        kp: 3.0,
                        ki: 5.0,
                        ..Default::default()
                    },
                },
                output: OutputMapConfig::default(),
            },
        ),
        (
            "iP -> ADRC",
            ip(P, Order::One, 4.0, 5.0, 0.0, 0.0),
            ChannelConfig {
                law: LawConfig::Adrc {
                    params: AdrcParams {
                        order: Order::One,
                        b0: 4.0,
                        wc: 5.0,
                        wo: 25.0,
                    },
                },
                output: OutputMapConfig::default(),
            },
        ),
        (
            "PID gains",
            ChannelConfig {
                law: LawConfig::Pid {
                    params: PidParams {
                        kp: 3.0,
                        ki: 5.0,
                        ..Default::default()
                    },
                },
                output: OutputMapConfig::default(),
            },
            ChannelConfig {
                law: LawConfig::Pid {
                    params: PidParams {
                        kp: 9.0,
                        ki: 2.0,
                        ..Default::default()
                    },
                },
                output: OutputMapConfig::default(),
            },
        ),
    ];
    for (name, from, to) in cases {
        let (largest, at_switch, after) = switch(from, to);
        eprintln!(
            "{name}: largest step {largest:.4}, at switch {at_switch:.4}, just after {after:.4}"
        );
        // The step at the switch is no larger than an ordinary step of the settled loop.
        assert!(
            at_switch <= 1.5 * largest,
            "{name}: {at_switch} vs {largest}"
        );
    }
}

/// The very first output after a gain change equals what the old gains would have given.
#[test]
fn first_output_after_change_is_the_old_one() {
    let from = ip(ControllerKind::P, Order::One, 4.0, 5.0, 0.0, 0.0);
    let to = ip(ControllerKind::P, Order::One, 8.0, 30.0, 0.0, 0.0);
    let mut a: Channel = Channel::new(&from).unwrap();
    let mut p = plant();
    for k in 0..100 {
        let t = k as f64 * H;
        let o = a.step(t, p.x[0], &reference(t)).unwrap();
        p.advance(H, o.v, 10);
    }
    let mut b = a.clone();
    b.reconfigure(&to).unwrap();
    let t = 1.0;
    let ua = a.step(t, p.x[0], &reference(t)).unwrap().v;
    let ub = b.step(t, p.x[0], &reference(t)).unwrap().v;
    assert!((ua - ub).abs() < 1e-9, "{ua} vs {ub}");
    // ... and the difference then fades: 1 s later b runs on its own gains.
    assert_eq!(b.config().law, to.law);
}

/// A channel given its input from outside (`step_input`, commissioning's excitation):
/// the output map applies to that input, the law's estimator sees it as applied (on `y'
/// = 2 u`, an iP with the true `α` estimates `F` = 0 although its own `u` was never
/// sent), a non-finite input moves nothing, and the law takes over bumplessly.
#[test]
fn an_input_from_outside_is_what_the_law_sees_applied() {
    let config = ChannelConfig {
        law: LawConfig::intelligent(ControllerKind::P, Order::One, 2.0, [1.0, 0.0, 0.0], 10),
        output: OutputMapConfig {
            min: -1.0,
            max: 1.0,
            ..OutputMapConfig::default()
        },
    };
    let mut ch: Channel = Channel::new(&config).unwrap();
    let r = Reference {
        y: 0.3,
        dy: 0.0,
        ddy: 0.0,
    };
    let (mut y, mut last) = (0.0, None);
    for k in 0..40 {
        let t = k as f64 * H;
        let u = if k % 20 < 10 { 0.5 } else { 3.0 };
        let o = ch.step_input(t, y, &r, u).unwrap();
        assert_eq!((o.u, o.v), (u, u.min(1.0)), "sample {k}");
        y += 2.0 * o.v * H;
        last = o.f_est;
    }
    let f = last.expect("an estimate after a window");
    assert!(
        f.abs() < 1e-9,
        "F_est {f}: the law took its own u for applied"
    );
    let before = ch.clone();
    assert!(ch.step_input(0.4, y, &r, f64::NAN).is_err());
    assert_eq!(
        format!("{before:?}"),
        format!("{ch:?}"),
        "a refused input moved nothing"
    );
    // The law commands again: e = y - 0.3, u = -(F + kp e) / alpha, no jump beyond that.
    let o = ch.step(0.4, y, &r).unwrap();
    let expected = -(0.0 + (y - 0.3)) / 2.0;
    assert!(
        (o.u - expected).abs() < 1e-6,
        "u {} expected {expected}",
        o.u
    );
}

//! `feedforward_within_range`: a reference's feedforward that opposes the rest of the law
//! and would saturate the command is cut for that step, kept in the proportion of the
//! range the rest leaves unused; everywhere else the law runs as without the rule, to the
//! bit.
//!
//! Each test runs two channels, the rule on and off, each closed around its own exact
//! double integrator `y'' = F + g v` (the ultra-local model itself, `F = -1`), on a shaped
//! step: one the actuator can follow, one it cannot. Each runs for a plant gain `g` of 1
//! and of -1 (`alpha` of the same sign), and with and without a smooth dead-zone map.

use mfc::{
    Channel, ChannelConfig, ChannelOutput, ControllerKind, EstimatorConfig, IntelligentController,
    IntelligentParams, LawConfig, Order, OutputMapConfig, Reference,
};

const H: f64 = 0.01;
const LIMIT: f64 = 3.0;
const F: f64 = -1.0;

/// A plant's gain and its channel's dead-zone compensation.
#[derive(Debug, Clone, Copy)]
struct Case {
    gain: f64,
    dead_zone: f64,
}

const CASES: [Case; 4] = [
    Case {
        gain: 1.0,
        dead_zone: 0.0,
    },
    Case {
        gain: -1.0,
        dead_zone: 0.0,
    },
    Case {
        gain: 1.0,
        dead_zone: 0.5,
    },
    Case {
        gain: -1.0,
        dead_zone: 0.5,
    },
];

fn params(rule: bool, case: Case) -> IntelligentParams {
    IntelligentParams {
        kind: ControllerKind::PD,
        order: Order::Two,
        alpha: case.gain,
        kp: 9.0,
        kd: 6.0,
        feedforward_within_range: rule,
        ..IntelligentParams::default()
    }
}

fn estimator() -> EstimatorConfig {
    EstimatorConfig {
        window: 10,
        ..EstimatorConfig::default()
    }
}

fn channel(rule: bool, case: Case) -> Channel {
    channel_with(
        rule,
        case,
        OutputMapConfig {
            min: -LIMIT,
            max: LIMIT,
            dead_zone: case.dead_zone,
            smoothing: 0.2 * case.dead_zone,
            ..OutputMapConfig::default()
        },
    )
}

fn channel_with(rule: bool, case: Case, output: OutputMapConfig) -> Channel {
    Channel::new(&ChannelConfig {
        law: LawConfig::Intelligent {
            params: params(rule, case),
            estimator: estimator(),
        },
        output,
    })
    .unwrap()
}

/// A quintic step of `height` over `duration` seconds from t = 1 s, with its derivatives.
fn shaped_step(t: f64, height: f64, duration: f64) -> Reference {
    let s = ((t - 1.0) / duration).clamp(0.0, 1.0);
    let inside = if (0.0..1.0).contains(&((t - 1.0) / duration)) {
        1.0
    } else {
        0.0
    };
    Reference {
        y: height * s * s * s * (10.0 - 15.0 * s + 6.0 * s * s),
        dy: inside * height / duration * 30.0 * s * s * (1.0 - s) * (1.0 - s),
        ddy: inside * height / (duration * duration) * 60.0 * s * (1.0 - s) * (1.0 - 2.0 * s),
    }
}

/// The plant `y'' = F + gain v`, exact over a period of constant `v`.
struct Plant {
    gain: f64,
    y: f64,
    dy: f64,
}

impl Plant {
    fn new(gain: f64) -> Self {
        Plant {
            gain,
            y: 0.0,
            dy: 0.0,
        }
    }

    fn advance(&mut self, v: f64) {
        let acc = F + self.gain * v;
        self.y += H * self.dy + 0.5 * H * H * acc;
        self.dy += H * acc;
    }
}

/// Each period's reference and output of a channel closed around its own plant, 6 s.
fn run(
    rule: bool,
    case: Case,
    reference: impl Fn(f64) -> Reference,
) -> Vec<(Reference, ChannelOutput)> {
    run_channel(channel(rule, case), case.gain, reference)
}

fn run_channel(
    mut ch: Channel,
    gain: f64,
    reference: impl Fn(f64) -> Reference,
) -> Vec<(Reference, ChannelOutput)> {
    let mut plant = Plant::new(gain);
    (0..600)
        .map(|k| {
            let t = k as f64 * H;
            let r = reference(t);
            let o = ch.step(t, plant.y, &r).unwrap();
            plant.advance(o.v);
            (r, o)
        })
        .collect()
}

fn rms(run: &[(Reference, ChannelOutput)]) -> f64 {
    let sum: f64 = run.iter().map(|(_, o)| o.error * o.error).sum();
    (sum / run.len() as f64).sqrt()
}

#[test]
fn a_reference_the_actuator_can_follow_runs_as_without_the_rule() {
    // 0.1 over 3 s: at most 0.06 of acceleration, where the actuator gives 3 - 1.
    let slow = |t| shaped_step(t, 0.1, 3.0);
    for case in CASES {
        let (on, off) = (run(true, case, slow), run(false, case, slow));
        // While the reference moves (where the rule could act), the command stays inside.
        let moving: Vec<_> = on.iter().filter(|(r, _)| r.ddy != 0.0).collect();
        assert!(moving.len() > 250, "the reference moved");
        assert!(moving.iter().all(|(_, o)| o.v.abs() < LIMIT), "{case:?}");
        for (k, (a, b)) in on.iter().zip(&off).enumerate() {
            assert_eq!(a.1.v.to_bits(), b.1.v.to_bits(), "{case:?} period {k}");
        }
    }
}

#[test]
fn a_feedforward_against_the_law_at_the_limit_is_cut() {
    for case in CASES {
        feedforward_against_the_law_at_the_limit_is_cut(case);
    }
}

fn feedforward_against_the_law_at_the_limit_is_cut(case: Case) {
    // 1 over 0.3 s: about 64 of acceleration, then as much braking.
    let fast = |t| shaped_step(t, 1.0, 0.3);
    let (on, off) = (run(true, case, fast), run(false, case, fast));
    let first = on
        .iter()
        .zip(&off)
        .position(|(a, b)| a.1.v != b.1.v)
        .unwrap_or_else(|| panic!("{case:?}: the rule changed no command"));
    // The voltage that pushes the plant up (the reference's way).
    let up = case.gain * LIMIT;
    // Until then the two ran alike, the command saturated in the reference's direction
    // while it accelerated away from the plant: the feedforward that agrees is kept.
    let pushed = off[..first]
        .iter()
        .filter(|(r, o)| r.ddy > 0.0 && o.v == up)
        .count();
    assert!(
        pushed > 0,
        "{case:?}: no saturated push before period {first}"
    );
    // The first difference: the reference brakes while the plant is still behind; without
    // the rule the command saturates on the braking, with it the braking is cut.
    let (r, with) = &on[first];
    let without = &off[first].1;
    assert!(
        r.ddy < 0.0,
        "{case:?}: the reference brakes at period {first}"
    );
    assert!(
        with.error < 0.0,
        "{case:?}: the plant is behind at period {first}"
    );
    assert_eq!(without.v, -up, "{case:?}");
    assert!(
        with.v * case.gain > -LIMIT,
        "{case:?} period {first}: {} with the rule",
        with.v
    );
    // And it pays: the plant arrives sooner and overshoots less.
    let (a, b) = (rms(&on), rms(&off));
    assert!(a < 0.9 * b, "{case:?}: RMS {a} with the rule, {b} without");
}

/// A range with a side of width 0 (a heater's `[0, max]`): a rest of the law that asks
/// for that side asks for all of it, so an opposing feedforward at the limit goes.
#[test]
fn a_side_of_width_zero_is_all_used() {
    let one_sided = OutputMapConfig {
        min: 0.0,
        max: LIMIT,
        ..OutputMapConfig::default()
    };
    // Down by 1 over 0.3 s: the braking (y*'' > 0) comes while the plant is still above.
    let fast_down = |t| shaped_step(t, -1.0, 0.3);
    let case = CASES[0];
    let on = run_channel(channel_with(true, case, one_sided), 1.0, fast_down);
    let off = run_channel(channel_with(false, case, one_sided), 1.0, fast_down);
    let first = on
        .iter()
        .zip(&off)
        .position(|(a, b)| a.1.v != b.1.v)
        .expect("the rule changed some command");
    let (r, with) = &on[first];
    assert!(r.ddy > 0.0, "the reference brakes at period {first}");
    assert!(with.error > 0.0, "the plant is above it at period {first}");
    assert_eq!((with.v, off[first].1.v), (0.0, LIMIT), "period {first}");
}

#[test]
fn a_controller_on_its_own_keeps_the_feedforward() {
    // No output map, no range: the rule cannot judge, and changes nothing.
    let fast = |t| shaped_step(t, 1.0, 0.3);
    let case = CASES[0];
    let mut on = IntelligentController::<256>::new(params(true, case), estimator()).unwrap();
    let mut off = IntelligentController::<256>::new(params(false, case), estimator()).unwrap();
    let mut plant = Plant::new(case.gain);
    for k in 0..300 {
        let t = k as f64 * H;
        let r = fast(t);
        let a = on.step(t, plant.y, &r).unwrap();
        let b = off.step(t, plant.y, &r).unwrap();
        assert_eq!(a.u.to_bits(), b.u.to_bits(), "period {k}");
        plant.advance(a.u.clamp(-LIMIT, LIMIT));
        on.set_applied(a.u.clamp(-LIMIT, LIMIT)).unwrap();
        off.set_applied(b.u.clamp(-LIMIT, LIMIT)).unwrap();
    }
}

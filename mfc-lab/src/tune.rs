//! A fair tuner: the same search, with the same budget of simulated runs, for every
//! controller kind, minimising the tracking IAE.
//!
//! The objective is IAE with penalties on saturation beyond 5 % of samples and on actuator
//! chatter (see [`SATURATION_ALLOWANCE`] and [`CHATTER_WEIGHT`]): IAE alone is minimised by
//! bang-bang control.
//!
//! Gains are searched in log space (each is a scale, not an offset; signs are kept).
//! A third of the budget goes to seeded random samples around the starting point
//! (σ = 1 in ln, i.e. a factor e either way), the rest to a compass search from the best
//! point found (steps of ×1.65, halved when no move helps). The objective is the sum over
//! channels of IAE / (duration · reference range): dimensionless, so the azimuth velocity
//! (about 1e-3 rad/ms) and the pitch (about 0.3 rad) weigh the same.
//!
//! Starting points are first guesses any engineer would write: the paper's gains for the
//! intelligent controllers, and, for PID and ADRC, gains computed from the *linear model's*
//! DC gains and time constants (knowledge the intelligent controllers do not get).

use mfc::{AdrcParams, ControllerKind, LawConfig, Order, PidParams};

use aero_sim::rng::Rng;
use plant::scenario::{ControllerSet, Scenario};

use crate::offline::{simulate_timed, IoTiming, RunError};
use mfc::trajectory::evaluate;

/// Controller kinds with a built-in starting point for the AERO. Other plants give theirs
/// as a controller file (`mfc-lab tune --start FILE`): a first guess needs the plant's
/// scales, which only its author knows.
pub const KINDS: [&str; 5] = ["ip", "ipi", "ipd", "pid", "adrc"];

fn intelligent(
    kind: ControllerKind,
    order: Order,
    alpha: f64,
    kp: f64,
    ki: f64,
    kd: f64,
    window: usize,
) -> LawConfig {
    LawConfig::intelligent(kind, order, alpha, [kp, ki, kd], window)
}

/// The pitch iPD's answer to the encoder's staircase: `y'` from the model-based observer at
/// 30 rad/s, `F_est` through a 50 ms low-pass.
fn quantisation_aware(mut law: LawConfig) -> LawConfig {
    if let LawConfig::Intelligent { params, .. } = &mut law {
        params.derivative_observer = 30.0;
        params.estimate_filter = 0.05;
    }
    law
}

/// Cuts a reference feedforward that brakes against the law at the actuator's limit
/// (`plants/aero/controllers/ipd.toml`: steps faster than the rotors).
fn within_range(mut law: LawConfig) -> LawConfig {
    if let LawConfig::Intelligent { params, .. } = &mut law {
        params.feedforward_within_range = true;
    }
    law
}

/// Estimates from 5 intervals on while the window fills, rather than hold 0 V for a
/// window (`plants/aero/controllers/ipd.toml`: the arm sags under the mass meanwhile).
fn started_early(mut law: LawConfig) -> LawConfig {
    if let LawConfig::Intelligent { estimator, .. } = &mut law {
        estimator.first_window = 5;
    }
    law
}

/// The untuned starting point of a kind on the AERO.
pub fn starting_point(kind: &str) -> Option<ControllerSet> {
    use ControllerKind::*;
    let channels = match kind {
        // The paper's structure taken literally: iP (n = 1) on both channels. Azimuth: the
        // paper's gains. Pitch: the paper's (alpha 5, Kp 500) diverge; these are the best
        // that stay bounded (a bang-bang limit cycle: n = 1 gives no damping, see README).
        "ip" => vec![
            intelligent(P, Order::One, 0.001, 0.5, 0.0, 0.0, 10),
            intelligent(P, Order::One, 0.01, 2.0, 0.0, 0.0, 5),
        ],
        "ipi" => vec![
            intelligent(PI, Order::One, 0.001, 0.5, 0.1, 0.0, 10),
            intelligent(PI, Order::One, 0.01, 2.0, 0.5, 0.0, 5),
        ],
        // The paper's own remedy for weak friction: n = 2 (iPD) on the pitch, the error
        // dynamics e'' + 3 e' + 9 e = 0 (3 rad/s, damping 0.5), a 20-sample window; alpha,
        // the observer and the estimate filter as `plants/aero/controllers/ipd.toml`
        // explains. Azimuth: the paper's iP. Both cut an unreachable feedforward.
        "ipd" => vec![
            within_range(started_early(intelligent(
                P,
                Order::One,
                0.001,
                0.5,
                0.0,
                0.0,
                10,
            ))),
            within_range(started_early(quantisation_aware(intelligent(
                PD,
                Order::Two,
                0.2,
                9.0,
                0.0,
                3.0,
                20,
            )))),
        ],
        // The same as first shipped: alpha by the magnitude rule for the step map (0.1),
        // y' from the derivative filter, F_est unfiltered.
        "ipd-plain" => vec![
            started_early(intelligent(P, Order::One, 0.001, 0.5, 0.0, 0.0, 10)),
            started_early(intelligent(PD, Order::Two, 0.1, 9.0, 0.0, 3.0, 20)),
        ],
        // From the linear model (default mixing): azimuth DC gain |Kyp|/Dy/1000 = 1.2e-4
        // (rad/ms)/V, time constant 1 s; pitch DC gain Kpy/Ksp = 0.056 rad/V, natural
        // frequency 1.3 rad/s, damping 0.12.
        "pid" => vec![
            LawConfig::Pid {
                params: PidParams {
                    kp: 5000.0,
                    ki: 5000.0,
                    kd: 0.0,
                    ..Default::default()
                },
            },
            LawConfig::Pid {
                params: PidParams {
                    kp: 50.0,
                    ki: 50.0,
                    kd: 10.0,
                    ..Default::default()
                },
            },
        ],
        // b0 from the model: |Kyp|/Jy/1000 = 1.2e-4 (n = 1), Kpy/Jp = 0.096 (n = 2).
        "adrc" => vec![
            LawConfig::Adrc {
                params: AdrcParams {
                    order: Order::One,
                    b0: 1.2e-4,
                    wc: 2.0,
                    wo: 10.0,
                },
            },
            LawConfig::Adrc {
                params: AdrcParams {
                    order: Order::Two,
                    b0: 0.096,
                    wc: 3.0,
                    wo: 15.0,
                },
            },
        ],
        _ => return None,
    };
    Some(ControllerSet {
        name: kind.to_string(),
        description: "untuned starting point".into(),
        channels,
    })
}

/// Pointers to the tunable gains of a law (all are positive scales, or signed for
/// alpha/b0).
fn gains(law: &mut LawConfig) -> Vec<&mut f64> {
    match law {
        LawConfig::Intelligent { params, .. } => {
            let kind = params.kind;
            let mut g = vec![&mut params.alpha, &mut params.kp];
            if kind.has_integral() {
                g.push(&mut params.ki);
            }
            if kind.has_derivative() {
                g.push(&mut params.kd);
            }
            g
        }
        LawConfig::Pid { params } => {
            let mut g = vec![&mut params.kp, &mut params.ki];
            if params.kd != 0.0 {
                g.push(&mut params.kd);
            }
            g
        }
        LawConfig::Adrc { params } => vec![&mut params.b0, &mut params.wc, &mut params.wo],
    }
}

fn to_logs(set: &ControllerSet) -> Vec<f64> {
    let mut set = set.clone();
    set.channels
        .iter_mut()
        .flat_map(|l| {
            gains(l)
                .into_iter()
                .map(|g| g.abs().max(1e-12).ln())
                .collect::<Vec<_>>()
        })
        .collect()
}

fn from_logs(base: &ControllerSet, x: &[f64]) -> ControllerSet {
    let mut set = base.clone();
    let mut i = 0;
    for law in &mut set.channels {
        for g in gains(law) {
            *g = g.signum() * x[i].exp();
            i += 1;
        }
    }
    set
}

/// Saturation allowed before the objective starts to penalise it (fraction of samples).
///
/// IAE alone rewards bang-bang control: left free, the search drives every kind into
/// chattering between ±24 V, which no one would run on a real rig. Beyond 5 % of samples
/// at a limit, each extra percent costs as much as 10 % of the reference range in IAE.
pub const SATURATION_ALLOWANCE: f64 = 0.05;

/// Weight of actuator chatter: mean |Δv| per sample as a fraction of the largest input the
/// actuator can give (24 V on the AERO).
///
/// Quantised encoders make every high-gain loop chatter; a chatter of 9 V per sample (a
/// third of the range, every 10 ms) costs about as much as the whole IAE of a good loop.
pub const CHATTER_WEIGHT: f64 = 0.1;

/// Objective: sum over channels of IAE / (duration · reference range), plus the saturation
/// and chatter penalties, plus 1 per hit of a mechanical limit (the AERO's pitch stop),
/// on a run with the I/O timing `timing` (the lockstep loop's by default). Invalid gains
/// (refused by the core) cost infinity.
pub fn objective(
    scenario: &Scenario,
    set: &ControllerSet,
    timing: IoTiming,
) -> Result<f64, RunError> {
    let r = match simulate_timed(scenario, set, false, timing) {
        Ok(r) => r,
        Err(RunError::Controller { .. } | RunError::Scenario(_)) => return Ok(f64::INFINITY),
        Err(e) => return Err(e),
    };
    let steps = scenario.steps();
    let mut j = r.summary.limit_hits as f64;
    for (m, c) in r.summary.channels.iter().zip(&scenario.channels) {
        let (lo, hi) = (0..steps).fold((f64::MAX, f64::MIN), |(lo, hi), k| {
            let y = evaluate(&c.reference, k as f64 * scenario.period).y;
            (lo.min(y), hi.max(y))
        });
        j += m.iae / (scenario.duration * (hi - lo).max(1e-12));
        j += 10.0 * (m.saturated_fraction - SATURATION_ALLOWANCE).max(0.0);
        j += CHATTER_WEIGHT * m.control_variation / c.input_scale();
    }
    Ok(if j.is_finite() { j } else { f64::INFINITY })
}

/// Result of a tuning.
#[derive(Debug, Clone)]
pub struct Tuned {
    /// The best set found.
    pub set: ControllerSet,
    /// Its objective.
    pub cost: f64,
    /// The starting point's objective.
    pub start_cost: f64,
    /// Runs used.
    pub runs: usize,
}

/// Tune `start` on `scenario` with exactly `budget` simulated runs, each with the I/O
/// timing `timing` (a law for a fieldbus whose values come late is tuned with them late).
/// `progress` is called after every run with (runs done, best cost).
pub fn tune(
    scenario: &Scenario,
    start: &ControllerSet,
    budget: usize,
    seed: u64,
    timing: IoTiming,
    mut progress: impl FnMut(usize, f64),
) -> Result<Tuned, RunError> {
    timing.check(scenario.period)?;
    let x0 = to_logs(start);
    let dims = x0.len();
    let mut rng = Rng::new(seed);
    let mut runs = 0usize;
    let eval = |x: &[f64], runs: &mut usize| -> Result<f64, RunError> {
        *runs += 1;
        objective(scenario, &from_logs(start, x), timing)
    };
    let start_cost = eval(&x0, &mut runs)?;
    let (mut best_x, mut best) = (x0.clone(), start_cost);
    progress(runs, best);
    let random_phase = budget / 3;
    while runs < random_phase.max(1) && runs < budget {
        let x: Vec<f64> = x0.iter().map(|v| v + rng.normal()).collect();
        let c = eval(&x, &mut runs)?;
        if c < best {
            best = c;
            best_x = x;
        }
        progress(runs, best);
    }
    let mut step = 0.5;
    'search: while runs < budget && step > 1e-3 {
        let mut moved = false;
        for d in 0..dims {
            for dir in [1.0, -1.0] {
                if runs >= budget {
                    break 'search;
                }
                let mut x = best_x.clone();
                x[d] += dir * step;
                let c = eval(&x, &mut runs)?;
                if c < best {
                    best = c;
                    best_x = x;
                    moved = true;
                }
                progress(runs, best);
            }
        }
        if !moved {
            step /= 2.0;
        }
    }
    let mut set = from_logs(start, &best_x);
    let late = if timing == IoTiming::default() {
        String::new()
    } else {
        format!(", {timing}")
    };
    set.description = format!(
        "tuned by `mfc-lab tune` on {} with {} runs (seed {}{late}): IAE objective {:.4} from \
         {:.4}",
        scenario.name, runs, seed, best, start_cost
    );
    Ok(Tuned {
        set,
        cost: best,
        start_cost,
        runs,
    })
}

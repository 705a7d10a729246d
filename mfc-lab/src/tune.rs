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
//!
//! [`tune_family`] tunes for a family of plants instead of one (the robustness benchmark's,
//! [`crate::robust`]): the same search, each candidate run on every variation, minimising
//! the worst of its [`Margins`] against issue 30's bars. A law tuned for one plant sits on
//! that plant's edge (the heater's `ipd` goes to 14.8x its nominal RMS when the process is
//! twice as fast); one tuned for the family gives up some nominal RMS to stay off it.

use mfc::{AdrcParams, ControllerKind, LawConfig, Order, PidParams};

use aero_sim::rng::Rng;
use plant::scenario::{ControllerSet, Scenario};

use crate::offline::{simulate_timed, IoTiming, RunError};
use crate::robust::{self, Cell, Variation};
use mfc::trajectory::evaluate;
use serde::Serialize;

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

/// Pointers to the tunable gains of a law, searched as scales (signed for alpha and b0):
/// a gain of 0 is not among them, as no scale leaves 0 (a PID's `kd` or `ki` of 0 stays
/// 0); with `filters`, also an intelligent law's derivative observer bandwidth and
/// estimate filter where it has them (a family search: what held a slow rotor on the AERO
/// was as much the filters as the gains, `plants/aero/controllers/ipd-lag.toml`).
fn gains(law: &mut LawConfig, filters: bool) -> Vec<&mut f64> {
    match law {
        LawConfig::Intelligent { params, .. } => {
            let kind = params.kind;
            let mut g = vec![&mut params.alpha];
            if params.kp != 0.0 {
                g.push(&mut params.kp);
            }
            if kind.has_integral() && params.ki != 0.0 {
                g.push(&mut params.ki);
            }
            if kind.has_derivative() && params.kd != 0.0 {
                g.push(&mut params.kd);
            }
            if filters && params.derivative_observer > 0.0 {
                g.push(&mut params.derivative_observer);
            }
            if filters && params.estimate_filter > 0.0 {
                g.push(&mut params.estimate_filter);
            }
            g
        }
        LawConfig::Pid { params } => {
            let mut g = vec![&mut params.kp];
            if params.ki != 0.0 {
                g.push(&mut params.ki);
            }
            if params.kd != 0.0 {
                g.push(&mut params.kd);
            }
            g
        }
        LawConfig::Adrc { params } => vec![&mut params.b0, &mut params.wc, &mut params.wo],
    }
}

fn to_logs(set: &ControllerSet, filters: bool) -> Vec<f64> {
    let mut set = set.clone();
    set.channels
        .iter_mut()
        .flat_map(|l| {
            gains(l, filters)
                .into_iter()
                .map(|g| g.abs().max(1e-12).ln())
                .collect::<Vec<_>>()
        })
        .collect()
}

fn from_logs(base: &ControllerSet, x: &[f64], filters: bool) -> ControllerSet {
    let mut set = base.clone();
    let mut i = 0;
    for law in &mut set.channels {
        for g in gains(law, filters) {
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

/// The best point a [`search`] found.
struct Found {
    x: Vec<f64>,
    cost: f64,
    start_cost: f64,
    runs: usize,
}

/// The tuner's search in log space, `budget` evaluations of `cost`: a third seeded random
/// samples around `x0` (σ = 1 in ln), then a compass search from the best (steps of ×1.65,
/// halved when no move helps). `progress` after each, with (evaluations, best cost).
fn search(
    x0: &[f64],
    budget: usize,
    seed: u64,
    mut cost: impl FnMut(&[f64]) -> Result<f64, RunError>,
    mut progress: impl FnMut(usize, f64),
) -> Result<Found, RunError> {
    let dims = x0.len();
    let mut rng = Rng::new(seed);
    let mut runs = 1usize;
    let start_cost = cost(x0)?;
    let (mut best_x, mut best) = (x0.to_vec(), start_cost);
    progress(runs, best);
    let random_phase = budget / 3;
    while runs < random_phase.max(1) && runs < budget {
        let x: Vec<f64> = x0.iter().map(|v| v + rng.normal()).collect();
        runs += 1;
        let c = cost(&x)?;
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
                runs += 1;
                let c = cost(&x)?;
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
    Ok(Found {
        x: best_x,
        cost: best,
        start_cost,
        runs,
    })
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
    progress: impl FnMut(usize, f64),
) -> Result<Tuned, RunError> {
    timing.check(scenario.period)?;
    let found = search(
        &to_logs(start, false),
        budget,
        seed,
        |x| objective(scenario, &from_logs(start, x, false), timing),
        progress,
    )?;
    let (best_x, best, start_cost, runs) = (found.x, found.cost, found.start_cost, found.runs);
    let mut set = from_logs(start, &best_x, false);
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

/// The bars a family tuning is held to (issue 30's robustness bars), each the limit its
/// figure is divided by in [`Margins`]: a law meets them all when no margin exceeds 1.
#[derive(Debug, Clone, PartialEq)]
pub struct Bars {
    /// Per variation (by name), per channel: the lowest RMS any baseline (the untouched
    /// PID and ADRC) had there: a law at or under it lost to none.
    pub baseline: Vec<(String, Vec<f64>)>,
    /// Per channel: the nominal RMS not to exceed (the starting point's, so that robustness
    /// is not bought with the rig the law was written for).
    pub nominal: Vec<f64>,
    /// The largest RMS over the law's own nominal RMS on any variation and channel.
    pub own_ratio: f64,
    /// The largest chatter (mean |v(k) - v(k-1)|, in the plant's input units) on any
    /// variation and channel.
    pub chatter: f64,
}

impl Bars {
    /// The bars for a family: the baselines' best RMS per variation and channel from
    /// `baselines` (their cells over the family, every baseline's in the family's order),
    /// the nominal and, unless `chatter` is given, the chatter from `start`'s cells (the
    /// law is not to get noisier than it was), and `own_ratio`.
    ///
    /// A baseline run that hit a mechanical limit does not set a bar: it did not do better
    /// (where every baseline did, the bar is infinite: any safe run meets it). A bar that
    /// is not a positive number (a start whose nominal run diverged, or that never
    /// chattered) would make every candidate's margin the same: refused, with the reason.
    pub fn new(
        variations: &[Variation],
        baselines: &[Cell],
        start: &[Cell],
        own_ratio: f64,
        chatter: Option<f64>,
    ) -> Result<Self, RunError> {
        let channels = start.first().map_or(0, |c| c.rms.len());
        let baseline = variations
            .iter()
            .map(|v| {
                let cells: Vec<&Cell> = baselines
                    .iter()
                    .filter(|c| c.variation == v.name && c.safe)
                    .collect();
                // `f64::min` passes over a NaN: a baseline run without a number did not
                // do better either.
                let best = (0..channels)
                    .map(|ch| {
                        cells
                            .iter()
                            .filter_map(|c| c.rms.get(ch).copied())
                            .fold(f64::INFINITY, f64::min)
                    })
                    .collect();
                (v.name.clone(), best)
            })
            .collect();
        let worst_chatter = start
            .iter()
            .flat_map(|c| c.chatter.iter().copied())
            .fold(0.0, f64::max);
        let bars = Bars {
            baseline,
            nominal: start.first().map(|c| c.rms.clone()).unwrap_or_default(),
            own_ratio,
            chatter: chatter.unwrap_or(worst_chatter),
        };
        let positive = |x: f64| x.is_finite() && x > 0.0;
        if bars.nominal.is_empty() || !bars.nominal.iter().all(|&x| positive(x)) {
            return Err(RunError::Bench(format!(
                "the start's nominal RMS {:?} is not a positive number on every channel: \
                 start from a law that runs the nominal plant",
                bars.nominal
            )));
        }
        if !positive(bars.chatter) {
            return Err(RunError::Bench(format!(
                "the chatter bar {} is not a positive number (the start never changed its \
                 command): give it with --chatter",
                bars.chatter
            )));
        }
        Ok(bars)
    }
}

/// One law's figures over the family, each as a fraction of its bar (at most 1: met).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Margins {
    /// The largest RMS over the best baseline's, on any variation and channel.
    pub baseline: f64,
    /// The largest nominal RMS over the nominal bar, on any channel.
    pub nominal: f64,
    /// The worst RMS over the law's own nominal, over the bar.
    pub own_ratio: f64,
    /// The worst chatter over the bar.
    pub chatter: f64,
    /// Every run finished without hitting a mechanical limit.
    pub safe: bool,
}

impl Margins {
    /// `cells`: one law over the family, nominal first (as [`robust::run`] gives them). A
    /// variation the bars have no baseline for, or a channel it lacks, is not a number.
    pub fn of(cells: &[Cell], bars: &Bars) -> Self {
        let most = |x: &mut dyn Iterator<Item = f64>| {
            x.fold(0.0, |m: f64, v| {
                if v.is_nan() || m.is_nan() {
                    f64::NAN
                } else {
                    m.max(v)
                }
            })
        };
        // Bars are positive (`Bars::new`), or infinite where every baseline was unsafe.
        let bar = |b: f64| if b > 0.0 { b } else { f64::NAN };
        Margins {
            baseline: most(&mut cells.iter().flat_map(|c| {
                let best = bars.baseline.iter().find(|(v, _)| *v == c.variation);
                c.rms.iter().enumerate().map(move |(ch, r)| {
                    best.and_then(|(_, b)| b.get(ch))
                        .map_or(f64::NAN, |b| r / bar(*b))
                })
            })),
            nominal: most(
                &mut cells
                    .first()
                    .into_iter()
                    .flat_map(|c| c.rms.iter().zip(&bars.nominal).map(|(r, b)| r / bar(*b))),
            ),
            own_ratio: most(&mut cells.iter().flat_map(|c| c.ratio.iter().copied()))
                / bars.own_ratio,
            chatter: most(&mut cells.iter().flat_map(|c| c.chatter.iter().copied()))
                / bar(bars.chatter),
            safe: cells.iter().all(|c| c.safe),
        }
    }

    /// The worst of the four; infinite for an unsafe run or a figure that is not a
    /// number. What a family tuning minimises: at most 1 when every bar is met, and below
    /// that, the margin of the tightest.
    pub fn worst(&self) -> f64 {
        let all = [self.baseline, self.nominal, self.own_ratio, self.chatter];
        if !self.safe || all.iter().any(|x| x.is_nan()) {
            return f64::INFINITY;
        }
        all.into_iter().fold(0.0, f64::max)
    }
}

impl std::fmt::Display for Margins {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "against the best baseline {:.2}, nominal {:.2}, own ratio {:.2}, chatter {:.2}{}",
            self.baseline,
            self.nominal,
            self.own_ratio,
            self.chatter,
            if self.safe { "" } else { ", unsafe" }
        )
    }
}

/// Result of a family tuning.
#[derive(Debug, Clone)]
pub struct FamilyTuned {
    /// The best set found.
    pub set: ControllerSet,
    /// Its margins.
    pub margins: Margins,
    /// The starting point's margins.
    pub start_margins: Margins,
    /// Candidates evaluated (each over the whole family).
    pub evaluations: usize,
}

/// Tune `start` for the whole family `variations` of `scenario`'s plant: `budget`
/// candidates, each run on every variation (over `threads` threads), minimising the
/// worst of its [`Margins`] against `bars`. Besides the gains, the search scales an
/// intelligent law's observer bandwidth and estimate filter where it has them. A
/// candidate the core refuses (a gain out of range) costs infinity. `progress` is
/// called after every candidate with (candidates done, best cost).
#[allow(clippy::too_many_arguments)]
pub fn tune_family(
    scenario: &Scenario,
    start: &ControllerSet,
    variations: &[Variation],
    bars: &Bars,
    budget: usize,
    seed: u64,
    threads: usize,
    progress: impl FnMut(usize, f64),
) -> Result<FamilyTuned, RunError> {
    let margins = |set: &ControllerSet| -> Result<Option<Margins>, RunError> {
        if scenario.check_controller(set).is_err() {
            return Ok(None);
        }
        let cells = robust::run(scenario, std::slice::from_ref(set), variations, threads)?;
        Ok(Some(Margins::of(&cells, bars)))
    };
    scenario.check_controller(start).map_err(|e| {
        RunError::Bench(format!(
            "the starting point `{}` is refused: {e}",
            start.name
        ))
    })?;
    let start_margins = margins(start)?.expect("checked above");
    let x0 = to_logs(start, true);
    // The search's first candidate is the start, just measured.
    let cost = |x: &[f64]| match x == x0.as_slice() {
        true => Ok(start_margins.worst()),
        false => Ok(margins(&from_logs(start, x, true))?.map_or(f64::INFINITY, |m| m.worst())),
    };
    let found = search(&x0, budget, seed, cost, progress)?;
    // Nothing better than the start: the start itself, not its gains through ln and exp.
    let (mut set, margins) = if found.x == x0 {
        (start.clone(), start_margins)
    } else {
        let set = from_logs(start, &found.x, true);
        let m = margins(&set)?
            .ok_or_else(|| RunError::Bench(format!("the tuned set `{}` is refused", set.name)))?;
        (set, m)
    };
    set.description = format!(
        "tuned by `mfc-lab tune --family` on {} over {} variations with {} candidates (seed \
         {seed}): worst margin {:.3} from {:.3} ({margins})",
        scenario.name,
        variations.len(),
        found.runs,
        margins.worst(),
        start_margins.worst(),
    );
    Ok(FamilyTuned {
        set,
        margins,
        start_margins,
        evaluations: found.runs,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::robust::{family_of, Factor};

    fn cell(variation: &str, rms: [f64; 2], nominal: [f64; 2], chatter: f64) -> Cell {
        Cell {
            controller: "x".into(),
            variation: variation.into(),
            rms: rms.to_vec(),
            ratio: vec![rms[0] / nominal[0], rms[1] / nominal[1]],
            saturated: vec![0.0; 2],
            chatter: vec![chatter, chatter / 2.0],
            hold_flips: vec![0.0; 2],
            safe: true,
        }
    }

    #[test]
    fn margins_are_each_bar_as_a_fraction_of_its_limit() {
        let family = family_of(&[Factor::Mass], 1, 0);
        assert_eq!(family.len(), 2, "nominal and 10 g");
        let names: Vec<&str> = family.iter().map(|v| v.name.as_str()).collect();
        let (n, m) = (names[0], names[1]);
        // Two baselines: the bar per variation and channel is the lower of the two.
        let base = [
            cell(n, [1.0, 4.0], [1.0, 4.0], 0.1),
            cell(m, [2.0, 4.0], [1.0, 4.0], 0.1),
            cell(n, [2.0, 2.0], [2.0, 2.0], 0.1),
            cell(m, [3.0, 8.0], [2.0, 2.0], 0.1),
        ];
        let start = [
            cell(n, [0.5, 1.0], [0.5, 1.0], 0.4),
            cell(m, [1.0, 3.0], [0.5, 1.0], 0.8),
        ];
        let bars = Bars::new(&family, &base, &start, 2.0, None).unwrap();
        assert_eq!(
            bars.baseline,
            vec![
                (n.to_string(), vec![1.0, 2.0]),
                (m.to_string(), vec![2.0, 4.0])
            ]
        );
        assert_eq!(bars.nominal, vec![0.5, 1.0]);
        assert_eq!(bars.chatter, 0.8, "the start's worst, unless given");
        let start_margins = Margins::of(&start, &bars);
        assert_eq!(start_margins.baseline, 0.75, "3 against the bar's 4");
        assert_eq!(start_margins.nominal, 1.0);
        assert_eq!(
            start_margins.own_ratio, 1.5,
            "3x its nominal over a bound of 2"
        );
        assert_eq!(start_margins.chatter, 1.0);
        assert_eq!(start_margins.worst(), 1.5);
        // A law that holds every bar has every margin at most 1, and the worst names the
        // tightest.
        let good = [
            cell(n, [0.4, 0.9], [0.4, 0.9], 0.3),
            cell(m, [0.6, 1.7], [0.4, 0.9], 0.2),
        ];
        let g = Margins::of(&good, &bars);
        assert_eq!(
            g.worst(),
            g.baseline.max(g.nominal).max(g.own_ratio).max(g.chatter)
        );
        assert!(g.worst() <= 1.0, "{g}");
        // Unsafe or not a number: infinitely bad, whatever the rest.
        let mut bad = good.clone();
        bad[1].safe = false;
        assert_eq!(Margins::of(&bad, &bars).worst(), f64::INFINITY);
        let mut nan = good.clone();
        nan[1].rms[0] = f64::NAN;
        assert_eq!(Margins::of(&nan, &bars).worst(), f64::INFINITY, "an RMS");
        let mut nan = good.clone();
        nan[1].ratio[0] = f64::NAN;
        assert_eq!(Margins::of(&nan, &bars).worst(), f64::INFINITY, "a ratio");
        // A variation the bars do not know is not judged as met.
        let mut stray = good.clone();
        stray[1].variation = "elsewhere".into();
        assert_eq!(Margins::of(&stray, &bars).worst(), f64::INFINITY);
        // A chatter bar given replaces the start's.
        assert_eq!(
            Bars::new(&family, &base, &start, 2.0, Some(0.7))
                .unwrap()
                .chatter,
            0.7
        );
    }

    /// A baseline that hit a mechanical limit sets no bar (where none was safe, any safe
    /// run meets it); bars that would make every candidate equal are refused.
    #[test]
    fn unsafe_baselines_set_no_bar_and_empty_bars_are_refused() {
        let family = family_of(&[Factor::Mass], 1, 0);
        let (n, m) = (family[0].name.as_str(), family[1].name.as_str());
        let mut base = [
            cell(n, [1.0, 4.0], [1.0, 4.0], 0.1),
            cell(m, [0.1, 0.1], [1.0, 4.0], 0.1),
            cell(n, [2.0, 2.0], [2.0, 2.0], 0.1),
            cell(m, [3.0, 8.0], [2.0, 2.0], 0.1),
        ];
        base[1].safe = false;
        let start = [
            cell(n, [0.5, 1.0], [0.5, 1.0], 0.4),
            cell(m, [1.0, 3.0], [0.5, 1.0], 0.8),
        ];
        let bars = Bars::new(&family, &base, &start, 2.0, None).unwrap();
        assert_eq!(bars.baseline[1], (m.to_string(), vec![3.0, 8.0]));
        base[3].safe = false;
        let bars = Bars::new(&family, &base, &start, 2.0, None).unwrap();
        assert_eq!(bars.baseline[1].1, vec![f64::INFINITY; 2]);
        let margins = Margins::of(&start, &bars);
        assert_eq!(
            margins.baseline, 0.5,
            "the nominal's 1 against 2; 0 on the mass"
        );
        let mut quiet = start.clone();
        for c in &mut quiet {
            c.chatter = vec![0.0; 2];
        }
        let e = Bars::new(&family, &base, &quiet, 2.0, None).unwrap_err();
        assert!(e.to_string().contains("--chatter"), "{e}");
        assert!(Bars::new(&family, &base, &quiet, 2.0, Some(0.5)).is_ok());
        let mut diverged = start.clone();
        diverged[0].rms[1] = f64::NAN;
        let e = Bars::new(&family, &base, &diverged, 2.0, None).unwrap_err();
        assert!(e.to_string().contains("nominal RMS"), "{e}");
        assert!(Bars::new(&family, &base, &[], 2.0, None).is_err());
    }

    /// On a slice of the AERO's family where the headline breaks the own-ratio bar (a
    /// rotor four times slower), the family search finds gains with a lower worst margin
    /// than the start's, and the margins it reports are those of the set it returns, run
    /// again.
    #[test]
    fn a_family_search_lowers_the_worst_margin_and_reports_what_it_returns() {
        let scenario = plant::scenario::load_scenario("1").unwrap();
        let start = plant::scenario::shipped_controller("ipd").unwrap();
        let base: Vec<_> = ["pid", "adrc"]
            .iter()
            .map(|n| plant::scenario::shipped_controller(n).unwrap())
            .collect();
        let family = family_of(&[Factor::Rotor], 1, 0);
        let base_cells = robust::run(&scenario, &base, &family, 2).unwrap();
        let start_cells = robust::run(&scenario, std::slice::from_ref(&start), &family, 2).unwrap();
        let bars = Bars::new(&family, &base_cells, &start_cells, 2.0, None).unwrap();
        let mut calls = 0;
        let tuned = tune_family(&scenario, &start, &family, &bars, 12, 1, 2, |_, _| {
            calls += 1
        })
        .unwrap();
        assert_eq!((tuned.evaluations, calls), (12, 12));
        assert!(
            tuned.start_margins.own_ratio > 1.0,
            "{}",
            tuned.start_margins
        );
        assert!(
            tuned.margins.worst() < tuned.start_margins.worst(),
            "{} against {}",
            tuned.margins,
            tuned.start_margins
        );
        let again = robust::run(&scenario, std::slice::from_ref(&tuned.set), &family, 1).unwrap();
        assert_eq!(Margins::of(&again, &bars), tuned.margins);
        assert!(tuned.set.description.contains("--family"));
    }
}

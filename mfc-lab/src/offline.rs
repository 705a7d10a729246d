//! The closed loop run offline, in lockstep: plant and controller in one thread, no
//! network, no real time, as fast as the plant answers.
//!
//! Each period: read the plant, step the MIMO controller, write the inputs (the plant
//! reports what it really applied: saturation, a driver's own limits), tell the controller
//! what was really applied, let one period of plant time pass. The plant is any
//! [`plant::Plant`]: the built-in AERO simulator or a driver process, so a
//! user tries and tunes a controller on their own simulator before going live. This is
//! also the reference the networked loop is compared against.
//!
//! The lockstep loop reads and writes at the sample instant. A plant behind a fieldbus
//! does not: a subscription serves a value the server sampled before the tick, and a
//! write lands when it crosses the network. [`IoTiming`] puts those two delays into the
//! offline run, so that a user sees what they cost a law before going live (a tight
//! tracking loop can lose a third of its accuracy to one millisecond, `docs/fieldbus.md`).

use mfc::trajectory::evaluate;
use mfc::{ChannelOutput, MimoController, Reference};
use plant::record::{Accumulator, ChannelMetrics, Period, RunRecord};
use plant::scenario::{ControllerSet, Scenario};
use plant::PlantError;
use serde::{Deserialize, Serialize};

/// Why a run could not be done.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// The controller configuration was refused. (The reason is in the message, not a
    /// `source`: an error chain printed with `{:#}` would say it twice.)
    #[error("controller `{controller}`: {reason}")]
    Controller {
        /// Controller name.
        controller: String,
        /// The control core's reason.
        reason: mfc::MfcError,
    },
    /// The controller does not fit the scenario.
    #[error(transparent)]
    Scenario(#[from] plant::scenario::ScenarioError),
    /// The plant could not be started or failed during the run (its reason in the
    /// message, not a `source`, as for `Controller`).
    #[error("plant: {0}")]
    Plant(PlantError),
    /// A benchmark ([`crate::robust`]) cannot vary this plant, or one of its runs failed.
    #[error("{0}")]
    Bench(String),
    /// The I/O timing asked for does not fit in a period ([`IoTiming::check`]).
    #[error("I/O timing: {0}")]
    Timing(String),
    /// A networked run in lockstep ([`crate::netsim`]) could not be set up or went wrong.
    #[error("network simulation: {reason}")]
    Link {
        /// Why.
        reason: String,
    },
}

impl From<PlantError> for RunError {
    fn from(e: PlantError) -> Self {
        RunError::Plant(e)
    }
}

/// OfflineSummary of an offline run, as written to `summary.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OfflineSummary {
    /// Scenario name.
    pub scenario: String,
    /// Controller name.
    pub controller: String,
    /// Per channel, on the measured outputs (what a rig would show).
    pub channels: Vec<ChannelMetrics>,
    /// The same on the plant's true outputs, where it can tell (the AERO simulator): free
    /// of the sensors' noise and quantisation, what the benchmarks judge.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub truth: Option<Vec<ChannelMetrics>>,
    /// Times the plant hit a mechanical limit (the AERO's pitch stop): a safety excursion.
    pub limit_hits: usize,
    /// Whether the run went to the end (a controller error stops it).
    pub completed: bool,
    /// The I/O timing the run had, when not the lockstep loop's ([`simulate_timed`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub timing: Option<IoTiming>,
}

/// A finished offline run.
#[derive(Debug, Clone)]
pub struct Simulation {
    /// Period by period (empty unless recorded).
    pub record: RunRecord,
    /// Metrics.
    pub summary: OfflineSummary,
}

/// Where, around the sample instant, the loop's I/O meets the plant, in seconds; both zero
/// (the default) is the lockstep loop. The plant is time-invariant, so what a run shows is
/// the loop's delay, their sum, more than either.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IoTiming {
    /// How old the value the controller gets is at the tick, in seconds: the plant is read
    /// this long before it (a subscription's last published value, sampled and sent
    /// before).
    pub value_age: f64,
    /// How long after the tick the command reaches the plant, in seconds (a write crossing
    /// the network, a server applying it when it arrives).
    pub write_delay: f64,
}

impl IoTiming {
    /// Both delays finite, not negative, and their sum under the period: a later value or
    /// write belongs to another period, which this loop cannot say.
    pub fn check(&self, period: f64) -> Result<(), RunError> {
        let (a, w) = (self.value_age, self.write_delay);
        if !(a.is_finite() && a >= 0.0 && w.is_finite() && w >= 0.0) {
            return Err(RunError::Timing(format!(
                "a value's age and a write's delay must be finite and at least 0 s, not {a} s \
                 and {w} s"
            )));
        }
        if a + w >= period {
            return Err(RunError::Timing(format!(
                "a value {a} s old and a write {w} s late take a whole {period} s period or more"
            )));
        }
        Ok(())
    }
}

/// "each value 1.5 ms old and each write 0.5 ms late" (the parts that are not zero, to the
/// microsecond), or "in lockstep".
impl std::fmt::Display for IoTiming {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let ms = |s: f64| (s * 1e6).round() / 1e3;
        let (a, w) = (self.value_age, self.write_delay);
        match (a != 0.0, w != 0.0) {
            (false, false) => write!(f, "in lockstep"),
            (true, false) => write!(f, "each value {} ms old", ms(a)),
            (false, true) => write!(f, "each write {} ms late", ms(w)),
            (true, true) => write!(
                f,
                "each value {} ms old and each write {} ms late",
                ms(a),
                ms(w)
            ),
        }
    }
}

/// Run `scenario` closed-loop with `controller`, recording every period if `record`.
pub fn simulate(
    scenario: &Scenario,
    controller: &ControllerSet,
    record: bool,
) -> Result<Simulation, RunError> {
    simulate_timed(scenario, controller, record, IoTiming::default())
}

/// [`simulate`] with the loop's I/O off the sample instant as `timing` says: each period
/// the plant is read, `value_age` passes (the tick: the controller steps on the reference
/// of that instant), `write_delay` passes, the command is written, and the rest of the
/// period passes. The metrics judge the value read (and the plant's truth at that read,
/// where it has one) against the reference at the tick, as a live run's report does.
pub fn simulate_timed(
    scenario: &Scenario,
    controller: &ControllerSet,
    record: bool,
    timing: IoTiming,
) -> Result<Simulation, RunError> {
    simulate_holding(scenario, controller, record, timing, &[])
}

/// [`simulate_timed`] with the periods where `held[k]` is true left without a write: the
/// plant keeps the input it had, and the law is told so, as a live agent holds its last
/// command when the period's own comes too late. A live run's twin holds where the run
/// held (its record's modes), so a busy machine's missed deadlines are in both, and what
/// is left between them is the loop. Periods past `held`'s end are written as usual.
pub fn simulate_holding(
    scenario: &Scenario,
    controller: &ControllerSet,
    record: bool,
    timing: IoTiming,
    held: &[bool],
) -> Result<Simulation, RunError> {
    timing.check(scenario.period)?;
    scenario.check_controller(controller)?;
    let n = scenario.channels.len();
    let configs = scenario.channel_configs(controller);
    let mut mimo: MimoController =
        MimoController::new(&configs).map_err(|reason| RunError::Controller {
            controller: controller.name.clone(),
            reason,
        })?;
    let mut plant = plant::open(&scenario.plant, scenario.seed, n)?;
    let h = scenario.period;
    let steps = scenario.steps();
    let mut acc = vec![Accumulator::default(); n];
    let mut acc_true = vec![Accumulator::default(); n];
    let mut has_truth = true;
    let mut periods = RunRecord::new(
        scenario.names(),
        scenario.channels.iter().map(|c| c.unit.clone()).collect(),
        if record { steps } else { 0 },
    );
    let mut out = vec![ChannelOutput::default(); n];
    let mut refs = vec![Reference::default(); n];
    let mut v = vec![0.0; n];
    // What the plant applies before the first write, and kept by a held period.
    let mut last = vec![0.0; n];
    let mut failed = false;
    for k in 0..steps {
        let t = k as f64 * h;
        let y = plant.read()?;
        // The truth at the read, before time passes (a write changes no state).
        let truth = plant.truth().filter(|x| x.len() == n);
        pass(&mut *plant, timing.value_age)?;
        for (r, c) in refs.iter_mut().zip(&scenario.channels) {
            *r = evaluate(&c.reference, t);
        }
        if mimo.step(t, &y, &refs, &mut out).is_err() {
            // Only non-finite plant data can do this; the run stops and says so.
            failed = true;
            break;
        }
        for (vi, o) in v.iter_mut().zip(&out) {
            *vi = o.v;
        }
        pass(&mut *plant, timing.write_delay)?;
        let applied = if held.get(k).copied().unwrap_or(false) {
            last.clone()
        } else {
            plant.write(&v)?
        };
        last.clone_from(&applied);
        if applied != v {
            // The plant limited the input: keep the estimator honest.
            let _ = mimo.report_applied(&applied);
        }
        has_truth &= truth.is_some();
        for (i, c) in scenario.channels.iter().enumerate() {
            let saturated = c.saturated(applied[i]);
            acc[i].add(y[i] - refs[i].y, h, applied[i], saturated);
            if let Some(x) = &truth {
                acc_true[i].add(x[i] - refs[i].y, h, applied[i], saturated);
            }
        }
        if record {
            let y_ref: Vec<f64> = refs.iter().map(|r| r.y).collect();
            let u: Vec<f64> = out.iter().map(|o| o.u).collect();
            let f: Vec<f64> = out.iter().map(|o| o.f_est.unwrap_or(f64::NAN)).collect();
            periods.push(Period {
                t,
                y_ref: &y_ref,
                y: &y,
                u: Some(&u),
                v: &applied,
                f_est: Some(&f),
                net: None,
            });
        }
        // Exactly `h` when both delays are zero: the lockstep run is unchanged to the bit.
        plant.advance(h - timing.value_age - timing.write_delay)?;
    }
    let limit_hits = plant.limit_hits();
    plant.stop()?;
    let summary = OfflineSummary {
        scenario: scenario.name.clone(),
        controller: controller.name.clone(),
        channels: finish(&acc, scenario),
        truth: has_truth.then(|| finish(&acc_true, scenario)),
        limit_hits,
        completed: !failed,
        timing: (timing != IoTiming::default()).then_some(timing),
    };
    Ok(Simulation {
        record: periods,
        summary,
    })
}

/// Let `dt` of plant time pass, if any.
fn pass(plant: &mut dyn plant::Plant, dt: f64) -> Result<(), PlantError> {
    if dt > 0.0 {
        plant.advance(dt)?;
    }
    Ok(())
}

/// Each channel's accumulated errors as its metrics, named as the scenario names it.
pub(crate) fn finish(acc: &[Accumulator], scenario: &Scenario) -> Vec<ChannelMetrics> {
    acc.iter()
        .zip(&scenario.channels)
        .map(|(a, c)| a.finish(&c.name))
        .collect()
}

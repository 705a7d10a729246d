//! The closed loop run offline: simulator and controller in one thread, no network.
//!
//! Each period: sample the sensors, step the MIMO controller, apply the voltages (the
//! simulator saturates them), tell the controller what was really applied, advance the
//! simulator by one period. This is the reference against which the networked loop is
//! compared later.

use mfc::{ChannelOutput, MimoController, Reference};

use crate::aero::{AeroSim, CHANNELS};
use crate::metrics::{Accumulator, Summary};
use crate::scenario::{ControllerSet, Scenario};
use mfc::trajectory::evaluate;

/// Why a run could not be done.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// The controller configuration was refused.
    #[error("controller `{controller}`: {source}")]
    Controller {
        /// Controller name.
        controller: String,
        /// The control core's reason.
        source: mfc::MfcError,
    },
    /// The plant parameters were refused.
    #[error("plant: {0}")]
    Plant(#[from] crate::aero::ParamError),
}

/// One channel's time series.
#[derive(Debug, Clone, Default)]
pub struct Trace {
    /// Reference `y*`.
    pub y_ref: Vec<f64>,
    /// Measured output `y`.
    pub y: Vec<f64>,
    /// Controller output `u`.
    pub u: Vec<f64>,
    /// Applied voltage `v`.
    pub v: Vec<f64>,
    /// Estimate of `F` (NaN while the window fills, or for PID).
    pub f_est: Vec<f64>,
}

/// A finished run.
#[derive(Debug, Clone)]
pub struct Run {
    /// Sample times.
    pub t: Vec<f64>,
    /// Per channel.
    pub traces: Vec<Trace>,
    /// Metrics.
    pub summary: Summary,
}

/// Run `scenario` closed-loop with `controller`, recording every sample if `record`.
pub fn run(scenario: &Scenario, controller: &ControllerSet, record: bool) -> Result<Run, RunError> {
    let configs = scenario.channel_configs(controller);
    let mut mimo: MimoController =
        MimoController::new(&configs).map_err(|source| RunError::Controller {
            controller: controller.name.clone(),
            source,
        })?;
    let mut plant = AeroSim::new(scenario.plant.clone(), scenario.seed)?;
    let h = scenario.period;
    let steps = scenario.steps();
    let mut acc = vec![Accumulator::default(); CHANNELS];
    let mut traces = vec![Trace::default(); CHANNELS];
    let mut times = Vec::new();
    let mut out = [ChannelOutput::default(); CHANNELS];
    let mut refs = [Reference::default(); CHANNELS];
    let mut failed = false;
    for k in 0..steps {
        let t = k as f64 * h;
        let y = plant.measure();
        for (r, c) in refs.iter_mut().zip(&scenario.channels) {
            *r = evaluate(&c.reference, t);
        }
        if mimo.step(t, &y, &refs, &mut out).is_err() {
            // Cannot happen with finite simulator data; treat as a lost loop.
            failed = true;
            break;
        }
        let v = [out[0].v, out[1].v];
        let applied = plant.apply(v);
        if applied != v {
            // Only a saturation inside the simulator can do this; keep the estimator honest.
            let _ = mimo.report_applied(&applied);
        }
        let vmax = plant.params().max_voltage;
        for i in 0..CHANNELS {
            let e = y[i] - refs[i].y;
            acc[i].add(e, h, applied[i], applied[i].abs() >= vmax - 1e-9);
            if record {
                let tr = &mut traces[i];
                tr.y_ref.push(refs[i].y);
                tr.y.push(y[i]);
                tr.u.push(out[i].u);
                tr.v.push(applied[i]);
                tr.f_est.push(out[i].f_est.unwrap_or(f64::NAN));
            }
        }
        if record {
            times.push(t);
        }
        plant.advance(h);
    }
    let summary = Summary {
        scenario: scenario.name.clone(),
        controller: controller.name.clone(),
        channels: acc
            .iter()
            .zip(&scenario.channels)
            .map(|(a, c)| a.finish(&c.name))
            .collect(),
        pitch_stop_hits: plant.stop_hits(),
        completed: !failed,
    };
    Ok(Run {
        t: times,
        traces,
        summary,
    })
}

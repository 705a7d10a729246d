//! Running a plant: what the agent next to a machine, the research bench (`mfc-lab`) and
//! the system tests all need, and nothing of the network.
//!
//! * [`Plant`]: the trait every plant is driven through, with two backends and [`open`]
//!   to get the one a scenario names: the AERO simulator ([`aero::AeroPlant`], in
//!   process) and the driver bridge for any other plant ([`driver::DriverPlant`], a
//!   process speaking `plant-agent/DRIVER.md`'s line protocol);
//! * [`scenario`]: what a plant is to the project (channels, actuator ranges, references,
//!   controller sets), read from TOML files; the AERO is one plant among others;
//! * [`record`]: the recorder every run uses, offline or networked ([`record::RunRecord`]:
//!   `run.csv`, `summary.json`, plots, per-channel metrics);
//! * [`chart`]: what every plot of the project shares (the embedded font, round ticks
//!   with plain labels, axis titles with their unit);
//! * [`progress`]: the terminal board of running plants (time, RMS so far, round trip,
//!   mode);
//! * [`LoopMode`]: who drives the plant in a period, as runs record and show it;
//! * [`run_id`]: the id that tells one run of a device from the next.
//!
//! Why a crate of its own: the bench runs plants offline, in lockstep, and records them
//! exactly as the agent does over the network, so that a networked run and its offline
//! twin compare column by column. Both build on this crate; neither reaches into the
//! other. It links no network (no zenoh, no tokio): the offline bench needs none, and the
//! agent adds its own.

pub mod aero;
pub mod chart;
pub mod driver;
pub mod modbus;
mod mode;
pub mod opcua;
pub mod progress;
pub mod record;
pub mod scenario;

pub use mode::LoopMode;

use std::time::Duration;

use scenario::PlantSource;

/// Why the plant could not be driven.
#[derive(Debug, thiserror::Error)]
pub enum PlantError {
    /// The driver process could not be started or talked to.
    #[error("driver: {0}")]
    Driver(String),
    /// The driver did not answer in time.
    #[error("driver did not answer `{request}` within {timeout:?}")]
    Timeout {
        /// The request.
        request: String,
        /// The timeout.
        timeout: Duration,
    },
    /// The driver answered something that does not follow the protocol.
    #[error("driver answered {answer:?} to `{request}`")]
    Protocol {
        /// The request.
        request: String,
        /// The answer.
        answer: String,
    },
    /// Simulator parameters.
    #[error(transparent)]
    Params(#[from] aero_sim::ParamError),
    /// The plant cannot be driven by this program (a Modbus plant offline).
    #[error("{0}")]
    Unsupported(String),
    /// The plant (a server behind an industrial protocol) answered with an error or
    /// something that cannot be a measurement.
    #[error("{0}")]
    Server(String),
    /// The plant has another number of channels than its scenario.
    #[error("the plant has {plant} channel(s), the scenario {scenario}")]
    Channels {
        /// What the plant said.
        plant: usize,
        /// What the scenario says.
        scenario: usize,
    },
}

/// A plant that can be driven: read its outputs, write its inputs, let time pass, stop.
///
/// The trait is synchronous on purpose: plant I/O can block (a driver thinking, a serial
/// line), so the agent's networked loop runs it on a thread of its own and the offline
/// loop calls it directly, in lockstep, as fast as the plant answers.
pub trait Plant: Send {
    /// Number of outputs (= number of inputs).
    fn channels(&self) -> usize;
    /// Measure the outputs now.
    fn read(&mut self) -> Result<Vec<f64>, PlantError>;
    /// Apply `v` from now on; returns what was really applied.
    fn write(&mut self, v: &[f64]) -> Result<Vec<f64>, PlantError>;
    /// Let `dt` seconds pass (simulators integrate; real plants ignore it: time passes).
    fn advance(&mut self, dt: f64) -> Result<(), PlantError>;
    /// Apply the safe stop (the scenario's safe inputs, [`scenario::Scenario::safe_inputs`]:
    /// zero, or a bridge's per-channel safe values) and release the plant.
    fn stop(&mut self) -> Result<(), PlantError>;
    /// Times the plant hit a mechanical limit (the AERO's pitch stop): a safety excursion
    /// the tuner penalises. Plants that cannot tell report 0.
    fn limit_hits(&self) -> usize {
        0
    }
    /// The true outputs at the last [`Plant::read`], free of the sensors' noise and
    /// quantisation, where the plant can tell (a simulator); `None` for a real plant or a
    /// driver. Benchmarks judge what the plant did on it.
    fn truth(&self) -> Option<Vec<f64>> {
        None
    }
}

/// Open the plant a scenario names: the AERO simulator with `seed`, or its driver process.
/// The channel count is checked against `channels`.
pub fn open(
    source: &PlantSource,
    seed: u64,
    channels: usize,
) -> Result<Box<dyn Plant>, PlantError> {
    let plant: Box<dyn Plant> = match source {
        PlantSource::Aero(params) => Box::new(aero::AeroPlant::new(params.clone(), seed)?),
        PlantSource::Driver(cmd) => Box::new(driver::DriverPlant::start(cmd)?),
        PlantSource::Modbus(m) => {
            return Err(PlantError::Unsupported(format!(
                "the plant at {} is a Modbus server: it runs in real time through plant-agent \
                 (its bridge), not offline",
                m.config.address
            )))
        }
        PlantSource::OpcUa(o) => {
            return Err(PlantError::Unsupported(format!(
                "the plant at {} is an OPC UA server: it runs in real time through plant-agent \
                 (its bridge), not offline",
                o.config.endpoint
            )))
        }
    };
    if plant.channels() != channels {
        return Err(PlantError::Channels {
            plant: plant.channels(),
            scenario: channels,
        });
    }
    Ok(plant)
}

/// A run id that differs between runs: the controller service rebuilds a device's state
/// when it changes (a restarted plant). Never 0, which the protocol reserves for "not
/// set". It grows from one start to the next, as the wall clock does: the time in
/// nanoseconds since the Unix epoch, its low 16 bits replaced by the process id's, so two
/// processes started within the same 65 µs still differ. A service with keys relies on
/// the order: an authenticated sample of a run older than the one in force is a replay
/// of a captured run, refused (`controller-service`'s rule 3).
pub fn run_id() -> u64 {
    let unix_ns = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or(0);
    ((unix_ns & !0xFFFF) | u64::from(std::process::id() & 0xFFFF)).max(1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn open_checks_the_channel_count_against_the_scenario() {
        let s = scenario::load_scenario("1").unwrap();
        let p = open(&s.plant, 1, 2).unwrap();
        assert_eq!(p.channels(), 2);
        match open(&s.plant, 1, 3) {
            Err(PlantError::Channels {
                plant: 2,
                scenario: 3,
            }) => {}
            Err(e) => panic!("expected a channel mismatch, got {e}"),
            Ok(_) => panic!("a 2-channel plant opened for a 3-channel scenario"),
        }
    }
}

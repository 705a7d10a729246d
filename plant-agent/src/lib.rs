//! Plant agent: bridges one plant (a rig's driver, or a simulator) to a model-free
//! controller service over Zenoh, paces the loop, and keeps the plant safe when commands
//! are late or lost.
//!
//! * [`scenario`]: what a plant is to the project (channels, actuator ranges, references,
//!   controller sets), read from TOML files; the AERO is one plant among others;
//! * [`plant`]: the [`plant::Plant`] trait, the AERO simulator behind it and the driver
//!   bridge for any other plant (`DRIVER.md`);
//! * [`safety`]: the agent's rules (command acceptance, hold, fallback, safe stop, what was
//!   really applied), pure: no I/O, no async, no clock;
//! * [`agent`]: the networked loop, thin wiring around [`safety`];
//! * [`pace`]: deadlines kept to a tenth of a millisecond, where tokio's timer keeps one
//!   or two;
//! * [`config`]: the agent's configuration file;
//! * [`record`]: the recorder every run uses (CSV, summary, plots, metrics);
//! * [`cli`]: the `plant-agent` command line.
//!
//! It depends on the core crates (`mfc`, `protocol`, `transport`) and the AERO simulator,
//! never on the controller service: the process next to a machine carries nothing it
//! does not run.

pub mod agent;
pub mod cli;
pub mod config;
pub mod gateway;
pub mod observe;
pub mod pace;
pub mod plant;
pub mod record;
pub mod safety;
pub mod scenario;

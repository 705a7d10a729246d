//! Controller service: holds per-device model-free control state and answers each sensor
//! sample, published over Zenoh, with a control command. One process serves many plants.
//!
//! * [`config`]: the TOML file (declared devices, templates, envelopes);
//! * [`envelope`]: a device's safety envelope, the limits no command leaves;
//! * [`registry`]: the per-device state and the rules for samples, configuration and status,
//!   without I/O;
//! * [`inbox`]: where samples wait for the worker: the latest per device, so one device's
//!   flood cannot delay another's;
//! * [`service`]: the Zenoh wiring and the worker task;
//! * [`cli`]: the command line (the binary is a one-line `main`).

pub mod cli;
pub mod config;
pub mod envelope;
pub mod fleet;
pub mod inbox;
pub mod observe;
pub mod registry;
pub mod replay;
pub mod service;
pub mod snapshot;

pub use config::ServiceConfig;
pub use registry::Registry;

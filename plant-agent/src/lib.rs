//! Plant agent: bridges a plant (the simulated Quanser AERO, or a real rig's driver) to the
//! model-free controller.
//!
//! This crate holds the AERO simulator ([`aero`]), the scenario format ([`scenario`], with references from
//! [`mfc::trajectory`]), the offline closed loop ([`offline`]), the fair tuner ([`tune`]), the
//! comparison ([`compare`]) and the plots ([`plot`]); the `plant-agent` binary is a thin CLI
//! over them.

pub mod aero;
pub mod agent;
pub mod compare;
pub mod demo;
pub mod metrics;
pub mod offline;
pub mod output;
pub mod plant;
pub mod plot;
pub mod rng;
pub mod scenario;
pub mod tune;

//! Controller service: holds per-device model-free control state and answers each sensor
//! sample, published over Zenoh, with a control command. One process serves many plants.
//!
//! The rules, without I/O, async or a clock of their own (time is passed in):
//! * [`registry`]: the per-device state and the rules for samples, configuration and status;
//! * [`envelope`]: a device's safety envelope, the limits no command leaves;
//! * [`fleet`]: several instances sharing the devices: who owns, who stands by, handover;
//! * [`standby`]: a hot-standby group: who is active, takeover after silence;
//! * [`lease`]: the plant's command lease seen from a member: answer, claim, yield, or
//!   stay silent because another holds it (the plant decides who commands it);
//! * [`access`]: operators, their roles and devices; [`audit`]: what an audit entry
//!   says, a change's old and new values, entries handed over with a device;
//! * [`journal`]: the audit file as the durable record of every change: its lines (an
//!   entry, the state it left, a CRC), a file read back into each device's latest state,
//!   and batches written all or nothing on a disk passed in;
//! * [`replication`]: the holds of a change by the partners that would take its device
//!   over, and when it may be acknowledged.
//!
//! Around them:
//! * [`config`]: the TOML file (declared devices, templates, envelopes, fleet, standby);
//! * [`inbox`]: where samples wait for the worker: the latest per device, so one device's
//!   flood cannot delay another's;
//! * [`service`]: the Zenoh wiring and the worker, [`service::serve`] its entry point;
//! * [`snapshot`]: the snapshots' format and files; [`replay`]: a recording played again;
//! * [`trail`]: the audit file on the real disk, its writer thread (a [`journal`] store);
//! * [`observe`]: metrics; [`cli`]: the command line (the binary is a one-line `main`).

pub mod access;
pub mod audit;
pub mod bounds;
pub mod changes;
pub mod cli;
pub mod config;
pub mod envelope;
pub mod fleet;
pub mod inbox;
pub mod journal;
pub mod lease;
pub mod observe;
pub mod registry;
pub mod replay;
pub mod replication;
pub mod service;
pub mod snapshot;
pub mod standby;
pub mod trail;

pub use config::ServiceConfig;
pub use registry::Registry;

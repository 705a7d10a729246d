//! The research bench of model-free control as a service.
//!
//! * [`offline`]: a scenario closed-loop, in lockstep, against any plant (the AERO
//!   simulator or a driver process), no network, no real time;
//! * [`tune`]: a fair tuner (the same search and budget for every controller kind);
//! * [`compare`]: every controller on every scenario, as a table;
//! * [`commission`]: `α` and the order found from a plant's response, offline;
//! * [`robust`]: every controller, untouched, on a seeded family of variations of the AERO;
//! * [`netsim`]: the networked loop in lockstep, the service's and the agent's own rules
//!   over a seeded model of the link;
//! * [`harness`]: a controller service and N plants in-process over Zenoh on loopback, the
//!   one setup behind the demo, the campaign, the system tests and the benchmarks;
//! * [`demo`]: the README's first command;
//! * [`campaign`]: the fault campaign through `faultlab`'s relay, with its plots;
//! * [`cli`]: the `mfc-lab` command line.
//!
//! This is the one crate that composes the others: it links the service, the agent and
//! the relay to run them together. Nothing depends on it but the system tests. The plants,
//! their scenario and controller files, the recorder and the progress board are the
//! `plant` crate's; of the agent it uses only the public entry points its crate doc lists
//! (running a loop, and the rules with their wire mapping for [`netsim`]).

pub mod campaign;
pub mod cli;
pub mod commission;
pub mod compare;
pub mod demo;
pub mod harness;
pub mod netsim;
pub mod offline;
pub mod robust;
pub mod tune;

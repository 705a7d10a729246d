//! Plant agent: what runs next to a machine. It bridges one plant (a rig's driver, or a
//! simulator), or a gateway's many, to a model-free controller service over Zenoh, paces
//! the loop, and keeps the plant safe when commands are late or lost.
//!
//! * [`safety`]: the agent's rules (command acceptance, hold, fallback, safe stop, what was
//!   really applied), pure: no I/O, no async, no clock;
//! * [`lease`]: the plant's command lease, pure: who may command it, under which epoch;
//! * [`wire`]: the rules on the wire (a decoded command as the rules judge it, a mode as a
//!   sample's flags);
//! * [`agent`]: the networked loop, thin wiring around [`safety`];
//! * [`gateway`]: many plants in one process, one batch of samples per period;
//! * [`pace`]: deadlines kept to a tenth of a millisecond, where tokio's timer keeps one
//!   or two;
//! * [`config`]: the agent's configuration file;
//! * [`observe`]: its Prometheus metrics and MCAP recording, and the feed of the progress
//!   board;
//! * [`cli`]: the `plant-agent` command line.
//!
//! The plant itself, its scenario and controller files, the run's recorder and the
//! progress board are the `plant` crate's, shared with the bench: a networked run and its
//! offline twin are the same plant, recorded the same way.
//!
//! # Public API
//!
//! The crate is a binary's library, but the research bench (`mfc-lab`) and the system
//! tests run the agent in process, as the binary would, so these are its public entry
//! points, kept stable for them:
//!
//! * running a loop: [`agent::open_plant`], [`agent::run_loop`], [`agent::LoopConfig`],
//!   and what a run returns ([`agent::AgentRun`], [`agent::AgentReport`] with its
//!   [`agent::End`] and [`agent::ControllerLink`]); a gateway: [`gateway::run_gateway`];
//! * the rules, for a loop run elsewhere with exactly the agent's decisions (the bench's
//!   lockstep network simulator): [`safety::Supervisor`] and the types of its calls
//!   ([`safety::SafetyConfig`] with [`safety::MAX_AGE_LIMIT`], [`safety::FallbackPolicy`]
//!   with [`safety::parse_fallback`], [`safety::IncomingCommand`], [`safety::Verdict`],
//!   [`safety::PeriodBegin`], [`safety::SupervisorCounters`], [`safety::LoopMode`]), and their
//!   mapping to the protocol in [`wire`];
//! * what a loop feeds: [`observe::LoopObservers`], [`observe::AgentMetrics`].
//!
//! Everything else public here serves the binary and may change with it.
//!
//! It depends on the core crates (`mfc`, `protocol`, `transport`) and `plant`, never on
//! the controller service: the process next to a machine carries nothing it does not run.

pub mod agent;
pub mod cli;
pub mod config;
pub mod gateway;
pub mod lease;
pub mod observe;
pub mod pace;
pub mod safety;
pub mod wire;

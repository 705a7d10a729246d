//! Load generator and benchmark for the controller service.
//!
//! * [`gen`]: N simulated plants (a first-order lag each, cheap enough for tens of
//!   thousands in one process) at a fixed rate, one sample per device per period, either
//!   each on its own key or batched through gateways; it counts what came back and when.
//! * [`echo`]: the anchor, a minimal protobuf echo that answers each sample with a command
//!   of the same `seq`: what Zenoh and protobuf alone cost, measured beside the service in
//!   the same run so that the figures are ratios, not absolute numbers of one machine.
//! * [`bench`]: the benchmark, which starts the service and the anchor as processes of
//!   their own, one at a time, runs the generator against each, reads their CPU time from
//!   `/proc`, and sweeps the number of devices for the largest that stays in the period.
//! * [`scrape`]: a real Prometheus server scraping the service while it serves thousands
//!   of plants: series, exposition size and scrape time per metrics configuration.
//! * [`stats`]: the latency histogram and the `/proc` readings.
//!
//! The generator and the benchmark are timing instruments: nothing here is a pass/fail
//! test. The system tests use the generator's counts (answered, duplicates), never its
//! times.

pub mod bench;
pub mod cli;
pub mod echo;
pub mod gen;
pub mod scrape;
pub mod stats;

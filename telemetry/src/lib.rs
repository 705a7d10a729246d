//! What operators see of a running loop, shared by the service and the agent.
//!
//! * [`prom`]: Prometheus metrics through the `metrics` facade. Each process owns its own
//!   recorder (no global one, so several services or agents in one test process never mix
//!   their figures) and serves it on an endpoint of its own, refreshing what it copies from
//!   its state just before each scrape, so that a scrape and a status query agree.
//! * [`record`]: MCAP recordings of samples, commands, configuration and events, with the
//!   protobuf schemas embedded (Foxglove and the `mcap` tools open them as they are),
//!   written on a thread of their own so that a slow disk never stalls a control loop, and
//!   read back for tests and `replay`.

pub mod prom;
pub mod record;

pub use prom::{serve_metrics, FixedHistogram, Metrics, MetricsError, MetricsSpec, MetricsTls};
pub use record::{
    read_recording, topic_name, RecordError, RecordSpec, RecordSummary, Recorded, Recording,
    RecordingContents, Topic,
};

//! `mfcctl`, the operator's command line: list the controllers and the devices they serve,
//! read status, counters and configuration, change one gain (a partial change, inside the
//! envelope), steer the reference, narrow an envelope. It only sends the protocol's
//! queries, so whatever the session may reach (an operator's credentials on a secured
//! router) is what it may do.
//!
//! * [`ops`]: the queries, decoded, with typed errors (in `transport`, shared with the
//!   browser console);
//! * [`render`]: text for people (pure), and the table of tunable parameters as text,
//!   JSON and Markdown (`mfcctl params`, `docs/parameters.md`);
//! * [`commission`]: `mfcctl commission`, a run followed to its end;
//! * [`cli`]: the command line (the binary is a one-line `main`).

pub mod cli;
pub mod commission;
pub use transport::ops;
pub mod render;

//! Network fault injection for the control loop.
//!
//! * [`profile`]: impairment profiles (TOML), seeded;
//! * [`relay`]: the user-space impairment relay (UDP and TCP, per direction);
//! * [`campaign`]: the service and simulated AEROs through the relay, profile by profile.

pub mod campaign;
pub mod profile;
pub mod relay;

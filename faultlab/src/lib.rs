//! Network fault injection for a control loop, independent of what runs over the link.
//!
//! * [`profile`]: impairment profiles (TOML), seeded;
//! * [`relay`]: the user-space impairment relay (UDP and TCP, per direction): loss,
//!   Gilbert-Elliott bursts, delay, jitter, reordering, duplication, rate limit, outages.
//!
//! It knows nothing of the controller, the agent or Zenoh: it forwards bytes between two
//! addresses, so it can sit in front of anyone's deployment. The campaign that runs the
//! project's own loop through it lives in `mfc-lab`.

pub mod profile;
pub mod relay;

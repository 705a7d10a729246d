//! The controller service on Zenoh: one [`Worker`](worker::Worker) owns a [`Registry`] and
//! answers what arrives, one named handler per kind of message, as a router hands each
//! event to its handler. This module holds the entry point, [`serve`].
//!
//! A sample's way, file by file:
//! * [`intake`]: zenoh's callbacks, on zenoh's receive threads. They must never block, so
//!   they only sort messages, and cheaply: a payload over [`MAX_PAYLOAD`] is counted and
//!   dropped before it is copied (a query over it is refused unread, with an error reply
//!   that says why: a sample over it has nothing to answer to); a key that names no
//!   device is counted and dropped; so is
//!   a sample for a device neither declared nor matched by a template (as unknown); a
//!   sample is decoded and prechecked ([`precheck`]: version, its key's own id, finite
//!   values). A good sample is answered at once on the callback's thread when the worker
//!   is free and nothing waits ([`core`]); otherwise it goes to the [`Inbox`] (the latest
//!   per device), so garbage on a device's key never pushes out one of its real samples.
//!   A refused one goes to the worker as a short refusal, to be answered. Everything else
//!   (requests, reference updates, fleet messages) goes to a bounded queue, and heartbeats
//!   to a queue of their own, so that a flood of requests cannot make a standby take over.
//! * [`core`]: what answering needs, shared by the worker and the callbacks: the registry,
//!   the observers, the command publishers.
//! * [`worker`]: the worker's loop and its handlers; [`requests`]: the handlers of
//!   operators' queries; [`handover`]: the fleet's and the hot standby's wiring around
//!   their pure rules ([`crate::fleet`], [`crate::standby`]).
//! * [`routes`]: every Zenoh declaration, owned by a struct that undeclares it on drop.
//! * [`log`]: throttled warnings. Every message the service does not serve lands in
//!   exactly one counter of the service status, and warnings about them are throttled:
//!   the first of each kind at once, then one line per interval with a count.
//!
//! [`Registry`]: crate::Registry
//! [`Inbox`]: crate::inbox::Inbox
//! [`precheck`]: crate::registry::precheck
//! [`MAX_PAYLOAD`]: protocol::MAX_PAYLOAD

mod core;
mod handover;
mod hold;
mod intake;
mod keyring;
mod log;
mod operators;
mod requests;
mod routes;
mod trail;
mod worker;

use std::sync::{Mutex, MutexGuard, PoisonError};
use std::time::Duration;

pub use log::Throttle;
pub use trail::{AuditTrail, TrailStats};

use crate::observe::Observers;
use crate::Registry;

/// Depth of the request queue (messages); when it is full new requests are dropped and
/// counted as `queue_full`.
const QUEUE: usize = 1024;
/// Depth of the heartbeat queue.
const HEARTBEATS: usize = 64;
/// Pending samples of devices not served (yet) share this many inbox slots.
const OTHERS: usize = 64;
/// Samples the worker serves before it looks at its other inputs again, so requests and
/// heartbeats are never starved by a busy fleet.
const BATCH: usize = 64;
/// Gateways whose batches may wait at once (each at most one batch's bytes in all,
/// `crate::inbox::Parts`): a flood of new gateway ids fills these and is dropped as
/// `queue_full`, never growing the service.
const GATEWAYS_PENDING: usize = 256;
/// Gateways with a publisher of their own; commands to any beyond go through the session
/// (same options, one declaration less), so the table is bounded whatever arrives.
const GATEWAY_PUBLISHERS: usize = 1024;
/// Gateway batches the worker serves per turn (each may hold thousands of samples); it
/// finishes a gateway's parts once it began them, so a turn may serve up to
/// `crate::inbox::PARTS - 1` more.
const GATEWAY_TURN: usize = 4;
/// Throttled warnings: at most one line per kind per interval.
const LOG_INTERVAL: Duration = Duration::from_secs(5);
/// How often a fleet member looks at its releases and unanswered requests.
const FLEET_TICK: Duration = Duration::from_millis(20);

/// Why the service stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    /// A zenoh declaration failed.
    #[error("declaring {what}: {reason}")]
    Declare {
        /// What was being declared, e.g. `sample subscriber`, `liveliness token`.
        what: String,
        /// zenoh's reason.
        reason: String,
    },
}

/// Run a controller service for `registry` on `session` until `shutdown` resolves,
/// feeding `observers` (the metrics scrape its status, the recording gets its devices'
/// samples, commands and configuration changes). At the end, its snapshots are saved and
/// everything it declared is undeclared, its liveliness token first, so plants and
/// standbys see a clean exit at once. The session stays open: several workers may share
/// it; whoever opened it closes it.
pub async fn serve(
    session: zenoh::Session,
    registry: Registry,
    observers: Observers,
    shutdown: impl std::future::Future<Output = ()>,
) -> Result<(), ServiceError> {
    let mut registry = registry;
    registry.set_instance(random_instance());
    let (worker, inputs) = worker::Worker::start(session, registry, observers).await?;
    worker.run(inputs, shutdown).await;
    Ok(())
}

/// A random nonzero number naming this process in the plants' leases: the standard
/// library's hasher keys come from the operating system's entropy.
fn random_instance() -> u64 {
    use std::hash::BuildHasher;
    std::collections::hash_map::RandomState::new()
        .hash_one(std::process::id())
        .max(1)
}

/// One of the service's locks: a panic elsewhere while it was held leaves plain data
/// behind, still usable, so a poisoned lock is taken as it is.
fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

fn declare_err(what: impl Into<String>) -> impl FnOnce(zenoh::Error) -> ServiceError {
    let what = what.into();
    move |e| ServiceError::Declare {
        what,
        reason: e.to_string(),
    }
}

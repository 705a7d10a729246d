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
//!   the observers, the command publishers; [`drops`] counts what the callbacks drop.
//! * [`run`]: the worker's start and loop, one handler per event, over the worker's state
//!   ([`worker`]). The handlers: [`requests`] for operators' queries, [`operators`] for a
//!   change's way to its acknowledgment (its pieces in [`change`], its record in
//!   [`crate::trail`], its entries numbered by [`gate`]), [`replies`] for what they
//!   share, [`handover`] and [`hold`] for the fleet's and the hot standby's wiring around
//!   their pure rules ([`crate::fleet`], [`crate::standby`]), and [`ask`] for one member's question to another
//!   (sealed, and answered only by a reply a member sealed, within its timeout).
//! * [`routes`]: every Zenoh declaration, owned by a struct that undeclares it on drop.
//! * [`log`]: throttled warnings. Every message the service does not serve lands in
//!   exactly one counter of the service status, and warnings about them are throttled:
//!   the first of each kind at once, then one line per interval with a count.
//!
//! The files build on each other from [`locks`] and [`log`] up to [`run`], never in a
//! circle (`.ci/layout` checks it; the floors are in `docs/architecture.md`): a handler
//! may use the worker's state and the handlers below it, never the loop.
//!
//! [`Registry`]: crate::Registry
//! [`Inbox`]: crate::inbox::Inbox
//! [`precheck`]: crate::registry::precheck
//! [`MAX_PAYLOAD`]: protocol::MAX_PAYLOAD

mod ask;
mod change;
mod core;
mod drops;
mod gate;
mod handover;
mod hold;
mod intake;
mod keyring;
mod locks;
mod log;
mod operators;
mod replies;
mod requests;
mod routes;
mod run;
mod worker;

pub use log::Throttle;
pub use routes::ServiceError;

use crate::observe::Observers;
use crate::Registry;

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

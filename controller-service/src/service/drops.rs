//! What zenoh's callbacks drop before the worker sees anything, counted: each drop lands
//! in exactly one counter of the service status.

use std::collections::BTreeSet;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;

use protocol::{printable, MAX_PAYLOAD};
use zenoh::query::Query;

use super::locks::lock;

/// Drops counted in zenoh's callbacks, before the worker sees anything.
#[derive(Debug, Default)]
pub(super) struct Drops {
    pub(super) oversized: AtomicU64,
    pub(super) undecodable: AtomicU64,
    pub(super) bad_key: AtomicU64,
    pub(super) queue_full: AtomicU64,
    /// Samples on the key of a device neither declared nor matched by a template: no slot,
    /// no decoding, just this count (added to the registry's in the status).
    pub(super) unknown: AtomicU64,
    /// Samples and batches refused for their MAC (`protocol::auth`), before decoding.
    pub(super) forged: AtomicU64,
    /// The first [`UNKNOWN_NAMED`] of their ids, for the status.
    pub(super) unknown_names: Mutex<BTreeSet<String>>,
}

/// Unknown ids named in the status (the registry keeps as many of its own).
pub(super) const UNKNOWN_NAMED: usize = 64;

impl Drops {
    pub(super) fn count(counter: &AtomicU64) {
        counter.fetch_add(1, Ordering::Relaxed);
    }

    pub(super) fn unknown(&self, id: &str) {
        Self::count(&self.unknown);
        let mut names = lock(&self.unknown_names);
        if names.len() < UNKNOWN_NAMED && !names.contains(id) {
            names.insert(printable(id));
        }
    }

    /// Whether a payload of `len` bytes may be read at all (else counted as oversized).
    pub(super) fn fits(&self, len: usize) -> bool {
        if len > MAX_PAYLOAD {
            Self::count(&self.oversized);
            return false;
        }
        true
    }

    /// Whether a query's payload (none: empty) may be read at all.
    pub(super) fn query_fits(&self, q: &Query) -> bool {
        self.fits(q.payload().map_or(0, |p| p.len()))
    }

    /// The counters a report tells, in its order: oversized, bad key, queue full (the
    /// inboxes' `full` added by the caller), undecodable, unknown, forged.
    pub(super) fn counts(&self) -> [u64; 6] {
        [
            self.oversized.load(Ordering::Relaxed),
            self.bad_key.load(Ordering::Relaxed),
            self.queue_full.load(Ordering::Relaxed),
            self.undecodable.load(Ordering::Relaxed),
            self.unknown.load(Ordering::Relaxed),
            self.forged.load(Ordering::Relaxed),
        ]
    }
}

//! The service's locks.

use std::sync::{Mutex, MutexGuard, PoisonError};

/// One of the service's locks: a panic elsewhere while it was held leaves plain data
/// behind, still usable, so a poisoned lock is taken as it is.
pub(super) fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

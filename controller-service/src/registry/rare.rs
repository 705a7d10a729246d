//! What a device keeps only for rare events: refusals, duplicates, ended runs, operators'
//! changes. Until the first such event (a plant that has sent good samples in order since
//! it started) all of it is empty or zero, so a device keeps a pointer that stays `None`
//! until then; the state itself was 216 bytes of every plant, enough to keep the device in
//! mimalloc's size class of 2048 bytes instead of the one of 1792 (`docs/scale.md`,
//! "Memory per plant"). Once allocated it stays, and a step does not read it unless it
//! holds something a good sample settles (`Device::unsettled`).

use std::collections::VecDeque;

use protocol::pb;

/// A device's state for rare events (see the module documentation). Its counters are the
/// status's: they carry on across runs, as the device's other counters do.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct Rare {
    /// Runs that ended, newest last, at most `RETIRED_RUNS`.
    pub(super) retired: VecDeque<u64>,
    /// The samples refused as out of step since the last answered one, if they form a
    /// consistent stream: its last sequence and time, and how many (`RESYNC_AFTER`).
    pub(super) astray: Option<(u64, f64, u32)>,
    /// Sequence numbers of the run in force, after the last answered one, whose samples
    /// were answered REJECTED (at most `REJECTED_KEPT`): they arrived, so the gap they
    /// leave before the next good sample is not counted as lost.
    pub(super) rejected_seqs: VecDeque<u64>,
    /// Its latest audited decisions, oldest first (at most `audit::KEPT`), handed over
    /// with its state so that the member taking it over keeps its history.
    pub(super) audit: VecDeque<pb::AuditEntry>,
    /// Why the last refused sample or request was refused (already cut to printable
    /// length); a later good one does not clear it.
    pub(super) last_error: String,
    /// Samples repeating `last_seq`, answered with the cached command when there is one.
    pub(super) duplicates: u64,
    /// Samples older than `last_seq`, or of an ended run: answered STALE.
    pub(super) stale: u64,
    /// Samples answered REJECTED: another device's id, bad values, a sequence jump, or a
    /// step the core refused.
    pub(super) rejected: u64,
    /// Samples sent while the plant was holding, on its local fallback or in safe stop:
    /// counts samples, not fallback episodes.
    pub(super) samples_off_remote: u64,
    /// Samples replaced by a newer one before the worker read them (reported by the
    /// service's inbox).
    pub(super) superseded: u64,
    /// Envelope changes accepted since the service started.
    pub(super) envelope_changes: u64,
    /// Reference updates refused.
    pub(super) references_refused: u64,
    /// Lost samples recovered from the copy the next one carried.
    pub(super) recovered: u64,
    /// Runs started after the device's first (a plant restarted).
    pub(super) restarts: u64,
}

impl Rare {
    /// A stray stream or refused sequence numbers are kept: what a good sample of the run
    /// in force settles (`Device::unsettled` mirrors it, so that a step reads this state
    /// only then).
    pub(super) fn unsettled(&self) -> bool {
        self.astray.is_some() || !self.rejected_seqs.is_empty()
    }
}

/// Everything empty or zero: what a device without rare state reads, and what the state
/// starts from when it is allocated.
impl Default for Rare {
    fn default() -> Self {
        NONE.clone()
    }
}

/// What a device without rare state reads ([`RareState::get`]).
static NONE: Rare = Rare {
    retired: VecDeque::new(),
    astray: None,
    rejected_seqs: VecDeque::new(),
    audit: VecDeque::new(),
    last_error: String::new(),
    duplicates: 0,
    stale: 0,
    rejected: 0,
    samples_off_remote: 0,
    superseded: 0,
    envelope_changes: 0,
    references_refused: 0,
    recovered: 0,
    restarts: 0,
};

/// A device's rare state, allocated on the first write (see the module documentation).
#[derive(Debug, Clone, Default)]
pub(super) struct RareState(Option<Box<Rare>>);

impl RareState {
    /// To read: the state, or all empty before any rare event.
    #[inline]
    pub(super) fn get(&self) -> &Rare {
        self.0.as_deref().unwrap_or(&NONE)
    }

    /// To write: the state, allocated now if this is the first rare event.
    pub(super) fn get_mut(&mut self) -> &mut Rare {
        self.0.get_or_insert_with(Box::default)
    }

    /// To write only if it was ever allocated: `None` until the first write (so that
    /// clearing nothing allocates nothing).
    #[inline]
    pub(super) fn existing(&mut self) -> Option<&mut Rare> {
        self.0.as_deref_mut()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nothing_is_allocated_until_something_is_written() {
        let mut r = RareState::default();
        assert_eq!(r.get(), &Rare::default());
        assert!(r.existing().is_none());
        assert!(r.0.is_none(), "a read allocates nothing");
        r.get_mut().stale += 1;
        assert_eq!(r.get().stale, 1);
        assert!(r.existing().is_some());
    }
}

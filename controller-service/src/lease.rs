//! A member's side of the plant's command lease: when to answer, claim, hold or give up.
//!
//! The plant decides who commands it (`plant_agent::lease`): it applies the commands of
//! the holder of its lease only, under the holder's epoch, and every sample says who
//! holds it. The fleet's ranking and the hot standby say who *should* command a device
//! (the *preferred* member: the shard's owner, the active member); the lease says who
//! *may*. This module turns what a sample says into what one member does with its answer:
//!
//! * the lease is this member's: answer under its epoch; a member that holds it without
//!   being preferred (it took over while the preferred one was silent) gives it up after
//!   [`LeasePolicy::yield_after`] samples, so that the preferred member, warm, claims it
//!   with no fallback in between; if nobody else claims, it takes it back, and waits
//!   twice as long before it yields again;
//! * another holds it: answer nothing (the device is *fenced* here): however sure this
//!   member is that it owns the shard (a partition, a pause), the plant would refuse it;
//! * vacant: the preferred member claims at once; any other that steps the device claims
//!   once the lease has been vacant for [`LeasePolicy::standby_delay`] samples in a row,
//!   so the preferred member wins whenever it is there, and a dead, paused or cut-off one
//!   is replaced before the plant falls back; a member whose state still warms up waits
//!   [`LeasePolicy::cold_delay`] samples (except at the run's start, when all are cold),
//!   so a warm one wins the race when there is one;
//! * a plant that grants no lease (no `SAMPLE_FLAGS_LEASE`: a test client, an older agent)
//!   is answered by the preferred member alone, as before leases.
//!
//! Pure: no I/O and no clock; the registry keeps one [`Claimer`] per device.

use protocol::pb;

/// The timing of claims and yields, in samples of the device.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LeasePolicy {
    /// Consecutive vacant samples after which a member that is not preferred claims: the
    /// preferred one gets this head start. The agent's lease lapses after half its
    /// `hold_periods` (3 of 5 by default), so one sample of delay still lands the claim
    /// before the fallback engages.
    pub standby_delay: u32,
    /// Samples a member holds the lease without being preferred before it yields it.
    pub yield_after: u32,
    /// The longest wait between two yields (the wait doubles each time nobody took it).
    pub max_yield_after: u32,
    /// Consecutive vacant samples after which a member whose state is still warming up
    /// claims: a warm member, preferred or not, wins the race for the lease whenever
    /// there is one, and a cold one takes it only when nobody warm did.
    pub cold_delay: u32,
}

impl Default for LeasePolicy {
    fn default() -> Self {
        Self {
            standby_delay: 1,
            yield_after: 100,
            max_yield_after: 12_800,
            cold_delay: 4,
        }
    }
}

/// What to do with the answer to one sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Decision {
    /// Send it as before leases (the plant grants none).
    Plain,
    /// Send it under the lease: `epoch` (the held one, or the one claimed), whether it
    /// claims a vacant lease, and whether it gives the lease up.
    Send {
        epoch: u64,
        claim: bool,
        release: bool,
    },
    /// Another member holds the lease: send nothing.
    Fenced,
    /// Send nothing: the lease has not been vacant long enough for this member to claim
    /// it (see the delays of [`LeasePolicy`]), or the plant grants no lease and this
    /// member is not the preferred one.
    Quiet,
}

impl Decision {
    /// Whether an answer is sent.
    pub fn sends(self) -> bool {
        matches!(self, Self::Plain | Self::Send { .. })
    }

    /// Write the lease's fields into the answer of process `instance` (for a plant of run
    /// `run_id`).
    pub fn stamp(self, run_id: u64, instance: u64, out: &mut pb::Command) {
        out.run_id = run_id;
        out.lease_instance = instance;
        (out.lease_epoch, out.claim, out.release) = match self {
            Self::Send {
                epoch,
                claim,
                release,
            } => (epoch, claim, release),
            _ => (0, false, false),
        };
    }
}

/// What a sample says of its plant's lease.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Seen<'a> {
    /// The plant grants leases.
    pub granted: bool,
    /// The holder (empty: vacant), and its process.
    pub holder: &'a str,
    pub instance: u64,
    pub epoch: u64,
}

impl<'a> Seen<'a> {
    /// The lease as sample `s` reports it.
    pub fn of(s: &'a pb::Sample) -> Self {
        Self {
            granted: s.flags & pb::SampleFlags::Lease as u32 != 0,
            holder: &s.lease_holder,
            instance: s.lease_instance,
            epoch: s.lease_epoch,
        }
    }
}

/// One member's lease state for one device (a few counters: it lives in every device).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Claimer {
    /// Vacant samples in a row.
    vacant: u32,
    /// Samples held in a row without being preferred.
    held_unpreferred: u32,
    /// The current wait before yielding (0: the policy's first).
    yield_after: u32,
    /// Answers this member held back because another held the lease.
    pub fenced: u64,
    /// Claims sent.
    pub claims: u64,
    /// Leases given up to the preferred member.
    pub yields: u64,
}

impl Claimer {
    /// What member `me` (its id and process) does with its answer to a sample that
    /// reports `seen`; `preferred`: the fleet or the hot standby wants `me` to command the
    /// device; `warm`: the answer is a command (not a warm-up answer).
    pub fn decide(
        &mut self,
        policy: &LeasePolicy,
        me: (&str, u64),
        (preferred, warm): (bool, bool),
        seen: Seen<'_>,
    ) -> Decision {
        if !seen.granted {
            return if preferred {
                Decision::Plain
            } else {
                Decision::Quiet
            };
        }
        if seen.holder.is_empty() {
            self.vacant = self.vacant.saturating_add(1);
            self.held_unpreferred = 0;
            // Before the first grant of a run every member is cold: no point waiting.
            let delay = match (warm || seen.epoch == 0, preferred) {
                (false, _) => policy.cold_delay,
                (true, true) => 0,
                (true, false) => policy.standby_delay,
            };
            if self.vacant <= delay {
                return Decision::Quiet;
            }
            self.claims = self.claims.saturating_add(1);
            return Decision::Send {
                epoch: seen.epoch.saturating_add(1),
                claim: true,
                release: false,
            };
        }
        self.vacant = 0;
        if (seen.holder, seen.instance) != me {
            self.held_unpreferred = 0;
            self.fenced = self.fenced.saturating_add(1);
            return Decision::Fenced;
        }
        let mut release = false;
        if preferred {
            self.held_unpreferred = 0;
            self.yield_after = 0;
        } else {
            self.held_unpreferred = self.held_unpreferred.saturating_add(1);
            let wait = match self.yield_after {
                0 => policy.yield_after,
                w => w,
            };
            if self.held_unpreferred >= wait {
                release = true;
                self.held_unpreferred = 0;
                self.yield_after = wait.saturating_mul(2).min(policy.max_yield_after);
                self.yields = self.yields.saturating_add(1);
            }
        }
        Decision::Send {
            epoch: seen.epoch,
            claim: false,
            release,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn seen(holder: &str, epoch: u64) -> Seen<'_> {
        Seen {
            granted: true,
            holder,
            instance: 0,
            epoch,
        }
    }

    const CLAIM2: Decision = Decision::Send {
        epoch: 2,
        claim: true,
        release: false,
    };

    #[test]
    fn a_plant_without_leases_is_answered_by_the_preferred_member_only() {
        let p = LeasePolicy::default();
        let mut c = Claimer::default();
        let plain = Seen {
            granted: false,
            holder: "",
            instance: 0,
            epoch: 0,
        };
        assert_eq!(c.decide(&p, ("a", 0), (true, true), plain), Decision::Plain);
        assert_eq!(
            c.decide(&p, ("a", 0), (false, true), plain),
            Decision::Quiet
        );
    }

    #[test]
    fn the_preferred_member_claims_at_once_another_after_the_delay() {
        let p = LeasePolicy::default();
        let (mut a, mut b) = (Claimer::default(), Claimer::default());
        assert_eq!(a.decide(&p, ("a", 0), (true, true), seen("", 1)), CLAIM2);
        for _ in 0..p.standby_delay {
            assert_eq!(
                b.decide(&p, ("b", 0), (false, true), seen("", 1)),
                Decision::Quiet
            );
        }
        assert_eq!(b.decide(&p, ("b", 0), (false, true), seen("", 1)), CLAIM2);
        // A sample that shows a holder resets the count.
        assert_eq!(
            b.decide(&p, ("b", 0), (false, true), seen("a", 2)),
            Decision::Fenced
        );
        assert_eq!(
            b.decide(&p, ("b", 0), (false, true), seen("", 2)),
            Decision::Quiet
        );
        assert_eq!((a.claims, b.claims, b.fenced), (1, 1, 1));
    }

    #[test]
    fn a_cold_member_claims_last() {
        let p = LeasePolicy::default();
        let mut c = Claimer::default();
        for _ in 0..p.cold_delay {
            assert_eq!(
                c.decide(&p, ("c", 0), (true, false), seen("", 1)),
                Decision::Quiet
            );
        }
        assert_eq!(c.decide(&p, ("c", 0), (true, false), seen("", 1)), CLAIM2);
        assert!(p.cold_delay > p.standby_delay);
        // At the run's start (nothing granted yet) everybody is cold: no wait.
        let mut c = Claimer::default();
        assert!(c.decide(&p, ("c", 0), (true, false), seen("", 0)).sends());
    }

    #[test]
    fn a_member_that_is_not_the_holder_is_fenced_even_if_preferred() {
        let p = LeasePolicy::default();
        let mut a = Claimer::default();
        assert_eq!(
            a.decide(&p, ("a", 0), (true, true), seen("b", 4)),
            Decision::Fenced
        );
        let held = a.decide(&p, ("a", 0), (true, true), seen("a", 4));
        assert_eq!(
            held,
            Decision::Send {
                epoch: 4,
                claim: false,
                release: false
            }
        );
        assert!(held.sends() && !Decision::Fenced.sends() && !Decision::Quiet.sends());
    }

    #[test]
    fn another_process_with_this_id_holds_and_this_one_is_fenced() {
        let p = LeasePolicy::default();
        let mut a = Claimer::default();
        let other = Seen {
            instance: 8,
            ..seen("a", 4)
        };
        assert_eq!(
            a.decide(&p, ("a", 7), (true, true), other),
            Decision::Fenced
        );
    }

    #[test]
    fn an_unpreferred_holder_yields_and_waits_longer_each_time() {
        let p = LeasePolicy {
            standby_delay: 1,
            yield_after: 3,
            max_yield_after: 10,
            cold_delay: 4,
        };
        let mut b = Claimer::default();
        let mut yields_at = Vec::new();
        for k in 0..40 {
            if let Decision::Send { release: true, .. } =
                b.decide(&p, ("b", 0), (false, true), seen("b", 1))
            {
                yields_at.push(k);
            }
        }
        // After 3, then 6, then 10 (the cap) samples held.
        assert_eq!(yields_at, [2, 8, 18, 28, 38]);
        // Preferred again: it holds for good, and the next yield waits the first time again.
        assert_eq!(
            b.decide(&p, ("b", 0), (true, true), seen("b", 1)),
            Decision::Send {
                epoch: 1,
                claim: false,
                release: false
            }
        );
        assert_eq!(b.yield_after, 0);
    }

    #[test]
    fn stamp_writes_the_lease_and_the_run() {
        let mut out = pb::Command {
            claim: true,
            lease_epoch: 9,
            ..Default::default()
        };
        CLAIM2.stamp(77, 5, &mut out);
        assert_eq!(
            (out.lease_epoch, out.claim, out.release, out.run_id),
            (2, true, false, 77)
        );
        assert_eq!(out.lease_instance, 5);
        Decision::Plain.stamp(78, 5, &mut out);
        assert_eq!((out.lease_epoch, out.claim, out.run_id), (0, false, 78));
    }
}

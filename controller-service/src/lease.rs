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
    /// `hold_periods` (3 of 5 by default; up to one period short of the hold when its
    /// holder's answers come late), so one sample of delay still lands the claim before
    /// the fallback engages on a prompt link.
    pub standby_delay: u32,
    /// Samples a member holds the lease without being preferred before it yields it.
    pub yield_after: u32,
    /// The longest wait between two yields (the wait doubles each time nobody took it).
    pub max_yield_after: u32,
    /// Consecutive vacant samples after which a member whose state is still warming up
    /// claims: a warm member, preferred or not, wins the race for the lease whenever
    /// there is one, and a cold one takes it only when nobody warm did.
    pub cold_delay: u32,
    /// Consecutive vacant samples after which a fleet member that may lack the changes
    /// acknowledged under the last holder ([`Claimer::behind`]) claims, plus three per
    /// epoch it is behind by (at most ten). Long (0.3 to 0.6 s at 100 Hz): the plant runs
    /// on its own fallback meanwhile, which is safe, and any member in step wins, even
    /// over lossy links; one behind takes the plant only when nobody in step is left to,
    /// the one nearest to the last holder first.
    pub behind_delay: u32,
    /// Samples in a row naming a holder this member does not see in its fleet's view
    /// after which its state may lack that holder's changes ([`Claimer::behind`]). Above
    /// the samples that name a dead holder until its lease lapses: the agent's lapse
    /// comes after up to 4 of its 5 hold periods without an answer (longer than half the
    /// hold when answers land late, `Supervisor::lease_lapse`), counted from the dead
    /// holder's last answer, which may land a few periods after the crash. So a crash,
    /// seen at once, leaves the standby in step; a partition, which lets the holder
    /// command on without it, does not. (At 5, below that, the simulation's takeovers of
    /// a crashed holder by a member in step took p99 24 periods instead of 9: the
    /// standby counted itself behind before the lease lapsed, and waited.)
    pub unseen_limit: u32,
    /// The longest silence of a device (ns: no sample of it reached this member, or this
    /// process was stopped) that a member stays in step through; after a longer one it is
    /// behind ([`Standing::gap`]) until a holder's state reaches it. Below the time its
    /// partners take to drop it from their view, since from then on the holder
    /// acknowledges changes without it: [`LeasePolicy::for_liveliness_lease`].
    pub silence_ns: u64,
}

/// [`LeasePolicy::silence_ns`] where nothing shorter is needed: zenoh's own liveliness
/// lease is 10 s.
const SILENCE_NS: u64 = 1_000_000_000;

impl LeasePolicy {
    /// This policy in a fleet whose members drop each other from their view after
    /// `lease` without a word (zenoh's `transport/link/tx/lease`): a member silent for
    /// half of it may still be in every partner's view (zenoh sends keep-alives four
    /// times a lease), so no change was acknowledged without it meanwhile; one silent for
    /// longer may have missed some. The fleet's simulation found the case (seed 138492):
    /// a member paused for 680 ms under a 500 ms lease claimed as in step, without the
    /// changes its holder acknowledged while it was out of view.
    pub fn for_liveliness_lease(self, lease: std::time::Duration) -> Self {
        let half = u64::try_from(lease.as_nanos() / 2).unwrap_or(u64::MAX);
        Self {
            silence_ns: half.min(SILENCE_NS),
            ..self
        }
    }
}

impl Default for LeasePolicy {
    fn default() -> Self {
        Self {
            standby_delay: 1,
            yield_after: 100,
            max_yield_after: 12_800,
            cold_delay: 4,
            behind_delay: 30,
            unseen_limit: 8,
            silence_ns: SILENCE_NS,
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

/// Which of two states of a device's configuration is newer. A change made by the member
/// holding the plant's lease, under its epoch, is numbered after every change made under
/// an earlier epoch (or an earlier run of the plant): holders follow one another, each
/// claiming only when none before it still holds, so the changes they acknowledge form
/// one ordered chain. Changes made while not holding the lease (never acknowledged) leave
/// the number as it was. A state handed from one member to another replaces the
/// receiver's only if it is not older ([`crate::Registry::restore_shard`]): a member cut
/// off and behind never overwrites changes made and held elsewhere meanwhile.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Default, bincode::Encode, bincode::Decode,
)]
pub struct Version {
    /// The plant's run (run ids grow from start to start).
    pub run: u64,
    /// The lease epoch under which the change was made.
    pub epoch: u64,
    /// Changes under that epoch, this one included.
    pub n: u64,
}

impl Version {
    /// The version of a change made by the holder of `(run, epoch)` on a state at `self`.
    pub fn next(self, run: u64, epoch: u64) -> Self {
        if (run, epoch) == (self.run, self.epoch) {
            Self {
                n: self.n.saturating_add(1),
                ..self
            }
        } else {
            Self { run, epoch, n: 1 }
        }
    }
}

/// The most epochs a member counts itself behind by ([`LeasePolicy::behind_delay`]): one
/// that cannot tell waits 27 samples more than one a single epoch behind.
const MAX_BEHIND: u64 = 10;

/// Samples after a silence that may still be late ones, waiting in the service's inbox
/// (which keeps only the newest per device) or in zenoh's queues.
const LATE_SAMPLES: u32 = 5;

/// Where a member stands for one device when a sample comes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Standing {
    /// The fleet or the hot standby wants this member to command the device.
    pub preferred: bool,
    /// Its answer is a command (not a warm-up answer).
    pub warm: bool,
    /// In a fleet, whether it sees the sample's holder among the fleet's members: it is
    /// then the holder's partner, which holds every change the holder acknowledges.
    /// `None` without a fleet: nothing to be in step with.
    pub sees_holder: Option<bool>,
    /// It heard nothing of the device for a long while before this sample (its process
    /// was stopped, or it was cut off): it may have missed any change.
    pub gap: bool,
}

impl Standing {
    /// Preferred or not, warm, without a fleet.
    pub fn plain(preferred: bool, warm: bool) -> Self {
        Self {
            preferred,
            warm,
            sees_holder: None,
            gap: false,
        }
    }
}

/// What a sample says of its plant's lease.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Seen<'a> {
    /// The plant grants leases.
    pub granted: bool,
    /// The plant's run.
    pub run: u64,
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
            run: s.run_id,
            holder: &s.lease_holder,
            instance: s.lease_instance,
            epoch: s.lease_epoch,
        }
    }
}

/// Who commands a device, as its last sample said.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Holder {
    /// No sample yet.
    #[default]
    Unknown,
    /// The plant grants no lease.
    Nobody,
    /// The lease is vacant: no member commands the device.
    Vacant,
    /// This member (this process of it).
    Me,
    /// Another member, or another process of this one: this member is fenced.
    Other,
}

/// Whether a change to a device whose lease stands as `holder` may be acknowledged by
/// this member, which last heard the device at `heard_ns` (Unix ns; now `now_ns`), and
/// if not, why. When the plant grants leases, only the member commanding it (holding its
/// lease, and hearing it still) acknowledges: a member cut off from the plant, or one
/// answering while the lease is vacant, could otherwise acknowledge a change that the
/// member commanding the plant never holds.
///
/// The service asks twice: when it accepts a change, and again when the change's holds
/// end, since the lease may have moved while the partners were asked (the fleet's
/// simulation, seed 140593: a member acknowledged a change after its lease lapsed and
/// another member took the device over without it).
pub fn may_acknowledge(
    holder: Holder,
    (heard_ns, live_ns): (u64, u64),
    now_ns: u64,
) -> Result<(), String> {
    match holder {
        Holder::Me if now_ns.saturating_sub(heard_ns) > live_ns => Err(format!(
            "the device has not been heard here for {:.1} s, so this member may no longer \
             command it",
            now_ns.saturating_sub(heard_ns) as f64 / 1e9
        )),
        Holder::Vacant => Err("the device's lease is vacant: no member commands it".into()),
        Holder::Other => Err("another member commands the device".into()),
        Holder::Me | Holder::Nobody | Holder::Unknown => Ok(()),
    }
}

/// Whether a change accepted when this member saw the device's lease as `accepted` may
/// still be acknowledged now that it stands as `holder`, when its holds end. As
/// [`may_acknowledge`], and a device known at acceptance that is unknown now was
/// forgotten meanwhile (this member stopped following its shard, and its state here was
/// dropped): the member that takes it over was handed a state from before the change,
/// so the change may be in force nowhere (the fleet's simulation, seed 225770).
pub fn may_still_acknowledge(
    accepted: Holder,
    holder: Holder,
    heard: (u64, u64),
    now_ns: u64,
) -> Result<(), String> {
    if holder == Holder::Unknown && accepted != Holder::Unknown {
        return Err(
            "this member stopped following the device while its partners were \
                    asked, so it no longer commands it"
                .into(),
        );
    }
    may_acknowledge(holder, heard, now_ns)
}

/// One member's lease state for one device (a few counters: it lives in every device).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Claimer {
    /// Who held the lease at the last sample. The member holding it is the one whose
    /// changes are in force on the plant: only it accepts changes to the device.
    pub holder: Holder,
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
    /// Samples in a row that named another holder this member does not see.
    unseen: u32,
    /// The lease (run, epoch) as the last sample named it.
    key: (u64, u64),
    /// The lease (run, epoch) under which this member last held the lease or got the
    /// holder's state (`None`: never, or it may have missed changes since: it lost sight
    /// of the holder, heard nothing for a long while, or was not in step when the plant's
    /// run ended): its state holds every change acknowledged under the lease up to then.
    /// A holder sends its state to its partners as soon as it holds, so a member that
    /// missed a new holder's state (stopped, cut off, or over lossy links) is behind its
    /// epoch. `(0, 0)`: in step with a device under no lease yet (where it starts).
    synced: Option<(u64, u64)>,
    /// After it heard nothing for a long while, the newest lease among the first samples
    /// since ([`LATE_SAMPLES`], which may have waited for it): states sent under it or
    /// before may be late copies of what it missed, so only a later holder's state (or
    /// holding the lease itself) puts it in step again. A member stopped for a while is
    /// thus behind until the lease changes hands (a holder that is not preferred makes it
    /// change hands to bring it in step).
    gap_at: Option<(u64, u64)>,
    /// Samples taken since the silence, while they may still be late ones that waited
    /// (the service keeps at most the newest few per device).
    since_gap: u32,
    /// While it holds the lease without being preferred: its partners said they are in
    /// step with it (its state reached them, and they were not behind): it may yield.
    handed: bool,
    /// It gave the lease up although its partners were not in step with it: it takes it
    /// back at the first vacant sample, under a new epoch.
    reclaim: bool,
    /// It claimed the lease since this state was made. The plant grants a lease only to
    /// a claim, so a lease that names this process while this state never claimed was
    /// taken by a state since dropped: the member forgot the device (it stopped following
    /// its shard, `Registry::forget_shard`) and made it fresh again. Commanding with the
    /// fresh state would drop every change acknowledged under that lease, so it stays
    /// silent while so named (the lease lapses, and a member in step claims it first),
    /// and claims only as a member behind does.
    claimed: bool,
}

impl Default for Claimer {
    fn default() -> Self {
        Self {
            holder: Holder::default(),
            vacant: 0,
            held_unpreferred: 0,
            yield_after: 0,
            fenced: 0,
            claims: 0,
            yields: 0,
            unseen: 0,
            key: (0, 0),
            synced: Some((0, 0)),
            gap_at: None,
            since_gap: 0,
            handed: false,
            reclaim: false,
            claimed: false,
        }
    }
}

impl Claimer {
    /// The state of the member holding the lease under `(run, epoch)` reached this one
    /// (a change it holds, or the states a holder sends its partners when it takes the
    /// lease, before it yields it, or to a member that comes into its view).
    pub fn caught_up(&mut self, at: (u64, u64)) {
        if self.gap_at.is_some_and(|g| at <= g) {
            return;
        }
        self.gap_at = None;
        self.synced = Some(self.synced.map_or(at, |s| s.max(at)));
        self.unseen = 0;
    }

    /// This member's partners, sent its state, said whether they are in step with it
    /// ([`Claimer::hand_over_due`]): only then does it yield the lease it holds without
    /// being preferred, so that the preferred member claims at once; otherwise it keeps
    /// it, and tries again after twice the wait.
    pub fn handed_over(&mut self, in_step: bool) {
        self.handed = in_step && self.holder == Holder::Me;
    }

    /// Another member that does not hold the lease handed this one a state it had under
    /// the lease `(run, epoch)`: if this member is in step only with an earlier one, it
    /// missed a holder (a fresh process learns here that the device has had holders).
    pub fn heard_of(&mut self, at: (u64, u64)) {
        if self.synced.is_some_and(|s| s < at) {
            self.synced = None;
        }
    }

    /// Whether this member, standing as `st` says, may lack changes acknowledged under
    /// the lease: then it claims a vacant lease only after
    /// [`LeasePolicy::behind_delay`], so that a member in step wins whenever one is
    /// there. Never without a fleet.
    pub fn behind(&self, st: Standing) -> bool {
        self.epochs_behind(st) > 0
    }

    /// How many of the lease's epochs this member may have missed the changes of (0: in
    /// step; [`MAX_BEHIND`] when it cannot tell). At a run's start (epoch 0) nobody has
    /// held yet: in step if it was at the end of the last run.
    fn epochs_behind(&self, st: Standing) -> u64 {
        match self.synced {
            _ if st.sees_holder.is_none() => 0,
            None => MAX_BEHIND,
            Some(s) if self.key.1 == 0 || s >= self.key => 0,
            Some(s) if s.0 == self.key.0 => (self.key.1 - s.1).min(MAX_BEHIND),
            Some(_) => MAX_BEHIND,
        }
    }

    /// Whether the lease this member holds without being preferred will be yielded
    /// soon (halfway through the wait): the time to send its state to the preferred
    /// member, so that it claims in step.
    pub fn hand_over_due(&self, policy: &LeasePolicy) -> bool {
        let wait = match self.yield_after {
            0 => policy.yield_after,
            w => w,
        };
        self.holder == Holder::Me && self.held_unpreferred > 0 && self.held_unpreferred == wait / 2
    }

    /// What member `me` (its id and process) does with its answer to a sample that
    /// reports `seen`, standing as `st` says.
    pub fn decide(
        &mut self,
        policy: &LeasePolicy,
        me: (&str, u64),
        st: Standing,
        seen: Seen<'_>,
    ) -> Decision {
        let Standing {
            preferred, warm, ..
        } = st;
        let key = (seen.run, seen.epoch);
        let run_ended = key.0 != self.key.0 && self.synced.is_some_and(|s| s < self.key);
        if st.gap || run_ended {
            self.synced = None;
        }
        if st.gap {
            self.since_gap = 0;
        }
        if st.gap || self.gap_at.is_some() && self.since_gap < LATE_SAMPLES {
            // Until a later holder's state comes, what arrives may be a late copy of a
            // state sent before or during the silence: the newest epoch among the samples
            // that waited for it is where a later one starts.
            self.gap_at = Some(self.gap_at.unwrap_or(self.key).max(key));
            self.since_gap += 1;
        }
        self.key = key;
        self.holder = match seen.holder {
            _ if !seen.granted => Holder::Nobody,
            "" => Holder::Vacant,
            h if (h, seen.instance) == me => Holder::Me,
            _ => Holder::Other,
        };
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
            // Of the members behind, the nearest to the holder's epoch claims first: it
            // missed the fewest holders' changes.
            let behind = self.epochs_behind(st);
            let delay = match (behind > 0, warm || seen.epoch == 0, preferred) {
                _ if self.reclaim => 0,
                (true, ..) => policy.behind_delay + 3 * behind as u32,
                (false, false, _) => policy.cold_delay,
                (false, true, true) => 0,
                (false, true, false) => policy.standby_delay,
            };
            if self.vacant <= delay {
                return Decision::Quiet;
            }
            self.claims = self.claims.saturating_add(1);
            self.claimed = true;
            return Decision::Send {
                epoch: seen.epoch.saturating_add(1),
                claim: true,
                release: false,
            };
        }
        if !self.claimed && self.holder == Holder::Me {
            // Its process holds the lease, with a state this device no longer has.
            self.holder = Holder::Vacant;
            return Decision::Quiet;
        }
        self.vacant = 0;
        self.reclaim = false;
        if (seen.holder, seen.instance) != me {
            self.held_unpreferred = 0;
            self.handed = false;
            self.fenced = self.fenced.saturating_add(1);
            self.unseen = match st.sees_holder {
                Some(false) => self.unseen.saturating_add(1),
                _ => 0,
            };
            if self.unseen > policy.unseen_limit {
                self.synced = None;
            }
            return Decision::Fenced;
        }
        // It holds the lease: its state is the one in force (unless this sample is a late
        // one, from before a silence, that still names it).
        if self.gap_at.is_none_or(|g| self.key > g) {
            (self.synced, self.gap_at, self.unseen) = (Some(self.key), None, 0);
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
                // Yield once its partners said they are in step with it. Otherwise yield
                // only if in step itself: the preferred member, behind, waits; this one
                // takes the lease back at once under a new epoch, and the state it sends
                // its partners then puts them in step, so the next yield succeeds. One
                // not in step itself keeps the lease (it would wait as long as they).
                release = self.handed || !self.behind(st);
                self.reclaim = release && !self.handed;
                self.handed = false;
                self.held_unpreferred = 0;
                self.yield_after = wait.saturating_mul(2).min(policy.max_yield_after);
                self.yields = self.yields.saturating_add(u64::from(release));
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

    #[test]
    fn only_the_member_commanding_the_plant_acknowledges() {
        let s = 1_000_000_000;
        let live = s / 20;
        assert!(may_acknowledge(Holder::Me, (10 * s, live), 10 * s + live / 2).is_ok());
        let late = may_acknowledge(Holder::Me, (10 * s, live), 10 * s + 2 * live);
        assert!(late.is_err(), "not heard for twice the window");
        assert!(may_acknowledge(Holder::Vacant, (10 * s, live), 10 * s).is_err());
        assert!(may_acknowledge(Holder::Other, (10 * s, live), 10 * s).is_err());
        // A plant that grants no lease, or a device not heard yet: the fleet decides.
        assert!(may_acknowledge(Holder::Nobody, (0, live), 10 * s).is_ok());
        assert!(may_acknowledge(Holder::Unknown, (0, live), 10 * s).is_ok());
    }

    #[test]
    fn a_device_forgotten_while_its_change_was_held_is_not_acknowledged() {
        let s = 1_000_000_000;
        let heard = (10 * s, s / 20);
        let now = 10 * s + s / 100;
        assert!(may_still_acknowledge(Holder::Me, Holder::Me, heard, now).is_ok());
        assert!(may_still_acknowledge(Holder::Me, Holder::Unknown, (0, s / 20), now).is_err());
        assert!(may_still_acknowledge(Holder::Nobody, Holder::Unknown, (0, 0), now).is_err());
        assert!(may_still_acknowledge(Holder::Me, Holder::Other, heard, now).is_err());
        // Never heard, then or now: the fleet decides, as at acceptance.
        assert!(may_still_acknowledge(Holder::Unknown, Holder::Unknown, (0, 0), now).is_ok());
    }

    fn seen(holder: &str, epoch: u64) -> Seen<'_> {
        Seen {
            granted: true,
            run: 1,
            holder,
            instance: 0,
            epoch,
        }
    }

    /// A member whose state claimed the lease (the plant names only a claimant holder).
    fn claimed() -> Claimer {
        Claimer {
            claimed: true,
            ..Claimer::default()
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
            run: 1,
            holder: "",
            instance: 0,
            epoch: 0,
        };
        assert_eq!(
            c.decide(&p, ("a", 0), Standing::plain(true, true), plain),
            Decision::Plain
        );
        assert_eq!(
            c.decide(&p, ("a", 0), Standing::plain(false, true), plain),
            Decision::Quiet
        );
    }

    #[test]
    fn the_preferred_member_claims_at_once_another_after_the_delay() {
        let p = LeasePolicy::default();
        let (mut a, mut b) = (Claimer::default(), Claimer::default());
        assert_eq!(
            a.decide(&p, ("a", 0), Standing::plain(true, true), seen("", 1)),
            CLAIM2
        );
        for _ in 0..p.standby_delay {
            assert_eq!(
                b.decide(&p, ("b", 0), Standing::plain(false, true), seen("", 1)),
                Decision::Quiet
            );
        }
        assert_eq!(
            b.decide(&p, ("b", 0), Standing::plain(false, true), seen("", 1)),
            CLAIM2
        );
        // A sample that shows a holder resets the count.
        assert_eq!(
            b.decide(&p, ("b", 0), Standing::plain(false, true), seen("a", 2)),
            Decision::Fenced
        );
        assert_eq!(
            b.decide(&p, ("b", 0), Standing::plain(false, true), seen("", 2)),
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
                c.decide(&p, ("c", 0), Standing::plain(true, false), seen("", 1)),
                Decision::Quiet
            );
        }
        assert_eq!(
            c.decide(&p, ("c", 0), Standing::plain(true, false), seen("", 1)),
            CLAIM2
        );
        assert!(p.cold_delay > p.standby_delay);
        // At the run's start (nothing granted yet) everybody is cold: no wait.
        let mut c = Claimer::default();
        assert!(c
            .decide(&p, ("c", 0), Standing::plain(true, false), seen("", 0))
            .sends());
    }

    #[test]
    fn a_member_that_is_not_the_holder_is_fenced_even_if_preferred() {
        let p = LeasePolicy::default();
        let mut a = claimed();
        assert_eq!(
            a.decide(&p, ("a", 0), Standing::plain(true, true), seen("b", 4)),
            Decision::Fenced
        );
        let held = a.decide(&p, ("a", 0), Standing::plain(true, true), seen("a", 4));
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
    fn a_member_that_forgot_the_device_stays_silent_under_its_own_lease_and_claims_as_one_behind() {
        let p = LeasePolicy::default();
        let fleet = Standing {
            preferred: true,
            warm: true,
            sees_holder: Some(true),
            gap: false,
        };
        let mut c = Claimer::default();
        for _ in 0..20 {
            assert_eq!(
                c.decide(&p, ("a", 0), fleet, seen("a", 4)),
                Decision::Quiet,
                "its process holds the lease, but not with this state"
            );
            assert_eq!(c.holder, Holder::Vacant, "it does not command the plant");
        }
        // The lease lapses: it claims, but only after a member in step would have.
        let mut quiet = 0;
        while c.decide(&p, ("a", 0), fleet, seen("", 4)) == Decision::Quiet {
            quiet += 1;
            assert!(quiet < 1000, "it never claims");
        }
        assert!(
            quiet >= p.behind_delay,
            "claimed after {quiet} vacant samples"
        );
        let held = c.decide(&p, ("a", 0), fleet, seen("a", 5));
        assert!(matches!(held, Decision::Send { .. }), "{held:?}");
        assert_eq!(
            c.holder,
            Holder::Me,
            "once it claimed, its state is in force"
        );
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
            a.decide(&p, ("a", 7), Standing::plain(true, true), other),
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
            behind_delay: 30,
            unseen_limit: 5,
            ..LeasePolicy::default()
        };
        let mut b = claimed();
        let mut yields_at = Vec::new();
        for k in 0..40 {
            let d = b.decide(&p, ("b", 0), Standing::plain(false, true), seen("b", 1));
            if let Decision::Send { release: true, .. } = d {
                yields_at.push(k);
            }
        }
        // After 3, then 6, then 10 (the cap) samples held.
        assert_eq!(yields_at, [2, 8, 18, 28, 38]);
        // A fleet member holding after a long silence (not in step itself) yields only
        // once its partners said they are in step with it.
        let fleet = Standing {
            preferred: false,
            warm: true,
            sees_holder: Some(true),
            gap: false,
        };
        let mut c = claimed();
        c.decide(&p, ("c", 0), Standing { gap: true, ..fleet }, seen("c", 1));
        let mut yields_at = Vec::new();
        for k in 0..20 {
            let d = c.decide(&p, ("c", 0), fleet, seen("c", 1));
            if let Decision::Send { release: true, .. } = d {
                yields_at.push(k);
            }
            c.handed_over(k >= 10);
        }
        assert_eq!(yields_at.len(), 1, "{yields_at:?}");
        assert!(yields_at[0] >= 10, "kept until handed over: {yields_at:?}");
        // Preferred again: it holds for good, and the next yield waits the first time again.
        assert_eq!(
            b.decide(&p, ("b", 0), Standing::plain(true, true), seen("b", 1)),
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

    #[test]
    fn a_fleet_member_not_in_step_with_the_holder_claims_late() {
        let p = LeasePolicy::default();
        let st = |sees| Standing {
            preferred: true,
            warm: true,
            sees_holder: Some(sees),
            gap: false,
        };
        let in_step = || {
            let mut c = Claimer::default();
            c.caught_up((1, 1));
            c
        };
        // A crashed holder is out of view for the few samples its lease takes to lapse:
        // still in step, the preferred member claims at once.
        let mut b = in_step();
        for _ in 0..3 {
            assert_eq!(
                b.decide(&p, ("b", 0), st(false), seen("a", 1)),
                Decision::Fenced
            );
        }
        assert!(!b.behind(st(false)));
        assert!(b.decide(&p, ("b", 0), st(false), seen("", 1)).sends());
        // A partitioned holder commands on out of view: the member falls behind, and
        // claims a vacant lease only after the long delay.
        let mut b = in_step();
        for _ in 0..=p.unseen_limit {
            b.decide(&p, ("b", 0), st(false), seen("a", 1));
        }
        assert!(b.behind(st(true)));
        // It cannot tell by how many epochs: the longest wait.
        for _ in 0..p.behind_delay + 3 * 10 {
            assert_eq!(
                b.decide(&p, ("b", 0), st(true), seen("", 1)),
                Decision::Quiet
            );
        }
        assert!(b.decide(&p, ("b", 0), st(true), seen("", 1)).sends());
        // One epoch behind: five samples more than the delay.
        let mut b = in_step();
        b.decide(&p, ("b", 0), st(true), seen("a", 2));
        let waited = (0..200)
            .take_while(|_| !b.decide(&p, ("b", 0), st(true), seen("", 2)).sends())
            .count();
        assert_eq!(waited as u32, p.behind_delay + 3);
        // A member that never got the holder's state is not in step either; the holder's
        // state puts it in step; holding the lease does too.
        let mut b = Claimer::default();
        b.decide(&p, ("b", 0), st(true), seen("a", 1));
        assert!(b.behind(st(true)));
        assert!(
            !b.behind(Standing::plain(true, true)),
            "without a fleet, never"
        );
        b.caught_up((1, 1));
        assert!(b.decide(&p, ("b", 0), st(true), seen("", 1)).sends());
        // In step at epoch 1, it missed the state of epoch 2's holder: behind again.
        b.decide(&p, ("b", 0), st(true), seen("a", 2));
        assert!(b.behind(st(true)));
        let mut b = claimed();
        b.decide(&p, ("b", 0), st(true), seen("b", 1));
        assert!(!b.behind(st(true)));
        // At a run's start (epoch 0), a member in step at the end of the last run (or in
        // step with a device never leased) claims at once; one never in step waits.
        let mut b = in_step();
        b.decide(&p, ("b", 0), st(true), seen("b", 1));
        let next_run = Seen {
            run: 2,
            ..seen("", 0)
        };
        assert!(b.decide(&p, ("b", 0), st(true), next_run).sends());
        let mut b = Claimer::default();
        assert!(
            b.decide(&p, ("b", 0), st(true), next_run).sends(),
            "a fresh device"
        );
        let mut b = Claimer::default();
        b.heard_of((1, 3));
        assert_eq!(b.decide(&p, ("b", 0), st(true), next_run), Decision::Quiet);
        // A long silence (a stopped process) puts it behind; a state sent under that
        // epoch may be a late copy of what it missed: only a later holder's counts.
        let mut b = in_step();
        let gap = Standing {
            gap: true,
            ..st(true)
        };
        assert_eq!(b.decide(&p, ("b", 0), gap, seen("a", 1)), Decision::Fenced);
        b.caught_up((1, 1));
        assert!(b.behind(st(true)));
        // Nor one of the holder heard since (it may have been sent during the silence);
        // a later holder's does.
        b.decide(&p, ("b", 0), st(true), seen("a", 2));
        b.caught_up((1, 2));
        assert!(b.behind(st(true)));
        b.caught_up((1, 3));
        assert!(!b.behind(st(true)));
    }

    #[test]
    fn an_unpreferred_holder_hands_its_state_over_halfway_to_its_yield() {
        let p = LeasePolicy::default();
        let mut a = claimed();
        let mut due = Vec::new();
        for k in 1..=p.yield_after {
            let d = a.decide(&p, ("a", 0), Standing::plain(false, true), seen("a", 1));
            if a.hand_over_due(&p) {
                due.push(k);
                a.handed_over(true);
            }
            if k == p.yield_after {
                assert!(matches!(d, Decision::Send { release: true, .. }));
            }
        }
        assert_eq!(due, [p.yield_after / 2]);
    }
}

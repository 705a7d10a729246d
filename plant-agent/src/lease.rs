//! The plant's command lease: the plant, not the controllers, decides who commands it.
//!
//! Several controllers may answer one plant at once: the owner and the standby of a fleet
//! that a partition split, a paused process that woke up after its successor took over, a
//! second service started by mistake. Whatever they believe, the plant applies the
//! commands of one of them only, the *holder* of its lease, and only under the holder's
//! *epoch*. That is the fencing token of Chubby's sequencers and of PROFINET's system
//! redundancy: the resource refuses a token that is not the newest it has granted, so a
//! stale holder is stopped where it matters, at the actuator, whatever the network did.
//!
//! The rules, all on numbers the agent passes in:
//! * Every sample publishes the lease: the holder (empty while vacant) and the epoch.
//! * A command from the holder under the current epoch and for this run passes; any other
//!   is refused ([`Fence`]) and counted, and the next sample tells its sender who holds the
//!   lease, so a stale controller stops at once.
//! * A vacant lease is granted to the first command that claims it, names the epoch one
//!   above the vacant one, and passes every other rule of the supervisor (a command the
//!   supervisor would drop grants nothing). The new epoch is never granted again in the
//!   run, and a run never reuses another's because commands carry the run's random id.
//! * The lease lapses when its holder has been silent (neither a command nor a warm-up
//!   answer of its own, nor an answer to a recent sample overtaken by a newer one of its
//!   own) for half the agent's `hold_periods`, or longer when the holder's answers come
//!   late (`Supervisor::lease_lapse`; timed on the agent's own pacing, never on
//!   a wall clock): a holder that warms up keeps it while the fallback runs, and
//!   otherwise another
//!   controller can then claim it while the plant still holds the last command, before
//!   the fallback engages; and it lapses when the holder gives it up (`release`, once its
//!   command is applied). Nobody claims: the fallback engages after the whole hold, as
//!   without leases.
//! * A lease that lapsed while its holder was answering, only late, goes back to it: while
//!   nobody has claimed since, the holder's answer to a sample published before the lapse,
//!   under its epoch, reinstates it (`Pass::Resumed`; `LeaseCounters::resumed`). Nobody
//!   else was granted anything meanwhile, so it is as if the lapse had come later; a claim
//!   sent on the vacant samples then finds the lease held and is refused. Without this, a
//!   spike of lateness past the lapse (a 10 ms loop, links of 2-15 ms each way) left the
//!   plant on its fallback for a period while the holder claimed again.
//!
//! No I/O, no clock: the [`crate::safety::Supervisor`] owns one and calls it.

use serde::{Deserialize, Serialize};

/// Why the lease refused a command.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Fence {
    /// It answers another run of the plant (a replay of an earlier run, or a controller
    /// that has not seen the restart yet).
    OtherRun,
    /// The lease is held by another controller.
    NotHolder,
    /// From the holder, but under another epoch: a paused or partitioned process that
    /// lost the lease and got it back would otherwise resume with an old state.
    StaleEpoch,
    /// A claim of a lease that is not vacant, or of an epoch other than the next one.
    BadClaim,
    /// Not a claim while the lease is vacant: a former holder still commanding.
    Vacant,
}

/// What the lease says of a command that passed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pass {
    /// From the holder, under its epoch.
    Holder,
    /// A valid claim of the vacant lease: granted if the supervisor applies the command.
    Claim,
    /// The holder whose lease lapsed, answering late a sample of its own tenure under its
    /// epoch while nobody has claimed since: reinstated if the supervisor accepts the
    /// command.
    Resumed,
}

/// The lease's counters over a run.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct LeaseCounters {
    /// Leases granted (also the last epoch).
    pub grants: u64,
    /// Leases that lapsed (their holder silent for the lapse: half the hold, or longer
    /// while its answers land late).
    pub lapses: u64,
    /// Leases given up by their holder.
    pub releases: u64,
    /// Lapsed leases that went back to their holder, whose late answer to a sample of its
    /// tenure came before anyone claimed.
    #[serde(default)]
    pub resumed: u64,
    /// Commands refused, by reason.
    pub other_run: u64,
    pub not_holder: u64,
    pub stale_epoch: u64,
    pub bad_claim: u64,
    pub vacant: u64,
}

impl LeaseCounters {
    /// All commands the lease refused.
    pub fn refused(&self) -> u64 {
        self.other_run + self.not_holder + self.stale_epoch + self.bad_claim + self.vacant
    }
}

/// Most holder spans a run keeps (the later ones are only counted): a fleet that changes
/// holder a thousand times in one run has a problem the first ones show.
pub const MAX_SPANS: usize = 1024;

/// A stretch of periods whose commands all came from one holder under one epoch: the
/// plant's own record of who commanded it, from which the tests count what matters
/// (two holders in one period, a stale epoch, the time a takeover took).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Span {
    pub holder: String,
    /// The holder's process (random per start, `Credentials::instance`): two processes
    /// carrying one controller id make two spans, told apart here. Absent in reports of
    /// older builds (read as 0).
    #[serde(default)]
    pub instance: u64,
    pub epoch: u64,
    /// The first and last period in which a command of this holder was applied.
    pub first: u64,
    pub last: u64,
    /// Commands applied.
    pub commands: u64,
}

/// The lease's part of a run's report (`summary.json`).
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct LeaseReport {
    pub counters: LeaseCounters,
    /// Who commanded, in order (at most [`MAX_SPANS`]).
    pub spans: Vec<Span>,
    /// Spans past [`MAX_SPANS`], counted only.
    pub spans_dropped: u64,
}

/// The command lease of one plant run (see the module documentation).
#[derive(Debug, Clone)]
pub struct Lease {
    run_id: u64,
    holder: Option<String>,
    instance: u64,
    /// Periods ended since the holder's last accepted answer (a command or a warm-up).
    idle: u32,
    /// An answer of the holder was accepted in the open period.
    renewed: bool,
    epoch: u64,
    /// The holder whose lease lapsed last, its process, and the first period after its
    /// tenure, while nobody has claimed since (see [`Pass::Resumed`]).
    lapsed: Option<(String, u64, u64)>,
    counters: LeaseCounters,
    spans: Vec<Span>,
    spans_dropped: u64,
    /// The grant counted last past [`MAX_SPANS`].
    spans_counted: u64,
}

/// Who sent a command and under which lease, as the wire says.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Credentials<'a> {
    /// The sender's controller id.
    pub from: &'a str,
    /// The sender's process (random per start): one id may be carried by two processes.
    pub instance: u64,
    /// The epoch it commands under, or claims.
    pub epoch: u64,
    /// It claims a vacant lease.
    pub claim: bool,
    /// It gives the lease up once this command is applied.
    pub release: bool,
    /// The run it answers.
    pub run_id: u64,
}

impl Lease {
    /// A vacant lease at epoch 0, for the run `run_id`.
    pub fn new(run_id: u64) -> Self {
        Self {
            run_id,
            holder: None,
            instance: 0,
            idle: 0,
            renewed: false,
            epoch: 0,
            lapsed: None,
            counters: LeaseCounters::default(),
            spans: Vec::new(),
            spans_dropped: 0,
            spans_counted: 0,
        }
    }

    /// What the run's report keeps of the lease.
    pub fn report(&self) -> LeaseReport {
        LeaseReport {
            counters: self.counters.clone(),
            spans: self.spans.clone(),
            spans_dropped: self.spans_dropped,
        }
    }

    /// The holder, if any.
    pub fn holder(&self) -> Option<&str> {
        self.holder.as_deref()
    }

    /// The holder's process (meaningful while held).
    pub fn instance(&self) -> u64 {
        self.instance
    }

    /// The epoch granted last (0: never granted).
    pub fn epoch(&self) -> u64 {
        self.epoch
    }

    /// The counters so far.
    pub fn counters(&self) -> &LeaseCounters {
        &self.counters
    }

    /// Whether a command with these credentials, answering the sample `seq`, may be
    /// applied; counts a refusal.
    pub fn check(&mut self, c: &Credentials<'_>, seq: u64) -> Result<Pass, Fence> {
        let verdict = self.judge(c, seq);
        if let Err(why) = verdict {
            let n = &mut self.counters;
            let counter = match why {
                Fence::OtherRun => &mut n.other_run,
                Fence::NotHolder => &mut n.not_holder,
                Fence::StaleEpoch => &mut n.stale_epoch,
                Fence::BadClaim => &mut n.bad_claim,
                Fence::Vacant => &mut n.vacant,
            };
            *counter = counter.saturating_add(1);
        }
        verdict
    }

    fn judge(&self, c: &Credentials<'_>, seq: u64) -> Result<Pass, Fence> {
        if c.run_id != self.run_id {
            return Err(Fence::OtherRun);
        }
        let same = |h: &String| h == c.from && c.instance == self.instance;
        match &self.holder {
            Some(h) if same(h) && c.epoch == self.epoch => Ok(Pass::Holder),
            Some(h) if same(h) => Err(Fence::StaleEpoch),
            Some(_) if c.claim => Err(Fence::BadClaim),
            Some(_) => Err(Fence::NotHolder),
            // Only a name a controller can have is granted (the protocol's id rules):
            // the holder is printable in every sample, and the state it keeps bounded.
            None if c.claim
                && Some(c.epoch) == self.epoch.checked_add(1)
                && protocol::keys::check_id(c.from).is_ok() =>
            {
                Ok(Pass::Claim)
            }
            None if c.claim => Err(Fence::BadClaim),
            None if self.resumes(c, seq) => Ok(Pass::Resumed),
            None => Err(Fence::Vacant),
        }
    }

    /// The supervisor accepted a command that passed [`Lease::check`] (and applied it in
    /// period `applied_in`, if it was a control): a claim is granted now, the command goes
    /// into the holder's span, and a release gives the lease up after it.
    pub fn accepted(&mut self, pass: Pass, c: &Credentials<'_>, applied_in: Option<u64>) {
        match pass {
            Pass::Claim => {
                self.epoch = c.epoch;
                self.holder = Some(c.from.to_owned());
                self.instance = c.instance;
                self.counters.grants = self.counters.grants.saturating_add(1);
            }
            Pass::Resumed => {
                self.holder = Some(c.from.to_owned());
                self.counters.resumed = self.counters.resumed.saturating_add(1);
            }
            Pass::Holder => {}
        }
        self.lapsed = None;
        self.renewed = true;
        if let Some(k) = applied_in {
            self.record(c.from, k);
        }
        if c.release {
            self.holder = None;
            self.counters.releases = self.counters.releases.saturating_add(1);
        }
    }

    fn record(&mut self, holder: &str, k: u64) {
        let (epoch, instance) = (self.epoch, self.instance);
        let full = self.spans.len() >= MAX_SPANS;
        match self.spans.last_mut() {
            Some(s) if s.holder == holder && s.epoch == epoch && s.instance == instance => {
                s.last = k;
                s.commands = s.commands.saturating_add(1);
            }
            _ if full => {
                // Past the cap, the spans are counted: a new one starts at each grant.
                if self.counters.grants > self.spans_counted {
                    self.spans_counted = self.counters.grants;
                    self.spans_dropped = self.spans_dropped.saturating_add(1);
                }
            }
            _ => self.spans.push(Span {
                holder: holder.to_owned(),
                instance,
                epoch,
                first: k,
                last: k,
                commands: 1,
            }),
        }
    }

    /// The holder's answer came but is not applied (the supervisor had applied a newer
    /// one of the holder's): it is not silent in this period, so the lease is renewed.
    /// The supervisor calls it only for an answer that passed [`Lease::check`] as the
    /// holder's, to a sample of the last lapse's worth of periods.
    pub fn heard(&mut self) {
        self.renewed = true;
    }

    /// A period ended: the holder's silence grows unless it answered in it.
    pub fn end_period(&mut self) {
        self.idle = if self.renewed {
            0
        } else {
            self.idle.saturating_add(1)
        };
        self.renewed = false;
    }

    /// Periods ended since the holder last answered (a command or a warm-up answer that
    /// passed): what the lapse is timed on.
    pub fn idle(&self) -> u32 {
        self.idle
    }

    /// The holder was silent too long: the lease lapses (if it was held) at the start of
    /// period `k`, the first after its tenure.
    pub fn lapse(&mut self, k: u64) {
        if let Some(holder) = self.holder.take() {
            self.counters.lapses = self.counters.lapses.saturating_add(1);
            self.lapsed = Some((holder, self.instance, k));
        }
    }

    /// Whether a command that does not claim the vacant lease comes from the holder whose
    /// lease lapsed, under its epoch, for a sample published before the lapse, with nobody
    /// granted since ([`Pass::Resumed`]).
    fn resumes(&self, c: &Credentials<'_>, seq: u64) -> bool {
        self.lapsed.as_ref().is_some_and(|(holder, instance, k)| {
            holder == c.from && *instance == c.instance && seq < *k && c.epoch == self.epoch
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cred(from: &str, epoch: u64, claim: bool) -> Credentials<'_> {
        Credentials {
            from,
            instance: 3,
            epoch,
            claim,
            release: false,
            run_id: 7,
        }
    }

    fn grant(l: &mut Lease, from: &str) -> u64 {
        let c = cred(from, l.epoch() + 1, true);
        assert_eq!(l.check(&c, 0), Ok(Pass::Claim));
        l.accepted(Pass::Claim, &c, None);
        l.epoch()
    }

    #[test]
    fn a_vacant_lease_goes_to_the_first_valid_claim_only() {
        let mut l = Lease::new(7);
        assert_eq!(l.check(&cred("a", 0, false), 0), Err(Fence::Vacant));
        assert_eq!(l.check(&cred("a", 0, true), 0), Err(Fence::BadClaim));
        assert_eq!(l.check(&cred("a", 2, true), 0), Err(Fence::BadClaim));
        assert_eq!(grant(&mut l, "a"), 1);
        assert_eq!(l.holder(), Some("a"));
        // The loser of the race is refused, claim or not.
        assert_eq!(l.check(&cred("b", 1, true), 0), Err(Fence::BadClaim));
        assert_eq!(l.check(&cred("b", 1, false), 0), Err(Fence::NotHolder));
        assert_eq!(l.check(&cred("a", 1, false), 0), Ok(Pass::Holder));
        // A holder's later claims of the same epoch (answers to samples sent before the
        // grant) pass as the holder's.
        assert_eq!(l.check(&cred("a", 1, true), 0), Ok(Pass::Holder));
        assert_eq!(l.counters().refused(), 5);
    }

    #[test]
    fn epochs_only_go_up_and_a_stale_holder_is_fenced() {
        let mut l = Lease::new(7);
        grant(&mut l, "a");
        l.lapse(5);
        assert_eq!(l.holder(), None);
        // The former holder wakes up: answering a sample that said the lease was vacant,
        // its old epoch is refused, it must claim again.
        assert_eq!(l.check(&cred("a", 1, false), 5), Err(Fence::Vacant));
        assert_eq!(grant(&mut l, "b"), 2);
        // Its late answers to its own tenure's samples no longer count once b holds.
        assert_eq!(l.check(&cred("a", 1, false), 4), Err(Fence::NotHolder));
        l.lapse(9);
        assert_eq!(grant(&mut l, "a"), 3);
        assert_eq!(l.check(&cred("a", 1, false), 0), Err(Fence::StaleEpoch));
        assert_eq!(l.counters().lapses, 2);
        assert_eq!(l.counters().grants, 3);
    }

    /// The holder answered, only late: its answer to a sample of its tenure gives it the
    /// lease back while nobody has claimed, under the same epoch and in the same span.
    #[test]
    fn a_lapsed_holder_answering_late_gets_its_lease_back_until_someone_claims() {
        let mut l = Lease::new(7);
        grant(&mut l, "a");
        l.accepted(Pass::Holder, &cred("a", 1, false), Some(1));
        l.lapse(5);
        assert_eq!(l.check(&cred("a", 1, false), 4), Ok(Pass::Resumed));
        // Not for a sample that said vacant, another process, or another epoch.
        assert_eq!(l.check(&cred("a", 1, false), 5), Err(Fence::Vacant));
        let mut twin = cred("a", 1, false);
        twin.instance = 4;
        assert_eq!(l.check(&twin, 4), Err(Fence::Vacant));
        assert_eq!(l.check(&cred("a", 2, false), 4), Err(Fence::Vacant));
        l.accepted(Pass::Resumed, &cred("a", 1, false), Some(6));
        assert_eq!((l.holder(), l.epoch(), l.instance()), (Some("a"), 1, 3));
        // A claim sent on the vacant samples finds it held.
        assert_eq!(l.check(&cred("b", 2, true), 6), Err(Fence::BadClaim));
        let c = l.counters();
        assert_eq!((c.lapses, c.resumed, c.grants, c.vacant), (1, 1, 1, 3));
        let spans: Vec<_> = l
            .report()
            .spans
            .iter()
            .map(|s| (s.epoch, s.first, s.last))
            .collect();
        assert_eq!(spans, [(1, 1, 6)], "one tenure");
        // Once another holds it, the late answers are refused as anyone's.
        l.lapse(8);
        assert_eq!(grant(&mut l, "b"), 2);
        assert_eq!(l.check(&cred("a", 1, false), 7), Err(Fence::NotHolder));
    }

    #[test]
    fn a_second_process_with_the_holders_id_is_fenced() {
        let mut l = Lease::new(7);
        grant(&mut l, "a");
        let mut c = cred("a", 1, false);
        c.instance = 4;
        assert_eq!(l.check(&c, 0), Err(Fence::NotHolder));
        assert_eq!(l.instance(), 3);
    }

    #[test]
    fn another_run_is_refused_whatever_it_says() {
        let mut l = Lease::new(7);
        grant(&mut l, "a");
        let mut c = cred("a", 1, false);
        c.run_id = 8;
        assert_eq!(l.check(&c, 0), Err(Fence::OtherRun));
        c.claim = true;
        c.epoch = 2;
        assert_eq!(l.check(&c, 0), Err(Fence::OtherRun));
        assert_eq!(l.counters().other_run, 2);
    }

    /// Two processes carrying one controller id (a copied bundle): the plant's record
    /// tells their spans apart by the process.
    #[test]
    fn two_processes_of_one_id_are_two_spans() {
        let mut l = Lease::new(7);
        grant(&mut l, "c-1");
        let first = cred("c-1", 1, false);
        l.accepted(Pass::Holder, &first, Some(1));
        l.lapse(2);
        let mut twin = cred("c-1", 2, true);
        twin.instance = 9;
        assert_eq!(l.check(&twin, 0), Ok(Pass::Claim));
        l.accepted(Pass::Claim, &twin, Some(5));
        let spans = l.report().spans;
        let who: Vec<(&str, u64, u64)> = spans
            .iter()
            .map(|s| (s.holder.as_str(), s.instance, s.epoch))
            .collect();
        assert_eq!(who, [("c-1", 3, 1), ("c-1", 9, 2)]);
    }

    #[test]
    fn release_vacates_after_the_command() {
        let mut l = Lease::new(7);
        grant(&mut l, "a");
        let mut c = cred("a", 1, false);
        c.release = true;
        assert_eq!(l.check(&c, 0), Ok(Pass::Holder));
        l.accepted(Pass::Holder, &c, Some(3));
        assert_eq!((l.holder(), l.epoch()), (None, 1));
        assert_eq!(l.counters().releases, 1);
        assert_eq!(
            l.report().spans,
            [Span {
                holder: "a".into(),
                instance: 3,
                epoch: 1,
                first: 3,
                last: 3,
                commands: 1
            }]
        );
        // Lapsing a vacant lease counts nothing.
        l.lapse(4);
        assert_eq!(l.counters().lapses, 0);
    }

    #[test]
    fn spans_past_the_cap_are_counted_once_per_grant() {
        let mut l = Lease::new(7);
        for k in 0..(MAX_SPANS as u64 + 10) {
            let who = if k % 2 == 0 { "a" } else { "b" };
            let c = cred(who, l.epoch() + 1, true);
            let pass = l.check(&c, 0).unwrap();
            l.accepted(pass, &c, Some(2 * k));
            // A second command of the same holder in the next period.
            let c = cred(who, l.epoch(), false);
            l.accepted(l.clone().check(&c, 0).unwrap(), &c, Some(2 * k + 1));
            l.lapse(2 * k + 2);
        }
        let r = l.report();
        assert_eq!(r.spans.len(), MAX_SPANS);
        assert_eq!(r.spans_dropped, 10);
        assert_eq!(
            (r.spans[5].first, r.spans[5].last, r.spans[5].commands),
            (10, 11, 2)
        );
    }

    #[test]
    fn only_a_name_a_controller_can_have_is_granted() {
        let mut l = Lease::new(7);
        let long = "x".repeat(65);
        for bad in [long.as_str(), "", "a/b", "a*", "ctl\n"] {
            assert_eq!(
                l.check(&cred(bad, 1, true), 0),
                Err(Fence::BadClaim),
                "{bad:?}"
            );
        }
        assert_eq!(grant(&mut l, &long[..64]), 1);
    }
}

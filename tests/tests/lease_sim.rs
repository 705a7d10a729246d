//! One controller per plant, under thousands of seeded fault schedules: the plant agent's
//! own rules ([`Supervisor`] with its command lease) and each fleet member's
//! ([`Claimer`], the fleet's rendezvous ranking), driven by a harness of virtual
//! milliseconds over a simulated network: loss, delay past a period, duplication and
//! reordering on every link; partitions one-way and two-way between the plant and a
//! member, and between members (each side then believes it owns the plant); members
//! paused (their inbox fills and is served, stale, when they resume), crashed and
//! restarted cold; the agent restarted with a new run while commands of the old one are
//! still in flight and the last 300 commands of the old run played back into the new one
//! at their sequence numbers; in one schedule in three, a rogue controller that answers every
//! sample as if it held the lease; and in one in eight, a member that now and then puts an
//! epoch of its own making on its commands while it holds the lease (a bug of ours, or a
//! forged command that passed the MACs). No clock is read and nothing is random but the
//! seed: a failing seed prints the command that replays it.
//!
//! The invariants come from the plant's side, as the agent records them:
//! * no period in which commands of two holders were applied;
//! * no command applied under another epoch than the lease's, or another run, or with a
//!   sequence number not above the last applied one; an epoch never granted twice, and
//!   never going back;
//! * no stretch of periods on a held command longer than the watchdog (`hold_periods`):
//!   past it the fallback runs;
//! * once the faults are over, the plant is back under remote control by one holder
//!   (off the fallback through the last half second, commands in most periods, from one
//!   holder, or two if it yielded to the member the fleet prefers);
//! * no acknowledged change lost: an operator changes the configuration every 150 to
//!   400 ms through whichever member answers operators (the holder, else the shard's
//!   owner), which acknowledges as the service does (only while it commands the plant,
//!   once every partner holds it); every command applied afterwards comes from a state
//!   that holds every change acknowledged before it was sent, unless no member holding
//!   the change could have commanded in step through a behind member's whole wait (all
//!   crashed, stopped, cut off, or unsure), which is counted and printed.
//!
//! The holds of a change are the service's own: each member's `Replication` (the rules of
//! `controller-service/src/replication.rs`, which the service's hold task drives), given
//! the partners' answers and the time, and carried out here over the simulated network.
//! Still modelled after the service's wiring: the states a holder sends when it takes the
//! lease, halfway to a yield and to a member that comes into its view, the copy a member
//! asks for when it starts following the shard, and the versioned, holder-checked restore
//! (`Registry::restore_shard`, `hold_shard`). The shard's ownership itself (handover
//! requests) is the fleet's own simulation's (`controller-service/tests/virtual_time.rs`).

use simulation::SplitMix;
use std::collections::{BTreeSet, HashMap};
use std::io::Write;

use controller_service::fleet::ranked;
use controller_service::lease::{
    may_acknowledge, may_still_acknowledge, Claimer, Decision, Holder, LeasePolicy, Seen, Standing,
    Version,
};
use controller_service::replication::{Effect, Job, PartnerAnswer, Replication};
use mfc::{ChannelConfig, ControllerKind, LawConfig, Order, OutputMapConfig, Reference};
use plant_agent::lease::Credentials;
use plant_agent::safety::{
    CommandBody, FallbackPolicy, IncomingCommand, LoopMode, SafetyConfig, Supervisor, Verdict,
};

/// The period, ms.
const H: u64 = 10;
const HOLD: u32 = 5;
const MAX_AGE: u32 = 10;
const MEMBERS: usize = 3;
/// Periods with faults, then periods of calm in which the plant must come back.
const FAULTY: u64 = 500;
const CALM: u64 = 200;
/// Samples a member answers "warming up" after it starts stepping a run cold.
const WARMUP: u32 = 20;
/// Commands an eavesdropper keeps, to replay into the plant's next run.
const CAPTURED: usize = 300;
/// How long the others still see a paused member (zenoh's link lease, in ms; shortened).
const ZENOH_LEASE: u64 = 500;
/// How long a member waits for its partners to hold a change (the fleet's
/// `handover_timeout_ms`), and how long the operator waits for the reply, ms.
const HOLD_TIMEOUT: u64 = 500;
/// A millisecond of virtual time in the service's units (ns).
const MS: u64 = 1_000_000;
const OPERATOR_TIMEOUT: u64 = 2000;
/// The stream of the miscounting member's draws (`Sim::miscount`), apart from the
/// schedule's: adding it changed no other draw of any seed.
const MISCOUNT_STREAM: u64 = 0x6d69_7363_6f75_6e74;
/// How recently the member commanding a device must have heard it to acknowledge (ms):
/// five periods (`Registry::live_ns`).
const LIVE: u64 = 5 * H;

#[derive(Debug, Clone)]
struct SampleMsg {
    run_id: u64,
    seq: u64,
    holder: String,
    instance: u64,
    epoch: u64,
}

#[derive(Debug, Clone)]
struct CommandMsg {
    from: String,
    /// The sender's configuration when it answered: the changes it holds.
    state: std::rc::Rc<Vec<u32>>,
    /// When it was sent (ms).
    sent_at: u64,
    instance: u64,
    run_id: u64,
    seq: u64,
    epoch: u64,
    claim: bool,
    release: bool,
    warming: bool,
}

#[derive(Debug, Clone)]
enum Payload {
    Sample(usize, SampleMsg),
    /// A sample to the rogue.
    Rogue(SampleMsg),
    Command(CommandMsg),
    /// A change to hold (or the states sent to a member back in view), member to member.
    Hold {
        from: usize,
        to: usize,
        /// The asker's replication job (0: the answer to a copy), and its process: an
        /// answer reaches the process that asked, not one restarted since.
        job: (u64, u64),
        handed: Handed,
    },
    /// A member that starts stepping the shard asks another that steps it for a copy of
    /// its state (`ShardAction::Copy`, `Acquire`); the answer comes as a `Hold` with job 0.
    Copy {
        from: usize,
        to: usize,
    },
    /// Its answer, from member `by`.
    Held {
        to: usize,
        by: usize,
        job: (u64, u64),
        ok: bool,
        /// The answering member is in step with the sender (`hold_state`).
        in_step: bool,
    },
}

/// A device's state as one member hands it to another (`HandedDevice`).
#[derive(Debug, Clone)]
struct Handed {
    state: Vec<u32>,
    version: Version,
    /// The run and epoch of the lease the sender holds, if it does, and as it last
    /// heard it.
    holds: Option<(u64, u64)>,
    heard: (u64, u64),
}

/// A fault over `[from, to)` ms.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Fault {
    /// Nothing from the plant reaches member `m`.
    CutToMember(usize),
    /// Nothing from member `m` reaches the plant.
    CutFromMember(usize),
    /// Both.
    Isolate(usize),
    /// Member `m` and the others cannot see each other; the plant reaches all.
    Split(usize),
    /// Member `m` is stopped (SIGSTOP): what arrives waits for it.
    Pause(usize),
    /// Member `m` is killed, and restarts cold at the end.
    Crash(usize),
    /// Heavy loss on every link.
    Lossy,
    /// The agent restarts with a new run at `from` (`to` unused).
    AgentRestart,
}

#[derive(Debug, Clone, Copy)]
struct Window {
    fault: Fault,
    from: u64,
    to: u64,
}

struct Member {
    name: String,
    /// Its process: a restart after a crash is a new one.
    instance: u64,
    claimer: Claimer,
    run: u64,
    stepped: u32,
    /// What it saw of the fleet when it was paused: a stopped process learns nothing.
    frozen_view: Option<BTreeSet<String>>,
    backlog: Vec<SampleMsg>,
    /// Crashed: its state is gone until it restarts (a new instance).
    down: bool,
    /// The changes its configuration holds, in order (a crash loses them: it restarts
    /// from its file).
    state: Vec<u32>,
    /// The holder its last sample named, the lease's epoch, and when it came (ms).
    holder: String,
    epoch: u64,
    heard: u64,
    /// Which changes its state holds (`Device::version`).
    version: Version,
    /// Its holds: the service's own rules (`Replication`), an operator's change and
    /// when it was asked as what a job answers.
    holds: Replication<(u32, u64), Handed>,
    /// The fleet it saw at the last tick, to tell who came into view.
    seen: BTreeSet<String>,
    /// Whether it stepped the device's shard at the last tick, to tell when it starts.
    stepping: bool,
    /// Since when it could have commanded the plant in step (running, reaching the plant
    /// both ways, following the shard, not behind), if it can now.
    ready_since: Option<u64>,
}

impl Member {
    fn new(name: String, instance: u64, down: bool) -> Self {
        Self {
            name,
            instance,
            claimer: Claimer::default(),
            run: 0,
            stepped: 0,
            frozen_view: None,
            backlog: Vec::new(),
            down,
            state: Vec::new(),
            holder: String::new(),
            epoch: 0,
            heard: 0,
            version: Version::default(),
            holds: Replication::new(HOLD_TIMEOUT * MS, 256),
            seen: BTreeSet::new(),
            stepping: false,
            ready_since: None,
        }
    }
}

/// A run's verdict, kept for the summary.
#[derive(Default)]
struct Tally {
    applied: u64,
    fenced: u64,
    grants: u64,
    takeovers: Vec<u64>,
    /// Periods from the holder's silencing (crash, pause, cut) to another member's first
    /// applied command, counted only when another member was free of faults, followed
    /// the device warm and in step with the holder, and the links lost nothing: the
    /// takeover the issue bounds.
    clean: Vec<u64>,
    /// Operators' changes: sent, acknowledged, and acknowledged but lost with every
    /// member that held them (crashed, so restarted from the file).
    changes: u64,
    acked: u64,
    lost_with_holders: u64,
    /// Commands sent under a miscounted epoch (`Sim::miscount`): each must be refused.
    miscounted: u64,
    /// Lapses undone by the holder's late answer to a sample of its tenure
    /// (`LeaseCounters::resumed`).
    resumed: u64,
}

struct Sim {
    seed: u64,
    rng: SplitMix,
    t: u64,
    members: Vec<Member>,
    windows: Vec<Window>,
    loss: f64,
    dup: f64,
    delay: (u64, u64),
    flight: Vec<(u64, u64, Payload)>,
    order: u64,
    sup: Supervisor,
    run_id: u64,
    k: u64,
    policy: LeasePolicy,
    // What the plant's record says, checked as it goes.
    holder_of_period: HashMap<u64, String>,
    epoch_holder: HashMap<(u64, u64), String>,
    last_seq: Option<u64>,
    last_epoch: u64,
    holding_streak: u32,
    silent_since: Option<u64>,
    last_holder: Option<String>,
    tally: Tally,
    /// Print every period (`MFC_LEASE_TRACE=1`, with one seed).
    trace: bool,
    /// A rogue controller answers too (one seed in three).
    rogue: bool,
    /// The member that miscounts the lease's epoch now and then, and the generator of its
    /// draws (one seed in eight): the plant must refuse every such command
    /// (`Fence::StaleEpoch`), which no other rule of the schedules reaches first.
    miscount: Option<(usize, SplitMix)>,
    /// The members' last commands, as an eavesdropper keeps them for a replay.
    captured: std::collections::VecDeque<CommandMsg>,
    /// A silenced holder (its name) and the period it went silent, while a takeover is
    /// awaited.
    watch: Option<(String, u64)>,
    /// Changes acknowledged to the operator, and when; those lost since with every member
    /// that held them.
    acked: HashMap<u32, u64>,
    /// Who held the lease, as the accepting member saw it, when each change waiting for
    /// its holds was accepted.
    accepted_holder: HashMap<u32, Holder>,
    lost: BTreeSet<u32>,
    next_change: u32,
    /// When the operator sends its next change (ms).
    next_op: u64,
}

fn channel() -> ChannelConfig {
    ChannelConfig {
        law: LawConfig::intelligent(ControllerKind::P, Order::One, 2.0, [3.0, 0.0, 0.0], 3),
        output: OutputMapConfig {
            dead_zone: 0.0,
            smoothing: 0.0,
            min: -24.0,
            max: 24.0,
            rate_limit: None,
        },
    }
}

fn supervisor(run_id: u64) -> Supervisor {
    let config = SafetyConfig {
        period: H as f64 / 1000.0,
        max_age: MAX_AGE,
        hold_periods: HOLD,
        fallback: FallbackPolicy::LocalController,
    };
    let mut s = Supervisor::new(config, &[channel()], vec![0.0]).expect("a valid supervisor");
    s.grant_leases(run_id);
    s
}

impl Sim {
    fn new(seed: u64) -> Self {
        let mut rng = SplitMix::new(seed);
        let horizon = FAULTY * H;
        let mut windows = Vec::new();
        for _ in 0..1 + rng.below(5) {
            let m = rng.below(MEMBERS as u64) as usize;
            let fault = rng.pick(&[
                Fault::CutToMember(m),
                Fault::CutFromMember(m),
                Fault::Isolate(m),
                Fault::Split(m),
                Fault::Pause(m),
                Fault::Crash(m),
                Fault::Lossy,
                Fault::AgentRestart,
            ]);
            let from = rng.below(horizon);
            let to = (from + H * (1 + rng.below(300))).min(horizon);
            windows.push(Window { fault, from, to });
        }
        let run_id = (rng.next_u64() >> 2) | 1;
        let rogue = rng.below(3) == 0;
        Self {
            rogue,
            miscount: miscount_of(seed),
            captured: std::collections::VecDeque::new(),
            watch: None,
            seed,
            loss: rng.pick(&[0.0, 0.01, 0.05, 0.2]),
            dup: rng.pick(&[0.0, 0.01, 0.05]),
            delay: (rng.below(6), rng.below(14)),
            members: (0..MEMBERS)
                .map(|i| Member::new(format!("m{i}"), 1, false))
                .collect(),
            acked: HashMap::new(),
            accepted_holder: HashMap::new(),
            lost: BTreeSet::new(),
            next_change: 1,
            next_op: 300,
            rng,
            t: 0,
            windows,
            flight: Vec::new(),
            order: 0,
            sup: supervisor(run_id),
            run_id,
            k: 0,
            policy: LeasePolicy::default()
                .for_liveliness_lease(std::time::Duration::from_millis(ZENOH_LEASE)),
            holder_of_period: HashMap::new(),
            epoch_holder: HashMap::new(),
            last_seq: None,
            last_epoch: 0,
            holding_streak: 0,
            silent_since: None,
            last_holder: None,
            tally: Tally::default(),
            trace: std::env::var_os("MFC_LEASE_TRACE").is_some(),
        }
    }

    fn active(&self, f: Fault) -> bool {
        self.windows
            .iter()
            .any(|w| w.fault == f && (w.from..w.to).contains(&self.t))
    }

    fn faulty(&self) -> bool {
        self.t < FAULTY * H
    }

    fn crashed(&self, m: usize) -> bool {
        self.active(Fault::Crash(m))
    }

    fn paused(&self, m: usize) -> bool {
        self.active(Fault::Pause(m))
    }

    /// Whether member `a` sees member `b` in the fleet (liveliness).
    fn sees(&self, a: usize, b: usize) -> bool {
        if a == b {
            return true;
        }
        // A crashed member's connections close: it leaves at once. A paused one, or a
        // partition, is noticed when zenoh's lease on the silent link ends.
        if self.crashed(b) {
            return false;
        }
        let late = |w: &Window| w.from + ZENOH_LEASE <= self.t && self.t < w.to;
        !self.windows.iter().any(|w| {
            let cut = matches!(w.fault, Fault::Split(x) if x == a || x == b);
            (w.fault == Fault::Pause(b) || cut) && late(w)
        })
    }

    fn view(&self, m: usize) -> BTreeSet<String> {
        if let Some(v) = &self.members[m].frozen_view {
            return v.clone();
        }
        (0..MEMBERS)
            .filter(|&o| self.sees(m, o))
            .map(|o| self.members[o].name.clone())
            .collect()
    }

    fn send(&mut self, payload: Payload, cut: bool) {
        let lossy = if self.active(Fault::Lossy) {
            0.5
        } else if self.faulty() {
            self.loss
        } else {
            0.0
        };
        if cut || self.rng.chance(lossy) {
            return;
        }
        let copies = if self.faulty() && self.rng.chance(self.dup) {
            2
        } else {
            1
        };
        for c in 0..copies {
            let mut d = self.delay.0 + self.rng.below(self.delay.1 + 1);
            if c == 1 {
                // A duplicate may come much later: a replay of an old message.
                d += self.rng.below(30 * H);
            }
            self.order += 1;
            self.flight.push((self.t + d, self.order, payload.clone()));
        }
    }

    fn publish_sample(&mut self) {
        let lease = self.sup.lease().expect("leases granted");
        let s = SampleMsg {
            run_id: self.run_id,
            seq: self.k,
            holder: lease.holder().unwrap_or_default().to_string(),
            instance: lease.instance(),
            epoch: lease.epoch(),
        };
        for m in 0..MEMBERS {
            let cut = self.active(Fault::CutToMember(m)) || self.active(Fault::Isolate(m));
            self.send(Payload::Sample(m, s.clone()), cut);
        }
        if self.rogue {
            self.send(Payload::Rogue(s), false);
        }
    }

    /// A controller that obeys no rule but the wire's: it answers every sample as if it
    /// held the lease under the sample's epoch, and claims a vacant one at once. With an
    /// identity of its own (forging another's is what authentication stops, not the
    /// lease), its commands may only ever be applied under an epoch granted to it.
    fn on_rogue(&mut self, s: &SampleMsg) {
        let vacant = s.holder.is_empty();
        let cmd = CommandMsg {
            from: "rogue".into(),
            state: std::rc::Rc::new(Vec::new()),
            sent_at: self.t,
            instance: 9,
            run_id: s.run_id,
            seq: s.seq,
            epoch: if vacant { s.epoch + 1 } else { s.epoch },
            claim: vacant,
            release: false,
            warming: false,
        };
        self.send(Payload::Command(cmd), false);
    }

    /// The epoch member `m` puts on a command it sends as the holder: the lease's, unless
    /// it is the schedule's miscounting member, one off in one command in ten while the
    /// faults last.
    fn miscounted(&mut self, m: usize, epoch: u64) -> u64 {
        if !self.miscounts(m) {
            return epoch;
        }
        let Some((_, rng)) = self.miscount.as_mut() else {
            return epoch;
        };
        if !rng.chance(0.1) {
            return epoch;
        }
        self.tally.miscounted += 1;
        if epoch > 1 && rng.chance(0.5) {
            epoch - 1
        } else {
            epoch + 1
        }
    }

    /// Member `m` steps sample `s` (if it follows the shard) and perhaps answers.
    fn on_sample(&mut self, m: usize, s: &SampleMsg) {
        let view = self.view(m);
        let ranks = ranked(0, &view);
        let me = self.members[m].name.clone();
        let Some(rank) = ranks.iter().position(|n| *n == me) else {
            return;
        };
        if rank > 1 {
            // Neither owner nor standby: not subscribed to the shard.
            return;
        }
        let sees_holder = Some(view.contains(&s.holder));
        let t = self.t;
        let member = &mut self.members[m];
        // A silence over half the liveliness lease may hide changes acknowledged without
        // this member (`LeasePolicy::silence_ns`).
        let gap = member.heard > 0 && (t - member.heard) * MS > self.policy.silence_ns;
        if member.run != s.run_id {
            member.run = s.run_id;
            member.stepped = 0;
        }
        member.stepped = member.stepped.saturating_add(1);
        member.holder.clone_from(&s.holder);
        member.epoch = s.epoch;
        member.heard = t;
        let seen = Seen {
            granted: true,
            run: s.run_id,
            holder: &s.holder,
            instance: s.instance,
            epoch: s.epoch,
        };
        let mine = (me.as_str(), member.instance);
        let warm = member.stepped > WARMUP;
        let st = Standing {
            preferred: rank == 0,
            warm,
            sees_holder,
            gap,
        };
        let before = member.claimer.holder;
        let decision = member.claimer.decide(&self.policy, mine, st, seen);
        if self.trace && matches!(decision, Decision::Send { claim: true, .. }) {
            eprintln!("t {t} m{m} claims: {:?} {st:?}", member.claimer);
        }
        if self.trace && s.holder == me && !matches!(decision, Decision::Send { .. }) {
            eprintln!("t {t} m{m} named holder, quiet: {decision:?} {st:?}");
        }
        if self.trace && s.holder.is_empty() && !matches!(decision, Decision::Send { .. }) {
            eprintln!(
                "t {t} m{m} quiet on a vacant lease: {:?} {st:?}",
                member.claimer
            );
        }
        let took = before != Holder::Me && member.claimer.holder == Holder::Me;
        if took || member.claimer.hand_over_due(&self.policy) {
            // Its state goes to its partners when it takes the lease and halfway to a
            // yield (`Worker::hand_over`).
            let partners = self.partners(m);
            self.queue_job(m, None, partners);
        }
        let Decision::Send {
            epoch,
            claim,
            release,
        } = decision
        else {
            return;
        };
        let epoch = if claim {
            epoch
        } else {
            self.miscounted(m, epoch)
        };
        let member = &mut self.members[m];
        let cmd = CommandMsg {
            instance: member.instance,
            state: std::rc::Rc::new(member.state.clone()),
            sent_at: t,
            from: me,
            run_id: s.run_id,
            seq: s.seq,
            epoch,
            claim,
            release,
            warming: member.stepped <= WARMUP,
        };
        let cut = self.active(Fault::CutFromMember(m)) || self.active(Fault::Isolate(m));
        if self.captured.len() == CAPTURED {
            self.captured.pop_front();
        }
        self.captured.push_back(cmd.clone());
        self.send(Payload::Command(cmd), cut);
    }

    fn on_command(&mut self, c: &CommandMsg) {
        let v = [0.5];
        let cmd = IncomingCommand {
            seq: c.seq,
            body: if c.warming {
                CommandBody::WarmingUp
            } else {
                CommandBody::Control(&v)
            },
            horizon: &[],
            lease: Credentials {
                from: &c.from,
                instance: c.instance,
                epoch: c.epoch,
                claim: c.claim,
                release: c.release,
                run_id: c.run_id,
            },
        };
        let at = (self.t % H) as f64 / 1000.0;
        let (verdict, _) = self.sup.on_command(at, cmd);
        if self.trace {
            eprintln!(
                "t {} command of {} seq {} epoch {} (sent at {}): {verdict:?}",
                self.t, c.from, c.seq, c.epoch, c.sent_at
            );
        }
        if let Verdict::Apply { .. } = verdict {
            self.check_applied(c);
        }
    }

    fn fail(&self, what: String) -> ! {
        panic!(
            "seed {}: {what} at t = {} ms, period {} (faults {:?}; links: loss {}, \
             duplicates {}, delay {:?} ms, rogue {}, miscounting member {:?}; replay: \
             MFC_LEASE_SEED={} cargo test -p system-tests --test lease_sim)",
            self.seed,
            self.t,
            self.k,
            self.windows,
            self.loss,
            self.dup,
            self.delay,
            self.rogue,
            self.miscount.as_ref().map(|m| m.0),
            self.seed
        );
    }

    fn check_applied(&mut self, c: &CommandMsg) {
        let lease = self.sup.lease().expect("leases granted");
        self.tally.applied += 1;
        if c.from != "rogue" {
            let missing = self.acked.iter().find(|(ch, at)| {
                **at <= c.sent_at && !self.lost.contains(*ch) && !c.state.contains(*ch)
            });
            let missing = missing.map(|(ch, at)| (*ch, *at));
            // Lost with its holders: every member holding it can no longer command the
            // plant (crashed, stopped, or cut off from it), and one behind took over after
            // waiting for them (`LeasePolicy::behind_delay`).
            let from = c.from.as_str();
            let lost = |ch: u32| self.unavailable_holders(ch, from, c.sent_at);
            if let Some((ch, _)) = missing.filter(|(ch, _)| lost(*ch)) {
                self.lost.insert(ch);
                self.tally.lost_with_holders += 1;
            } else if let Some((ch, at)) = missing {
                self.fail(format!(
                    "change {ch}, acknowledged at {at} ms, missing from the configuration \
                     of {}, whose command sent at {} ms was applied",
                    c.from, c.sent_at
                ));
            }
        }
        if c.run_id != self.run_id {
            self.fail(format!("a command of run {:#x} applied", c.run_id));
        }
        if c.epoch != lease.epoch() || c.epoch < self.last_epoch {
            self.fail(format!(
                "a command under epoch {} applied, lease at {} (last {})",
                c.epoch,
                lease.epoch(),
                self.last_epoch
            ));
        }
        self.last_epoch = c.epoch;
        if let Some(h) = self
            .epoch_holder
            .insert((self.run_id, c.epoch), c.from.clone())
        {
            if h != c.from {
                self.fail(format!("epoch {} held by {h} and {}", c.epoch, c.from));
            }
        }
        if self.last_seq.is_some_and(|l| c.seq <= l) {
            self.fail(format!("seq {} applied after {:?}", c.seq, self.last_seq));
        }
        self.last_seq = Some(c.seq);
        let k = self.k;
        match self.holder_of_period.get(&k) {
            Some(h) if *h != c.from => self.fail(format!(
                "period {k}: commands of {h} and {} applied",
                c.from
            )),
            _ => {
                self.holder_of_period.insert(k, c.from.clone());
            }
        }
        if let Some((_, since)) = self.watch.take_if(|(h, _)| *h != c.from) {
            self.tally.clean.push(self.k - since);
            if (self.trace || std::env::var_os("MFC_LEASE_SLOW").is_some()) && self.k - since > 10 {
                eprintln!(
                    "slow takeover: seed {}, period {}, faults {:?}, miscounting member {:?}",
                    self.seed,
                    self.k,
                    self.windows,
                    self.miscount.as_ref().map(|m| m.0)
                );
            }
        }
        if let Some(since) = self.silent_since.take() {
            if self.last_holder.as_deref() != Some(&c.from) {
                self.tally.takeovers.push(self.k - since);
            }
        }
        self.last_holder = Some(c.from.clone());
    }

    fn end_period(&mut self) {
        let end = self.sup.end_period().expect("a period is open");
        if self.trace {
            let l = self.sup.lease().expect("leases granted");
            eprintln!(
                "t {} k {} {:?} holder {:?}/{} epoch {} fenced {}",
                self.t,
                self.k,
                end.mode,
                l.holder(),
                l.instance(),
                l.epoch(),
                self.sup.counters().fenced
            );
        }
        self.holding_streak = match end.mode {
            LoopMode::Holding => self.holding_streak + 1,
            _ => 0,
        };
        if self.holding_streak > HOLD {
            self.fail(format!(
                "{} periods on a held command (watchdog {HOLD})",
                self.holding_streak
            ));
        }
        if end.missing && self.silent_since.is_none() {
            self.silent_since = Some(self.k);
        }
        if !end.missing && end.mode == LoopMode::Remote {
            self.silent_since = None;
        }
        self.holder_of_period
            .remove(&self.k.saturating_sub(2 * u64::from(MAX_AGE)));
    }

    fn begin_period(&mut self) {
        if self
            .windows
            .iter()
            .any(|w| w.fault == Fault::AgentRestart && w.from / H * H == self.t && self.t > 0)
        {
            // Run ids grow from start to start (`plant::run_id`).
            self.run_id += 1 + self.rng.below(1 << 20);
            self.sup = supervisor(self.run_id);
            // Someone captured the last run's commands and plays each one back when the
            // new run reaches its sequence number: same holder names, same epochs.
            for c in std::mem::take(&mut self.captured) {
                self.order += 1;
                let at = self.t + c.seq * H + 1 + self.rng.below(H - 1);
                self.flight.push((at, self.order, Payload::Command(c)));
            }
            self.k = 0;
            self.last_seq = None;
            self.last_epoch = 0;
            self.holding_streak = 0;
            self.holder_of_period.clear();
            self.silent_since = None;
            self.last_holder = None;
            self.watch = None;
        } else if self.t > 0 {
            self.k += 1;
        }
        let epoch = self.sup.lease().map_or(0, |l| l.epoch());
        self.sup
            .begin_period(
                self.k,
                self.t as f64 / 1000.0,
                &[0.0],
                &[Reference::constant(0.0)],
            )
            .expect("periods in order");
        if self.sup.lease().map_or(0, |l| l.epoch()) < epoch {
            self.fail("the lease's epoch went back".into());
        }
        self.watch_takeover();
        self.publish_sample();
    }

    /// Whether member `m` can no longer command the plant: dead, stopped, or cut off
    /// from it.
    fn silenced(&self, m: usize) -> bool {
        self.crashed(m)
            || self.paused(m)
            || self.active(Fault::Isolate(m))
            || self.active(Fault::CutFromMember(m))
    }

    /// Whether member `m` is free of every fault.
    fn healthy(&self, m: usize) -> bool {
        !self.silenced(m) && !self.active(Fault::CutToMember(m)) && !self.active(Fault::Split(m))
    }

    /// Whether member `m` is the schedule's miscounting member, while the faults last.
    fn miscounts(&self, m: usize) -> bool {
        self.t < FAULTY * H && self.miscount.as_ref().is_some_and(|(who, _)| *who == m)
    }

    /// Start (or drop) the wait for a takeover of a silenced holder.
    fn watch_takeover(&mut self) {
        let index = |name: &str| (0..MEMBERS).find(|&m| self.members[m].name == name);
        if let Some((h, _)) = &self.watch {
            if index(h).is_some_and(|m| !self.silenced(m)) {
                // It came back before anyone took over: nothing to time.
                self.watch = None;
            }
            return;
        }
        let holder = self
            .sup
            .lease()
            .and_then(|l| l.holder().map(str::to_string));
        let Some((h, m)) = holder.and_then(|h| index(&h).map(|m| (h, m))) else {
            return;
        };
        let calm = !self.active(Fault::Lossy) && self.loss == 0.0;
        let fleet = Standing {
            preferred: false,
            warm: true,
            sees_holder: Some(true),
            gap: false,
        };
        // Another member free of faults that follows the device (owner or standby in its
        // own view of the fleet), is warm (it has stepped this run past the warm-up) and
        // in step with the holder (a member behind waits longer, by design).
        let ready = |o: usize| {
            let in_step = !self.members[o].claimer.behind(fleet);
            let view = self.view(o);
            let follows = ranked(0, &view)
                .iter()
                .position(|n| *n == self.members[o].name)
                .is_some_and(|r| r <= 1);
            let warm = self.members[o].run == self.run_id && self.members[o].stepped > WARMUP;
            o != m && self.healthy(o) && follows && warm && in_step
        };
        if calm && self.silenced(m) && (0..MEMBERS).any(ready) {
            self.watch = Some((h, self.k));
        }
    }

    /// Members that just resumed serve what waited; crashed ones lose everything.
    fn members_tick(&mut self) {
        let fleet = Standing {
            preferred: false,
            warm: true,
            sees_holder: Some(true),
            gap: false,
        };
        for m in 0..MEMBERS {
            let ready = !self.silenced(m)
                && !self.active(Fault::CutToMember(m))
                && self.members[m].stepping
                && !self.members[m].claimer.behind(fleet);
            let since = self.members[m].ready_since;
            self.members[m].ready_since = if ready { since.or(Some(self.t)) } else { None };
        }
        for m in 0..MEMBERS {
            if self.crashed(m) {
                if self.members[m].down {
                    continue;
                }
                let name = self.members[m].name.clone();
                let instance = self.members[m].instance + 1;
                self.members[m] = Member::new(name, instance, true);
                self.forget_lost();
            } else if self.paused(m) {
                if self.members[m].frozen_view.is_none() {
                    let v = self.view(m);
                    self.members[m].frozen_view = Some(v);
                }
            } else if self.members[m].down {
                self.members[m].down = false;
            } else if self.members[m].frozen_view.is_some() {
                let backlog = std::mem::take(&mut self.members[m].backlog);
                for s in &backlog {
                    self.on_sample(m, s);
                }
                self.members[m].frozen_view = None;
            }
        }
    }

    /// Whether members `a` and `b` reach each other (a stopped one reads later).
    fn linked(&self, a: usize, b: usize) -> bool {
        !self.crashed(a)
            && !self.crashed(b)
            && !self.active(Fault::Split(a))
            && !self.active(Fault::Split(b))
    }

    /// The rank of member `m` for the device's shard in its own view, if it steps it.
    fn rank(&self, m: usize) -> Option<usize> {
        let view = self.view(m);
        ranked(0, &view)
            .iter()
            .position(|n| *n == self.members[m].name)
            .filter(|&r| r <= 1)
    }

    /// The members that must hold a change member `m` makes (`Fleet::partners`).
    fn partners(&self, m: usize) -> Vec<usize> {
        let view = self.view(m);
        ranked(0, &view)
            .into_iter()
            .take(2)
            .filter_map(|n| (0..MEMBERS).find(|&o| self.members[o].name == n))
            .filter(|&o| o != m)
            .collect()
    }

    /// Now and then an operator changes the device's configuration, through whichever
    /// member answers operators about it (`answers_device`), which acknowledges as the
    /// service does (`to_hold`, `may_acknowledge`).
    fn operate(&mut self) {
        if self.t < self.next_op || self.t + OPERATOR_TIMEOUT >= (FAULTY + CALM) * H {
            return;
        }
        self.next_op = self.t + 150 + self.rng.below(250);
        let answering: Vec<usize> = (0..MEMBERS)
            .filter(|&m| !self.crashed(m) && !self.paused(m))
            .filter(|&m| match self.members[m].claimer.holder {
                Holder::Me => true,
                Holder::Other => false,
                _ => self.rank(m) == Some(0),
            })
            .collect();
        if answering.is_empty() {
            return;
        }
        let m = self.rng.pick(&answering);
        let change = self.next_change;
        self.next_change += 1;
        self.tally.changes += 1;
        let member = &mut self.members[m];
        member.state.push(change);
        if member.claimer.holder == Holder::Me {
            member.version = member.version.next(member.run, member.epoch);
        }
        let member = &self.members[m];
        let may = self.may_acknowledge(m);
        let partners = self.partners(m);
        if self.trace {
            eprintln!(
                "t {} change {change} on m{m} (holder {:?}, may {may}, partners {partners:?})",
                self.t, member.claimer.holder
            );
        }
        if may && !partners.is_empty() {
            self.accepted_holder.insert(change, member.claimer.holder);
            self.queue_job(m, Some((change, self.t)), partners);
        }
    }

    /// Whether member `m` may acknowledge a change now, by the service's own rule
    /// (`lease::may_acknowledge`, asked when a change is accepted and when its holds end).
    fn may_acknowledge(&self, m: usize) -> bool {
        let member = &self.members[m];
        let heard = (member.heard * MS, LIVE * MS);
        may_acknowledge(member.claimer.holder, heard, self.t * MS).is_ok()
    }

    /// Whether member `m` may still acknowledge, as its holds end, a change accepted when
    /// the lease stood as `accepted` (`lease::may_still_acknowledge`).
    fn may_still_acknowledge(&self, m: usize, accepted: Holder) -> bool {
        let member = &self.members[m];
        let heard = (member.heard * MS, LIVE * MS);
        may_still_acknowledge(accepted, member.claimer.holder, heard, self.t * MS).is_ok()
    }

    fn queue_job(&mut self, m: usize, change: Option<(u32, u64)>, partners: Vec<usize>) {
        let job = Job {
            answer: change,
            shard: 0,
            state: self.handed(m),
            partners: partners
                .iter()
                .map(|&o| self.members[o].name.clone())
                .collect(),
            devices: Vec::new(),
        };
        if self.members[m].holds.submit(job, self.t * MS).is_err() {
            panic!("seed {}: m{m}'s holds are full", self.seed);
        }
        self.carry_out_holds(m);
    }

    /// Member `m`'s state as it hands it (`Registry::handed`).
    fn handed(&self, m: usize) -> Handed {
        let member = &self.members[m];
        Handed {
            state: member.state.clone(),
            version: member.version,
            holds: (member.claimer.holder == Holder::Me).then_some((member.run, member.epoch)),
            heard: (member.run, member.epoch),
        }
    }

    /// Each running member's holds, given the time: a job ends when every partner
    /// answered or its time is up ([`Replication::tick`]). A member that sees another
    /// come into view sends it the states of the devices it commands (`send_commanded`).
    fn replicate(&mut self) {
        for m in 0..MEMBERS {
            if self.crashed(m) || self.paused(m) {
                continue;
            }
            self.members[m].holds.tick(self.t * MS);
            self.carry_out_holds(m);
            // Changes of view, every 5 ms (a member hears of them through liveliness).
            if self.t % 5 != 0 {
                continue;
            }
            let view = self.view(m);
            let new: Vec<String> = view.difference(&self.members[m].seen).cloned().collect();
            self.members[m].seen = view;
            let stepping = self.rank(m).is_some();
            if !stepping && self.members[m].stepping {
                // It no longer follows the shard: its devices' state is dropped
                // (`ShardAction::Unsubscribe`, `Registry::forget_shard`), their run,
                // lease and warm-up with it: a device made fresh warms up again.
                if self.trace {
                    eprintln!("t {} m{m} no longer steps the shard", self.t);
                }
                let member = &mut self.members[m];
                member.claimer = Claimer::default();
                member.state.clear();
                member.version = Version::default();
                (member.run, member.stepped, member.epoch) = (0, 0, 0);
                member.holder.clear();
            }
            if stepping && !self.members[m].stepping {
                if self.trace {
                    eprintln!("t {} m{m} steps the shard, asks for copies", self.t);
                }
                for o in self.partners(m) {
                    let cut = !self.linked(m, o);
                    self.send(Payload::Copy { from: m, to: o }, cut);
                }
            }
            self.members[m].stepping = stepping;
            if self.members[m].claimer.holder == Holder::Me {
                for n in new {
                    let partners = self.partners(m);
                    if let Some(o) = partners.into_iter().find(|&o| self.members[o].name == n) {
                        self.queue_job(m, None, vec![o]);
                    }
                }
            }
        }
    }

    /// What member `m`'s holds say to do, carried out as the service's hold task does
    /// (`service/hold.rs`).
    fn carry_out_holds(&mut self, m: usize) {
        let t = self.t;
        for effect in self.members[m].holds.take() {
            match effect {
                Effect::Ask {
                    job,
                    partner,
                    state,
                    ..
                } => {
                    let to = self.index(&partner);
                    let cut = !self.linked(m, to);
                    let job = (job, self.members[m].instance);
                    let p = Payload::Hold {
                        from: m,
                        to,
                        job,
                        handed: state,
                    };
                    self.send(p, cut);
                }
                Effect::HandedOver { in_step, .. } => {
                    // States sent without a change: the holder learns whether its
                    // partners are in step with it (`Msg::HandedOver`).
                    self.members[m].claimer.handed_over(in_step);
                }
                Effect::Answer {
                    answer: (change, asked),
                    held,
                    missing,
                } => {
                    if self.trace {
                        eprintln!(
                            "t {t} change {change} on m{m}: held by {held:?}, not {missing:?}"
                        );
                    }
                    // Asked again as the holds end, as the service's hold task does
                    // (`Replicator::answer`): the lease may have moved meanwhile, or the
                    // member forgotten the device.
                    let accepted = self.accepted_holder.remove(&change).unwrap_or_default();
                    let may = self.may_still_acknowledge(m, accepted);
                    if missing.is_empty() && may && t - asked <= OPERATOR_TIMEOUT {
                        self.acked.insert(change, t);
                        self.tally.acked += 1;
                    }
                }
            }
        }
    }

    fn index(&self, name: &str) -> usize {
        (0..MEMBERS)
            .find(|&o| self.members[o].name == name)
            .expect("a member")
    }

    /// Member `to` is asked by `from` to hold `state` (`Fleet::hold`, `hold_state`,
    /// `from_holder`).
    fn on_hold(&mut self, from: usize, to: usize, job: (u64, u64), handed: Handed) {
        let copy = job.0 == 0;
        let sender = self.members[from].name.clone();
        // A hold is taken by a member that steps the shard, from a member in its view
        // (`Fleet::hold`); a copy's answer by one that steps it (`restore_handed`).
        let view = self.view(to);
        let steps = self.rank(to).is_some() && (copy || view.contains(&sender));
        let member = &mut self.members[to];
        // `Registry::restore_shard`: never an older configuration, nor the same one over
        // the holder's own; in step with a holder under an epoch not older than heard.
        let mine = member.claimer.holder == Holder::Me;
        // A change to hold comes from the holder the plant last named here, or is refused
        // (`Registry::hold_shard`).
        let leased = matches!(
            member.claimer.holder,
            Holder::Me | Holder::Other | Holder::Vacant
        );
        let from_holder = copy
            || !leased
            || handed
                .holds
                .is_some_and(|k| k >= (member.run, member.epoch));
        let ok = steps
            && from_holder
            && !(handed.version < member.version || mine && handed.version == member.version);
        let same = steps && from_holder && mine && handed.version == member.version;
        if self.trace {
            eprintln!(
                "t {} m{to} handed by {sender} {:?} at {:?}: {ok} (steps {steps}, own {:?})",
                self.t, handed.state, handed.version, member.version
            );
        }
        if ok {
            member.state = handed.state;
            member.version = handed.version;
        }
        let heard = (member.run, member.epoch);
        if let Some(k) = handed.holds.filter(|k| (ok || same) && *k >= heard) {
            member.claimer.caught_up(k);
        } else if ok || same {
            member.claimer.heard_of(handed.heard);
        }
        let ok = ok || same;
        if copy {
            return;
        }
        let fleet = Standing {
            preferred: false,
            warm: true,
            sees_holder: Some(true),
            gap: false,
        };
        let in_step = !self.members[to].claimer.behind(fleet);
        let cut = !self.linked(from, to);
        let p = Payload::Held {
            to: from,
            by: to,
            job,
            ok,
            in_step,
        };
        self.send(p, cut);
    }

    fn on_held(&mut self, to: usize, by: usize, job: (u64, u64), in_step: bool, ok: bool) {
        let (job, asker) = job;
        if asker != self.members[to].instance {
            return;
        }
        let answer = match ok {
            true => PartnerAnswer::Held { in_step },
            false => PartnerAnswer::Refused,
        };
        let by = self.members[by].name.clone();
        self.members[to].holds.answer(job, &by, answer, self.t * MS);
        self.carry_out_holds(to);
    }

    /// Whether no member but `sender` that holds change `ch` could have commanded the
    /// plant in step through the wait of a member behind (`LeasePolicy::behind_delay`)
    /// before `sent_at` (the sender may have taken the change back since from another
    /// member): each was crashed, stopped, cut off from the plant, not following the
    /// shard, or unsure that it was in step (it lost sight of the holder, or heard
    /// nothing for a long while) at some time in it.
    fn unavailable_holders(&self, ch: u32, sender: &str, sent_at: u64) -> bool {
        let wait = u64::from(self.policy.behind_delay) * H;
        (0..MEMBERS)
            .filter(|&m| self.members[m].name != sender && self.members[m].state.contains(&ch))
            .all(|m| {
                self.members[m]
                    .ready_since
                    .is_none_or(|r| r + wait > sent_at)
            })
    }

    /// Acknowledged changes that no member holds any more (every one that held them
    /// crashed, restarting from its file): lost with their holders, not by the rules.
    fn forget_lost(&mut self) {
        let gone: Vec<u32> = self
            .acked
            .keys()
            .filter(|c| !self.lost.contains(*c))
            .filter(|c| !self.members.iter().any(|m| m.state.contains(*c)))
            .copied()
            .collect();
        self.tally.lost_with_holders += gone.len() as u64;
        self.lost.extend(gone);
    }

    fn deliver(&mut self) {
        let now = self.t;
        let mut due: Vec<(u64, u64, Payload)> = Vec::new();
        self.flight.retain(|f| {
            if f.0 <= now {
                due.push(f.clone());
                false
            } else {
                true
            }
        });
        // Same-millisecond arrivals in a seeded random order.
        due.sort_by_key(|f| (f.1.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ self.seed, f.1));
        for (_, _, p) in due {
            match p.clone() {
                Payload::Sample(m, s) if self.crashed(m) => drop(s),
                Payload::Sample(m, s) if self.paused(m) => {
                    // What waits for a stopped member: the service's inbox keeps the
                    // newest sample per device, zenoh's queues a few more.
                    let backlog = &mut self.members[m].backlog;
                    backlog.push(s);
                    if backlog.len() > 3 {
                        backlog.remove(0);
                    }
                }
                Payload::Sample(m, s) => self.on_sample(m, &s),
                Payload::Command(c) => self.on_command(&c),
                Payload::Rogue(s) => self.on_rogue(&s),
                Payload::Hold { to, .. } | Payload::Held { to, .. } | Payload::Copy { to, .. }
                    if self.crashed(to) => {}
                Payload::Hold { to, .. } | Payload::Held { to, .. } | Payload::Copy { to, .. }
                    if self.paused(to) =>
                {
                    // A stopped process reads it when it resumes.
                    self.order += 1;
                    self.flight.push((now + 1, self.order, p));
                }
                Payload::Hold {
                    from,
                    to,
                    job,
                    handed,
                } => self.on_hold(from, to, job, handed),
                Payload::Held {
                    to,
                    by,
                    job,
                    ok,
                    in_step,
                } => self.on_held(to, by, job, ok && in_step, ok),
                Payload::Copy { from, to } => {
                    let handed = self.handed(to);
                    let cut = !self.linked(from, to);
                    let p = Payload::Hold {
                        from: to,
                        to: from,
                        job: (0, 0),
                        handed,
                    };
                    self.send(p, cut);
                }
            }
        }
    }

    fn run(mut self) -> Tally {
        let end = (FAULTY + CALM) * H;
        let mut remote_tail = 0;
        let mut tail_holders = BTreeSet::new();
        let mut tail_applied = 0;
        while self.t < end {
            if self.t % H == 0 {
                if self.t > 0 {
                    self.end_period();
                    if self.t > end - 50 * H {
                        // Holding a command between two late ones is the link's jitter;
                        // the fallback is not.
                        let mode = self.sup.mode();
                        remote_tail +=
                            u64::from(!matches!(mode, LoopMode::Local | LoopMode::SafeStop));
                        if let Some(h) = self.holder_of_period.get(&self.k) {
                            tail_holders.insert(h.clone());
                            tail_applied += 1;
                        }
                    }
                }
                self.begin_period();
            }
            self.members_tick();
            self.deliver();
            self.operate();
            self.replicate();
            self.t += 1;
        }
        self.end_period();
        if remote_tail < 49 {
            self.fail(format!(
                "after the faults, only {remote_tail} of the last 49 periods off the fallback"
            ));
        }
        // One holder, or two if the last one yielded to the preferred member meanwhile.
        if tail_holders.len() > 2 || tail_applied < 25 {
            self.fail(format!(
                "after the faults, commands in {tail_applied} of the last 49 periods, \
                 from {tail_holders:?}"
            ));
        }
        let lease = self.sup.lease().expect("leases granted");
        let c = self.sup.counters();
        self.tally.fenced = c.fenced;
        self.tally.grants = lease.counters().grants;
        self.tally.resumed = lease.counters().resumed;
        self.tally
    }
}

/// Seed `seed`'s miscounting member, if it has one (one in eight), with the generator of
/// its draws. The seeds the soak found ([`SOAK_FOUND`]) have none: each stays the schedule
/// that showed its defect.
fn miscount_of(seed: u64) -> Option<(usize, SplitMix)> {
    let mut rng = SplitMix::new(seed ^ MISCOUNT_STREAM);
    let who = rng.below(MEMBERS as u64) as usize;
    (rng.below(8) == 0 && !SOAK_FOUND.contains(&seed)).then_some((who, rng))
}

/// The seeds to run: `MFC_LEASE_SEED` alone, or `MFC_LEASE_SEEDS` of them (10 000 by
/// default) from `MFC_LEASE_FROM` (0 by default).
fn seeds() -> std::ops::Range<u64> {
    let var = |k: &str| std::env::var(k).ok().and_then(|s| s.parse::<u64>().ok());
    if let Some(seed) = var("MFC_LEASE_SEED") {
        return seed..seed + 1;
    }
    let from = var("MFC_LEASE_FROM").unwrap_or(0);
    from..from.saturating_add(var("MFC_LEASE_SEEDS").unwrap_or(10_000))
}

/// The threads the schedules are spread over (`MFC_LEASE_THREADS`, else one per core).
/// Each schedule is a world of its own, so the figures do not depend on how many.
fn threads() -> u64 {
    std::env::var("MFC_LEASE_THREADS")
        .ok()
        .and_then(|s| s.parse::<u64>().ok())
        .or_else(|| {
            std::thread::available_parallelism()
                .ok()
                .map(|n| n.get() as u64)
        })
        .unwrap_or(1)
        .max(1)
}

impl Tally {
    fn add(&mut self, t: Tally) {
        self.applied += t.applied;
        self.fenced += t.fenced;
        self.grants += t.grants;
        self.takeovers.extend(t.takeovers);
        self.clean.extend(t.clean);
        self.changes += t.changes;
        self.acked += t.acked;
        self.lost_with_holders += t.lost_with_holders;
        self.miscounted += t.miscounted;
        self.resumed += t.resumed;
    }
}

/// Run every `step`th seed of `seeds` from the `first`: the schedules run and their sum.
fn run_share(seeds: std::ops::Range<u64>, first: u64, step: u64) -> (u64, Tally) {
    let (mut runs, mut total) = (0u64, Tally::default());
    for seed in seeds.skip(first as usize).step_by(step as usize) {
        if std::env::var_os("MFC_LEASE_SURVEY").is_some() {
            // A survey (the soak): list the failing seeds instead of stopping at the
            // first, and sum the figures of the others.
            match std::panic::catch_unwind(|| Sim::new(seed).run()) {
                Ok(t) => {
                    total.add(t);
                    runs += 1;
                }
                Err(_) => eprintln!("SURVEY failed seed {seed}"),
            }
            continue;
        }
        total.add(Sim::new(seed).run());
        runs += 1;
    }
    (runs, total)
}

/// Seeds past CI's 10 000 that the soak found failing, each on a defect since fixed: they
/// run in every CI so that the defect cannot come back unseen. 140593: a member
/// acknowledged a change after its lease lapsed while the holds waited
/// (`lease::may_acknowledge` is now asked again when they end); 225770: a member
/// acknowledged a change after it stopped following the device while the holds waited
/// (`lease::may_still_acknowledge`); the others: a live holder's lease lapsed on answers
/// the network reordered (an overtaken answer of the holder now renews it,
/// `plant_agent::lease::Lease::heard`); 138492: a member paused past half the
/// liveliness lease claimed as in step (`LeasePolicy::silence_ns`); 31675, 51534 and
/// 218981: a holder answering three periods late lost its lease to one run of late
/// answers (the agent's lapse now waits out its answers' lateness,
/// `Supervisor::lease_lapse`); 150789, 366081, 540749 and 553219: a holder's answers, prompt until then,
/// landed past the lapse, and the plant fell back for a period while it claimed again
/// (its late answer to a sample of its tenure now undoes the lapse while nobody has
/// claimed, `plant_agent::lease::Pass::Resumed`).
const SOAK_FOUND: [u64; 19] = [
    21257, 31675, 51140, 51534, 60248, 63298, 68962, 87049, 103087, 134580, 138492, 140593, 150789,
    196088, 218981, 225770, 366081, 540749, 553219,
];

#[test]
fn the_seeds_the_soak_found_pass() {
    let mut total = Tally::default();
    for seed in SOAK_FOUND {
        total.add(Sim::new(seed).run());
    }
    assert!(total.applied > SOAK_FOUND.len() as u64 * (FAULTY + CALM) / 2);
}

fn percentile(v: &mut [u64], q: f64) -> u64 {
    v.sort_unstable();
    v.get(((v.len().max(1) - 1) as f64 * q).round() as usize)
        .copied()
        .unwrap_or(0)
}

#[test]
fn one_holder_per_period_under_random_faults() {
    let started = std::time::Instant::now();
    let k = threads();
    // A failing schedule panics in its thread; the scope passes the panic (with the
    // command that replays the seed) on to the test.
    let shares: Vec<(u64, Tally)> = std::thread::scope(|scope| {
        let handles: Vec<_> = (0..k)
            .map(|i| scope.spawn(move || run_share(seeds(), i, k)))
            .collect();
        handles
            .into_iter()
            .map(|h| h.join().unwrap_or_else(|e| std::panic::resume_unwind(e)))
            .collect()
    });
    let (mut runs, mut total) = (0u64, Tally::default());
    for (n, t) in shares {
        runs += n;
        total.add(t);
    }
    // Something was judged: commands were applied, and some were fenced off (over many
    // schedules: one replayed alone may spend most of its faults on the fallback).
    assert!(runs < 100 || total.applied > runs * (FAULTY + CALM) / 2);
    assert!(runs < 100 || total.fenced > 0);
    assert!(
        runs < 100 || total.acked > total.changes / 4,
        "changes were acknowledged"
    );
    assert!(
        runs < 100 || total.miscounted > 0,
        "commands under a miscounted epoch were sent"
    );
    let n = total.takeovers.len();
    let (p50, p99, max) = (
        percentile(&mut total.takeovers, 0.5),
        percentile(&mut total.takeovers, 0.99),
        total.takeovers.iter().max().copied().unwrap_or(0),
    );
    let m = total.clean.len();
    let (c50, c99, cmax) = (
        percentile(&mut total.clean, 0.5),
        percentile(&mut total.clean, 0.99),
        total.clean.iter().max().copied().unwrap_or(0),
    );
    // Straight to stderr, past the test harness's capture: the figures show in CI's log.
    let _ = writeln!(
        std::io::stderr(),
        "{runs} fault schedules (seeds {:?}, {k} threads) in {:.1} s: {} commands applied, {} fenced, {} leases granted, {} lapses undone by the holder's late answer; \
         {n} changes of holder after silence, periods from the first silent one to the new \
         holder's first command: p50 {p50}, p99 {p99}, max {max}; {m} takeovers of a \
         silenced holder with a healthy member in step and no loss, periods from the \
         silencing to \
         the new holder's first command: p50 {c50}, p99 {c99}, max {cmax}; operators' \
         changes: {} made, {} acknowledged, none lost but {} with every member that held \
         them (each crashed, stopped, cut off from the plant, or itself behind, for the \
         whole wait of a member behind); {} commands under a miscounted epoch sent, none \
         applied",
        seeds(),
        started.elapsed().as_secs_f64(),
        total.applied,
        total.fenced,
        total.grants,
        total.resumed,
        total.changes,
        total.acked,
        total.lost_with_holders,
        total.miscounted
    );
}

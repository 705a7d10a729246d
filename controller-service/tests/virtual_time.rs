//! The fleet's and the hot standby's rules in virtual time: members are the service's own
//! pure state machines ([`Fleet`], [`HotStandby`]), carried out by a small harness that
//! does what the service's wiring does (send each request, deliver its answer or report
//! none after the timeout, tick every 20 ms, tell each member who joined and who left)
//! over a simulated network with delays, loss and partitions. No clock is read: an event
//! queue orders everything on virtual instants, so a run of minutes takes milliseconds
//! and the same seed gives the same run.

use std::collections::BTreeSet;
use std::time::{Duration, Instant};

use controller_service::config::{StandbyRole, StandbySpec};
use controller_service::fleet::{
    Fleet, FleetTiming, Got, Reply, Request, RequestKind, ShardAction, ShardRole,
};
use controller_service::standby::{HotStandby, STANDBY_GRACE};
use protocol::{pb, PROTOCOL_VERSION, SHARDS};
use simulation::{Events, SplitMix};

fn ms(x: u64) -> Duration {
    Duration::from_millis(x)
}

/// Uniform in `lo..=hi` milliseconds.
fn draw_ms(rng: &mut SplitMix, lo: u64, hi: u64) -> Duration {
    ms(rng.between(lo, hi))
}

/// What travels between members, or happens to one.
#[derive(Debug, Clone)]
enum Event {
    /// `member` learns that `who` joined (`true`) or left.
    View {
        member: usize,
        who: usize,
        alive: bool,
    },
    /// A request arrives at `to`.
    Request {
        from: usize,
        to: usize,
        shard: u32,
        body: String,
    },
    /// The answer to `member`'s request arrives (`None`: its timeout passed first).
    Answer {
        member: usize,
        shard: u32,
        asked: Asked,
        reply: Option<Reply>,
    },
    /// Every member's 20 ms tick.
    Tick,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Asked {
    Release,
    Copy,
    Offer,
}

/// A fleet over a simulated network.
struct Sim {
    t0: Instant,
    now: Duration,
    queue: Events<Duration, Event>,
    names: Vec<String>,
    fleets: Vec<Option<Fleet>>,
    /// Pairs that cannot reach each other.
    cut: BTreeSet<(usize, usize)>,
    rng: SplitMix,
    /// One-way delay of a message, and how often a request or answer is lost.
    delay: (u64, u64),
    loss: f64,
    timeout: Duration,
    /// For every shard, the time during which more than one member answered it.
    doubled: Vec<Duration>,
}

impl Sim {
    fn new(names: &[&str], seed: u64) -> Self {
        Self {
            t0: Instant::now(),
            now: Duration::ZERO,
            queue: Events::new(),
            names: names.iter().map(|s| s.to_string()).collect(),
            fleets: names.iter().map(|_| None).collect(),
            cut: BTreeSet::new(),
            rng: SplitMix::new(seed),
            delay: (1, 3),
            loss: 0.0,
            timeout: ms(500),
            doubled: vec![Duration::ZERO; SHARDS as usize],
        }
    }

    fn at(&mut self, after: Duration, e: Event) {
        self.queue.push(self.now + after, e);
    }

    fn reachable(&self, a: usize, b: usize) -> bool {
        !self.cut.contains(&(a.min(b), a.max(b)))
    }

    fn alive(&self) -> Vec<usize> {
        (0..self.names.len())
            .filter(|&i| self.fleets[i].is_some())
            .collect()
    }

    /// Start member `i`, knowing `others` already; everybody reachable hears of it.
    fn start(&mut self, i: usize, others: &[usize]) {
        let mut f = Fleet::new(&self.names[i], true, FleetTiming::default());
        let actions = f.start(others.iter().map(|&o| self.names[o].clone()));
        self.fleets[i] = Some(f);
        self.carry_out(i, actions);
        // Every member reachable sees this one's token appear; this one sees the token of
        // every member it did not find at start appear too (its subscription is declared
        // before it looks).
        for m in self.alive() {
            if m != i && self.reachable(m, i) {
                let d = draw_ms(&mut self.rng, self.delay.0, self.delay.1);
                self.at(
                    d,
                    Event::View {
                        member: m,
                        who: i,
                        alive: true,
                    },
                );
                if !others.contains(&m) {
                    let d = draw_ms(&mut self.rng, self.delay.0, self.delay.1);
                    self.at(
                        d,
                        Event::View {
                            member: i,
                            who: m,
                            alive: true,
                        },
                    );
                }
            }
        }
    }

    /// Member `i` dies; the others see its token go after `lease`.
    fn kill(&mut self, i: usize, lease: Duration) {
        self.fleets[i] = None;
        for m in self.alive() {
            self.at(
                lease,
                Event::View {
                    member: m,
                    who: i,
                    alive: false,
                },
            );
        }
    }

    /// Cut `a` from `b`: each sees the other leave after `lease`.
    fn partition(&mut self, a: usize, b: usize, lease: Duration) {
        self.cut.insert((a.min(b), a.max(b)));
        self.at(
            lease,
            Event::View {
                member: a,
                who: b,
                alive: false,
            },
        );
        self.at(
            lease,
            Event::View {
                member: b,
                who: a,
                alive: false,
            },
        );
    }

    /// Reconnect `a` and `b`: each sees the other's token again, if it is alive.
    fn heal(&mut self, a: usize, b: usize) {
        self.cut.remove(&(a.min(b), a.max(b)));
        if self.fleets[a].is_none() || self.fleets[b].is_none() {
            return;
        }
        let (d1, d2) = (draw_ms(&mut self.rng, 1, 20), draw_ms(&mut self.rng, 1, 20));
        self.at(
            d1,
            Event::View {
                member: a,
                who: b,
                alive: true,
            },
        );
        self.at(
            d2,
            Event::View {
                member: b,
                who: a,
                alive: true,
            },
        );
    }

    /// What the service's `apply_fleet` does with the fleet's actions: send requests.
    fn carry_out(&mut self, i: usize, actions: Vec<ShardAction>) {
        for a in actions {
            let me = self.names[i].clone();
            let (to, shard, request, asked) = match &a {
                ShardAction::Acquire { shard, from } => {
                    (from, *shard, Request::Release(&me), Asked::Release)
                }
                ShardAction::Copy { shard, from } => {
                    (from, *shard, Request::Copy(&me), Asked::Copy)
                }
                ShardAction::Offer { shard, to } => (to, *shard, Request::Offer(&me), Asked::Offer),
                ShardAction::Subscribe(_) | ShardAction::Unsubscribe(_) => continue,
            };
            let to = self.names.iter().position(|n| n == to).expect("a member");
            let body = request.body();
            let lost = !self.reachable(i, to) || self.rng.chance(self.loss);
            if lost {
                let timeout = self.timeout;
                self.at(
                    timeout,
                    Event::Answer {
                        member: i,
                        shard,
                        asked,
                        reply: None,
                    },
                );
            } else {
                let d = draw_ms(&mut self.rng, self.delay.0, self.delay.1);
                self.at(
                    d,
                    Event::Request {
                        from: i,
                        to,
                        shard,
                        body,
                    },
                );
            }
        }
    }

    fn deliver(&mut self, e: Event) {
        // MFC_SIM_TRACE=<shard>: print the views and that shard's messages as they come.
        if let Some(traced) = std::env::var("MFC_SIM_TRACE")
            .ok()
            .and_then(|s| s.parse::<u32>().ok())
        {
            let show = match &e {
                Event::Request { shard, .. } | Event::Answer { shard, .. } => *shard == traced,
                Event::Tick => false,
                Event::View { .. } => true,
            };
            if show {
                eprintln!("{:?} {:?}", self.now, e);
            }
        }
        match e {
            // A lease ends only for a member dead or still cut off: a partition healed
            // before its lease ran out loses no token.
            Event::View {
                who,
                alive: false,
                member,
            } if self.fleets[who].is_some() && self.reachable(member, who) => {}
            Event::View { member, who, alive } => {
                let name = self.names[who].clone();
                let Some(f) = self.fleets[member].as_mut() else {
                    return;
                };
                let actions = if alive { f.join(&name) } else { f.leave(&name) };
                self.carry_out(member, actions);
            }
            Event::Request {
                from,
                to,
                shard,
                body,
            } => self.request(from, to, shard, &body),
            Event::Answer {
                member,
                shard,
                asked,
                reply,
            } => self.answer(member, shard, asked, reply),
            Event::Tick => {
                let now = self.t0 + self.now;
                for i in self.alive() {
                    let actions = self.fleets[i]
                        .as_mut()
                        .map(|f| f.tick(now))
                        .unwrap_or_default();
                    self.carry_out(i, actions);
                }
                self.at(ms(20), Event::Tick);
            }
        }
    }

    /// A request reaches `to`, which answers as the service's `handle_handover` does.
    fn request(&mut self, from: usize, to: usize, shard: u32, body: &str) {
        let asked = match Request::parse(body) {
            Some(Request::Release(_)) => Asked::Release,
            Some(Request::Copy(_)) => Asked::Copy,
            Some(Request::Offer(_)) => Asked::Offer,
            Some(Request::Hold(_)) | None => {
                panic!("the harness sent a request the fleet cannot parse: {body}")
            }
        };
        let Some(f) = self.fleets[to].as_mut() else {
            let timeout = self.timeout;
            self.at(
                timeout,
                Event::Answer {
                    member: from,
                    shard,
                    asked,
                    reply: None,
                },
            );
            return;
        };
        let (reply, actions) = f.on_request(shard, Request::parse(body).expect("parsed"));
        self.carry_out(to, actions);
        let back = self.reachable(from, to) && !self.rng.chance(self.loss);
        let d = if back {
            draw_ms(&mut self.rng, self.delay.0, self.delay.1)
        } else {
            self.timeout
        };
        self.at(
            d,
            Event::Answer {
                member: from,
                shard,
                asked,
                reply: back.then_some(reply),
            },
        );
    }

    /// An answer reaches the asker, which acts as the service's `handle_answer` does.
    fn answer(&mut self, member: usize, shard: u32, asked: Asked, reply: Option<Reply>) {
        let now = self.t0 + self.now;
        let Some(f) = self.fleets[member].as_mut() else {
            return;
        };
        let kind = match asked {
            Asked::Release => RequestKind::Release,
            Asked::Copy => RequestKind::Copy,
            Asked::Offer => RequestKind::Offer,
        };
        let got = match reply {
            Some(Reply::State) => Got::State,
            Some(Reply::Owned) => Got::Owned,
            Some(Reply::Refused(_) | Reply::Hold) | None => Got::Nothing,
        };
        let actions = f.on_answer(shard, kind, got, now);
        self.carry_out(member, actions);
    }

    /// How many members answer each shard now.
    fn answering(&self) -> Vec<usize> {
        (0..SHARDS)
            .map(|s| {
                self.fleets
                    .iter()
                    .flatten()
                    .filter(|f| f.answers(s))
                    .count()
            })
            .collect()
    }

    /// Run until `until`, accumulating per shard the time answered twice or more.
    fn run_until(&mut self, until: Duration) {
        while let Some((t, e)) = self.queue.pop_until(until) {
            let counts = self.answering();
            for (s, n) in counts.iter().enumerate() {
                if *n > 1 {
                    self.doubled[s] += t - self.now;
                }
            }
            self.now = t;
            self.deliver(e);
        }
        self.now = until;
    }

    fn doubled_total(&self) -> Duration {
        self.doubled.iter().sum()
    }

    fn settled(&self) -> bool {
        self.answering().iter().all(|&n| n == 1)
    }
}

/// A member that joins takes its shards by asking the owner: never two answering one
/// shard, every shard answered by exactly one once it is done, and the old owner the
/// standby of what it gave away.
#[test]
fn a_joining_member_takes_its_shards_without_double_answers() {
    for seed in 0..200 {
        let mut sim = Sim::new(&["a", "b"], seed);
        sim.loss = 0.2;
        sim.at(Duration::ZERO, Event::Tick);
        sim.start(0, &[]);
        sim.run_until(ms(50));
        assert!(sim.settled());
        sim.start(1, &[0]);
        // One in five requests and answers lost: a shard may take several 500 ms
        // timeouts (and its release may end meanwhile, leaving it unanswered until the
        // next try), but never is it answered twice.
        sim.run_until(ms(30_000));
        assert_eq!(sim.doubled_total(), Duration::ZERO, "seed {seed}");
        assert!(sim.settled(), "seed {seed}: {:?}", sim.answering());
        let (a, b) = (
            sim.fleets[0].as_ref().unwrap(),
            sim.fleets[1].as_ref().unwrap(),
        );
        assert!(b.answer_mask() != 0 && a.answer_mask() != 0, "seed {seed}");
        for s in 0..SHARDS {
            let standby = if a.answers(s) { b } else { a };
            assert_eq!(standby.role(s), ShardRole::Standby, "seed {seed} shard {s}");
        }
    }
}

/// A dead owner's shards are answered by their standby the moment its death is seen,
/// with nothing to ask anyone.
#[test]
fn a_dead_owners_standby_takes_over_at_once() {
    let mut sim = Sim::new(&["a", "b", "c"], 7);
    sim.at(Duration::ZERO, Event::Tick);
    sim.start(0, &[]);
    sim.run_until(ms(100));
    sim.start(1, &[0]);
    sim.run_until(ms(1_000));
    sim.start(2, &[0, 1]);
    sim.run_until(ms(2_000));
    assert!(sim.settled(), "{:?}", sim.answering());
    let had: Vec<u32> = (0..SHARDS)
        .filter(|&s| sim.fleets[1].as_ref().unwrap().answers(s))
        .collect();
    assert!(!had.is_empty());
    sim.kill(1, ms(10));
    // Seen at 2 010 ms: answered by the standby from then on.
    sim.run_until(ms(2_010));
    assert!(sim.settled(), "{:?}", sim.answering());
    sim.run_until(ms(3_000));
    assert!(sim.settled());
    assert_eq!(sim.doubled_total(), Duration::ZERO);
}

/// Two members that each believed themselves alone (started together, before either saw
/// the other) both answer every shard until they see each other; then each offers the
/// other what it outranks it for, and one owner remains per shard within a round trip.
#[test]
fn two_members_started_together_settle_on_one_owner_each() {
    for seed in 0..200 {
        let mut sim = Sim::new(&["a", "b"], seed);
        sim.at(Duration::ZERO, Event::Tick);
        sim.start(0, &[]);
        sim.start(1, &[]);
        assert_eq!(sim.answering(), vec![2; SHARDS as usize]);
        // They see each other within 1-3 ms, then an offer's round trip.
        sim.run_until(ms(20));
        assert!(sim.settled(), "seed {seed}: {:?}", sim.answering());
        let worst = sim.doubled.iter().max().copied().unwrap_or_default();
        assert!(
            worst <= ms(10),
            "seed {seed}: a shard answered twice for {worst:?}"
        );
        sim.run_until(ms(5_000));
        assert!(sim.settled(), "seed {seed}");
    }
}

/// A partition: each side believes the other gone and answers everything (what the
/// plant's lease must bound, not the fleet). After the heal they converge to one owner
/// per shard within an offer's round trip, and stay so: no release that ends in a
/// standby leaves the shard answered twice, or not at all.
#[test]
fn a_partitions_heal_converges_and_stays_converged() {
    for seed in 0..100 {
        let mut sim = Sim::new(&["a", "b", "c"], seed);
        sim.at(Duration::ZERO, Event::Tick);
        sim.start(0, &[]);
        sim.start(1, &[0]);
        sim.start(2, &[0, 1]);
        sim.run_until(ms(2_000));
        assert!(sim.settled(), "seed {seed}");
        // c is cut from a and b; each side sees the other leave after the lease.
        sim.partition(0, 2, ms(500));
        sim.partition(1, 2, ms(500));
        sim.run_until(ms(4_000));
        let during = sim.answering();
        assert!(
            during.iter().all(|&n| n == 2),
            "seed {seed}: both sides answer: {during:?}"
        );
        sim.heal(0, 2);
        sim.heal(1, 2);
        sim.run_until(ms(4_100));
        assert!(sim.settled(), "seed {seed}: {:?}", sim.answering());
        let at_heal = sim.doubled_total();
        sim.run_until(ms(20_000));
        assert!(sim.settled(), "seed {seed}");
        assert_eq!(
            sim.doubled_total(),
            at_heal,
            "seed {seed}: answered twice after settling"
        );
    }
}

/// One random schedule of joins, deaths, partitions and heals with lossy, delayed
/// messages, then the network made whole; returns the simulation and when it was whole.
fn random_run(seed: u64) -> (Sim, Duration) {
    let mut sim = Sim::new(&["a", "b", "c", "d"], seed);
    sim.loss = 0.1;
    sim.delay = (1, 10);
    sim.at(Duration::ZERO, Event::Tick);
    sim.start(0, &[]);
    let mut t = ms(100);
    for _ in 0..8 {
        sim.run_until(t);
        let k = (sim.rng.next_u64() % 4) as usize;
        let alive = sim.alive();
        match sim.rng.next_u64() % 4 {
            0 if sim.fleets[k].is_none() => {
                let others: Vec<usize> =
                    alive.into_iter().filter(|&o| sim.reachable(o, k)).collect();
                sim.start(k, &others);
            }
            1 if alive.len() > 1 && sim.fleets[k].is_some() => sim.kill(k, ms(50)),
            2 => {
                let j = (k + 1) % 4;
                if sim.fleets[k].is_some() && sim.fleets[j].is_some() {
                    sim.partition(k, j, ms(300));
                }
            }
            _ => {
                for (a, b) in sim.cut.clone() {
                    sim.heal(a, b);
                }
            }
        }
        t += draw_ms(&mut sim.rng, 50, 1_500);
    }
    sim.run_until(t);
    for (a, b) in sim.cut.clone() {
        sim.heal(a, b);
    }
    (sim, t)
}

/// Random schedules: whatever happened, once the network is whole and every view has
/// caught up, every shard is answered by exactly one member. With one message in ten
/// lost and a 500 ms timeout per request, a shard may need several tries: 30 s leaves
/// room for about fifty, which all fail with a probability below 1e-30.
#[test]
fn random_schedules_always_settle_once_the_network_is_whole() {
    let seeds: u64 = std::env::var("MFC_SIM_SEEDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(1_000);
    let started = std::time::Instant::now();
    for seed in 0..seeds {
        let (mut sim, whole) = random_run(seed);
        sim.run_until(whole + ms(30_000));
        assert!(
            sim.settled(),
            "seed {seed}: {:?} (replay: MFC_SIM_SEEDS={} cargo test -p controller-service --test virtual_time random_schedules)",
            sim.answering(),
            seed + 1
        );
    }
    eprintln!(
        "{seeds} random schedules settled in {:.1} s",
        started.elapsed().as_secs_f64()
    );
}

fn spec(role: StandbyRole) -> StandbySpec {
    StandbySpec {
        group: "g".into(),
        role,
        heartbeat_ms: 10,
        takeover_ms: 30,
    }
}

fn hb(id: &str, term: u64) -> pb::Heartbeat {
    pb::Heartbeat {
        version: PROTOCOL_VERSION,
        controller_id: id.into(),
        term,
    }
}

/// Takeover after silence with a higher term, step-down on hearing a higher term (so at
/// most one member answers), and a `standby` member's grace at start.
#[test]
fn hot_standby_takes_over_after_silence_and_steps_down_for_a_higher_term() {
    let t0 = Instant::now();
    let mut a = HotStandby::new(Some(&spec(StandbyRole::Active)), t0);
    assert!(!a.active, "silent until it has listened");
    assert!(!a.on_tick(t0 + ms(20)), "30 ms of silence not over yet");
    assert!(
        a.on_tick(t0 + ms(40)) && a.active && a.term == 1,
        "nobody spoke: takes over"
    );
    // A member that heard a term-1 active and then silence takes over with term 2.
    let mut b = HotStandby::new(Some(&spec(StandbyRole::Active)), t0 + ms(40));
    assert!(!b.on_heartbeat("b", &hb("a", 1), t0 + ms(45)));
    assert!(!b.on_tick(t0 + ms(70)), "heard 25 ms ago: stays standby");
    assert!(b.on_tick(t0 + ms(80)) && b.term == 2);
    // The old active hears term 2 and steps down; its own heartbeats are ignored.
    assert!(!a.on_heartbeat("a", &hb("a", 1), t0 + ms(81)));
    assert!(a.on_heartbeat("a", &hb("b", 2), t0 + ms(82)) && !a.active);
    // Equal terms: the greater id stays.
    let mut c = HotStandby::new(Some(&spec(StandbyRole::Active)), t0);
    assert!(c.on_tick(t0 + ms(31)) && c.term == 1);
    assert!(
        !c.on_heartbeat("c", &hb("b", 1), t0 + ms(32)),
        "c > b: c stays"
    );
    assert!(
        c.on_heartbeat("c", &hb("d", 1), t0 + ms(33)),
        "d > c: c steps down"
    );
    // A standby member waits its grace before it may take over.
    let mut s = HotStandby::new(Some(&spec(StandbyRole::Standby)), t0);
    assert!(!s.on_tick(t0 + STANDBY_GRACE));
    assert!(s.on_tick(t0 + STANDBY_GRACE + ms(31)));
    // Without a group the service is simply active, and never steps down.
    let mut alone = HotStandby::new(None, t0);
    assert!(alone.active && !alone.on_tick(t0 + ms(1_000_000)));
}

/// A group of three over a network that loses one heartbeat in ten: a run of lost
/// heartbeats may make a standby take over beside the active member, but such a double
/// is over within a few heartbeats (the lower term steps down on hearing the higher), and
/// never is the group without an active member for longer than the takeover time and a
/// couple of heartbeats, the active member's death included.
#[test]
fn a_standby_group_keeps_one_active_member() {
    for seed in 0..200 {
        let mut rng = SplitMix::new(seed);
        let t0 = Instant::now();
        let ids = ["m1", "m2", "m3"];
        let mut m: Vec<HotStandby> = ids
            .iter()
            .map(|_| HotStandby::new(Some(&spec(StandbyRole::Active)), t0))
            .collect();
        let mut alive = [true; 3];
        let (mut doubled, mut silent) = (Duration::ZERO, Duration::ZERO);
        let mut t = ms(0);
        while t < ms(5_000) {
            t += ms(10);
            if t == ms(2_500) {
                let k = (0..3).find(|&k| m[k].active).expect("one active");
                alive[k] = false;
            }
            let now = t0 + t;
            for k in (0..3).filter(|&k| alive[k]) {
                m[k].on_tick(now);
            }
            let speaking: Vec<usize> = (0..3).filter(|&k| alive[k] && m[k].active).collect();
            for k in speaking {
                let beat = m[k].heartbeat_of(ids[k]);
                for j in (0..3).filter(|&j| j != k && alive[j]) {
                    if rng.chance(0.9) {
                        m[j].on_heartbeat(ids[j], &beat, now + draw_ms(&mut rng, 0, 3));
                    }
                }
            }
            let active = (0..3).filter(|&k| alive[k] && m[k].active).count();
            doubled = if active > 1 {
                doubled + ms(10)
            } else {
                Duration::ZERO
            };
            silent = if active == 0 {
                silent + ms(10)
            } else {
                Duration::ZERO
            };
            assert!(
                doubled <= ms(50),
                "seed {seed} at {t:?}: two active for {doubled:?}"
            );
            if t > ms(100) {
                assert!(
                    silent <= ms(60),
                    "seed {seed} at {t:?}: none active for {silent:?}"
                );
            }
        }
        assert!((0..3).any(|k| alive[k] && m[k].active), "seed {seed}");
    }
}

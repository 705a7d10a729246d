//! Several service instances sharing one fleet of devices: who answers what. Pure logic,
//! no I/O and no clock: the service wires it to liveliness, subscriptions and queries, and
//! passes the time of the events that need one ([`Fleet::tick`], [`Fleet::unanswered`]).
//!
//! # Ownership
//! Device state lives in [`SHARDS`](protocol::SHARDS) shards: a device on its own key is in
//! the shard of its id, a gateway's plants in the shard of the gateway's id (one batch per
//! period goes to one owner). The members of a fleet find each other by liveliness
//! (`mfc/v1/fleet/{fleet}/member/{controller}`), and every member ranks the members of each
//! shard by rendezvous hashing ([`ranked`]): the first is the shard's owner, the only one
//! that answers its samples and queries; the second, its standby, steps every sample of
//! the shard too (it subscribes to it) but answers nothing, so that its state is warm the
//! moment the owner disappears. No member keeps a list of devices: the hash decides, the
//! same on every member.
//!
//! Rendezvous hashing moves the least: a member that joins takes only the shards it now
//! ranks first (about 1/M of them), and a member that leaves gives each of its shards to
//! the next in rank, its standby. Shards never move between two members that stay.
//!
//! # Handover
//! * A member leaves (its token disappears: a clean stop or a crash, which zenoh tells at
//!   once on a closed connection and after the lease on a silent one): each of its shards
//!   goes to its standby, which answers at once with the state it already holds.
//! * A member joins: for each shard it now owns, it asks the previous owner to release it
//!   ([`ShardAction::Acquire`]). The previous owner keeps answering until that request comes
//!   (its [`ShardRole::Releasing`]), then stops, and replies with the shard's state, which the
//!   newcomer restores before it answers. So at every moment at most one member answers a
//!   shard, and the gap is one request's round trip. If the request is never made (the
//!   newcomer died at once), the release ends after [`FleetTiming::release_timeout`].
//! * A new standby asks the owner for a copy of the shard's state ([`ShardAction::Copy`]).
//! * A request that gets no answer (lost, refused because the other's view has not caught
//!   up yet, or timed out) is asked again [`FleetTiming::retry`] later, for as long as it
//!   is still wanted: the shard is still awaited from a member still in view.
//! * Two members that each believed themselves alone (started together, or a partition
//!   healed) both own some shards: the one outranked offers each such shard to the other
//!   ([`ShardAction::Offer`]), which answers that it owns it ([`Reply::Owned`]); the offerer
//!   then stops answering it at once. The offer is made again every [`FleetTiming::retry`]
//!   to whoever owns the shard in the view of the time; without an answer, the release
//!   ends after [`FleetTiming::release_timeout`].
//!
//! Two members that cannot see each other (a partition) both believe they own; that is
//! what the lease and access control bound, not this module.

use std::collections::BTreeSet;
use std::time::{Duration, Instant};

use protocol::SHARDS;

/// A member's part in one shard.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ShardRole {
    /// Nothing: not subscribed, no state.
    #[default]
    None,
    /// Steps every sample of the shard, answers nothing.
    Standby,
    /// Waiting for the previous owner's state: steps, answers nothing.
    Acquiring,
    /// Owns the shard: steps and answers.
    Owner,
    /// Owned it until a newcomer outranked it: still answers until the newcomer asks for
    /// the shard (or [`FleetTiming::release_timeout`] ends it), then becomes what it
    /// would be under the new view.
    Releasing,
}

/// What the wiring must do after a change of view.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ShardAction {
    /// Start receiving the shard's traffic.
    Subscribe(u32),
    /// Stop receiving it and drop its devices' state.
    Unsubscribe(u32),
    /// Ask `from` to release the shard and send its state ([`Request::Release`]); then
    /// call [`Fleet::on_answer`] with what came back.
    Acquire { shard: u32, from: String },
    /// Ask the owner `from` for a copy of the shard's state (a new standby,
    /// [`Request::Copy`]); then [`Fleet::on_answer`].
    Copy { shard: u32, from: String },
    /// Tell `to`, which now outranks this member for the shard, that this member still
    /// answers it ([`Request::Offer`]); then [`Fleet::on_answer`]: if `to` owns it already
    /// this member stops answering it at once, otherwise `to` will ask, and the offer is
    /// made again while the shard is being released.
    Offer { shard: u32, to: String },
}

/// A request another member makes about one shard: the body of a handover query.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Request<'a> {
    /// `release:{id}`: `id` ranks first now and asks for the shard and its state.
    Release(&'a str),
    /// `copy:{id}`: `id` is the shard's new standby and asks for a copy of its state.
    Copy(&'a str),
    /// `offer:{id}`: `id` still answers the shard, which this member outranks it for.
    Offer(&'a str),
    /// `hold:{id}`: `id` answers the shard and accepted a change; this member, which
    /// would take the shard over from it, is to hold the device's new state (sent with
    /// the request) before `id` acknowledges the change.
    Hold(&'a str),
}

impl<'a> Request<'a> {
    /// Parse a handover query's body; `None` for anything else (the asker's id must be a
    /// valid id: it comes from the network).
    pub fn parse(body: &'a str) -> Option<Self> {
        let (kind, who) = body.split_once(':')?;
        let who = protocol::keys::check_id(who).ok()?;
        match kind {
            "release" => Some(Self::Release(who)),
            "copy" => Some(Self::Copy(who)),
            "offer" => Some(Self::Offer(who)),
            "hold" => Some(Self::Hold(who)),
            _ => None,
        }
    }

    /// The body that [`Request::parse`] reads.
    pub fn body(&self) -> String {
        match self {
            Self::Release(id) => format!("release:{id}"),
            Self::Copy(id) => format!("copy:{id}"),
            Self::Offer(id) => format!("offer:{id}"),
            Self::Hold(id) => format!("hold:{id}"),
        }
    }
}

/// This member's answer to a [`Request`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Reply {
    /// Send the shard's state as this member holds it, taken after this call (so that no
    /// sample answered here is missing from it).
    State,
    /// This member owns the shard already: the offerer must stop answering it.
    Owned,
    /// Restore the state sent with the request, then say it is held.
    Hold,
    /// Refused, with why: the asker asks again later.
    Refused(&'static str),
}

/// The kinds of [`Request`], for matching an answer to what was asked.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RequestKind {
    Release,
    Copy,
    Offer,
    Hold,
}

impl Request<'_> {
    /// What kind of request this is.
    pub fn kind(&self) -> RequestKind {
        match self {
            Self::Release(_) => RequestKind::Release,
            Self::Copy(_) => RequestKind::Copy,
            Self::Offer(_) => RequestKind::Offer,
            Self::Hold(_) => RequestKind::Hold,
        }
    }
}

/// What came back for one of this member's requests ([`Fleet::on_answer`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Got {
    /// A shard's state (restored by the caller if it could be, before this call).
    State,
    /// "Owned": the member offered the shard owns it already.
    Owned,
    /// Nothing usable: an error reply, no reply before the timeout, a lost message.
    Nothing,
}

/// The answer to a request to release a shard ([`Fleet::release`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Release {
    /// This member held the shard and no longer answers it: reply with its state, then
    /// carry out the actions.
    Granted(Vec<ShardAction>),
    /// This member did not hold it (a copy of what it has may be sent), then the actions.
    NotHeld(Vec<ShardAction>),
    /// Refused (why): reply with an error; the asker asks again.
    Refused(&'static str),
}

/// The fleet's times (from the service's file, `FleetSpec`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FleetTiming {
    /// How long an outranked owner keeps answering a shard while nobody asks for it.
    pub release_timeout: Duration,
    /// How long after a request that got no answer it is made again.
    pub retry: Duration,
}

impl Default for FleetTiming {
    /// The file's defaults: a release of one second, a retry after 50 ms.
    fn default() -> Self {
        Self {
            release_timeout: Duration::from_millis(1000),
            retry: Duration::from_millis(50),
        }
    }
}

/// Rendezvous weight of `member` for `shard`: FNV-1a over the member's id and the shard,
/// then a SplitMix64 finaliser so that nearby shards rank members independently.
pub fn weight(member: &str, shard: u32) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in member.bytes().chain(shard.to_le_bytes()) {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h = (h ^ (h >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    h = (h ^ (h >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    h ^ (h >> 31)
}

/// The members ranked for `shard`, best first (ties, which need equal hashes, by id).
pub fn ranked(shard: u32, members: &BTreeSet<String>) -> Vec<&str> {
    let mut v: Vec<&str> = members.iter().map(String::as_str).collect();
    v.sort_by(|a, b| weight(b, shard).cmp(&weight(a, shard)).then(a.cmp(b)));
    v
}

/// The owner of `shard` among `members`.
pub fn owner(shard: u32, members: &BTreeSet<String>) -> Option<&str> {
    ranked(shard, members).first().copied()
}

/// Where a request for a shard's state stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
enum Ask {
    /// None wanted (or the answer came).
    #[default]
    Done,
    /// Made; its answer is awaited.
    InFlight,
    /// Unanswered: to be made again at this time.
    RetryAt(Instant),
}

/// One member's part in one shard, and its handover in progress.
#[derive(Debug, Clone, Default)]
struct Slot {
    role: ShardRole,
    /// For a `Releasing` shard: the role it takes once released.
    after: ShardRole,
    /// For an `Acquiring` shard, whom it waits for; for a new `Standby`, the owner it asks
    /// for a copy.
    from: Option<String>,
    ask: Ask,
    /// For a `Releasing` shard: since when (the first [`Fleet::tick`] that saw it).
    releasing_since: Option<Instant>,
}

/// One member's view of the fleet and its roles.
#[derive(Debug, Clone)]
pub struct Fleet {
    me: String,
    members: BTreeSet<String>,
    slots: Vec<Slot>,
    standby: bool,
    timing: FleetTiming,
}

impl Fleet {
    /// A member alone (it owns nothing until [`Fleet::start`]). `standby`: whether members
    /// keep warm standbys (twice the stepping, takeover with no warm-up).
    pub fn new(me: &str, standby: bool, timing: FleetTiming) -> Self {
        Self {
            me: me.to_string(),
            members: BTreeSet::new(),
            slots: vec![Slot::default(); SHARDS as usize],
            standby,
            timing,
        }
    }

    /// This member's id.
    pub fn me(&self) -> &str {
        &self.me
    }

    /// The members in view, this one included once started.
    pub fn members(&self) -> &BTreeSet<String> {
        &self.members
    }

    /// The role in `shard` (shards beyond [`SHARDS`] are nobody's).
    pub fn role(&self, shard: u32) -> ShardRole {
        self.slots
            .get(shard as usize)
            .map_or(ShardRole::None, |s| s.role)
    }

    /// Whether this member answers the samples and queries of `shard`.
    pub fn answers(&self, shard: u32) -> bool {
        matches!(self.role(shard), ShardRole::Owner | ShardRole::Releasing)
    }

    /// Whether this member steps the samples of `shard` (answering or not).
    pub fn steps(&self, shard: u32) -> bool {
        self.role(shard) != ShardRole::None
    }

    /// Whether this member owns `shard` outright (not releasing it).
    pub fn owns(&self, shard: u32) -> bool {
        self.role(shard) == ShardRole::Owner
    }

    /// Shards this member answers, as a bit mask (bit `s` for shard `s`).
    pub fn answer_mask(&self) -> u64 {
        self.mask(|s| self.answers(s))
    }

    /// Shards this member steps, as a bit mask.
    pub fn step_mask(&self) -> u64 {
        self.mask(|s| self.steps(s))
    }

    fn mask(&self, f: impl Fn(u32) -> bool) -> u64 {
        (0..SHARDS).filter(|&s| f(s)).fold(0, |m, s| m | 1 << s)
    }

    /// Shards in `Releasing`.
    pub fn releasing(&self) -> impl Iterator<Item = u32> + '_ {
        (0..SHARDS).filter(|&s| self.role(s) == ShardRole::Releasing)
    }

    /// The role this member should end up with in `shard` under `members`.
    fn target(&self, shard: u32, members: &BTreeSet<String>) -> ShardRole {
        let r = ranked(shard, members);
        if r.first() == Some(&self.me.as_str()) {
            ShardRole::Owner
        } else if self.standby && r.get(1) == Some(&self.me.as_str()) {
            ShardRole::Standby
        } else {
            ShardRole::None
        }
    }

    /// Give `shard` the role `role`, forgetting whatever belonged to the one before.
    fn set_role(&mut self, shard: u32, role: ShardRole) {
        let slot = &mut self.slots[shard as usize];
        if slot.role != role {
            slot.role = role;
            slot.from = None;
            slot.ask = Ask::Done;
            slot.releasing_since = None;
        }
    }

    /// Make a request for `shard`'s state to `from` (the caller emits the action).
    fn ask(&mut self, shard: u32, from: &str) {
        let slot = &mut self.slots[shard as usize];
        slot.from = Some(from.to_string());
        slot.ask = Ask::InFlight;
    }

    /// Offer a shard this member releases to `to`, its owner now.
    fn offer(&mut self, shard: u32, to: Option<String>, out: &mut Vec<ShardAction>) {
        if let Some(to) = to.filter(|o| *o != self.me) {
            self.ask(shard, &to);
            out.push(ShardAction::Offer { shard, to });
        }
    }

    /// Start with the members already in the fleet (this one is added).
    pub fn start(&mut self, others: impl IntoIterator<Item = String>) -> Vec<ShardAction> {
        let mut next: BTreeSet<String> = others.into_iter().collect();
        next.insert(self.me.clone());
        // Before this member, the others owned everything among themselves.
        self.members = next.iter().filter(|m| **m != self.me).cloned().collect();
        self.change(next)
    }

    /// `member` appeared.
    pub fn join(&mut self, member: &str) -> Vec<ShardAction> {
        if self.members.contains(member) {
            return Vec::new();
        }
        let mut next = self.members.clone();
        next.insert(member.to_string());
        self.change(next)
    }

    /// `member` disappeared (stopped or died).
    pub fn leave(&mut self, member: &str) -> Vec<ShardAction> {
        if member == self.me || !self.members.contains(member) {
            return Vec::new();
        }
        let mut next = self.members.clone();
        next.remove(member);
        self.change(next)
    }

    fn change(&mut self, next: BTreeSet<String>) -> Vec<ShardAction> {
        let mut out = Vec::new();
        for s in 0..SHARDS {
            let role = self.next_role(s, &next, &mut out);
            self.set_role(s, role);
        }
        self.members = next;
        out
    }

    /// The role of `shard` under the view `next`, with the actions that takes.
    fn next_role(
        &mut self,
        s: u32,
        next: &BTreeSet<String>,
        out: &mut Vec<ShardAction>,
    ) -> ShardRole {
        let target = self.target(s, next);
        let slot = &self.slots[s as usize];
        let cur = slot.role;
        match (cur, target) {
            (ShardRole::Owner, ShardRole::Owner) | (ShardRole::Standby, ShardRole::Standby) => cur,
            // Still waiting, unless the one it waits for is gone.
            (ShardRole::Acquiring, ShardRole::Owner) => match &slot.from {
                Some(o) if next.contains(o) => cur,
                _ => ShardRole::Owner,
            },
            (ShardRole::Releasing, ShardRole::Owner) => ShardRole::Owner,
            (ShardRole::Releasing, t) => {
                // Offer it again if the view names another owner now.
                self.slots[s as usize].after = t;
                let to = owner(s, next).map(str::to_string);
                if to != owner(s, &self.members).map(str::to_string) {
                    self.offer(s, to, out);
                }
                ShardRole::Releasing
            }
            (ShardRole::None | ShardRole::Standby, ShardRole::Owner) => {
                if cur == ShardRole::None {
                    out.push(ShardAction::Subscribe(s));
                }
                let old = owner(s, &self.members).map(str::to_string);
                match old {
                    Some(o) if o != self.me && next.contains(&o) => {
                        self.set_role(s, ShardRole::Acquiring);
                        self.ask(s, &o);
                        out.push(ShardAction::Acquire { shard: s, from: o });
                        ShardRole::Acquiring
                    }
                    _ => ShardRole::Owner,
                }
            }
            (ShardRole::Owner, t) => {
                // Outranked by a newcomer: it will ask; answer until then. Say so, in
                // case it believes it owns the shard already.
                self.set_role(s, ShardRole::Releasing);
                self.slots[s as usize].after = t;
                let to = owner(s, next).map(str::to_string);
                self.offer(s, to, out);
                ShardRole::Releasing
            }
            (ShardRole::None | ShardRole::Acquiring, ShardRole::Standby) => {
                if cur == ShardRole::None {
                    out.push(ShardAction::Subscribe(s));
                }
                if let Some(o) = owner(s, next).filter(|o| *o != self.me).map(str::to_string) {
                    self.set_role(s, ShardRole::Standby);
                    self.ask(s, &o);
                    out.push(ShardAction::Copy { shard: s, from: o });
                }
                ShardRole::Standby
            }
            (ShardRole::Standby | ShardRole::Acquiring, ShardRole::None) => {
                out.push(ShardAction::Unsubscribe(s));
                ShardRole::None
            }
            (ShardRole::None, ShardRole::None) => ShardRole::None,
            (_, ShardRole::Acquiring | ShardRole::Releasing) => {
                unreachable!("target() never returns Acquiring or Releasing")
            }
        }
    }

    /// Another member's [`Request`] about `shard`: the reply to send, then the actions.
    pub fn on_request(&mut self, shard: u32, request: Request<'_>) -> (Reply, Vec<ShardAction>) {
        match request {
            Request::Release(by) => match self.release(shard, by) {
                Release::Granted(a) | Release::NotHeld(a) => (Reply::State, a),
                Release::Refused(why) => (Reply::Refused(why), Vec::new()),
            },
            Request::Copy(_) if shard < SHARDS => (Reply::State, Vec::new()),
            Request::Offer(_) if self.owns(shard) => (Reply::Owned, Vec::new()),
            Request::Offer(_) => (
                Reply::Refused("this member does not own the shard (yet): it will ask"),
                Vec::new(),
            ),
            Request::Copy(_) => (Reply::Refused("no such shard"), Vec::new()),
            Request::Hold(by) => (self.hold(shard, by), Vec::new()),
        }
    }

    /// `by` asks this member to hold a change to one of `shard`'s devices. Taken from a
    /// member in this view only (a stray or forged request changes nothing), and only
    /// for a shard this member steps: it is then the one that takes the shard over, warm.
    fn hold(&self, shard: u32, by: &str) -> Reply {
        if !self.steps(shard) {
            Reply::Refused("this member does not step the shard: it cannot hold its changes")
        } else if by == self.me || !self.members.contains(by) {
            Reply::Refused("the asker is not a member in this view (yet)")
        } else {
            Reply::Hold
        }
    }

    /// The members that must hold a change to one of `shard`'s devices before this member
    /// acknowledges it: the others among those that step the shard in this view (its
    /// owner and, with standbys, the standby). Empty when this member is alone.
    ///
    /// The owner's partner is its standby, which takes over warm if the owner goes; a
    /// member that commands a device in the owner's place (it holds the plant's lease
    /// while the owner is paused or cut off) has the owner as partner, so the owner, once
    /// back, claims the device with every change made meanwhile.
    pub fn partners(&self, shard: u32) -> Vec<String> {
        let k = if self.standby { 2 } else { 1 };
        ranked(shard, &self.members)
            .into_iter()
            .take(k)
            .filter(|m| *m != self.me)
            .map(str::to_string)
            .collect()
    }

    /// Whether members keep warm standbys (a change then needs a partner to be held).
    pub fn keeps_standbys(&self) -> bool {
        self.standby
    }

    /// `by` asks this member to release `shard`.
    ///
    /// Granted only to a member in this view (its liveliness token is seen: it travels
    /// before its requests) that ranks first for the shard: a stray or forged request, or
    /// one from a member this view has not caught up with, is refused and changes nothing,
    /// and the asker asks again. When granted, the caller sends the shard's state in the
    /// reply *after* this call, so that no sample is answered by both.
    pub fn release(&mut self, shard: u32, by: &str) -> Release {
        if shard >= SHARDS {
            return Release::Refused("no such shard");
        }
        let known = self.members.contains(by) && by != self.me;
        match self.role(shard) {
            ShardRole::Owner | ShardRole::Releasing => {
                if !known {
                    return Release::Refused("the asker is not a member in this view (yet)");
                }
                if owner(shard, &self.members) != Some(by) {
                    return Release::Refused("the asker does not rank first for this shard");
                }
                let t = self.target(shard, &self.members);
                self.set_role(shard, t);
                Release::Granted(if t == ShardRole::None {
                    vec![ShardAction::Unsubscribe(shard)]
                } else {
                    Vec::new()
                })
            }
            ShardRole::Acquiring => {
                // Two members starting together may each wait for the other: whoever does
                // not rank first gives up its claim, so one owner remains.
                if !known {
                    return Release::Refused("the asker is not a member in this view (yet)");
                }
                let t = self.target(shard, &self.members);
                if t != ShardRole::Owner {
                    self.set_role(shard, t);
                    if t == ShardRole::None {
                        return Release::NotHeld(vec![ShardAction::Unsubscribe(shard)]);
                    }
                }
                Release::NotHeld(Vec::new())
            }
            _ => Release::NotHeld(Vec::new()),
        }
    }

    /// What came back for this member's request of `kind` about `shard`, at `now`:
    /// * the state for a release: the previous owner stopped answering the shard before it
    ///   replied, so this member answers it from now on (with the state restored, or with
    ///   what it had if it could not be);
    /// * the state for a copy: the new standby has its copy;
    /// * "owned" for an offer: the other member answers the shard, this one stops at once;
    /// * nothing: the request is made again [`FleetTiming::retry`] later, if still wanted
    ///   then ([`Fleet::tick`]).
    pub fn on_answer(
        &mut self,
        shard: u32,
        kind: RequestKind,
        got: Got,
        now: Instant,
    ) -> Vec<ShardAction> {
        let Some(slot) = self.slots.get_mut(shard as usize) else {
            return Vec::new();
        };
        match (kind, got, slot.role) {
            // A hold's answer goes to the change it was for, never to a handover.
            (RequestKind::Hold, ..) => {}
            (RequestKind::Release, Got::State, ShardRole::Acquiring) => {
                self.set_role(shard, ShardRole::Owner);
            }
            (RequestKind::Copy, Got::State, ShardRole::Standby) => {
                slot.from = None;
                slot.ask = Ask::Done;
            }
            (RequestKind::Offer, Got::Owned, ShardRole::Releasing) => {
                return self.release_expired(shard);
            }
            _ if slot.ask == Ask::InFlight => slot.ask = Ask::RetryAt(now + self.timing.retry),
            _ => {}
        }
        Vec::new()
    }

    /// A release is over (asked for elsewhere, or waited too long): stop answering.
    fn release_expired(&mut self, shard: u32) -> Vec<ShardAction> {
        if self.role(shard) != ShardRole::Releasing {
            return Vec::new();
        }
        let after = self.slots[shard as usize].after;
        self.set_role(shard, after);
        if after == ShardRole::None {
            vec![ShardAction::Unsubscribe(shard)]
        } else {
            Vec::new()
        }
    }

    /// Time passed: at `now`, releases nobody asked for within
    /// [`FleetTiming::release_timeout`] end, and unanswered requests still wanted are
    /// made again. The service calls it every few tens of milliseconds.
    pub fn tick(&mut self, now: Instant) -> Vec<ShardAction> {
        let mut out = Vec::new();
        for s in 0..SHARDS {
            let slot = &mut self.slots[s as usize];
            if slot.role == ShardRole::Releasing {
                let since = *slot.releasing_since.get_or_insert(now);
                if now.saturating_duration_since(since) > self.timing.release_timeout {
                    out.extend(self.release_expired(s));
                    continue;
                }
            }
            if !matches!(slot.ask, Ask::RetryAt(t) if t <= now) {
                continue;
            }
            slot.ask = Ask::Done;
            let to = match slot.role {
                // An offer goes to whoever owns the shard in this view.
                ShardRole::Releasing => owner(s, &self.members).map(str::to_string),
                _ => slot.from.clone().filter(|f| self.members.contains(f)),
            };
            let Some(to) = to.filter(|t| *t != self.me) else {
                continue;
            };
            self.ask(s, &to);
            out.push(match self.slots[s as usize].role {
                ShardRole::Acquiring => ShardAction::Acquire { shard: s, from: to },
                ShardRole::Releasing => ShardAction::Offer { shard: s, to },
                _ => ShardAction::Copy { shard: s, from: to },
            });
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn set(ms: &[&str]) -> BTreeSet<String> {
        ms.iter().map(|s| s.to_string()).collect()
    }

    fn owners(fleets: &[&Fleet]) -> Vec<usize> {
        (0..SHARDS)
            .map(|s| fleets.iter().filter(|f| f.answers(s)).count())
            .collect()
    }

    #[test]
    fn rendezvous_spreads_and_moves_the_least() {
        let three = set(&["a", "b", "c"]);
        let four = set(&["a", "b", "c", "d"]);
        let mut counts = std::collections::BTreeMap::new();
        let mut moved = 0;
        for s in 0..SHARDS {
            let o3 = owner(s, &three).unwrap();
            let o4 = owner(s, &four).unwrap();
            *counts.entry(o3).or_insert(0) += 1;
            if o3 != o4 {
                moved += 1;
                assert_eq!(o4, "d", "a shard moves only to the newcomer");
            }
            // Removing a member gives its shards to its standby, the second in rank.
            let r = ranked(s, &three);
            let without: BTreeSet<String> = three.iter().filter(|m| *m != r[0]).cloned().collect();
            assert_eq!(owner(s, &without), Some(r[1]));
        }
        assert_eq!(counts.len(), 3);
        assert!(
            counts.values().all(|&n| n >= 10),
            "each of 3 owns some: {counts:?}"
        );
        assert!(
            (8..=28).contains(&moved),
            "about a quarter move to a fourth: {moved}"
        );
    }

    #[test]
    fn a_member_alone_owns_everything_at_once() {
        let mut f = Fleet::new("a", true, FleetTiming::default());
        let acts = f.start([]);
        assert_eq!(acts.len(), SHARDS as usize);
        assert!(acts.iter().all(|a| matches!(a, ShardAction::Subscribe(_))));
        assert_eq!(f.answer_mask(), u64::MAX);
    }

    #[test]
    fn a_newcomer_acquires_and_the_old_owner_answers_until_asked() {
        let mut a = Fleet::new("a", true, FleetTiming::default());
        a.start([]);
        let mut b = Fleet::new("b", true, FleetTiming::default());
        let acts = b.start(["a".to_string()]);
        let offers = a.join("b");
        // b acquires every shard it now ranks first, from a; a answers them until asked.
        let wanted: Vec<u32> = (0..SHARDS)
            .filter(|&s| owner(s, &set(&["a", "b"])) == Some("b"))
            .collect();
        assert!(!wanted.is_empty());
        for &s in &wanted {
            assert!(acts.contains(&ShardAction::Acquire {
                shard: s,
                from: "a".into()
            }));
            assert_eq!(b.role(s), ShardRole::Acquiring);
            assert_eq!(a.role(s), ShardRole::Releasing);
            assert!(offers.contains(&ShardAction::Offer {
                shard: s,
                to: "b".into()
            }));
            assert!(
                !b.owns(s),
                "b acquires: it will ask, a keeps answering until then"
            );
        }
        // At every step, at most one answers each shard.
        assert!(owners(&[&a, &b]).iter().all(|&n| n <= 1));
        // A stray or forged request changes nothing.
        for &s in &wanted {
            assert!(matches!(a.release(s, "mallory"), Release::Refused(_)));
            assert_eq!(a.role(s), ShardRole::Releasing);
        }
        let other = (0..SHARDS).find(|s| !wanted.contains(s)).unwrap();
        assert!(
            matches!(a.release(other, "b"), Release::Refused(_)),
            "b does not outrank a there"
        );
        assert!(a.answers(other));
        for &s in &wanted {
            assert!(matches!(a.release(s, "b"), Release::Granted(_)));
            assert!(owners(&[&a, &b]).iter().all(|&n| n <= 1));
            b.on_answer(s, RequestKind::Release, Got::State, Instant::now());
        }
        assert_eq!(
            owners(&[&a, &b]),
            vec![1; SHARDS as usize],
            "exactly one owner each"
        );
        // a is the standby of what it gave away (two members: the other is always second).
        for &s in &wanted {
            assert_eq!(a.role(s), ShardRole::Standby);
        }
    }

    #[test]
    fn a_dead_owners_shards_go_to_their_standby_at_once() {
        let names = ["a", "b", "c"];
        let mut fleets: Vec<Fleet> = names
            .iter()
            .map(|n| Fleet::new(n, true, FleetTiming::default()))
            .collect();
        // All start knowing each other: nobody to acquire from who owned before.
        for f in &mut fleets {
            let others: Vec<String> = names
                .iter()
                .filter(|n| **n != f.me())
                .map(|n| n.to_string())
                .collect();
            f.start(others);
        }
        // Settle the acquisitions the start asked for.
        for s in 0..SHARDS {
            for f in fleets.iter_mut() {
                if f.role(s) == ShardRole::Acquiring {
                    f.on_answer(s, RequestKind::Release, Got::State, Instant::now());
                }
                if f.role(s) == ShardRole::Releasing {
                    f.release_expired(s);
                }
            }
        }
        let refs: Vec<&Fleet> = fleets.iter().collect();
        assert_eq!(owners(&refs), vec![1; SHARDS as usize]);
        let standbys = |fs: &[Fleet], s: u32| {
            fs.iter()
                .filter(|f| f.role(s) == ShardRole::Standby)
                .count()
        };
        assert!((0..SHARDS).all(|s| standbys(&fleets, s) == 1));
        // "b" dies.
        let b_had: Vec<u32> = (0..SHARDS).filter(|&s| fleets[1].answers(s)).collect();
        let mut acts = Vec::new();
        for i in [0, 2] {
            acts.push(fleets[i].leave("b"));
        }
        let (a, c) = (&fleets[0], &fleets[2]);
        for &s in &b_had {
            let n = [a, c].iter().filter(|f| f.answers(s)).count();
            assert_eq!(n, 1, "shard {s} answered by exactly one survivor at once");
            // The survivor answering was the standby: it held warm state already.
            assert!(!acts
                .iter()
                .flatten()
                .any(|x| matches!(x, ShardAction::Acquire { shard, .. } if *shard == s)));
        }
        assert_eq!(owners(&[a, c]), vec![1; SHARDS as usize]);
    }

    #[test]
    fn two_members_that_started_alone_settle_on_one_owner() {
        let (mut a, mut b) = (
            Fleet::new("a", true, FleetTiming::default()),
            Fleet::new("b", true, FleetTiming::default()),
        );
        a.start([]);
        b.start([]);
        assert_eq!(
            owners(&[&a, &b]),
            vec![2; SHARDS as usize],
            "both believe they are alone"
        );
        let offers_a = a.join("b");
        let offers_b = b.join("a");
        // Each offers the other the shards the other outranks it in; the other owns them
        // already, so the offerer stops at once.
        let shards = |offers: Vec<ShardAction>| -> Vec<u32> {
            offers
                .into_iter()
                .filter_map(|a| match a {
                    ShardAction::Offer { shard, .. } => Some(shard),
                    _ => None,
                })
                .collect()
        };
        let (from_a, from_b) = (shards(offers_a), shards(offers_b));
        assert!(from_a.iter().all(|&s| b.owns(s)) && from_b.iter().all(|&s| a.owns(s)));
        for s in from_a {
            a.release_expired(s);
        }
        for s in from_b {
            b.release_expired(s);
        }
        assert_eq!(owners(&[&a, &b]), vec![1; SHARDS as usize]);
    }

    #[test]
    fn an_expired_release_stops_answering() {
        let mut a = Fleet::new("a", false, FleetTiming::default());
        a.start([]);
        a.join("b");
        let s = a.releasing().next().expect("b outranks a somewhere");
        assert!(a.answers(s));
        assert_eq!(a.release_expired(s), vec![ShardAction::Unsubscribe(s)]);
        assert!(!a.answers(s) && !a.steps(s));
        // Without standbys, the other member's shards are not stepped here.
        assert_eq!(a.step_mask(), a.answer_mask());
    }

    #[test]
    fn the_newcomer_leaving_before_it_asks_gives_the_shard_back() {
        let mut a = Fleet::new("a", true, FleetTiming::default());
        a.start([]);
        a.join("b");
        let s = a.releasing().next().unwrap();
        a.leave("b");
        assert_eq!(a.role(s), ShardRole::Owner);
        assert_eq!(a.answer_mask(), u64::MAX);
    }
}

//! Several service instances sharing one fleet of devices: who answers what. Pure logic,
//! no I/O and no clock; the service wires it to liveliness, subscriptions and queries.
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
//!   ([`Action::Acquire`]). The previous owner keeps answering until that request comes
//!   (its [`Role::Releasing`]), then stops, and replies with the shard's state, which the
//!   newcomer restores before it answers. So at every moment at most one member answers a
//!   shard, and the gap is one request's round trip. If the request is never made (the
//!   newcomer died at once), the release ends after a timeout the caller keeps.
//! * A new standby asks the owner for a copy of the shard's state ([`Action::Copy`]).
//!
//! Two members that cannot see each other (a partition) both believe they own; that is
//! what the lease and access control bound, not this module.

use std::collections::BTreeSet;

use protocol::SHARDS;

/// A member's part in one shard.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Role {
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
    /// the shard (or the caller's timeout ends it), then becomes `after`.
    Releasing,
}

/// What the wiring must do after a change of view.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Action {
    /// Start receiving the shard's traffic.
    Subscribe(u32),
    /// Stop receiving it and drop its devices' state.
    Unsubscribe(u32),
    /// Ask `from` to release the shard and send its state; then call [`Fleet::acquired`].
    Acquire { shard: u32, from: String },
    /// Ask the owner `from` for a copy of the shard's state (a new standby).
    Copy { shard: u32, from: String },
    /// Tell `to`, which now outranks this member for the shard, that this member still
    /// answers it. If `to` already owns it (two members started together, each believing
    /// itself alone), call [`Fleet::release_expired`] at once; otherwise `to` will ask.
    Offer { shard: u32, to: String },
}

/// The answer to a request to release a shard ([`Fleet::release`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Release {
    /// This member held the shard and no longer answers it: reply with its state, then
    /// carry out the actions.
    Granted(Vec<Action>),
    /// This member did not hold it (a copy of what it has may be sent), then the actions.
    NotHeld(Vec<Action>),
    /// Refused (why): reply with an error; the asker asks again.
    Refused(&'static str),
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

/// One member's view of the fleet and its roles.
#[derive(Debug, Clone)]
pub struct Fleet {
    me: String,
    members: BTreeSet<String>,
    roles: [Role; SHARDS as usize],
    /// For a `Releasing` shard: the role it takes once released.
    after: [Role; SHARDS as usize],
    /// For an `Acquiring` shard: whom it waits for.
    from: Vec<Option<String>>,
    standby: bool,
}

impl Fleet {
    /// A member alone (it owns nothing until [`Fleet::start`]). `standby`: whether members
    /// keep warm standbys (twice the stepping, takeover with no warm-up).
    pub fn new(me: &str, standby: bool) -> Self {
        Self {
            me: me.to_string(),
            members: BTreeSet::new(),
            roles: [Role::None; SHARDS as usize],
            after: [Role::None; SHARDS as usize],
            from: vec![None; SHARDS as usize],
            standby,
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
    pub fn role(&self, shard: u32) -> Role {
        self.roles.get(shard as usize).copied().unwrap_or_default()
    }

    /// Whether this member answers the samples and queries of `shard`.
    pub fn answers(&self, shard: u32) -> bool {
        matches!(self.role(shard), Role::Owner | Role::Releasing)
    }

    /// Whether this member steps the samples of `shard` (answering or not).
    pub fn steps(&self, shard: u32) -> bool {
        self.role(shard) != Role::None
    }

    /// Shards this member answers, as a bit mask (bit `s` for shard `s`).
    pub fn answer_mask(&self) -> u64 {
        (0..SHARDS)
            .filter(|&s| self.answers(s))
            .fold(0, |m, s| m | 1 << s)
    }

    /// Shards this member waits for (`Acquiring`), as a bit mask: a handover request still
    /// wanted.
    pub fn acquiring_mask(&self) -> u64 {
        (0..SHARDS)
            .filter(|&s| self.role(s) == Role::Acquiring)
            .fold(0, |m, s| m | 1 << s)
    }

    /// Shards this member steps, as a bit mask.
    pub fn step_mask(&self) -> u64 {
        (0..SHARDS)
            .filter(|&s| self.steps(s))
            .fold(0, |m, s| m | 1 << s)
    }

    /// The role this member should end up with in `shard` under `members`.
    fn target(&self, shard: u32, members: &BTreeSet<String>) -> Role {
        let r = ranked(shard, members);
        if r.first() == Some(&self.me.as_str()) {
            Role::Owner
        } else if self.standby && r.get(1) == Some(&self.me.as_str()) {
            Role::Standby
        } else {
            Role::None
        }
    }

    /// Start with the members already in the fleet (this one is added).
    pub fn start(&mut self, others: impl IntoIterator<Item = String>) -> Vec<Action> {
        let mut next: BTreeSet<String> = others.into_iter().collect();
        next.insert(self.me.clone());
        // Before this member, the others owned everything among themselves.
        self.members = next.iter().filter(|m| **m != self.me).cloned().collect();
        self.change(next)
    }

    /// `member` appeared.
    pub fn join(&mut self, member: &str) -> Vec<Action> {
        if self.members.contains(member) {
            return Vec::new();
        }
        let mut next = self.members.clone();
        next.insert(member.to_string());
        self.change(next)
    }

    /// `member` disappeared (stopped or died).
    pub fn leave(&mut self, member: &str) -> Vec<Action> {
        if member == self.me || !self.members.contains(member) {
            return Vec::new();
        }
        let mut next = self.members.clone();
        next.remove(member);
        self.change(next)
    }

    fn change(&mut self, next: BTreeSet<String>) -> Vec<Action> {
        let mut out = Vec::new();
        for s in 0..SHARDS {
            let i = s as usize;
            let old_owner = owner(s, &self.members).map(str::to_string);
            let target = self.target(s, &next);
            let cur = self.roles[i];
            let new = match (cur, target) {
                (Role::Owner, Role::Owner) | (Role::Standby, Role::Standby) => cur,
                (Role::Acquiring, Role::Owner) => {
                    // Still waiting, unless the one it waits for is gone.
                    match &self.from[i] {
                        Some(o) if next.contains(o) => cur,
                        _ => Role::Owner,
                    }
                }
                (Role::Releasing, Role::Owner) => Role::Owner,
                (Role::Releasing, t) => {
                    self.after[i] = t;
                    Role::Releasing
                }
                (Role::None | Role::Standby, Role::Owner) => {
                    if cur == Role::None {
                        out.push(Action::Subscribe(s));
                    }
                    match old_owner {
                        Some(o) if o != self.me && next.contains(&o) => {
                            out.push(Action::Acquire {
                                shard: s,
                                from: o.clone(),
                            });
                            self.from[i] = Some(o);
                            Role::Acquiring
                        }
                        _ => Role::Owner,
                    }
                }
                (Role::Owner, t) => {
                    // Outranked by a newcomer: it will ask; answer until then. Say so, in
                    // case it believes it owns the shard already.
                    self.after[i] = t;
                    if let Some(o) = owner(s, &next) {
                        out.push(Action::Offer {
                            shard: s,
                            to: o.to_string(),
                        });
                    }
                    Role::Releasing
                }
                (Role::None, Role::Standby) => {
                    out.push(Action::Subscribe(s));
                    if let Some(o) = owner(s, &next).filter(|o| *o != self.me) {
                        out.push(Action::Copy {
                            shard: s,
                            from: o.to_string(),
                        });
                    }
                    Role::Standby
                }
                (Role::Acquiring, Role::Standby) => Role::Standby,
                (Role::Standby | Role::Acquiring, Role::None) => {
                    out.push(Action::Unsubscribe(s));
                    Role::None
                }
                (Role::None, Role::None) => Role::None,
                (
                    Role::None | Role::Acquiring | Role::Standby,
                    Role::Acquiring | Role::Releasing,
                ) => {
                    unreachable!("target() never returns Acquiring or Releasing")
                }
            };
            self.roles[i] = new;
        }
        self.members = next;
        out
    }

    /// `by` asks this member to release `shard`.
    ///
    /// Granted only to a member in this view (its liveliness token is seen: it travels
    /// before its requests) that ranks first for the shard: a stray or forged request, or
    /// one from a member this view has not caught up with, is refused and changes nothing,
    /// and the asker asks again. When granted, the caller sends the shard's state in the
    /// reply *after* this call, so that no sample is answered by both.
    pub fn release(&mut self, shard: u32, by: &str) -> Release {
        let i = shard as usize;
        if i >= SHARDS as usize {
            return Release::Refused("no such shard");
        }
        let known = self.members.contains(by) && by != self.me;
        match self.roles[i] {
            Role::Owner | Role::Releasing => {
                if !known {
                    return Release::Refused("the asker is not a member in this view (yet)");
                }
                if owner(shard, &self.members) != Some(by) {
                    return Release::Refused("the asker does not rank first for this shard");
                }
                let t = self.target(shard, &self.members);
                self.roles[i] = t;
                Release::Granted(if t == Role::None {
                    vec![Action::Unsubscribe(shard)]
                } else {
                    Vec::new()
                })
            }
            Role::Acquiring => {
                // Two members starting together may each wait for the other: whoever does
                // not rank first gives up its claim, so one owner remains.
                if !known {
                    return Release::Refused("the asker is not a member in this view (yet)");
                }
                let t = self.target(shard, &self.members);
                if t != Role::Owner {
                    self.roles[i] = t;
                    if t == Role::None {
                        return Release::NotHeld(vec![Action::Unsubscribe(shard)]);
                    }
                }
                Release::NotHeld(Vec::new())
            }
            _ => Release::NotHeld(Vec::new()),
        }
    }

    /// A release waited too long for its request: stop answering anyway.
    pub fn release_expired(&mut self, shard: u32) -> Vec<Action> {
        let i = shard as usize;
        if self.roles.get(i) != Some(&Role::Releasing) {
            return Vec::new();
        }
        self.roles[i] = self.after[i];
        if self.after[i] == Role::None {
            vec![Action::Unsubscribe(shard)]
        } else {
            Vec::new()
        }
    }

    /// Another member offers `shard` (it still answers it, see [`Action::Offer`]): whether
    /// this member owns it already, so that the other must stop at once.
    pub fn owns(&self, shard: u32) -> bool {
        self.role(shard) == Role::Owner
    }

    /// The previous owner's state arrived (or the request failed): answer from now on.
    pub fn acquired(&mut self, shard: u32) {
        if let Some(r) = self.roles.get_mut(shard as usize) {
            if *r == Role::Acquiring {
                *r = Role::Owner;
            }
        }
    }

    /// Shards in `Releasing`.
    pub fn releasing(&self) -> impl Iterator<Item = u32> + '_ {
        (0..SHARDS).filter(|&s| self.role(s) == Role::Releasing)
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
        let mut f = Fleet::new("a", true);
        let acts = f.start([]);
        assert_eq!(acts.len(), SHARDS as usize);
        assert!(acts.iter().all(|a| matches!(a, Action::Subscribe(_))));
        assert_eq!(f.answer_mask(), u64::MAX);
    }

    #[test]
    fn a_newcomer_acquires_and_the_old_owner_answers_until_asked() {
        let mut a = Fleet::new("a", true);
        a.start([]);
        let mut b = Fleet::new("b", true);
        let acts = b.start(["a".to_string()]);
        let offers = a.join("b");
        // b acquires every shard it now ranks first, from a; a answers them until asked.
        let wanted: Vec<u32> = (0..SHARDS)
            .filter(|&s| owner(s, &set(&["a", "b"])) == Some("b"))
            .collect();
        assert!(!wanted.is_empty());
        for &s in &wanted {
            assert!(acts.contains(&Action::Acquire {
                shard: s,
                from: "a".into()
            }));
            assert_eq!(b.role(s), Role::Acquiring);
            assert_ne!(b.acquiring_mask() & 1 << s, 0);
            assert_eq!(a.role(s), Role::Releasing);
            assert!(offers.contains(&Action::Offer {
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
            assert_eq!(a.role(s), Role::Releasing);
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
            b.acquired(s);
        }
        assert_eq!(
            owners(&[&a, &b]),
            vec![1; SHARDS as usize],
            "exactly one owner each"
        );
        // a is the standby of what it gave away (two members: the other is always second).
        for &s in &wanted {
            assert_eq!(a.role(s), Role::Standby);
        }
    }

    #[test]
    fn a_dead_owners_shards_go_to_their_standby_at_once() {
        let names = ["a", "b", "c"];
        let mut fleets: Vec<Fleet> = names.iter().map(|n| Fleet::new(n, true)).collect();
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
                if f.role(s) == Role::Acquiring {
                    f.acquired(s);
                }
                if f.role(s) == Role::Releasing {
                    f.release_expired(s);
                }
            }
        }
        let refs: Vec<&Fleet> = fleets.iter().collect();
        assert_eq!(owners(&refs), vec![1; SHARDS as usize]);
        let standbys =
            |fs: &[Fleet], s: u32| fs.iter().filter(|f| f.role(s) == Role::Standby).count();
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
                .any(|x| matches!(x, Action::Acquire { shard, .. } if *shard == s)));
        }
        assert_eq!(owners(&[a, c]), vec![1; SHARDS as usize]);
    }

    #[test]
    fn two_members_that_started_alone_settle_on_one_owner() {
        let (mut a, mut b) = (Fleet::new("a", true), Fleet::new("b", true));
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
        let shards = |offers: Vec<Action>| -> Vec<u32> {
            offers
                .into_iter()
                .filter_map(|a| match a {
                    Action::Offer { shard, .. } => Some(shard),
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
        let mut a = Fleet::new("a", false);
        a.start([]);
        a.join("b");
        let s = a.releasing().next().expect("b outranks a somewhere");
        assert!(a.answers(s));
        assert_eq!(a.release_expired(s), vec![Action::Unsubscribe(s)]);
        assert!(!a.answers(s) && !a.steps(s));
        // Without standbys, the other member's shards are not stepped here.
        assert_eq!(a.step_mask(), a.answer_mask());
    }

    #[test]
    fn the_newcomer_leaving_before_it_asks_gives_the_shard_back() {
        let mut a = Fleet::new("a", true);
        a.start([]);
        a.join("b");
        let s = a.releasing().next().unwrap();
        a.leave("b");
        assert_eq!(a.role(s), Role::Owner);
        assert_eq!(a.answer_mask(), u64::MAX);
    }
}

//! The wiring of the fleet's and the hot standby's rules: the worker's handlers for their
//! messages and ticks. What to do is decided by [`crate::fleet::Fleet`] and
//! [`crate::standby::HotStandby`], given the time; here it is carried out: requests sent
//! (each on a task of its own, its answer coming back as a message), state restored or
//! sent, shard routes declared or dropped, and the masks the callbacks read set, always
//! after any change, with the core held.

use std::sync::Arc;
use std::time::{Duration, Instant};

use protocol::{decode, encode, keys, pb, printable};
use tokio::sync::mpsc;
use zenoh::query::Query;
use zenoh::Session;

use super::ask::{self, ask_member};
use super::hold::HoldJob;
use super::intake::Msg;
use super::keyring::Keyring;
use super::locks::lock;
use super::log::throttled;
use super::worker::Worker;
use crate::fleet::{Got, Reply, Request, RequestKind, ShardAction};
use crate::lease::Holder;
use crate::registry::Restored;
use crate::snapshot::{decode_shard, encode_shard};

impl Worker {
    /// Set the masks the callbacks read from the fleet's roles and the standby's state.
    /// The core is held while they change: callbacks answer only with it held, so a
    /// sample is answered under one set of masks or the next, never half of each.
    pub(super) fn sync_masks(&self) {
        let step = self
            .member
            .as_ref()
            .map_or(u64::MAX, |m| m.fleet.step_mask());
        let answer = match &self.member {
            _ if !self.standby.active => 0,
            Some(m) => m.fleet.answer_mask(),
            None => u64::MAX,
        };
        let core = lock(&self.shared.core);
        self.shared.masks.store(&core, step, answer);
    }

    /// Carry out a fleet change: start the requests it asks for, drop the state of shards
    /// no longer held, then make the masks and the shard routes match the roles.
    pub(super) async fn apply_fleet(&mut self, actions: Vec<ShardAction>) {
        for a in actions {
            self.carry_out(a);
        }
        self.sync_masks();
        if let Some(m) = &self.member {
            lock(&self.shared.core).registry.set_view(m.fleet.members());
            self.shard_routes
                .sync(&self.session, &self.intake, &m.fleet)
                .await;
        }
    }

    fn carry_out(&mut self, action: ShardAction) {
        let Some(m) = &self.member else { return };
        let name = m.spec.name.as_str();
        let timeout = Duration::from_millis(m.spec.handover_timeout_ms);
        let ask = |to: &str, shard, request: Request<'_>| {
            spawn_request(
                (
                    self.session.clone(),
                    self.tx.clone(),
                    self.shared.keys.clone(),
                ),
                (keys::fleet_handover(name, to, shard), to.to_string()),
                (request.body(), request.kind(), shard),
                timeout,
            );
        };
        match &action {
            ShardAction::Acquire { shard, from } => ask(from, *shard, Request::Release(&self.id)),
            ShardAction::Copy { shard, from } => ask(from, *shard, Request::Copy(&self.id)),
            ShardAction::Offer { shard, to } => ask(to, *shard, Request::Offer(&self.id)),
            ShardAction::Unsubscribe(shard) => {
                let mut c = lock(&self.shared.core);
                let gone = c.registry.forget_shard(*shard);
                let mut ib = lock(&self.shared.inbox);
                for d in &gone {
                    ib.unserve(d);
                    c.forget(d);
                }
            }
            ShardAction::Subscribe(_) => {}
        }
    }

    /// A fleet member appeared or disappeared.
    pub(super) async fn handle_member(&mut self, member: &str, alive: bool) {
        let Some(m) = self.member.as_mut() else {
            return;
        };
        let actions = if alive {
            m.fleet.join(member)
        } else {
            m.fleet.leave(member)
        };
        if member != self.id {
            tracing::info!(controller = %self.id, member = %member, alive, owned = m.fleet.answer_mask().count_ones(), "fleet member {}", if alive { "joined" } else { "left" });
        }
        self.apply_fleet(actions).await;
        if alive && member != self.id {
            self.send_commanded(member);
        }
    }

    /// The devices whose lease this member just took, or will soon yield to the preferred
    /// member: their state goes to their partners, which are then in step with it (and
    /// the preferred member claims in step).
    fn hand_over(&self) {
        let due = lock(&self.shared.core).registry.take_handing();
        if !due.is_empty() {
            self.send_states(due, None);
        }
    }

    /// A member came (back) into view: the state of every device this member commands
    /// (holds the plant's lease of) in a shard it shares with the newcomer goes to it, as
    /// changes to hold. After a partition, the member the fleet prefers, fenced meanwhile,
    /// so holds the state in force before the lease is yielded to it; and a standby that
    /// lost sight of its owner is in step again.
    fn send_commanded(&self, member: &str) {
        let commanded: Vec<String> = {
            let c = lock(&self.shared.core);
            let r = &c.registry;
            r.device_ids()
                .filter(|d| r.lease_holder(d) == Holder::Me)
                .map(str::to_string)
                .collect()
        };
        self.send_states(commanded, Some(member));
    }

    /// Send the state of `devices`, one message per shard, to each shard's partners (or
    /// to `only` that one of them), through the queue of holds; nothing waits for it.
    fn send_states(&self, devices: Vec<String>, only: Option<&str>) {
        let Some(m) = &self.member else { return };
        let jobs: Vec<HoldJob> = {
            let c = lock(&self.shared.core);
            let r = &c.registry;
            let mut by_shard: std::collections::BTreeMap<u32, Vec<&str>> = Default::default();
            for d in &devices {
                if let Some(home) = r.home_of(d) {
                    by_shard.entry(home).or_default().push(d);
                }
            }
            by_shard
                .into_iter()
                .filter_map(|(shard, devs)| {
                    let mut partners = m.fleet.partners(shard);
                    partners.retain(|p| only.is_none_or(|o| o == p));
                    let state = encode_shard(&r.devices_state(shard, &devs)).ok()?;
                    (!partners.is_empty()).then(|| HoldJob {
                        answer: None,
                        shard,
                        state,
                        partners,
                        devices: devs.iter().map(|d| d.to_string()).collect(),
                    })
                })
                .collect()
        };
        for job in jobs {
            if m.holds.try_send(job).is_err() {
                tracing::warn!(controller = %self.id, "too many changes waiting: devices' states not sent to their partners");
                break;
            }
        }
    }

    /// Another member's request about one of this member's shards.
    pub(super) async fn handle_handover(&mut self, q: Query) {
        let Some(m) = self.member.as_mut() else {
            let _ = q.reply_err("not a fleet member").await;
            return;
        };
        let key = q.key_expr().as_str().to_string();
        let payload = q
            .payload()
            .map(|p| p.to_bytes().into_owned())
            .unwrap_or_default();
        let opened = ask::open(self.shared.keys.as_deref(), &key, &payload);
        let parsed = keys::last_shard(&key)
            .zip(opened.and_then(|(head, rest)| Some((Request::parse(head)?, rest))));
        let Some((shard, (request, rest))) = parsed else {
            lock(&self.shared.core).registry.note_request_refused();
            let _ = q
                .reply_err(
                    "a handover request is release:{id}, copy:{id}, offer:{id} or hold:{id} on \
                     a shard's key, sealed by a member when the fleet has keys",
                )
                .await;
            return;
        };
        let (reply, actions) = m.fleet.on_request(shard, request);
        let answer = match reply {
            Reply::State => self.shard_bytes(shard),
            Reply::Owned => Ok(b"owned".to_vec()),
            Reply::Hold => match request {
                Request::Hold(by) => self.hold_state(shard, by, rest),
                _ => Err("not a hold".into()),
            },
            Reply::Refused(why) => Err(why.to_string()),
        };
        match answer {
            Ok(bytes) => {
                let bytes = match &self.shared.keys {
                    Some(k) => k.seal_handover(&[key.as_bytes(), &payload], bytes),
                    None => bytes,
                };
                let _ = q.reply(q.key_expr().clone(), bytes).await;
            }
            Err(why) => {
                let _ = q.reply_err(why).await;
            }
        }
        tracing::debug!(controller = %self.id, shard, request = ?request, "answered a handover request");
        self.apply_fleet(actions).await;
    }

    /// `shard`'s state, to reply with. The role changed before the state is taken, and the
    /// answer mask with it, both with the core held (callbacks answer only with it held):
    /// every sample answered here is in the state, and none is answered here after it.
    fn shard_bytes(&self, shard: u32) -> Result<Vec<u8>, String> {
        self.sync_masks();
        let st = lock(&self.shared.core).registry.shard_state(shard);
        encode_shard(&st).map_err(|e| e.to_string())
    }

    /// A partner's change to hold (or the states it sends a member back in view), from
    /// `by`: its devices' state restored here, then `held:{me}`; an error if any of it
    /// could not be, or a newer configuration is held here (the partner then does not
    /// acknowledge the change).
    fn hold_state(&self, shard: u32, by: &str, bytes: &[u8]) -> Result<Vec<u8>, String> {
        let st = decode_shard(bytes).map_err(|e| e.to_string())?;
        if st.shard != shard {
            return Err("a state for another shard".into());
        }
        let r = self.take_states(&st, true);
        if let Some((dev, why)) = r.refused.first() {
            tracing::warn!(shard, device = %dev, from = %by, "a partner's change not held: {why}");
            return Err(format!("device {dev} not held: {why}"));
        }
        // Held; and whether this member is in step with the sender now, which the sender
        // waits for before it yields the lease to it.
        let c = lock(&self.shared.core);
        let behind = st
            .devices
            .iter()
            .any(|d| !c.registry.in_step(&d.snapshot.id));
        let suffix = if behind { ":behind" } else { "" };
        Ok(format!("held:{}{suffix}", self.id).into_bytes())
    }

    /// Restore the devices of `st` as [`crate::Registry::restore_shard`] allows (never an
    /// older configuration over a newer one), and serve them.
    /// With `hold`, as [`crate::Registry::hold_shard`] allows.
    fn take_states(&self, st: &crate::snapshot::ShardState, hold: bool) -> Restored {
        let mut c = lock(&self.shared.core);
        let r = if hold {
            c.registry.hold_shard(st)
        } else {
            c.registry.restore_shard(st)
        };
        // The entries handed with the devices that this member did not have go to its
        // own audit file: its history of a device survives the member it came from.
        // And the states taken are kept there too, so that a restart of this member puts
        // back what it held for its partners (nothing waits for it: the partner that
        // asked keeps the change in its own file before it is acknowledged).
        if let Some(t) = &c.gate.trail {
            for e in &r.audit {
                t.append(e.clone());
            }
            for d in &st.devices {
                let id = d.snapshot.id.as_str();
                if let (Some((config, version)), Some(file)) =
                    (c.registry.state_of(id), c.registry.file_config_of(id))
                {
                    let state = crate::journal::State {
                        config,
                        version,
                        file,
                    };
                    t.keep(id, state);
                }
            }
        }
        let mut ib = lock(&self.shared.inbox);
        for d in &st.devices {
            if c.registry.serves(&d.snapshot.id) {
                ib.serve(&d.snapshot.id);
            }
        }
        r
    }

    /// What came back for this member's own request about `shard`: a state is restored
    /// (if it decodes and this member still steps the shard), then the fleet decides.
    pub(super) async fn handle_answer(
        &mut self,
        (shard, from): (u32, &str),
        kind: RequestKind,
        reply: Option<Vec<u8>>,
    ) {
        let got = match (kind, reply) {
            (RequestKind::Offer, Some(r)) if r == b"owned" => Got::Owned,
            (RequestKind::Release | RequestKind::Copy, Some(bytes)) => {
                // Taken as a state even if it does not restore: after a release the
                // previous owner no longer answers, so this member must.
                self.restore_handed((shard, from), &bytes);
                Got::State
            }
            _ => Got::Nothing,
        };
        let Some(m) = self.member.as_mut() else {
            return;
        };
        let actions = m.fleet.on_answer(shard, kind, got, Instant::now());
        tracing::debug!(controller = %self.id, shard, ?kind, ?got, "a handover answer");
        if got != Got::Nothing {
            self.apply_fleet(actions).await;
        }
    }

    /// Restore a shard's state handed by member `from` (a release or a copy), device by
    /// device unless the configuration here is newer.
    fn restore_handed(&mut self, (shard, from): (u32, &str), bytes: &[u8]) {
        let steps = self.member.as_ref().is_some_and(|m| m.fleet.steps(shard));
        match decode_shard(bytes) {
            Ok(st) if st.shard == shard && steps => {
                let r = self.take_states(&st, false);
                for (dev, why) in &r.refused {
                    tracing::warn!(shard, device = %dev, from = %from, "handed state not restored: {why}");
                }
                tracing::debug!(controller = %self.id, shard, from = %from, restored = r.restored, "took a shard's state");
            }
            Ok(st) if st.shard != shard => {
                tracing::warn!(shard, "a handover reply for another shard: ignored");
            }
            Ok(_) => {}
            Err(e) => tracing::warn!(shard, "a handover reply that does not decode: {e}"),
        }
    }

    /// Time passed: releases nobody asked for end, unanswered requests are made again.
    pub(super) async fn on_fleet_tick(&mut self) {
        self.hand_over();
        let Some(m) = self.member.as_mut() else {
            return;
        };
        let before: Vec<u32> = m.fleet.releasing().collect();
        let actions = m.fleet.tick(Instant::now());
        let ended = before.iter().filter(|s| !m.fleet.answers(**s)).count();
        if ended == 0 && actions.is_empty() {
            return;
        }
        if ended > 0 {
            tracing::warn!(controller = %self.id, shards = ended, "nobody asked for released shards: no longer answering them");
        }
        self.apply_fleet(actions).await;
    }

    /// A heartbeat of the standby group.
    pub(super) fn handle_heartbeat(&mut self, bytes: &[u8]) {
        match decode::<pb::Heartbeat>(bytes) {
            Ok(hb) => {
                let stood_by = self.standby.on_heartbeat(&self.id, &hb, Instant::now());
                self.sync_masks();
                if stood_by {
                    tracing::warn!(controller = %self.id, other = %printable(&hb.controller_id), "another member is active: standing by");
                }
            }
            Err(e) => {
                lock(&self.shared.core).registry.note_undecodable();
                throttled!(self.warn.undecodable, warn, "undecodable heartbeat: {e}");
            }
        }
    }

    /// A heartbeat period passed: take over after the active member's silence; send a
    /// heartbeat while active.
    pub(super) async fn on_heartbeat_tick(&mut self) {
        let took_over = self.standby.on_tick(Instant::now());
        self.sync_masks();
        if took_over {
            tracing::warn!(controller = %self.id, term = self.standby.term, "no heartbeat from the active member: taking over");
        }
        if let (true, Some(routes)) = (self.standby.active, &self.standby_routes) {
            let hb = encode(&self.standby.heartbeat_of(&self.id));
            let key = routes.publisher.key_expr().as_str().as_bytes();
            let bytes = match &self.shared.keys {
                Some(k) => k.seal_handover(&[key], hb),
                None => hb,
            };
            let _ = routes.publisher.put(bytes).await;
        }
    }
}

/// Make one request to another member on a task of its own; what came back (the reply's
/// payload, or nothing if no reply sealed by a member came within `timeout`) returns as
/// [`Msg::Answer`]. Whether to ask again is the fleet's decision, not this task's.
fn spawn_request(
    (session, tx, keys): (Session, mpsc::Sender<Msg>, Option<Arc<Keyring>>),
    (key, from): (String, String),
    (body, kind, shard): (String, RequestKind, u32),
    timeout: Duration,
) {
    tokio::spawn(async move {
        let query = (&session, keys.as_deref(), key.as_str());
        let reply = ask_member(query, (&body, &[]), timeout, |b| Some(b.to_vec())).await;
        let msg = Msg::Answer {
            shard,
            kind,
            from,
            reply,
        };
        let _ = tx.send(msg).await;
    });
}

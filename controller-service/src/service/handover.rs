//! The wiring of the fleet's and the hot standby's rules: the worker's handlers for their
//! messages and ticks. What to do is decided by [`crate::fleet::Fleet`] and
//! [`crate::standby::HotStandby`], given the time; here it is carried out: requests sent
//! (each on a task of its own, its answer coming back as a message), state restored or
//! sent, shard routes declared or dropped, and the masks the callbacks read set, always
//! after any change, with the core held.

use std::time::{Duration, Instant};

use protocol::{decode, encode, keys, pb, printable};
use tokio::sync::mpsc;
use zenoh::query::Query;
use zenoh::Session;

use super::intake::Msg;
use super::lock;
use super::log::throttled;
use super::worker::Worker;
use crate::fleet::{Got, Reply, Request, RequestKind, ShardAction};
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
                (self.session.clone(), self.tx.clone()),
                keys::fleet_handover(name, to, shard),
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
    }

    /// Another member's request about one of this member's shards.
    pub(super) async fn handle_handover(&mut self, q: Query) {
        let Some(m) = self.member.as_mut() else {
            let _ = q.reply_err("not a fleet member").await;
            return;
        };
        let shard = keys::last_shard(q.key_expr().as_str());
        let body = q
            .payload()
            .and_then(|p| String::from_utf8(p.to_bytes().into_owned()).ok())
            .unwrap_or_default();
        let (Some(shard), Some(request)) = (shard, Request::parse(&body)) else {
            lock(&self.shared.core).registry.note_request_refused();
            let _ = q
                .reply_err(
                    "a handover request is release:{id}, copy:{id} or offer:{id} on a shard's key",
                )
                .await;
            return;
        };
        let (reply, actions) = m.fleet.on_request(shard, request);
        match reply {
            Reply::State => self.send_state(&q, shard).await,
            Reply::Owned => {
                let _ = q.reply(q.key_expr().clone(), b"owned".to_vec()).await;
            }
            Reply::Refused(why) => {
                let _ = q.reply_err(why).await;
            }
        }
        tracing::debug!(controller = %self.id, shard, request = %body, "answered a handover request");
        self.apply_fleet(actions).await;
    }

    /// Reply with `shard`'s state. The role changed before the state is taken, and the
    /// answer mask with it, both with the core held (callbacks answer only with it held):
    /// every sample answered here is in the state, and none is answered here after it.
    async fn send_state(&self, q: &Query, shard: u32) {
        self.sync_masks();
        let st = lock(&self.shared.core).registry.shard_state(shard);
        match encode_shard(&st) {
            Ok(bytes) => {
                let _ = q.reply(q.key_expr().clone(), bytes).await;
            }
            Err(e) => {
                let _ = q.reply_err(e.to_string()).await;
            }
        }
    }

    /// What came back for this member's own request about `shard`: a state is restored
    /// (if it decodes and this member still steps the shard), then the fleet decides.
    pub(super) async fn handle_answer(
        &mut self,
        shard: u32,
        kind: RequestKind,
        reply: Option<Vec<u8>>,
    ) {
        let got = match (kind, reply) {
            (RequestKind::Offer, Some(r)) if r == b"owned" => Got::Owned,
            (RequestKind::Release | RequestKind::Copy, Some(bytes)) => {
                // Taken as a state even if it does not restore: after a release the
                // previous owner no longer answers, so this member must.
                self.restore_handed(shard, &bytes);
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

    /// Restore a shard's state handed by another member.
    fn restore_handed(&mut self, shard: u32, bytes: &[u8]) {
        let steps = self.member.as_ref().is_some_and(|m| m.fleet.steps(shard));
        match decode_shard(bytes) {
            Ok(st) if st.shard == shard && steps => {
                let mut c = lock(&self.shared.core);
                let r = c.registry.restore_shard(&st);
                let mut ib = lock(&self.shared.inbox);
                for d in &st.devices {
                    if c.registry.serves(&d.snapshot.id) {
                        ib.serve(&d.snapshot.id);
                    }
                }
                for (dev, why) in &r.refused {
                    tracing::warn!(shard, device = %dev, "handed state not restored: {why}");
                }
                tracing::debug!(controller = %self.id, shard, restored = r.restored, "took a shard's state");
            }
            Ok(st) if st.shard != shard => {
                tracing::warn!(shard, "a handover reply for another shard: ignored");
            }
            Ok(_) => {}
            Err(e) => tracing::warn!(shard, "a handover reply that does not decode: {e}"),
        }
    }

    /// An owner's update after a configuration change. Only a member that steps the shard
    /// without answering it takes it: the owner itself, and members outside the shard,
    /// ignore it.
    pub(super) fn handle_sync(&mut self, shard: u32, bytes: &[u8]) {
        let follows = self
            .member
            .as_ref()
            .is_some_and(|m| m.fleet.steps(shard) && !m.fleet.answers(shard));
        if !follows {
            return;
        }
        let mut c = lock(&self.shared.core);
        match decode_shard(bytes) {
            Ok(st) if st.shard == shard => {
                for (dev, why) in c.registry.restore_shard(&st).refused {
                    tracing::warn!(shard, device = %dev, "an owner's update not restored: {why}");
                }
            }
            _ => c.registry.note_undecodable(),
        }
    }

    /// After a configuration change accepted by the owner: the device's state to its
    /// standby, so a takeover keeps the change.
    pub(super) async fn sync_device(&self, dev: &str) {
        let Some(m) = &self.member else { return };
        let update = {
            let c = lock(&self.shared.core);
            c.registry.home_of(dev).and_then(|home| {
                let st = c.registry.devices_state(home, &[dev]);
                let bytes = encode_shard(&st).ok()?;
                Some((keys::fleet_sync(&m.spec.name, home), bytes))
            })
        };
        if let Some((key, bytes)) = update {
            let _ = self.session.put(key, bytes).await;
        }
    }

    /// Time passed: releases nobody asked for end, unanswered requests are made again.
    pub(super) async fn on_fleet_tick(&mut self) {
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
            let hb = self.standby.heartbeat_of(&self.id);
            let _ = routes.publisher.put(encode(&hb)).await;
        }
    }
}

/// Make one request to another member on a task of its own; what came back (the reply's
/// payload, or nothing if no good reply came within `timeout`) returns as
/// [`Msg::Answer`]. Whether to ask again is the fleet's decision, not this task's.
fn spawn_request(
    (session, tx): (Session, mpsc::Sender<Msg>),
    key: String,
    (body, kind, shard): (String, RequestKind, u32),
    timeout: Duration,
) {
    tokio::spawn(async move {
        let mut reply = None;
        if let Ok(replies) = session.get(key).payload(body).timeout(timeout).await {
            while let Ok(r) = replies.recv_async().await {
                if let Ok(s) = r.result() {
                    reply = Some(s.payload().to_bytes().into_owned());
                    break;
                }
            }
        }
        let _ = tx.send(Msg::Answer { shard, kind, reply }).await;
    });
}

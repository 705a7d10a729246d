//! What the worker's handlers share to answer a query: who asks and whether they may, the
//! device a key names, error replies, sealed replies, one reply per device for a wildcard
//! key, and an accepted change's reply once the partners the fleet requires hold it.

use protocol::{encode, keys, pb};
use zenoh::query::Query;

use super::hold::{self, Answering, HoldJob};
use super::locks::lock;
use super::worker::Worker;
use crate::access::Action;
use crate::lease::Holder;
use crate::snapshot::encode_shard;
use crate::Registry;

/// Who must hold an accepted change before it is acknowledged.
pub(super) enum ToHold {
    /// This member only: no fleet, or a fleet without standbys (whose takeovers start
    /// afresh from the file anyway).
    Here,
    /// Not acknowledged, why: a fleet with standbys, and nobody else in view, or this
    /// member does not command the plant now.
    Not(String),
    /// These partners, sent the device's state in its shard.
    Partners {
        device: String,
        /// Who held the device's lease when the change was accepted.
        holder: Holder,
        shard: u32,
        state: Vec<u8>,
        partners: Vec<String>,
    },
}

impl Worker {
    /// The operator a request's key names (`…/by/{operator}`), or the error reply for a
    /// key of another shape. `Ok(None)`: it names nobody.
    pub(super) async fn named(&self, q: &Query) -> Option<Option<String>> {
        match keys::request_parts(q.key_expr().as_str()) {
            Some((_, who)) => Some(who.map(str::to_string)),
            None => {
                lock(&self.shared.core).registry.note_request_refused();
                self.reply_error(q, "not a request key: …/device/{id}/{leaf}[/by/{operator}]")
                    .await;
                None
            }
        }
    }

    /// Whether `who` may read `dev`; if not, the query gets why.
    pub(super) async fn may_read(&self, q: &Query, who: Option<&str>, dev: &str) -> bool {
        let check = lock(&self.shared.core)
            .gate
            .access
            .check(who, dev, Action::Read);
        match check {
            Ok(_) => true,
            Err((_, why)) => {
                self.reply_error(q, &why).await;
                false
            }
        }
    }

    /// The device a request names, if this member answers for it. Otherwise the query
    /// gets its error reply, or silence for a device another fleet member answers for
    /// (the client takes the one good reply, never another member's "does not serve").
    /// A key that names no single device (a wildcard, a bad id) is counted as refused; a
    /// device served elsewhere is not, since with several services that is every other
    /// service's normal answer.
    pub(super) async fn served(&self, q: &Query) -> Option<String> {
        let why = {
            let mut c = lock(&self.shared.core);
            let registry = &mut c.registry;
            match keys::device_of(q.key_expr().as_str()) {
                None => {
                    registry.note_request_refused();
                    Some("not the key of one device".to_string())
                }
                Some(dev) => {
                    let home = registry
                        .home_of(dev)
                        .unwrap_or_else(|| protocol::shard_of(dev));
                    if !self.answers_device(registry, dev, home) {
                        return None;
                    }
                    if registry.serves(dev) {
                        return Some(dev.to_string());
                    }
                    Some(format!(
                        "controller {} does not serve device \"{dev}\"",
                        self.id
                    ))
                }
            }
        };
        if let Some(why) = why {
            self.reply_error(q, &why).await;
        }
        None
    }

    /// An error reply to an operator's query, sealed when the service has keys (bound to
    /// the key expression and the request, as a good reply is).
    pub(super) async fn reply_error(&self, q: &Query, why: &str) {
        let bytes = match &self.shared.keys {
            Some(k) => {
                let request = q
                    .payload()
                    .map(|p| p.to_bytes().to_vec())
                    .unwrap_or_default();
                k.seal_error(q.key_expr().as_str(), &request, why)
            }
            None => why.as_bytes().to_vec(),
        };
        let _ = q.reply_err(bytes).await;
    }

    /// A good reply's bytes, sealed for the operators when this member has keys: bound to
    /// the key it goes out on and to the query's payload (`protocol::auth::reply_context`).
    /// Error replies stay plain text: a client shows one only when no good reply came.
    pub(super) fn sealed_reply(
        &self,
        key: &str,
        request: Option<&[u8]>,
        bytes: Vec<u8>,
    ) -> Vec<u8> {
        match &self.shared.keys {
            Some(k) => k.seal_reply(key, request.unwrap_or_default(), bytes),
            None => bytes,
        }
    }

    /// Reply to a wildcard query on `leaf` with `what` of each device it asks for
    /// ([`Worker::matching`]), each sealed on its own key.
    pub(super) async fn reply_matching(
        &self,
        q: &Query,
        who: Option<&str>,
        leaf: &str,
        what: impl Fn(&Registry, &str) -> Option<Vec<u8>>,
    ) {
        for (key, bytes) in self.matching(q, who, leaf, what) {
            let bytes = self.sealed_reply(&key, None, bytes);
            let _ = q.reply(key, bytes).await;
        }
    }

    /// What a wildcard query on `leaf` asks for (`what` of each device), for the devices
    /// answered here that `who` may see, each with the key it goes on (the shard's key if
    /// the query was on shard keys, naming the asker as the query did).
    pub(super) fn matching(
        &self,
        q: &Query,
        who: Option<&str>,
        leaf: &str,
        what: impl Fn(&Registry, &str) -> Option<Vec<u8>>,
    ) -> Vec<(String, Vec<u8>)> {
        let sharded = q
            .key_expr()
            .as_str()
            .starts_with(&format!("{}/shard/", keys::PREFIX));
        let c = lock(&self.shared.core);
        let registry = &c.registry;
        registry
            .device_ids()
            .filter(|d| self.answers_for(registry, d) && c.gate.access.may_see(who, d))
            .filter_map(|d| {
                let home = registry.home_of(d).filter(|_| sharded);
                let key = reply_key(home, d, leaf, who);
                let wanted = zenoh::key_expr::KeyExpr::try_from(key.clone())
                    .is_ok_and(|k| q.key_expr().intersects(&k));
                wanted
                    .then(|| what(registry, d))
                    .flatten()
                    .map(|b| (key, b))
            })
            .collect()
    }

    /// Whether this member answers for device `d`, served here.
    pub(super) fn answers_for(&self, registry: &Registry, d: &str) -> bool {
        registry
            .home_of(d)
            .is_some_and(|h| self.answers_device(registry, d, h))
    }

    /// Whether this member answers operators about device `d` of shard `home`: the one
    /// that holds the plant's lease does (its changes are the ones in force, whatever the
    /// fleet's ranking says, while it commands in the owner's place); one fenced by
    /// another holder never does (a paused or cut-off owner would accept changes the
    /// plant never sees); before a lease (none granted, vacant, not heard yet), the
    /// shard's owner, or any service without a fleet.
    pub(super) fn answers_device(&self, registry: &Registry, d: &str, home: u32) -> bool {
        match registry.lease_holder(d) {
            Holder::Me => true,
            Holder::Other => false,
            Holder::Nobody | Holder::Vacant | Holder::Unknown => {
                self.member.as_ref().is_none_or(|m| m.fleet.answers(home))
            }
        }
    }

    /// Who must hold an accepted change to `dev` before it is acknowledged. The state to
    /// hold is taken under the same lock as the answer: what the partners hold is exactly
    /// what is in force here.
    pub(super) fn to_hold(&self, dev: &str) -> ToHold {
        let c = lock(&self.shared.core);
        let registry = &c.registry;
        let Some(m) = &self.member else {
            return ToHold::Here;
        };
        let Some(home) = registry.home_of(dev) else {
            return ToHold::Here;
        };
        if !m.fleet.keeps_standbys() {
            return ToHold::Here;
        }
        if let Err(why) = registry.may_acknowledge(dev, protocol::unix_ns()) {
            return ToHold::Not(why);
        }
        let partners = m.fleet.partners(home);
        if partners.is_empty() {
            return ToHold::Not("no other member in the fleet's view holds it".into());
        }
        match encode_shard(&registry.devices_state(home, &[dev])) {
            Ok(state) => ToHold::Partners {
                device: dev.to_string(),
                holder: registry.lease_holder(dev),
                shard: home,
                state,
                partners,
            },
            Err(e) => ToHold::Not(format!("its state could not be encoded: {e}")),
        }
    }

    /// Reply to a change made: at once (held here, or not acknowledged with why), or once
    /// the partners `hold` names hold it.
    pub(super) async fn reply_held(
        &mut self,
        q: Query,
        request: Vec<u8>,
        mut reply: pb::ConfigReply,
        hold: ToHold,
    ) {
        match hold {
            ToHold::Partners {
                device,
                holder,
                shard,
                state,
                partners,
            } => {
                let Some(m) = &self.member else { return };
                let job = HoldJob {
                    answer: Some(Answering {
                        query: q,
                        request,
                        reply,
                        device,
                        holder,
                    }),
                    shard,
                    state,
                    partners,
                    devices: Vec::new(),
                };
                if let Err(e) = m.holds.try_send(job) {
                    let Some(Answering {
                        query: q,
                        request,
                        mut reply,
                        ..
                    }) = e.into_inner().answer
                    else {
                        return;
                    };
                    let busy = Some(hold::BUSY);
                    hold::acknowledge(&mut reply, &self.id, vec![self.id.clone()], busy);
                    let key = q.key_expr().as_str();
                    let bytes = self.sealed_reply(key, Some(&request), encode(&reply));
                    let _ = q.reply(q.key_expr().clone(), bytes).await;
                }
                return;
            }
            ToHold::Not(why) => {
                hold::acknowledge(&mut reply, &self.id, vec![self.id.clone()], Some(&why));
            }
            ToHold::Here => reply.held_by = vec![self.id.clone()],
        }
        let bytes = self.sealed_reply(q.key_expr().as_str(), Some(&request), encode(&reply));
        let _ = q.reply(q.key_expr().clone(), bytes).await;
    }
}

/// The key a reply about `dev` goes on for a wildcard query on `leaf`: the device's own,
/// on the shard's key if the query was, naming the asker as the query did.
pub(super) fn reply_key(sharded: Option<u32>, dev: &str, leaf: &str, who: Option<&str>) -> String {
    let key = match sharded {
        Some(h) => format!("{}/shard/{h}/device/{dev}/{leaf}", keys::PREFIX),
        None => format!("{}/device/{dev}/{leaf}", keys::PREFIX),
    };
    match who {
        Some(w) => keys::by(&key, w),
        None => key,
    }
}

//! The worker's handlers of operators' requests: configuration, envelope, reference and
//! commissioning changes (as queries, and the reference as a put), device and service
//! status. Here a request is matched to a served device and decoded; a change then goes
//! the way of [`super::operators`], and once made it is sent on to the shard's partners
//! before it is acknowledged.

use protocol::{decode, encode, keys, pb};
use zenoh::query::Query;

use super::hold::{self, HoldJob};
use super::lock;
use super::operators::{reply_key, Change, Request};
use super::worker::Worker;
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
    /// These partners, sent the device's state in shard `.0`.
    Partners(u32, Vec<u8>, Vec<String>),
}

impl Worker {
    /// A live reference update (put). A put reaches every service, and every fleet
    /// member: one that does not serve the device, or does not step its shard, lets it
    /// pass, uncounted, as it does a request for a device served elsewhere.
    pub(super) async fn handle_reference_put(
        &mut self,
        dev: &str,
        bytes: &[u8],
        who: Option<&str>,
    ) {
        let home = lock(&self.shared.core).registry.home_of(dev);
        let stepped = match (&self.member, home) {
            (_, None) => false,
            (None, Some(_)) => true,
            (Some(m), Some(h)) => m.fleet.steps(h),
        };
        if !stepped {
            return;
        }
        let u = match decode::<pb::ReferenceUpdate>(bytes) {
            Ok(u) => u,
            Err(e) => return self.undecodable("reference", dev, &e),
        };
        let change = Change {
            dev: dev.to_string(),
            who: who.map(str::to_string),
            request: Request::Reference(u),
            bytes: bytes.to_vec(),
            query: None,
        };
        self.submit(change).await;
    }

    /// A configuration query: a read, or a change of laws, gains, maps or reference.
    pub(super) async fn handle_config(&mut self, q: Query) {
        self.change_query(q, |b| decode(b).map(Request::Config))
            .await;
    }

    /// An envelope query: a read, or a change (narrowing; widening where the file allows).
    pub(super) async fn handle_envelope(&mut self, q: Query) {
        self.change_query(q, |b| decode(b).map(Request::Envelope))
            .await;
    }

    /// A reference update sent as a query, to be answered.
    pub(super) async fn handle_reference_query(&mut self, q: Query) {
        self.change_query(q, |b| decode(b).map(Request::Reference))
            .await;
    }

    /// A commissioning query (`crate::registry` decides): a start, a confirmation (the
    /// proposed law put in force like a configuration change) or an abort.
    pub(super) async fn handle_commission(&mut self, q: Query) {
        self.change_query(q, |b| decode(b).map(Request::Commission))
            .await;
    }

    /// A configuration, envelope, reference or commissioning query on a device this member
    /// answers for: no payload reads the configuration in force (who asks must be allowed
    /// to read it); a payload is decoded by `decode` and goes the way of every change
    /// ([`super::operators`]).
    async fn change_query(
        &mut self,
        q: Query,
        decode: impl FnOnce(&[u8]) -> Result<Request, protocol::DecodeError>,
    ) {
        let Some(dev) = self.served(&q).await else {
            return;
        };
        let Some(who) = self.named(&q).await else {
            return;
        };
        let Some(bytes) = q.payload().map(|p| p.to_bytes().into_owned()) else {
            if !self.may_read(&q, who.as_deref(), &dev).await {
                return;
            }
            let reply = read_config(&lock(&self.shared.core).registry, &dev);
            let bytes = self.sealed_reply(q.key_expr().as_str(), None, encode(&reply));
            let _ = q.reply(q.key_expr().clone(), bytes).await;
            return;
        };
        let request = match decode(&bytes) {
            Ok(r) => r,
            Err(e) => {
                let reply = undecodable_request(&mut lock(&self.shared.core).registry, &dev, e);
                self.refused(&dev, "request", &reply.reason);
                let key = q.key_expr().as_str().to_string();
                let sealed = self.sealed_reply(&key, Some(&bytes), encode(&reply));
                let _ = q.reply(q.key_expr().clone(), sealed).await;
                return;
            }
        };
        let change = Change {
            dev,
            who,
            request,
            bytes,
            query: Some(q),
        };
        self.submit(change).await;
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
            ToHold::Partners(shard, state, partners) => {
                let Some(m) = &self.member else { return };
                let job = HoldJob {
                    answer: Some((q, request, reply)),
                    shard,
                    state,
                    partners,
                    devices: Vec::new(),
                };
                if let Err(e) = m.holds.try_send(job) {
                    let Some((q, request, mut reply)) = e.into_inner().answer else {
                        return;
                    };
                    let busy = Some("too many changes are waiting for their partners");
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
        let holder = registry.lease_holder(dev);
        let heard = (registry.heard_unix_ns(dev), registry.live_ns(dev));
        if let Err(why) = hold::may_acknowledge(holder, heard, protocol::unix_ns()) {
            return ToHold::Not(why);
        }
        let partners = m.fleet.partners(home);
        if partners.is_empty() {
            return ToHold::Not("no other member in the fleet's view holds it".into());
        }
        match encode_shard(&registry.devices_state(home, &[dev])) {
            Ok(state) => ToHold::Partners(home, state, partners),
            Err(e) => ToHold::Not(format!("its state could not be encoded: {e}")),
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

    /// A device status query; a wildcard key gets one reply per device answered here
    /// that the asker may see, each on its own key.
    pub(super) async fn handle_status(&mut self, q: Query) {
        let Some(who) = self.named(&q).await else {
            return;
        };
        if q.key_expr().as_str().contains('*') {
            let now = protocol::unix_ns();
            let status = |r: &Registry, d: &str| r.device_status_at(d, now).map(|s| encode(&s));
            return self
                .reply_matching(&q, who.as_deref(), "status", status)
                .await;
        }
        let Some(d) = keys::device_of(q.key_expr().as_str()) else {
            return self.reply_error(&q, "not the key of one device").await;
        };
        let status = {
            let c = lock(&self.shared.core);
            if self.member.is_some() && !self.answers_for(&c.registry, d) {
                // Another member's device: its owner answers, the others stay silent.
                return;
            }
            c.registry.device_status_at(d, protocol::unix_ns())
        };
        let Some(status) = status else {
            let why = format!("controller {} does not serve device \"{d}\"", self.id);
            return self.reply_error(&q, &why).await;
        };
        if self.may_read(&q, who.as_deref(), d).await {
            let bytes = self.sealed_reply(q.key_expr().as_str(), None, encode(&status));
            let _ = q.reply(q.key_expr().clone(), bytes).await;
        }
    }

    /// A query whose payload is over the limit, refused unread: on a device's key by the
    /// member that answers for the device (the others stay silent, as for any query), on
    /// this service's status key by this service.
    pub(super) async fn handle_too_large(&mut self, q: Query, device: bool) {
        if device && self.served(&q).await.is_none() {
            return;
        }
        let len = q.payload().map_or(0, |p| p.len());
        let why = format!(
            "a request of {len} bytes, refused unread: at most {} bytes",
            protocol::MAX_PAYLOAD
        );
        self.reply_error(&q, &why).await;
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

    /// Whether this member answers for device `d`, served here.
    fn answers_for(&self, registry: &Registry, d: &str) -> bool {
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
    fn answers_device(&self, registry: &Registry, d: &str, home: u32) -> bool {
        match registry.lease_holder(d) {
            Holder::Me => true,
            Holder::Other => false,
            Holder::Nobody | Holder::Vacant | Holder::Unknown => {
                self.member.as_ref().is_none_or(|m| m.fleet.answers(home))
            }
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
    fn matching(
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

    /// A service status query, on this service's own key, so that a wildcard query over
    /// several services gets one reply from each, each telling which service it is.
    pub(super) async fn handle_service_status(&mut self, q: Query) {
        let s = self.service_status();
        let key = keys::service_status(&self.id);
        let bytes = self.sealed_reply(&key, None, encode(&s));
        let _ = q.reply(key, bytes).await;
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
}

fn read_config(registry: &Registry, dev: &str) -> pb::ConfigReply {
    match registry.config_of(dev) {
        Some(c) => pb::ConfigReply {
            version: protocol::PROTOCOL_VERSION,
            held_by: Vec::new(),
            durable: false,
            accepted: true,
            reason: String::new(),
            config: Some(c),
        },
        None => pb::ConfigReply {
            version: protocol::PROTOCOL_VERSION,
            held_by: Vec::new(),
            durable: false,
            accepted: false,
            reason: format!("unknown device \"{dev}\""),
            config: None,
        },
    }
}

fn undecodable_request(
    registry: &mut Registry,
    dev: &str,
    e: protocol::DecodeError,
) -> pb::ConfigReply {
    registry.note_undecodable();
    pb::ConfigReply {
        version: protocol::PROTOCOL_VERSION,
        held_by: Vec::new(),
        durable: false,
        accepted: false,
        reason: e.to_string(),
        config: registry.config_of(dev),
    }
}

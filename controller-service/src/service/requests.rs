//! The worker's handlers of operators' requests: configuration, envelope, reference and
//! commissioning changes (as queries, and the reference as a put), device and service
//! status. Here a request is matched to a served device and decoded; a change then goes
//! the way of [`super::operators`], and once made it is sent on to the shard's partners
//! before it is acknowledged.

use protocol::{decode, encode, keys, pb, PROTOCOL_VERSION};
use zenoh::query::Query;

use super::change::{Change, Request};
use super::locks::lock;
use super::worker::Worker;
use crate::Registry;

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
    pub(super) async fn change_query(
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

    /// A service status query, on this service's own key, so that a wildcard query over
    /// several services gets one reply from each, each telling which service it is.
    pub(super) async fn handle_service_status(&mut self, q: Query) {
        let s = self.service_status();
        let key = keys::service_status(&self.id);
        let bytes = self.sealed_reply(&key, None, encode(&s));
        let _ = q.reply(key, bytes).await;
    }

    /// An audit query: a device's latest entries, or for a wildcard key one reply per
    /// device answered here that the asker may see, each on its own key.
    pub(super) async fn handle_audit(&mut self, q: Query) {
        let Some(who) = self.named(&q).await else {
            return;
        };
        if q.key_expr().as_str().contains('*') {
            let log = |r: &Registry, d: &str| r.audit_of(d).map(|l| protocol::encode(&l));
            return self.reply_matching(&q, who.as_deref(), "audit", log).await;
        }
        let Some(dev) = self.served(&q).await else {
            return;
        };
        if !self.may_read(&q, who.as_deref(), &dev).await {
            return;
        }
        let log = lock(&self.shared.core).registry.audit_of(&dev);
        let log = log.unwrap_or(pb::AuditLog {
            version: PROTOCOL_VERSION,
            device_id: dev,
            entries: Vec::new(),
        });
        let bytes = self.sealed_reply(q.key_expr().as_str(), None, protocol::encode(&log));
        let _ = q.reply(q.key_expr().clone(), bytes).await;
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

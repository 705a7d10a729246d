//! Zenoh's callbacks: they run on zenoh's receive threads and must never block, so they
//! only check, sort and count what arrives, then hand it on: a good sample to the
//! [`Core`](super::core::Core) at once or to the inbox, a gateway batch to its inbox,
//! everything else to the worker's queue as a [`Msg`]. Nothing here changes the registry.

use std::sync::Arc;

use protocol::{
    decode, decode_from, keys, pb, Bytes, SampleBatchView, MAX_BATCH_PAYLOAD, MAX_BATCH_SAMPLES,
};
use tokio::sync::mpsc;
use zenoh::key_expr::OwnedKeyExpr;
use zenoh::query::Query;
use zenoh::sample::{Sample, SampleKind};
use zenoh::Session;

use super::core::Shared;
use super::drops::Drops;
use super::locks::lock;
use crate::fleet::RequestKind;
use crate::inbox::{Cap, Parts, Push, Taken};
use crate::registry::precheck;

/// Messages from zenoh's callbacks (and the worker's own request tasks) to the worker,
/// other than samples: one handler each (`Worker::handle`).
pub(super) enum Msg {
    /// A sample the callback refused ([`precheck`]): answered REJECTED with the reason.
    Refused {
        /// The device id from the key.
        dev: String,
        /// The sample (its `seq` and `sent_unix_ns` are echoed in the answer, its lease
        /// decides whether this member sends it).
        sample: Box<pb::Sample>,
        /// Why, already cut to printable length.
        reason: String,
    },
    /// A live reference update (put): the device id from its key, the payload, and the
    /// operator the key names (`…/reference/by/{operator}`), if any.
    Reference(String, Vec<u8>, Option<String>),
    /// A config query: a read without payload, a change with one.
    Config(Query),
    /// An envelope query: a read without payload, a change with one.
    Envelope(Query),
    /// A reference update sent as a query, to be answered.
    ReferenceQuery(Query),
    /// A device status query; a wildcard key gets one reply per device.
    Status(Query),
    /// A device's audit trail; a wildcard key gets one reply per device.
    Audit(Query),
    /// A commissioning request: a read without payload, a start, confirm or abort.
    Commission(Query),
    /// A service status query, answered with the hot-standby state and the drops.
    ServiceStatus(Query),
    /// An operator's query whose payload is over [`MAX_PAYLOAD`], on a device's key
    /// (`device`) or on this service's status key: counted as oversized, refused unread
    /// with an error reply that says so, so the operator does not wait for nothing.
    TooLarge { q: Query, device: bool },
    /// A fleet member appeared (`true`) or disappeared.
    Member(String, bool),
    /// Another member's request about one of this member's shards
    /// ([`crate::fleet::Request`]).
    Handover(Query),
    /// Whether a member's partners are in step with it for these devices, after it sent
    /// them their states ([`super::hold`]).
    HandedOver { devices: Vec<String>, in_step: bool },
    /// What came back for this member's own request about a shard: the reply's payload,
    /// or `None` if no good reply came (an error reply, none before the timeout).
    Answer {
        shard: u32,
        kind: RequestKind,
        /// The member asked.
        from: String,
        reply: Option<Vec<u8>>,
    },
}

/// What the callbacks need; one per worker, shared by all its callbacks.
pub(super) struct Intake {
    pub(super) shared: Arc<Shared>,
    pub(super) tx: mpsc::Sender<Msg>,
    pub(super) heartbeats: mpsc::Sender<Vec<u8>>,
    /// The templates' patterns: which ids could ever be served besides the declared ones
    /// (the inbox's served set). They do not change while the service runs.
    pub(super) templates: Vec<OwnedKeyExpr>,
    pub(super) session: Session,
}

impl Intake {
    fn queue(&self, msg: Msg) {
        if self.tx.try_send(msg).is_err() {
            Drops::count(&self.shared.drops.queue_full);
        }
    }

    /// A sample on a device's key (with or without its shard).
    pub(super) fn on_sample(&self, s: Sample) {
        let drops = &self.shared.drops;
        if !drops.fits(s.payload().len()) {
            return;
        }
        let Some(dev) = keys::device_of(s.key_expr().as_str()) else {
            Drops::count(&drops.bad_key);
            return;
        };
        if !self.shared.masks.steps(protocol::shard_of(dev)) {
            // Another fleet member's device, on the key every member receives.
            return;
        }
        // A device nobody serves or could serve: counted here, whatever the load, and
        // never queued, decoded or answered.
        let templated = || {
            zenoh::key_expr::keyexpr::new(dev)
                .is_ok_and(|ke| self.templates.iter().any(|t| t.includes(ke)))
        };
        if !lock(&self.shared.inbox).serves(dev) && !templated() {
            drops.unknown(dev);
            return;
        }
        let bytes = s.payload().to_bytes();
        // Proof of origin first: a forged sample is neither decoded nor answered.
        let body = match &self.shared.keys {
            Some(k) => match k.open_sample(dev, &bytes) {
                Some(body) => body,
                None => return Drops::count(&drops.forged),
            },
            None => &bytes[..],
        };
        // A sample of another protocol version is undecodable too, and not answered: an
        // answer would be a command of this version, which its agent refuses unread.
        let Ok(sample) = decode::<pb::Sample>(body) else {
            Drops::count(&drops.undecodable);
            return;
        };
        if let Err(reason) = precheck(dev, &sample) {
            self.queue(Msg::Refused {
                dev: dev.to_string(),
                sample: Box::new(sample),
                reason,
            });
            return;
        }
        self.answer_or_queue(dev, sample);
    }

    /// Answer at once, on this thread, when the worker is free and nothing waits before
    /// this sample (so each device's samples are still stepped in order); else queue it.
    fn answer_or_queue(&self, dev: &str, sample: pb::Sample) {
        let shared = &self.shared;
        let mut held = match shared.core.try_lock() {
            Ok(c) => Some(c),
            Err(std::sync::TryLockError::Poisoned(p)) => Some(p.into_inner()),
            Err(std::sync::TryLockError::WouldBlock) => None,
        };
        if let Some(c) = held.as_mut().filter(|_| lock(&shared.inbox).is_empty()) {
            let answers = shared.masks.answers(protocol::shard_of(dev));
            let taken = Taken {
                id: dev.to_string(),
                item: sample,
                superseded: 0,
            };
            if let Some(cmd) = c.serve_sample(answers, &shared.inbox, taken) {
                c.publish_now(&self.session, dev, &cmd);
            }
            return;
        }
        drop(held);
        // A replayed sample of the same run must not push out a newer one.
        let pushed = lock(&shared.inbox).push_unless_older(dev, sample, |new, old| {
            new.run_id == old.run_id && new.seq < old.seq
        });
        if pushed == Push::Queued {
            shared.wake.notify_one();
        }
    }

    /// A gateway's batch: one per period with the samples of all its plants. Checked here
    /// as a whole (size, count, the key's own gateway id, the MAC); each sample inside is
    /// decoded by the worker and checked by the registry, as if it had come alone (one
    /// that does not decode is dropped alone, counted as undecodable).
    pub(super) fn on_gateway_batch(&self, s: Sample) {
        let drops = &self.shared.drops;
        if s.payload().len() > MAX_BATCH_PAYLOAD {
            Drops::count(&drops.oversized);
            return;
        }
        let Some(gw) = keys::gateway_of(s.key_expr().as_str()) else {
            Drops::count(&drops.bad_key);
            return;
        };
        if !self.shared.masks.steps(protocol::shard_of(gw)) {
            return;
        }
        // One copy of the payload, which the batch's samples are slices of until the
        // worker decodes them (`protocol::SampleBatchView`).
        let bytes = Bytes::from(s.payload().to_bytes().into_owned());
        let body = match &self.shared.keys {
            Some(k) => match k.open_batch(gw, &bytes) {
                Some(body) => bytes.slice_ref(body),
                None => return Drops::count(&drops.forged),
            },
            None => bytes,
        };
        let size = body.len();
        let Ok(batch) = decode_from::<SampleBatchView>(body) else {
            Drops::count(&drops.undecodable);
            return;
        };
        if batch.gateway_id != gw {
            Drops::count(&drops.bad_key);
            return;
        }
        let (plants, n) = (batch.plants as usize, batch.samples.len());
        if n > MAX_BATCH_SAMPLES || (plants > 0 && n > plants) {
            Drops::count(&drops.oversized);
            return;
        }
        // Batches always go through the worker: stepping a thousand samples on zenoh's
        // thread would hold up decoding the next batch, and the tail grew that way
        // (p99 at 10 000 plants in gateways of 1000: 1.7-2.4 ms against 1.3-1.6 ms).
        // A part joins the gateway's unread batches, within one period's samples and one
        // batch's bytes (`Parts`): a complete batch replaces them.
        let cap = Cap {
            samples: plants,
            bytes: MAX_BATCH_PAYLOAD,
        };
        let part = Parts::one(batch, n, size);
        let pushed = lock(&self.shared.gateways).push_merged(gw, part, |p, new| p.join(new, cap));
        match pushed {
            Push::Queued => self.shared.wake.notify_one(),
            Push::Superseded | Push::Joined => {}
            Push::Full => Drops::count(&drops.queue_full),
        }
    }

    /// A live reference update (put). A put reaches every service: one that does not
    /// serve the device lets it pass, uncounted, before it can take a place in the queue.
    pub(super) fn on_reference(&self, s: Sample) {
        let drops = &self.shared.drops;
        if !drops.fits(s.payload().len()) {
            return;
        }
        let key = s.key_expr().as_str();
        let (Some(dev), Some(("reference", who))) =
            (keys::device_of(key), keys::request_parts(key))
        else {
            Drops::count(&drops.bad_key);
            return;
        };
        if !lock(&self.shared.inbox).serves(dev) {
            return;
        }
        self.queue(Msg::Reference(
            dev.to_string(),
            s.payload().to_bytes().into_owned(),
            who.map(str::to_string),
        ));
    }

    /// A query on a device's key (`.../device/{id}/{leaf}`, with or without its shard),
    /// sorted by its leaf. An oversized payload is counted and refused unread.
    pub(super) fn on_device_query(&self, q: Query) {
        let drops = &self.shared.drops;
        if !drops.query_fits(&q) {
            return self.queue(Msg::TooLarge { q, device: true });
        }
        let msg = match keys::request_parts(q.key_expr().as_str()).map(|(leaf, _)| leaf) {
            Some("config") => Msg::Config(q),
            Some("envelope") => Msg::Envelope(q),
            Some("reference") => Msg::ReferenceQuery(q),
            Some("status") => Msg::Status(q),
            Some("audit") => Msg::Audit(q),
            Some("commission") => Msg::Commission(q),
            _ => {
                Drops::count(&drops.bad_key);
                return;
            }
        };
        self.queue(msg);
    }

    /// A query on this service's own status key.
    pub(super) fn on_service_query(&self, q: Query) {
        if self.shared.drops.query_fits(&q) {
            self.queue(Msg::ServiceStatus(q));
        } else {
            self.queue(Msg::TooLarge { q, device: false });
        }
    }

    /// A fleet member's liveliness token appeared or disappeared.
    pub(super) fn on_member(&self, s: Sample) {
        let Some(m) = keys::member_of(s.key_expr().as_str()) else {
            return;
        };
        self.queue(Msg::Member(m.to_string(), s.kind() == SampleKind::Put));
    }

    /// Another member's request about one of this member's shards.
    pub(super) fn on_handover(&self, q: Query) {
        if self.shared.drops.query_fits(&q) {
            self.queue(Msg::Handover(q));
        }
    }

    /// A heartbeat of the standby group, on its own queue.
    pub(super) fn on_heartbeat(&self, s: Sample) {
        if !self.shared.drops.fits(s.payload().len()) {
            return;
        }
        let bytes = s.payload().to_bytes();
        // With keys, only a member's heartbeat counts: a forged one with a higher term
        // would make the active member stand by.
        let body = match &self.shared.keys {
            Some(k) => match k.open_handover(&[s.key_expr().as_str().as_bytes()], &bytes) {
                Some(body) => body,
                None => return Drops::count(&self.shared.drops.forged),
            },
            None => &bytes[..],
        };
        if self.heartbeats.try_send(body.to_vec()).is_err() {
            Drops::count(&self.shared.drops.queue_full);
        }
    }
}

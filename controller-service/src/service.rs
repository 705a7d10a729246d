//! The controller service on Zenoh: subscriptions, queryables, liveliness, and one worker
//! task that owns the [`Registry`].
//!
//! Zenoh's callbacks run on zenoh's receive threads and must never block, so they only
//! sort messages, and cheaply: a payload over [`MAX_PAYLOAD`] is counted and dropped
//! before it is copied; a key that names no device is counted and dropped; so is a sample
//! for a device neither declared nor matched by a template (as unknown); a sample is
//! decoded and prechecked ([`precheck`]: version, its key's own id, finite values), and
//! only then goes to the [`Inbox`] (the latest per device, behind a mutex held only to
//! push or pop), so garbage on a device's key never pushes out one of its real samples; a
//! refused one goes to the worker as a short refusal, to be answered. Everything else
//! (requests, reference updates) goes to a bounded queue, and heartbeats to a queue of
//! their own, so that a flood of requests cannot make a standby take over. The
//! worker decodes, steps the controllers and publishes. Every message it does not serve
//! lands in exactly one counter of the service status, and warnings about them are
//! throttled: the first of each kind at once, then one line per interval with a count.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use protocol::{decode, encode, keys, pb, printable, MAX_PAYLOAD};
use tokio::sync::{mpsc, Notify};
use zenoh::pubsub::Publisher;
use zenoh::query::Query;
use zenoh::Session;

use crate::inbox::{Inbox, Push, Taken};
use crate::registry::{precheck, Outcome, Registry};

/// Messages from zenoh's callbacks to the worker, other than samples.
enum Msg {
    /// A sample the callback refused ([`precheck`]): answered REJECTED with the reason.
    Refused {
        /// The device id from the key.
        dev: String,
        /// The sample's `seq` and `sent_unix_ns`, echoed in the answer.
        seq: u64,
        sent_unix_ns: u64,
        /// Why, already cut to printable length.
        reason: String,
    },
    /// A live reference update (put): the device id from its key, and the payload.
    Reference(String, Vec<u8>),
    /// A config query: a read without payload, a change with one.
    Config(Query),
    /// An envelope query: a read without payload, a change with one.
    Envelope(Query),
    /// A reference update sent as a query, to be answered.
    ReferenceQuery(Query),
    /// A device status query; a wildcard key gets one reply per device.
    Status(Query),
    /// A service status query, answered with the hot-standby state and the drops.
    ServiceStatus(Query),
}

/// Depth of the request queue (messages); when it is full new requests are dropped and
/// counted as `queue_full`.
const QUEUE: usize = 1024;
/// Pending samples of devices not served (yet) share this many inbox slots.
const OTHERS: usize = 64;
/// Samples the worker serves before it looks at its other inputs again, so requests and
/// heartbeats are never starved by a busy fleet.
const BATCH: usize = 64;
/// Throttled warnings: at most one line per kind per interval.
const LOG_INTERVAL: Duration = Duration::from_secs(5);

/// Why the service stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    /// A zenoh declaration failed.
    #[error("declaring {what}: {reason}")]
    Declare {
        /// What was being declared, e.g. `sample subscriber`, `liveliness token`.
        what: String,
        /// zenoh's reason.
        reason: String,
    },
}

fn declare_err(what: impl Into<String>) -> impl FnOnce(zenoh::Error) -> ServiceError {
    let what = what.into();
    move |e| ServiceError::Declare {
        what,
        reason: e.to_string(),
    }
}

/// Drops counted in zenoh's callbacks, before the worker sees anything.
#[derive(Debug, Default)]
struct Drops {
    oversized: AtomicU64,
    undecodable: AtomicU64,
    bad_key: AtomicU64,
    queue_full: AtomicU64,
    /// Samples on the key of a device neither declared nor matched by a template: no slot,
    /// no decoding, just this count (added to the registry's in the status).
    unknown: AtomicU64,
    /// The first [`UNKNOWN_NAMED`] of their ids, for the status.
    unknown_names: Mutex<std::collections::BTreeSet<String>>,
}

/// Unknown ids named in the status (the registry keeps as many of its own).
const UNKNOWN_NAMED: usize = 64;

impl Drops {
    fn count(counter: &AtomicU64) {
        counter.fetch_add(1, Ordering::Relaxed);
    }

    fn unknown(&self, id: &str) {
        Self::count(&self.unknown);
        let mut names = lock(&self.unknown_names);
        if names.len() < UNKNOWN_NAMED && !names.contains(id) {
            names.insert(printable(id));
        }
    }
}

/// Throttled logging of one kind of event: the first at once, then at most one line per
/// interval saying how many were not logged. Pure: the caller passes the time.
#[derive(Debug, Default)]
pub struct Throttle {
    last: Option<Instant>,
    suppressed: u64,
}

impl Throttle {
    /// An event at `now`: `Some(n)` if it should be logged, `n` being how many were
    /// suppressed since the last line; `None` if it is only counted.
    pub fn hit(&mut self, now: Instant, interval: Duration) -> Option<u64> {
        match self.last {
            Some(t) if now.saturating_duration_since(t) < interval => {
                self.suppressed += 1;
                None
            }
            _ => {
                self.last = Some(now);
                Some(std::mem::take(&mut self.suppressed))
            }
        }
    }

    /// At `now`, the events counted but not logged, if a line is due: so a burst's count
    /// is told even when nothing of its kind follows.
    pub fn flush(&mut self, now: Instant, interval: Duration) -> Option<u64> {
        match self.last {
            Some(t) if self.suppressed > 0 && now.saturating_duration_since(t) >= interval => {
                self.last = Some(now);
                Some(std::mem::take(&mut self.suppressed))
            }
            _ => None,
        }
    }
}

/// The kinds of throttled warnings.
#[derive(Debug, Default)]
struct Warnings {
    undecodable: Throttle,
    rejected: Throttle,
    unknown: Throttle,
    table_full: Throttle,
    refused: Throttle,
    changed: Throttle,
    envelope: Throttle,
}

impl Warnings {
    /// Log how many of each kind were held back, for the kinds whose interval is over.
    fn flush(&mut self, now: Instant) {
        for (kind, t) in [
            ("undecodable requests or heartbeats", &mut self.undecodable),
            ("samples refused", &mut self.rejected),
            ("samples from unknown devices", &mut self.unknown),
            (
                "samples refused for a full device table",
                &mut self.table_full,
            ),
            ("requests refused", &mut self.refused),
            ("configuration changes", &mut self.changed),
            ("envelope changes", &mut self.envelope),
        ] {
            if let Some(n) = t.flush(now, LOG_INTERVAL) {
                tracing::warn!(
                    count = n,
                    "{kind} not logged one by one since the last line"
                );
            }
        }
    }
}

/// Log through a throttle: `warn_throttled!(throttle, level, fields..., "fmt", args)`.
macro_rules! throttled {
    ($t:expr, $level:ident, $($arg:tt)+) => {
        if let Some(n) = $t.hit(Instant::now(), LOG_INTERVAL) {
            if n > 0 {
                tracing::$level!(suppressed = n, $($arg)+);
            } else {
                tracing::$level!($($arg)+);
            }
        }
    };
}

fn fits(len: usize, drops: &Drops) -> bool {
    if len > MAX_PAYLOAD {
        Drops::count(&drops.oversized);
        return false;
    }
    true
}

/// Run the service on `session` until `shutdown` resolves; then undeclare everything
/// (the liveliness token disappears at once, so plants and standbys see a clean exit).
pub async fn serve(
    session: Session,
    mut registry: Registry,
    shutdown: impl std::future::Future<Output = ()>,
) -> Result<(), ServiceError> {
    let started = Instant::now();
    let id = registry.controller_id().to_string();
    let snapshots = registry.snapshot_spec().cloned();
    if let Some(sn) = &snapshots {
        let (ok, refused) = registry.load_snapshots(&sn.dir);
        tracing::info!(dir = %sn.dir.display(), restored = ok, refused, "snapshots");
    }
    let (tx, mut rx) = mpsc::channel::<Msg>(QUEUE);
    let (hb_tx, mut hb_rx) = mpsc::channel::<Vec<u8>>(64);
    let drops = Arc::new(Drops::default());
    let inbox = Arc::new(Mutex::new(Inbox::<pb::Sample>::new(OTHERS)));
    let wake = Arc::new(Notify::new());
    {
        let mut ib = lock(&inbox);
        for d in registry.device_ids() {
            ib.serve(d);
        }
    }

    // Which ids could ever be served: the declared ones (in the inbox's served set) and
    // those a template matches. The patterns do not change while the service runs.
    let templates = registry.template_patterns();
    let sub = {
        let (drops, inbox, wake, tx) = (drops.clone(), inbox.clone(), wake.clone(), tx.clone());
        session
            .declare_subscriber(keys::all_devices("sample"))
            .callback(move |s| {
                if !fits(s.payload().len(), &drops) {
                    return;
                }
                let Some(dev) = keys::device_of(s.key_expr().as_str()) else {
                    Drops::count(&drops.bad_key);
                    return;
                };
                // A device nobody serves or could serve: counted here, whatever the load,
                // and never queued, decoded or answered.
                let templated = || {
                    zenoh::key_expr::keyexpr::new(dev)
                        .is_ok_and(|ke| templates.iter().any(|t| t.includes(ke)))
                };
                let served = lock(&inbox).serves(dev);
                if !served && !templated() {
                    drops.unknown(dev);
                    return;
                }
                let Ok(sample) = decode::<pb::Sample>(&s.payload().to_bytes()) else {
                    Drops::count(&drops.undecodable);
                    return;
                };
                if let Err(reason) = precheck(dev, &sample) {
                    let msg = Msg::Refused {
                        dev: dev.to_string(),
                        seq: sample.seq,
                        sent_unix_ns: sample.sent_unix_ns,
                        reason,
                    };
                    if tx.try_send(msg).is_err() {
                        Drops::count(&drops.queue_full);
                    }
                    return;
                }
                // A replayed sample of the same run must not push out a newer one.
                let pushed = lock(&inbox).push_unless_older(dev, sample, |new, old| {
                    new.run_id == old.run_id && new.seq < old.seq
                });
                if pushed == Push::Queued {
                    wake.notify_one();
                }
            })
            .await
            .map_err(declare_err("sample subscriber"))?
    };
    let ref_sub = {
        let (tx, drops, inbox) = (tx.clone(), drops.clone(), inbox.clone());
        session
            .declare_subscriber(keys::all_devices("reference"))
            .callback(move |s| {
                if !fits(s.payload().len(), &drops) {
                    return;
                }
                let Some(dev) = keys::device_of(s.key_expr().as_str()) else {
                    Drops::count(&drops.bad_key);
                    return;
                };
                // A put reaches every service: one that does not serve the device lets it
                // pass, uncounted, before it can take a place in the queue.
                if !lock(&inbox).serves(dev) {
                    return;
                }
                let msg = Msg::Reference(dev.to_string(), s.payload().to_bytes().into_owned());
                if tx.try_send(msg).is_err() {
                    Drops::count(&drops.queue_full);
                }
            })
            .await
            .map_err(declare_err("reference subscriber"))?
    };
    // Every queryable sorts the same way: oversized payloads are dropped (the querier gets
    // no reply, as from a lost message), the rest is queued for the worker.
    let queryable = |leaf: String, what: &'static str, wrap: fn(Query) -> Msg| {
        let (tx, drops) = (tx.clone(), drops.clone());
        let session = session.clone();
        async move {
            session
                .declare_queryable(leaf)
                .callback(move |q| {
                    if !fits(q.payload().map_or(0, |p| p.len()), &drops) {
                        return;
                    }
                    if tx.try_send(wrap(q)).is_err() {
                        Drops::count(&drops.queue_full);
                    }
                })
                .await
                .map_err(declare_err(what))
        }
    };
    let q_config = queryable(keys::all_devices("config"), "config queryable", Msg::Config).await?;
    let q_envelope = queryable(
        keys::all_devices("envelope"),
        "envelope queryable",
        Msg::Envelope,
    )
    .await?;
    let q_reference = queryable(
        keys::all_devices("reference"),
        "reference queryable",
        Msg::ReferenceQuery,
    )
    .await?;
    let q_status = queryable(keys::all_devices("status"), "status queryable", Msg::Status).await?;
    let q_service = queryable(
        keys::service_status(&id),
        "service status queryable",
        Msg::ServiceStatus,
    )
    .await?;
    // Hot standby: heartbeats of the group, on their own queue.
    let standby = registry.standby().cloned();
    let hb_sub = match &standby {
        Some(sb) => {
            let (hb_tx, drops) = (hb_tx.clone(), drops.clone());
            Some(
                session
                    .declare_subscriber(keys::heartbeat(&sb.group))
                    .callback(move |s| {
                        if !fits(s.payload().len(), &drops) {
                            return;
                        }
                        if hb_tx.try_send(s.payload().to_bytes().into_owned()).is_err() {
                            Drops::count(&drops.queue_full);
                        }
                    })
                    .await
                    .map_err(declare_err("heartbeat subscriber"))?,
            )
        }
        None => None,
    };
    let hb_pub = match &standby {
        Some(sb) => Some(
            transport::control_publisher(&session, keys::heartbeat(&sb.group))
                .await
                .map_err(|e| ServiceError::Declare {
                    what: "heartbeat publisher".into(),
                    reason: e.to_string(),
                })?,
        ),
        None => None,
    };
    let mut ha = HotStandby::new(standby.as_ref());
    drop(tx);
    drop(hb_tx);
    let token = session
        .liveliness()
        .declare_token(keys::alive_controller(&id))
        .await
        .map_err(declare_err("liveliness token"))?;
    tracing::info!(controller = %id, devices = registry.device_count(), "serving");

    let mut warn = Warnings::default();
    let mut reported = [0u64; 6];
    // One publisher per served device, made at its first command: bounded by the file's
    // `max_devices`, never by what arrives.
    let mut publishers: HashMap<String, Publisher<'static>> = HashMap::new();
    let mut tick = tokio::time::interval(ha.heartbeat);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut snap_tick = tokio::time::interval(Duration::from_millis(
        snapshots.as_ref().map_or(3_600_000, |s| s.interval_ms),
    ));
    snap_tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut report_tick = tokio::time::interval(LOG_INTERVAL);
    report_tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    tokio::pin!(shutdown);
    loop {
        let msg = tokio::select! {
            () = wake.notified() => {
                for _ in 0..BATCH {
                    let Some(taken) = lock(&inbox).pop() else { break };
                    serve_sample(&session, &mut registry, &ha, &mut publishers, &inbox, &mut warn, taken).await;
                }
                if !lock(&inbox).is_empty() {
                    // More waits: come back after the other inputs had their turn.
                    wake.notify_one();
                }
                continue;
            }
            m = rx.recv() => match m { Some(m) => m, None => break },
            Some(bytes) = hb_rx.recv() => {
                match decode::<pb::Heartbeat>(&bytes) {
                    Ok(hb) => {
                        if ha.on_heartbeat(&id, &hb) {
                            tracing::warn!(controller = %id, other = %printable(&hb.controller_id), "another member is active: standing by");
                        }
                    }
                    Err(e) => {
                        registry.note_undecodable();
                        throttled!(warn.undecodable, warn, "undecodable heartbeat: {e}");
                    }
                }
                continue;
            }
            _ = tick.tick(), if hb_pub.is_some() => {
                if ha.on_tick() {
                    tracing::warn!(controller = %id, term = ha.term, "no heartbeat from the active member: taking over");
                }
                if let (true, Some(p)) = (ha.active, &hb_pub) {
                    let hb = pb::Heartbeat { version: protocol::PROTOCOL_VERSION, controller_id: id.clone(), term: ha.term };
                    let _ = p.put(encode(&hb)).await;
                }
                continue;
            }
            _ = snap_tick.tick(), if snapshots.is_some() => {
                if let Some(sn) = &snapshots {
                    let saved = tokio::task::block_in_place(|| registry.save_snapshots(&sn.dir));
                    if let Err(e) = saved {
                        tracing::warn!(dir = %sn.dir.display(), "writing snapshots: {e}");
                    }
                }
                continue;
            }
            _ = report_tick.tick() => {
                // The callbacks' drops cannot log themselves (they run on zenoh's threads,
                // possibly thousands of times a second): one line per interval, if any.
                let (superseded, full) = { let ib = lock(&inbox); (ib.superseded(), ib.full()) };
                let now = [
                    drops.oversized.load(Ordering::Relaxed),
                    drops.bad_key.load(Ordering::Relaxed),
                    drops.queue_full.load(Ordering::Relaxed) + full,
                    superseded,
                    drops.undecodable.load(Ordering::Relaxed),
                    drops.unknown.load(Ordering::Relaxed),
                ];
                let d: Vec<u64> = now.iter().zip(&reported).map(|(a, b)| a - b).collect();
                if d.iter().any(|&x| x > 0) {
                    tracing::warn!(oversized = d[0], bad_key = d[1], queue_full = d[2], superseded = d[3], undecodable_samples = d[4],
                        unknown_devices = d[5], "messages dropped since the last report (every drop is counted in the service status)");
                }
                reported = now;
                warn.flush(Instant::now());
                continue;
            }
            () = &mut shutdown => break,
        };
        match msg {
            Msg::Refused {
                dev,
                seq,
                sent_unix_ns,
                reason,
            } => {
                let outcome = registry.refuse_sample(&dev, seq, sent_unix_ns, reason);
                if let Outcome::Reply(cmd) = outcome {
                    throttled!(warn.rejected, warn, device = %dev, seq, "sample refused: {}", cmd.error);
                    if ha.active {
                        publish(&session, &mut publishers, &dev, &cmd).await;
                    }
                }
            }
            // A put reaches every service: one that does not serve the device lets it pass,
            // uncounted, as it does a request for a device served elsewhere.
            Msg::Reference(dev, _) if !registry.serves(&dev) => {}
            Msg::Reference(dev, bytes) => match decode::<pb::ReferenceUpdate>(&bytes) {
                Ok(u) => {
                    let reply = registry.set_reference(&dev, &u);
                    if !reply.accepted {
                        throttled!(warn.refused, warn, device = %printable(&dev), "reference refused: {}", reply.reason);
                    }
                }
                Err(e) => {
                    registry.note_undecodable();
                    throttled!(warn.undecodable, warn, device = %printable(&dev), "undecodable reference: {e}");
                }
            },
            Msg::Config(q) => {
                let Some(dev) = served_device(&q, &mut registry, &id).await else {
                    continue;
                };
                let reply = match payload(&q) {
                    None => read_config(&registry, &dev),
                    Some(bytes) => match decode::<pb::ConfigRequest>(&bytes) {
                        Ok(req) => {
                            let r = registry.configure(&dev, &req);
                            if r.accepted {
                                throttled!(warn.changed, info, device = %dev, "configuration changed");
                            }
                            r
                        }
                        Err(e) => undecodable_request(&mut registry, &dev, e),
                    },
                };
                if !reply.accepted {
                    throttled!(warn.refused, warn, device = %printable(&dev), "configuration refused: {}", reply.reason);
                }
                let _ = q.reply(keys::config(&dev), encode(&reply)).await;
            }
            Msg::Envelope(q) => {
                let Some(dev) = served_device(&q, &mut registry, &id).await else {
                    continue;
                };
                let reply = match payload(&q) {
                    None => read_config(&registry, &dev),
                    Some(bytes) => match decode::<pb::EnvelopeRequest>(&bytes) {
                        Ok(req) => {
                            let before = registry.envelope_of(&dev);
                            let r = registry.change_envelope(&dev, &req);
                            let after = registry.envelope_of(&dev);
                            let widened = before
                                .iter()
                                .flatten()
                                .zip(after.iter().flatten())
                                .any(|(b, a)| b.is_widened_by(a));
                            if r.accepted && widened {
                                // Every widening has its own line: it is rare (the file must
                                // allow it) and it is what an audit looks for.
                                tracing::warn!(device = %dev, by = %printable(&req.reason),
                                    envelope = ?r.config.as_ref().and_then(|c| c.envelope.clone()), "envelope WIDENED");
                            } else if r.accepted {
                                throttled!(warn.envelope, info, device = %dev, by = %printable(&req.reason),
                                    envelope = ?r.config.as_ref().and_then(|c| c.envelope.clone()), "envelope narrowed");
                            }
                            r
                        }
                        Err(e) => undecodable_request(&mut registry, &dev, e),
                    },
                };
                if !reply.accepted {
                    throttled!(warn.refused, warn, device = %printable(&dev), "envelope change refused: {}", reply.reason);
                }
                let _ = q.reply(keys::envelope(&dev), encode(&reply)).await;
            }
            Msg::ReferenceQuery(q) => {
                let Some(dev) = served_device(&q, &mut registry, &id).await else {
                    continue;
                };
                let reply = match payload(&q) {
                    None => read_config(&registry, &dev),
                    Some(bytes) => match decode::<pb::ReferenceUpdate>(&bytes) {
                        Ok(u) => registry.set_reference(&dev, &u),
                        Err(e) => undecodable_request(&mut registry, &dev, e),
                    },
                };
                if !reply.accepted {
                    throttled!(warn.refused, warn, device = %printable(&dev), "reference refused: {}", reply.reason);
                }
                let _ = q.reply(keys::reference(&dev), encode(&reply)).await;
            }
            Msg::Status(q) => {
                if q.key_expr().as_str().contains('*') {
                    // A wildcard: one reply per device served, each on its own key.
                    let ids: Vec<String> = registry.device_ids().map(str::to_string).collect();
                    for d in ids {
                        let wanted = zenoh::key_expr::KeyExpr::try_from(keys::status(&d))
                            .is_ok_and(|k| q.key_expr().intersects(&k));
                        if let (true, Some(s)) = (wanted, registry.device_status(&d)) {
                            let _ = q.reply(keys::status(&d), encode(&s)).await;
                        }
                    }
                    continue;
                }
                match keys::device_of(q.key_expr().as_str()) {
                    Some(d) => match registry.device_status(d) {
                        Some(s) => {
                            let _ = q.reply(keys::status(d), encode(&s)).await;
                        }
                        None => {
                            let _ = q
                                .reply_err(format!("controller {id} does not serve device \"{d}\""))
                                .await;
                        }
                    },
                    None => {
                        let _ = q.reply_err("not the key of one device").await;
                    }
                }
            }
            Msg::ServiceStatus(q) => {
                let mut s = registry.service_status(started.elapsed().as_secs_f64());
                let (superseded, full) = {
                    let ib = lock(&inbox);
                    (ib.superseded(), ib.full())
                };
                s.unknown_samples += drops.unknown.load(Ordering::Relaxed);
                for name in lock(&drops.unknown_names).iter() {
                    if s.unknown_devices.len() >= UNKNOWN_NAMED {
                        break;
                    }
                    if !s.unknown_devices.contains(name) {
                        s.unknown_devices.push(name.clone());
                    }
                }
                s.oversized = drops.oversized.load(Ordering::Relaxed);
                s.undecodable += drops.undecodable.load(Ordering::Relaxed);
                s.bad_key = drops.bad_key.load(Ordering::Relaxed);
                s.queue_full = drops.queue_full.load(Ordering::Relaxed) + full;
                s.superseded = superseded;
                s.active = ha.active;
                s.term = ha.term;
                // On its own key, so that a wildcard query over several services gets one
                // reply from each, each telling which service it is.
                let _ = q.reply(keys::service_status(&id), encode(&s)).await;
            }
        }
    }
    tracing::info!(controller = %id, "shutting down");
    if let Some(sn) = &snapshots {
        if let Err(e) = registry.save_snapshots(&sn.dir) {
            tracing::warn!(dir = %sn.dir.display(), "writing snapshots: {e}");
        }
    }
    drop(token);
    drop(hb_sub);
    drop(hb_pub);
    drop(sub);
    drop(ref_sub);
    drop(q_config);
    drop(q_envelope);
    drop(q_reference);
    drop(q_status);
    drop(q_service);
    drop(publishers);
    let _ = session.close().await;
    Ok(())
}

/// One of the service's locks (the inbox, the unknown ids): a panic elsewhere while it was
/// held leaves plain data behind, still usable, so a poisoned lock is taken as it is.
fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

fn payload(q: &Query) -> Option<Vec<u8>> {
    q.payload().map(|p| p.to_bytes().into_owned())
}

/// The device a request's key names, if this service serves it. Otherwise the query gets
/// an explicit error reply and `None`: a key that names no single device (a wildcard, a
/// bad id) is counted as refused; a device served elsewhere is not, since with several
/// services that is every other service's normal answer (the client takes the good reply
/// of the one that serves it).
async fn served_device(q: &Query, registry: &mut Registry, controller: &str) -> Option<String> {
    let Some(dev) = keys::device_of(q.key_expr().as_str()).map(str::to_string) else {
        registry.note_request_refused();
        let _ = q.reply_err("not the key of one device").await;
        return None;
    };
    if !registry.serves(&dev) {
        let _ = q
            .reply_err(format!(
                "controller {controller} does not serve device \"{dev}\""
            ))
            .await;
        return None;
    }
    Some(dev)
}

fn read_config(registry: &Registry, dev: &str) -> pb::ConfigReply {
    match registry.config_of(dev) {
        Some(c) => pb::ConfigReply {
            version: protocol::PROTOCOL_VERSION,
            accepted: true,
            reason: String::new(),
            config: Some(c),
        },
        None => pb::ConfigReply {
            version: protocol::PROTOCOL_VERSION,
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
        accepted: false,
        reason: e.to_string(),
        config: registry.config_of(dev),
    }
}

/// Answer one sample from the inbox.
async fn serve_sample(
    session: &Session,
    registry: &mut Registry,
    ha: &HotStandby,
    publishers: &mut HashMap<String, Publisher<'static>>,
    inbox: &Mutex<Inbox<pb::Sample>>,
    warn: &mut Warnings,
    taken: Taken<pb::Sample>,
) {
    let dev = taken.id.as_str();
    let sample = taken.item;
    let was_served = registry.serves(dev);
    // Every member follows every sample (a standby stays warm); only the active one answers.
    let outcome = registry.handle_sample(dev, &sample);
    if taken.superseded > 0 {
        registry.note_superseded(dev, taken.superseded);
    }
    if !was_served && registry.serves(dev) {
        tracing::info!(device = %dev, "provisioned from a template");
        lock(inbox).serve(dev);
    }
    let cmd = match outcome {
        Outcome::Reply(cmd) => cmd,
        Outcome::Unknown => {
            throttled!(warn.unknown, warn, device = %dev, "sample from a device this service does not serve (no template matches): dropped");
            return;
        }
        Outcome::TableFull => {
            throttled!(warn.table_full, warn, device = %dev, "a template matches but the device table is full (max_devices): dropped");
            return;
        }
    };
    if cmd.mode == pb::Mode::Rejected as i32 {
        throttled!(warn.rejected, warn, device = %dev, seq = cmd.seq, "sample refused: {}", cmd.error);
    }
    if ha.active {
        publish(session, publishers, dev, &cmd).await;
    }
}

/// Publish a command on a served device's key, declaring its publisher the first time.
async fn publish(
    session: &Session,
    publishers: &mut HashMap<String, Publisher<'static>>,
    dev: &str,
    cmd: &pb::Command,
) {
    let publisher = match publishers.get(dev) {
        Some(p) => p,
        None => match transport::control_publisher(session, keys::command(dev)).await {
            Ok(p) => publishers.entry(dev.to_string()).or_insert(p),
            Err(e) => {
                tracing::error!(device = %dev, "{e}");
                return;
            }
        },
    };
    if let Err(e) = publisher.put(encode(cmd)).await {
        tracing::warn!(device = %dev, "publishing a command: {e}");
    }
}

/// The hot-standby state machine (no I/O).
#[derive(Debug)]
pub struct HotStandby {
    /// Whether this member publishes commands and heartbeats. A standby still steps every
    /// sample, so its state is warm when it takes over.
    pub active: bool,
    /// Its term, sent in heartbeats and the status: at a takeover, one above the highest
    /// term it holds or has heard. When two members are active the higher term stays, and
    /// on equal terms the greater controller id.
    pub term: u64,
    /// Heartbeat period, also the period of the takeover check. 10 ms without a group,
    /// where nothing uses it.
    pub heartbeat: std::time::Duration,
    /// Silence after which a standby takes over; never (`Duration::MAX`) without a group.
    takeover: std::time::Duration,
    /// When another member was last heard; set one second ahead at start for a `standby`
    /// member (its grace).
    last_heard: Instant,
    /// Highest term heard from another member, so that a takeover outranks it.
    peer_term: u64,
}

impl HotStandby {
    /// Without a group the service is simply active; with one it starts silent and takes
    /// over after the takeover time (an `active` member at once if nobody speaks, a
    /// `standby` member after a grace of one second, so that it does not race the active
    /// one at start-up).
    pub fn new(spec: Option<&crate::config::StandbySpec>) -> Self {
        let now = Instant::now();
        match spec {
            None => Self {
                active: true,
                term: 0,
                heartbeat: std::time::Duration::from_millis(10),
                takeover: std::time::Duration::MAX,
                last_heard: now,
                peer_term: 0,
            },
            Some(sb) => Self {
                active: false,
                term: 0,
                heartbeat: std::time::Duration::from_millis(sb.heartbeat_ms),
                takeover: std::time::Duration::from_millis(sb.takeover_ms),
                last_heard: match sb.role {
                    crate::config::Role::Active => now,
                    crate::config::Role::Standby => now + std::time::Duration::from_secs(1),
                },
                peer_term: 0,
            },
        }
    }

    /// A heartbeat period passed; returns true if this member just took over.
    pub fn on_tick(&mut self) -> bool {
        let now = Instant::now();
        if !self.active && now > self.last_heard && now - self.last_heard > self.takeover {
            self.active = true;
            self.term = self.peer_term.max(self.term) + 1;
            return true;
        }
        false
    }

    /// A heartbeat from the group; returns true if this member just stepped down.
    pub fn on_heartbeat(&mut self, me: &str, hb: &pb::Heartbeat) -> bool {
        if hb.controller_id == me {
            return false;
        }
        self.last_heard = self.last_heard.max(Instant::now());
        self.peer_term = self.peer_term.max(hb.term);
        let they_win =
            hb.term > self.term || (hb.term == self.term && hb.controller_id.as_str() > me);
        if self.active && they_win {
            self.active = false;
            return true;
        }
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn throttle_logs_the_first_then_one_line_per_interval_with_a_count() {
        let t0 = Instant::now();
        let s = Duration::from_secs(5);
        let mut t = Throttle::default();
        assert_eq!(t.hit(t0, s), Some(0), "the first is logged at once");
        for k in 1..1000u64 {
            assert_eq!(t.hit(t0 + Duration::from_millis(k), s), None);
        }
        assert_eq!(t.flush(t0 + Duration::from_secs(1), s), None, "not due yet");
        assert_eq!(t.flush(t0 + s, s), Some(999), "the burst's count is told");
        assert_eq!(t.flush(t0 + 3 * s, s), None, "nothing more to tell");
        assert_eq!(t.hit(t0 + 3 * s, s), Some(0));
    }
}

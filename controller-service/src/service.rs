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

use protocol::{
    decode, encode, keys, pb, printable, MAX_BATCH_PAYLOAD, MAX_BATCH_SAMPLES, MAX_PAYLOAD,
};
use tokio::sync::{mpsc, Notify};
use zenoh::pubsub::{Publisher, Subscriber};
use zenoh::query::{Query, Queryable};
use zenoh::{Session, Wait};

use crate::fleet::{Action, Fleet, Release};
use crate::inbox::{Inbox, Push, Taken};
use crate::observe::{thread_cpu, DeviceHistograms, Observers, Scraped, ServiceMetrics};
use crate::registry::{precheck, Outcome, Registry, Served};
use telemetry::{Recording, Topic};

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
    /// A fleet member appeared (`true`) or disappeared.
    Member(String, bool),
    /// Another member asks for a shard's state (`release:{id}` or `copy:{id}`).
    Handover(Query),
    /// The answer to this member's own handover request for a shard: the state, if any
    /// came, and whether it was a release (this member then owns the shard).
    Handed {
        shard: u32,
        release: bool,
        state: Option<Vec<u8>>,
    },
    /// An owner's device state after a configuration change, for its standbys.
    Sync(u32, Vec<u8>),
    /// The member this one offered a shard to owns it already: stop answering it now.
    Owned(u32),
}

/// Which shards this member steps and answers, read by zenoh's callbacks (bit `s` for
/// shard `s`); all of them without a fleet.
#[derive(Debug)]
struct Masks {
    step: AtomicU64,
    /// The shards whose samples are answered (all or none without a fleet: whether this
    /// member is active). Written only with the [`Core`] held, and read with it held by
    /// whoever answers, so that a handover's state and the answers agree (see
    /// `Msg::Handover`).
    answer: AtomicU64,
    /// The shards whose previous owner's state is still awaited: a handover request for
    /// any other is no longer wanted.
    acquiring: AtomicU64,
}

impl Masks {
    fn steps(&self, shard: u32) -> bool {
        self.step.load(Ordering::Relaxed) & (1u64 << (shard % 64)) != 0
    }

    fn answers(&self, shard: u32) -> bool {
        self.answer.load(Ordering::Relaxed) & (1u64 << (shard % 64)) != 0
    }

    fn acquiring(&self, shard: u32) -> bool {
        self.acquiring.load(Ordering::Relaxed) & (1u64 << (shard % 64)) != 0
    }
}

/// Depth of the request queue (messages); when it is full new requests are dropped and
/// counted as `queue_full`.
const QUEUE: usize = 1024;
/// Pending samples of devices not served (yet) share this many inbox slots.
const OTHERS: usize = 64;
/// Samples the worker serves before it looks at its other inputs again, so requests and
/// heartbeats are never starved by a busy fleet.
const BATCH: usize = 64;
/// Gateways whose batches may wait at once (one unread batch each): a flood of new gateway
/// ids fills these and is dropped as `queue_full`, never growing the service.
const GATEWAYS_PENDING: usize = 256;
/// Gateways with a publisher of their own; commands to any beyond go through the session
/// (same options, one declaration less), so the table is bounded whatever arrives.
const GATEWAY_PUBLISHERS: usize = 1024;
/// Gateway batches the worker serves per turn (each may hold thousands of samples).
const GATEWAY_TURN: usize = 4;
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

/// What the answer to a sample needs: the worker's device state, its observers and the
/// publishers of its commands. Shared by the worker's task and zenoh's callbacks: a
/// callback that finds the core free and nothing queued answers its sample at once, on
/// its own thread, as the echo anchor does; otherwise the sample is queued for the
/// worker. Waking the worker's task costs a thread switch per sample (about 20 us on the
/// reference machine, and much more in the tail when the other core is busy), which was
/// most of what the service cost beyond the anchor. The callbacks only ever `try_lock`
/// it, so they never wait for the worker; the worker never holds it across an `.await`.
/// Lock order: the core, then the inbox.
struct Core {
    registry: Registry,
    watch: Watch,
    /// Throttles for what is logged while answering (the worker keeps its own for the rest).
    warn: Warnings,
    /// One publisher per served device, made at its first command: bounded by the file's
    /// `max_devices`, never by what arrives. Shared out, so the worker can publish with
    /// the core released.
    publishers: HashMap<String, Arc<Publisher<'static>>>,
    /// The same for gateways' command batches (at most [`GATEWAY_PUBLISHERS`]).
    gw_publishers: HashMap<String, Arc<Publisher<'static>>>,
    /// The commands of the last batch, kept with their buffers for the next one.
    pool: Vec<pb::Command>,
}

impl Core {
    /// Step one sample of `dev`; the command to send, if this worker answers it.
    fn serve_sample(
        &mut self,
        answers: bool,
        inbox: &Mutex<Inbox<pb::Sample>>,
        taken: Taken<pb::Sample>,
    ) -> Option<pb::Command> {
        let Core {
            registry,
            watch,
            warn,
            ..
        } = self;
        let dev = taken.id.as_str();
        let sample = taken.item;
        let log_ns = protocol::unix_ns();
        let cpu0 = watch.timing().then(thread_cpu);
        // Every member follows every sample (a standby stays warm); only the active one answers.
        let (outcome, provisioned) =
            registry.handle_sample_from(dev, &sample, Some(protocol::shard_of(dev)));
        let cpu = cpu0.map(|c| thread_cpu() - c);
        if taken.superseded > 0 {
            registry.note_superseded(dev, taken.superseded);
        }
        if provisioned && matches!(outcome, Outcome::Reply(_)) {
            tracing::info!(device = %dev, "provisioned from a template");
            lock(inbox).serve(dev);
        }
        let cmd = match outcome {
            Outcome::Reply(cmd) => cmd,
            Outcome::Unknown => {
                throttled!(warn.unknown, warn, device = %dev, "sample from a device this service does not serve (no template matches): dropped");
                return None;
            }
            Outcome::TableFull => {
                throttled!(warn.table_full, warn, device = %dev, "a template matches but the device table is full (max_devices): dropped");
                return None;
            }
            // Answered before a restore or by the member that handed it over: once is enough.
            Outcome::AlreadyAnswered => return None,
        };
        if cmd.mode == pb::Mode::Rejected as i32 {
            throttled!(warn.rejected, warn, device = %dev, seq = cmd.seq, "sample refused: {}", cmd.error);
        }
        watch.served(registry, dev, &sample, &cmd, cpu, provisioned, log_ns);
        answers.then_some(cmd)
    }

    /// Publish `cmd` from one of zenoh's callbacks (a blocking put there is zenoh's own
    /// way, never in async code), declaring the device's publisher the first time.
    fn publish_now(&mut self, session: &Session, dev: &str, cmd: &pb::Command) {
        if !self.publishers.contains_key(dev) {
            match transport::control_publisher_now(session, keys::command(dev)) {
                Ok(p) => {
                    self.publishers.insert(dev.to_string(), Arc::new(p));
                }
                Err(e) => {
                    tracing::error!(device = %dev, "{e}");
                    return;
                }
            }
        }
        if let Some(p) = self.publishers.get(dev) {
            if let Err(e) = p.put(encode(cmd)).wait() {
                tracing::warn!(device = %dev, "publishing a command: {e}");
            }
        }
    }
}

fn fits(len: usize, drops: &Drops) -> bool {
    if len > MAX_PAYLOAD {
        Drops::count(&drops.oversized);
        return false;
    }
    true
}

/// Run the service on `session` until `shutdown` resolves; then undeclare everything
/// (the liveliness token disappears at once, so plants and standbys see a clean exit) and
/// close the session.
pub async fn serve(
    session: Session,
    registry: Registry,
    shutdown: impl std::future::Future<Output = ()>,
) -> Result<(), ServiceError> {
    let result = serve_shared(session.clone(), registry, shutdown).await;
    let _ = session.close().await;
    result
}

/// [`serve`] on a session other workers share: everything this worker declared is
/// undeclared at the end, and the session stays open for the others.
pub async fn serve_shared(
    session: Session,
    registry: Registry,
    shutdown: impl std::future::Future<Output = ()>,
) -> Result<(), ServiceError> {
    serve_observed(session, registry, Observers::default(), shutdown).await
}

/// What a worker feeds its observers, and the histogram handles of its devices (one entry
/// per device it served: bounded by its device table).
struct Watch {
    controller: String,
    recording: Option<Recording>,
    metrics: Option<Arc<ServiceMetrics>>,
    histograms: HashMap<String, Option<DeviceHistograms>>,
}

impl Watch {
    /// Whether samples are timed (only for the metrics: the clock costs a system call).
    fn timing(&self) -> bool {
        self.metrics.is_some()
    }

    /// Note a served sample: its round trip and CPU time, and into the recording the
    /// sample, its answer and, for a device just provisioned, its configuration.
    #[allow(clippy::too_many_arguments)]
    fn served(
        &mut self,
        registry: &Registry,
        dev: &str,
        sample: &pb::Sample,
        cmd: &pb::Command,
        cpu: Option<f64>,
        provisioned: bool,
        log_ns: u64,
    ) {
        if let Some(m) = &self.metrics {
            let h = self
                .histograms
                .entry(dev.to_string())
                .or_insert_with(|| m.device(&self.controller, dev));
            if let Some(h) = h {
                if sample.last_rtt_us > 0 {
                    h.rtt.record(f64::from(sample.last_rtt_us) * 1e-6);
                }
                if let Some(c) = cpu {
                    h.cpu.record(c);
                }
            }
        }
        if let Some(r) = &self.recording {
            if provisioned {
                record_config(r, registry, dev, "provisioned from a template");
            }
            r.record(
                dev,
                Topic::Sample,
                log_ns,
                sample.sent_unix_ns,
                encode(sample),
            );
            let now = protocol::unix_ns();
            r.record(
                dev,
                Topic::Command,
                now,
                cmd.controller_unix_ns,
                encode(cmd),
            );
            if cmd.mode == pb::Mode::Rejected as i32 {
                r.event(dev, "rejected", cmd.error.clone(), sample.plant_time);
            }
        }
    }

    /// Record an accepted change: the request as it came, the configuration it left, and
    /// an event saying who changed what.
    fn changed(&self, registry: &Registry, dev: &str, topic: Topic, request: &[u8], what: &str) {
        if let Some(r) = &self.recording {
            let now = protocol::unix_ns();
            r.record(dev, topic, now, now, request.to_vec());
            record_config(r, registry, dev, what);
        }
    }
}

/// The device's configuration in force, and an event saying why it is recorded.
fn record_config(r: &Recording, registry: &Registry, dev: &str, why: &str) {
    if let Some(c) = registry.config_of(dev) {
        let now = protocol::unix_ns();
        r.record(dev, Topic::Config, now, now, encode(&c));
    }
    let t = registry.device_status(dev).map_or(0.0, |s| s.plant_time);
    r.event(dev, "config", why, t);
}

/// [`serve_shared`] feeding `observers`: the metrics scrape this worker's status, the
/// recording gets its devices' samples, commands and configuration changes.
pub async fn serve_observed(
    session: Session,
    mut registry: Registry,
    observers: Observers,
    shutdown: impl std::future::Future<Output = ()>,
) -> Result<(), ServiceError> {
    let started = Instant::now();
    let id = registry.controller_id().to_string();
    let snapshots = registry.snapshot_spec().cloned();
    if let Some(sn) = &snapshots {
        let (ok, refused) = registry.load_snapshots(&sn.dir);
        tracing::info!(dir = %sn.dir.display(), restored = ok, refused, "snapshots");
        if let (Some(r), true) = (&observers.recording, ok > 0) {
            // What a replay must start from: the state these devices were restored to.
            for snap in registry.snapshots() {
                if snap.last_seq.is_some() {
                    if let Ok(bytes) = crate::snapshot::encode(&snap) {
                        r.attach(
                            &format!("snapshot/{}", snap.id),
                            "application/x-mfc-snapshot",
                            bytes,
                        );
                    }
                }
            }
        }
    }
    let watch = Watch {
        controller: id.clone(),
        recording: observers.recording.clone(),
        metrics: observers.metrics.clone(),
        histograms: HashMap::new(),
    };
    if let Some(r) = &watch.recording {
        for d in registry.device_ids() {
            record_config(r, &registry, d, "recording starts");
        }
    }
    let mut scrapes = watch.metrics.as_ref().map(|m| m.join());
    let (tx, mut rx) = mpsc::channel::<Msg>(QUEUE);
    let (hb_tx, mut hb_rx) = mpsc::channel::<Vec<u8>>(64);
    let drops = Arc::new(Drops::default());
    let inbox = Arc::new(Mutex::new(Inbox::<pb::Sample>::new(OTHERS)));
    let gateways = Arc::new(Mutex::new(Inbox::<pb::SampleBatch>::new(GATEWAYS_PENDING)));
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
    let fleet_spec = registry.fleet().cloned();
    let standby = registry.standby().cloned();
    let mut pending_actions: Vec<Action> = Vec::new();
    let masks = Arc::new(Masks {
        step: AtomicU64::new(if fleet_spec.is_some() { 0 } else { u64::MAX }),
        // A plain service answers from its first sample; a fleet member or a member of a
        // standby group answers nothing until its role is known (set before serving).
        answer: AtomicU64::new(if fleet_spec.is_none() && standby.is_none() {
            u64::MAX
        } else {
            0
        }),
        acquiring: AtomicU64::new(0),
    });
    let core = Arc::new(Mutex::new(Core {
        registry,
        watch,
        warn: Warnings::default(),
        publishers: HashMap::new(),
        gw_publishers: HashMap::new(),
        pool: Vec::new(),
    }));
    // One callback for every subscription to samples: the key without a shard (every
    // member receives it and keeps its own shards' samples) and the keys of each shard
    // (only its owner and standby subscribe: zenoh routes them nothing else).
    let sample_cb = || {
        let (drops, inbox, wake, tx) = (drops.clone(), inbox.clone(), wake.clone(), tx.clone());
        let (templates, masks) = (templates.clone(), masks.clone());
        let (core, session) = (core.clone(), session.clone());
        move |s: zenoh::sample::Sample| {
            if !fits(s.payload().len(), &drops) {
                return;
            }
            let Some(dev) = keys::device_of(s.key_expr().as_str()) else {
                Drops::count(&drops.bad_key);
                return;
            };
            if !masks.steps(protocol::shard_of(dev)) {
                // Another fleet member's device, on the key every member receives.
                return;
            }
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
            // At once, on this thread, when the worker is free and nothing waits before
            // this sample (so each device's samples are still stepped in order).
            let mut held = match core.try_lock() {
                Ok(c) => Some(c),
                Err(std::sync::TryLockError::Poisoned(p)) => Some(p.into_inner()),
                Err(std::sync::TryLockError::WouldBlock) => None,
            };
            if let Some(c) = held.as_mut().filter(|_| lock(&inbox).is_empty()) {
                let shard = protocol::shard_of(dev);
                let taken = Taken {
                    id: dev.to_string(),
                    item: sample,
                    superseded: 0,
                };
                if let Some(cmd) = c.serve_sample(masks.answers(shard), &inbox, taken) {
                    c.publish_now(&session, dev, &cmd);
                }
                return;
            }
            drop(held);
            // A replayed sample of the same run must not push out a newer one.
            let pushed = lock(&inbox).push_unless_older(dev, sample, |new, old| {
                new.run_id == old.run_id && new.seq < old.seq
            });
            if pushed == Push::Queued {
                wake.notify_one();
            }
        }
    };
    let sub = session
        .declare_subscriber(keys::all_devices("sample"))
        .callback(sample_cb())
        .await
        .map_err(declare_err("sample subscriber"))?;
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
    // Gateways: one batch per period with the samples of all their plants. Checked here
    // as a whole (size, count, the key's own gateway id); each sample inside is checked by
    // the registry, as if it had come alone.
    let gateway_cb = || {
        let (drops, gateways, wake, masks) =
            (drops.clone(), gateways.clone(), wake.clone(), masks.clone());
        move |s: zenoh::sample::Sample| {
            if s.payload().len() > MAX_BATCH_PAYLOAD {
                Drops::count(&drops.oversized);
                return;
            }
            let Some(gw) = keys::gateway_of(s.key_expr().as_str()) else {
                Drops::count(&drops.bad_key);
                return;
            };
            if !masks.steps(protocol::shard_of(gw)) {
                return;
            }
            let Ok(batch) = decode::<pb::SampleBatch>(&s.payload().to_bytes()) else {
                Drops::count(&drops.undecodable);
                return;
            };
            if batch.gateway_id != gw {
                Drops::count(&drops.bad_key);
                return;
            }
            if batch.samples.len() > MAX_BATCH_SAMPLES {
                Drops::count(&drops.oversized);
                return;
            }
            // Batches always go through the worker: stepping a thousand samples on zenoh's
            // thread would hold up decoding the next batch, and the tail grew that way
            // (p99 at 10 000 plants in gateways of 1000: 1.7-2.4 ms against 1.3-1.6 ms).
            match lock(&gateways).push(gw, batch) {
                Push::Queued => wake.notify_one(),
                Push::Superseded => {}
                Push::Full => Drops::count(&drops.queue_full),
            }
        }
    };
    let gw_sub = session
        .declare_subscriber(keys::all_gateways("samples"))
        .callback(gateway_cb())
        .await
        .map_err(declare_err("gateway subscriber"))?;
    // Without a fleet, the shard keys are served as they come (every shard is this
    // service's); with one, each shard's are declared as it is taken (see `Dynamic`).
    let static_shards = if fleet_spec.is_none() {
        Some((
            session
                .declare_subscriber(format!("{}/shard/*/device/*/sample", keys::PREFIX))
                .callback(sample_cb())
                .await
                .map_err(declare_err("shard sample subscriber"))?,
            session
                .declare_subscriber(format!("{}/shard/*/gateway/*/samples", keys::PREFIX))
                .callback(gateway_cb())
                .await
                .map_err(declare_err("shard gateway subscriber"))?,
        ))
    } else {
        None
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
    // The same requests on the shard keys: `mfc/v1/shard/{s}/device/{id}/{leaf}`, one
    // queryable per shard, sorted by leaf.
    let query_cb = || {
        let (tx, drops) = (tx.clone(), drops.clone());
        move |q: Query| {
            if !fits(q.payload().map_or(0, |p| p.len()), &drops) {
                return;
            }
            let msg = match q.key_expr().as_str().rsplit('/').next() {
                Some("config") => Msg::Config(q),
                Some("envelope") => Msg::Envelope(q),
                Some("reference") => Msg::ReferenceQuery(q),
                Some("status") => Msg::Status(q),
                _ => {
                    Drops::count(&drops.bad_key);
                    return;
                }
            };
            if tx.try_send(msg).is_err() {
                Drops::count(&drops.queue_full);
            }
        }
    };
    let static_shard_queries = if fleet_spec.is_none() {
        Some(
            session
                .declare_queryable(format!("{}/shard/*/device/*/*", keys::PREFIX))
                .callback(query_cb())
                .await
                .map_err(declare_err("shard queryable"))?,
        )
    } else {
        None
    };
    // A fleet: membership by liveliness, handover requests, and the owners' updates for
    // their standbys. The members' events queue for the worker like requests do.
    let mut fleet: Option<Fleet> = None;
    let mut fleet_decls: Vec<Box<dyn std::any::Any + Send>> = Vec::new();
    if let Some(f) = &fleet_spec {
        let members_sub = {
            let (tx, drops) = (tx.clone(), drops.clone());
            session
                .liveliness()
                .declare_subscriber(keys::fleet_members(&f.name))
                .callback(move |s| {
                    let Some(m) = keys::member_of(s.key_expr().as_str()) else {
                        return;
                    };
                    let alive = s.kind() == zenoh::sample::SampleKind::Put;
                    if tx.try_send(Msg::Member(m.to_string(), alive)).is_err() {
                        Drops::count(&drops.queue_full);
                    }
                })
                .await
                .map_err(declare_err("fleet member subscriber"))?
        };
        fleet_decls.push(Box::new(members_sub));
        let handover_q = {
            let (tx, drops) = (tx.clone(), drops.clone());
            session
                .declare_queryable(format!("{}/shard/*", keys::fleet_member(&f.name, &id)))
                .callback(move |q| {
                    if tx.try_send(Msg::Handover(q)).is_err() {
                        Drops::count(&drops.queue_full);
                    }
                })
                .await
                .map_err(declare_err("handover queryable"))?
        };
        fleet_decls.push(Box::new(handover_q));
        let sync_sub = {
            let (tx, drops, masks) = (tx.clone(), drops.clone(), masks.clone());
            session
                .declare_subscriber(format!("{}/fleet/{}/sync/*", keys::PREFIX, f.name))
                .callback(move |s| {
                    let Some(shard) = keys::last_shard(s.key_expr().as_str()) else {
                        return;
                    };
                    if !masks.steps(shard) {
                        return;
                    }
                    let msg = Msg::Sync(shard, s.payload().to_bytes().into_owned());
                    if tx.try_send(msg).is_err() {
                        Drops::count(&drops.queue_full);
                    }
                })
                .await
                .map_err(declare_err("fleet sync subscriber"))?
        };
        fleet_decls.push(Box::new(sync_sub));
        // Who is there already: what was theirs stays theirs until they hand it over.
        let mut others = Vec::new();
        if let Ok(replies) = session
            .liveliness()
            .get(keys::fleet_members(&f.name))
            .timeout(Duration::from_millis(f.discover_ms))
            .await
        {
            while let Ok(r) = replies.recv_async().await {
                if let Ok(sample) = r.result() {
                    if let Some(m) = keys::member_of(sample.key_expr().as_str()) {
                        if m != id {
                            others.push(m.to_string());
                        }
                    }
                }
            }
        }
        // The token before any request: a member that hears from this one can also hear
        // it leave.
        let member_token = session
            .liveliness()
            .declare_token(keys::fleet_member(&f.name, &id))
            .await
            .map_err(declare_err("fleet member token"))?;
        fleet_decls.push(Box::new(member_token));
        let mut fl = Fleet::new(&id, f.standby);
        let actions = fl.start(others.clone());
        tracing::info!(controller = %id, fleet = %f.name, others = ?others, "joining the fleet");
        fleet = Some(fl);
        pending_actions = actions;
    }
    let mut dynamic = Dynamic::default();
    // Hot standby: heartbeats of the group, on their own queue.
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
    // Handover results come back through the queue from tasks of their own.
    // (`tx` itself stays alive with the callback factories: the queue never closes, the
    // loop ends on `shutdown`.)
    let internal_tx = tx.clone();
    drop(hb_tx);
    let token = session
        .liveliness()
        .declare_token(keys::alive_controller(&id))
        .await
        .map_err(declare_err("liveliness token"))?;
    tracing::info!(controller = %id, devices = lock(&core).registry.device_count(), "serving");

    let mut warn = Warnings::default();
    let mut reported = [0u64; 6];
    let mut tick = tokio::time::interval(ha.heartbeat);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut snap_tick = tokio::time::interval(Duration::from_millis(
        snapshots.as_ref().map_or(3_600_000, |s| s.interval_ms),
    ));
    snap_tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut report_tick = tokio::time::interval(LOG_INTERVAL);
    report_tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    // Which samples are answered, for every thread that answers them (see `Masks`). Call
    // it with the core held.
    macro_rules! store_answers {
        () => {{
            let m = if ha.active {
                fleet.as_ref().map_or(u64::MAX, |f| f.answer_mask())
            } else {
                0
            };
            masks.answer.store(m, Ordering::Relaxed);
        }};
    }
    // The device a request names, if this member answers for it; otherwise the query gets
    // its error reply (or silence, for another member's device) and `None`.
    macro_rules! served {
        ($q:expr) => {{
            let checked = served_device(&$q, &mut lock(&core).registry, &id, fleet.as_ref());
            match checked {
                Ok(dev) => Some(dev),
                Err(why) => {
                    if let Some(why) = why {
                        let _ = $q.reply_err(why).await;
                    }
                    None
                }
            }
        }};
    }
    // Fleet changes: start the handover requests the change asks for, drop the state of
    // shards no longer held, and make the shard subscriptions and queryables match.
    macro_rules! fleet_apply {
        ($actions:expr) => {{
            let actions: Vec<Action> = $actions;
            if let (Some(fl), Some(spec)) = (fleet.as_ref(), fleet_spec.as_ref()) {
                for a in &actions {
                    match a {
                        Action::Acquire { shard, from } | Action::Copy { shard, from } => {
                            spawn_handover(
                                session.clone(),
                                internal_tx.clone(),
                                (&spec.name, &id),
                                from.clone(),
                                (*shard, matches!(a, Action::Acquire { .. })),
                                masks.clone(),
                                (
                                    Duration::from_millis(spec.handover_timeout_ms),
                                    Duration::from_millis(spec.release_timeout_ms),
                                ),
                            );
                        }
                        Action::Offer { shard, to } => {
                            spawn_offer(
                                session.clone(),
                                internal_tx.clone(),
                                keys::fleet_handover(&spec.name, to, *shard),
                                format!("offer:{id}"),
                                *shard,
                                Duration::from_millis(spec.handover_timeout_ms),
                            );
                        }
                        Action::Unsubscribe(shard) => {
                            let mut c = lock(&core);
                            let gone = c.registry.forget_shard(*shard);
                            let mut ib = lock(&inbox);
                            for d in &gone {
                                ib.unserve(d);
                                c.watch.histograms.remove(d);
                            }
                        }
                        Action::Subscribe(_) => {}
                    }
                }
                {
                    let _held = lock(&core);
                    store_answers!();
                }
                masks.step.store(fl.step_mask(), Ordering::Relaxed);
                masks
                    .acquiring
                    .store(fl.acquiring_mask(), Ordering::Relaxed);
                dynamic
                    .sync(&session, fl, &sample_cb, &gateway_cb, &query_cb)
                    .await;
            }
        }};
    }
    // After a configuration change accepted by the owner: the device's state to its
    // standby, so a takeover keeps the change.
    macro_rules! sync_device {
        ($dev:expr) => {{
            let dev: &str = $dev;
            let update = fleet_spec.as_ref().and_then(|spec| {
                let c = lock(&core);
                let home = c.registry.home_of(dev)?;
                let st = c.registry.devices_state(home, &[dev]);
                let bytes = crate::snapshot::encode_shard(&st).ok()?;
                Some((keys::fleet_sync(&spec.name, home), bytes))
            });
            if let Some((key, bytes)) = update {
                let _ = session.put(key, bytes).await;
            }
        }};
    }
    // A configuration, envelope or reference query: no payload reads the configuration in
    // force; a payload is decoded as `$req` and applied by `$apply` with the core held
    // (`$registry`, `$watch`, the decoded `$r` and its `$bytes` in scope). A refusal is
    // logged, the reply sent, and an accepted change synced to the standby.
    macro_rules! change_query {
        ($q:expr, $dev:expr, $req:ty, $what:literal,
         |$registry:ident, $watch:ident, $r:ident, $bytes:ident| $apply:expr) => {{
            let reply = {
                let mut held = lock(&core);
                let Core {
                    registry: $registry,
                    watch: $watch,
                    ..
                } = &mut *held;
                match payload(&$q) {
                    None => read_config($registry, &$dev),
                    Some($bytes) => match decode::<$req>(&$bytes) {
                        Ok($r) => $apply,
                        Err(e) => undecodable_request($registry, &$dev, e),
                    },
                }
            };
            if !reply.accepted {
                throttled!(warn.refused, warn, device = %printable(&$dev), "{} refused: {}", $what, reply.reason);
            }
            let _ = $q.reply($q.key_expr().clone(), encode(&reply)).await;
            if reply.accepted && payload(&$q).is_some() {
                sync_device!(&$dev);
            }
        }};
    }
    fleet_apply!(std::mem::take(&mut pending_actions));
    {
        let _held = lock(&core);
        store_answers!();
    }
    if let Some(fl) = &fleet {
        tracing::info!(controller = %id, owned = fl.answer_mask().count_ones(), stepped = fl.step_mask().count_ones(), "fleet shards at start");
    }
    let mut releasing_since: HashMap<u32, Instant> = HashMap::new();
    let mut fleet_tick = tokio::time::interval(Duration::from_millis(20));
    fleet_tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    tokio::pin!(shutdown);
    loop {
        let msg = tokio::select! {
            () = wake.notified() => {
                for _ in 0..BATCH {
                    let out = {
                        let mut c = lock(&core);
                        let Some(taken) = lock(&inbox).pop() else { break };
                        let dev = taken.id.clone();
                        let answers = masks.answers(protocol::shard_of(&dev));
                        c.serve_sample(answers, &inbox, taken).map(|cmd| (dev, cmd))
                    };
                    if let Some((dev, cmd)) = out {
                        publish(&session, &core, &dev, &cmd).await;
                    }
                }
                for _ in 0..GATEWAY_TURN {
                    let out = {
                        let mut c = lock(&core);
                        let Some(taken) = lock(&gateways).pop() else { break };
                        let answers = masks.answers(protocol::shard_of(&taken.id));
                        step_batch(&mut c, answers, &inbox, taken)
                    };
                    if let Some((gw, payload)) = out {
                        publish_batch(&session, &core, gw, payload).await;
                    }
                }
                if !lock(&inbox).is_empty() || !lock(&gateways).is_empty() {
                    // More waits: come back after the other inputs had their turn.
                    wake.notify_one();
                }
                continue;
            }
            Some(reply) = async { match scrapes.as_mut() { Some(s) => s.recv().await, None => std::future::pending().await } } => {
                let status = service_status_now(&lock(&core).registry, started, &inbox, &gateways, &drops, &ha, fleet.as_ref());
                let _ = reply.send(Scraped {
                    status,
                    inbox: lock(&inbox).len(),
                    gateways: lock(&gateways).len(),
                    queue: internal_tx.max_capacity() - internal_tx.capacity(),
                });
                continue;
            }
            m = rx.recv() => match m { Some(m) => m, None => break },
            Some(bytes) = hb_rx.recv() => {
                match decode::<pb::Heartbeat>(&bytes) {
                    Ok(hb) => {
                        let stood_by = ha.on_heartbeat(&id, &hb);
                        {
                            let _held = lock(&core);
                            store_answers!();
                        }
                        if stood_by {
                            tracing::warn!(controller = %id, other = %printable(&hb.controller_id), "another member is active: standing by");
                        }
                    }
                    Err(e) => {
                        lock(&core).registry.note_undecodable();
                        throttled!(warn.undecodable, warn, "undecodable heartbeat: {e}");
                    }
                }
                continue;
            }
            _ = tick.tick(), if hb_pub.is_some() => {
                let took_over = ha.on_tick();
                {
                    let _held = lock(&core);
                    store_answers!();
                }
                if took_over {
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
                    let saved = tokio::task::block_in_place(|| lock(&core).registry.save_snapshots(&sn.dir));
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
                let full = full + lock(&gateways).full();
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
            _ = fleet_tick.tick(), if fleet.is_some() => {
                // Releases nobody asked for end after their timeout.
                let now = Instant::now();
                let timeout = Duration::from_millis(fleet_spec.as_ref().map_or(1000, |f| f.release_timeout_ms));
                let mut expired = Vec::new();
                if let Some(fl) = fleet.as_mut() {
                    let rel: Vec<u32> = fl.releasing().collect();
                    releasing_since.retain(|s, _| rel.contains(s));
                    for s in rel {
                        let since = *releasing_since.entry(s).or_insert(now);
                        if now.duration_since(since) > timeout {
                            tracing::warn!(shard = s, "nobody asked for a released shard: no longer answering it");
                            expired.extend(fl.release_expired(s));
                            releasing_since.remove(&s);
                        }
                    }
                }
                if !expired.is_empty() {
                    fleet_apply!(expired);
                }
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
                let outcome = {
                    let mut c = lock(&core);
                    let outcome = c.registry.refuse_sample(&dev, seq, sent_unix_ns, reason);
                    if let (Outcome::Reply(cmd), Some(r)) = (&outcome, &c.watch.recording) {
                        let now = protocol::unix_ns();
                        r.record(&dev, Topic::Command, now, now, encode(cmd));
                        r.event(&dev, "rejected", cmd.error.clone(), 0.0);
                    }
                    outcome
                };
                if let Outcome::Reply(cmd) = outcome {
                    throttled!(warn.rejected, warn, device = %dev, seq, "sample refused: {}", cmd.error);
                    if masks.answers(protocol::shard_of(&dev)) {
                        publish(&session, &core, &dev, &cmd).await;
                    }
                }
            }
            // A put reaches every service: one that does not serve the device lets it pass,
            // uncounted, as it does a request for a device served elsewhere.
            Msg::Reference(dev, _) if !lock(&core).registry.serves(&dev) => {}
            Msg::Reference(dev, _)
                if fleet.as_ref().is_some_and(|f| {
                    !lock(&core)
                        .registry
                        .home_of(&dev)
                        .is_some_and(|h| f.steps(h))
                }) =>
            {
                // Another member's device: a put reaches every member.
            }
            Msg::Reference(dev, bytes) => match decode::<pb::ReferenceUpdate>(&bytes) {
                Ok(u) => {
                    let mut held = lock(&core);
                    let Core {
                        registry, watch, ..
                    } = &mut *held;
                    let reply = registry.set_reference(&dev, &u);
                    if reply.accepted {
                        watch.changed(
                            registry,
                            &dev,
                            Topic::ReferenceUpdate,
                            &bytes,
                            "reference changed",
                        );
                    }
                    if !reply.accepted {
                        throttled!(warn.refused, warn, device = %printable(&dev), "reference refused: {}", reply.reason);
                    }
                }
                Err(e) => {
                    lock(&core).registry.note_undecodable();
                    throttled!(warn.undecodable, warn, device = %printable(&dev), "undecodable reference: {e}");
                }
            },
            Msg::Config(q) => {
                let Some(dev) = served!(q) else { continue };
                change_query!(
                    q,
                    dev,
                    pb::ConfigRequest,
                    "configuration",
                    |registry, watch, req, bytes| {
                        let r = registry.configure(&dev, &req);
                        if r.accepted {
                            throttled!(warn.changed, info, device = %dev, "configuration changed");
                            watch.changed(
                                registry,
                                &dev,
                                Topic::ConfigRequest,
                                &bytes,
                                "configuration changed",
                            );
                        }
                        r
                    }
                );
            }
            Msg::Envelope(q) => {
                let Some(dev) = served!(q) else { continue };
                change_query!(
                    q,
                    dev,
                    pb::EnvelopeRequest,
                    "envelope change",
                    |registry, watch, req, bytes| {
                        let before = registry.envelope_of(&dev);
                        let r = registry.change_envelope(&dev, &req);
                        let after = registry.envelope_of(&dev);
                        let widened = before
                            .iter()
                            .flatten()
                            .zip(after.iter().flatten())
                            .any(|(b, a)| b.is_widened_by(a));
                        if r.accepted {
                            let what = format!(
                                "envelope {} by {}",
                                if widened { "WIDENED" } else { "narrowed" },
                                printable(&req.reason)
                            );
                            watch.changed(registry, &dev, Topic::EnvelopeRequest, &bytes, &what);
                        }
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
                );
            }
            Msg::ReferenceQuery(q) => {
                let Some(dev) = served!(q) else { continue };
                change_query!(
                    q,
                    dev,
                    pb::ReferenceUpdate,
                    "reference",
                    |registry, watch, u, bytes| {
                        let r = registry.set_reference(&dev, &u);
                        if r.accepted {
                            watch.changed(
                                registry,
                                &dev,
                                Topic::ReferenceUpdate,
                                &bytes,
                                "reference changed",
                            );
                        }
                        r
                    }
                );
            }
            Msg::Status(q) => {
                let sharded = q
                    .key_expr()
                    .as_str()
                    .starts_with(&format!("{}/shard/", keys::PREFIX));
                let answers = |registry: &Registry, d: &str| {
                    fleet
                        .as_ref()
                        .is_none_or(|f| registry.home_of(d).is_some_and(|h| f.answers(h)))
                };
                if q.key_expr().as_str().contains('*') {
                    // A wildcard: one reply per device answered here, each on its own key.
                    let replies: Vec<(String, Vec<u8>)> = {
                        let c = lock(&core);
                        let registry = &c.registry;
                        registry
                            .device_ids()
                            .filter(|d| answers(registry, d))
                            .filter_map(|d| {
                                let key = match (sharded, registry.home_of(d)) {
                                    (true, Some(h)) => {
                                        format!("{}/shard/{h}/device/{d}/status", keys::PREFIX)
                                    }
                                    _ => keys::status(d),
                                };
                                let wanted = zenoh::key_expr::KeyExpr::try_from(key.clone())
                                    .is_ok_and(|k| q.key_expr().intersects(&k));
                                wanted
                                    .then(|| registry.device_status(d))
                                    .flatten()
                                    .map(|s| (key, encode(&s)))
                            })
                            .collect()
                    };
                    for (key, bytes) in replies {
                        let _ = q.reply(key, bytes).await;
                    }
                    continue;
                }
                let reply =
                    match keys::device_of(q.key_expr().as_str()) {
                        Some(d) => {
                            let c = lock(&core);
                            if fleet.is_some() && !answers(&c.registry, d) {
                                // Another member's device: its owner answers, the others stay silent.
                                None
                            } else {
                                Some(c.registry.device_status(d).map(|s| encode(&s)).ok_or_else(
                                    || format!("controller {id} does not serve device \"{d}\""),
                                ))
                            }
                        }
                        None => Some(Err("not the key of one device".to_string())),
                    };
                match reply {
                    Some(Ok(bytes)) => {
                        let _ = q.reply(q.key_expr().clone(), bytes).await;
                    }
                    Some(Err(why)) => {
                        let _ = q.reply_err(why).await;
                    }
                    None => {}
                }
            }
            Msg::Member(m, alive) => {
                let Some(fl) = fleet.as_mut() else { continue };
                let actions = if alive { fl.join(&m) } else { fl.leave(&m) };
                if m != id {
                    tracing::info!(controller = %id, member = %m, alive, owned = fl.answer_mask().count_ones(), "fleet member {}", if alive { "joined" } else { "left" });
                }
                fleet_apply!(actions);
            }
            Msg::Handover(q) => {
                let Some(fl) = fleet.as_mut() else {
                    let _ = q.reply_err("not a fleet member").await;
                    continue;
                };
                let shard = keys::last_shard(q.key_expr().as_str());
                let body = payload(&q)
                    .and_then(|b| String::from_utf8(b).ok())
                    .unwrap_or_default();
                let (kind, asker) = body.split_once(':').unwrap_or(("", ""));
                let (Some(shard), true, Ok(asker)) = (
                    shard,
                    kind == "release" || kind == "copy",
                    keys::check_id(asker),
                ) else {
                    lock(&core).registry.note_request_refused();
                    let _ = q
                        .reply_err(
                            "a handover request is release:{id} or copy:{id} on a shard's key",
                        )
                        .await;
                    continue;
                };
                let actions = if kind == "release" {
                    match fl.release(shard, asker) {
                        Release::Granted(a) | Release::NotHeld(a) => a,
                        Release::Refused(why) => {
                            let _ = q.reply_err(why).await;
                            continue;
                        }
                    }
                } else {
                    Vec::new()
                };
                // The role changed before the state is taken, and the answer mask with it,
                // both with the core held (callbacks answer only with it held): every sample
                // answered here is in the state, and none is answered here after it.
                let st = {
                    let c = lock(&core);
                    store_answers!();
                    c.registry.shard_state(shard)
                };
                match crate::snapshot::encode_shard(&st) {
                    Ok(bytes) => {
                        let _ = q.reply(q.key_expr().clone(), bytes).await;
                    }
                    Err(e) => {
                        let _ = q.reply_err(e.to_string()).await;
                    }
                }
                tracing::debug!(controller = %id, shard, to = %asker, kind, devices = st.devices.len(), "handed a shard's state over");
                fleet_apply!(actions);
            }
            Msg::Handed {
                shard,
                release,
                state,
            } => {
                let mut restored = 0;
                match state.as_deref().map(crate::snapshot::decode_shard) {
                    Some(Ok(st)) if st.shard == shard => {
                        if fleet.as_ref().is_some_and(|f| f.steps(shard)) {
                            let mut c = lock(&core);
                            let (ok, refused) = c.registry.restore_shard(&st);
                            let mut ib = lock(&inbox);
                            for d in &st.devices {
                                if c.registry.serves(&d.snapshot.id) {
                                    ib.serve(&d.snapshot.id);
                                }
                            }
                            restored = ok;
                            if refused > 0 {
                                tracing::warn!(
                                    shard,
                                    refused,
                                    "some handed devices were not restored"
                                );
                            }
                        }
                    }
                    Some(Ok(_)) => {
                        tracing::warn!(shard, "a handover reply for another shard: ignored")
                    }
                    Some(Err(e)) => {
                        tracing::warn!(shard, "a handover reply that does not decode: {e}")
                    }
                    None => tracing::warn!(
                        shard,
                        "no state came for the shard: serving it with what this member has"
                    ),
                }
                if let Some(fl) = fleet.as_mut() {
                    if release {
                        fl.acquired(shard);
                    }
                }
                tracing::debug!(controller = %id, shard, release, restored, "took a shard's state");
                fleet_apply!(Vec::new());
            }
            Msg::Owned(shard) => {
                let mut acts = Vec::new();
                if let Some(fl) = fleet.as_mut() {
                    acts = fl.release_expired(shard);
                }
                tracing::debug!(controller = %id, shard, "the shard's new owner has it already: no longer answering it");
                fleet_apply!(acts);
            }
            Msg::Sync(shard, bytes) => {
                // Only a member that steps the shard without answering it takes an owner's
                // update: the owner itself, and members outside the shard, ignore it.
                let follows = fleet
                    .as_ref()
                    .is_some_and(|f| f.steps(shard) && !f.answers(shard));
                if follows {
                    match crate::snapshot::decode_shard(&bytes) {
                        Ok(st) if st.shard == shard => {
                            lock(&core).registry.restore_shard(&st);
                        }
                        _ => lock(&core).registry.note_undecodable(),
                    }
                }
            }
            Msg::ServiceStatus(q) => {
                let s = service_status_now(
                    &lock(&core).registry,
                    started,
                    &inbox,
                    &gateways,
                    &drops,
                    &ha,
                    fleet.as_ref(),
                );
                // On its own key, so that a wildcard query over several services gets one
                // reply from each, each telling which service it is.
                let _ = q.reply(keys::service_status(&id), encode(&s)).await;
            }
        }
    }
    tracing::info!(controller = %id, "shutting down");
    if let Some(sn) = &snapshots {
        if let Err(e) = lock(&core).registry.save_snapshots(&sn.dir) {
            tracing::warn!(dir = %sn.dir.display(), "writing snapshots: {e}");
        }
    }
    drop(token);
    drop(hb_sub);
    drop(hb_pub);
    drop(sub);
    drop(ref_sub);
    drop(gw_sub);
    drop(static_shards);
    drop(static_shard_queries);
    drop(dynamic);
    drop(fleet_decls);
    drop(q_config);
    drop(q_envelope);
    drop(q_reference);
    drop(q_status);
    drop(q_service);
    {
        let mut c = lock(&core);
        c.publishers.clear();
        c.gw_publishers.clear();
    }
    Ok(())
}

/// The worker's status as a `ServiceStatus` query gets it: the registry's, with the drops
/// counted before anything reached the worker and the standby and fleet state.
fn service_status_now(
    registry: &Registry,
    started: Instant,
    inbox: &Mutex<Inbox<pb::Sample>>,
    gateways: &Mutex<Inbox<pb::SampleBatch>>,
    drops: &Drops,
    ha: &HotStandby,
    fleet: Option<&Fleet>,
) -> pb::ServiceStatus {
    let mut s = registry.service_status(started.elapsed().as_secs_f64());
    let (superseded, full) = {
        let ib = lock(inbox);
        (ib.superseded(), ib.full())
    };
    let (superseded_batches, gw_full) = {
        let g = lock(gateways);
        (g.superseded(), g.full())
    };
    let full = full + gw_full;
    s.superseded_batches = superseded_batches;
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
    if let Some(f) = fleet {
        s.devices
            .retain(|d| registry.home_of(&d.device_id).is_some_and(|h| f.answers(h)));
        s.owned_shards = (0..protocol::SHARDS).filter(|&x| f.answers(x)).collect();
        s.fleet_members = f.members().iter().cloned().collect();
    }
    s
}

/// One of the service's locks (the inbox, the unknown ids): a panic elsewhere while it was
/// held leaves plain data behind, still usable, so a poisoned lock is taken as it is.
fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

fn payload(q: &Query) -> Option<Vec<u8>> {
    q.payload().map(|p| p.to_bytes().into_owned())
}

/// The device a request's key names, if this service serves it. Otherwise the error the
/// query is to get (`Some`), or `None` for silence: a key that names no single device (a wildcard, a
/// bad id) is counted as refused; a device served elsewhere is not, since with several
/// services that is every other service's normal answer (the client takes the good reply
/// of the one that serves it).
fn served_device(
    q: &Query,
    registry: &mut Registry,
    controller: &str,
    fleet: Option<&Fleet>,
) -> Result<String, Option<String>> {
    let Some(dev) = keys::device_of(q.key_expr().as_str()).map(str::to_string) else {
        registry.note_request_refused();
        return Err(Some("not the key of one device".into()));
    };
    if let Some(f) = fleet {
        // In a fleet, only the owner answers; the others stay silent, so a client gets
        // exactly one reply and never another member's "does not serve".
        let home = registry
            .home_of(&dev)
            .unwrap_or_else(|| protocol::shard_of(&dev));
        if !f.answers(home) {
            return Err(None);
        }
    }
    if !registry.serves(&dev) {
        return Err(Some(format!(
            "controller {controller} does not serve device \"{dev}\""
        )));
    }
    Ok(dev)
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

/// Answer one gateway batch with one batch: every sample is handled exactly as a lone
/// sample of its device would be (the registry's rules, per device), and every answer goes
/// back in one [`pb::CommandBatch`] on the gateway's command key. The commands are written
/// into `pool`'s, kept from batch to batch, so that answering thousands of samples a period
/// allocates nothing.
/// Returns the gateway and the encoded batch to send, if this worker answers it.
fn step_batch(
    core: &mut Core,
    answers: bool,
    inbox: &Mutex<Inbox<pb::Sample>>,
    taken: Taken<pb::SampleBatch>,
) -> Option<(String, Vec<u8>)> {
    let Core {
        registry,
        watch,
        warn,
        pool,
        ..
    } = core;
    let gw = taken.id;
    let home = protocol::shard_of(&gw);
    let batch = taken.item;
    let mut commands = std::mem::take(pool);
    let mut n = 0;
    let log_ns = protocol::unix_ns();
    // One clock read for the batch: its time is shared by its samples (reading the clock
    // per sample would cost as much as a step).
    let cpu0 = watch.timing().then(thread_cpu);
    let mut answered: Vec<(usize, usize, bool)> = Vec::new();
    for (k, sample) in batch.samples.iter().enumerate() {
        let dev = sample.device_id.as_str();
        if keys::check_id(dev).is_err() {
            // No device to answer: an id that could not even be a key.
            registry.note_bad_id();
            throttled!(warn.rejected, warn, gateway = %gw, device = %printable(dev), "sample in a batch with an invalid device id: dropped");
            continue;
        }
        if commands.len() == n {
            commands.push(pb::Command::default());
        }
        let (served, provisioned) =
            registry.handle_sample_into(dev, sample, Some(home), &mut commands[n]);
        if provisioned && served == Served::Answered {
            tracing::info!(device = %dev, gateway = %gw, "provisioned from a template");
            lock(inbox).serve(dev);
        }
        match served {
            Served::Answered => {
                let cmd = &commands[n];
                if cmd.mode == pb::Mode::Rejected as i32 {
                    throttled!(warn.rejected, warn, device = %dev, seq = cmd.seq, "sample refused: {}", cmd.error);
                }
                if watch.timing() || watch.recording.is_some() {
                    answered.push((k, n, provisioned));
                }
                n += 1;
            }
            Served::Unknown => {
                throttled!(warn.unknown, warn, device = %dev, gateway = %gw, "sample from a device this service does not serve (no template matches): dropped");
            }
            Served::TableFull => {
                throttled!(warn.table_full, warn, device = %dev, "a template matches but the device table is full (max_devices): dropped");
            }
            Served::AlreadyAnswered => {}
        }
    }
    if !answered.is_empty() {
        let cpu = cpu0.map(|c| (thread_cpu() - c) / answered.len() as f64);
        for &(k, i, provisioned) in &answered {
            let (sample, cmd) = (&batch.samples[k], &commands[i]);
            watch.served(
                registry,
                &sample.device_id,
                sample,
                cmd,
                cpu,
                provisioned,
                log_ns,
            );
        }
    }
    // Only the answered ones go out; the spare ones keep their buffers for the next batch.
    let spare = commands.split_off(n);
    let out = pb::CommandBatch {
        version: protocol::PROTOCOL_VERSION,
        gateway_id: gw.clone(),
        commands,
        controller_id: registry.controller_id().to_string(),
    };
    let payload = (answers && n > 0).then(|| encode(&out));
    *pool = out.commands;
    pool.extend(spare);
    payload.map(|p| (gw, p))
}

/// Send a gateway's command batch from the worker's task, declaring its publisher the
/// first time; the core is not held while sending.
async fn publish_batch(session: &Session, core: &Mutex<Core>, gw: String, payload: Vec<u8>) {
    let key = keys::gateway_commands(&gw);
    let known = {
        let c = lock(core);
        c.gw_publishers
            .get(&gw)
            .cloned()
            .ok_or(c.gw_publishers.len() < GATEWAY_PUBLISHERS)
    };
    let publisher = match known {
        Ok(p) => Some(p),
        Err(room) if room => match transport::control_publisher(session, key.clone()).await {
            Ok(p) => Some(
                lock(core)
                    .gw_publishers
                    .entry(gw.clone())
                    .or_insert_with(|| Arc::new(p))
                    .clone(),
            ),
            Err(e) => {
                tracing::error!(gateway = %gw, "{e}");
                None
            }
        },
        Err(_) => None,
    };
    let sent = match publisher {
        Some(p) => p.put(payload).await,
        None => {
            session
                .put(key, payload)
                .congestion_control(zenoh::qos::CongestionControl::Drop)
                .priority(zenoh::qos::Priority::RealTime)
                .express(true)
                .await
        }
    };
    if let Err(e) = sent {
        tracing::warn!(gateway = %gw, "publishing a command batch: {e}");
    }
}

/// Publish a command on a served device's key from the worker's task, declaring its
/// publisher the first time; the core is not held while sending.
async fn publish(session: &Session, core: &Mutex<Core>, dev: &str, cmd: &pb::Command) {
    let known = lock(core).publishers.get(dev).cloned();
    let publisher = match known {
        Some(p) => p,
        None => match transport::control_publisher(session, keys::command(dev)).await {
            Ok(p) => lock(core)
                .publishers
                .entry(dev.to_string())
                .or_insert_with(|| Arc::new(p))
                .clone(),
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

/// The shard subscriptions and queryables of a fleet member, declared as it takes shards
/// and dropped as it gives them up, so that zenoh routes it only its own shards' traffic.
#[derive(Default)]
struct Dynamic {
    subs: HashMap<u32, (Subscriber<()>, Subscriber<()>)>,
    queryables: HashMap<u32, Queryable<()>>,
}

impl Dynamic {
    /// Make the declarations match `fleet`'s masks. A declaration that fails is logged
    /// and retried at the next change.
    async fn sync<S, G, Q, FS, FG, FQ>(
        &mut self,
        session: &Session,
        fleet: &Fleet,
        sample_cb: &FS,
        gateway_cb: &FG,
        query_cb: &FQ,
    ) where
        S: Fn(zenoh::sample::Sample) + Send + Sync + 'static,
        G: Fn(zenoh::sample::Sample) + Send + Sync + 'static,
        Q: Fn(Query) + Send + Sync + 'static,
        FS: Fn() -> S,
        FG: Fn() -> G,
        FQ: Fn() -> Q,
    {
        let (step, answer) = (fleet.step_mask(), fleet.answer_mask());
        self.subs.retain(|s, _| step & (1u64 << s) != 0);
        self.queryables.retain(|s, _| answer & (1u64 << s) != 0);
        for shard in 0..protocol::SHARDS {
            if step & (1u64 << shard) != 0 && !self.subs.contains_key(&shard) {
                let a = session
                    .declare_subscriber(keys::shard_devices(shard, "sample"))
                    .callback(sample_cb())
                    .await;
                let b = session
                    .declare_subscriber(keys::shard_gateways(shard))
                    .callback(gateway_cb())
                    .await;
                match (a, b) {
                    (Ok(a), Ok(b)) => {
                        self.subs.insert(shard, (a, b));
                    }
                    (Err(e), _) | (_, Err(e)) => {
                        tracing::error!(shard, "subscribing to a shard: {e}");
                    }
                }
            }
            if answer & (1u64 << shard) != 0 && !self.queryables.contains_key(&shard) {
                match session
                    .declare_queryable(keys::shard_devices(shard, "*"))
                    .callback(query_cb())
                    .await
                {
                    Ok(q) => {
                        self.queryables.insert(shard, q);
                    }
                    Err(e) => tracing::error!(shard, "declaring a shard's queryable: {e}"),
                }
            }
        }
    }
}

/// Ask member `from` for shard `shard`'s state (a release, or a copy for a standby), on a
/// task of its own; the answer comes back as [`Msg::Handed`]: the state, or none if the
/// member is gone.
///
/// A newcomer answers a shard only once the previous owner has stopped answering it (its
/// reply says so) or has left the fleet (its token is gone: the worker's view then makes
/// the newcomer owner on its own). Neither a refusal (the owner's view has not caught up
/// with this member yet) nor silence (the owner is slow, or its reply was lost) ends the
/// wait while the owner's token is alive: giving up on a timer let a slow owner and the
/// newcomer answer the same samples. Meanwhile the owner keeps answering, so the plants
/// are served. A wait past `timeout` plus the owner's `release_timeout` is logged; the
/// task ends without an answer once the shard is no longer awaited (`masks`).
fn spawn_handover(
    session: Session,
    tx: mpsc::Sender<Msg>,
    (fleet, me): (&str, &str),
    from: String,
    (shard, release): (u32, bool),
    masks: Arc<Masks>,
    (timeout, release_timeout): (Duration, Duration),
) {
    let key = keys::fleet_handover(fleet, &from, shard);
    let member = keys::fleet_member(fleet, &from);
    let body = format!("{}:{me}", if release { "release" } else { "copy" });
    tokio::spawn(async move {
        let started = std::time::Instant::now();
        let mut warned = false;
        let state = loop {
            let mut got = None;
            if let Ok(replies) = session
                .get(key.clone())
                .payload(body.clone())
                .timeout(timeout)
                .await
            {
                while let Ok(r) = replies.recv_async().await {
                    if let Ok(s) = r.result() {
                        got = Some(s.payload().to_bytes().into_owned());
                        break;
                    }
                }
            }
            if got.is_some() || !member_alive(&session, &member, timeout).await {
                break got;
            }
            // The view moved on (another member took the shard, or this one no longer
            // follows it): nobody waits for this answer any more.
            let wanted = if release {
                masks.acquiring(shard)
            } else {
                masks.steps(shard) && !masks.answers(shard)
            };
            if !wanted {
                return;
            }
            if !warned && started.elapsed() > timeout + release_timeout {
                warned = true;
                tracing::warn!(shard, owner = %from, "the shard's owner is alive but has not handed it over yet: still asking (it keeps answering meanwhile)");
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        };
        let _ = tx
            .send(Msg::Handed {
                shard,
                release,
                state,
            })
            .await;
    });
}

/// Whether a fleet member's liveliness token (`member`, its key) is still seen.
async fn member_alive(session: &Session, member: &str, timeout: Duration) -> bool {
    match session.liveliness().get(member).timeout(timeout).await {
        Ok(replies) => replies.recv_async().await.is_ok_and(|r| r.result().is_ok()),
        // The query could not even be sent: do not conclude the owner is gone.
        Err(_) => true,
    }
}

/// Offer a shard to the member that now outranks this one ([`Action::Offer`]); if it owns
/// the shard already, [`Msg::Owned`] comes back.
fn spawn_offer(
    session: Session,
    tx: mpsc::Sender<Msg>,
    key: String,
    body: String,
    shard: u32,
    timeout: Duration,
) {
    tokio::spawn(async move {
        let Ok(replies) = session.get(key).payload(body).timeout(timeout).await else {
            return;
        };
        while let Ok(r) = replies.recv_async().await {
            if r.result()
                .is_ok_and(|s| s.payload().to_bytes().as_ref() == b"owned")
            {
                let _ = tx.send(Msg::Owned(shard)).await;
                return;
            }
        }
    });
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

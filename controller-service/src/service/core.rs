//! What answering a sample needs, shared by the worker's task and zenoh's callbacks: the
//! registry, the observers, the command publishers ([`Core`]), and the inboxes and masks
//! the callbacks read without waiting ([`Shared`]).

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use protocol::{encode, encode_command_batch, keys, pb, printable, SampleBatchView};
use tokio::sync::Notify;
use zenoh::pubsub::Publisher;
use zenoh::{Session, Wait};

use super::drops::Drops;
use super::keyring::{sealed, Keyring};
use super::locks::lock;
use super::log::{throttled, Warnings};
use crate::inbox::{Inbox, Parts, Taken};
use crate::observe::{thread_cpu, DeviceHistograms, Observers, ServiceMetrics};
use crate::registry::{Registry, Served, Slot, Via};
use telemetry::{Recording, Topic};

/// Which shards this member steps and answers, read by zenoh's callbacks (bit `s` for
/// shard `s`); all of them without a fleet.
#[derive(Debug)]
pub(super) struct Masks {
    step: AtomicU64,
    /// The shards whose samples are answered (all or none without a fleet: whether this
    /// member is active). Written only with the [`Core`] held, and read with it held by
    /// whoever answers, so that a handover's state and the answers agree (see
    /// `Worker::handle_handover`).
    answer: AtomicU64,
}

impl Masks {
    pub(super) fn new(step: u64, answer: u64) -> Self {
        Self {
            step: AtomicU64::new(step),
            answer: AtomicU64::new(answer),
        }
    }

    pub(super) fn steps(&self, shard: u32) -> bool {
        self.step.load(Ordering::Relaxed) & (1u64 << (shard % 64)) != 0
    }

    pub(super) fn answers(&self, shard: u32) -> bool {
        self.answer.load(Ordering::Relaxed) & (1u64 << (shard % 64)) != 0
    }

    /// Store new masks; call it with the [`Core`] held (the `_held` guard says so).
    pub(super) fn store(&self, _held: &Core, step: u64, answer: u64) {
        self.step.store(step, Ordering::Relaxed);
        self.answer.store(answer, Ordering::Relaxed);
    }
}

/// What the worker and zenoh's callbacks share. Lock order: the core, then an inbox.
pub(super) struct Shared {
    pub(super) core: Mutex<Core>,
    /// Samples waiting for the worker: the latest per device.
    pub(super) inbox: Mutex<Inbox<pb::Sample>>,
    /// Gateway batches waiting for the worker: the unread ones of each gateway (up to a
    /// period's worth: a complete batch, or parts), their samples still encoded (the worker
    /// decodes them one at a time, [`Core::serve_batch`]).
    pub(super) gateways: Mutex<Inbox<Parts<SampleBatchView>>>,
    pub(super) masks: Masks,
    /// Drops counted in the callbacks, before the worker sees anything.
    pub(super) drops: Drops,
    /// Wakes the worker when a sample or a batch waits.
    pub(super) wake: Notify,
    /// The fleet's keys (`None`: the service runs open).
    pub(super) keys: Option<Arc<Keyring>>,
    /// Other processes seen carrying this service's controller id, by instance
    /// ([`super::routes::Twins`]).
    pub(super) twins: Mutex<std::collections::BTreeSet<u64>>,
}

/// Positions of gateways' batches whose device slots are remembered, in all: 8 MiB at
/// most, whatever gateways send (a thousand gateways of a thousand plants).
const KEPT_SLOTS: usize = 1 << 20;

/// Gateways with a publisher of their own; commands to any beyond go through the session
/// (same options, one declaration less), so the table is bounded whatever arrives.
const GATEWAY_PUBLISHERS: usize = 1024;

/// What the answer to a sample needs: the device state, its observers and the publishers
/// of its commands. Shared by the worker's task and zenoh's callbacks: a callback that
/// finds the core free and nothing queued answers its sample at once, on its own thread,
/// as the echo anchor does; otherwise the sample is queued for the worker. Waking the
/// worker's task costs a thread switch per sample (about 20 us on the reference machine,
/// and much more in the tail when the other core is busy), which was most of what the
/// service cost beyond the anchor. The callbacks only ever `try_lock` it, so they never
/// wait for the worker; the worker never holds it across an `.await`.
pub(super) struct Core {
    pub(super) registry: Registry,
    pub(super) watch: Watch,
    /// Throttles for what is logged while answering (the worker keeps its own for the rest).
    pub(super) warn: Warnings,
    /// One publisher per served device, made at its first command: bounded by the file's
    /// `max_devices`, never by what arrives. Shared out, so the worker can publish with
    /// the core released.
    publishers: HashMap<String, Arc<Publisher<'static>>>,
    /// The same for gateways' command batches (at most [`GATEWAY_PUBLISHERS`]).
    gw_publishers: HashMap<String, Arc<Publisher<'static>>>,
    /// The commands of the last batch, kept with their buffers for the next one.
    pool: Vec<pb::Command>,
    /// The samples of the last batch, decoded, kept with their buffers for the next one:
    /// a batch's samples are decoded into these, and allocate nothing once they are as
    /// many and as long as the batch's.
    samples: Vec<pb::Sample>,
    /// Whether each answer of a batch is sent, kept for the next batch.
    sends: Vec<bool>,
    /// Which of a batch's samples decoded with a valid device id, kept for the next batch.
    good: Vec<usize>,
    /// Per gateway, where each position of its last batch found its device in the
    /// registry ([`Registry::handle_sample_at`]): a gateway names the same plants in the
    /// same order every period (the agent's batcher sends them in the order it hosts
    /// them), so its next batch finds them without a lookup. At most
    /// [`GATEWAY_PUBLISHERS`] gateways and [`KEPT_SLOTS`] positions in all; when a
    /// gateway finds them full, every gateway's are forgotten, and each is kept again
    /// at its next batch.
    slots: HashMap<String, Vec<Option<Slot>>>,
    /// Positions in `slots`.
    slots_kept: usize,
    /// The fleet's keys, to seal commands (`None`: open).
    keys: Option<Arc<Keyring>>,
    /// Who may change what, and the audit trail every decision goes to.
    pub(super) gate: super::gate::Gate,
}

impl Core {
    pub(super) fn new(
        registry: Registry,
        watch: Watch,
        keys: Option<Arc<Keyring>>,
        gate: super::gate::Gate,
    ) -> Self {
        Self {
            keys,
            gate,
            registry,
            watch,
            warn: Warnings::default(),
            publishers: HashMap::new(),
            gw_publishers: HashMap::new(),
            pool: Vec::new(),
            samples: Vec::new(),
            sends: Vec::new(),
            good: Vec::new(),
            slots: HashMap::new(),
            slots_kept: 0,
        }
    }

    /// Step one sample of its device; the command to send, if this worker answers it.
    pub(super) fn serve_sample(
        &mut self,
        answers: bool,
        inbox: &Mutex<Inbox<pb::Sample>>,
        taken: Taken<pb::Sample>,
    ) -> Option<pb::Command> {
        let dev = taken.id.as_str();
        let sample = taken.item;
        let log_ns = protocol::unix_ns();
        let cpu0 = self.watch.timing().then(thread_cpu);
        // Every member follows every sample (a standby stays warm); only the active one
        // answers.
        let mut cmd = pb::Command::default();
        let via = Via::key(dev).preferred(answers);
        let served = self.registry.handle_sample(via, &sample, log_ns, &mut cmd);
        let cpu = cpu0.map(|c| thread_cpu() - c);
        if taken.superseded > 0 {
            self.registry.note_superseded(dev, taken.superseded);
        }
        let provisioned = self.note_served(dev, None, served, &cmd);
        if !served.answered() {
            return None;
        }
        if provisioned {
            lock(inbox).serve(dev);
        }
        self.watch
            .served(&self.registry, dev, &sample, &cmd, cpu, provisioned, log_ns);
        matches!(served, Served::Answered { send: true, .. }).then_some(cmd)
    }

    /// Log what the registry did with a sample of `dev` (from gateway `gw`, if any), as a
    /// warning throttled by kind; whether it provisioned its device.
    fn note_served(
        &mut self,
        dev: &str,
        gw: Option<&str>,
        served: Served,
        cmd: &pb::Command,
    ) -> bool {
        let warn = &mut self.warn;
        match (served, gw) {
            (Served::Answered { provisioned, .. }, _) => {
                match (provisioned, gw) {
                    (true, Some(gw)) => {
                        tracing::info!(device = %dev, gateway = %gw, "provisioned from a template");
                    }
                    (true, None) => tracing::info!(device = %dev, "provisioned from a template"),
                    (false, _) => {}
                }
                if cmd.mode == pb::Mode::Rejected as i32 {
                    throttled!(warn.rejected, warn, device = %dev, seq = cmd.seq, "sample refused: {}", cmd.error);
                }
                return provisioned;
            }
            (Served::Unknown, Some(gw)) => {
                throttled!(warn.unknown, warn, device = %dev, gateway = %gw, "sample from a device this service does not serve (no template matches): dropped");
            }
            (Served::Unknown, None) => {
                throttled!(warn.unknown, warn, device = %dev, "sample from a device this service does not serve (no template matches): dropped");
            }
            (Served::TableFull, _) => {
                throttled!(warn.table_full, warn, device = %dev, "a template matches but the device table is full (max_devices): dropped");
            }
            // Answered before a restore or by the member that handed it over: once is enough.
            (Served::AlreadyAnswered, _) => {}
        }
        false
    }

    /// Answer one gateway batch with one batch: every sample is handled exactly as a lone
    /// sample of its device would be (the registry's rules, per device), and every answer
    /// goes back in one [`pb::CommandBatch`] on the gateway's command key. The commands
    /// are written into the pool's, and the samples decoded into the samples', both kept
    /// from batch to batch, so that answering thousands of samples a period allocates
    /// nothing. A sample that does not decode is dropped (counted as undecodable), the
    /// others answered. Returns the encoded batch to send to gateway `gw`, if this worker
    /// answers it.
    pub(super) fn serve_batch(
        &mut self,
        answers: bool,
        (inbox, drops): (&Mutex<Inbox<pb::Sample>>, &Drops),
        gw: &str,
        batch: SampleBatchView,
    ) -> Option<Vec<u8>> {
        let home = protocol::shard_of(gw);
        let mut samples = std::mem::take(&mut self.samples);
        let mut commands = std::mem::take(&mut self.pool);
        let mut sends = std::mem::take(&mut self.sends);
        let mut good = std::mem::take(&mut self.good);
        self.read_batch(gw, &batch, &mut samples, &mut good, drops);
        let mut slots = self.slots.remove(gw).unwrap_or_default();
        self.slots_kept -= slots.len();
        // This batch's positions: `samples` keeps the longest batch's buffers.
        slots.resize(batch.samples.len(), None);
        let mut n = 0;
        // One clock read for the batch: its time is shared by its samples (reading the
        // clock per sample would cost as much as a step).
        let log_ns = protocol::unix_ns();
        let cpu0 = self.watch.timing().then(thread_cpu);
        let mut answered: Vec<(usize, usize, bool)> = Vec::new();
        for (j, &k) in good.iter().enumerate() {
            if let Some(&next) = good.get(j + 1) {
                // The next sample's device comes from memory while this one is stepped:
                // with thousands of devices, each one's state is a cache miss otherwise.
                self.registry
                    .prefetch_at(&mut slots[next], &samples[next].device_id);
            }
            let sample = &samples[k];
            let dev = sample.device_id.as_str();
            if commands.len() == n {
                commands.push(pb::Command::default());
            }
            let via = Via::gateway(dev, home).preferred(answers);
            let served = self.registry.handle_sample_at(
                &mut slots[k],
                via,
                sample,
                log_ns,
                &mut commands[n],
            );
            let provisioned = self.note_served(dev, Some(gw), served, &commands[n]);
            if provisioned {
                lock(inbox).serve(dev);
            }
            if let Served::Answered { send, .. } = served {
                if self.watch.timing() || self.watch.recording.is_some() {
                    answered.push((k, n, provisioned));
                }
                sends.push(send);
                n += 1;
            }
        }
        if !answered.is_empty() {
            let cpu = cpu0.map(|c| (thread_cpu() - c) / answered.len() as f64);
            for &(k, i, provisioned) in &answered {
                let (sample, cmd) = (&samples[k], &commands[i]);
                let dev = &sample.device_id;
                self.watch
                    .served(&self.registry, dev, sample, cmd, cpu, provisioned, log_ns);
            }
        }
        // Only the answers this member sends go out, in the batch's order (the plant's
        // lease decides, per device); the others keep their buffers for the next batch.
        let mut sent = 0;
        for (i, &send) in sends.iter().enumerate().take(n) {
            if send {
                // A swap in place still copies the command (a few hundred bytes) twice.
                if sent != i {
                    commands.swap(sent, i);
                }
                sent += 1;
            }
        }
        sends.clear();
        self.sends = sends;
        self.good = good;
        self.keep_slots(gw, slots);
        let spare = commands.split_off(sent);
        let out = pb::CommandBatch {
            version: protocol::PROTOCOL_VERSION,
            gateway_id: gw.to_string(),
            commands,
            controller_id: self.registry.controller_id().to_string(),
            mac: Vec::new(),
        };
        let payload = (sent > 0).then(|| {
            sealed(self.keys.as_deref(), encode_command_batch(&out), |k, b| {
                k.seal_batch(gw, b)
            })
        });
        self.pool = out.commands;
        self.pool.extend(spare);
        keep_small(&mut samples, &batch.samples);
        self.samples = samples;
        payload
    }

    /// Keep where `gw`'s batch found its devices, for its next batch, within the bounds:
    /// when they are full, every gateway's are forgotten first (gateways that stopped
    /// sending would otherwise hold the room for good), and each is kept again at its
    /// next batch, which looks its devices up meanwhile.
    fn keep_slots(&mut self, gw: &str, slots: Vec<Option<Slot>>) {
        if !slots.iter().any(Option::is_some) {
            return;
        }
        if self.slots.len() >= GATEWAY_PUBLISHERS || self.slots_kept + slots.len() > KEPT_SLOTS {
            self.slots.clear();
            self.slots_kept = 0;
        }
        self.slots_kept += slots.len();
        self.slots.insert(gw.to_string(), slots);
    }

    /// Decode a batch's samples into `samples` (kept from batch to batch) and list in
    /// `good` those that decoded with a valid device id; any other is counted and dropped
    /// alone. All of them first, so that the serving pass knows each sample's next one.
    fn read_batch(
        &mut self,
        gw: &str,
        batch: &SampleBatchView,
        samples: &mut Vec<pb::Sample>,
        good: &mut Vec<usize>,
        drops: &Drops,
    ) {
        good.clear();
        for (k, raw) in batch.samples.iter().enumerate() {
            if samples.len() == k {
                samples.push(pb::Sample::default());
            }
            let sample = &mut samples[k];
            if let Err(e) = SampleBatchView::read_sample(raw, sample) {
                Drops::count(&drops.undecodable);
                let warn = &mut self.warn;
                throttled!(warn.rejected, warn, gateway = %gw, "sample in a batch that does not decode: dropped ({e})");
                continue;
            }
            let dev = sample.device_id.as_str();
            if keys::check_id(dev).is_err() {
                // No device to answer: an id that could not even be a key.
                self.registry.note_bad_id();
                let warn = &mut self.warn;
                throttled!(warn.rejected, warn, gateway = %gw, device = %printable(dev), "sample in a batch with an invalid device id: dropped");
                continue;
            }
            good.push(k);
        }
    }

    /// Publish `cmd` from one of zenoh's callbacks (a blocking put there is zenoh's own
    /// way, never in async code), declaring the device's publisher the first time.
    pub(super) fn publish_now(&mut self, session: &Session, dev: &str, cmd: &pb::Command) {
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
            let bytes = sealed(self.keys.as_deref(), encode(cmd), |k, b| {
                k.seal_command(dev, b)
            });
            if let Err(e) = p.put(bytes).wait() {
                tracing::warn!(device = %dev, "publishing a command: {e}");
            }
        }
    }

    /// Drop the publishers (at the end: they are declarations too).
    pub(super) fn undeclare_publishers(&mut self) {
        self.publishers.clear();
        self.gw_publishers.clear();
    }

    /// A device's state is gone from here: its histograms go with it.
    pub(super) fn forget(&mut self, dev: &str) {
        if self.watch.histograms.remove(dev).flatten().is_some() {
            if let Some(m) = &self.watch.metrics {
                m.forget(dev);
            }
        }
    }
}

/// Publish a command on a served device's key from the worker's task, declaring its
/// publisher the first time; the core is not held while sending.
pub(super) async fn publish(session: &Session, core: &Mutex<Core>, dev: &str, cmd: &pb::Command) {
    let (known, keys) = {
        let c = lock(core);
        (c.publishers.get(dev).cloned(), c.keys.clone())
    };
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
    let bytes = sealed(keys.as_deref(), encode(cmd), |k, b| k.seal_command(dev, b));
    if let Err(e) = publisher.put(bytes).await {
        tracing::warn!(device = %dev, "publishing a command: {e}");
    }
}

/// Send a gateway's command batch from the worker's task, declaring its publisher the
/// first time (up to [`GATEWAY_PUBLISHERS`]; beyond, through the session); the core is
/// not held while sending.
pub(super) async fn publish_batch(
    session: &Session,
    core: &Mutex<Core>,
    gw: String,
    payload: Vec<u8>,
) {
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

/// Largest encoded sample whose decoded buffers [`Core::serve_batch`] keeps for the next
/// batch (bytes): a sample of 16 channels carrying 3 earlier samples is about 1 KiB. The
/// samples kept are as many as the longest batch (at most `MAX_BATCH_SAMPLES`), so without
/// this a gateway sending one huge sample at each position in turn would leave each holding
/// a batch's worth of capacity, gigabytes in all.
const KEPT_SAMPLE_BYTES: usize = 2048;

/// Give back the buffers of every sample of `samples` decoded from one of `raw` longer
/// than [`KEPT_SAMPLE_BYTES`]; the others keep theirs.
fn keep_small(samples: &mut [pb::Sample], raw: &[protocol::Bytes]) {
    for (s, r) in samples.iter_mut().zip(raw) {
        if r.len() > KEPT_SAMPLE_BYTES {
            *s = pb::Sample::default();
        }
    }
}

/// What a worker feeds its observers, and the histogram handles of its devices (one entry
/// per device it served: bounded by its device table).
pub(super) struct Watch {
    pub(super) controller: String,
    pub(super) recording: Option<Recording>,
    pub(super) metrics: Option<Arc<ServiceMetrics>>,
    pub(super) histograms: HashMap<String, Option<DeviceHistograms>>,
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
            let rtt = (sample.last_rtt_us > 0).then(|| f64::from(sample.last_rtt_us) * 1e-6);
            m.served(rtt, cpu);
            // With the service-wide series only, no lookup per sample.
            if m.per_device_series() {
                if !self.histograms.contains_key(dev) {
                    let h = m.device(&self.controller, dev);
                    self.histograms.insert(dev.to_string(), h);
                }
                if let Some(Some(h)) = self.histograms.get(dev) {
                    if let Some(r) = rtt {
                        h.rtt.record(r);
                    }
                    if let Some(c) = cpu {
                        h.cpu.record(c);
                    }
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

    /// Record a refusal the worker answered (a sample refused by the callback's precheck).
    pub(super) fn refused(&self, dev: &str, cmd: &pb::Command) {
        if let Some(r) = &self.recording {
            let now = protocol::unix_ns();
            r.record(dev, Topic::Command, now, now, encode(cmd));
            r.event(dev, "rejected", cmd.error.clone(), 0.0);
        }
    }

    /// Record an accepted change: the request as it came, the configuration it left, and
    /// an event saying who changed what.
    pub(super) fn changed(
        &self,
        registry: &Registry,
        dev: &str,
        topic: Topic,
        request: &[u8],
        what: &str,
    ) {
        if let Some(r) = &self.recording {
            let now = protocol::unix_ns();
            r.record(dev, topic, now, now, request.to_vec());
            record_config(r, registry, dev, what);
        }
    }
}

/// The device's configuration in force, and an event saying why it is recorded.
impl Watch {
    /// What `registry`'s worker feeds `observers`; a recording starts with every device's
    /// configuration.
    pub(super) fn of(registry: &Registry, observers: &Observers) -> Self {
        let watch = Self {
            controller: registry.controller_id().to_string(),
            recording: observers.recording.clone(),
            metrics: observers.metrics.clone(),
            histograms: HashMap::new(),
        };
        if let Some(r) = &watch.recording {
            for d in registry.device_ids() {
                record_config(r, registry, d, "recording starts");
            }
        }
        watch
    }
}

pub(super) fn record_config(r: &Recording, registry: &Registry, dev: &str, why: &str) {
    if let Some(c) = registry.config_of(dev) {
        let now = protocol::unix_ns();
        r.record(dev, Topic::Config, now, now, encode(&c));
    }
    let t = registry.device_status(dev).map_or(0.0, |s| s.plant_time);
    r.event(dev, "config", why, t);
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A sample decoded from a long encoding gives its buffers back; a short one keeps
    /// them, and so do kept samples the batch did not reach.
    #[test]
    fn only_samples_of_ordinary_size_keep_their_buffers() {
        let short = pb::Sample {
            outputs: vec![1.0; 4],
            ..Default::default()
        };
        let long = pb::Sample {
            outputs: vec![1.0; 1000],
            ..Default::default()
        };
        let raw: Vec<protocol::Bytes> = [&short, &long]
            .iter()
            .map(|s| protocol::Bytes::from(encode(*s)))
            .collect();
        assert!(raw[0].len() <= KEPT_SAMPLE_BYTES && raw[1].len() > KEPT_SAMPLE_BYTES);
        let mut kept = vec![short.clone(), long, short.clone()];
        keep_small(&mut kept, &raw);
        assert_eq!(kept[0].outputs.capacity(), 4);
        assert_eq!(
            kept[1].outputs.capacity(),
            0,
            "the long one gave its buffer back"
        );
        assert_eq!(kept[2], short, "beyond the batch: untouched");
    }
}

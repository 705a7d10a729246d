//! The generator: N simulated plants at a fixed rate against whatever answers on the
//! network (the service, or the echo anchor).
//!
//! Each plant is a first-order lag (`tau dy/dt = -y + v`), one channel, stepped once per
//! period: a few nanoseconds, so the generator's cost is the messages, as a real fleet's
//! would be. Plants send at evenly spread offsets of the period (real machines are not
//! phase-locked): with gateways, each gateway sends the samples of all its plants at its
//! own offset, in one [`pb::SampleBatch`].
//!
//! A sample counts as *answered* when the first command with its `seq` arrives, and as
//! *within the period* when that happens less than one period after it was sent. A second
//! command for a `seq` already answered is counted as a duplicate: with several service
//! instances, that is the "answered twice" the ownership rules must prevent. Only samples
//! sent in the measurement window (after the warm-up) are counted, except duplicates,
//! which are counted over the whole run.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use protocol::auth::{Key, Kind};
use protocol::{decode, encode, keys, pb, PROTOCOL_VERSION};
use serde::Serialize;
use zenoh::{Session, Wait};

use crate::stats::Histogram;

/// What to generate.
#[derive(Debug, Clone)]
pub struct Spec {
    /// Number of simulated plants (devices `{prefix}-0` ... `{prefix}-{N-1}`).
    pub devices: usize,
    /// Samples per device per second.
    pub rate_hz: f64,
    /// 0: every device sends on its own key; otherwise this many gateways
    /// (`{prefix}-gw-{g}`) share the devices evenly and send one batch per period each.
    pub gateways: usize,
    /// Prefix of the ids.
    pub prefix: String,
    /// Time before counting starts (templates provision, estimator windows fill).
    pub warmup: Duration,
    /// Time counted.
    pub measure: Duration,
    /// Earlier samples each sample carries again, as an agent's `resend` (0 to
    /// [`protocol::RESENT_SAMPLES`]): what a real agent's samples weigh. The copies hold the
    /// plant's current values at the earlier times (no sample is lost on loopback, so
    /// only their size matters).
    pub resend: usize,
    /// The fleet's secret, for a target that has it (`protocol::auth`): samples and
    /// batches go out sealed with the device's or gateway's key, and only commands sealed
    /// with it count as answers. `None`: open (the echo anchor's way).
    pub secret: Option<protocol::auth::Secret>,
}

/// What came back. Times are round trips measured on this process's clock (sample sent to
/// command received), in microseconds.
#[derive(Debug, Clone, Default, Serialize)]
pub struct LoadReport {
    pub devices: usize,
    pub gateways: usize,
    pub rate_hz: f64,
    /// Samples sent in the measurement window.
    pub sent: u64,
    /// Of those, answered at all (first answer).
    pub answered: u64,
    /// Of those, answered within one period.
    pub within: u64,
    /// Of those, answered with MODE_CONTROL (the rest: warming up, rejected, stale).
    pub control: u64,
    /// Second answers to a `seq` already answered, over the whole run.
    pub duplicates: u64,
    /// Longest run of consecutive samples of one device left unanswered inside the window
    /// (periods): how long a plant would have held its command or run its fallback.
    pub max_gap: u64,
    /// Sends that left more than one period after their due time: the generator itself
    /// could not keep up, and the run says little about the target.
    pub generator_late: u64,
    pub p50_us: Option<f64>,
    pub p90_us: Option<f64>,
    pub p99_us: Option<f64>,
    pub p999_us: Option<f64>,
    pub max_us: u64,
}

impl LoadReport {
    /// Fraction of the window's samples answered at all.
    pub fn answered_fraction(&self) -> f64 {
        frac(self.answered, self.sent)
    }
    /// Fraction of the window's samples answered within one period.
    pub fn within_fraction(&self) -> f64 {
        frac(self.within, self.sent)
    }
}

fn frac(a: u64, b: u64) -> f64 {
    if b == 0 {
        0.0
    } else {
        a as f64 / b as f64
    }
}

/// Why a run could not be made.
#[derive(Debug, thiserror::Error)]
pub enum GenError {
    #[error("zenoh: {0}")]
    Zenoh(String),
    #[error("no controller appeared on the network within {0:?}")]
    NoTarget(Duration),
    #[error("bad spec: {0}")]
    Spec(String),
}

fn zerr(e: impl std::fmt::Display) -> GenError {
    GenError::Zenoh(e.to_string())
}

/// Per-device receive state: the last command's volts and which seqs were answered.
struct Rx {
    v: Vec<f64>,
    /// Highest seq answered per device, and a bit per seq of the 64 below and at it.
    last: Vec<u64>,
    mask: Vec<u64>,
}

struct Shared {
    rx: Mutex<Rx>,
    prefix: String,
    devices: usize,
    period_ns: u64,
    /// Window of seqs counted: [first, end).
    first: u64,
    end: u64,
    hist: Histogram,
    answered: AtomicU64,
    within: AtomicU64,
    control: AtomicU64,
    duplicates: AtomicU64,
    max_gap: AtomicU64,
}

impl Shared {
    fn index(&self, id: &str) -> Option<usize> {
        let i: usize = id
            .strip_prefix(self.prefix.as_str())?
            .strip_prefix('-')?
            .parse()
            .ok()?;
        (i < self.devices).then_some(i)
    }

    /// Take one command (any path); `now` in Unix ns.
    fn take(&self, rx: &mut Rx, c: &pb::Command, now: u64) {
        let Some(i) = self.index(&c.device_id) else {
            return;
        };
        let (last, mask) = (&mut rx.last[i], &mut rx.mask[i]);
        let first_answer = if c.seq > *last {
            let shift = c.seq - *last;
            // A gap inside the window: the samples between were not answered (yet; a late
            // answer still counts as answered, not as closing the gap).
            if *last >= self.first && c.seq < self.end {
                self.max_gap.fetch_max(shift - 1, Ordering::Relaxed);
            }
            *mask = if shift >= 64 { 0 } else { *mask << shift } | 1;
            *last = c.seq;
            true
        } else if *last - c.seq < 64 {
            let bit = 1u64 << (*last - c.seq);
            let fresh = *mask & bit == 0;
            *mask |= bit;
            fresh
        } else {
            false // too old to tell: not counted either way
        };
        if !first_answer {
            if *last - c.seq < 64 {
                self.duplicates.fetch_add(1, Ordering::Relaxed);
            }
            return;
        }
        if c.mode == pb::Mode::Control as i32 {
            if let Some(&v) = c.v.first() {
                if v.is_finite() {
                    rx.v[i] = v;
                }
            }
        }
        if c.seq < self.first || c.seq >= self.end {
            return;
        }
        let rtt_ns = now.saturating_sub(c.sample_sent_unix_ns);
        self.hist.record(rtt_ns / 1000);
        self.answered.fetch_add(1, Ordering::Relaxed);
        if rtt_ns < self.period_ns {
            self.within.fetch_add(1, Ordering::Relaxed);
        }
        if c.mode == pb::Mode::Control as i32 {
            self.control.fetch_add(1, Ordering::Relaxed);
        }
    }
}

fn lock(m: &Mutex<Rx>) -> std::sync::MutexGuard<'_, Rx> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// Plant time constant (s).
const TAU: f64 = 0.5;

/// Run the generator on `session` (already connected to the target) and report.
pub async fn run(session: &Session, spec: &Spec) -> Result<LoadReport, GenError> {
    check(spec)?;
    let wait = Duration::from_secs(20);
    if !transport::wait_for_token(session, &keys::alive_controller("*"), wait).await {
        return Err(GenError::NoTarget(wait));
    }
    let period = Duration::from_secs_f64(1.0 / spec.rate_hz);
    let first = (spec.warmup.as_secs_f64() * spec.rate_hz).ceil() as u64 + 1;
    let end = first + (spec.measure.as_secs_f64() * spec.rate_hz).ceil() as u64;
    let shared = Arc::new(Shared {
        rx: Mutex::new(Rx {
            v: vec![0.0; spec.devices],
            last: vec![0; spec.devices],
            mask: vec![0; spec.devices],
        }),
        prefix: spec.prefix.clone(),
        devices: spec.devices,
        period_ns: period.as_nanos() as u64,
        first,
        end,
        hist: Histogram::new(),
        answered: AtomicU64::new(0),
        within: AtomicU64::new(0),
        control: AtomicU64::new(0),
        duplicates: AtomicU64::new(0),
        max_gap: AtomicU64::new(0),
    });
    let sub = subscribe_commands(session, &shared, spec).await?;
    let publishers = publishers(session, spec).await?;
    let late = Arc::new(AtomicU64::new(0));
    let stop = Arc::new(AtomicBool::new(false));
    let thread = {
        let (shared, late, stop, spec) = (shared.clone(), late.clone(), stop.clone(), spec.clone());
        std::thread::Builder::new()
            .name("loadgen-send".into())
            .spawn(move || send_loop(&spec, &shared, &publishers, period, end, &late, &stop))
            .map_err(|e| GenError::Zenoh(format!("starting the sender thread: {e}")))?
    };
    // The sender runs on its own thread (blocking puts, its own pacing); wait for it here
    // without blocking the runtime.
    while !thread.is_finished() {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    stop.store(true, Ordering::Relaxed);
    let _ = thread.join();
    // Late answers of the window's last samples.
    tokio::time::sleep(Duration::from_millis(300)).await;
    drop(sub);
    let sh = &shared;
    Ok(LoadReport {
        devices: spec.devices,
        gateways: spec.gateways,
        rate_hz: spec.rate_hz,
        sent: (end - first) * spec.devices as u64,
        answered: sh.answered.load(Ordering::Relaxed),
        within: sh.within.load(Ordering::Relaxed),
        control: sh.control.load(Ordering::Relaxed),
        duplicates: sh.duplicates.load(Ordering::Relaxed),
        max_gap: sh.max_gap.load(Ordering::Relaxed),
        generator_late: late.load(Ordering::Relaxed),
        p50_us: sh.hist.quantile(0.5),
        p90_us: sh.hist.quantile(0.9),
        p99_us: sh.hist.quantile(0.99),
        p999_us: sh.hist.quantile(0.999),
        max_us: sh.hist.max(),
    })
}

/// Refuse a spec the generator cannot run, saying why.
fn check(spec: &Spec) -> Result<(), GenError> {
    if spec.devices == 0 || !(spec.rate_hz > 0.0 && spec.rate_hz <= 10_000.0) {
        return Err(GenError::Spec(
            "devices must be > 0 and rate_hz in (0, 10000]".into(),
        ));
    }
    if spec.gateways > 0 && spec.devices.div_ceil(spec.gateways) > protocol::MAX_BATCH_SAMPLES {
        return Err(GenError::Spec(format!(
            "{} devices over {} gateways exceed {} per batch",
            spec.devices,
            spec.gateways,
            protocol::MAX_BATCH_SAMPLES
        )));
    }
    if spec.resend > protocol::RESENT_SAMPLES {
        return Err(GenError::Spec(format!(
            "resend is at most {}, got {}",
            protocol::RESENT_SAMPLES,
            spec.resend
        )));
    }
    keys::check_id(&format!("{}-gw-{}", spec.prefix, spec.devices))
        .map_err(|e| GenError::Spec(e.to_string()))?;
    Ok(())
}

/// The keys of every sender (device, or gateway), by id, when the spec has a secret.
fn sender_keys(spec: &Spec) -> HashMap<String, Key> {
    let Some(secret) = &spec.secret else {
        return HashMap::new();
    };
    if spec.gateways == 0 {
        (0..spec.devices)
            .map(|i| format!("{}-{i}", spec.prefix))
            .map(|id| (id.clone(), secret.device(&id)))
            .collect()
    } else {
        (0..spec.gateways)
            .map(|g| format!("{}-gw-{g}", spec.prefix))
            .map(|id| (id.clone(), secret.gateway(&id)))
            .collect()
    }
}

/// The body of a command (batch) that came on `key` for sender `id`: checked with its
/// key when the spec has keys (a bad MAC is no answer), as it is otherwise.
fn opened<'a>(
    keys: &HashMap<String, Key>,
    kind: Kind,
    id: Option<&str>,
    bytes: &'a [u8],
) -> Option<&'a [u8]> {
    if keys.is_empty() {
        return Some(bytes);
    }
    keys.get(id?)?.open(kind, bytes).ok()
}

/// Take every command (or, through gateways, every command batch) into `shared`.
async fn subscribe_commands(
    session: &Session,
    shared: &Arc<Shared>,
    spec: &Spec,
) -> Result<zenoh::pubsub::Subscriber<()>, GenError> {
    let sh = shared.clone();
    let sealers = sender_keys(spec);
    if spec.gateways == 0 {
        return session
            .declare_subscriber(keys::all_devices("command"))
            .callback(move |s| {
                let now = protocol::unix_ns();
                let bytes = s.payload().to_bytes();
                let id = keys::device_of(s.key_expr().as_str());
                let Some(body) = opened(&sealers, Kind::Command, id, &bytes) else {
                    return;
                };
                if let Ok(c) = decode::<pb::Command>(body) {
                    sh.take(&mut lock(&sh.rx), &c, now);
                }
            })
            .await
            .map_err(zerr);
    }
    session
        .declare_subscriber(keys::all_gateways("commands"))
        .callback(move |s| {
            let now = protocol::unix_ns();
            let bytes = s.payload().to_bytes();
            let id = keys::gateway_of(s.key_expr().as_str());
            let Some(body) = opened(&sealers, Kind::CommandBatch, id, &bytes) else {
                return;
            };
            if let Ok(b) = decode::<pb::CommandBatch>(body) {
                let mut rx = lock(&sh.rx);
                for c in &b.commands {
                    sh.take(&mut rx, c, now);
                }
            }
        })
        .await
        .map_err(zerr)
}

/// One publisher per sending key: per device, or per gateway.
async fn publishers(
    session: &Session,
    spec: &Spec,
) -> Result<Vec<zenoh::pubsub::Publisher<'static>>, GenError> {
    let senders: Vec<String> = if spec.gateways == 0 {
        (0..spec.devices)
            .map(|i| keys::shard_sample(&format!("{}-{i}", spec.prefix)))
            .collect()
    } else {
        (0..spec.gateways)
            .map(|g| keys::shard_gateway_samples(&format!("{}-gw-{g}", spec.prefix)))
            .collect()
    };
    let mut publishers = Vec::with_capacity(senders.len());
    for k in senders {
        publishers.push(
            transport::control_publisher(session, k)
                .await
                .map_err(zerr)?,
        );
    }
    Ok(publishers)
}

/// The pacing loop: period `k` = 1, 2, ... up to `end` (exclusive); within a period,
/// sender `j` of `S` at offset `j / S` of the period. Sleeps, never spins: on two cores a
/// spinning generator would take a core from what it measures.
fn send_loop(
    spec: &Spec,
    shared: &Shared,
    publishers: &[zenoh::pubsub::Publisher<'static>],
    period: Duration,
    end: u64,
    late: &AtomicU64,
    stop: &AtomicBool,
) {
    let run_id = protocol::unix_ns() | 1;
    let dt = period.as_secs_f64();
    let resend = spec.resend;
    let n = spec.devices;
    let senders = publishers.len();
    let ids: Vec<String> = (0..n).map(|i| format!("{}-{i}", spec.prefix)).collect();
    let sealers = sender_keys(spec);
    let mut y = vec![0.0f64; n];
    let mut applied = vec![0.0f64; n];
    let start = Instant::now() + Duration::from_millis(10);
    for k in 1..end {
        for (j, publisher) in publishers.iter().enumerate() {
            if stop.load(Ordering::Relaxed) {
                return;
            }
            let due = start + period.mul_f64((k - 1) as f64 + j as f64 / senders as f64);
            let now = Instant::now();
            if due > now {
                std::thread::sleep(due - now);
            } else if now - due > period {
                late.fetch_add(1, Ordering::Relaxed);
            }
            // The devices this sender carries.
            let range = if spec.gateways == 0 {
                j..j + 1
            } else {
                let per = n.div_ceil(senders);
                (j * per).min(n)..((j + 1) * per).min(n)
            };
            {
                let rx = lock(&shared.rx);
                for i in range.clone() {
                    applied[i] = rx.v[i];
                }
            }
            let sample = |i: usize, y: &mut [f64]| {
                y[i] += dt / TAU * (applied[i] - y[i]);
                pb::Sample {
                    version: PROTOCOL_VERSION,
                    device_id: ids[i].clone(),
                    seq: k,
                    plant_time: k as f64 * dt,
                    outputs: vec![y[i]],
                    applied: vec![applied[i]],
                    flags: 0,
                    sent_unix_ns: protocol::unix_ns(),
                    last_rtt_us: 0,
                    run_id,
                    previous_plant_time: (1..=resend).map(|j| (k as f64 - j as f64) * dt).collect(),
                    previous_outputs: vec![y[i]; resend],
                    previous_applied: vec![applied[i]; resend],
                    // A load without leases: the service answers as the fleet's owner.
                    ..Default::default()
                }
            };
            let (payload, kind, sender) = if spec.gateways == 0 {
                (encode(&sample(j, &mut y)), Kind::Sample, ids[j].clone())
            } else {
                let batch = pb::SampleBatch {
                    version: PROTOCOL_VERSION,
                    gateway_id: format!("{}-gw-{j}", spec.prefix),
                    // Every plant each period: complete, as a gateway's batch on time.
                    plants: u32::try_from(range.len()).unwrap_or(u32::MAX),
                    samples: range.map(|i| sample(i, &mut y)).collect(),
                    mac: Vec::new(),
                };
                (encode(&batch), Kind::SampleBatch, batch.gateway_id)
            };
            let payload = match sealers.get(&sender) {
                Some(k) => k.seal(kind, payload),
                None => payload,
            };
            let _ = publisher.put(payload).wait();
        }
    }
}

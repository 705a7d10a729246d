//! Per-device control state and the rules for answering samples. No I/O, no clock, no
//! logging: the Zenoh wiring in [`crate::service`] feeds it decoded messages, publishes what
//! it returns and decides what to log, so every rule here is tested without a network.
//!
//! A sample of device `d` is checked completely before anything about `d` changes (the
//! rules, in order, are written for clients in the `.proto`, on `Sample`):
//! 1. `d` must be served: declared, or provisioned from the first matching template while
//!    the device table has room; otherwise it is counted and not answered (no publisher,
//!    no state: a flood of unknown keys costs a counter);
//! 2. its `device_id` must equal the key's, and its values must be usable (one finite
//!    output per channel, finite applied values, finite plant time): else `REJECTED`;
//! 3. a new `run_id` starts a new run (fresh control state); a late sample of one of the
//!    last few runs, arriving within the new run's first [`REORDER_WINDOW`] samples, is
//!    `STALE` (later, that run is taken to be back, so one stray sample can never lock the
//!    real plant out); a plant that sends no `run_id` is recognised as restarted when its
//!    sequence goes back far, or to 0 or 1;
//! 4. within a run: the last sequence again is a duplicate (the cached command again, or
//!    nothing if it was answered before a restore or by the member that handed the device
//!    over: [`Outcome::AlreadyAnswered`]);
//!    older is `STALE`; a forward jump of more than [`MAX_SEQ_JUMP`] is `REJECTED`; plant
//!    time must advance (else `REJECTED`). After [`RESYNC_AFTER`] such refusals in a row
//!    that form a consistent stream of their own, the device follows that stream as a new
//!    run: no value of `seq` or of plant time can lock a device out for longer;
//! 5. the step's inputs (time, outputs, the references at that time) are checked against
//!    the controllers (a fresh one for a new run): else `REJECTED`. Only now does the
//!    device change: a new run starts, the numbers skipped count as lost, what the plant
//!    applied is reported, and the controllers step;
//! 6. the command is checked against the device's envelope a last time: a non-finite value
//!    is never sent (`REJECTED`); one outside `[min, max]`, or further than the rate limit
//!    allows from what the actuator holds, is clipped and counted (`clamped`). The rate
//!    limit runs from the last command when the plant applied it, otherwise from what the
//!    sample says the plant applies, or the last command sent, or rest; over at most two
//!    periods of plant time (the lower median of recent intervals), so a leap of plant
//!    time cannot open it.

use smallvec::SmallVec;
use std::collections::{BTreeSet, HashMap, VecDeque};

use mfc::trajectory::{evaluate, Piece};
use mfc::{ChannelConfig, ChannelOutput, MimoController, Reference};
use protocol::convert::{
    apply_update, channel_from_pb, channel_to_pb, reference_from_pb, reference_to_pb,
};
use protocol::{pb, printable, MAX_HORIZON, PROTOCOL_VERSION};

use crate::config::{DeviceChannel, Prediction, ServiceConfig};
use crate::envelope::Limits;

/// A gap longer than this (s) between a snapshot and the next sample makes the restored
/// estimators start a fresh window.
const RESUME_GAP: f64 = 0.1;
/// Most recent round trips kept per device for the status percentiles; older ones drop out.
const RTT_WINDOW: usize = 1000;
/// Unknown device ids listed in the status; samples from further unknown ids are still
/// counted, just not named.
const UNKNOWN_KEPT: usize = 64;
/// Largest forward jump of `seq` within a run. An hour's outage at 100 Hz skips 360 000;
/// anything larger is garbage or hostile, and accepting it would make every later sample
/// of the real plant look stale.
pub const MAX_SEQ_JUMP: u64 = 1_000_000;
/// How far back (samples) a sequence may go and still be a late sample of the same run,
/// for plants that send no `run_id`; further back is taken for a restart.
pub const REORDER_WINDOW: u64 = 64;
/// Longest reason stored or sent back (bytes): reasons quote values from the network.
const MAX_REASON: usize = 240;
/// Consecutive samples of the run in force that the device refused as out of step (older
/// than the last answered one, past a sequence jump, or with a plant time that does not
/// advance) while forming a consistent stream of their own (sequence and time increasing)
/// before the device follows that stream as a new run. Whatever put the device ahead of
/// the plant (a jump of `seq` inside [`MAX_SEQ_JUMP`], a glitch of the plant's clock, a
/// forged sample), the real plant is locked out for at most this many samples.
pub const RESYNC_AFTER: u32 = 64;
/// Sample intervals kept per device to estimate its period (their lower median, so that
/// leaps in fewer than five of the last eight intervals do not move it).
const PERIOD_WINDOW: usize = 8;
/// Intervals needed before the estimate counts.
const PERIOD_MIN_INTERVALS: usize = 3;
/// The rate limit allows a step of `rate * dt` with `dt` at most this many estimated
/// periods: plant time comes from the network, and a leap of it must not open the limit.
const RATE_DT_PERIODS: f64 = 2.0;
/// ... and at most this long (s) while no period is known yet (a device's first three
/// intervals).
const RATE_DT_UNKNOWN: f64 = 1.0;

/// A reason cut to [`MAX_REASON`] bytes (on a character boundary), so that no input can
/// make what the service stores, sends or logs large.
fn capped(mut reason: String) -> String {
    if reason.len() > MAX_REASON {
        let mut end = MAX_REASON;
        while !reason.is_char_boundary(end) {
            end -= 1;
        }
        reason.truncate(end);
        reason.push_str("...");
    }
    reason
}

/// Run ids remembered after their run ended, so a late sample of one is STALE instead of
/// starting that run again.
const RETIRED_RUNS: usize = 4;

/// Round-trip reports the delay compensation takes its median over: the most recent ones,
/// so that it follows a link whose delay changes.
const DELAY_WINDOW: usize = 32;

/// Per-channel values kept inline in a device's state: a plant has one or two channels (the
/// AERO has two), and a value that lives beside the rest of the device costs no pointer
/// chase, where a separate allocation per field costs a cache miss per sample once
/// thousands of devices no longer fit the caches (`docs/scale.md`). More channels spill to
/// the heap and work the same.
type PerChannel<T> = SmallVec<[T; 2]>;

/// The last CONTROL or WARMING_UP answer, kept to send again verbatim for a duplicate: the
/// values of the command without its ids (the device's key and the controller's own),
/// inline rather than a whole [`pb::Command`] with five allocations of its own.
#[derive(Debug, Clone)]
struct Answer {
    seq: u64,
    mode: i32,
    controller_unix_ns: u64,
    sample_sent_unix_ns: u64,
    u: PerChannel<f64>,
    v: PerChannel<f64>,
    f_est: PerChannel<f64>,
    /// The packetized horizon (empty without prediction), as [`pb::Command::horizon`].
    horizon: Vec<f64>,
    /// `y*` per channel at the sample's time, as [`pb::Command::reference`].
    reference: PerChannel<f64>,
}

impl Answer {
    /// Write this answer into `out`, reusing its buffers: a batch's commands are kept
    /// from one batch to the next, so answering allocates nothing.
    fn write_into(&self, controller_id: &str, device_id: &str, out: &mut pb::Command) {
        out.version = PROTOCOL_VERSION;
        out.device_id.clear();
        out.device_id.push_str(device_id);
        out.seq = self.seq;
        out.u.clear();
        out.u.extend_from_slice(&self.u);
        out.v.clear();
        out.v.extend_from_slice(&self.v);
        out.controller_unix_ns = self.controller_unix_ns;
        out.f_est.clear();
        out.f_est.extend_from_slice(&self.f_est);
        out.horizon.clear();
        out.horizon.extend_from_slice(&self.horizon);
        out.reference.clear();
        out.reference.extend_from_slice(&self.reference);
        out.mode = self.mode;
        out.sample_sent_unix_ns = self.sample_sent_unix_ns;
        out.controller_id.clear();
        out.controller_id.push_str(controller_id);
        out.error.clear();
    }
}

/// How a sample was answered, inside the registry.
// The command is the common case and is moved out at once: boxing it would cost an
// allocation per answer to save stack space nobody holds.
#[allow(clippy::large_enum_variant)]
enum Answered {
    /// With the device's cached answer (`last_command`): a new one, or the same again for
    /// a duplicate.
    Cached,
    /// With this command (a refusal, a stale answer).
    Reply(pb::Command),
    /// Not at all ([`Outcome::AlreadyAnswered`]).
    Not,
}

/// What [`Registry::handle_sample_into`] did with a sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Served {
    /// The command to publish is in `out`.
    Answered,
    /// As [`Outcome::Unknown`].
    Unknown,
    /// As [`Outcome::TableFull`].
    TableFull,
    /// As [`Outcome::AlreadyAnswered`]: nothing in `out`.
    AlreadyAnswered,
}

/// A device's id as the device table's key. Ids of up to [`INLINE_ID`] bytes (`aero-1`,
/// `load-1234`) live inside the table's own slot, so that finding a device among thousands
/// reads the table and nothing else: with the id behind a pointer, every lookup missed the
/// caches once more for the comparison. Longer ids are kept on the heap and work the same.
#[derive(Debug, Clone)]
enum DeviceKey {
    Inline { len: u8, bytes: [u8; INLINE_ID] },
    Heap(Box<str>),
}

/// Bytes of an id kept inline in [`DeviceKey`]: the key is then 24 bytes, as a `String`.
const INLINE_ID: usize = 22;

impl DeviceKey {
    fn new(id: &str) -> Self {
        if id.len() <= INLINE_ID {
            let mut bytes = [0; INLINE_ID];
            bytes[..id.len()].copy_from_slice(id.as_bytes());
            Self::Inline {
                len: id.len() as u8,
                bytes,
            }
        } else {
            Self::Heap(id.into())
        }
    }

    fn as_str(&self) -> &str {
        match self {
            // Whole bytes of a `&str`: always UTF-8, so never the empty fallback.
            Self::Inline { len, bytes } => {
                std::str::from_utf8(&bytes[..*len as usize]).unwrap_or("")
            }
            Self::Heap(s) => s,
        }
    }
}

impl std::borrow::Borrow<str> for DeviceKey {
    fn borrow(&self) -> &str {
        self.as_str()
    }
}

// Hash and equality are the id's, as `Borrow<str>` requires.
impl std::hash::Hash for DeviceKey {
    fn hash<H: std::hash::Hasher>(&self, state: &mut H) {
        self.as_str().hash(state);
    }
}

impl PartialEq for DeviceKey {
    fn eq(&self, other: &Self) -> bool {
        self.as_str() == other.as_str()
    }
}

impl Eq for DeviceKey {}

/// What to do with a sample.
#[derive(Debug, Clone, PartialEq)]
// As `Answered`: a reply is the common case, boxing it would allocate per answer.
#[allow(clippy::large_enum_variant)]
pub enum Outcome {
    /// Publish this command on the device's command key: a new answer, the cached one again
    /// for a duplicate, or a refusal (`REJECTED`/`STALE`, with the reason in `error`).
    Reply(pb::Command),
    /// Not a device this service serves, and no template provisions it: nothing to publish
    /// (counted in `unknown_samples`).
    Unknown,
    /// A template matches but the device table is full: nothing to publish (counted in
    /// `device_table_full`).
    TableFull,
    /// A sample answered before this state was restored (by this service before a
    /// restart, or by the fleet member that handed the device over): its answer went out
    /// then, so nothing is published again (counted in `duplicates`). Answering it, even
    /// STALE, would make two answers to one sample, from two instances in a handover.
    AlreadyAnswered,
}

/// How a sample relates to the run in force.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Run {
    Same,
    New,
    /// A late sample of a run that already ended.
    Retired,
}

/// What the service holds for one device: its control state, where the plant's run stands,
/// and the counters of its status.
#[derive(Debug, Clone)]
struct Device {
    /// The shard the device lives in ([`crate::fleet`]): its id's, or its gateway's if its
    /// samples come in a gateway's batches.
    home: u32,
    /// Restored from a snapshot and not yet resumed: the first sample decides whether the
    /// data history still holds (no gap) or must be forgotten.
    restored: bool,
    /// Provisioned from a template, not declared: reported in the status, and lets a
    /// snapshot rebuild the device although no declaration names it.
    from_template: bool,
    /// The safety envelope per channel. Every output map in `configs` lies inside it.
    envelope: PerChannel<Limits>,
    /// Laws and output maps in force (changed by `configure`); a snapshot of a declared
    /// device is restored only if its laws equal these.
    configs: Vec<ChannelConfig>,
    mimo: MimoController,
    /// Reference pieces per channel, evaluated at `plant_time - reference_start`.
    reference: PerChannel<Vec<Piece>>,
    /// Plant time (s) at which the reference starts: 0 from the file, moved by a live
    /// reference update.
    reference_start: f64,
    /// The plant run this state belongs to (`None` before the first sample).
    run_id: Option<u64>,
    /// Runs that ended, newest last, at most `RETIRED_RUNS`.
    retired: VecDeque<u64>,
    /// Samples received since the run in force started, refused ones included: a sample of
    /// a retired run is late only while this is below `REORDER_WINDOW`.
    run_samples: u64,
    /// Sequence number of the last sample answered with control values; refused samples do
    /// not move it.
    last_seq: Option<u64>,
    /// Plant time of that sample (s); the next must come strictly later. Minus infinity
    /// until the first one (and after a plant restart), so any first time is accepted.
    last_time: f64,
    /// The command answering `last_seq`, sent again verbatim for a duplicate. `None` after a
    /// restart or a restore.
    last_command: Option<Answer>,
    /// The samples refused as out of step since the last answered one, if they form a
    /// consistent stream: its last sequence and time, and how many ([`RESYNC_AFTER`]).
    astray: Option<(u64, f64, u32)>,
    /// Recent intervals between consecutive samples (s), for the period estimate that
    /// bounds the rate limit's `dt`; kept across runs (the same rig, the same period).
    intervals: [f64; PERIOD_WINDOW],
    /// How many of `intervals` are filled, and where the next goes.
    intervals_len: usize,
    intervals_next: usize,
    /// The values of the last CONTROL command sent, kept across runs (the same actuator):
    /// where the rate limit runs from when a sample does not say what is applied.
    held: Option<PerChannel<f64>>,
    /// Each step's outputs per channel, a buffer reused from sample to sample.
    outputs: PerChannel<ChannelOutput>,
    /// The references per channel at the current sample, likewise reused.
    refs: PerChannel<Reference>,
    /// Samples for this device, counted before any check.
    samples: u64,
    /// Commands computed (CONTROL or WARMING_UP); not resends for duplicates, not REJECTED
    /// or STALE answers.
    commands: u64,
    /// Sequence numbers skipped between one answered sample and the next; a sample that
    /// arrived but was refused in between counts here too.
    lost: u64,
    /// Samples repeating `last_seq`, answered with the cached command when there is one.
    duplicates: u64,
    /// Samples older than `last_seq`, or of an ended run: answered STALE.
    stale: u64,
    /// Samples answered REJECTED: another device's id, bad values, a sequence jump, or a
    /// step the core refused.
    rejected: u64,
    /// Samples replaced by a newer one before the worker read them (reported by the
    /// service's inbox).
    superseded: u64,
    /// Samples sent while the plant was holding, on its local fallback or in safe stop:
    /// counts samples, not fallback episodes.
    samples_off_remote: u64,
    /// Envelope changes accepted since the service started.
    envelope_changes: u64,
    /// Commands the final envelope check clipped: 0 unless a law or map misbehaves, or a
    /// rate-limited channel starts (a run, a restore) where the law's first value is not
    /// within reach of what the actuator holds.
    clamped: u64,
    /// Reference updates refused.
    references_refused: u64,
    /// Runs started (the first sample's included).
    restarts: u64,
    /// The plant's round-trip reports (µs), oldest first, at most `RTT_WINDOW`; a report of
    /// 0 (no round trip yet) is not kept.
    rtts: VecDeque<u32>,
    /// The last F estimate per channel; NaN until a step gives one.
    f_est: PerChannel<f64>,
    /// Why the last refused sample or request was refused (already cut to printable
    /// length); a later good one does not clear it.
    last_error: String,
    /// Horizon and delay compensation of its commands (from the file).
    prediction: Prediction,
    /// Lost samples recovered from the copy the next one carried.
    recovered: u64,
    /// The last sample's flags (what its plant was doing), for the status.
    last_flags: u32,
    /// With delay compensation: what the plant will apply in each coming period, as this
    /// device's commands already sent will have it.
    schedule: Option<Box<Schedule>>,
}

/// What the plant will apply in each period, as far as the commands already sent decide
/// it: a ring over the coming periods (absolute sequence numbers), `n` channels each. The
/// delay compensation drives its prediction with these until its own command lands.
#[derive(Debug, Clone)]
struct Schedule {
    n: usize,
    /// The period each slot holds (`u64::MAX`: none).
    period: Vec<u64>,
    values: Vec<f64>,
}

impl Schedule {
    const SLOTS: usize = MAX_HORIZON as usize + 1;

    fn new(n: usize) -> Self {
        Self {
            n,
            period: vec![u64::MAX; Self::SLOTS],
            values: vec![0.0; Self::SLOTS * n],
        }
    }

    fn get(&self, k: u64, i: usize) -> Option<f64> {
        let slot = (k % Self::SLOTS as u64) as usize;
        (self.period[slot] == k).then(|| self.values[slot * self.n + i])
    }

    fn set(&mut self, k: u64, values: impl Iterator<Item = f64>) {
        let slot = (k % Self::SLOTS as u64) as usize;
        self.period[slot] = k;
        for (x, v) in self.values[slot * self.n..(slot + 1) * self.n]
            .iter_mut()
            .zip(values)
        {
            *x = v;
        }
    }
}

impl Device {
    fn new(
        channels: &[DeviceChannel],
        prediction: Prediction,
        from_template: bool,
    ) -> Result<Self, String> {
        let envelope: PerChannel<Limits> = channels.iter().map(DeviceChannel::limits).collect();
        // The file's check already did this; a configuration built in code must not get
        // past it either (a NaN limit would make the last check meaningless).
        for (i, e) in envelope.iter().enumerate() {
            e.check()
                .map_err(|r| format!("channels[{i}].envelope: {r}"))?;
        }
        let configs = channels
            .iter()
            .zip(&envelope)
            .enumerate()
            .map(|(i, (c, e))| {
                Ok(ChannelConfig {
                    law: c.law,
                    output: e.fit_request(c.output, &format!("channels[{i}].output"))?,
                })
            })
            .collect::<Result<Vec<_>, String>>()?;
        let n = configs.len();
        Ok(Self {
            home: 0,
            restored: false,
            from_template,
            envelope,
            mimo: MimoController::new(&configs).map_err(|e| e.to_string())?,
            configs,
            reference: channels.iter().map(|c| c.reference.clone()).collect(),
            reference_start: 0.0,
            run_id: None,
            retired: VecDeque::with_capacity(RETIRED_RUNS),
            run_samples: 0,
            last_seq: None,
            last_time: f64::NEG_INFINITY,
            last_command: None,
            astray: None,
            held: None,
            intervals: [0.0; PERIOD_WINDOW],
            intervals_len: 0,
            intervals_next: 0,
            outputs: smallvec::smallvec![ChannelOutput::default(); n],
            refs: smallvec::smallvec![Reference::default(); n],
            samples: 0,
            commands: 0,
            lost: 0,
            duplicates: 0,
            stale: 0,
            rejected: 0,
            superseded: 0,
            samples_off_remote: 0,
            envelope_changes: 0,
            clamped: 0,
            references_refused: 0,
            restarts: 0,
            rtts: VecDeque::with_capacity(RTT_WINDOW),
            f_est: smallvec::smallvec![f64::NAN; n],
            last_error: String::new(),
            prediction,
            recovered: 0,
            last_flags: 0,
            schedule: prediction
                .delay_compensation
                .then(|| Box::new(Schedule::new(n))),
        })
    }

    /// A new plant run: fresh control state, same configuration and reference. The
    /// counters carry on across runs.
    fn start_run(&mut self, run_id: u64, fresh: MimoController) {
        if let Some(old) = self.run_id {
            if old != run_id {
                if self.retired.len() == RETIRED_RUNS {
                    self.retired.pop_front();
                }
                self.retired.push_back(old);
            }
        }
        self.retired.retain(|r| *r != run_id);
        self.mimo = fresh;
        self.run_id = Some(run_id);
        self.run_samples = 0;
        self.restored = false;
        self.last_seq = None;
        self.last_time = f64::NEG_INFINITY;
        self.last_command = None;
        self.astray = None;
        self.restarts += 1;
        if let Some(s) = &mut self.schedule {
            **s = Schedule::new(s.n);
        }
    }

    /// The sample period: the lower median of the recent intervals; `None` before
    /// [`PERIOD_MIN_INTERVALS`] of them.
    fn period(&self) -> Option<f64> {
        let n = self.intervals_len;
        if n < PERIOD_MIN_INTERVALS {
            return None;
        }
        let mut v = self.intervals;
        let v = &mut v[..n];
        v.sort_unstable_by(f64::total_cmp);
        Some(v[(n - 1) / 2])
    }

    /// Note the interval between two consecutive accepted samples (positive: time must
    /// advance; finite, or it is not an interval anyone can use).
    fn note_interval(&mut self, dt: f64) {
        if !(dt.is_finite() && dt > 0.0) {
            return;
        }
        self.intervals[self.intervals_next] = dt;
        self.intervals_next = (self.intervals_next + 1) % PERIOD_WINDOW;
        self.intervals_len = (self.intervals_len + 1).min(PERIOD_WINDOW);
    }

    /// Count a sample of the run in force refused as out of step; true once
    /// [`RESYNC_AFTER`] of them in a row form a stream of their own, which the device then
    /// follows as a new run.
    fn out_of_step(&mut self, s: &pb::Sample) -> bool {
        let n = match self.astray {
            Some((seq, t, n)) if s.seq > seq && s.plant_time > t => n + 1,
            _ => 1,
        };
        self.astray = Some((s.seq, s.plant_time, n));
        n >= RESYNC_AFTER
    }

    fn channels(&self) -> usize {
        self.configs.len()
    }

    /// Rule 2, the part that depends on the device: how many values.
    fn check_values(&self, s: &pb::Sample) -> Result<(), String> {
        let n = self.channels();
        if s.outputs.len() != n {
            return Err(format!("expected {n} outputs, got {}", s.outputs.len()));
        }
        if !s.applied.is_empty() && s.applied.len() != n {
            return Err(format!(
                "expected {n} applied values (or none), got {}",
                s.applied.len()
            ));
        }
        Ok(())
    }

    /// Rule 3.
    fn run_of(&self, s: &pb::Sample) -> Run {
        match (self.run_id, self.last_seq) {
            (None, _) => Run::New,
            (Some(r), _) if s.run_id != r => {
                if self.retired.contains(&s.run_id) && self.run_samples < REORDER_WINDOW {
                    Run::Retired
                } else {
                    Run::New
                }
            }
            // No run id from this plant: guess a restart from the sequence going back to
            // a fresh start, or further back than any reordering and with an earlier time.
            (Some(0), Some(last))
                if s.seq < last
                    && (s.seq <= 1
                        || (last - s.seq > REORDER_WINDOW && s.plant_time < self.last_time)) =>
            {
                Run::New
            }
            _ => Run::Same,
        }
    }

    fn limits_pb(&self) -> pb::Envelope {
        pb::Envelope {
            channels: self
                .envelope
                .iter()
                .map(|l| pb::ChannelLimits {
                    min: l.min.is_finite().then_some(l.min),
                    max: l.max.is_finite().then_some(l.max),
                    rate_limit: l.rate_limit,
                })
                .collect(),
        }
    }

    fn config_pb(&self, id: &str) -> pb::DeviceConfig {
        pb::DeviceConfig {
            version: PROTOCOL_VERSION,
            device_id: id.into(),
            channels: self.configs.iter().map(channel_to_pb).collect(),
            reference: Some(reference_to_pb(&self.reference, self.reference_start)),
            envelope: Some(self.limits_pb()),
        }
    }

    fn status_pb(&self, id: &str) -> pb::DeviceStatus {
        pb::DeviceStatus {
            version: PROTOCOL_VERSION,
            device_id: id.into(),
            last_seq: self.last_seq.unwrap_or(0),
            plant_time: if self.last_time.is_finite() {
                self.last_time
            } else {
                0.0
            },
            samples: self.samples,
            commands: self.commands,
            lost: self.lost,
            duplicates: self.duplicates,
            stale: self.stale,
            rejected: self.rejected,
            samples_off_remote: self.samples_off_remote,
            loop_rtt: Some(latency(&self.rtts)),
            f_est: self.f_est.to_vec(),
            last_error: self.last_error.clone(),
            from_template: self.from_template,
            superseded: self.superseded,
            envelope: Some(self.limits_pb()),
            envelope_changes: self.envelope_changes,
            clamped: self.clamped,
            references_refused: self.references_refused,
            restarts: self.restarts,
            recovered: self.recovered,
            last_flags: self.last_flags,
        }
    }

    /// The laws and maps a configuration request asks for, checked against the envelope,
    /// and its reference; nothing changes here (the caller applies it all or nothing).
    #[allow(clippy::type_complexity)]
    fn plan(
        &self,
        req: &pb::ConfigRequest,
    ) -> Result<(Vec<ChannelConfig>, Option<(Vec<Vec<Piece>>, f64)>), String> {
        let n = self.channels();
        let mut configs = self.configs.clone();
        if !req.channels.is_empty() {
            if req.channels.len() != n {
                return Err(format!(
                    "device has {n} channels, request has {}",
                    req.channels.len()
                ));
            }
            for (i, c) in req.channels.iter().enumerate() {
                let field = format!("channels[{i}]");
                let cfg =
                    channel_from_pb(c).map_err(|e| format!("{field}.{}: {}", e.field, e.reason))?;
                // No output map in the request: keep the one in force (a client that sends
                // only laws must not drop the limits).
                let output = match c.output {
                    None => configs[i].output,
                    Some(_) => {
                        self.envelope[i].fit_request(cfg.output, &format!("{field}.output"))?
                    }
                };
                configs[i] = ChannelConfig {
                    law: cfg.law,
                    output,
                };
            }
        }
        for (k, u) in req.updates.iter().enumerate() {
            let i = u.channel as usize;
            if i >= n {
                return Err(format!(
                    "updates[{k}].channel: {} but the device has {n} channels",
                    u.channel
                ));
            }
            let next = apply_update(&configs[i], u)
                .map_err(|e| format!("updates[{k}].{}: {}", e.field, e.reason))?;
            let output = self.envelope[i].fit_request(next.output, &format!("updates[{k}]"))?;
            configs[i] = ChannelConfig {
                law: next.law,
                output,
            };
        }
        let reference = match &req.reference {
            None => None,
            Some(r) => match reference_from_pb(r) {
                Ok((pieces, _)) if pieces.len() != n => {
                    return Err(format!(
                        "device has {n} channels, reference has {}",
                        pieces.len()
                    ))
                }
                Ok(r) => Some(r),
                Err(e) => return Err(format!("reference.{}: {}", e.field, e.reason)),
            },
        };
        Ok((configs, reference))
    }
}

/// Median, 99th percentile and maximum of round trips (µs), nearest rank on the sorted
/// window; all zero (count 0) for an empty window.
pub fn latency(rtts: &VecDeque<u32>) -> pb::LatencyStats {
    if rtts.is_empty() {
        return pb::LatencyStats::default();
    }
    let mut v: Vec<u32> = rtts.iter().copied().collect();
    v.sort_unstable();
    let pick = |q: f64| f64::from(v[((v.len() - 1) as f64 * q).round() as usize]);
    pb::LatencyStats {
        count: v.len() as u32,
        p50_us: pick(0.5),
        p99_us: pick(0.99),
        max_us: f64::from(*v.last().unwrap_or(&0)),
    }
}

/// The checks of rule 2 that need no state: the sample's `device_id` is the key's, and
/// every value is finite. The service runs them in Zenoh's callback, before a sample may
/// take its device's place in the inbox (so garbage cannot supersede a real sample), and
/// [`Registry::handle_sample`] runs them again. The reason is cut to printable length.
pub fn precheck(key_id: &str, s: &pb::Sample) -> Result<(), String> {
    if s.device_id != key_id {
        return Err(format!(
            "device id \"{}\" in a sample on the key of \"{key_id}\"",
            printable(&s.device_id)
        ));
    }
    if let Some(bad) = s.outputs.iter().chain(&s.applied).find(|v| !v.is_finite()) {
        return Err(format!("non-finite value {bad:?}"));
    }
    if !s.plant_time.is_finite() {
        return Err(format!("non-finite plant time {:?}", s.plant_time));
    }
    Ok(())
}

/// A command without control values (refusals and stale answers) for the sample `seq`
/// sent at `sent_unix_ns`.
fn reply(
    controller_id: &str,
    id: &str,
    (seq, sent_unix_ns): (u64, u64),
    mode: pb::Mode,
    error: String,
) -> pb::Command {
    pb::Command {
        version: PROTOCOL_VERSION,
        device_id: id.into(),
        seq,
        controller_unix_ns: protocol::unix_ns(),
        mode: mode as i32,
        sample_sent_unix_ns: sent_unix_ns,
        controller_id: controller_id.into(),
        error,
        ..Default::default()
    }
}

fn refused(reason: String, config: Option<pb::DeviceConfig>) -> pb::ConfigReply {
    pb::ConfigReply {
        version: PROTOCOL_VERSION,
        accepted: false,
        reason,
        config,
    }
}

/// The reply to a request on device `d` (`id`): the configuration in force afterwards,
/// and for a refusal the reason, also kept as the device's last error and counted.
fn conclude(
    d: &mut Device,
    requests_refused: &mut u64,
    id: &str,
    applied: Result<(), String>,
) -> pb::ConfigReply {
    match applied {
        Ok(()) => pb::ConfigReply {
            version: PROTOCOL_VERSION,
            accepted: true,
            reason: String::new(),
            config: Some(d.config_pb(id)),
        },
        Err(reason) => {
            let reason = capped(reason);
            *requests_refused += 1;
            d.last_error.clone_from(&reason);
            refused(reason, Some(d.config_pb(id)))
        }
    }
}

/// Wire limits to core, checked; `i` names the channel in errors.
fn limits_from_pb(l: &pb::ChannelLimits, i: usize) -> Result<Limits, String> {
    let out = Limits {
        min: l.min.unwrap_or(f64::NEG_INFINITY),
        max: l.max.unwrap_or(f64::INFINITY),
        rate_limit: l.rate_limit,
    };
    out.check()
        .map_err(|e| format!("envelope.channels[{i}]: {e}"))?;
    Ok(out)
}

/// Why a registry could not be built from a configuration.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RegistryError {
    /// A declared device's channels do not make a controller, or its output map lies
    /// outside its envelope ([`ServiceConfig::check`] catches these first).
    #[error("device {id:?}: {reason}")]
    Device {
        /// The declared id.
        id: String,
        /// The core's or the envelope's reason.
        reason: String,
    },
}

/// All devices of one controller.
#[derive(Debug)]
pub struct Registry {
    controller_id: String,
    config: ServiceConfig,
    /// A hash map: a gateway's batch looks up thousands of devices a period. Whatever
    /// lists them sorts them first, so listings stay in id order.
    ///
    /// Each device is boxed: the table itself stays small enough for the caches (its slots
    /// hold the key and a pointer), and a lookup reads only it.
    devices: HashMap<DeviceKey, Box<Device>>,
    /// Samples whose id is neither declared nor matched by a template.
    unknown_samples: u64,
    /// The first `UNKNOWN_KEPT` of those ids.
    unknown_devices: BTreeSet<String>,
    /// Samples a template would have provisioned, refused because the table was full.
    device_table_full: u64,
    /// Payloads that did not decode (samples, reference updates, requests).
    undecodable: u64,
    /// Samples answered REJECTED, every device.
    rejected: u64,
    /// Configuration, envelope and reference requests refused.
    requests_refused: u64,
    /// Samples in gateway batches whose device id is not an id.
    bad_device_ids: u64,
}

impl Registry {
    /// Build every declared device from a checked configuration.
    pub fn new(config: ServiceConfig) -> Result<Self, RegistryError> {
        let mut devices = HashMap::new();
        for d in &config.devices {
            let mut dev = Device::new(&d.channels, d.prediction, false).map_err(|reason| {
                RegistryError::Device {
                    id: d.id.clone(),
                    reason,
                }
            })?;
            dev.home = protocol::shard_of(&d.id);
            devices.insert(DeviceKey::new(&d.id), Box::new(dev));
        }
        Ok(Self {
            controller_id: config.controller_id.clone(),
            config,
            devices,
            unknown_samples: 0,
            unknown_devices: BTreeSet::new(),
            device_table_full: 0,
            undecodable: 0,
            rejected: 0,
            requests_refused: 0,
            bad_device_ids: 0,
        })
    }

    /// The snapshot settings, if any.
    pub fn snapshot_spec(&self) -> Option<&crate::config::SnapshotSpec> {
        self.config.snapshots.as_ref()
    }

    /// The fleet settings, if any.
    pub fn fleet(&self) -> Option<&crate::config::FleetSpec> {
        self.config.fleet.as_ref()
    }

    /// The state of the devices `ids` (those served), as a one-shard handover of `shard`:
    /// what an owner sends its standby after a configuration change.
    pub fn devices_state(&self, shard: u32, ids: &[&str]) -> crate::snapshot::ShardState {
        crate::snapshot::ShardState {
            version: crate::snapshot::SNAPSHOT_VERSION,
            shard,
            devices: ids
                .iter()
                .filter_map(|id| Self::handed(id, self.devices.get(*id)?))
                .collect(),
        }
    }

    /// The hot-standby settings, if any.
    pub fn standby(&self) -> Option<&crate::config::StandbySpec> {
        self.config.standby.as_ref()
    }

    /// This controller's id, carried in every command and in the service status.
    pub fn controller_id(&self) -> &str {
        &self.controller_id
    }

    /// Ids of the devices served now: the declared ones and those provisioned so far.
    pub fn device_ids(&self) -> impl Iterator<Item = &str> {
        let mut ids: Vec<&str> = self.devices.keys().map(DeviceKey::as_str).collect();
        ids.sort_unstable();
        ids.into_iter()
    }

    /// The devices in id order.
    fn sorted(&self) -> Vec<(&str, &Device)> {
        let mut v: Vec<(&str, &Device)> = self
            .devices
            .iter()
            .map(|(k, d)| (k.as_str(), &**d))
            .collect();
        v.sort_unstable_by(|a, b| a.0.cmp(b.0));
        v
    }

    /// Whether `id` is served now.
    pub fn serves(&self, id: &str) -> bool {
        self.devices.contains_key(id)
    }

    /// How many devices are served now; never more than the file's `max_devices`.
    pub fn device_count(&self) -> usize {
        self.devices.len()
    }

    /// Count a payload that did not decode; reported as `undecodable` in the service status.
    pub fn note_undecodable(&mut self) {
        self.undecodable += 1;
    }

    /// Count a refused request that never reached a device (undecodable, bad key).
    pub fn note_request_refused(&mut self) {
        self.requests_refused += 1;
    }

    /// Count a sample in a gateway batch whose device id is not a valid id (nothing to
    /// answer); reported as `bad_device_ids` in the service status.
    pub fn note_bad_id(&mut self) {
        self.bad_device_ids += 1;
    }

    /// Add `n` superseded samples to device `id`'s status (the service-wide count is the
    /// inbox's own).
    pub fn note_superseded(&mut self, id: &str, n: u64) {
        if let Some(d) = self.devices.get_mut(id) {
            d.superseded += n;
        }
    }

    /// The templates' patterns, parsed (a pattern that does not parse matches nothing,
    /// as in [`Registry::handle_sample`]): what zenoh's callbacks check an unknown id
    /// against before they queue anything for it.
    pub fn template_patterns(&self) -> Vec<zenoh::key_expr::OwnedKeyExpr> {
        self.config
            .templates
            .iter()
            .filter_map(|t| zenoh::key_expr::OwnedKeyExpr::try_from(t.pattern.clone()).ok())
            .collect()
    }

    fn template_for(&self, id: &str) -> Option<&crate::config::TemplateSpec> {
        let ke = zenoh::key_expr::KeyExpr::try_from(id).ok()?;
        self.config.templates.iter().find(|t| {
            zenoh::key_expr::KeyExpr::try_from(t.pattern.as_str()).is_ok_and(|p| p.includes(&ke))
        })
    }

    /// Rule 1: serve `id` if it is declared or a template provisions it with room left;
    /// otherwise why not ([`Outcome::Unknown`] or [`Outcome::TableFull`]).
    fn provision(&mut self, id: &str) -> Option<Outcome> {
        if self.devices.contains_key(id) {
            return None;
        }
        let Some(t) = self.template_for(id) else {
            return Some(Outcome::Unknown);
        };
        if self.devices.len() >= self.config.max_devices {
            return Some(Outcome::TableFull);
        }
        match Device::new(&t.channels, t.prediction, true) {
            Ok(mut d) => {
                d.home = protocol::shard_of(id);
                self.devices.insert(DeviceKey::new(id), Box::new(d));
                None
            }
            Err(_) => Some(Outcome::Unknown),
        }
    }

    /// Answer a sample received on the key of device `key_id` (the key decides the device;
    /// a sample whose own `device_id` differs is rejected), by the rules of the module doc.
    pub fn handle_sample(&mut self, key_id: &str, s: &pb::Sample) -> Outcome {
        self.handle_sample_from(key_id, s, None).0
    }

    /// [`Registry::handle_sample`] for a sample that came by a path of shard `home` (its own
    /// key: its id's shard; a gateway's batch: the gateway's; `None`: leave it as it is),
    /// which is where the device's state is handed over from; also says whether this sample
    /// provisioned its device from a template. The hot path of a gateway's batch: one
    /// lookup of the device when it is known, besides the step itself.
    pub fn handle_sample_from(
        &mut self,
        key_id: &str,
        s: &pb::Sample,
        home: Option<u32>,
    ) -> (Outcome, bool) {
        let mut command = pb::Command::default();
        let (served, provisioned) = self.handle_sample_into(key_id, s, home, &mut command);
        let outcome = match served {
            Served::Answered => Outcome::Reply(command),
            Served::Unknown => Outcome::Unknown,
            Served::TableFull => Outcome::TableFull,
            Served::AlreadyAnswered => Outcome::AlreadyAnswered,
        };
        (outcome, provisioned)
    }

    /// [`Registry::handle_sample_from`], writing the command into `out` (reusing its
    /// buffers) instead of returning a new one: what a gateway's batch uses, with one
    /// command per sample kept from batch to batch.
    pub fn handle_sample_into(
        &mut self,
        key_id: &str,
        s: &pb::Sample,
        home: Option<u32>,
        out: &mut pb::Command,
    ) -> (Served, bool) {
        if let Some(d) = self.devices.get_mut(key_id) {
            let served = answer(
                &self.controller_id,
                &mut self.rejected,
                d,
                key_id,
                s,
                home,
                out,
            );
            return (served, false);
        }
        // Not served yet (the rare path): a template may provision it, and then it is
        // served as any other.
        if let Some(outcome) = self.provision_outcome(key_id) {
            let served = match outcome {
                Outcome::TableFull => Served::TableFull,
                _ => Served::Unknown,
            };
            return (served, false);
        }
        if !self.devices.contains_key(key_id) {
            return (Served::Unknown, false);
        }
        (self.handle_sample_into(key_id, s, home, out).0, true)
    }

    /// Count and answer a sample whose device cannot be served (rule 1).
    fn provision_outcome(&mut self, key_id: &str) -> Option<Outcome> {
        if let Some(outcome) = self.provision(key_id) {
            match outcome {
                Outcome::TableFull => self.device_table_full += 1,
                _ => {
                    self.unknown_samples += 1;
                    if self.unknown_devices.len() < UNKNOWN_KEPT {
                        self.unknown_devices.insert(printable(key_id));
                    }
                }
            }
            return Some(outcome);
        }
        None
    }
}

/// Step device `d` with a sample that came by a path of shard `home`, and write the
/// command into `out`.
fn answer(
    controller_id: &str,
    rejected: &mut u64,
    d: &mut Device,
    key_id: &str,
    s: &pb::Sample,
    home: Option<u32>,
    out: &mut pb::Command,
) -> Served {
    if let Some(h) = home {
        d.home = h;
    }
    match step_sample(controller_id, rejected, d, key_id, s) {
        Answered::Cached => match &d.last_command {
            Some(a) => a.write_into(controller_id, key_id, out),
            // Not reached: a cached answer is always there.
            None => {
                *out = reply(
                    controller_id,
                    key_id,
                    (s.seq, s.sent_unix_ns),
                    pb::Mode::Stale,
                    String::new(),
                )
            }
        },
        Answered::Reply(c) => *out = c,
        Answered::Not => return Served::AlreadyAnswered,
    }
    Served::Answered
}

/// Rules 2-6 for a served device `d` (`rejected`: the service-wide count).
fn step_sample(
    controller_id: &str,
    rejected: &mut u64,
    d: &mut Device,
    key_id: &str,
    s: &pb::Sample,
) -> Answered {
    d.samples += 1;
    let refuse = |d: &mut Device, rejected: &mut u64, reason: String| {
        let reason = capped(reason);
        d.rejected += 1;
        *rejected += 1;
        d.last_error.clone_from(&reason);
        Answered::Reply(reply(
            controller_id,
            key_id,
            (s.seq, s.sent_unix_ns),
            pb::Mode::Rejected,
            reason,
        ))
    };
    let stale = |d: &mut Device, why: &str| {
        d.stale += 1;
        Answered::Reply(reply(
            controller_id,
            key_id,
            (s.seq, s.sent_unix_ns),
            pb::Mode::Stale,
            why.into(),
        ))
    };
    // Rule 2.
    if let Err(reason) = precheck(key_id, s).and_then(|()| d.check_values(s)) {
        return refuse(d, rejected, reason);
    }
    // Rule 3.
    d.run_samples = d.run_samples.saturating_add(1);
    let mut new_run = match d.run_of(s) {
        Run::Same => false,
        Run::New => true,
        Run::Retired => return stale(d, "a sample of an earlier run of the plant"),
    };
    // Rule 4, within the run in force.
    if !new_run {
        let out_of_step = match d.last_seq {
            Some(last) if s.seq == last => {
                d.duplicates += 1;
                return match &d.last_command {
                    Some(_) => Answered::Cached,
                    // Answered before a restore or a handover: nothing cached to send
                    // again, and the answer went out then (counted as a duplicate only).
                    None => Answered::Not,
                };
            }
            Some(last) if s.seq < last => Some(None),
            Some(last) if s.seq - last > MAX_SEQ_JUMP => Some(Some(format!(
                "sequence jumps from {last} to {}, more than {MAX_SEQ_JUMP}",
                s.seq
            ))),
            _ if s.plant_time <= d.last_time => Some(Some(format!(
                "plant time {:?} does not advance past {:?}",
                s.plant_time, d.last_time
            ))),
            _ => None,
        };
        if let Some(why) = out_of_step {
            if !d.out_of_step(s) {
                return match why {
                    None => stale(d, ""),
                    Some(reason) => refuse(d, rejected, reason),
                };
            }
            // A consistent stream the device has refused RESYNC_AFTER times: the plant
            // is there and the device is out of step with it, so follow the plant.
            new_run = true;
        }
    }
    // Rule 5, checked before anything moves: the step's inputs (a new run is checked
    // against the fresh state it would start from).
    for (r, pieces) in d.refs.iter_mut().zip(&d.reference) {
        *r = evaluate(pieces, s.plant_time - d.reference_start);
    }
    let fresh = if new_run {
        match MimoController::new(&d.configs) {
            Ok(m) => Some(m),
            Err(e) => return refuse(d, rejected, e.to_string()),
        }
    } else {
        None
    };
    if let Err(e) = fresh
        .as_ref()
        .unwrap_or(&d.mimo)
        .check(s.plant_time, &s.outputs, &d.refs)
    {
        return refuse(d, rejected, e.to_string());
    }
    // The sample is good: from here on it may change state.
    if let Some(m) = fresh {
        d.start_run(s.run_id, m);
    }
    d.astray = None;
    if s.last_rtt_us > 0 {
        if d.rtts.len() == RTT_WINDOW {
            d.rtts.pop_front();
        }
        d.rtts.push_back(s.last_rtt_us);
    }
    let plant_trouble = pb::SampleFlags::Holding as u32
        | pb::SampleFlags::Fallback as u32
        | pb::SampleFlags::SafeStop as u32;
    if s.flags & plant_trouble != 0 {
        d.samples_off_remote += 1;
    }
    d.last_flags = s.flags;
    let dt = s.plant_time - d.last_time;
    // The plant applied the last command and nothing else since: the rate limit runs
    // from it. Otherwise (a new run, a restore, a gap, a plant holding or on its
    // fallback, a warm-up answer it did not apply) from what the plant says it applies,
    // or from the last command sent to the device, or from rest.
    let follows = d.last_seq == Some(s.seq.wrapping_sub(1))
        && s.flags & plant_trouble == 0
        && d.last_command
            .as_ref()
            .is_some_and(|c| c.mode == pb::Mode::Control as i32);
    // Read before this sample's interval joins the estimate: a leap cannot vouch for
    // itself.
    let period = d.period();
    // Within a run, the time since the last answered sample, at most two periods (a
    // lost sample in between gives the law that much more room, and the envelope the
    // same); at the start of a run or after a restore, one period from what is held
    // (nothing, before a period is known).
    let rate_dt = if d.last_seq.is_some() && !d.restored {
        dt.min(period.map_or(RATE_DT_UNKNOWN, |p| RATE_DT_PERIODS * p))
    } else {
        period.unwrap_or(0.0)
    };
    if let Some(last) = d.last_seq {
        // s.seq > last here.
        d.lost += s.seq.saturating_sub(last).saturating_sub(1);
        if s.seq - last == 1 {
            d.note_interval(dt);
        }
    }
    if d.last_seq
        .is_some_and(|last| s.seq.saturating_sub(last) > 1)
    {
        recover_previous(d, s);
    }
    if d.last_seq.is_some() && !s.applied.is_empty() {
        // Checked finite above, so this cannot fail.
        let _ = d.mimo.report_applied(&s.applied);
    }
    if std::mem::take(&mut d.restored) && dt > RESUME_GAP {
        // Restarted from a snapshot after a gap: the estimators' history does not reach
        // across it. Keep gains and the reference phase, and start bumplessly from what
        // the plant applies now (its local fallback's output, reported above).
        d.mimo.forget_windows();
    }
    if let Err(e) = d
        .mimo
        .step(s.plant_time, &s.outputs, &d.refs, &mut d.outputs)
    {
        // Not reached: the same inputs passed `check` above.
        return refuse(d, rejected, e.to_string());
    }
    // Rule 6: the last check before anything leaves.
    if let Some(bad) = d.outputs.iter().find(|o| !o.v.is_finite()) {
        let reason = format!(
            "the controller produced a non-finite command ({:?}): check the gains",
            bad.v
        );
        return refuse(d, rejected, reason);
    }
    let mut v: PerChannel<f64> = PerChannel::with_capacity(d.outputs.len());
    let mut clipped = false;
    for (i, o) in d.outputs.iter().enumerate() {
        let from = match &d.last_command {
            Some(c) if follows => c.v.get(i).copied(),
            _ => s
                .applied
                .get(i)
                .copied()
                .or_else(|| d.held.as_ref().and_then(|h| h.get(i).copied())),
        }
        .unwrap_or(0.0);
        let (x, c) = d.envelope[i].clamp(o.v, Some((from, rate_dt)));
        clipped |= c;
        v.push(x);
    }
    if clipped {
        d.clamped += 1;
    }
    d.last_seq = Some(s.seq);
    d.last_time = s.plant_time;
    for (f, o) in d.f_est.iter_mut().zip(&d.outputs) {
        *f = o.f_est.unwrap_or(f64::NAN);
    }
    let control = !d.outputs.iter().any(|o| o.warming_up);
    let buffer = d.last_command.take().map(|a| a.horizon).unwrap_or_default();
    let horizon = if control {
        predict(d, s, &v, period, buffer)
    } else {
        Vec::new()
    };
    let answer = Answer {
        seq: s.seq,
        mode: if control {
            pb::Mode::Control
        } else {
            pb::Mode::WarmingUp
        } as i32,
        controller_unix_ns: protocol::unix_ns(),
        sample_sent_unix_ns: s.sent_unix_ns,
        u: d.outputs.iter().map(|o| o.u).collect(),
        v,
        f_est: d.f_est.clone(),
        horizon,
        reference: d.refs.iter().map(|r| r.y).collect(),
    };
    d.commands += 1;
    if answer.mode == pb::Mode::Control as i32 {
        d.held = Some(answer.v.clone());
    }
    // Kept for a duplicate, inline in the device; the caller writes it out.
    d.last_command = Some(answer);
    Answered::Cached
}

/// The samples lost between the last answered one and `s`, from the copies `s` carries
/// (`previous_*`, newest first): the controller steps on each, oldest first (their outputs
/// are not sent, the moment has passed), so that its estimators see the data points
/// instead of a gap. Copies of samples already seen, and anything that does not fit
/// (lengths that are not whole samples, non-finite values, times that do not advance
/// inside the gap, a step the core refuses), are skipped: at worst the sample is served as
/// if it carried nothing.
fn recover_previous(d: &mut Device, s: &pb::Sample) {
    let n = d.channels();
    let k = s.previous_plant_time.len().min(protocol::RESENT_SAMPLES);
    if n == 0 || s.previous_outputs.len() != k * n || s.previous_applied.len() != k * n {
        return;
    }
    for j in (0..k).rev() {
        let t = s.previous_plant_time[j];
        let y = &s.previous_outputs[j * n..(j + 1) * n];
        let applied = &s.previous_applied[j * n..(j + 1) * n];
        let fits = t.is_finite()
            && t > d.last_time
            && t < s.plant_time
            && y.iter().chain(applied).all(|x| x.is_finite());
        if !fits {
            continue;
        }
        let refs: PerChannel<Reference> = d
            .reference
            .iter()
            .map(|pieces| evaluate(pieces, t - d.reference_start))
            .collect();
        if d.mimo.check(t, y, &refs).is_err() {
            continue;
        }
        let _ = d.mimo.report_applied(applied);
        let mut outputs = d.outputs.clone();
        if d.mimo.step(t, y, &refs, &mut outputs).is_ok() {
            d.recovered += 1;
            // Time moves on to the recovered sample: a later copy must come after it.
            d.last_time = t;
        }
    }
}

/// Rule 7, for a device with a horizon or delay compensation: the outputs its command
/// predicts for the periods after the sample's, period-major (`[j * n + i]`: channel `i`
/// in period `seq + 1 + j`), each through the envelope with the rate limit from the one
/// before, so that whatever the agent plays stays inside it. Written into `out`'s buffer
/// (kept from the last answer). Empty without prediction or before the period is known.
fn predict(
    d: &mut Device,
    s: &pb::Sample,
    v: &[f64],
    period: Option<f64>,
    mut out: Vec<f64>,
) -> Vec<f64> {
    out.clear();
    let p = d.prediction;
    let Some(h) = period.filter(|h| *h > 0.0 && h.is_finite()) else {
        return out;
    };
    // The round trip in periods: the command for `seq` lands in period `seq + m`.
    let m = if p.delay_compensation {
        let mut recent: Vec<u32> = d.rtts.iter().rev().take(DELAY_WINDOW).copied().collect();
        if recent.is_empty() {
            0
        } else {
            let mid = recent.len() / 2;
            let (_, median, _) = recent.select_nth_unstable(mid);
            ((f64::from(*median) * 1e-6 / h).round() as u32).min(MAX_HORIZON)
        }
    } else {
        0
    };
    let len = p.horizon.max(m).min(MAX_HORIZON) as usize;
    if len == 0 {
        return out;
    }
    let n = v.len();
    out.resize(len * n, 0.0);
    let mut refs = Vec::with_capacity(len);
    let mut applied = Vec::with_capacity(m as usize);
    let mut elements = vec![0.0; len];
    for i in 0..n {
        refs.clear();
        refs.extend((1..=len).map(|j| {
            evaluate(
                &d.reference[i],
                s.plant_time + j as f64 * h - d.reference_start,
            )
        }));
        applied.clear();
        if let Some(sched) = &d.schedule {
            applied.extend((0..u64::from(m)).map(|j| sched.get(s.seq + j, i).unwrap_or(f64::NAN)));
        }
        let mut last = d.outputs[i];
        last.v = v[i];
        let trend = mfc::Trend {
            moving: p.trend,
            at_rest: p.trend_at_rest,
        };
        d.mimo.channels()[i].plan(&last, h, &refs, &applied, trend, &mut elements);
        let mut prev = v[i];
        for (j, e) in elements.iter().enumerate() {
            let (x, _) = d.envelope[i].clamp(*e, Some((prev, h)));
            out[j * n + i] = x;
            prev = x;
        }
    }
    if let Some(sched) = &mut d.schedule {
        // From the period it lands in on, this command drives the plant until the next
        // one lands.
        for j in m.max(1) as usize..=len {
            sched.set(s.seq + j as u64, out[(j - 1) * n..j * n].iter().copied());
        }
    }
    out
}

impl Registry {
    /// Answer a sample that [`precheck`] refused before it reached the inbox: REJECTED with
    /// `reason` if the key's device is served, else counted as unknown (a malformed
    /// sample never provisions a device).
    pub fn refuse_sample(
        &mut self,
        key_id: &str,
        seq: u64,
        sent_unix_ns: u64,
        reason: String,
    ) -> Outcome {
        let Some(d) = self.devices.get_mut(key_id) else {
            self.unknown_samples += 1;
            if self.unknown_devices.len() < UNKNOWN_KEPT {
                self.unknown_devices.insert(printable(key_id));
            }
            return Outcome::Unknown;
        };
        let reason = capped(reason);
        d.samples += 1;
        d.rejected += 1;
        self.rejected += 1;
        d.last_error.clone_from(&reason);
        Outcome::Reply(reply(
            &self.controller_id,
            key_id,
            (seq, sent_unix_ns),
            pb::Mode::Rejected,
            reason,
        ))
    }

    /// The safety envelope in force for a device, if served.
    pub fn envelope_of(&self, id: &str) -> Option<Vec<Limits>> {
        self.devices.get(id).map(|d| d.envelope.to_vec())
    }

    /// The configuration of a device, if served.
    pub fn config_of(&self, id: &str) -> Option<pb::DeviceConfig> {
        self.devices.get(id).map(|d| d.config_pb(id))
    }

    /// Apply a configuration request (see `ConfigRequest` in the `.proto`): all or nothing,
    /// bumpless, never outside the envelope. The reply carries the configuration in force
    /// afterwards, accepted or not (none for an unknown device).
    pub fn configure(&mut self, id: &str, req: &pb::ConfigRequest) -> pb::ConfigReply {
        let Some(d) = self.devices.get_mut(id) else {
            self.requests_refused += 1;
            return refused(format!("unknown device \"{}\"", printable(id)), None);
        };
        let planned = d.plan(req).and_then(|(configs, reference)| {
            d.mimo.reconfigure(&configs).map_err(|e| e.to_string())?;
            Ok((configs, reference))
        });
        let applied = planned.map(|(configs, reference)| {
            d.configs = configs;
            if let Some((pieces, start)) = reference {
                d.reference = pieces.into();
                d.reference_start = start;
            }
        });
        conclude(d, &mut self.requests_refused, id, applied)
    }

    /// Replace a device's reference (live steering); the reply says why if refused.
    pub fn set_reference(&mut self, id: &str, update: &pb::ReferenceUpdate) -> pb::ConfigReply {
        let req = pb::ConfigRequest {
            version: PROTOCOL_VERSION,
            reference: Some(update.reference.clone().unwrap_or_default()),
            ..Default::default()
        };
        let reply = self.configure(id, &req);
        if !reply.accepted {
            if let Some(d) = self.devices.get_mut(id) {
                d.references_refused += 1;
            }
        }
        reply
    }

    /// Change a device's envelope (see `EnvelopeRequest` in the `.proto`). Narrowing is
    /// always accepted; widening only if the file sets `allow_remote_widening`. The output
    /// maps in force are narrowed to fit, bumplessly.
    pub fn change_envelope(&mut self, id: &str, req: &pb::EnvelopeRequest) -> pb::ConfigReply {
        let allow_widening = self.config.allow_remote_widening;
        let Some(d) = self.devices.get_mut(id) else {
            self.requests_refused += 1;
            return refused(format!("unknown device \"{}\"", printable(id)), None);
        };
        let n = d.channels();
        let planned = (|| {
            let asked = req.envelope.clone().unwrap_or_default().channels;
            if asked.len() != n {
                return Err(format!(
                    "device has {n} channels, envelope has {}",
                    asked.len()
                ));
            }
            let limits = asked
                .iter()
                .enumerate()
                .map(|(i, l)| limits_from_pb(l, i))
                .collect::<Result<Vec<_>, _>>()?;
            if !allow_widening {
                if let Some(i) = (0..n).find(|&i| d.envelope[i].is_widened_by(&limits[i])) {
                    return Err(format!(
                        "envelope.channels[{i}] widens the envelope; this service allows only \
                         narrowing (allow_remote_widening = false in its file)"
                    ));
                }
            }
            let configs: Vec<ChannelConfig> = d
                .configs
                .iter()
                .zip(&limits)
                .map(|(c, l)| ChannelConfig {
                    law: c.law,
                    output: l.narrow(c.output),
                })
                .collect();
            d.mimo.reconfigure(&configs).map_err(|e| e.to_string())?;
            Ok((limits, configs))
        })();
        let applied = planned.map(|(limits, configs)| {
            d.envelope = limits.into();
            d.configs = configs;
            d.envelope_changes += 1;
        });
        conclude(d, &mut self.requests_refused, id, applied)
    }

    /// Status of one device.
    pub fn device_status(&self, id: &str) -> Option<pb::DeviceStatus> {
        self.devices.get(id).map(|d| d.status_pb(id))
    }

    /// Status of the whole service, `uptime` in seconds. It reports `active` true and term
    /// 0, and none of the inbox's drops: the caller fills those in.
    pub fn service_status(&self, uptime: f64) -> pb::ServiceStatus {
        pb::ServiceStatus {
            version: PROTOCOL_VERSION,
            controller_id: self.controller_id.clone(),
            devices: self
                .sorted()
                .into_iter()
                .map(|(id, d)| d.status_pb(id))
                .collect(),
            unknown_samples: self.unknown_samples,
            unknown_devices: self.unknown_devices.iter().cloned().collect(),
            undecodable: self.undecodable,
            uptime,
            active: true,
            term: 0,
            rejected: self.rejected,
            device_table_full: self.device_table_full,
            requests_refused: self.requests_refused,
            bad_device_ids: self.bad_device_ids,
            ..Default::default()
        }
    }
}

/// Fleet support ([`crate::fleet`]): which shard each device lives in, and the state of a
/// shard as handed between members.
impl Registry {
    /// The shard `id` lives in, if served.
    pub fn home_of(&self, id: &str) -> Option<u32> {
        self.devices.get(id).map(|d| d.home)
    }

    /// Ids of the devices served whose shard is in `mask` (bit `s` for shard `s`).
    pub fn device_ids_in(&self, mask: u64) -> Vec<String> {
        self.devices
            .iter()
            .filter(|(_, d)| mask & (1u64 << (d.home % 64)) != 0)
            .map(|(id, _)| id.as_str().to_string())
            .collect()
    }

    /// The state of every device of `shard`, for a handover.
    pub fn shard_state(&self, shard: u32) -> crate::snapshot::ShardState {
        crate::snapshot::ShardState {
            version: crate::snapshot::SNAPSHOT_VERSION,
            shard,
            devices: self
                .sorted()
                .into_iter()
                .filter(|(_, d)| d.home == shard)
                .filter_map(|(id, d)| Self::handed(id, d))
                .collect(),
        }
    }

    /// Take over a shard's state from another member: every device is restored as the
    /// previous owner had it (configuration, envelope, estimators, sequence), so the next
    /// sample continues bumplessly. Returns how many were restored and how many refused
    /// (each with its reason logged).
    pub fn restore_shard(&mut self, state: &crate::snapshot::ShardState) -> (usize, usize) {
        let (mut ok, mut refused) = (0, 0);
        for h in &state.devices {
            match self.restore_handed(h) {
                Ok(()) => ok += 1,
                Err(reason) => {
                    refused += 1;
                    tracing::warn!(device = %printable(&h.snapshot.id), "handed state not restored: {reason}");
                }
            }
        }
        (ok, refused)
    }

    fn restore_handed(&mut self, h: &crate::snapshot::HandedDevice) -> Result<(), String> {
        keys_check(&h.snapshot.id)?;
        let envelope: Vec<Limits> = h
            .envelope
            .iter()
            .map(|&(min, max, rate_limit)| Limits {
                min,
                max,
                rate_limit,
            })
            .collect();
        for l in &envelope {
            l.check()?;
        }
        // Build the device if this member never saw it, then narrow its envelope to the
        // handed one: a handover never widens what the file allows here.
        if !self.devices.contains_key(h.snapshot.id.as_str()) {
            self.provision(&h.snapshot.id)
                .map_or(Ok(()), |o| Err(format!("cannot serve it here: {o:?}")))?;
        }
        let d = self
            .devices
            .get_mut(h.snapshot.id.as_str())
            .ok_or("not served here")?;
        if envelope.len() != d.envelope.len() {
            return Err(format!(
                "{} envelope channels, the device has {}",
                envelope.len(),
                d.envelope.len()
            ));
        }
        let narrowed: Vec<Limits> = d
            .envelope
            .iter()
            .zip(&envelope)
            .map(|(mine, theirs)| mine.intersect(theirs))
            .collect();
        for l in &narrowed {
            l.check()?;
        }
        d.envelope = narrowed.into();
        d.home = h.home;
        self.restore_with(&h.snapshot, h.live_config)
    }

    /// Drop the state of every device of `shard` (this member no longer owns or backs it
    /// up): template devices are removed (their ids are returned), declared ones rebuilt
    /// from the file.
    pub fn forget_shard(&mut self, shard: u32) -> Vec<String> {
        let mut removed = Vec::new();
        let ids: Vec<String> = self
            .devices
            .iter()
            .filter(|(_, d)| d.home == shard)
            .map(|(id, _)| id.as_str().to_string())
            .collect();
        for id in ids {
            let declared = self.config.devices.iter().find(|d| d.id == id).cloned();
            match declared.and_then(|spec| Device::new(&spec.channels, spec.prediction, false).ok())
            {
                Some(mut fresh) => {
                    fresh.home = protocol::shard_of(&id);
                    self.devices.insert(DeviceKey::new(&id), Box::new(fresh));
                }
                None => {
                    self.devices.remove(id.as_str());
                    removed.push(id);
                }
            }
        }
        removed
    }
}

fn keys_check(id: &str) -> Result<(), String> {
    protocol::keys::check_id(id)
        .map(|_| ())
        .map_err(|e| e.to_string())
}

impl Registry {
    /// Snapshots of every device (for [`crate::snapshot`]); a device whose control state
    /// does not encode is left out.
    pub fn snapshots(&self) -> Vec<crate::snapshot::DeviceSnapshot> {
        self.snapshots_where(|_, _| true)
    }

    fn snapshots_where(
        &self,
        keep: impl Fn(&str, &Device) -> bool,
    ) -> Vec<crate::snapshot::DeviceSnapshot> {
        self.sorted()
            .into_iter()
            .filter(|(id, d)| keep(id, d))
            .filter_map(|(id, d)| Self::snapshot_of(id, d))
            .collect()
    }

    /// One device's snapshot; `None` if its control state does not encode.
    fn snapshot_of(id: &str, d: &Device) -> Option<crate::snapshot::DeviceSnapshot> {
        Some(crate::snapshot::DeviceSnapshot {
            version: crate::snapshot::SNAPSHOT_VERSION,
            id: id.to_string(),
            mimo: mfc::snapshot::to_bytes(&d.mimo).ok()?,
            reference: d.reference.to_vec(),
            reference_start: d.reference_start,
            run_id: d.run_id,
            last_seq: d.last_seq,
            last_time: d.last_time,
            counters: [
                d.samples,
                d.commands,
                d.lost,
                d.duplicates,
                d.stale,
                d.rejected,
                d.samples_off_remote,
            ],
            from_template: d.from_template,
        })
    }

    /// One device as handed to another fleet member: its snapshot, shard and envelope.
    fn handed(id: &str, d: &Device) -> Option<crate::snapshot::HandedDevice> {
        Some(crate::snapshot::HandedDevice {
            snapshot: Self::snapshot_of(id, d)?,
            home: d.home,
            envelope: d
                .envelope
                .iter()
                .map(|l| (l.min, l.max, l.rate_limit))
                .collect(),
            live_config: true,
        })
    }

    /// Restore a device from its snapshot. Refused (and the device left as configured) if
    /// the snapshot's laws differ from the configuration in force: a changed configuration
    /// wins over an old state.
    pub fn restore(&mut self, snap: &crate::snapshot::DeviceSnapshot) -> Result<(), String> {
        self.restore_with(snap, false)
    }

    /// [`Registry::restore`]; with `live_config`, a declared device takes the snapshot's
    /// laws even where they differ from the file's (a handover from a member on which they
    /// were changed remotely). The output maps must still lie inside the envelope.
    fn restore_with(
        &mut self,
        snap: &crate::snapshot::DeviceSnapshot,
        live_config: bool,
    ) -> Result<(), String> {
        let mimo: MimoController =
            mfc::snapshot::from_bytes(&snap.mimo).map_err(|e| e.to_string())?;
        let configs: Vec<ChannelConfig> = mimo.channels().iter().map(|c| *c.config()).collect();
        let d = match self.devices.get_mut(snap.id.as_str()) {
            Some(d) => d,
            None if snap.from_template => {
                // Rebuilt from the template that matches it now, for its envelope; a device
                // no template matches any more is not served any more.
                let Some(t) = self.template_for(&snap.id) else {
                    return Err(format!("no template matches device {:?} any more", snap.id));
                };
                if self.devices.len() >= self.config.max_devices {
                    return Err(format!("device {:?}: the device table is full", snap.id));
                }
                let d = Device::new(&t.channels, t.prediction, true)?;
                self.devices
                    .entry(DeviceKey::new(&snap.id))
                    .or_insert(Box::new(d))
            }
            None => return Err(format!("device {:?} is no longer configured", snap.id)),
        };
        if configs.len() != d.channels() {
            return Err(format!(
                "device {:?}: the snapshot has {} channels, the device {}",
                snap.id,
                configs.len(),
                d.channels()
            ));
        }
        if !snap.from_template && !live_config && configs != d.configs {
            return Err(format!(
                "device {:?}: configuration changed since the snapshot",
                snap.id
            ));
        }
        // A template device's laws may have been changed remotely; its maps must still lie
        // inside the envelope it has now.
        for (i, (c, l)) in configs.iter().zip(&d.envelope).enumerate() {
            if *c
                != (ChannelConfig {
                    law: c.law,
                    output: l.narrow(c.output),
                })
            {
                return Err(format!(
                    "device {:?}: channel {i}'s output map lies outside its envelope",
                    snap.id
                ));
            }
        }
        if snap.reference.len() != configs.len() {
            return Err(format!(
                "device {:?}: reference has the wrong number of channels",
                snap.id
            ));
        }
        d.outputs = smallvec::smallvec![ChannelOutput::default(); configs.len()];
        d.refs = smallvec::smallvec![Reference::default(); configs.len()];
        d.f_est = smallvec::smallvec![f64::NAN; configs.len()];
        d.configs = configs;
        d.mimo = mimo;
        d.reference = snap.reference.iter().cloned().collect();
        d.reference_start = snap.reference_start;
        d.run_id = snap.run_id;
        d.last_seq = snap.last_seq;
        d.last_time = snap.last_time;
        [
            d.samples,
            d.commands,
            d.lost,
            d.duplicates,
            d.stale,
            d.rejected,
            d.samples_off_remote,
        ] = snap.counters;
        d.last_command = None;
        d.retired.clear();
        d.restored = true;
        Ok(())
    }

    /// Write every device's snapshot into `dir` (write to a temporary file, then rename:
    /// a crash mid-write never leaves a torn snapshot). Returns how many were written; a
    /// device that does not encode is skipped; the first I/O error ends the pass.
    pub fn save_snapshots(&self, dir: &std::path::Path) -> std::io::Result<usize> {
        std::fs::create_dir_all(dir)?;
        let mut n = 0;
        for s in self.snapshots() {
            let Ok(bytes) = crate::snapshot::encode(&s) else {
                continue;
            };
            let tmp = dir.join(format!(".{}.snap.tmp", s.id));
            std::fs::write(&tmp, bytes)?;
            std::fs::rename(&tmp, dir.join(format!("{}.snap", s.id)))?;
            n += 1;
        }
        Ok(n)
    }

    /// Restore every device that has a `.snap` file in `dir`; returns (restored, refused),
    /// (0, 0) if `dir` cannot be read. Each refusal is logged with its reason.
    pub fn load_snapshots(&mut self, dir: &std::path::Path) -> (usize, usize) {
        let Ok(entries) = std::fs::read_dir(dir) else {
            return (0, 0);
        };
        let (mut ok, mut refused) = (0, 0);
        for e in entries.flatten() {
            let path = e.path();
            if path.extension().is_none_or(|x| x != "snap") {
                continue;
            }
            let result = std::fs::read(&path)
                .map_err(|e| e.to_string())
                .and_then(|b| crate::snapshot::decode(&b).map_err(|e| e.to_string()))
                .and_then(|s| self.restore(&s));
            match result {
                Ok(()) => ok += 1,
                Err(reason) => {
                    refused += 1;
                    tracing::warn!(file = %path.display(), "snapshot not restored: {reason}");
                }
            }
        }
        (ok, refused)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::hash_map::RandomState;
    use std::hash::BuildHasher;

    #[test]
    fn a_device_key_is_its_id_inline_or_not() {
        let short = "load-1234";
        let edge = "a".repeat(INLINE_ID);
        let long = "cell-7/a-rather-long-device-id-9";
        assert!(matches!(DeviceKey::new(short), DeviceKey::Inline { .. }));
        assert!(matches!(DeviceKey::new(&edge), DeviceKey::Inline { .. }));
        assert!(matches!(DeviceKey::new(long), DeviceKey::Heap(_)));
        let mut table: HashMap<DeviceKey, u32> = HashMap::new();
        for (i, id) in [short, edge.as_str(), long, "é-ü", ""].iter().enumerate() {
            table.insert(DeviceKey::new(id), i as u32);
            assert_eq!(DeviceKey::new(id).as_str(), *id);
            // `Borrow<str>` requires the same hash as the id's own.
            let h = RandomState::new();
            assert_eq!(h.hash_one(DeviceKey::new(id)), h.hash_one(*id));
        }
        assert_eq!(table.get(short), Some(&0));
        assert_eq!(table.get(edge.as_str()), Some(&1));
        assert_eq!(table.get(long), Some(&2));
        assert_eq!(table.get("é-ü"), Some(&3));
        assert_eq!(table.get("load-123"), None);
        assert_eq!(table.get(&edge[1..]), None);
    }
}

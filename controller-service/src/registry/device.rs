//! What the service holds for one device: its control state, where the plant's run
//! stands, the counters of its status, and the answer it sent last.

use smallvec::SmallVec;
use std::collections::VecDeque;

use mfc::trajectory::Piece;
use mfc::{ChannelConfig, ChannelOutput, MimoController, Reference};
use protocol::convert::{
    apply_update, channel_from_pb, channel_to_pb, reference_from_pb, reference_to_pb,
};
use protocol::{pb, PROTOCOL_VERSION};

use super::commission::Commission;
use super::rare::RareState;
use super::{latency, REORDER_WINDOW, RESYNC_AFTER};
use crate::bounds::ChannelBounds;
use crate::config::{DeviceChannel, Prediction};
use crate::envelope::Limits;
use crate::lease::{Claimer, Holder, Version};
use protocol::MAX_HORIZON;

/// Most recent round trips kept per device for the status percentiles (and the delay
/// compensation's median); older ones drop out. 64 (0.64 s at 100 Hz, the 99th percentile
/// its second largest): 256 bytes per device, where 1000 took four kilobytes of the four a
/// device may cost at ten thousand plants. The whole distribution over time is the
/// metrics' histograms' (`mfc_service_loop_rtt_seconds`, per device for named devices).
pub(super) const RTT_WINDOW: usize = 64;
/// Sample intervals kept per device to estimate its period (their lower median, so that
/// leaps in fewer than five of the last eight intervals do not move it).
const PERIOD_WINDOW: usize = 8;
/// Intervals needed before the estimate counts.
const PERIOD_MIN_INTERVALS: usize = 3;

/// Run ids remembered after their run ended, so a late sample of one is STALE instead of
/// starting that run again.
const RETIRED_RUNS: usize = 4;

/// Per-channel values kept inline in a device's state: a plant has one or two channels (the
/// AERO has two), and a value that lives beside the rest of the device costs no pointer
/// chase, where a separate allocation per field costs a cache miss per sample once
/// thousands of devices no longer fit the caches (`docs/scale.md`). More channels spill to
/// the heap and work the same.
pub(super) type PerChannel<T> = SmallVec<[T; 2]>;

/// Rejected sequence numbers a device keeps at most (`Rare::rejected_seqs`): a stream of
/// rejected samples longer than this counts the rest as lost, never more memory.
pub(super) const REJECTED_KEPT: usize = 64;

/// The last CONTROL or WARMING_UP answer, kept to send again verbatim for a duplicate: the
/// values of the command without its ids (the device's key and the controller's own),
/// inline rather than a whole [`pb::Command`] with five allocations of its own.
#[derive(Debug, Clone, Default)]
pub(super) struct Answer {
    pub(super) seq: u64,
    pub(super) mode: i32,
    pub(super) controller_unix_ns: u64,
    pub(super) sample_sent_unix_ns: u64,
    pub(super) u: PerChannel<f64>,
    pub(super) v: PerChannel<f64>,
    pub(super) f_est: PerChannel<f64>,
    /// The packetized horizon (empty without prediction), as [`pb::Command::horizon`].
    pub(super) horizon: Vec<f64>,
    /// `y*` per channel at the sample's time, as [`pb::Command::reference`].
    pub(super) reference: PerChannel<f64>,
}

impl Answer {
    /// Write this answer into `out`, reusing its buffers: a batch's commands are kept
    /// from one batch to the next, so answering allocates nothing.
    pub(super) fn write_into(&self, controller_id: &str, device_id: &str, out: &mut pb::Command) {
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
pub(super) enum Answered {
    /// With the device's cached answer (`last_command`): a new one, or the same again for
    /// a duplicate.
    Cached,
    /// With this command (a refusal, a stale answer).
    Reply(pb::Command),
    /// Not at all ([`Outcome::AlreadyAnswered`]).
    Not,
}

/// An id read on every sample (a device's, as the table's key; the lease holder's a sample
/// reports): short ones (up to 22 bytes, as `load-1234` or `bench.w0`) live inline, in the
/// table's own slot or in the device, so that finding a device among thousands reads the
/// table and nothing else, and checking who holds its lease reads the device and nothing
/// else: with the id behind a pointer, each missed the caches once more for the comparison
/// (a sixth of stepping a thousand devices went to the holder's). Longer ids are kept on
/// the heap and work the same. The representation is private to this module, so that
/// [`ShortId::new`] is the only way to make one (what `as_str` relies on).
#[derive(Debug, Clone)]
pub(super) struct ShortId(Repr);

#[derive(Debug, Clone)]
enum Repr {
    Inline { len: u8, bytes: [u8; INLINE_ID] },
    Heap(Box<str>),
}

/// Bytes of an id kept inline in [`ShortId`]: the key is then 24 bytes, as a `String`.
const INLINE_ID: usize = 22;

impl ShortId {
    pub(super) fn new(id: &str) -> Self {
        if id.len() <= INLINE_ID {
            let mut bytes = [0; INLINE_ID];
            bytes[..id.len()].copy_from_slice(id.as_bytes());
            Self(Repr::Inline {
                len: id.len() as u8,
                bytes,
            })
        } else {
            Self(Repr::Heap(id.into()))
        }
    }

    pub(super) fn as_str(&self) -> &str {
        match &self.0 {
            // Not checked again: on every comparison in the device table, that was 2 %
            // of the registry benchmark's profile.
            Repr::Inline { len, bytes } => {
                let bytes = &bytes[..usize::from(*len)];
                debug_assert!(std::str::from_utf8(bytes).is_ok());
                // SAFETY: `new` is the only constructor (the representation is private
                // to this module, which changes no id once made), and the first `len`
                // bytes it keeps are a whole `&str`'s, so UTF-8.
                unsafe { std::str::from_utf8_unchecked(bytes) }
            }
            Repr::Heap(s) => s,
        }
    }
}

impl std::borrow::Borrow<str> for ShortId {
    fn borrow(&self) -> &str {
        self.as_str()
    }
}

// Hash and equality are the id's, as `Borrow<str>` requires.
impl std::hash::Hash for ShortId {
    fn hash<H: std::hash::Hasher>(&self, state: &mut H) {
        self.as_str().hash(state);
    }
}

impl PartialEq for ShortId {
    fn eq(&self, other: &Self) -> bool {
        self.as_str() == other.as_str()
    }
}

impl Eq for ShortId {}

/// How a sample relates to the run in force.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Run {
    Same,
    New,
    /// A late sample of a run that already ended.
    Retired,
    /// With ordered runs: a run id below the one in force, not a late one of those retired.
    Earlier,
}

/// What the service holds for one device: its control state, where the plant's run stands,
/// and the counters of its status.
///
/// In declaration order (`repr(C)`): the controller (whose own fields are laid out the same
/// way), then the rest of what every sample reads or writes, roughly in the order a step
/// reads it, then what only a status, a snapshot or a change reads; what only rare events
/// write (refusals, duplicates, ended runs) is behind a pointer ([`RareState`]). At ten
/// thousand devices none of them is in the caches when its sample comes, so each cache
/// line a step touches is a miss, and lines read together cost fewer (the processor fetches
/// neighbouring lines with a missed one). Left to the compiler, the fields are ordered by
/// their alignment, not by use: stepping ten thousand devices took 6.06 ms against 5.32
/// with this order (`cargo bench -p controller-service --bench registry --
/// every_device_once`, medians of six alternated runs, 2026-11-28), and 6.8 with the
/// controller after the rest.
#[derive(Debug, Clone)]
#[repr(C)]
pub(super) struct Device {
    /// The controller, which holds the laws and output maps in force ([`Device::config`]:
    /// one copy, changed only through `MimoController::reconfigure`).
    pub(super) mimo: MimoController,
    /// When its last sample was stepped here (Unix ns; 0: never).
    pub(super) heard_unix_ns: u64,
    /// The shard the device lives in ([`crate::fleet`]): its id's, or its gateway's if its
    /// samples come in a gateway's batches.
    pub(super) home: u32,
    /// The last sample's flags (what its plant was doing), for the status.
    pub(super) last_flags: u32,
    /// Samples for this device, counted before any check.
    pub(super) samples: u64,
    /// Samples received since the run in force started, refused ones included: a sample of
    /// a retired run is late only while this is below `REORDER_WINDOW`.
    pub(super) run_samples: u64,
    /// The plant run this state belongs to (`None` before the first sample).
    pub(super) run_id: Option<u64>,
    /// Sequence number of the last sample answered with control values; refused samples do
    /// not move it.
    pub(super) last_seq: Option<u64>,
    /// Plant time of that sample (s); the next must come strictly later. Minus infinity
    /// until the first one (and after a plant restart), so any first time is accepted.
    pub(super) last_time: f64,
    /// What it keeps for rare events (refusals, duplicates, ended runs, operators'
    /// changes), allocated on the first. A step follows the pointer only when `unsettled`
    /// says the state holds something for a good sample to settle.
    pub(super) rare: RareState,
    /// Recent intervals between consecutive samples (s), for the period estimate that
    /// bounds the rate limit's `dt`; kept across runs (the same rig, the same period).
    pub(super) intervals: [f64; PERIOD_WINDOW],
    /// How many of `intervals` are filled, and where the next goes.
    pub(super) intervals_len: u8,
    pub(super) intervals_next: u8,
    /// The rare state holds a stray stream or refused sequence numbers
    /// ([`super::rare::Rare::unsettled`]), which a good sample then reads; otherwise a step
    /// does not touch the rare state at all (it is not among the lines a step asks for).
    pub(super) unsettled: bool,
    /// Sequence numbers skipped between one answered sample and the next; a sample that
    /// arrived but was refused in between counts here too.
    pub(super) lost: u64,
    /// Plant time (s) at which the reference starts: 0 from the file, moved by a live
    /// reference update.
    pub(super) reference_start: f64,
    /// The references per channel at the current sample, likewise reused.
    pub(super) refs: PerChannel<Reference>,
    /// Reference pieces per channel, evaluated at `plant_time - reference_start`.
    pub(super) reference: PerChannel<Vec<Piece>>,
    /// The plant's round-trip reports (µs), oldest first, at most `RTT_WINDOW`; a report of
    /// 0 (no round trip yet) is not kept.
    pub(super) rtts: VecDeque<u32>,
    /// Restored from a snapshot and not yet resumed: the first sample decides whether the
    /// data history still holds (no gap) or must be forgotten.
    pub(super) restored: bool,
    /// The last commissioning run (`super::commission`), kept until the next starts; not
    /// in snapshots (a run does not survive its member).
    pub(super) commission: Option<Box<Commission>>,
    /// Each step's outputs per channel, a buffer reused from sample to sample.
    pub(super) outputs: PerChannel<ChannelOutput>,
    /// The safety envelope per channel. Every output map in force ([`Device::config`])
    /// lies inside it.
    pub(super) envelope: PerChannel<Limits>,
    /// The values of the last CONTROL command sent, kept across runs (the same actuator):
    /// where the rate limit runs from when a sample does not say what is applied.
    pub(super) held: Option<PerChannel<f64>>,
    /// Commands the final envelope check clipped: 0 unless a law or map misbehaves, or a
    /// rate-limited channel starts (a run, a restore) where the law's first value is not
    /// within reach of what the actuator holds. Not with the rare events: every run of a
    /// rate-limited plant starts with one.
    pub(super) clamped: u64,
    /// Commands computed (CONTROL or WARMING_UP); not resends for duplicates, not REJECTED
    /// or STALE answers.
    pub(super) commands: u64,
    /// The last F estimate per channel; NaN until a step gives one.
    pub(super) f_est: PerChannel<f64>,
    /// Horizon and delay compensation of its commands (from the file).
    pub(super) prediction: Prediction,
    /// The command answering `last_seq`, sent again verbatim for a duplicate. `None` after a
    /// restart or a restore.
    pub(super) last_command: Option<Answer>,
    /// The lease as the last sample reported it: holder (at most an id's length, printable),
    /// epoch, and the plant's count of refused commands.
    pub(super) lease_holder: ShortId,
    pub(super) lease_epoch: u64,
    /// The holder's process (two processes may carry one id): what tells them apart.
    pub(super) lease_instance: u64,
    /// Saturating at `u32::MAX` (497 days of refusals at 100 Hz): room for the instance.
    pub(super) lease_refused: u32,
    /// This member's side of the plant's command lease ([`crate::lease`]).
    pub(super) claimer: Claimer,
    /// With delay compensation: what the plant will apply in each coming period, as this
    /// device's commands already sent will have it.
    pub(super) schedule: Option<Box<Schedule>>,
    // Read only for a status, a snapshot or a change. The first of these ends what
    // `Device::prefetch` asks for.
    /// Which changes its configuration holds ([`crate::lease::Version`]).
    pub(super) version: Version,
    /// Provisioned from a template, not declared: reported in the status, and lets a
    /// snapshot rebuild the device although no declaration names it.
    pub(super) from_template: bool,
    /// What a change of each channel may set (`crate::bounds`), from the file. Boxed: read
    /// only on a change, and inline it was 96 bytes of every plant, enough to put the
    /// device in the allocator's next size class (`docs/scale.md`, "Memory per plant").
    pub(super) bounds: Box<PerChannel<ChannelBounds>>,
}

/// What the plant will apply in each period, as far as the commands already sent decide
/// it: a ring over the coming periods (absolute sequence numbers), `n` channels each. The
/// delay compensation drives its prediction with these until its own command lands.
#[derive(Debug, Clone)]
pub(super) struct Schedule {
    pub(super) n: usize,
    /// The period each slot holds (`u64::MAX`: none).
    pub(super) period: Vec<u64>,
    pub(super) values: Vec<f64>,
}

impl Schedule {
    const SLOTS: usize = MAX_HORIZON as usize + 1;

    pub(super) fn new(n: usize) -> Self {
        Self {
            n,
            period: vec![u64::MAX; Self::SLOTS],
            values: vec![0.0; Self::SLOTS * n],
        }
    }

    pub(super) fn get(&self, k: u64, i: usize) -> Option<f64> {
        let slot = (k % Self::SLOTS as u64) as usize;
        (self.period[slot] == k).then(|| self.values[slot * self.n + i])
    }

    pub(super) fn set(&mut self, k: u64, values: impl Iterator<Item = f64>) {
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
    /// A change was accepted: numbered after the last if this member holds the plant's
    /// lease (only the holder's changes are ever acknowledged), left as it was otherwise.
    pub(super) fn changed(&mut self) {
        if self.claimer.holder == Holder::Me {
            self.version = self
                .version
                .next(self.run_id.unwrap_or(0), self.lease_epoch);
        }
    }

    /// Why a change to hold, sent by a member that holds the lease under `holds` (if it
    /// does), is not from the device's holder as heard here; `None` if it is, or if the
    /// device is under no lease here.
    pub(super) fn not_holder(&self, holds: Option<(u64, u64)>) -> Option<String> {
        let leased = matches!(
            self.claimer.holder,
            Holder::Me | Holder::Other | Holder::Vacant
        );
        match holds {
            _ if !leased => None,
            Some(k) if k >= self.lease_key() => None,
            Some(k) => Some(format!(
                "sent under epoch {} of run {:#x}; epoch {} of run {:#x} heard here since",
                k.1,
                k.0,
                self.lease_epoch,
                self.run_id.unwrap_or(0)
            )),
            None => Some("sent by a member that does not hold the device's lease".into()),
        }
    }

    /// The run and epoch of the lease as last heard here.
    pub(super) fn lease_key(&self) -> (u64, u64) {
        (self.run_id.unwrap_or(0), self.lease_epoch)
    }

    /// The counters a snapshot keeps, in its order (`DeviceSnapshot::counters`).
    pub(super) fn counters(&self) -> [u64; 7] {
        let rare = self.rare.get();
        [
            self.samples,
            self.commands,
            self.lost,
            rare.duplicates,
            rare.stale,
            rare.rejected,
            rare.samples_off_remote,
        ]
    }

    /// Restore what [`Device::counters`] gave.
    pub(super) fn set_counters(&mut self, c: [u64; 7]) {
        let [samples, commands, lost, rest @ ..] = c;
        (self.samples, self.commands, self.lost) = (samples, commands, lost);
        // Zeros need no rare state: allocated only for a count to keep.
        let rare = match self.rare.existing() {
            Some(rare) => rare,
            None if rest == [0; 4] => return,
            None => self.rare.get_mut(),
        };
        [
            rare.duplicates,
            rare.stale,
            rare.rejected,
            rare.samples_off_remote,
        ] = rest;
    }

    pub(super) fn new(
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
        let bounds = channels
            .iter()
            .enumerate()
            .map(|(i, c)| {
                c.bounds()
                    .map_err(|(f, r)| format!("channels[{i}].{f}: {r}"))
            })
            .collect::<Result<PerChannel<_>, String>>()?;
        let n = configs.len();
        Ok(Self {
            bounds: Box::new(bounds),
            home: 0,
            claimer: Claimer::default(),
            heard_unix_ns: 0,
            version: Version::default(),
            lease_holder: ShortId::new(""),
            lease_epoch: 0,
            lease_instance: 0,
            lease_refused: 0,
            restored: false,
            from_template,
            envelope,
            mimo: MimoController::new(&configs).map_err(|e| e.to_string())?,
            reference: channels.iter().map(|c| c.reference.clone()).collect(),
            reference_start: 0.0,
            run_id: None,
            run_samples: 0,
            last_seq: None,
            last_time: f64::NEG_INFINITY,
            last_command: None,
            rare: RareState::default(),
            held: None,
            intervals: [0.0; PERIOD_WINDOW],
            intervals_len: 0,
            intervals_next: 0,
            unsettled: false,
            clamped: 0,
            outputs: smallvec::smallvec![ChannelOutput::default(); n],
            refs: smallvec::smallvec![Reference::default(); n],
            samples: 0,
            commands: 0,
            lost: 0,
            rtts: VecDeque::with_capacity(RTT_WINDOW),
            f_est: smallvec::smallvec![f64::NAN; n],
            prediction,
            last_flags: 0,
            schedule: prediction
                .delay_compensation
                .then(|| Box::new(Schedule::new(n))),
            commission: None,
        })
    }

    /// Ask the processor for every line of the state a step reads, all at once, before
    /// the step reads the first: at ten thousand devices none is in the caches, and read
    /// one after another by code whose branches wait on them, each miss would cost its
    /// whole latency in turn (`docs/scale.md`, "The gateway path today": 10 000 devices
    /// stepped in 0.79x the time). On x86_64; elsewhere nothing.
    #[inline]
    pub(super) fn prefetch(&self) {
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
            let start = std::ptr::from_ref(self).cast::<i8>();
            for at in (0..std::mem::offset_of!(Device, version)).step_by(64) {
                // SAFETY: a prefetch is a hint that reads nothing and never faults, and SSE
                // (its target feature) is part of every x86_64; the address is inside
                // `self` anyway.
                unsafe { _mm_prefetch::<_MM_HINT_T0>(start.wrapping_add(at)) };
            }
        }
    }

    /// A new plant run: fresh control state, same configuration and reference. The
    /// counters carry on across runs.
    pub(super) fn start_run(&mut self, run_id: u64, fresh: MimoController) {
        // A plant's first run is not a rare event: nothing to keep, nothing allocated.
        if let Some(old) = self.run_id.filter(|&old| old != run_id) {
            let retired = &mut self.rare.get_mut().retired;
            if retired.len() == RETIRED_RUNS {
                retired.pop_front();
            }
            retired.push_back(old);
        }
        if let Some(rare) = self.rare.existing() {
            rare.retired.retain(|r| *r != run_id);
            rare.rejected_seqs.clear();
            rare.astray = None;
        }
        self.unsettled = false;
        if self.run_id.is_some() {
            // A run after the first is a rare event; the first one is counted by `run_id`.
            self.rare.get_mut().restarts += 1;
        }
        self.mimo = fresh;
        self.run_id = Some(run_id);
        self.run_samples = 0;
        self.restored = false;
        self.last_seq = None;
        self.last_time = f64::NEG_INFINITY;
        self.last_command = None;
        self.abort_commission("the plant restarted");
        if let Some(s) = &mut self.schedule {
            **s = Schedule::new(s.n);
        }
    }

    /// A sample of the run in force was answered REJECTED: note its number if it lies
    /// ahead of the last answered one (see `Rare::rejected_seqs`).
    pub(super) fn note_rejected(&mut self, run_id: u64, seq: u64) {
        let ahead = self.last_seq.is_some_and(|l| seq > l);
        let kept = &self.rare.get().rejected_seqs;
        if self.run_id == Some(run_id)
            && ahead
            && kept.len() < REJECTED_KEPT
            && !kept.contains(&seq)
        {
            self.rare.get_mut().rejected_seqs.push_back(seq);
            self.unsettled = true;
        }
    }

    /// Samples missing between the last answered one (`last`) and `seq`: the numbers in
    /// between that never arrived (those answered REJECTED did). Forgets the noted ones up
    /// to `seq`.
    pub(super) fn missing_before(&mut self, last: u64, seq: u64) -> u64 {
        let gap = seq.saturating_sub(last).saturating_sub(1);
        if !self.unsettled {
            return gap;
        }
        let Some(rare) = self.rare.existing() else {
            return gap;
        };
        let arrived = rare
            .rejected_seqs
            .iter()
            .filter(|&&q| q > last && q < seq)
            .count() as u64;
        rare.rejected_seqs.retain(|&q| q > seq);
        self.unsettled = rare.unsettled();
        gap.saturating_sub(arrived)
    }

    /// A sample of the run in force was answered: the stray stream it ends is forgotten.
    /// Reads the rare state only if it holds one (or refused numbers).
    pub(super) fn settle(&mut self) {
        // Every write of the two keeps the flag in step (checked by every test's samples,
        // the property tests of `tests/untrusted.rs` among them).
        debug_assert_eq!(self.unsettled, self.rare.get().unsettled());
        if !self.unsettled {
            return;
        }
        if let Some(rare) = self.rare.existing() {
            rare.astray = None;
            self.unsettled = rare.unsettled();
        }
    }

    /// The sample period: the lower median of the recent intervals; `None` before
    /// [`PERIOD_MIN_INTERVALS`] of them.
    pub(super) fn period(&self) -> Option<f64> {
        let n = usize::from(self.intervals_len);
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
    pub(super) fn note_interval(&mut self, dt: f64) {
        if !(dt.is_finite() && dt > 0.0) {
            return;
        }
        // A byte each for the count and the place: PERIOD_WINDOW (8) fits a u8.
        self.intervals[usize::from(self.intervals_next)] = dt;
        self.intervals_next = (self.intervals_next + 1) % PERIOD_WINDOW as u8;
        self.intervals_len = (self.intervals_len + 1).min(PERIOD_WINDOW as u8);
    }

    /// Count a sample of the run in force refused as out of step; true once
    /// [`RESYNC_AFTER`] of them in a row form a stream of their own, which the device then
    /// follows as a new run.
    pub(super) fn out_of_step(&mut self, s: &pb::Sample) -> bool {
        let rare = self.rare.get_mut();
        let n = match rare.astray {
            Some((seq, t, n)) if s.seq > seq && s.plant_time > t => n + 1,
            _ => 1,
        };
        rare.astray = Some((s.seq, s.plant_time, n));
        self.unsettled = true;
        n >= RESYNC_AFTER
    }

    pub(super) fn channels(&self) -> usize {
        self.mimo.len()
    }

    /// Channel `i`'s law and output map in force (changed by `configure`, an envelope
    /// change or a commissioning); a snapshot of a declared device is restored only if its
    /// laws equal these.
    pub(super) fn config(&self, i: usize) -> ChannelConfig {
        self.mimo.channels()[i].config()
    }

    /// Every channel's law and output map in force, to change some of them.
    pub(super) fn configs(&self) -> Vec<ChannelConfig> {
        self.mimo.channels().iter().map(|c| c.config()).collect()
    }

    /// Rule 2, the part that depends on the device: how many values.
    pub(super) fn check_values(&self, s: &pb::Sample) -> Result<(), String> {
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

    /// Rule 3; `ordered`: run ids grow from one start to the next (authenticated plants,
    /// `plant::run_id`), so one below the run in force is [`Run::Earlier`].
    pub(super) fn run_of(&self, s: &pb::Sample, ordered: bool) -> Run {
        match (self.run_id, self.last_seq) {
            (None, _) => Run::New,
            (Some(r), _) if s.run_id != r => {
                if self.rare.get().retired.contains(&s.run_id) && self.run_samples < REORDER_WINDOW
                {
                    Run::Retired
                } else if ordered && s.run_id < r {
                    Run::Earlier
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

    pub(super) fn limits_pb(&self) -> pb::Envelope {
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

    pub(super) fn config_pb(&self, id: &str) -> pb::DeviceConfig {
        pb::DeviceConfig {
            version: PROTOCOL_VERSION,
            device_id: id.into(),
            channels: self.configs().iter().map(channel_to_pb).collect(),
            reference: Some(reference_to_pb(&self.reference, self.reference_start)),
            envelope: Some(self.limits_pb()),
        }
    }

    /// Every setting an operator may change, by name ("channel 0 kp", "channel 1
    /// envelope", "channel 0 reference"), as text: an audit entry lists those a change
    /// moved (`crate::audit::diff`).
    pub(super) fn settings(&self) -> std::collections::BTreeMap<String, String> {
        use mfc::params::{names, param, Readable};
        let mut out = std::collections::BTreeMap::new();
        for (i, c) in self.configs().iter().enumerate() {
            let kind = c.law.kind();
            out.insert(format!("channel {i} law"), kind.name().to_string());
            for p in names().filter_map(param).filter(|p| p.applies_to(kind)) {
                if let Ok(v) = p.get(c) {
                    out.insert(format!("channel {i} {}", p.name), Readable(v).to_string());
                }
            }
            if let Some(l) = self.envelope.get(i) {
                let rate = l
                    .rate_limit
                    .map_or("none".into(), |r| Readable(r).to_string());
                let text = format!(
                    "[{}, {}], rate limit {rate}",
                    Readable(l.min),
                    Readable(l.max)
                );
                out.insert(format!("channel {i} envelope"), text);
            }
            if let Some(r) = self.reference.get(i) {
                out.insert(format!("channel {i} reference"), format!("{r:?}"));
            }
            if let Some(c) = self.commission.as_ref().filter(|c| c.channel == i) {
                out.insert(format!("channel {i} commission"), c.setting());
            }
        }
        out.insert(
            "reference start".into(),
            Readable(self.reference_start).to_string(),
        );
        out
    }

    pub(super) fn status_pb(&self, id: &str) -> pb::DeviceStatus {
        pb::DeviceStatus {
            device_id: id.into(),
            loop_rtt: Some(latency(&self.rtts)),
            f_est: self.f_est.to_vec(),
            last_error: self.rare.get().last_error.clone(),
            envelope: Some(self.limits_pb()),
            lease_holder: self.lease_holder.as_str().into(),
            commission: self.commission.as_ref().map(|c| {
                let output = self
                    .mimo
                    .channels()
                    .get(c.channel)
                    .map(|k| k.config().output);
                c.status_pb(output.unwrap_or_default())
            }),
            ..self.counters_pb()
        }
    }

    /// [`Self::status_pb`]'s numbers alone, with nothing that allocates or sorts (no id,
    /// round trips, estimates, envelope or strings): what a metrics scrape sums over
    /// every device.
    pub(super) fn counters_pb(&self) -> pb::DeviceStatus {
        let rare = self.rare.get();
        pb::DeviceStatus {
            version: PROTOCOL_VERSION,
            last_seq: self.last_seq.unwrap_or(0),
            plant_time: if self.last_time.is_finite() {
                self.last_time
            } else {
                0.0
            },
            samples: self.samples,
            commands: self.commands,
            lost: self.lost,
            duplicates: rare.duplicates,
            stale: rare.stale,
            rejected: rare.rejected,
            samples_off_remote: rare.samples_off_remote,
            from_template: self.from_template,
            superseded: rare.superseded,
            envelope_changes: rare.envelope_changes,
            clamped: self.clamped,
            references_refused: rare.references_refused,
            restarts: u64::from(self.run_id.is_some()) + rare.restarts,
            recovered: rare.recovered,
            last_flags: self.last_flags,
            lease_epoch: self.lease_epoch,
            lease_refused: u64::from(self.lease_refused),
            lease_instance: self.lease_instance,
            lease_fenced: self.claimer.fenced,
            lease_claims: self.claimer.claims,
            lease_yields: self.claimer.yields,
            ..Default::default()
        }
    }

    /// The laws and maps a configuration request asks for, checked against the envelope,
    /// and its reference; nothing changes here (the caller applies it all or nothing).
    #[allow(clippy::type_complexity)]
    pub(super) fn plan(
        &self,
        req: &pb::ConfigRequest,
    ) -> Result<(Vec<ChannelConfig>, Option<(Vec<Vec<Piece>>, f64)>), String> {
        let n = self.channels();
        let mut configs = self.configs();
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
        self.check_bounds(&configs, reference.as_ref().map(|(p, _)| &p[..]))?;
        Ok((configs, reference))
    }

    /// Whether `configs` move no parameter, and `reference` (if any) no piece, out of its
    /// bounds at the device's period as known now (`crate::bounds`).
    pub(super) fn check_bounds(
        &self,
        configs: &[ChannelConfig],
        reference: Option<&[Vec<Piece>]>,
    ) -> Result<(), String> {
        let h = self.period();
        for (i, new) in configs.iter().enumerate() {
            self.bounds[i]
                .check_change(&self.config(i), new, &self.envelope[i], h)
                .map_err(|e| format!("channel {i}: {e}"))?;
        }
        for (i, pieces) in reference.into_iter().flatten().enumerate() {
            self.bounds[i]
                .check_reference(pieces, h)
                .map_err(|e| format!("reference.channels[{i}]: {e}"))?;
        }
        Ok(())
    }

    /// End a run in force, or dismiss a proposal waiting for its confirmation, for `why`
    /// (a restart, a restore, a change of configuration, envelope or reference, the
    /// lease): a proposal made for the law before the change must not overwrite it.
    pub(super) fn abort_commission(&mut self, why: &str) {
        let live = |c: &&mut Box<Commission>| {
            matches!(
                c.phase,
                pb::CommissionPhase::CommissionRunning | pb::CommissionPhase::CommissionProposed
            )
        };
        if let Some(c) = self.commission.as_mut().filter(live) {
            c.abort("service", why.into());
        }
    }
}

/// A command without control values (refusals and stale answers) for the sample `seq`
/// sent at `sent_unix_ns`.
pub(super) fn reply(
    (controller_id, id): (&str, &str),
    (seq, sent_unix_ns, now_unix_ns): (u64, u64, u64),
    mode: pb::Mode,
    error: String,
) -> pb::Command {
    pb::Command {
        version: PROTOCOL_VERSION,
        device_id: id.into(),
        seq,
        controller_unix_ns: now_unix_ns,
        mode: mode as i32,
        sample_sent_unix_ns: sent_unix_ns,
        controller_id: controller_id.into(),
        error,
        ..Default::default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::hash_map::RandomState;
    use std::collections::HashMap;
    use std::hash::BuildHasher;

    #[test]
    pub(super) fn a_device_key_is_its_id_inline_or_not() {
        let short = "load-1234";
        let edge = "a".repeat(INLINE_ID);
        let long = "cell-7/a-rather-long-device-id-9";
        assert!(matches!(ShortId::new(short).0, Repr::Inline { .. }));
        assert!(matches!(ShortId::new(&edge).0, Repr::Inline { .. }));
        assert!(matches!(ShortId::new(long).0, Repr::Heap(_)));
        let mut table: HashMap<ShortId, u32> = HashMap::new();
        for (i, id) in [short, edge.as_str(), long, "é-ü", ""].iter().enumerate() {
            table.insert(ShortId::new(id), i as u32);
            assert_eq!(ShortId::new(id).as_str(), *id);
            // `Borrow<str>` requires the same hash as the id's own.
            let h = RandomState::new();
            assert_eq!(h.hash_one(ShortId::new(id)), h.hash_one(*id));
        }
        assert_eq!(table.get(short), Some(&0));
        assert_eq!(table.get(edge.as_str()), Some(&1));
        assert_eq!(table.get(long), Some(&2));
        assert_eq!(table.get("é-ü"), Some(&3));
        assert_eq!(table.get("load-123"), None);
        assert_eq!(table.get(&edge[1..]), None);
    }
}

#[cfg(all(test, target_pointer_width = "64"))]
mod size_tests {
    /// A device is one allocation of mimalloc's class of 1792 bytes: a field more and it
    /// takes the class of 2048, 256 bytes more for every plant (`docs/scale.md`, "Memory
    /// per plant"). Make room (what only rare events need goes to `super::rare::Rare`)
    /// rather than raise this.
    #[test]
    fn a_device_fits_the_allocators_class_of_1792_bytes() {
        let size = std::mem::size_of::<super::Device>();
        assert!(size <= 1792, "a device is {size} bytes");
    }
}

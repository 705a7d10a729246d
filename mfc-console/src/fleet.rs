//! The console's view of the fleet: which devices exist, whether their plants are up, the
//! recent history of each loop, and the latest status and configuration the services gave.
//!
//! Pure: no I/O, no async, no clock of its own (every call that depends on time is given
//! `now`, seconds on the console's monotonic clock). The Zenoh wiring (`crate::net`) feeds
//! it what arrives; the HTTP side (`crate::http`) reads it. Everything from the network is
//! checked whole here ([`parse_sample`], [`parse_command`], the batch parsers,
//! [`FleetView::apply_services`]) before any state changes: size, decoding and version, ids
//! (`protocol::keys::check_id`, and the key's id equal to the message's), at most
//! [`MAX_CHANNELS`] values per vector, finite numbers. What is refused is counted, once,
//! in [`Counters`].
//!
//! Memory is bounded: at most `max_devices` devices ([`ViewBounds`]; beyond it a device whose
//! plant is gone is evicted, else the newcomer is refused, both counted), and per device a
//! ring of at most `points` joined points plus [`PENDING`] samples waiting for their
//! command.
//!
//! # Joining samples and commands
//!
//! A point of the plots is one period: the plant's sample (plant time, outputs, flags) and
//! the service's command for it (same `seq`: reference, `u`, `v`, F estimate). A sample
//! waits in a short pending queue for its command; points enter the ring in `seq` order,
//! each with the next value of a per-device counter `n`, so a reader that asks for the
//! points from `n` on never misses or repeats one. A sample whose command has not come
//! when [`PENDING`] newer samples have is committed without one (its command was lost, or
//! the console does not see it).

use std::collections::{BTreeMap, VecDeque};

use mfc::params::{Scope, PARAMS};
use protocol::convert::update_values;
use protocol::{keys, pb};
use serde::Serialize;

/// Most values a vector of a sample or command may carry (the service's own limit of
/// channels per device); longer is refused.
pub const MAX_CHANNELS: usize = 16;

/// Samples of one device waiting for their command before they are committed without one.
pub const PENDING: usize = 8;

/// Most points one [`FleetView::series`] answer carries (a reader asks again from `next`).
pub const MAX_POINTS_PER_READ: usize = 4000;

/// The bounds of the view.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViewBounds {
    /// Most devices held.
    pub max_devices: usize,
    /// Points kept per device (the ring's size).
    pub points: usize,
    /// Seconds after which a device whose plant is gone and that no service serves is
    /// forgotten.
    pub forget_after: f64,
}

impl Default for ViewBounds {
    fn default() -> Self {
        Self {
            max_devices: 256,
            points: 3000,
            forget_after: 300.0,
        }
    }
}

/// What was received and what was refused, each message in exactly one counter.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct Counters {
    /// Samples taken into a device's history.
    pub samples: u64,
    /// Commands joined to their sample.
    pub commands: u64,
    /// Commands without values (the service refused the sample, or is warming up).
    pub commands_without_values: u64,
    /// Commands whose sample is no longer pending (late, or never seen).
    pub commands_unmatched: u64,
    /// Samples already seen (the same sample on two keys, or a copy).
    pub duplicates: u64,
    /// Messages over the size limit, dropped unread.
    pub oversized: u64,
    /// Messages that do not decode, or carry another protocol version.
    pub undecodable: u64,
    /// Messages whose key or content names no valid id, or another device than the key.
    pub bad_id: u64,
    /// Messages with too many values or a non-finite number.
    pub bad_values: u64,
    /// Samples or commands of a device the console does not hold (table full).
    pub unknown_device: u64,
    /// New devices refused because the table was full of live ones.
    pub devices_refused: u64,
    /// Devices dropped to make room for a new one.
    pub devices_evicted: u64,
    /// Devices forgotten after being gone for `forget_after`.
    pub devices_forgotten: u64,
    /// Restarts of a device's run seen in its samples (its history starts again).
    pub runs: u64,
}

/// Why a message was not taken (each maps to one counter).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Drop {
    /// Over the size limit.
    Oversized,
    /// Not the expected message.
    Undecodable,
    /// No valid id, or not the key's.
    BadId,
    /// Too many values, or a non-finite one.
    BadValues,
}

/// A sample, checked.
#[derive(Debug, Clone, PartialEq)]
pub struct SampleIn {
    /// Device id (valid, and the key's).
    pub id: String,
    /// The plant's run (0: the plant sends none).
    pub run_id: u64,
    /// Sequence number.
    pub seq: u64,
    /// Plant time, seconds.
    pub t: f64,
    /// Outputs per channel.
    pub y: Vec<f64>,
    /// `SampleFlags` bits: holding, fallback, safe stop.
    pub flags: u32,
}

/// A command, checked.
#[derive(Debug, Clone, PartialEq)]
pub struct CommandIn {
    /// Device id.
    pub id: String,
    /// The sample it answers.
    pub seq: u64,
    /// Whether it carries control values (mode `CONTROL`).
    pub control: bool,
    /// Reference y* per channel (empty if the service sends none).
    pub r: Vec<f64>,
    /// Raw command per channel.
    pub u: Vec<f64>,
    /// Command after the output map: what the actuator gets.
    pub v: Vec<f64>,
    /// F estimate per channel.
    pub f: Vec<f64>,
}

fn sized(bytes: &[u8], max: usize) -> Result<(), Drop> {
    if bytes.len() > max {
        Err(Drop::Oversized)
    } else {
        Ok(())
    }
}

fn values(v: &[f64]) -> Result<Vec<f64>, Drop> {
    if v.len() > MAX_CHANNELS || v.iter().any(|x| !x.is_finite()) {
        Err(Drop::BadValues)
    } else {
        Ok(v.to_vec())
    }
}

/// The device id of a device key (`mfc/v1/[shard/{s}/]device/{id}/...`), valid.
fn key_id(key: &str) -> Result<&str, Drop> {
    keys::device_key(key).map(|(id, _)| id).ok_or(Drop::BadId)
}

/// The message's id: valid, and the key's if the key names one.
fn own_id(msg_id: &str, key_id: Option<&str>) -> Result<String, Drop> {
    let id = keys::check_id(msg_id).map_err(|_| Drop::BadId)?;
    match key_id {
        Some(k) if k != id => Err(Drop::BadId),
        _ => Ok(id.to_string()),
    }
}

fn check_sample(s: &pb::Sample, key_id: Option<&str>) -> Result<SampleIn, Drop> {
    let id = own_id(&s.device_id, key_id)?;
    if !s.plant_time.is_finite() {
        return Err(Drop::BadValues);
    }
    Ok(SampleIn {
        id,
        run_id: s.run_id,
        seq: s.seq,
        t: s.plant_time,
        y: values(&s.outputs)?,
        flags: s.flags,
    })
}

fn check_command(c: &pb::Command, key_id: Option<&str>) -> Result<CommandIn, Drop> {
    let id = own_id(&c.device_id, key_id)?;
    let control = c.mode == pb::Mode::Control as i32;
    if !control {
        // A warm-up, stale or refusal answer: nothing of it is plotted (a warming-up
        // estimator's F is not a number yet), so its values are not taken.
        return Ok(CommandIn {
            id,
            seq: c.seq,
            control,
            r: vec![],
            u: vec![],
            v: vec![],
            f: vec![],
        });
    }
    Ok(CommandIn {
        id,
        seq: c.seq,
        control,
        r: values(&c.reference)?,
        u: values(&c.u)?,
        v: values(&c.v)?,
        f: values(&c.f_est)?,
    })
}

/// A sample from `key` (`mfc/v1/[shard/{s}/]device/{id}/sample`), checked whole.
pub fn parse_sample(key: &str, bytes: &[u8]) -> Result<SampleIn, Drop> {
    sized(bytes, protocol::MAX_PAYLOAD)?;
    let id = key_id(key)?;
    let s: pb::Sample = protocol::decode(bytes).map_err(|_| Drop::Undecodable)?;
    check_sample(&s, Some(id))
}

/// A command from `key` (`mfc/v1/device/{id}/command`), checked whole.
pub fn parse_command(key: &str, bytes: &[u8]) -> Result<CommandIn, Drop> {
    sized(bytes, protocol::MAX_PAYLOAD)?;
    let id = key_id(key)?;
    let c: pb::Command = protocol::decode(bytes).map_err(|_| Drop::Undecodable)?;
    check_command(&c, Some(id))
}

/// A gateway's batch of samples (`mfc/v1/[shard/{s}/]gateway/{gw}/samples`), checked
/// whole: one bad sample refuses the batch, as the service does.
pub fn parse_sample_batch(key: &str, bytes: &[u8]) -> Result<Vec<SampleIn>, Drop> {
    sized(bytes, protocol::MAX_BATCH_PAYLOAD)?;
    let gw = keys::gateway_of(key).ok_or(Drop::BadId)?;
    let b: pb::SampleBatch = protocol::decode(bytes).map_err(|_| Drop::Undecodable)?;
    if b.gateway_id != gw {
        return Err(Drop::BadId);
    }
    if b.samples.len() > protocol::MAX_BATCH_SAMPLES {
        return Err(Drop::Oversized);
    }
    b.samples.iter().map(|s| check_sample(s, None)).collect()
}

/// A gateway's batch of commands (`mfc/v1/gateway/{gw}/commands`), checked whole.
pub fn parse_command_batch(key: &str, bytes: &[u8]) -> Result<Vec<CommandIn>, Drop> {
    sized(bytes, protocol::MAX_BATCH_PAYLOAD)?;
    let gw = keys::gateway_of(key).ok_or(Drop::BadId)?;
    let b: pb::CommandBatch = protocol::decode(bytes).map_err(|_| Drop::Undecodable)?;
    if b.gateway_id != gw {
        return Err(Drop::BadId);
    }
    if b.commands.len() > protocol::MAX_BATCH_SAMPLES {
        return Err(Drop::Oversized);
    }
    b.commands.iter().map(|c| check_command(c, None)).collect()
}

/// The plant's mode from a sample's flags (`SampleFlags`), the most severe first.
pub fn mode_of(flags: u32) -> &'static str {
    if flags & pb::SampleFlags::SafeStop as u32 != 0 {
        "safe_stop"
    } else if flags & pb::SampleFlags::Fallback as u32 != 0 {
        "local"
    } else if flags & pb::SampleFlags::Holding as u32 != 0 {
        "holding"
    } else {
        "remote"
    }
}

/// One period of a loop, as plotted.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PlotPoint {
    /// Position in the device's history (consecutive, from 0).
    pub n: u64,
    /// The sample's sequence number.
    pub seq: u64,
    /// Plant time, seconds.
    pub t: f64,
    /// Outputs.
    pub y: Vec<f64>,
    /// References (empty: the command did not come or carried none).
    pub r: Vec<f64>,
    /// Raw commands.
    pub u: Vec<f64>,
    /// Commands applied to the actuator.
    pub v: Vec<f64>,
    /// F estimates.
    pub f: Vec<f64>,
    /// The sample's flags.
    pub flags: u32,
}

/// One device as the console sees it.
#[derive(Debug, Clone, Default)]
pub struct Device {
    /// Its plant's liveliness token is up.
    pub alive: bool,
    /// The controller that lists it in its status, if any.
    pub served_by: Option<String>,
    /// When it last went down or stopped being served (for forgetting it).
    pub since: f64,
    /// When a reader last asked for its details (the configuration is polled while read).
    pub watched_at: Option<f64>,
    /// The console's count of this device's runs (a reader's plot starts again when it
    /// changes).
    pub run: u64,
    run_id: Option<u64>,
    last_seq: Option<u64>,
    last_t: f64,
    next_n: u64,
    pending: VecDeque<PlotPoint>,
    /// Commands that came before their sample (the console's copy of a sample can travel
    /// a slower path than the service's answer to it).
    early: VecDeque<CommandIn>,
    points: VecDeque<PlotPoint>,
    /// Flags of the last sample.
    pub last_flags: u32,
    /// When the last sample came (console time).
    pub last_sample_at: Option<f64>,
    /// Channels of the last sample.
    pub channels: usize,
    /// The last status its controller gave, and when.
    pub status: Option<(pb::DeviceStatus, f64)>,
    /// The last configuration its controller gave, and when.
    pub config: Option<(pb::DeviceConfig, f64)>,
    /// Why the last configuration read failed.
    pub config_error: Option<String>,
}

impl Device {
    fn new(now: f64) -> Self {
        Self {
            since: now,
            ..Default::default()
        }
    }

    fn commit_front(&mut self, limit: usize) {
        if let Some(mut p) = self.pending.pop_front() {
            p.n = self.next_n;
            self.next_n += 1;
            self.points.push_back(p);
            while self.points.len() > limit {
                self.points.pop_front();
            }
        }
    }

    /// Commit the samples at the front of the queue that have their command.
    fn commit_ready(&mut self, limit: usize) {
        while self.pending.front().is_some_and(|p| !p.v.is_empty()) {
            self.commit_front(limit);
        }
    }

    /// The latest committed point.
    pub fn last_point(&self) -> Option<&PlotPoint> {
        self.points.back()
    }

    /// Whether a reader should treat it as gone: no token and no service.
    fn idle(&self) -> bool {
        !self.alive && self.served_by.is_none()
    }
}

fn join(p: &mut PlotPoint, c: CommandIn) {
    p.r = c.r;
    p.u = c.u;
    p.v = c.v;
    p.f = c.f;
}

/// One line of the device list.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Summary {
    /// Device id.
    pub id: String,
    /// Its plant's liveliness token is up.
    pub alive: bool,
    /// The controller serving it.
    pub served_by: Option<String>,
    /// The plant's mode from its last sample (`remote`, `holding`, `local`, `safe_stop`),
    /// or `null` before any.
    pub mode: Option<&'static str>,
    /// Plant time of its last point.
    pub plant_time: Option<f64>,
    /// Seconds since its last sample.
    pub sample_age: Option<f64>,
    /// Channels.
    pub channels: usize,
}

/// Points of one device from a position on.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Series {
    /// The device's run (see [`Device::run`]).
    pub run: u64,
    /// The oldest position still held.
    pub first: u64,
    /// The position to ask from next time.
    pub next: u64,
    /// The points.
    pub points: Vec<PlotPoint>,
}

/// The console's view of the fleet: every device it holds, what it knows of each, and its
/// counters. (The service's `Fleet` is another thing: the shards it owns.)
#[derive(Debug, Clone, Default)]
pub struct FleetView {
    limits: ViewBounds,
    devices: BTreeMap<String, Device>,
    counters: Counters,
}

impl FleetView {
    /// An empty view with these bounds.
    pub fn new(limits: ViewBounds) -> Self {
        Self {
            limits,
            ..Default::default()
        }
    }

    /// The counters.
    pub fn counters(&self) -> Counters {
        self.counters
    }

    /// One device.
    pub fn device(&self, id: &str) -> Option<&Device> {
        self.devices.get(id)
    }

    /// Number of devices held.
    pub fn len(&self) -> usize {
        self.devices.len()
    }

    /// No device held.
    pub fn is_empty(&self) -> bool {
        self.devices.is_empty()
    }

    /// Count a message refused by a parser.
    pub fn dropped(&mut self, why: Drop) {
        let c = &mut self.counters;
        match why {
            Drop::Oversized => c.oversized += 1,
            Drop::Undecodable => c.undecodable += 1,
            Drop::BadId => c.bad_id += 1,
            Drop::BadValues => c.bad_values += 1,
        }
    }

    /// The device `id`, made if there is room: a full table evicts the device whose plant
    /// went down longest ago (one still served only if none is unserved), and refuses the
    /// newcomer if every plant is up.
    fn admit(&mut self, id: &str, now: f64) -> Option<&mut Device> {
        if !self.devices.contains_key(id) {
            if keys::check_id(id).is_err() {
                self.counters.bad_id += 1;
                return None;
            }
            if self.devices.len() >= self.limits.max_devices {
                let victim = self
                    .devices
                    .iter()
                    .filter(|(_, d)| !d.alive)
                    .min_by(|(_, a), (_, b)| {
                        (a.served_by.is_some(), a.since)
                            .partial_cmp(&(b.served_by.is_some(), b.since))
                            .unwrap_or(std::cmp::Ordering::Equal)
                    })
                    .map(|(k, _)| k.clone());
                match victim {
                    Some(v) => {
                        self.devices.remove(&v);
                        self.counters.devices_evicted += 1;
                    }
                    None => {
                        self.counters.devices_refused += 1;
                        return None;
                    }
                }
            }
            self.devices.insert(id.to_string(), Device::new(now));
        }
        self.devices.get_mut(id)
    }

    /// A plant's liveliness token appeared.
    pub fn plant_up(&mut self, id: &str, now: f64) {
        if let Some(d) = self.admit(id, now) {
            if !d.alive {
                d.alive = true;
                d.since = now;
            }
        }
    }

    /// A plant's liveliness token went away.
    pub fn plant_down(&mut self, id: &str, now: f64) {
        if let Some(d) = self.devices.get_mut(id) {
            if d.alive {
                d.alive = false;
                d.since = now;
            }
        }
    }

    /// What the services said (one poll's answers, all of them): who serves which device,
    /// and each device's status. A device no answer lists is no longer served.
    pub fn apply_services(&mut self, services: &[pb::ServiceStatus], now: f64) {
        let mut served: BTreeMap<String, (String, pb::DeviceStatus)> = BTreeMap::new();
        for s in services {
            if keys::check_id(&s.controller_id).is_err() {
                self.counters.bad_id += 1;
                continue;
            }
            for d in &s.devices {
                if keys::check_id(&d.device_id).is_err() || d.f_est.len() > MAX_CHANNELS {
                    self.counters.bad_id += 1;
                    continue;
                }
                // An active instance's word wins over a standby's (which lists the device
                // too, with older counters).
                let keep = match served.get(&d.device_id) {
                    Some(_) => s.active,
                    None => true,
                };
                if keep {
                    served.insert(d.device_id.clone(), (s.controller_id.clone(), d.clone()));
                }
            }
        }
        for (id, d) in self.devices.iter_mut() {
            if !served.contains_key(id) && d.served_by.take().is_some() {
                d.since = now;
            }
        }
        for (id, (controller, status)) in served {
            if let Some(d) = self.admit(&id, now) {
                if d.served_by.is_none() {
                    d.since = now;
                }
                d.served_by = Some(controller);
                d.status = Some((status, now));
            }
        }
    }

    /// A configuration read (or changed) from the device's controller.
    pub fn apply_config(&mut self, id: &str, config: pb::DeviceConfig, now: f64) {
        if let Some(d) = self.devices.get_mut(id) {
            if config.channels.len() <= MAX_CHANNELS && config.device_id == id {
                d.config = Some((config, now));
                d.config_error = None;
            } else {
                self.counters.bad_id += 1;
            }
        }
    }

    /// A configuration read failed.
    pub fn config_failed(&mut self, id: &str, reason: String) {
        if let Some(d) = self.devices.get_mut(id) {
            d.config_error = Some(reason);
        }
    }

    /// A checked sample.
    pub fn apply_sample(&mut self, s: SampleIn, now: f64) {
        let limit = self.limits.points.max(1);
        let known = self.devices.contains_key(&s.id);
        // Samples make a device known only if there is room without evicting: a flood of
        // samples from made-up ids must not push out the devices an operator watches.
        if !known && self.devices.len() >= self.limits.max_devices {
            self.counters.unknown_device += 1;
            return;
        }
        let Some(d) = self.admit(&s.id, now) else {
            self.counters.unknown_device += 1;
            return;
        };
        let new_run = match (d.run_id, d.last_seq) {
            (Some(r), _) if s.run_id != 0 && r != s.run_id => true,
            (_, Some(last)) if s.seq <= last => {
                // The same run sends each sample once; a sequence far back, or a clock that
                // went back, is a plant that started again without a run id.
                s.run_id == 0 && (last - s.seq > 1000 || s.t + 1.0 < d.last_t)
            }
            _ => false,
        };
        if new_run {
            d.pending.clear();
            d.early.clear();
            d.points.clear();
            d.last_seq = None;
            d.run += 1;
        } else if d.last_seq.is_some_and(|last| s.seq <= last) {
            self.counters.duplicates += 1;
            return;
        }
        d.run_id = Some(s.run_id);
        d.last_seq = Some(s.seq);
        d.last_t = s.t;
        d.last_flags = s.flags;
        d.last_sample_at = Some(now);
        d.channels = s.y.len();
        let mut p = PlotPoint {
            n: 0,
            seq: s.seq,
            t: s.t,
            y: s.y,
            r: vec![],
            u: vec![],
            v: vec![],
            f: vec![],
            flags: s.flags,
        };
        let mut joined = false;
        if let Some(i) = d.early.iter().position(|c| c.seq == s.seq) {
            if let Some(c) = d.early.remove(i) {
                join(&mut p, c);
                joined = true;
            }
        }
        d.pending.push_back(p);
        while d.pending.len() > PENDING {
            d.commit_front(limit);
        }
        d.commit_ready(limit);
        self.counters.samples += 1;
        self.counters.commands += u64::from(joined);
        self.counters.runs += u64::from(new_run);
    }

    /// A checked command: joined to its pending sample; then every sample at the front of
    /// the queue that has its command is committed.
    pub fn apply_command(&mut self, c: CommandIn) {
        let limit = self.limits.points.max(1);
        let Some(d) = self.devices.get_mut(&c.id) else {
            self.counters.unknown_device += 1;
            return;
        };
        if !c.control {
            self.counters.commands_without_values += 1;
            return;
        }
        let Some(p) = d.pending.iter_mut().find(|p| p.seq == c.seq) else {
            // Ahead of every sample seen: its sample may still come. Kept for a while.
            if d.last_seq.is_none_or(|last| c.seq > last) && !d.early.iter().any(|e| e.seq == c.seq)
            {
                d.early.push_back(c);
                if d.early.len() > PENDING {
                    d.early.pop_front();
                    self.counters.commands_unmatched += 1;
                }
            } else {
                self.counters.commands_unmatched += 1;
            }
            return;
        };
        if !p.v.is_empty() {
            self.counters.duplicates += 1;
            return;
        }
        join(p, c);
        self.counters.commands += 1;
        d.commit_ready(limit);
    }

    /// Forget the devices gone (no token, no service) for longer than `forget_after`.
    pub fn forget(&mut self, now: f64) {
        let after = self.limits.forget_after;
        let before = self.devices.len();
        self.devices
            .retain(|_, d| !(d.idle() && now - d.since > after));
        self.counters.devices_forgotten += (before - self.devices.len()) as u64;
    }

    /// Record that a reader looked at `id` (its configuration is then polled).
    pub fn watch(&mut self, id: &str, now: f64) {
        if let Some(d) = self.devices.get_mut(id) {
            d.watched_at = Some(now);
        }
    }

    /// The devices served and read within `within` seconds: whose configuration to poll.
    pub fn watched(&self, now: f64, within: f64) -> Vec<String> {
        self.devices
            .iter()
            .filter(|(_, d)| {
                d.served_by.is_some() && d.watched_at.is_some_and(|w| now - w <= within)
            })
            .map(|(k, _)| k.clone())
            .collect()
    }

    /// The device list.
    pub fn list(&self, now: f64) -> Vec<Summary> {
        self.devices
            .iter()
            .map(|(id, d)| Summary {
                id: id.clone(),
                alive: d.alive,
                served_by: d.served_by.clone(),
                mode: d.last_sample_at.map(|_| mode_of(d.last_flags)),
                plant_time: d.points.back().map(|p| p.t),
                sample_age: d.last_sample_at.map(|t| now - t),
                channels: d.channels,
            })
            .collect()
    }

    /// The points of `id` from position `since` on (from the oldest held if `since` is
    /// older; at most [`MAX_POINTS_PER_READ`]).
    pub fn series(&self, id: &str, since: u64) -> Option<Series> {
        let d = self.devices.get(id)?;
        let first = d.points.front().map_or(d.next_n, |p| p.n);
        let skip = since.saturating_sub(first).min(d.points.len() as u64) as usize;
        let points: Vec<PlotPoint> = d
            .points
            .iter()
            .skip(skip)
            .take(MAX_POINTS_PER_READ)
            .cloned()
            .collect();
        let next = points.last().map_or(first + skip as u64, |p| p.n + 1);
        Some(Series {
            run: d.run,
            first,
            next,
            points,
        })
    }
}

/// Check a partial change against the device's configuration before it is sent: the
/// channel exists, every value is finite, and the output limits it sets stay inside the
/// envelope (`min` not below the envelope's, `max` not above, a rate limit not faster,
/// `min < max` with the limits in force). The service checks the same and more; checking
/// here too gives the operator the reason at once and never sends a change the envelope
/// refuses.
pub fn check_update(update: &pb::ChannelUpdate, config: &pb::DeviceConfig) -> Result<(), String> {
    let ch = update.channel as usize;
    let Some(channel) = config.channels.get(ch) else {
        return Err(format!(
            "device {} has {} channels, no channel {ch}",
            config.device_id,
            config.channels.len()
        ));
    };
    let set: Vec<(&str, f64)> = update_values(update).map(|(p, v)| (p.name, v)).collect();
    if set.is_empty() {
        return Err("nothing to change: give at least one field".into());
    }
    if let Some((name, v)) = set.iter().find(|(_, v)| !v.is_finite()) {
        return Err(format!("{name} {v:?} is not a finite number"));
    }
    let env = config
        .envelope
        .as_ref()
        .and_then(|e| e.channels.get(ch))
        .copied()
        .unwrap_or_default();
    let (emin, emax) = (
        env.min.unwrap_or(f64::NEG_INFINITY),
        env.max.unwrap_or(f64::INFINITY),
    );
    if let Some(m) = update.min {
        if m < emin {
            return Err(format!(
                "channel {ch}: min {m} is below the envelope's {emin} (the envelope is [{emin}, {emax}]; change the envelope first)"
            ));
        }
    }
    if let Some(m) = update.max {
        if m > emax {
            return Err(format!(
                "channel {ch}: max {m} is above the envelope's {emax} (the envelope is [{emin}, {emax}]; change the envelope first)"
            ));
        }
    }
    if let Some(r) = update.rate_limit {
        if r <= 0.0 {
            return Err(format!("channel {ch}: rate_limit {r} must be > 0"));
        }
        if let Some(e) = env.rate_limit {
            if r > e {
                return Err(format!(
                    "channel {ch}: rate_limit {r} is above the envelope's {e} (change the envelope first)"
                ));
            }
        }
    }
    let output = channel.output.unwrap_or_default();
    let lo = update.min.or(output.min).unwrap_or(emin);
    let hi = update.max.or(output.max).unwrap_or(emax);
    if lo >= hi {
        return Err(format!("channel {ch}: min {lo} must be below max {hi}"));
    }
    Ok(())
}

/// One channel's configuration for a form: the law and its parameters by the names a
/// partial change uses, the output map and the envelope. The names, their order and their
/// help come from the core's table ([`mfc::params::PARAMS`]).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ChannelView {
    /// `ip`, `ipi`, `ipd`, `ipid`, `pid`, `adrc` or `none`.
    pub law: String,
    /// The law's parameters a change may set, with their values (none if the configuration
    /// does not convert to the core's, which a service never sends).
    pub params: Vec<(String, f64)>,
    /// The output map's fields a change may set (`dead_zone`, `smoothing`, `min`, `max`,
    /// `rate_limit`; a missing limit is `null`).
    pub output: Vec<(String, Option<f64>)>,
    /// Per field of `params` and `output`: its meaning, unit and sane bounds, in one line.
    pub help: BTreeMap<&'static str, String>,
    /// The envelope's limits (`null`: unbounded, no rate limit).
    pub envelope: pb::ChannelLimits,
}

/// The law's name as a form shows it (`ipd`, `pid`, `adrc`).
fn law_name(c: &pb::ChannelConfig) -> String {
    use pb::channel_config::Law;
    match &c.law {
        Some(Law::Intelligent(x)) => pb::IntelligentKind::try_from(x.kind)
            .map(|k| {
                k.as_str_name()
                    .trim_start_matches("INTELLIGENT_KIND_")
                    .to_lowercase()
            })
            .unwrap_or_else(|_| "intelligent".into()),
        Some(Law::Pid(_)) => "pid".into(),
        Some(Law::Adrc(_)) => "adrc".into(),
        None => "none".into(),
    }
}

/// One channel as a form shows it: every parameter of the table its law has, read from
/// the core's configuration (a limit or rate that is not there is `null`).
fn channel_view(c: &pb::ChannelConfig, envelope: pb::ChannelLimits) -> ChannelView {
    let core = protocol::convert::channel_from_pb(c).ok();
    let (mut params, mut output, mut help) = (Vec::new(), Vec::new(), BTreeMap::new());
    for p in PARAMS.iter() {
        let Some(v) = core.as_ref().and_then(|k| p.get(k).ok()) else {
            continue;
        };
        match p.scope {
            Scope::OutputMap => {
                output.push((p.name.to_string(), Some(v).filter(|v| v.is_finite())))
            }
            Scope::Laws(_) => params.push((p.name.to_string(), v)),
        }
        help.insert(
            p.name,
            format!("{} ({}; sane: {})", p.meaning, p.unit, p.bounds),
        );
    }
    ChannelView {
        law: law_name(c),
        params,
        output,
        help,
        envelope,
    }
}

/// The configuration as channel views.
pub fn channel_views(config: &pb::DeviceConfig) -> Vec<ChannelView> {
    let env = config.envelope.clone().unwrap_or_default();
    config
        .channels
        .iter()
        .enumerate()
        .map(|(i, c)| channel_view(c, env.channels.get(i).copied().unwrap_or_default()))
        .collect()
}

/// A constant reference per channel, checked: one finite value per channel of the device.
pub fn check_reference(values: &[f64], channels: usize) -> Result<(), String> {
    if values.len() != channels {
        return Err(format!(
            "give one value per channel: the device has {channels}, got {}",
            values.len()
        ));
    }
    if let Some(v) = values.iter().find(|v| !v.is_finite()) {
        return Err(format!("{v:?} is not a finite number"));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use protocol::{encode, PROTOCOL_VERSION};

    fn sample(id: &str, seq: u64, t: f64, y: &[f64]) -> pb::Sample {
        pb::Sample {
            version: PROTOCOL_VERSION,
            device_id: id.into(),
            seq,
            plant_time: t,
            outputs: y.to_vec(),
            run_id: 7,
            ..Default::default()
        }
    }

    fn command(id: &str, seq: u64, v: f64) -> pb::Command {
        pb::Command {
            version: PROTOCOL_VERSION,
            device_id: id.into(),
            seq,
            u: vec![v],
            v: vec![v],
            f_est: vec![0.5],
            reference: vec![1.0],
            mode: pb::Mode::Control as i32,
            ..Default::default()
        }
    }

    fn limits(max_devices: usize, points: usize) -> ViewBounds {
        ViewBounds {
            max_devices,
            points,
            forget_after: 10.0,
        }
    }

    fn feed(f: &mut FleetView, id: &str, seq: u64, with_command: bool) {
        let s = parse_sample(
            &keys::sample(id),
            &encode(&sample(id, seq, seq as f64 * 0.01, &[seq as f64])),
        )
        .unwrap();
        f.apply_sample(s, 0.0);
        if with_command {
            let c = parse_command(&keys::command(id), &encode(&command(id, seq, 2.0))).unwrap();
            f.apply_command(c);
        }
    }

    #[test]
    fn messages_are_checked_whole_before_they_count() {
        let good = encode(&sample("a", 1, 0.0, &[1.0]));
        assert!(parse_sample("mfc/v1/device/a/sample", &good).is_ok());
        assert!(parse_sample(&keys::shard_sample("a"), &good).is_ok());
        // The key's id must be the message's, and valid.
        assert_eq!(
            parse_sample("mfc/v1/device/b/sample", &good),
            Err(Drop::BadId)
        );
        assert_eq!(
            parse_sample("mfc/v1/device/a b/sample", &good),
            Err(Drop::BadId)
        );
        assert_eq!(
            parse_sample("mfc/v1/device/a/sample", b"\xff\xff\xff"),
            Err(Drop::Undecodable)
        );
        let huge = vec![0u8; protocol::MAX_PAYLOAD + 1];
        assert_eq!(
            parse_sample("mfc/v1/device/a/sample", &huge),
            Err(Drop::Oversized)
        );
        let nan = encode(&sample("a", 1, 0.0, &[f64::NAN]));
        assert_eq!(
            parse_sample("mfc/v1/device/a/sample", &nan),
            Err(Drop::BadValues)
        );
        let wide = encode(&sample("a", 1, 0.0, &[0.0; MAX_CHANNELS + 1]));
        assert_eq!(
            parse_sample("mfc/v1/device/a/sample", &wide),
            Err(Drop::BadValues)
        );
        let mut other_version = sample("a", 1, 0.0, &[1.0]);
        other_version.version = 99;
        assert_eq!(
            parse_sample("mfc/v1/device/a/sample", &encode(&other_version)),
            Err(Drop::Undecodable)
        );
        let mut c = command("a", 1, 1.0);
        c.f_est = vec![f64::INFINITY];
        assert_eq!(
            parse_command("mfc/v1/device/a/command", &encode(&c)),
            Err(Drop::BadValues)
        );
        // A warming-up answer's F is not a number yet: taken, without values.
        c.mode = pb::Mode::WarmingUp as i32;
        let w = parse_command("mfc/v1/device/a/command", &encode(&c)).unwrap();
        assert!(!w.control && w.f.is_empty());
        // A batch with one bad sample is refused whole.
        let batch = pb::SampleBatch {
            version: PROTOCOL_VERSION,
            gateway_id: "gw".into(),
            samples: vec![sample("a", 1, 0.0, &[1.0]), sample("", 1, 0.0, &[1.0])],
            ..Default::default()
        };
        assert_eq!(
            parse_sample_batch(&keys::gateway_samples("gw"), &encode(&batch)),
            Err(Drop::BadId)
        );
        assert_eq!(
            parse_sample_batch(&keys::gateway_samples("other"), &encode(&batch)),
            Err(Drop::BadId)
        );
        let batch = pb::SampleBatch {
            samples: vec![sample("a", 1, 0.0, &[1.0]), sample("b", 1, 0.0, &[2.0])],
            ..batch
        };
        assert_eq!(
            parse_sample_batch(&keys::shard_gateway_samples("gw"), &encode(&batch))
                .unwrap()
                .len(),
            2
        );
        let mut f = FleetView::new(ViewBounds::default());
        f.dropped(Drop::BadId);
        f.dropped(Drop::Oversized);
        assert_eq!((f.counters().bad_id, f.counters().oversized), (1, 1));
        assert!(f.is_empty(), "refused messages change no device");
    }

    #[test]
    fn samples_and_commands_join_into_points_in_order() {
        let mut f = FleetView::new(limits(4, 100));
        for seq in 1..=3 {
            feed(&mut f, "a", seq, true);
        }
        let s = f.series("a", 0).unwrap();
        assert_eq!(s.points.len(), 3);
        assert_eq!(
            s.points.iter().map(|p| (p.n, p.seq)).collect::<Vec<_>>(),
            [(0, 1), (1, 2), (2, 3)]
        );
        assert_eq!(
            (s.points[0].r.clone(), s.points[0].v.clone()),
            (vec![1.0], vec![2.0])
        );
        assert_eq!(s.next, 3);
        // Reading from `next` gives nothing new until something comes.
        assert!(f.series("a", 3).unwrap().points.is_empty());
        // A command for the second of two pending samples waits for the first.
        feed(&mut f, "a", 4, false);
        feed(&mut f, "a", 5, true);
        assert_eq!(f.series("a", 3).unwrap().points.len(), 0);
        let c = parse_command(&keys::command("a"), &encode(&command("a", 4, 1.0))).unwrap();
        f.apply_command(c);
        let s = f.series("a", 3).unwrap();
        assert_eq!(s.points.iter().map(|p| p.seq).collect::<Vec<_>>(), [4, 5]);
        // Samples whose command never comes are committed once PENDING newer ones wait.
        for seq in 6..6 + PENDING as u64 + 2 {
            feed(&mut f, "a", seq, false);
        }
        let s = f.series("a", 5).unwrap();
        assert_eq!(s.points.len(), 2);
        assert!(s.points[0].v.is_empty());
        let c = f.counters();
        assert_eq!((c.samples, c.commands), (15, 5));
    }

    #[test]
    fn a_command_that_overtakes_its_sample_is_joined_when_the_sample_comes() {
        let mut f = FleetView::new(limits(4, 100));
        feed(&mut f, "a", 1, true);
        let c = parse_command(&keys::command("a"), &encode(&command("a", 2, 3.0))).unwrap();
        f.apply_command(c);
        assert_eq!(f.series("a", 0).unwrap().points.len(), 1);
        feed(&mut f, "a", 2, false);
        let s = f.series("a", 0).unwrap();
        assert_eq!(s.points.iter().map(|p| p.seq).collect::<Vec<_>>(), [1, 2]);
        assert_eq!(s.points[1].v, [3.0]);
        assert_eq!(
            (f.counters().commands, f.counters().commands_unmatched),
            (2, 0)
        );
        // Commands for samples that never come are forgotten, counted, after PENDING more.
        for seq in 10..10 + PENDING as u64 + 3 {
            let c = parse_command(&keys::command("a"), &encode(&command("a", seq, 1.0))).unwrap();
            f.apply_command(c);
        }
        assert_eq!(f.counters().commands_unmatched, 3);
    }

    #[test]
    fn duplicates_late_commands_and_refusals_are_counted_not_plotted() {
        let mut f = FleetView::new(limits(4, 100));
        feed(&mut f, "a", 1, true);
        feed(&mut f, "a", 1, false); // the same sample on the shard key
        let c = parse_command(&keys::command("a"), &encode(&command("a", 1, 1.0))).unwrap();
        f.apply_command(c); // already joined and committed
        let mut refused = command("a", 2, 0.0);
        refused.mode = pb::Mode::Rejected as i32;
        refused.u.clear();
        refused.v.clear();
        feed(&mut f, "a", 2, false);
        f.apply_command(parse_command(&keys::command("a"), &encode(&refused)).unwrap());
        let c = f.counters();
        assert_eq!(
            (
                c.duplicates,
                c.commands_unmatched,
                c.commands_without_values
            ),
            (1, 1, 1)
        );
        assert_eq!(f.series("a", 0).unwrap().points.len(), 1);
    }

    #[test]
    fn a_new_run_starts_the_history_again() {
        let mut f = FleetView::new(limits(4, 100));
        for seq in 1..=3 {
            feed(&mut f, "a", seq, true);
        }
        let mut s = sample("a", 1, 0.0, &[0.0]);
        s.run_id = 8;
        f.apply_sample(parse_sample(&keys::sample("a"), &encode(&s)).unwrap(), 1.0);
        let c = parse_command(&keys::command("a"), &encode(&command("a", 1, 1.0))).unwrap();
        f.apply_command(c);
        let s = f.series("a", 0).unwrap();
        assert_eq!((s.run, s.points.len(), s.points[0].n), (1, 1, 3));
        assert_eq!(f.counters().runs, 1);
    }

    #[test]
    fn the_ring_is_bounded_and_a_slow_reader_resumes_at_the_oldest() {
        let mut f = FleetView::new(limits(4, 5));
        for seq in 1..=12 {
            feed(&mut f, "a", seq, true);
        }
        let s = f.series("a", 2).unwrap();
        assert_eq!(s.first, 7);
        assert_eq!(
            s.points.iter().map(|p| p.n).collect::<Vec<_>>(),
            [7, 8, 9, 10, 11]
        );
        assert_eq!(s.next, 12);
        assert_eq!(f.series("a", 40).unwrap().points.len(), 0);
    }

    #[test]
    fn liveliness_and_services_make_the_list_and_the_table_is_bounded() {
        let mut f = FleetView::new(limits(2, 10));
        f.plant_up("a", 0.0);
        f.plant_up("b", 0.0);
        f.plant_up("c", 1.0); // full of live plants: refused
        assert_eq!(f.counters().devices_refused, 1);
        assert_eq!(f.len(), 2);
        f.plant_down("a", 2.0);
        f.plant_up("c", 3.0); // evicts the plant that went down
        assert_eq!(f.counters().devices_evicted, 1);
        let ids: Vec<_> = f.list(3.0).into_iter().map(|s| (s.id, s.alive)).collect();
        assert_eq!(ids, [("b".to_string(), true), ("c".to_string(), true)]);
        // Samples from an unknown id do not push anyone out.
        feed(&mut f, "zz", 1, false);
        assert_eq!(f.counters().unknown_device, 1);
        f.plant_up("bad id", 3.0);
        assert_eq!(f.counters().bad_id, 1);

        // A service lists b: served; c is not served; b's status is kept.
        let svc = pb::ServiceStatus {
            version: PROTOCOL_VERSION,
            controller_id: "controller-1".into(),
            active: true,
            devices: vec![pb::DeviceStatus {
                device_id: "b".into(),
                samples: 42,
                ..Default::default()
            }],
            ..Default::default()
        };
        f.apply_services(std::slice::from_ref(&svc), 4.0);
        let b = f.device("b").unwrap();
        assert_eq!(b.served_by.as_deref(), Some("controller-1"));
        assert_eq!(b.status.as_ref().unwrap().0.samples, 42);
        // Gone and unserved: forgotten after forget_after; served: kept.
        f.plant_down("b", 5.0);
        f.plant_down("c", 5.0);
        f.forget(14.0);
        assert_eq!(f.len(), 2);
        f.forget(16.0);
        assert_eq!(f.len(), 1);
        assert!(f.device("b").is_some());
        f.apply_services(&[], 20.0);
        assert!(f.device("b").unwrap().served_by.is_none());
        f.forget(29.0);
        assert_eq!(f.len(), 1);
        f.forget(31.0);
        assert!(f.is_empty());
        assert_eq!(f.counters().devices_forgotten, 2);
    }

    #[test]
    fn configuration_is_polled_only_while_read() {
        let mut f = FleetView::new(limits(4, 10));
        f.plant_up("a", 0.0);
        let svc = pb::ServiceStatus {
            version: PROTOCOL_VERSION,
            controller_id: "c".into(),
            devices: vec![pb::DeviceStatus {
                device_id: "a".into(),
                ..Default::default()
            }],
            ..Default::default()
        };
        f.apply_services(&[svc], 0.0);
        assert!(f.watched(1.0, 10.0).is_empty());
        f.watch("a", 1.0);
        assert_eq!(f.watched(5.0, 10.0), ["a"]);
        assert!(f.watched(12.0, 10.0).is_empty());
    }

    fn config(min: f64, max: f64, env: (f64, f64, Option<f64>)) -> pb::DeviceConfig {
        pb::DeviceConfig {
            version: PROTOCOL_VERSION,
            device_id: "a".into(),
            channels: vec![pb::ChannelConfig {
                law: Some(pb::channel_config::Law::Intelligent(pb::Intelligent {
                    kind: pb::IntelligentKind::Ipd as i32,
                    order: 2,
                    alpha: 1.0,
                    kp: 9.0,
                    estimator: Some(pb::Estimator {
                        window: 20,
                        ..Default::default()
                    }),
                    ..Default::default()
                })),
                output: Some(pb::OutputMap {
                    min: Some(min),
                    max: Some(max),
                    ..Default::default()
                }),
            }],
            envelope: Some(pb::Envelope {
                channels: vec![pb::ChannelLimits {
                    min: Some(env.0),
                    max: Some(env.1),
                    rate_limit: env.2,
                }],
            }),
            ..Default::default()
        }
    }

    #[test]
    fn a_change_outside_the_envelope_is_refused_here() {
        let c = config(-10.0, 10.0, (-12.0, 12.0, Some(50.0)));
        let u = |f: &[&str]| {
            transport::ops::parse_update(0, &f.iter().map(|s| s.to_string()).collect::<Vec<_>>())
                .unwrap()
        };
        assert!(check_update(&u(&["kp=12"]), &c).is_ok());
        assert!(check_update(&u(&["min=-12", "max=11"]), &c).is_ok());
        let e = check_update(&u(&["max=100"]), &c).unwrap_err();
        assert!(e.contains("above the envelope"), "{e}");
        let e = check_update(&u(&["min=-13"]), &c).unwrap_err();
        assert!(e.contains("below the envelope"), "{e}");
        let e = check_update(&u(&["rate_limit=60"]), &c).unwrap_err();
        assert!(e.contains("rate_limit"), "{e}");
        let e = check_update(&u(&["min=10"]), &c).unwrap_err();
        assert!(e.contains("below max"), "{e}");
        let mut wrong_channel = u(&["kp=1"]);
        wrong_channel.channel = 3;
        assert!(check_update(&wrong_channel, &c).is_err());
        assert!(check_update(&u(&[]), &c).is_err());
        let mut nan = u(&["kp=1"]);
        nan.kp = Some(f64::NAN);
        assert!(check_update(&nan, &c).is_err());
    }

    #[test]
    fn views_name_the_fields_a_change_uses() {
        let v = channel_views(&config(-10.0, 10.0, (-12.0, 12.0, None)));
        assert_eq!(v[0].law, "ipd");
        assert_eq!(v[0].params[0], ("kp".to_string(), 9.0));
        assert_eq!(v[0].envelope.max, Some(12.0));
        fn names<T>(l: &[(String, T)]) -> Vec<String> {
            l.iter().map(|(n, _)| n.clone()).collect()
        }
        assert_eq!(
            names(&v[0].params),
            [
                "kp",
                "ki",
                "kd",
                "alpha",
                "derivative_filter",
                "derivative_observer",
                "estimate_filter",
                "hold_estimate_filter",
                "hold_after",
                "hold_band"
            ]
        );
        assert_eq!(
            v[0].output,
            [
                ("dead_zone".to_string(), Some(0.0)),
                ("smoothing".to_string(), Some(0.0)),
                ("min".to_string(), Some(-10.0)),
                ("max".to_string(), Some(10.0)),
                ("rate_limit".to_string(), None),
            ]
        );
        // Every field shown is one a change accepts, with its help.
        for name in names(&v[0].params).iter().chain(&names(&v[0].output)) {
            assert!(transport::ops::parse_update(0, &[format!("{name}=1")]).is_ok());
            assert!(v[0].help[name.as_str()].contains("sane: "), "{name}");
        }
        // A PID shows its own parameters; a law the core refuses shows none.
        let mut pid = config(-10.0, 10.0, (-12.0, 12.0, None));
        pid.channels[0].law = Some(pb::channel_config::Law::Pid(pb::Pid {
            kp: 2.0,
            ..Default::default()
        }));
        let v = channel_views(&pid);
        assert_eq!(
            (v[0].law.as_str(), names(&v[0].params)),
            (
                "pid",
                vec![
                    "kp".to_string(),
                    "ki".into(),
                    "kd".into(),
                    "derivative_filter".into(),
                    "setpoint_weight".into()
                ]
            )
        );
        let mut bad = config(-10.0, 10.0, (-12.0, 12.0, None));
        if let Some(pb::channel_config::Law::Intelligent(i)) = &mut bad.channels[0].law {
            i.alpha = 0.0;
        }
        let v = channel_views(&bad);
        assert!(v[0].params.is_empty() && v[0].output.is_empty(), "{v:?}");
        assert!(check_reference(&[0.0], 1).is_ok());
        assert!(check_reference(&[0.0, 1.0], 1).is_err());
        assert!(check_reference(&[f64::NAN], 1).is_err());
    }

    #[test]
    fn modes_come_from_the_flags() {
        assert_eq!(mode_of(0), "remote");
        assert_eq!(mode_of(1), "holding");
        assert_eq!(mode_of(3), "local");
        assert_eq!(mode_of(7), "safe_stop");
    }
}

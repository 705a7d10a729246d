//! Per-device control state and the rules for answering samples. No I/O: the Zenoh wiring
//! in [`crate::service`] feeds it decoded messages and publishes what it returns, so every
//! rule here is tested without a network.
//!
//! Rules for a sample of device `d` with sequence `s` and plant time `t`:
//! * unknown `d`: provisioned from the first matching template, else refused and counted;
//! * a new `run_id`: the plant restarted; its state is rebuilt from the configuration;
//! * `s` = last: a duplicate; the cached command is sent again (commands are idempotent);
//! * `s` < last: older than one already answered; answered `STALE`, nothing moves;
//! * `s` > last + 1: the samples in between were lost (counted); the estimator follows the
//!   timestamps, so the hole does not bias it;
//! * bad values (NaN, wrong channel count, `t` not after the last one): answered
//!   `REJECTED` with the reason, counted, state untouched;
//! * otherwise the applied inputs the plant reports are given to the estimators, the
//!   controllers step, and a `CONTROL` command carries the same `s`.

use std::collections::{BTreeMap, BTreeSet, VecDeque};

use mfc::trajectory::{evaluate, Piece};
use mfc::{ChannelConfig, ChannelOutput, MimoController, Reference};
use protocol::convert::{channel_from_pb, channel_to_pb, reference_from_pb, reference_to_pb};
use protocol::{pb, PROTOCOL_VERSION};

use crate::config::{DeviceChannel, ServiceConfig};

/// A gap longer than this (s) between a snapshot and the next sample makes the restored
/// estimators start a fresh window.
const RESUME_GAP: f64 = 0.1;
/// Most recent round trips kept per device for the status percentiles; older ones drop out.
const RTT_WINDOW: usize = 1000;
/// Unknown device ids listed in the status (each warned about once); samples from further
/// unknown ids are still counted, just not named.
const UNKNOWN_KEPT: usize = 64;

/// What to do with a sample.
#[derive(Debug, Clone, PartialEq)]
pub enum Outcome {
    /// Publish this command on the device's command key: a new answer, or the cached one
    /// again for a duplicate.
    Reply(pb::Command),
    /// Unknown device and no template: nothing to publish (counted).
    Unknown,
}

/// What the service holds for one device: its control state, where the plant's run stands,
/// and the counters of its status.
#[derive(Debug, Clone)]
struct Device {
    /// Restored from a snapshot and not yet resumed: the first sample decides whether the
    /// data history still holds (no gap) or must be forgotten.
    restored: bool,
    /// Provisioned from a template, not declared: reported in the status, and lets a
    /// snapshot rebuild the device although no declaration names it.
    from_template: bool,
    /// Laws and output maps in force (changed by `configure`); a snapshot of a declared
    /// device is restored only if its laws equal these.
    configs: Vec<ChannelConfig>,
    mimo: MimoController,
    /// Reference pieces per channel, evaluated at `plant_time - reference_start`.
    reference: Vec<Vec<Piece>>,
    /// Plant time (s) at which the reference starts: 0 from the file, moved by a live
    /// reference update.
    reference_start: f64,
    /// The plant run this state belongs to (`None` before the first sample); a sample with
    /// another one resets the control state.
    run_id: Option<u64>,
    /// Sequence number of the last sample answered with control values; rejected and stale
    /// samples do not move it.
    last_seq: Option<u64>,
    /// Plant time of that sample (s); the next must come strictly later. Minus infinity
    /// until the first one (and after a plant restart), so any first time is accepted.
    last_time: f64,
    /// The command answering `last_seq`, sent again verbatim for a duplicate. `None` after a
    /// restart or a restore.
    last_command: Option<pb::Command>,
    /// Each step's outputs per channel, a buffer reused from sample to sample.
    outputs: Vec<ChannelOutput>,
    /// The references per channel at the current sample, likewise reused.
    refs: Vec<Reference>,
    /// Samples for this device, counted before the sequence and value checks (duplicates,
    /// stale and rejected ones included; one carrying another device's id is not).
    samples: u64,
    /// Commands computed (CONTROL or WARMING_UP); not resends for duplicates, not REJECTED
    /// or STALE answers.
    commands: u64,
    /// Sequence numbers skipped between one answered sample and the next; a sample that
    /// arrived but was rejected in between counts here too.
    lost: u64,
    /// Samples repeating `last_seq`, answered with the cached command when there is one.
    duplicates: u64,
    /// Samples older than `last_seq`, answered STALE.
    stale: u64,
    /// Samples answered REJECTED: another device's id, bad values, or a step the core
    /// refused.
    rejected: u64,
    /// Samples sent while the plant was holding, on its local fallback or in safe stop:
    /// counts samples, not fallback episodes.
    samples_off_remote: u64,
    /// The plant's round-trip reports (µs), oldest first, at most `RTT_WINDOW`; a report of
    /// 0 (no round trip yet) is not kept.
    rtts: VecDeque<u32>,
    /// The last F estimate per channel; NaN until a step gives one.
    f_est: Vec<f64>,
    /// Why the last refused sample was refused; a later good sample does not clear it.
    last_error: String,
}

impl Device {
    fn new(channels: &[DeviceChannel], from_template: bool) -> Result<Self, mfc::MfcError> {
        let configs: Vec<ChannelConfig> = channels.iter().map(DeviceChannel::channel).collect();
        let n = configs.len();
        Ok(Self {
            restored: false,
            from_template,
            mimo: MimoController::new(&configs)?,
            configs,
            reference: channels.iter().map(|c| c.reference.clone()).collect(),
            reference_start: 0.0,
            run_id: None,
            last_seq: None,
            last_time: f64::NEG_INFINITY,
            last_command: None,
            outputs: vec![ChannelOutput::default(); n],
            refs: vec![Reference::default(); n],
            samples: 0,
            commands: 0,
            lost: 0,
            duplicates: 0,
            stale: 0,
            rejected: 0,
            samples_off_remote: 0,
            rtts: VecDeque::with_capacity(RTT_WINDOW),
            f_est: vec![f64::NAN; n],
            last_error: String::new(),
        })
    }

    /// A restarted plant: fresh control state, same configuration and reference. The
    /// counters carry on across runs.
    fn restart(&mut self) {
        if let Ok(m) = MimoController::new(&self.configs) {
            self.mimo = m;
        }
        self.last_seq = None;
        self.last_time = f64::NEG_INFINITY;
        self.last_command = None;
    }

    fn channels(&self) -> usize {
        self.configs.len()
    }

    fn check(&self, s: &pb::Sample) -> Result<(), String> {
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
        if let Some(bad) = s.outputs.iter().chain(&s.applied).find(|v| !v.is_finite()) {
            return Err(format!("non-finite value {bad}"));
        }
        if !s.plant_time.is_finite() || s.plant_time <= self.last_time {
            return Err(format!(
                "plant time {} does not advance past {}",
                s.plant_time, self.last_time
            ));
        }
        Ok(())
    }

    fn config_pb(&self, id: &str) -> pb::DeviceConfig {
        pb::DeviceConfig {
            version: PROTOCOL_VERSION,
            device_id: id.into(),
            channels: self.configs.iter().map(channel_to_pb).collect(),
            reference: Some(reference_to_pb(&self.reference, self.reference_start)),
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
            f_est: self.f_est.clone(),
            last_error: self.last_error.clone(),
            from_template: self.from_template,
        }
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

/// A command without control values (refusals and stale answers).
fn reply(
    controller_id: &str,
    id: &str,
    s: &pb::Sample,
    mode: pb::Mode,
    error: String,
) -> pb::Command {
    pb::Command {
        version: PROTOCOL_VERSION,
        device_id: id.into(),
        seq: s.seq,
        controller_unix_ns: protocol::unix_ns(),
        mode: mode as i32,
        sample_sent_unix_ns: s.sent_unix_ns,
        controller_id: controller_id.into(),
        error,
        ..Default::default()
    }
}

/// All devices of one controller.
#[derive(Debug)]
pub struct Registry {
    controller_id: String,
    config: ServiceConfig,
    devices: BTreeMap<String, Device>,
    /// Samples whose id is neither declared nor matched by a template.
    unknown_samples: u64,
    /// The first `UNKNOWN_KEPT` of those ids.
    unknown_devices: BTreeSet<String>,
    /// Payloads that did not decode (samples, reference updates, config requests).
    decode_errors: u64,
}

impl Registry {
    /// Build every declared device from a checked configuration.
    pub fn new(config: ServiceConfig) -> Result<Self, mfc::MfcError> {
        let mut devices = BTreeMap::new();
        for d in &config.devices {
            devices.insert(d.id.clone(), Device::new(&d.channels, false)?);
        }
        Ok(Self {
            controller_id: config.controller_id.clone(),
            config,
            devices,
            unknown_samples: 0,
            unknown_devices: BTreeSet::new(),
            decode_errors: 0,
        })
    }

    /// The snapshot settings, if any.
    pub fn snapshot_spec(&self) -> Option<&crate::config::SnapshotSpec> {
        self.config.snapshots.as_ref()
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
        self.devices.keys().map(String::as_str)
    }

    /// Count a payload that did not decode; reported as `decode_errors` in the service status.
    pub fn note_decode_error(&mut self) {
        self.decode_errors += 1;
    }

    fn provision(&mut self, id: &str) -> bool {
        let Ok(ke) = zenoh::key_expr::KeyExpr::try_from(id) else {
            return false;
        };
        for t in &self.config.templates {
            let Ok(pattern) = zenoh::key_expr::KeyExpr::try_from(t.pattern.as_str()) else {
                continue;
            };
            if pattern.includes(&ke) {
                if let Ok(d) = Device::new(&t.channels, true) {
                    tracing::info!(device = id, pattern = %t.pattern, "provisioned from template");
                    self.devices.insert(id.to_string(), d);
                    return true;
                }
            }
        }
        false
    }

    /// Answer a sample received on the key of device `key_id` (the key decides the device; a
    /// sample whose own `device_id` differs is rejected), by the rules of the module doc.
    pub fn handle_sample(&mut self, key_id: &str, s: &pb::Sample) -> Outcome {
        let controller_id = self.controller_id.clone();
        if s.device_id != key_id {
            let reason = format!(
                "device id {:?} in a sample on the key of {key_id:?}",
                s.device_id
            );
            tracing::warn!(device = key_id, "{reason}");
            if let Some(d) = self.devices.get_mut(key_id) {
                d.rejected += 1;
                d.last_error = reason.clone();
            }
            return Outcome::Reply(reply(&controller_id, key_id, s, pb::Mode::Rejected, reason));
        }
        if !self.devices.contains_key(key_id) && !self.provision(key_id) {
            self.unknown_samples += 1;
            if self.unknown_devices.len() < UNKNOWN_KEPT
                && self.unknown_devices.insert(key_id.into())
            {
                tracing::warn!(
                    device = key_id,
                    "sample from an unknown device (no template matches): refused"
                );
            }
            return Outcome::Unknown;
        }
        let Some(d) = self.devices.get_mut(key_id) else {
            return Outcome::Unknown;
        };
        if d.run_id.is_some_and(|r| r != s.run_id) {
            tracing::info!(device = key_id, "plant restarted (new run id): state reset");
            d.restart();
        }
        d.run_id = Some(s.run_id);
        d.samples += 1;
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
        match d.last_seq {
            Some(last) if s.seq == last => {
                d.duplicates += 1;
                if let Some(c) = &d.last_command {
                    return Outcome::Reply(c.clone());
                }
            }
            Some(last) if s.seq < last => {
                d.stale += 1;
                return Outcome::Reply(reply(
                    &controller_id,
                    key_id,
                    s,
                    pb::Mode::Stale,
                    String::new(),
                ));
            }
            _ => {}
        }
        if let Err(reason) = d.check(s) {
            d.rejected += 1;
            tracing::debug!(device = key_id, seq = s.seq, "sample refused: {reason}");
            d.last_error = reason.clone();
            return Outcome::Reply(reply(&controller_id, key_id, s, pb::Mode::Rejected, reason));
        }
        if let Some(last) = d.last_seq {
            d.lost += s.seq.saturating_sub(last + 1);
        }
        if d.last_seq.is_some() && !s.applied.is_empty() {
            // Checked finite above, so this cannot fail.
            let _ = d.mimo.report_applied(&s.applied);
        }
        if std::mem::take(&mut d.restored) && s.plant_time - d.last_time > RESUME_GAP {
            // Restarted from a snapshot after a gap: the estimators' history does not reach
            // across it. Keep gains and the reference phase, and start bumplessly from what
            // the plant applies now (its local fallback's output, reported above).
            d.mimo.forget_windows();
        }
        for (r, pieces) in d.refs.iter_mut().zip(&d.reference) {
            *r = evaluate(pieces, s.plant_time - d.reference_start);
        }
        if let Err(e) = d
            .mimo
            .step(s.plant_time, &s.outputs, &d.refs, &mut d.outputs)
        {
            d.rejected += 1;
            d.last_error = e.to_string();
            return Outcome::Reply(reply(
                &controller_id,
                key_id,
                s,
                pb::Mode::Rejected,
                e.to_string(),
            ));
        }
        d.last_seq = Some(s.seq);
        d.last_time = s.plant_time;
        for (f, o) in d.f_est.iter_mut().zip(&d.outputs) {
            *f = o.f_est.unwrap_or(f64::NAN);
        }
        let command = pb::Command {
            version: PROTOCOL_VERSION,
            device_id: key_id.into(),
            seq: s.seq,
            u: d.outputs.iter().map(|o| o.u).collect(),
            v: d.outputs.iter().map(|o| o.v).collect(),
            controller_unix_ns: protocol::unix_ns(),
            f_est: d.f_est.clone(),
            mode: if d.outputs.iter().any(|o| o.warming_up) {
                pb::Mode::WarmingUp
            } else {
                pb::Mode::Control
            } as i32,
            sample_sent_unix_ns: s.sent_unix_ns,
            controller_id,
            error: String::new(),
        };
        d.commands += 1;
        d.last_command = Some(command.clone());
        Outcome::Reply(command)
    }

    /// The configuration of a device, if served.
    pub fn config_of(&self, id: &str) -> Option<pb::DeviceConfig> {
        self.devices.get(id).map(|d| d.config_pb(id))
    }

    /// Apply a configuration request, all or nothing, bumplessly. Empty `channels` keeps the
    /// laws, no `reference` keeps the reference; the reply carries the configuration in
    /// force afterwards, accepted or not (none for an unknown device).
    pub fn configure(&mut self, id: &str, req: &pb::ConfigRequest) -> pb::ConfigReply {
        let refuse = |reason: String, config: Option<pb::DeviceConfig>| pb::ConfigReply {
            version: PROTOCOL_VERSION,
            accepted: false,
            reason,
            config,
        };
        let Some(d) = self.devices.get_mut(id) else {
            return refuse(format!("unknown device {id:?}"), None);
        };
        let n = d.channels();
        let configs = if req.channels.is_empty() {
            None
        } else {
            if req.channels.len() != n {
                return refuse(
                    format!(
                        "device has {n} channels, request has {}",
                        req.channels.len()
                    ),
                    Some(d.config_pb(id)),
                );
            }
            match req
                .channels
                .iter()
                .enumerate()
                .map(|(i, c)| {
                    channel_from_pb(c)
                        .map_err(|e| format!("channels[{i}].{}: {}", e.field, e.reason))
                })
                .collect::<Result<Vec<_>, _>>()
            {
                Ok(c) => Some(c),
                Err(reason) => return refuse(reason, Some(d.config_pb(id))),
            }
        };
        let reference = match &req.reference {
            None => None,
            Some(r) => match reference_from_pb(r) {
                Ok((pieces, _)) if pieces.len() != n => {
                    return refuse(
                        format!("device has {n} channels, reference has {}", pieces.len()),
                        Some(d.config_pb(id)),
                    )
                }
                Ok(r) => Some(r),
                Err(e) => {
                    return refuse(format!("{}: {}", e.field, e.reason), Some(d.config_pb(id)))
                }
            },
        };
        if let Some(configs) = configs {
            if let Err(e) = d.mimo.reconfigure(&configs) {
                return refuse(e.to_string(), Some(d.config_pb(id)));
            }
            d.configs = configs;
        }
        if let Some((pieces, start)) = reference {
            d.reference = pieces;
            d.reference_start = start;
        }
        tracing::info!(device = id, "configuration changed");
        pb::ConfigReply {
            version: PROTOCOL_VERSION,
            accepted: true,
            reason: String::new(),
            config: Some(d.config_pb(id)),
        }
    }

    /// Replace a device's reference (live steering).
    pub fn set_reference(&mut self, id: &str, update: &pb::ReferenceUpdate) -> Result<(), String> {
        let req = pb::ConfigRequest {
            version: PROTOCOL_VERSION,
            channels: Vec::new(),
            reference: update.reference.clone(),
        };
        let reply = self.configure(id, &req);
        if reply.accepted {
            Ok(())
        } else {
            Err(reply.reason)
        }
    }

    /// Status of one device.
    pub fn device_status(&self, id: &str) -> Option<pb::DeviceStatus> {
        self.devices.get(id).map(|d| d.status_pb(id))
    }

    /// Status of the whole service, `uptime` in seconds. It reports `active` true and term
    /// 0: the caller overwrites them with its hot-standby state.
    pub fn service_status(&self, uptime: f64) -> pb::ServiceStatus {
        pb::ServiceStatus {
            version: PROTOCOL_VERSION,
            controller_id: self.controller_id.clone(),
            devices: self.devices.iter().map(|(id, d)| d.status_pb(id)).collect(),
            unknown_samples: self.unknown_samples,
            unknown_devices: self.unknown_devices.iter().cloned().collect(),
            decode_errors: self.decode_errors,
            uptime,
            active: true,
            term: 0,
        }
    }
}

impl Registry {
    /// Snapshots of every device (for [`crate::snapshot`]); a device whose control state
    /// does not encode is left out.
    pub fn snapshots(&self) -> Vec<crate::snapshot::DeviceSnapshot> {
        self.devices
            .iter()
            .filter_map(|(id, d)| {
                Some(crate::snapshot::DeviceSnapshot {
                    version: crate::snapshot::SNAPSHOT_VERSION,
                    id: id.clone(),
                    mimo: mfc::snapshot::to_bytes(&d.mimo).ok()?,
                    reference: d.reference.clone(),
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
            })
            .collect()
    }

    /// Restore a device from its snapshot. Refused (and the device left as configured) if
    /// the snapshot's laws differ from the configuration in force: a changed configuration
    /// wins over an old state.
    pub fn restore(&mut self, snap: &crate::snapshot::DeviceSnapshot) -> Result<(), String> {
        let mimo: MimoController =
            mfc::snapshot::from_bytes(&snap.mimo).map_err(|e| e.to_string())?;
        let configs: Vec<ChannelConfig> = mimo.channels().iter().map(|c| *c.config()).collect();
        let d = match self.devices.get_mut(&snap.id) {
            Some(d) => d,
            None if snap.from_template => {
                let specs: Vec<DeviceChannel> = configs
                    .iter()
                    .map(|c| DeviceChannel {
                        law: c.law,
                        output: c.output,
                        reference: Vec::new(),
                    })
                    .collect();
                let d = Device::new(&specs, true).map_err(|e| e.to_string())?;
                self.devices.entry(snap.id.clone()).or_insert(d)
            }
            None => return Err(format!("device {:?} is no longer configured", snap.id)),
        };
        if !snap.from_template && configs != d.configs {
            return Err(format!(
                "device {:?}: configuration changed since the snapshot",
                snap.id
            ));
        }
        if snap.reference.len() != configs.len() {
            return Err(format!(
                "device {:?}: reference has the wrong number of channels",
                snap.id
            ));
        }
        d.outputs = vec![ChannelOutput::default(); configs.len()];
        d.refs = vec![Reference::default(); configs.len()];
        d.f_est = vec![f64::NAN; configs.len()];
        d.configs = configs;
        d.mimo = mimo;
        d.reference = snap.reference.clone();
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

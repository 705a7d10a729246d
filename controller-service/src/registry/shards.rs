//! Fleet support ([`crate::fleet`]) and snapshots: which shard each device lives in, a
//! shard's state as handed between members, a device's state as saved and restored. The
//! files themselves are [`crate::snapshot`]'s.

use mfc::{ChannelConfig, ChannelOutput, MimoController, Reference};
use protocol::{pb, printable};

use super::device::{Device, ShortId};
use super::Registry;
use crate::envelope::Limits;
use crate::snapshot::{DeviceSnapshot, HandedDevice, ShardState, SNAPSHOT_VERSION};

/// What [`Registry::restore_shard`] did.
#[derive(Debug, Default, Clone, PartialEq)]
pub struct Restored {
    /// Devices restored.
    pub restored: usize,
    /// Devices whose state here is already as new (the same changes), kept.
    pub same: usize,
    /// Devices refused: their id (printable) and why (an older configuration among them).
    pub refused: Vec<(String, String)>,
    /// Audit entries handed with the devices that this member did not have yet, for its
    /// own audit file.
    pub audit: Vec<pb::AuditEntry>,
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

    /// The state of the devices `ids` (those served), as a one-shard handover of `shard`:
    /// what an owner sends its standby after a configuration change.
    pub fn devices_state(&self, shard: u32, ids: &[&str]) -> ShardState {
        ShardState {
            version: SNAPSHOT_VERSION,
            shard,
            devices: ids
                .iter()
                .filter_map(|id| Self::handed(id, self.devices.get(id)?))
                .collect(),
        }
    }

    /// The state of every device of `shard`, for a handover.
    pub fn shard_state(&self, shard: u32) -> ShardState {
        ShardState {
            version: SNAPSHOT_VERSION,
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
    /// sample continues bumplessly. Returns how many were restored, and each device
    /// refused with its reason (for the caller to log).
    ///
    /// A handed state replaces this member's only if its configuration is not older
    /// ([`crate::lease::Version`]), and not a state as new while this member holds the
    /// device's lease (its own is the one in force). A device handed by the member that
    /// holds its lease, under an epoch not older than this member has heard, with every
    /// change this member now holds, is in step with the holder
    /// ([`crate::lease::Claimer::caught_up`]).
    pub fn restore_shard(&mut self, state: &ShardState) -> Restored {
        self.take_shard(state, false)
    }

    /// [`Registry::restore_shard`] for a change to hold (or the states a holder sends its
    /// partners): besides, a device under a lease is taken only from the member that
    /// holds it, under an epoch not older than this member has heard. A member cut off
    /// from the plant, which still believes it holds, cannot have its changes held here
    /// once this member has heard of its successor.
    pub fn hold_shard(&mut self, state: &ShardState) -> Restored {
        self.take_shard(state, true)
    }

    fn take_shard(&mut self, state: &ShardState, hold: bool) -> Restored {
        let mut out = Restored::default();
        for h in &state.devices {
            let id = h.snapshot.id.as_str();
            if hold {
                if let Some(why) = self.devices.get(id).and_then(|d| d.not_holder(h.holds)) {
                    out.refused.push((printable(id), why));
                    continue;
                }
            }
            let here = self.devices.get(id).map(|d| {
                let holds = d.claimer.holder == crate::lease::Holder::Me;
                (d.version, holds, d.lease_key())
            });
            let heard = here.map_or((0, 0), |x| x.2);
            match here {
                Some((v, _, _)) if h.config_version < v => {
                    let why = format!("its configuration ({v:?}) is newer than the one handed");
                    out.refused.push((printable(id), why));
                    continue;
                }
                Some((v, true, _)) if h.config_version == v => out.same += 1,
                _ => match self.restore_handed(h) {
                    Ok(()) => out.restored += 1,
                    Err(reason) => {
                        out.refused.push((printable(id), reason));
                        continue;
                    }
                },
            }
            if let Some(d) = self.devices.get_mut(id) {
                if let Ok(log) = protocol::decode::<pb::AuditLog>(&h.audit) {
                    let handed: Vec<_> = log
                        .entries
                        .into_iter()
                        .filter(|e| e.device_id == id)
                        .collect();
                    if !handed.is_empty() {
                        let kept = &mut d.rare.get_mut().audit;
                        out.audit.extend(crate::audit::merge(kept, &handed));
                    }
                }
                d.version = d.version.max(h.config_version);
                if let Some(k) = h.holds.filter(|k| *k >= heard) {
                    d.claimer.caught_up(k);
                } else {
                    d.claimer.heard_of(h.heard);
                }
            }
        }
        out
    }

    fn restore_handed(&mut self, h: &HandedDevice) -> Result<(), String> {
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
        // handed one: a handover never widens what the file allows here. Where the file
        // allows remote widening (the same file on every member), the handed envelope is
        // taken as it is: a widening the owner acknowledged is held here too.
        if !self.devices.contains_key(h.snapshot.id.as_str()) {
            self.provision(&h.snapshot.id)
                .map_err(|why| format!("cannot serve it here: {why:?}"))?;
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
        let widen = self.config.allow_remote_widening;
        let narrowed: Vec<Limits> = d
            .envelope
            .iter()
            .zip(&envelope)
            .map(|(mine, theirs)| {
                if widen {
                    *theirs
                } else {
                    mine.intersect(theirs)
                }
            })
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
                    self.devices.insert(ShortId::new(&id), Box::new(fresh));
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
    pub fn snapshots(&self) -> Vec<DeviceSnapshot> {
        self.snapshots_where(|_, _| true)
    }

    fn snapshots_where(&self, keep: impl Fn(&str, &Device) -> bool) -> Vec<DeviceSnapshot> {
        self.sorted()
            .into_iter()
            .filter(|(id, d)| keep(id, d))
            .filter_map(|(id, d)| Self::snapshot_of(id, d))
            .collect()
    }

    /// One device's snapshot; `None` if its control state does not encode.
    fn snapshot_of(id: &str, d: &Device) -> Option<DeviceSnapshot> {
        Some(DeviceSnapshot {
            version: SNAPSHOT_VERSION,
            id: id.to_string(),
            mimo: mfc::snapshot::to_bytes(&d.mimo).ok()?,
            reference: d.reference.to_vec(),
            reference_start: d.reference_start,
            run_id: d.run_id,
            last_seq: d.last_seq,
            last_time: d.last_time,
            counters: d.counters(),
            from_template: d.from_template,
        })
    }

    /// One device as handed to another fleet member: its snapshot, shard and envelope.
    fn handed(id: &str, d: &Device) -> Option<HandedDevice> {
        Some(HandedDevice {
            snapshot: Self::snapshot_of(id, d)?,
            home: d.home,
            envelope: d
                .envelope
                .iter()
                .map(|l| (l.min, l.max, l.rate_limit))
                .collect(),
            live_config: true,
            config_version: d.version,
            holds: (d.claimer.holder == crate::lease::Holder::Me).then(|| d.lease_key()),
            heard: d.lease_key(),
            audit: protocol::encode(&pb::AuditLog {
                version: protocol::PROTOCOL_VERSION,
                device_id: id.into(),
                entries: d.rare.get().audit.iter().cloned().collect(),
            }),
        })
    }

    /// Restore a device from its snapshot file: its control state (estimators, integrals,
    /// sequence, run, counters), never its configuration. The laws, output maps, envelope
    /// and reference in force stay (the file's, or the journal's put back by
    /// [`Registry::recover`] before the snapshots are read), and the restored controller is
    /// moved to them bumplessly: a snapshot older than an acknowledged change cannot roll it
    /// back, one newer than the file cannot undo an edit of the file.
    pub fn restore(&mut self, snap: &DeviceSnapshot) -> Result<(), String> {
        self.restore_with(snap, false)
    }

    /// [`Registry::restore`]; with `live_config` (a handover from another member, on which
    /// the laws may have been changed remotely), the snapshot's laws and reference are
    /// taken instead. The output maps must still lie inside the envelope.
    fn restore_with(&mut self, snap: &DeviceSnapshot, live_config: bool) -> Result<(), String> {
        let mut mimo: MimoController =
            mfc::snapshot::from_bytes(&snap.mimo).map_err(|e| e.to_string())?;
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
                self.devices.or_insert(ShortId::new(&snap.id), Box::new(d))
            }
            None => return Err(format!("device {:?} is no longer configured", snap.id)),
        };
        if mimo.channels().len() != d.channels() {
            return Err(format!(
                "device {:?}: the snapshot has {} channels, the device {}",
                snap.id,
                mimo.channels().len(),
                d.channels()
            ));
        }
        if !live_config {
            mimo.reconfigure(&d.configs())
                .map_err(|e| format!("device {:?}: {e}", snap.id))?;
        }
        let configs: Vec<ChannelConfig> = mimo.channels().iter().map(|c| c.config()).collect();
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
        d.mimo = mimo;
        if live_config {
            d.reference = snap.reference.iter().cloned().collect();
            d.reference_start = snap.reference_start;
        }
        d.run_id = snap.run_id;
        d.last_seq = snap.last_seq;
        d.last_time = snap.last_time;
        d.set_counters(snap.counters);
        d.last_command = None;
        if let Some(rare) = d.rare.existing() {
            rare.retired.clear();
        }
        d.restored = true;
        d.abort_commission("the device's state was restored");
        Ok(())
    }
}

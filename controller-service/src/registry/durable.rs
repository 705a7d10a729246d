//! What makes an operator's change durable, on the registry's side: a change is *tried*
//! first (applied, its result noted, the device put back as it was), its record made
//! durable by the caller, and only then applied for real (`service::operators`); a restart
//! puts every device's journaled state back in force ([`Registry::recover`]), merged with
//! the service's file where the file was edited since ([`merge`]).
//!
//! The precedence, in one sentence: a setting the file changed since the journaled state
//! was made is a change of its own, made at this start and recorded like any other;
//! every other setting keeps its acknowledged live value. "A setting" is one parameter of a
//! channel's law (`kp`, `alpha`: `mfc::params`), one field of its output map or envelope, or
//! the reference as a whole; a file that changes a channel's law to another kind, or a field
//! no parameter names, replaces that channel's law and map whole, and a file that changes
//! the number of channels replaces the device whole.

use std::collections::BTreeMap;

use mfc::params::{names, param};
use mfc::ChannelConfig;
use protocol::convert::{channel_from_pb, channel_to_pb, reference_from_pb};
use protocol::pb;

use super::device::Device;
use super::Registry;
use crate::envelope::Limits;
use crate::journal::State;
use crate::lease::Version;

/// A change tried on a device ([`Registry::trial`]): the configuration it was tried on,
/// the one it would leave, and what it moves, by setting.
#[derive(Debug, Clone, PartialEq)]
pub struct ChangeTrial {
    pub before: (pb::DeviceConfig, Version),
    pub after: (pb::DeviceConfig, Version),
    pub changes: Vec<pb::AuditChange>,
}

/// A device's configuration changed at a start because the file was edited since its
/// journaled state was made ([`Registry::recover`]).
#[derive(Debug, Clone, PartialEq)]
pub struct FileChange {
    pub device: String,
    /// The state now in force, to journal.
    pub state: State,
    /// What moved from the journaled state, by setting.
    pub changes: Vec<pb::AuditChange>,
    /// How the file and the live changes were joined.
    pub how: String,
}

/// What [`Registry::recover`] did.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Recovery {
    /// Devices put back in their journaled state as it was.
    pub restored: usize,
    /// Devices whose file was edited since: each a change to journal before serving.
    pub file_changes: Vec<FileChange>,
    /// Journaled devices not served any more, each with why.
    pub dropped: Vec<(String, String)>,
}

impl Registry {
    /// The configuration in force for `id` and the version of the change that left it.
    pub fn state_of(&self, id: &str) -> Option<(pb::DeviceConfig, Version)> {
        self.devices.get(id).map(|d| (d.config_pb(id), d.version))
    }

    /// The configuration the service's file gives `id`: its declaration's, or that of the
    /// template that matches it; `None` if neither does.
    pub fn file_config_of(&self, id: &str) -> Option<pb::DeviceConfig> {
        let declared = self.config.devices.iter().find(|d| d.id == id);
        let (channels, prediction, template) = match declared {
            Some(d) => (&d.channels, d.prediction, false),
            None => {
                let t = self.template_for(id)?;
                (&t.channels, t.prediction, true)
            }
        };
        Device::new(channels, prediction, template)
            .ok()
            .map(|d| d.config_pb(id))
    }

    /// Try a change on `id`: `apply` makes it as it would be made, then the device is put
    /// back as it was. Returns `apply`'s reply and, for an accepted change, what it would
    /// leave ([`ChangeTrial`]). An accepted change changes nothing here; a refusal is counted as
    /// `apply` counts it (the registry's and the device's refusals, its last error).
    pub fn trial(
        &mut self,
        id: &str,
        apply: impl FnOnce(&mut Self) -> pb::ConfigReply,
    ) -> (pb::ConfigReply, Option<ChangeTrial>) {
        let Some(saved) = self.devices.get(id).cloned() else {
            return (apply(self), None);
        };
        let before = (saved.config_pb(id), saved.version);
        let settings = saved.settings();
        let reply = apply(self);
        if !reply.accepted {
            // A refusal changes nothing but what counts it (the device's refusals, its last
            // error): those stay, as they would for any refusal.
            return (reply, None);
        }
        let d = self.devices.get(id).expect("tried on a served device");
        let trial = ChangeTrial {
            before,
            after: (d.config_pb(id), d.version),
            changes: crate::audit::diff(&settings, &d.settings()),
        };
        self.put_back(id, saved);
        (reply, Some(trial))
    }

    /// Make a change tried earlier, now that its record is durable: `apply` must find the
    /// device in the state it was tried on and leave the state recorded
    /// ([`ChangeTrial::after`]); otherwise the device is left as it was and why is returned (the
    /// caller withdraws the change). `apply` is the same change as tried.
    pub fn commit(
        &mut self,
        id: &str,
        trial: &ChangeTrial,
        apply: impl FnOnce(&mut Self) -> pb::ConfigReply,
    ) -> Result<pb::ConfigReply, String> {
        if self.state_of(id).as_ref() != Some(&trial.before) {
            return Err("the device's configuration changed while the change was written (a fleet member's state taken meanwhile)".into());
        }
        let saved = self
            .save(id)
            .ok_or("the device is not served here any more")?;
        let reply = apply(self);
        if !reply.accepted {
            self.put_back(id, saved);
            return Err(format!("refused when made: {}", reply.reason));
        }
        if self.state_of(id).as_ref() != Some(&trial.after) {
            self.put_back(id, saved);
            return Err("made now, it would leave another state than the one recorded (the plant's lease changed meanwhile)".into());
        }
        Ok(reply)
    }

    /// A copy of the device `id` as it is, to [`Registry::put_back`] if what follows must
    /// be undone.
    fn save(&self, id: &str) -> Option<Device> {
        self.devices.get(id).cloned()
    }

    /// Put back a device [`Registry::save`]d (it is served again as it was then).
    fn put_back(&mut self, id: &str, saved: Device) {
        if let Some(d) = self.devices.get_mut(id) {
            *d = saved;
        }
    }

    /// Put `state` in force on `id` (laws and output maps bumplessly, envelope, reference
    /// and its start, version), all or nothing: refused if it does not fit the device (its
    /// channels, an output map outside its envelope, a law the core refuses).
    pub fn put_state(
        &mut self,
        id: &str,
        state: &pb::DeviceConfig,
        version: Version,
    ) -> Result<(), String> {
        let d = self.devices.get_mut(id).ok_or("not served")?;
        let n = d.channels();
        let (configs, envelope, reference) = parse_state(state, n)?;
        d.mimo.reconfigure(&configs).map_err(|e| e.to_string())?;
        d.envelope = envelope.into();
        d.reference = reference.0.into();
        d.reference_start = reference.1;
        d.version = version;
        Ok(())
    }

    /// Put every journaled state in `states` back in force, before anything is served: a
    /// device served by the file (declared, or matched by a template, which provisions it
    /// now) gets its state as journaled, or, where the file was edited since, the state
    /// [`merge`] makes of both. Each of the latter is a change to journal (and audit)
    /// before the service answers anyone.
    pub fn recover(&mut self, states: &BTreeMap<String, State>) -> Recovery {
        let mut out = Recovery::default();
        for (id, st) in states {
            if let Err(why) = self.provision(id) {
                let why =
                    format!("not served any more ({why:?}): its live changes are not in force");
                out.dropped.push((id.clone(), why));
                continue;
            }
            let Some(file) = self.file_config_of(id) else {
                out.dropped
                    .push((id.clone(), "no configuration in the file".into()));
                continue;
            };
            if file == st.file {
                match self.put_state(id, &st.config, st.version) {
                    Ok(()) => out.restored += 1,
                    Err(why) => self.file_wins(id, st, &file, why, &mut out),
                }
                continue;
            }
            let merged = merge(&st.file, &st.config, &file);
            let checked = merged.and_then(|m| {
                self.fits_bounds(id, &m)?;
                Ok(m)
            });
            match checked {
                Ok(m) => {
                    let how = "the file was edited since: the settings it changed are taken \
                               from it, every other keeps its live value"
                        .to_string();
                    self.file_change(id, st, m, how, &mut out);
                }
                Err(why) => self.file_wins(id, st, &file, why, &mut out),
            }
        }
        out
    }

    /// The file's configuration of `id` in force (it is already: the device was built from
    /// it), recorded as a change from the journaled state with the reason it won.
    fn file_wins(
        &mut self,
        id: &str,
        st: &State,
        file: &pb::DeviceConfig,
        why: String,
        out: &mut Recovery,
    ) {
        let how = format!("the file's configuration, whole: the live one cannot be kept ({why})");
        self.file_change(id, st, file.clone(), how, out);
    }

    fn file_change(
        &mut self,
        id: &str,
        st: &State,
        config: pb::DeviceConfig,
        how: String,
        out: &mut Recovery,
    ) {
        let before = self.settings_as(id, &st.config, st.version);
        if let Err(why) = self.put_state(id, &config, st.version) {
            out.dropped.push((
                id.to_string(),
                format!("the file's configuration does not fit: {why}"),
            ));
            return;
        }
        let after = self.settings_of(id).unwrap_or_default();
        let file = self.file_config_of(id).unwrap_or_else(|| config.clone());
        out.file_changes.push(FileChange {
            device: id.to_string(),
            state: State {
                config,
                version: st.version,
                file,
            },
            changes: crate::audit::diff(&before, &after),
            how,
        });
    }

    /// The settings `id` would have with `config` in force (empty if it does not fit).
    fn settings_as(
        &mut self,
        id: &str,
        config: &pb::DeviceConfig,
        v: Version,
    ) -> BTreeMap<String, String> {
        let Some(saved) = self.save(id) else {
            return BTreeMap::new();
        };
        let out = match self.put_state(id, config, v) {
            Ok(()) => self.settings_of(id).unwrap_or_default(),
            Err(_) => BTreeMap::new(),
        };
        self.put_back(id, saved);
        out
    }

    /// Whether `config`'s laws lie within the bounds a change of `id` is held to.
    fn fits_bounds(&self, id: &str, config: &pb::DeviceConfig) -> Result<(), String> {
        let d = self.devices.get(id).ok_or("not served")?;
        let (configs, _, (pieces, _)) = parse_state(config, d.channels())?;
        d.check_bounds(&configs, Some(&pieces))
    }
}

type Parsed = (
    Vec<ChannelConfig>,
    Vec<Limits>,
    (Vec<Vec<mfc::trajectory::Piece>>, f64),
);

/// A state's laws, envelope and reference, checked for a device of `n` channels.
fn parse_state(s: &pb::DeviceConfig, n: usize) -> Result<Parsed, String> {
    let count = |what: &str, k: usize| {
        if k == n {
            Ok(())
        } else {
            Err(format!("{k} {what} for a device of {n} channels"))
        }
    };
    count("channels", s.channels.len())?;
    let limits = s.envelope.clone().unwrap_or_default().channels;
    count("envelope channels", limits.len())?;
    let envelope = limits
        .iter()
        .enumerate()
        .map(|(i, l)| super::requests::limits_from_pb(l, i))
        .collect::<Result<Vec<_>, _>>()?;
    let configs = s
        .channels
        .iter()
        .map(|c| channel_from_pb(c).map_err(|e| format!("{}: {}", e.field, e.reason)))
        .collect::<Result<Vec<_>, _>>()?;
    for (i, (c, l)) in configs.iter().zip(&envelope).enumerate() {
        if c.output != l.narrow(c.output) {
            return Err(format!(
                "channel {i}'s output map lies outside its envelope"
            ));
        }
    }
    let reference = reference_from_pb(&s.reference.clone().unwrap_or_default())
        .map_err(|e| format!("{}: {}", e.field, e.reason))?;
    count("reference channels", reference.0.len())?;
    Ok((configs, envelope, reference))
}

/// The state in force when the file went from `base` to `file` while the live state went
/// from `base` to `live` (module documentation): per setting, the file's where the file
/// changed it, the live one otherwise; output maps narrowed into the envelope that results.
pub fn merge(
    base: &pb::DeviceConfig,
    live: &pb::DeviceConfig,
    file: &pb::DeviceConfig,
) -> Result<pb::DeviceConfig, String> {
    let n = file.channels.len();
    if base.channels.len() != n || live.channels.len() != n {
        return Err("the file changed the device's channels".into());
    }
    let ch = |c: &pb::DeviceConfig, i: usize| {
        channel_from_pb(&c.channels[i])
            .map_err(|e| format!("channel {i}: {}: {}", e.field, e.reason))
    };
    let limits = |c: &pb::DeviceConfig| -> Result<Vec<Limits>, String> {
        let l = c.envelope.clone().unwrap_or_default().channels;
        if l.len() != n {
            return Err("an envelope of another number of channels".into());
        }
        l.iter()
            .enumerate()
            .map(|(i, l)| super::requests::limits_from_pb(l, i))
            .collect()
    };
    let (eb, el, ef) = (limits(base)?, limits(live)?, limits(file)?);
    let mut channels = Vec::with_capacity(n);
    let mut envelope = Vec::with_capacity(n);
    for i in 0..n {
        let e = merge_limits(&eb[i], &el[i], &ef[i]);
        e.check()
            .map_err(|why| format!("channel {i}'s envelope: {why}"))?;
        let c = merge_channel(&ch(base, i)?, &ch(live, i)?, &ch(file, i)?);
        channels.push(channel_to_pb(&ChannelConfig {
            law: c.law,
            output: e.narrow(c.output),
        }));
        envelope.push(e);
    }
    let reference = if file.reference == base.reference {
        live.reference.clone()
    } else {
        file.reference.clone()
    };
    Ok(pb::DeviceConfig {
        version: protocol::PROTOCOL_VERSION,
        device_id: file.device_id.clone(),
        channels,
        reference,
        envelope: Some(pb::Envelope {
            channels: envelope.iter().map(limits_to_pb).collect(),
        }),
    })
}

fn limits_to_pb(l: &Limits) -> pb::ChannelLimits {
    pb::ChannelLimits {
        min: l.min.is_finite().then_some(l.min),
        max: l.max.is_finite().then_some(l.max),
        rate_limit: l.rate_limit,
    }
}

/// Per field: the file's where it moved from `base`, the live one otherwise.
fn pick<T: PartialEq + Copy>(base: T, live: T, file: T) -> T {
    if file == base {
        live
    } else {
        file
    }
}

fn merge_limits(base: &Limits, live: &Limits, file: &Limits) -> Limits {
    Limits {
        min: pick(base.min, live.min, file.min),
        max: pick(base.max, live.max, file.max),
        rate_limit: pick(base.rate_limit, live.rate_limit, file.rate_limit),
    }
}

/// One channel: per parameter where all three have the same kind of law; the file's whole
/// where it changed the kind, or a field that no parameter names.
fn merge_channel(
    base: &ChannelConfig,
    live: &ChannelConfig,
    file: &ChannelConfig,
) -> ChannelConfig {
    if file == base {
        return *live;
    }
    if live == base {
        return *file;
    }
    let kind = base.law.kind();
    if file.law.kind() != kind || live.law.kind() != kind {
        return *file;
    }
    let params: Vec<_> = names()
        .filter_map(param)
        .filter(|p| p.applies_to(kind))
        .collect();
    // The file's change lies in the parameters alone if the file, with the base's values
    // put back, is the base.
    let mut probe = *file;
    let mut moved = Vec::new();
    for p in &params {
        if let (Ok(b), Ok(f)) = (p.get(base), p.get(file)) {
            if f.to_bits() != b.to_bits() {
                let _ = p.set(&mut probe, b);
                moved.push((p, f));
            }
        }
    }
    if no_rate_limit(probe) != *base {
        return *file;
    }
    let mut out = *live;
    for (p, f) in moved {
        let _ = p.set(&mut out, f);
    }
    no_rate_limit(out)
}

/// An infinite rate limit is none (the parameter table reads a missing one as infinite).
fn no_rate_limit(mut c: ChannelConfig) -> ChannelConfig {
    if c.output.rate_limit.is_some_and(f64::is_infinite) {
        c.output.rate_limit = None;
    }
    c
}

//! Configuration, reference and envelope changes: each all or nothing, checked before
//! anything changes, never outside the device's envelope; the reply carries the
//! configuration in force afterwards.

use mfc::ChannelConfig;
use protocol::{pb, printable, PROTOCOL_VERSION};

use super::device::Device;
use super::{capped, Registry};
use crate::envelope::Limits;

impl Registry {
    /// The safety envelope in force for a device, if served.
    pub fn envelope_of(&self, id: &str) -> Option<Vec<Limits>> {
        self.devices.get(id).map(|d| d.envelope.to_vec())
    }

    /// Every setting of a device an operator may change, as text by name, if served
    /// (an audit entry's old and new values: `crate::audit::diff`).
    pub fn settings_of(&self, id: &str) -> Option<std::collections::BTreeMap<String, String>> {
        self.devices.get(id).map(|d| d.settings())
    }

    /// Keep an audit entry with its device (dropped if the device is not served).
    pub fn audit(&mut self, entry: pb::AuditEntry) {
        if let Some(d) = self.devices.get_mut(entry.device_id.as_str()) {
            crate::audit::push(&mut d.rare.get_mut().audit, entry);
        }
    }

    /// A device's latest audit entries, oldest first, if served.
    pub fn audit_of(&self, id: &str) -> Option<pb::AuditLog> {
        self.devices.get(id).map(|d| pb::AuditLog {
            version: PROTOCOL_VERSION,
            device_id: id.into(),
            entries: d.rare.get().audit.iter().cloned().collect(),
        })
    }

    /// Refuse a request on `id` before it is looked at (who asks may not make it, the
    /// audit trail is full): counted, kept as the device's last error, and the reply
    /// carries the configuration in force.
    pub fn refuse_request(&mut self, id: &str, why: String) -> pb::ConfigReply {
        let why = capped(why);
        self.requests_refused += 1;
        let config = self.devices.get_mut(id).map(|d| {
            d.rare.get_mut().last_error.clone_from(&why);
            d.config_pb(id)
        });
        refused(why, config)
    }

    /// Whether an envelope request would widen the envelope of `id` on some channel (an
    /// admin's change); false if it does not apply (it is then refused for its own
    /// reason).
    pub fn widens(&self, id: &str, req: &pb::EnvelopeRequest) -> bool {
        let Some(d) = self.devices.get(id) else {
            return false;
        };
        let asked = req.envelope.clone().unwrap_or_default().channels;
        asked
            .iter()
            .enumerate()
            .any(|(i, l)| match (limits_from_pb(l, i), d.envelope.get(i)) {
                (Ok(l), Some(now)) => now.is_widened_by(&l),
                _ => false,
            })
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
            Ok(reference)
        });
        let applied = planned.map(|reference| {
            d.abort_commission("the configuration changed");
            if let Some((pieces, start)) = reference {
                d.reference = pieces.into();
                d.reference_start = start;
            }
        });
        conclude(d, &mut self.requests_refused, id, applied)
    }

    /// A commissioning request (`super::commission`) from `who`: start a run, confirm
    /// its proposal, or abort. The reply carries the configuration in force afterwards;
    /// the run's progress is in the device's status.
    ///
    /// `now_unix_ns` is when the service heard it: a run on a device silent for
    /// [`super::commission::SILENT_NS`] by then is ended, so that vanished devices do
    /// not hold the service's slots.
    pub fn commission(
        &mut self,
        id: &str,
        req: &pb::CommissionRequest,
        who: &str,
        now_unix_ns: u64,
    ) -> pb::ConfigReply {
        let mut running = 0;
        for d in self.devices.values_mut() {
            let silent = now_unix_ns.saturating_sub(d.heard_unix_ns);
            if silent > super::commission::SILENT_NS {
                d.abort_silent_commission(silent);
            } else if d.commission.as_ref().is_some_and(|c| c.running()) {
                running += 1;
            }
        }
        let Some(d) = self.devices.get_mut(id) else {
            self.requests_refused += 1;
            return refused(format!("unknown device \"{}\"", printable(id)), None);
        };
        let run = (req.channel as usize, req.run);
        let mine = usize::from(d.commission.as_ref().is_some_and(|c| c.running()));
        let applied = match pb::CommissionAction::try_from(req.action) {
            Ok(pb::CommissionAction::CommissionStart) => {
                d.start_commission(req, who, running - mine)
            }
            Ok(pb::CommissionAction::CommissionConfirm) => d.confirm_commission(run, who),
            Ok(pb::CommissionAction::CommissionAbort) => d.dismiss_commission(run, who),
            _ => Err(format!("action {}: START, CONFIRM or ABORT", req.action)),
        };
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
                d.rare.get_mut().references_refused += 1;
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
                .configs()
                .iter()
                .zip(&limits)
                .map(|(c, l)| ChannelConfig {
                    law: c.law,
                    output: l.narrow(c.output),
                })
                .collect();
            d.mimo.reconfigure(&configs).map_err(|e| e.to_string())?;
            Ok(limits)
        })();
        let applied = planned.map(|limits| {
            d.abort_commission("the envelope changed");
            d.envelope = limits.into();
            d.rare.get_mut().envelope_changes += 1;
        });
        conclude(d, &mut self.requests_refused, id, applied)
    }
}

fn refused(reason: String, config: Option<pb::DeviceConfig>) -> pb::ConfigReply {
    pb::ConfigReply {
        version: PROTOCOL_VERSION,
        held_by: Vec::new(),
        durable: false,
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
    if applied.is_ok() {
        d.changed();
    }
    match applied {
        Ok(()) => pb::ConfigReply {
            version: PROTOCOL_VERSION,
            held_by: Vec::new(),
            durable: false,
            accepted: true,
            reason: String::new(),
            config: Some(d.config_pb(id)),
        },
        Err(reason) => {
            let reason = capped(reason);
            *requests_refused += 1;
            d.rare.get_mut().last_error.clone_from(&reason);
            refused(reason, Some(d.config_pb(id)))
        }
    }
}

/// Wire limits to core, checked; `i` names the channel in errors.
pub(super) fn limits_from_pb(l: &pb::ChannelLimits, i: usize) -> Result<Limits, String> {
    let out = Limits {
        min: l.min.unwrap_or(f64::NEG_INFINITY),
        max: l.max.unwrap_or(f64::INFINITY),
        rate_limit: l.rate_limit,
    };
    out.check()
        .map_err(|e| format!("envelope.channels[{i}]: {e}"))?;
    Ok(out)
}

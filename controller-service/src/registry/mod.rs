//! Per-device control state and the rules for answering samples. No I/O, no clock, no
//! logging: the Zenoh wiring in [`crate::service`] feeds it decoded messages and the time,
//! publishes what it returns and decides what to log, so every rule here is tested without
//! a network, with plain numbers for time. Snapshot files are read and written by
//! [`crate::snapshot`]; this module only makes and restores their contents.
//!
//! * [`device`]: what the service holds for one device;
//! * [`step`]: rules 2-7 for one sample of a served device;
//! * [`requests`]: configuration, reference and envelope changes;
//! * [`commission`]: commissioning runs on the live plant;
//! * [`shards`]: a shard's state for a fleet handover, snapshots and their restore.
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
//!    over: [`Served::AlreadyAnswered`]);
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

mod commission;
mod commission_requests;
mod device;
mod devices;
mod durable;
mod rare;
mod requests;
mod sample;
mod shards;
mod step;

use std::collections::BTreeSet;

use protocol::{pb, printable, PROTOCOL_VERSION};

use crate::config::ServiceConfig;
use crate::lease::{LeasePolicy, Seen, Standing};
pub use commission::{MAX_CYCLES, MAX_PERIOD, MAX_RUNNING, SILENT_NS};
use device::{reply, Device, ShortId};
use devices::Devices;
pub use devices::Slot;
pub use durable::{merge, ChangeTrial, FileChange, Recovery};
use sample::capped;
pub use sample::{latency, precheck, Via, MAX_SEQ_JUMP, REORDER_WINDOW, RESYNC_AFTER};
pub use shards::Restored;

/// Unknown device ids listed in the status; samples from further unknown ids are still
/// counted, just not named.
const UNKNOWN_KEPT: usize = 64;
/// What [`Registry::handle_sample`] did with a sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Served {
    /// The command to publish is in `out`: a new answer, the cached one again for a
    /// duplicate, or a refusal (`REJECTED`/`STALE`, with the reason in `error`).
    /// `provisioned`: this sample made its device from a template.
    Answered {
        /// Whether this sample provisioned its device from a template.
        provisioned: bool,
        /// Whether this member is to publish it: the plant's lease and the member's
        /// place in the fleet decide ([`crate::lease`]); the command is written either way
        /// (the answer is cached and observed as if sent).
        send: bool,
    },
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

impl Served {
    /// Whether a command was written (to be published).
    pub fn answered(self) -> bool {
        matches!(self, Self::Answered { .. })
    }
}

/// What [`Registry::handle_sample`] tells of a sample [`step::answer`] answered or not.
fn served(answered: Option<bool>, provisioned: bool) -> Served {
    match answered {
        Some(send) => Served::Answered { provisioned, send },
        None => Served::AlreadyAnswered,
    }
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
    /// When this member claims and yields plants' leases.
    lease_policy: LeasePolicy,
    /// The fleet's members this one sees (`None` without a fleet): a member that does not
    /// see a device's holder may lack its changes ([`crate::lease::Claimer::behind`]).
    view: Option<std::collections::BTreeSet<String>>,
    /// Devices whose state is to go to their partners ([`Registry::take_handing`]).
    handing: Vec<String>,
    /// This process among those that may carry the same controller id: the plant's lease
    /// names it ([`Registry::set_instance`]).
    instance: u64,
    /// The fleet's secret ([`Registry::set_secret`]); not part of the configuration's
    /// copy in recordings.
    secret: Option<protocol::auth::Secret>,
    config: ServiceConfig,
    /// By id through a hash table, or by slot (`devices.rs`): a gateway's batch finds
    /// thousands of devices a period. Whatever lists them sorts them first, so listings
    /// stay in id order.
    devices: Devices,
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
    /// Operators' changes decided and recorded in the audit trail: accepted, refused, and
    /// refusals whose entry found the audit file's queue full (kept in memory only).
    changes_accepted: u64,
    changes_refused: u64,
    audit_unwritten: u64,
}

impl Registry {
    /// Build every declared device from a checked configuration.
    pub fn new(config: ServiceConfig) -> Result<Self, RegistryError> {
        let mut devices = Devices::default();
        for d in &config.devices {
            let mut dev = Device::new(&d.channels, d.prediction, false).map_err(|reason| {
                RegistryError::Device {
                    id: d.id.clone(),
                    reason,
                }
            })?;
            dev.home = protocol::shard_of(&d.id);
            devices.insert(ShortId::new(&d.id), Box::new(dev));
        }
        Ok(Self {
            controller_id: config.controller_id.clone(),
            lease_policy: LeasePolicy::default(),
            view: None,
            handing: Vec::new(),
            instance: 0,
            secret: None,
            config,
            devices,
            unknown_samples: 0,
            unknown_devices: BTreeSet::new(),
            device_table_full: 0,
            undecodable: 0,
            rejected: 0,
            requests_refused: 0,
            bad_device_ids: 0,
            changes_accepted: 0,
            changes_refused: 0,
            audit_unwritten: 0,
        })
    }

    /// The snapshot settings, if any.
    pub fn snapshot_spec(&self) -> Option<&crate::config::SnapshotSpec> {
        self.config.snapshots.as_ref()
    }

    /// The file's access section, if any (`crate::access`).
    pub fn access_spec(&self) -> Option<&crate::access::AccessSpec> {
        self.config.access.as_ref()
    }

    /// The fleet settings, if any.
    pub fn fleet(&self) -> Option<&crate::config::FleetSpec> {
        self.config.fleet.as_ref()
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
        let mut ids: Vec<&str> = self.devices.keys().map(ShortId::as_str).collect();
        ids.sort_unstable();
        ids.into_iter()
    }

    /// The devices in id order.
    fn sorted(&self) -> Vec<(&str, &Device)> {
        let mut v: Vec<(&str, &Device)> =
            self.devices.iter().map(|(k, d)| (k.as_str(), d)).collect();
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

    /// Count an operator's change decided and recorded (`changes_accepted` or
    /// `changes_refused` in the service status).
    pub fn note_audited(&mut self, accepted: bool) {
        if accepted {
            self.changes_accepted += 1;
        } else {
            self.changes_refused += 1;
        }
    }

    /// Count an audit entry that the file's queue had no room for (a refusal's: a change
    /// is refused before it is applied unrecorded).
    pub fn note_audit_unwritten(&mut self) {
        self.audit_unwritten += 1;
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
            d.rare.get_mut().superseded += n;
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
    /// otherwise why not ([`Served::Unknown`] or [`Served::TableFull`]).
    fn provision(&mut self, id: &str) -> Result<(), Served> {
        if self.devices.contains_key(id) {
            return Ok(());
        }
        let Some(t) = self.template_for(id) else {
            return Err(Served::Unknown);
        };
        if self.devices.len() >= self.config.max_devices {
            return Err(Served::TableFull);
        }
        let mut d = Device::new(&t.channels, t.prediction, true).map_err(|_| Served::Unknown)?;
        d.home = protocol::shard_of(id);
        self.devices.insert(ShortId::new(id), Box::new(d));
        Ok(())
    }

    /// Name this process for the plants' leases: random per start, so that a second
    /// process with the same controller id (a restart, a copy started by mistake) is not
    /// taken for the holder. 0 (the default) until the service sets it.
    pub fn set_instance(&mut self, instance: u64) {
        self.instance = instance;
    }

    /// The liveliness lease of this member's zenoh session (`transport/link/tx/lease`),
    /// after which its fleet's partners drop it from their view if it falls silent: a
    /// silence of half that makes it count itself behind
    /// ([`LeasePolicy::for_liveliness_lease`]).
    pub fn set_liveliness_lease(&mut self, lease: std::time::Duration) {
        self.lease_policy = self.lease_policy.for_liveliness_lease(lease);
    }

    /// Give this member the fleet's secret (`protocol::auth`): its samples are then
    /// checked and its commands and replies sealed. Without it the service runs open.
    pub fn set_secret(&mut self, secret: Option<protocol::auth::Secret>) {
        self.secret = secret;
    }

    /// The fleet's secret, if this member has it.
    pub fn secret(&self) -> Option<&protocol::auth::Secret> {
        self.secret.as_ref()
    }

    /// Answer a sample by the rules of the module doc, writing the command into `out`
    /// (reusing its buffers: a gateway's batch keeps one command per sample from batch to
    /// batch, so answering allocates nothing). `now_unix_ns` is the time the answer
    /// carries (`controller_unix_ns`). The hot path: one lookup of the device when it is
    /// known, besides the step itself.
    pub fn handle_sample(
        &mut self,
        via: Via<'_>,
        s: &pb::Sample,
        now_unix_ns: u64,
        out: &mut pb::Command,
    ) -> Served {
        self.handle_sample_at(&mut None, via, s, now_unix_ns, out)
    }

    /// [`Self::handle_sample`] for a device the caller may have found before, in `slot`
    /// (a position of a gateway's batch, whose plants come in the same order every
    /// period): served from that slot if it still holds the device's id, without a
    /// lookup; otherwise looked up, and `slot` set to where it was found (`None` if it is
    /// not served).
    pub fn handle_sample_at(
        &mut self,
        slot: &mut Option<Slot>,
        via: Via<'_>,
        s: &pb::Sample,
        now_unix_ns: u64,
        out: &mut pb::Command,
    ) -> Served {
        // A device already served: the common case.
        if let Some(answered) = self.serve_in(slot, via, s, (now_unix_ns, false), out) {
            return answered;
        }
        // Not served yet (the rare path): a template may provision it, and then it is
        // served as any other.
        if let Err(why) = self.provision(via.key_id) {
            self.count_unserved(via.key_id, why);
            return why;
        }
        self.serve_in(slot, via, s, (now_unix_ns, true), out)
            .unwrap_or(Served::Unknown)
    }

    /// Step the device served under `via`'s id, found from `slot` as
    /// [`Devices::find_mut`] finds it (`None` if it is not served), at `now_unix_ns`,
    /// `provisioned` by this sample or not.
    fn serve_in(
        &mut self,
        slot: &mut Option<Slot>,
        via: Via<'_>,
        s: &pb::Sample,
        (now_unix_ns, provisioned): (u64, bool),
        out: &mut pb::Command,
    ) -> Option<Served> {
        let d = self.devices.find_mut(slot, via.key_id)?;
        d.prefetch();
        let cx = step::Context {
            controller_id: &self.controller_id,
            rejected: &mut self.rejected,
            now_unix_ns,
            lease: &self.lease_policy,
            view: self.view.as_ref(),
            instance: self.instance,
            ordered_runs: self.secret.is_some(),
        };
        Some(served(
            step::answer((cx, &mut self.handing), d, via, s, out),
            provisioned,
        ))
    }

    /// Ask the processor for a served device's state ahead of its sample (a batch's next
    /// one): the lines of the device a step reads arrive while the sample before it is
    /// stepped. Changes nothing; an unknown id does nothing.
    pub fn prefetch(&self, key_id: &str) {
        self.prefetch_at(&mut None, key_id);
    }

    /// [`Self::prefetch`] for a device the caller may have found before, in `slot`, as
    /// [`Self::handle_sample_at`]: from the slot if it holds the id, else looked up, and
    /// `slot` set to where it was found.
    pub fn prefetch_at(&self, slot: &mut Option<Slot>, key_id: &str) {
        if let Some(d) = self.devices.find(slot, key_id) {
            d.prefetch();
        }
    }

    /// Count a sample whose device cannot be served (rule 1).
    fn count_unserved(&mut self, key_id: &str, why: Served) {
        if why == Served::TableFull {
            self.device_table_full += 1;
        } else {
            self.unknown_samples += 1;
            if self.unknown_devices.len() < UNKNOWN_KEPT {
                self.unknown_devices.insert(printable(key_id));
            }
        }
    }

    /// Answer a sample that [`precheck`] refused before it reached the inbox: REJECTED with
    /// `reason` if the key's device is served (`None`: counted as unknown; a malformed
    /// sample never provisions a device), and whether this member sends it (the plant's
    /// lease decides, as for any answer; `preferred` as in [`Via::preferred`]).
    pub fn refuse_sample(
        &mut self,
        key_id: &str,
        s: &pb::Sample,
        reason: String,
        now_unix_ns: u64,
        preferred: bool,
    ) -> Option<(pb::Command, bool)> {
        let Some(d) = self.devices.get_mut(key_id) else {
            self.count_unserved(key_id, Served::Unknown);
            return None;
        };
        let reason = capped(reason);
        d.samples += 1;
        d.rare.get_mut().rejected += 1;
        d.note_rejected(s.run_id, s.seq);
        self.rejected += 1;
        d.rare.get_mut().last_error.clone_from(&reason);
        let mut cmd = reply(
            (&self.controller_id, key_id),
            (s.seq, s.sent_unix_ns, now_unix_ns),
            pb::Mode::Rejected,
            reason,
        );
        let me = (self.controller_id.as_str(), self.instance);
        let decision = d.claimer.decide(
            &self.lease_policy,
            me,
            Standing::plain(preferred, true),
            Seen::of(s),
        );
        decision.stamp(s.run_id, self.instance, &mut cmd);
        Some((cmd, decision.sends()))
    }

    /// The fleet's members this one sees now (the wiring sets it at every change of view).
    pub fn set_view(&mut self, members: &std::collections::BTreeSet<String>) {
        self.view = Some(members.clone());
    }

    /// The devices whose lease this member just took, or will soon yield to the
    /// preferred member, in the order they came due: the wiring sends their state to the
    /// device's partners, so that they are in step with it (and the preferred member
    /// claims in step).
    pub fn take_handing(&mut self) -> Vec<String> {
        std::mem::take(&mut self.handing)
    }

    /// The id of the member holding device `id`'s lease at its last sample (empty:
    /// vacant or none granted).
    pub fn lease_holder_id(&self, id: &str) -> Option<&str> {
        self.devices.get(id).map(|d| d.lease_holder.as_str())
    }

    /// How recently the member holding device `id`'s lease must have heard it to be sure
    /// enough it still commands it: five periods (the agent's lease lapses after three
    /// without a command), 50 ms at least; one second while the period is not known.
    pub fn live_ns(&self, id: &str) -> u64 {
        let period = self.devices.get(id).and_then(|d| d.period());
        period.map_or(1_000_000_000, |p| ((5.0 * p).max(0.05) * 1e9) as u64)
    }

    /// Whether this member's partners are in step with it for device `id`
    /// ([`crate::lease::Claimer::handed_over`]).
    pub fn handed_over(&mut self, id: &str, in_step: bool) {
        if let Some(d) = self.devices.get_mut(id) {
            d.claimer.handed_over(in_step);
        }
    }

    /// Whether this member is in step with the holder of device `id`'s lease (see
    /// [`crate::lease::Claimer::behind`]; always without a fleet, or for a device not
    /// served).
    pub fn in_step(&self, id: &str) -> bool {
        let fleet = crate::lease::Standing {
            preferred: false,
            warm: true,
            sees_holder: self.view.as_ref().map(|_| true),
            gap: false,
        };
        self.devices
            .get(id)
            .is_none_or(|d| !d.claimer.behind(fleet))
    }

    /// When device `id`'s last sample was stepped here (Unix ns, as the
    /// caller passed it to [`Registry::handle_sample`]; 0: never).
    pub fn heard_unix_ns(&self, id: &str) -> u64 {
        self.devices.get(id).map_or(0, |d| d.heard_unix_ns)
    }

    /// Whether this member may acknowledge a change to device `id` now (`now_ns`, Unix
    /// ns), and if not, why ([`crate::lease::may_acknowledge`] on what it last heard).
    pub fn may_acknowledge(&self, id: &str, now_ns: u64) -> Result<(), String> {
        let heard = (self.heard_unix_ns(id), self.live_ns(id));
        crate::lease::may_acknowledge(self.lease_holder(id), heard, now_ns)
    }

    /// Whether this member may still acknowledge a change to device `id`, accepted when
    /// its lease stood as `accepted`, now that its holds end
    /// ([`crate::lease::may_still_acknowledge`]).
    pub fn may_still_acknowledge(
        &self,
        id: &str,
        accepted: crate::lease::Holder,
        now_ns: u64,
    ) -> Result<(), String> {
        let heard = (self.heard_unix_ns(id), self.live_ns(id));
        crate::lease::may_still_acknowledge(accepted, self.lease_holder(id), heard, now_ns)
    }

    /// Who held device `id`'s lease at its last sample (`Unknown` for a device not
    /// served or not heard yet).
    pub fn lease_holder(&self, id: &str) -> crate::lease::Holder {
        self.devices
            .get(id)
            .map_or(crate::lease::Holder::Unknown, |d| d.claimer.holder)
    }

    /// Every device's numbers (its status without the parts that allocate or sort: no id,
    /// round trips, estimates, envelope or strings), in no order: a metrics scrape sums
    /// them over ten thousand devices without holding up the worker for long.
    pub fn for_each_counters(&self, mut f: impl FnMut(&str, &pb::DeviceStatus)) {
        for (k, d) in self.devices.iter() {
            f(k.as_str(), &d.counters_pb());
        }
    }

    /// Status of one device.
    pub fn device_status(&self, id: &str) -> Option<pb::DeviceStatus> {
        self.devices.get(id).map(|d| d.status_pb(id))
    }

    /// Status of one device as this member answers it at `now_unix_ns`: who answers, and
    /// how old what it says of the plant is ([`Registry::stamp`]).
    pub fn device_status_at(&self, id: &str, now_unix_ns: u64) -> Option<pb::DeviceStatus> {
        let mut s = self.device_status(id)?;
        self.stamp(&mut s, now_unix_ns);
        Some(s)
    }

    /// Say in `s` which member answers (id and process) and how long ago it last heard the
    /// device (0: never), at `now_unix_ns`.
    pub fn stamp(&self, s: &mut pb::DeviceStatus, now_unix_ns: u64) {
        let heard = self.heard_unix_ns(&s.device_id);
        s.heard_ms_ago = if heard == 0 {
            0
        } else {
            now_unix_ns.saturating_sub(heard).div_ceil(1_000_000).max(1)
        };
        s.answered_by.clone_from(&self.controller_id);
        s.answered_by_instance = self.instance;
    }

    /// This process, as the plants' leases name it ([`Registry::set_instance`]).
    pub fn instance(&self) -> u64 {
        self.instance
    }

    /// Status of the whole service, `uptime` in seconds. It reports `active` true and term
    /// 0, and none of the inbox's drops: the caller fills those in.
    pub fn service_status(&self, uptime: f64) -> pb::ServiceStatus {
        self.service_status_where(uptime, |_| true)
    }

    /// [`Self::service_status`] with only the devices `keep` says in `devices`.
    pub fn service_status_where(
        &self,
        uptime: f64,
        keep: impl Fn(&str) -> bool,
    ) -> pb::ServiceStatus {
        let mut devices: Vec<(&str, &Device)> = self
            .devices
            .iter()
            .map(|(k, d)| (k.as_str(), d))
            .filter(|(id, _)| keep(id))
            .collect();
        devices.sort_unstable_by(|a, b| a.0.cmp(b.0));
        pb::ServiceStatus {
            version: PROTOCOL_VERSION,
            controller_id: self.controller_id.clone(),
            devices: devices.into_iter().map(|(id, d)| d.status_pb(id)).collect(),
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
            changes_accepted: self.changes_accepted,
            changes_refused: self.changes_refused,
            audit_unwritten: self.audit_unwritten,
            ..Default::default()
        }
    }
}

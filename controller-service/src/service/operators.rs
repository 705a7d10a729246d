//! Operators' changes, from the request to the reply. A change (configuration, envelope,
//! reference, commissioning) goes through five steps, and the operator hears only at the
//! end:
//! 1. it waits while another change of its device is being written
//!    ([`crate::changes::Serial`]): each is decided on the state the one before it left;
//! 2. it is decided ([`Core::decide`]): who asks must be allowed ([`crate::access`]), the
//!    audit file must have room for its record, and the registry tries it
//!    ([`crate::Registry::trial`]): refused, or the state it would leave;
//! 3. its record goes to the audit file ([`super::trail`]): the decision and, if accepted,
//!    that state ([`crate::journal`]); nothing is in force yet;
//! 4. once the record is durable, the change is made ([`Core::commit`]) and must leave the
//!    state recorded, or it is withdrawn (recorded too); a record that could not be written
//!    refuses its change, and nothing changed;
//! 5. the reply goes out, at once or once the fleet's partners hold the change
//!    ([`super::hold`]).
//!
//! Without an audit file, steps 3 and 4 are one: the change is in force at once, and its
//! reply says that it is not durable (`ConfigReply.durable`).

use std::collections::HashMap;

use protocol::{encode, keys, pb, printable, PROTOCOL_VERSION};
use telemetry::Topic;
use tokio::sync::mpsc;
use zenoh::query::Query;

use super::core::Core;
use super::lock;
use super::log::throttled;
use super::trail::{AuditTrail, NotWritten, Pending, Written};
use super::worker::Worker;
use crate::access::{Access, Action, Actor};
use crate::changes::{Arrival, Serial};
use crate::journal::{Record, State, Write};
use crate::registry::ChangeTrial;
use crate::Registry;

/// The access rules and the audit trail of one worker.
pub(super) struct Gate {
    pub(super) access: Access,
    pub(super) trail: Option<AuditTrail>,
    /// The member whose decisions these are, and its last entry number.
    member: String,
    last_n: u64,
}

impl Gate {
    /// The gate of the member `registry` is for: its file's access rules (said in the
    /// log: open, names as claims, or names bound to certificates) and the audit trail.
    pub(super) fn of(registry: &Registry, trail: Option<AuditTrail>) -> Self {
        let spec = registry.access_spec().cloned();
        match &spec {
            Some(a) if a.verified => {
                tracing::info!(operators = a.operators.len(), "access: operators' names are bound to their certificates by the deployment's access control");
            }
            Some(a) => {
                tracing::warn!(operators = a.operators.len(), "access: operators' names are claims (verified = false): roles are checked, but anyone who may query can name anyone");
            }
            None => {
                tracing::warn!("access: open (no [access] section): every request is taken, from whoever its key names; the audit trail records names as unverified");
            }
        }
        Self {
            access: Access::new(spec),
            trail,
            member: registry.controller_id().to_string(),
            last_n: 0,
        }
    }

    /// A new audit entry of this member's, numbered after the last.
    pub(super) fn entry(&mut self, dev: &str, actor: &Actor, what: &str) -> pb::AuditEntry {
        let unix_ns = protocol::unix_ns();
        let n = crate::audit::next_number(self.last_n, unix_ns);
        self.last_n = n;
        pb::AuditEntry {
            unix_ns,
            member: self.member.clone(),
            n,
            device_id: dev.to_string(),
            operator: actor.name.clone(),
            verified: actor.verified,
            role: actor.role.map_or("", |r| r.name()).to_string(),
            action: what.to_string(),
            ..Default::default()
        }
    }
}

/// A change as asked, decoded.
#[derive(Debug)]
pub(super) enum Request {
    Config(pb::ConfigRequest),
    Envelope(pb::EnvelopeRequest),
    Reference(pb::ReferenceUpdate),
    Commission(pb::CommissionRequest),
}

impl Request {
    /// What the audit entry calls it.
    fn what(&self) -> &'static str {
        match self {
            Self::Config(_) => "configuration",
            Self::Envelope(_) => "envelope",
            Self::Reference(_) => "reference",
            Self::Commission(_) => "commission",
        }
    }

    /// What who asks must be allowed to do.
    fn action(&self, r: &Registry, dev: &str) -> Action {
        match self {
            Self::Envelope(e) if r.widens(dev, e) => Action::Widen,
            _ => Action::Change,
        }
    }

    /// Make the change on `dev`, as `who` (the registry decides, and refuses with why).
    fn apply(&self, r: &mut Registry, dev: &str, who: &str) -> pb::ConfigReply {
        match self {
            Self::Config(c) => r.configure(dev, c),
            Self::Envelope(e) => r.change_envelope(dev, e),
            Self::Reference(u) => r.set_reference(dev, u),
            Self::Commission(c) => r.commission(dev, c, who, protocol::unix_ns()),
        }
    }

    /// The recording's topic for it.
    fn topic(&self) -> Topic {
        match self {
            Self::Config(_) => Topic::ConfigRequest,
            Self::Envelope(_) => Topic::EnvelopeRequest,
            Self::Reference(_) => Topic::ReferenceUpdate,
            Self::Commission(_) => Topic::CommissionRequest,
        }
    }
}

/// One change on its way (module documentation): the device, who asks (the name its key
/// gives), the request and its bytes (a reply is bound to them), and the query to answer
/// (`None` for a reference put, which nobody waits for).
pub(super) struct Change {
    pub(super) dev: String,
    pub(super) who: Option<String>,
    pub(super) request: Request,
    pub(super) bytes: Vec<u8>,
    pub(super) query: Option<Query>,
}

/// What a decision leaves to do.
enum Decision {
    /// Refused (by the access rules or the registry): its entry is to be written.
    Refused(Box<(pb::ConfigReply, pb::AuditEntry)>),
    /// Accepted as tried: its record (entry and state) is to be written, then it is made.
    Tried(Box<Tried>),
    /// No room for its record: refused at once, nothing written.
    NoRoom(pb::ConfigReply),
}

/// An accepted change waiting for its record.
struct Tried {
    trial: ChangeTrial,
    entry: pb::AuditEntry,
    /// The name it is made as (commissioning records who runs it).
    actor: String,
}

/// A change whose record is being written, and what to do when it is.
enum Waiting {
    Refusal(Change, pb::ConfigReply),
    Tried(Change, Box<Tried>),
    /// A change withdrawn after its record was written: the reply waits for the record
    /// that withdraws it.
    Withdrawn(Change, pb::ConfigReply),
}

/// The worker's changes on their way: those waiting for their device, and those waiting
/// for their records, by number.
pub(super) struct Changes {
    serial: Serial<Change>,
    waiting: HashMap<u64, Waiting>,
    next: u64,
    /// Where the writer sends its word on this worker's records.
    written: mpsc::Sender<Written>,
}

impl Changes {
    pub(super) fn new(written: mpsc::Sender<Written>) -> Self {
        Self {
            serial: Serial::default(),
            waiting: HashMap::new(),
            next: 0,
            written,
        }
    }
}

impl Core {
    /// Decide a change (module documentation, step 2). A refusal's entry is kept with the
    /// device now; an accepted change's, once it is in force.
    fn decide(&mut self, c: &Change) -> (Decision, Option<mpsc::OwnedPermit<Pending>>) {
        let dev = c.dev.as_str();
        let action = c.request.action(&self.registry, dev);
        let actor = match self.gate.access.check(c.who.as_deref(), dev, action) {
            Ok(actor) => actor,
            Err((actor, why)) => {
                let reply = self.registry.refuse_request(dev, why);
                let permit = self.gate.trail.as_ref().and_then(AuditTrail::reserve);
                let entry = self.refusal(c, &actor, &reply, permit.is_some());
                return (Decision::Refused(Box::new((reply, entry))), permit);
            }
        };
        let permit = match &self.gate.trail {
            None => None,
            Some(t) => match t.reserve() {
                Some(p) => Some(p),
                None => {
                    let why = format!(
                        "the audit trail is full ({} records wait to be written to {}); nothing changed, send it again",
                        super::trail::WAITING,
                        t.path().display()
                    );
                    return (
                        Decision::NoRoom(self.registry.refuse_request(dev, why)),
                        None,
                    );
                }
            },
        };
        let name = actor.name.clone();
        let (reply, trial) = self.registry.trial(dev, |r| c.request.apply(r, dev, &name));
        let Some(trial) = trial else {
            let entry = self.refusal(c, &actor, &reply, permit.is_some());
            return (Decision::Refused(Box::new((reply, entry))), permit);
        };
        let mut entry = self.gate.entry(dev, &actor, c.request.what());
        entry.accepted = true;
        entry.changes.clone_from(&trial.changes);
        let tried = Tried {
            trial,
            entry,
            actor: name,
        };
        (Decision::Tried(Box::new(tried)), permit)
    }

    /// The entry of a refusal, kept with the device (and counted as unwritten if it has no
    /// place in the file).
    fn refusal(
        &mut self,
        c: &Change,
        actor: &Actor,
        reply: &pb::ConfigReply,
        written: bool,
    ) -> pb::AuditEntry {
        let mut entry = self.gate.entry(&c.dev, actor, c.request.what());
        entry.asked = crate::audit::abridged(&format!("{:?}", c.request));
        entry.reason.clone_from(&reply.reason);
        self.registry.note_audited(false);
        if !written && self.gate.trail.is_some() {
            self.registry.note_audit_unwritten();
        }
        self.registry.audit(entry.clone());
        entry
    }

    /// Make a tried change whose record is durable (step 4): it must be tried on the state
    /// it was tried on, and leave the state recorded; otherwise the device is left as it
    /// was and why is returned. The change's entry is kept with the device, the recording
    /// and the log hear of it.
    fn commit(&mut self, c: &Change, t: &Tried) -> Result<pb::ConfigReply, String> {
        let dev = c.dev.as_str();
        let widened = self.registry.widens_any(dev, &c.request);
        let reply = self
            .registry
            .commit(dev, &t.trial, |r| c.request.apply(r, dev, &t.actor))?;
        self.registry.audit(t.entry.clone());
        self.registry.note_audited(true);
        self.made(c, widened);
        Ok(reply)
    }

    /// The log and the recording hear of a change made.
    fn made(&mut self, c: &Change, widened: bool) {
        let dev = c.dev.as_str();
        let what = match &c.request {
            Request::Envelope(e) => {
                let by = printable(&e.reason);
                let envelope = self.registry.config_of(dev).and_then(|c| c.envelope);
                if widened {
                    // Every widening has its own line: it is rare (the file must allow it)
                    // and it is what an audit looks for.
                    tracing::warn!(device = %dev, by = %by, envelope = ?envelope, "envelope WIDENED");
                } else {
                    let warn = &mut self.warn;
                    throttled!(warn.envelope, info, device = %dev, by = %by, envelope = ?envelope, "envelope narrowed");
                }
                format!(
                    "envelope {} by {by}",
                    if widened { "WIDENED" } else { "narrowed" }
                )
            }
            Request::Config(_) => {
                let warn = &mut self.warn;
                throttled!(warn.changed, info, device = %dev, "configuration changed");
                "configuration changed".into()
            }
            Request::Reference(_) => "reference changed".into(),
            Request::Commission(r) => {
                let action =
                    pb::CommissionAction::try_from(r.action).map_or("?", |a| a.as_str_name());
                let by = printable(c.who.as_deref().unwrap_or_default());
                tracing::info!(device = %dev, by = %by, channel = r.channel, action, "commissioning");
                "commissioning".into()
            }
        };
        let topic = c.request.topic();
        self.watch
            .changed(&self.registry, dev, topic, &c.bytes, &what);
    }
}

impl Registry {
    /// Whether `request` is an envelope change that widens `dev`'s envelope.
    fn widens_any(&self, dev: &str, request: &Request) -> bool {
        matches!(request, Request::Envelope(e) if self.widens(dev, e))
    }
}

impl Worker {
    /// A change arrives: decided now, or queued behind its device's change being written,
    /// or refused if too many wait.
    pub(super) async fn submit(&mut self, c: Change) {
        let dev = c.dev.clone();
        match self.changes.serial.arrive(&dev, c) {
            Arrival::Now(c) => self.run_changes(c).await,
            Arrival::Queued => {}
            Arrival::Full(c, n) => {
                let why = format!("{n} changes of this device wait to be written; nothing changed, send it again later");
                let reply = lock(&self.shared.core).registry.refuse_request(&dev, why);
                self.respond(c, reply).await;
            }
        }
    }

    /// Decide `first` and, while each is done at once (no audit file, or refused without
    /// a record), the changes of its device that wait behind it.
    async fn run_changes(&mut self, first: Change) {
        let mut next = Some(first);
        while let Some(c) = next {
            next = self.begin(c).await;
        }
    }

    /// Decide one change and hand its record to the writer; the next change of its
    /// device to decide, if this one is done already.
    async fn begin(&mut self, c: Change) -> Option<Change> {
        let (decision, permit) = lock(&self.shared.core).decide(&c);
        let dev = c.dev.clone();
        match decision {
            Decision::NoRoom(reply) => {
                self.respond(c, reply).await;
                self.changes.serial.done(&dev)
            }
            Decision::Refused(refused) => {
                let (reply, entry) = *refused;
                match permit {
                    Some(p) => {
                        let w = Write::Record(Record { entry, state: None });
                        self.wait_for(p, w, Waiting::Refusal(c, reply));
                    }
                    None => self.respond(c, reply).await,
                }
                self.changes.serial.done(&dev)
            }
            Decision::Tried(t) => match permit {
                Some(p) => {
                    let state = self.state_to_keep(&dev, &t.trial.after);
                    let w = Write::Record(Record {
                        entry: t.entry.clone(),
                        state: Some(state),
                    });
                    self.wait_for(p, w, Waiting::Tried(c, t));
                    None
                }
                None => {
                    self.finish_tried(c, &t, Ok(())).await;
                    self.changes.serial.done(&dev)
                }
            },
        }
    }

    /// The state a record keeps: what the change leaves, and the file's configuration.
    fn state_to_keep(&self, dev: &str, after: &(pb::DeviceConfig, crate::lease::Version)) -> State {
        let file = lock(&self.shared.core).registry.file_config_of(dev);
        State {
            config: after.0.clone(),
            version: after.1,
            file: file.unwrap_or_else(|| after.0.clone()),
        }
    }

    /// Send a record to the writer and remember what waits for it.
    fn wait_for(&mut self, permit: mpsc::OwnedPermit<Pending>, w: Write, then: Waiting) {
        let id = self.changes.next;
        self.changes.next += 1;
        self.changes.waiting.insert(id, then);
        permit.send((w, Some((id, self.changes.written.clone()))));
    }

    /// The writer's word on one of this worker's records.
    pub(super) async fn handle_written(&mut self, w: Written) {
        let Some(waiting) = self.changes.waiting.remove(&w.id) else {
            return;
        };
        match waiting {
            Waiting::Refusal(c, reply) => {
                if w.result.is_err() {
                    lock(&self.shared.core).registry.note_audit_unwritten();
                }
                self.respond(c, reply).await;
            }
            Waiting::Tried(c, t) => {
                let dev = c.dev.clone();
                if self.finish_tried(c, &t, w.result).await {
                    if let Some(next) = self.changes.serial.done(&dev) {
                        self.run_changes(next).await;
                    }
                }
            }
            Waiting::Withdrawn(c, reply) => {
                let dev = c.dev.clone();
                self.respond(c, reply).await;
                if let Some(next) = self.changes.serial.done(&dev) {
                    self.run_changes(next).await;
                }
            }
        }
    }

    /// A tried change whose record is durable (or could not be written): made and replied
    /// to, refused, or withdrawn. Whether its device is done with it (a withdrawal waits for
    /// its own record).
    async fn finish_tried(
        &mut self,
        c: Change,
        t: &Tried,
        written: Result<(), NotWritten>,
    ) -> bool {
        let dev = c.dev.clone();
        if let Err(e) = written {
            let reply = {
                let mut core = lock(&self.shared.core);
                let why = if e.in_doubt {
                    format!("in doubt: the audit file failed ({}); the change is not in force, but its record may be on the disk, so a restart of this service may put it in force: read the configuration after a restart", e.why)
                } else {
                    format!(
                        "the audit file could not be written ({}); nothing changed",
                        e.why
                    )
                };
                let reply = core.registry.refuse_request(&dev, why);
                let mut entry = t.entry.clone();
                (entry.accepted, entry.reason) = (false, reply.reason.clone());
                entry.changes.clear();
                core.registry.audit(entry);
                core.registry.note_audit_unwritten();
                reply
            };
            self.respond(c, reply).await;
            return true;
        }
        let made = lock(&self.shared.core).commit(&c, t);
        match made {
            Ok(reply) => {
                self.acknowledge(c, reply).await;
                true
            }
            Err(why) => self.withdraw(c, t, why).await,
        }
    }

    /// A change whose record says accepted could not be made: a record saying it was
    /// withdrawn, with the state in force, follows it; the reply waits for that record.
    async fn withdraw(&mut self, c: Change, t: &Tried, why: String) -> bool {
        tracing::warn!(device = %printable(&c.dev), "change withdrawn after its record: {why}");
        let (reply, entry, now) = {
            let mut core = lock(&self.shared.core);
            let why = format!("withdrawn: {why}; nothing changed, send it again");
            let reply = core.registry.refuse_request(&c.dev, why);
            let mut entry = t.entry.clone();
            entry.n = core.gate.last_n_next();
            entry.unix_ns = protocol::unix_ns();
            (entry.accepted, entry.reason) = (false, reply.reason.clone());
            entry.changes.clear();
            core.registry.audit(entry.clone());
            (reply, entry, core.registry.state_of(&c.dev))
        };
        let trail = lock(&self.shared.core).gate.trail.clone();
        let (Some(trail), Some(now)) = (trail, now) else {
            self.respond(c, reply).await;
            return true;
        };
        let state = self.state_to_keep(&c.dev, &now);
        let w = Write::Record(Record {
            entry,
            state: Some(state),
        });
        let id = self.changes.next;
        self.changes.next += 1;
        self.changes
            .waiting
            .insert(id, Waiting::Withdrawn(c, reply));
        let sent = trail
            .send((w, Some((id, self.changes.written.clone()))))
            .await;
        if let Err(e) = sent {
            tracing::error!("{e}");
        }
        false
    }

    /// Reply to a change made: it is durable here if this member has an audit file, and
    /// acknowledged once the partners the fleet requires hold it ([`super::hold`]).
    async fn acknowledge(&mut self, c: Change, mut reply: pb::ConfigReply) {
        reply.durable = lock(&self.shared.core).gate.trail.is_some();
        let Some(q) = c.query else { return };
        let hold = self.to_hold(&c.dev);
        self.reply_held(q, c.bytes, reply, hold).await;
    }

    /// Reply to a change not made (refused, withdrawn); a put has nobody to reply to, and
    /// its refusal is logged.
    async fn respond(&mut self, c: Change, reply: pb::ConfigReply) {
        if !reply.accepted {
            self.refused(&c.dev, c.request.what(), &reply.reason);
        }
        let Some(q) = c.query else { return };
        let key = q.key_expr().as_str().to_string();
        let bytes = self.sealed_reply(&key, Some(&c.bytes), encode(&reply));
        let _ = q.reply(q.key_expr().clone(), bytes).await;
    }

    /// The operator a request's key names (`…/by/{operator}`), or the error reply for a
    /// key of another shape. `Ok(None)`: it names nobody.
    pub(super) async fn named(&self, q: &Query) -> Option<Option<String>> {
        match keys::request_parts(q.key_expr().as_str()) {
            Some((_, who)) => Some(who.map(str::to_string)),
            None => {
                lock(&self.shared.core).registry.note_request_refused();
                self.reply_error(q, "not a request key: …/device/{id}/{leaf}[/by/{operator}]")
                    .await;
                None
            }
        }
    }

    /// Whether `who` may read `dev`; if not, the query gets why.
    pub(super) async fn may_read(&self, q: &Query, who: Option<&str>, dev: &str) -> bool {
        let check = lock(&self.shared.core)
            .gate
            .access
            .check(who, dev, Action::Read);
        match check {
            Ok(_) => true,
            Err((_, why)) => {
                self.reply_error(q, &why).await;
                false
            }
        }
    }

    /// An audit query: a device's latest entries, or for a wildcard key one reply per
    /// device answered here that the asker may see, each on its own key.
    pub(super) async fn handle_audit(&mut self, q: Query) {
        let Some(who) = self.named(&q).await else {
            return;
        };
        if q.key_expr().as_str().contains('*') {
            let log = |r: &Registry, d: &str| r.audit_of(d).map(|l| protocol::encode(&l));
            return self.reply_matching(&q, who.as_deref(), "audit", log).await;
        }
        let Some(dev) = self.served(&q).await else {
            return;
        };
        if !self.may_read(&q, who.as_deref(), &dev).await {
            return;
        }
        let log = lock(&self.shared.core).registry.audit_of(&dev);
        let log = log.unwrap_or(pb::AuditLog {
            version: PROTOCOL_VERSION,
            device_id: dev,
            entries: Vec::new(),
        });
        let bytes = self.sealed_reply(q.key_expr().as_str(), None, protocol::encode(&log));
        let _ = q.reply(q.key_expr().clone(), bytes).await;
    }
}

impl Gate {
    /// The next entry number, for an entry that follows another of this member's.
    fn last_n_next(&mut self) -> u64 {
        self.last_n = crate::audit::next_number(self.last_n, protocol::unix_ns());
        self.last_n
    }
}

/// The key a reply about `dev` goes on for a wildcard query on `leaf`: the device's own,
/// on the shard's key if the query was, naming the asker as the query did.
pub(super) fn reply_key(sharded: Option<u32>, dev: &str, leaf: &str, who: Option<&str>) -> String {
    let key = match sharded {
        Some(h) => format!("{}/shard/{h}/device/{dev}/{leaf}", keys::PREFIX),
        None => format!("{}/device/{dev}/{leaf}", keys::PREFIX),
    };
    match who {
        Some(w) => keys::by(&key, w),
        None => key,
    }
}

//! A change as an operator asks it, as it is decided on the core and as it waits for its
//! record: the pieces of [`super::operators`]' way from the request to the reply.

use std::collections::HashMap;

use protocol::{pb, printable};
use telemetry::Topic;
use tokio::sync::mpsc;
use zenoh::query::Query;

use super::core::Core;
use super::log::throttled;
use crate::access::{Action, Actor};
use crate::changes::Serial;
use crate::registry::ChangeTrial;
use crate::trail::{AuditTrail, Pending, Written};
use crate::Registry;

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
    pub(super) fn what(&self) -> &'static str {
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
pub(super) enum Decision {
    /// Refused (by the access rules or the registry): its entry is to be written.
    Refused(Box<(pb::ConfigReply, pb::AuditEntry)>),
    /// Accepted as tried: its record (entry and state) is to be written, then it is made.
    Tried(Box<Tried>),
    /// No room for its record: refused at once, nothing written.
    NoRoom(pb::ConfigReply),
}

/// An accepted change waiting for its record.
pub(super) struct Tried {
    pub(super) trial: ChangeTrial,
    pub(super) entry: pb::AuditEntry,
    /// The name it is made as (commissioning records who runs it).
    pub(super) actor: String,
}

/// A change whose record is being written, and what to do when it is.
pub(super) enum Waiting {
    Refusal(Change, pb::ConfigReply),
    Tried(Change, Box<Tried>),
    /// A change withdrawn after its record was written: the reply waits for the record
    /// that withdraws it.
    Withdrawn(Change, pb::ConfigReply),
}

/// The worker's changes on their way: those waiting for their device, and those waiting
/// for their records, by number.
pub(super) struct Changes {
    pub(super) serial: Serial<Change>,
    pub(super) waiting: HashMap<u64, Waiting>,
    pub(super) next: u64,
    /// Where the writer sends its word on this worker's records.
    pub(super) written: mpsc::Sender<Written>,
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
    pub(super) fn decide(&mut self, c: &Change) -> (Decision, Option<mpsc::OwnedPermit<Pending>>) {
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
                        crate::trail::WAITING,
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
    pub(super) fn commit(&mut self, c: &Change, t: &Tried) -> Result<pb::ConfigReply, String> {
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

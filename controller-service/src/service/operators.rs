//! Operators' requests meet the access rules and the audit trail here: every change is
//! checked against who asks ([`crate::access`]), given its place in the audit file before
//! it is applied ([`super::trail`]), and recorded with its old and new values, accepted or
//! refused ([`crate::audit`]). Reads are checked, not recorded.

use protocol::{keys, pb, PROTOCOL_VERSION};
use zenoh::query::Query;

use super::core::Core;
use super::lock;
use super::trail::AuditTrail;
use super::worker::Worker;
use crate::access::{Access, Action, Actor};

/// The access rules and the audit trail of one worker.
pub(super) struct Gate {
    pub(super) access: Access,
    pub(super) trail: Option<AuditTrail>,
    /// The member whose decisions these are, and its last entry number.
    member: String,
    last_n: u64,
    /// Resolves once the last decision's entry is on disk ([`Gate::written`]).
    written: Option<tokio::sync::oneshot::Receiver<()>>,
}

impl Gate {
    /// The gate of the member `registry` is for: its file's access rules (said in the
    /// log: open, names as claims, or names bound to certificates) and the audit trail.
    pub(super) fn of(registry: &crate::Registry, trail: Option<AuditTrail>) -> Self {
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
            written: None,
        }
    }

    /// What resolves once the entry of the decision just made is written and fsynced
    /// (`None` without an audit file): the reply to the change waits for it, so that an
    /// acknowledged change is on the record.
    pub(super) fn written(&mut self) -> Option<tokio::sync::oneshot::Receiver<()>> {
        self.written.take()
    }
}

/// One change as asked: which device, who (the name in its key), what kind, and the
/// request abridged for a refusal's entry.
pub(super) struct Asked<'a> {
    pub(super) dev: &'a str,
    pub(super) who: Option<&'a str>,
    pub(super) action: Action,
    /// "configuration", "reference" or "envelope".
    pub(super) what: &'static str,
    pub(super) asked: &'a dyn std::fmt::Debug,
}

impl Core {
    /// Decide an operator's change: refused if who asks may not make it, or if the audit
    /// file has no room for its entry; otherwise `apply`. The decision is recorded either
    /// way (with the old and new values of what moved), kept with the device and handed
    /// to the file. The reply is `apply`'s, or the refusal.
    pub(super) fn decide(
        &mut self,
        a: Asked<'_>,
        apply: impl FnOnce(&mut Core, &Actor) -> pb::ConfigReply,
    ) -> pb::ConfigReply {
        let actor = match self.gate.access.check(a.who, a.dev, a.action) {
            Ok(actor) => actor,
            Err((actor, why)) => {
                let reply = self.registry.refuse_request(a.dev, why);
                let permit = self.gate.trail.as_ref().and_then(AuditTrail::reserve);
                self.record(&a, &actor, &reply, Vec::new(), permit);
                return reply;
            }
        };
        let permit = match &self.gate.trail {
            Some(t) => match t.reserve() {
                Some(p) => Some(p),
                None => {
                    let why = format!(
                        "the audit trail is full ({} entries wait to be written to {}); nothing changed, send it again",
                        super::trail::WAITING,
                        t.path().display()
                    );
                    return self.registry.refuse_request(a.dev, why);
                }
            },
            None => None,
        };
        let before = self.registry.settings_of(a.dev).unwrap_or_default();
        let reply = apply(self, &actor);
        let changes = match (reply.accepted, self.registry.settings_of(a.dev)) {
            (true, Some(after)) => crate::audit::diff(&before, &after),
            _ => Vec::new(),
        };
        self.record(&a, &actor, &reply, changes, permit);
        reply
    }

    fn record(
        &mut self,
        a: &Asked<'_>,
        actor: &Actor,
        reply: &pb::ConfigReply,
        changes: Vec<pb::AuditChange>,
        permit: Option<tokio::sync::mpsc::OwnedPermit<super::trail::Pending>>,
    ) {
        let unix_ns = protocol::unix_ns();
        let n = crate::audit::next_number(self.gate.last_n, unix_ns);
        self.gate.last_n = n;
        let entry = pb::AuditEntry {
            unix_ns,
            member: self.gate.member.clone(),
            n,
            device_id: a.dev.to_string(),
            operator: actor.name.clone(),
            verified: actor.verified,
            role: actor.role.map_or("", |r| r.name()).to_string(),
            action: a.what.to_string(),
            changes,
            asked: if reply.accepted {
                String::new()
            } else {
                crate::audit::abridged(&format!("{:?}", a.asked))
            },
            accepted: reply.accepted,
            reason: reply.reason.clone(),
        };
        self.registry.note_audited(reply.accepted);
        self.gate.written = None;
        if let Some(p) = permit {
            let (tx, rx) = tokio::sync::oneshot::channel();
            self.gate.written = Some(rx);
            p.send((entry.clone(), Some(tx)));
        } else if self.gate.trail.is_some() {
            // A refusal that found the queue full: kept with the device, not in the file.
            self.registry.note_audit_unwritten();
        }
        self.registry.audit(entry);
    }
}

impl Worker {
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
            let log = |r: &crate::Registry, d: &str| r.audit_of(d).map(|l| protocol::encode(&l));
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

//! The gate every change and every read passes: the access rules of the file, and the
//! audit trail that numbers and keeps their entries.

use protocol::pb;

use crate::access::{Access, Actor};
use crate::trail::AuditTrail;
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

impl Gate {
    /// The next entry number, for an entry that follows another of this member's.
    pub(super) fn last_n_next(&mut self) -> u64 {
        self.last_n = crate::audit::next_number(self.last_n, protocol::unix_ns());
        self.last_n
    }
}

//! What a person may do, one definition for every part that decides it: the service's
//! access rules (`[access]`), the console's logins and `mfc-deploy`'s inventory. Roles
//! follow Grafana's: a viewer reads, an operator also changes gains, laws, references and
//! narrows envelopes, an admin also widens an envelope (where the service's file allows
//! widening at all).

use serde::{Deserialize, Serialize};

/// What an operator may do.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    /// Reads configurations, statuses, envelopes and the audit trail.
    Viewer,
    /// Also changes laws, gains, output maps and references, and narrows envelopes.
    Operator,
    /// Also widens envelopes (only where the service's file sets `allow_remote_widening`).
    Admin,
}

impl Role {
    /// The roles' names, as files write them, least first.
    pub const NAMES: [&'static str; 3] = ["viewer", "operator", "admin"];

    /// Its name, as in the files.
    pub fn name(self) -> &'static str {
        match self {
            Role::Viewer => "viewer",
            Role::Operator => "operator",
            Role::Admin => "admin",
        }
    }

    /// Whether this role may do `action`.
    pub fn may(self, action: Action) -> bool {
        self >= action.needs()
    }
}

/// What a request does, by the least role it needs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Action {
    /// A read: a configuration, an envelope, a status, the audit trail.
    Read,
    /// A change of laws, gains, maps or reference, or an envelope narrowed.
    Change,
    /// An envelope widened.
    Widen,
}

impl Action {
    /// The least role that may do it.
    pub fn needs(self) -> Role {
        match self {
            Action::Read => Role::Viewer,
            Action::Change => Role::Operator,
            Action::Widen => Role::Admin,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_role_may_what_the_ones_below_may() {
        let may = |r: Role| [Action::Read, Action::Change, Action::Widen].map(|a| r.may(a));
        assert_eq!(may(Role::Viewer), [true, false, false]);
        assert_eq!(may(Role::Operator), [true, true, false]);
        assert_eq!(may(Role::Admin), [true, true, true]);
        for (r, n) in [Role::Viewer, Role::Operator, Role::Admin]
            .iter()
            .zip(Role::NAMES)
        {
            assert_eq!(r.name(), n);
        }
    }
}

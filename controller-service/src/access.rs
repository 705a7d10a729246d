//! Who may do what: operators, their roles and their devices, as the service's file lists
//! them. No I/O: a request's key names its operator (`protocol::keys::by`), and
//! [`Access::check`] decides from that name, the device and the action.
//!
//! The name in a key is only as good as what binds it to a person. Under a deployment the
//! router's access control (`mfc-deploy`) lets each operator's certificate query and put
//! under its own name only, and the file says `verified = true`; without one, a name is a
//! claim (mfcctl sends the local user's), and every audit entry says so. Roles follow
//! Grafana's: a viewer reads, an operator also changes gains, laws, references and
//! narrows envelopes, an admin also widens an envelope (where the file allows widening
//! at all).

use serde::{Deserialize, Serialize};

pub use protocol::roles::{Action, Role};

/// One operator in the file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OperatorSpec {
    /// The name in its request keys (under a deployment, its certificate's common name):
    /// 1 to 64 letters, digits, `-`, `_` or `.`.
    pub name: String,
    /// `viewer`, `operator` or `admin`.
    pub role: Role,
    /// The devices it may see and act on: ids, or prefixes ending in `*` (`"aero-*"`,
    /// `"*"` for all). Default `["*"]`.
    #[serde(default = "all_devices")]
    pub devices: Vec<String>,
}

fn all_devices() -> Vec<String> {
    vec!["*".into()]
}

/// The file's `[access]` section. Absent, the service takes every request from whoever
/// its key names (or nobody), and records each name as unverified.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AccessSpec {
    /// Whether the deployment's access control binds each operator's name in request
    /// keys to its certificate (`mfc-deploy` writes `true` with the rules that do). Default
    /// false: names are claims, and the audit trail says so.
    #[serde(default)]
    pub verified: bool,
    /// The operators, each name once. A request that names nobody, or someone not
    /// listed, is refused.
    #[serde(default)]
    pub operators: Vec<OperatorSpec>,
}

impl AccessSpec {
    /// Check names and device patterns; the error names the field.
    pub fn check(&self) -> Result<(), (String, String)> {
        let mut seen = std::collections::BTreeSet::new();
        for (i, o) in self.operators.iter().enumerate() {
            let at = format!("access.operators[{i}]");
            protocol::keys::check_id(&o.name).map_err(|e| (format!("{at}.name"), e.to_string()))?;
            if !seen.insert(o.name.as_str()) {
                return Err((format!("{at}.name"), format!("\"{}\" listed twice", o.name)));
            }
            for (j, p) in o.devices.iter().enumerate() {
                let stem = p.strip_suffix('*').unwrap_or(p);
                if !(stem.is_empty() || protocol::keys::check_id(stem).is_ok()) {
                    return Err((
                        format!("{at}.devices[{j}]"),
                        format!("{p:?}: a device id, or a prefix ending in '*'"),
                    ));
                }
            }
        }
        Ok(())
    }
}

/// Who asked, as an audit entry records it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Actor {
    /// The name in the request's key, or `anonymous`.
    pub name: String,
    /// Whether the name is bound to a certificate ([`AccessSpec::verified`]).
    pub verified: bool,
    /// Its role in the file (`None`: the service lists no operators, or not this one).
    pub role: Option<Role>,
}

/// The access rules of a service: its file's section, if any.
#[derive(Debug, Clone, Default)]
pub struct Access {
    spec: Option<AccessSpec>,
}

/// The name recorded for a request that names nobody.
pub const ANONYMOUS: &str = "anonymous";

impl Access {
    /// From the file's section (checked by the configuration's loader).
    pub fn new(spec: Option<AccessSpec>) -> Self {
        Self { spec }
    }

    /// Whether operators are checked at all.
    pub fn enforced(&self) -> bool {
        self.spec.is_some()
    }

    /// May `named` do `action` on `device`? The actor either way, and on refusal why.
    pub fn check(
        &self,
        named: Option<&str>,
        device: &str,
        action: Action,
    ) -> Result<Actor, (Actor, String)> {
        let name = named.unwrap_or(ANONYMOUS).to_string();
        let Some(spec) = &self.spec else {
            return Ok(Actor {
                name,
                verified: false,
                role: None,
            });
        };
        let op = named.and_then(|n| spec.operators.iter().find(|o| o.name == n));
        let actor = Actor {
            name,
            verified: spec.verified,
            role: op.map(|o| o.role),
        };
        let Some(op) = op else {
            let why = match named {
                None => {
                    "this service takes requests from named operators only (…/by/{operator})".into()
                }
                Some(n) => format!("operator \"{n}\" is not listed in this service's access"),
            };
            return Err((actor, why));
        };
        if !sees(op, device) {
            let why = format!(
                "operator \"{}\" may not act on device \"{device}\"",
                op.name
            );
            return Err((actor, why));
        }
        if op.role < action.needs() {
            let why = format!(
                "operator \"{}\" is a {}; this needs an {}",
                op.name,
                op.role.name(),
                action.needs().name()
            );
            return Err((actor, why));
        }
        Ok(actor)
    }

    /// Whether `named` may see `device` (a wildcard status or audit query returns only
    /// these).
    pub fn may_see(&self, named: Option<&str>, device: &str) -> bool {
        self.check(named, device, Action::Read).is_ok()
    }
}

fn sees(op: &OperatorSpec, device: &str) -> bool {
    op.devices.iter().any(|p| match p.strip_suffix('*') {
        Some(stem) => device.starts_with(stem),
        None => p == device,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec() -> AccessSpec {
        toml::from_str(
            r#"
            verified = true
            [[operators]]
            name = "vera"
            role = "viewer"
            [[operators]]
            name = "alice"
            role = "operator"
            devices = ["aero-*", "pump"]
            [[operators]]
            name = "root"
            role = "admin"
            "#,
        )
        .unwrap()
    }

    #[test]
    fn roles_devices_and_names_decide() {
        let a = Access::new(Some(spec()));
        let ok = |n, d, act| a.check(Some(n), d, act).is_ok();
        assert!(ok("vera", "x", Action::Read));
        assert!(!ok("vera", "x", Action::Change));
        assert!(ok("alice", "aero-3", Action::Change));
        assert!(ok("alice", "pump", Action::Change));
        assert!(!ok("alice", "pump-2", Action::Read));
        assert!(!ok("alice", "aero-3", Action::Widen));
        assert!(ok("root", "anything", Action::Widen));
        let (who, why) = a
            .check(Some("mallory"), "aero-1", Action::Read)
            .unwrap_err();
        assert_eq!(who.name, "mallory");
        assert!(why.contains("not listed"), "{why}");
        let (who, why) = a.check(None, "aero-1", Action::Read).unwrap_err();
        assert_eq!(who.name, ANONYMOUS);
        assert!(why.contains("named operators"), "{why}");
        let (who, why) = a.check(Some("vera"), "x", Action::Change).unwrap_err();
        assert_eq!((who.verified, who.role), (true, Some(Role::Viewer)));
        assert!(why.contains("is a viewer; this needs an operator"), "{why}");
        assert!(a.may_see(Some("alice"), "aero-9"));
        assert!(!a.may_see(Some("alice"), "crane"));
    }

    #[test]
    fn without_a_section_everyone_is_taken_unverified() {
        let a = Access::default();
        let who = a.check(Some("bob"), "x", Action::Widen).unwrap();
        assert_eq!(
            (who.name.as_str(), who.verified, who.role),
            ("bob", false, None)
        );
        assert_eq!(a.check(None, "x", Action::Change).unwrap().name, ANONYMOUS);
    }

    #[test]
    fn bad_sections_are_refused_with_the_field() {
        let mut s = spec();
        s.operators[1].devices.push("a/b*".into());
        assert_eq!(s.check().unwrap_err().0, "access.operators[1].devices[2]");
        let mut s = spec();
        s.operators[2].name = "vera".into();
        assert_eq!(s.check().unwrap_err().0, "access.operators[2].name");
        let mut s = spec();
        s.operators[0].name = "a b".into();
        assert_eq!(s.check().unwrap_err().0, "access.operators[0].name");
        assert!(spec().check().is_ok());
    }
}

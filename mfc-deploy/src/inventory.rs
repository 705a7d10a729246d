//! The fleet's inventory: who is in it, where the router is, where files land.
//!
//! It is the one file an operator edits. Everything else (certificates, zenoh configs,
//! access control) is generated from it, so adding a device is one line here and one
//! `mfc-deploy generate`.

use std::collections::BTreeSet;
use std::net::IpAddr;
use std::path::Path;

use serde::Deserialize;

use crate::DeployError;

/// The fleet (`fleet.toml`).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Inventory {
    /// Directory where every host keeps its bundle (default `/etc/mfc`). The zenoh configs
    /// name their certificates by absolute path, because zenoh resolves relative paths from
    /// the process's working directory, not from the config file. Bundles have distinct
    /// file names, so several can share one host (router and service, say).
    #[serde(default = "default_install_dir")]
    pub install_dir: String,
    /// Lifetime of the CA certificate, in days (default 3650).
    #[serde(default = "default_ca_days")]
    pub ca_days: u32,
    /// Lifetime of every other certificate, in days (default 397: what browsers accept,
    /// and short enough that rotation is practised).
    #[serde(default = "default_leaf_days")]
    pub leaf_days: u32,
    /// A certificate that expires within this many days is renewed by `generate`
    /// (default 30).
    #[serde(default = "default_renew_days")]
    pub renew_days: u32,
    /// The router everybody dials.
    pub router: Router,
    /// Controller services (their `--id`); each may serve every device.
    pub services: Vec<String>,
    /// Devices (plant agents' `device_id`): CN of their certificates, and the only keys
    /// their agents may use.
    #[serde(default)]
    pub devices: Vec<String>,
    /// Operators (people, consoles, scripts): each a name (`"alice"`: role `operator`
    /// on every device) or a table (`{ name = "vera", role = "viewer", devices =
    /// ["aero-*"] }`). They act through the services only, never put a command or a
    /// sample; the router holds each certificate to requests under its own name, and
    /// the services check its role and devices (`ID.access.toml`, written for each
    /// service).
    #[serde(default)]
    pub operators: Vec<OperatorGrant>,
    /// Gateways (`plant-agent gateway`: one process hosting many plants, one batch a
    /// period each way): CN of their certificates; each may speak for the plants it lists
    /// only.
    #[serde(default)]
    pub gateways: Vec<Gateway>,
    /// Browser consoles (`mfc-console`) that act for people: each gets a zenoh
    /// certificate, an HTTPS certificate for its `hosts` and a settings file whose
    /// `[login]` lists its `people`; the router lets it ask under their names (and its
    /// own, for its polls), and the console holds each person to a login.
    #[serde(default)]
    pub consoles: Vec<ConsoleGrant>,
}

/// A browser console and the operators it may act for.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ConsoleGrant {
    /// The common name of its certificates; its own requests (its polls) name it, a viewer.
    pub name: String,
    /// Names and addresses people's browsers reach it by: its HTTPS certificate's
    /// subjectAltName.
    pub hosts: Vec<String>,
    /// Operators (from `operators`) who may log in to it, each with the role and devices
    /// the inventory gives them.
    pub people: Vec<String>,
}

/// An operator: who (its certificate's common name), its role and its devices.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OperatorGrant {
    /// The common name of its certificate, and the name in its request keys.
    pub name: String,
    /// `viewer` (reads), `operator` (also changes gains, laws, references, narrows
    /// envelopes) or `admin` (also widens envelopes where a service allows it). Default
    /// `operator`.
    pub role: String,
    /// Device ids, or prefixes ending in `*`. Default `["*"]`.
    pub devices: Vec<String>,
}

/// The roles an operator may have (the services' `access::Role`).
pub const ROLES: [&str; 3] = protocol::roles::Role::NAMES;

impl<'de> Deserialize<'de> for OperatorGrant {
    /// A bare name, or a table with `name`, `role` and `devices` (unknown fields refused).
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        #[derive(Deserialize)]
        #[serde(deny_unknown_fields)]
        struct Table {
            name: String,
            #[serde(default = "operator_role")]
            role: String,
            #[serde(default = "every_device")]
            devices: Vec<String>,
        }
        struct V;
        impl<'de> serde::de::Visitor<'de> for V {
            type Value = OperatorGrant;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("an operator's name, or a table { name, role, devices }")
            }
            fn visit_str<E: serde::de::Error>(self, v: &str) -> Result<OperatorGrant, E> {
                Ok(OperatorGrant {
                    name: v.into(),
                    role: operator_role(),
                    devices: every_device(),
                })
            }
            fn visit_map<A: serde::de::MapAccess<'de>>(
                self,
                m: A,
            ) -> Result<OperatorGrant, A::Error> {
                let t = Table::deserialize(serde::de::value::MapAccessDeserializer::new(m))?;
                Ok(OperatorGrant {
                    name: t.name,
                    role: t.role,
                    devices: t.devices,
                })
            }
        }
        d.deserialize_any(V)
    }
}

fn operator_role() -> String {
    "operator".into()
}
fn every_device() -> Vec<String> {
    vec!["*".into()]
}

/// A gateway and the plants it hosts.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Gateway {
    /// Its id (the gateway file's `gateway`): the CN of its certificate.
    pub id: String,
    /// The device ids of its plants (the gateway file's `plants[].device`). They get no
    /// certificate of their own: the gateway announces them (`alive/plant/{id}`) and its
    /// key seals their batches. A plant is hosted by one gateway at most, and is not also
    /// listed in `devices`.
    pub plants: Vec<String>,
}

/// The router (zenohd).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Router {
    /// Names and addresses clients dial. All go into the router certificate's
    /// subjectAltName (clients verify the name they dial); the first is the one the
    /// generated client configs dial.
    pub hosts: Vec<String>,
    /// Port (default 7447; UDP for QUIC, TCP for TLS).
    #[serde(default = "default_port")]
    pub port: u16,
    /// The secured link every client uses (default `quic`). Both carry TLS 1.3 with
    /// certificates on both ends and the same access control. `tls` (TLS over TCP) is
    /// offered but not the default: zenoh 1.10.2's TLS link reads and writes one rustls
    /// stream from two threads (eclipse-zenoh/zenoh#2557), and under this project's
    /// two-way 100 Hz traffic it crashed a process in 3 of 4 multi-host runs (an invalid
    /// jump in the `tx-0` thread). The QUIC link keeps send and receive apart.
    #[serde(default)]
    pub protocol: Protocol,
    /// Common name of the router certificate (default `router`); no client may use it.
    #[serde(default = "default_router_name")]
    pub name: String,
    /// The endpoint zenohd listens on (default `{protocol}/[::]:{port}`: every address,
    /// IPv4 included; name one address to listen on one interface only). It must use
    /// `protocol`.
    #[serde(default)]
    pub listen: Option<String>,
    /// How long each client's attempt to reach the router may take (ms, default 500),
    /// handshakes included: about three round trips, so 500 ms serves a router up to
    /// about 150 ms of round trip away; raise it for a farther one. While the router is
    /// down, an attempt waits this long for an answer that does not come (QUIC hears no
    /// refusal), so a client is back at most about this long plus `retry` (100 ms) after
    /// the router: zenoh's default of 10 s kept plants on their fallback for 4 s after a
    /// 6 s outage.
    #[serde(default = "default_open_timeout_ms")]
    pub open_timeout_ms: u64,
}

fn default_open_timeout_ms() -> u64 {
    500
}

fn default_install_dir() -> String {
    "/etc/mfc".into()
}
fn default_ca_days() -> u32 {
    3650
}
fn default_leaf_days() -> u32 {
    397
}
fn default_renew_days() -> u32 {
    30
}
fn default_port() -> u16 {
    7447
}
fn default_router_name() -> String {
    "router".into()
}

/// The secured link (see [`Router::protocol`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Protocol {
    /// QUIC: TLS 1.3 over UDP.
    #[default]
    Quic,
    /// TLS over TCP.
    Tls,
}

impl Protocol {
    /// The zenoh locator prefix.
    pub fn prefix(self) -> &'static str {
        match self {
            Protocol::Quic => "quic",
            Protocol::Tls => "tls",
        }
    }
}

/// The role an identity plays; its access-control rules follow from it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum IdentityKind {
    /// zenohd.
    Router,
    /// A controller service.
    Service,
    /// A plant agent.
    Device,
    /// An operator.
    Operator,
    /// A gateway (one agent process hosting many plants).
    Gateway,
    /// A browser console acting for people.
    Console,
}

impl IdentityKind {
    /// The bundle directory of this role under the output directory.
    pub fn dir(self) -> &'static str {
        match self {
            IdentityKind::Router => "router",
            IdentityKind::Service => "services",
            IdentityKind::Device => "devices",
            IdentityKind::Operator => "operators",
            IdentityKind::Gateway => "gateways",
            IdentityKind::Console => "consoles",
        }
    }
}

impl Inventory {
    /// Read and check `path`.
    pub fn load(path: &Path) -> Result<Self, DeployError> {
        let text = std::fs::read_to_string(path).map_err(|e| DeployError::Io {
            path: path.to_path_buf(),
            reason: e.to_string(),
        })?;
        Self::parse(&text).map_err(|e| match e {
            DeployError::Inventory(reason) => {
                DeployError::Inventory(format!("{}: {reason}", path.display()))
            }
            e => e,
        })
    }

    /// Parse and check an inventory's text.
    pub fn parse(text: &str) -> Result<Self, DeployError> {
        let inv: Inventory =
            toml::from_str(text).map_err(|e| DeployError::Inventory(e.to_string()))?;
        inv.check()?;
        Ok(inv)
    }

    /// Every identity with its role, router first. Names are unique across roles (checked):
    /// the access control tells roles apart by certificate common name alone.
    pub fn identities(&self) -> Vec<(IdentityKind, String)> {
        let mut v = vec![(IdentityKind::Router, self.router.name.clone())];
        v.extend(
            self.services
                .iter()
                .map(|s| (IdentityKind::Service, s.clone())),
        );
        v.extend(
            self.devices
                .iter()
                .map(|s| (IdentityKind::Device, s.clone())),
        );
        v.extend(
            self.operators
                .iter()
                .map(|o| (IdentityKind::Operator, o.name.clone())),
        );
        v.extend(
            self.gateways
                .iter()
                .map(|g| (IdentityKind::Gateway, g.id.clone())),
        );
        v.extend(
            self.consoles
                .iter()
                .map(|c| (IdentityKind::Console, c.name.clone())),
        );
        v
    }

    /// The console of this name.
    pub fn console(&self, name: &str) -> Option<&ConsoleGrant> {
        self.consoles.iter().find(|c| c.name == name)
    }

    /// The endpoint clients dial: `{protocol}/{first host}:{port}` (IPv6 in brackets).
    pub fn router_endpoint(&self) -> String {
        let host = &self.router.hosts[0];
        let p = self.router.protocol.prefix();
        match host.parse::<IpAddr>() {
            Ok(IpAddr::V6(a)) => format!("{p}/[{a}]:{}", self.router.port),
            _ => format!("{p}/{host}:{}", self.router.port),
        }
    }

    /// The endpoint zenohd listens on.
    pub fn router_listen(&self) -> String {
        self.router.listen.clone().unwrap_or_else(|| {
            format!(
                "{}/[::]:{}",
                self.router.protocol.prefix(),
                self.router.port
            )
        })
    }

    fn check(&self) -> Result<(), DeployError> {
        let bad = |m: String| Err(DeployError::Inventory(m));
        if !self.install_dir.starts_with('/') {
            return bad(format!(
                "install_dir {:?} must be absolute (zenoh reads certificate paths from its working directory)",
                self.install_dir
            ));
        }
        if self.ca_days == 0 || self.leaf_days == 0 {
            return bad("ca_days and leaf_days must be at least 1".into());
        }
        if self.leaf_days > self.ca_days {
            return bad(format!(
                "leaf_days ({}) outlives ca_days ({}): certificates would outlive their CA",
                self.leaf_days, self.ca_days
            ));
        }
        if self.renew_days >= self.leaf_days {
            return bad(format!(
                "renew_days ({}) must be below leaf_days ({}), or every run renews everything",
                self.renew_days, self.leaf_days
            ));
        }
        if self.router.hosts.is_empty() {
            return bad(
                "router.hosts is empty: name at least one address or DNS name clients dial".into(),
            );
        }
        let consoles = self
            .consoles
            .iter()
            .map(|c| (format!("console {:?}", c.name), &c.hosts));
        for (who, hosts) in
            std::iter::once(("router".to_string(), &self.router.hosts)).chain(consoles)
        {
            if hosts.is_empty() {
                return bad(format!(
                    "{who}: hosts is empty: name an address or DNS name it is reached by"
                ));
            }
            if let Some(h) = hosts
                .iter()
                .find(|h| h.parse::<IpAddr>().is_err() && !is_dns_name(h))
            {
                return bad(format!(
                    "{who} host {h:?} is neither an IP address nor a DNS name"
                ));
            }
        }
        let prefix = format!("{}/", self.router.protocol.prefix());
        if !self.router_listen().starts_with(&prefix) {
            return bad(format!(
                "router.listen {:?} is not a {prefix} endpoint: the router must accept only the secured link",
                self.router_listen()
            ));
        }
        if self.router.port == 0 {
            return bad("router.port must not be 0".into());
        }
        if self.services.is_empty() {
            return bad("services is empty: at least one controller service must be listed".into());
        }
        let mut seen = BTreeSet::new();
        for (role, id) in self.identities() {
            // Device and service ids become key segments; the same rule keeps every common
            // name safe in a key expression and in a file name.
            protocol::keys::check_id(&id)
                .map_err(|e| DeployError::Inventory(format!("{role:?} {id:?}: {e}")))?;
            if RESERVED.contains(&id.as_str()) {
                // Bundles share a host's install_dir: these would overwrite `ca.pem` or
                // `zenohd.json5`.
                return bad(format!(
                    "{role:?} {id:?}: the name is reserved ({RESERVED:?})"
                ));
            }
            if id.starts_with('.') {
                // Names are also file names in the output: "." and ".." would escape it.
                return bad(format!("{role:?} {id:?}: a name must not start with '.'"));
            }
            if !seen.insert(id.clone()) {
                return bad(format!(
                    "{id:?} is listed twice: every router, service, device, operator and gateway needs its own name (the access control tells them apart by certificate name)"
                ));
            }
        }
        self.check_operators()?;
        self.check_consoles()?;
        self.check_hosted(&self.devices.iter().cloned().collect())
    }

    /// Every operator's role is one of [`ROLES`], every device pattern an id or a prefix
    /// ending in `*`.
    fn check_operators(&self) -> Result<(), DeployError> {
        for o in &self.operators {
            if !ROLES.contains(&o.role.as_str()) {
                return Err(DeployError::Inventory(format!(
                    "operator {:?}: role {:?} is not one of {ROLES:?}",
                    o.name, o.role
                )));
            }
            for p in &o.devices {
                let stem = p.strip_suffix('*').unwrap_or(p);
                if !(stem.is_empty() || protocol::keys::check_id(stem).is_ok()) {
                    return Err(DeployError::Inventory(format!(
                        "operator {:?}: devices {p:?} is neither a device id nor a prefix ending in '*'",
                        o.name
                    )));
                }
            }
        }
        Ok(())
    }

    /// Every console acts for at least one listed operator, each named once.
    fn check_consoles(&self) -> Result<(), DeployError> {
        for c in &self.consoles {
            let bad = |m: String| Err(DeployError::Inventory(format!("console {:?}: {m}", c.name)));
            if c.people.is_empty() {
                return bad("people is empty: nobody could log in".into());
            }
            let mut seen = BTreeSet::new();
            for p in &c.people {
                if !self.operators.iter().any(|o| &o.name == p) {
                    return bad(format!("{p:?} is not one of the operators"));
                }
                if !seen.insert(p) {
                    return bad(format!("{p:?} is listed twice"));
                }
            }
        }
        Ok(())
    }

    /// The settings file of console `name` (`mfc-console --config`): its people as
    /// `[login]` users with the inventory's roles (certificate logins; a password is one
    /// `password_hash` line each), HTTPS with its certificate, and the CA of people's
    /// certificates.
    pub fn console_settings(&self, name: &str) -> String {
        let mut out = format!(
            "# Generated by `mfc-deploy generate` for console {name:?}: `mfc-console --config` this\n# file. Edit the inventory's consoles and operators, not the users here; a person who\n# logs in with a password gets `password_hash = \"…\"` (mfc-console --hash-password).\n\n[login]\n"
        );
        let people = self
            .console(name)
            .map(|c| c.people.as_slice())
            .unwrap_or_default();
        for p in people {
            let role = self
                .operators
                .iter()
                .find(|o| &o.name == p)
                .map_or("viewer", |o| o.role.as_str());
            out.push_str(&format!(
                "\n[[login.users]]\nname = {p:?}\nrole = {role:?}\n"
            ));
        }
        out.push_str(&format!(
            "\n[login.https]\ncert_file = \"{name}.https.pem\"\nkey_file = \"{name}.https.key\"\nclient_ca_file = \"ca.pem\"\n"
        ));
        out
    }

    /// The `[access]` section (and the audit file) of service `s`'s configuration: the
    /// operators, their roles and devices, and `verified = true`, which the router's
    /// access control makes true (each certificate may use its own name only).
    pub fn service_access(&self, s: &str) -> String {
        let mut out = format!(
            "# Generated by `mfc-deploy generate` for service {s:?}: append it to the service's\n# configuration file. Edit the inventory's operators, not this file.\n\n[audit]\npath = \"/var/lib/mfc/audit/{s}.jsonl\"\n\n[access]\n# The router holds every operator's certificate to requests under its own name.\nverified = true\n"
        );
        for o in &self.operators {
            let devices: Vec<String> = o.devices.iter().map(|d| format!("{d:?}")).collect();
            out.push_str(&format!(
                "\n[[access.operators]]\nname = {:?}\nrole = {:?}\ndevices = [{}]\n",
                o.name,
                o.role,
                devices.join(", ")
            ));
        }
        for c in &self.consoles {
            out.push_str(&format!(
                "\n# Console {0:?}'s own requests (its polls); its people ask under their names.\n[[access.operators]]\nname = {0:?}\nrole = \"viewer\"\ndevices = [\"*\"]\n",
                c.name
            ));
        }
        out
    }

    /// Every gateway hosts at least one plant, each plant a valid device id hosted once
    /// and not also a device of its own (two processes would speak for it).
    fn check_hosted(&self, devices: &BTreeSet<String>) -> Result<(), DeployError> {
        let mut hosted = BTreeSet::new();
        for g in &self.gateways {
            if g.plants.is_empty() {
                return Err(DeployError::Inventory(format!(
                    "gateway {:?} lists no plants",
                    g.id
                )));
            }
            for p in &g.plants {
                protocol::keys::check_id(p).map_err(|e| {
                    DeployError::Inventory(format!("gateway {:?}: plant {p:?}: {e}", g.id))
                })?;
                if devices.contains(p) || !hosted.insert(p.clone()) {
                    return Err(DeployError::Inventory(format!(
                        "plant {p:?} of gateway {:?} is already a device or another gateway's plant: one process speaks for a plant",
                        g.id
                    )));
                }
            }
        }
        Ok(())
    }
}

/// Names no identity may take: they are file names of every bundle (`ca.pem`) or of the
/// router's (`zenohd.json5`).
pub const RESERVED: [&str; 2] = ["ca", "zenohd"];

/// A DNS name as certificates carry it: labels of letters, digits and hyphens.
fn is_dns_name(h: &str) -> bool {
    !h.is_empty()
        && h.len() <= 253
        && h.split('.').all(|l| {
            !l.is_empty()
                && l.len() <= 63
                && !l.starts_with('-')
                && !l.ends_with('-')
                && l.chars().all(|c| c.is_ascii_alphanumeric() || c == '-')
        })
}

/// An example inventory, printed by `mfc-deploy example`.
pub const EXAMPLE: &str = r#"# The fleet's inventory. Edit, then `mfc-deploy generate --inventory fleet.toml --out fleet`.
# Adding a device: add its id to `devices`, generate again (nothing else is reissued),
# copy its bundle to its host and the router bundle to the router, restart the router.

# Where every host keeps its bundle (certificates are named by absolute path in the configs).
install_dir = "/etc/mfc"
# Certificate lifetimes in days, and how close to expiry `generate` renews one.
ca_days = 3650
leaf_days = 397
renew_days = 30

# Controller services (their --id), devices (the agents' device_id), operators.
services = ["controller-1"]
devices = ["aero-1", "aero-2"]
operators = ["alice"]

# Gateways (`plant-agent gateway`): the id is the gateway file's `gateway`, the plants its
# `plants[].device`. Optional; none by default.
# [[gateways]]
# id = "cell-1"
# plants = ["heater-1", "heater-2"]

[router]
# Addresses or DNS names clients dial; all go into the router certificate. The first is dialled.
hosts = ["10.0.0.1", "router.example.org"]
port = 7447          # UDP (QUIC)
protocol = "quic"    # or "tls" (TCP); see Router::protocol before choosing it
"#;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_example_parses() {
        let inv = Inventory::parse(EXAMPLE).unwrap();
        assert_eq!(inv.devices, ["aero-1", "aero-2"]);
        assert_eq!(inv.router_endpoint(), "quic/10.0.0.1:7447");
        assert_eq!(inv.identities().len(), 5);
    }

    #[test]
    fn bad_inventories_are_refused_with_the_reason() {
        let base = "services = [\"c\"]\n[router]\nhosts = [\"10.0.0.1\"]\n";
        assert!(Inventory::parse(base).is_ok());
        let cases = [
            ("devices = [\"c\"]\n", "listed twice"),
            ("devices = [\"router\"]\n", "listed twice"),
            ("devices = [\"a/b\"]\n", "Device"),
            ("devices = [\"a*\"]\n", "Device"),
            ("devices = [\"..\"]\n", "must not start"),
            ("devices = [\"ca\"]\n", "reserved"),
            ("operators = [\"zenohd\"]\n", "reserved"),
            ("install_dir = \"etc\"\n", "absolute"),
            ("leaf_days = 5000\n", "outlives"),
            ("renew_days = 400\n", "renew_days"),
            ("colour = 1\n", "unknown field"),
        ];
        let gw = |g: &str| format!("devices = [\"d\"]\n{base}{g}");
        let gateway_cases = [
            ("[[gateways]]\nid = \"c\"\nplants = [\"p\"]\n", "listed twice"),
            ("[[gateways]]\nid = \"g\"\nplants = []\n", "no plants"),
            ("[[gateways]]\nid = \"g\"\nplants = [\"d\"]\n", "already a device"),
            (
                "[[gateways]]\nid = \"g\"\nplants = [\"p\"]\n[[gateways]]\nid = \"h\"\nplants = [\"p\"]\n",
                "another gateway's plant",
            ),
            ("[[gateways]]\nid = \"g\"\nplants = [\"p/q\"]\n", "plant \"p/q\""),
            ("[[gateways]]\nid = \"g\"\nplants = [\"p\"]\nrole = 1\n", "unknown field"),
        ];
        for (g, want) in gateway_cases {
            let e = Inventory::parse(&gw(g)).unwrap_err().to_string();
            assert!(e.contains(want), "{g:?}: {e}");
        }
        let ok =
            Inventory::parse(&gw("[[gateways]]\nid = \"g\"\nplants = [\"p\", \"q\"]\n")).unwrap();
        assert_eq!(ok.gateways[0].plants, ["p", "q"]);
        for (extra, want) in cases {
            let e = Inventory::parse(&format!("{extra}{base}"))
                .unwrap_err()
                .to_string();
            assert!(e.contains(want), "{extra:?}: {e}");
        }
        let e = Inventory::parse("services = []\n[router]\nhosts = [\"h\"]\n").unwrap_err();
        assert!(e.to_string().contains("services is empty"), "{e}");
        let plain = "services = [\"c\"]\n[router]\nhosts = [\"h\"]\nlisten = \"tcp/[::]:7447\"\n";
        let e = Inventory::parse(plain).unwrap_err();
        assert!(e.to_string().contains("not a quic/"), "{e}");
        let tls = "services = [\"c\"]\n[router]\nhosts = [\"h\"]\nprotocol = \"tls\"\n";
        let inv = Inventory::parse(tls).unwrap();
        assert_eq!(
            (inv.router_endpoint().as_str(), inv.router_listen().as_str()),
            ("tls/h:7447", "tls/[::]:7447")
        );
        let e = Inventory::parse("services = [\"c\"]\n[router]\nhosts = []\n").unwrap_err();
        assert!(e.to_string().contains("hosts is empty"), "{e}");
        let e = Inventory::parse("services = [\"c\"]\n[router]\nhosts = [\"a b\"]\n").unwrap_err();
        assert!(e.to_string().contains("neither"), "{e}");
    }

    #[test]
    fn ipv6_hosts_are_bracketed() {
        let inv =
            Inventory::parse("services = [\"c\"]\n[router]\nhosts = [\"fd00::1\"]\n").unwrap();
        assert_eq!(inv.router_endpoint(), "quic/[fd00::1]:7447");
    }
}

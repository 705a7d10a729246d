//! What a plant behind an OPC UA server is to the project: the `[plant.opcua]` table of a
//! plant file (the endpoint, who the bridge is, and per channel the node ids of the
//! measured output, the input to write and the applied value), checked. No I/O here: the
//! client is the `fieldbus` crate's.
//!
//! OPC UA addresses values by node id (`ns=2;s=Heater.Temperature`, `ns=3;i=1002`); the
//! server declares each node's type, and the bridge writes the type the server holds.
//!
//! Security follows OPC UA's own scheme: a policy and a mode for the secure channel, the
//! bridge's application certificate and the servers it trusts in a PKI directory laid out
//! as OPC UA clients lay it out (`own/cert.der`, `private/private.pem`, `trusted/`,
//! `rejected/`), and the user as anonymous, a name and password, or a certificate.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use crate::modbus::{check_safe, request_timeout, LinkLimits, MapError};

/// The `[plant.opcua]` table of a plant file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OpcUaConfig {
    /// The server's endpoint, `opc.tcp://host:port/path`.
    pub endpoint: String,
    /// Security policy of the secure channel, one of [`SECURITY_POLICIES`]. Default
    /// `None`: no signature and no encryption, for a trusted network only.
    #[serde(default = "none")]
    pub security_policy: String,
    /// Message security mode: `None` (with the policy `None`, and only with it), `Sign`
    /// or `SignAndEncrypt`. Default `None`.
    #[serde(default = "none")]
    pub security_mode: String,
    /// The bridge's PKI directory, relative to the plant file: its certificate
    /// (`own/cert.der`) and key (`private/private.pem`), the servers' certificates it
    /// trusts (`trusted/`), and those it refused (`rejected/`, where an operator checks a
    /// new server's certificate before moving it to `trusted/`). Needed by any policy but
    /// `None`; `plant-agent probe opcua --pki-dir DIR --create-keypair` makes the pair.
    #[serde(default)]
    pub pki_dir: Option<PathBuf>,
    /// A user name (absent: anonymous). Its password is in `password_file`.
    #[serde(default)]
    pub user: Option<String>,
    /// A file holding the user's password (its first line), relative to the plant file:
    /// the password itself stays out of files that get shared.
    #[serde(default)]
    pub password_file: Option<PathBuf>,
    /// The user as a certificate (DER or PEM, relative to the plant file) instead of a
    /// name: needs `user_private_key`, excludes `user`.
    #[serde(default)]
    pub user_certificate: Option<PathBuf>,
    /// The private key (PEM) of `user_certificate`.
    #[serde(default)]
    pub user_private_key: Option<PathBuf>,
    /// How the outputs reach the bridge: `read` (one Read per period, default) or
    /// `subscribe` (the server samples them and sends changes, no request per period;
    /// a value is then up to two sampling intervals older than a Read's).
    #[serde(default)]
    pub sampling: Sampling,
    /// The sampling (and publishing) interval (ms) of a subscription: at most the
    /// period. Default: a tenth of the period, at least 1 ms. A value reaches the loop up
    /// to two intervals late (sampled, then published), and a loop tuned on fresh values
    /// may not take that: the DC motor's iPD at 10 ms tracked within 1.03x of its offline
    /// twin at 1 ms, 1.25x at 2 ms, and went unstable at 10 ms (`docs/fieldbus.md`).
    #[serde(default)]
    pub sampling_ms: Option<u64>,
    /// Longest wait for one answer (ms). Default: half the period, at least 20 ms.
    #[serde(default)]
    pub timeout_ms: Option<u64>,
    /// Longest wait for the session at start (ms). Default: 5000.
    #[serde(default = "default_connect_timeout_ms")]
    pub connect_timeout_ms: u64,
    /// How long (ms) failing requests are tried again (the client reconnects behind
    /// them) before the run ends with the safe stop. Default 0: the first failure ends it.
    #[serde(default)]
    pub reconnect_ms: u64,
    /// One per channel, in the scenario's order.
    pub channels: Vec<OpcUaChannel>,
}

fn none() -> String {
    "None".into()
}

/// The security policies the bridge speaks, by the ends of their OPC UA URIs. Basic128Rsa15
/// and Basic256 are left out: OPC UA deprecated them (SHA-1), though servers still offer
/// them.
pub const SECURITY_POLICIES: [&str; 4] = [
    "None",
    "Basic256Sha256",
    "Aes128_Sha256_RsaOaep",
    "Aes256_Sha256_RsaPss",
];

/// The message security modes.
pub const SECURITY_MODES: [&str; 3] = ["None", "Sign", "SignAndEncrypt"];

/// How the bridge learns the outputs.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Sampling {
    /// One Read of every output per period.
    #[default]
    Read,
    /// A subscription: the server samples each output and publishes its changes (and a
    /// keep-alive when nothing changed), so that a period costs no request for them.
    Subscribe,
}
fn default_connect_timeout_ms() -> u64 {
    5000
}

/// Where one channel lives in the server: node ids.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OpcUaChannel {
    /// The measured output.
    pub output: String,
    /// The input to write (a writable variable; the bridge writes the type it holds).
    pub input: String,
    /// What the plant really applies, where the server has it.
    #[serde(default)]
    pub applied: Option<String>,
    /// The input written on every way out. Default 0; inside the channel's actuator range.
    #[serde(default)]
    pub safe: f64,
}

fn map_error(field: impl Into<String>, reason: impl Into<String>) -> MapError {
    MapError {
        field: field.into(),
        reason: reason.into(),
    }
}

/// A node id as OPC UA writes it: an optional `ns=N;` then `i=`, `s=`, `g=` or `b=` and
/// an identifier (numeric for `i=`).
pub fn is_node_id(s: &str) -> bool {
    let rest = match s.strip_prefix("ns=") {
        Some(r) => match r.split_once(';') {
            Some((ns, rest)) if ns.parse::<u16>().is_ok() => rest,
            _ => return false,
        },
        None => s,
    };
    match rest.split_at_checked(2) {
        Some(("i=", id)) => id.parse::<u32>().is_ok(),
        Some(("s=" | "g=" | "b=", id)) => !id.is_empty(),
        _ => false,
    }
}

impl OpcUaConfig {
    /// Check the map for channels whose actuator ranges are `ranges`, in a loop of
    /// period `period` (s).
    pub fn check(&self, ranges: &[(f64, f64)], period: f64) -> Result<(), MapError> {
        if !self.endpoint.starts_with("opc.tcp://") || self.endpoint.len() <= "opc.tcp://".len() {
            return Err(map_error("endpoint", "needs opc.tcp://host:port"));
        }
        self.check_security()?;
        self.check_sampling(period)?;
        let link = LinkLimits {
            timeout_ms: self.timeout_ms,
            connect_timeout_ms: self.connect_timeout_ms,
            connect_max_ms: 600_000,
            reconnect_ms: self.reconnect_ms,
        };
        link.check(self.channels.len(), ranges.len())?;
        for (i, (c, &(min, max))) in self.channels.iter().zip(ranges).enumerate() {
            let ids = [
                ("output", Some(&c.output)),
                ("input", Some(&c.input)),
                ("applied", c.applied.as_ref()),
            ];
            for (name, id) in ids {
                if let Some(id) = id.filter(|id| !is_node_id(id)) {
                    return Err(map_error(
                        format!("channels[{i}].{name}"),
                        format!("{id:?} is not a node id (ns=2;s=Name or ns=3;i=1002)"),
                    ));
                }
            }
            check_safe(&format!("channels[{i}]"), c.safe, min, max)?;
        }
        for (i, a) in self.channels.iter().enumerate() {
            if let Some(j) = self.channels[i + 1..]
                .iter()
                .position(|b| b.input == a.input)
            {
                return Err(map_error(
                    format!("channels[{}].input", i + 1 + j),
                    format!("{} is channels[{i}]'s input too", a.input),
                ));
            }
        }
        Ok(())
    }

    /// The policy, the mode, the PKI and who the user is, consistent.
    fn check_security(&self) -> Result<(), MapError> {
        let (policy, mode) = (self.security_policy.as_str(), self.security_mode.as_str());
        if !SECURITY_POLICIES.contains(&policy) {
            return Err(map_error(
                "security_policy",
                format!("{policy:?} is none of {SECURITY_POLICIES:?}"),
            ));
        }
        if !SECURITY_MODES.contains(&mode) {
            return Err(map_error(
                "security_mode",
                format!("{mode:?} is none of {SECURITY_MODES:?}"),
            ));
        }
        if (policy == "None") != (mode == "None") {
            return Err(map_error(
                "security_mode",
                format!("{mode} goes with the policy {policy}: the policy None takes the mode None, any other policy Sign or SignAndEncrypt"),
            ));
        }
        if policy != "None" && self.pki_dir.is_none() {
            return Err(map_error(
                "pki_dir",
                format!("the policy {policy} needs the bridge's certificate and the servers it trusts: set pki_dir"),
            ));
        }
        if self.user.is_some() != self.password_file.is_some() {
            return Err(map_error(
                "user",
                "a user needs its password_file, and a password_file its user",
            ));
        }
        if self.user_certificate.is_some() != self.user_private_key.is_some() {
            return Err(map_error(
                "user_certificate",
                "a user certificate needs its user_private_key, and a key its certificate",
            ));
        }
        if self.user.is_some() && self.user_certificate.is_some() {
            return Err(map_error(
                "user_certificate",
                "the user is a name or a certificate, not both",
            ));
        }
        if self.user_certificate.is_some() && policy == "None" {
            return Err(map_error(
                "user_certificate",
                "a user certificate proves the user to a server the bridge cannot check under the policy None: choose a policy",
            ));
        }
        Ok(())
    }

    fn check_sampling(&self, period: f64) -> Result<(), MapError> {
        let Some(ms) = self.sampling_ms else {
            return Ok(());
        };
        if self.sampling != Sampling::Subscribe {
            return Err(map_error(
                "sampling_ms",
                "a sampling interval is for sampling = \"subscribe\"",
            ));
        }
        if ms == 0 || ms as f64 > period * 1000.0 + 1e-9 {
            return Err(map_error(
                "sampling_ms",
                format!(
                    "{ms} ms: between 1 and the period ({} ms), or the loop reads values older than a period",
                    period * 1000.0
                ),
            ));
        }
        Ok(())
    }

    /// The timeout per request for a loop of period `period` (s).
    pub fn timeout(&self, period: f64) -> std::time::Duration {
        request_timeout(self.timeout_ms, period)
    }

    /// The sampling interval of a subscription in a loop of period `period` (s).
    pub fn sampling_interval(&self, period: f64) -> std::time::Duration {
        let tenth = (period * 100.0).floor().max(1.0) as u64;
        std::time::Duration::from_millis(self.sampling_ms.unwrap_or(tenth))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn node_ids_are_recognised_as_opc_ua_writes_them() {
        for ok in [
            "ns=2;s=Heater.Temperature",
            "ns=3;i=1002",
            "i=85",
            "s=X",
            "ns=0;g=09087e75-8e5e-499b-954f-f2a9603db28a",
        ] {
            assert!(is_node_id(ok), "{ok}");
        }
        for bad in [
            "",
            "ns=2",
            "ns=x;s=A",
            "ns=2;s=",
            "ns=2;i=abc",
            "Heater.Temperature",
            "ns=70000;i=1",
            "x=1",
        ] {
            assert!(!is_node_id(bad), "{bad}");
        }
    }

    fn config() -> OpcUaConfig {
        OpcUaConfig {
            endpoint: "opc.tcp://127.0.0.1:4840/".into(),
            security_policy: none(),
            security_mode: none(),
            pki_dir: None,
            user: None,
            password_file: None,
            user_certificate: None,
            user_private_key: None,
            sampling: Sampling::Read,
            sampling_ms: None,
            timeout_ms: None,
            connect_timeout_ms: 5000,
            reconnect_ms: 0,
            channels: vec![OpcUaChannel {
                output: "ns=2;s=Plant.Output".into(),
                input: "ns=2;s=Plant.Input".into(),
                applied: None,
                safe: 0.0,
            }],
        }
    }

    #[test]
    fn a_map_that_cannot_work_is_refused_with_its_field() {
        let ok = config();
        assert_eq!(ok.check(&[(0.0, 24.0)], 0.01), Ok(()));
        let field = |c: &OpcUaConfig| c.check(&[(0.0, 24.0)], 0.01).unwrap_err().field;
        let mut c = ok.clone();
        c.security_policy = "Basic128Rsa15".into();
        assert_eq!(field(&c), "security_policy");
        c.security_policy = "Basic256Sha256".into();
        assert_eq!(
            field(&c),
            "security_mode",
            "a secure policy with the mode None"
        );
        c.security_mode = "SignAndEncrypt".into();
        assert_eq!(field(&c), "pki_dir");
        c.pki_dir = Some("pki".into());
        assert_eq!(c.check(&[(0.0, 24.0)], 0.01), Ok(()));
        c.security_mode = "Encrypt".into();
        assert_eq!(field(&c), "security_mode");
        let mut c = ok.clone();
        c.security_mode = "Sign".into();
        assert_eq!(field(&c), "security_mode", "the policy None with a mode");
        let mut c = ok.clone();
        c.security_policy = "Basic256Sha256".into();
        c.security_mode = "Sign".into();
        c.pki_dir = Some("pki".into());
        c.user_certificate = Some("user.der".into());
        assert_eq!(field(&c), "user_certificate");
        c.user_private_key = Some("user.pem".into());
        assert_eq!(c.check(&[(0.0, 24.0)], 0.01), Ok(()));
        let mut none = c.clone();
        none.security_policy = "None".into();
        none.security_mode = "None".into();
        assert_eq!(
            field(&none),
            "user_certificate",
            "a user certificate under None"
        );
        c.user = Some("op".into());
        c.password_file = Some("pw".into());
        assert_eq!(field(&c), "user_certificate", "a name and a certificate");
        let mut c = ok.clone();
        c.sampling_ms = Some(5);
        assert_eq!(
            field(&c),
            "sampling_ms",
            "an interval without a subscription"
        );
        c.sampling = Sampling::Subscribe;
        assert_eq!(c.check(&[(0.0, 24.0)], 0.01), Ok(()));
        for bad in [0, 11] {
            c.sampling_ms = Some(bad);
            assert_eq!(field(&c), "sampling_ms", "{bad} ms in a 10 ms period");
        }
        let ms = std::time::Duration::from_millis;
        c.sampling_ms = None;
        assert_eq!(c.sampling_interval(0.01), ms(1), "a tenth of the period");
        assert_eq!(c.sampling_interval(0.1), ms(10));
        assert_eq!(c.sampling_interval(0.005), ms(1), "at least 1 ms");
        c.sampling_ms = Some(4);
        assert_eq!(c.sampling_interval(0.01), ms(4));
        let mut c = ok.clone();
        c.user = Some("op".into());
        assert_eq!(field(&c), "user");
        let mut c = ok.clone();
        c.channels[0].input = "Plant.Input".into();
        assert_eq!(field(&c), "channels[0].input");
        let mut c = ok.clone();
        c.channels[0].safe = -1.0;
        assert_eq!(field(&c), "channels[0].safe");
        let mut c = ok.clone();
        c.endpoint = "http://x".into();
        assert_eq!(field(&c), "endpoint");
        let mut c = ok.clone();
        c.channels.push(c.channels[0].clone());
        assert_eq!(
            c.check(&[(0.0, 24.0), (0.0, 24.0)], 0.01)
                .unwrap_err()
                .field,
            "channels[1].input"
        );
    }
}

//! What a plant behind an OPC UA server is to the project: the `[plant.opcua]` table of a
//! plant file (the endpoint, who the bridge is, and per channel the node ids of the
//! measured output, the input to write and the applied value), checked. No I/O here: the
//! client is the `fieldbus` crate's.
//!
//! OPC UA addresses values by node id (`ns=2;s=Heater.Temperature`, `ns=3;i=1002`); the
//! server declares each node's type, and the bridge writes the type the server holds.

use serde::{Deserialize, Serialize};

use crate::modbus::{check_safe, request_timeout, LinkLimits, MapError};

/// The `[plant.opcua]` table of a plant file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OpcUaConfig {
    /// The server's endpoint, `opc.tcp://host:port/path`.
    pub endpoint: String,
    /// Security policy. Default and, in this version, the only one: `None` (the bridge
    /// refuses the others rather than pretend).
    #[serde(default = "none")]
    pub security_policy: String,
    /// Message security mode. Default and only: `None`.
    #[serde(default = "none")]
    pub security_mode: String,
    /// A user name (absent: anonymous). Its password is in `password_file`.
    #[serde(default)]
    pub user: Option<String>,
    /// A file holding the user's password (its first line), relative to the plant file:
    /// the password itself stays out of files that get shared.
    #[serde(default)]
    pub password_file: Option<std::path::PathBuf>,
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
    /// Check the map for channels whose actuator ranges are `ranges`.
    pub fn check(&self, ranges: &[(f64, f64)]) -> Result<(), MapError> {
        if !self.endpoint.starts_with("opc.tcp://") || self.endpoint.len() <= "opc.tcp://".len() {
            return Err(map_error("endpoint", "needs opc.tcp://host:port"));
        }
        for (field, value) in [
            ("security_policy", &self.security_policy),
            ("security_mode", &self.security_mode),
        ] {
            if value != "None" {
                return Err(map_error(
                    field,
                    format!(
                        "{value}: this bridge speaks only None so far (no signing or encryption)"
                    ),
                ));
            }
        }
        if self.user.is_some() != self.password_file.is_some() {
            return Err(map_error(
                "user",
                "a user needs its password_file, and a password_file its user",
            ));
        }
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

    /// The timeout per request for a loop of period `period` (s).
    pub fn timeout(&self, period: f64) -> std::time::Duration {
        request_timeout(self.timeout_ms, period)
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
            user: None,
            password_file: None,
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
        assert_eq!(ok.check(&[(0.0, 24.0)]), Ok(()));
        let field = |c: &OpcUaConfig| c.check(&[(0.0, 24.0)]).unwrap_err().field;
        let mut c = ok.clone();
        c.security_policy = "Basic256Sha256".into();
        assert_eq!(field(&c), "security_policy");
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
            c.check(&[(0.0, 24.0), (0.0, 24.0)]).unwrap_err().field,
            "channels[1].input"
        );
    }
}

//! The service's configuration file (TOML).
//!
//! ```toml
//! controller_id = "controller-1"      # default "controller-1"
//!
//! [[devices]]                          # declared devices
//! id = "aero-1"
//! [[devices.channels]]
//! law = { law = "intelligent", params = { kind = "ip", alpha = 0.001, kp = 0.5 } }
//! output = { dead_zone = 10.0, min = -24.0, max = 24.0 }
//! reference = [{ kind = "constant", value = 0.0 }]
//!
//! [[templates]]                        # provision unknown devices whose id matches
//! pattern = "aero-$*"                  # a zenoh key expression over the id (`*`: any)
//! [[templates.channels]]
//! ...
//! ```
//!
//! A sample from a device that is neither declared nor matched by a template is refused and
//! counted in the service status.

use std::path::Path;

use mfc::trajectory::Piece;
use mfc::{ChannelConfig, LawConfig, OutputMapConfig};
use serde::{Deserialize, Serialize};

/// Why a configuration was refused.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// Unreadable file.
    #[error("{file}: {source}")]
    Io {
        /// File.
        file: String,
        /// Cause.
        source: std::io::Error,
    },
    /// Not valid TOML for the schema (the message names the field and line).
    #[error("{file}: {message}")]
    Parse {
        /// File.
        file: String,
        /// Parser message.
        message: String,
    },
    /// A value is out of range.
    #[error("{file}: `{field}`: {reason}")]
    Invalid {
        /// File.
        file: String,
        /// Field path.
        field: String,
        /// Reason.
        reason: String,
    },
}

/// One channel of a device: its law, its output map and its reference.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DeviceChannel {
    /// Control law. Default: iP, alpha 1, Kp 1.
    #[serde(default)]
    pub law: LawConfig,
    /// Output map. Default: identity.
    #[serde(default)]
    pub output: OutputMapConfig,
    /// Reference pieces (evaluated on the plant's clock). Default: constant 0.
    #[serde(default)]
    pub reference: Vec<Piece>,
}

impl DeviceChannel {
    /// The core configuration of the channel.
    pub fn channel(&self) -> ChannelConfig {
        ChannelConfig {
            law: self.law,
            output: self.output,
        }
    }
}

/// A declared device.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DeviceSpec {
    /// Device id (letters, digits, `-`, `_`, `.`).
    pub id: String,
    /// One entry per plant output.
    pub channels: Vec<DeviceChannel>,
}

/// A template that provisions unknown devices on their first sample.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TemplateSpec {
    /// Zenoh key expression matched against the device id: `*` for any id, `aero-$*` for
    /// ids that start with `aero-` (zenoh syntax: `$*` inside a chunk).
    pub pattern: String,
    /// Channels given to a matching device.
    pub channels: Vec<DeviceChannel>,
}

/// Hot standby: several services of one group serve the same devices; one is active.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StandbySpec {
    /// Group name (key chunk).
    pub group: String,
    /// Role at start. An `active` member that hears another active one at start becomes
    /// standby. Default: standby.
    #[serde(default)]
    pub role: Role,
    /// Heartbeat period of the active member (ms). Default 10 (one control period).
    #[serde(default = "heartbeat_ms")]
    pub heartbeat_ms: u64,
    /// Silence after which a standby takes over (ms). Default 30: three heartbeats, so a
    /// takeover lands within five control periods.
    #[serde(default = "takeover_ms")]
    pub takeover_ms: u64,
}

fn heartbeat_ms() -> u64 {
    10
}
fn takeover_ms() -> u64 {
    30
}

/// A member's role.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Role {
    /// Answers samples and sends heartbeats.
    Active,
    /// Follows every sample (warm state) and publishes nothing.
    #[default]
    Standby,
}

/// Per-device state snapshots, so that a restarted service carries on where it stopped.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SnapshotSpec {
    /// Directory of the snapshot files (one per device, `{id}.snap`), created if missing.
    pub dir: std::path::PathBuf,
    /// How often to write them (ms). Default 1000. They are also written on shutdown.
    #[serde(default = "snapshot_ms")]
    pub interval_ms: u64,
}

fn snapshot_ms() -> u64 {
    1000
}

/// The whole file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ServiceConfig {
    /// This controller's id (in commands, status and liveliness keys). Default
    /// `controller-1`.
    #[serde(default = "default_id")]
    pub controller_id: String,
    /// Declared devices.
    #[serde(default)]
    pub devices: Vec<DeviceSpec>,
    /// Templates for devices provisioned on first sample, tried in order.
    #[serde(default)]
    pub templates: Vec<TemplateSpec>,
    /// Hot standby group, if any (absent: this service is always active).
    #[serde(default)]
    pub standby: Option<StandbySpec>,
    /// State snapshots, if any.
    #[serde(default)]
    pub snapshots: Option<SnapshotSpec>,
}

fn default_id() -> String {
    "controller-1".into()
}

impl Default for ServiceConfig {
    fn default() -> Self {
        Self {
            controller_id: default_id(),
            devices: Vec::new(),
            templates: Vec::new(),
            standby: None,
            snapshots: None,
        }
    }
}

fn check_channels(file: &str, at: &str, channels: &[DeviceChannel]) -> Result<(), ConfigError> {
    let invalid = |field: String, reason: String| ConfigError::Invalid {
        file: file.into(),
        field,
        reason,
    };
    if channels.is_empty() {
        return Err(invalid(
            format!("{at}.channels"),
            "at least one channel".into(),
        ));
    }
    for (i, c) in channels.iter().enumerate() {
        mfc::Channel::<{ mfc::DEFAULT_CAPACITY }>::new(&c.channel())
            .map_err(|e| invalid(format!("{at}.channels[{i}]"), e.to_string()))?;
        for (j, p) in c.reference.iter().enumerate() {
            p.validate().map_err(|(f, r)| {
                invalid(format!("{at}.channels[{i}].reference[{j}].{f}"), r.into())
            })?;
        }
    }
    Ok(())
}

impl ServiceConfig {
    /// Read and check a configuration file.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let file = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Io {
            file: file.clone(),
            source,
        })?;
        Self::parse(&file, &text)
    }

    /// Parse and check configuration text; `file` names it in errors.
    pub fn parse(file: &str, text: &str) -> Result<Self, ConfigError> {
        let cfg: ServiceConfig = toml::from_str(text).map_err(|e| ConfigError::Parse {
            file: file.into(),
            message: e.to_string().trim_end().into(),
        })?;
        cfg.check(file)?;
        Ok(cfg)
    }

    /// Check ids, patterns and every channel.
    pub fn check(&self, file: &str) -> Result<(), ConfigError> {
        let invalid = |field: String, reason: String| ConfigError::Invalid {
            file: file.into(),
            field,
            reason,
        };
        protocol::keys::check_id(&self.controller_id)
            .map_err(|e| invalid("controller_id".into(), e.to_string()))?;
        let mut seen = std::collections::HashSet::new();
        for (i, d) in self.devices.iter().enumerate() {
            protocol::keys::check_id(&d.id)
                .map_err(|e| invalid(format!("devices[{i}].id"), e.to_string()))?;
            if !seen.insert(d.id.clone()) {
                return Err(invalid(
                    format!("devices[{i}].id"),
                    format!("duplicate id {:?}", d.id),
                ));
            }
            check_channels(file, &format!("devices[{i}]"), &d.channels)?;
        }
        if let Some(sb) = &self.standby {
            protocol::keys::check_id(&sb.group)
                .map_err(|e| invalid("standby.group".into(), e.to_string()))?;
            if sb.heartbeat_ms == 0 || sb.takeover_ms <= sb.heartbeat_ms {
                return Err(invalid(
                    "standby.takeover_ms".into(),
                    "heartbeat_ms must be > 0 and takeover_ms longer than heartbeat_ms".into(),
                ));
            }
        }
        if let Some(sn) = &self.snapshots {
            if sn.interval_ms == 0 {
                return Err(invalid(
                    "snapshots.interval_ms".into(),
                    "must be > 0".into(),
                ));
            }
        }
        for (i, t) in self.templates.iter().enumerate() {
            zenoh::key_expr::KeyExpr::try_from(t.pattern.as_str())
                .map_err(|e| invalid(format!("templates[{i}].pattern"), e.to_string()))?;
            check_channels(file, &format!("templates[{i}]"), &t.channels)?;
        }
        Ok(())
    }
}

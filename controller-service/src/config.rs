//! The service's configuration file (TOML).
//!
//! ```toml
//! controller_id = "controller-1"      # default "controller-1"
//! max_devices = 1024                   # declared + provisioned, default 1024
//! allow_remote_widening = false        # may an EnvelopeRequest widen? default false
//!
//! [[devices]]                          # declared devices
//! id = "aero-1"
//! prediction = { horizon = 10, delay_compensation = true }   # default: none (trend = 0.5, trend_at_rest = 0)
//! [[devices.channels]]
//! law = { law = "intelligent", params = { kind = "ip", alpha = 0.001, kp = 0.5 } }
//! output = { dead_zone = 10.0, smoothing = 2.0, min = -24.0, max = 24.0 }
//! envelope = { min = -24.0, max = 24.0, rate_limit = 2400.0 }  # default: output's limits
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
use protocol::MAX_HORIZON;
use serde::{Deserialize, Serialize};

use crate::bounds::ChannelBounds;
use crate::envelope::Limits;

/// Why a configuration was refused.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read (only from [`ServiceConfig::load`]).
    #[error("{file}: {source}")]
    Io {
        /// The path as given to [`ServiceConfig::load`], so the message names what the user
        /// typed.
        file: String,
        /// The I/O error of reading it (missing file, no permission, not UTF-8).
        source: std::io::Error,
    },
    /// Not valid TOML for the schema (the message names the field and line).
    #[error("{file}: {message}")]
    Parse {
        /// The path for [`ServiceConfig::load`], the caller's label for
        /// [`ServiceConfig::parse`].
        file: String,
        /// toml's message with trailing whitespace trimmed: it locates the error in the text
        /// and says what is wrong there (an unknown field, a wrong type, ...).
        message: String,
    },
    /// The TOML parsed but a value breaks a rule: out of range, a bad id or pattern, a
    /// duplicate device id, an empty channel list, or a law the core refuses.
    #[error("{file}: `{field}`: {reason}")]
    Invalid {
        /// As in [`ConfigError::Parse`].
        file: String,
        /// Where the bad value sits, in the file's own terms:
        /// `devices[1].channels[0].reference[2].duration`, `standby.takeover_ms`, ...
        field: String,
        /// Why it is refused, readable on its own (e.g. `must be > 0`); for a channel, the
        /// core's own error.
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
    /// Output map from the law's control value to what is sent to the plant (dead-zone
    /// compensation, limits, rate limit). Default: identity.
    #[serde(default)]
    pub output: OutputMapConfig,
    /// Reference pieces, summed and evaluated on the plant's clock (from the file the
    /// reference starts at plant time 0; a live update may move its start). Default: none,
    /// that is a constant 0.
    #[serde(default)]
    pub reference: Vec<Piece>,
    /// The channel's safety envelope: limits no command ever leaves, whatever law, gains or
    /// output map a client sets later (`{ min = -24.0, max = 24.0, rate_limit = 500.0 }`).
    /// Default: the limits of `output` above, so that a file without envelopes means what
    /// it meant before. The output map must lie inside it; limits it leaves out are the
    /// envelope's.
    #[serde(default)]
    pub envelope: Option<Limits>,
    /// Bounds on what a change may set, per parameter, replacing the ones derived from
    /// the device's period and envelope and the table's (`crate::bounds`), wider or
    /// narrower: `{ kp = [0.0, 500.0] }`. Default: none (the derived ones apply).
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub bounds: std::collections::BTreeMap<String, [f64; 2]>,
    /// The range of the channel's measured output, `[lo, hi]`: every reference, its pieces
    /// summed at their extremes, stays inside. Default: none (each piece at most
    /// `crate::bounds::REFERENCE_LIMIT` in size).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub range: Option<[f64; 2]>,
}

impl DeviceChannel {
    /// The law and output map, as the core builds a controller from them. The reference is
    /// left out: the service evaluates it itself and hands the controller its value.
    pub fn channel(&self) -> ChannelConfig {
        ChannelConfig {
            law: self.law,
            output: self.output,
        }
    }

    /// The channel's envelope: the one written, else the output map's limits.
    pub fn limits(&self) -> Limits {
        self.envelope
            .unwrap_or_else(|| Limits::of_map(&self.output))
    }

    /// What a change of this channel may set (`bounds` and `range` checked).
    pub fn bounds(&self) -> Result<ChannelBounds, (String, String)> {
        ChannelBounds::from_file(&self.bounds, self.range)
    }
}

/// What a device's commands predict beyond their own period, for plants on lossy or slow
/// links (packetized predictive control, `docs/results-faults.md`). Off by default: a command
/// then carries its own outputs only, as before.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Prediction {
    /// Periods of future outputs each command carries, predicted with the ultra-local model
    /// (or ADRC's observer) and the reference known ahead; the agent plays them while
    /// commands are lost or late. At most [`MAX_HORIZON`]. Default 0: none.
    pub horizon: u32,
    /// Predict from the state the plant will be in when the command lands: the model is
    /// driven, over the measured round trip (the median of the plant's recent reports, in
    /// periods), by the outputs already on their way, and the horizon is lengthened to
    /// reach the landing period. Default false.
    pub delay_compensation: bool,
    /// How an intelligent channel with an `estimate_filter` predicts `F`: 0 holds the
    /// filtered `F_est` (an estimate already `estimate_filter` old) over the whole
    /// prediction; `g > 0` takes the filter's lag back and extrapolates `F` at the fraction
    /// `g` of its trend (`F(s) = F_est + Ḟ (τ + g s)`, see `mfc::intelligent`), while any
    /// of the device's references moves. Other laws ignore it. 0 to 2; default
    /// [`DEFAULT_TREND`].
    pub trend: f64,
    /// The same, once every reference of the device has rested for the channel's
    /// `hold_after`: there the trend is mostly the encoder's counts, so the default holds
    /// `F`; a plant whose load drifts while it holds wants `trend` here too. 0 to 2;
    /// default [`DEFAULT_TREND_AT_REST`].
    pub trend_at_rest: f64,
}

/// Default [`Prediction::trend`]: half the trend. In the lockstep simulator
/// (`mfc-lab netsim`, AERO scenarios 1 to 4, four link seeds) it took the pitch RMS ratio
/// of `ipd+h10+dc` at 50 / 100 ms from 1.44 / 2.03 to 1.09 / 1.46 on scenario 2 and from
/// 1.49 / 2.14 to 1.12 / 1.52 on scenario 4, helped scenarios 1 and 3 at 20 and 50 ms and
/// left them where they were at 100 ms (`docs/results-faults.md`); a whole trend (1)
/// over-extrapolates the estimate's noise at 100 ms. The price is more chatter.
pub const DEFAULT_TREND: f64 = 0.5;

/// Default [`Prediction::trend_at_rest`]: `F` held. In the lockstep simulator (AERO
/// scenarios 1 to 4, three link seeds) following half the trend at rest too left scenarios
/// 1 and 3 at 1.60 and 1.51 at 100 ms with 1.7 V of pitch chatter per sample; holding `F`
/// there, 1.46 and 1.39 with 1.3, and scenarios 2 and 4 unchanged (`docs/results-faults.md`).
pub const DEFAULT_TREND_AT_REST: f64 = 0.0;

impl Default for Prediction {
    fn default() -> Self {
        Self {
            horizon: 0,
            delay_compensation: false,
            trend: DEFAULT_TREND,
            trend_at_rest: DEFAULT_TREND_AT_REST,
        }
    }
}

impl Prediction {
    /// The offending field (`horizon`, `trend`, `trend_at_rest`) and why.
    fn check(&self) -> Result<(), (&'static str, String)> {
        if self.horizon > MAX_HORIZON {
            return Err((
                "horizon",
                format!(
                    "prediction.horizon {} is above {MAX_HORIZON} periods",
                    self.horizon
                ),
            ));
        }
        for (field, g) in [("trend", self.trend), ("trend_at_rest", self.trend_at_rest)] {
            if !(0.0..=2.0).contains(&g) {
                return Err((
                    field,
                    format!("prediction.{field} {g} is not between 0 and 2"),
                ));
            }
        }
        Ok(())
    }
}

/// A declared device: built when the service starts, before its first sample, so it shows
/// in the status at once and a snapshot of it is restored only while it stays declared.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DeviceSpec {
    /// Device id: 1 to 64 letters, digits, `-`, `_`, `.`; unique in the file. It is the
    /// `{id}` chunk of the device's keys, and a sample whose own `device_id` differs from
    /// the key it came on is rejected.
    pub id: String,
    /// One entry per plant output, in the plant's channel order; at least one. Every sample
    /// must carry exactly this many outputs.
    pub channels: Vec<DeviceChannel>,
    /// Horizon and delay compensation of its commands. Default: none.
    #[serde(default)]
    pub prediction: Prediction,
}

/// A template that provisions unknown devices on their first sample.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TemplateSpec {
    /// Zenoh key expression matched against the device id: `*` for any id, `aero-$*` for
    /// ids that start with `aero-` (zenoh syntax: `$*` inside a chunk).
    pub pattern: String,
    /// Channels of every device the pattern provisions (at least one); each such device
    /// gets its own control state built from them.
    pub channels: Vec<DeviceChannel>,
    /// Horizon and delay compensation of its devices' commands. Default: none.
    #[serde(default)]
    pub prediction: Prediction,
}

/// Hot standby: several services of one group serve the same devices; one is active.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StandbySpec {
    /// Name shared by the members that back each other up: the `{group}` chunk of the
    /// heartbeat key, so the same rules as a device id.
    pub group: String,
    /// Role at start. An `active` member that hears another active one at start becomes
    /// standby. Default: standby.
    #[serde(default)]
    pub role: StandbyRole,
    /// Heartbeat period of the active member, also how often a standby checks for silence
    /// (ms, > 0). Default 10 (one control period).
    #[serde(default = "heartbeat_ms")]
    pub heartbeat_ms: u64,
    /// Silence after which a standby takes over (ms, longer than `heartbeat_ms`). Default
    /// 30: three heartbeats, so a takeover lands within five control periods.
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
pub enum StandbyRole {
    /// Answers samples and sends heartbeats.
    Active,
    /// Follows every sample (warm state) and publishes nothing.
    #[default]
    Standby,
}

/// Several service instances sharing one fleet of devices ([`crate::fleet`]): each device
/// is owned by exactly one live member, chosen by rendezvous hashing over the members
/// found by liveliness, with no per-instance device list. Every member must have the same
/// devices and templates in its file (the hash, not the file, decides who serves).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FleetSpec {
    /// Name shared by the members (a key chunk, the same rules as a device id).
    pub name: String,
    /// Warm standbys: the second member in each shard's rank steps its samples too, so it
    /// takes over a dead owner's devices with their state at once (twice the stepping
    /// over the fleet). Without, a dead owner's devices restart afresh (a warm-up) on
    /// their new owner. Default true.
    #[serde(default = "yes")]
    pub standby: bool,
    /// How long an owner outranked by a newcomer keeps answering a shard while it waits
    /// for the newcomer to ask for it (ms, > 0). Default 1000.
    #[serde(default = "release_timeout_ms")]
    pub release_timeout_ms: u64,
    /// How long a member waits for one reply from a shard's previous owner before it
    /// checks that the owner is still in the fleet and asks again (ms, > 0). Default 500.
    /// A member never takes a shard from an owner that is still there without its reply.
    #[serde(default = "handover_timeout_ms")]
    pub handover_timeout_ms: u64,
    /// How long a starting member looks for the others before it decides what it owns
    /// (ms, > 0). Default 300.
    #[serde(default = "discover_ms")]
    pub discover_ms: u64,
    /// How long a starting member waits to be connected to every endpoint it was told to
    /// connect to (`--connect`, `connect/endpoints`) before it looks for the others (ms).
    /// Zenoh may return the session before its connections are up; a member that looked
    /// then would believe itself alone and answer shards the others still answer. An
    /// endpoint that stays down costs this much at start (0: do not wait). Default 5000.
    #[serde(default = "connect_wait_ms")]
    pub connect_wait_ms: u64,
}

fn yes() -> bool {
    true
}
fn one() -> usize {
    1
}
fn release_timeout_ms() -> u64 {
    1000
}
fn handover_timeout_ms() -> u64 {
    500
}
fn discover_ms() -> u64 {
    300
}
fn connect_wait_ms() -> u64 {
    5000
}

/// Per-device state snapshots, so that a restarted service carries on where it stopped.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SnapshotSpec {
    /// Directory of the snapshot files (one per device, `{id}.snap`), created if missing.
    pub dir: std::path::PathBuf,
    /// How often to write them (ms, > 0). Default 1000. They are also written on shutdown,
    /// so this bounds only what a crash loses.
    #[serde(default = "snapshot_ms")]
    pub interval_ms: u64,
}

fn snapshot_ms() -> u64 {
    1000
}

/// The whole file. [`Default`] is an empty service (`controller-1`, no devices, no
/// templates) for programs that fill it in themselves.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ServiceConfig {
    /// This controller's id (in commands, status and liveliness keys). Default
    /// `controller-1`.
    #[serde(default = "default_id")]
    pub controller_id: String,
    /// Devices served from the start, with unique ids. Default none: then only templates
    /// provision devices.
    #[serde(default)]
    pub devices: Vec<DeviceSpec>,
    /// Templates for devices provisioned on first sample, tried in order: the first whose
    /// pattern matches wins. A declared id never reaches them.
    #[serde(default)]
    pub templates: Vec<TemplateSpec>,
    /// Hot standby group, if any (absent: this service is always active).
    #[serde(default)]
    pub standby: Option<StandbySpec>,
    /// Workers that device state is sharded over, each on a task of its own, so that one
    /// process uses every core (at least 1; default 1). With more than one, each worker
    /// is a member of a fleet inside the process (`{controller_id}.w{i}`, without
    /// standbys): the shards are split among them as among instances, each worker
    /// subscribes to its own shards only, and no state or lock is shared between them.
    /// Its status, liveliness token and commands carry the worker's id. With a `fleet`,
    /// every worker is a member of it.
    #[serde(default = "one")]
    pub workers: usize,
    /// Fleet membership, if several instances share the devices (absent: this service
    /// serves every device it is configured for). Not with `standby`.
    #[serde(default)]
    pub fleet: Option<FleetSpec>,
    /// Where and how often to save device state (absent: nothing is saved, and a restarted
    /// service starts every device afresh).
    #[serde(default)]
    pub snapshots: Option<SnapshotSpec>,
    /// Most devices served at once, declared and provisioned together (at least the number
    /// declared). A template device beyond it is refused and counted
    /// (`device_table_full`), so a flood of new ids cannot grow the service. Default 1024.
    #[serde(default = "max_devices")]
    pub max_devices: usize,
    /// Whether an `EnvelopeRequest` from the network may widen a device's envelope.
    /// Narrowing is always allowed. Default false: only this file widens an envelope.
    #[serde(default)]
    pub allow_remote_widening: bool,
    /// A Prometheus endpoint (absent: none). `metrics = { listen = "127.0.0.1:9464" }`:
    /// service-wide series only, whatever the number of devices; `devices = ["aero-1"]`
    /// or `per_device = true` (up to `max_devices`) add series of their own; see
    /// `telemetry::MetricsSpec`.
    #[serde(default)]
    pub metrics: Option<telemetry::MetricsSpec>,
    /// Record samples, commands, configuration changes and events to an MCAP file (absent:
    /// no recording). `record = { path = "service.mcap" }`; see `telemetry::RecordSpec`.
    #[serde(default)]
    pub record: Option<telemetry::RecordSpec>,
    /// The fleet's secret file (64 hexadecimal digits; `mfc-deploy` writes
    /// `keys/fleet.secret`), relative to this file. With it, every sample and gateway batch
    /// must carry its device's or gateway's MAC (`protocol::auth`; others are counted as
    /// `forged` and change nothing), and commands and replies to operators are sealed.
    /// Absent: the service runs open, and the log says so.
    #[serde(default)]
    pub secret_file: Option<std::path::PathBuf>,
    /// Who may do what (`crate::access`): `[access] verified = true` and
    /// `[[access.operators]] name = "alice", role = "operator", devices = ["aero-*"]`.
    /// Absent: every request is taken, from whoever its key names (or nobody), and the
    /// audit trail records each name as unverified.
    #[serde(default)]
    pub access: Option<crate::access::AccessSpec>,
    /// The audit trail's file (absent: the entries are kept in memory only, the latest
    /// 64 per device, and the log says so at start). `audit = { path = "audit.jsonl" }`.
    #[serde(default)]
    pub audit: Option<AuditSpec>,
    /// Whether the kernel may back the service's memory with transparent huge pages
    /// (2 MiB; Linux). Default false: the allocator asks for them, and every thread's heap
    /// then holds whole 2 MiB pages for the few kilobytes it uses; with them a service grew
    /// by 1.1-1.6 KiB a plant more at ten thousand plants and by 7-9 KiB a plant more at two
    /// thousand (`docs/scale.md`, "Memory per plant"). True trades that memory for fewer
    /// misses in the processor's page tables, which did not show in the service's CPU.
    #[serde(default)]
    pub huge_pages: bool,
}

/// The audit trail's file: one JSON line per decision on an operator's change
/// (`crate::audit::to_line`), appended and fsynced before the change is acknowledged,
/// rotated by size.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AuditSpec {
    /// The file, relative to this configuration file; its directory is created if
    /// missing. Rotated files are `{path}.1` (newest) to `{path}.{keep}`.
    pub path: std::path::PathBuf,
    /// Size at which the file is rotated (bytes, at least 4096). Default 16 MiB.
    #[serde(default = "rotate_bytes")]
    pub rotate_bytes: u64,
    /// Rotated files kept (at least 1). Default 10: with the default size, the latest
    /// 176 MiB of decisions.
    #[serde(default = "audit_keep")]
    pub keep: u32,
}

fn rotate_bytes() -> u64 {
    16 << 20
}
fn audit_keep() -> u32 {
    10
}

fn max_devices() -> usize {
    1024
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
            fleet: None,
            workers: 1,
            snapshots: None,
            max_devices: max_devices(),
            allow_remote_widening: false,
            metrics: None,
            record: None,
            secret_file: None,
            access: None,
            audit: None,
            huge_pages: false,
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
        let limits = c.limits();
        limits
            .check()
            .map_err(|e| invalid(format!("{at}.channels[{i}].envelope"), e))?;
        limits
            .fit_request(c.output, "output")
            .map_err(|e| invalid(format!("{at}.channels[{i}]"), e))?;
        for (j, p) in c.reference.iter().enumerate() {
            p.validate().map_err(|(f, r)| {
                invalid(format!("{at}.channels[{i}].reference[{j}].{f}"), r.into())
            })?;
        }
        // The file's own values obey the bounds it sets (the device's period is not known
        // yet: the table's and the envelope's apply).
        let bounds = c
            .bounds()
            .map_err(|(f, r)| invalid(format!("{at}.channels[{i}].{f}"), r))?;
        bounds
            .check_all(&c.channel(), &limits, None)
            .map_err(|r| invalid(format!("{at}.channels[{i}]"), r))?;
        bounds
            .check_reference(&c.reference, None)
            .map_err(|r| invalid(format!("{at}.channels[{i}].reference"), r))?;
    }
    Ok(())
}

impl ServiceConfig {
    /// The configuration of each worker (see `workers`): this one for a single worker;
    /// otherwise one per worker, each a fleet member with its own id, in this file's fleet
    /// or, without one, in a fleet of the process's own workers with no standbys (they
    /// would die with the process anyway).
    pub fn worker_configs(&self) -> Vec<ServiceConfig> {
        if self.workers <= 1 {
            return vec![self.clone()];
        }
        (0..self.workers)
            .map(|i| {
                let mut c = self.clone();
                c.controller_id = format!("{}.w{i}", self.controller_id);
                c.workers = 1;
                if c.fleet.is_none() {
                    c.fleet = Some(FleetSpec {
                        name: format!("{}.workers", self.controller_id),
                        standby: false,
                        release_timeout_ms: release_timeout_ms(),
                        handover_timeout_ms: handover_timeout_ms(),
                        discover_ms: discover_ms(),
                        // The workers share the process's session: it is connected already.
                        connect_wait_ms: 0,
                    });
                }
                c
            })
            .collect()
    }

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
        let invalid = |(field, reason): (String, String)| ConfigError::Invalid {
            file: file.into(),
            field,
            reason,
        };
        protocol::keys::check_id(&self.controller_id)
            .map_err(|e| invalid(("controller_id".into(), e.to_string())))?;
        self.check_devices(file)?;
        self.check_workers().map_err(invalid)?;
        self.check_groups().map_err(invalid)?;
        if let Some(sn) = &self.snapshots {
            if sn.interval_ms == 0 {
                return Err(invalid((
                    "snapshots.interval_ms".into(),
                    "must be > 0".into(),
                )));
            }
        }
        if let Some(a) = &self.access {
            a.check().map_err(invalid)?;
        }
        if let Some(m) = &self.metrics {
            m.check().map_err(|e| invalid(("metrics".into(), e)))?;
        }
        if let Some(a) = &self.audit {
            if a.rotate_bytes < 4096 || a.keep == 0 {
                return Err(invalid((
                    "audit".into(),
                    format!(
                        "rotate_bytes must be at least 4096 and keep at least 1 (got {} and {})",
                        a.rotate_bytes, a.keep
                    ),
                )));
            }
        }
        if self.max_devices < self.devices.len() {
            return Err(invalid((
                "max_devices".into(),
                format!(
                    "{} is fewer than the {} devices declared",
                    self.max_devices,
                    self.devices.len()
                ),
            )));
        }
        for (i, t) in self.templates.iter().enumerate() {
            zenoh::key_expr::KeyExpr::try_from(t.pattern.as_str())
                .map_err(|e| invalid((format!("templates[{i}].pattern"), e.to_string())))?;
            check_channels(file, &format!("templates[{i}]"), &t.channels)?;
            t.prediction
                .check()
                .map_err(|(f, r)| invalid((format!("templates[{i}].prediction.{f}"), r)))?;
        }
        Ok(())
    }

    /// The declared devices: valid and distinct ids, channels, predictions.
    fn check_devices(&self, file: &str) -> Result<(), ConfigError> {
        let invalid = |field: String, reason: String| ConfigError::Invalid {
            file: file.into(),
            field,
            reason,
        };
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
            d.prediction
                .check()
                .map_err(|(f, r)| invalid(format!("devices[{i}].prediction.{f}"), r))?;
        }
        Ok(())
    }

    /// The number of workers, and what it excludes: the bad field and why.
    fn check_workers(&self) -> Result<(), (String, String)> {
        let bad = |field: &str, reason: &str| Err((field.to_string(), reason.to_string()));
        if self.workers == 0 || self.workers > 64 {
            return bad("workers", "between 1 and 64");
        }
        if self.workers > 1 {
            protocol::keys::check_id(&format!("{}.w{}", self.controller_id, self.workers - 1))
                .map_err(|e| {
                    (
                        "controller_id".to_string(),
                        format!("with its workers' suffix: {e}"),
                    )
                })?;
        }
        if self.workers > 1 && self.standby.is_some() {
            return bad(
                "workers",
                "several workers and a hot-standby group exclude each other (use a fleet)",
            );
        }
        if self.workers > 1 && self.snapshots.is_some() {
            return bad(
                "workers",
                "several workers and snapshot files exclude each other for now: each worker would write every device it ever held",
            );
        }
        Ok(())
    }

    /// The fleet and the hot-standby group: names, times, and that they exclude each
    /// other. The bad field and why.
    fn check_groups(&self) -> Result<(), (String, String)> {
        if let Some(f) = &self.fleet {
            protocol::keys::check_id(&f.name)
                .map_err(|e| ("fleet.name".to_string(), e.to_string()))?;
            if self.standby.is_some() {
                return Err((
                    "fleet".into(),
                    "a fleet and a hot-standby group exclude each other: a fleet keeps standbys per shard itself".into(),
                ));
            }
            for (field, v) in [
                ("fleet.release_timeout_ms", f.release_timeout_ms),
                ("fleet.handover_timeout_ms", f.handover_timeout_ms),
                ("fleet.discover_ms", f.discover_ms),
            ] {
                if v == 0 {
                    return Err((field.into(), "must be > 0".into()));
                }
            }
        }
        if let Some(sb) = &self.standby {
            protocol::keys::check_id(&sb.group)
                .map_err(|e| ("standby.group".to_string(), e.to_string()))?;
            if sb.heartbeat_ms == 0 || sb.takeover_ms <= sb.heartbeat_ms {
                return Err((
                    "standby.takeover_ms".into(),
                    "heartbeat_ms must be > 0 and takeover_ms longer than heartbeat_ms".into(),
                ));
            }
        }
        Ok(())
    }
}

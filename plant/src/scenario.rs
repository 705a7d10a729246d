//! Scenario files: what to run, on which plant, with which controller.
//!
//! A scenario is a TOML file (the format is documented in `scenarios/README.md`, and the
//! four shipped ones are examples):
//!
//! ```toml
//! name = "scenario-1"
//! description = "simple references, nominal rig"
//! duration = 40.0          # s
//! period = 0.01            # s, sampling and actuation (default 0.01)
//! seed = 1                 # noise seed (default 0)
//!
//! [plant]                        # the built-in AERO simulator (the default) ...
//! file = "../plant.toml"         # optional, relative to this file
//! added_mass = false             # the paper's 4 g at the arm (default false)
//! params = { pitch_noise = 0.0 } # inline overrides of the plant file
//! # ... or any plant behind a driver process (plant-agent/DRIVER.md), started in
//! # this file's directory:
//! # driver = ["python3", "../heater.py", "--seed", "1"]
//!
//! [[channels]]                   # one per output, in the plant's order (1 to 64)
//! name = "azimuth_velocity"
//! reference = [{ kind = "constant", value = 0.0 }]
//! output = { dead_zone = 10.0, min = -24.0, max = 24.0 }   # default: identity, no limits
//!
//! [controller]                   # or a file or shipped name: controller = "ipd"
//! name = "ip"
//! channels = [ { law = "intelligent", params = { alpha = 0.001, kp = 0.5 } }, ... ]
//! ```
//!
//! Nothing here is specific to the AERO except the `[plant]` table's simulator fields:
//! the channel count, the output maps and the actuator ranges come from the files, and an
//! output map is the identity unless the file says otherwise (a heater must be able to
//! get 3 V). Every error names the file, the field and the reason.

use std::path::{Path, PathBuf};

use mfc::{ChannelConfig, LawConfig, OutputMapConfig};
use serde::{Deserialize, Serialize};

use crate::modbus::ModbusConfig;
use crate::opcua::OpcUaConfig;
use aero_sim::{AeroParams, PAPER_ADDED_MASS};
use mfc::trajectory::Piece;

/// Most channels a plant may have: far beyond any rig we know of, small enough that a
/// typo (`channels = 1e6` in a generated file) is caught here rather than as a huge
/// allocation.
pub const MAX_CHANNELS: usize = 64;

/// Why a scenario, plant or controller file could not be used.
#[derive(Debug, thiserror::Error)]
pub enum ScenarioError {
    /// The file could not be read.
    #[error("{file}: cannot read: {source}")]
    Io {
        /// The file.
        file: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The file is not valid TOML for its schema (the message names the field and line).
    #[error("{file}: {message}")]
    Parse {
        /// The file.
        file: PathBuf,
        /// The parser's message, with the offending key and position.
        message: String,
    },
    /// A value is out of range.
    #[error("{file}: field `{field}`: {reason}")]
    Invalid {
        /// The file.
        file: PathBuf,
        /// Dotted path of the field.
        field: String,
        /// What is wrong.
        reason: String,
    },
    /// A name that is neither a file nor a shipped scenario or controller.
    #[error("no such {what} `{name}`: not a file, and not one of the shipped ones ({known})")]
    Unknown {
        /// "scenario" or "controller".
        what: &'static str,
        /// The name.
        name: String,
        /// The shipped names.
        known: String,
    },
}

/// The `[plant]` table as written: the AERO simulator's fields, or a driver command.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PlantTable {
    /// AERO plant file (TOML of `AeroParams`), relative to the scenario file.
    pub file: Option<PathBuf>,
    /// Add the paper's 4 g mass at the rotor arm (AERO).
    pub added_mass: bool,
    /// Inline overrides of AERO plant parameters.
    pub params: toml::Table,
    /// A driver process (argv), started in the scenario file's directory. Excludes the
    /// AERO fields above.
    pub driver: Option<Vec<String>>,
    /// How long a driver may take to answer one request (ms). Default: five periods, at
    /// least 500 ms. The first answer (`hello`) may take up to 10 s (interpreters start
    /// slowly).
    pub timeout_ms: Option<u64>,
    /// A plant behind a Modbus TCP server (`crate::modbus`): where each channel's values
    /// sit in its registers. Excludes the AERO fields and a driver.
    pub modbus: Option<ModbusConfig>,
    /// A plant behind an OPC UA server (`crate::opcua`): the node ids of each channel's
    /// values. Excludes the AERO fields, a driver and a Modbus map.
    pub opcua: Option<OpcUaConfig>,
}

/// The plant of a loaded scenario.
#[derive(Debug, Clone, PartialEq)]
pub enum PlantSource {
    /// The built-in AERO simulator with these parameters.
    Aero(AeroParams),
    /// A plant behind a driver process.
    Driver(DriverCommand),
    /// A plant behind a Modbus TCP server (checked against the channels' actuator ranges),
    /// reached in real time through `plant-agent`: there is no offline twin.
    Modbus(ModbusPlant),
    /// A plant behind an OPC UA server, reached in real time through `plant-agent`
    /// (boxed: its map and paths make it the largest plant by far).
    OpcUa(Box<OpcUaPlant>),
}

/// An OPC UA plant: its map, what its period gives (the request timeout, the sampling
/// interval), the user's password read from the map's `password_file`, and the map's
/// paths resolved against the plant file's directory.
#[derive(Clone, PartialEq)]
pub struct OpcUaPlant {
    /// The map, checked.
    pub config: OpcUaConfig,
    /// Longest wait for one answer.
    pub timeout: std::time::Duration,
    /// The sampling interval of a subscription (the map's, or a tenth of the period).
    pub sampling_interval: std::time::Duration,
    /// The loop's period: no subscription may sample slower.
    pub period: std::time::Duration,
    /// The password of `config.user`, if any.
    pub password: Option<String>,
    /// The bridge's PKI directory, if the map has one.
    pub pki_dir: Option<PathBuf>,
    /// The user's certificate and private key, if the user is a certificate.
    pub user_certificate: Option<(PathBuf, PathBuf)>,
}

impl std::fmt::Debug for OpcUaPlant {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // Never the password: a Debug print ends up in logs.
        f.debug_struct("OpcUaPlant")
            .field("config", &self.config)
            .field("timeout", &self.timeout)
            .field("sampling_interval", &self.sampling_interval)
            .field("password", &self.password.as_ref().map(|_| "(set)"))
            .field("pki_dir", &self.pki_dir)
            .field("user_certificate", &self.user_certificate)
            .finish()
    }
}

/// A Modbus plant: its map, and the request timeout its period gives.
#[derive(Debug, Clone, PartialEq)]
pub struct ModbusPlant {
    /// The map, checked.
    pub config: ModbusConfig,
    /// Longest wait for one answer.
    pub timeout: std::time::Duration,
}

/// How to start a driver process.
#[derive(Debug, Clone, PartialEq)]
pub struct DriverCommand {
    /// Program and arguments.
    pub argv: Vec<String>,
    /// Working directory (the scenario file's directory; `None`: the current one).
    pub dir: Option<PathBuf>,
    /// Longest wait for one answer.
    pub timeout: std::time::Duration,
}

impl Scenario {
    /// The inputs that leave the plant safe, one per channel: what the agent writes at
    /// start and under its safe-stop fallback, and what the plant's own stop writes. Zero,
    /// but for a Modbus plant whose map names other values (a valve that must stay half
    /// open, a heater's idle power).
    pub fn safe_inputs(&self) -> Vec<f64> {
        match &self.plant {
            PlantSource::Modbus(m) => m.config.channels.iter().map(|c| c.safe).collect(),
            PlantSource::OpcUa(o) => o.config.channels.iter().map(|c| c.safe).collect(),
            _ => vec![0.0; self.channels.len()],
        }
    }
}

impl PlantSource {
    /// The AERO's parameters, if the plant is the simulator.
    pub fn aero(&self) -> Option<&AeroParams> {
        match self {
            PlantSource::Aero(p) => Some(p),
            PlantSource::Driver(_) | PlantSource::Modbus(_) | PlantSource::OpcUa(_) => None,
        }
    }
}

/// One channel of a scenario: an output of the plant, its reference and its actuator.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScenarioChannel {
    /// Channel name (used in the CSV and the plots).
    pub name: String,
    /// Unit of the output, for the plots. Default: none.
    #[serde(default)]
    pub unit: String,
    /// Reference: the sum of these pieces.
    pub reference: Vec<Piece>,
    /// Output map and actuator range. Default: the identity with no limits; the AERO's
    /// files state their ±10 V dead-zone compensation and ±24 V range.
    #[serde(default)]
    pub output: OutputMapConfig,
}

impl ScenarioChannel {
    /// Whether an applied input sits at one of the channel's actuator limits.
    pub fn saturated(&self, v: f64) -> bool {
        const EPS: f64 = 1e-9;
        (self.output.max.is_finite() && v >= self.output.max - EPS)
            || (self.output.min.is_finite() && v <= self.output.min + EPS)
    }

    /// The largest input magnitude the actuator can give (1 when unlimited), to make
    /// actuator figures comparable across plants.
    pub fn input_scale(&self) -> f64 {
        let m = self.output.max.abs().max(self.output.min.abs());
        if m.is_finite() && m > 0.0 {
            m
        } else {
            1.0
        }
    }
}

/// A controller for every channel of a plant: what `tune` writes and `sim` reads.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ControllerSet {
    /// Short name (`ip`, `pid`, ...), shown in tables.
    pub name: String,
    /// Free text: where the gains come from.
    #[serde(default)]
    pub description: String,
    /// One law per channel, in the plant's order.
    pub channels: Vec<LawConfig>,
}

/// The controller of a scenario: a file or shipped name, or inline.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum ControllerRef {
    /// A controller file relative to the scenario, or a shipped AERO set (`ip`, `ipi`,
    /// `ipd`, `ipd-tuned`, `pid`, `adrc`).
    Named(String),
    /// Inline.
    Inline(ControllerSet),
}

/// A scenario as written in its file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct ScenarioFile {
    name: String,
    #[serde(default)]
    description: String,
    duration: f64,
    #[serde(default = "default_period")]
    period: f64,
    #[serde(default)]
    seed: u64,
    #[serde(default)]
    plant: PlantTable,
    channels: Vec<ScenarioChannel>,
    controller: ControllerRef,
}

fn default_period() -> f64 {
    0.01
}

/// A loaded, checked scenario.
#[derive(Debug, Clone, PartialEq)]
pub struct Scenario {
    /// Name.
    pub name: String,
    /// Description.
    pub description: String,
    /// Duration (s).
    pub duration: f64,
    /// Sampling period (s).
    pub period: f64,
    /// Noise seed of the built-in simulator (drivers take theirs on their command line).
    pub seed: u64,
    /// The plant.
    pub plant: PlantSource,
    /// Channels, in the plant's order.
    pub channels: Vec<ScenarioChannel>,
    /// The scenario's own controller.
    pub controller: ControllerSet,
}

impl Scenario {
    /// Channel configurations (law + output map) for a controller set.
    pub fn channel_configs(&self, controller: &ControllerSet) -> Vec<ChannelConfig> {
        self.channels
            .iter()
            .zip(&controller.channels)
            .map(|(c, law)| ChannelConfig {
                law: *law,
                output: c.output,
            })
            .collect()
    }

    /// Number of samples of a run.
    pub fn steps(&self) -> usize {
        (self.duration / self.period).round() as usize + 1
    }

    /// Channel names, in order.
    pub fn names(&self) -> Vec<String> {
        self.channels.iter().map(|c| c.name.clone()).collect()
    }

    /// Reference pieces of every channel, in order.
    pub fn references(&self) -> Vec<Vec<Piece>> {
        self.channels.iter().map(|c| c.reference.clone()).collect()
    }

    /// Check that `set` has one valid law per channel of this scenario.
    pub fn check_controller(&self, set: &ControllerSet) -> Result<(), ScenarioError> {
        check_controller(
            Path::new(&format!("controller `{}`", set.name)),
            set,
            self.channels.len(),
        )
    }
}

/// Where the shipped plants live in the source tree (`plants/` at the workspace root).
const SHIPPED_ROOT: &str = "<shipped>/plants/aero";

/// The shipped AERO scenarios: (name, file name, text).
pub const SHIPPED_SCENARIOS: [(&str, &str, &str); 5] = [
    (
        "1",
        "1-simple.toml",
        include_str!("../../plants/aero/scenarios/1-simple.toml"),
    ),
    (
        "2",
        "2-complex.toml",
        include_str!("../../plants/aero/scenarios/2-complex.toml"),
    ),
    (
        "3",
        "3-simple-mass.toml",
        include_str!("../../plants/aero/scenarios/3-simple-mass.toml"),
    ),
    (
        "4",
        "4-complex-mass.toml",
        include_str!("../../plants/aero/scenarios/4-complex-mass.toml"),
    ),
    (
        "5",
        "5-fast-steps.toml",
        include_str!("../../plants/aero/scenarios/5-fast-steps.toml"),
    ),
];

/// The shipped AERO controller sets: (name, text).
pub const SHIPPED_CONTROLLERS: [(&str, &str); 11] = [
    ("ip", include_str!("../../plants/aero/controllers/ip.toml")),
    (
        "ipi",
        include_str!("../../plants/aero/controllers/ipi.toml"),
    ),
    (
        "ipd",
        include_str!("../../plants/aero/controllers/ipd.toml"),
    ),
    (
        "ipd-hold",
        include_str!("../../plants/aero/controllers/ipd-hold.toml"),
    ),
    (
        "ipd-plain",
        include_str!("../../plants/aero/controllers/ipd-plain.toml"),
    ),
    (
        "ipd-tuned",
        include_str!("../../plants/aero/controllers/ipd-tuned.toml"),
    ),
    (
        "ipd-fast",
        include_str!("../../plants/aero/controllers/ipd-fast.toml"),
    ),
    (
        "ipd-lag",
        include_str!("../../plants/aero/controllers/ipd-lag.toml"),
    ),
    (
        "ipd-quiet",
        include_str!("../../plants/aero/controllers/ipd-quiet.toml"),
    ),
    (
        "pid",
        include_str!("../../plants/aero/controllers/pid.toml"),
    ),
    (
        "adrc",
        include_str!("../../plants/aero/controllers/adrc.toml"),
    ),
];

const SHIPPED_PLANT: &str = include_str!("../../plants/aero/plant.toml");

fn parse<T: serde::de::DeserializeOwned>(file: &Path, text: &str) -> Result<T, ScenarioError> {
    toml::from_str(text).map_err(|e| ScenarioError::Parse {
        file: file.to_path_buf(),
        message: e.to_string().trim_end().to_string(),
    })
}

fn read(file: &Path) -> Result<String, ScenarioError> {
    std::fs::read_to_string(file).map_err(|source| ScenarioError::Io {
        file: file.to_path_buf(),
        source,
    })
}

fn invalid(file: &Path, field: impl Into<String>, reason: impl Into<String>) -> ScenarioError {
    ScenarioError::Invalid {
        file: file.to_path_buf(),
        field: field.into(),
        reason: reason.into(),
    }
}

/// Load a scenario from a file path, or one of the shipped AERO ones by name (`1` to `4`,
/// or their file names, e.g. `2-complex`).
pub fn load_scenario(name_or_file: &str) -> Result<Scenario, ScenarioError> {
    let path = Path::new(name_or_file);
    if path.is_file() {
        let text = read(path)?;
        let dir = path.parent().map(|d| {
            if d.as_os_str().is_empty() {
                Path::new(".")
            } else {
                d
            }
        });
        return from_text(path, &text, dir);
    }
    let key = name_or_file
        .trim_start_matches("scenario-")
        .trim_end_matches(".toml");
    for (name, file, text) in SHIPPED_SCENARIOS {
        if key == name || key == file.trim_end_matches(".toml") {
            return from_text(
                Path::new(&format!("{SHIPPED_ROOT}/scenarios/{file}")),
                text,
                None,
            );
        }
    }
    Err(ScenarioError::Unknown {
        what: "scenario",
        name: name_or_file.into(),
        known: SHIPPED_SCENARIOS
            .iter()
            .map(|s| s.0)
            .collect::<Vec<_>>()
            .join(", "),
    })
}

/// Parse and check a scenario's text; `dir` resolves relative plant, driver and
/// controller paths (`None`: a shipped scenario).
pub fn from_text(file: &Path, text: &str, dir: Option<&Path>) -> Result<Scenario, ScenarioError> {
    let raw: ScenarioFile = parse(file, text)?;
    if !(raw.duration.is_finite() && raw.duration > 0.0) {
        return Err(invalid(file, "duration", "must be finite and > 0"));
    }
    if !(raw.period.is_finite() && raw.period > 0.0 && raw.period <= raw.duration) {
        return Err(invalid(
            file,
            "period",
            "must be > 0 and at most the duration",
        ));
    }
    if raw.duration / raw.period > 10_000_000.0 {
        return Err(invalid(file, "period", "more than 10 million steps"));
    }
    let plant = resolve_plant(file, &raw.plant, dir, raw.period)?;
    let n = raw.channels.len();
    check_server_map(file, &plant, &raw.channels, raw.period)?;
    if matches!(plant, PlantSource::Aero(_)) && n != aero_sim::CHANNELS {
        return Err(invalid(
            file,
            "channels",
            format!(
                "the built-in AERO simulator has {} outputs ({}); got {n} channels (for another plant, set plant.driver)",
                aero_sim::CHANNELS,
                aero_sim::CHANNEL_NAMES.join(", ")
            ),
        ));
    }
    let mut names = std::collections::HashSet::new();
    for (i, c) in raw.channels.iter().enumerate() {
        if c.name.is_empty()
            || !c
                .name
                .chars()
                .all(|ch| ch.is_ascii_alphanumeric() || "_-.".contains(ch))
        {
            return Err(invalid(
                file,
                format!("channels[{i}].name"),
                "letters, digits, `_`, `-` and `.` only (it names CSV columns and files)",
            ));
        }
        if !names.insert(c.name.as_str()) {
            return Err(invalid(
                file,
                format!("channels[{i}].name"),
                format!("duplicate name {:?}", c.name),
            ));
        }
        for (j, piece) in c.reference.iter().enumerate() {
            piece.validate().map_err(|(field, reason)| {
                invalid(
                    file,
                    format!("channels[{i}].reference[{j}].{field}"),
                    reason,
                )
            })?;
        }
        c.output
            .validate()
            .map_err(|e| invalid(file, format!("channels[{i}].output"), e.to_string()))?;
    }
    let controller = match raw.controller {
        ControllerRef::Named(name) => {
            let local = dir.map(|d| d.join(&name)).filter(|p| p.is_file());
            match local {
                Some(p) => load_controller_file(&p)?,
                None => shipped_controller(&name)?,
            }
        }
        ControllerRef::Inline(set) => set,
    };
    check_controller(file, &controller, n)?;
    Ok(Scenario {
        name: raw.name,
        description: raw.description,
        duration: raw.duration,
        period: raw.period,
        seed: raw.seed,
        plant,
        channels: raw.channels,
        controller,
    })
}

/// A plant behind a server (`[plant.opcua]` or `[plant.modbus]`), alone in its table;
/// `None` for any other plant.
fn server_plant(
    file: &Path,
    spec: &PlantTable,
    dir: Option<&Path>,
    period: f64,
) -> Result<Option<PlantSource>, ScenarioError> {
    if let Some(config) = &spec.opcua {
        let aero = spec.file.is_some() || spec.added_mass || !spec.params.is_empty();
        if aero || spec.driver.is_some() || spec.timeout_ms.is_some() || spec.modbus.is_some() {
            return Err(invalid(
                file,
                "plant.opcua",
                "an OPC UA plant is its server: drop file, added_mass, params, driver, modbus and timeout_ms (the map has its own timeout_ms)",
            ));
        }
        let beside = |p: &PathBuf| match dir {
            Some(d) if p.is_relative() => d.join(p),
            _ => p.clone(),
        };
        let password = match &config.password_file {
            Some(p) => Some(
                read(&beside(p))?
                    .lines()
                    .next()
                    .unwrap_or_default()
                    .to_string(),
            ),
            None => None,
        };
        let user_certificate = match (&config.user_certificate, &config.user_private_key) {
            (Some(c), Some(k)) => {
                let pair = (beside(c), beside(k));
                for (field, path) in [("user_certificate", &pair.0), ("user_private_key", &pair.1)]
                {
                    if !path.is_file() {
                        return Err(invalid(
                            file,
                            format!("plant.opcua.{field}"),
                            format!("{} is not a file", path.display()),
                        ));
                    }
                }
                Some(pair)
            }
            _ => None,
        };
        return Ok(Some(PlantSource::OpcUa(Box::new(OpcUaPlant {
            config: config.clone(),
            timeout: config.timeout(period),
            sampling_interval: config.sampling_interval(period),
            period: std::time::Duration::from_secs_f64(period),
            password,
            pki_dir: config.pki_dir.as_ref().map(beside),
            user_certificate,
        }))));
    }
    if let Some(config) = &spec.modbus {
        let aero = spec.file.is_some() || spec.added_mass || !spec.params.is_empty();
        if aero || spec.driver.is_some() || spec.timeout_ms.is_some() {
            return Err(invalid(
                file,
                "plant.modbus",
                "a Modbus plant is its server: drop file, added_mass, params, driver and timeout_ms (the map has its own timeout_ms)",
            ));
        }
        return Ok(Some(PlantSource::Modbus(ModbusPlant {
            config: config.clone(),
            timeout: config.timeout(period),
        })));
    }
    Ok(None)
}

/// A server's map checked against the file's channels (their count and actuator ranges).
fn check_server_map(
    file: &Path,
    plant: &PlantSource,
    channels: &[ScenarioChannel],
    period: f64,
) -> Result<(), ScenarioError> {
    let ranges: Vec<(f64, f64)> = channels
        .iter()
        .map(|c| (c.output.min, c.output.max))
        .collect();
    let (table, checked) = match plant {
        PlantSource::OpcUa(o) => ("opcua", o.config.check(&ranges, period)),
        PlantSource::Modbus(m) => ("modbus", m.config.check(&ranges)),
        _ => return Ok(()),
    };
    checked.map_err(|e| invalid(file, format!("plant.{table}.{}", e.field), e.reason))
}

fn resolve_plant(
    file: &Path,
    spec: &PlantTable,
    dir: Option<&Path>,
    period: f64,
) -> Result<PlantSource, ScenarioError> {
    if let Some(plant) = server_plant(file, spec, dir, period)? {
        return Ok(plant);
    }
    if let Some(argv) = &spec.driver {
        if spec.file.is_some() || spec.added_mass || !spec.params.is_empty() {
            return Err(invalid(
                file,
                "plant.driver",
                "a driver plant takes its parameters on its command line: drop file, added_mass and params",
            ));
        }
        if argv.first().is_none_or(|p| p.trim().is_empty()) {
            return Err(invalid(file, "plant.driver", "needs a program"));
        }
        let default_ms = ((period * 5.0 * 1000.0).ceil() as u64).max(500);
        let timeout_ms = spec.timeout_ms.unwrap_or(default_ms);
        if timeout_ms == 0 || timeout_ms > 600_000 {
            return Err(invalid(file, "plant.timeout_ms", "must be 1 to 600000"));
        }
        return Ok(PlantSource::Driver(DriverCommand {
            argv: argv.clone(),
            dir: dir.map(Path::to_path_buf),
            timeout: std::time::Duration::from_millis(timeout_ms),
        }));
    }
    if spec.timeout_ms.is_some() {
        return Err(invalid(
            file,
            "plant.timeout_ms",
            "only for a driver plant (plant.driver)",
        ));
    }
    let (plant_file, mut table) = match &spec.file {
        Some(p) => {
            let full = match dir {
                Some(d) if p.is_relative() => d.join(p),
                _ => p.clone(),
            };
            let text = read(&full)?;
            let table: toml::Table = parse(&full, &text)?;
            (full, table)
        }
        None => {
            let shipped = PathBuf::from(format!("{SHIPPED_ROOT}/plant.toml"));
            let table = parse(&shipped, SHIPPED_PLANT)?;
            (shipped, table)
        }
    };
    for (k, v) in &spec.params {
        table.insert(k.clone(), v.clone());
    }
    let mut params: AeroParams =
        toml::Value::Table(table)
            .try_into()
            .map_err(|e: toml::de::Error| ScenarioError::Parse {
                file: file.to_path_buf(),
                message: format!("plant (from {}): {}", plant_file.display(), e.message()),
            })?;
    if spec.added_mass {
        params.added_mass = PAPER_ADDED_MASS;
    }
    params
        .validate()
        .map_err(|e| invalid(file, format!("plant.{}", e.field), e.to_string()))?;
    Ok(PlantSource::Aero(params))
}

/// Check a controller set: `channels` valid laws.
pub fn check_controller(
    file: &Path,
    set: &ControllerSet,
    channels: usize,
) -> Result<(), ScenarioError> {
    if set.channels.len() != channels {
        return Err(invalid(
            file,
            "controller.channels",
            format!(
                "the plant has {channels} channel(s); controller `{}` has {} law(s)",
                set.name,
                set.channels.len()
            ),
        ));
    }
    for (i, law) in set.channels.iter().enumerate() {
        mfc::Channel::<{ mfc::DEFAULT_CAPACITY }>::new(&ChannelConfig {
            law: *law,
            output: OutputMapConfig::default(),
        })
        .map_err(|e| invalid(file, format!("controller.channels[{i}]"), e.to_string()))?;
    }
    Ok(())
}

/// A shipped AERO controller set by name.
pub fn shipped_controller(name: &str) -> Result<ControllerSet, ScenarioError> {
    for (n, text) in SHIPPED_CONTROLLERS {
        if n == name {
            let file = PathBuf::from(format!("{SHIPPED_ROOT}/controllers/{n}.toml"));
            let set: ControllerSet = parse(&file, text)?;
            check_controller(&file, &set, aero_sim::CHANNELS)?;
            return Ok(set);
        }
    }
    Err(ScenarioError::Unknown {
        what: "controller",
        name: name.into(),
        known: SHIPPED_CONTROLLERS
            .iter()
            .map(|s| s.0)
            .collect::<Vec<_>>()
            .join(", "),
    })
}

fn load_controller_file(path: &Path) -> Result<ControllerSet, ScenarioError> {
    let set: ControllerSet = parse(path, &read(path)?)?;
    if set.channels.is_empty() || set.channels.len() > MAX_CHANNELS {
        return Err(invalid(
            path,
            "channels",
            format!("need 1 to {MAX_CHANNELS} laws, got {}", set.channels.len()),
        ));
    }
    // Each law on its own; the count is checked against the plant where it is used.
    check_controller(path, &set, set.channels.len())?;
    Ok(set)
}

/// Load a controller set from a file (as written by `tune`), or a shipped one by name.
/// Its channel count is checked against the plant where it is used
/// ([`Scenario::check_controller`]).
pub fn load_controller(name_or_file: &str) -> Result<ControllerSet, ScenarioError> {
    let path = Path::new(name_or_file);
    if path.is_file() {
        return load_controller_file(path);
    }
    shipped_controller(name_or_file)
}

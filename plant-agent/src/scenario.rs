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
//! [plant]
//! file = "../plants/aero.toml"   # optional, relative to this file
//! added_mass = false             # the paper's 4 g at the arm (default false)
//! params = { pitch_noise = 0.0 } # inline overrides of the plant file
//!
//! [[channels]]                   # one per output, in the plant's order
//! name = "azimuth_velocity"
//! reference = [{ kind = "constant", value = 0.0 }]
//! output = { dead_zone = 10.0, min = -24.0, max = 24.0 }
//!
//! [controller]                   # or a shipped one by name: controller = "ip"
//! name = "ip"
//! channels = [ { law = "intelligent", params = { alpha = 0.001, kp = 0.5 } }, ... ]
//! ```
//!
//! Every error names the file, the field and the reason.

use std::path::{Path, PathBuf};

use mfc::{ChannelConfig, LawConfig, OutputMapConfig};
use serde::{Deserialize, Serialize};

use crate::aero::{AeroParams, CHANNELS, PAPER_ADDED_MASS};
use mfc::trajectory::Piece;

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

/// The plant of a scenario.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PlantSpec {
    /// Plant file (TOML of `AeroParams`), relative to the scenario file.
    pub file: Option<PathBuf>,
    /// Add the paper's 4 g mass at the rotor arm.
    pub added_mass: bool,
    /// Inline overrides of plant parameters.
    pub params: toml::Table,
}

/// One channel of a scenario.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ChannelSpec {
    /// Channel name (used in the CSV and the plots).
    pub name: String,
    /// Unit of the output, for the plots. Default: none.
    #[serde(default)]
    pub unit: String,
    /// Reference: the sum of these pieces.
    pub reference: Vec<Piece>,
    /// Output map. Default: the AERO's (±10 V dead-zone compensation, ±24 V).
    #[serde(default = "aero_map")]
    pub output: OutputMapConfig,
}

fn aero_map() -> OutputMapConfig {
    OutputMapConfig::AERO
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

/// The controller of a scenario: inline, or a shipped one by name.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum ControllerRef {
    /// A shipped controller set (`ip`, `ipi`, `ipd`, `pid`, `adrc`).
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
    plant: PlantSpec,
    channels: Vec<ChannelSpec>,
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
    /// Noise seed.
    pub seed: u64,
    /// Resolved plant parameters.
    pub plant: AeroParams,
    /// Channels.
    pub channels: Vec<ChannelSpec>,
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
}

/// The shipped scenarios: (name, file name, text).
pub const SHIPPED_SCENARIOS: [(&str, &str, &str); 4] = [
    (
        "1",
        "1-simple.toml",
        include_str!("../scenarios/1-simple.toml"),
    ),
    (
        "2",
        "2-complex.toml",
        include_str!("../scenarios/2-complex.toml"),
    ),
    (
        "3",
        "3-simple-mass.toml",
        include_str!("../scenarios/3-simple-mass.toml"),
    ),
    (
        "4",
        "4-complex-mass.toml",
        include_str!("../scenarios/4-complex-mass.toml"),
    ),
];

/// The shipped controller sets: (name, text).
pub const SHIPPED_CONTROLLERS: [(&str, &str); 6] = [
    ("ip", include_str!("../controllers/ip.toml")),
    ("ipi", include_str!("../controllers/ipi.toml")),
    ("ipd", include_str!("../controllers/ipd.toml")),
    ("ipd-tuned", include_str!("../controllers/ipd-tuned.toml")),
    ("pid", include_str!("../controllers/pid.toml")),
    ("adrc", include_str!("../controllers/adrc.toml")),
];

const SHIPPED_PLANT: &str = include_str!("../plants/aero.toml");

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

/// Load a scenario from a file path, or one of the shipped ones by name (`1` to `4`, or
/// their file names, e.g. `2-complex`).
pub fn load_scenario(name_or_file: &str) -> Result<Scenario, ScenarioError> {
    let path = Path::new(name_or_file);
    if path.is_file() {
        let text = read(path)?;
        return from_text(path, &text, path.parent());
    }
    let key = name_or_file
        .trim_start_matches("scenario-")
        .trim_end_matches(".toml");
    for (name, file, text) in SHIPPED_SCENARIOS {
        if key == name || key == file.trim_end_matches(".toml") {
            return from_text(Path::new(&format!("<shipped>/{file}")), text, None);
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

/// Parse and check a scenario's text; `dir` resolves a relative plant file.
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
    let plant = resolve_plant(file, &raw.plant, dir)?;
    if raw.channels.len() != CHANNELS {
        return Err(invalid(
            file,
            "channels",
            format!(
                "the AERO has {CHANNELS} outputs (azimuth velocity, pitch); got {} channels",
                raw.channels.len()
            ),
        ));
    }
    for (i, c) in raw.channels.iter().enumerate() {
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
        ControllerRef::Named(name) => shipped_controller(&name)?,
        ControllerRef::Inline(set) => {
            check_controller(file, &set)?;
            set
        }
    };
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

fn resolve_plant(
    file: &Path,
    spec: &PlantSpec,
    dir: Option<&Path>,
) -> Result<AeroParams, ScenarioError> {
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
        None => (
            PathBuf::from("<shipped>/plants/aero.toml"),
            parse(Path::new("<shipped>/plants/aero.toml"), SHIPPED_PLANT)?,
        ),
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
    Ok(params)
}

/// Check a controller set against the AERO (one valid law per channel).
pub fn check_controller(file: &Path, set: &ControllerSet) -> Result<(), ScenarioError> {
    if set.channels.len() != CHANNELS {
        return Err(invalid(
            file,
            "controller.channels",
            format!("need {CHANNELS} laws, got {}", set.channels.len()),
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

/// A shipped controller set by name.
pub fn shipped_controller(name: &str) -> Result<ControllerSet, ScenarioError> {
    for (n, text) in SHIPPED_CONTROLLERS {
        if n == name {
            let file = PathBuf::from(format!("<shipped>/controllers/{n}.toml"));
            let set: ControllerSet = parse(&file, text)?;
            check_controller(&file, &set)?;
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

/// Load a controller set from a file (as written by `tune`), or a shipped one by name.
pub fn load_controller(name_or_file: &str) -> Result<ControllerSet, ScenarioError> {
    let path = Path::new(name_or_file);
    if path.is_file() {
        let set: ControllerSet = parse(path, &read(path)?)?;
        check_controller(path, &set)?;
        return Ok(set);
    }
    shipped_controller(name_or_file)
}

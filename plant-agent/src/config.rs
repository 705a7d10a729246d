//! The agent's configuration file (TOML). Every field has its default here, in
//! [`AgentFile::default`], and nowhere else; command-line flags override the file.
//!
//! ```toml
//! device = "aero-1"          # device id (key chunk); required, here or as --device
//! scenario = "2"             # scenario file (relative to this file) or a shipped AERO one:
//!                            # the plant, its channels, references, period and duration
//! controller = "ipd"         # local controller (fallback): file or shipped name; default: the scenario's
//! duration = 40.0            # s; default: the scenario's
//! max_age = 10               # oldest command still applied, in periods
//! hold_periods = 5           # periods holding the last command before the fallback
//! fallback = "local"         # "local" (the local controller) or "safe_stop" (zero inputs)
//! resend = 3                 # earlier samples sent again with each one (0 to 3), for losses
//! out = "out/run"            # where the record goes (relative to the working directory)
//! ```

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::agent::LoopConfig;
use crate::safety::{FallbackPolicy, SafetyConfig};
use plant::scenario::{load_controller, load_scenario, ControllerSet, Scenario, ScenarioError};

/// Why the agent's configuration was refused.
#[derive(Debug, thiserror::Error)]
pub enum AgentConfigError {
    /// The file could not be read.
    #[error("{file}: cannot read: {source}")]
    Io {
        /// The file.
        file: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// Not valid TOML for the schema (the message names the field and line).
    #[error("{file}: {message}")]
    Parse {
        /// The file.
        file: PathBuf,
        /// The parser's message.
        message: String,
    },
    /// A value is out of range or missing.
    #[error("{file}: `{field}`: {reason}")]
    Invalid {
        /// The file (or `(flags)`).
        file: PathBuf,
        /// The field.
        field: &'static str,
        /// What is wrong.
        reason: String,
    },
    /// The scenario or the controller.
    #[error(transparent)]
    Scenario(#[from] ScenarioError),
}

/// The agent's configuration file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AgentFile {
    /// Device id. No default: two agents with the same id would fight over one device.
    pub device: Option<String>,
    /// Scenario file or shipped name. Default `2` (the AERO's complex references).
    pub scenario: String,
    /// Local controller: file or shipped name. Default: the scenario's.
    pub controller: Option<String>,
    /// Run length (s). Default: the scenario's duration.
    pub duration: Option<f64>,
    /// Oldest command still worth applying, in periods. Default 10 (100 ms at 10 ms): on a
    /// slow link the newest command is still the best there is; older ones are stale.
    pub max_age: u32,
    /// Periods to hold the last command before falling back. Default 5.
    pub hold_periods: u32,
    /// What to fall back to. Default: the local controller.
    pub fallback: FallbackPolicy,
    /// Earlier samples sent again with each sample, 0 to 3: after a run of that many lost
    /// samples the controller still gets their data, and its estimators see no gap (on a
    /// lossy link the difference is large: `docs/results.md`). Each copy costs about 25
    /// bytes per channel. Default 3.
    pub resend: usize,
    /// Where to write the record (`run.csv`, `summary.json`, plots). Default `out/run`.
    pub out: PathBuf,
    /// A Prometheus endpoint (absent: none): `metrics = { listen = "127.0.0.1:9465" }`.
    /// In a gateway's file, set it once at the top level (a plant's is ignored).
    pub metrics: Option<telemetry::MetricsSpec>,
    /// Record the plant's side (samples sent, commands received, mode changes) to MCAP:
    /// `record = { path = "agent.mcap" }` (absent: no recording). In a gateway's file, set
    /// it once at the top level.
    pub record: Option<telemetry::RecordSpec>,
    /// The device's key file (64 hexadecimal digits; `mfc-deploy` writes
    /// `keys/{device}.key`), relative to this file: samples go out sealed with it and only
    /// commands sealed with it are judged (`protocol::auth`). Absent: the plant runs open,
    /// commands from anyone who can put on its key are judged, and the log says so. In a
    /// gateway's file, the gateway's own `key_file` serves all its plants.
    pub key_file: Option<PathBuf>,
}

impl Default for AgentFile {
    fn default() -> Self {
        Self {
            device: None,
            scenario: "2".into(),
            controller: None,
            duration: None,
            max_age: SafetyConfig::DEFAULT_MAX_AGE,
            hold_periods: SafetyConfig::DEFAULT_HOLD_PERIODS,
            fallback: FallbackPolicy::LocalController,
            resend: protocol::RESENT_SAMPLES,
            out: PathBuf::from("out/run"),
            metrics: None,
            record: None,
            key_file: None,
        }
    }
}

/// A key file named in `file`, read (relative to `file`'s directory).
pub fn read_key(
    file: &Path,
    key_file: Option<&Path>,
) -> Result<Option<protocol::auth::Key>, AgentConfigError> {
    let Some(k) = key_file else {
        return Ok(None);
    };
    let path = file.parent().unwrap_or(Path::new(".")).join(k);
    protocol::auth::Key::from_file(&path)
        .map(Some)
        .map_err(|e| AgentConfigError::Invalid {
            file: file.to_path_buf(),
            field: "key_file",
            reason: e.to_string(),
        })
}

/// `p` relative to `dir` when it names a file there; otherwise as given (a shipped name,
/// an absolute path).
fn rebase(dir: &Path, p: &str) -> String {
    let full = dir.join(p);
    if Path::new(p).is_relative() && full.is_file() {
        full.to_string_lossy().into_owned()
    } else {
        p.to_string()
    }
}

/// A configuration resolved against its files: ready to run.
#[derive(Debug, Clone)]
pub struct Resolved {
    /// The scenario (with the duration override applied).
    pub scenario: Scenario,
    /// The local controller.
    pub controller: ControllerSet,
    /// The loop's settings.
    pub loop_config: LoopConfig,
    /// Where to write the record.
    pub out: PathBuf,
}

impl AgentFile {
    /// Read a configuration file.
    pub fn load(path: &Path) -> Result<Self, AgentConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| AgentConfigError::Io {
            file: path.to_path_buf(),
            source,
        })?;
        let mut file: AgentFile = toml::from_str(&text).map_err(|e| AgentConfigError::Parse {
            file: path.to_path_buf(),
            message: e.to_string().trim_end().into(),
        })?;
        // Paths in the file are relative to the file, so it can be moved with its
        // scenario and controller.
        let dir = path.parent().unwrap_or(Path::new("."));
        file.scenario = rebase(dir, &file.scenario);
        file.controller = file.controller.as_deref().map(|c| rebase(dir, c));
        Ok(file)
    }

    /// Load the scenario and the controller and check every value; `file` names the
    /// source in errors.
    pub fn resolve(&self, file: &Path) -> Result<Resolved, AgentConfigError> {
        let invalid = |field: &'static str, reason: String| AgentConfigError::Invalid {
            file: file.to_path_buf(),
            field,
            reason,
        };
        let device = self
            .device
            .clone()
            .ok_or_else(|| invalid("device", "required (or --device)".into()))?;
        protocol::keys::check_id(&device).map_err(|e| invalid("device", e.to_string()))?;
        let mut scenario = load_scenario(&self.scenario)?;
        if let Some(d) = self.duration {
            if !(d.is_finite() && d >= scenario.period && d <= 366.0 * 86_400.0) {
                return Err(invalid(
                    "duration",
                    format!("must be between one period and a year, got {d}"),
                ));
            }
            scenario.duration = d;
        }
        let controller = match &self.controller {
            Some(c) => load_controller(c)?,
            None => scenario.controller.clone(),
        };
        scenario.check_controller(&controller)?;
        let safety = SafetyConfig {
            period: scenario.period,
            max_age: self.max_age,
            hold_periods: self.hold_periods,
            fallback: self.fallback,
        };
        safety
            .validate()
            .map_err(|e| invalid("max_age/hold_periods", e.to_string()))?;
        if self.resend > protocol::RESENT_SAMPLES {
            return Err(invalid(
                "resend",
                format!(
                    "at most {} earlier samples, got {}",
                    protocol::RESENT_SAMPLES,
                    self.resend
                ),
            ));
        }
        let mut loop_config = LoopConfig::new(&scenario, &controller, &device, safety);
        loop_config.resend = self.resend;
        loop_config.auth = read_key(file, self.key_file.as_deref())?;
        Ok(Resolved {
            scenario,
            controller,
            loop_config,
            out: self.out.clone(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
        let p = dir.join(name);
        std::fs::write(&p, text).unwrap();
        p
    }

    fn scratch(name: &str) -> PathBuf {
        let d =
            std::env::temp_dir().join(format!("mfc-agent-config-{name}-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    /// An empty file is the documented defaults, and every default is in `Default`.
    #[test]
    fn defaults_live_in_one_place() {
        let d = scratch("defaults");
        let f = AgentFile::load(&write(&d, "a.toml", "")).unwrap();
        assert_eq!(f, AgentFile::default());
        assert_eq!((f.max_age, f.hold_periods), (10, 5));
        assert_eq!(f.fallback, FallbackPolicy::LocalController);
        // No device: refused, naming the field.
        let e = f.resolve(Path::new("a.toml")).unwrap_err().to_string();
        assert!(e.contains("device"), "{e}");
    }

    #[test]
    fn unknown_fields_and_bad_values_are_refused_with_the_field() {
        let d = scratch("bad");
        let e = AgentFile::load(&write(&d, "a.toml", "device = \"x\"\nmax_ag = 3\n"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("a.toml") && e.contains("max_ag"), "{e}");
        let f = AgentFile::load(&write(&d, "b.toml", "device = \"x y\"\n")).unwrap();
        assert!(f.resolve(Path::new("b.toml")).is_err(), "not a key chunk");
        let f = AgentFile::load(&write(&d, "c.toml", "device = \"x\"\nduration = -1.0\n")).unwrap();
        let e = f.resolve(Path::new("c.toml")).unwrap_err().to_string();
        assert!(e.contains("duration"), "{e}");
        let f = AgentFile::load(&write(
            &d,
            "d.toml",
            "device = \"x\"\ncontroller = \"pid-3\"\n",
        ))
        .unwrap();
        assert!(
            f.resolve(Path::new("d.toml")).is_err(),
            "no such controller"
        );
        let f = AgentFile::load(&write(&d, "e.toml", "device = \"x\"\nresend = 4\n")).unwrap();
        let e = f.resolve(Path::new("e.toml")).unwrap_err().to_string();
        assert!(e.contains("resend") && e.contains("at most 3"), "{e}");
        let f = AgentFile::load(&write(&d, "f.toml", "device = \"x\"\nresend = 0\n")).unwrap();
        assert_eq!(
            f.resolve(Path::new("f.toml")).unwrap().loop_config.resend,
            0
        );
    }

    /// A scenario and a controller named relative to the file are found next to it, so an
    /// agent's directory can be moved as a whole.
    #[test]
    fn paths_are_relative_to_the_file() {
        let d = scratch("relative");
        let scenario = include_str!("../../plants/aero/scenarios/1-simple.toml");
        write(&d, "s.toml", scenario);
        write(
            &d,
            "c.toml",
            include_str!("../../plants/aero/controllers/pid.toml"),
        );
        let cfg = write(
            &d,
            "agent.toml",
            "device = \"rig-7\"\nscenario = \"s.toml\"\ncontroller = \"c.toml\"\nduration = 2.0\nfallback = \"safe_stop\"\n",
        );
        let r = AgentFile::load(&cfg).unwrap().resolve(&cfg).unwrap();
        assert_eq!(r.scenario.name, "scenario-1");
        assert_eq!(r.controller.name, "pid");
        assert_eq!(r.scenario.duration, 2.0);
        assert_eq!(r.loop_config.steps, 201);
        assert_eq!(r.loop_config.device_id, "rig-7");
        assert_eq!(r.loop_config.safety.fallback, FallbackPolicy::SafeStop);
    }
}

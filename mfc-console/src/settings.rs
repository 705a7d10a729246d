//! The console's optional settings file (`--config FILE`, TOML). Every field has a default,
//! so the file names only what it changes; an unknown field is an error, so a typo is not
//! silently ignored.
//!
//! ```toml
//! max_devices = 256        # devices held at once (beyond: a gone one is evicted, else refused)
//! points = 3000            # points kept per device (30 s at 100 Hz)
//! forget_after_s = 300     # a device gone and unserved this long leaves the list
//! status_period_ms = 1000  # how often the services' status is asked for
//! config_period_ms = 2000  # how often the configuration of a device being read is asked for
//! query_timeout_ms = 2000  # how long a query waits for answers
//! allowed_hosts = []       # more `Host` names the page may be reached by (e.g. "console.lan:8080")
//!
//! [login]                  # who may use the console; see `crate::login` (default: nobody
//!                          # logs in, loopback only, everyone acts as the console's operator)
//! ```

use std::path::Path;

use serde::Deserialize;

use crate::fleet::ViewBounds;
use crate::login::LoginSpec;

/// The settings.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Settings {
    /// Devices held at once.
    pub max_devices: usize,
    /// Points kept per device.
    pub points: usize,
    /// Seconds after which a device whose plant is gone and that no service serves leaves
    /// the list.
    pub forget_after_s: f64,
    /// Period of the services' status poll (ms): device list, counters, F estimates.
    pub status_period_ms: u64,
    /// Period of the configuration poll of the devices a page is showing (ms).
    pub config_period_ms: u64,
    /// How long a query waits (ms).
    pub query_timeout_ms: u64,
    /// `Host` header values accepted besides the listen address (and, on loopback,
    /// `localhost:PORT`). Requests naming any other host are refused: a page of another
    /// site cannot reach the console by rebinding a name to 127.0.0.1.
    pub allowed_hosts: Vec<String>,
    /// Logins, sessions and HTTPS ([`LoginSpec`]). Without it the console answers on
    /// loopback only, and whoever reaches it acts as the console's operator.
    pub login: Option<LoginSpec>,
}

impl Default for Settings {
    fn default() -> Self {
        let l = ViewBounds::default();
        Self {
            max_devices: l.max_devices,
            points: l.points,
            forget_after_s: l.forget_after,
            status_period_ms: 1000,
            config_period_ms: 2000,
            query_timeout_ms: 2000,
            allowed_hosts: vec![],
            login: None,
        }
    }
}

/// Why the settings cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum SettingsError {
    /// The file cannot be read.
    #[error("reading {path}: {source}")]
    Read {
        /// The file.
        path: String,
        /// The reason.
        source: std::io::Error,
    },
    /// The file is not valid.
    #[error("{path}: {reason}")]
    Invalid {
        /// The file.
        path: String,
        /// The reason.
        reason: String,
    },
}

impl Settings {
    /// Read and check a settings file.
    pub fn load(path: &Path) -> Result<Self, SettingsError> {
        let text = std::fs::read_to_string(path).map_err(|source| SettingsError::Read {
            path: path.display().to_string(),
            source,
        })?;
        let mut s = Self::parse(&text).map_err(|reason| SettingsError::Invalid {
            path: path.display().to_string(),
            reason,
        })?;
        if let Some(l) = &mut s.login {
            l.resolve(path.parent().unwrap_or(Path::new(".")));
        }
        Ok(s)
    }

    /// Parse and check settings from TOML text.
    pub fn parse(text: &str) -> Result<Self, String> {
        let s: Settings = toml::from_str(text).map_err(|e| e.to_string())?;
        s.check()?;
        Ok(s)
    }

    /// Every bound positive and sane.
    pub fn check(&self) -> Result<(), String> {
        if !(1..=100_000).contains(&self.max_devices) {
            return Err(format!(
                "max_devices {} must be 1..=100000",
                self.max_devices
            ));
        }
        if !(10..=1_000_000).contains(&self.points) {
            return Err(format!("points {} must be 10..=1000000", self.points));
        }
        if !(self.forget_after_s.is_finite() && self.forget_after_s >= 0.0) {
            return Err(format!(
                "forget_after_s {} must be >= 0",
                self.forget_after_s
            ));
        }
        for (name, v) in [
            ("status_period_ms", self.status_period_ms),
            ("config_period_ms", self.config_period_ms),
            ("query_timeout_ms", self.query_timeout_ms),
        ] {
            if !(50..=600_000).contains(&v) {
                return Err(format!("{name} {v} must be 50..=600000"));
            }
        }
        if let Some(l) = &self.login {
            l.check().map_err(|e| format!("[login]: {e}"))?;
        }
        Ok(())
    }

    /// The fleet view's bounds.
    pub fn limits(&self) -> ViewBounds {
        ViewBounds {
            max_devices: self.max_devices,
            points: self.points,
            forget_after: self.forget_after_s,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_and_partial_files() {
        assert_eq!(Settings::parse("").unwrap(), Settings::default());
        let s = Settings::parse("points = 500\nallowed_hosts = [\"c.lan:8080\"]").unwrap();
        assert_eq!((s.points, s.max_devices), (500, 256));
        assert!(Settings::parse("pionts = 500").is_err(), "unknown field");
        assert!(Settings::parse("points = 0").is_err());
        assert!(Settings::parse("status_period_ms = 1").is_err());
    }
}

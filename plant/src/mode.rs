//! Who drives the plant in a period. The agent's rules (`plant_agent::safety`) decide it;
//! the run's record keeps it per period and the progress board shows it, so it lives here
//! with them.

use serde::{Deserialize, Serialize};

/// Who drives the plant.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LoopMode {
    /// Applying the remote controller's commands.
    Remote,
    /// A command is missing: the last one applied is held, or its horizon played.
    Holding,
    /// The fallback engaged: the local controller drives the plant.
    Local,
    /// The fallback engaged (or the local controller could not run): zero inputs.
    SafeStop,
}

impl LoopMode {
    /// Whether this is a fallback mode (the agent, not the remote controller, decides the
    /// inputs).
    pub fn is_fallback(self) -> bool {
        matches!(self, LoopMode::Local | LoopMode::SafeStop)
    }

    /// The name used in records and logs (the same as its serde name).
    pub fn as_str(self) -> &'static str {
        match self {
            LoopMode::Remote => "remote",
            LoopMode::Holding => "holding",
            LoopMode::Local => "local",
            LoopMode::SafeStop => "safe_stop",
        }
    }
}

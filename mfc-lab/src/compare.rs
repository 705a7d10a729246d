//! Every controller on every shipped scenario: the comparison table.

use std::fmt::Write as _;

use serde::{Deserialize, Serialize};

use plant::scenario::{ControllerSet, Scenario};

use crate::offline::{simulate, OfflineSummary, RunError};

/// The comparison: one summary per (scenario, controller).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Comparison {
    /// Scenario names, in order.
    pub scenarios: Vec<String>,
    /// Controller names, in order.
    pub controllers: Vec<String>,
    /// Summaries, scenario-major.
    pub runs: Vec<OfflineSummary>,
}

/// Run every controller on every scenario; `progress` is called after each run.
pub fn compare(
    scenarios: &[Scenario],
    controllers: &[ControllerSet],
    mut progress: impl FnMut(&str, &str),
) -> Result<Comparison, RunError> {
    let mut runs = Vec::new();
    for s in scenarios {
        for c in controllers {
            progress(&s.name, &c.name);
            runs.push(simulate(s, c, false)?.summary);
        }
    }
    Ok(Comparison {
        scenarios: scenarios.iter().map(|s| s.name.clone()).collect(),
        controllers: controllers.iter().map(|c| c.name.clone()).collect(),
        runs,
    })
}

impl Comparison {
    /// The table in Markdown: RMS and max |error| per channel, and the saturated fraction.
    pub fn markdown(&self) -> String {
        let mut out = String::new();
        let channels: Vec<&str> = self
            .runs
            .first()
            .map(|r| r.channels.iter().map(|c| c.name.as_str()).collect())
            .unwrap_or_default();
        let _ = write!(out, "| scenario | controller |");
        for c in &channels {
            let _ = write!(out, " {c} RMS | {c} max |");
        }
        let _ = writeln!(out, " saturated | chatter (V/sample) | limit hits |");
        let _ = write!(out, "|---|---|");
        for _ in &channels {
            let _ = write!(out, "---:|---:|");
        }
        let _ = writeln!(out, "---:|---:|---:|");
        for r in &self.runs {
            let _ = write!(out, "| {} | {} |", r.scenario, r.controller);
            for c in &r.channels {
                let _ = write!(out, " {:.3e} | {:.3e} |", c.rms, c.max_abs);
            }
            let sat = r
                .channels
                .iter()
                .map(|c| format!("{:.0}%", 100.0 * c.saturated_fraction))
                .collect::<Vec<_>>()
                .join(" / ");
            let tv = r
                .channels
                .iter()
                .map(|c| format!("{:.2}", c.control_variation))
                .collect::<Vec<_>>()
                .join(" / ");
            let _ = writeln!(out, " {sat} | {tv} | {} |", r.limit_hits);
        }
        out
    }

    /// Mass sensitivity: per controller and channel, RMS of scenario 3 over scenario 1 and of
    /// scenario 4 over scenario 2 (the shipped order: 3 and 4 are 1 and 2 with the added
    /// mass). Empty unless the shipped scenarios were run (the first four, in order).
    pub fn mass_markdown(&self) -> String {
        let mut out = String::new();
        if self.scenarios.len() < 4
            || !self.scenarios[..4]
                .iter()
                .enumerate()
                .all(|(i, s)| s.starts_with(&format!("scenario-{}", i + 1)))
        {
            return out;
        }
        let channels: Vec<String> = self.runs[0]
            .channels
            .iter()
            .map(|c| c.name.clone())
            .collect();
        let _ = write!(out, "| controller |");
        for c in &channels {
            let _ = write!(out, " {c}: 3 / 1 | {c}: 4 / 2 |");
        }
        let _ = writeln!(out);
        let _ = writeln!(out, "|---|{}", "---:|".repeat(2 * channels.len()));
        for c in &self.controllers {
            let _ = write!(out, "| {c} |");
            for ch in 0..channels.len() {
                for (mass, nominal) in [(2, 0), (3, 1)] {
                    let ratio = self
                        .rms(&self.scenarios[mass], c, ch)
                        .zip(self.rms(&self.scenarios[nominal], c, ch))
                        .map(|(a, b)| a / b);
                    let _ = match ratio {
                        Some(r) => write!(out, " {r:.2} |"),
                        None => write!(out, " - |"),
                    };
                }
            }
            let _ = writeln!(out);
        }
        out
    }

    /// RMS of channel `ch` for a controller on a scenario.
    pub fn rms(&self, scenario: &str, controller: &str, ch: usize) -> Option<f64> {
        self.runs
            .iter()
            .find(|r| r.scenario == scenario && r.controller == controller)
            .and_then(|r| r.channels.get(ch))
            .map(|c| c.rms)
    }
}

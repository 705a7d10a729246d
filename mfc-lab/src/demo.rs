//! The demo: a controller service and N plants, each in its own Zenoh session on loopback
//! (peers, no router, no multicast scouting), running a scenario in real time.

use std::path::PathBuf;

use plant_agent::agent::AgentReport;
use plant_agent::record::write_run;
use plant_agent::safety::SafetyConfig;
use plant_agent::scenario::{ControllerSet, PlantSource, Scenario};

use crate::harness::{run_fleet, service_config, PlantSpec};

/// Options of a demo run.
#[derive(Debug, Clone)]
pub struct DemoOptions {
    /// Number of plants.
    pub plants: usize,
    /// Acceptance, hold and fallback settings of every agent.
    pub safety: SafetyConfig,
    /// Where to write each plant's record (None: nowhere).
    pub out: Option<PathBuf>,
}

/// The device ids of a demo: `aero-1..` for the AERO, `plant-1..` for a driver plant.
pub fn device_ids(scenario: &Scenario, plants: usize) -> Vec<String> {
    let prefix = match scenario.plant {
        PlantSource::Aero(_) => "aero",
        PlantSource::Driver(_) => "plant",
    };
    (1..=plants).map(|i| format!("{prefix}-{i}")).collect()
}

/// Run the demo; returns one report per plant, and writes each plant's record under
/// `out/{id}/` if asked.
pub async fn demo(
    scenario: &Scenario,
    controller: &ControllerSet,
    options: &DemoOptions,
) -> anyhow::Result<Vec<AgentReport>> {
    let ids = device_ids(scenario, options.plants);
    let plants = ids
        .iter()
        .enumerate()
        .map(|(i, id)| {
            let mut p = PlantSpec::new(scenario, controller, id);
            p.loop_config.safety = options.safety;
            p.seed = scenario.seed.wrapping_add(i as u64);
            p
        })
        .collect();
    let runs = run_fleet(plants, service_config(scenario, controller, &ids)).await?;
    let mut reports = Vec::new();
    for run in runs {
        if let Some(dir) = &options.out {
            let title = format!("{} — {} over Zenoh", scenario.name, run.report.device_id);
            write_run(
                &dir.join(&run.report.device_id),
                &title,
                &run.recording,
                &run.report,
            )?;
        }
        reports.push(run.report);
    }
    Ok(reports)
}

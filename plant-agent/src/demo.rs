//! The demo: a controller service and N simulated AEROs, each in its own Zenoh session on
//! loopback (peers, no router, no multicast scouting), running a scenario in real time.

use std::path::Path;

use controller_service::config::{ChannelSpec, DeviceSpec, ServiceConfig};
use controller_service::{service, Registry};
use transport::ZenohArgs;

use crate::agent::{run_agent, AgentConfig, AgentReport, Fallback, Row};
use crate::offline::Trace;
use crate::plant::SimPlant;
use crate::scenario::{ControllerSet, Scenario};

/// Default oldest command worth applying, in periods (100 ms at 10 ms).
pub const DEFAULT_MAX_AGE: u32 = 10;

/// Options of a demo run.
#[derive(Debug, Clone)]
pub struct DemoOptions {
    /// Number of simulated plants.
    pub plants: usize,
    /// Periods to hold before falling back.
    pub hold_periods: u32,
    /// Fallback.
    pub fallback: Fallback,
    /// Where to write per-plant CSV and plots (None: nowhere).
    pub out: Option<std::path::PathBuf>,
}

/// The service configuration that serves `ids` with `controller` on `scenario`.
pub fn service_config(
    scenario: &Scenario,
    controller: &ControllerSet,
    ids: &[String],
) -> ServiceConfig {
    ServiceConfig {
        controller_id: "controller-1".into(),
        devices: ids
            .iter()
            .map(|id| DeviceSpec {
                id: id.clone(),
                channels: scenario
                    .channels
                    .iter()
                    .zip(&controller.channels)
                    .map(|(c, law)| ChannelSpec {
                        law: *law,
                        output: c.output,
                        reference: c.reference.clone(),
                    })
                    .collect(),
            })
            .collect(),
        templates: Vec::new(),
        standby: None,
        snapshots: None,
    }
}

/// The agent configuration of plant `id` on `scenario` with `controller` as its local copy.
pub fn agent_config(
    scenario: &Scenario,
    controller: &ControllerSet,
    id: &str,
    hold_periods: u32,
    fallback: Fallback,
    record: Option<std::path::PathBuf>,
) -> AgentConfig {
    AgentConfig {
        device_id: id.into(),
        period: scenario.period,
        steps: scenario.steps(),
        max_age: DEFAULT_MAX_AGE,
        hold_periods,
        fallback,
        channels: scenario.channel_configs(controller),
        reference: scenario
            .channels
            .iter()
            .map(|c| c.reference.clone())
            .collect(),
        names: scenario.channels.iter().map(|c| c.name.clone()).collect(),
        max_voltage: scenario.plant.max_voltage,
        record,
    }
}

/// Run the demo; returns one report per plant.
pub async fn demo(
    scenario: &Scenario,
    controller: &ControllerSet,
    options: &DemoOptions,
) -> anyhow::Result<Vec<AgentReport>> {
    let port = transport::free_local_port()?;
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let ids: Vec<String> = (1..=options.plants).map(|i| format!("aero-{i}")).collect();
    let registry = Registry::new(service_config(scenario, controller, &ids))?;
    let service_session = ZenohArgs::loopback(Some(endpoint.clone()), vec![])
        .open()
        .await?;
    let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
    let service = tokio::spawn(service::run(service_session, registry, async {
        let _ = stop_rx.await;
    }));

    let mut tasks = Vec::new();
    for (i, id) in ids.iter().enumerate() {
        let session = ZenohArgs::loopback(None, vec![endpoint.clone()])
            .open()
            .await?;
        let record = options.out.as_ref().map(|d| d.join(id).join("run.csv"));
        let config = agent_config(
            scenario,
            controller,
            id,
            options.hold_periods,
            options.fallback,
            record,
        );
        let params = scenario.plant.clone();
        let seed = scenario.seed.wrapping_add(i as u64);
        tasks.push(tokio::spawn(async move {
            let mut plant = SimPlant::new(params, seed)?;
            let out = run_agent(&session, &mut plant, &config, rand_id(seed)).await;
            let _ = session.close().await;
            anyhow::Ok(out?)
        }));
    }
    let mut reports = Vec::new();
    for (task, id) in tasks.into_iter().zip(&ids) {
        let (report, rows) = task.await??;
        if let Some(dir) = &options.out {
            plot_rows(&dir.join(id), scenario, &report, &rows)?;
        }
        reports.push(report);
    }
    let _ = stop_tx.send(());
    service.await??;
    Ok(reports)
}

/// A run id that differs between runs (and between plants).
pub fn rand_id(salt: u64) -> u64 {
    protocol::unix_ns() ^ salt.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ u64::from(std::process::id())
}

/// Write the plots of a networked run.
pub fn plot_rows(
    dir: &Path,
    scenario: &Scenario,
    report: &AgentReport,
    rows: &[Row],
) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir)?;
    let t: Vec<f64> = rows.iter().map(|r| r.t).collect();
    for (i, c) in scenario.channels.iter().enumerate() {
        let trace = Trace {
            y_ref: rows.iter().map(|r| r.y_ref[i]).collect(),
            y: rows.iter().map(|r| r.y[i]).collect(),
            u: Vec::new(),
            v: rows.iter().map(|r| r.v[i]).collect(),
            f_est: Vec::new(),
        };
        let title = format!(
            "{} — {} over Zenoh — {}",
            scenario.name, report.device_id, c.name
        );
        crate::plot::channel(dir, &c.name, &c.unit, &title, &t, &trace)?;
    }
    std::fs::write(
        dir.join("summary.json"),
        serde_json::to_string_pretty(report)? + "\n",
    )?;
    Ok(())
}

//! The demo: a controller service and N plants, each in its own Zenoh session on loopback
//! (peers, no router, no multicast scouting), running a scenario in real time.

use std::path::PathBuf;

use plant::progress::ProgressBoard;
use plant::record::write_run;
use plant::scenario::{ControllerSet, PlantSource, Scenario};
use plant_agent::agent::AgentReport;
use plant_agent::observe::LoopObservers;
use plant_agent::safety::SafetyConfig;
use telemetry::{RecordSpec, Recording};

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
    /// Record to MCAP in this directory: `service.mcap` (the controller's side, which
    /// `mfc-lab replay` re-runs) and `plants.mcap` (the plants' side). None: no recording.
    pub record: Option<PathBuf>,
    /// Serve the service's Prometheus metrics on this address.
    pub metrics: Option<String>,
    /// Show each plant's time, RMS so far, round trip and mode on stderr while it runs.
    pub progress: bool,
}

/// Print `board` to stderr every second until `done` resolves, then once more: in place on
/// a terminal, as blocks of lines every five seconds otherwise (a log, a CI run).
pub async fn show_progress(
    board: std::sync::Arc<ProgressBoard>,
    done: impl std::future::Future<Output = ()>,
) {
    use std::io::{IsTerminal, Write};
    let tty = std::io::stderr().is_terminal();
    let every = std::time::Duration::from_secs(if tty { 1 } else { 5 });
    let mut tick = tokio::time::interval(every);
    tick.tick().await;
    tokio::pin!(done);
    let mut shown = 0usize;
    loop {
        let last = tokio::select! {
            _ = tick.tick() => false,
            () = &mut done => true,
        };
        let text = board.render();
        let mut err = std::io::stderr().lock();
        if tty && shown > 0 {
            // Back over the last board, and clear it.
            let _ = write!(err, "\x1b[{shown}A\x1b[J");
        }
        if !tty {
            let _ = writeln!(err, "--");
        }
        let _ = write!(err, "{text}");
        let _ = err.flush();
        shown = text.lines().count();
        if last {
            break;
        }
    }
}

/// The device ids of a demo: `aero-1..` for the AERO, `plant-1..` for a driver plant.
pub fn device_ids(scenario: &Scenario, plants: usize) -> Vec<String> {
    let prefix = match scenario.plant {
        PlantSource::Aero(_) => "aero",
        PlantSource::Driver(_) | PlantSource::Modbus(_) | PlantSource::OpcUa(_) => "plant",
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
    let mut config = service_config(scenario, controller, &ids);
    let mut observers = LoopObservers::default();
    if let Some(dir) = &options.record {
        std::fs::create_dir_all(dir)?;
        // A demo's output directory holds its last run: replaced, not accumulated.
        let spec = |name: &str| RecordSpec {
            keep_previous: false,
            ..RecordSpec::at(dir.join(name))
        };
        config.record = Some(spec("service.mcap"));
        observers.recording = Some(Recording::create(&spec("plants.mcap"), "plant-agent")?);
    }
    if let Some(addr) = &options.metrics {
        config.metrics = Some(telemetry::MetricsSpec {
            listen: addr.clone(),
            // A demo's few plants: each with series of its own.
            per_device: true,
            ..telemetry::MetricsSpec::default()
        });
    }
    let board = std::sync::Arc::new(ProgressBoard::new());
    if options.progress {
        observers.progress = Some(board.clone());
    }
    let plants = ids
        .iter()
        .enumerate()
        .map(|(i, id)| {
            let mut p = PlantSpec::new(scenario, controller, id);
            p.loop_config.safety = options.safety;
            p.loop_config.observers = observers.clone();
            p.seed = scenario.seed.wrapping_add(i as u64);
            p
        })
        .collect();
    let (done_tx, done_rx) = tokio::sync::oneshot::channel::<()>();
    let shown = options.progress.then(|| {
        tokio::spawn(show_progress(board.clone(), async {
            let _ = done_rx.await;
        }))
    });
    let runs = run_fleet(plants, config).await;
    let _ = done_tx.send(());
    if let Some(s) = shown {
        let _ = s.await;
    }
    if let Some(r) = observers.recording.take() {
        tokio::task::spawn_blocking(move || r.finish()).await??;
    }
    let runs = runs?;
    let mut reports = Vec::new();
    for run in runs {
        if let Some(dir) = &options.out {
            let title = format!("{} — {} over Zenoh", scenario.name, run.report.device_id);
            write_run(
                &dir.join(&run.report.device_id),
                &title,
                &run.record,
                &run.report,
            )?;
        }
        reports.push(run.report);
    }
    Ok(reports)
}

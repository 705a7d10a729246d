//! What a running loop shows: live progress for a terminal (the board of
//! [`plant::progress`]), Prometheus metrics, and an MCAP recording of the plant's side
//! (samples sent, commands received, mode changes).
//!
//! The loop hands each period's figures over once, at the end of the period; everything
//! here is either a store into shared state (progress), atomic handles (metrics) or a
//! bounded queue (recording), so observing never blocks a period.

use std::sync::Arc;

use metrics::{Counter, Gauge, Histogram, Unit};
use plant::progress::ProgressBoard;
use telemetry::{Metrics, Recording};

use crate::safety::{LoopMode, SupervisorCounters};

/// Everything a loop may feed; all optional (the default feeds nothing).
#[derive(Clone, Default)]
pub struct LoopObservers {
    /// Live progress, shared by the plants of one run.
    pub progress: Option<Arc<ProgressBoard>>,
    /// Metrics of this process's plants.
    pub metrics: Option<Arc<AgentMetrics>>,
    /// The recording of this process's plants.
    pub recording: Option<Recording>,
}

impl std::fmt::Debug for LoopObservers {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LoopObservers")
            .field("progress", &self.progress.is_some())
            .field("metrics", &self.metrics.is_some())
            .field("recording", &self.recording)
            .finish()
    }
}

/// The metrics of an agent process (one or many plants).
pub struct AgentMetrics {
    metrics: Metrics,
}

impl AgentMetrics {
    /// Metrics into `metrics`.
    pub fn new(metrics: Metrics) -> Self {
        for (name, help, _) in COUNTERS {
            metrics.describe(name, None, help);
        }
        metrics.describe(
            "mfc_agent_rtt_seconds",
            Some(Unit::Seconds),
            "Round trips: sample sent to its command received.",
        );
        metrics.describe(
            "mfc_agent_mode",
            None,
            "The loop's mode: 0 remote, 1 holding, 2 local fallback, 3 safe stop.",
        );
        metrics.describe(
            "mfc_agent_remote",
            None,
            "1 while the plant applies the controller's commands.",
        );
        metrics.describe(
            "mfc_agent_f_estimate",
            None,
            "The last F estimate received, per channel.",
        );
        metrics.describe(
            "mfc_agent_command_queue_depth",
            None,
            "Commands waiting to be read at the end of a period.",
        );
        metrics.describe(
            "mfc_agent_overruns_total",
            None,
            "Periods started more than half a period late.",
        );
        Self { metrics }
    }

    /// The recorder.
    pub fn metrics(&self) -> &Metrics {
        &self.metrics
    }

    /// A plant's handles, registered once.
    pub fn device(&self, device: &str, channels: usize) -> DeviceMetrics {
        let l = [("device", device)];
        DeviceMetrics {
            counters: COUNTERS
                .iter()
                .map(|(name, _, _)| self.metrics.counter(name, &l))
                .collect(),
            rtt: self.metrics.histogram("mfc_agent_rtt_seconds", &l),
            mode: self.metrics.gauge("mfc_agent_mode", &l),
            remote: self.metrics.gauge("mfc_agent_remote", &l),
            queue: self.metrics.gauge("mfc_agent_command_queue_depth", &l),
            overruns: self.metrics.counter("mfc_agent_overruns_total", &l),
            f_est: (0..channels)
                .map(|i| {
                    let ch = i.to_string();
                    self.metrics.gauge(
                        "mfc_agent_f_estimate",
                        &[("device", device), ("channel", ch.as_str())],
                    )
                })
                .collect(),
        }
    }
}

type Field = fn(&SupervisorCounters) -> u64;

/// The supervisor's counters, exported as they are.
const COUNTERS: &[(&str, &str, Field)] = &[
    ("mfc_agent_periods_total", "Periods ended.", |c| c.periods),
    ("mfc_agent_commands_total", "Commands applied.", |c| {
        c.commands
    }),
    (
        "mfc_agent_late_total",
        "Commands applied after their own period.",
        |c| c.late,
    ),
    (
        "mfc_agent_missing_total",
        "Periods that ended without their command.",
        |c| c.missing,
    ),
    (
        "mfc_agent_too_old_total",
        "Commands dropped as too old (stale).",
        |c| c.too_old,
    ),
    (
        "mfc_agent_superseded_total",
        "Commands dropped because a newer one was applied.",
        |c| c.superseded,
    ),
    (
        "mfc_agent_duplicates_total",
        "Answers to a sample already answered.",
        |c| c.duplicates,
    ),
    ("mfc_agent_warming_up_total", "Warming-up answers.", |c| {
        c.warming_up
    }),
    (
        "mfc_agent_rejected_total",
        "Samples the controller refused.",
        |c| c.rejected,
    ),
    ("mfc_agent_malformed_total", "Malformed commands.", |c| {
        c.malformed
    }),
    (
        "mfc_agent_future_total",
        "Commands for a sample not sent yet.",
        |c| c.future,
    ),
    (
        "mfc_agent_fallbacks_total",
        "Times the local fallback engaged.",
        |c| c.fallbacks,
    ),
    (
        "mfc_agent_holding_periods_total",
        "Periods holding a command.",
        |c| c.holding_periods,
    ),
    (
        "mfc_agent_local_periods_total",
        "Periods on the local fallback.",
        |c| c.local_periods,
    ),
    (
        "mfc_agent_safe_stop_periods_total",
        "Periods in safe stop.",
        |c| c.safe_stop_periods,
    ),
    (
        "mfc_agent_horizon_periods_total",
        "Periods driven by a horizon element.",
        |c| c.horizon_periods,
    ),
];

/// One plant's metric handles.
pub struct DeviceMetrics {
    counters: Vec<Counter>,
    rtt: Histogram,
    mode: Gauge,
    remote: Gauge,
    queue: Gauge,
    overruns: Counter,
    f_est: Vec<Gauge>,
}

/// What one period hands to the metrics.
pub struct PeriodFigures<'a> {
    /// The supervisor's counters after the period.
    pub counters: &'a SupervisorCounters,
    /// The period's round trip (µs; 0: none).
    pub rtt_us: u32,
    /// The mode at the end of the period.
    pub mode: LoopMode,
    /// The last F estimates received, if a command came.
    pub f_est: Option<&'a [f64]>,
    /// Commands still queued.
    pub queue: usize,
    /// Overruns so far.
    pub overruns: u64,
}

/// The number of a mode in `mfc_agent_mode`.
pub fn mode_number(m: LoopMode) -> f64 {
    match m {
        LoopMode::Remote => 0.0,
        LoopMode::Holding => 1.0,
        LoopMode::Local => 2.0,
        LoopMode::SafeStop => 3.0,
    }
}

impl DeviceMetrics {
    /// Store one period's figures.
    pub fn period(&self, f: &PeriodFigures<'_>) {
        for (c, (_, _, get)) in self.counters.iter().zip(COUNTERS) {
            c.absolute(get(f.counters));
        }
        if f.rtt_us > 0 {
            self.rtt.record(f64::from(f.rtt_us) * 1e-6);
        }
        self.mode.set(mode_number(f.mode));
        self.remote
            .set(if f.mode == LoopMode::Remote { 1.0 } else { 0.0 });
        self.queue.set(f.queue as f64);
        self.overruns.absolute(f.overruns);
        if let Some(fe) = f.f_est {
            for (g, v) in self.f_est.iter().zip(fe) {
                g.set(*v);
            }
        }
    }
}

/// The observers a process started, and what must end with it.
pub struct Started {
    /// What each loop feeds.
    pub observers: LoopObservers,
    endpoint: Option<(
        tokio::sync::oneshot::Sender<()>,
        tokio::task::JoinHandle<()>,
    )>,
}

/// Why observing could not start.
#[derive(Debug, thiserror::Error)]
pub enum ObserveError {
    /// The metrics endpoint did not start.
    #[error(transparent)]
    Metrics(#[from] telemetry::MetricsError),
    /// The recording did not start.
    #[error(transparent)]
    Record(#[from] telemetry::RecordError),
}

/// Start the metrics endpoint and the recording a file asks for (either may be absent).
pub async fn start(
    metrics: Option<&telemetry::MetricsSpec>,
    record: Option<&telemetry::RecordSpec>,
) -> Result<Started, ObserveError> {
    let recording = record
        .map(|r| Recording::create(r, "plant-agent"))
        .transpose()?;
    let mut observers = LoopObservers {
        recording,
        ..Default::default()
    };
    let mut endpoint = None;
    if let Some(spec) = metrics {
        let am = Arc::new(AgentMetrics::new(Metrics::new()));
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        // The loops store their figures every period: nothing to refresh at a scrape.
        let refresh: telemetry::prom::Refresh = Arc::new(|| Box::pin(async { String::new() }));
        let (_, serve) = telemetry::serve_metrics(spec, am.metrics().clone(), refresh, async {
            let _ = rx.await;
        })
        .await?;
        endpoint = Some((tx, tokio::spawn(serve)));
        observers.metrics = Some(am);
    }
    Ok(Started {
        observers,
        endpoint,
    })
}

impl Started {
    /// Stop the endpoint and finish the recording (its summary and footer written).
    pub async fn finish(self) {
        if let Some((tx, task)) = self.endpoint {
            let _ = tx.send(());
            let _ = task.await;
        }
        if let Some(r) = &self.observers.recording {
            let r = r.clone();
            let path = r.path().display().to_string();
            match tokio::task::spawn_blocking(move || r.finish()).await {
                Ok(Ok(s)) => {
                    tracing::info!(%path, messages = s.messages, dropped = s.dropped, "recording finished")
                }
                Ok(Err(e)) => tracing::warn!(%path, "recording: {e}"),
                Err(e) => tracing::warn!(%path, "recording: {e}"),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_period_moves_the_counters_to_the_supervisors() {
        let m = AgentMetrics::new(Metrics::new());
        let d = m.device("aero-1", 2);
        let c = SupervisorCounters {
            periods: 10,
            commands: 9,
            missing: 1,
            ..Default::default()
        };
        d.period(&PeriodFigures {
            counters: &c,
            rtt_us: 2000,
            mode: LoopMode::Holding,
            f_est: Some(&[1.0, -4.0]),
            queue: 0,
            overruns: 0,
        });
        let t = m.metrics().render();
        for line in [
            "mfc_agent_periods_total{device=\"aero-1\"} 10",
            "mfc_agent_commands_total{device=\"aero-1\"} 9",
            "mfc_agent_missing_total{device=\"aero-1\"} 1",
            "mfc_agent_mode{device=\"aero-1\"} 1",
            "mfc_agent_remote{device=\"aero-1\"} 0",
            "mfc_agent_f_estimate{device=\"aero-1\",channel=\"1\"} -4",
            "mfc_agent_rtt_seconds_count{device=\"aero-1\"} 1",
        ] {
            assert!(t.contains(line), "missing {line} in\n{t}");
        }
    }
}

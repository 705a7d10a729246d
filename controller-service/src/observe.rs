//! What the service shows of itself to operators: Prometheus metrics and MCAP recordings.
//!
//! The registry already counts everything that happens to a device (its status). The
//! metrics copy those counters at each scrape, from every worker, through a request each
//! worker answers between two samples, so that a scrape and a status query taken at the
//! same moment agree and nothing is counted twice. What no status holds (each round trip,
//! the CPU each sample took) is recorded as it happens, into histograms whose handles a
//! worker registers once per device.
//!
//! Recordings are written by `telemetry`'s thread; here is only what to record and when.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use metrics::{Histogram, Unit};
use protocol::pb;
use telemetry::{Metrics, Recording};
use tokio::sync::{mpsc, oneshot};

/// What a worker reports at a scrape.
#[derive(Debug, Clone, Default)]
pub struct Scraped {
    /// Its status, exactly as a `ServiceStatus` query would get it.
    pub status: pb::ServiceStatus,
    /// Devices with a sample waiting in its inbox.
    pub inbox: usize,
    /// Gateway batches waiting.
    pub gateways: usize,
    /// Requests and internal messages waiting in its queue.
    pub queue: usize,
}

/// How a worker is asked for a [`Scraped`].
pub type ScrapeRequest = oneshot::Sender<Scraped>;

/// The observers a worker feeds; both optional.
#[derive(Clone, Default)]
pub struct Observers {
    /// The metrics of this process.
    pub metrics: Option<Arc<ServiceMetrics>>,
    /// The recording of this process.
    pub recording: Option<Recording>,
    /// The audit trail's file of this process (absent: entries in memory only).
    pub audit: Option<crate::service::AuditTrail>,
}

/// A device's histograms, registered at its first sample.
#[derive(Clone)]
pub struct DeviceHistograms {
    /// The plant's round trips, as it measured them (`Sample.last_rtt_us`).
    pub rtt: Histogram,
    /// The thread CPU time the service spent on one of its samples.
    pub cpu: Histogram,
}

/// The metrics of a service process (all its workers).
pub struct ServiceMetrics {
    metrics: Metrics,
    per_device: bool,
    workers: Mutex<Vec<mpsc::Sender<ScrapeRequest>>>,
    recording: Option<Recording>,
}

/// Counters of a device's status, by metric name (`mfc_device_{name}_total`).
type Field<T> = fn(&T) -> u64;

const DEVICE_COUNTERS: &[(&str, &str, Field<pb::DeviceStatus>)] = &[
    ("mfc_device_samples_total", "Samples received.", |d| {
        d.samples
    }),
    (
        "mfc_device_commands_total",
        "Commands computed (CONTROL and WARMING_UP); those held back because another controller held the plant's lease are in mfc_device_lease_fenced_total too.",
        |d| d.commands,
    ),
    (
        "mfc_device_lost_total",
        "Sequence numbers never received.",
        |d| d.lost,
    ),
    (
        "mfc_device_recovered_total",
        "Lost samples whose data came later in a resent copy.",
        |d| d.recovered,
    ),
    (
        "mfc_device_duplicates_total",
        "Duplicates of the last sample.",
        |d| d.duplicates,
    ),
    (
        "mfc_device_stale_total",
        "Samples older than one already answered (late).",
        |d| d.stale,
    ),
    (
        "mfc_device_rejected_total",
        "Samples answered REJECTED.",
        |d| d.rejected,
    ),
    (
        "mfc_device_superseded_total",
        "Samples replaced by a newer one before they were served.",
        |d| d.superseded,
    ),
    (
        "mfc_device_off_remote_total",
        "Samples sent while the plant held, ran its fallback or was stopped.",
        |d| d.samples_off_remote,
    ),
    (
        "mfc_device_clamped_total",
        "Commands the final envelope check clipped.",
        |d| d.clamped,
    ),
    (
        "mfc_device_references_refused_total",
        "Reference updates refused.",
        |d| d.references_refused,
    ),
    ("mfc_device_restarts_total", "Plant runs started.", |d| {
        d.restarts
    }),
    (
        "mfc_device_envelope_changes_total",
        "Envelope changes since the service started.",
        |d| d.envelope_changes,
    ),
    (
        "mfc_device_lease_fenced_total",
        "Answers held back because another controller held the plant's lease.",
        |d| d.lease_fenced,
    ),
    (
        "mfc_device_lease_claims_total",
        "Claims of the plant's vacant lease sent.",
        |d| d.lease_claims,
    ),
    (
        "mfc_device_lease_yields_total",
        "Leases given up to the member the fleet prefers.",
        |d| d.lease_yields,
    ),
    (
        "mfc_device_lease_refused_total",
        "Commands the plant refused in its run (not the holder's, a stale epoch, another run), as it reports them.",
        |d| d.lease_refused,
    ),
];

/// Service-wide counters of a worker's status.
const SERVICE_COUNTERS: &[(&str, &str, Field<pb::ServiceStatus>)] = &[
    (
        "mfc_service_unknown_samples_total",
        "Samples of devices nobody serves here.",
        |s| s.unknown_samples,
    ),
    (
        "mfc_service_undecodable_total",
        "Messages that did not decode.",
        |s| s.undecodable,
    ),
    (
        "mfc_service_oversized_total",
        "Messages over the size limit, dropped unread.",
        |s| s.oversized,
    ),
    (
        "mfc_service_bad_key_total",
        "Messages on a key that names no device.",
        |s| s.bad_key,
    ),
    (
        "mfc_service_superseded_total",
        "Samples replaced by a newer one of their device.",
        |s| s.superseded,
    ),
    (
        "mfc_service_queue_full_total",
        "Messages dropped on a full queue.",
        |s| s.queue_full,
    ),
    (
        "mfc_service_rejected_total",
        "Samples answered REJECTED.",
        |s| s.rejected,
    ),
    (
        "mfc_service_device_table_full_total",
        "Template devices refused at max_devices.",
        |s| s.device_table_full,
    ),
    (
        "mfc_service_requests_refused_total",
        "Operator requests refused.",
        |s| s.requests_refused,
    ),
    (
        "mfc_service_superseded_batches_total",
        "Gateway batches replaced by a newer one.",
        |s| s.superseded_batches,
    ),
    (
        "mfc_service_bad_device_ids_total",
        "Samples in batches with an invalid device id.",
        |s| s.bad_device_ids,
    ),
    (
        "mfc_service_forged_total",
        "Samples and batches refused for their proof of origin (no MAC, or another key's).",
        |s| s.forged,
    ),
    (
        "mfc_service_changes_accepted_total",
        "Operators' changes accepted, each an audit entry.",
        |s| s.changes_accepted,
    ),
    (
        "mfc_service_changes_refused_total",
        "Operators' changes refused (access, bounds, any check), each an audit entry.",
        |s| s.changes_refused,
    ),
    (
        "mfc_service_audit_unwritten_total",
        "Refusals whose audit entry found the audit file's queue full (kept in memory only).",
        |s| s.audit_unwritten,
    ),
    (
        "mfc_service_audit_written_total",
        "Audit entries written and fsynced to the process's audit file (each worker of a process reports the same file).",
        |s| s.audit_written,
    ),
    (
        "mfc_service_audit_errors_total",
        "Audit entries the process's audit file could not take (the log says why).",
        |s| s.audit_errors,
    ),
];

const TROUBLE: u32 = pb::SampleFlags::Holding as u32
    | pb::SampleFlags::Fallback as u32
    | pb::SampleFlags::SafeStop as u32;

/// How long a scrape waits for a worker; a worker that does not answer in time (stuck, or
/// stopping) keeps the figures of its last answer.
pub const SCRAPE_TIMEOUT: Duration = Duration::from_secs(2);

impl ServiceMetrics {
    /// Metrics into `metrics`; per device only if `per_device`.
    pub fn new(metrics: Metrics, per_device: bool, recording: Option<Recording>) -> Self {
        for (name, help, _) in DEVICE_COUNTERS {
            metrics.describe(name, None, help);
        }
        for (name, help, _) in SERVICE_COUNTERS {
            metrics.describe(name, None, help);
        }
        metrics.describe(
            "mfc_device_loop_rtt_seconds",
            Some(Unit::Seconds),
            "Round trips as the plant measured them (sample sent to command received).",
        );
        metrics.describe(
            "mfc_device_sample_cpu_seconds",
            Some(Unit::Seconds),
            "Thread CPU time the service spent on one sample (a gateway batch's time shared by its samples).",
        );
        metrics.describe(
            "mfc_device_f_estimate",
            None,
            "The last estimate of F per channel (NaN while the window fills, or for PID).",
        );
        metrics.describe(
            "mfc_device_remote",
            None,
            "1 while the device's plant applies this service's commands; 0 while it holds, runs its fallback or is stopped.",
        );
        metrics.describe(
            "mfc_device_plant_time_seconds",
            None,
            "Plant time of the last sample.",
        );
        metrics.describe("mfc_service_devices", None, "Devices served.");
        metrics.describe(
            "mfc_service_active",
            None,
            "1 if this worker answers (hot standby: the active member).",
        );
        metrics.describe(
            "mfc_service_inbox_depth",
            None,
            "Devices with a sample waiting to be served.",
        );
        metrics.describe(
            "mfc_service_gateway_depth",
            None,
            "Gateway batches waiting to be served.",
        );
        metrics.describe(
            "mfc_service_queue_depth",
            None,
            "Requests and internal messages waiting for the worker.",
        );
        metrics.describe(
            "mfc_service_recording_dropped_total",
            None,
            "Messages the recording dropped because its writer fell behind.",
        );
        Self {
            metrics,
            per_device,
            workers: Mutex::new(Vec::new()),
            recording,
        }
    }

    /// The recorder (for rendering).
    pub fn metrics(&self) -> &Metrics {
        &self.metrics
    }

    /// Register a worker: it answers scrape requests from the returned queue.
    pub fn join(&self) -> mpsc::Receiver<ScrapeRequest> {
        let (tx, rx) = mpsc::channel(4);
        self.workers
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .push(tx);
        rx
    }

    /// A device's histograms (none without per-device series).
    pub fn device(&self, controller: &str, device: &str) -> Option<DeviceHistograms> {
        if !self.per_device {
            return None;
        }
        let labels = [("controller", controller), ("device", device)];
        Some(DeviceHistograms {
            rtt: self
                .metrics
                .histogram("mfc_device_loop_rtt_seconds", &labels),
            cpu: self
                .metrics
                .histogram("mfc_device_sample_cpu_seconds", &labels),
        })
    }

    /// Ask every worker for its status and copy it into the recorder.
    pub async fn refresh(&self) {
        let workers: Vec<_> = self
            .workers
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone();
        let mut scraped = Vec::with_capacity(workers.len());
        for w in workers {
            let (tx, rx) = oneshot::channel();
            if w.send(tx).await.is_err() {
                continue;
            }
            if let Ok(Ok(s)) = tokio::time::timeout(SCRAPE_TIMEOUT, rx).await {
                scraped.push(s);
            }
        }
        self.apply(&scraped);
    }

    /// Copy what the workers reported into the recorder (no I/O: unit-tested).
    pub fn apply(&self, scraped: &[Scraped]) {
        let m = &self.metrics;
        for w in scraped {
            let s = &w.status;
            let c = s.controller_id.as_str();
            let sl = [("controller", c)];
            for (name, _, get) in SERVICE_COUNTERS {
                m.counter(name, &sl).absolute(get(s));
            }
            m.gauge("mfc_service_devices", &sl)
                .set(s.devices.len() as f64);
            m.gauge("mfc_service_active", &sl)
                .set(if s.active { 1.0 } else { 0.0 });
            m.gauge("mfc_service_inbox_depth", &sl).set(w.inbox as f64);
            m.gauge("mfc_service_gateway_depth", &sl)
                .set(w.gateways as f64);
            m.gauge("mfc_service_queue_depth", &sl).set(w.queue as f64);
            if !self.per_device {
                continue;
            }
            for d in &s.devices {
                let dl = [("controller", c), ("device", d.device_id.as_str())];
                for (name, _, get) in DEVICE_COUNTERS {
                    m.counter(name, &dl).absolute(get(d));
                }
                m.gauge("mfc_device_remote", &dl).set(
                    if d.samples > 0 && d.last_flags & TROUBLE == 0 {
                        1.0
                    } else {
                        0.0
                    },
                );
                m.gauge("mfc_device_plant_time_seconds", &dl)
                    .set(d.plant_time);
                for (i, f) in d.f_est.iter().enumerate() {
                    let ch = i.to_string();
                    let fl = [
                        ("controller", c),
                        ("device", d.device_id.as_str()),
                        ("channel", ch.as_str()),
                    ];
                    m.gauge("mfc_device_f_estimate", &fl).set(*f);
                }
            }
        }
        if let Some(r) = &self.recording {
            m.counter("mfc_service_recording_dropped_total", &[])
                .absolute(r.dropped());
        }
    }
}

/// Serve `m` on the endpoint `spec` describes until `stop` resolves; each scrape first
/// asks every worker for its status ([`ServiceMetrics::refresh`]).
pub async fn serve_endpoint(
    spec: &telemetry::MetricsSpec,
    m: Arc<ServiceMetrics>,
    stop: impl std::future::Future<Output = ()> + Send + 'static,
) -> Result<(std::net::SocketAddr, tokio::task::JoinHandle<()>), telemetry::MetricsError> {
    let recorder = m.metrics().clone();
    let refresh: telemetry::prom::Refresh = Arc::new(move || {
        let m = m.clone();
        Box::pin(async move { m.refresh().await })
    });
    let (addr, serve) = telemetry::serve_metrics(spec, recorder, refresh, stop).await?;
    Ok((addr, tokio::spawn(serve)))
}

/// Thread CPU time now (s): what one sample cost, measured around its step. The clock is
/// the thread's own, so time the worker spent descheduled does not count.
pub fn thread_cpu() -> f64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `ts` is a valid, writable timespec; the call only writes it.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    if rc != 0 {
        return 0.0;
    }
    ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9
}

#[cfg(test)]
mod tests {
    use super::*;

    fn status() -> Scraped {
        Scraped {
            status: pb::ServiceStatus {
                controller_id: "c1".into(),
                active: true,
                queue_full: 3,
                devices: vec![pb::DeviceStatus {
                    device_id: "aero-1".into(),
                    samples: 100,
                    commands: 98,
                    lost: 2,
                    stale: 1,
                    f_est: vec![1.5, -2.0],
                    last_flags: pb::SampleFlags::Fallback as u32,
                    ..Default::default()
                }],
                ..Default::default()
            },
            inbox: 1,
            gateways: 0,
            queue: 2,
        }
    }

    #[test]
    fn a_scrape_copies_every_counter_of_the_status() {
        let sm = ServiceMetrics::new(Metrics::new(), true, None);
        sm.apply(&[status()]);
        let t = sm.metrics().render();
        for line in [
            "mfc_device_samples_total{controller=\"c1\",device=\"aero-1\"} 100",
            "mfc_device_commands_total{controller=\"c1\",device=\"aero-1\"} 98",
            "mfc_device_lost_total{controller=\"c1\",device=\"aero-1\"} 2",
            "mfc_device_stale_total{controller=\"c1\",device=\"aero-1\"} 1",
            "mfc_device_remote{controller=\"c1\",device=\"aero-1\"} 0",
            "mfc_device_f_estimate{controller=\"c1\",device=\"aero-1\",channel=\"1\"} -2",
            "mfc_service_queue_full_total{controller=\"c1\"} 3",
            "mfc_service_queue_depth{controller=\"c1\"} 2",
            "mfc_service_active{controller=\"c1\"} 1",
        ] {
            assert!(t.contains(line), "missing {line} in\n{t}");
        }
        // A later scrape moves the counters to the new figures, not by them.
        let mut s = status();
        s.status.devices[0].samples = 150;
        sm.apply(&[s]);
        let t = sm.metrics().render();
        assert!(
            t.contains("mfc_device_samples_total{controller=\"c1\",device=\"aero-1\"} 150"),
            "{t}"
        );
    }

    #[test]
    fn without_per_device_series_only_the_service_is_shown() {
        let sm = ServiceMetrics::new(Metrics::new(), false, None);
        sm.apply(&[status()]);
        let t = sm.metrics().render();
        assert!(!t.contains("aero-1"), "{t}");
        assert!(
            t.contains("mfc_service_devices{controller=\"c1\"} 1"),
            "{t}"
        );
        assert!(sm.device("c1", "aero-1").is_none());
    }

    #[test]
    fn thread_cpu_advances_with_work() {
        let a = thread_cpu();
        let mut x = 0u64;
        for i in 0..2_000_000u64 {
            x = x.wrapping_mul(31).wrapping_add(i);
        }
        std::hint::black_box(x);
        assert!(thread_cpu() > a);
    }
}

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

use std::collections::{BTreeSet, HashMap, HashSet};
use std::fmt::Write as _;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use metrics::{Histogram, Unit};
use protocol::pb;
use telemetry::{FixedHistogram, Metrics, MetricsSpec, Recording};
use tokio::sync::{mpsc, oneshot};

/// What a worker reports at a scrape.
#[derive(Debug, Clone, Default)]
pub struct Scraped {
    /// Its status as a `ServiceStatus` query would get it, with only the devices that
    /// have series of their own in `devices` (every device is in `tally`).
    pub status: pb::ServiceStatus,
    /// Every device's counters, summed.
    pub tally: Tally,
    /// Devices with a sample waiting in its inbox.
    pub inbox: usize,
    /// Gateways with batches waiting.
    pub gateways: usize,
    /// Requests and internal messages waiting in its queue.
    pub queue: usize,
}

/// How a worker is asked for a [`Scraped`].
#[derive(Debug)]
pub struct ScrapeRequest {
    /// The devices whose whole status the scrape wants (those with series of their own).
    pub detail: Arc<BTreeSet<String>>,
    /// Where the answer goes.
    pub reply: oneshot::Sender<Scraped>,
}

/// Every device's counters summed by a worker at a scrape, and the devices that missed
/// samples: what the service-wide series are made of.
#[derive(Debug, Clone, Default)]
pub struct Tally {
    /// Devices counted.
    pub devices: u64,
    /// Per counter of the device status (`mfc_devices_*_total`), the sum.
    pub sums: Vec<u64>,
    /// Devices whose plant applies this service's commands.
    pub remote: u64,
    /// Each device that ever lost a sample or got one late, with how many (lost + stale).
    pub missed: Vec<(String, u64)>,
}

impl Tally {
    /// Count device `id`, whose numbers are `d`.
    pub fn add(&mut self, id: &str, d: &pb::DeviceStatus) {
        self.sums.resize(DEVICE_COUNTERS.len(), 0);
        for (sum, (_, _, _, get)) in self.sums.iter_mut().zip(DEVICE_COUNTERS) {
            *sum += get(d);
        }
        self.devices += 1;
        self.remote += u64::from(remote(d));
        let missed = d.lost + d.stale;
        if missed > 0 {
            self.missed.push((id.to_string(), missed));
        }
    }
}

/// Whether the device's plant applies this service's commands (by its last sample).
fn remote(d: &pb::DeviceStatus) -> bool {
    d.samples > 0 && d.last_flags & TROUBLE == 0
}

/// The observers a worker feeds; both optional.
#[derive(Clone, Default)]
pub struct Observers {
    /// The metrics of this process.
    pub metrics: Option<Arc<ServiceMetrics>>,
    /// The recording of this process.
    pub recording: Option<Recording>,
    /// The audit trail's file of this process (absent: entries in memory only).
    pub audit: Option<crate::trail::AuditTrail>,
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
///
/// By default a bounded set of series whatever the number of devices: the service-wide
/// counters, the sums of every device's counters, two fixed-bucket histograms over every
/// sample, and the `worst` devices by samples missed since the previous scrape. Devices
/// get series of their own only when named, or with `per_device` up to `max_devices`.
pub struct ServiceMetrics {
    metrics: Metrics,
    spec: MetricsSpec,
    controller: String,
    named: HashSet<String>,
    /// Devices with series of their own (the named ones, and with `per_device` the first
    /// up to `max_devices`).
    chosen: Mutex<BTreeSet<String>>,
    workers: Mutex<Vec<mpsc::Sender<ScrapeRequest>>>,
    recording: Option<Recording>,
    rtt: FixedHistogram,
    cpu: FixedHistogram,
    /// Each device's samples missed (lost + stale) at the previous scrape.
    missed: Mutex<HashMap<String, u64>>,
}

fn locked<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// `v` as a Prometheus label value: backslash, double quote and newline escaped.
fn label_value(v: &str) -> String {
    v.replace('\\', "\\\\")
        .replace('"', "\\\"")
        .replace('\n', "\\n")
}

const RTT_HELP: &str =
    "Round trips of every device, as their plants measured them (sample sent to command received).";
const CPU_HELP: &str = "Thread CPU time the service spent on one sample, over every device (a gateway batch's time shared by its samples).";
const WORST_HELP: &str = "Samples lost or late since the previous scrape, for the devices that missed the most (at most metrics.worst of them, changing as the trouble moves).";

/// Counters of a device's status: the name of a device's series, the name of the sum
/// over every device, the help, and where the status holds it.
type Field<T> = fn(&T) -> u64;

const DEVICE_COUNTERS: &[(&str, &str, &str, Field<pb::DeviceStatus>)] = &[
    ("mfc_device_samples_total", "mfc_devices_samples_total", "Samples received.", |d| {
        d.samples
    }),
    ("mfc_device_commands_total", "mfc_devices_commands_total",
        "Commands computed (CONTROL and WARMING_UP); those held back because another controller held the plant's lease are in mfc_device_lease_fenced_total too.",
        |d| d.commands,
    ),
    ("mfc_device_lost_total", "mfc_devices_lost_total",
        "Sequence numbers never received.",
        |d| d.lost,
    ),
    ("mfc_device_recovered_total", "mfc_devices_recovered_total",
        "Lost samples whose data came later in a resent copy.",
        |d| d.recovered,
    ),
    ("mfc_device_duplicates_total", "mfc_devices_duplicates_total",
        "Duplicates of the last sample.",
        |d| d.duplicates,
    ),
    ("mfc_device_stale_total", "mfc_devices_stale_total",
        "Samples older than one already answered (late).",
        |d| d.stale,
    ),
    ("mfc_device_rejected_total", "mfc_devices_rejected_total",
        "Samples answered REJECTED.",
        |d| d.rejected,
    ),
    ("mfc_device_superseded_total", "mfc_devices_superseded_total",
        "Samples replaced by a newer one before they were served.",
        |d| d.superseded,
    ),
    ("mfc_device_off_remote_total", "mfc_devices_off_remote_total",
        "Samples sent while the plant held, ran its fallback or was stopped.",
        |d| d.samples_off_remote,
    ),
    ("mfc_device_clamped_total", "mfc_devices_clamped_total",
        "Commands the final envelope check clipped.",
        |d| d.clamped,
    ),
    ("mfc_device_references_refused_total", "mfc_devices_references_refused_total",
        "Reference updates refused.",
        |d| d.references_refused,
    ),
    ("mfc_device_restarts_total", "mfc_devices_restarts_total", "Plant runs started.", |d| {
        d.restarts
    }),
    ("mfc_device_envelope_changes_total", "mfc_devices_envelope_changes_total",
        "Envelope changes since the service started.",
        |d| d.envelope_changes,
    ),
    ("mfc_device_lease_fenced_total", "mfc_devices_lease_fenced_total",
        "Answers held back because another controller held the plant's lease.",
        |d| d.lease_fenced,
    ),
    ("mfc_device_lease_claims_total", "mfc_devices_lease_claims_total",
        "Claims of the plant's vacant lease sent.",
        |d| d.lease_claims,
    ),
    ("mfc_device_lease_yields_total", "mfc_devices_lease_yields_total",
        "Leases given up to the member the fleet prefers.",
        |d| d.lease_yields,
    ),
    ("mfc_device_lease_refused_total", "mfc_devices_lease_refused_total",
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
        "Gateway batches dropped unserved (the oldest, when a gateway's unread ones held more than a period's worth).",
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

/// Gauges of a worker's report.
const SERVICE_GAUGES: &[(&str, Field<Scraped>)] = &[
    ("mfc_service_devices", |w| w.tally.devices),
    ("mfc_devices_remote", |w| w.tally.remote),
    ("mfc_service_device_series", |w| {
        w.status.devices.len() as u64
    }),
    ("mfc_service_active", |w| u64::from(w.status.active)),
    ("mfc_service_twins", |w| w.status.twins.len() as u64),
    ("mfc_service_inbox_depth", |w| w.inbox as u64),
    ("mfc_service_gateway_depth", |w| w.gateways as u64),
    ("mfc_service_queue_depth", |w| w.queue as u64),
];

const TROUBLE: u32 = pb::SampleFlags::Holding as u32
    | pb::SampleFlags::Fallback as u32
    | pb::SampleFlags::SafeStop as u32;

/// How long a scrape waits for a worker; a worker that does not answer in time (stuck, or
/// stopping) keeps the recorder's figures of its last answer, its sums are left out of
/// that scrape, and its devices keep their counts for the worst list.
pub const SCRAPE_TIMEOUT: Duration = Duration::from_secs(2);

impl ServiceMetrics {
    /// Metrics of service `controller` into `metrics`, as `spec` says (checked by the
    /// configuration: [`MetricsSpec::check`]).
    pub fn new(
        metrics: Metrics,
        controller: &str,
        spec: &MetricsSpec,
        recording: Option<Recording>,
    ) -> Self {
        for (name, _, help, _) in DEVICE_COUNTERS {
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
            "mfc_devices_remote",
            None,
            "Devices whose plant applies this service's commands (not holding, on its fallback or stopped).",
        );
        metrics.describe(
            "mfc_service_device_series",
            None,
            "Devices with series of their own (metrics.devices, or per_device up to metrics.max_devices).",
        );
        metrics.describe(
            "mfc_service_active",
            None,
            "1 if this worker answers (hot standby: the active member).",
        );
        metrics.describe(
            "mfc_service_twins",
            None,
            "Other processes seen carrying this service's controller id (a copied bundle, a service started twice): should be 0.",
        );
        metrics.describe(
            "mfc_service_inbox_depth",
            None,
            "Devices with a sample waiting to be served.",
        );
        metrics.describe(
            "mfc_service_gateway_depth",
            None,
            "Gateways with batches waiting to be served.",
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
        let named: HashSet<String> = spec.devices.iter().cloned().collect();
        Self {
            metrics,
            spec: spec.clone(),
            controller: controller.to_string(),
            chosen: Mutex::new(named.iter().cloned().collect()),
            named,
            workers: Mutex::new(Vec::new()),
            recording,
            rtt: FixedHistogram::new(telemetry::prom::RTT_BUCKETS),
            cpu: FixedHistogram::new(telemetry::prom::CPU_BUCKETS),
            missed: Mutex::new(HashMap::new()),
        }
    }

    /// The recorder (for rendering).
    pub fn metrics(&self) -> &Metrics {
        &self.metrics
    }

    /// Register a worker: it answers scrape requests from the returned queue.
    pub fn join(&self) -> mpsc::Receiver<ScrapeRequest> {
        let (tx, rx) = mpsc::channel(4);
        locked(&self.workers).push(tx);
        rx
    }

    /// Count a served sample in the service-wide histograms: its round trip as the plant
    /// reported it (`None`: not known yet) and the CPU time it took (if timed).
    pub fn served(&self, rtt: Option<f64>, cpu: Option<f64>) {
        if let Some(r) = rtt {
            self.rtt.record(r);
        }
        if let Some(c) = cpu {
            self.cpu.record(c);
        }
    }

    /// Whether any device may have series of its own (`per_device`, or devices named):
    /// otherwise a worker need not look its devices up at each sample.
    pub fn per_device_series(&self) -> bool {
        self.spec.per_device || !self.named.is_empty()
    }

    /// A device's histograms, if it has series of its own: named in `devices`, or with
    /// `per_device` while fewer than `max_devices` have them. Asked once per device (at
    /// its first sample).
    pub fn device(&self, controller: &str, device: &str) -> Option<DeviceHistograms> {
        if !self.named.contains(device) {
            let mut chosen = locked(&self.chosen);
            if !chosen.contains(device) {
                if !self.spec.per_device || chosen.len() >= self.spec.max_devices {
                    return None;
                }
                chosen.insert(device.to_string());
            }
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

    /// Device `id` is no longer served here: its place among the devices with series of
    /// their own is free again (a named device keeps it).
    pub fn forget(&self, id: &str) {
        if !self.named.contains(id) {
            locked(&self.chosen).remove(id);
        }
    }

    /// Ask every worker for its status, copy it into the recorder, and return the text of
    /// what is rendered here (the service-wide histograms, the worst devices).
    pub async fn refresh(&self) -> String {
        let workers: Vec<_> = locked(&self.workers).clone();
        let asked = workers.len();
        let detail = Arc::new(locked(&self.chosen).clone());
        let mut scraped = Vec::with_capacity(workers.len());
        for w in workers {
            let (reply, rx) = oneshot::channel();
            let detail = detail.clone();
            if w.send(ScrapeRequest { detail, reply }).await.is_err() {
                continue;
            }
            if let Ok(Ok(s)) = tokio::time::timeout(SCRAPE_TIMEOUT, rx).await {
                scraped.push(s);
            }
        }
        self.apply(&scraped, scraped.len() == asked)
    }

    /// Copy what the workers reported into the recorder, and return the text rendered
    /// here (no I/O: unit-tested). `all`: every worker answered.
    pub fn apply(&self, scraped: &[Scraped], all: bool) -> String {
        self.apply_service(scraped);
        for w in scraped {
            let c = w.status.controller_id.as_str();
            for d in &w.status.devices {
                self.apply_device(c, d);
            }
        }
        if let Some(r) = &self.recording {
            self.metrics
                .counter("mfc_service_recording_dropped_total", &[])
                .absolute(r.dropped());
        }
        let mut out = String::new();
        let labels = format!("controller=\"{}\"", label_value(&self.controller));
        self.rtt.render(
            &mut out,
            ("mfc_service_loop_rtt_seconds", RTT_HELP),
            &labels,
        );
        self.cpu.render(
            &mut out,
            ("mfc_service_sample_cpu_seconds", CPU_HELP),
            &labels,
        );
        Self::render_sums(&mut out, scraped);
        self.render_worst(&mut out, (scraped, all), &labels);
        out
    }

    /// The service-wide series of the recorder: each worker's counters and gauges, labelled
    /// with its id.
    fn apply_service(&self, scraped: &[Scraped]) {
        let m = &self.metrics;
        for w in scraped {
            let sl = [("controller", w.status.controller_id.as_str())];
            for (name, _, get) in SERVICE_COUNTERS {
                m.counter(name, &sl).absolute(get(&w.status));
            }
            for (name, get) in SERVICE_GAUGES {
                m.gauge(name, &sl).set(get(w) as f64);
            }
        }
    }

    /// `mfc_devices_*_total`, per worker: rendered here rather than through the recorder,
    /// whose counters only rise, because a sum falls when a device leaves (Prometheus
    /// takes the fall for a counter reset).
    fn render_sums(out: &mut String, scraped: &[Scraped]) {
        for (i, (_, name, help, _)) in DEVICE_COUNTERS.iter().enumerate() {
            let _ = writeln!(
                out,
                "# HELP {name} Over every device this worker answers: {help}\n# TYPE {name} counter"
            );
            for w in scraped {
                let total = w.tally.sums.get(i).copied().unwrap_or(0);
                let c = label_value(&w.status.controller_id);
                let _ = writeln!(out, "{name}{{controller=\"{c}\"}} {total}");
            }
        }
    }

    /// The series of one device with series of its own.
    fn apply_device(&self, c: &str, d: &pb::DeviceStatus) {
        let m = &self.metrics;
        let dl = [("controller", c), ("device", d.device_id.as_str())];
        for (name, _, _, get) in DEVICE_COUNTERS {
            m.counter(name, &dl).absolute(get(d));
        }
        m.gauge("mfc_device_remote", &dl)
            .set(if remote(d) { 1.0 } else { 0.0 });
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

    /// `mfc_worst_device_missed`: the `worst` devices by samples missed since the previous
    /// scrape (none that missed nothing), most first.
    fn render_worst(&self, out: &mut String, (scraped, all): (&[Scraped], bool), labels: &str) {
        let mut previous = locked(&self.missed);
        // A device in two reports (moving between workers): its larger count.
        let mut now: HashMap<String, u64> = HashMap::with_capacity(previous.len());
        for (id, missed) in scraped.iter().flat_map(|w| &w.tally.missed) {
            let e = now.entry(id.clone()).or_insert(0);
            *e = (*e).max(*missed);
        }
        let mut worst: Vec<(u64, &str)> = Vec::new();
        for (id, missed) in &now {
            // A count below the last one is a new run of the device: all of it is new.
            let before = previous.get(id).copied().filter(|b| b <= missed);
            let delta = missed - before.unwrap_or(0);
            if delta > 0 {
                worst.push((delta, id));
            }
        }
        let n = self.spec.worst.min(worst.len());
        if n > 0 {
            worst.select_nth_unstable_by(n - 1, |a, b| b.0.cmp(&a.0).then(a.1.cmp(b.1)));
            worst.truncate(n);
            worst.sort_unstable_by(|a, b| b.0.cmp(&a.0).then(a.1.cmp(b.1)));
        }
        let name = "mfc_worst_device_missed";
        let _ = writeln!(out, "# HELP {name} {WORST_HELP}\n# TYPE {name} gauge");
        for (delta, id) in worst {
            let _ = writeln!(
                out,
                "{name}{{{labels},device=\"{}\"}} {delta}",
                label_value(id)
            );
        }
        // A worker that did not answer keeps its devices' counts for the next scrape.
        if !all {
            for (id, missed) in previous.drain() {
                now.entry(id).or_insert(missed);
            }
        }
        *previous = now;
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

    fn device(id: &str, lost: u64, stale: u64, flags: u32) -> pb::DeviceStatus {
        pb::DeviceStatus {
            device_id: id.into(),
            samples: 100,
            commands: 98,
            lost,
            stale,
            f_est: vec![1.5, -2.0],
            last_flags: flags,
            ..Default::default()
        }
    }

    /// Worker `id`'s answer for `devices`, the whole status of those in `detail`.
    fn scraped(id: &str, devices: &[pb::DeviceStatus], detail: &[&str]) -> Scraped {
        let mut tally = Tally::default();
        for d in devices {
            tally.add(&d.device_id, d);
        }
        Scraped {
            status: pb::ServiceStatus {
                controller_id: id.into(),
                active: true,
                queue_full: 3,
                devices: devices
                    .iter()
                    .filter(|d| detail.contains(&d.device_id.as_str()))
                    .cloned()
                    .collect(),
                ..Default::default()
            },
            tally,
            inbox: 1,
            gateways: 0,
            queue: 2,
        }
    }

    fn spec(per_device: bool, devices: &[&str], max_devices: usize) -> MetricsSpec {
        MetricsSpec {
            per_device,
            devices: devices.iter().map(|d| d.to_string()).collect(),
            max_devices,
            ..MetricsSpec::default()
        }
    }

    /// Every line that is a series (not a comment).
    fn series(text: &str) -> Vec<&str> {
        text.lines()
            .filter(|l| !l.is_empty() && !l.starts_with('#'))
            .collect()
    }

    #[test]
    fn a_named_device_gets_every_counter_of_its_status() {
        let sm = ServiceMetrics::new(Metrics::new(), "c1", &spec(false, &["aero-1"], 100), None);
        assert!(sm.device("c1", "aero-1").is_some());
        assert!(sm.device("c1", "aero-2").is_none(), "not named");
        let d = [device("aero-1", 2, 1, pb::SampleFlags::Fallback as u32)];
        let extra = sm.apply(&[scraped("c1", &d, &["aero-1"])], true);
        let t = sm.metrics().render() + &extra;
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
            "mfc_worst_device_missed{controller=\"c1\",device=\"aero-1\"} 3",
        ] {
            assert!(t.lines().any(|l| l == line), "missing {line} in\n{t}");
        }
        // A later scrape moves the counters to the new figures, not by them; the worst
        // devices count what was missed since the previous scrape.
        let mut d = d;
        d[0].samples = 150;
        d[0].lost = 4;
        let extra = sm.apply(&[scraped("c1", &d, &["aero-1"])], true);
        let t = sm.metrics().render() + &extra;
        for line in [
            "mfc_device_samples_total{controller=\"c1\",device=\"aero-1\"} 150",
            "mfc_worst_device_missed{controller=\"c1\",device=\"aero-1\"} 2",
        ] {
            assert!(t.lines().any(|l| l == line), "missing {line} in\n{t}");
        }
    }

    /// Ten thousand devices, two workers: by default a few dozen series, whatever the
    /// number of devices: the sums, the service histograms and the ten worst devices.
    #[test]
    fn ten_thousand_devices_make_a_bounded_set_of_series_by_default() {
        let sm = ServiceMetrics::new(Metrics::new(), "c1", &MetricsSpec::default(), None);
        let all: Vec<pb::DeviceStatus> = (0..10_000u64)
            .map(|i| {
                let flags = if i % 4 == 0 {
                    pb::SampleFlags::Holding as u32
                } else {
                    0
                };
                device(&format!("load-{i}"), i % 37, 0, flags)
            })
            .collect();
        for i in 0..10_000 {
            sm.served(Some(0.002), Some(4e-6));
            assert!(sm.device("c1", &format!("load-{i}")).is_none());
        }
        let (a, b) = all.split_at(5_000);
        let extra = sm.apply(&[scraped("c1.w0", a, &[]), scraped("c1.w1", b, &[])], true);
        let t = sm.metrics().render() + &extra;
        let n = series(&t).len();
        assert!(n < 200, "{n} series:\n{t}");
        let lost: u64 = (0..5_000u64).map(|i| i % 37).sum();
        for line in [
            "mfc_service_devices{controller=\"c1.w0\"} 5000".to_string(),
            "mfc_service_devices{controller=\"c1.w1\"} 5000".into(),
            "mfc_devices_remote{controller=\"c1.w0\"} 3750".into(),
            "mfc_devices_samples_total{controller=\"c1.w1\"} 500000".into(),
            format!("mfc_devices_lost_total{{controller=\"c1.w0\"}} {lost}"),
            "mfc_service_loop_rtt_seconds_count{controller=\"c1\"} 10000".into(),
            "mfc_service_loop_rtt_seconds_bucket{controller=\"c1\",le=\"0.002\"} 10000".into(),
            "mfc_service_loop_rtt_seconds_bucket{controller=\"c1\",le=\"0.001\"} 0".into(),
            "mfc_service_sample_cpu_seconds_count{controller=\"c1\"} 10000".into(),
            "mfc_service_device_series{controller=\"c1.w0\"} 0".into(),
            "# TYPE mfc_devices_lost_total counter".into(),
        ] {
            assert!(t.lines().any(|l| l == line), "missing {line} in\n{t}");
        }
        // The ten worst: 36 missed each (ids i with i % 37 == 36), the first ids in
        // text order among equals.
        let worst: Vec<&str> = t
            .lines()
            .filter(|l| l.starts_with("mfc_worst_device_missed{"))
            .collect();
        assert_eq!(worst.len(), 10, "{worst:?}");
        assert!(worst.iter().all(|l| l.ends_with(" 36")), "{worst:?}");
        assert!(worst[0].contains("device=\"load-1035\""), "{worst:?}");
        // Nothing missed since: no worst device at the next scrape.
        let extra = sm.apply(&[scraped("c1.w0", a, &[]), scraped("c1.w1", b, &[])], true);
        assert!(!extra.contains("mfc_worst_device_missed{"), "{extra}");
    }

    /// A sum falls when a device leaves (the recorder's counters would stay at their peak);
    /// a worker that did not answer does not turn its devices' whole history into misses
    /// at the next scrape; a device in two reports (moving between workers) is one of the
    /// worst once.
    #[test]
    fn sums_fall_and_the_worst_devices_survive_a_silent_worker_and_a_move() {
        let sm = ServiceMetrics::new(Metrics::new(), "c1", &MetricsSpec::default(), None);
        let (a, b) = (device("a", 5, 0, 0), device("b", 7, 0, 0));
        let line = |t: &str, name: &str| {
            t.lines()
                .find(|l| l.starts_with(name))
                .map(str::to_string)
                .unwrap_or_default()
        };
        let t = sm.apply(&[scraped("w0", &[a.clone(), b.clone()], &[])], true);
        assert_eq!(
            line(&t, "mfc_devices_lost_total{"),
            "mfc_devices_lost_total{controller=\"w0\"} 12"
        );
        let t = sm.apply(&[scraped("w0", std::slice::from_ref(&a), &[])], true);
        assert_eq!(
            line(&t, "mfc_devices_lost_total{"),
            "mfc_devices_lost_total{controller=\"w0\"} 5"
        );
        // A fresh service: w1 (holding b) does not answer once: b keeps its count; then b
        // is in both reports, with 2 more.
        let sm = ServiceMetrics::new(Metrics::new(), "c1", &MetricsSpec::default(), None);
        let _ = sm.apply(
            &[
                scraped("w0", std::slice::from_ref(&a), &[]),
                scraped("w1", &[b], &[]),
            ],
            true,
        );
        let _ = sm.apply(&[scraped("w0", std::slice::from_ref(&a), &[])], false);
        let b9 = device("b", 9, 0, 0);
        let t = sm.apply(
            &[
                scraped("w0", &[a.clone(), b9.clone()], &[]),
                scraped("w1", &[b9], &[]),
            ],
            true,
        );
        let worst: Vec<&str> = t
            .lines()
            .filter(|l| l.starts_with("mfc_worst_device_missed{"))
            .collect();
        assert_eq!(
            worst,
            ["mfc_worst_device_missed{controller=\"c1\",device=\"b\"} 2"]
        );
    }

    #[test]
    fn per_device_series_stop_at_max_devices_and_a_forgotten_device_frees_its_place() {
        let sm = ServiceMetrics::new(Metrics::new(), "c1", &spec(true, &["named"], 3), None);
        let got: Vec<bool> = ["a", "b", "c", "named"]
            .iter()
            .map(|d| sm.device("c1", d).is_some())
            .collect();
        assert_eq!(
            got,
            [true, true, false, true],
            "named counts toward the cap, and always gets its series"
        );
        assert!(
            sm.device("c1", "a").is_some(),
            "asked again (on another worker)"
        );
        sm.forget("a");
        assert!(sm.device("c1", "c").is_some(), "a's place");
        sm.forget("named");
        assert!(
            sm.device("c1", "d").is_none(),
            "a named device keeps its place"
        );
        let detail = locked(&sm.chosen).clone();
        assert_eq!(detail.into_iter().collect::<Vec<_>>(), ["b", "c", "named"]);
    }

    #[test]
    fn device_ids_are_escaped_in_labels() {
        assert_eq!(label_value("a\"b\\c\nd"), "a\\\"b\\\\c\\nd");
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

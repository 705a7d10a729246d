//! A Prometheus endpoint over a recorder of the `metrics` ecosystem.
//!
//! Counters that the service or the agent already keeps (in its status) are copied into
//! the recorder by a refresh just before each scrape rather than incremented twice: one
//! source of truth, and a scrape that matches a status query taken at the same moment.
//! Histograms (round trips, CPU per sample) are recorded as values arrive, through handles
//! registered once per device.

use std::future::Future;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::Arc;

use metrics::{Counter, Gauge, Histogram, Key, Label, Level, Metadata, Recorder, Unit};
use metrics_exporter_prometheus::{
    Matcher, PrometheusBuilder, PrometheusHandle, PrometheusRecorder,
};
use serde::{Deserialize, Serialize};

/// Where and what to export. `per_device`, `devices`, `max_devices` and `worst` choose
/// the controller service's series; an agent or a gateway exports every plant it runs.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MetricsSpec {
    /// Address of the endpoint (`GET /metrics`). Default `127.0.0.1:9464`: loopback, since
    /// the figures name every device; put a reverse proxy or a wider address in front on
    /// purpose.
    #[serde(default = "default_listen")]
    pub listen: String,
    /// Series per device (counters, round-trip and CPU histograms, F estimates) for every
    /// device, up to `max_devices` of them (the first to send a sample). Default false:
    /// each device costs about 53 series, and Prometheus's guidance is to keep unbounded
    /// sets such as device ids out of labels; the service-wide series (histograms over all
    /// devices, counters summed, the `worst` devices) say how the fleet does, and a
    /// device's detail is in `mfcctl status` and the console.
    #[serde(default)]
    pub per_device: bool,
    /// Devices that get their series whatever `per_device` says (an operator watching a
    /// few plants closely). Default none. At most `max_devices`.
    #[serde(default)]
    pub devices: Vec<String>,
    /// At most this many devices get series of their own. Default 100 (about 5,000
    /// series); at most 100,000.
    #[serde(default = "default_max_devices")]
    pub max_devices: usize,
    /// The devices that lost or got late the most samples since the previous scrape,
    /// this many at most, each a series of its own in `mfc_worst_device_missed` (a bounded
    /// set that follows the trouble). Default 10; at most 1,000; 0: none.
    #[serde(default = "default_worst")]
    pub worst: usize,
    /// Serve over TLS, to scrapers holding a client certificate of `client_ca_file` only
    /// (absent: plain HTTP, meant for loopback; the log warns when it is not). The names
    /// are those of Prometheus exporter-toolkit's `tls_server_config`, with its
    /// `client_auth_type` fixed at `RequireAndVerifyClientCert`.
    #[serde(default)]
    pub tls: Option<MetricsTls>,
}

/// The endpoint's TLS: its certificate and key, and the CA its scrapers' client
/// certificates must chain to. Relative paths are resolved against the directory of the
/// file that holds them ([`MetricsSpec::resolve`]).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MetricsTls {
    /// The endpoint's certificate chain (PEM).
    pub cert_file: std::path::PathBuf,
    /// Its private key (PEM).
    pub key_file: std::path::PathBuf,
    /// The CA (PEM) of the scrapers' client certificates: a scrape without one of its
    /// certificates fails the handshake.
    pub client_ca_file: std::path::PathBuf,
}

impl MetricsSpec {
    /// Largest `max_devices`.
    pub const MAX_DEVICES: usize = 100_000;
    /// Largest `worst`.
    pub const MAX_WORST: usize = 1_000;

    /// Check the bounds; the error names the field.
    pub fn check(&self) -> Result<(), String> {
        if self.max_devices > Self::MAX_DEVICES {
            return Err(format!(
                "metrics.max_devices = {}: at most {}",
                self.max_devices,
                Self::MAX_DEVICES
            ));
        }
        if self.devices.len() > self.max_devices {
            return Err(format!(
                "metrics.devices names {} devices, more than max_devices = {}",
                self.devices.len(),
                self.max_devices
            ));
        }
        if self.worst > Self::MAX_WORST {
            return Err(format!(
                "metrics.worst = {}: at most {}",
                self.worst,
                Self::MAX_WORST
            ));
        }
        Ok(())
    }

    /// Make the TLS files' relative paths relative to `dir` (the directory of the
    /// configuration file that names them).
    pub fn resolve(&mut self, dir: &std::path::Path) {
        if let Some(t) = &mut self.tls {
            for p in [&mut t.cert_file, &mut t.key_file, &mut t.client_ca_file] {
                if p.is_relative() {
                    *p = dir.join(&*p);
                }
            }
        }
    }
}

fn default_listen() -> String {
    "127.0.0.1:9464".into()
}

fn default_max_devices() -> usize {
    100
}

fn default_worst() -> usize {
    10
}

impl Default for MetricsSpec {
    fn default() -> Self {
        Self {
            listen: default_listen(),
            per_device: false,
            devices: Vec::new(),
            max_devices: default_max_devices(),
            worst: default_worst(),
            tls: None,
        }
    }
}

/// Why the endpoint could not start.
#[derive(Debug, thiserror::Error)]
pub enum MetricsError {
    /// `listen` is not a socket address.
    #[error("metrics.listen = {0:?}: not an address like 127.0.0.1:9464")]
    Address(String),
    /// Binding failed (in use, not permitted).
    #[error("metrics endpoint on {addr}: {source}")]
    Bind {
        /// The address.
        addr: String,
        /// The system's reason.
        source: std::io::Error,
    },
    /// A TLS file cannot be read or used.
    #[error("metrics.tls: {0}")]
    Tls(String),
}

/// Round-trip buckets (s): 100 µs to 1 s, denser where a 10 ms loop lives.
pub const RTT_BUCKETS: &[f64] = &[
    1e-4, 2.5e-4, 5e-4, 1e-3, 2e-3, 3e-3, 5e-3, 7.5e-3, 1e-2, 1.5e-2, 2e-2, 3e-2, 5e-2, 0.1, 0.25,
    1.0,
];

/// CPU-per-sample buckets (s): 1 µs to 10 ms.
pub const CPU_BUCKETS: &[f64] = &[
    1e-6, 2e-6, 5e-6, 1e-5, 2e-5, 5e-5, 1e-4, 2e-4, 5e-4, 1e-3, 1e-2,
];

/// A recorder of its own and what renders it.
#[derive(Debug, Clone)]
pub struct Metrics {
    recorder: Arc<PrometheusRecorder>,
    handle: PrometheusHandle,
}

const META: Metadata<'static> = Metadata::new("mfc", Level::INFO, Some(module_path!()));

fn key(name: &'static str, labels: &[(&'static str, &str)]) -> Key {
    Key::from_parts(
        name,
        labels
            .iter()
            .map(|(k, v)| Label::new(*k, v.to_string()))
            .collect::<Vec<_>>(),
    )
}

impl Metrics {
    /// A recorder whose histograms named `*_rtt_seconds` use [`RTT_BUCKETS`] and
    /// `*_cpu_seconds` use [`CPU_BUCKETS`] (Prometheus histograms, not summaries, so that
    /// they aggregate across devices and instances).
    pub fn new() -> Self {
        let recorder = PrometheusBuilder::new()
            .set_buckets_for_metric(Matcher::Suffix("rtt_seconds".into()), RTT_BUCKETS)
            .and_then(|b| {
                b.set_buckets_for_metric(Matcher::Suffix("cpu_seconds".into()), CPU_BUCKETS)
            })
            .expect("bucket lists are constant and non-empty")
            .build_recorder();
        let handle = recorder.handle();
        Self {
            recorder: Arc::new(recorder),
            handle,
        }
    }

    /// Say what a metric is (the `# HELP` line) and its unit.
    pub fn describe(&self, name: &'static str, unit: Option<Unit>, help: &'static str) {
        self.recorder.describe_gauge(name.into(), unit, help.into());
    }

    /// The counter `name{labels}` (created at first use).
    pub fn counter(&self, name: &'static str, labels: &[(&'static str, &str)]) -> Counter {
        self.recorder.register_counter(&key(name, labels), &META)
    }

    /// The gauge `name{labels}`.
    pub fn gauge(&self, name: &'static str, labels: &[(&'static str, &str)]) -> Gauge {
        self.recorder.register_gauge(&key(name, labels), &META)
    }

    /// The histogram `name{labels}`.
    pub fn histogram(&self, name: &'static str, labels: &[(&'static str, &str)]) -> Histogram {
        self.recorder.register_histogram(&key(name, labels), &META)
    }

    /// The exposition text of everything recorded.
    pub fn render(&self) -> String {
        self.handle.render()
    }
}

impl Default for Metrics {
    fn default() -> Self {
        Self::new()
    }
}

/// What the endpoint runs before rendering: copies the owner's counters into the recorder,
/// and returns the exposition text of what it renders itself ([`FixedHistogram`], sets
/// that change between scrapes), appended to the recorder's.
pub type Refresh = Arc<dyn Fn() -> Pin<Box<dyn Future<Output = String> + Send>> + Send + Sync>;

/// A histogram of fixed buckets, shared by threads that record into it with a relaxed
/// atomic add each, never growing. The recorder's own histograms keep every value until
/// the next scrape: at ten thousand plants of 100 samples a second, 15 s between scrapes
/// are 15 million values.
#[derive(Debug)]
pub struct FixedHistogram {
    bounds: &'static [f64],
    /// Per bucket (not cumulative), the last one past every bound.
    counts: Vec<std::sync::atomic::AtomicU64>,
    /// Sum of the values, an `f64`'s bits (an integer count of nanoseconds would wrap in
    /// about a hundred days at a million samples a second of 2 ms).
    sum_bits: std::sync::atomic::AtomicU64,
}

impl FixedHistogram {
    /// A histogram with these upper bounds (increasing).
    pub fn new(bounds: &'static [f64]) -> Self {
        Self {
            bounds,
            counts: (0..=bounds.len())
                .map(|_| std::sync::atomic::AtomicU64::new(0))
                .collect(),
            sum_bits: std::sync::atomic::AtomicU64::new(0f64.to_bits()),
        }
    }

    /// Count `v` (a NaN or a negative value counts in the first bucket, adding nothing to
    /// the sum).
    pub fn record(&self, v: f64) {
        use std::sync::atomic::Ordering::Relaxed;
        let i = self.bounds.partition_point(|b| *b < v);
        self.counts[i].fetch_add(1, Relaxed);
        if v > 0.0 {
            let _ = self.sum_bits.fetch_update(Relaxed, Relaxed, |b| {
                Some((f64::from_bits(b) + v).to_bits())
            });
        }
    }

    /// Values counted so far.
    pub fn count(&self) -> u64 {
        use std::sync::atomic::Ordering::Relaxed;
        self.counts.iter().map(|c| c.load(Relaxed)).sum()
    }

    /// Append the exposition text (`# HELP`, `# TYPE`, the cumulative buckets with `le`,
    /// `_sum`, `_count`) of `name{labels}` to `out`.
    pub fn render(&self, out: &mut String, (name, help): (&str, &str), labels: &str) {
        use std::fmt::Write as _;
        use std::sync::atomic::Ordering::Relaxed;
        let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} histogram");
        let sep = if labels.is_empty() { "" } else { "," };
        let mut total = 0u64;
        for (i, c) in self.counts.iter().enumerate() {
            total += c.load(Relaxed);
            let le = self
                .bounds
                .get(i)
                .map_or_else(|| "+Inf".to_string(), |b| b.to_string());
            let _ = writeln!(out, "{name}_bucket{{{labels}{sep}le=\"{le}\"}} {total}");
        }
        let sum = f64::from_bits(self.sum_bits.load(Relaxed));
        let braces = |l: &str| {
            if l.is_empty() {
                String::new()
            } else {
                format!("{{{l}}}")
            }
        };
        let _ = writeln!(out, "{name}_sum{} {sum}", braces(labels));
        let _ = writeln!(out, "{name}_count{} {total}", braces(labels));
    }
}

/// Bind the endpoint described by `spec`; the returned future serves `GET /metrics` (any
/// other path: 404) until `shutdown` resolves. Binding happens here, so that a port in use
/// is an error at start, not a log line later.
pub async fn serve_metrics(
    spec: &MetricsSpec,
    metrics: Metrics,
    refresh: Refresh,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(SocketAddr, impl Future<Output = ()> + Send), MetricsError> {
    let addr: SocketAddr = spec
        .listen
        .parse()
        .map_err(|_| MetricsError::Address(spec.listen.clone()))?;
    let listener = tokio::net::TcpListener::bind(addr)
        .await
        .map_err(|source| MetricsError::Bind {
            addr: spec.listen.clone(),
            source,
        })?;
    let local = listener.local_addr().map_err(|source| MetricsError::Bind {
        addr: spec.listen.clone(),
        source,
    })?;
    let app = axum::Router::new().route(
        "/metrics",
        axum::routing::get(move || {
            let (metrics, refresh) = (metrics.clone(), refresh.clone());
            async move {
                let extra = refresh().await;
                let mut text = metrics.render();
                text.push_str(&extra);
                (
                    [(
                        axum::http::header::CONTENT_TYPE,
                        "text/plain; version=0.0.4; charset=utf-8",
                    )],
                    text,
                )
            }
        }),
    );
    let fut: Pin<Box<dyn Future<Output = ()> + Send>> = match &spec.tls {
        Some(tls) => {
            let files = transport::https::TlsFiles {
                cert_file: tls.cert_file.clone(),
                key_file: tls.key_file.clone(),
                client_ca_file: Some(tls.client_ca_file.clone()),
            };
            let acceptor =
                transport::https::acceptor(&files, transport::https::ClientCerts::Required)
                    .map_err(|e| MetricsError::Tls(e.to_string()))?;
            tracing::info!(addr = %local, "metrics endpoint: GET /metrics over TLS, client certificates required");
            Box::pin(transport::https::serve(
                listener,
                acceptor,
                app,
                shutdown,
                "metrics endpoint",
            ))
        }
        None => {
            if !local.ip().is_loopback() {
                tracing::warn!(addr = %local, "metrics endpoint: plain HTTP on a non-loopback address; anyone who reaches it reads every device's figures (set metrics.tls)");
            }
            tracing::info!(addr = %local, "metrics endpoint: GET /metrics");
            Box::pin(async move {
                if let Err(e) = axum::serve(listener, app)
                    .with_graceful_shutdown(shutdown)
                    .await
                {
                    tracing::warn!("metrics endpoint stopped: {e}");
                }
            })
        }
    };
    Ok((local, fut))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counters_gauges_and_histograms_render_with_their_labels_and_buckets() {
        let m = Metrics::new();
        m.describe("mfc_device_samples_total", None, "Samples received.");
        m.counter("mfc_device_samples_total", &[("device", "aero-1")])
            .absolute(42);
        m.gauge("mfc_f_estimate", &[("device", "aero-1"), ("channel", "1")])
            .set(-3.5);
        let h = m.histogram("mfc_loop_rtt_seconds", &[("device", "aero-1")]);
        h.record(0.0012);
        h.record(0.004);
        let text = m.render();
        assert!(
            text.contains("# HELP mfc_device_samples_total Samples received."),
            "{text}"
        );
        assert!(
            text.contains("mfc_device_samples_total{device=\"aero-1\"} 42"),
            "{text}"
        );
        assert!(
            text.contains("mfc_f_estimate{device=\"aero-1\",channel=\"1\"} -3.5"),
            "{text}"
        );
        assert!(
            text.contains("mfc_loop_rtt_seconds_bucket{device=\"aero-1\",le=\"0.002\"} 1"),
            "{text}"
        );
        assert!(
            text.contains("mfc_loop_rtt_seconds_count{device=\"aero-1\"} 2"),
            "{text}"
        );
    }

    #[test]
    fn a_fixed_histogram_renders_cumulative_buckets_its_sum_and_count() {
        let h = FixedHistogram::new(&[0.001, 0.01]);
        for v in [0.0005, 0.001, 0.002, 0.5, f64::NAN] {
            h.record(v);
        }
        let mut out = String::new();
        h.render(&mut out, ("x_seconds", "Things."), "controller=\"c\"");
        for line in [
            "# HELP x_seconds Things.",
            "# TYPE x_seconds histogram",
            "x_seconds_bucket{controller=\"c\",le=\"0.001\"} 3",
            "x_seconds_bucket{controller=\"c\",le=\"0.01\"} 4",
            "x_seconds_bucket{controller=\"c\",le=\"+Inf\"} 5",
            "x_seconds_sum{controller=\"c\"} 0.5035",
            "x_seconds_count{controller=\"c\"} 5",
        ] {
            assert!(out.lines().any(|l| l == line), "missing {line} in\n{out}");
        }
        assert_eq!(h.count(), 5);
    }

    #[test]
    fn the_spec_bounds_are_checked_and_named() {
        assert!(MetricsSpec::default().check().is_ok());
        for (spec, field) in [
            (
                MetricsSpec {
                    max_devices: MetricsSpec::MAX_DEVICES + 1,
                    ..MetricsSpec::default()
                },
                "max_devices",
            ),
            (
                MetricsSpec {
                    devices: vec!["a".into(), "b".into()],
                    max_devices: 1,
                    ..MetricsSpec::default()
                },
                "metrics.devices",
            ),
            (
                MetricsSpec {
                    worst: MetricsSpec::MAX_WORST + 1,
                    ..MetricsSpec::default()
                },
                "worst",
            ),
        ] {
            let e = spec.check().unwrap_err();
            assert!(e.contains(field), "{e}");
        }
    }

    #[test]
    fn two_recorders_do_not_share_figures() {
        let (a, b) = (Metrics::new(), Metrics::new());
        a.counter("x_total", &[]).absolute(1);
        assert!(!b.render().contains("x_total"));
    }

    #[test]
    fn a_bad_address_is_named() {
        let spec = MetricsSpec {
            listen: "nowhere".into(),
            ..MetricsSpec::default()
        };
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        let r = rt.block_on(serve_metrics(
            &spec,
            Metrics::new(),
            Arc::new(|| Box::pin(async { String::new() })),
            async {},
        ));
        let Err(e) = r else {
            panic!("bound to nowhere")
        };
        assert!(e.to_string().contains("nowhere"), "{e}");
    }
}

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

/// Where and what to export.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MetricsSpec {
    /// Address of the endpoint (`GET /metrics`). Default `127.0.0.1:9464`: loopback, since
    /// the figures name every device; put a reverse proxy or a wider address in front on
    /// purpose.
    #[serde(default = "default_listen")]
    pub listen: String,
    /// Series per device (counters, round-trip and CPU histograms, F estimates). Default
    /// true. A service of thousands of devices may turn them off and keep the service-wide
    /// series only: each device costs about 60 series.
    #[serde(default = "yes")]
    pub per_device: bool,
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

fn yes() -> bool {
    true
}

impl Default for MetricsSpec {
    fn default() -> Self {
        Self {
            listen: default_listen(),
            per_device: true,
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

/// What the endpoint runs before rendering: copies the owner's counters into the recorder.
pub type Refresh = Arc<dyn Fn() -> Pin<Box<dyn Future<Output = ()> + Send>> + Send + Sync>;

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
                refresh().await;
                (
                    [(
                        axum::http::header::CONTENT_TYPE,
                        "text/plain; version=0.0.4; charset=utf-8",
                    )],
                    metrics.render(),
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
            Arc::new(|| Box::pin(async {})),
            async {},
        ));
        let Err(e) = r else {
            panic!("bound to nowhere")
        };
        assert!(e.to_string().contains("nowhere"), "{e}");
    }
}

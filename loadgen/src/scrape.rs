//! `loadgen scrape`: a real Prometheus server scraping the service while it serves
//! thousands of plants through gateways, for each metrics configuration asked: how many
//! series a scrape brings, how large the exposition is, how long a scrape takes (as
//! Prometheus measures it, and as a plain GET does), and what the plants saw meanwhile.
//!
//! The service and Prometheus run as processes of their own; the plants are this
//! process's generator ([`crate::gen`]).

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use serde::Serialize;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

use crate::bench::SERVICE_TOML;
use crate::gen::{self, LoadReport, Spec};

/// What to run.
#[derive(Debug, Clone)]
pub struct ScrapeSpec {
    /// The controller-service binary.
    pub service_bin: PathBuf,
    /// The Prometheus binary.
    pub prometheus_bin: PathBuf,
    /// Plants, and the gateways they share.
    pub devices: usize,
    pub gateways: usize,
    /// Samples per plant per second.
    pub rate_hz: f64,
    /// Prometheus's scrape interval.
    pub interval: Duration,
    /// How long the plants run (scrapes are read at the end).
    pub duration: Duration,
    /// The `[metrics]` settings to compare, by name (TOML after `listen`; `None`: no
    /// metrics endpoint, the anchor: what the plants see without any scrape).
    pub variants: Vec<(String, Option<String>)>,
    /// Where the results and the processes' files go.
    pub out: PathBuf,
}

/// One configuration's figures.
#[derive(Debug, Clone, Serialize)]
pub struct ScrapeResult {
    pub variant: String,
    /// Series in the last scrape (`scrape_samples_scraped`).
    pub series: Option<f64>,
    /// Prometheus's time for the last scrape (`scrape_duration_seconds`), s.
    pub prometheus_scrape_s: Option<f64>,
    /// Series in Prometheus's head block (`prometheus_tsdb_head_series`; Prometheus
    /// scrapes itself too, about a thousand series).
    pub head_series: Option<f64>,
    /// Prometheus's resident memory at the end, bytes.
    pub prometheus_rss: Option<u64>,
    /// A plain `GET /metrics` at the end: bytes, and the median time of three, s (NaN
    /// without an endpoint).
    pub exposition_bytes: usize,
    pub get_s: f64,
    /// What the plants saw meanwhile.
    pub load: LoadReport,
}

/// A child process killed when dropped.
struct Reaped(Child);

impl Drop for Reaped {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn port() -> anyhow::Result<u16> {
    Ok(transport::free_local_port()?)
}

/// `GET path` from `port` on loopback: the body, or `None` on any failure.
async fn get(port: u16, path: &str) -> Option<String> {
    let mut s = tokio::net::TcpStream::connect(("127.0.0.1", port))
        .await
        .ok()?;
    let req = format!("GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n");
    s.write_all(req.as_bytes()).await.ok()?;
    let mut buf = Vec::new();
    s.read_to_end(&mut buf).await.ok()?;
    let text = String::from_utf8(buf).ok()?;
    Some(text.split_once("\r\n\r\n")?.1.to_string())
}

/// `GET path` on the HTTP API of the Prometheus server at `port` on loopback: its JSON
/// body, or `None` on any failure.
pub async fn prometheus_api(port: u16, path: &str) -> Option<serde_json::Value> {
    let body = get(port, path).await?;
    // A chunked body starts with its size line: take the JSON object inside.
    let json = &body[body.find('{')?..=body.rfind('}')?];
    serde_json::from_str(json).ok()
}

/// The value of the first result of an instant query on Prometheus at `port`.
async fn query(port: u16, q: &str) -> Option<f64> {
    let v = prometheus_api(port, &format!("/api/v1/query?query={q}")).await?;
    v["data"]["result"][0]["value"][1].as_str()?.parse().ok()
}

/// A Prometheus server of its own, killed when dropped: configuration `yml`, its data
/// and log (`prometheus.log`) in `dir`, its web and API on `127.0.0.1:{web}`.
pub struct Prometheus(Reaped);

impl Prometheus {
    /// Start `binary` (its data directory emptied first).
    pub fn start(binary: &Path, dir: &Path, yml: &str, web: u16) -> std::io::Result<Self> {
        std::fs::write(dir.join("prometheus.yml"), yml)?;
        let _ = std::fs::remove_dir_all(dir.join("data"));
        let child = Command::new(binary)
            .arg(format!(
                "--config.file={}",
                dir.join("prometheus.yml").display()
            ))
            .arg(format!(
                "--storage.tsdb.path={}",
                dir.join("data").display()
            ))
            .arg(format!("--web.listen-address=127.0.0.1:{web}"))
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(dir.join("prometheus.log"))?)
            .spawn()?;
        Ok(Self(Reaped(child)))
    }

    /// Its process id.
    pub fn pid(&self) -> u32 {
        self.0 .0.id()
    }
}

/// Run every variant in turn; the results, also written to `out/scrape.json` and
/// `out/scrape.md`.
pub async fn run(spec: &ScrapeSpec) -> anyhow::Result<Vec<ScrapeResult>> {
    std::fs::create_dir_all(&spec.out)
        .with_context(|| format!("creating {}", spec.out.display()))?;
    let mut results = Vec::new();
    for (name, toml) in &spec.variants {
        eprintln!(
            "{name}: {} plants through {} gateways at {} Hz, Prometheus every {:?}, for {:?}",
            spec.devices, spec.gateways, spec.rate_hz, spec.interval, spec.duration
        );
        let r = variant(spec, name, toml.as_deref()).await?;
        eprintln!(
            "{name}: {} series, exposition {} bytes, scrape {:?} s (Prometheus) {:.4} s (GET), answered within the period {:.3} %",
            r.series.unwrap_or(f64::NAN),
            r.exposition_bytes,
            r.prometheus_scrape_s,
            r.get_s,
            100.0 * r.load.within_fraction()
        );
        results.push(r);
    }
    std::fs::write(
        spec.out.join("scrape.json"),
        serde_json::to_string_pretty(&results)?,
    )?;
    std::fs::write(spec.out.join("scrape.md"), markdown(spec, &results))?;
    Ok(results)
}

async fn variant(
    spec: &ScrapeSpec,
    name: &str,
    toml: Option<&str>,
) -> anyhow::Result<ScrapeResult> {
    let dir = spec.out.join(name);
    std::fs::create_dir_all(&dir)?;
    let (mport, zport, wport) = (port()?, port()?, port()?);
    let config = match toml {
        Some(t) => format!("{SERVICE_TOML}\n[metrics]\nlisten = \"127.0.0.1:{mport}\"\n{t}\n"),
        None => SERVICE_TOML.to_string(),
    };
    std::fs::write(dir.join("service.toml"), config)?;
    let endpoint = format!("tcp/127.0.0.1:{zport}");
    let _service = Reaped(
        Command::new(&spec.service_bin)
            .arg("--config")
            .arg(dir.join("service.toml"))
            .args(["--listen", &endpoint, "--no-multicast-scouting"])
            .env("RUST_LOG", "warn,zenoh=error")
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(dir.join("service.log"))?)
            .spawn()
            .with_context(|| format!("starting {}", spec.service_bin.display()))?,
    );
    let prometheus = start_prometheus(spec, &dir, mport, wport)?;
    let session = transport::ZenohArgs::loopback(None, vec![endpoint])
        .open()
        .await?;
    let gspec = Spec {
        devices: spec.devices,
        rate_hz: spec.rate_hz,
        gateways: spec.gateways,
        prefix: "load".into(),
        warmup: Duration::from_secs(3),
        measure: spec.duration,
        resend: 0,
        secret: None,
    };
    let load = gen::run(&session, &gspec).await?;
    // Read while the plants' state is still in the service: the last scrape Prometheus
    // took, then our own GETs.
    let job = "scrape_samples_scraped%7Bjob%3D%22mfc%22%7D";
    let series = query(wport, job).await;
    let prometheus_scrape_s = query(wport, "scrape_duration_seconds%7Bjob%3D%22mfc%22%7D").await;
    let head_series = query(wport, "prometheus_tsdb_head_series").await;
    let prometheus_rss = crate::stats::rss_bytes(prometheus.pid());
    let mut times = Vec::new();
    let mut bytes = 0;
    for _ in 0..3 {
        if toml.is_none() {
            break;
        }
        let t0 = Instant::now();
        let body = get(mport, "/metrics").await.context("GET /metrics")?;
        times.push(t0.elapsed().as_secs_f64());
        bytes = body.len();
    }
    let _ = session.close().await;
    Ok(ScrapeResult {
        variant: name.to_string(),
        series,
        prometheus_scrape_s,
        head_series,
        prometheus_rss,
        exposition_bytes: bytes,
        get_s: crate::bench::median(times).unwrap_or(f64::NAN),
        load,
    })
}

fn start_prometheus(
    spec: &ScrapeSpec,
    dir: &Path,
    mport: u16,
    wport: u16,
) -> anyhow::Result<Prometheus> {
    let secs = spec.interval.as_secs_f64();
    let yml = format!(
        "global:\n  scrape_interval: {secs}s\n  scrape_timeout: {secs}s\nscrape_configs:\n  - job_name: mfc\n    static_configs:\n      - targets: [\"127.0.0.1:{mport}\"]\n  - job_name: prometheus\n    static_configs:\n      - targets: [\"127.0.0.1:{wport}\"]\n"
    );
    match Prometheus::start(&spec.prometheus_bin, dir, &yml, wport) {
        Ok(p) => Ok(p),
        Err(e) => bail!(
            "starting {} ({e}): `loadgen scrape` needs a Prometheus server (apt-get install prometheus, or --prometheus PATH)",
            spec.prometheus_bin.display()
        ),
    }
}

/// The results as a table.
pub fn markdown(spec: &ScrapeSpec, results: &[ScrapeResult]) -> String {
    let opt = |v: Option<f64>, f: &dyn Fn(f64) -> String| v.map_or("-".into(), f);
    let mut s = format!(
        "{} plants through {} gateways at {} Hz; Prometheus scraping every {:?}; figures at the end of {:?}.\n\n",
        spec.devices, spec.gateways, spec.rate_hz, spec.interval, spec.duration
    );
    s += "| metrics | series per scrape | exposition | scrape (Prometheus) | GET /metrics | Prometheus head series (its own included) | Prometheus RSS | plants answered within the period |\n|---|---:|---:|---:|---:|---:|---:|---:|\n";
    for r in results {
        s += &format!(
            "| {} | {} | {} | {} | {} | {} | {} | {:.3} % |\n",
            r.variant,
            opt(r.series, &|v| format!("{v:.0}")),
            opt(
                Some(r.exposition_bytes as f64).filter(|b| *b > 0.0),
                &|b| format!("{:.1} KiB", b / 1024.0)
            ),
            opt(r.prometheus_scrape_s, &|v| format!("{:.1} ms", v * 1e3)),
            opt(Some(r.get_s).filter(|v| v.is_finite()), &|v| format!(
                "{:.1} ms",
                v * 1e3
            )),
            opt(r.head_series, &|v| format!("{v:.0}")),
            r.prometheus_rss
                .map_or("-".into(), |b| format!("{:.0} MiB", b as f64 / 1048576.0)),
            100.0 * r.load.within_fraction()
        );
    }
    s
}

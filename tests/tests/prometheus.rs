//! A real Prometheus server (Debian's `prometheus`) scrapes the service's metrics endpoint
//! over TLS with a client certificate from the deployment's PKI (`mfc-deploy generate`):
//! that scrape is up and brings the service's series in; scrapes without a certificate,
//! with another fleet's, or over plain HTTP are refused and down. Without `prometheus` on
//! the PATH the test installs Debian's package itself when it runs as root (as the browser
//! test installs chromium), and otherwise fails saying how to install it.

use std::process::Command;
use std::time::Duration;

use loadgen::scrape::{prometheus_api, Prometheus};
use system_tests::{scratch_dir, SERIAL};

/// A fleet's PKI in `dir`: a CA, a server certificate for 127.0.0.1 (the router's role)
/// and a client certificate (an operator's).
fn pki(dir: &std::path::Path) {
    let inv = mfc_deploy::Inventory::parse(
        "services = [\"svc\"]\noperators = [\"scraper\"]\n[router]\nhosts = [\"127.0.0.1\"]\n",
    )
    .unwrap();
    mfc_deploy::generate(&inv, dir, &[], time::OffsetDateTime::now_utc()).unwrap();
}

/// Every target's job, health and last error, once each has been scraped.
async fn targets(port: u16) -> Vec<(String, String, String)> {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(60);
    loop {
        if let Some(v) = prometheus_api(port, "/api/v1/targets").await {
            let active = v["data"]["activeTargets"]
                .as_array()
                .cloned()
                .unwrap_or_default();
            let got: Vec<(String, String, String)> = active
                .iter()
                .map(|t| {
                    let s = |k: &str| t[k].as_str().unwrap_or_default().to_string();
                    (
                        t["labels"]["job"].as_str().unwrap_or_default().to_string(),
                        s("health"),
                        s("lastError"),
                    )
                })
                .collect();
            if got.len() == 4 && got.iter().all(|(_, h, _)| h != "unknown") {
                return got;
            }
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "Prometheus never scraped every target"
        );
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
}

fn is_root() -> bool {
    Command::new("id")
        .arg("-u")
        .output()
        .is_ok_and(|o| o.stdout.trim_ascii() == b"0")
}

/// The Prometheus server to run (`MFC_PROMETHEUS`, default `prometheus`), installed from
/// Debian when missing and root; the test fails if there is none.
fn prometheus_binary() -> String {
    let prometheus = std::env::var("MFC_PROMETHEUS").unwrap_or_else(|_| "prometheus".into());
    let runs = || {
        Command::new(&prometheus)
            .arg("--version")
            .output()
            .is_ok_and(|o| o.status.success())
    };
    if !runs() && prometheus == "prometheus" && is_root() {
        let log = std::env::temp_dir().join("mfc-apt-prometheus.log");
        let install = format!(
            "{{ apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends prometheus; }} >{} 2>&1",
            log.display()
        );
        let _ = Command::new("sh").args(["-c", &install]).status();
    }
    assert!(
        runs(),
        "no `{prometheus}`: this test needs a real Prometheus server (as root it installs Debian's, logging to $TMPDIR/mfc-apt-prometheus.log; otherwise apt-get install prometheus, or set MFC_PROMETHEUS)"
    );
    prometheus
}

#[tokio::test(flavor = "multi_thread")]
async fn prometheus_scrapes_over_tls_with_a_client_certificate_only() {
    let _s = SERIAL.lock().await;
    let prometheus = prometheus_binary();
    let dir = scratch_dir("prometheus");
    let (ours, theirs) = (dir.join("ours"), dir.join("theirs"));
    pki(&ours);
    pki(&theirs);

    // The service, its endpoint over TLS: the router-role certificate, scrapers' client
    // certificates of our CA required.
    let port = transport::free_local_port().unwrap();
    let mut config = mfc_lab::harness::service_config(
        &plant::scenario::load_scenario("2").unwrap(),
        &plant::scenario::shipped_controller("ipd").unwrap(),
        &["aero-1".to_string()],
    );
    config.metrics = Some(telemetry::MetricsSpec {
        listen: format!("127.0.0.1:{port}"),
        devices: vec!["aero-1".into()],
        tls: Some(telemetry::MetricsTls {
            cert_file: ours.join("router/router.pem"),
            key_file: ours.join("router/router.key"),
            client_ca_file: ours.join("ca/ca.pem"),
        }),
        ..telemetry::MetricsSpec::default()
    });
    let service = mfc_lab::harness::ServiceHandle::start(config, None)
        .await
        .unwrap();

    // Prometheus with four jobs on the same endpoint: with our client certificate,
    // without one, with another fleet's, and over plain HTTP.
    let target = format!("[\"127.0.0.1:{port}\"]");
    let job = |name: &str, scheme: &str, tls: &str| {
        format!("  - job_name: {name}\n    scheme: {scheme}\n{tls}    static_configs:\n      - targets: {target}\n")
    };
    let ca = ours.join("ca/ca.pem").display().to_string();
    let cert = |d: &std::path::Path| {
        format!(
            "    tls_config:\n      ca_file: {ca}\n      cert_file: {}\n      key_file: {}\n",
            d.join("operators/scraper/scraper.pem").display(),
            d.join("operators/scraper/scraper.key").display()
        )
    };
    let yml = format!(
        "global:\n  scrape_interval: 1s\n  scrape_timeout: 900ms\nscrape_configs:\n{}{}{}{}",
        job("with-cert", "https", &cert(&ours)),
        job(
            "no-cert",
            "https",
            &format!("    tls_config:\n      ca_file: {ca}\n")
        ),
        job("other-fleet", "https", &cert(&theirs)),
        job("plain", "http", ""),
    );
    let web = transport::free_local_port().unwrap();
    let _prom = Prometheus::start(std::path::Path::new(&prometheus), &dir, &yml, web).unwrap();

    let got = targets(web).await;
    let health = |job: &str| got.iter().find(|(j, _, _)| j == job).cloned().unwrap();
    let (_, h, e) = health("with-cert");
    assert_eq!(h, "up", "the scrape with our client certificate: {e}");
    for job in ["no-cert", "other-fleet", "plain"] {
        let (_, h, e) = health(job);
        assert_eq!(h, "down", "{job} must be refused");
        assert!(!e.is_empty(), "{job}: down without a reason");
    }
    // The series came in through the TLS scrape: the service's device count, from the
    // job with the certificate only.
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    let series = loop {
        let v = prometheus_api(web, "/api/v1/query?query=mfc_service_devices").await;
        let r = v
            .as_ref()
            .and_then(|v| v["data"]["result"].as_array().cloned())
            .unwrap_or_default();
        if !r.is_empty() || tokio::time::Instant::now() > deadline {
            break r;
        }
        tokio::time::sleep(Duration::from_millis(250)).await;
    };
    assert_eq!(series.len(), 1, "{series:?}");
    assert_eq!(series[0]["metric"]["job"], "with-cert");
    assert_eq!(series[0]["value"][1], "1", "one device served: {series:?}");
    service.stop().await.unwrap();
}
